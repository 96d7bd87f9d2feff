"""Video over real calls: VideoSender on the robot, VideoReceiver on the user, through
authenticated calls on a (lossy) memory hub; and, across two processes over zenoh, a video
flood that must not hold up stop commands on the CONTROL lane.

The memory transport records lanes but does not model their priorities (all lanes share
one FIFO link), so lane priority is tested over zenoh. This file is also that test's child
process: ``python tests/test_video.py --flood-child PORT HOME``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import io
import json
import os
import re
import statistics
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import ROBOT, Homes, memory_endpoints, wait_until
from telebot.apps import video_cli
from telebot.apps.video_cli import MAX_FILL, Recorder, video, video_log
from telebot.channels.call import Call, RobotEndpoint, UserEndpoint
from telebot.channels.channel import ReceivedDatagram
from telebot.channels.transports.base import Lane
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import AppConfig, CallSettings, MemorySettings, SimSettings, TransportSettings
from telebot.identity import ContactBook, Identity
from telebot.robot.nav import CameraFrame, CameraInfo
from telebot.robot.sim.stack import SimNavStack
from telebot.services.media.wire import CODEC_H264, CODEC_JPEG
from telebot.services.shm import FrameRingReader, FrameRingWriter, RingFrame
from telebot.services.video.receiver import VideoFrame, VideoReceiver, frames
from telebot.services.video.sender import VideoSender, _shared_camera
from telebot.services.video.stream import video_channel
from telebot.services.video.wire import VIDEO, VideoSettings, encode_jpeg, fragment
from telebot.testing.net import free_port


def sim_nav() -> SimNavStack:
    return SimNavStack.from_settings(SimSettings(map="small", camera_width=640, camera_height=480))


@pytest.fixture(scope="module")
def nav() -> SimNavStack:
    return sim_nav()


@dataclass
class Link:
    hub: MemoryHub
    robot_call: Call
    call: Call


@contextlib.asynccontextmanager
async def linked(homes: Homes, *, seed: int = 5, timeout: float = 2.0) -> AsyncIterator[Link]:
    """A robot and a user on one memory hub, in a call (a lenient timeout for lossy links)."""
    hub = MemoryHub(seed=seed)
    settings = CallSettings(timeout=timeout)
    robot_calls: list[Call] = []
    async with memory_endpoints(homes, hub, settings) as (robot, user):
        robot.on_call = robot_calls.append
        call = await user.call(ROBOT)
        try:
            yield Link(hub, robot_calls[0], call)
        finally:
            await call.hangup()


async def take(receiver: VideoReceiver, n: int, timeout: float = 10.0) -> list[VideoFrame]:
    return [await receiver.next_frame(timeout) for _ in range(n)]


def diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean(np.abs(a.astype(np.int16) - b.astype(np.int16))))


async def test_frames_flow_decoded_with_their_camera_id_and_capture_time(
    homes: Homes, nav: SimNavStack
) -> None:
    nav.select_camera("navcam")
    async with linked(homes) as link:
        started = time.time()
        async with (
            VideoSender.for_call(link.robot_call, nav) as sender,
            VideoReceiver(video_channel(link.call)) as receiver,
        ):
            got = await take(receiver, 10)
            assert (sender.width, sender.height, sender.quality, sender.fps) == (640, 480, 80, 30)
            assert sender.watched and sender.running
        assert not sender.running
    for frame in got:
        assert frame.image.shape == (480, 640, 3) and frame.image.dtype == np.uint8
        assert frame.camera == "navcam" and frame.fragments == 1
        assert started <= frame.capture_time <= frame.received_time <= time.time()
    ids = [f.frame_id for f in got]
    assert ids == sorted(set(ids))
    # JPEG at quality 80 of the very picture the camera renders (the robot does not move).
    assert diff(got[-1].image, nav.get_frame("navcam").image) < 4.0
    assert receiver.stats.delivered == 10 and receiver.stats.reports >= 1
    assert sender.stats.frames >= 10 and sender.stats.reports >= 1


async def test_a_frame_needing_more_than_one_datagram_is_rebuilt(
    homes: Homes, nav: SimNavStack
) -> None:
    nav.select_camera("navcam")
    settings = VideoSettings(max_payload=8000)  # a ~23 KB frame takes 3 datagrams
    async with (
        linked(homes) as link,
        VideoSender.for_call(link.robot_call, nav, settings) as sender,
        VideoReceiver(video_channel(link.call)) as receiver,
    ):
        got = await take(receiver, 5)
        # The live bit rate counts the whole frames of the last second, as they came.
        live = receiver.bitrate
    assert live > 0 and receiver.stats.received_bytes >= sum(f.jpeg_bytes for f in got)
    assert receiver.stats.codec == CODEC_JPEG
    assert all(f.fragments >= 3 for f in got)
    assert sender.stats.fragments >= 3 * sender.stats.frames > 0
    assert diff(got[-1].image, nav.get_frame("navcam").image) < 4.0
    # Nothing is lost on this hub, but a loaded machine may starve the receiver past a
    # partial frame's deadline, which then drops it whole (counted as incomplete, never
    # shown half; its late fragments may open and give it up once more): no frame is shown
    # that was not sent whole.
    stats = receiver.reassembler.stats
    assert len(got) <= stats.frames <= sender.stats.frames


async def test_camera_switch_changes_the_picture(homes: Homes, nav: SimNavStack) -> None:
    nav.select_camera("navcam")
    async with (
        linked(homes) as link,
        VideoSender.for_call(link.robot_call, nav),
        VideoReceiver(video_channel(link.call)) as receiver,
    ):
        before = await take(receiver, 2)
        nav.select_camera("usercam")  # as the chat command "usercam" does
        after = before[-1]
        for _ in range(30):
            after = await receiver.next_frame(5.0)
            if after.camera == "usercam":
                break
    nav.select_camera("navcam")
    assert [f.camera for f in before] == ["navcam", "navcam"]
    assert after.camera == "usercam"
    same = diff(before[0].image, before[1].image)
    switched = diff(before[-1].image, after.image)
    assert same < 2.0 < 10.0 < switched


async def test_video_is_sent_only_while_someone_watches(homes: Homes, nav: SimNavStack) -> None:
    settings = VideoSettings(idle_after=0.3)
    async with (
        linked(homes) as link,
        VideoSender.for_call(link.robot_call, nav, settings) as sender,
    ):
        await asyncio.sleep(0.2)
        assert sender.stats.frames == 0 and not sender.watched  # nobody asked
        async with VideoReceiver(video_channel(link.call), report_interval=0.1) as receiver:
            await take(receiver, 3)
        # The receiver is gone: it said bye (and its reports stop), and so does the video.
        await wait_until(lambda: not sender.watched)
        sent = sender.stats.frames
        await asyncio.sleep(0.2)
        assert sender.stats.frames == sent
        assert sender.running  # idle, ready for the next viewer
        async with VideoReceiver(video_channel(link.call)) as again:
            frame = await again.next_frame(5.0)
        assert frame.frame_id > sent  # fresh: nothing stale from the channel's queue
        assert again.stats.stale > 0 or again.stats.delivered == 1


async def test_video_on_a_lossy_link(homes: Homes, nav: SimNavStack) -> None:
    async with linked(homes, seed=11) as link:
        link.hub.set_link("robot", "user", loss=0.1, jitter=0.005)
        async with (
            VideoSender.for_call(link.robot_call, nav) as sender,
            VideoReceiver(video_channel(link.call)) as receiver,
        ):
            got = await take(receiver, 40)
    ids = [f.frame_id for f in got]
    assert ids == sorted(set(ids))  # latest frame wins: never an older one after a newer
    stats = receiver.stats
    assert stats.lost > 0 and stats.loss < 0.3
    assert sender.controller.loss > 0
    assert sender.controller.max_fragments <= 2
    # Whole pictures, at most the camera's size: to fit two fragments at 10 % loss the
    # rate control may scale them down (more so on a loaded machine).
    assert all(f.image.shape[2] == 3 and 0 < f.image.shape[1] <= 640 for f in got)


async def test_both_ends_stop_when_the_call_ends(homes: Homes, nav: SimNavStack) -> None:
    async with linked(homes) as link:
        sender = VideoSender.for_call(link.robot_call, nav)
        sender.start()
        seen = 0
        try:
            async with contextlib.aclosing(frames(video_channel(link.call))) as video:
                async for _ in video:
                    seen += 1
                    if seen == 3:
                        await link.call.hangup("done")
            await wait_until(lambda: not sender.running)
        finally:
            await sender.close()
    assert seen >= 3
    assert not sender.running


async def test_corrupt_frames_and_garbage_are_dropped_and_counted(
    homes: Homes, nav: SimNavStack
) -> None:
    good = encode_jpeg(nav.get_frame("navcam").image, 70)
    corrupt = good[:100] + b"\x00" * 50 + b"\xff\xd9"
    async with linked(homes) as link:
        robot = video_channel(link.robot_call)
        async with VideoReceiver(video_channel(link.call)) as receiver:
            waiting = asyncio.ensure_future(receiver.next_frame(5.0))
            for datagram in [b"\x01garbage", "text", *fragment(1, "navcam", time.time(), corrupt)]:
                robot.send(datagram)
            await wait_until(lambda: receiver.reassembler.stats.corrupt == 1)
            for datagram in fragment(2, "navcam", time.time(), good, 9000):
                robot.send(datagram)
            frame = await waiting
    assert frame.frame_id == 2 and frame.fragments == 3
    stats = receiver.reassembler.stats
    assert stats.corrupt == 1 and stats.malformed == 2 and stats.frames == 2
    assert receiver.stats.lost == 1  # frame 1 never reached the consumer whole


class CountingNav:
    """A NavStack stand-in that counts renders."""

    def __init__(self, inner: SimNavStack) -> None:
        self.inner = inner
        self.renders = 0

    @property
    def active_camera(self) -> str:
        return self.inner.active_camera

    def select_camera(self, name: str) -> None:
        self.inner.select_camera(name)

    def cameras(self) -> tuple[CameraInfo, ...]:
        return self.inner.cameras()

    def get_frame(self, camera: str | None = None) -> CameraFrame:
        self.renders += 1
        return self.inner.get_frame(camera)


def test_senders_sharing_a_navstack_render_once_per_half_interval(nav: SimNavStack) -> None:
    counting = CountingNav(nav)
    nav.select_camera("navcam")
    camera = _shared_camera(counting)  # type: ignore[arg-type]
    assert _shared_camera(counting) is camera  # type: ignore[arg-type]
    first = camera.grab(counting, 10.0, 0.016, time.time)  # type: ignore[arg-type]
    again = camera.grab(counting, 10.01, 0.016, time.time)  # type: ignore[arg-type]
    assert again is first and counting.renders == 1
    later = camera.grab(counting, 10.03, 0.016, time.time)  # type: ignore[arg-type]
    assert later is not first and counting.renders == 2
    counting.select_camera("usercam")  # a switch is never served from the cache
    switched = camera.grab(counting, 10.031, 0.016, time.time)  # type: ignore[arg-type]
    assert switched.camera == "usercam" and counting.renders == 3
    counting.select_camera("navcam")


async def test_two_calls_share_one_navstack(homes: Homes, nav: SimNavStack) -> None:
    counting = CountingNav(nav)
    hub = MemoryHub(seed=3)
    robot_calls: list[Call] = []
    async with (
        MemoryTransport(hub, "robot") as rt,
        MemoryTransport(hub, "u1") as t1,
        MemoryTransport(hub, "u2") as t2,
        RobotEndpoint(rt, homes.robot, homes.contacts) as robot,
        UserEndpoint(t1, homes.user, homes.known) as u1,
        UserEndpoint(t2, homes.user, homes.known) as u2,
    ):
        robot.on_call = robot_calls.append
        calls = [await u1.call(ROBOT), await u2.call(ROBOT)]
        senders = [VideoSender.for_call(c, counting) for c in robot_calls]  # type: ignore[arg-type]
        try:
            for sender in senders:
                sender.start()
            async with (
                VideoReceiver(video_channel(calls[0])) as r1,
                VideoReceiver(video_channel(calls[1])) as r2,
            ):
                a, b = await asyncio.gather(take(r1, 10), take(r2, 10))
        finally:
            for sender in senders:
                await sender.close()
            for call in calls:
                await call.hangup()
    assert len(a) == len(b) == 10
    assert counting.renders <= sum(s.stats.frames for s in senders)


async def test_channels_of_the_wrong_kind_are_refused(homes: Homes, nav: SimNavStack) -> None:
    async with linked(homes) as link:
        with pytest.raises(ValueError, match="BULK"):
            VideoSender(nav, link.robot_call.channel("v-data", lane=Lane.DATA))
        latest = link.robot_call.channel("v-latest", lane=Lane.BULK, latest_only=True)
        with pytest.raises(ValueError, match="latest_only"):
            VideoSender(nav, latest)
        with pytest.raises(ValueError, match="latest_only"):
            VideoReceiver(link.call.channel("v-latest", lane=Lane.BULK, latest_only=True))
        assert video_channel(link.call).lane is Lane.BULK
        assert video_channel(link.call).name == VIDEO


# --------------------------------------------------------------------------- commands


async def test_the_video_command_records_and_shares_frames(
    homes: Homes, nav: SimNavStack, tmp_path: Path
) -> None:
    hub_name = f"video-cli-{uuid.uuid4().hex[:8]}"
    ring_name = f"tb-cli-{uuid.uuid4().hex[:8]}"
    config = AppConfig(
        transport=TransportSettings(kind="memory", memory=MemorySettings(hub=hub_name, node="u"))
    )
    out = tmp_path / "out.mp4"
    senders: list[VideoSender] = []
    shared: list[int] = []

    def read_shared() -> None:
        reader = None
        deadline = time.monotonic() + 10
        while reader is None and time.monotonic() < deadline:
            try:
                reader = FrameRingReader(ring_name)
            except FileNotFoundError:
                time.sleep(0.02)
        assert reader is not None
        with reader:
            shared.extend(f.frame_id for f in reader.frames(timeout=5.0))

    async with (
        MemoryTransport(MemoryHub.named(hub_name), "robot") as transport,
        RobotEndpoint(transport, homes.robot, homes.contacts) as robot,
    ):

        def on_call(call: Call) -> None:
            sender = VideoSender.for_call(call, nav)
            sender.start()
            senders.append(sender)

        robot.on_call = on_call
        log = io.StringIO()
        reading = asyncio.ensure_future(asyncio.to_thread(read_shared))
        code = await video(
            ROBOT,
            home=homes.user_home,
            config=config,
            record=out,
            shm=ring_name,
            duration=1.0,
            stream=log,
        )
        await reading
        for sender in senders:
            await sender.close()
    assert code == 0, log.getvalue()
    summary = log.getvalue().strip().splitlines()[-1]
    assert "fps, " in summary and "kbit/s on average" in summary, summary
    assert summary.startswith(f"{ROBOT}: JPEG, ") and "lost 0 of" in summary, summary
    assert len(shared) > 5 and shared == sorted(shared)  # a local program saw the frames
    capture = cv2.VideoCapture(str(out))
    try:
        size = (capture.get(cv2.CAP_PROP_FRAME_WIDTH), capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        count = capture.get(cv2.CAP_PROP_FRAME_COUNT)
    finally:
        capture.release()
    assert size == (640, 480) and count >= 15  # about a second at 30 fps


async def test_the_video_command_prints_the_codec_and_bit_rate_it_receives(
    homes: Homes, nav: SimNavStack
) -> None:
    hub_name = f"video-rate-{uuid.uuid4().hex[:8]}"
    config = AppConfig(
        transport=TransportSettings(kind="memory", memory=MemorySettings(hub=hub_name, node="u"))
    )
    senders: list[VideoSender] = []
    settings = VideoSettings(codecs=(CODEC_H264, CODEC_JPEG))
    async with (
        MemoryTransport(MemoryHub.named(hub_name), "robot") as transport,
        RobotEndpoint(transport, homes.robot, homes.contacts) as robot,
    ):

        def on_call(call: Call) -> None:
            sender = VideoSender.for_call(call, nav, settings)
            sender.start()
            senders.append(sender)

        robot.on_call = on_call
        log = io.StringIO()
        code = await video(ROBOT, home=homes.user_home, config=config, duration=1.0, stream=log)
        for sender in senders:
            await sender.close()
    assert code == 0, log.getvalue()
    summary = log.getvalue().strip().splitlines()[-1]
    found = re.match(rf"{ROBOT}: H\.264, [\d.]+ fps, (\d+) kbit/s on average, ", summary)
    assert found is not None, summary
    assert int(found[1]) > 0 and senders[0].stats.frames > 5, summary


def test_the_recorder_keeps_real_time_repeating_over_gaps_and_cutting_outages(
    tmp_path: Path,
) -> None:
    out = tmp_path / "gaps.mp4"
    recorder = Recorder(out, 10.0)

    def shade(value: int) -> np.ndarray:
        return np.full((48, 64, 3), value, dtype=np.uint8)

    recorder.write(shade(0), 100.0)
    recorder.write(shade(50), 100.3)  # 0.3 s later: two repeats fill the gap
    assert recorder.written == 4
    recorder.write(shade(60), 100.31)  # faster than 10 fps: no slot of its own
    assert recorder.written == 4
    recorder.write(shade(90), 100.3 + MAX_FILL + 60)  # a long outage: cut, not filled
    assert recorder.written == 5
    recorder.write(shade(120), 100.5 + MAX_FILL + 60)  # and real time again after it
    assert recorder.written == 7 and recorder.seconds == pytest.approx(0.7)
    recorder.close()
    capture = cv2.VideoCapture(str(out))
    try:
        shades = []
        while True:
            ok, image = capture.read()
            if not ok:
                break
            shades.append(int(round(float(image.mean()), -1)))
    finally:
        capture.release()
    assert shades == [0, 0, 0, 50, 90, 90, 120]


def test_video_log_records_a_shared_ring(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ring_name = f"tb-log-{uuid.uuid4().hex[:8]}"
    out = tmp_path / "log.mp4"
    log = io.StringIO()
    result: list[int] = []
    logged: list[int] = []  # frame ids the logger read, in order

    class WatchedReader(FrameRingReader):
        def read_next(self, timeout: float | None = None) -> RingFrame | None:
            frame = super().read_next(timeout)
            if frame is not None:
                logged.append(frame.frame_id)
            return frame

    monkeypatch.setattr(video_cli, "FrameRingReader", WatchedReader)
    thread = threading.Thread(
        target=lambda: result.append(video_log(ring_name, out, fps=10.0, stream=log))
    )
    thread.start()
    with FrameRingWriter(ring_name, 320, 240) as writer:
        start = time.time()
        for i in range(20):
            image = np.full((240, 320, 3), i * 10, dtype=np.uint8)
            writer.write(image, frame_id=i, capture_time=start + i / 10, camera="navcam")
            # Each frame once the logger has it: a ring keeps only the newest, and how
            # fast a loaded machine runs the logger is not what this test is about.
            deadline = time.monotonic() + 10
            while logged[-1:] != [i] and time.monotonic() < deadline:
                time.sleep(0.002)
        assert logged == list(range(20))
    thread.join(timeout=20)
    assert result == [0], log.getvalue()
    capture = cv2.VideoCapture(str(out))
    try:
        count = capture.get(cv2.CAP_PROP_FRAME_COUNT)
    finally:
        capture.release()
    # Frames were written far faster than their capture times: the log keeps their
    # time (20 frames of a 10 fps camera = 2 s), one video frame per camera frame.
    assert count == 20, log.getvalue()
    assert video_log("bad/name", out, stream=log) == 2
    assert video_log(f"tb-none-{uuid.uuid4().hex[:6]}", out, wait=0.1, stream=log) == 1


# --------------------------------------------------------------------------- zenoh flood

FLOOD_PINGS = 20
#: How long a stop's echo is awaited before the stop is sent again (s), and how many of a
#: run's stops may need that (one lost datagram; a starved stop lane loses many).
FLOOD_ECHO_WAIT = 3.0
FLOOD_RESENDS = 1
STOP = "stop"


async def next_echo(
    echoes: asyncio.Queue[ReceivedDatagram], payload: str, timeout: float
) -> ReceivedDatagram | None:
    """The echo of ``payload`` within ``timeout`` (earlier stops' late echoes skipped)."""
    deadline = time.perf_counter() + timeout
    while (left := deadline - time.perf_counter()) > 0:
        try:
            echo = await asyncio.wait_for(echoes.get(), left)
        except TimeoutError:
            return None
        if echo.payload == payload:
            return echo
    return None


class NoiseNav:
    """A camera of incompressible noise: every frame is a ~200 KB JPEG (7 fragments)."""

    active_camera = "navcam"

    def __init__(self) -> None:
        self._rng = np.random.default_rng(1)
        self._images = [self._rng.integers(0, 256, (480, 640, 3), dtype=np.uint8) for _ in range(4)]
        self._n = 0

    def get_frame(self, camera: str | None = None) -> CameraFrame:
        self._n += 1
        return CameraFrame("navcam", self._images[self._n % 4], 0.0, self._n)


async def flood_child(port: int, home: Path) -> None:
    """The robot: floods video (no adaptation, 120 fps) and echoes "stop" on CONTROL."""
    from telebot.channels.transports.zenoh import ZenohTransport
    from telebot.config import ZenohSettings

    settings = ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    flood = VideoSettings(max_fps=120, quality=80, adaptive=False, on_demand=False)
    senders: list[VideoSender] = []
    async with (
        ZenohTransport(settings) as transport,
        RobotEndpoint(transport, Identity.load(home), ContactBook.load(home)) as robot,
    ):

        def on_call(call: Call) -> None:
            stop = call.channel(STOP, lane=Lane.CONTROL)
            stop.set_callback(lambda d: stop.send(d.payload))
            sender = VideoSender.for_call(call, NoiseNav(), flood)  # type: ignore[arg-type]
            sender.start()
            senders.append(sender)

        robot.on_call = on_call
        print("ready", flush=True)
        await asyncio.to_thread(sys.stdin.read)
        for sender in senders:
            await sender.close()
    stats = senders[0].stats if senders else None
    print(json.dumps({"frames": stats.frames if stats else 0}), flush=True)


def start_flood_child(port: int, home: Path) -> subprocess.Popen[str]:
    env = dict(os.environ)
    src = str(Path(__file__).resolve().parents[1] / "src")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [src, env.get("PYTHONPATH")]))
    return subprocess.Popen(
        [sys.executable, __file__, "--flood-child", str(port), str(home)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )


@pytest.mark.zenoh
async def test_a_video_flood_does_not_hold_up_stop_commands(homes: Homes) -> None:
    from telebot.channels.transports.zenoh import ZenohTransport
    from telebot.config import ZenohSettings

    port = free_port()
    child = start_flood_child(port, homes.robot_home)
    assert child.stdin is not None and child.stdout is not None
    try:
        line = await asyncio.wait_for(asyncio.to_thread(child.stdout.readline), 20)
        assert line.strip() == "ready"
        settings = ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
        async with (
            ZenohTransport(settings) as transport,
            UserEndpoint(transport, homes.user, homes.known) as user,
        ):
            call = await user.call(ROBOT, timeout=10.0)
            fragments = 0

            def count(datagram: ReceivedDatagram) -> None:
                nonlocal fragments
                fragments += 1

            video_channel(call).set_callback(count)
            stop = call.channel(STOP, lane=Lane.CONTROL)
            echoes: asyncio.Queue[ReceivedDatagram] = asyncio.Queue()
            stop.set_callback(echoes.put_nowait)
            await wait_until(lambda: fragments >= 200, 10.0)  # the flood is on
            before = fragments
            rtts: list[float] = []
            resent = 0
            # At least FLOOD_PINGS stops, and on until 100 fragments came meanwhile: a
            # count, not a rate (a loaded machine encodes slower). Bounded all the same.
            while len(rtts) < FLOOD_PINGS or fragments - before < 100:
                assert len(rtts) < 20 * FLOOD_PINGS, f"the flood dried up: {fragments - before}"
                i = len(rtts)
                sent = time.perf_counter()
                stop.send(f"stop {i}")
                echo = await next_echo(echoes, f"stop {i}", FLOOD_ECHO_WAIT)
                if echo is None:
                    # The lane is lossy (its zenoh publisher drops rather than blocks
                    # when the link is congested): one stop, or its echo, may be lost;
                    # telebot's stops repeat for that. Sent again, it must come back.
                    resent += 1
                    stop.send(f"stop {i}")
                    echo = await next_echo(echoes, f"stop {i}", FLOOD_ECHO_WAIT)
                    assert echo is not None, f"stop {i} came back neither time"
                rtts.append(time.perf_counter() - sent)
                await asyncio.sleep(0.02)
            during = fragments - before
            await call.hangup()
    finally:
        child.stdin.close()
        with contextlib.suppress(subprocess.TimeoutExpired):
            child.wait(timeout=10)
        if child.poll() is None:
            child.kill()
            child.wait()
        child.stdout.close()
    # Every stop came back while the video kept flowing, at most one of them sent twice.
    assert during >= 100 and len(rtts) >= FLOOD_PINGS
    assert resent <= FLOOD_RESENDS, f"{resent} of {len(rtts)} stops had to be sent again"
    print(
        f"stop round trip under a video flood: p50 {statistics.median(rtts) * 1000:.2f} ms, "
        f"max {max(rtts) * 1000:.2f} ms; {during} video fragments meanwhile; {resent} resent"
    )


def _child_main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--flood-child", nargs=2, metavar=("PORT", "HOME"), required=True)
    args = parser.parse_args()
    asyncio.run(flood_child(int(args.flood_child[0]), Path(args.flood_child[1])))


if __name__ == "__main__":
    _child_main()
