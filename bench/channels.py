"""Raw zenoh vs telebot channels: throughput and round trip, across two processes.

Run ``.venv/bin/python bench/channels.py`` (about 40 s on 2 cores). What it measures:

A. Raw zenoh throughput. This process publishes as fast as it can for ``DURATION``
   seconds per payload size (64 B, 1 KB, 32 KB) with the QoS of telebot's DATA lane
   (``LANE_QOS[Lane.DATA]``); a child process subscribes with a plain callback that
   takes ``sample.payload.to_bytes()`` and counts.
B. telebot throughput. The same flood through an authenticated call: this process is
   a ``UserEndpoint`` that calls a ``RobotEndpoint`` in the child and sends datagrams on
   a DATA-lane channel from asyncio (yielding to the loop every ``YIELD_EVERY`` sends, so
   heartbeats still flow); the child counts what reaches the channel's asyncio callback.
C. Round trip of 64 B, one ping in flight, ``WARMUP_PINGS`` then ``PINGS`` measured.
   Raw zenoh bridged into asyncio at both ends, as telebot is: the child's subscriber
   callback hands each ping to its event loop with ``call_soon_threadsafe``, the loop
   re-publishes it; here the pong subscriber hands the reply to this process's loop
   the same way, and the loop awaits it before the next ping. telebot: the child robot
   echoes on a channel from its loop and this process awaits each echo in asyncio.
   The pings of all three kinds (with the informational one below) alternate in
   ``PING_ROUNDS`` rounds, so the load of a shared machine falls on them alike.

A+AEAD. The encrypted baseline: A again, but the publisher seals every payload with the
   AEAD of the cipher suite telebot negotiates on this machine (AES-256-GCM with AES
   instructions, ChaCha20-Poly1305 without: ``suite_preference("auto")``) under an
   18-byte header like a DATA frame's (counter nonce, header as associated data), and the
   child's zenoh callback opens it. Raw zenoh's shared memory moves 32 KB faster than any
   cipher can touch it, so this, not A, is the physical limit of an encrypted channel on
   this CPU; ``ratio_32k_aead`` is telebot's 32 KB rate against it. (Small datagrams
   can beat it: telebot seals a BUNDLE of many in one AEAD operation.)

D. Flood survival and E. reconnection, against a real ``telebot-robot run`` daemon: see
   ``bench/_survival.py`` (``--survival-only`` runs just these two, about 60 s).

Two informational measurements help to tell where telebot's time goes: the flood of A
received by a bare ``ZenohTransport.subscribe`` (zenoh thread -> bounded queue ->
asyncio batch callback, no call, no crypto), and a third ping-pong, raw with the echo
answered straight from the child's zenoh callback (no loop on that side).

Both processes run zenoh in peer mode over TCP on 127.0.0.1 with multicast scouting
off: the child listens on a free port, this process connects. The receiver's count is
read ``GRACE`` seconds after the sender stopped (what is still queued then is reported
as "late" and not counted, so a backlog cannot inflate a rate), and msgs/s = arrived /
sending duration. Zenoh drops under congestion (DROP), so "sent" may exceed "arrived".
Payloads are random bytes. zenoh's default config enables its shared-memory
optimisation for messages over 3 KB (``transport/shared_memory``); it applies to raw
and telebot alike, and it is what makes raw 32 KB fast: with it switched off, raw
zenoh delivers about 30,000 msgs/s of 32 KB here, not 200,000+.

telebot sends the datagrams of one event-loop turn after the first in one BUNDLE frame
(docs/protocol.md section 6.4); the receiver still hands each one to the channel's
asyncio callback on its own, and only those are counted.

How to read it: ``ratio_*`` = telebot msgs/s ÷ raw msgs/s (higher is better; targets
≥ 0.30 / 0.40 / 0.60 for 64 B / 1 KB / 32 KB); ``rtt_*_ratio`` = telebot RTT ÷ raw
RTT (lower is better; targets ≤ 1.5 for p50 and ≤ 2 for p99). PASS/MISS is
informational; the exit status is non-zero only when the benchmark itself broke.
The last line (``RESULT ...``) is meant for scripts. ``--quick``: 0.1 s floods with short
settle, grace and drain waits, 40 pings, a 0.3 s flood and one 0.6 s cut in D and E, which
run beside A to C rather than after them (a check that it runs, in seconds; the figures are
noise).

Children (internal): ``--child raw|transport PORT``, ``--child raw-aead PORT SUITE KEY``
and ``--child telebot PORT HOME``.
They talk to this process by lines: it sends ``reset``, ``count`` or ``quit`` on their
stdin; they answer ``ready``, ``ok`` or one JSON object of counters on stdout.
``--profile`` runs the telebot child under cProfile and prints its hottest functions
on stderr (cProfile slows it down several times: use it for shares, not rates).
"""

from __future__ import annotations

import argparse
import asyncio
import concurrent.futures
import contextlib
import cProfile
import io
import json
import os
import pstats
import queue
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Coroutine, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Generic, NamedTuple, TypeVar

import zenoh

from telebot.channels.call import Call, RobotEndpoint, UserEndpoint
from telebot.channels.channel import ReceivedDatagram
from telebot.channels.proto.frames import DataFrame
from telebot.channels.proto.noise import Suite
from telebot.channels.proto.session import choose_suite
from telebot.channels.suites import suite_preference
from telebot.channels.transports.base import Lane, Sample
from telebot.channels.transports.zenoh import LANE_QOS, ZenohTransport, build_zenoh_config
from telebot.config import ZenohSettings
from telebot.identity import ContactBook, Identity, KnownRobots, create_paired_homes
from telebot.testing.net import free_port

if TYPE_CHECKING:
    from _survival import Survival

SIZES: tuple[int, ...] = (64, 1024, 32768)
DURATION = 3.0  # seconds of flooding per size
GRACE = 0.25  # seconds after the flood before the receiver's count is read
SETTLE = 0.2  # seconds between warm-up and measurement
DRAIN_POLL = 0.2  # seconds between two reads of the receiver's count while it drains
YIELD_EVERY = 32  # the asyncio sender yields to the loop (and reads the clock) this often
CHECK_CLOCK_EVERY = 32  # the raw sender reads the clock after this many puts
PING_SIZE = 64
WARMUP_PINGS = 100
PINGS = 2000
PING_ROUNDS = 10  # the measured pings of each kind come in this many alternating rounds
assert PINGS % PING_ROUNDS == 0, "every round has as many pings"
PING_TIMEOUT = 1.0  # a ping without reply after this long counts as lost

ROBOT = "benchbot"
USER = "benchuser"
RAW_DATA_KEY = "bench/raw/data"
RAW_PING_KEY = "bench/raw/ping"
RAW_PONG_KEY = "bench/raw/pong"
RAW_LOOP_PING_KEY = "bench/raw/loop-ping"  # echoed from an asyncio loop: C's baseline
RAW_LOOP_PONG_KEY = "bench/raw/loop-pong"
PING_CHANNEL = "ping"
DATA_QOS: dict[str, Any] = LANE_QOS[Lane.DATA]

THROUGHPUT_TARGETS: dict[int, float] = {64: 0.30, 1024: 0.40, 32768: 0.60}  # at least
RTT_TARGETS: dict[str, float] = {"p50": 1.5, "p99": 2.0}  # at most

_SEQ = struct.Struct(">I")
#: Random bytes: what telebot puts on the wire is ciphertext, so no side sends zeros.
PAYLOADS: dict[int, bytes] = {size: os.urandom(size) for size in SIZES}

Counters = dict[str, int]
_T = TypeVar("_T")


# -- shared helpers ---------------------------------------------------------------------


def listen_settings(port: int) -> ZenohSettings:
    return ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)


def connect_settings(port: int) -> ZenohSettings:
    return ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)


def open_session(settings: ZenohSettings) -> Any:
    """A raw zenoh session with the config telebot builds from ``settings``."""
    return zenoh.open(build_zenoh_config(settings))


def percentile(values: Sequence[float], q: float) -> float:
    """Nearest-rank ``q``-th percentile (nan when empty)."""
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q / 100 * len(ordered)))]


def divided(value: float, base: float) -> float:
    """``value / base``, nan where ``base`` is 0 (a starved receiver counted nothing yet)."""
    return value / base if base else float("nan")


def ping_payload(seq: int) -> bytes:
    return _SEQ.pack(seq) + PAYLOADS[PING_SIZE][_SEQ.size :]


def reply(line: str) -> None:
    """A child's answer to the parent: one line on stdout."""
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


# -- child processes (receivers and echoes) ---------------------------------------------


def raw_child(port: int) -> None:
    """Raw zenoh: counts ``RAW_DATA_KEY``, echoes both ping keys (one via a loop)."""
    session = open_session(listen_settings(port))
    delivered = 0

    def on_data(sample: Any) -> None:
        nonlocal delivered
        sample.payload.to_bytes()
        delivered += 1

    pong = session.declare_publisher(RAW_PONG_KEY, **DATA_QOS)

    def on_ping(sample: Any) -> None:
        pong.put(sample.payload.to_bytes())

    loop = asyncio.new_event_loop()
    threading.Thread(target=loop.run_forever, name="echo-loop", daemon=True).start()
    loop_pong = session.declare_publisher(RAW_LOOP_PONG_KEY, **DATA_QOS)

    def on_loop_ping(sample: Any) -> None:
        loop.call_soon_threadsafe(loop_pong.put, sample.payload.to_bytes())

    subscribers = [
        session.declare_subscriber(RAW_DATA_KEY, on_data),
        session.declare_subscriber(RAW_PING_KEY, on_ping),
        session.declare_subscriber(RAW_LOOP_PING_KEY, on_loop_ping),
    ]
    reply("ready")
    try:
        for line in sys.stdin:
            command = line.strip()
            if command == "reset":
                delivered = 0
                reply("ok")
            elif command == "count":
                reply(json.dumps({"delivered": delivered}))
            elif command == "quit":
                break
    finally:
        for subscriber in subscribers:
            subscriber.undeclare()
        pong.undeclare()
        loop_pong.undeclare()
        session.close()


async def serve_commands(totals: Callable[[], Counters]) -> None:
    """An asyncio child's command loop; ``count`` answers ``totals()`` minus the last reset."""
    baseline = {key: 0 for key in totals()}
    reply("ready")
    while True:
        command = (await asyncio.to_thread(sys.stdin.readline)).strip()
        if command == "reset":
            baseline = totals()
            reply("ok")
        elif command == "count":
            reply(json.dumps({key: value - baseline[key] for key, value in totals().items()}))
        else:  # "quit" or end of input
            return


def transport_totals(transport: ZenohTransport) -> Counters:
    return {
        # Taken off zenoh by the transport's reader thread.
        "zenoh_received": transport.stats.received,
        # Dropped by the transport's bounded queue: the event loop fell behind.
        "queue_dropped": transport.stats.dropped,
    }


async def transport_child(port: int) -> None:
    """Informational: ``RAW_DATA_KEY`` received through ``ZenohTransport.subscribe`` only."""
    delivered = batches = 0

    def on_batch(batch: Sequence[Sample]) -> None:
        nonlocal delivered, batches
        delivered += len(batch)
        batches += 1

    async with ZenohTransport(listen_settings(port)) as transport:
        transport.subscribe(RAW_DATA_KEY, on_batch)
        await serve_commands(
            lambda: {"delivered": delivered, "batches": batches, **transport_totals(transport)}
        )


async def telebot_child(port: int, home: Path) -> None:
    """A robot that counts datagrams on every channel but ``ping``, which it echoes."""
    identity = Identity.load(home)
    contacts = ContactBook.load(home)
    calls: list[Call] = []
    delivered = 0

    def count(datagram: ReceivedDatagram) -> None:
        nonlocal delivered
        delivered += 1

    def on_call(call: Call) -> None:
        calls.append(call)

        def open_channel(name: str) -> None:
            channel = call.channel(name)
            if name == PING_CHANNEL:
                channel.set_callback(lambda datagram: channel.send(datagram.payload))
            else:
                channel.set_callback(count)

        call.on_unopened_channel = open_channel

    async with (
        ZenohTransport(listen_settings(port)) as transport,
        RobotEndpoint(transport, identity, contacts) as robot,
    ):
        robot.on_call = on_call

        def totals() -> Counters:
            channels = [ch for call in calls for ch in call.channels.values()]
            return {
                "delivered": delivered,
                **transport_totals(transport),
                "channel_dropped": sum(ch.stats.dropped for ch in channels),
                "calls_ended": sum(not call.active for call in calls),
            }

        await serve_commands(totals)


def run_child(argv: Sequence[str], profile: bool) -> None:
    kind, port = argv[0], int(argv[1])
    if kind == "raw":
        raw_child(port)
        return
    if kind == "raw-aead":
        raw_aead_child(port, Suite[argv[2]], bytes.fromhex(argv[3]))
        return
    child: Coroutine[Any, Any, None] = (
        transport_child(port) if kind == "transport" else telebot_child(port, Path(argv[2]))
    )
    profiler = cProfile.Profile() if profile else None  # profiles the loop thread only
    if profiler is not None:
        profiler.enable()
    try:
        asyncio.run(child)
    finally:
        if profiler is not None:
            profiler.disable()
            text = io.StringIO()
            pstats.Stats(profiler, stream=text).sort_stats("tottime").print_stats(25)
            print(text.getvalue(), file=sys.stderr, flush=True)


# -- the parent: senders and pingers ----------------------------------------------------


class Child:
    """A child process of this script, driven by lines on its stdin and stdout.

    The calls block; from the event loop, run them with ``asyncio.to_thread`` so that a
    call's heartbeats keep flowing meanwhile.
    """

    def __init__(self, args: Sequence[str], *, profile: bool = False) -> None:
        command = [sys.executable, str(Path(__file__).resolve()), "--child", *args]
        if profile:
            command.append("--profile")
        self._proc = subprocess.Popen(
            command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1
        )
        self._lines: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._read, name="child-stdout", daemon=True).start()
        try:
            self._expect("ready", timeout=30.0)
        except BaseException:
            self.close()
            raise

    def _read(self) -> None:
        assert self._proc.stdout is not None
        for line in self._proc.stdout:
            self._lines.put(line.strip())
        self._lines.put(None)

    def _next_line(self, timeout: float) -> str:
        try:
            line = self._lines.get(timeout=timeout)
        except queue.Empty:
            raise RuntimeError(f"child {self._proc.args!r} did not answer in {timeout} s") from None
        if line is None:
            raise RuntimeError(f"child exited with status {self._proc.wait()}")
        return line

    def _expect(self, expected: str, timeout: float = 10.0) -> None:
        line = self._next_line(timeout)
        if line != expected:
            raise RuntimeError(f"child said {line!r}, expected {expected!r}")

    def _send(self, command: str) -> None:
        assert self._proc.stdin is not None
        self._proc.stdin.write(command + "\n")
        self._proc.stdin.flush()

    def reset(self) -> None:
        """Zero the child's counters."""
        self._send("reset")
        self._expect("ok")

    def count(self) -> Counters:
        """The child's counters since the last reset."""
        self._send("count")
        counts: Counters = json.loads(self._next_line(10.0))
        return counts

    def wait_drained(self, timeout: float = 10.0) -> Counters:
        """Poll until the delivered count stops moving: nothing is left in flight."""
        deadline = time.monotonic() + timeout
        last = self.count()
        while time.monotonic() < deadline:
            time.sleep(DRAIN_POLL)
            now = self.count()
            if now["delivered"] == last["delivered"]:
                return now
            last = now
        return last

    def close(self) -> None:
        """Ask the child to quit; kill it if it has not within a few seconds."""
        with contextlib.suppress(OSError, ValueError):
            self._send("quit")
            assert self._proc.stdin is not None
            self._proc.stdin.close()
        try:
            self._proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()


@dataclass
class Flood:
    """One throughput measurement."""

    sent: int
    elapsed: float
    counts: Counters  # the receiver's counters at read-out
    late: int  # delivered after the read-out (not counted)

    @property
    def arrived(self) -> int:
        return self.counts["delivered"]

    @property
    def rate(self) -> float:
        return self.arrived / self.elapsed


@dataclass
class Pings:
    """Round-trip times in microseconds, and how many pings got no reply."""

    rtts_us: list[float]
    lost: int

    def p(self, q: float) -> float:
        return percentile(self.rtts_us, q)

    def add(self, other: Pings) -> None:
        self.rtts_us += other.rtts_us
        self.lost += other.lost


class RoundTrips(NamedTuple, Generic[_T]):
    """One value per kind of ping in C."""

    raw: _T  # raw zenoh, bridged into asyncio at both ends: the baseline
    raw_callback: _T  # raw zenoh, echoed from the child's zenoh callback (info)
    telebot: _T


async def await_route(send: Callable[[], None], child: Child, timeout: float = 10.0) -> None:
    """Send until something arrives, let it drain, zero the counters: set-up is over."""
    deadline = time.monotonic() + timeout
    while (await asyncio.to_thread(child.count))["delivered"] == 0:
        if time.monotonic() > deadline:
            raise RuntimeError("nothing reached the receiver: no route between the processes")
        for _ in range(10):
            send()
        await asyncio.sleep(0.05)
    await asyncio.sleep(SETTLE)
    await asyncio.to_thread(child.wait_drained)
    await asyncio.to_thread(child.reset)


def finish_flood(child: Child, sent: int, elapsed: float) -> Flood:
    """Read the receiver's count (the sender has just stopped), then let it drain."""
    time.sleep(GRACE)
    counts = child.count()
    drained = child.wait_drained()
    return Flood(sent, elapsed, counts, drained["delivered"] - counts["delivered"])


def raw_flood(publisher: Any, child: Child, size: int) -> Flood:
    """A: put as fast as possible for DURATION seconds; the child counts arrivals."""
    payload = PAYLOADS[size]
    asyncio.run(await_route(lambda: publisher.put(payload), child))
    sent = 0
    start = time.perf_counter()
    end = start + DURATION
    while time.perf_counter() < end:
        for _ in range(CHECK_CLOCK_EVERY):
            publisher.put(payload)
        sent += CHECK_CLOCK_EVERY
    return finish_flood(child, sent, time.perf_counter() - start)


def raw_floods(child: Child, port: int) -> dict[int, Flood]:
    """Flood ``child`` (listening on ``port``) from a raw zenoh publisher, every size."""
    with contextlib.closing(open_session(connect_settings(port))) as session:
        publisher = session.declare_publisher(RAW_DATA_KEY, **DATA_QOS)
        try:
            return {size: raw_flood(publisher, child, size) for size in SIZES}
        finally:
            publisher.undeclare()


class Pinger:
    """Sends pings one at a time; ``on_reply(seq)`` (on the loop) completes the current one.

    Sequence numbers go on across runs, so a late reply never completes a later ping.
    """

    def __init__(self) -> None:
        self._seq = 0
        self._waiting: tuple[int, asyncio.Future[None]] | None = None

    def on_reply(self, seq: int) -> None:
        waiting = self._waiting
        if waiting is not None and waiting[0] == seq and not waiting[1].done():
            waiting[1].set_result(None)

    async def run(self, send: Callable[[bytes], None], count: int) -> Pings:
        """Send ``count`` pings, each after the reply to the last (or its timeout)."""
        loop = asyncio.get_running_loop()
        pings = Pings([], 0)
        for seq in range(self._seq, self._seq + count):
            future: asyncio.Future[None] = loop.create_future()
            self._waiting = (seq, future)
            payload = ping_payload(seq)
            start = time.perf_counter_ns()
            send(payload)
            try:
                await asyncio.wait_for(future, PING_TIMEOUT)
            except TimeoutError:
                pings.lost += 1
                continue
            pings.rtts_us.append((time.perf_counter_ns() - start) / 1000)
        self._seq += count
        self._waiting = None
        return pings


@contextlib.contextmanager
def raw_ping_route(
    session: Any, ping_key: str, pong_key: str, pinger: Pinger
) -> Iterator[Callable[[bytes], None]]:
    """C, raw: replies reach the loop from zenoh's thread by ``call_soon_threadsafe``."""
    loop = asyncio.get_running_loop()

    def on_pong(sample: Any) -> None:
        (seq,) = _SEQ.unpack_from(sample.payload.to_bytes())
        loop.call_soon_threadsafe(pinger.on_reply, seq)

    subscriber = session.declare_subscriber(pong_key, on_pong)
    publisher = session.declare_publisher(ping_key, **DATA_QOS)
    try:
        yield publisher.put
    finally:
        subscriber.undeclare()
        publisher.undeclare()


@contextlib.contextmanager
def telebot_ping_route(call: Call, pinger: Pinger) -> Iterator[Callable[[bytes], None]]:
    """C, telebot: ping on a channel; the child robot echoes every datagram."""
    channel = call.channel(PING_CHANNEL)

    def on_echo(datagram: ReceivedDatagram) -> None:
        assert isinstance(datagram.payload, bytes)
        pinger.on_reply(_SEQ.unpack_from(datagram.payload)[0])

    channel.set_callback(on_echo)
    try:
        yield channel.send
    finally:
        channel.set_callback(None)


async def round_trips(call: Call, raw_session: Any) -> RoundTrips[Pings]:
    """C: the three kinds of ping, warmed up, then alternating in ``PING_ROUNDS`` rounds."""
    pingers = RoundTrips(Pinger(), Pinger(), Pinger())
    with contextlib.ExitStack() as routes:
        sends = RoundTrips(
            routes.enter_context(
                raw_ping_route(raw_session, RAW_LOOP_PING_KEY, RAW_LOOP_PONG_KEY, pingers.raw)
            ),
            routes.enter_context(
                raw_ping_route(raw_session, RAW_PING_KEY, RAW_PONG_KEY, pingers.raw_callback)
            ),
            routes.enter_context(telebot_ping_route(call, pingers.telebot)),
        )
        await asyncio.sleep(SETTLE)  # let the raw subscriptions reach the child
        for pinger, send in zip(pingers, sends, strict=True):
            await pinger.run(send, WARMUP_PINGS)
        results = RoundTrips(Pings([], 0), Pings([], 0), Pings([], 0))
        for _ in range(PING_ROUNDS):
            for pinger, send, pings in zip(pingers, sends, results, strict=True):
                pings.add(await pinger.run(send, PINGS // PING_ROUNDS))
    return results


def measure_raw() -> dict[int, Flood]:
    """A: raw floods into a raw child."""
    port = free_port()
    child = Child(["raw", str(port)])
    try:
        return raw_floods(child, port)
    finally:
        child.close()


def measure_transport() -> dict[int, Flood]:
    """Informational: A's raw flood received by a bare ``ZenohTransport.subscribe``."""
    port = free_port()
    child = Child(["transport", str(port)])
    try:
        return raw_floods(child, port)
    finally:
        child.close()


async def telebot_flood(call: Call, child: Child, size: int) -> Flood:
    """B: send on a channel as fast as possible from asyncio, yielding regularly."""
    channel = call.channel(f"data{size}")
    payload = PAYLOADS[size]
    await await_route(lambda: channel.send(payload), child)
    loop = asyncio.get_running_loop()
    sent = 0
    start = loop.time()
    end = start + DURATION
    while loop.time() < end:
        for _ in range(YIELD_EVERY):
            channel.send(payload)
        sent += YIELD_EVERY
        await asyncio.sleep(0)
    elapsed = loop.time() - start
    flood = await asyncio.to_thread(finish_flood, child, sent, elapsed)
    if not call.active:
        raise RuntimeError(f"the call {call.end} during the {size} B flood")
    return flood


async def telebot_measurements(
    port: int, user_home: Path, child: Child, raw_port: int
) -> tuple[dict[int, Flood], RoundTrips[Pings]]:
    identity = Identity.load(user_home)
    known = KnownRobots.load(user_home)
    async with (
        ZenohTransport(connect_settings(port)) as transport,
        UserEndpoint(transport, identity, known) as user,
    ):
        # Set-up is not measured: a loaded machine (a test run beside other work) may be slow.
        call = await user.call(ROBOT, timeout=30.0)
        if call.suite is not bench_suite():  # A+AEAD would not be its baseline
            raise RuntimeError(f"the call uses {call.suite.label}, not {bench_suite().label}")
        try:
            floods = {size: await telebot_flood(call, child, size) for size in SIZES}
            raw_session = await asyncio.to_thread(open_session, connect_settings(raw_port))
            try:
                pings = await round_trips(call, raw_session)
            finally:
                await asyncio.to_thread(raw_session.close)
        finally:
            await call.hangup("benchmark done")
    return floods, pings


def measure_telebot(profile: bool) -> tuple[dict[int, Flood], RoundTrips[Pings]]:
    """B against a robot child, then C against it and a raw echo child side by side."""
    with tempfile.TemporaryDirectory(prefix="telebot-bench-") as tmp:
        create_paired_homes(Path(tmp), ROBOT, USER)
        robot_home, user_home = Path(tmp) / "robot", Path(tmp) / "user"
        port, raw_port = free_port(), free_port()
        with contextlib.ExitStack() as children:
            child = Child(["telebot", str(port), str(robot_home)], profile=profile)
            children.callback(child.close)
            children.callback(Child(["raw", str(raw_port)]).close)
            return asyncio.run(telebot_measurements(port, user_home, child, raw_port))


# -- baseline: raw zenoh + AEAD ---------------------------------------------------------


def bench_suite() -> Suite:
    """The suite two telebot ends with ``cipher = "auto"`` on this machine agree on."""
    preference = suite_preference("auto")
    suite = choose_suite(preference, preference)
    assert suite is not None
    return suite


def raw_aead_child(port: int, suite: Suite, key: bytes) -> None:
    """Raw zenoh + AEAD: opens every sample of ``RAW_DATA_KEY`` in the zenoh callback."""
    session = open_session(listen_settings(port))
    opener, nonce = suite.aead(key), suite.nonce
    delivered = forged = 0

    def on_data(sample: Any) -> None:
        nonlocal delivered, forged
        data = sample.payload.to_bytes()
        header = data[:18]
        try:
            opener.decrypt(nonce(int.from_bytes(data[10:18], "big")), data[18:], header)
        except Exception:  # InvalidTag: never expected, but counted rather than hidden
            forged += 1
            return
        delivered += 1

    subscriber = session.declare_subscriber(RAW_DATA_KEY, on_data)
    reply("ready")
    try:
        for line in sys.stdin:
            command = line.strip()
            if command == "reset":
                delivered = forged = 0
                reply("ok")
            elif command == "count":
                reply(json.dumps({"delivered": delivered, "forged": forged}))
            elif command == "quit":
                break
    finally:
        subscriber.undeclare()
        session.close()


class Sealer:
    """Seals payloads as DATA frames are sealed: 18-byte header, counter nonce."""

    def __init__(self, suite: Suite, key: bytes) -> None:
        self._aead, self._nonce = suite.aead(key), suite.nonce
        self._counter = 0
        self._call_id = os.urandom(8)

    def seal(self, payload: bytes) -> bytes:
        counter = self._counter
        self._counter = counter + 1
        header = DataFrame.make_header(self._call_id, counter)
        return header + self._aead.encrypt(self._nonce(counter), payload, header)


def raw_aead_flood(publisher: Any, sealer: Sealer, child: Child, size: int) -> Flood:
    """A+AEAD: seal and put as fast as possible for DURATION seconds."""
    payload = PAYLOADS[size]
    seal, put = sealer.seal, publisher.put
    asyncio.run(await_route(lambda: put(seal(payload)), child))
    sent = 0
    start = time.perf_counter()
    end = start + DURATION
    while time.perf_counter() < end:
        for _ in range(CHECK_CLOCK_EVERY):
            put(seal(payload))
        sent += CHECK_CLOCK_EVERY
    return finish_flood(child, sent, time.perf_counter() - start)


def measure_raw_aead(suite: Suite) -> dict[int, Flood]:
    """A+AEAD: sealed raw floods into a child that opens them in its zenoh callback."""
    port, key = free_port(), os.urandom(32)
    child = Child(["raw-aead", str(port), suite.name, key.hex()])
    try:
        with contextlib.closing(open_session(connect_settings(port))) as session:
            publisher = session.declare_publisher(RAW_DATA_KEY, **DATA_QOS)
            try:
                sealer = Sealer(suite, key)
                return {size: raw_aead_flood(publisher, sealer, child, size) for size in SIZES}
            finally:
                publisher.undeclare()
    finally:
        child.close()


def raw_aead_report(res: Results) -> tuple[list[str], float]:
    """The A+AEAD table, and telebot's 32 KB rate against it."""
    lines = [
        "",
        f"A+AEAD. Encrypted baseline: raw zenoh, sealed with {res.suite.label} before each "
        "put and opened in the child's zenoh callback",
        f"{'size':>6} | {'sent':>10} {'arrived':>10} {'msg/s':>10} {'÷ raw':>6} | "
        f"{'telebot ÷ it':>12}",
    ]
    for size in SIZES:
        aead, raw, tb = res.raw_aead[size], res.raw[size], res.telebot[size]
        if aead.counts.get("forged"):
            raise RuntimeError(f"{aead.counts['forged']} sealed samples failed to open")
        lines.append(
            f"{size_label(size):>6} | {aead.sent:>10,} {aead.arrived:>10,} {aead.rate:>10,.0f} "
            f"{divided(aead.rate, raw.rate):>6.3f} | {divided(tb.rate, aead.rate):>12.3f}"
        )
    lines.append(
        "  the physical limit of an encrypted channel on this CPU: one AEAD operation "
        "per message on each side, nothing else"
    )
    return lines, divided(res.telebot[32768].rate, res.raw_aead[32768].rate)


# -- report -----------------------------------------------------------------------------


@dataclass
class Results:
    raw: dict[int, Flood]
    transport: dict[int, Flood]
    telebot: dict[int, Flood]
    pings: RoundTrips[Pings]
    suite: Suite  # the cipher of the telebot call and of the A+AEAD baseline
    raw_aead: dict[int, Flood]


def verdict(ok: bool) -> str:
    return "PASS" if ok else "MISS"


def size_label(size: int) -> str:
    return f"{size // 1024} KB" if size >= 1024 else f"{size} B"


def report(res: Results, survival: Survival, elapsed: float) -> list[str]:
    from _survival import survival_report

    qos = ", ".join(f"{key}={value}" for key, value in DATA_QOS.items())
    lines = [
        "",
        f"A/B. Throughput: {DURATION:g} s flood per size, DATA lane ({qos})",
        f"{'size':>6} | {'raw sent':>10} {'arrived':>10} {'msg/s':>10} | "
        f"{'telebot sent':>12} {'arrived':>10} {'msg/s':>10} | {'ratio':>6}  target",
    ]
    ratios: dict[int, float] = {}
    for size in SIZES:
        raw, tb = res.raw[size], res.telebot[size]
        ratios[size] = ratio = divided(tb.rate, raw.rate)
        target = THROUGHPUT_TARGETS[size]
        lines.append(
            f"{size_label(size):>6} | {raw.sent:>10,} {raw.arrived:>10,} {raw.rate:>10,.0f} | "
            f"{tb.sent:>12,} {tb.arrived:>10,} {tb.rate:>10,.0f} | {ratio:>6.3f}  "
            f">= {target:.2f} {verdict(ratio >= target)}"
        )
    aead_lines, ratio_32k_aead = raw_aead_report(res)
    lines += aead_lines
    lines += [
        "",
        "Where the receive side stops (info). Late = delivered after the read-out.",
        f"{'size':>6} | {'raw late':>8} | {'transport only':>14} {'÷ raw':>6} {'batch':>5} "
        f"{'q.drop':>7} {'late':>6} | {'telebot off zenoh':>17} {'q.drop':>7} {'late':>6}",
    ]
    for size in SIZES:
        raw, tr, tb = res.raw[size], res.transport[size], res.telebot[size]
        batch = tr.arrived / max(1, tr.counts["batches"])
        lines.append(
            f"{size_label(size):>6} | {raw.late:>8,} | {tr.rate:>14,.0f} {divided(tr.rate, raw.rate):>6.3f} "
            f"{batch:>5.1f} {tr.counts['queue_dropped']:>7,} {tr.late:>6,} | "
            f"{tb.counts['zenoh_received'] / tb.elapsed:>15,.0f}/s "
            f"{tb.counts['queue_dropped']:>7,} {tb.late:>6,}"
        )
    lines += [
        "  transport only: A's raw publisher -> ZenohTransport.subscribe -> asyncio batch "
        "callback (msg/s; batch = mean samples per loop wake-up)",
        "  telebot off zenoh: frames/s that telebot's reader thread took in during B "
        "(a BUNDLE frame carries many datagrams); "
        "q.drop: dropped by the transport's bounded queue (the loop fell behind)",
        "",
        f"C. Round trip: {PING_SIZE} B, one in flight, {PINGS} pings after {WARMUP_PINGS} "
        f"warm-up, in {PING_ROUNDS} alternating rounds",
        f"{'':>4} | {'raw µs':>9} | {'telebot µs':>10} | {'ratio':>6}  target "
        f"| {'raw, echo in callback (info)':>28}",
    ]
    pings = res.pings
    rtt_ratios: dict[str, float] = {}
    for name, q in (("p50", 50.0), ("p99", 99.0)):
        raw_us, tb_us = pings.raw.p(q), pings.telebot.p(q)
        rtt_ratios[name] = ratio = tb_us / raw_us
        target = RTT_TARGETS[name]
        lines.append(
            f"{name:>4} | {raw_us:>9.1f} | {tb_us:>10.1f} | {ratio:>6.3f}  "
            f"<= {target:.1f} {verdict(ratio <= target)} | {pings.raw_callback.p(q):>25.1f} µs"
        )
    lines += [
        "  raw: zenoh bridged into asyncio at both ends (call_soon_threadsafe), as telebot is",
        f"lost pings: raw {pings.raw.lost}, telebot {pings.telebot.lost}, "
        f"raw echo in callback {pings.raw_callback.lost}",
    ]
    survival_lines, fields = survival_report(survival)
    lines += survival_lines
    lines += [
        f"(took {elapsed:.1f} s)",
        f"RESULT ratio_64={ratios[64]:.3f} ratio_1k={ratios[1024]:.3f} "
        f"ratio_32k_aead={ratio_32k_aead:.3f} rtt_p50_ratio={rtt_ratios['p50']:.3f} "
        f"rtt_p99_ratio={rtt_ratios['p99']:.3f} ratio_32k={ratios[32768]:.3f} "
        + " ".join(f"{key}={value}" for key, value in fields.items()),
    ]
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--child", nargs="+", metavar="ARG", help=argparse.SUPPRESS)
    parser.add_argument(
        "--profile", action="store_true", help="cProfile the telebot receiver (to stderr)"
    )
    parser.add_argument(
        "--survival-only", action="store_true", help="run sections D and E only (about 60 s)"
    )
    parser.add_argument("--quick", action="store_true", help="a little of each (seconds)")
    args = parser.parse_args()
    if args.child:  # before importing D and E: the tests' rig and client cost a child ~1 s
        run_child(args.child, args.profile)
        return
    import _survival
    from _survival import measure_survival, survival_report

    if args.quick:
        global DURATION, WARMUP_PINGS, PINGS, PING_ROUNDS, SETTLE, GRACE, DRAIN_POLL
        DURATION, WARMUP_PINGS, PINGS, PING_ROUNDS = 0.1, 10, 40, 2
        SETTLE, GRACE, DRAIN_POLL = 0.05, 0.05, 0.05
        # The cut outlasts the call timeout (0.5 s): the call drops, whatever drops it first.
        _survival.FLOOD_SECONDS, _survival.CUTS, _survival.CUT_SECONDS = 0.3, 1, 0.6
    started = time.monotonic()
    if args.survival_only:
        lines, fields = survival_report(measure_survival(free_port()))
        print("\n".join(lines))
        print(f"(took {time.monotonic() - started:.1f} s)")
        print("RESULT " + " ".join(f"{k}={v}" for k, v in fields.items()))
        return
    # A quick run measures D and E beside A to C (in a thread, with an event loop of its
    # own): mostly process start-ups and waits, they overlap well; a full run measures
    # each on an otherwise idle machine.
    with concurrent.futures.ThreadPoolExecutor(max_workers=1) as beside:
        later = beside.submit(measure_survival, free_port()) if args.quick else None
        results = measure_a_to_c(args.profile)
        survival = later.result() if later is not None else measure_survival(free_port())
    print("\n".join(report(results, survival, time.monotonic() - started)))


def measure_a_to_c(profile: bool) -> Results:
    """Sections A, A+AEAD, the transport-only flood, B and C, one after the other."""
    print("raw zenoh: floods ...", flush=True)
    raw = measure_raw()
    suite = bench_suite()
    print(f"raw zenoh + AEAD ({suite.label}): floods ...", flush=True)
    raw_aead = measure_raw_aead(suite)
    print("zenoh transport only: floods ...", flush=True)
    transport = measure_transport()
    print("telebot call: floods, then pings alternating with raw zenoh ...", flush=True)
    telebot, pings = measure_telebot(profile)
    return Results(raw, transport, telebot, pings, suite, raw_aead)


if __name__ == "__main__":
    main()
