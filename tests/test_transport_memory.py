"""The memory transport: key matching, delivery, link conditions, presence, lifecycle."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from contextlib import AsyncExitStack
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

from telebot.channels.call import RobotEndpoint, UserEndpoint
from telebot.channels.transports import Lane, Sample, create_transport
from telebot.channels.transports.base import ReceiveLimits
from telebot.channels.transports.memory import (
    LinkConditions,
    MemoryHub,
    MemoryTransport,
    key_matches,
)
from telebot.config import CallSettings, MemorySettings, TransportSettings
from telebot.errors import TransportError
from telebot.identity import ContactBook, Identity, KnownRobots, create_paired_homes
from telebot.testing.clock import run_virtual

if TYPE_CHECKING:
    from telebot.channels.call import Call

# --------------------------------------------------------------------------- helpers


class Inbox:
    """A subscription callback that records batches and arrival times."""

    def __init__(self) -> None:
        self.batches: list[list[Sample]] = []
        self.arrivals: list[tuple[float, bytes]] = []
        self._changed = asyncio.Event()

    def __call__(self, batch: Sequence[Sample]) -> None:
        now = asyncio.get_running_loop().time()
        self.batches.append(list(batch))
        self.arrivals.extend((now, s.payload) for s in batch)
        self._changed.set()

    @property
    def payloads(self) -> list[bytes]:
        return [payload for _, payload in self.arrivals]

    async def wait_for(self, count: int) -> None:
        """Wait until ``count`` samples arrived; fail after 2 s."""
        async with asyncio.timeout(2.0):
            while len(self.arrivals) < count:
                self._changed.clear()
                await self._changed.wait()


class Events:
    """A presence callback that records (key, alive) events."""

    def __init__(self) -> None:
        self.events: list[tuple[str, bool]] = []

    def __call__(self, key: str, alive: bool) -> None:
        self.events.append((key, alive))


async def settle(seconds: float = 0.0) -> None:
    """Let the loop run pending callbacks (and timers due within ``seconds``)."""
    await asyncio.sleep(seconds)
    for _ in range(3):
        await asyncio.sleep(0)


@pytest.fixture
async def stack() -> AsyncIterator[AsyncExitStack]:
    async with AsyncExitStack() as s:
        yield s


Join = Callable[[MemoryHub, str], Awaitable[MemoryTransport]]


@pytest.fixture
def join(stack: AsyncExitStack) -> Join:
    """Open a transport on ``hub`` as ``node``, closed at the end of the test."""

    async def _join(hub: MemoryHub, node: str) -> MemoryTransport:
        return await stack.enter_async_context(MemoryTransport(hub, node))

    return _join


def nums(inbox: Inbox) -> list[int]:
    return [int(p) for p in inbox.payloads]


# --------------------------------------------------------------------------- key expressions


@pytest.mark.parametrize(
    ("pattern", "key", "expected"),
    [
        ("a/b/c", "a/b/c", True),
        ("a/b/c", "a/b/d", False),
        ("a/b", "a/b/c", False),
        ("a/*/c", "a/b/c", True),
        ("a/*/c", "a/c", False),
        ("a/*/c", "a/b/x/c", False),
        ("a/*", "a/b/c", False),
        ("*", "a", True),
        ("a/**", "a", True),
        ("a/**", "a/b/c/d", True),
        ("a/**", "b/a", False),
        ("a/**/d", "a/d", True),
        ("a/**/d", "a/b/c/d", True),
        ("a/**/d", "a/b/c/e", False),
        ("**", "x/y/z", True),
        ("**/z", "x/y/z", True),
        ("**/*/z", "z", False),
        ("a/**/*/c", "a/b/c", True),
        ("telebot/robot/*/in", "telebot/robot/guiabot/in", True),
        ("telebot/robot/*/in", "telebot/robot/guiabot/out", False),
    ],
)
def test_key_matches(pattern: str, key: str, expected: bool) -> None:
    assert key_matches(pattern, key) is expected


# --------------------------------------------------------------------------- delivery


async def test_delivered_to_matching_subscription_only_in_one_batch(join: Join) -> None:
    hub = MemoryHub(seed=1)
    a, b = await join(hub, "a"), await join(hub, "b")
    hit, miss = Inbox(), Inbox()
    b.subscribe("telebot/*/in", hit)
    b.subscribe("telebot/*/out", miss)
    pub = a.publisher("telebot/r1/in")
    buf = bytearray(b"x")
    for i in range(5):
        buf[0] = ord(str(i))
        pub.put(bytes(buf))
    assert hit.batches == []  # never delivered inside put()
    await hit.wait_for(5)
    await settle()
    assert [len(batch) for batch in hit.batches] == [5]
    assert hit.payloads == [b"0", b"1", b"2", b"3", b"4"]
    assert hit.batches[0][0].key == "telebot/r1/in"
    assert miss.batches == []
    assert a.stats.published == 5
    assert b.stats.received == 5
    assert hub.link_stats("a", "b").delivered == 5


async def test_oversized_payloads_are_dropped_and_counted(join: Join) -> None:
    hub = MemoryHub(seed=1)
    a, b = await join(hub, "a"), await join(hub, "b")
    small, anything = Inbox(), Inbox()
    limited = b.subscribe("k", small, limits=ReceiveLimits(max_payload=10))
    b.subscribe("k", anything)
    pub = a.publisher("k")
    pub.put(bytes(11))
    pub.put(bytes(10))
    await anything.wait_for(2)
    await settle()
    assert small.payloads == [bytes(10)]
    assert limited.stats.oversized == 1 and limited.stats.received == 1
    assert b.stats.oversized == 1


async def test_payload_is_copied(join: Join) -> None:
    hub = MemoryHub(seed=1)
    a, b = await join(hub, "a"), await join(hub, "b")
    inbox = Inbox()
    b.subscribe("k", inbox)
    buf = bytearray(b"before")
    a.publisher("k").put(buf)  # type: ignore[arg-type]  # senders may pass a buffer
    buf[:] = b"after!"
    await inbox.wait_for(1)
    assert inbox.payloads == [b"before"]


async def test_own_frames_are_unimpaired(join: Join) -> None:
    hub = MemoryHub(seed=1)
    a, b = await join(hub, "a"), await join(hub, "b")
    hub.set_link("a", "b", loss=1.0)
    own, other = Inbox(), Inbox()
    a.subscribe("k", own)
    b.subscribe("k", other)
    pub = a.publisher("k", Lane.CONTROL)
    for _ in range(10):
        pub.put(b"p")
    await own.wait_for(10)
    await settle()
    assert other.arrivals == []
    assert hub.link_stats("a", "b").lost == 10
    with pytest.raises(ValueError, match="itself"):
        hub.link("a", "a")


async def test_closed_subscription_stops_even_in_flight(join: Join) -> None:
    hub = MemoryHub(seed=1)
    a, b = await join(hub, "a"), await join(hub, "b")
    hub.set_link("a", "b", latency=0.02)
    inbox = Inbox()
    sub = b.subscribe("k", inbox)
    a.publisher("k").put(b"1")
    sub.close()
    sub.close()  # idempotent
    await settle(0.04)
    assert inbox.arrivals == []


# --------------------------------------------------------------------------- loss


async def _lost_set(seed: int, loss: float, count: int) -> tuple[set[int], MemoryHub]:
    hub = MemoryHub(seed=seed)
    async with MemoryTransport(hub, "a") as a, MemoryTransport(hub, "b") as b:
        hub.set_link("a", "b", loss=loss)
        inbox = Inbox()
        b.subscribe("k", inbox)
        pub = a.publisher("k")
        for i in range(count):
            pub.put(str(i).encode())
        # What crossed the link comes in batches, one per loop turn.
        stats = hub.link_stats("a", "b")
        while stats.in_flight or len(inbox.arrivals) < stats.delivered:
            await settle()
        return set(range(count)) - set(nums(inbox)), hub


async def test_loss_rate_and_determinism() -> None:
    lost, hub = await _lost_set(seed=42, loss=0.3, count=2000)
    assert 0.26 < len(lost) / 2000 < 0.34
    stats = hub.link_stats("a", "b")
    assert (stats.sent, stats.delivered, stats.lost) == (2000, 2000 - len(lost), len(lost))
    again, _ = await _lost_set(seed=42, loss=0.3, count=2000)
    assert again == lost
    other, _ = await _lost_set(seed=43, loss=0.3, count=2000)
    assert other != lost


async def test_links_have_independent_streams(join: Join) -> None:
    hub = MemoryHub(seed=5)
    a, b, c = await join(hub, "a"), await join(hub, "b"), await join(hub, "c")
    hub.set_link("a", "b", loss=0.5)
    hub.set_link("a", "c", loss=0.5)
    at_b, at_c = Inbox(), Inbox()
    b.subscribe("k", at_b)
    c.subscribe("k", at_c)
    pub = a.publisher("k")
    for i in range(200):
        pub.put(str(i).encode())
    await settle()
    assert 0 < len(at_b.arrivals) < 200
    assert nums(at_b) != nums(at_c)


# --------------------------------------------------------------------------- timing


def test_latency_delays_delivery() -> None:
    # On the virtual clock the delay is exact, however loaded the machine.
    async def main() -> None:
        hub = MemoryHub(seed=1)
        async with MemoryTransport(hub, "a") as a, MemoryTransport(hub, "b") as b:
            hub.link("a", "b").latency = 0.05
            inbox = Inbox()
            b.subscribe("k", inbox)
            sent = asyncio.get_running_loop().time()
            a.publisher("k").put(b"x")
            await settle(0.049)
            assert inbox.arrivals == []
            await inbox.wait_for(1)
            assert inbox.arrivals[0][0] - sent == pytest.approx(0.05)

    run_virtual(main())


async def test_latency_without_jitter_keeps_order(join: Join) -> None:
    hub = MemoryHub(seed=1)
    a, b = await join(hub, "a"), await join(hub, "b")
    hub.set_link("a", "b", latency=0.01)
    inbox = Inbox()
    b.subscribe("k", inbox)
    pub = a.publisher("k")
    for i in range(100):
        pub.put(str(i).encode())
    await inbox.wait_for(100)
    assert nums(inbox) == list(range(100))


async def test_jitter_reorders(join: Join) -> None:
    hub = MemoryHub(seed=3)
    a, b = await join(hub, "a"), await join(hub, "b")
    hub.set_link("a", "b", latency=0.005, jitter=0.03)
    inbox = Inbox()
    b.subscribe("k", inbox)
    pub = a.publisher("k")
    for i in range(50):
        pub.put(str(i).encode())
    await inbox.wait_for(50)
    received = nums(inbox)
    assert sorted(received) == list(range(50))  # nothing lost or duplicated
    assert received != list(range(50))


def test_bandwidth_spaces_frames() -> None:
    async def main() -> None:
        hub = MemoryHub(seed=1)
        async with MemoryTransport(hub, "a") as a, MemoryTransport(hub, "b") as b:
            hub.set_link("a", "b", bandwidth=25_000)  # 1000-byte frames: 40 ms each
            inbox = Inbox()
            b.subscribe("k", inbox)
            pub = a.publisher("k")
            start = asyncio.get_running_loop().time()
            for _ in range(5):
                pub.put(bytes(1000))
            await inbox.wait_for(5)
            times = [t - start for t, _ in inbox.arrivals]
            assert times == pytest.approx([0.04, 0.08, 0.12, 0.16, 0.2])

    run_virtual(main())


async def test_tail_drop_beyond_max_queue_delay(join: Join) -> None:
    hub = MemoryHub(seed=1)
    a, b = await join(hub, "a"), await join(hub, "b")
    # 1000-byte frames take 50 ms each: frames 0-2 wait 0, 50, 100 ms, frame 3 would wait 150.
    hub.set_link("a", "b", bandwidth=20_000, max_queue_delay=0.12)
    inbox = Inbox()
    b.subscribe("k", inbox)
    pub = a.publisher("k")
    for i in range(10):
        pub.put(str(i).encode().ljust(1000))
    await inbox.wait_for(3)
    await settle(0.05)
    assert [p.strip() for p in inbox.payloads] == [b"0", b"1", b"2"]
    stats = hub.link_stats("a", "b")
    assert (stats.sent, stats.delivered, stats.lost, stats.tail_dropped) == (10, 3, 7, 7)
    assert stats.in_flight == 0


async def test_conditions_changed_while_running_apply_to_later_frames(join: Join) -> None:
    hub = MemoryHub(seed=1)
    a, b = await join(hub, "a"), await join(hub, "b")
    inbox = Inbox()
    b.subscribe("k", inbox)
    pub = a.publisher("k")
    pub.put(b"0")
    await inbox.wait_for(1)
    hub.link("a", "b").loss = 1.0
    pub.put(b"1")
    await settle()
    assert inbox.payloads == [b"0"]
    hub.set_link("a", "b", loss=0.0, latency=0.03)
    sent = asyncio.get_running_loop().time()
    pub.put(b"2")
    await inbox.wait_for(2)
    assert inbox.payloads == [b"0", b"2"]
    assert inbox.arrivals[-1][0] - sent >= 0.029


# --------------------------------------------------------------------------- cut and heal


async def test_cut_drops_frames_and_presence_heal_restores_both(join: Join) -> None:
    hub = MemoryHub(seed=1)
    a, b = await join(hub, "a"), await join(hub, "b")
    a.declare_presence("telebot/robot/a")
    b.declare_presence("telebot/robot/b")
    seen_by_a, seen_by_b = Events(), Events()
    a.watch_presence("telebot/robot/*", seen_by_a)
    b.watch_presence("telebot/robot/*", seen_by_b)
    inbox = Inbox()
    b.subscribe("k", inbox)
    pub = a.publisher("k")
    await settle()
    assert ("telebot/robot/a", True) in seen_by_b.events
    assert ("telebot/robot/b", True) in seen_by_a.events
    seen_by_a.events.clear()
    seen_by_b.events.clear()

    hub.cut("a", "b")
    for _ in range(20):
        pub.put(b"lost")
    await settle(0.01)
    assert inbox.arrivals == []
    assert hub.link_stats("a", "b").lost == 20
    assert seen_by_b.events == [("telebot/robot/a", False)]
    assert seen_by_a.events == [("telebot/robot/b", False)]

    hub.heal("a", "b")
    pub.put(b"back")
    await inbox.wait_for(1)
    await settle()
    assert inbox.payloads == [b"back"]
    assert seen_by_b.events == [("telebot/robot/a", False), ("telebot/robot/a", True)]
    assert seen_by_a.events == [("telebot/robot/b", False), ("telebot/robot/b", True)]


async def test_one_direction_down(join: Join) -> None:
    hub = MemoryHub(seed=1)
    a, b = await join(hub, "a"), await join(hub, "b")
    a.declare_presence("p/a")
    b.declare_presence("p/b")
    seen_by_a, seen_by_b = Events(), Events()
    a.watch_presence("p/**", seen_by_a)
    b.watch_presence("p/**", seen_by_b)
    await settle()
    seen_by_a.events.clear()
    seen_by_b.events.clear()
    hub.link("a", "b").up = False  # setting the field directly also updates presence
    await settle()
    assert seen_by_b.events == [("p/a", False)]  # b still sees its own token
    assert seen_by_a.events == []  # b -> a is still up
    hub.link("a", "b").up = False  # no change, no event
    await settle()
    assert seen_by_b.events == [("p/a", False)]


# --------------------------------------------------------------------------- presence


async def test_presence_history_then_changes(join: Join) -> None:
    hub = MemoryHub(seed=1)
    a, b = await join(hub, "a"), await join(hub, "b")
    first = a.declare_presence("telebot/robot/one")
    a.declare_presence("telebot/user/x")
    events = Events()
    b.watch_presence("telebot/robot/*", events)
    assert events.events == []  # history is reported asynchronously too
    await settle()
    assert events.events == [("telebot/robot/one", True)]
    a.declare_presence("telebot/robot/two")
    first.close()
    first.close()  # idempotent
    await settle()
    assert events.events == [
        ("telebot/robot/one", True),
        ("telebot/robot/two", True),
        ("telebot/robot/one", False),
    ]


async def test_closed_watch_reports_nothing(join: Join) -> None:
    hub = MemoryHub(seed=1)
    a, b = await join(hub, "a"), await join(hub, "b")
    events = Events()
    watch = b.watch_presence("**", events)
    a.declare_presence("x")
    watch.close()  # before the loop ran the pending report
    await settle()
    assert events.events == []


async def test_transport_close_removes_presence_and_detaches(join: Join) -> None:
    hub = MemoryHub(seed=1)
    b = await join(hub, "b")
    a = MemoryTransport(hub, "a")
    await a.open()
    assert sorted(hub.nodes) == ["a", "b"]
    a.declare_presence("telebot/robot/a")
    own, other = Events(), Events()
    a.watch_presence("**", own)
    b.watch_presence("**", other)
    inbox = Inbox()
    a.subscribe("k", inbox)
    await settle()
    assert other.events == [("telebot/robot/a", True)]
    own.events.clear()

    await a.close()
    await a.close()  # idempotent
    b.publisher("k").put(b"nobody")
    await settle()
    assert hub.nodes == ["b"]
    assert other.events == [("telebot/robot/a", True), ("telebot/robot/a", False)]
    assert own.events == []
    assert inbox.arrivals == []


# --------------------------------------------------------------------------- validation and lifecycle


@pytest.mark.parametrize(
    ("fields", "name"),
    [
        ({"loss": -0.1}, "loss"),
        ({"loss": 1.5}, "loss"),
        ({"loss": float("nan")}, "loss"),
        ({"latency": -1.0}, "latency"),
        ({"jitter": -0.01}, "jitter"),
        ({"bandwidth": 0}, "bandwidth"),
        ({"bandwidth": -5.0}, "bandwidth"),
        ({"max_queue_delay": -1.0}, "max_queue_delay"),
        ({"up": "yes"}, "up"),
    ],
)
def test_invalid_conditions(fields: dict[str, object], name: str) -> None:
    with pytest.raises(ValueError, match=name):
        LinkConditions(**fields)  # type: ignore[arg-type]
    conditions = LinkConditions()
    with pytest.raises(ValueError, match=name):
        setattr(conditions, name, next(iter(fields.values())))
    assert conditions == LinkConditions()  # a rejected value changes nothing


def test_set_link_validates_before_changing() -> None:
    hub = MemoryHub(seed=1)
    with pytest.raises(ValueError, match=r"unknown link condition.*lose"):
        hub.set_link("a", "b", lose=0.5)
    with pytest.raises(ValueError, match="latency"):
        hub.set_link("a", "b", loss=0.5, latency=-1)
    assert hub.link("a", "b") == LinkConditions()
    assert hub.link("b", "a") == LinkConditions()


async def test_use_before_open_and_after_close_raises() -> None:
    transport = MemoryTransport(MemoryHub(seed=1), "a")
    with pytest.raises(TransportError, match="not open"):
        transport.publisher("k")
    with pytest.raises(TransportError, match="not open"):
        transport.subscribe("k", Inbox())
    with pytest.raises(TransportError, match="not open"):
        transport.declare_presence("k")
    with pytest.raises(TransportError, match="not open"):
        transport.watch_presence("k", Events())
    async with transport:
        pub = transport.publisher("k")
        with pytest.raises(TransportError, match="already open"):
            await transport.open()
    with pytest.raises(TransportError, match="closed"):
        pub.put(b"x")
    with pytest.raises(TransportError, match="closed"):
        transport.subscribe("k", Inbox())
    with pytest.raises(TransportError, match="closed"):
        await transport.open()


async def test_invalid_keys_and_duplicate_nodes(join: Join) -> None:
    hub = MemoryHub(seed=1)
    a = await join(hub, "a")
    with pytest.raises(TransportError, match="wildcard"):
        a.publisher("telebot/*")
    with pytest.raises(TransportError, match="empty chunk"):
        a.subscribe("telebot//x", Inbox())
    with pytest.raises(TransportError, match="whole chunk"):
        a.subscribe("telebot/ro*", Inbox())
    with pytest.raises(TransportError, match="already has an open node 'a'"):
        await MemoryTransport(hub, "a").open()


async def test_from_settings_and_registry() -> None:
    settings = TransportSettings(
        kind="memory", memory=MemorySettings(hub="test-transport-memory", node="robot")
    )
    transport = create_transport(settings)
    assert isinstance(transport, MemoryTransport)
    assert transport.hub is MemoryHub.named("test-transport-memory")
    assert transport.node == "robot"
    unnamed = MemoryTransport.from_settings(
        TransportSettings(kind="memory", memory=MemorySettings(hub="test-transport-memory"))
    )
    assert unnamed.node.startswith("node-")
    assert unnamed.node != MemoryTransport(unnamed.hub).node
    async with transport:
        assert transport.node in transport.hub.nodes
    assert transport.node not in transport.hub.nodes


def test_a_call_whose_answer_is_lost_for_longer_than_the_timeout_still_comes_up(
    tmp_path: Path,
) -> None:
    # The robot's answers are lost for 1 s (twice the call timeout): the caller keeps
    # repeating its HELLO, which keeps the robot's half of the call alive, so once the
    # answer gets through the call works, instead of dying at once on the robot's side.
    # On the virtual clock: the seconds are the calls' own, whatever the machine's load.
    from telebot.apps.echo import echo_call

    async def main() -> None:
        hub = MemoryHub(seed=3)
        async with call_rig(tmp_path, hub, CallSettings(timeout=0.5)) as (robot, user):
            robot.on_call = lambda call: echo_call(call, robot, lambda event: None)
            hub.link("robot", "user").loss = 1.0
            calling = asyncio.create_task(user.call("guiabot", timeout=5.0))
            await asyncio.sleep(1.0)
            assert not calling.done()
            hub.link("robot", "user").loss = 0.0
            call = await calling
            chat = call.channel("chat")
            await asyncio.sleep(1.0)  # longer than the timeout: a dead half would show now
            assert call.active
            chat.send("still there?")
            reply = await asyncio.wait_for(chat.receive(), 2.0)
            assert reply.payload == "still there?"
            await call.hangup()

    run_virtual(main())


@contextlib.asynccontextmanager
async def call_rig(
    home: Path, hub: MemoryHub, settings: CallSettings
) -> AsyncIterator[tuple[RobotEndpoint, UserEndpoint]]:
    """A robot "guiabot" (node "robot") and its contact alice (node "user") on ``hub``."""
    create_paired_homes(home, "guiabot", "alice")
    async with (
        MemoryTransport(hub, "robot") as robot_transport,
        MemoryTransport(hub, "user") as user_transport,
        RobotEndpoint(
            robot_transport,
            Identity.load(home / "robot"),
            ContactBook.load(home / "robot"),
            settings=settings,
        ) as robot,
        UserEndpoint(
            user_transport,
            Identity.load(home / "user"),
            KnownRobots.load(home / "user"),
            settings=settings,
        ) as user,
    ):
        yield robot, user


# --------------------------------------------------------------------------- floods, in-process

#: A flood of 32 KB datagrams (what tests/flood_proc.py sends over zenoh), in one loop turn.
FLOOD = 600
DATAGRAM = 32_768


def test_a_data_flood_is_bounded_counted_and_leaves_the_call_up(tmp_path: Path) -> None:
    """alice floods her call's DATA key with 600 datagrams of 32 KB in one turn (19 MB):
    the robot's inbox for that key keeps at most 8 MB (the transport's queue_bytes),
    dropping the oldest and counting them in the call's receive_dropped; the call stays
    up and a chat message sent after the flood gets through. Deterministic: in-process,
    on the virtual clock."""

    async def main() -> None:
        hub = MemoryHub(seed=1)
        async with call_rig(tmp_path, hub, CallSettings(timeout=0.5)) as (robot, user):
            answered: list[Call] = []
            robot.on_call = answered.append
            call = await user.call("guiabot", timeout=5.0)
            robot_call = answered[0]
            robot_transport = hub._nodes["robot"]
            flood, chat = call.channel("flood"), call.channel("chat")
            received: list[int] = []
            robot_call.channel("flood").set_callback(lambda d: received.append(len(d.payload)))
            robot_chat = robot_call.channel("chat")
            payload = bytes(DATAGRAM)
            for _ in range(FLOOD):
                flood.send(payload)
            chat.send("after the flood")
            message = await asyncio.wait_for(robot_chat.receive(), 5.0)
            assert message.payload == "after the flood"
            kept = (8 << 20) // DATAGRAM  # the documented default queue_bytes: 8 MB
            assert FLOOD - kept <= robot_call.receive_dropped < FLOOD, robot_call.receive_dropped
            assert robot_transport.stats.dropped >= robot_call.receive_dropped
            assert len(received) == FLOOD - robot_call.receive_dropped
            await asyncio.sleep(1.0)  # twice the call timeout: the flood cost no heartbeat
            assert call.active and robot_call.active
            await call.hangup()

    run_virtual(main())


async def test_a_flooded_subscription_waits_its_turn_behind_another(join: Join) -> None:
    """2000 frames due at once on one key are delivered in batches of ``batch``; a frame
    on another key due at the same time gets its callback after the flood's first batch,
    not after the whole flood (as a call's CONTROL frames behind its DATA flood)."""
    hub = MemoryHub(seed=1)
    a, b = await join(hub, "a"), await join(hub, "b")
    order: list[tuple[str, int]] = []
    b.subscribe("data", lambda batch: order.append(("data", len(batch))))
    b.subscribe("control", lambda batch: order.append(("control", len(batch))))
    data, control = a.publisher("data"), a.publisher("control")
    for _ in range(2000):
        data.put(b"x")
    control.put(b"stop")
    await settle()
    while sum(n for kind, n in order if kind == "data") < 2000:
        await settle()
    assert order[:2] == [("data", 256), ("control", 1)]
    assert all(n <= 256 for _, n in order)
