"""The user's side of media: :class:`UserMedia`, :class:`UserMediaService` and
:class:`AudioReceiver` (see the service's overview in :mod:`telebot.services.media`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import TYPE_CHECKING, Any, Protocol, Self, cast

from telebot.channels.transports.base import Lane
from telebot.errors import ProtocolError, TelebotError
from telebot.robot.nav import CameraFrame
from telebot.services.base import ClientHost
from telebot.services.codecs import OpusDecoder, OpusEncoder
from telebot.services.media.stream import AudioBlock, Unsubscribe, _AudioIn, _AudioOut, _pace
from telebot.services.media.wire import (
    AUDIO,
    CODEC_H264,
    CODEC_JPEG,
    CODEC_VP8,
    USER_AUDIO,
    USER_MEDIA_PROBE,
    USER_VIDEO,
    AudioPacket,
)
from telebot.services.video.sender import VideoSender
from telebot.services.video.wire import VideoSettings

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

    from telebot.channels.call import Call
    from telebot.services.media.audio import AudioSource

__all__ = [
    "AudioReceiver",
    "PictureSource",
    "TestPattern",
    "UserMedia",
    "UserMediaService",
    "open_user_media",
]

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- user


class PictureSource:
    """Pictures for the user's camera stream: ``grab()`` returns a BGR picture."""

    def __init__(self, grab: Callable[[], npt.NDArray[np.uint8]], name: str = "user") -> None:
        self.grab = grab
        self.name = name
        self._n = 0

    # The VideoSender takes its pictures from a NavStack; these two are all it uses.
    @property
    def active_camera(self) -> str:
        """The camera name on the wire."""
        return self.name

    def get_frame(self) -> CameraFrame:
        """The next picture."""
        self._n += 1
        return CameraFrame(self.name, self.grab(), time.time(), self._n)


class TestPattern:
    """A moving colour pattern (640 × 480 by default), for ``talk --camera test`` and tests."""

    __test__ = False  # not a pytest class

    def __init__(self, width: int = 640, height: int = 480) -> None:
        import numpy as np

        y, x = np.mgrid[0:height, 0:width]
        self._base = np.stack([x * 255 // width, y * 255 // height, (x + y) % 256], axis=-1)
        self._n = 0

    def __call__(self) -> npt.NDArray[np.uint8]:
        """The next picture."""
        import numpy as np

        self._n += 1
        return cast(
            "npt.NDArray[np.uint8]", np.roll(self._base, self._n * 4, axis=1).astype(np.uint8)
        )


@dataclass(slots=True)
class _UserSources:
    mic: AudioSource | None = None
    camera: PictureSource | None = None
    video: VideoSettings = field(
        default_factory=lambda: VideoSettings(
            codecs=(CODEC_VP8, CODEC_H264, CODEC_JPEG),
            max_fps=15.0,
            max_bitrate=800_000,
            probe=USER_MEDIA_PROBE,
        )
    )


class UserMedia:
    """The user's media across calls (``robot.media``): the robot's audio for
    :meth:`audio` receivers, and the microphone and camera :meth:`talk` sends."""

    def __init__(self) -> None:
        self._audio_subs: list[Callable[[list[AudioPacket | None]], None]] = []
        self._end_subs: list[Callable[[], None]] = []
        self.sources = _UserSources()
        self._service: UserMediaService | None = None
        self.ended = False

    @property
    def audio_wanted(self) -> bool:
        """Whether someone listens to the robot's microphone."""
        return bool(self._audio_subs) and not self.ended

    def subscribe_audio(
        self,
        on_packets: Callable[[list[AudioPacket | None]], None],
        on_end: Callable[[], None] | None = None,
    ) -> Unsubscribe:
        """Hand the robot's audio packets (None for a lost one) to ``on_packets``."""
        self._audio_subs.append(on_packets)
        if on_end is not None:
            self._end_subs.append(on_end)
        self._update()

        def unsubscribe() -> None:
            with contextlib.suppress(ValueError):
                self._audio_subs.remove(on_packets)
            if on_end is not None:
                with contextlib.suppress(ValueError):
                    self._end_subs.remove(on_end)
            self._update()

        return unsubscribe

    def talk(
        self,
        mic: AudioSource | str | None = None,
        camera: PictureSource | Callable[[], npt.NDArray[np.uint8]] | None = None,
    ) -> None:
        """Send ``mic`` (a source or a spec such as ``wav:hello.wav``, ``default``) and
        ``camera`` (pictures) to the robot while it asks for them; None stops either."""
        from telebot.services.media.audio import open_source

        old = self.sources.mic
        self.sources.mic = open_source(mic) if isinstance(mic, str) else mic
        if old is not None and old is not self.sources.mic:
            old.close()
        if camera is not None and not isinstance(camera, PictureSource):
            camera = PictureSource(camera)
        self.sources.camera = camera
        if self._service is not None:
            self._service.sources_changed()

    def send_audio(self, packet: bytes, capture_time: float) -> bool:
        """Send one already encoded Opus packet (a browser page's microphone) on the
        current call while the robot asks for the user's voice; False when not sent (no
        call, not asked). TelebotError if the call refuses it."""
        service = self._service
        if service is None or not service.audio_out.watching(service._loop.time()):
            return False
        service.audio_out.send(packet, capture_time)
        return True

    def end(self) -> None:
        """The client closes: receivers end."""
        if self.ended:
            return
        self.ended = True
        for callback in list(self._end_subs):
            with contextlib.suppress(Exception):
                callback()
        if self.sources.mic is not None:
            self.sources.mic.close()

    def _update(self) -> None:
        if self._service is not None:
            self._service.update()

    def _deliver(self, packets: list[AudioPacket | None]) -> None:
        for callback in list(self._audio_subs):
            try:
                callback(packets)
            except Exception:
                log.exception("audio subscriber failed")


class UserMediaService:
    """The ``media`` call service of a user client: one call's part of :class:`UserMedia`."""

    def __init__(self, media: UserMedia, call: Call) -> None:
        self.media = media
        self.call = call
        self._loop = asyncio.get_running_loop()
        self.audio_in = _AudioIn(call.channel(AUDIO, lane=Lane.BULK), media._deliver, self._loop)
        self.audio_out = _AudioOut(
            call.channel(USER_AUDIO, lane=Lane.BULK), self._loop, probe=USER_MEDIA_PROBE
        )
        self._video_channel = call.channel(USER_VIDEO, lane=Lane.BULK)
        self.video_out: VideoSender | None = None
        self._opus: OpusEncoder | None = None
        self._pump: asyncio.Task[None] | None = None
        self._closed = False
        media._service = self
        self.update()
        self.sources_changed()

    def update(self) -> None:
        """Listen to the robot's microphone while someone wants it."""
        if self._closed:
            return
        if self.media.audio_wanted:
            self.audio_in.start()
        else:
            self.audio_in.stop(bye=self.call.active)

    def sources_changed(self) -> None:
        """Start or stop sending the microphone and camera."""
        if self._closed:
            return
        sources = self.media.sources
        if sources.mic is not None and self._pump is None:
            self._pump = self._loop.create_task(_pace(self._loop, self._mic_block), name="user-mic")
        elif sources.mic is None and self._pump is not None:
            self._pump.cancel()
            self._pump = None
        if sources.camera is not None and self.video_out is None:
            self.video_out = VideoSender(
                cast("Any", sources.camera),
                self._video_channel,
                sources.video,
                call_stats=self.call.stats,
            )
            self.video_out.start()
        elif sources.camera is None and self.video_out is not None:
            self.video_out.stop()
            self.video_out = None
            self._video_channel.set_callback(None)

    def tick(self, now: float) -> None:
        """Nothing: the streams have their own timers."""

    def close(self) -> None:
        """The call ended or the client closes."""
        if self._closed:
            return
        self._closed = True
        self.audio_in.stop(bye=self.call.active)
        self.audio_out.close()
        if self._pump is not None:
            self._pump.cancel()
        if self.video_out is not None:
            self.video_out.stop()
        if self.media._service is self:
            self.media._service = None

    def _mic_block(self, now: float) -> None:
        mic = self.media.sources.mic
        if mic is None:
            return
        block = mic.read()
        if not self.audio_out.watching(now):
            return
        if self._opus is None:
            self._opus = OpusEncoder()
        with contextlib.suppress(TelebotError):  # the call is ending
            self.audio_out.send(self._opus.encode(block), time.time())


class AudioReceiver:
    """The robot's microphone, decoded: ``async for block in robot.audio()`` gives
    :class:`AudioBlock` s of 20 ms (silence for a lost packet) until the client closes.

    A consumer that falls more than ``max_queue`` blocks behind loses the oldest ones.
    """

    def __init__(self, media: UserMedia, *, max_queue: int = 50) -> None:
        self.media = media
        self.max_queue = max_queue
        self._decoder = OpusDecoder()
        self._queue: list[AudioBlock] = []
        self._ready = asyncio.Event()
        self._unsubscribe: Unsubscribe | None = None
        self._ended = False
        #: Blocks dropped because the consumer was behind; packets that did not decode.
        self.overflow = 0
        self.corrupt = 0

    def start(self) -> None:
        """Ask the robot for its audio (idempotent)."""
        if self._unsubscribe is None and not self._ended:
            self._unsubscribe = self.media.subscribe_audio(self._on_packets, self._on_end)

    async def close(self) -> None:
        """Stop listening."""
        self._ended = True
        self._ready.set()
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None

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

    def __aiter__(self) -> AudioReceiver:
        return self

    async def __anext__(self) -> AudioBlock:
        self.start()
        while not self._queue:
            if self._ended:
                raise StopAsyncIteration
            self._ready.clear()
            await self._ready.wait()
        return self._queue.pop(0)

    def _on_end(self) -> None:
        self._ended = True
        self._ready.set()

    def _on_packets(self, packets: list[AudioPacket | None]) -> None:
        now = time.time()
        for packet in packets:
            try:
                samples = self._decoder.decode(packet.data if packet is not None else None)
            except ProtocolError:
                self.corrupt += 1
                continue
            seq = packet.seq if packet is not None else -1
            capture = packet.capture_time if packet is not None else 0.0
            self._queue.append(AudioBlock(samples, seq, capture, now))
        if len(self._queue) > self.max_queue:
            self.overflow += len(self._queue) - self.max_queue
            del self._queue[: len(self._queue) - self.max_queue]
        self._ready.set()


class MediaClient(ClientHost, Protocol):
    """What the user's media uses of the client: its :class:`UserMedia` too."""

    media: UserMedia


def open_user_media(client: MediaClient, call: Call) -> UserMediaService:
    """The user's ``media`` call service factory (registered by the client)."""
    return UserMediaService(client.media, call)
