"""Messages of the ``people`` channel (robot → user, JSON text datagrams): tracked people and
alerts about them.
::

    {"type": "people", "seq": 41, "t": 1234.5, "cams": {"navcam": 70.0, "usercam": 90.0},
     "tracks": [{"id": 3, "x": 4.02, "y": 1.5, "vx": -0.9, "vy": 0.0, "c": 0.93,
                 "src": ["camera", "laser"], "r": 2.1, "b": 0.52}, ...]}
    {"type": "alert", "seq": 7, "kind": "approaching", "id": 3,
     "text": "person approaching from the left, 2.1 m", "distance": 2.1, "bearing": 1.2}

``people``: every confirmed track (map frame: metres, metres a second), its confidence
``c`` (0 … 1), the sensors that saw it lately, and its range ``r`` (m) and bearing ``b``
(radians from the robot's heading, left positive) for marking it in the video; ``cams``
gives each camera's horizontal field of view (degrees; the cameras face the heading).
``seq`` goes up by one per message, ``t`` is the robot's clock. ``alert``: ``kind``
``approaching`` or ``screen``; each alert is sent several times with the same ``seq``
(the channel is lossy): a receiver shows it once.

Sans-IO: encoding and decoding (a one-line :class:`~telebot.errors.ProtocolError` on
anything malformed).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from telebot.errors import ProtocolError
from telebot.services.messages import (
    decode_object,
    encode_object,
    is_finite_number,
    require_int,
)

__all__ = [
    "ALERT_KINDS",
    "MAX_TRACKS",
    "PEOPLE",
    "PeopleAlertMessage",
    "PeopleUpdate",
    "TrackInfo",
    "decode_people_message",
]

#: The channel's name.
PEOPLE = "people"
#: Most tracks one message carries (about 120 bytes each: far below a datagram).
MAX_TRACKS = 100
#: Alert kinds.
ALERT_KINDS = frozenset({"approaching", "screen"})
MAX_SEQ = 2**53 - 1
MAX_TEXT = 200
_SOURCES = frozenset({"laser", "camera"})


@dataclass(frozen=True, slots=True)
class TrackInfo:
    """One tracked person as the stream carries it."""

    id: int
    x: float
    y: float
    vx: float
    vy: float
    confidence: float
    sources: tuple[str, ...]
    range: float
    bearing: float

    def to_json(self) -> dict[str, object]:
        """The track's JSON object (rounded to the millimetre / milliradian)."""
        return {
            "id": self.id,
            "x": round(self.x, 3),
            "y": round(self.y, 3),
            "vx": round(self.vx, 3),
            "vy": round(self.vy, 3),
            "c": round(self.confidence, 3),
            "src": sorted(self.sources),
            "r": round(self.range, 3),
            "b": round(self.bearing, 4),
        }


@dataclass(frozen=True, slots=True)
class PeopleUpdate:
    """The tracks at robot time ``stamp``."""

    seq: int
    stamp: float
    tracks: tuple[TrackInfo, ...]
    cameras: Mapping[str, float] = field(default_factory=dict)

    def encode(self) -> str:
        """The datagram text (at most :data:`MAX_TRACKS` tracks, nearest first)."""
        tracks = sorted(self.tracks, key=lambda t: t.range)[:MAX_TRACKS]
        return encode_object(
            {
                "type": "people",
                "seq": self.seq,
                "t": round(self.stamp, 3),
                "cams": {name: round(fov, 2) for name, fov in self.cameras.items()},
                "tracks": [t.to_json() for t in tracks],
            }
        )


@dataclass(frozen=True, slots=True)
class PeopleAlertMessage:
    """An alert (see :mod:`telebot.robot.perception.alerts`)."""

    seq: int
    kind: str
    track: int
    text: str
    distance: float
    bearing: float

    def encode(self) -> str:
        """The datagram text."""
        return encode_object(
            {
                "type": "alert",
                "seq": self.seq,
                "kind": self.kind,
                "id": self.track,
                "text": self.text[:MAX_TEXT],
                "distance": round(self.distance, 2),
                "bearing": round(self.bearing, 3),
            }
        )


def _number(message: Mapping[str, object], key: str, what: str) -> float:
    value = message.get(key)
    if not is_finite_number(value):
        raise ProtocolError(f"{what}: {key!r} must be a finite number")
    return float(value)


def _track(entry: object) -> TrackInfo:
    what = "people track"
    if not isinstance(entry, dict):
        raise ProtocolError("people: each track must be an object")
    sources = entry.get("src", [])
    if not isinstance(sources, list) or not all(s in _SOURCES for s in sources):
        raise ProtocolError("people track: 'src' must be a list of 'laser' / 'camera'")
    confidence = _number(entry, "c", what)
    if not 0.0 <= confidence <= 1.0:
        raise ProtocolError("people track: 'c' must be in 0..1")
    return TrackInfo(
        id=require_int(entry, "id", what=what, high=MAX_SEQ),
        x=_number(entry, "x", what),
        y=_number(entry, "y", what),
        vx=_number(entry, "vx", what),
        vy=_number(entry, "vy", what),
        confidence=confidence,
        sources=tuple(sources),
        range=_number(entry, "r", what),
        bearing=_number(entry, "b", what),
    )


def decode_people_message(payload: str | bytes) -> PeopleUpdate | PeopleAlertMessage:
    """Parse a ``people`` channel datagram; ProtocolError (one line) when malformed."""
    msg = decode_object(payload, what=PEOPLE)
    kind = msg.get("type")
    if kind == "people":
        tracks = msg.get("tracks")
        if not isinstance(tracks, list) or len(tracks) > MAX_TRACKS:
            raise ProtocolError(f"people: 'tracks' must be a list of at most {MAX_TRACKS}")
        cams = msg.get("cams", {})
        if not isinstance(cams, dict):
            raise ProtocolError("people: 'cams' must be an object of camera fields of view")
        cameras = {}
        for name, fov in cams.items():
            if isinstance(fov, bool) or not isinstance(fov, int | float) or not 0 < fov < 180:
                raise ProtocolError(f"people: camera {name!r} needs a field of view in (0, 180)")
            cameras[str(name)] = float(fov)
        return PeopleUpdate(
            seq=require_int(msg, "seq", what=PEOPLE, high=MAX_SEQ),
            stamp=_number(msg, "t", PEOPLE),
            tracks=tuple(_track(t) for t in tracks),
            cameras=cameras,
        )
    if kind == "alert":
        alert_kind = msg.get("kind")
        if alert_kind not in ALERT_KINDS:
            raise ProtocolError(f"people alert: unknown kind {alert_kind!r}")
        text = msg.get("text")
        if not isinstance(text, str) or not 0 < len(text) <= MAX_TEXT:
            raise ProtocolError(f"people alert: 'text' must be 1..{MAX_TEXT} characters")
        return PeopleAlertMessage(
            seq=require_int(msg, "seq", what="people alert", high=MAX_SEQ),
            kind=str(alert_kind),
            track=require_int(msg, "id", what="people alert", high=MAX_SEQ),
            text=text,
            distance=_number(msg, "distance", "people alert"),
            bearing=_number(msg, "bearing", "people alert"),
        )
    raise ProtocolError(f"people: unknown type {kind!r}")
