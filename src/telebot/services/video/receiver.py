"""The user's side of video: :class:`VideoReceiver`, :func:`frames`, and :class:`VideoFeed` with
its call service :class:`VideoFeedService` (see the overview in :mod:`telebot.services.video`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from types import TracebackType
from typing import TYPE_CHECKING, Any, Self

from telebot.channels.channel import Channel, ReceivedDatagram
from telebot.errors import CallEnded, ProtocolError, TelebotError
from telebot.services.codecs import VideoDecoder
from telebot.services.media.wire import (
    KeyframeGate,
    KeyframeRequests,
)
from telebot.services.video.stream import (
    DECODED_CODECS,
    REPORT_INTERVAL,
    _RateMeter,
    _until_call_ends,
    video_channel,
)
from telebot.services.video.wire import (
    CODEC_JPEG,
    MAX_PIXELS,
    VIDEO_CODECS,
    CompleteFrame,
    Reassembler,
    ReassemblyStats,
    serial_diff,
)

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

    from telebot.channels.call import Call

__all__ = [
    "VideoFeed",
    "VideoFeedService",
    "VideoFrame",
    "VideoReceiver",
    "VideoReceiverStats",
    "frames",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True, eq=False)
class VideoFrame:
    """A decoded video frame."""

    #: BGR uint8 picture, shape (height, width, 3).
    image: npt.NDArray[np.uint8]
    camera: str
    #: The sender's frame number (consecutive: a gap is a frame that did not arrive).
    frame_id: int
    #: Robot's wall clock (Unix seconds) when it took the picture from the camera.
    capture_time: float
    #: This side's wall clock when the frame was decoded.
    received_time: float
    #: Datagrams the frame came in, and the encoded frame's size in bytes.
    fragments: int
    jpeg_bytes: int
    #: The codec it came in (:data:`~telebot.services.video.wire.CODEC_JPEG`, H.264, VP8).
    codec: int = CODEC_JPEG

    @property
    def width(self) -> int:
        """Picture width in pixels."""
        return int(self.image.shape[1])

    @property
    def height(self) -> int:
        """Picture height in pixels."""
        return int(self.image.shape[0])

    @property
    def latency(self) -> float:
        """``received_time − capture_time``: meaningful when both clocks agree (NTP)."""
        return self.received_time - self.capture_time


@dataclass(slots=True)
class VideoReceiverStats:
    """Counters of one receiver (reassembly counters are in :attr:`reassembly`)."""

    reassembly: ReassemblyStats
    #: Frames decoded and handed to the consumer.
    delivered: int = 0
    #: Complete frames replaced by a newer one before the consumer took them.
    skipped: int = 0
    reports: int = 0
    #: Datagrams that waited on the channel from before this receiver started (dropped).
    stale: int = 0
    #: Frame ids from the first to the newest frame completed (what the sender sent).
    expected: int = 0
    #: Encoded bytes of the whole frames received (what the link carried to the decoder).
    received_bytes: int = 0
    #: The codec of the newest whole frame (None before the first).
    codec: int | None = None

    @property
    def lost(self) -> int:
        """Frames of the stream that never reached the consumer whole: lost, late or corrupt."""
        return max(0, self.expected - self.reassembly.frames) + self.reassembly.corrupt

    @property
    def loss(self) -> float:
        """:attr:`lost` as a share of :attr:`expected` (0 before any frame)."""
        return self.lost / self.expected if self.expected else 0.0


class VideoReceiver:
    """Receives, rebuilds and decodes the robot's video (the user's side).

    Iterate with ``async for frame in receiver`` (inside ``async with``, or between
    :meth:`start` and :meth:`close`); iteration ends when the call ends. Latest frame
    wins: a consumer slower than the stream gets the newest frame and never an older
    one after it (the skipped ones are counted). JPEG frames are decoded on the event
    loop when the consumer takes them (~0.4 ms for 640 × 480); H.264 and VP8 frames as
    they arrive (a delta frame needs the one before it), with PyAV. ``codecs`` are the
    codecs asked for, best first (JPEG only: ``(CODEC_JPEG,)``). After a lost or corrupt
    frame it waits for a keyframe and asks for one.
    """

    def __init__(
        self,
        channel: Channel | VideoFeed,
        *,
        report_interval: float = REPORT_INTERVAL,
        clock: Callable[[], float] = time.time,
        max_pixels: int = MAX_PIXELS,
        codecs: tuple[int, ...] = DECODED_CODECS,
    ) -> None:
        if report_interval <= 0:
            raise ValueError("report_interval must be positive")
        self.codecs = codecs
        #: On a feed (``robot.video()``) frames keep coming across reconnects; the feed's
        #: call service then reports to the robot, and iteration ends with the client.
        self.feed = channel if isinstance(channel, VideoFeed) else None
        self._unsubscribe: Callable[[], None] | None = None
        #: The call's video channel (None on a feed).
        self.channel: Channel | None = None
        if not isinstance(channel, VideoFeed):
            if channel.latest_only:
                raise ValueError("a video channel must keep every datagram (not latest_only)")
            self.channel = channel
        self.report_interval = report_interval
        self.max_pixels = max_pixels
        self._clock = clock
        self._loop = asyncio.get_running_loop()
        self.reassembler = Reassembler(codec=VIDEO_CODECS)
        self.stats = VideoReceiverStats(self.reassembler.stats)
        self.gate = KeyframeGate()
        self.requests = KeyframeRequests()
        self.decoder = VideoDecoder(max_pixels=max_pixels)
        self._first_id: int | None = None
        self._pending: CompleteFrame | VideoFrame | None = None
        self._ready = asyncio.Event()
        self._meter = _RateMeter()
        self._bytes = _RateMeter()
        self._timer: asyncio.TimerHandle | None = None
        self._watch: asyncio.Task[None] | None = None
        self._ended = False
        self._started = False
        self._started_at = 0.0
        self._closed = False

    @property
    def fps(self) -> float:
        """Frames handed to the consumer over the last second."""
        return self._meter.rate(self._loop.time())

    @property
    def bitrate(self) -> float:
        """Bits per second of the whole frames received over the last second."""
        return 8 * self._bytes.rate(self._loop.time())

    @property
    def ended(self) -> bool:
        """True once the call ended or the receiver was closed."""
        return self._ended or self._closed

    def start(self) -> None:
        """Take the channel and ask the robot for video (first report now); idempotent."""
        if self._closed:
            raise RuntimeError("this video receiver is closed")
        if self._started:
            return
        self._started = True
        self._started_at = self._loop.time()
        if self.feed is not None:
            if self.feed.ended:
                self._ended = True
            self._unsubscribe = self.feed.subscribe(
                self._on_complete, on_end=self._on_feed_end, codecs=self.codecs
            )
            return
        assert self.channel is not None
        self.channel.set_callback(self._on_datagram)
        self._watch = self._loop.create_task(
            _until_call_ends(self.channel), name="video-receiver-end"
        )
        self._watch.add_done_callback(self._on_call_end)
        self._on_timer()

    async def close(self) -> None:
        """Stop receiving (the robot stops sending once reports stop); idempotent."""
        if self._closed:
            return
        self._closed = True
        self._ready.set()
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        elif self._started and self.channel is not None:
            self.channel.set_callback(None)
            if not self._ended:  # tell the robot to stop now rather than after its timeout
                bye = self.reassembler.report(
                    int(self._loop.time() * 1000), bye=True, codecs=self.codecs
                )
                with contextlib.suppress(TelebotError):
                    self.channel.send(bye.encode())
        if self._watch is not None:
            self._watch.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watch

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

    def __aiter__(self) -> VideoReceiver:
        return self

    async def __anext__(self) -> VideoFrame:
        if not self._started:
            self.start()
        while True:
            pending = self._pending
            if pending is not None:
                self._pending = None
                if isinstance(pending, VideoFrame):
                    return pending
                frame = self._decode(pending)
                if frame is not None:
                    return frame
                continue
            if self.ended:
                raise StopAsyncIteration
            self._ready.clear()
            await self._ready.wait()

    async def next_frame(self, timeout: float | None = None) -> VideoFrame:
        """The next frame; TimeoutError after ``timeout`` s, CallEnded once the call ended."""
        async with asyncio.timeout(timeout):
            try:
                return await self.__anext__()
            except StopAsyncIteration:
                raise CallEnded("the call ended: no more video") from None

    # -- internals

    def _decode(self, complete: CompleteFrame) -> VideoFrame | None:
        try:
            image = self.decoder.decode(complete.data, complete.codec)
        except ProtocolError as exc:
            self.reassembler.corrupt()
            self.gate.corrupt()
            self._ask_keyframe()
            log.debug("video frame %d dropped: %s", complete.frame_id, exc)
            return None
        self.stats.delivered += 1
        self._meter.tick(self._loop.time())
        return VideoFrame(
            image=image,
            camera=complete.camera,
            frame_id=complete.frame_id,
            capture_time=complete.capture_time,
            received_time=self._clock(),
            fragments=complete.fragments,
            jpeg_bytes=len(complete.data),
            codec=complete.codec,
        )

    def _ask_keyframe(self) -> None:
        """Ask the sender for a keyframe now, unless asked within max(RTT, 300 ms)."""
        if not self.requests.due(self.gate.need_keyframe, self._loop.time()):
            return
        if self.feed is not None:
            self.feed.request_keyframe()
        elif self.channel is not None and not self.ended:
            report = self.reassembler.report(
                int(self._loop.time() * 1000), keyframe=True, codecs=self.codecs
            )
            with contextlib.suppress(TelebotError):
                self.channel.send(report.encode())

    def _on_datagram(self, datagram: ReceivedDatagram) -> None:
        if self._closed:
            return
        if datagram.received_at < self._started_at:
            # Queued on the channel while nobody was receiving: stale by now.
            self.stats.stale += 1
            return
        complete = self.reassembler.on_datagram(datagram.payload, self._loop.time())
        if complete is not None:
            self._on_complete(complete)

    def _on_feed_end(self) -> None:
        self._ended = True
        self._ready.set()

    def _on_complete(self, complete: CompleteFrame) -> None:
        if self._closed:
            return
        if self._first_id is None:
            self._first_id = complete.frame_id
        self.stats.received_bytes += len(complete.data)
        self.stats.codec = complete.codec
        self._bytes.tick(self._loop.time(), len(complete.data))
        self.stats.expected = serial_diff(complete.frame_id, self._first_id) + 1
        if not self.gate.admit(complete.frame_id, complete.codec, complete.keyframe):
            self._ask_keyframe()  # a delta frame after a loss: wait for a keyframe
            return
        pending: CompleteFrame | VideoFrame = complete
        if complete.codec != CODEC_JPEG:
            # A delta codec's decoder must see every frame, so decode now, not when taken.
            frame = self._decode(complete)
            if frame is None:
                return
            pending = frame
        if self._pending is not None:
            self.stats.skipped += 1
        self._pending = pending
        self._ready.set()

    def _on_call_end(self, task: asyncio.Task[None]) -> None:
        if not task.cancelled():
            self._ended = True
            self._ready.set()

    def _on_timer(self) -> None:
        self._timer = None
        if self.ended or self.channel is None:
            return
        now = self._loop.time()
        self.reassembler.poll(now)
        report = self.reassembler.report(
            int(now * 1000), keyframe=self.gate.need_keyframe, codecs=self.codecs
        )
        try:
            self.channel.send(report.encode())
            self.stats.reports += 1
        except CallEnded:
            self._ended = True
            self._ready.set()
            return
        except TelebotError as exc:  # a transport hiccup: the next report will do
            log.debug("video report not sent: %s", exc)
        self._timer = self._loop.call_later(self.report_interval, self._on_timer)


FrameCallback = Callable[[CompleteFrame], None]


class VideoFeed:
    """The user's video across calls: whole frames (JPEG bytes) for each subscriber.

    The feed lives as long as its client; the current call's :class:`VideoFeedService`
    feeds it. The robot is asked for video (receiver reports) only while someone is
    subscribed. :meth:`end` (the client's end) tells ``on_end`` subscribers no more comes.
    """

    def __init__(self, *, report_interval: float = REPORT_INTERVAL) -> None:
        if report_interval <= 0:
            raise ValueError("report_interval must be positive")
        self.report_interval = report_interval
        self._subscribers: list[FrameCallback] = []
        self._codecs: dict[int, tuple[int, ...]] = {}
        self._end_callbacks: list[Callable[[], None]] = []
        self._service: VideoFeedService | None = None
        self.ended = False
        #: Whole frames handed to subscribers, over every call.
        self.frames = 0

    @property
    def wanted(self) -> bool:
        """Whether someone is subscribed (the robot is asked for video)."""
        return bool(self._subscribers) and not self.ended

    @property
    def codecs(self) -> tuple[int, ...]:
        """The codecs asked for: those every subscriber decodes, in the first one's order."""
        lists = list(self._codecs.values())
        if not lists:
            return (CODEC_JPEG,)
        common = tuple(c for c in lists[0] if all(c in other for other in lists[1:]))
        return common or lists[0]

    def request_keyframe(self) -> None:
        """A subscriber could not decode a frame: ask the robot for a keyframe (paced)."""
        if self._service is not None:
            self._service.request_keyframe()

    def subscribe(
        self,
        on_frame: FrameCallback,
        *,
        on_end: Callable[[], None] | None = None,
        codecs: tuple[int, ...] = (CODEC_JPEG,),
    ) -> Callable[[], None]:
        """Hand every whole frame to ``on_frame`` until the returned function is called.

        ``codecs``: what ``on_frame`` can decode, best first (the robot is asked for a
        codec every subscriber takes). Frames of H.264 / VP8 come in decodable order:
        after a loss the deltas up to the next keyframe are left out.
        """
        key = id(on_frame)
        self._codecs[key] = tuple(codecs)
        self._subscribers.append(on_frame)
        if on_end is not None:
            self._end_callbacks.append(on_end)
        if self._service is not None:
            self._service.update()

        def unsubscribe() -> None:
            self._codecs.pop(key, None)
            with contextlib.suppress(ValueError):
                self._subscribers.remove(on_frame)
            if on_end is not None:
                with contextlib.suppress(ValueError):
                    self._end_callbacks.remove(on_end)
            if self._service is not None:
                self._service.update()

        return unsubscribe

    def end(self) -> None:
        """No more calls: tell the subscribers (their iteration ends); idempotent."""
        if self.ended:
            return
        self.ended = True
        for callback in list(self._end_callbacks):
            try:
                callback()
            except Exception:
                log.exception("video feed end callback failed")

    def _deliver(self, complete: CompleteFrame) -> None:
        self.frames += 1
        for callback in list(self._subscribers):
            try:
                callback(complete)
            except Exception:  # one bad subscriber must not starve the others
                log.exception("video subscriber failed")


class VideoFeedService:
    """The ``video`` call service of a user client: one call's part of a :class:`VideoFeed`.

    While the feed is wanted it takes the call's video channel, reassembles frames and
    sends a receiver report at once and then every ``report_interval`` (so the robot
    keeps sending); when nobody is subscribed any more, or on :meth:`close` with the call
    still up, it sends a *bye*. With ``wait_for_media`` (the robot, on ``video/user``) the
    reports, keyframe requests and bye begin only once a fragment came: a call that sends
    no video gets none (docs/protocol.md §25).
    """

    def __init__(
        self,
        feed: VideoFeed,
        call: Call,
        *,
        channel: Channel | None = None,
        wait_for_media: bool = False,
    ) -> None:
        self.feed = feed
        self.call = call
        #: The call's ``video`` channel, or another stream's (the robot's ``video/user``).
        self.channel = channel if channel is not None else video_channel(call)
        self.reassembler = Reassembler(codec=VIDEO_CODECS)
        self.gate = KeyframeGate()
        self.requests = KeyframeRequests()
        self._loop = asyncio.get_running_loop()
        self._timer: asyncio.TimerHandle | None = None
        self._started_at = 0.0
        self._running = False
        self._closed = False
        self.wait_for_media = wait_for_media
        #: Whether reports are going (while running, once media came if it waits for it).
        self.reporting = False
        #: The loop time of the newest whole frame handed to the feed (None: none yet).
        self.last_frame_at: float | None = None
        feed._service = self
        self.update()

    @property
    def running(self) -> bool:
        """True while this call asks the robot for video."""
        return self._running

    def update(self) -> None:
        """Start or stop asking for video as the feed is wanted or not."""
        if self._closed:
            return
        if self.feed.wanted and not self._running:
            self._running = True
            self._started_at = self._loop.time()
            self.channel.set_callback(self._on_datagram)
            if not self.wait_for_media or self.reassembler.stats.fragments:
                self._start_reports()
        elif not self.feed.wanted and self._running:
            self._halt(bye=True)

    def tick(self, now: float) -> None:
        """Nothing: reports have their own timer (a call without ticks still gets video)."""

    def close(self) -> None:
        """The call ended or the client closes; a *bye* if the call is still up."""
        if self._closed:
            return
        if self._running:
            self._halt(bye=self.call.active)
        self._closed = True
        if self.feed._service is self:
            self.feed._service = None

    def request_keyframe(self) -> None:
        """Wait for a keyframe and ask for one now (at most once per max(RTT, 300 ms))."""
        self.gate.corrupt()
        self._ask_keyframe()

    def _start_reports(self) -> None:
        self.reporting = True
        self._on_timer()

    def _ask_keyframe(self) -> None:
        now = self._loop.time()
        if not self.reporting or not self.requests.due(self.gate.need_keyframe, now):
            return
        report = self.reassembler.report(int(now * 1000), keyframe=True, codecs=self.feed.codecs)
        with contextlib.suppress(TelebotError):
            self.channel.send(report.encode())

    def _halt(self, *, bye: bool) -> None:
        self._running = False
        reporting, self.reporting = self.reporting, False
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self.channel.set_callback(None)
        if bye and reporting:
            report = self.reassembler.report(
                int(self._loop.time() * 1000), bye=True, codecs=self.feed.codecs
            )
            with contextlib.suppress(TelebotError):
                self.channel.send(report.encode())

    def _on_datagram(self, datagram: ReceivedDatagram) -> None:
        if not self._running or datagram.received_at < self._started_at:
            return
        complete = self.reassembler.on_datagram(datagram.payload, self._loop.time())
        if not self.reporting and self.reassembler.stats.fragments:
            self._start_reports()  # the first video of the call: ask for more from now on
        if complete is None:
            return
        if not self.gate.admit(complete.frame_id, complete.codec, complete.keyframe):
            self._ask_keyframe()
            return
        self.last_frame_at = self._loop.time()
        self.feed._deliver(complete)

    def _on_timer(self) -> None:
        self._timer = None
        if not self._running or not self.reporting:
            return
        now = self._loop.time()
        self.reassembler.poll(now)
        report = self.reassembler.report(
            int(now * 1000), keyframe=self.gate.need_keyframe, codecs=self.feed.codecs
        )
        try:
            self.channel.send(report.encode())
        except CallEnded:
            self._running = self.reporting = False
            return
        except TelebotError as exc:  # a transport hiccup: the next report will do
            log.debug("video report not sent: %s", exc)
        self._timer = self._loop.call_later(self.feed.report_interval, self._on_timer)


async def frames(channel: Channel, **options: Any) -> AsyncIterator[VideoFrame]:
    """Decoded frames from ``channel`` (see :func:`video_channel`) until the call ends.

    ``options`` go to :class:`VideoReceiver`. Close the generator when done (``async with
    contextlib.aclosing(frames(ch)) as video:``), so the receiver stops at once.
    """
    async with VideoReceiver(channel, **options) as receiver:
        async for frame in receiver:
            yield frame
