"""Messages of the ``safety`` channel (CONTROL lane, JSON text datagrams).

User → robot, repeated (same ``id``) until acknowledged, so loss cannot eat a stop::

    {"type": "stop", "id": 7, "how": "button"}   anyone; never refused; idempotent
    {"type": "arm", "id": 8}         re-arm after a stop (the drive holder)
    {"type": "take", "id": 9}        take the drive (free, or an admin's takeover)
    {"type": "release", "id": 10}    give the drive up (the robot stops)

Robot → user: ``{"type": "ack", "id": 7, "ok": true, "reason": "", "code": "ok"}`` for each
request (``reason``: the text for people; ``code``: the reason code of
:mod:`~telebot.reasons`)
(again for each repeat), and the safety state on every change and once a second::

    {"type": "state", "armed": false, "reason": "stop requested by alice",
     "code": "stopped", "holder": "alice", "cap": 0.0, "blocked": false}

(``code``: the reason code of the latest stop, ``ok`` while armed; ``link_silent`` when the
deadman stopped the robot, ``video_stale`` for a frozen picture, …: see :class:`SafetyStatus`.)

A request's ``id`` is an integer in 0 … 2³² − 1, the client's own per call and per channel (it
does not share a number space with chat or goal ids). A request that does not decode (not
JSON, an unknown ``type``, an ``id`` that is not such an integer) is answered with one error
line instead of an ack, and a ``stop`` among them is still carried out (when in doubt, stop)::

    {"type": "error", "ok": false, "reason": "safety: 'id' must be an integer in 0..4294967295", "code": "invalid"}
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Literal, cast

from telebot.errors import ProtocolError, excerpt
from telebot.reasons import decode_code
from telebot.services.messages import (
    decode_object,
    encode_object,
    finite_number,
    require_int,
)

__all__ = [
    "LATCHED",
    "SAFETY",
    "SELF_STOPS",
    "STOP_HOWS",
    "InvalidSafetyRequest",
    "SafetyAck",
    "SafetyError",
    "SafetyRequest",
    "SafetyStatus",
    "decode_safety_reply",
    "decode_safety_request",
    "latched_text",
]

#: The channel's name.
SAFETY = "safety"

#: Safety state codes of the robot stopping itself, not of someone's stop: the holder's
#: link went silent (the deadman), its video froze while the robot moved, its call dropped.
SELF_STOPS = frozenset({"link_silent", "video_stale", "dropped"})

#: The robot's state, as chat ``status`` and ``telebot-user where`` say it, while it is
#: stopped and latched (it stays stopped until the drive holder re-arms it).
LATCHED = "stopped (latched: re-arm with arm)"


def latched_text(reason: str) -> str:
    """The robot's state while stopped and latched, with who or what stopped it
    (``reason``: the safety state's, e.g. "stop requested by alice (key)")."""
    return f"{LATCHED}: {reason}" if reason else LATCHED


RequestType = Literal["stop", "arm", "take", "release"]
_REQUEST_TYPES = ("stop", "arm", "take", "release")
#: Longest piece of a peer's input an error text quotes (characters).
_QUOTE = 40

#: How a user stopped the robot (a stop's ``how``), for the audit log and the stop reason.
STOP_HOWS: dict[str, str] = {
    "button": "a STOP button (the web UI's)",
    "key": "a key pressed while the robot moved (the chat prompt, the web page)",
    "tab_closed": "the web page closed, or went silent, while the robot might move",
    "page_hidden": "the web page was hidden or frozen (another tab, the phone locked) while the robot might move",
    "touch": "touched the web page's video while the robot moved",
    "exit": "the user's client quit while the robot moved",
    "api": "a program through the client library",
}
# A stop is never dropped for its ``how``: one that is not a short word is just unknown.
_HOW = re.compile(r"[a-z][a-z0-9_]{0,31}")


@dataclass(frozen=True, slots=True)
class SafetyRequest:
    """A user's stop, re-arm or drive hand-over request.

    ``how`` (stops only) says how the user stopped: a key of :data:`STOP_HOWS`, or ``""``.
    """

    type: RequestType
    id: int
    how: str = ""

    def encode(self) -> str:
        """The datagram text."""
        message: dict[str, Any] = {"type": self.type, "id": self.id}
        if self.type == "stop" and self.how:
            message["how"] = self.how
        return encode_object(message)


@dataclass(frozen=True, slots=True)
class SafetyAck:
    """The robot's answer to request ``id``.

    ``text`` says why in words (the wire's ``reason`` field); ``code`` is the stable code
    to decide on (the wire's ``code``, see :class:`~telebot.reasons.Reason`).
    """

    id: int
    ok: bool
    text: str = ""
    code: str = ""

    def encode(self) -> str:
        """The datagram text."""
        return encode_object(
            {"type": "ack", "id": self.id, "ok": self.ok, "reason": self.text, "code": self.code}
        )


@dataclass(frozen=True, slots=True)
class SafetyError:
    """The robot's answer to a request that does not decode (it has no valid ``id`` to ack).

    ``text`` says what was wrong in one line (the wire's ``reason``); ``code`` is the code
    (the wire's ``code``, ``invalid``).
    """

    text: str
    code: str

    def encode(self) -> str:
        """The datagram text."""
        return encode_object({"type": "error", "ok": False, "reason": self.text, "code": self.code})


class InvalidSafetyRequest(ProtocolError):
    """A ``safety`` request that does not decode; :attr:`stop` says it asked for a stop.

    A stop is carried out even then (with :attr:`how` if that much was valid): when in
    doubt, stop.
    """

    def __init__(self, message: str, *, stop: bool = False, how: str = "") -> None:
        super().__init__(message)
        self.stop = stop
        self.how = how


@dataclass(frozen=True, slots=True)
class SafetyStatus:
    """The supervisor's state as the users see it.

    ``code`` is the reason code of the latest stop (``ok`` while armed; ``""`` from a robot
    older than the field): ``link_silent`` (the deadman), ``video_stale``, ``dropped``
    (the holder's call dropped) are the robot stopping itself, which the holder undoes
    with one re-arm; ``stopped`` is someone's stop (see :data:`SELF_STOPS`).
    """

    armed: bool
    #: Why the robot was last stopped, in words (the wire's ``reason``; empty while armed).
    text: str
    holder: str | None
    cap: float
    blocked: bool
    code: str = ""

    @property
    def stopped_itself(self) -> bool:
        """Whether the robot is stopped because it stopped itself (a silent link, a frozen
        picture, a dropped call): a re-arm by the holder is all it takes to drive on."""
        return not self.armed and self.code in SELF_STOPS

    def encode(self) -> str:
        """The datagram text."""
        return encode_object(
            {
                "type": "state",
                "armed": self.armed,
                "reason": self.text,
                "code": self.code,
                "holder": self.holder,
                "cap": round(self.cap, 3),
                "blocked": self.blocked,
            }
        )


def decode_safety_request(payload: str | bytes) -> SafetyRequest:
    """Parse a user → robot ``safety`` datagram.

    Raises :class:`InvalidSafetyRequest` (one line, quoting at most a few dozen characters
    of the input) when malformed.
    """
    try:
        msg = decode_object(payload, what="safety")
    except ProtocolError as exc:
        raise InvalidSafetyRequest(str(exc)) from None
    kind = msg.get("type")
    if kind not in _REQUEST_TYPES:
        raise InvalidSafetyRequest(
            f"safety: unknown type {_quote(kind)}: stop, arm, take or release"
        )
    how = msg.get("how", "")
    if kind != "stop" or not isinstance(how, str) or not _HOW.fullmatch(how):
        how = ""  # never a reason to drop a stop
    try:
        request_id = require_int(msg, "id", what="safety")
    except ProtocolError as exc:
        raise InvalidSafetyRequest(str(exc), stop=kind == "stop", how=how) from None
    return SafetyRequest(cast(RequestType, kind), request_id, how)


def _quote(value: object) -> str:
    """``repr(value)``, cut to a few dozen characters: an error never echoes big input back."""
    return excerpt(repr(value), _QUOTE)


def decode_safety_reply(payload: str | bytes) -> SafetyAck | SafetyStatus | SafetyError:
    """Parse a robot → user ``safety`` datagram; ProtocolError when malformed."""
    msg = decode_object(payload, what="safety")
    kind = msg.get("type")
    if kind == "ack":
        return SafetyAck(
            require_int(msg, "id", what="safety"),
            _bool(msg, "ok"),
            _text(msg, "reason"),
            decode_code(msg, what="safety"),
        )
    if kind == "state":
        holder = msg.get("holder")
        if holder is not None and not isinstance(holder, str):
            raise ProtocolError("safety: 'holder' must be text or null")
        return SafetyStatus(
            _bool(msg, "armed"),
            _text(msg, "reason"),
            holder,
            finite_number(msg, "cap", what="safety"),
            _bool(msg, "blocked"),
            decode_code(msg, what="safety"),
        )
    if kind == "error":
        return SafetyError(_text(msg, "reason"), decode_code(msg, what="safety"))
    raise ProtocolError(f"safety: unknown type {_quote(kind)}")


def _bool(msg: dict[str, Any], key: str) -> bool:
    value = msg.get(key)
    if not isinstance(value, bool):
        raise ProtocolError(f"safety: {key!r} must be true or false")
    return value


def _text(msg: dict[str, Any], key: str) -> str:
    value = msg.get(key, "")
    if not isinstance(value, str):
        raise ProtocolError(f"safety: {key!r} must be text")
    return value
