"""The robot's side of video: :class:`VideoSender` grabs pictures, encodes them and paces the
datagrams, one per call (see the service's overview in :mod:`telebot.services.video`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import TYPE_CHECKING, Any, Self, cast

from telebot.channels.channel import Channel, ReceivedDatagram
from telebot.channels.transports.base import Lane
from telebot.errors import CallEnded, ProtocolError
from telebot.robot.nav import CameraFrame, NavStack
from telebot.services.codecs import ThreadedEncoder, VideoEncoder, stamp_number
from telebot.services.media.wire import (
    KeyframePacer,
    choose_codec,
)
from telebot.services.video.stream import (
    _RateMeter,
    _until_call_ends,
    video_channel,
)
from telebot.services.video.wire import (
    CODEC_JPEG,
    FRAGMENT_HEADER,
    MAX_CAMERA_NAME,
    Report,
    VideoRateController,
    VideoSettings,
    encode_jpeg,
    fragment,
    parse_report,
)

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

    from telebot.channels.call import Call
    from telebot.channels.proto.session import CallStats

__all__ = ["VideoSender", "VideoSenderStats", "video_channel"]

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- robot side


@dataclass(slots=True)
class _Shot:
    """One picture of the camera and what was made of it (shared by the senders)."""

    camera: str
    image: npt.NDArray[np.uint8]
    taken_at: float  # loop time
    capture_time: float  # wall clock
    resized: dict[tuple[int, int], npt.NDArray[np.uint8]] = field(default_factory=dict)
    encoded: dict[tuple[int, int, int], bytes] = field(default_factory=dict)


class _SharedCamera:
    """The newest picture of one NavStack, so that several calls render it once."""

    __slots__ = ("shot",)

    def __init__(self) -> None:
        self.shot: _Shot | None = None

    def grab(self, nav: NavStack, now: float, max_age: float, clock: Callable[[], float]) -> _Shot:
        shot = self.shot
        if shot is not None and shot.camera == nav.active_camera and now - shot.taken_at <= max_age:
            return shot
        frame: CameraFrame = nav.get_frame()
        shot = _Shot(frame.camera, frame.image, now, clock())
        self.shot = shot
        return shot


# Keyed weakly by the NavStack: the cache goes with it. Values must not refer to the nav.
_CAMERAS: weakref.WeakKeyDictionary[Any, _SharedCamera] = weakref.WeakKeyDictionary()


def _shared_camera(nav: NavStack) -> _SharedCamera:
    try:
        camera = _CAMERAS.get(nav)
        if camera is None:
            camera = _CAMERAS[nav] = _SharedCamera()
        return camera
    except TypeError:  # not weakly referenceable: this sender renders on its own
        return _SharedCamera()


@dataclass(slots=True)
class VideoSenderStats:
    """Counters of one sender."""

    frames: int = 0
    fragments: int = 0
    #: Datagram bytes sent (headers included).
    bytes: int = 0
    #: Frames encoded a second time because they needed more fragments than the loss allows.
    reencoded: int = 0
    #: Receiver reports taken.
    reports: int = 0
    #: Datagrams from the receiver that were not reports (dropped).
    rejected: int = 0
    #: Frames not sent because grabbing, encoding or sending failed (logged).
    errors: int = 0
    #: H.264 / VP8 keyframes sent; frame times skipped because the receiver takes no codec
    #: the sender has.
    keyframes: int = 0
    no_codec: int = 0
    #: Frame times skipped because the link held a backlog of earlier frames.
    held: int = 0


class VideoSender:
    """Streams the NavStack's active camera on one call's video channel (the robot's side).

    ``channel`` must be on the BULK lane (:func:`video_channel`), so video can never
    delay a stop. ``call_stats`` (the call's :attr:`~telebot.channels.call.Call.stats`)
    gives the heartbeat loss and round trip, used while no receiver report is at hand.
    ``clock`` is the wall clock stamped on frames as their capture time.

    Lifecycle: :meth:`start` creates its task; :meth:`close` (or :meth:`stop` from code
    that cannot await) ends it; it also ends by itself when the call ends. While nobody
    watches (no report for ``settings.idle_after`` s, when ``settings.on_demand``) it
    neither renders nor sends.
    """

    def __init__(
        self,
        nav: NavStack,
        channel: Channel,
        settings: VideoSettings | None = None,
        *,
        call_stats: CallStats | None = None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        if channel.lane is not Lane.BULK:
            raise ValueError(f"video must ride the BULK lane, not {channel.lane.value}")
        if channel.latest_only:
            raise ValueError("a video channel must keep every datagram (not latest_only)")
        self.nav = nav
        self.channel = channel
        self.settings = settings if settings is not None else VideoSettings()
        self._call_stats = call_stats
        self._clock = clock
        self._loop = asyncio.get_running_loop()
        # Budget with the longest camera name, so a frame fits whatever the camera.
        data = self.settings.max_payload - FRAGMENT_HEADER.size - MAX_CAMERA_NAME
        self.controller = VideoRateController(
            self.settings, data_per_fragment=data, now=self._loop.time()
        )
        self.stats = VideoSenderStats()
        self._camera = _shared_camera(nav)
        #: Keyframes of H.264 / VP8: periodic and on the receiver's request (paced).
        self.pacer = KeyframePacer(interval=self.settings.keyframe_interval)
        #: The codecs the receiver's last report listed (empty: JPEG only).
        self.accepted: tuple[int, ...] = ()
        self._encoder: ThreadedEncoder | None = None
        self._frame_id = 0
        self._seq = 0
        self._size = (self.settings.width, self.settings.height)
        self._meter = _RateMeter()
        self._wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._watch: asyncio.Task[None] | None = None
        self._ended = False
        self._closed = False
        #: Called with each receiver report the sender takes (reordered ones are not): the
        #: robot's safety supervisor learns from it whether its driver still gets pictures.
        self.on_report: Callable[[Report], None] | None = None
        channel.set_callback(self._on_datagram)

    @classmethod
    def for_call(
        cls, call: Call, nav: NavStack, settings: VideoSettings | None = None
    ) -> VideoSender:
        """A sender on ``call``'s video channel, fed with the call's link statistics."""
        return cls(nav, video_channel(call), settings, call_stats=call.stats)

    # -- telemetry

    @property
    def fps(self) -> float:
        """The frame rate the sender aims at now (frames per second)."""
        return self.controller.fps

    @property
    def measured_fps(self) -> float:
        """Frames actually sent over the last second."""
        return self._meter.rate(self._loop.time())

    @property
    def width(self) -> int:
        """Width of the frames sent now (pixels)."""
        return self._size[0]

    @property
    def height(self) -> int:
        """Height of the frames sent now (pixels)."""
        return self._size[1]

    @property
    def quality(self) -> int:
        """JPEG quality used now (1..100)."""
        return self.controller.quality

    @property
    def codec(self) -> int | None:
        """The codec used for the receiver now (None: they share none); before any report,
        while it probes (the user's camera), its own first choice."""
        if self.settings.probe > 0 and self.controller.reports == 0:
            return self.settings.codecs[0]
        return choose_codec(self.accepted, self.settings.codecs)

    @property
    def watched(self) -> bool:
        """Whether a receiver is asking for video (reports are coming)."""
        return self.controller.watching(self._loop.time())

    @property
    def running(self) -> bool:
        """True from :meth:`start` until the sender stops."""
        return self._task is not None and not self._task.done()

    # -- lifecycle

    def start(self) -> None:
        """Start streaming (a task on the running loop); idempotent."""
        if self._closed:
            raise RuntimeError("this video sender is closed")
        if self._task is None:
            self._task = self._loop.create_task(self._run(), name="video-sender")
            self._watch = self._loop.create_task(
                _until_call_ends(self.channel), name="video-sender-end"
            )
            self._watch.add_done_callback(self._on_call_end)

    def stop(self) -> None:
        """Stop streaming without waiting (for callbacks); idempotent."""
        if self._closed:
            return
        self._closed = True
        self.channel.set_callback(None)
        for task in (self._task, self._watch):
            if task is not None:
                task.cancel()
        if self._encoder is not None:
            self._encoder.close()

    async def close(self) -> None:
        """Stop streaming and wait until the sender's tasks are gone; idempotent."""
        self.stop()
        for task in (self._task, self._watch):
            if task is not None:
                with contextlib.suppress(asyncio.CancelledError):
                    await task

    async def __aenter__(self) -> Self:
        self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    # -- internals

    def _on_call_end(self, task: asyncio.Task[None]) -> None:
        if not task.cancelled():
            self._ended = True
            self._wake.set()

    def _on_datagram(self, datagram: ReceivedDatagram) -> None:
        try:
            report = parse_report(datagram.payload)
        except ProtocolError:
            self.stats.rejected += 1
            return
        now = self._loop.time()
        idle = not self.controller.watching(now)
        taken = self.controller.reports
        self.controller.on_report(report, now)
        if self.on_report is not None and self.controller.reports != taken:
            try:
                self.on_report(report)
            except Exception:  # a listener's fault must not stop the video
                log.exception("video report listener failed")
        self.stats.reports += 1
        self.accepted = report.codecs
        if report.keyframe:
            rtt = self._call_stats.rtt if self._call_stats is not None else None
            self.pacer.request(now, rtt)
        if idle:
            self._wake.set()

    async def _run(self) -> None:
        loop = self._loop
        controller = self.controller
        due = loop.time()
        while not self._ended:
            now = loop.time()
            stats = self._call_stats
            if stats is not None:
                controller.on_link(loss=stats.loss, rtt=stats.rtt, now=now)
            if not controller.watching(now):
                self._wake.clear()
                await self._wake.wait()
                due = loop.time()
                continue
            if now < due:
                await asyncio.sleep(due - now)
                continue
            try:
                codec = self.codec
                if controller.held_up(now):
                    self.stats.held += 1
                elif codec is None:
                    self.stats.no_codec += 1
                elif codec == CODEC_JPEG:
                    self._send_frame(now)
                else:
                    await self._send_coded(now, codec)
            except CallEnded:
                return
            except Exception:  # a camera or encoder hiccup costs one frame, not the stream
                self.stats.errors += 1
                if self.stats.errors <= 3 or self.stats.errors % 100 == 0:
                    log.exception("video frame not sent (%d so far)", self.stats.errors)
            interval = controller.frame_interval
            due += interval
            if due < loop.time() - interval:  # fell behind: do not catch up in a burst
                due = loop.time()
            # Always yield after a frame, even when late: heartbeats and a stop come first.
            await asyncio.sleep(max(0.0, due - loop.time()))

    def _send_frame(self, now: float) -> None:
        controller = self.controller
        shot = self._camera.grab(self.nav, now, 0.5 * controller.frame_interval, self._clock)
        image = self._scaled(shot)
        if self.settings.stamp:  # a stamped picture is this sender's own: no shared cache
            image = stamp_number(image, self._frame_id + 1)
            jpeg = encode_jpeg(image, controller.quality)
        else:
            jpeg = self._encoded(shot, image, controller.quality)
        if controller.on_encoded(len(jpeg), now):
            self.stats.reencoded += 1
            image = self._scaled(shot)
            if self.settings.stamp:
                image = stamp_number(image, self._frame_id + 1)
                jpeg = encode_jpeg(image, controller.quality)
            else:
                jpeg = self._encoded(shot, image, controller.quality)
        self._frame_id += 1
        datagrams = fragment(
            self._frame_id,
            shot.camera,
            shot.capture_time,
            jpeg,
            self.settings.max_payload,
            seq=self._seq,
            interval=controller.frame_interval,
        )
        for datagram in datagrams:
            self.channel.send(datagram)
            self._seq += 1
            self.stats.fragments += 1
            self.stats.bytes += len(datagram)
        self.stats.frames += 1
        self.controller.frame_sent(now, (self._seq - 1) % 2**32)
        self._meter.tick(now)

    async def _send_coded(self, now: float, codec: int) -> None:
        """One H.264 / VP8 frame, encoded on the encoder's thread (off the event loop)."""
        controller = self.controller
        shot = self._camera.grab(self.nav, now, 0.5 * controller.frame_interval, self._clock)
        image = self._scaled(shot)
        if self.settings.stamp:
            image = stamp_number(image, self._frame_id + 1)
        encoder = self._encoder
        if encoder is None or encoder.encoder.codec != codec:
            if encoder is not None:
                encoder.close()
            encoder = self._encoder = ThreadedEncoder(
                VideoEncoder(
                    codec,
                    fps=self.settings.max_fps,
                    keyframe_interval=self.settings.keyframe_interval,
                )
            )
        frame = await encoder.encode(
            image, keyframe=self.pacer.next_is_key(now), bitrate=self.bitrate, now=now
        )
        self.pacer.sent(frame.keyframe, now)
        if self._closed or self._ended:
            return
        self._frame_id += 1
        datagrams = fragment(
            self._frame_id,
            shot.camera,
            shot.capture_time,
            frame.data,
            self.settings.max_payload,
            seq=self._seq,
            interval=controller.frame_interval,
            codec=codec,
            keyframe=frame.keyframe,
        )
        for datagram in datagrams:
            self.channel.send(datagram)
            self._seq += 1
            self.stats.fragments += 1
            self.stats.bytes += len(datagram)
        self.stats.frames += 1
        self.stats.keyframes += frame.keyframe
        controller.frame_sent(now, (self._seq - 1) % 2**32)
        self._meter.tick(now)

    @property
    def bitrate(self) -> int:
        """Target bit rate of H.264 / VP8 now (bits/s): the controller's rate and fragment
        budget, within the settings' bounds."""
        settings, controller = self.settings, self.controller
        frag_cap = controller.max_fragments * controller.data_per_fragment * controller.fps * 8
        target = settings.max_bitrate if controller.rate is None else controller.rate * 8
        return int(max(settings.min_bitrate, min(settings.max_bitrate, target, frag_cap)))

    def _scaled(self, shot: _Shot) -> npt.NDArray[np.uint8]:
        import cv2

        scale = self.controller.scale
        # Even sizes: video writers downstream (MPEG-4, H.264) need them.
        width = max(2, round(self.settings.width * scale / 2) * 2)
        height = max(2, round(self.settings.height * scale / 2) * 2)
        self._size = (width, height)
        if shot.image.shape[1] == width and shot.image.shape[0] == height:
            return shot.image
        image = shot.resized.get((width, height))
        if image is None:
            shrinking = width < shot.image.shape[1]
            interpolation = cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR
            resized = cv2.resize(shot.image, (width, height), interpolation=interpolation)
            image = shot.resized[(width, height)] = cast("npt.NDArray[np.uint8]", resized)
        return image

    def _encoded(self, shot: _Shot, image: npt.NDArray[np.uint8], quality: int) -> bytes:
        key = (image.shape[1], image.shape[0], quality)
        jpeg = shot.encoded.get(key)
        if jpeg is None:
            jpeg = shot.encoded[key] = encode_jpeg(image, quality)
        return jpeg


# --------------------------------------------------------------------------- user side
