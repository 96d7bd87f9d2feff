"""The network emulator's link model (sans-IO) and its use by the memory transport.

Every figure here is seeded: the assertions are about the model's statistics, which a
fixed seed makes exact run to run.
"""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
from pathlib import Path

import pytest

from conftest import wait_until
from telebot.channels.transports.base import Sample
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.errors import ConfigError
from telebot.netem import PROFILES, Burst, InOrder, LinkModel, Outages, Profile, profile


def quiet(name: str, **changes: object) -> Profile:
    """A named profile without its outages, bandwidth cap (and whatever else is given)."""
    base = dict(outages=None, rate_up=None, rate_down=None)
    return dataclasses.replace(profile(name), **{**base, **changes})  # type: ignore[arg-type]


def fates(model: LinkModel, count: int, step: float = 0.001, size: int = 100) -> list[bool]:
    """Which of ``count`` packets sent ``step`` apart arrive."""
    return [model.transmit(size, i * step) is not None for i in range(count)]


def runs_of_losses(arrived: list[bool]) -> list[int]:
    return [len(list(group)) for lost, group in itertools.groupby(not a for a in arrived) if lost]


def test_the_named_profiles_have_the_issues_figures() -> None:
    assert set(PROFILES) == {"lan", "wifi", "4g", "intercontinental", "bad"}
    wifi, g4, ocean, bad = (profile(n) for n in ("wifi", "4g", "intercontinental", "bad"))
    assert (wifi.delay, wifi.jitter, wifi.mean_loss) == pytest.approx((0.005, 0.003, 0.005))
    assert wifi.outages == Outages(period=30.0, duration=0.3)
    assert (g4.delay, g4.jitter, g4.mean_loss) == pytest.approx((0.040, 0.015, 0.01))
    assert (g4.rate_down, g4.rate_up) == (5e6, 2e6)
    assert (ocean.delay, ocean.jitter, ocean.mean_loss) == pytest.approx((0.16, 0.01, 0.005))
    assert (bad.delay, bad.jitter, bad.mean_loss) == pytest.approx((0.08, 0.04, 0.05))
    assert (bad.rate_down, bad.rate_up, bad.reorder) == (1e6, 1e6, 0.01)
    assert profile("lan").mean_loss == 0 and profile("lan").delay == 0


def test_an_unknown_profile_name_is_one_error_naming_the_known_ones() -> None:
    with pytest.raises(ConfigError, match=r"unknown network profile 'wfi'; known: lan, wifi, 4g"):
        profile("wfi")
    with pytest.raises(ValueError, match="loss must be a number in"):
        Profile("x", loss=1.5)


def test_the_same_seed_loses_the_same_packets_and_another_seed_others() -> None:
    bad = profile("bad")
    first = fates(LinkModel(bad, seed=3, direction="up"), 3000)
    again = fates(LinkModel(bad, seed=3, direction="up"), 3000)
    other = fates(LinkModel(bad, seed=4, direction="up"), 3000)
    down = fates(LinkModel(bad, seed=3, direction="down"), 3000)
    assert first == again
    assert first != other and first != down  # each seed and direction its own stream
    assert not all(first)


def test_changing_the_delay_does_not_change_which_packets_are_lost() -> None:
    base = quiet("bad")
    slower = dataclasses.replace(base, delay=0.3, jitter=0.1)
    assert fates(LinkModel(base, 9), 2000) == fates(LinkModel(slower, 9), 2000)


@pytest.mark.parametrize("name", ["wifi", "4g", "intercontinental", "bad"])
def test_the_loss_rate_over_many_packets_is_the_profiles(name: str) -> None:
    model = LinkModel(quiet(name), seed=1)
    arrived = fates(model, 80_000)
    rate = arrived.count(False) / len(arrived)
    assert rate == pytest.approx(profile(name).mean_loss, rel=0.25)
    assert model.stats.lost == arrived.count(False)
    assert 0 < model.stats.burst_lost < model.stats.lost  # some in bursts, some random


def test_bursts_lose_runs_of_packets_and_random_loss_single_ones() -> None:
    bursty = fates(LinkModel(quiet("bad", loss=0.0, burst=Burst.of(0.05, length=8)), 2), 50_000)
    random = fates(LinkModel(quiet("bad", loss=0.05, burst=None), 2), 50_000)
    for arrived in (bursty, random):  # the same share of packets lost...
        assert arrived.count(False) / len(arrived) == pytest.approx(0.05, rel=0.2)
    bursts, singles = runs_of_losses(bursty), runs_of_losses(random)
    # ...but in runs as long as the chain's bad spells, against ~1.05 for random loss.
    assert sum(bursts) / len(bursts) == pytest.approx(8, rel=0.2)
    assert sum(singles) / len(singles) < 1.2
    assert max(bursts) > 20 and max(singles) < 6


def test_burst_parameters_give_the_share_and_length_asked_for() -> None:
    burst = Burst.of(0.02, length=5)
    assert burst.mean_loss == pytest.approx(0.02)
    assert burst.mean_length == pytest.approx(5)
    with pytest.raises(ValueError, match="burst leave must be > 0"):
        Burst(enter=0.1, leave=0.0)


def test_the_bandwidth_cap_spaces_packets_and_drops_beyond_the_queue() -> None:
    # 1 Mbit/s: a 1250-byte packet takes 10 ms; the queue holds 0.2 s.
    link = Profile("cap", rate_up=1e6, queue=0.2, delay=0.05)
    model = LinkModel(link, direction="up")
    burst = [model.transmit(1250, 0.0) for _ in range(100)]
    arrived = [t for t in burst if t is not None]
    assert len(arrived) in (20, 21)  # what 0.2 s of queue holds, one in service
    assert model.stats.tail_dropped == 100 - len(arrived) == burst.count(None)
    assert arrived == pytest.approx([0.05 + 0.01 * (i + 1) for i in range(len(arrived))])
    assert model.backlog(0.0) == pytest.approx(0.01 * len(arrived))
    # Once the queue has drained, packets pass at once again; the other way is uncapped.
    assert model.transmit(1250, 1.0) == pytest.approx(1.06)
    assert LinkModel(link, direction="down").transmit(1250, 0.0) == pytest.approx(0.05)


def test_jitter_spreads_delays_and_only_the_reorder_share_overtakes() -> None:
    wifi = quiet("wifi", loss=0.0, burst=None)
    for reorder, ordered in ((0.0, False), (0.05, False), (0.05, True)):
        link = dataclasses.replace(wifi, reorder=reorder)
        model = LinkModel(link, seed=5, ordered=ordered)
        sent = [i * 0.001 for i in range(2000)]
        arrivals = [model.transmit(100, t) for t in sent]
        delays = [a - s for a, s in zip(arrivals, sent, strict=True)]  # type: ignore[operator]
        # 5 +- 3 ms; waiting for the datagram ahead never adds more than the spread.
        assert min(delays) >= 0.002 - 1e-9 and max(delays) <= 0.008 + 1e-9
        assert max(delays) - min(delays) > 0.005  # the jitter is there
        inversions = sum(b < a for a, b in itertools.pairwise(arrivals))  # type: ignore[operator]
        # Datagrams keep their order but for the reorder share; a stream always does.
        assert (20 < inversions < 150) if reorder and not ordered else (inversions == 0)


def test_a_lost_stream_chunk_arrives_after_a_retransmission_and_holds_up_the_rest() -> None:
    link = quiet("intercontinental", jitter=0.0)
    model = LinkModel(link, seed=0, ordered=True)
    sent = [i * 0.01 for i in range(3000)]
    arrivals = [model.transmit(100, t) for t in sent]
    assert None not in arrivals  # a stream loses nothing...
    late = [i for i, (a, s) in enumerate(zip(arrivals, sent, strict=True)) if a - s > 0.161]  # type: ignore[operator]
    assert model.stats.retransmitted > 0 and late
    first = late[0]
    # ...the chunk a loss hit waits one RTO (2 x 160 ms + 4 x 0) and the next ones wait for it.
    assert arrivals[first] - sent[first] == pytest.approx(0.16 + link.rto)  # type: ignore[operator]
    assert arrivals[first + 1] == arrivals[first]
    assert link.rto == pytest.approx(0.32)


def test_streams_on_one_link_share_its_queue_but_each_keeps_its_own_order() -> None:
    # 1 Mbit/s, 50 ms one way: a 12,500-byte chunk takes 0.1 s to leave.
    link = Profile("cap", rate_up=1e6, queue=1.0, delay=0.05)
    model = LinkModel(link, direction="up", ordered=True)
    picture, keys = InOrder(), InOrder()
    assert model.transmit(12_500, 0.0, picture) == pytest.approx(0.15)
    # A key press sent just after waits behind the picture in the queue (one dongle)...
    assert model.transmit(100, 0.001, keys) == pytest.approx(0.1008 + 0.05)
    assert keys.last_arrival == pytest.approx(0.1508)
    assert picture.last_arrival == pytest.approx(0.15)
    # ...but not behind a retransmission of the picture's stream: each stream its own order.
    lossy = LinkModel(quiet("intercontinental", jitter=0.0), seed=0, ordered=True)
    first, second = InOrder(), InOrder()
    sent = 0.0
    while (arrival := lossy.transmit(100, sent, first)) == pytest.approx(sent + 0.16):
        sent += 0.01  # until a chunk of the first stream is lost and resent one RTO later
        assert sent < 100, "0.5 % loss lost nothing in 10,000 chunks"
    assert arrival == pytest.approx(sent + 0.16 + lossy.profile.rto)
    assert lossy.transmit(100, sent + 0.001, first) == arrival  # held up behind it
    # The other stream is not: its chunk sent at the same time arrives one delay later.
    assert lossy.transmit(100, sent + 0.001, second) == pytest.approx(sent + 0.161)


def test_the_outage_schedule_cuts_both_directions_for_its_duration_every_period() -> None:
    wifi = quiet("wifi", loss=0.0, burst=None, outages=Outages(period=30.0, duration=0.3))
    up, down = LinkModel.pair(wifi, seed=11)
    step = 0.01
    lost_up = [i * step for i, ok in enumerate(fates(up, 12_000, step)) if not ok]
    lost_down = [i * step for i, ok in enumerate(fates(down, 12_000, step)) if not ok]
    assert lost_up == lost_down  # one schedule for both ways
    gaps = [[t for t in lost_up if start <= t < start + 1.0] for start in lost_up[::30]]
    assert len(gaps) == 4  # 120 s: four gaps of 30 packets (300 ms) each, 30 s apart
    assert all(len(gap) == 30 for gap in gaps)
    assert [round(b[0] - a[0], 6) for a, b in itertools.pairwise(gaps)] == [30.0] * 3
    assert up.stats.outage_lost == 120
    # The phase is drawn from the seed: another seed puts the gaps elsewhere.
    other = [i for i, ok in enumerate(fates(LinkModel(wifi, seed=12), 3000, step)) if not ok]
    assert other and other[0] * step != lost_up[0]


def test_a_forced_outage_loses_datagrams_and_delays_a_stream_until_it_ends() -> None:
    lan = profile("lan")
    datagrams, stream = LinkModel(lan), LinkModel(lan, ordered=True)
    for model in (datagrams, stream):
        model.schedule.force(1.0, 0.3)
    assert datagrams.transmit(10, 0.99) == 0.99
    assert datagrams.transmit(10, 1.0) is None and datagrams.transmit(10, 1.29) is None
    assert datagrams.transmit(10, 1.3) == 1.3
    # The stream's chunk is retried at 1.2 (still out), then 1.6: TCP's backoff doubles.
    assert stream.transmit(10, 1.0) == pytest.approx(1.6)
    assert stream.transmit(10, 1.35) == pytest.approx(1.6)  # held up behind it
    assert stream.transmit(10, 2.0) == 2.0


async def test_the_memory_hub_plays_a_profile_and_forced_outages() -> None:
    hub = MemoryHub(seed=1)
    hub.set_profile("robot", "user", "bad")
    got: list[Sample] = []
    async with MemoryTransport(hub, "robot") as robot, MemoryTransport(hub, "user") as user:
        user.subscribe("pose", got.extend)
        pose = robot.publisher("pose")
        loop = asyncio.get_running_loop()
        for _ in range(2000):
            pose.put(b"x" * 200)
        stats = hub.link_stats("robot", "user")
        await wait_until(lambda: stats.in_flight == 0)
        # 2000 frames at once into 1 Mbit/s with 0.5 s of queue: the tail is dropped.
        assert stats.tail_dropped > 0 and stats.lost > stats.tail_dropped
        assert len(got) == stats.delivered == 2000 - stats.lost
        hub.outage("robot", "user", 0.5, loop.time())
        before = len(got)
        pose.put(b"during the gap")
        hub.set_profile("robot", "user", None)  # back to the plain conditions: no loss
        pose.put(b"after")
        await wait_until(lambda: len(got) == before + 1)
        assert got[-1].payload == b"after"
    with pytest.raises(ConfigError, match="unknown network profile"):
        hub.set_profile("robot", "user", "dialup")


def test_the_readme_table_lists_every_profile_with_its_figures() -> None:
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    section = readme.split("### Network emulator", 1)[1].split("\n### ", 1)[0]
    rows = {
        cells[0].strip("` "): cells[1:]
        for line in section.splitlines()
        if line.startswith("| `") and (cells := [c.strip() for c in line.strip("|").split("|")])
    }
    assert set(rows) == set(PROFILES)
    for name, (delay, loss, _rate, _outages) in rows.items():
        p = profile(name)
        assert delay == ("0" if not p.delay else f"{p.delay * 1e3:g} ± {p.jitter * 1e3:g} ms")
        assert loss.split(",")[0] == ("0" if not p.mean_loss else f"{p.mean_loss * 100:g} %")
