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

import json
import math
import struct
from dataclasses import dataclass
from typing import Any, Final, Literal

__all__ = [
    "MAX_AUDIO_PACKET",
    "MAX_HEADER",
    "MAX_VIDEO_FRAME",
    "PAGE_CODECS",
    "MediaMessage",
    "pack_media",
    "parse_media",
]

_LEN: Final = struct.Struct(">I")
#: Longest JSON header a page may send (bytes).
MAX_HEADER: Final = 1024
#: Largest encoded picture a page may send: 2 MB (the call's largest frame).
MAX_VIDEO_FRAME: Final = 2_000_000
#: Largest Opus packet (RFC 6716: 1275 bytes per frame; a little room for framing).
MAX_AUDIO_PACKET: Final = 1500
#: Codecs a page may send its camera in (what WebCodecs encodes; never JPEG).
PAGE_CODECS: Final = ("vp8", "h264")
_U32: Final = 1 << 32


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
    if not math.isfinite(capture) or capture < 0:
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
