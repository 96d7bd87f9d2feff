"""Sections D and E of ``bench/channels.py``: a robot daemon under floods, and reconnection.

D. Flood survival. A ``telebot-robot run`` daemon (the small map) in its own process; alice,
   a driver in this process, sends a stop every ``STOP_EVERY`` seconds and times each
   stop -> acknowledgement (the robot acknowledges once the base has stopped) while
   D1. another user in a call of its own floods 32 KB datagrams as fast as it can for
       ``FLOOD_SECONDS`` (a child process), and
   D2. a stranger, a raw zenoh peer in no call, floods the robot's handshake key for
       ``FLOOD_SECONDS`` (a child process): garbage, truncated frames, frames that carry
       alice's call id but no valid seal, and 1 MB payloads.
   D3. the same stranger, having sniffed alice's call keys (possible on an open zenoh
       network; a router's access control stops it, docs/protocol.md section 22.2),
       floods those keys too: frames that fail authentication are refused before they
       are queued on her CONTROL key, so they cannot push her heartbeats out.
   Reported: stop -> ack p50/p99 (target p99 <= 20 ms under D1, <= 100 ms under D2 and
   D3), calls dropped (alice's and the flooder's, target 0, in all three) and the
   daemon's RSS growth (its largest VmRSS during the flood minus before it; target
   < 50 MB in every flood). A stop that fails because alice's call dropped under it is
   counted as a drop (her client reconnects), never the end of the benchmark.
E. Reconnect. alice's client (zenoh client mode, reconnecting) reaches the daemon through a
   loopback TCP proxy (``tests/loopback_proxy.py``); ``CUTS`` times the proxy is stopped for
   ``CUT_SECONDS`` and started again; reported is the time from the heal to the first pose
   on the new call (p50/p99, target p99 <= 1 s).

The flooders of D1, D2 and D3 are child processes: ``bench/_flooders.py``.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from _child import Child
from _flooders import peer_config
from telebot.errors import TelebotError
from telebot.services.client import RobotClient, connect

TESTS = Path(__file__).resolve().parent.parent / "tests"
sys.path.insert(0, str(TESTS))
import rig  # noqa: E402  (the tests' rig and proxy: one piece of code)
from loopback_proxy import TcpProxy  # noqa: E402

ROBOT = "survivor"
USER = "alice"
FLOODER = "flo"
FLOOD_SECONDS = 10.0
STOP_EVERY = 0.05  # alice's stops: one round trip, then this pause
CUTS = 10
CUT_SECONDS = 2.0
TARGETS = {
    "stop_p99_ms_d1": 20.0,
    "stop_p99_ms_d2": 100.0,
    "stop_p99_ms_d3": 100.0,
    "rss_mb": 50.0,
    "reconnect_ms": 1000.0,
}


def percentile(values: Sequence[float], q: float) -> float:
    ordered = sorted(values)
    if not ordered:
        return float("nan")
    index = min(len(ordered) - 1, max(0, round(q / 100 * (len(ordered) - 1))))
    return ordered[index]


class Daemon(rig.Daemon):
    """The tests' robot daemon rig (``tests/rig.py``), and its memory use."""

    def rss_mb(self) -> float:
        """The daemon's resident set size now (MB)."""
        for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        raise RuntimeError("no VmRSS")


@dataclass
class Flood:
    """One flood of section D as alice and the daemon saw it."""

    stops_ms: list[float]
    rss_before: float
    rss_peak: float
    alice_drops: int
    child: dict[str, Any]

    @property
    def rss_growth(self) -> float:
        return self.rss_peak - self.rss_before


async def stops_during(
    alice: RobotClient, daemon: Daemon, seconds: float
) -> tuple[list[float], float]:
    """Time alice's stops and sample the daemon's RSS until ``seconds`` have passed."""
    stops: list[float] = []
    peak = daemon.rss_mb()
    loop = asyncio.get_running_loop()
    end = loop.time() + seconds
    while loop.time() < end:
        started = time.perf_counter()
        try:
            ack = await alice.stop(how="api")
        except TelebotError:  # her call dropped under the stop: counted by measure_flood
            await asyncio.sleep(STOP_EVERY)
            continue
        if ack.ok:
            stops.append((time.perf_counter() - started) * 1000)
        peak = max(peak, daemon.rss_mb())
        await asyncio.sleep(STOP_EVERY)
    return stops, peak


async def measure_flood(
    alice: RobotClient, daemon: Daemon, script: str, args: Sequence[str]
) -> Flood:
    reconnects = alice.reconnects
    rss_before = daemon.rss_mb()
    child = Child(script, *args)
    try:
        # In a thread: the child takes a while to start (imports, zenoh), and a loop
        # blocked that long drops alice's call (no heartbeats) before any flood begins.
        if await asyncio.to_thread(child.next_line, 60) != "ready":
            raise RuntimeError("the flooding child did not start")
        stops, peak = await stops_during(alice, daemon, FLOOD_SECONDS)
    finally:
        counters = await asyncio.to_thread(child.close)
    return Flood(stops, rss_before, peak, alice.reconnects - reconnects, counters)


async def measure_reconnects(daemon: Daemon, home: Path) -> list[float]:
    """Section E: the time from each heal to the first pose on the new call (ms)."""
    proxy = TcpProxy(daemon.port)
    await proxy.start()
    config = proxy.client_config({"base": 0.05, "cap": 0.25})
    loop = asyncio.get_running_loop()
    backs: list[float] = []
    poses: list[tuple[float, int]] = []
    try:
        async with connect(ROBOT, home=home, config=config, timeout=20) as client:

            async def follow() -> None:
                async for _ in client.poses():
                    poses.append((loop.time(), client.reconnects))

            follower = asyncio.create_task(follow())
            try:
                for cut in range(CUTS):
                    cut_at = loop.time()
                    await proxy.stop()
                    await asyncio.sleep(max(0.0, cut_at + CUT_SECONDS - loop.time()))
                    await proxy.start()
                    healed = loop.time()
                    async with asyncio.timeout(30):
                        while not any(t > healed and n > cut for t, n in poses):  # noqa: ASYNC110
                            await asyncio.sleep(0.005)  # a pose wakes nobody: poll for it
                    back = next(t for t, n in poses if t > healed and n > cut)
                    backs.append((back - healed) * 1000)
            finally:
                follower.cancel()
                await asyncio.gather(follower, return_exceptions=True)
    finally:
        if proxy._server is not None:
            await proxy.stop()
    return backs


@contextlib.contextmanager
def daemon_rig() -> Iterator[Daemon]:
    """A daemon (not started) with the homes of alice (driver) and flo (observer, the
    flooder), in a temporary directory; the product's call timeout, which is measured."""
    with tempfile.TemporaryDirectory(prefix="telebot-bench-") as tmp:
        yield Daemon(
            Path(tmp),
            robot=ROBOT,
            driver=USER,
            observer=FLOODER,
            timeout=rig.REAL_TIMEOUT,
            sim={"map": "small"},
        )


@dataclass
class Survival:
    call_flood: Flood
    stranger_flood: Flood
    sniffer_flood: Flood
    reconnects_ms: list[float]


FLOODERS = str(Path(__file__).with_name("_flooders.py").resolve())


async def measure_survival_async(port: int) -> Survival:
    with daemon_rig() as daemon:
        user_home, flooder_home = daemon.user_home, daemon.observer_home
        await asyncio.to_thread(daemon.start, port=port)
        try:
            async with connect(
                ROBOT, home=user_home, config=peer_config(daemon.endpoint), timeout=20
            ) as alice:
                for _ in range(20):  # warm-up: the stop path, and a measured round trip
                    await alice.stop()
                print("D1. a call floods 32 KB datagrams ...", flush=True)
                call_flood = await measure_flood(
                    alice,
                    daemon,
                    FLOODERS,
                    ["flood", str(daemon.port), ROBOT, str(flooder_home), str(FLOOD_SECONDS)],
                )
                print("D2. a stranger floods the robot's handshake key ...", flush=True)
                # A stranger's flood: "in" on the robot's handshake key, "call" on the call's.
                stranger_args = [
                    "stranger",
                    str(daemon.port),
                    ROBOT,
                    USER,
                    alice.call.id,
                    str(FLOOD_SECONDS),
                ]
                stranger = await measure_flood(alice, daemon, FLOODERS, [*stranger_args, "in"])
                print("D3. a stranger floods alice's call keys too ...", flush=True)
                sniffer = await measure_flood(alice, daemon, FLOODERS, [*stranger_args, "call"])
            print(f"E. {CUTS} cuts of {CUT_SECONDS:g} s through a loopback proxy ...", flush=True)
            reconnects = await measure_reconnects(daemon, user_home)
        finally:
            daemon.stop(graceful=True)
    return Survival(call_flood, stranger, sniffer, reconnects)


def measure_survival(port: int) -> Survival:
    """Sections D and E (about 60 s)."""
    return asyncio.run(measure_survival_async(port))


def verdict(ok: bool) -> str:
    return "PASS" if ok else "MISS"


def survival_report(res: Survival) -> tuple[list[str], dict[str, str]]:
    """Report lines and the RESULT fields of sections D and E."""
    lines = [
        "",
        f"D. Flood survival: a robot daemon, alice's stop -> ack every {STOP_EVERY * 1000:.0f} ms"
        f" during a {FLOOD_SECONDS:g} s flood",
        f"{'flood':>18} | {'stops':>5} {'p50 ms':>7} {'p99 ms':>7}  target | calls dropped | "
        f"{'RSS +MB':>7}  target | flooder",
    ]
    rows: tuple[tuple[str, Flood, float], ...] = (
        ("D1 call, 32 KB", res.call_flood, TARGETS["stop_p99_ms_d1"]),
        ("D2 stranger", res.stranger_flood, TARGETS["stop_p99_ms_d2"]),
        ("D3 sniffer", res.sniffer_flood, TARGETS["stop_p99_ms_d3"]),
    )
    drops_total = 0
    for name, flood, target in rows:
        p50, p99 = percentile(flood.stops_ms, 50), percentile(flood.stops_ms, 99)
        child = flood.child
        dropped = (
            flood.alice_drops + int(child.get("reconnects", 0)) + int(not child.get("active", True))
        )
        drops_total += dropped
        if "sent" in child and "rx_dropped" in child:
            what = f"sent {child['sent']:,} datagrams, robot dropped {child['rx_dropped']:,} unread"
        else:
            what = f"offered {child.get('sent', 0):,} frames, {child.get('mb', 0):,.0f} MB (zenoh drops most)"
        lines.append(
            f"{name:>18} | {len(flood.stops_ms):>5} {p50:>7.1f} {p99:>7.1f}  "
            + f"<= {target:g} {verdict(p99 <= target)}"
            + f" | {dropped:>13} | "
            f"{flood.rss_growth:>7.1f}  < {TARGETS['rss_mb']:g} "
            f"{verdict(flood.rss_growth < TARGETS['rss_mb'])} | {what}"
        )
    backs = res.reconnects_ms
    r50, r99 = percentile(backs, 50), percentile(backs, 99)
    lines += [
        "",
        f"E. Reconnect: {CUTS} cuts of {CUT_SECONDS:g} s (loopback TCP proxy stopped), heal -> "
        "first pose on the new call",
        f"  p50 {r50:.0f} ms, p99 {r99:.0f} ms  target p99 <= {TARGETS['reconnect_ms']:.0f} "
        f"{verdict(r99 <= TARGETS['reconnect_ms'])}  (all: "
        + ", ".join(f"{b:.0f}" for b in backs)
        + ")",
    ]
    fields = {
        "flood_call_drops": str(drops_total),
        "flood_stop_p99_ms": f"{percentile(res.call_flood.stops_ms, 99):.1f}",
        "stranger_stop_p99_ms": f"{percentile(res.stranger_flood.stops_ms, 99):.1f}",
        "sniffer_stop_p99_ms": f"{percentile(res.sniffer_flood.stops_ms, 99):.1f}",
        "flood_rss_mb": f"{max(f.rss_growth for f in (res.call_flood, res.stranger_flood, res.sniffer_flood)):.1f}",
        "reconnect_p99_ms": f"{r99:.0f}",
    }
    return lines, fields
