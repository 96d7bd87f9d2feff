"""Video: 640 × 480 at 30 fps over zenoh loopback across two processes, and on a lossy link.

Run ``.venv/bin/python bench/video.py`` (about 45 s). What it measures:

A. zenoh loopback. A child process is the robot: ``ZenohTransport`` listening on a free TCP
   port of 127.0.0.1 (multicast scouting off), ``RobotEndpoint``, the simulated robot on
   the "small" map turning in place (stepped at 20 Hz, so every frame is a new picture),
   and a ``VideoSender`` per call with the default settings (640 × 480, up to 30 fps,
   JPEG quality 80, adaptive). This process calls it and reads frames with a
   ``VideoReceiver`` for ``DURATION`` seconds after ``WARMUP``: delivered fps, and the
   telebot-added latency of each frame, from the robot's capture time (wall clock, taken
   when the camera handed over the picture) to the decoded frame here (wall clock after
   decoding): JPEG encoding, fragmentation, sealing, zenoh, opening, reassembly and
   decoding. Both processes share the machine's clock. Targets: >= 29 fps, p50 <= 5 ms,
   p99 <= 15 ms.
A2. (info) The same with frames forced into several datagrams (``max_payload`` 9 KB, a
   second video channel on the same call): fragmentation's cost.
B. Memory transport at 10 % loss both ways (seeded), robot and user in this process, for
   ``DURATION`` seconds: the share of the frames the robot sent that reached the consumer
   decoded. Target >= 80 %.
C. (info) Memory transport capped at 250 KB/s (no random loss): what the adaptation settles
   on (frame rate, size, quality) and what arrives.

Each target line prints target ÷ measured (above 1 = within the target; for fps and the
delivered share, measured ÷ target). The last line (``RESULT ...``) is for scripts.
``--quick``: video at 320 × 240 (A2 in datagrams of <= 3000 B, so that its frames are
still fragmented), 0.3 s of warm-up, 0.6 s of A and B, 0.5 s of C (a check that it runs).
Child
(internal): ``--child PORT HOME``; it prints ``ready`` and serves until its stdin closes,
then prints its counters as JSON.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from _child import Child
from telebot.channels.call import Call, RobotEndpoint, UserEndpoint
from telebot.channels.transports.base import Lane
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.channels.transports.zenoh import ZenohTransport
from telebot.config import CallSettings, SimSettings, ZenohSettings
from telebot.identity import ContactBook, Identity, KnownRobots, create_paired_homes
from telebot.robot.sim.stack import SimNavStack
from telebot.services.video.receiver import VideoReceiver
from telebot.services.video.sender import VideoSender
from telebot.services.video.stream import video_channel
from telebot.services.video.wire import VideoSettings
from telebot.testing.net import free_port

ROBOT = "videobot"
USER = "videouser"
#: A second video channel, bench only: the same camera forced into several datagrams.
FRAG_CHANNEL = "video-frag"
FRAG_PAYLOAD = 9000
CAMERA = (640, 480)  # the simulated camera's and the video's size
# Setting up a call takes well under a second, but a loaded machine (a test run beside
# other work) has been seen to take over 10 s while the robot's video starts.
CALL_TIMEOUT = 30.0
WARMUP = 2.0
DURATION = 10.0
CAPPED_DURATION = 8.0
LOSS = 0.10
CAP = 250_000.0
TARGET_FPS = 29.0
TARGET_P50_MS = 5.0
TARGET_P99_MS = 15.0
TARGET_DELIVERED = 0.80


def video_settings(**settings: Any) -> VideoSettings:
    """The default video settings at the bench's camera size."""
    width, height = CAMERA
    return VideoSettings(width=width, height=height, **settings)


def sim_robot() -> SimNavStack:
    """The simulated robot, its clock the event loop's (:func:`drive_robot` steps it to
    ``loop.time()``: from a clock at 0 the first step would integrate the machine's whole
    uptime, a minute of blocked loop on a machine up for a day)."""
    width, height = CAMERA
    return SimNavStack.from_settings(
        SimSettings(map="small", camera_width=width, camera_height=height),
        now=asyncio.get_running_loop().time(),
    )


async def drive_robot(nav: SimNavStack) -> None:
    """Step the robot at 20 Hz, turning in place, as the robot daemon steps it."""
    loop = asyncio.get_running_loop()
    while True:
        nav.drive(0.0, 0.4)
        nav.step(loop.time())
        await asyncio.sleep(0.05)


def serve(call: Call, nav: SimNavStack, senders: list[VideoSender]) -> None:
    """The robot's video senders on ``call``: the real one and the bench's fragmented one."""
    main = VideoSender.for_call(call, nav, video_settings())
    frag = VideoSender(
        nav,
        call.channel(FRAG_CHANNEL, lane=Lane.BULK),
        video_settings(max_payload=FRAG_PAYLOAD),
        call_stats=call.stats,
    )
    for sender in (main, frag):
        sender.start()
        senders.append(sender)


# -- child: the robot -------------------------------------------------------------------


async def robot_child(port: int, home: Path) -> None:
    nav = sim_robot()
    nav.get_frame()  # build the renderer before the clock starts
    settings = ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    senders: list[VideoSender] = []
    async with (
        ZenohTransport(settings) as transport,
        RobotEndpoint(transport, Identity.load(home), ContactBook.load(home)) as robot,
    ):
        robot.on_call = lambda call: serve(call, nav, senders)
        stepping = asyncio.ensure_future(drive_robot(nav))
        print("ready", flush=True)
        await asyncio.to_thread(sys.stdin.read)  # until the parent closes our stdin
        stepping.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await stepping
        for sender in senders:
            await sender.close()
    stats = {
        "frames": [s.stats.frames for s in senders],
        "errors": sum(s.stats.errors for s in senders),
        "quality": [s.quality for s in senders],
    }
    print(json.dumps(stats), flush=True)


# -- parent: the user -------------------------------------------------------------------


@dataclass
class Run:
    """What one receiver saw during the measured window."""

    seconds: float = 0.0
    latencies_ms: list[float] = field(default_factory=list)
    fragments: list[int] = field(default_factory=list)
    sizes: list[int] = field(default_factory=list)
    lost: int = 0
    expected: int = 0

    @property
    def fps(self) -> float:
        return len(self.latencies_ms) / self.seconds if self.seconds else 0.0


async def watch(receiver: VideoReceiver, warmup: float, duration: float) -> Run:
    """Read frames for ``warmup`` then ``duration`` seconds; measure the second part."""
    loop = asyncio.get_running_loop()
    run = Run()
    end_warmup = loop.time() + warmup
    while loop.time() < end_warmup:
        await receiver.next_frame(10.0)
    lost0, expected0 = receiver.stats.lost, receiver.stats.expected
    start = loop.time()
    end = start + duration
    while loop.time() < end:
        frame = await receiver.next_frame(10.0)
        run.latencies_ms.append(frame.latency * 1000)
        run.fragments.append(frame.fragments)
        run.sizes.append(frame.jpeg_bytes)
    run.seconds = loop.time() - start
    run.lost = receiver.stats.lost - lost0
    run.expected = receiver.stats.expected - expected0
    return run


async def zenoh_runs(port: int, user_home: Path) -> tuple[Run, Run]:
    """A and A2: the default stream, then the fragmented one, in one call to the child."""
    settings = ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    async with (
        ZenohTransport(settings) as transport,
        UserEndpoint(transport, Identity.load(user_home), KnownRobots.load(user_home)) as user,
    ):
        call = await user.call(ROBOT, timeout=CALL_TIMEOUT)
        try:
            async with VideoReceiver(video_channel(call)) as receiver:
                plain = await watch(receiver, WARMUP, DURATION)
            frag_channel = call.channel(FRAG_CHANNEL, lane=Lane.BULK)
            async with VideoReceiver(frag_channel) as receiver:
                frag = await watch(receiver, WARMUP, DURATION / 2)
        finally:
            await call.hangup("benchmark done")
    return plain, frag


@dataclass
class MemoryRun:
    sent: int
    delivered: int
    run: Run
    fps: float
    size: tuple[int, int]
    quality: int


async def memory_run(homes: Path, *, seed: int, duration: float, **link: float) -> MemoryRun:
    """B and C: robot and user in this process on a memory hub with ``link`` conditions."""
    hub = MemoryHub(seed=seed)
    settings = CallSettings(timeout=2.0)  # a lossy link must not drop the call at set-up
    robot_home, user_home = homes / "robot", homes / "user"
    nav = sim_robot()
    nav.get_frame()
    senders: list[VideoSender] = []
    async with (
        MemoryTransport(hub, "robot") as robot_transport,
        MemoryTransport(hub, "user") as user_transport,
        RobotEndpoint(
            robot_transport,
            Identity.load(robot_home),
            ContactBook.load(robot_home),
            settings=settings,
        ) as robot,
        UserEndpoint(
            user_transport,
            Identity.load(user_home),
            KnownRobots.load(user_home),
            settings=settings,
        ) as user,
    ):

        def on_call(call: Call) -> None:
            sender = VideoSender.for_call(call, nav, video_settings())
            sender.start()
            senders.append(sender)

        robot.on_call = on_call
        hub.set_link("robot", "user", **link)
        stepping = asyncio.ensure_future(drive_robot(nav))
        call = await user.call(ROBOT, timeout=CALL_TIMEOUT)
        try:
            async with VideoReceiver(video_channel(call)) as receiver:
                await watch(receiver, WARMUP, 0.0)
                sender = senders[0]
                sent0, delivered0 = sender.stats.frames, receiver.stats.delivered
                run = await watch(receiver, 0.0, duration)
                await asyncio.sleep(0.1)  # the last frames in flight
                sent = sender.stats.frames - sent0
                delivered = receiver.stats.delivered - delivered0
                result = MemoryRun(
                    sent,
                    delivered,
                    run,
                    sender.measured_fps,
                    (sender.width, sender.height),
                    sender.quality,
                )
        finally:
            await call.hangup("benchmark done")
            stepping.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await stepping
            for s in senders:
                await s.close()
    return result


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def verdict(ok: bool) -> str:
    return "PASS" if ok else "MISS"


def capped_line(capped: MemoryRun) -> str:
    """Section C's line (informational)."""
    share = capped.delivered / capped.sent if capped.sent else 0.0
    return (
        f"C. (info) memory capped at {CAP / 1000:g} KB/s, {CAPPED_DURATION:g} s: sender "
        f"settled at {capped.fps:.0f} fps, {capped.size[0]}x{capped.size[1]}, quality "
        f"{capped.quality}; {capped.run.fps:.1f} fps arrived "
        f"({share:.0%} of those sent), JPEG "
        f"{statistics.fmean(capped.run.sizes) / 1000:.1f} KB, latency p50 "
        f"{statistics.median(capped.run.latencies_ms):.0f} ms"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--child", nargs=2, metavar=("PORT", "HOME"), help=argparse.SUPPRESS)
    parser.add_argument("--quick", action="store_true", help="a second of each (seconds)")
    args = parser.parse_args()
    global CAMERA, WARMUP, DURATION, CAPPED_DURATION, FRAG_PAYLOAD
    if args.quick:
        CAMERA, WARMUP, DURATION, CAPPED_DURATION = (320, 240), 0.3, 0.6, 0.5
        FRAG_PAYLOAD = 3000  # a 320 × 240 frame is about 10 KB
    if args.child:
        asyncio.run(robot_child(int(args.child[0]), Path(args.child[1])))
        return
    started = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="telebot-bench-") as tmp:
        homes = Path(tmp)
        create_paired_homes(homes, ROBOT, USER)
        port = free_port()
        print("A. zenoh loopback: robot in a child process ...", flush=True)
        quick = ["--quick"] if args.quick else []
        child = Child(__file__, str(port), str(homes / "robot"), *quick)
        try:
            if child.next_line(60.0) != "ready":
                raise RuntimeError("the robot child did not start")
            plain, frag = asyncio.run(zenoh_runs(port, homes / "user"))
        finally:
            robot_stats = child.close()
        print(f"B. memory transport at {LOSS:.0%} loss both ways ...", flush=True)
        lossy = asyncio.run(memory_run(homes, seed=2024, duration=DURATION, loss=LOSS))
        print(f"C. memory transport capped at {CAP / 1000:g} KB/s ...", flush=True)
        capped = asyncio.run(
            memory_run(homes, seed=7, duration=CAPPED_DURATION, bandwidth=CAP, max_queue_delay=0.5)
        )

    p50 = statistics.median(plain.latencies_ms)
    p99 = percentile(plain.latencies_ms, 0.99)
    f50 = statistics.median(frag.latencies_ms)
    f99 = percentile(frag.latencies_ms, 0.99)
    share = lossy.delivered / lossy.sent if lossy.sent else 0.0
    lines = [
        "",
        f"A. zenoh loopback, {CAMERA[0]}x{CAMERA[1]} @ 30 fps, {DURATION:g} s after {WARMUP:g} s warm-up: "
        f"{len(plain.latencies_ms)} frames, {plain.fps:.2f} fps delivered "
        f"(lost {plain.lost} of {plain.expected}); "
        f"{statistics.fmean(plain.fragments):.2f} fragments/frame, "
        f"JPEG {statistics.fmean(plain.sizes) / 1000:.1f} KB on average",
        f"   fps target >= {TARGET_FPS:g}: ratio {plain.fps / TARGET_FPS:.2f} "
        f"{verdict(plain.fps >= TARGET_FPS)}",
        f"   added latency (capture -> decoded): p50 {p50:.2f} ms, p99 {p99:.2f} ms, "
        f"max {max(plain.latencies_ms):.2f} ms | targets p50 <= {TARGET_P50_MS:g} ms: ratio "
        f"{TARGET_P50_MS / p50:.1f} {verdict(p50 <= TARGET_P50_MS)}; p99 <= {TARGET_P99_MS:g} "
        f"ms: ratio {TARGET_P99_MS / p99:.1f} {verdict(p99 <= TARGET_P99_MS)}",
        f"A2. (info) same camera in datagrams of <= {FRAG_PAYLOAD} B, {DURATION / 2:g} s: "
        f"{frag.fps:.2f} fps, {statistics.fmean(frag.fragments):.2f} fragments/frame, "
        f"latency p50 {f50:.2f} ms, p99 {f99:.2f} ms (lost {frag.lost} of {frag.expected})",
        f"   robot child: frames sent {robot_stats.get('frames')}, "
        f"errors {robot_stats.get('errors')}",
        f"B. memory, {LOSS:.0%} loss both ways, {DURATION:g} s: {lossy.delivered} of "
        f"{lossy.sent} frames sent reached the consumer = {share:.1%}; "
        f"{lossy.run.fps:.1f} fps; sender at {lossy.fps:.0f} fps, "
        f"{lossy.size[0]}x{lossy.size[1]}, quality {lossy.quality}; "
        f"{statistics.fmean(lossy.run.fragments):.2f} fragments/frame",
        f"   target >= {TARGET_DELIVERED:.0%}: ratio {share / TARGET_DELIVERED:.2f} "
        f"{verdict(share >= TARGET_DELIVERED)}",
        capped_line(capped),
        f"(took {time.monotonic() - started:.1f} s)",
        f"RESULT fps={plain.fps:.2f} lat_p50_ms={p50:.2f} lat_p99_ms={p99:.2f} "
        f"delivered_loss10={share:.3f}",
    ]
    print("\n".join(lines))


if __name__ == "__main__":
    main()
