"""Video over lossy datagrams, sans-IO: fragments, reassembly, receiver reports, adaptation.

A video stream runs on a call's "video" channel (BULK lane, never *latest only*: that would
drop the fragments of a frame). The robot sends JPEG frames cut into fragments; the user
rebuilds them and, while it wants video, sends receiver reports back on the same channel.
All integers are big-endian; the wire format is specified in ``docs/protocol.md``
("The video channel").

Fragment (robot -> user), 29 + L header bytes, then the fragment's share of the JPEG::

    0  u8   kind = 0x01            10 u16  index (0 .. count-1)
    1  u8   codec = 0x01 (JPEG)    12 u16  count (1 .. 64)
    2  u32  seq (per datagram)     14 u32  size: bytes of the whole JPEG
    6  u32  frame_id               18 u64  capture time, µs since the Unix epoch (sender's clock)
                                   26 u16  interval_ms: the sender's current frame interval
                                   28 u8   L, then L bytes of camera name (UTF-8, 1..32)

Fragment ``i`` of ``count`` carries bytes ``[off(i), off(i+1))`` of the JPEG, where
``off(i) = i·q + min(i, r)`` with ``q, r = divmod(size, count)`` (the first ``r`` fragments
carry one byte more; numpy's ``array_split``), so a receiver knows every fragment's place and
length from the header alone, and every fragment is non-empty.

Report (user -> robot), 28 bytes, cumulative counters (a lost report loses nothing)::

    0 u8 kind = 0x02   1 u8 flags (bit 0: bye)   2 u32 receiver_ms (receiver's clock, wraps)
    6 u32 highest_seq   10 u32 fragments received   14 u32 fragment bytes received (wraps)
    18 u32 frames completed   22 u32 frames dropped   26 u16 queue_delay_ms

The sender streams only while reports come (they are the subscription): a user who does not
watch costs no bandwidth; a report with the *bye* flag stops the stream at once. From two reports it learns the fragment loss, the delivered bit
rate and the queueing delay, which :class:`VideoRateController` turns into frame rate, JPEG
quality and picture scale. Nothing here reads a clock or does I/O (``now`` is passed in).
"""

from __future__ import annotations

import math
import struct
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final, cast

from telebot.channels.proto.frames import MAX_DATAGRAM
from telebot.errors import ProtocolError

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

__all__ = [
    "CODEC_CDR",
    "CODEC_H264",
    "CODEC_JPEG",
    "CODEC_KEYFRAME",
    "CODEC_VP8",
    "FLAG_BYE",
    "FLAG_KEYFRAME",
    "FRAGMENT_HEADER",
    "KIND_FRAGMENT",
    "KIND_REPORT",
    "MAX_CAMERA_NAME",
    "MAX_FRAGMENTS",
    "MAX_FRAME_BYTES",
    "MAX_IN_FLIGHT",
    "MAX_PIXELS",
    "MAX_REPORT_CODECS",
    "REPORT",
    "SCALES",
    "VIDEO",
    "VIDEO_CODECS",
    "CompleteFrame",
    "Fragment",
    "Reassembler",
    "ReassemblyStats",
    "Report",
    "VideoRateController",
    "VideoSettings",
    "decode_jpeg",
    "encode_jpeg",
    "encode_report",
    "fragment",
    "fragment_span",
    "jpeg_size",
    "parse_fragment",
    "parse_report",
    "serial_diff",
]

#: The channel name of the video stream (both ends open it on the BULK lane).
VIDEO: Final = "video"

KIND_FRAGMENT: Final = 0x01
KIND_REPORT: Final = 0x02
CODEC_JPEG: Final = 0x01
#: Codec of opaque payloads: the topic relay's CDR messages (:mod:`telebot.services.relay.wire`
#: reuses these fragments; the "camera" field then names the relay stream).
CODEC_CDR: Final = 0x02
#: Codecs of the media streams (``docs/protocol.md`` "Media"): H.264 Annex B access units
#: (SPS/PPS before every IDR) and VP8 frames; see :mod:`telebot.services.media.wire`.
CODEC_H264: Final = 0x03
CODEC_VP8: Final = 0x04
#: The video codecs a fragment may carry on a video channel.
VIDEO_CODECS: Final = frozenset({CODEC_JPEG, CODEC_H264, CODEC_VP8})
#: Bit 7 of the codec byte: this frame is a keyframe (decodable alone). A JPEG frame
#: always is, with or without the bit (old senders leave it clear).
CODEC_KEYFRAME: Final = 0x80
_WHAT: Final = {
    CODEC_JPEG: "video fragment",
    CODEC_CDR: "relay fragment",
    CODEC_H264: "video fragment",
    CODEC_VP8: "video fragment",
}
#: Report flag: the receiver stops watching.
FLAG_BYE: Final = 0x01
#: Report flag: the receiver needs a keyframe (it lost a frame of a delta codec).
FLAG_KEYFRAME: Final = 0x02
#: Most codec ids in a report's codec list.
MAX_REPORT_CODECS: Final = 8
#: kind, codec, seq, frame_id, index, count, size, capture_us, interval_ms, camera length.
FRAGMENT_HEADER: Final = struct.Struct(">BBIIHHIQHB")
#: kind, flags, receiver_ms, highest_seq, fragments, bytes, frames, dropped, queue_delay_ms.
REPORT: Final = struct.Struct(">BBIIIIIIH")
#: Longest camera name on the wire (UTF-8 bytes).
MAX_CAMERA_NAME: Final = 32
#: Most fragments of one frame: 64 × ~32 KB ≈ 2 MB, more than a 1080p JPEG needs.
MAX_FRAGMENTS: Final = 64
#: Largest JPEG a receiver accepts (bounds the memory of one frame in reassembly).
MAX_FRAME_BYTES: Final = 2_000_000
#: Largest picture a receiver decodes (width × height): a forged JPEG header must not make
#: the decoder allocate gigabytes. 4096 × 4096 BGR is 48 MB.
MAX_PIXELS: Final = 4096 * 4096
#: Frames a receiver rebuilds at once; a newer one beyond this evicts the oldest.
MAX_IN_FLIGHT: Final = 4
#: A partial frame waits at least this long and at most MAX_HOLD for its missing fragments,
#: within those bounds one frame interval (the header's ``interval_ms``).
MIN_HOLD: Final = 0.005
MAX_HOLD: Final = 1.0
#: A frame id may run ahead of the newest seen by this many frames per second of silence
#: (plus JUMP_SLACK): a sender that kept counting through an outage is followed, a wild id
#: (which would make every later real frame look old) is refused.
MAX_WIRE_FPS: Final = 240
JUMP_SLACK: Final = 64
#: Picture scales the sender may step through (of the configured size), best first.
SCALES: Final = (1.0, 0.75, 0.5, 0.375, 0.25)

_U32: Final = 1 << 32


def serial_diff(a: int, b: int) -> int:
    """``a − b`` in 32-bit serial-number arithmetic (RFC 1982): positive if ``a`` is newer."""
    diff = (a - b) % _U32
    return diff - _U32 if diff >= 1 << 31 else diff


def fragment_span(size: int, count: int, index: int) -> tuple[int, int]:
    """Byte range ``(start, end)`` of fragment ``index`` of a ``size``-byte frame in ``count``."""
    q, r = divmod(size, count)
    start = index * q + min(index, r)
    return start, start + q + (1 if index < r else 0)


# --------------------------------------------------------------------------- fragments


@dataclass(frozen=True, slots=True)
class Fragment:
    """A parsed fragment datagram (``data`` is this fragment's share of the JPEG)."""

    seq: int
    frame_id: int
    index: int
    count: int
    size: int
    capture_us: int
    interval_ms: int
    camera: str
    data: bytes
    codec: int = CODEC_JPEG
    #: The frame decodes alone (bit 7 of the codec byte; always True for JPEG).
    keyframe: bool = True


def _camera_bytes(camera: str) -> bytes:
    raw = camera.encode("utf-8")
    if not 0 < len(raw) <= MAX_CAMERA_NAME:
        raise ValueError(f"camera name must be 1..{MAX_CAMERA_NAME} UTF-8 bytes, got {camera!r}")
    return raw


def fragment(
    frame_id: int,
    camera: str,
    capture_time: float,
    jpeg: bytes,
    max_payload: int = MAX_DATAGRAM,
    *,
    seq: int = 0,
    interval: float = 1 / 30,
    codec: int = CODEC_JPEG,
    keyframe: bool = False,
) -> list[bytes]:
    """Cut one JPEG frame into fragment datagrams of at most ``max_payload`` bytes each.

    ``capture_time`` is wall-clock seconds (Unix epoch); ``seq`` is the sequence number of
    the first datagram (the next ones count up, modulo 2³²); ``interval`` is the sender's
    current frame interval in seconds (the receiver waits that long for missing fragments);
    ``codec`` says what the bytes are (JPEG for video, :data:`CODEC_CDR` for the relay,
    :data:`CODEC_H264` or :data:`CODEC_VP8` for coded video); ``keyframe`` sets bit 7 of the
    codec byte (a frame that decodes alone). Raises ValueError when the frame is empty, too large, or ``max_payload`` too small.
    """
    name = _camera_bytes(camera)
    header_len = FRAGMENT_HEADER.size + len(name)
    room = min(max_payload, MAX_DATAGRAM) - header_len
    if room < 1:
        raise ValueError(f"max_payload {max_payload} leaves no room after the header")
    size = len(jpeg)
    if not 0 < size <= MAX_FRAME_BYTES:
        raise ValueError(f"a frame must be 1..{MAX_FRAME_BYTES} bytes, got {size}")
    count = -(-size // room)
    if count > MAX_FRAGMENTS:
        raise ValueError(f"a {size}-byte frame needs {count} fragments (at most {MAX_FRAGMENTS})")
    if not 0 < codec < CODEC_KEYFRAME:
        raise ValueError(f"codec must be 1..127, got {codec}")
    codec_byte = codec | (CODEC_KEYFRAME if keyframe else 0)
    capture_us = max(0, min(round(capture_time * 1e6), (1 << 64) - 1))
    interval_ms = max(1, min(round(interval * 1000), 0xFFFF))
    view = memoryview(jpeg)
    out = []
    for index in range(count):
        start, end = fragment_span(size, count, index)
        header = FRAGMENT_HEADER.pack(
            KIND_FRAGMENT,
            codec_byte,
            (seq + index) % _U32,
            frame_id % _U32,
            index,
            count,
            size,
            capture_us,
            interval_ms,
            len(name),
        )
        out.append(b"".join((header, name, view[start:end])))
    return out


def parse_fragment(payload: str | bytes, *, codec: int | frozenset[int] = CODEC_JPEG) -> Fragment:
    """Parse and check a fragment datagram of ``codec`` (one id or a set of accepted ids).

    ProtocolError says what is wrong. Bit 7 of the codec byte is the keyframe flag.
    """
    codecs = frozenset({codec}) if isinstance(codec, int) else codec
    what = _WHAT.get(min(codecs, default=0), "fragment")
    if not isinstance(payload, bytes):
        raise ProtocolError(f"{what}: expected a binary datagram")
    if len(payload) < FRAGMENT_HEADER.size:
        raise ProtocolError(f"{what}: {len(payload)} bytes is shorter than its header")
    kind, codec_byte, seq, frame_id, index, count, size, capture_us, interval_ms, name_len = (
        FRAGMENT_HEADER.unpack_from(payload)
    )
    got_codec = codec_byte & ~CODEC_KEYFRAME
    if kind != KIND_FRAGMENT:
        raise ProtocolError(f"{what}: datagram kind {kind:#04x} is not a fragment")
    if got_codec not in codecs:
        raise ProtocolError(f"{what}: unknown codec {got_codec}")
    if not 1 <= count <= MAX_FRAGMENTS or index >= count:
        raise ProtocolError(f"{what}: index {index} of {count} fragments")
    if not count <= size <= MAX_FRAME_BYTES:
        raise ProtocolError(f"{what}: frame size {size} for {count} fragments")
    if not 0 < name_len <= MAX_CAMERA_NAME:
        raise ProtocolError(f"{what}: camera name of {name_len} bytes")
    data_at = FRAGMENT_HEADER.size + name_len
    if len(payload) < data_at:
        raise ProtocolError(f"{what}: truncated camera name")
    try:
        camera = payload[FRAGMENT_HEADER.size : data_at].decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ProtocolError(f"{what}: camera name is not UTF-8") from exc
    start, end = fragment_span(size, count, index)
    if len(payload) - data_at != end - start:
        raise ProtocolError(
            f"{what}: {len(payload) - data_at} data bytes, "
            f"fragment {index} of a {size}-byte frame in {count} has {end - start}"
        )
    return Fragment(
        seq=seq,
        frame_id=frame_id,
        index=index,
        count=count,
        size=size,
        capture_us=capture_us,
        interval_ms=interval_ms,
        camera=camera,
        data=payload[data_at:],
        codec=got_codec,
        keyframe=bool(codec_byte & CODEC_KEYFRAME) or got_codec == CODEC_JPEG,
    )


# --------------------------------------------------------------------------- reports


@dataclass(frozen=True, slots=True)
class Report:
    """A receiver report: cumulative counters of what reached the receiver (see module doc)."""

    receiver_ms: int
    highest_seq: int
    fragments: int
    data_bytes: int
    frames: int
    dropped: int
    queue_delay_ms: int
    #: The receiver stops watching (flag bit 0): the sender may stop at once.
    bye: bool = False
    #: The receiver needs a keyframe (flag bit 1): it lost a frame of a delta codec.
    keyframe: bool = False
    #: Codecs the receiver accepts, in preference order (the report's extension); empty:
    #: an old receiver, which takes JPEG only.
    codecs: tuple[int, ...] = ()

    def encode(self) -> bytes:
        """The report datagram."""
        return encode_report(self)


def encode_report(report: Report) -> bytes:
    """The report datagram (counters wrap modulo 2³², the delay saturates).

    28 bytes, then, when ``report.codecs`` is not empty, one byte ``n`` and ``n`` codec ids.
    """
    codecs = report.codecs
    if len(codecs) > MAX_REPORT_CODECS or not all(0 < c < CODEC_KEYFRAME for c in codecs):
        raise ValueError(f"a report lists 0..{MAX_REPORT_CODECS} codec ids in 1..127")
    flags = (FLAG_BYE if report.bye else 0) | (FLAG_KEYFRAME if report.keyframe else 0)
    fixed = REPORT.pack(
        KIND_REPORT,
        flags,
        report.receiver_ms % _U32,
        report.highest_seq % _U32,
        report.fragments % _U32,
        report.data_bytes % _U32,
        report.frames % _U32,
        report.dropped % _U32,
        max(0, min(report.queue_delay_ms, 0xFFFF)),
    )
    return fixed + bytes((len(codecs), *codecs)) if codecs else fixed


def parse_report(payload: str | bytes) -> Report:
    """Parse a report datagram (28 bytes, or with its codec list); ProtocolError if not one."""
    if not isinstance(payload, bytes) or len(payload) < REPORT.size:
        raise ProtocolError("video: a report is a binary datagram of at least 28 bytes")
    kind, flags, receiver_ms, highest, fragments, data_bytes, frames, dropped, delay = (
        REPORT.unpack_from(payload)
    )
    if kind != KIND_REPORT:
        raise ProtocolError(f"video: datagram kind {kind:#04x} is not a report")
    codecs: tuple[int, ...] = ()
    if len(payload) > REPORT.size:
        count = payload[REPORT.size]
        if not 0 < count <= MAX_REPORT_CODECS or len(payload) != REPORT.size + 1 + count:
            raise ProtocolError(
                f"video: a report's codec list of {count} ids in {len(payload)} bytes"
            )
        codecs = tuple(payload[REPORT.size + 1 :])
        if not all(0 < c < CODEC_KEYFRAME for c in codecs) or len(set(codecs)) != count:
            raise ProtocolError("video: a report's codec list has bad or repeated ids")
    return Report(
        receiver_ms,
        highest,
        fragments,
        data_bytes,
        frames,
        dropped,
        delay,
        bye=bool(flags & FLAG_BYE),  # the other flag bits are reserved and ignored
        keyframe=bool(flags & FLAG_KEYFRAME),
        codecs=codecs,
    )


# --------------------------------------------------------------------------- reassembly


@dataclass(frozen=True, slots=True, eq=False)
class CompleteFrame:
    """A frame rebuilt from all its fragments (still JPEG)."""

    frame_id: int
    camera: str
    #: Sender's wall-clock time (Unix seconds) when it took the picture from the camera.
    capture_time: float
    #: The sender's frame interval when it sent this frame (seconds).
    interval: float
    data: bytes
    fragments: int
    #: The receiver's ``now`` when the last fragment arrived.
    completed_at: float
    #: What the bytes are (:data:`CODEC_JPEG`, :data:`CODEC_H264`, :data:`CODEC_VP8`…).
    codec: int = CODEC_JPEG
    #: The frame decodes alone (a JPEG always does).
    keyframe: bool = True


@dataclass(slots=True)
class ReassemblyStats:
    """What the reassembler took and what it dropped, by reason (all counters)."""

    #: Fragments accepted into a frame (duplicates, late and refused ones not included).
    fragments: int = 0
    #: Data bytes of the accepted fragments.
    data_bytes: int = 0
    #: Frames completed and returned.
    frames: int = 0
    #: Frames dropped unfinished: a fragment did not come within one frame interval, a newer
    #: frame completed first, or more than MAX_IN_FLIGHT frames were open.
    incomplete: int = 0
    #: Fragments of a frame older than one already returned (latest frame wins).
    late: int = 0
    duplicates: int = 0
    #: Datagrams that are not valid fragments (bad header, sizes, kind or codec).
    malformed: int = 0
    #: Fragments that contradict earlier fragments of the same frame (count, size, camera…).
    inconsistent: int = 0
    #: Fragments whose frame id is implausibly far ahead of the stream.
    absurd: int = 0
    #: Frames whose JPEG did not decode (counted by the driver with :meth:`Reassembler.corrupt`).
    corrupt: int = 0

    @property
    def dropped(self) -> int:
        """Frames lost after some of them arrived: incomplete plus corrupt."""
        return self.incomplete + self.corrupt


class _Partial:
    """A frame being rebuilt."""

    __slots__ = (
        "buffer",
        "camera",
        "capture_us",
        "codec",
        "count",
        "deadline",
        "first_seen",
        "have",
        "interval_ms",
        "keyframe",
        "missing",
        "size",
    )

    def __init__(self, first: Fragment, now: float) -> None:
        self.count = first.count
        self.size = first.size
        self.camera = first.camera
        self.capture_us = first.capture_us
        self.interval_ms = first.interval_ms
        self.codec = first.codec
        self.keyframe = first.keyframe
        self.buffer = bytearray(first.size)
        self.have = bytearray(first.count)
        self.missing = first.count
        self.first_seen = now
        self.deadline = now + min(max(first.interval_ms / 1000, MIN_HOLD), MAX_HOLD)

    def matches(self, frag: Fragment) -> bool:
        return (frag.count, frag.size, frag.camera, frag.capture_us, frag.codec) == (
            self.count,
            self.size,
            self.camera,
            self.capture_us,
            self.codec,
        ) and frag.keyframe == self.keyframe


class Reassembler:
    """Rebuilds frames from fragments: bounded, latest frame wins (the user's side).

    :meth:`on_datagram` takes each datagram with the receiver's ``now`` and returns a
    :class:`CompleteFrame` when one completes. It never returns a frame older than one it
    returned before; it keeps at most ``max_in_flight`` partial frames and drops a partial
    frame one frame interval after its first fragment (call :meth:`poll` at
    :meth:`next_deadline`). Bad input is dropped and counted in :attr:`stats`, never raised.
    """

    def __init__(
        self, *, max_in_flight: int = MAX_IN_FLIGHT, codec: int | frozenset[int] = CODEC_JPEG
    ) -> None:
        if max_in_flight < 1:
            raise ValueError("max_in_flight must be at least 1")
        self.max_in_flight = max_in_flight
        #: The codec (or set of codecs) whose fragments are taken (others are malformed).
        self.codec = codec
        self.stats = ReassemblyStats()
        self._partials: OrderedDict[int, _Partial] = OrderedDict()
        self._newest_returned: int | None = None
        self._newest_seen: int | None = None
        self._newest_seen_at = 0.0
        self._highest_seq: int | None = None
        # Queueing delay: (first fragment's arrival − capture time); its minimum over a
        # window is the path's base delay (the clocks' offset included), the excess is queue.
        self._transits: deque[tuple[float, float]] = deque()
        self._queue_delay = 0.0

    @property
    def newest_returned(self) -> int | None:
        """Frame id of the newest frame returned so far."""
        return self._newest_returned

    @property
    def in_flight(self) -> int:
        """Partial frames held now."""
        return len(self._partials)

    @property
    def highest_seq(self) -> int | None:
        """Highest fragment sequence number seen (serial arithmetic)."""
        return self._highest_seq

    @property
    def queue_delay(self) -> float:
        """Latest estimate of the queueing delay on the path (seconds)."""
        return self._queue_delay

    def on_datagram(self, payload: str | bytes, now: float) -> CompleteFrame | None:
        """Take one datagram; returns the frame it completes, if any."""
        self.poll(now)
        try:
            frag = parse_fragment(payload, codec=self.codec)
        except ProtocolError:
            self.stats.malformed += 1
            return None
        return self.on_fragment(frag, now)

    def on_fragment(self, frag: Fragment, now: float) -> CompleteFrame | None:
        """Take one parsed fragment (see :meth:`on_datagram`)."""
        fid = frag.frame_id
        if self._newest_returned is not None and serial_diff(fid, self._newest_returned) <= 0:
            self.stats.late += 1
            return None
        if self._newest_seen is not None:
            ahead = serial_diff(fid, self._newest_seen)
            allowed = MAX_WIRE_FPS * max(0.0, now - self._newest_seen_at) + JUMP_SLACK
            if ahead > allowed:
                self.stats.absurd += 1
                return None
        partial = self._partials.get(fid)
        if partial is None:
            partial = self._open(frag, now)
        elif not partial.matches(frag):
            self.stats.inconsistent += 1
            return None
        if partial.have[frag.index]:
            self.stats.duplicates += 1
            return None
        self._note_seq(frag.seq)
        if self._newest_seen is None or serial_diff(fid, self._newest_seen) > 0:
            self._newest_seen, self._newest_seen_at = fid, now
        start, end = fragment_span(partial.size, partial.count, frag.index)
        partial.buffer[start:end] = frag.data
        partial.have[frag.index] = 1
        partial.missing -= 1
        self.stats.fragments += 1
        self.stats.data_bytes += len(frag.data)
        if partial.missing:
            return None
        return self._complete(fid, partial, now)

    def poll(self, now: float) -> None:
        """Drop partial frames whose time is up."""
        for fid in [f for f, p in self._partials.items() if p.deadline <= now]:
            del self._partials[fid]
            self.stats.incomplete += 1

    def next_deadline(self) -> float | None:
        """When the next partial frame expires (None when none is held)."""
        return min((p.deadline for p in self._partials.values()), default=None)

    def corrupt(self) -> None:
        """Count a returned frame whose JPEG did not decode (the driver decodes)."""
        self.stats.corrupt += 1

    def report(
        self,
        receiver_ms: int,
        *,
        bye: bool = False,
        keyframe: bool = False,
        codecs: tuple[int, ...] = (),
    ) -> Report:
        """A receiver report of the counters now (``receiver_ms``: this side's clock in ms).

        ``keyframe`` asks for a keyframe; ``codecs`` lists the codecs taken, best first.
        """
        stats = self.stats
        return Report(
            receiver_ms=receiver_ms,
            highest_seq=self._highest_seq or 0,
            fragments=stats.fragments,
            data_bytes=stats.data_bytes,
            frames=stats.frames,
            dropped=stats.dropped,
            queue_delay_ms=round(self._queue_delay * 1000),
            bye=bye,
            keyframe=keyframe,
            codecs=codecs,
        )

    # -- internals

    def _open(self, frag: Fragment, now: float) -> _Partial:
        while len(self._partials) >= self.max_in_flight:
            self._partials.popitem(last=False)  # the oldest opened: the least likely to finish
            self.stats.incomplete += 1
        partial = _Partial(frag, now)
        self._partials[frag.frame_id] = partial
        self._note_transit(frag.capture_us / 1e6, now)
        return partial

    def _complete(self, fid: int, partial: _Partial, now: float) -> CompleteFrame:
        del self._partials[fid]
        # Latest frame wins: older partial frames can never be shown now.
        for older in [f for f in self._partials if serial_diff(f, fid) < 0]:
            del self._partials[older]
            self.stats.incomplete += 1
        self._newest_returned = fid
        self.stats.frames += 1
        return CompleteFrame(
            frame_id=fid,
            camera=partial.camera,
            capture_time=partial.capture_us / 1e6,
            interval=partial.interval_ms / 1000,
            data=bytes(partial.buffer),
            fragments=partial.count,
            completed_at=now,
            codec=partial.codec,
            keyframe=partial.keyframe,
        )

    def _note_seq(self, seq: int) -> None:
        if self._highest_seq is None or serial_diff(seq, self._highest_seq) > 0:
            self._highest_seq = seq

    def _note_transit(self, capture_time: float, now: float, window: float = 5.0) -> None:
        transit = now - capture_time
        # A monotone deque keeps the window's minimum in O(1) amortised.
        while self._transits and self._transits[-1][1] >= transit:
            self._transits.pop()
        self._transits.append((now, transit))
        while self._transits[0][0] < now - window:
            self._transits.popleft()
        self._queue_delay = transit - self._transits[0][1]


# --------------------------------------------------------------------------- JPEG


def encode_jpeg(image: npt.NDArray[np.uint8], quality: int) -> bytes:
    """``image`` (BGR uint8) as JPEG at ``quality`` (1..100)."""
    import cv2

    ok, buffer = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("OpenCV could not encode the frame as JPEG")
    return bytes(buffer)


_SOF_MARKERS: Final = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def jpeg_size(data: bytes) -> tuple[int, int]:
    """``(width, height)`` from a JPEG's frame header, without decoding; ProtocolError if none."""
    if data[:2] != b"\xff\xd8":
        raise ProtocolError("video frame: not a JPEG")
    at = 2
    while at + 4 <= len(data):
        if data[at] != 0xFF:
            raise ProtocolError("video frame: JPEG marker expected")
        marker = data[at + 1]
        if marker == 0xFF:  # fill byte
            at += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a length
            at += 2
            continue
        length = int.from_bytes(data[at + 2 : at + 4], "big")
        if marker in _SOF_MARKERS:
            if length < 7 or at + 9 > len(data):
                raise ProtocolError("video frame: truncated JPEG frame header")
            height = int.from_bytes(data[at + 5 : at + 7], "big")
            width = int.from_bytes(data[at + 7 : at + 9], "big")
            return width, height
        if marker == 0xDA or length < 2:  # image data before any frame header
            break
        at += 2 + length
    raise ProtocolError("video frame: no JPEG frame header")


def decode_jpeg(data: bytes, *, max_pixels: int = MAX_PIXELS) -> npt.NDArray[np.uint8]:
    """A JPEG as a BGR uint8 image; ProtocolError for a corrupt or oversized one."""
    import cv2
    import numpy as np

    width, height = jpeg_size(data)
    if not 0 < width * height <= max_pixels:
        raise ProtocolError(f"video frame: a {width} × {height} picture is out of bounds")
    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR)
    except cv2.error as exc:
        raise ProtocolError(f"video frame: OpenCV cannot decode it ({exc})") from exc
    if image is None or image.shape[:2] != (height, width):
        raise ProtocolError("video frame: OpenCV cannot decode this JPEG")
    return cast("npt.NDArray[np.uint8]", image)


# --------------------------------------------------------------------------- adaptation


@dataclass(frozen=True, slots=True)
class VideoSettings:
    """What the robot sends: size, rate and quality bounds (the controller moves within them)."""

    #: Picture size at scale 1 (frames of another size are resized).
    width: int = 640
    height: int = 480
    #: Frame rate ceiling and floor (frames per second).
    max_fps: float = 30.0
    min_fps: float = 2.0
    #: JPEG quality ceiling (the quality on a good link) and floor.
    quality: int = 80
    min_quality: int = 30
    #: Smallest picture scale the controller may step down to (of width × height).
    min_scale: float = 0.25
    #: Largest datagram sent (the fragment size); smaller only to test fragmentation.
    max_payload: int = MAX_DATAGRAM
    #: False: fixed rate and quality (max_fps, quality, scale 1) whatever the link does.
    adaptive: bool = True
    #: Send only while receiver reports come; stop this long (s) after the last one.
    on_demand: bool = True
    idle_after: float = 2.0
    #: Seconds an on-demand sender sends before any report came (0: none). The user's
    #: camera uses it: the robot asks for it only once it came (docs/protocol.md §25).
    probe: float = 0.0
    #: Codecs the sender may use, its preference first (:func:`~telebot.services.media.wire.
    #: choose_codec` picks among those the receiver lists; JPEG for an old receiver).
    codecs: tuple[int, ...] = (CODEC_JPEG,)
    #: H.264 / VP8: seconds between periodic keyframes, and the bit rate bounds (bits/s).
    keyframe_interval: float = 3.0
    min_bitrate: int = 150_000
    max_bitrate: int = 2_000_000
    #: Draw each frame's ``frame_id`` into its top edge (a test pattern the simulator, the
    #: tests and the bench read back; :func:`telebot.services.codecs.read_number`).
    stamp: bool = False

    def __post_init__(self) -> None:
        checks = [
            (16 <= self.width <= 4096 and 16 <= self.height <= 4096, "width/height 16..4096"),
            (0 < self.min_fps <= self.max_fps <= 120, "0 < min_fps <= max_fps <= 120"),
            (1 <= self.min_quality <= self.quality <= 100, "1 <= min_quality <= quality <= 100"),
            (0 < self.min_scale <= 1, "0 < min_scale <= 1"),
            (FRAGMENT_HEADER.size + MAX_CAMERA_NAME < self.max_payload <= MAX_DATAGRAM, ""),
            (self.idle_after > 0, "idle_after > 0"),
            (self.probe >= 0, "probe >= 0"),
            (bool(self.codecs), "at least one codec"),
            (self.keyframe_interval > 0, "keyframe_interval > 0"),
            (0 < self.min_bitrate <= self.max_bitrate, "0 < min_bitrate <= max_bitrate"),
        ]
        for ok, what in checks:
            if not ok:
                what = what or f"max_payload in {FRAGMENT_HEADER.size + MAX_CAMERA_NAME + 1}.."
                raise ValueError(f"video settings: need {what}")

    @property
    def scales(self) -> tuple[float, ...]:
        """The scale ladder allowed by ``min_scale``, best first."""
        return tuple(s for s in SCALES if s >= self.min_scale - 1e-9) or (1.0,)


#: Frame delivery the fragment budget aims for: a frame of k fragments arrives whole with
#: probability (1 − loss)^k, so at 10 % loss frames stay in one fragment (90 %, not 81 %).
#: (0.88 rather than 0.85: the loss estimate is noisy, and 10 % loss measured as 7 %
#: must still mean one fragment.)
TARGET_FRAME_SUCCESS: Final = 0.88
#: Most fragments per frame the controller allows on a loss-free link.
MAX_BUDGET_FRAGMENTS: Final = 8
#: Queueing delay (s) above which the link is congested, below which it has room.
QUEUE_DELAY_HIGH: Final = 0.05
QUEUE_DELAY_LOW: Final = 0.02
#: Smoothed fragment loss above which the link counts as congested (random loss of a
#: radio link stays below; a flooded link far above).
LOSS_CONGESTED: Final = 0.3
#: On congestion the rate drops to this share of what arrived (GCC's 0.85).
DECREASE: Final = 0.85
#: Rate growth per second while the link has room, and the cap over the delivered rate.
INCREASE_PER_S: Final = 1.5
CAP_OVER_DELIVERED: Final = 2.0
#: Least target rate (bytes/s).
MIN_RATE: Final = 16_000.0
#: A frame smaller than this share of its budget lets quality, scale or rate go up.
GROW_BELOW: Final = 0.6
#: Reports older than this (s) no longer count: the call's heartbeat loss is used instead.
REPORT_STALE: Final = 1.5
#: Weight of the past in the fragment-weighted loss average (per report).
LOSS_DECAY: Final = 0.9
#: A frame not yet reported received this long (s) after the path's round trip and the
#: gap between reports means the link holds a backlog: send no new frame until it drains.
BACKLOG_SLACK: Final = 0.1
#: While held, one frame still goes this often at least (s): the picture never freezes for
#: the safety supervisor's stale-video rule (1 s) because of the hold itself.
BACKLOG_PROBE: Final = 0.25


#: JPEG quality points that about double a frame's size (between quality 50 and 90).
_QUALITY_PER_DOUBLING: Final = 40


def _quality_factor(delta: int) -> float:
    """How a frame's size changes when its quality changes by ``delta`` points (a model)."""
    return float(2 ** (delta / _QUALITY_PER_DOUBLING))


@dataclass(slots=True)
class _LinkEstimate:
    loss: float = 0.0
    rtt: float | None = None
    delivered_rate: float | None = None
    queue_delay: float = 0.0
    lost_weight: float = 0.0
    expected_weight: float = 0.0
    heartbeat_loss: float = 0.0


class VideoRateController:
    """Chooses frame rate, JPEG quality and picture scale from what the link does.

    Inputs: receiver reports (:meth:`on_report`: fragment loss, delivered rate, queueing
    delay), the call's heartbeat loss and round trip (:meth:`on_link`, used while no fresh
    report is at hand) and the size of each encoded frame (:meth:`on_encoded`).

    Two budgets bound a frame's size:

    * fragments: a frame of k fragments arrives whole with probability (1 − loss)^k, so
      k ≤ log(TARGET_FRAME_SUCCESS) / log(1 − loss), between 1 and MAX_BUDGET_FRAGMENTS;
    * rate: a target bit rate, unlimited until the link shows congestion (queueing delay
      over QUEUE_DELAY_HIGH or smoothed loss over LOSS_CONGESTED); then DECREASE × the
      delivered rate, held for max(0.5 s, 2 RTT) so the queue drains, then growing by
      INCREASE_PER_S per second (at most CAP_OVER_DELIVERED × delivered) while the delay
      stays low, and unlimited again once the stream is back at its best.

    A frame over budget lowers the quality (by about 40 points per doubling of the excess,
    JPEG's size roughly doubles from quality 50 to 90), then the scale, then the frame
    rate; a frame under GROW_BELOW of its budget raises them in the reverse order, one
    step per frame. Random loss shrinks frames to fewer fragments but never the rate, so a
    lossy but fast link keeps its frame rate.
    """

    def __init__(self, settings: VideoSettings, *, data_per_fragment: int, now: float = 0.0):
        if data_per_fragment < 1:
            raise ValueError("data_per_fragment must be positive")
        self.settings = settings
        self.data_per_fragment = data_per_fragment
        self._scales = settings.scales
        self._scale_index = 0
        self.quality = settings.quality
        self.fps = settings.max_fps
        #: Target bytes per second (None: not limited).
        self.rate: float | None = None
        self.link = _LinkEstimate()
        self._last_report: Report | None = None
        self._last_report_at: float | None = None
        # The probe (see VideoSettings.probe) runs from the first frame sent, not from
        # creation: a camera or encoder slow to start must not use it up.
        self._probe_from: float | None = None
        self._hold_until = -math.inf
        self._best_since: float | None = None
        self._bye = False
        self.reports = 0
        self.decreases = 0
        #: (last fragment's seq, time sent) of the frames no report has covered yet.
        self._unacked: deque[tuple[int, float]] = deque(maxlen=256)
        self._min_rtt: float | None = None
        self._report_gap = 0.0

    # -- outputs

    @property
    def scale(self) -> float:
        """Current picture scale (of the configured width and height)."""
        return self._scales[self._scale_index]

    @property
    def frame_interval(self) -> float:
        """Seconds between frames at the current rate."""
        return 1.0 / self.fps

    @property
    def max_fragments(self) -> int:
        """The fragment budget of a frame under the current loss."""
        loss = self.loss
        if loss <= 0.0:
            return MAX_BUDGET_FRAGMENTS
        if loss >= 1.0:
            return 1
        k = math.floor(math.log(TARGET_FRAME_SUCCESS) / math.log1p(-loss))
        return max(1, min(MAX_BUDGET_FRAGMENTS, k))

    @property
    def loss(self) -> float:
        """Fragment loss the controller believes in (reports, else heartbeats)."""
        if self._last_report is not None and self.link.expected_weight > 0:
            return self.link.loss
        return self.link.heartbeat_loss

    def budget(self) -> float:
        """Most bytes the next frame should take."""
        frag_budget = float(self.max_fragments * self.data_per_fragment)
        if self.rate is None:
            return frag_budget
        return min(frag_budget, self.rate / self.fps)

    def watching(self, now: float) -> bool:
        """Whether a receiver reported within ``idle_after`` (always True if not on demand),
        or, before any report, whether the ``probe`` time since the first frame sent runs
        (:meth:`frame_sent`; until then it does)."""
        if not self.settings.on_demand:
            return True
        at = self._last_report_at
        if at is None:
            probe_from = self._probe_from
            return self.settings.probe > 0 and (
                probe_from is None or now - probe_from <= self.settings.probe
            )
        return not self._bye and now - at <= self.settings.idle_after

    # -- inputs

    def on_link(self, *, loss: float, rtt: float | None, now: float) -> None:
        """The call's heartbeat loss and round trip; loss counts only without fresh reports."""
        if math.isfinite(loss):
            self.link.heartbeat_loss = min(max(loss, 0.0), 1.0)
        if rtt is not None and math.isfinite(rtt) and rtt >= 0:
            self.link.rtt = rtt
            self._min_rtt = rtt if self._min_rtt is None else min(self._min_rtt, rtt)
        if self._last_report_at is not None and now - self._last_report_at > REPORT_STALE:
            # Stale reports: start the loss average afresh from the heartbeats' view.
            self._last_report = None
            self.link.lost_weight = self.link.expected_weight = 0.0

    def on_report(self, report: Report, now: float) -> None:
        """A receiver report arrived at ``now`` (the sender's clock)."""
        previous = self._last_report
        if previous is not None and serial_diff(report.receiver_ms, previous.receiver_ms) <= 0:
            return  # a duplicate or an older report, reordered
        if self._last_report_at is not None:
            self._report_gap = now - self._last_report_at
        unacked = self._unacked
        while unacked and serial_diff(unacked[0][0], report.highest_seq) <= 0:
            unacked.popleft()  # arrived, or lost for good: no longer on the way
        self._last_report, self._last_report_at = report, now
        self._bye = report.bye
        self.reports += 1
        if previous is None:
            return  # the first one is the baseline
        elapsed = serial_diff(report.receiver_ms, previous.receiver_ms) / 1000
        expected = serial_diff(report.highest_seq, previous.highest_seq)
        received = (report.fragments - previous.fragments) % _U32
        link = self.link
        if expected > 0:
            lost = min(max(expected - received, 0), expected)
            link.lost_weight = link.lost_weight * LOSS_DECAY + lost
            link.expected_weight = link.expected_weight * LOSS_DECAY + expected
            link.loss = link.lost_weight / link.expected_weight
        if elapsed > 0:
            link.delivered_rate = ((report.data_bytes - previous.data_bytes) % _U32) / elapsed
        link.queue_delay = report.queue_delay_ms / 1000
        if self.settings.adaptive:
            self._adapt_rate(elapsed, now)

    def frame_sent(self, now: float, last_seq: int | None = None) -> None:
        """A frame went out (``last_seq``: its last fragment's seq): the first one starts
        the ``probe`` time."""
        if self._probe_from is None:
            self._probe_from = now
        if last_seq is not None:
            self._unacked.append((last_seq, now))

    def held_up(self, now: float) -> bool:
        """Whether the link holds a backlog of this sender's frames: the oldest frame no
        report covers was sent longer ago than the path's least round trip, the gap between
        reports and :data:`BACKLOG_SLACK`. Send no frame then: every frame added would only
        be shown later (a sender faster than the link's congestion control lets through,
        on a reliable stream, queues there). Still one frame per such time, at most
        :data:`BACKLOG_PROBE`, goes (a probe: frames lost for good, or a receiver that took
        none, must not stop the video for ever). False before the second report (the gap
        between reports is not known yet)."""
        if self._report_gap <= 0.0 or not self._unacked:
            return False
        limit = (self._min_rtt or 0.0) + self._report_gap + BACKLOG_SLACK
        probe = min(limit, BACKLOG_PROBE)
        return now - self._unacked[0][1] > limit and now - self._unacked[-1][1] < probe

    def on_encoded(self, size: int, now: float) -> bool:
        """Adapt to the size of the frame just encoded; True if it is worth encoding again.

        (It is: the frame needs more fragments than the loss allows, and the quality or
        scale just went down.)
        """
        if not self.settings.adaptive:
            return False
        budget = self.budget()
        before = (self.quality, self._scale_index)
        if size > budget:
            self._shrink(size, budget)
        elif size < GROW_BELOW * budget and now >= self._hold_until:
            self._grow(size, budget)
        self._note_best(now)
        over = -(-size // self.data_per_fragment) > self.max_fragments
        return over and (self.quality, self._scale_index) != before

    # -- internals

    def _adapt_rate(self, elapsed: float, now: float) -> None:
        link = self.link
        congested = link.queue_delay > QUEUE_DELAY_HIGH or link.loss > LOSS_CONGESTED
        if congested:
            if now < self._hold_until:
                return  # the last decrease has not shown yet
            delivered = link.delivered_rate or 0.0
            base = delivered if delivered > 0 else (self.rate or MIN_RATE * 4) / 2
            self.rate = max(MIN_RATE, DECREASE * base)
            hold = max(0.5, 2 * (link.rtt or 0.0))
            self._hold_until = now + hold
            self._best_since = None
            self.decreases += 1
            return
        if self.rate is None or link.queue_delay > QUEUE_DELAY_LOW or now < self._hold_until:
            return
        grown = self.rate * INCREASE_PER_S ** max(elapsed, 0.0)
        cap = CAP_OVER_DELIVERED * max(link.delivered_rate or 0.0, MIN_RATE)
        self.rate = max(MIN_RATE, min(grown, max(cap, self.rate)))

    def _shrink(self, size: int, budget: float) -> None:
        settings = self.settings
        if self.quality > settings.min_quality:
            step = min(40, max(2, math.ceil(_QUALITY_PER_DOUBLING * math.log2(size / budget))))
            self.quality = max(settings.min_quality, self.quality - step)
        elif self._scale_index < len(self._scales) - 1:
            self._scale_index += 1
            self.quality = self._mid_quality()
        elif self.rate is not None and size * self.fps > self.rate:
            self.fps = max(settings.min_fps, self.rate / size)

    def _grow(self, size: int, budget: float) -> None:
        settings = self.settings
        if self.fps < settings.max_fps:
            self.fps = min(settings.max_fps, self.fps * 1.25)
            return
        if self._scale_index > 0:
            up = self._scales[self._scale_index - 1] / self.scale
            quality = min(self.quality, self._mid_quality())
            if size * up * up * _quality_factor(quality - self.quality) < 0.8 * budget:
                self._scale_index -= 1
                self.quality = quality
                return
        if self.quality < settings.quality:
            self.quality = min(settings.quality, self.quality + 2)

    def _mid_quality(self) -> int:
        return (self.settings.quality + self.settings.min_quality) // 2

    def _note_best(self, now: float) -> None:
        # Back at the best settings with room to spare for a while: the rate no longer
        # limits anything, so stop limiting it (the next congestion sets it again).
        best = (
            self.quality == self.settings.quality
            and self._scale_index == 0
            and self.fps >= self.settings.max_fps
        )
        if not best or self.rate is None:
            self._best_since = None
            return
        if self._best_since is None:
            self._best_since = now
        elif now - self._best_since > 2.0 and self.link.queue_delay <= QUEUE_DELAY_LOW:
            self.rate = None
            self._best_since = None
