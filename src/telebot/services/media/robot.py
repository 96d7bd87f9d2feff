"""The robot's side of media: :class:`RobotMedia`, the per-robot ``media`` service (see the
service's overview in :mod:`telebot.services.media`).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import shutil
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from telebot.channels.transports.base import Lane
from telebot.config import MediaConfig
from telebot.errors import ProtocolError, TelebotError
from telebot.services.base import HostService, RobotHost
from telebot.services.codecs import OpusDecoder, OpusEncoder, VideoDecoder
from telebot.services.media.stream import AudioBlock, Unsubscribe, _AudioIn, _AudioOut, _pace
from telebot.services.media.wire import AUDIO, USER_AUDIO, USER_VIDEO, AudioPacket
from telebot.services.video.receiver import VideoFeed, VideoFeedService
from telebot.services.video.stream import DECODED_CODECS
from telebot.services.video.wire import CompleteFrame

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

    from telebot.channels.call import Call
    from telebot.services.chat.wire import ChatReply

__all__ = [
    "AudioBlock",
    "CallState",
    "MediaHost",
    "RobotMedia",
    "RobotMediaService",
    "Voice",
]

log = logging.getLogger(__name__)

#: The user's camera counts as off when no picture of it came for this long (s): the
#: user turned it off, or its video stalled (the screen must not show a frozen face).
USER_VIDEO_STALE = 2.0
#: User frames waiting for the robot's decoder thread before new ones are dropped.
MAX_DECODE_QUEUE = 8


class MediaHost(RobotHost, Protocol):
    """What the robot's media uses of the robot besides :class:`RobotHost`: the chat
    replies, to speak them."""

    chat_listeners: list[Callable[[Call, ChatReply], None]]


@dataclass(frozen=True, slots=True)
class CallState:
    """What the robot's screen shows about the call."""

    #: Short line for the screen: "alice is driving", "alice is watching",
    #: "connecting…", "no call".
    text: str
    user: str | None = None
    role: str | None = None
    driving: bool = False
    #: Whether pictures of the user's camera came within :data:`USER_VIDEO_STALE` s
    #: (False: the camera is off, or its video stalled); whether the user was heard.
    video: bool = False
    audio: bool = False


# --------------------------------------------------------------------------- voice


class Voice:
    """Speech for the robot's replies: ``command`` (espeak-ng) writes a WAV to stdout.

    :meth:`synthesise` runs it (call it off the event loop) and returns 48 kHz samples;
    :attr:`error` is a one-line reason when the synthesiser is missing.
    """

    def __init__(self, command: tuple[str, ...] = ("espeak-ng", "--stdout")) -> None:
        self.command = command
        self.error: str | None = None
        if not command or shutil.which(command[0]) is None:
            name = command[0] if command else "(none)"
            self.error = (
                f"voice: {name} is not installed (Debian: apt install espeak-ng, "
                "or `make install-debian`); replies are not spoken"
            )

    def synthesise(self, text: str) -> npt.NDArray[np.int16]:
        """``text`` spoken, as 48 kHz mono int16; RuntimeError with a one-line reason."""
        if self.error is not None:
            raise RuntimeError(self.error)
        try:
            done = subprocess.run(
                [*self.command, text], capture_output=True, timeout=10, check=True
            )
        except (OSError, subprocess.SubprocessError) as exc:
            raise RuntimeError(f"voice: {self.command[0]} failed ({exc})") from None
        return _wav_bytes(done.stdout)


def _wav_bytes(data: bytes) -> npt.NDArray[np.int16]:
    import io
    import wave

    import numpy as np

    from telebot.services.media.audio import resample

    try:
        with wave.open(io.BytesIO(data), "rb") as wav:
            rate, channels = wav.getframerate(), wav.getnchannels()
            raw = wav.readframes(wav.getnframes())
    except (EOFError, wave.Error) as exc:
        raise RuntimeError(f"voice: the synthesiser wrote no WAV ({exc})") from None
    samples = np.frombuffer(raw, dtype="<i2").reshape(-1, channels).mean(axis=1)
    return resample(samples, rate)


# --------------------------------------------------------------------------- robot


class RobotMedia(HostService[MediaHost]):
    """The robot's media across calls, the robot's ``media`` service: once per robot, with
    its ``[media]`` section (:class:`~telebot.config.MediaConfig`) of the host's config.

    Its microphone and speaker open when the robot starts it (``[media] mic`` and
    ``speaker``, ``memory`` for a sink tests read back) and close with the robot. See the
    service's overview in :mod:`telebot.services.media` for the screen's API.
    """

    def __init__(self, host: MediaHost) -> None:
        from telebot.services.media.audio import MixSource, open_sink, open_source

        super().__init__(host)
        #: The ``[media]`` section.
        self.settings = host.config.get("media", MediaConfig)
        #: The microphone, with spoken replies mixed in.
        self.mic = MixSource(open_source(self.settings.mic))
        self.speaker = open_sink(self.settings.speaker)
        self._opus: OpusEncoder | None = None
        self._calls: dict[str, RobotMediaService] = {}
        self._pump: asyncio.Task[None] | None = None
        self._video_subs: list[Callable[[CompleteFrame], None]] = []
        self._audio_subs: list[Callable[[AudioPacket], None]] = []
        self._state_subs: list[Callable[[CallState], None]] = []
        self._picture_subs: list[Callable[[npt.NDArray[np.uint8], CompleteFrame], None]] = []
        #: The user's camera across calls; the robot asks for it once a call sends it.
        self.user_video = VideoFeed()
        self._decoder = VideoDecoder()
        self._decode_pool: concurrent.futures.ThreadPoolExecutor | None = None
        self._decoding = 0
        self.user_video.subscribe(self._on_user_frame, codecs=DECODED_CODECS)
        #: The newest decoded picture of the user's camera (BGR), and its frame id.
        self.user_picture: npt.NDArray[np.uint8] | None = None
        self.user_frame_id: int | None = None
        self.user_frames_decoded = 0
        self.user_frames_corrupt = 0
        self._ring: Any = None
        # The ring's name; "" once it could not be opened (said once, not retried).
        self._ring_name = self.settings.user_video_ring
        self.voice: Voice | None = None
        if self.settings.voice != "off":
            self.voice = Voice(tuple(self.settings.voice_command))
            if self.voice.error is not None:
                log.warning("%s", self.voice.error)
        self.spoken = 0
        self._state = CallState("no call")

    # -- the screen's API

    @property
    def state(self) -> CallState:
        """The call as the robot's screen shows it."""
        return self._state

    def subscribe(
        self,
        *,
        on_video: Callable[[CompleteFrame], None] | None = None,
        on_audio: Callable[[AudioPacket], None] | None = None,
        on_state: Callable[[CallState], None] | None = None,
        codecs: tuple[int, ...] = DECODED_CODECS,
    ) -> Unsubscribe:
        """Encoded user media and call state for a consumer (the screen page).

        ``on_state`` is called at once with the current state. Returns the function that
        ends the subscription.
        """
        unsub_video: Unsubscribe | None = None
        if on_video is not None:
            unsub_video = self.user_video.subscribe(on_video, codecs=codecs)
        if on_audio is not None:
            self._audio_subs.append(on_audio)
        if on_state is not None:
            self._state_subs.append(on_state)
            on_state(self._state)

        def unsubscribe() -> None:
            if unsub_video is not None:
                unsub_video()
            for subs, item in ((self._audio_subs, on_audio), (self._state_subs, on_state)):
                with contextlib.suppress(ValueError):
                    subs.remove(item)  # type: ignore[arg-type]

        return unsubscribe

    def on_user_picture(
        self, callback: Callable[[npt.NDArray[np.uint8], CompleteFrame], None]
    ) -> Unsubscribe:
        """Call ``callback(image, frame)`` with each decoded picture of the user's camera."""
        self._picture_subs.append(callback)
        return lambda: self._picture_subs.remove(callback)

    def request_keyframe(self) -> None:
        """A consumer's decoder failed: ask the user's side for a keyframe (paced)."""
        self.user_video.request_keyframe()

    def speak(self, text: str) -> None:
        """Say ``text`` (in a thread) into the user's audio and/or the speaker (``voice``)."""
        voice = self.voice
        if voice is None or voice.error is not None or not text.strip():
            return
        loop = asyncio.get_running_loop()
        future = loop.run_in_executor(None, voice.synthesise, text)
        future.add_done_callback(self._spoken)

    # -- the host's

    def start(self) -> None:
        """Hear the robot's chat replies (to speak them)."""
        self.host.chat_listeners.append(self._on_chat_reply)

    def open(self, call: Call) -> RobotMediaService:
        """The ``media`` service of ``call``."""
        return RobotMediaService(self, call)

    def close(self) -> None:
        """The robot is closing: stop the microphone pump, close devices and the ring."""
        if self._pump is not None:
            self._pump.cancel()
            self._pump = None
        if self._decode_pool is not None:
            self._decode_pool.shutdown(wait=False, cancel_futures=True)
            self._decode_pool = None
        self.mic.close()
        self.speaker.close()
        if self._ring is not None:
            self._ring.close()
            self._ring = None

    # -- internals

    def _spoken(self, future: asyncio.Future[npt.NDArray[np.int16]]) -> None:
        try:
            samples = future.result()
        except Exception as exc:
            log.warning("%s", exc)
            return
        self.spoken += 1
        if self.settings.voice in ("user", "both"):
            self.mic.play(samples)
        if self.settings.voice in ("speaker", "both"):
            self.speaker.write(samples)

    def _on_chat_reply(self, call: Call, reply: ChatReply) -> None:
        if reply.text and call.id in self._calls:
            self.speak(reply.text)

    def _added(self, service: RobotMediaService) -> None:
        self._calls[service.call.id] = service
        if self._pump is None:
            loop = asyncio.get_running_loop()
            self._pump = loop.create_task(_pace(loop, self._mic_block), name="robot-mic")
        self.update_state()

    def _removed(self, service: RobotMediaService) -> None:
        self._calls.pop(service.call.id, None)
        if not self._calls and self._pump is not None:
            self._pump.cancel()
            self._pump = None
        self.update_state()

    def _mic_block(self, now: float) -> None:
        block = self.mic.read()  # read whether or not anyone listens: the tone keeps time
        senders = [s.audio_out for s in self._calls.values() if s.audio_out.watching(now)]
        if not senders:
            return
        if self._opus is None:
            self._opus = OpusEncoder()
        packet = self._opus.encode(block)
        capture = time.time()
        for sender in senders:
            with contextlib.suppress(TelebotError):  # the call is ending; its service closes
                sender.send(packet, capture)

    def _on_user_frame(self, complete: CompleteFrame) -> None:
        # Decoded on a worker thread, in order: the robot's loop (its control) never waits
        # for a decoder. A worker far behind drops the frame and waits for a keyframe.
        if self._decoding >= MAX_DECODE_QUEUE:
            self.user_frames_corrupt += 1
            self.user_video.request_keyframe()
            return
        if self._decode_pool is None:
            self._decode_pool = concurrent.futures.ThreadPoolExecutor(
                1, thread_name_prefix="user-video-decode"
            )
        loop = asyncio.get_running_loop()
        self._decoding += 1
        future = loop.run_in_executor(
            self._decode_pool, self._decoder.decode, complete.data, complete.codec
        )
        future.add_done_callback(lambda done: self._user_decoded(complete, done))

    def _user_decoded(
        self, complete: CompleteFrame, done: asyncio.Future[npt.NDArray[np.uint8]]
    ) -> None:
        self._decoding -= 1
        if done.cancelled():
            return
        exc = done.exception()
        if exc is not None:
            self.user_frames_corrupt += 1
            log.debug("user frame %d dropped: %s", complete.frame_id, exc)
            self.user_video.request_keyframe()
            return
        image = done.result()
        self.user_picture, self.user_frame_id = image, complete.frame_id
        self.user_frames_decoded += 1
        self._to_ring(image, complete)
        for callback in list(self._picture_subs):
            try:
                callback(image, complete)
            except Exception:
                log.exception("user picture subscriber failed")

    def _to_ring(self, image: npt.NDArray[np.uint8], complete: CompleteFrame) -> None:
        name = self._ring_name
        if not name:
            return
        if self._ring is None:
            from telebot.services.shm import FrameRingWriter

            try:
                self._ring = FrameRingWriter(name, 1280, 720)
            except (OSError, ValueError) as exc:
                log.warning("user video ring %r not opened: %s", name, exc)
                self._ring_name = ""
                return
        self._ring.write(
            image,
            frame_id=complete.frame_id,
            capture_time=complete.capture_time,
            camera=complete.camera[:20],
        )

    def _on_user_audio(self, packet: AudioPacket) -> None:
        for callback in list(self._audio_subs):
            try:
                callback(packet)
            except Exception:
                log.exception("user audio subscriber failed")

    def update_state(self) -> None:
        """Recompute the call state and tell the subscribers if it changed."""
        state = CallState("no call")
        holder = None
        if self.host.safety is not None:
            holder = self.host.safety.state().holder_call
        calls = list(self._calls.values())
        # The screen shows the driver's call, else the newest.
        chosen = next((s for s in calls if s.call.id == holder), calls[-1] if calls else None)
        if chosen is not None:
            call, driving = chosen.call, chosen.call.id == holder
            heard = chosen.audio_in.sequencer.stats.packets > 0
            seen = chosen.video_in.reassembler.stats.frames > 0
            if not (heard or seen) and not driving:
                text = f"connecting… ({call.peer})"
            else:
                text = f"{call.peer} is {'driving' if driving else 'watching'}"
            state = CallState(text, call.peer, str(call.role), driving, chosen.camera_on(), heard)
        if state != self._state:
            self._state = state
            for callback in list(self._state_subs):
                try:
                    callback(state)
                except Exception:
                    log.exception("call state subscriber failed")


class RobotMediaService:
    """The ``media`` service of one call on the robot (see :class:`RobotMedia`)."""

    def __init__(self, media: RobotMedia, call: Call) -> None:
        self.media = media
        self.call = call
        loop = self._loop = asyncio.get_running_loop()
        self.audio_out = _AudioOut(call.channel(AUDIO, lane=Lane.BULK), loop)
        # The robot asks for the caller's camera and voice (reports) once they came: a
        # call that sends none gets no reports on video/user and audio/user (§25).
        self.video_in = VideoFeedService(
            media.user_video,
            call,
            channel=call.channel(USER_VIDEO, lane=Lane.BULK),
            wait_for_media=True,
        )
        self._decoder = OpusDecoder()
        self.audio_in = _AudioIn(
            call.channel(USER_AUDIO, lane=Lane.BULK),
            self._on_user_audio,
            loop,
            wait_for_media=True,
        )
        self.audio_in.start()
        media._added(self)

    def tick(self, now: float) -> None:
        """Keep the screen's call state current (who drives changes with the safety state,
        the camera goes off when its pictures stop)."""
        self.media.update_state()

    def camera_on(self) -> bool:
        """Whether a picture of the caller's camera came within :data:`USER_VIDEO_STALE` s."""
        at = self.video_in.last_frame_at
        return at is not None and self._loop.time() - at <= USER_VIDEO_STALE

    def close(self) -> None:
        """The call ended: stop asking for the user's media."""
        self.audio_in.stop(bye=self.call.active)
        self.video_in.close()
        self.audio_out.close()
        self.media._removed(self)

    def _on_user_audio(self, packets: list[AudioPacket | None]) -> None:
        for packet in packets:
            try:
                samples = self._decoder.decode(packet.data if packet is not None else None)
            except ProtocolError as exc:
                self.audio_in.sequencer.corrupt()
                log.debug("user audio packet dropped: %s", exc)
                continue
            self.media.speaker.write(samples)
            if packet is not None:
                self.media._on_user_audio(packet)
