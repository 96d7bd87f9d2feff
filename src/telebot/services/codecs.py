"""Video and audio codecs with PyAV (``import av``; its wheels carry FFmpeg with libx264,
libvpx and libopus): what the media streams of :mod:`telebot.services.media.wire` carry.

* :class:`VideoEncoder`: H.264 Constrained Baseline (no B-frames, Annex B with SPS/PPS on
  every keyframe, ultrafast/zerolatency, keyframes capped in size by the VBV to about two
  datagrams) or VP8 (realtime); keyframes when asked; the bit rate follows the caller.
  :class:`ThreadedEncoder` runs one off the event loop.
* :class:`VideoDecoder`: H.264, VP8 or JPEG to BGR pictures; a corrupt frame raises
  :class:`~telebot.errors.ProtocolError` (the caller drops and counts it and waits for
  the next keyframe), never anything else.
* :class:`OpusEncoder` / :class:`OpusDecoder`: 48 kHz mono, 20 ms packets, in-band FEC.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
from fractions import Fraction
from typing import TYPE_CHECKING, Any, Final, cast

from telebot.channels.proto.frames import MAX_DATAGRAM
from telebot.errors import ProtocolError
from telebot.services.media.wire import (
    CODEC_H264,
    CODEC_JPEG,
    CODEC_NAMES,
    CODEC_VP8,
    FRAME_SAMPLES,
    SAMPLE_RATE,
)
from telebot.services.video.wire import MAX_PIXELS, decode_jpeg, encode_jpeg

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

__all__ = [
    "STAMP_BITS",
    "EncodedFrame",
    "OpusDecoder",
    "OpusEncoder",
    "ThreadedEncoder",
    "VideoDecoder",
    "VideoEncoder",
    "read_number",
    "stamp_number",
]

log = logging.getLogger(__name__)

#: A keyframe should fit in about this many bytes (two datagrams): the VBV buffer size.
KEYFRAME_CAP: Final = 2 * MAX_DATAGRAM - 2 * 64
#: Re-open the encoder for a new bit rate only when it moved by this factor (a re-open
#: costs a keyframe), and at most once per this many seconds.
RATE_STEP: Final = 1.3
RATE_REOPEN_GAP: Final = 2.0

_ENCODERS: Final = {CODEC_H264: "libx264", CODEC_VP8: "libvpx"}
_DECODERS: Final = {CODEC_H264: "h264", CODEC_VP8: "vp8"}


class EncodedFrame:
    """One encoded video frame: its bytes, codec and whether it is a keyframe."""

    __slots__ = ("codec", "data", "keyframe")

    def __init__(self, data: bytes, codec: int, keyframe: bool) -> None:
        self.data = data
        self.codec = codec
        self.keyframe = keyframe


class VideoEncoder:
    """Encodes BGR pictures as H.264, VP8 or JPEG (one frame in, one frame out, no delay).

    ``bitrate`` (bits/s) may change between frames: the encoder is re-opened (the next
    frame is then a keyframe) when it moved by more than :data:`RATE_STEP` and at most
    every :data:`RATE_REOPEN_GAP` s, or at once when the picture size changes.
    """

    def __init__(self, codec: int, *, fps: float = 30.0, keyframe_interval: float = 3.0) -> None:
        if codec not in (CODEC_H264, CODEC_VP8, CODEC_JPEG):
            raise ValueError(f"cannot encode video as {CODEC_NAMES.get(codec, codec)}")
        self.codec = codec
        self.fps = fps
        self.keyframe_interval = keyframe_interval
        self._ctx: Any = None
        self._size: tuple[int, int] | None = None
        self._rate = 0
        self._opened_at = -1e9
        self._pts = 0
        #: Encoder re-opens (size or rate changes).
        self.reopens = 0

    def encode(
        self,
        image: npt.NDArray[np.uint8],
        *,
        keyframe: bool = False,
        bitrate: int = 1_000_000,
        quality: int = 80,
        now: float = 0.0,
    ) -> EncodedFrame:
        """``image`` (BGR uint8, even width and height) as one frame; ``keyframe`` forces one.

        ``quality`` is for JPEG only; ``now`` (any clock, seconds) paces re-opens.
        """
        if self.codec == CODEC_JPEG:
            return EncodedFrame(encode_jpeg(image, quality), CODEC_JPEG, True)
        import av  # here, not at the top: JPEG-only users never load PyAV

        image = image[: image.shape[0] & ~1, : image.shape[1] & ~1]  # 4:2:0 needs even sizes
        size = (int(image.shape[1]), int(image.shape[0]))
        rate = max(50_000, int(bitrate))
        moved = rate > self._rate * RATE_STEP or rate * RATE_STEP < self._rate
        if (
            self._ctx is None
            or size != self._size
            or (moved and now - self._opened_at >= RATE_REOPEN_GAP)
        ):
            self._open(size, rate, now)
            keyframe = True
        frame = av.VideoFrame.from_ndarray(_to_i420(image), format="yuv420p")
        frame.pts = self._pts
        self._pts += 1
        if keyframe:
            frame.pict_type = av.video.frame.PictureType.I
        data = b"".join(bytes(p) for p in self._ctx.encode(frame))
        if not data:  # an encoder that buffers would break the one-in-one-out contract
            raise ValueError(f"the {CODEC_NAMES[self.codec]} encoder returned no frame")
        return EncodedFrame(data, self.codec, keyframe or _is_key(self.codec, data))

    def _open(self, size: tuple[int, int], rate: int, now: float) -> None:
        import av

        ctx: Any = av.CodecContext.create(_ENCODERS[self.codec], "w")
        ctx.width, ctx.height = size
        ctx.pix_fmt = "yuv420p"
        ctx.time_base = Fraction(1, max(1, round(self.fps)))
        ctx.framerate = Fraction(max(1, round(self.fps)), 1)
        ctx.bit_rate = rate
        gop = max(1, round(self.keyframe_interval * self.fps))
        ctx.gop_size = gop
        ctx.max_b_frames = 0
        kbps = rate // 1000
        if self.codec == CODEC_H264:
            # VBV: a keyframe may take at most the buffer, ~2 datagrams; keyint/scenecut
            # off: the sender decides keyframes (KeyframePacer), forced-idr makes them IDR.
            bufsize = min(KEYFRAME_CAP * 8 // 1000, max(kbps, 100))
            ctx.options = {
                "preset": "ultrafast",
                "tune": "zerolatency",
                "profile": "baseline",
                "forced-idr": "1",
                "x264-params": (
                    f"keyint={gop * 4}:min-keyint={gop * 4}:scenecut=0:bframes=0:"
                    f"vbv-maxrate={kbps}:vbv-bufsize={bufsize}:repeat-headers=1:annexb=1"
                ),
            }
        else:
            ctx.options = {
                "deadline": "realtime",
                "cpu-used": "8",
                "lag-in-frames": "0",
                "auto-alt-ref": "0",
                "error-resilient": "1",
                "maxrate": str(rate),
                "bufsize": str(min(KEYFRAME_CAP * 8, rate)),
                "qmin": "4",
                "qmax": "56",
                "keyint_min": str(gop * 4),
            }
        ctx.open()
        self._ctx, self._size, self._rate, self._opened_at = ctx, size, rate, now
        self._pts = 0
        self.reopens += 1


def _to_i420(image: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """BGR → planar YUV 4:2:0 (BT.601) with OpenCV: ~53 dB luma PSNR on a round trip where
    FFmpeg's default conversion gives ~42 dB, a loss the codec would add to its own."""
    import cv2

    return cast("npt.NDArray[np.uint8]", cv2.cvtColor(image, cv2.COLOR_BGR2YUV_I420))


def _to_bgr(frame: Any) -> npt.NDArray[np.uint8]:
    """A decoded frame as BGR (OpenCV's conversion for 4:2:0 of even size, else FFmpeg's)."""
    import cv2

    if frame.format.name == "yuv420p" and frame.width % 2 == 0 and frame.height % 2 == 0:
        i420 = frame.to_ndarray(format="yuv420p")
        return cast("npt.NDArray[np.uint8]", cv2.cvtColor(i420, cv2.COLOR_YUV2BGR_I420))
    return cast("npt.NDArray[np.uint8]", frame.to_ndarray(format="bgr24"))


def _is_key(codec: int, data: bytes) -> bool:
    """Whether an encoded frame is a keyframe, from its bytes."""
    if codec == CODEC_VP8:
        return len(data) > 0 and not data[0] & 0x01  # RFC 6386: bit 0 clear = key frame
    # H.264 Annex B: an IDR slice (NAL type 5) anywhere in the access unit.
    at = data.find(b"\x00\x00\x01")
    while at != -1 and at + 3 < len(data):
        if data[at + 3] & 0x1F == 5:
            return True
        at = data.find(b"\x00\x00\x01", at + 3)
    return False


class ThreadedEncoder:
    """A :class:`VideoEncoder` run on its own worker thread (encoding is off the event loop).

    One frame at a time: :meth:`encode` awaits the worker. :meth:`close` ends the thread.
    """

    def __init__(self, encoder: VideoEncoder) -> None:
        self.encoder = encoder
        self._pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="video-encode")

    async def encode(self, image: npt.NDArray[np.uint8], **options: Any) -> EncodedFrame:
        """Encode on the worker thread (see :meth:`VideoEncoder.encode`)."""
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._pool, lambda: self.encoder.encode(image, **options))

    def close(self) -> None:
        """Let the worker thread end (a frame being encoded finishes first)."""
        self._pool.shutdown(wait=False, cancel_futures=True)


class VideoDecoder:
    """Decodes frames of one stream (codec per frame: a change re-opens the decoder).

    :meth:`decode` returns the BGR picture, or raises ProtocolError for a frame that does
    not decode (corrupt, truncated, oversized or a codec it does not know). Decoders are
    state machines: feed every frame of a delta codec in order (a
    :class:`~telebot.services.media.wire.KeyframeGate` says which).
    """

    def __init__(self, *, max_pixels: int = MAX_PIXELS) -> None:
        self.max_pixels = max_pixels
        self._ctx: Any = None
        self._codec: int | None = None
        #: Frames that did not decode.
        self.errors = 0

    def decode(self, data: bytes, codec: int) -> npt.NDArray[np.uint8]:
        """The picture of one encoded frame (ProtocolError when it does not decode)."""
        if codec == CODEC_JPEG:
            try:
                return decode_jpeg(data, max_pixels=self.max_pixels)
            except ProtocolError:
                self.errors += 1
                raise
        import av  # here, not at the top: JPEG-only users never load PyAV

        if not data:  # an empty packet would flush (end) the decoder
            self.errors += 1
            raise ProtocolError("video frame: empty")
        if codec not in _DECODERS:
            self.errors += 1
            raise ProtocolError(f"video frame: codec {codec} is not one this side decodes")
        if codec != self._codec or self._ctx is None:
            self._ctx = av.CodecContext.create(_DECODERS[codec], "r")
            self._codec = codec
        try:
            frames = self._ctx.decode(av.Packet(data))
            if not frames:
                raise ProtocolError(f"video frame: the {CODEC_NAMES[codec]} decoder gave nothing")
            frame = frames[-1]
            if frame.width * frame.height > self.max_pixels:
                raise ProtocolError(f"video frame: {frame.width} × {frame.height} is too large")
            image = _to_bgr(frame)
        except ProtocolError:
            self.errors += 1
            raise
        except (av.FFmpegError, ValueError, MemoryError) as exc:
            self.errors += 1
            self._ctx = None  # start afresh at the next keyframe
            raise ProtocolError(f"video frame: {CODEC_NAMES[codec]} decoder error ({exc})") from exc
        return image


class OpusEncoder:
    """48 kHz mono int16 samples in 20 ms blocks → Opus packets (in-band FEC on)."""

    def __init__(self, *, bitrate: int = 32_000, expected_loss: int = 10) -> None:
        import av

        ctx: Any = av.CodecContext.create("libopus", "w")
        ctx.sample_rate = SAMPLE_RATE
        ctx.layout = "mono"
        ctx.format = "s16"
        ctx.bit_rate = bitrate
        ctx.options = {
            "application": "voip",
            "frame_duration": "20",
            "fec": "1",
            "packet_loss": str(expected_loss),
        }
        ctx.open()
        self._ctx = ctx
        self._pts = 0

    def encode(self, samples: npt.NDArray[np.int16]) -> bytes:
        """One 20 ms block (960 int16 samples) → one Opus packet."""
        import av
        import numpy as np

        if samples.shape != (FRAME_SAMPLES,):
            raise ValueError(f"an Opus block is {FRAME_SAMPLES} mono samples, got {samples.shape}")
        frame = av.AudioFrame.from_ndarray(
            np.ascontiguousarray(samples, dtype=np.int16).reshape(1, -1),
            format="s16",
            layout="mono",
        )
        frame.sample_rate = SAMPLE_RATE
        frame.pts = self._pts
        self._pts += FRAME_SAMPLES
        packets = self._ctx.encode(frame)
        return b"".join(bytes(p) for p in packets)


class OpusDecoder:
    """Opus packets → 48 kHz mono int16 samples; a lost packet becomes silence."""

    def __init__(self) -> None:
        self._ctx: Any = None
        self._reset()
        #: Packets that did not decode.
        self.errors = 0

    def _reset(self) -> None:
        import av

        ctx: Any = av.CodecContext.create("libopus", "r")
        ctx.sample_rate = SAMPLE_RATE
        ctx.layout = "mono"
        self._ctx = ctx

    def decode(self, packet: bytes | None) -> npt.NDArray[np.int16]:
        """The samples of one packet (None: a lost packet, 20 ms of silence).

        ProtocolError for a packet that does not decode.
        """
        import av
        import numpy as np

        if packet is None:
            return np.zeros(FRAME_SAMPLES, dtype=np.int16)
        try:
            frames = self._ctx.decode(av.Packet(packet))
            parts = [f.to_ndarray().reshape(-1) for f in frames]
        except (av.FFmpegError, ValueError) as exc:
            self.errors += 1
            self._reset()
            raise ProtocolError(f"audio packet: Opus decoder error ({exc})") from exc
        if not parts:
            return np.zeros(0, dtype=np.int16)
        out = np.concatenate(parts)
        if out.dtype != np.int16:  # a float decoder (planar fltp): scale to int16
            out = np.clip(out * 32767.0, -32768, 32767).astype(np.int16)
        return cast("npt.NDArray[np.int16]", out)


#: Bits of a frame number stamped into a picture (it wraps at 2²⁴).
STAMP_BITS: Final = 24


def stamp_number(image: npt.NDArray[np.uint8], number: int) -> npt.NDArray[np.uint8]:
    """A copy of ``image`` with ``number`` drawn as 24 black/white cells along its top edge.

    Each cell is width / 32 pixels square (MSB first, white = 1, after a white-black
    start pair), big enough to survive JPEG, H.264 and VP8 at low rates and any scale, so a
    test or the bench reads back which frame a decoded picture is (:func:`read_number`).
    """
    out = image.copy()
    cell = max(2, image.shape[1] // 32)
    bits = [1, 0] + [(number >> (STAMP_BITS - 1 - i)) & 1 for i in range(STAMP_BITS)]
    for i, bit in enumerate(bits):
        out[:cell, i * cell : (i + 1) * cell] = 255 if bit else 0
    return out


def read_number(image: npt.NDArray[np.uint8]) -> int | None:
    """The number :func:`stamp_number` drew into ``image``, or None when there is none."""
    cell = max(2, image.shape[1] // 32)
    if image.shape[0] < cell or image.shape[1] < (STAMP_BITS + 2) * cell:
        return None
    margin = max(1, cell // 4)

    def bit(i: int) -> float:
        block = image[margin : cell - margin, i * cell + margin : (i + 1) * cell - margin]
        return float(block.mean())

    if not (bit(0) > 160 and bit(1) < 96):
        return None
    number = 0
    for i in range(STAMP_BITS):
        number = (number << 1) | (1 if bit(i + 2) > 128 else 0)
    return number
