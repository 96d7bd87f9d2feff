"""Stop latency and drop-to-stop latency, across processes over zenoh on loopback.

Run ``.venv/bin/python bench/safety.py`` (about 2 minutes on 2 cores). Three processes on
one machine, zenoh in peer mode over TCP on 127.0.0.1 with multicast scouting off:

- the robot (a child, ``--child robot PORT HOME``): the simulated robot on the small map
  with a fast base (1.5 m/s, 3 m/s²), the :class:`~telebot.services.safety.robot.SafetyDriver`
  (deadman = the default call timeout, 0.5 s; watchdog thread) and the
  :class:`~telebot.services.robot.RobotServer`, as ``telebot-robot run`` wires them, on a
  ``RobotEndpoint`` listening on a free port. Its NavStack is :class:`TimedNavStack`: a
  ``SimNavStack`` whose ``stop()`` takes ``time.monotonic()`` right after the base has been
  halted (``SimNavStack.stop()`` sets the base's velocity to zero at once, no ramp) and
  prints it on stdout, with whether the base was moving, how long the robot had heard
  nothing on any call, and who stopped it: the supervisor (its reason, and the event that
  made it check: a request, a control step, a call's drop timer) or the watchdog thread
  (whose ``emergency_stop()`` request is carried out by the next control step; the moment
  of the request is printed too);
- the user (this process): ``RobotClient`` on a call to the robot;
- a driver (a child, ``--child driver PORT HOME``), only for B.

``CLOCK_MONOTONIC`` is system-wide on Linux, so times taken in different processes compare.

A. Stop latency: ``STOPS`` times: ``arm``, ``fwd ±3`` by chat (towards the middle of the
   corridor; its first reply awaited), ``MOTION`` s of driving, then ``t0 =
   time.monotonic()`` and ``await client.stop()``; the latency is the robot's stop time
   minus ``t0``: user → zenoh → the robot's event loop → the safety channel's handler →
   ``SafetyDriver`` → ``SimNavStack.stop()`` returned. It is measured idle and while video-sized
   floods run on a BULK channel (``flood``): 30 frames/s of 2 datagrams × 30,000 random bytes
   (a 640×480 JPEG is 30–60 KB: 2 datagrams of at most 32 KB), 1.8 MB/s per direction:
   (a) robot → user only, as the robot's camera video flows; (b) both ways, as in a
   telepresence call whose user's webcam also shows on the robot's screen (the paper's
   robot). (b) is the honest stress of the stop path: the flood then shares the user's
   sending loop and session, the TCP link and the robot's receiving path with the stop,
   which travels user → robot. The flood target is the worse of the two p99s.
B. Drop-to-stop: ``DROP_RUNS`` times: the driver child calls, arms, starts ``fwd ±3``
   and prints ``moving`` once its pose stream shows the base driving; this process takes
   ``t_sig = time.monotonic()`` and freezes it with SIGSTOP; the latency is the robot's next
   stop time minus ``t_sig``. Then SIGCONT: the thawed driver finds its call dropped and calls
   again. What bounds it: the deadman counts from the driver's last frame, and heartbeats
   come every 50 ms, so that frame left 0–50 ms before the freeze. The robot's call drops
   on its own timer 1 ms after the timeout, and the supervisor checks the deadman first
   thing then (the watchdog thread, polling every 10 ms, and the 20 Hz control step are
   usually later), so the stop lands in [t_sig + 0.45 s, t_sig + 0.5 s + a few ms]: its
   p99 sits on the 0.5 s target, a few milliseconds over or under from run to run.

Percentiles are nearest-rank. Each target line prints target ÷ measured (above 1 = within
the target); PASS/MISS is informational, the exit status is non-zero only when the
benchmark itself broke. The last line (``RESULT ...``) is for scripts. ``--quick``: 3 stops
a series (its floods settling 0.1 s) and 1 freeze (a check that it runs).

Children (internal) talk by lines. The robot prints JSON objects (``{"ready": true}``,
``{"stop": t, "moving": bool, "by": ..., "silent": s}``, ``{"emergency": t}``,
``{"flood": {...}}``)
and reads ``flood on``, ``flood off``, ``counts`` and ``quit`` on stdin. The driver prints
``{"moving": t}`` and ``{"ended": kind}`` and runs until killed.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import math
import os
import queue
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import AsyncGenerator, Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from telebot.apps.robot_daemon import deadman_time
from telebot.channels.call import Call, RobotEndpoint, UserEndpoint
from telebot.channels.channel import Channel, ReceivedDatagram
from telebot.channels.transports.base import Lane
from telebot.channels.transports.zenoh import ZenohTransport
from telebot.config import CallSettings, MediaConfig, RobotConfig, SimSettings, ZenohSettings
from telebot.errors import TelebotError
from telebot.identity import ContactBook, Identity, KnownRobots, Role, create_paired_homes
from telebot.reasons import Reason
from telebot.robot.nav import Velocity
from telebot.robot.sim.stack import SimNavStack
from telebot.safety import Action, Stop
from telebot.services.base import ServiceConfig
from telebot.services.chat.wire import ChatReply
from telebot.services.client import RobotClient
from telebot.services.robot import RobotServer
from telebot.services.safety.robot import SafetyDriver
from telebot.testing.net import free_port

ROBOT = "safebot"
USER = "safeuser"
STOPS = 200
DROP_RUNS = 30
#: Driving time before each stop (s): the base is well under way (it accelerates at 3 m/s²).
MOTION = 0.1
#: How long a flood runs before the first stop under it (s).
FLOOD_SETTLE = 0.5
FLOOD = "flood"
FLOOD_FPS = 30.0
FLOOD_DATAGRAM = 30_000
FLOOD_PER_FRAME = 2
#: The corridor of the small map runs from x = 1.0 to 10.5 at y = 1.2: drive to its middle.
MIDDLE_X = 5.75
TARGET_STOP_MS = 5.0
TARGET_FLOOD_MS = 20.0
TARGET_DROP_S = 0.5
FAST = SimSettings(
    map="small", max_linear_speed=1.5, linear_accel=3.0, max_angular_speed=3.0, angular_accel=8.0
)


_out = threading.Lock()


def emit(message: dict[str, Any]) -> None:
    """One JSON line on stdout (the loop and the watchdog thread both write)."""
    line = json.dumps(message) + "\n"
    with _out:
        sys.stdout.write(line)
        sys.stdout.flush()


# -- child: the robot -----------------------------------------------------------------------


class TimedNavStack(SimNavStack):
    """A SimNavStack that reports when each stop has halted the base (see the docstring)."""

    report: Callable[[dict[str, Any]], None] | None = None
    #: ``reason|event`` of the supervisor's Stop being carried out (see :class:`TimedDriver`).
    why = ""
    #: How long the robot has heard nothing on any call (s): the driver's, in part B.
    silence: Callable[[], float] = staticmethod(lambda: math.nan)
    _in_step = False

    def _report(self, message: dict[str, Any]) -> None:
        if self.report is not None:
            self.report(message)

    def stop(self) -> None:
        moving = self.velocity() != Velocity()
        super().stop()
        t = time.monotonic()  # the base's velocity is zero from here on
        by = "watchdog" if self._in_step else self.why
        self._report({"stop": t, "moving": moving, "by": by, "silent": self.silence()})

    def step(self, now: float) -> None:
        # A stop() inside step() is the watchdog's emergency request being carried out.
        self._in_step = True
        try:
            super().step(now)
        finally:
            self._in_step = False

    def emergency_stop(self, reason: str) -> None:
        t = time.monotonic()
        super().emergency_stop(reason)
        self._report({"emergency": t})


class TimedDriver(SafetyDriver):
    """A SafetyDriver that tells its :class:`TimedNavStack` why each Stop is carried out.

    The reason is the supervisor's; the event that made the supervisor check is noted
    too: its control-step ``tick`` or a call's end (``leave``, when the call's own drop
    timer fired). Both run the deadman check first.
    """

    nav: TimedNavStack
    _event = "a request"

    def apply(self, actions: Iterable[Action]) -> None:
        for action in actions:
            if isinstance(action, Stop):
                self.nav.why = f"{action.text}|{self._event}"
            super().apply((action,))

    def tick(self) -> None:
        self._event = "a control step"
        try:
            super().tick()
        finally:
            self._event = "a request"

    def leave(self, call: Call) -> None:
        self._event = "the call's drop timer"
        try:
            super().leave(call)
        finally:
            self._event = "a request"


def stopped_by(by: str) -> str:
    """A stop's cause in words, from the record's ``reason|event`` (see telebot.safety)."""
    if by == "watchdog":
        return "the watchdog thread (carried out at the next control step)"
    reason, _, event = by.partition("|")
    if reason.endswith("link lost"):
        return f"the deadman, checked at {event}"
    if reason.endswith("dropped"):
        return f"the driver's call dropping, at {event}"
    return reason


class Flood:
    """Video-sized datagrams on the ``flood`` channel of every call, and a count of arrivals."""

    def __init__(self) -> None:
        self.channels: list[tuple[Call, Channel]] = []
        self.sending = False
        self.sent = 0
        self.received = 0
        self.payloads = [os.urandom(FLOOD_DATAGRAM) for _ in range(FLOOD_PER_FRAME)]

    def attach(self, call: Call) -> Channel:
        channel = call.channel(FLOOD, lane=Lane.BULK)
        channel.set_callback(self._on_datagram)
        self.channels.append((call, channel))
        return channel

    def _on_datagram(self, datagram: ReceivedDatagram) -> None:
        self.received += 1

    def send_frame(self) -> None:
        for call, channel in list(self.channels):
            if not call.active:
                self.channels.remove((call, channel))
                continue
            with contextlib.suppress(TelebotError):
                for payload in self.payloads:
                    channel.send(payload)
                    self.sent += 1

    async def run(self) -> None:
        """Send a frame every 1/30 s while ``sending`` (on an absolute schedule)."""
        loop = asyncio.get_running_loop()
        period = 1.0 / FLOOD_FPS
        next_frame = loop.time()
        while True:
            if self.sending:
                self.send_frame()
            next_frame = max(next_frame + period, loop.time() - period)
            await asyncio.sleep(max(0.0, next_frame - loop.time()))


async def robot_child(port: int, home: Path) -> None:
    loop = asyncio.get_running_loop()
    nav = await asyncio.to_thread(TimedNavStack.from_settings, FAST, now=loop.time())
    assert isinstance(nav, TimedNavStack)  # from_settings builds ``cls``
    nav.report = emit
    # The daemon's deadman: one heartbeat before the call timeout (robot_daemon.deadman_time).
    safety = TimedDriver(nav, timeout=deadman_time(RobotConfig()), max_speed=FAST.max_linear_speed)
    server = RobotServer(
        nav,
        control_hz=FAST.control_hz,
        map_name="small",
        safety=safety,
        # Replies unspoken: an espeak-ng run per chat command would load the measured robot.
        config=ServiceConfig(media=MediaConfig(voice="off")),
    )
    await server.prepare()
    flood = Flood()
    calls: list[Call] = []
    nav.silence = lambda: min((time.monotonic() - c.last_heard for c in calls), default=math.nan)
    settings = ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    with safety:
        async with (
            ZenohTransport(settings) as transport,
            RobotEndpoint(transport, Identity.load(home), ContactBook.load(home)) as endpoint,
        ):

            def on_call(call: Call) -> None:
                calls.append(call)
                server.serve(call)
                flood.attach(call)

            endpoint.on_call = on_call
            tasks = [asyncio.create_task(server.run()), asyncio.create_task(flood.run())]
            emit({"ready": True})
            try:
                while True:
                    command = (await asyncio.to_thread(sys.stdin.readline)).strip()
                    if command in ("", "quit"):
                        break
                    if command == "flood on":
                        flood.sending = True
                    elif command == "flood off":
                        flood.sending = False
                    elif command == "counts":
                        emit({"flood": {"sent": flood.sent, "received": flood.received}})
            finally:
                for task in tasks:
                    task.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)
                for call in endpoint.calls:
                    call.hangup_now("benchmark done")
                await asyncio.sleep(0.05)


# -- child: the driver that gets frozen -----------------------------------------------------


async def arm(client: RobotClient, patience: float = 10.0) -> None:
    """Re-arm; the drive may still be held for a moment by a call about to be dropped."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + patience
    while True:
        ack = await client.arm()
        if ack.ok:
            return
        if loop.time() > deadline:
            raise RuntimeError(f"arm refused: {ack.text}")
        if ack.code == Reason.NOT_HOLDER:
            await client.take_drive()
        await asyncio.sleep(0.05)


async def first_reply(client: RobotClient, command: str, timeout: float | None = None) -> ChatReply:
    """The first reply to ``command`` (a motion's acknowledgement); the motion runs on."""
    replies = client.chat_replies(command, timeout=timeout)
    assert isinstance(replies, AsyncGenerator)  # closed here, not left to the GC
    async with contextlib.aclosing(replies):
        return await anext(replies)


async def start_motion(client: RobotClient) -> None:
    """``fwd ±3`` towards the middle of the corridor; returns once it is acknowledged."""
    pose = client.latest_pose.value or await client.pose()
    command = "fwd 3" if pose.x < MIDDLE_X else "fwd -3"
    reply = await first_reply(client, command, timeout=10)
    if not reply.ok or reply.final:
        raise RuntimeError(f"{command!r} refused: {reply.text}")


async def driver_child(port: int, home: Path) -> None:
    settings = ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    async with (
        ZenohTransport(settings) as transport,
        UserEndpoint(transport, Identity.load(home), KnownRobots.load(home)) as user,
    ):
        while True:
            call = await user.call(ROBOT, timeout=10)
            client = RobotClient(call)
            try:
                await arm(client)
                await start_motion(client)
                async with asyncio.timeout(5):
                    while abs((await client.pose()).v) <= 0.05:
                        pass
                emit({"moving": time.monotonic()})
                end = await call.wait_ended()  # the parent freezes us meanwhile
                emit({"ended": end.kind})
            finally:
                await call.hangup()


# -- the parent: the user -------------------------------------------------------------------


class Child:
    """A child process of this script; its JSON stdout lines are read by a thread."""

    def __init__(self, role: str, port: int, home: Path) -> None:
        command = [sys.executable, str(Path(__file__).resolve()), "--child", role, str(port)]
        self.proc = subprocess.Popen(
            [*command, str(home)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )
        self.role = role
        self.lines: queue.Queue[dict[str, Any] | None] = queue.Queue()
        threading.Thread(target=self._read, name=f"{role}-stdout", daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(json.loads(line))
        self.lines.put(None)

    def next(self, timeout: float) -> dict[str, Any]:
        try:
            message = self.lines.get(timeout=timeout)
        except queue.Empty:
            raise RuntimeError(f"the {self.role} child said nothing for {timeout} s") from None
        if message is None:
            raise RuntimeError(f"the {self.role} child exited with status {self.proc.wait()}")
        return message

    def until(self, check: Callable[[dict[str, Any]], bool], timeout: float) -> dict[str, Any]:
        """Skip lines until one passes ``check``."""
        deadline = time.monotonic() + timeout
        while True:
            message = self.next(max(0.001, deadline - time.monotonic()))
            if check(message):
                return message

    async def wait(self, check: Callable[[dict[str, Any]], bool], timeout: float) -> dict[str, Any]:
        return await asyncio.to_thread(self.until, check, timeout)

    async def after(self, t: float, timeout: float, *keys: str) -> dict[str, Any]:
        """The first record with one of ``keys`` (default ``stop``) at or after time ``t``."""
        wanted = keys or ("stop",)
        return await self.wait(lambda m: any(m.get(k, -math.inf) >= t for k in wanted), timeout)

    def tell(self, command: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def signal(self, sig: signal.Signals) -> None:
        self.proc.send_signal(sig)

    def close(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            if self.proc.stdin is not None:
                self.proc.stdin.close()
        if self.role != "robot":
            self.proc.send_signal(signal.SIGCONT)
            self.proc.kill()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


@dataclass
class Stops:
    """A series of stops: latencies to the base (ms), to the acknowledgement (ms), and how."""

    name: str
    base_ms: list[float] = field(default_factory=list)
    ack_ms: list[float] = field(default_factory=list)
    moving: int = 0
    flood: dict[str, int] = field(default_factory=dict)
    user_received: int = 0
    seconds: float = 0.0


async def stop_series(
    name: str, client: RobotClient, robot: Child, user_flood: Flood, flood: str
) -> Stops:
    """A: ``STOPS`` stops; ``flood`` is "off", "robot->user" or "both"."""
    result = Stops(name)
    sender = asyncio.create_task(user_flood.run())
    user_flood.sending = flood == "both"
    robot.tell("flood on" if flood != "off" else "flood off")
    received_before = user_flood.received
    robot.tell("counts")
    before = (await robot.wait(lambda m: "flood" in m, 5))["flood"]
    started = time.monotonic()
    try:
        await asyncio.sleep(FLOOD_SETTLE if flood != "off" else 0.0)
        for _ in range(STOPS):
            if not (await client.arm()).ok:
                raise RuntimeError("arm refused")
            await start_motion(client)
            await asyncio.sleep(MOTION)
            t0 = time.monotonic()
            ack = await client.stop()
            acked = time.monotonic()
            if not ack.ok:
                raise RuntimeError(f"stop not acknowledged: {ack.text}")
            record = await robot.after(t0, 5)
            result.base_ms.append((record["stop"] - t0) * 1000)
            result.ack_ms.append((acked - t0) * 1000)
            result.moving += bool(record["moving"])
    finally:
        result.seconds = time.monotonic() - started
        user_flood.sending = False
        robot.tell("flood off")
        sender.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await sender
    robot.tell("counts")
    after = (await robot.wait(lambda m: "flood" in m, 5))["flood"]
    result.flood = {key: after[key] - before[key] for key in after}
    result.user_received = user_flood.received - received_before
    return result


async def stop_latencies(port: int, user_home: Path, robot: Child) -> list[Stops]:
    settings = ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    async with (
        ZenohTransport(settings) as transport,
        UserEndpoint(transport, Identity.load(user_home), KnownRobots.load(user_home)) as user,
    ):
        call = await user.call(ROBOT, timeout=10)
        client = RobotClient(call)
        user_flood = Flood()
        user_flood.attach(call)
        try:
            await arm(client)
            series = []
            for name, flood in (
                ("idle", "off"),
                ("video robot -> user", "robot->user"),
                ("video both ways", "both"),
            ):
                print(f"A. {STOPS} stops, {name} ...", flush=True)
                series.append(await stop_series(name, client, robot, user_flood, flood))
            return series
        finally:
            await call.hangup("benchmark done")


@dataclass
class Drops:
    base_s: list[float] = field(default_factory=list)
    request_s: list[float] = field(default_factory=list)
    silent_s: list[float] = field(default_factory=list)
    by: dict[str, int] = field(default_factory=dict)
    moving: int = 0


async def drop_latencies(driver: Child, robot: Child) -> Drops:
    """B: freeze the driver ``DROP_RUNS`` times; time until the robot's base stopped."""
    result = Drops()
    for _ in range(DROP_RUNS):
        await driver.wait(lambda m: "moving" in m, 30)
        await asyncio.sleep(0.05)  # a few frames of driving after the pose said so
        t_sig = time.monotonic()
        driver.signal(signal.SIGSTOP)
        # When the watchdog thread sees the silence first, its request comes before the stop.
        first = await robot.after(t_sig, 5, "stop", "emergency")
        record = first
        if "emergency" in first:
            result.request_s.append(first["emergency"] - t_sig)
            record = await robot.after(t_sig, 5)
        result.base_s.append(record["stop"] - t_sig)
        by = stopped_by(record["by"])
        result.by[by] = result.by.get(by, 0) + 1
        result.moving += bool(record["moving"])
        result.silent_s.append(record["silent"])
        await asyncio.sleep(0.3)  # the robot drops the call: the driver must find it gone
        driver.signal(signal.SIGCONT)
        await driver.wait(lambda m: "ended" in m, 10)
    return result


def nearest_rank(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[max(0, math.ceil(q * len(ordered)) - 1)]


def verdict(ok: bool) -> str:
    return "PASS" if ok else "MISS"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--child", nargs=3, metavar=("ROLE", "PORT", "HOME"), help=argparse.SUPPRESS
    )
    parser.add_argument("--quick", action="store_true", help="3 stops a series, 1 freeze")
    args = parser.parse_args()
    if args.quick:
        global STOPS, DROP_RUNS, FLOOD_SETTLE
        STOPS, DROP_RUNS, FLOOD_SETTLE = 3, 1, 0.1
    if args.child:
        # The robot logs every safety stop as a warning: hundreds of lines here.
        logging.basicConfig(level=logging.ERROR)
        role, port, home = args.child[0], int(args.child[1]), Path(args.child[2])
        with contextlib.suppress(KeyboardInterrupt):
            asyncio.run(robot_child(port, home) if role == "robot" else driver_child(port, home))
        return
    started = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="telebot-bench-") as tmp:
        homes = Path(tmp)
        create_paired_homes(homes, ROBOT, USER, role=Role.DRIVER)
        port = free_port()
        robot = Child("robot", port, homes / "robot")
        try:
            robot.until(lambda m: "ready" in m, 60)
            series = asyncio.run(stop_latencies(port, homes / "user", robot))
            print(f"B. {DROP_RUNS} freezes of a driver process ...", flush=True)
            driver = Child("driver", port, homes / "user")
            try:
                drops = asyncio.run(drop_latencies(driver, robot))
            finally:
                driver.close()
        finally:
            robot.close()

    lines = [""]
    for stops in series:
        p50, p99 = nearest_rank(stops.base_ms, 0.5), nearest_rank(stops.base_ms, 0.99)
        lines.append(
            f"A. stop -> base at rest, {stops.name}, {len(stops.base_ms)} stops "
            f"({stops.moving} while driving): p50 {p50:.2f} ms, p99 {p99:.2f} ms, "
            f"max {max(stops.base_ms):.2f} ms; stop -> ack p50 "
            f"{statistics.median(stops.ack_ms):.2f} ms"
        )
        if stops.name != "idle":
            fps_out = stops.flood["sent"] / FLOOD_PER_FRAME / stops.seconds
            fps_in = stops.flood["received"] / FLOOD_PER_FRAME / stops.seconds
            got = stops.user_received / FLOOD_PER_FRAME / stops.seconds
            lines.append(
                f"   flood: robot sent {fps_out:.1f} frames/s ({got:.1f} reached the user), "
                f"the user's reached the robot at {fps_in:.1f} frames/s; "
                f"{FLOOD_PER_FRAME} × {FLOOD_DATAGRAM:,} B per frame"
            )
    idle = series[0]
    floods = series[1:]
    stop_p99 = nearest_rank(idle.base_ms, 0.99)
    flood_p99 = max(nearest_rank(s.base_ms, 0.99) for s in floods)
    drop_p50 = nearest_rank(drops.base_s, 0.5) * 1000
    drop_p99 = nearest_rank(drops.base_s, 0.99) * 1000
    by = ", ".join(f"{count} by {who}" for who, count in sorted(drops.by.items()))
    requests = (
        f"; the watchdog's request came p50 {nearest_rank(drops.request_s, 0.5) * 1000:.0f} ms "
        f"after SIGSTOP in {len(drops.request_s)} runs (carried out at the next control step)"
        if drops.request_s
        else ""
    )
    lines += [
        f"B. SIGSTOP -> base at rest, {len(drops.base_s)} runs ({drops.moving} while driving; "
        f"{by}): p50 {drop_p50:.1f} ms, p99 {drop_p99:.1f} ms, "
        f"min {min(drops.base_s) * 1000:.0f} ms, max {max(drops.base_s) * 1000:.0f} ms "
        f"(deadman {deadman_time(RobotConfig()):g} s, call timeout {CallSettings().timeout:g} s){requests}",
        f"   the robot had heard nothing from the driver for p50 "
        f"{nearest_rank(drops.silent_s, 0.5) * 1000:.1f} ms, max {max(drops.silent_s) * 1000:.1f} "
        "ms when it stopped (the freeze came 0–50 ms, one heartbeat period, after the driver's "
        "last frame)",
        "",
        f"target stop p99 <= {TARGET_STOP_MS:g} ms idle: ratio {TARGET_STOP_MS / stop_p99:.1f} "
        f"{verdict(stop_p99 <= TARGET_STOP_MS)}",
        f"target stop p99 <= {TARGET_FLOOD_MS:g} ms under flood (worse of the two): ratio "
        f"{TARGET_FLOOD_MS / flood_p99:.1f} {verdict(flood_p99 <= TARGET_FLOOD_MS)}",
        f"target drop-to-stop p99 <= {TARGET_DROP_S * 1000:.0f} ms: ratio "
        f"{TARGET_DROP_S * 1000 / drop_p99:.2f} {verdict(drop_p99 <= TARGET_DROP_S * 1000)}",
        f"(took {time.monotonic() - started:.1f} s)",
        f"RESULT stop_p99_ms={stop_p99:.2f} stop_flood_p99_ms={flood_p99:.2f} "
        f"drop_p99_ms={drop_p99:.1f}",
    ]
    print("\n".join(lines))


if __name__ == "__main__":
    main()
