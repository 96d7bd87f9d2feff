"""Messages of the topic relay, sans-IO: JSON control on ``relay``, fragments on ``relay/data``.

The user asks the robot for a topic by name; the robot answers with the topic's type and
schema and a *stream* number, then sends each message of the topic as CDR bytes on the
``relay/data`` channel (BULK lane), cut into the video's fragments
(:func:`telebot.services.video.wire.fragment` with codec :data:`CODEC_CDR`; the fragment's
"camera" field carries the stream number in decimal, its capture time the robot's
``time.time()`` when it had the message). Control messages (``relay`` channel, JSON text)::

    user  -> robot  {"type": "list", "id": 1}
    robot -> user   {"type": "topics", "id": 1, "part": 0, "parts": 1,
                     "topics": [{"name": "/scan", "type": "sensor_msgs/msg/LaserScan",
                                 "schema": "...", "encoding": "cdr"}, ...]}
    user  -> robot  {"type": "start", "id": 2, "topic": "/scan", "rate": 5.0,
                     "latest_only": false}
    robot -> user   {"type": "started", "id": 2, "stream": 1, "topic": {...TopicInfo...}}
    robot -> user   {"type": "refused", "id": 2, "code": "unknown_topic", "text": "...",
                     "near": ["/scan_filtered"]}
    user  -> robot  {"type": "stop", "id": 3, "stream": 1}
    robot -> user   {"type": "stopped", "id": 3, "stream": 1, "sent": 120, "dropped": 4}
    robot -> user   {"type": "ended", "stream": 1, "text": "the topic's source closed"}

A topic list longer than one datagram comes in ``parts`` parts (``part`` 0 .. parts-1).
Requests are repeated by the user until answered; the robot answers a repeat (same ``id``)
with its first answer, so nothing starts twice. Code: this module; the robot's side is
:mod:`telebot.services.relay.robot`. Specified in ``docs/protocol.md`` ("The relay channel").
"""

from __future__ import annotations

import fnmatch
import math
from dataclasses import dataclass
from typing import Any, Final

from telebot.config import RelaySettings
from telebot.errors import ProtocolError
from telebot.identity import Role
from telebot.services.messages import decode_object, encode_object, require_int
from telebot.services.video.wire import (
    CODEC_CDR,
    MAX_CAMERA_NAME,
    MAX_FRAME_BYTES,
    Reassembler,
    fragment,
)

__all__ = [
    "MAX_DATA",
    "MAX_LIST_TEXT",
    "MAX_RATE",
    "MAX_SCHEMA",
    "MAX_TOPIC_NAME",
    "RELAY",
    "RELAY_DATA",
    "ListRequest",
    "RelayEnded",
    "RelayRefusal",
    "RelayedMessage",
    "StartRequest",
    "Started",
    "StopRequest",
    "Stopped",
    "TopicInfo",
    "TopicList",
    "allowed_topic",
    "decode_relay_message",
    "encode_topic_list",
    "fragment_message",
    "relay_reassembler",
    "stream_of",
]

#: The control channel (JSON text, both ways).
RELAY: Final = "relay"
#: The data channel (binary fragments robot -> user, BULK lane).
RELAY_DATA: Final = "relay/data"
#: Longest topic or type name accepted (characters).
MAX_TOPIC_NAME: Final = 256
#: Longest schema text accepted (characters): it must fit one datagram with its list entry.
MAX_SCHEMA: Final = 24_000
#: Longest ``topics`` message the robot sends (characters); longer lists come in parts.
MAX_LIST_TEXT: Final = 30_000
#: Most parts of one topic list.
MAX_PARTS: Final = 64
#: Highest rate (messages/s) a user may ask for.
MAX_RATE: Final = 1000.0
#: Largest message relayed (bytes of CDR): the fragments' limit.
MAX_DATA: Final = MAX_FRAME_BYTES
#: Longest refusal text.
MAX_TEXT: Final = 2000
#: Most near matches in a refusal.
MAX_NEAR: Final = 10


@dataclass(frozen=True, slots=True)
class TopicInfo:
    """A topic the robot can relay.

    ``schema`` is the type's ros2msg text with its dependencies, as MCAP's ``ros2msg``
    schema encoding wants (the ``.msg`` text, then for each dependency ``"=" * 80``,
    ``MSG: pkg/Type`` and its text), ``""`` when unknown.
    """

    name: str
    type: str
    schema: str
    encoding: str = "cdr"

    def to_json(self) -> dict[str, Any]:
        """The topic as a JSON object."""
        return {
            "name": self.name,
            "type": self.type,
            "schema": self.schema,
            "encoding": self.encoding,
        }


@dataclass(frozen=True, slots=True)
class RelayedMessage:
    """One relayed message: ``data`` is CDR with its 4-byte encapsulation header, exactly
    as on the robot; ``stamp`` the robot's ``time.time()`` when it had the message."""

    topic: str
    type: str
    data: bytes
    stamp: float


@dataclass(frozen=True, slots=True)
class ListRequest:
    """The user asks for the relayable topics."""

    id: int

    def encode(self) -> str:
        """The datagram text."""
        return encode_object({"type": "list", "id": self.id})


@dataclass(frozen=True, slots=True)
class TopicList:
    """Part ``part`` of ``parts`` of the answer to list request ``id``."""

    id: int
    part: int
    parts: int
    topics: tuple[TopicInfo, ...]

    def encode(self) -> str:
        """The datagram text."""
        return encode_object(
            {
                "type": "topics",
                "id": self.id,
                "part": self.part,
                "parts": self.parts,
                "topics": [t.to_json() for t in self.topics],
            }
        )


@dataclass(frozen=True, slots=True)
class StartRequest:
    """The user asks for a relay of ``topic`` at most ``rate`` messages/s (None: as they
    come, up to the robot's cap); ``latest_only``: keep only the newest unsent message."""

    id: int
    topic: str
    rate: float | None = None
    latest_only: bool = False

    def encode(self) -> str:
        """The datagram text."""
        return encode_object(
            {
                "type": "start",
                "id": self.id,
                "topic": self.topic,
                "rate": self.rate,
                "latest_only": self.latest_only,
            }
        )


@dataclass(frozen=True, slots=True)
class Started:
    """The robot relays ``info`` as stream ``stream`` (answer to start request ``id``)."""

    id: int
    stream: int
    info: TopicInfo

    def encode(self) -> str:
        """The datagram text."""
        return encode_object(
            {"type": "started", "id": self.id, "stream": self.stream, "topic": self.info.to_json()}
        )


@dataclass(frozen=True, slots=True)
class RelayRefusal:
    """The robot refused start request ``id``: ``code`` (a reason code), ``text`` for people,
    ``near``: topics whose names are close to the one asked for."""

    id: int
    code: str
    text: str
    near: tuple[str, ...] = ()

    def encode(self) -> str:
        """The datagram text."""
        return encode_object(
            {
                "type": "refused",
                "id": self.id,
                "code": self.code,
                "text": self.text[:MAX_TEXT],
                "near": list(self.near[:MAX_NEAR]),
            }
        )


@dataclass(frozen=True, slots=True)
class StopRequest:
    """The user ends relay stream ``stream``."""

    id: int
    stream: int

    def encode(self) -> str:
        """The datagram text."""
        return encode_object({"type": "stop", "id": self.id, "stream": self.stream})


@dataclass(frozen=True, slots=True)
class Stopped:
    """The robot ended stream ``stream`` (answer to stop request ``id``): messages ``sent``
    and ``dropped`` (over the rate, the byte budget or the queue)."""

    id: int
    stream: int
    sent: int = 0
    dropped: int = 0

    def encode(self) -> str:
        """The datagram text."""
        return encode_object(
            {
                "type": "stopped",
                "id": self.id,
                "stream": self.stream,
                "sent": self.sent,
                "dropped": self.dropped,
            }
        )


@dataclass(frozen=True, slots=True)
class RelayEnded:
    """The robot ended stream ``stream`` by itself (``text`` says why)."""

    stream: int
    text: str

    def encode(self) -> str:
        """The datagram text."""
        return encode_object({"type": "ended", "stream": self.stream, "text": self.text[:MAX_TEXT]})


RelayMessage = (
    ListRequest
    | TopicList
    | StartRequest
    | Started
    | RelayRefusal
    | StopRequest
    | Stopped
    | RelayEnded
)

_WHAT = "relay message"


def _text(message: dict[str, Any], key: str, limit: int, *, empty: bool = False) -> str:
    value = message.get(key)
    if not isinstance(value, str) or len(value) > limit or (not empty and not value):
        size = "0.." if empty else "1.."
        raise ProtocolError(f"{_WHAT}: {key!r} must be text of {size}{limit} characters")
    return value


def _topic_info(value: Any) -> TopicInfo:
    if not isinstance(value, dict):
        raise ProtocolError(f"{_WHAT}: a topic must be a JSON object")
    return TopicInfo(
        name=_text(value, "name", MAX_TOPIC_NAME),
        type=_text(value, "type", MAX_TOPIC_NAME),
        schema=_text(value, "schema", MAX_SCHEMA, empty=True),
        encoding=_text(value, "encoding", 32),
    )


def decode_relay_message(payload: str | bytes) -> RelayMessage:
    """Decode one control datagram; ProtocolError says what is wrong with it."""
    message = decode_object(payload, what=_WHAT)
    kind = message.get("type")
    if kind == "ended":
        return RelayEnded(_stream(message), _text(message, "text", MAX_TEXT, empty=True))
    request_id = require_int(message, "id", what=_WHAT)
    if kind == "list":
        return ListRequest(request_id)
    if kind == "topics":
        parts = require_int(message, "parts", what=_WHAT, low=1, high=MAX_PARTS)
        part = require_int(message, "part", what=_WHAT, high=parts - 1)
        topics = message.get("topics")
        if not isinstance(topics, list):
            raise ProtocolError(f"{_WHAT}: 'topics' must be a list")
        return TopicList(request_id, part, parts, tuple(_topic_info(t) for t in topics))
    if kind == "start":
        rate = message.get("rate")
        if rate is not None and (
            isinstance(rate, bool)
            or not isinstance(rate, int | float)
            or not math.isfinite(rate)
            or not 0 < rate <= MAX_RATE
        ):
            raise ProtocolError(f"{_WHAT}: 'rate' must be null or a number in (0, {MAX_RATE:g}]")
        latest = message.get("latest_only", False)
        if not isinstance(latest, bool):
            raise ProtocolError(f"{_WHAT}: 'latest_only' must be true or false")
        return StartRequest(
            request_id,
            _text(message, "topic", MAX_TOPIC_NAME),
            None if rate is None else float(rate),
            latest,
        )
    if kind == "started":
        return Started(request_id, _stream(message), _topic_info(message.get("topic")))
    if kind == "refused":
        near = message.get("near", [])
        if not isinstance(near, list) or len(near) > MAX_NEAR:
            raise ProtocolError(f"{_WHAT}: 'near' must be a list of at most {MAX_NEAR} names")
        names = tuple(_text({"n": n}, "n", MAX_TOPIC_NAME) for n in near)
        return RelayRefusal(
            request_id,
            _text(message, "code", 64),
            _text(message, "text", MAX_TEXT, empty=True),
            names,
        )
    if kind == "stop":
        return StopRequest(request_id, _stream(message))
    if kind == "stopped":
        return Stopped(
            request_id,
            _stream(message),
            require_int(message, "sent", what=_WHAT, high=2**53 - 1),
            require_int(message, "dropped", what=_WHAT, high=2**53 - 1),
        )
    raise ProtocolError(f"{_WHAT}: unknown type {kind!r}")


def _stream(message: dict[str, Any]) -> int:
    return require_int(message, "stream", what=_WHAT, low=1, high=2**31 - 1)


def encode_topic_list(request_id: int, topics: list[TopicInfo]) -> list[str]:
    """The ``topics`` answer to list request ``request_id``, in as many datagrams as needed.

    A topic whose schema alone would not fit a datagram goes with an empty schema; topics
    beyond :data:`MAX_PARTS` parts are left out.
    """
    groups: list[list[TopicInfo]] = [[]]
    size = 0
    for info in topics:
        if len(info.schema) > MAX_SCHEMA:
            info = TopicInfo(info.name, info.type, "", info.encoding)
        entry = len(encode_object(info.to_json())) + 1
        if groups[-1] and size + entry > MAX_LIST_TEXT - 200:
            if len(groups) == MAX_PARTS:
                break
            groups.append([])
            size = 0
        groups[-1].append(info)
        size += entry
    parts = len(groups)
    return [
        TopicList(request_id, index, parts, tuple(group)).encode()
        for index, group in enumerate(groups)
    ]


def fragment_message(
    stream: int, message_id: int, stamp: float, data: bytes, *, seq: int, interval: float
) -> list[bytes]:
    """The ``relay/data`` datagrams of one message of ``stream`` (ValueError if too large)."""
    return fragment(
        message_id, str(stream), stamp, data, seq=seq, interval=interval, codec=CODEC_CDR
    )


def stream_of(camera: str) -> int | None:
    """The stream number a fragment's name field carries (None if it is not one)."""
    if not camera.isdigit() or len(camera) > MAX_CAMERA_NAME:
        return None
    value = int(camera)
    return value if 1 <= value < 2**31 else None


def relay_reassembler() -> Reassembler:
    """A reassembler of one relay stream's fragments (latest message wins)."""
    return Reassembler(codec=CODEC_CDR)


def allowed_topic(settings: RelaySettings, role: Role | None, topic: str) -> bool:
    """Whether ``role`` may relay ``topic`` by ``settings`` (globs; admins as drivers)."""
    patterns = settings.observer if role in (None, Role.OBSERVER) else settings.driver
    return any(fnmatch.fnmatchcase(topic, pattern) for pattern in patterns)
