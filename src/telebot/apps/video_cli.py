"""``telebot-user video`` (watch, record, share a robot's camera) and ``telebot-user video-log``
(record frames another telebot-user shares in shared memory).

``video ROBOT [--record out.mp4] [--shm NAME] [--duration S]`` calls the robot, receives its
video, shows the codec, frame rate, bit rate and frame loss on stderr while it runs, records to an MP4 file
(OpenCV's video writer, ``mp4v``) and publishes every frame into the shared-memory ring
``NAME`` for local programs. ``video-log NAME -o out.mp4 [--duration S]`` is such a program.

Recordings keep real time: the video's frame rate is fixed, so when frames come slower
(the link is poor, the robot lowered its rate) the last frame is repeated, up to
:data:`MAX_FILL` seconds of a gap; frames of another size (the robot scaled its picture
down) are resized to the size of the first one.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
import time
from pathlib import Path
from typing import TextIO

import cv2
import numpy as np
import numpy.typing as npt

from telebot.apps.common import EXIT_FAILURE, EXIT_OK, EXIT_USAGE
from telebot.config import AppConfig
from telebot.services.client import connect
from telebot.services.media.wire import CODEC_H264, CODEC_JPEG, CODEC_VP8
from telebot.services.shm import FrameRingReader, FrameRingWriter, validate_ring_name
from telebot.services.video.receiver import VideoFrame, VideoReceiver
from telebot.services.video.stream import video_channel

__all__ = ["MAX_FILL", "Recorder", "video", "video_log"]

PROG = "telebot-user"
#: Longest gap (seconds) a recording fills by repeating the last frame; longer gaps are cut.
MAX_FILL = 5.0
#: Seconds to wait for the first frame before giving up.
FIRST_FRAME_TIMEOUT = 10.0
#: The shared-memory ring holds pictures up to this size (larger ones are shrunk).
RING_SIZE = (1280, 720)
#: How the status line names the codec the frames come in.
CODEC_LABELS = {CODEC_H264: "H.264", CODEC_VP8: "VP8", CODEC_JPEG: "JPEG"}
#: Status lines: every second on a terminal, every STATUS_EVERY seconds otherwise.
STATUS_EVERY = 5.0


class Recorder:
    """Writes frames to a video file at a fixed rate, in real time (see the module doc)."""

    def __init__(self, path: Path, fps: float) -> None:
        if not fps > 0:
            raise ValueError("the recording frame rate must be positive")
        self.path = path
        self.fps = fps
        self.written = 0
        self._writer: cv2.VideoWriter | None = None
        self._size: tuple[int, int] | None = None
        self._start: float | None = None
        self._last: npt.NDArray[np.uint8] | None = None

    @property
    def seconds(self) -> float:
        """Length of the recording so far."""
        return self.written / self.fps

    def write(self, image: npt.NDArray[np.uint8], stamp: float) -> None:
        """Add ``image`` taken at ``stamp`` (seconds, any clock that the stamps share)."""
        if self._writer is None:
            self._open(image)
        if self._start is None:
            self._start = stamp
        assert self._writer is not None and self._size is not None
        if (image.shape[1], image.shape[0]) != self._size:
            image = np.asarray(cv2.resize(image, self._size), dtype=np.uint8)
        slot = round((stamp - self._start) * self.fps)
        gap = slot - self.written
        if gap < 0:
            return  # faster than the recording's rate: this frame has no slot of its own
        if gap > MAX_FILL * self.fps:  # a long outage: cut it rather than fill minutes
            self._start += gap / self.fps  # this frame takes the next slot, and time
            gap = 0  # runs on from it
        if self._last is not None:
            for _ in range(gap):
                self._writer.write(self._last)
                self.written += 1
        self._writer.write(image)
        self.written += 1
        self._last = image

    def _open(self, image: npt.NDArray[np.uint8]) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        size = (int(image.shape[1]), int(image.shape[0]))
        fourcc = cv2.VideoWriter.fourcc(*"mp4v")
        writer = cv2.VideoWriter(str(self.path), fourcc, self.fps, size)
        if not writer.isOpened():
            raise OSError(f"cannot write video to {self.path} (OpenCV's mp4v writer failed)")
        self._writer, self._size = writer, size

    def close(self) -> None:
        """Finish the file; idempotent."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None


class _Status:
    """One status line on stderr: redrawn on a terminal, printed now and then otherwise."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream
        self.tty = stream.isatty()
        self._next = time.monotonic() + (1.0 if self.tty else STATUS_EVERY)

    def show(self, text: str) -> None:
        now = time.monotonic()
        if now < self._next:
            return
        self._next = now + (1.0 if self.tty else STATUS_EVERY)
        if self.tty:
            self.stream.write(f"\r\033[K{text}")
            self.stream.flush()
        else:
            print(text, file=self.stream, flush=True)

    def finish(self, text: str) -> None:
        if self.tty:
            self.stream.write("\r\033[K")
        print(text, file=self.stream, flush=True)


def _describe(frame: VideoFrame) -> str:
    return f"{frame.width}x{frame.height} {frame.camera}"


async def video(
    robot: str,
    *,
    home: Path,
    config: AppConfig,
    record: Path | None = None,
    shm: str | None = None,
    duration: float | None = None,
    record_fps: float = 30.0,
    stream: TextIO = sys.stderr,
) -> int:
    """``telebot-user video``: receive the robot's video; record it and/or share it locally.

    Ends after ``duration`` seconds, when the call ends, or on Ctrl-C / SIGTERM (the
    recording is finished and the shared-memory ring removed in every case). Exit 0 when
    frames came, 1 when none did.
    """
    if shm is not None:
        try:
            validate_ring_name(shm)
        except ValueError as exc:
            print(f"{PROG}: error: {exc}", file=stream)
            return EXIT_USAGE
    recorder = Recorder(record, record_fps) if record is not None else None
    ring: FrameRingWriter | None = None
    status = _Status(stream)
    receiver: VideoReceiver | None = None
    last: VideoFrame | None = None
    started = time.monotonic()
    try:
        async with (
            connect(robot, home=home, config=config, timeout=config.call.connect_timeout) as client,
            VideoReceiver(video_channel(client.call)) as receiver,
        ):
            print(f"video from {robot}: waiting for the first frame ...", file=stream)
            try:
                last = await receiver.next_frame(FIRST_FRAME_TIMEOUT)
            except TimeoutError:
                print(
                    f"{PROG}: error: no video from {robot} within {FIRST_FRAME_TIMEOUT:g} s",
                    file=stream,
                )
                return EXIT_FAILURE
            started = time.monotonic()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(duration):
                    frame: VideoFrame | None = last
                    while frame is not None:
                        last = frame
                        if recorder is not None:
                            recorder.write(frame.image, frame.capture_time)
                        if shm is not None:
                            if ring is None:
                                width = max(RING_SIZE[0], frame.width)
                                height = max(RING_SIZE[1], frame.height)
                                ring = FrameRingWriter(shm, width, height)
                                print(f"sharing frames in shared memory {shm!r}", file=stream)
                            ring.write(
                                frame.image,
                                frame_id=frame.frame_id,
                                capture_time=frame.capture_time,
                                camera=frame.camera,
                            )
                        status.show(_summary(robot, receiver, frame, recorder))
                        frame = await anext(receiver, None)
    finally:
        if recorder is not None:
            recorder.close()
        if ring is not None:
            ring.close()
    if receiver is not None and last is not None:
        status.finish(_summary(robot, receiver, last, recorder, elapsed=time.monotonic() - started))
    return EXIT_OK if last is not None else EXIT_FAILURE


def _summary(
    robot: str,
    receiver: VideoReceiver,
    frame: VideoFrame,
    recorder: Recorder | None,
    *,
    elapsed: float | None = None,
) -> str:
    stats = receiver.stats
    if elapsed:
        bits = 8 * stats.received_bytes / elapsed
        rate = f"{stats.delivered / elapsed:.1f} fps, {bits / 1000:.0f} kbit/s on average"
    else:
        rate = f"{receiver.fps:.1f} fps, {receiver.bitrate / 1000:.0f} kbit/s"
    codec = CODEC_LABELS.get(frame.codec, f"codec {frame.codec}")
    text = (
        f"{robot}: {codec}, {rate}, {_describe(frame)}, {stats.delivered} frames, "
        f"lost {stats.lost} of {stats.expected} ({stats.loss:.1%})"
    )
    if recorder is not None:
        text += f", recorded {recorder.seconds:.1f} s to {recorder.path}"
    return text


def video_log(
    name: str,
    output: Path,
    *,
    duration: float | None = None,
    fps: float = 30.0,
    wait: float = 10.0,
    stream: TextIO = sys.stderr,
) -> int:
    """``telebot-user video-log``: record the frames shared in memory as ``name`` to ``output``.

    Waits up to ``wait`` seconds for the ring to appear; ends after ``duration`` seconds,
    when the writer closes the ring, or on Ctrl-C. Exit 0 when frames were recorded.
    """
    try:
        validate_ring_name(name)
    except ValueError as exc:
        print(f"{PROG}: error: {exc}", file=stream)
        return EXIT_USAGE
    reader = _attach(name, wait)
    if reader is None:
        print(f"{PROG}: error: no shared-memory video {name!r} within {wait:g} s", file=stream)
        return EXIT_FAILURE
    recorder = Recorder(output, fps)
    status = _Status(stream)
    frames = 0
    started = time.monotonic()
    end = None if duration is None else started + duration
    try:
        with reader:
            while end is None or time.monotonic() < end:
                left = None if end is None else max(0.0, end - time.monotonic())
                frame = reader.read_next(timeout=min(left, 1.0) if left is not None else 1.0)
                if frame is None:
                    if reader.writer_closed:
                        break
                    continue
                stamp = frame.capture_time or time.time()
                recorder.write(frame.image, stamp)
                frames += 1
                status.show(
                    f"{name}: {frames} frames, skipped {reader.skipped}, "
                    f"recorded {recorder.seconds:.1f} s"
                )
    except KeyboardInterrupt:
        pass  # finish the file below: Ctrl-C is how a log is usually stopped
    finally:
        recorder.close()
    elapsed = time.monotonic() - started
    status.finish(
        f"{name}: {frames} frames in {elapsed:.1f} s, skipped {reader.skipped}; "
        f"recorded {recorder.seconds:.1f} s to {output}"
    )
    return EXIT_OK if frames else EXIT_FAILURE


def _attach(name: str, wait: float) -> FrameRingReader | None:
    deadline = time.monotonic() + wait
    while True:
        try:
            return FrameRingReader(name)
        except FileNotFoundError:
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.1)
