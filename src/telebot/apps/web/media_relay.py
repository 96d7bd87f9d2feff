"""Browser media over the web UI's websocket: message format and the relay (never transcodes).

The page (``static/media.js``) decodes the robot's H.264 / VP8 / Opus with WebCodecs and
encodes the user's camera and microphone the same way; this process only moves the encoded
bytes between the page's websocket and the call (docs/protocol.md §19).

Binary websocket message, both ways: a 4-byte big-endian header length, a UTF-8 JSON
object, then the encoded bytes::

    {"kind": "video", "codec": "h264"|"vp8"|"jpeg", "key": bool, "frame_id": u32,
     "capture_time": unix_s, "camera": str}    one encoded picture (H.264 in Annex B)
    {"kind": "audio", "seq": u32, "capture_time": unix_s}    one Opus packet, 20 ms

A header without ``kind`` is JPEG video (the web UI's first format, still sent for JPEG).
"""

from __future__ import annotations

import asyncio
import json
import logging
import struct
from collections.abc import Callable, Collection, Hashable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final, Generic, Literal, Protocol, TypeVar

from telebot.apps.web.messages import PAGE_CODECS, PAGE_DECODES, Keyframe, MediaCaps
from telebot.channels.transports.base import Lane
from telebot.errors import CallEnded, ProtocolError, TelebotError
from telebot.services.media.wire import (
    CODEC_NAMES,
    USER_MEDIA_PROBE,
    USER_VIDEO,
    AudioPacket,
    choose_codec,
    codec_id,
    parse_media_report,
)
from telebot.services.messages import is_finite_number
from telebot.services.video.wire import CompleteFrame, Report, fragment, serial_diff

if TYPE_CHECKING:
    from telebot.channels.call import Call
    from telebot.channels.channel import Channel, ReceivedDatagram
    from telebot.services.client import RobotClient

__all__ = [
    "MAX_AUDIO_PACKET",
    "MAX_HEADER",
    "MAX_PAGE_MESSAGE",
    "MAX_VIDEO_FRAME",
    "MediaMessage",
    "MediaRelay",
    "PageSink",
    "pack_media",
    "parse_media",
    "uplink_report",
]

_LEN: Final = struct.Struct(">I")
#: Longest JSON header a page may send (bytes).
MAX_HEADER: Final = 1024
#: Largest encoded picture a page may send: 2 MB (the call's largest frame).
MAX_VIDEO_FRAME: Final = 2_000_000
#: Largest Opus packet (RFC 6716: 1275 bytes per frame; a little room for framing).
MAX_AUDIO_PACKET: Final = 1500
_U32: Final = 1 << 32
#: Largest websocket message a page may send (a picture and its header).
MAX_PAGE_MESSAGE: Final = MAX_VIDEO_FRAME + 4 + MAX_HEADER
#: Video codecs a page decodes when it says nothing (the web UI's first format).
JPEG_ONLY: Final = ("jpeg",)

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class MediaMessage:
    """One parsed binary message: a video frame or an audio packet."""

    kind: Literal["video", "audio"]
    #: Video: frame_id; audio: seq (both u32, wrapping).
    number: int
    #: Unix seconds at capture, as the sender's clock says.
    capture_time: float
    data: bytes
    codec: str = ""
    key: bool = False


def pack_media(header: dict[str, Any], data: bytes) -> bytes:
    """The binary websocket message for ``header`` (a JSON object) and ``data``."""
    raw = json.dumps(header, separators=(",", ":")).encode()
    return _LEN.pack(len(raw)) + raw + data


def _u32(header: dict[str, Any], name: str) -> int:
    value = header.get(name)
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < _U32:
        raise ValueError(f"{name} must be an integer 0..2^32-1, got {value!r}")
    return value


def parse_media(message: bytes, codecs: tuple[str, ...] = PAGE_CODECS) -> MediaMessage:
    """Parse a page's binary message; ValueError (one line naming the fault) if malformed.

    ``codecs`` are the video codecs accepted (those the robot offered).
    """
    if len(message) < _LEN.size:
        raise ValueError("a media message needs a 4-byte header length")
    (length,) = _LEN.unpack_from(message)
    if not 2 <= length <= MAX_HEADER or len(message) < _LEN.size + length:
        raise ValueError(f"bad media header length {length}")
    try:
        header = json.loads(message[_LEN.size : _LEN.size + length])
    except (UnicodeDecodeError, ValueError):
        raise ValueError("the media header is not JSON") from None
    if not isinstance(header, dict):
        raise ValueError("the media header is not a JSON object")
    data = bytes(message[_LEN.size + length :])
    capture = header.get("capture_time")
    if isinstance(capture, bool) or not isinstance(capture, int | float):
        raise ValueError(f"capture_time must be a number, got {capture!r}")
    if not is_finite_number(capture) or capture < 0:
        raise ValueError(f"capture_time must be finite and >= 0, got {capture!r}")
    kind = header.get("kind")
    if kind == "video":
        codec = header.get("codec")
        if codec not in codecs:
            raise ValueError(f"video codec {codec!r} not offered (offered: {', '.join(codecs)})")
        key = header.get("key")
        if not isinstance(key, bool):
            raise ValueError(f"key must be true or false, got {key!r}")
        if not 0 < len(data) <= MAX_VIDEO_FRAME:
            raise ValueError(f"a video frame must be 1..{MAX_VIDEO_FRAME} bytes, got {len(data)}")
        return MediaMessage("video", _u32(header, "frame_id"), float(capture), data, codec, key)
    if kind == "audio":
        if not 0 < len(data) <= MAX_AUDIO_PACKET:
            raise ValueError(f"an Opus packet must be 1..{MAX_AUDIO_PACKET} bytes, got {len(data)}")
        return MediaMessage("audio", _u32(header, "seq"), float(capture), data, "opus")
    raise ValueError(f"unknown media kind {kind!r} (video or audio)")


# --------------------------------------------------------------------------- the relay


def video_header(frame: CompleteFrame) -> dict[str, Any]:
    """The websocket header of one of the robot's pictures."""
    return {
        "kind": "video",
        "codec": CODEC_NAMES.get(frame.codec, "jpeg"),
        "key": frame.keyframe,
        "camera": frame.camera,
        "frame_id": frame.frame_id,
        "capture_time": frame.capture_time,
    }


def uplink_report(report: Report) -> dict[str, Any]:
    """The page's ``uplink_report`` message: the counters of one of the robot's REPORTs on
    ``video/user`` (§17.2 names), which the page's camera encoder adapts its bit rate to."""
    return {
        "type": "uplink_report",
        "receiver_ms": report.receiver_ms,
        "highest_seq": report.highest_seq,
        "fragments": report.fragments,
        "bytes": report.data_bytes,
        "frames": report.frames,
        "dropped": report.dropped,
        "queue_delay_ms": report.queue_delay_ms,
    }


#: The robot stops asking for the user's camera this long after its last report (s).
IDLE_AFTER: Final = 2.0
#: A keyframe request of the robot is passed on to the page at most this often (s).
KEY_GAP: Final = 0.3


class _Uplink:
    """The user's camera to the robot: the page's encoded pictures, fragmented on
    ``video/user`` while the robot's reports ask for them (never decoded here), and, before
    the call's first report, for :data:`USER_MEDIA_PROBE` s from the first picture (the
    robot asks only once pictures came)."""

    def __init__(self, relay: MediaRelay[Any]) -> None:
        self.relay = relay
        self.call: Call | None = None
        self.channel: Channel | None = None
        self.seq = 0
        #: The next frame id on the wire: +1 per page picture taken while the robot asks,
        #: sent or not, so a picture that did not go out is a gap the robot sees.
        self.frame_id = 0
        self.last_report: float | None = None
        self.last_report_ms: int | None = None
        self.probe_from: float | None = None
        self.bye = False
        #: The robot's codec list, best first (empty: none yet).
        self.codecs: tuple[int, ...] = ()
        self.keys_asked_at: float | None = None
        self.sent = 0
        self.dropped = 0

    def bind(self, call: Call) -> None:
        """Follow the client's current call (a reconnection brings a new one)."""
        if call is self.call:
            return
        if self.channel is not None:
            self.channel.set_callback(None)
        self.call = call
        self.channel = call.channel(USER_VIDEO, lane=Lane.BULK)
        self.channel.set_callback(self._on_report)
        self.last_report = self.last_report_ms = self.probe_from = None
        self.codecs = ()

    def wanted(self, now: float) -> bool:
        """Whether the robot asks for the user's camera now (or has not been offered it)."""
        at = self.last_report
        if at is None:
            return self.probe_from is None or now - self.probe_from <= USER_MEDIA_PROBE
        return not self.bye and now - at <= IDLE_AFTER

    def _on_report(self, datagram: ReceivedDatagram) -> None:
        try:
            report = parse_media_report(datagram.payload)
        except ProtocolError:
            return
        if (
            self.last_report_ms is not None
            and serial_diff(report.receiver_ms, self.last_report_ms) < 0
        ):
            return  # reordered: an older report must not undo a bye
        loop = asyncio.get_running_loop()
        was = self.wanted(loop.time())
        self.last_report, self.last_report_ms = loop.time(), report.receiver_ms
        self.bye = report.bye
        codecs_changed = report.codecs != self.codecs
        self.codecs = report.codecs
        if was != self.wanted(loop.time()) or codecs_changed:
            self.relay.tell_pages()
        if not report.bye:
            self.relay.pass_report(report)
        if report.keyframe:
            now = loop.time()
            rtt = self.call.stats.rtt if self.call is not None else None
            if self.keys_asked_at is None or now - self.keys_asked_at >= max(KEY_GAP, rtt or 0):
                self.keys_asked_at = now
                self.relay.ask_page_keyframe()

    def send(self, codec: str, key: bool, capture_time: float, data: bytes) -> bool:
        """Fragment one page picture onto the call; False when not sent (not wanted, no room)."""
        channel = self.channel
        now = asyncio.get_running_loop().time()
        if channel is None or not self.wanted(now):
            return False
        if self.last_report is None and self.probe_from is None:
            self.probe_from = now  # the first picture offered on this call, unasked
        frame_id = self.frame_id
        self.frame_id = (frame_id + 1) % _U32
        try:
            datagrams = fragment(
                frame_id,
                "user",
                capture_time,
                data,
                seq=self.seq,
                codec=codec_id(codec),
                keyframe=key,
            )
        except ValueError as exc:
            self.dropped += 1
            log.debug("page picture not sent: %s", exc)
            return False
        try:
            for datagram in datagrams:
                channel.send(datagram)
        except CallEnded:
            return False
        except TelebotError as exc:
            log.debug("page picture not sent: %s", exc)
            self.dropped += 1
            return False
        finally:
            self.seq = (self.seq + len(datagrams)) % _U32
        self.sent += 1
        return True


#: A page, as the page server knows it (the relay only tells pages apart).
P = TypeVar("P", bound=Hashable)


class PageSink(Protocol[P]):
    """What the relay needs of the page server (:class:`~telebot.apps.web.server.WebUI`):
    the open pages and the ways to reach them."""

    @property
    def pages(self) -> Collection[P]:
        """The pages open now."""
        ...

    def send(self, page: P, message: dict[str, Any]) -> None:
        """A JSON text message to ``page``."""
        ...

    def broadcast_audio(self, data: bytes) -> None:
        """A binary audio message to every page (small, in order)."""
        ...

    def codecs_changed(self) -> None:
        """What the pages decode changed (:meth:`MediaRelay.codecs`): ask the robot again."""
        ...


class MediaRelay(Generic[P]):
    """The web UI's media: the robot's video and voice to the pages, the page's camera and
    microphone to the robot, as encoded bytes (never decoded or re-encoded here).

    ``sink`` is the page server; ``client`` the call's client (its current call, video
    feed and media). One page at a time sends the user's camera and microphone (the
    first that can; the next when it closes): a user with two tabs open is one user to
    the robot.
    """

    def __init__(self, sink: PageSink[P], client: RobotClient) -> None:
        self.sink = sink
        self.client = client
        #: What each open page decodes and encodes (from its ``media`` message).
        self.decode: dict[P, tuple[str, ...]] = {}
        self.encode: dict[P, tuple[str, ...]] = {}
        #: The page whose camera and microphone go to the robot.
        self.sender: P | None = None
        self.uplink = _Uplink(self)
        #: Page messages dropped as malformed (each page is told once per kind of fault).
        self.malformed = 0
        self.audio_sent = 0
        self._audio_unsub: Callable[[], None] | None = None
        self._told: dict[P, dict[str, Any]] = {}

    # -- what the pages can do

    def codecs(self) -> tuple[int, ...]:
        """Video codecs every open page decodes, best first.

        A page that has not said yet (it says so right after it connects) does not count,
        so a page opening does not switch the others to JPEG for a moment; JPEG while no
        page has said anything.
        """
        lists = [self.decode[page] for page in self.sink.pages if page in self.decode]
        lists = lists or [JPEG_ONLY]
        common = [c for c in lists[0] if all(c in other for other in lists[1:])]
        ids = [codec_id(c) for c in common if c in PAGE_DECODES]
        return tuple(ids) or (codec_id("jpeg"),)

    def page_opened(self, page: P) -> None:
        """A page connected: start hearing the robot (its voice goes to every page)."""
        if self._audio_unsub is None:
            self._audio_unsub = self.client.media.subscribe_audio(self._on_robot_audio)

    def page_closed(self, page: P) -> None:
        """A page went away: forget it; another page may take over the camera."""
        self.decode.pop(page, None)
        self.encode.pop(page, None)
        self._told.pop(page, None)
        if self.sender is page:
            self.sender = None
            self.tell_pages()
        if not self.sink.pages and self._audio_unsub is not None:
            self._audio_unsub()
            self._audio_unsub = None
        self.sink.codecs_changed()

    def close(self) -> None:
        """The web UI closes."""
        if self._audio_unsub is not None:
            self._audio_unsub()
            self._audio_unsub = None
        if self.uplink.channel is not None:
            self.uplink.channel.set_callback(None)

    # -- page -> relay

    def on_message(self, page: P, msg: MediaCaps | Keyframe) -> None:
        """A media text message from ``page``."""
        if isinstance(msg, Keyframe):
            self.client.video_feed.request_keyframe()
            return
        self.decode[page] = msg.decode or JPEG_ONLY
        self.encode[page] = msg.encode
        self.sink.codecs_changed()
        self.tell_pages()

    def on_binary(self, page: P, data: bytes) -> None:
        """A binary message (the user's camera or microphone) from ``page``."""
        codecs = self.encode.get(page, PAGE_CODECS)
        try:
            msg = parse_media(data, codecs)
        except ValueError as exc:
            self.malformed += 1
            self.sink.send(page, {"type": "error", "text": f"media dropped: {exc}"})
            return
        if page is not self.sender:
            return  # another tab sends the camera; this one's is not wanted
        self.uplink.bind(self.client.call)
        if msg.kind == "video":
            self.uplink.send(msg.codec, msg.key, msg.capture_time, msg.data)
            return
        # The current call's media service owns audio/user (its sender's numbering and
        # the robot's reports); the page's Opus packets go out through it as they are.
        try:
            if self.client.media.send_audio(msg.data, msg.capture_time):
                self.audio_sent += 1
        except TelebotError as exc:
            log.debug("page audio not sent: %s", exc)

    # -- relay -> pages

    def tell_pages(self) -> None:
        """Tell each page whether to send its camera and microphone, and in which codec."""
        pages = self.sink.pages
        if self.sender is not None and self.sender not in pages:
            self.sender = None
        if self.sender is None:
            self.sender = next((p for p in pages if self.encode.get(p)), None)
        for page in list(pages):
            if page not in self.encode:
                continue  # it has not said what it can do yet
            message = self._media_message(page)
            if self._told.get(page) != message:
                self._told[page] = message
                self.sink.send(page, message)

    def _media_message(self, page: P) -> dict[str, Any]:
        if page is not self.sender:
            note = (
                "another page of this call sends your camera and microphone"
                if self.encode.get(page)
                else "this browser cannot send your camera or microphone (it has no "
                "WebCodecs): the call goes on without them"
            )
            return {"type": "media", "send": False, "codec": "", "note": note}
        robot = self.uplink.codecs
        mine = tuple(codec_id(c) for c in self.encode[page])
        chosen = choose_codec(robot, mine) if robot else mine[0]
        if chosen is None:
            return {
                "type": "media",
                "send": False,
                "codec": "",
                "note": "the robot decodes none of the video codecs this browser encodes",
            }
        return {"type": "media", "send": True, "codec": CODEC_NAMES[chosen], "note": ""}

    def pass_report(self, report: Report) -> None:
        """A robot's REPORT on the user's camera: to the sending page, whose encoder's bit
        rate follows it (static/uplink-rate.js)."""
        if self.sender is not None:
            self.sink.send(self.sender, uplink_report(report))

    def ask_page_keyframe(self) -> None:
        """The robot lost a picture of the user's camera: the sending page makes a keyframe."""
        if self.sender is not None:
            self.sink.send(self.sender, {"type": "keyframe_request"})

    def _on_robot_audio(self, packets: list[AudioPacket | None]) -> None:
        for packet in packets:
            if packet is None:
                continue  # lost: the page's jitter buffer conceals it
            header = {"kind": "audio", "seq": packet.seq, "capture_time": packet.capture_time}
            self.sink.broadcast_audio(pack_media(header, packet.data))
