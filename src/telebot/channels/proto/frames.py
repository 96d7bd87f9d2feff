"""The bytes on the wire: outer frames and the messages sealed inside them. Sans-IO.

Every frame starts with a version byte and a type byte, then the 8-byte call id that
the caller picked at random. Integers are big-endian unless said otherwise::

    HELLO    ver=2 | type=4 | call_id[8] | name_len u8 | name | instance[8]
                   | suite u8 | offer_len u8 | offers[offer_len] | noise_msg1
    WELCOME  ver=2 | type=2 | call_id[8] | noise_msg2
    DATA     ver=2 | type=3 | call_id[8] | counter u64 | AEAD(ciphertext + 16-byte tag)
    RETRY    ver=2 | type=5 | call_id[8] | suite u8

HELLO's header (everything before ``noise_msg1``) is the Noise prologue, so a frame
whose header was changed in flight fails the handshake. Its ``offers`` are the cipher
suites the caller accepts, in its order of preference, and ``suite`` (one of them) the
one ``noise_msg1`` is written with; a robot that picks another answers RETRY, and the
caller sends the HELLO again with that suite (see ``session.py``). DATA's 18-byte
header is the AEAD's associated data and its counter is the nonce (see :mod:`.noise`).
Type 1 was the HELLO of telebot before cipher suites were negotiated; it is refused
with an error that says so. Version 2 put the sender's name in the zenoh keys (see
``call.py``); the frames are those of version 1 but for the version byte. A version-1
HELLO (type 4) still decodes, as a :class:`Hello` with ``version=1``, so that a robot
can tell an older client why it will not be answered (:data:`LEGACY_VERSION`).

Inside a DATA frame's plaintext the first byte says what it carries::

    DATAGRAM   kind=1 | flags u8 (bit 0: text) | name_len u8 | channel name | payload
    HEARTBEAT  kind=2 | seq u32 | sent_us u64 | echo_us u64 | echo_delay_us u32
    HANGUP     kind=3 | reason (UTF-8)
    BUNDLE     kind=4 | 2 or more of (len u16 | DATAGRAM)

A BUNDLE carries several datagrams sent in one event-loop turn on one lane in a single
frame (one AEAD operation and one publish instead of one each); the receiver hands them
to their channels one by one, as if they had come in separate frames.

Decoders raise :class:`~telebot.errors.ProtocolError` on anything malformed.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

from telebot.errors import DatagramTooLarge, IncompatiblePeer, ProtocolError

__all__ = [
    "CALL_ID_LEN",
    "INSTANCE_LEN",
    "LEGACY_VERSION",
    "MAX_BUNDLE",
    "MAX_CHANNEL_NAME",
    "MAX_DATAGRAM",
    "NAME_PATTERN",
    "VERSION",
    "Bundle",
    "Coalescer",
    "DataFrame",
    "Datagram",
    "Hangup",
    "Heartbeat",
    "Hello",
    "Message",
    "Retry",
    "Welcome",
    "decode_frame",
    "decode_message",
    "encode_bundle",
    "encode_datagram",
    "encode_hangup",
    "encode_heartbeat",
    "validate_channel_name",
    "validate_name",
]

VERSION = 2
#: The protocol before the sender's name was in the keys: only its HELLO is read, to
#: refuse it with a reason (docs/protocol.md section 4.2).
LEGACY_VERSION = 1
CALL_ID_LEN = 8
INSTANCE_LEN = 8
#: Largest datagram payload a channel carries, as Skype's App2App did (32 KB).
MAX_DATAGRAM = 32_768
MAX_CHANNEL_NAME = 255
#: Robot and user names: they become zenoh key chunks, so no ``/ * $ ? #`` and no spaces.
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")

TYPE_LEGACY_HELLO = 1  # before cipher suite negotiation: refused, with a clear error
TYPE_WELCOME = 2
TYPE_DATA = 3
TYPE_HELLO = 4
TYPE_RETRY = 5
#: Most cipher suites a HELLO may offer.
MAX_OFFERS = 8

KIND_DATAGRAM = 1
KIND_HEARTBEAT = 2
KIND_HANGUP = 3
KIND_BUNDLE = 4

FLAG_TEXT = 0x01

_DATA_HEADER = struct.Struct(">BB8sQ")
DATA_HEADER_LEN = _DATA_HEADER.size  # 18
_HEARTBEAT = struct.Struct(">BIQQI")
_TAG_LEN = 16
# A DATA frame's largest plaintext: a full datagram with the longest channel name.
_MAX_PLAINTEXT = 3 + MAX_CHANNEL_NAME + MAX_DATAGRAM
MAX_FRAME = DATA_HEADER_LEN + _MAX_PLAINTEXT + _TAG_LEN
#: Largest BUNDLE plaintext: no bigger than the largest single datagram's, so a frame
#: never grows past MAX_FRAME.
MAX_BUNDLE = _MAX_PLAINTEXT
_BUNDLE_ENTRY = struct.Struct(">H")
_MAX_NOISE_MESSAGE = 2048


def validate_name(name: str, what: str = "name") -> str:
    """Check a robot or user name (a zenoh key chunk); return it or raise ValueError."""
    if not NAME_PATTERN.fullmatch(name):
        raise ValueError(
            f"invalid {what} {name!r}: use 1-64 letters, digits, '.', '_' or '-', "
            "starting with a letter or digit"
        )
    return name


def validate_channel_name(name: str) -> bytes:
    """A channel name's UTF-8 bytes, or ValueError when empty, too long or not text."""
    if not isinstance(name, str) or not name:
        raise ValueError("a channel name is a non-empty string")
    encoded = name.encode("utf-8", "strict")
    if len(encoded) > MAX_CHANNEL_NAME:
        raise ValueError(f"channel name longer than {MAX_CHANNEL_NAME} bytes")
    return encoded


@dataclass(frozen=True, slots=True)
class Hello:
    """A caller asks for a call: its name, its client instance, the cipher suites it
    offers (by number, preferred first), the one Noise message 1 uses, and that message.
    """

    call_id: bytes
    caller: str
    instance: bytes
    noise_message: bytes
    suite: int = 1
    offers: tuple[int, ...] = (1,)
    #: :data:`VERSION`, or :data:`LEGACY_VERSION` for an older client's HELLO.
    version: int = VERSION

    @property
    def prologue(self) -> bytes:
        """The header bytes, bound into the handshake as the Noise prologue."""
        name = self.caller.encode("ascii")
        return (
            bytes([self.version, TYPE_HELLO])
            + self.call_id
            + bytes([len(name)])
            + name
            + self.instance
            + bytes([self.suite, len(self.offers), *self.offers])
        )

    def encode(self) -> bytes:
        """The frame's bytes."""
        return self.prologue + self.noise_message


@dataclass(frozen=True, slots=True)
class Welcome:
    """The robot's answer to a HELLO: Noise message 2 (accepting or refusing inside)."""

    call_id: bytes
    noise_message: bytes
    #: :data:`VERSION`, or :data:`LEGACY_VERSION` for the refusal sent to an older client.
    version: int = VERSION

    def encode(self) -> bytes:
        """The frame's bytes."""
        return bytes([self.version, TYPE_WELCOME]) + self.call_id + self.noise_message


@dataclass(slots=True)
class DataFrame:
    """An encrypted message of an established call."""

    call_id: bytes
    counter: int
    header: bytes  # the 18 bytes authenticated as associated data
    ciphertext: bytes

    @staticmethod
    def make_header(call_id: bytes, counter: int) -> bytes:
        """The 18-byte header of a DATA frame (also its AEAD associated data)."""
        return _DATA_HEADER.pack(VERSION, TYPE_DATA, call_id, counter)


@dataclass(frozen=True, slots=True)
class Retry:
    """The robot's answer to a HELLO written with another suite than the one it picks.

    Not authenticated (it comes before any handshake); the caller sends its HELLO
    again with ``suite``, and the handshake then proves that the robot did pick it.
    """

    call_id: bytes
    suite: int

    def encode(self) -> bytes:
        """The frame's bytes."""
        return bytes([VERSION, TYPE_RETRY]) + self.call_id + bytes([self.suite])


Frame = Hello | Welcome | DataFrame | Retry


def decode_frame(data: bytes) -> Frame:
    """Parse an outer frame; raise ProtocolError when it is not one."""
    if len(data) < 2 + CALL_ID_LEN:
        raise ProtocolError(f"frame too short ({len(data)} bytes)")
    if len(data) > MAX_FRAME:
        raise ProtocolError(f"frame too long ({len(data)} bytes)")
    version, kind = data[0], data[1]
    call_id = bytes(data[2:10])
    if version != VERSION:
        if version == LEGACY_VERSION and kind == TYPE_HELLO:
            return _decode_hello(data, call_id, LEGACY_VERSION)
        if version == LEGACY_VERSION and kind == TYPE_LEGACY_HELLO:
            raise IncompatiblePeer(
                "HELLO without cipher suite negotiation (frame type 1): the caller runs an "
                "older telebot and must be upgraded"
            )
        raise ProtocolError(f"unsupported protocol version {version}")
    if kind == TYPE_DATA:
        if len(data) < DATA_HEADER_LEN + _TAG_LEN:
            raise ProtocolError("DATA frame too short")
        counter = int.from_bytes(data[10:18], "big")
        return DataFrame(call_id, counter, bytes(data[:DATA_HEADER_LEN]), bytes(data[18:]))
    if kind == TYPE_HELLO:
        return _decode_hello(data, call_id)
    if kind == TYPE_RETRY:
        if len(data) != 2 + CALL_ID_LEN + 1:
            raise ProtocolError("RETRY frame of the wrong size")
        return Retry(call_id, data[10])
    if kind == TYPE_WELCOME:
        noise_message = bytes(data[10:])
        if not noise_message or len(noise_message) > _MAX_NOISE_MESSAGE:
            raise ProtocolError("WELCOME handshake message missing or too long")
        return Welcome(call_id, noise_message)
    raise ProtocolError(f"unknown frame type {kind}")


def _decode_hello(data: bytes, call_id: bytes, version: int = VERSION) -> Hello:
    if len(data) < 11:
        raise ProtocolError("HELLO frame too short")
    name_len = data[10]
    name_end = 11 + name_len
    suite_at = name_end + INSTANCE_LEN
    if len(data) < suite_at + 2:
        raise ProtocolError("HELLO frame truncated")
    try:
        caller = validate_name(bytes(data[11:name_end]).decode("ascii"), "caller name")
    except (UnicodeDecodeError, ValueError) as exc:
        raise ProtocolError("HELLO frame with an invalid caller name") from exc
    suite, offer_len = data[suite_at], data[suite_at + 1]
    noise_start = suite_at + 2 + offer_len
    if len(data) <= noise_start:
        raise ProtocolError("HELLO frame truncated")
    offers = tuple(data[suite_at + 2 : noise_start])
    if not 1 <= offer_len <= MAX_OFFERS or len(set(offers)) != offer_len or 0 in offers:
        raise ProtocolError(f"HELLO with an invalid list of cipher suites {list(offers)}")
    if suite not in offers:
        raise ProtocolError(f"HELLO written with cipher suite {suite}, which it does not offer")
    noise_message = bytes(data[noise_start:])
    if len(noise_message) > _MAX_NOISE_MESSAGE:
        raise ProtocolError("HELLO handshake message too long")
    return Hello(
        call_id, caller, bytes(data[name_end:suite_at]), noise_message, suite, offers, version
    )


@dataclass(slots=True)
class Datagram:
    """A channel datagram: channel name and payload (``str`` if sent as text).

    Not frozen: a frozen dataclass costs several times more to build, and this one is
    built for every datagram received.
    """

    channel: str
    payload: str | bytes


@dataclass(slots=True)
class Bundle:
    """Several datagrams that travelled in one frame, in the order they were sent."""

    datagrams: list[Datagram]


@dataclass(frozen=True, slots=True)
class Heartbeat:
    """Liveness plus what the peer needs to measure round-trip time and loss.

    ``sent_us`` is the sender's clock; ``echo_us`` repeats the ``sent_us`` of the last
    heartbeat the sender received and ``echo_delay_us`` how long it held it, so the
    first side computes RTT = now - echo_us - echo_delay_us on its own clock (as RTCP).
    """

    seq: int
    sent_us: int
    echo_us: int
    echo_delay_us: int


@dataclass(frozen=True, slots=True)
class Hangup:
    """The peer ends the call."""

    reason: str


Message = Datagram | Heartbeat | Hangup | Bundle


def encode_datagram(channel_name: bytes, payload: str | bytes) -> bytes:
    """Plaintext of a DATAGRAM; raises DatagramTooLarge before anything is sent."""
    if isinstance(payload, str):
        body = payload.encode("utf-8")
        flags = FLAG_TEXT
    elif isinstance(payload, bytes | bytearray | memoryview):
        body = bytes(payload)
        flags = 0
    else:
        raise TypeError(f"a datagram is str or bytes, not {type(payload).__name__}")
    if len(body) > MAX_DATAGRAM:
        raise DatagramTooLarge(
            f"datagram of {len(body)} bytes is larger than the {MAX_DATAGRAM}-byte limit"
        )
    return bytes([KIND_DATAGRAM, flags, len(channel_name)]) + channel_name + body


def encode_bundle(datagrams: list[bytes]) -> bytes:
    """Plaintext of a BUNDLE of DATAGRAM plaintexts (from :func:`encode_datagram`).

    The caller keeps the total within :data:`MAX_BUNDLE` (:class:`Coalescer` does);
    anything over raises ValueError rather than build a frame the peer would refuse.
    """
    if len(datagrams) < 2:
        raise ValueError("a BUNDLE carries at least two datagrams")
    pack = _BUNDLE_ENTRY.pack
    parts = [bytes([KIND_BUNDLE])]
    for datagram in datagrams:
        parts.append(pack(len(datagram)))
        parts.append(datagram)
    plaintext = b"".join(parts)
    if len(plaintext) > MAX_BUNDLE:
        raise ValueError(f"BUNDLE of {len(plaintext)} bytes is over {MAX_BUNDLE}")
    return plaintext


class Coalescer:
    """Gathers DATAGRAM plaintexts into as few DATA messages as fit. Sans-IO.

    :meth:`add` each datagram as it is sent; :meth:`take` when the batch is over (the
    end of an event-loop turn) gives one message for all of them: the DATAGRAM itself
    if it is alone, else a BUNDLE. A datagram that would make the BUNDLE too large
    makes :meth:`add` hand back what was gathered before it, to be sent first.
    """

    __slots__ = ("_datagrams", "_size")

    def __init__(self) -> None:
        self._datagrams: list[bytes] = []
        self._size = 1  # the BUNDLE kind byte

    def __bool__(self) -> bool:
        return bool(self._datagrams)

    def add(self, datagram: bytes) -> bytes | None:
        """Gather ``datagram``; returns a message to send now if it did not fit, else None."""
        added = _BUNDLE_ENTRY.size + len(datagram)
        full = None
        if self._datagrams and self._size + added > MAX_BUNDLE:
            full = self.take()
        self._datagrams.append(datagram)
        self._size += added
        return full

    def take(self) -> bytes | None:
        """The message carrying everything gathered (None if nothing), and start afresh."""
        datagrams = self._datagrams
        if not datagrams:
            return None
        self._datagrams = []
        self._size = 1
        return datagrams[0] if len(datagrams) == 1 else encode_bundle(datagrams)


def encode_heartbeat(beat: Heartbeat) -> bytes:
    """Plaintext of a HEARTBEAT."""
    return _HEARTBEAT.pack(
        KIND_HEARTBEAT,
        beat.seq & 0xFFFFFFFF,
        beat.sent_us & 0xFFFFFFFFFFFFFFFF,
        beat.echo_us & 0xFFFFFFFFFFFFFFFF,
        min(max(beat.echo_delay_us, 0), 0xFFFFFFFF),
    )


def encode_hangup(reason: str) -> bytes:
    """Plaintext of a HANGUP (the reason is cut to 200 bytes, on a character boundary)."""
    cut = reason.encode("utf-8")[:200].decode("utf-8", "ignore")
    return bytes([KIND_HANGUP]) + cut.encode("utf-8")


def _decode_datagram(plaintext: bytes, start: int, end: int) -> Datagram:
    """The DATAGRAM in ``plaintext[start:end]`` (sliced once: payloads may be 32 KB)."""
    if end - start < 3:
        raise ProtocolError("DATAGRAM truncated")
    flags, name_len = plaintext[start + 1], plaintext[start + 2]
    if flags & ~FLAG_TEXT:
        raise ProtocolError(f"DATAGRAM with unknown flags {flags:#x}")
    name_end = start + 3 + name_len
    if name_len == 0 or end < name_end:
        raise ProtocolError("DATAGRAM with a missing or truncated channel name")
    if end - name_end > MAX_DATAGRAM:
        raise ProtocolError("DATAGRAM payload over the limit")
    try:
        channel = plaintext[start + 3 : name_end].decode("utf-8")
        if flags & FLAG_TEXT:
            return Datagram(channel, plaintext[name_end:end].decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ProtocolError("DATAGRAM text is not UTF-8") from exc
    return Datagram(channel, plaintext[name_end:end])


def _decode_bundle(plaintext: bytes) -> Bundle:
    """The datagrams of a BUNDLE; one bad entry makes the whole BUNDLE malformed."""
    if len(plaintext) > MAX_BUNDLE:
        raise ProtocolError("BUNDLE over the limit")
    datagrams: list[Datagram] = []
    position, total = 1, len(plaintext)
    unpack = _BUNDLE_ENTRY.unpack_from
    while position < total:
        if total - position < _BUNDLE_ENTRY.size:
            raise ProtocolError("BUNDLE entry length truncated")
        (length,) = unpack(plaintext, position)
        start = position + _BUNDLE_ENTRY.size
        end = start + length
        if end > total:
            raise ProtocolError("BUNDLE entry truncated")
        if length == 0 or plaintext[start] != KIND_DATAGRAM:
            raise ProtocolError("BUNDLE entry is not a DATAGRAM")
        datagrams.append(_decode_datagram(plaintext, start, end))
        position = end
    if len(datagrams) < 2:
        raise ProtocolError("BUNDLE with fewer than two datagrams")
    return Bundle(datagrams)


def decode_message(plaintext: bytes) -> Message:
    """Parse a DATA frame's plaintext; raise ProtocolError when malformed."""
    if not plaintext:
        raise ProtocolError("empty message")
    kind = plaintext[0]
    if kind == KIND_DATAGRAM:
        return _decode_datagram(plaintext, 0, len(plaintext))
    if kind == KIND_BUNDLE:
        return _decode_bundle(plaintext)
    if kind == KIND_HEARTBEAT:
        if len(plaintext) != _HEARTBEAT.size:
            raise ProtocolError("HEARTBEAT of the wrong size")
        _, seq, sent_us, echo_us, echo_delay_us = _HEARTBEAT.unpack(plaintext)
        return Heartbeat(seq, sent_us, echo_us, echo_delay_us)
    if kind == KIND_HANGUP:
        try:
            return Hangup(plaintext[1:].decode("utf-8"))
        except UnicodeDecodeError as exc:
            raise ProtocolError("HANGUP reason is not UTF-8") from exc
    raise ProtocolError(f"unknown message kind {kind}")
