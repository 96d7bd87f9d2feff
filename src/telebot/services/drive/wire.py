"""Messages of the ``drive`` channel: driving by hand (CONTROL lane, JSON text datagrams).

User → robot, sent at 20 Hz while the user holds a drive key, stick or button::

    {"type": "drive", "seq": 41, "linear": 0.3, "angular": -0.5}

``seq`` is an integer in 0 … 2³² − 1, one more per command; the robot ignores a command
that is not newer than the newest it took (serial arithmetic, :func:`seq_newer`), so a
reordered old command never undoes a newer one. ``linear`` (m/s, + forward) and
``angular`` (rad/s, + counter-clockwise, REP-103) are finite numbers; both 0 is a
*release*: the robot stops at once (not latched) and direct driving ends.

Robot → user, at once whenever ``active`` or ``code`` changes, at 5 Hz while active, and an
inactive one twice more (0.2 s apart: the lane is lossy)::

    {"type": "drive_state", "seq": 41, "active": true, "code": "ok", "reason": "",
     "linear": 0.3, "angular": -0.5, "cap": 0.42}

``seq``: the newest command taken; ``linear``/``angular``: what the robot commands now
(after its clamps); ``cap``: the linear speed cap now; ``code``: a reason code
(:mod:`telebot.reasons`). See ``docs/protocol.md`` §27.
"""

from __future__ import annotations

from dataclasses import dataclass

from telebot.errors import ProtocolError, excerpt
from telebot.reasons import decode_code
from telebot.services.messages import (
    decode_object,
    encode_object,
    finite_number,
    require_int,
)

__all__ = [
    "DRIVE",
    "DriveCommand",
    "DriveState",
    "InvalidDriveCommand",
    "NotADriveCommand",
    "decode_drive_command",
    "decode_drive_state",
    "seq_newer",
]

#: The channel's name.
DRIVE = "drive"
#: Sequence numbers wrap at this (2³²).
SEQ_MODULUS = 2**32
#: Longest piece of a peer's input an error text quotes (characters).
_QUOTE = 40


def seq_newer(seq: int, than: int) -> bool:
    """Whether ``seq`` is newer than ``than`` in serial arithmetic (RFC 1982, 32 bits)."""
    diff = (seq - than) % SEQ_MODULUS
    return 0 < diff < SEQ_MODULUS // 2


@dataclass(frozen=True, slots=True)
class DriveCommand:
    """One velocity command (a release when both are 0)."""

    seq: int
    linear: float
    angular: float

    @property
    def release(self) -> bool:
        """Both velocities 0: stop now and end direct driving."""
        return self.linear == 0.0 and self.angular == 0.0

    def encode(self) -> str:
        """The datagram text."""
        return encode_object(
            {"type": "drive", "seq": self.seq, "linear": self.linear, "angular": self.angular}
        )


@dataclass(frozen=True, slots=True)
class DriveState:
    """The robot's direct-driving state, as the user hears it.

    ``code`` is the reason code (:class:`~telebot.reasons.Reason`: ``ok``, ``released``,
    ``stale``, ``replaced``, ``stopped``, ``obstacle``, ``invalid`` or a motion refusal);
    ``text`` says why in words (the wire's ``reason`` field), empty while all is well.
    """

    seq: int
    active: bool
    code: str
    text: str = ""
    linear: float = 0.0
    angular: float = 0.0
    cap: float = 0.0

    def encode(self) -> str:
        """The datagram text."""
        return encode_object(
            {
                "type": "drive_state",
                "seq": self.seq,
                "active": self.active,
                "code": self.code,
                "reason": self.text,
                "linear": round(self.linear, 3),
                "angular": round(self.angular, 3),
                "cap": round(self.cap, 3),
            }
        )


class InvalidDriveCommand(ProtocolError):
    """A ``drive`` datagram that does not decode: direct driving stops, the robot answers."""


class NotADriveCommand(ProtocolError):
    """A JSON object of another ``type`` on the channel: dropped and counted, not answered."""


def decode_drive_command(payload: str | bytes) -> DriveCommand:
    """Parse a user → robot ``drive`` datagram.

    Raises :class:`NotADriveCommand` for an object whose ``type`` is other text, and
    :class:`InvalidDriveCommand` (one line, quoting at most 40 characters of the input)
    for anything else that is not a valid command.
    """
    try:
        msg = decode_object(payload, what="drive")
    except ProtocolError as exc:
        text = str(exc)
        if isinstance(payload, str) and "not JSON" in text:
            text = f"drive: not JSON: {excerpt(payload, _QUOTE)!r}"
        raise InvalidDriveCommand(text) from None
    kind = msg.get("type")
    if isinstance(kind, str) and kind != "drive":
        raise NotADriveCommand(f"drive: a {excerpt(kind, _QUOTE)!r} message is not a command")
    if kind is None:
        raise InvalidDriveCommand("drive: 'type' is missing (expected \"drive\")")
    if not isinstance(kind, str):
        raise InvalidDriveCommand(f"drive: 'type' must be \"drive\", not {_quote(kind)}")
    try:
        seq = require_int(msg, "seq", what="drive")
        linear = finite_number(msg, "linear", what="drive")
        angular = finite_number(msg, "angular", what="drive")
    except ProtocolError as exc:
        raise InvalidDriveCommand(str(exc)) from None
    return DriveCommand(seq, linear, angular)


def _quote(value: object) -> str:
    return excerpt(repr(value), _QUOTE)


def decode_drive_state(payload: str | bytes) -> DriveState:
    """Parse a robot → user ``drive_state`` datagram; ProtocolError when malformed."""
    msg = decode_object(payload, what="drive_state")
    if msg.get("type") != "drive_state":
        raise ProtocolError(f"drive_state: unknown type {_quote(msg.get('type'))}")
    active = msg.get("active")
    if not isinstance(active, bool):
        raise ProtocolError("drive_state: 'active' must be true or false")
    text = msg.get("reason", "")
    if not isinstance(text, str):
        raise ProtocolError("drive_state: 'reason' must be text")
    return DriveState(
        require_int(msg, "seq", what="drive_state"),
        active,
        decode_code(msg, what="drive_state"),
        text,
        finite_number(msg, "linear", what="drive_state"),
        finite_number(msg, "angular", what="drive_state"),
        finite_number(msg, "cap", what="drive_state"),
    )
