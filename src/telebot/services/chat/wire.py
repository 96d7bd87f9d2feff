"""The chat channel, sans-IO: the paper's text commands (Table I) and their message format.

Parsing turns one line a person typed into one command event (h11 style: a frozen, slotted
dataclass per command, handled with ``match``)::

    >>> parse_command("  FWD 2 ")
    Forward(metres=2.0)
    >>> parse_command("turn -45")
    Turn(degrees_right=-45.0)

A line that is not a command raises :class:`CommandError`, whose message is the exact reply
the robot sends back: ``"unknown command 'xyz' — try help"`` or the command's usage line.

Messages are JSON text datagrams (see ``docs/protocol.md``)::

    user → robot   {"id": 7, "text": "fwd 2"}
    robot → user   {"id": 7, "seq": 0, "text": "Forward command received", "final": false,
                    "ok": true, "code": "accepted"}
    robot → user   {"id": 7, "seq": 1, "text": "finished moving", "final": true, "ok": true,
                    "code": "finished"}

Conventions: ``goto X Y [YAW]`` is in the map frame with ``YAW`` in degrees counter-clockwise
(ROS REP-103), while ``turn X`` keeps the paper's convention, degrees positive to the right.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any, TypeAlias

from telebot.errors import ProtocolError
from telebot.reasons import Reason, decode_code
from telebot.services.messages import decode_object, encode_object, require_int

__all__ = [
    "CHAT",
    "HELP_TEXT",
    "MAX_FORWARD_M",
    "MAX_REPLY_TEXT",
    "MAX_REQUEST_TEXT",
    "MAX_TURN_DEG",
    "USAGE",
    "Arm",
    "BatteryQuery",
    "Cancel",
    "ChatReply",
    "ChatRequest",
    "Command",
    "CommandError",
    "Follow",
    "Forward",
    "GetMap",
    "GotoPlace",
    "GotoPoint",
    "Help",
    "Left",
    "NavCam",
    "Places",
    "ReleaseDrive",
    "Right",
    "Status",
    "Stop",
    "TakeDrive",
    "Topics",
    "Turn",
    "Unfollow",
    "UserCam",
    "Where",
    "decode_reply",
    "decode_request",
    "encode_request",
    "parse_command",
]

#: The chat channel's name (both ends open it by this name).
CHAT = "chat"

#: Longest command text a request may carry (characters): a typed line, not a document.
MAX_REQUEST_TEXT = 1000
#: Longest reply text (characters). At most 4 UTF-8 bytes a character, a reply stays well
#: inside a 32 KB datagram; the robot shortens longer texts (a huge places list) with "…".
MAX_REPLY_TEXT = 4000
#: Largest ``fwd`` distance (metres) and ``turn`` angle (degrees) the parser accepts.
MAX_FORWARD_M = 100.0
MAX_TURN_DEG = 360.0


class CommandError(ProtocolError):
    """A chat line that is not a valid command; ``str(exc)`` is the exact reply text.

    ``code`` is the reply's code: :attr:`Reason.USAGE` for bad arguments (the text is the
    usage line), :attr:`Reason.UNKNOWN_COMMAND` for an unknown word or an empty line.
    """

    def __init__(self, text: str, code: Reason = Reason.USAGE) -> None:
        super().__init__(text)
        self.code = code


# ---------------------------------------------------------------------------- commands


@dataclass(frozen=True, slots=True)
class GotoPlace:
    """``goto N``: drive to the named place ``N`` (as typed; the robot matches any case)."""

    name: str


@dataclass(frozen=True, slots=True)
class GotoPoint:
    """``goto X Y [YAW]``: drive to a map-frame point (metres), then face ``yaw_deg``.

    ``yaw_deg`` is in degrees counter-clockwise from the map's x axis (REP-103), or ``None``
    to arrive with any heading.
    """

    x: float
    y: float
    yaw_deg: float | None = None


@dataclass(frozen=True, slots=True)
class GetMap:
    """``getmap``: send the map (the transfer runs on the ``map`` channel)."""


@dataclass(frozen=True, slots=True)
class Where:
    """``where?``: report the robot's pose in the map frame."""


@dataclass(frozen=True, slots=True)
class Forward:
    """``fwd X``: drive straight ``metres`` (negative: backwards)."""

    metres: float


@dataclass(frozen=True, slots=True)
class Turn:
    """``turn X``: turn on the spot by ``degrees_right`` (the paper's sign: positive right)."""

    degrees_right: float


@dataclass(frozen=True, slots=True)
class Left:
    """``left``: turn 90° to the left."""


@dataclass(frozen=True, slots=True)
class Right:
    """``right``: turn 90° to the right."""


@dataclass(frozen=True, slots=True)
class NavCam:
    """``navcam``: select the navigation camera."""


@dataclass(frozen=True, slots=True)
class UserCam:
    """``usercam``: select the user-interaction camera."""


@dataclass(frozen=True, slots=True)
class Stop:
    """``stop``: stop now (any participant may)."""


@dataclass(frozen=True, slots=True)
class Cancel:
    """``cancel``: cancel the running goal."""


@dataclass(frozen=True, slots=True)
class Arm:
    """``arm``: re-arm the robot after a stop (the driver holding the drive only)."""


@dataclass(frozen=True, slots=True)
class TakeDrive:
    """``take``: take the drive (a driver when nobody holds it; an admin always)."""


@dataclass(frozen=True, slots=True)
class ReleaseDrive:
    """``release``: give the drive up (the robot stops)."""


@dataclass(frozen=True, slots=True)
class Follow:
    """``follow`` (the nearest person in front) or ``follow ID`` (a tracked person's id)."""

    target: int | None = None


@dataclass(frozen=True, slots=True)
class Unfollow:
    """``unfollow``: stop following (the robot stops)."""


@dataclass(frozen=True, slots=True)
class Places:
    """``places``: list the named places with their coordinates."""


@dataclass(frozen=True, slots=True)
class Topics:
    """``topics``: list the robot topics the caller may relay (the ``relay`` service)."""


@dataclass(frozen=True, slots=True)
class Status:
    """``status``: what the robot is doing, and how far the goal has got."""


@dataclass(frozen=True, slots=True)
class BatteryQuery:
    """``battery``: the battery charge."""


@dataclass(frozen=True, slots=True)
class Help:
    """``help`` (all commands) or ``help CMD`` (``topic``: the canonical name of one)."""

    topic: str | None = None


#: Any chat command.
Command: TypeAlias = (
    GotoPlace
    | GotoPoint
    | GetMap
    | Where
    | Forward
    | Turn
    | Left
    | Right
    | NavCam
    | UserCam
    | Stop
    | Cancel
    | Arm
    | TakeDrive
    | ReleaseDrive
    | Follow
    | Unfollow
    | Places
    | Topics
    | Status
    | BatteryQuery
    | Help
)

# ---------------------------------------------------------------------------- usage

#: The usage line of every command, by canonical name (the first word of Table I's form).
USAGE: dict[str, str] = {
    "goto": (
        "usage: goto N — drive to the place N (see places); "
        "goto X Y [YAW] — drive to the map point X Y (metres), facing YAW degrees "
        "(counter-clockwise)"
    ),
    "getmap": "usage: getmap — send the map",
    "where?": "usage: where? — report the robot's position and heading on the map",
    "fwd": (f"usage: fwd X — drive X metres forward (negative: back), at most {MAX_FORWARD_M:g} m"),
    "turn": (f"usage: turn X — turn X degrees, positive to the right, at most {MAX_TURN_DEG:g}°"),
    "left": "usage: left — turn 90° to the left",
    "right": "usage: right — turn 90° to the right",
    "navcam": "usage: navcam — select the navigation camera",
    "usercam": "usage: usercam — select the user-interaction camera",
    "stop": "usage: stop — stop the robot now",
    "cancel": "usage: cancel — cancel the running goal",
    "arm": "usage: arm — re-arm the robot after a stop (the driver holding the drive)",
    "take": "usage: take — take the drive (if free; an admin takes it over)",
    "release": "usage: release — give the drive up (the robot stops)",
    "follow": (
        "usage: follow [ID] — follow the nearest person in front, or the tracked person ID, "
        "at walking pace (unfollow or stop ends it)"
    ),
    "unfollow": "usage: unfollow — stop following (the robot stops)",
    "places": "usage: places — list the named places",
    "topics": "usage: topics — list the robot topics you may relay",
    "status": "usage: status — what the robot is doing",
    "battery": "usage: battery — the battery charge",
    "help": "usage: help [COMMAND] — list the commands, or explain one",
}

#: The reply to ``help``: every command on its own line.
HELP_TEXT = "commands (any case):\n" + "\n".join(
    "  " + line.removeprefix("usage: ") for line in USAGE.values()
)

# Every accepted spelling of a command word → its canonical name. Two-word spellings
# ("go to", "get map") are joined before the lookup.
_ALIASES: dict[str, str] = {
    "goto": "goto",
    "go to": "goto",
    "navigate": "goto",
    "getmap": "getmap",
    "get map": "getmap",
    "map": "getmap",
    "where": "where?",
    "pose": "where?",
    "fwd": "fwd",
    "forward": "fwd",
    "back": "back",
    "backward": "back",
    "backwards": "back",
    "turn": "turn",
    "rotate": "turn",
    "left": "left",
    "right": "right",
    "navcam": "navcam",
    "nav cam": "navcam",
    "usercam": "usercam",
    "user cam": "usercam",
    "stop": "stop",
    "halt": "stop",
    "cancel": "cancel",
    "abort": "cancel",
    "arm": "arm",
    "rearm": "arm",
    "re-arm": "arm",
    "take": "take",
    "take drive": "take",
    "take over": "take",
    "release": "release",
    "release drive": "release",
    "follow": "follow",
    "follow me": "follow",
    "unfollow": "unfollow",
    "stop following": "unfollow",
    "places": "places",
    "topics": "topics",
    "rostopic list": "topics",
    "status": "status",
    "battery": "battery",
    "help": "help",
    "?": "help",
    "commands": "help",
}

# Plain decimal numbers only: Python's float() would also take "nan", "1_0" or "١٢".
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
_WHERE_QUESTIONS = (["am", "i"], ["are", "you"], ["is", "the", "robot"])
_METRES = ("m", "metre", "metres", "meter", "meters")
_DEGREES = ("°", "deg", "degs", "degree", "degrees")
# A long unknown word is echoed shortened: the reply is for a person, not a hex dump.
_ECHO_MAX = 32


# ---------------------------------------------------------------------------- parsing


def parse_command(text: str) -> Command:
    """The command in one chat line; raises :class:`CommandError` with the reply text.

    Forgiving: any case, spaces anywhere, ``where?``/``where``/``where am i``, aliases
    (``forward``, ``go to``, ``back X``, ``turn left``), units (``fwd 2m``, ``turn 90°``).
    Numbers must be finite and within the command's limit, else the usage line.
    """
    # "−" (U+2212) is what phones and word processors put in front of numbers.
    words = text.replace("\u2212", "-").lower().split()
    if not words:
        raise CommandError("empty command — try help", Reason.UNKNOWN_COMMAND)
    word, args = words[0], words[1:]
    # "where?", "status?", and above all "STOP!!" (someone typing in a hurry).
    word = word.rstrip("?!.") or word
    if args and f"{word} {args[0]}" in _ALIASES:
        word, args = f"{word} {args[0]}", args[1:]
    name = _ALIASES.get(word)
    if name is None:
        raise CommandError(_unknown(text.split()[0]), Reason.UNKNOWN_COMMAND)  # as typed
    match name:
        case "goto":
            return _goto(_original_args(text, len(words) - len(args)))
        case "fwd":
            return Forward(_forward_metres(args, "fwd"))
        case "back":
            return Forward(-abs(_forward_metres(args, "fwd")))
        case "turn":
            if args in (["left"], ["right"]):
                return Left() if args[0] == "left" else Right()
            degrees = _number(args, _DEGREES, "turn")
            if abs(degrees) > MAX_TURN_DEG:
                raise CommandError(USAGE["turn"])
            return Turn(degrees)
        case "where?":
            # Only the questions that ask for the robot: "where lab" wants something else.
            if args and [arg.rstrip("?") for arg in args] not in _WHERE_QUESTIONS:
                raise CommandError(USAGE["where?"])
            return Where()
        case "help":
            return _help(args)
        case "follow":
            return _follow(args)
        case _:
            if args:
                raise CommandError(USAGE[name])
            return _SIMPLE[name]


_SIMPLE: dict[str, Command] = {
    "getmap": GetMap(),
    "left": Left(),
    "right": Right(),
    "navcam": NavCam(),
    "usercam": UserCam(),
    "stop": Stop(),
    "cancel": Cancel(),
    "arm": Arm(),
    "take": TakeDrive(),
    "release": ReleaseDrive(),
    "unfollow": Unfollow(),
    "places": Places(),
    "topics": Topics(),
    "status": Status(),
    "battery": BatteryQuery(),
}


def _follow(args: list[str]) -> Follow:
    if not args:
        return Follow()
    # "follow person 3", "follow #3", "follow id 3": the number is what counts.
    words = [arg for arg in args if arg not in ("person", "id", "track")]
    if len(words) != 1 or not words[0].lstrip("#").isascii() or not words[0].lstrip("#").isdigit():
        raise CommandError(USAGE["follow"])
    target = int(words[0].lstrip("#"))
    if target > 2**31:
        raise CommandError(USAGE["follow"])
    return Follow(target)


def _unknown(word: str) -> str:
    shown = word if len(word) <= _ECHO_MAX else word[: _ECHO_MAX - 1] + "…"
    return f"unknown command '{shown}' — try help"


def _original_args(text: str, skip: int) -> list[str]:
    # Place names keep the case the user typed: a real robot's names may be case-sensitive.
    return text.replace("\u2212", "-").split()[skip:]


def _goto(args: list[str]) -> GotoPlace | GotoPoint:
    if not args:
        raise CommandError(USAGE["goto"])
    # One word is always a place, even "101": room numbers are good place names. Two or
    # three words starting with a number are a point; "goto room 101" is a place again.
    if len(args) == 1 or not _NUMBER.fullmatch(args[0]):
        return GotoPlace(" ".join(args))
    if len(args) > 3:
        raise CommandError(USAGE["goto"])
    values = [_finite(arg, "goto") for arg in args]
    return GotoPoint(values[0], values[1], values[2] if len(values) == 3 else None)


def _forward_metres(args: list[str], name: str) -> float:
    metres = _number(args, _METRES, name)
    if abs(metres) > MAX_FORWARD_M:
        raise CommandError(USAGE[name])
    return metres


def _number(args: list[str], units: tuple[str, ...], name: str) -> float:
    """The single number in ``args``, with an optional unit attached or after it."""
    if len(args) == 2 and args[1] in units:
        args = args[:1]
    if len(args) != 1:
        raise CommandError(USAGE[name])
    token = args[0]
    for unit in sorted(units, key=len, reverse=True):
        if token.endswith(unit) and len(token) > len(unit):
            token = token[: -len(unit)]
            break
    return _finite(token, name)


def _finite(token: str, name: str) -> float:
    if not _NUMBER.fullmatch(token):
        raise CommandError(USAGE[name])
    value = float(token)
    # "1e999" matches the pattern but is infinite.
    if not math.isfinite(value):
        raise CommandError(USAGE[name])
    return value + 0.0  # no "-0.0" in replies


def _help(args: list[str]) -> Help:
    if not args:
        return Help()
    topic = " ".join(args)
    if len(topic) > 1:
        topic = topic.rstrip("?")
    name = _ALIASES.get(topic)
    if name is None:
        raise CommandError(_unknown(topic), Reason.UNKNOWN_COMMAND)
    return Help("fwd" if name == "back" else name)


# ---------------------------------------------------------------------------- messages


@dataclass(frozen=True, slots=True)
class ChatRequest:
    """A chat line from the user: ``id`` (u32, chosen by the user) and the typed ``text``."""

    id: int
    text: str


@dataclass(frozen=True, slots=True)
class ChatReply:
    """The robot's answer to request ``id``.

    ``final`` is false for acknowledgements and notices while a motion runs, true on the
    request's last reply. ``ok`` is false when the reply reports trouble (a refusal, a
    failure, a blocked robot). ``attachment`` names what follows on another channel
    (``"map"``). ``seq`` numbers the replies to one request from 0, so that a client can
    drop the copies a robot sends again when a request is repeated over the lossy link.
    ``code`` is the stable code to decide on (the wire's ``code``, see
    :class:`~telebot.reasons.Reason`; ``""`` from a robot that sends none).
    """

    id: int
    text: str
    final: bool = True
    ok: bool = True
    attachment: str | None = None
    seq: int = 0
    code: str = ""

    def encode(self) -> str:
        """The reply as a JSON text datagram (text shortened to :data:`MAX_REPLY_TEXT`)."""
        text = self.text
        if len(text) > MAX_REPLY_TEXT:
            text = text[: MAX_REPLY_TEXT - 1] + "…"
        message: dict[str, Any] = {
            "id": self.id,
            "seq": self.seq,
            "text": text,
            "final": self.final,
            "ok": self.ok,
        }
        if self.attachment is not None:
            message["attachment"] = self.attachment
        if self.code:
            message["code"] = self.code
        return encode_object(message)


def _request(message: dict[str, Any]) -> ChatRequest:
    """The request in a decoded (or about to be encoded) message; ProtocolError if invalid."""
    what = "chat request"
    request_id = require_int(message, "id", what=what)
    text = message.get("text")
    if not isinstance(text, str):
        raise ProtocolError(f"{what}: 'text' must be a string")
    if len(text) > MAX_REQUEST_TEXT:
        raise ProtocolError(f"{what}: text is longer than {MAX_REQUEST_TEXT} characters")
    return ChatRequest(request_id, text)


def encode_request(id: int, text: str) -> str:
    """A request datagram; :class:`ProtocolError` for anything :func:`decode_request` refuses."""
    message = {"id": id, "text": text}
    _request(message)
    return encode_object(message)


def decode_request(payload: str | bytes) -> ChatRequest:
    """Parse a request datagram; :class:`ProtocolError` on anything else.

    Unknown keys are ignored, so that newer clients can add fields.
    """
    return _request(decode_object(payload, what="chat request"))


def decode_reply(payload: str | bytes) -> ChatReply:
    """Parse a reply datagram; :class:`ProtocolError` on anything else (unknown keys ignored)."""
    what = "chat reply"
    message = decode_object(payload, what=what)
    reply_id = require_int(message, "id", what=what)
    seq = require_int(message, "seq", what=what)
    text = message.get("text")
    if not isinstance(text, str):
        raise ProtocolError(f"{what}: 'text' must be a string")
    final, ok = message.get("final"), message.get("ok")
    if not isinstance(final, bool) or not isinstance(ok, bool):
        raise ProtocolError(f"{what}: 'final' and 'ok' must be booleans")
    attachment = message.get("attachment")
    if attachment is not None and not isinstance(attachment, str):
        raise ProtocolError(f"{what}: 'attachment' must be a string")
    return ChatReply(reply_id, text, final, ok, attachment, seq, decode_code(message, what=what))
