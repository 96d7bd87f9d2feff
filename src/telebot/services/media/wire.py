"""Media streams of a call, sans-IO: channel names, codecs, keyframe logic, Opus datagrams.

A call carries four media streams, each on its own channel of the BULK lane (specified in
``docs/protocol.md``, "Media: two-way video and voice"):

========================  ==============  =========================================
channel                   direction       datagrams
========================  ==============  =========================================
``video``                 robot -> user   FRAGMENTs (JPEG, H.264 or VP8), REPORTs back
``video/user``            user -> robot   FRAGMENTs (H.264 or VP8, or JPEG), REPORTs back
``audio``                 robot -> user   AUDIO (one Opus packet each), REPORTs back
``audio/user``            user -> robot   AUDIO, REPORTs back
========================  ==============  =========================================

Video generalises the JPEG stream of :mod:`telebot.services.video.wire`: the same
FRAGMENT header, whose codec byte now names the codec in bits 0-6 (:data:`CODEC_JPEG`,
:data:`CODEC_H264`, :data:`CODEC_VP8`) and flags a keyframe in bit 7; a frame with a
missing fragment is dropped whole (the :class:`~telebot.services.video.wire.Reassembler`).
The receiver's REPORT (the subscription, every 200 ms) may set flag bit 1, *keyframe
wanted*, and may end with the list of codecs it accepts, best first; a REPORT without
the list (an old client) means JPEG only.

Audio: one AUDIO datagram per 20 ms Opus packet (48 kHz mono), 14 header bytes::

    0 u8 kind = 0x03   1 u8 codec = 0x10 (Opus)   2 u32 seq (+1 per packet, wraps)
    6 u64 capture_us (sender's wall clock at the packet's first sample), then the packet

The pieces here hold no clock and do no I/O (``now`` is passed in):

* :class:`KeyframeGate` (receiver): which complete frames of a delta codec may be decoded,
  and whether to ask for a keyframe (after a lost or corrupt frame, until one comes);
* :class:`KeyframeRequests` (receiver): when to send an extra report asking for one;
* :class:`KeyframePacer` (sender): when to force a keyframe (periodic, and on request at
  most once per max(RTT, 300 ms));
* :func:`choose_codec`: the codec a sender uses for a receiver's list;
* :class:`AudioSequencer` (receiver): orders AUDIO packets, counts loss, late and garbage.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Final

from telebot.errors import ProtocolError
from telebot.services.video.wire import (
    CODEC_H264,
    CODEC_JPEG,
    CODEC_VP8,
    KIND_REPORT,
    VIDEO,
    VIDEO_CODECS,
    Report,
    parse_report,
    serial_diff,
)

__all__ = [
    "AUDIO",
    "AUDIO_HEADER",
    "CODEC_H264",
    "CODEC_JPEG",
    "CODEC_NAMES",
    "CODEC_OPUS",
    "CODEC_VP8",
    "FRAME_MS",
    "FRAME_SAMPLES",
    "KIND_AUDIO",
    "MAX_OPUS_PACKET",
    "MEDIA_CHANNELS",
    "MIN_KEYFRAME_GAP",
    "SAMPLE_RATE",
    "USER_AUDIO",
    "USER_MEDIA_PROBE",
    "USER_VIDEO",
    "VIDEO",
    "VIDEO_CODECS",
    "AudioPacket",
    "AudioSequencer",
    "AudioStats",
    "KeyframeGate",
    "KeyframePacer",
    "KeyframeRequests",
    "choose_codec",
    "codec_id",
    "encode_audio",
    "parse_audio",
    "parse_media_report",
]

#: Channel of the user's camera (user -> robot; the robot reports back on it).
USER_VIDEO: Final = "video/user"
#: Channel of the robot's microphone (robot -> user).
AUDIO: Final = "audio"
#: Channel of the user's microphone (user -> robot).
USER_AUDIO: Final = "audio/user"
#: All media channels (all BULK lane, every datagram kept).
MEDIA_CHANNELS: Final = (VIDEO, USER_VIDEO, AUDIO, USER_AUDIO)
#: Seconds a user sends on ``video/user`` / ``audio/user`` before the robot's first report:
#: the robot reports (asks for more) only once media came (docs/protocol.md §25).
USER_MEDIA_PROBE: Final = 2.0

KIND_AUDIO: Final = 0x03
CODEC_OPUS: Final = 0x10
#: Codec names as the config and the web page spell them.
CODEC_NAMES: Final = {CODEC_JPEG: "jpeg", CODEC_H264: "h264", CODEC_VP8: "vp8", CODEC_OPUS: "opus"}
#: kind, codec, seq, capture_us.
AUDIO_HEADER: Final = struct.Struct(">BBIQ")
#: Largest Opus packet taken (RFC 6716: 1275 bytes per frame; 3 frames is ample for 20 ms).
MAX_OPUS_PACKET: Final = 3 * 1275
SAMPLE_RATE: Final = 48_000
FRAME_MS: Final = 20
#: Samples per 20 ms packet at 48 kHz (mono).
FRAME_SAMPLES: Final = SAMPLE_RATE * FRAME_MS // 1000
#: A sender forces a keyframe on request at most once per max(RTT, this) seconds; a
#: receiver repeats its request no faster.
MIN_KEYFRAME_GAP: Final = 0.3

_U32: Final = 1 << 32


def codec_id(name: str) -> int:
    """The codec id of ``name`` (``jpeg``, ``h264``, ``vp8``, ``opus``); ValueError if unknown."""
    for cid, known in CODEC_NAMES.items():
        if known == name.lower():
            return cid
    raise ValueError(f"unknown codec {name!r} (known: {', '.join(CODEC_NAMES.values())})")


def choose_codec(accepted: tuple[int, ...], preferred: tuple[int, ...]) -> int | None:
    """The video codec a sender uses for a receiver that accepts ``accepted`` (best first).

    ``preferred`` lists what the sender can encode, its configured choice first. An empty
    ``accepted`` is an old receiver: JPEG. The sender's first preference the receiver
    accepts wins, so the robot's configured codec is used whenever the user can take it;
    None when they share no codec (the sender sends nothing and counts it).
    """
    if not accepted:
        return CODEC_JPEG if CODEC_JPEG in preferred else None
    for codec in preferred:
        if codec in accepted:
            return codec
    return None


def parse_media_report(payload: str | bytes) -> Report:
    """A REPORT from any media channel (:func:`~telebot.services.video.wire.parse_report`)."""
    if isinstance(payload, bytes) and payload[:1] != bytes((KIND_REPORT,)):
        raise ProtocolError(f"media: datagram kind {payload[:1].hex() or 'none'} is not a report")
    return parse_report(payload)


# --------------------------------------------------------------------------- keyframes


@dataclass(slots=True)
class KeyframeGate:
    """Receiver: decode a delta-coded frame only if the one before it was decoded.

    Frame ids count +1 per frame sent, so a gap means a frame was lost; from then on (and
    after a frame that did not decode, or a change of codec) only a keyframe may be
    decoded, and :attr:`need_keyframe` says to ask for one. JPEG frames always pass.
    """

    #: Frames skipped while waiting for a keyframe.
    skipped: int = 0
    #: Times the gate started waiting for a keyframe.
    waits: int = 0
    _last: int | None = None
    _codec: int | None = None
    _need: bool = True

    @property
    def need_keyframe(self) -> bool:
        """True while only a keyframe can be decoded (also before the first frame)."""
        return self._need

    def admit(self, frame_id: int, codec: int, keyframe: bool) -> bool:
        """Whether to decode this complete frame (updates the gate's state)."""
        if codec != self._codec and self._codec is not None:
            self._lose()
        self._codec = codec
        contiguous = self._last is not None and serial_diff(frame_id, self._last) == 1
        self._last = frame_id
        if keyframe or codec == CODEC_JPEG:
            self._need = False
            return True
        if self._need or not contiguous:
            if not self._need:
                self._lose()
            self.skipped += 1
            return False
        return True

    def corrupt(self) -> None:
        """The frame just admitted did not decode: wait for a keyframe."""
        self._lose()

    def _lose(self) -> None:
        if not self._need:
            self.waits += 1
        self._need = True


@dataclass(slots=True)
class KeyframeRequests:
    """Receiver: when to send an extra report asking for a keyframe.

    Every report carries the *keyframe wanted* flag while the gate waits; besides those,
    :meth:`due` is True at once when the need arises and then at most once per
    max(RTT, 300 ms), so a lost request is repeated and a slow sender is not flooded.
    """

    min_gap: float = MIN_KEYFRAME_GAP
    #: Requests sent (extra reports).
    sent: int = 0
    _last: float | None = None

    def due(self, need: bool, now: float, rtt: float | None = None) -> bool:
        """Whether to send a request now (call when a frame is skipped and on a timer)."""
        if not need:
            self._last = None
            return False
        gap = max(self.min_gap, rtt or 0.0)
        if self._last is not None and now - self._last < gap:
            return False
        self._last = now
        self.sent += 1
        return True


@dataclass(slots=True)
class KeyframePacer:
    """Sender: when the next frame must be a keyframe.

    Periodic (every ``interval`` seconds) and on a receiver's request, but a request
    forces one at most once per max(RTT, ``min_gap``) after the last keyframe: requests
    repeat while the receiver waits, and one keyframe answers them all. A request that
    comes sooner is not forgotten but *deferred* to the end of that gap: it means the
    last keyframe was lost (or is still on its way), and waiting for the receiver's next
    repeat instead would add up to a whole repeat interval to the recovery.
    """

    interval: float = 3.0
    min_gap: float = MIN_KEYFRAME_GAP
    #: Keyframes forced by requests; requests that came too soon after the last keyframe.
    forced: int = 0
    ignored: int = 0
    _last: float | None = None
    _pending: bool = field(default=True)
    _deferred_until: float | None = None

    def request(self, now: float, rtt: float | None = None) -> bool:
        """A receiver asks for a keyframe; True if the next frame will be one."""
        if self._pending:
            return True
        gap = max(self.min_gap, rtt or 0.0)
        if self._last is not None and now - self._last < gap:
            self.ignored += 1
            self._deferred_until = self._last + gap
            return False
        self._pending = True
        self._deferred_until = None
        self.forced += 1
        return True

    def next_is_key(self, now: float) -> bool:
        """Whether the frame about to be encoded must be a keyframe."""
        if self._deferred_until is not None and now >= self._deferred_until:
            self._deferred_until = None
            if not self._pending:
                self._pending = True
                self.forced += 1
        return self._pending or self._last is None or now - self._last >= self.interval

    def sent(self, keyframe: bool, now: float) -> None:
        """A frame was encoded (``keyframe``: the encoder made it one, forced or not)."""
        if keyframe:
            self._last = now
            self._pending = False
            self._deferred_until = None


# --------------------------------------------------------------------------- audio


@dataclass(frozen=True, slots=True)
class AudioPacket:
    """A parsed AUDIO datagram."""

    seq: int
    capture_us: int
    data: bytes
    codec: int = CODEC_OPUS

    @property
    def capture_time(self) -> float:
        """Sender's wall clock (Unix seconds) at the packet's first sample."""
        return self.capture_us / 1e6


def encode_audio(seq: int, capture_time: float, packet: bytes, *, codec: int = CODEC_OPUS) -> bytes:
    """The AUDIO datagram of one Opus packet; ValueError when the packet is empty or too long."""
    if not 0 < len(packet) <= MAX_OPUS_PACKET:
        raise ValueError(f"an audio packet must be 1..{MAX_OPUS_PACKET} bytes, got {len(packet)}")
    capture_us = max(0, min(round(capture_time * 1e6), (1 << 64) - 1))
    return AUDIO_HEADER.pack(KIND_AUDIO, codec, seq % _U32, capture_us) + packet


def parse_audio(payload: str | bytes) -> AudioPacket:
    """Parse an AUDIO datagram; ProtocolError says what is wrong."""
    if not isinstance(payload, bytes):
        raise ProtocolError("audio: expected a binary datagram")
    if len(payload) <= AUDIO_HEADER.size:
        raise ProtocolError(f"audio: {len(payload)} bytes is no longer than its header")
    kind, codec, seq, capture_us = AUDIO_HEADER.unpack_from(payload)
    if kind != KIND_AUDIO:
        raise ProtocolError(f"audio: datagram kind {kind:#04x} is not an audio packet")
    if codec != CODEC_OPUS:
        raise ProtocolError(f"audio: unknown codec {codec:#04x}")
    if len(payload) - AUDIO_HEADER.size > MAX_OPUS_PACKET:
        raise ProtocolError(f"audio: a {len(payload) - AUDIO_HEADER.size}-byte packet is too long")
    return AudioPacket(seq, capture_us, payload[AUDIO_HEADER.size :], codec)


@dataclass(slots=True)
class AudioStats:
    """What an audio receiver took and dropped (all counters)."""

    packets: int = 0
    data_bytes: int = 0
    #: Packets that never came (gaps in seq before a newer one).
    lost: int = 0
    #: Packets older than one already played (reordered beyond use, or duplicates).
    late: int = 0
    malformed: int = 0
    #: Packets that did not decode (counted by the driver with :meth:`AudioSequencer.corrupt`).
    corrupt: int = 0


#: A gap longer than this many packets is a restart (the sender paused), not loss to conceal.
MAX_CONCEAL: Final = 5


class AudioSequencer:
    """Receiver: AUDIO datagrams in order; gaps reported for concealment, garbage counted.

    :meth:`on_datagram` returns the packets to play, oldest first: ``None`` for each lost
    packet of a short gap (up to :data:`MAX_CONCEAL`, for the decoder's concealment or
    FEC), then the packet. A packet older than the newest played is late and dropped (the
    jitter buffer, if any, sits before the sequencer). Bad input is counted, never raised.
    """

    def __init__(self) -> None:
        self.stats = AudioStats()
        self._highest: int | None = None
        self._transit_min: float | None = None
        self.queue_delay = 0.0

    @property
    def highest_seq(self) -> int | None:
        """Highest packet seq taken."""
        return self._highest

    def on_datagram(self, payload: str | bytes, now: float) -> list[AudioPacket | None]:
        """Take one datagram; returns what to play (empty for a late or bad one)."""
        try:
            packet = parse_audio(payload)
        except ProtocolError:
            self.stats.malformed += 1
            return []
        out: list[AudioPacket | None] = []
        if self._highest is not None:
            ahead = serial_diff(packet.seq, self._highest)
            if ahead <= 0:
                self.stats.late += 1
                return []
            missing = ahead - 1
            self.stats.lost += missing
            out.extend([None] * min(missing, MAX_CONCEAL))
        self._highest = packet.seq
        self.stats.packets += 1
        self.stats.data_bytes += len(packet.data)
        transit = now - packet.capture_time
        if self._transit_min is None or transit < self._transit_min:
            self._transit_min = transit
        self.queue_delay = transit - self._transit_min
        out.append(packet)
        return out

    def corrupt(self) -> None:
        """Count a packet that did not decode."""
        self.stats.corrupt += 1

    def report(self, receiver_ms: int, *, bye: bool = False) -> Report:
        """A receiver report (``fragments``/``frames``: packets taken, ``dropped``: corrupt)."""
        stats = self.stats
        return Report(
            receiver_ms=receiver_ms,
            highest_seq=self._highest or 0,
            fragments=stats.packets,
            data_bytes=stats.data_bytes,
            frames=stats.packets - stats.corrupt,
            dropped=stats.corrupt,
            queue_delay_ms=round(self.queue_delay * 1000),
            bye=bye,
            codecs=(CODEC_OPUS,),
        )
