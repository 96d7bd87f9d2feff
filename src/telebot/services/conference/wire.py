"""Messages of the ``conference`` channel (CONTROL lane, JSON text datagrams): many users,
one robot.

The users of one robot's calls see each other (a roster the robot pushes) and talk to each
other through it (messages the robot relays to every call, with the sender's name)::

    user → robot
      {"type": "say", "id": 7, "text": "hello all"}   repeated (same id) until answered
      {"type": "since", "seq": 41}                    resend the messages after seq 41
    robot → user
      {"type": "said", "id": 7, "ok": true, "reason": "", "code": "ok"}
      {"type": "msg", "seq": 42, "from": "alice", "kind": "user", "text": "hello all"}
      {"type": "roster", "seq": 42, "users": [
          {"name": "alice", "role": "driver", "driving": true, "you": true},
          {"name": "bob", "role": "observer", "driving": false, "you": false}]}

``seq`` numbers the robot's messages (1, 2, …; one sequence for all calls); the roster
carries the newest, so a user who missed one (the channel is lossy) asks ``since`` its last
and the robot sends again what it still holds. ``kind`` is ``user`` (a user's ``say``) or
``robot`` (the robot's announcements: who joined, reconnected, left, holds the drive,
stopped it). The roster has one entry per call; ``driving`` is true for the one call that
holds the drive (a user's second call is listed, not driving).
Refusals of ``say`` carry a reason code: ``empty``, ``too_long``, ``too_fast``.

:class:`Conference` is the robot's sans-IO state: who is in, the message history, the
rate limit; it takes ``now`` and returns the datagrams to send to which call.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from telebot.errors import ProtocolError
from telebot.reasons import Reason, decode_code
from telebot.services.messages import decode_object, encode_object, require_int

__all__ = [
    "CONFERENCE",
    "HISTORY",
    "MAX_TEXT",
    "RESEND_AFTER",
    "Conference",
    "Member",
    "Message",
    "Roster",
    "Said",
    "Say",
    "Since",
    "decode_conference_reply",
    "decode_conference_request",
    "say_text",
]

#: The channel's name.
CONFERENCE = "conference"
#: Longest message text (characters).
MAX_TEXT = 1000
#: Messages the robot keeps for users who missed some.
HISTORY = 64
#: Messages one call may say per :data:`RATE_WINDOW` seconds.
RATE_LIMIT = 10
RATE_WINDOW = 10.0
#: Longest user name on the wire (names are zenoh key chunks, short anyway).
_MAX_NAME = 128


@dataclass(frozen=True, slots=True)
class Say:
    """A user's free message to everyone in the robot's calls."""

    id: int
    text: str

    def encode(self) -> str:
        """The datagram text."""
        return encode_object({"type": "say", "id": self.id, "text": self.text})


@dataclass(frozen=True, slots=True)
class Since:
    """A user asks again for the messages after ``seq``."""

    seq: int

    def encode(self) -> str:
        """The datagram text."""
        return encode_object({"type": "since", "seq": self.seq})


@dataclass(frozen=True, slots=True)
class Said:
    """The robot's answer to :class:`Say` ``id`` (``text``: why, for people; ``code``: its reason code)."""

    id: int
    ok: bool
    text: str = ""
    code: str = ""

    def encode(self) -> str:
        """The datagram text."""
        return encode_object(
            {"type": "said", "id": self.id, "ok": self.ok, "reason": self.text, "code": self.code}
        )


@dataclass(frozen=True, slots=True)
class Message:
    """A message every call hears: a user's (``kind`` ``user``) or the robot's (``robot``)."""

    seq: int
    sender: str
    kind: str
    text: str

    def encode(self) -> str:
        """The datagram text."""
        return encode_object(
            {
                "type": "msg",
                "seq": self.seq,
                "from": self.sender,
                "kind": self.kind,
                "text": self.text,
            }
        )


@dataclass(frozen=True, slots=True)
class Member:
    """One call in the roster: its user, role, whether it drives, whether it is the reader."""

    name: str
    role: str
    driving: bool
    you: bool = False


@dataclass(frozen=True, slots=True)
class Roster:
    """Who is in the robot's calls; ``seq``: the newest message's number (0: none yet)."""

    seq: int
    users: tuple[Member, ...]

    def encode(self) -> str:
        """The datagram text."""
        return encode_object(
            {
                "type": "roster",
                "seq": self.seq,
                "users": [
                    {"name": m.name, "role": m.role, "driving": m.driving, "you": m.you}
                    for m in self.users
                ],
            }
        )


def decode_conference_request(payload: str | bytes) -> Say | Since:
    """Parse a user → robot ``conference`` datagram; ProtocolError when malformed."""
    msg = decode_object(payload, what="conference")
    kind = msg.get("type")
    if kind == "say":
        text = msg.get("text")
        if not isinstance(text, str):
            raise ProtocolError("conference: 'text' must be text")
        return Say(require_int(msg, "id", what="conference"), text)
    if kind == "since":
        return Since(require_int(msg, "seq", what="conference", high=2**53 - 1))
    raise ProtocolError(f"conference: unknown type {kind!r}")


def decode_conference_reply(payload: str | bytes) -> Said | Message | Roster:
    """Parse a robot → user ``conference`` datagram; ProtocolError when malformed."""
    msg = decode_object(payload, what="conference")
    kind = msg.get("type")
    if kind == "said":
        ok = msg.get("ok")
        if not isinstance(ok, bool):
            raise ProtocolError("conference: 'ok' must be true or false")
        return Said(
            require_int(msg, "id", what="conference"),
            ok,
            _text(msg, "reason"),
            decode_code(msg, what="conference"),
        )
    if kind == "msg":
        return Message(
            require_int(msg, "seq", what="conference", high=2**53 - 1),
            _name(msg.get("from")),
            _text(msg, "kind"),
            _text(msg, "text"),
        )
    if kind == "roster":
        users = msg.get("users")
        if not isinstance(users, list):
            raise ProtocolError("conference: 'users' must be a list")
        members = []
        for user in users:
            if not isinstance(user, dict):
                raise ProtocolError("conference: each user must be an object")
            members.append(
                Member(
                    _name(user.get("name")),
                    _text(user, "role"),
                    user.get("driving") is True,
                    user.get("you") is True,
                )
            )
        return Roster(require_int(msg, "seq", what="conference", high=2**53 - 1), tuple(members))
    raise ProtocolError(f"conference: unknown type {kind!r}")


def say_text(line: str) -> str | None:
    """The message of a chat line ``say TEXT`` (None: the line is no ``say``)."""
    word, _, rest = line.strip().partition(" ")
    if word.lower() != "say":
        return None
    return rest.strip()


def _text(msg: dict[str, Any], key: str) -> str:
    value = msg.get(key, "")
    if not isinstance(value, str) or len(value) > MAX_TEXT:
        raise ProtocolError(f"conference: {key!r} must be text of at most {MAX_TEXT} characters")
    return value


def _name(value: Any) -> str:
    if not isinstance(value, str) or not value or len(value) > _MAX_NAME:
        raise ProtocolError("conference: a user name must be non-empty text")
    return value


@dataclass(slots=True)
class _Caller:
    name: str
    role: str
    says: deque[float]
    answers: dict[int, Said]


class Conference:
    """The robot's side of the conference: members, message history and rate limits.

    Sans-IO: methods take ``now`` where time matters and return what to send; the service
    (:mod:`telebot.services.conference.robot`) moves it onto each call's channel.
    """

    def __init__(self, robot: str = "robot") -> None:
        self.robot = robot
        self._calls: dict[str, _Caller] = {}
        self._history: deque[Message] = deque(maxlen=HISTORY)
        self._seq = 0

    @property
    def seq(self) -> int:
        """The newest message's number (0: none yet)."""
        return self._seq

    @property
    def calls(self) -> list[str]:
        """The call ids in the conference, in joining order."""
        return list(self._calls)

    def join(
        self,
        call_id: str,
        user: str,
        role: str,
        *,
        replaces: str | None = None,
        again: bool = False,
    ) -> Message:
        """A call came in; returns the announcement every call hears.

        ``replaces``: the same user's earlier call that this one takes the place of (its
        client called again): it leaves without a word, and everyone hears one
        ``NAME reconnected (ROLE)`` instead of a join and a leave. ``again``: the call
        comes from a client whose call dropped (its leave was heard): also ``reconnected``.
        """
        old = self._calls.get(replaces) if replaces is not None else None
        if replaces is not None and old is not None and old.name == user:
            del self._calls[replaces]
            # The rate limit goes on across the new call: calling again is no way round it.
            self._calls[call_id] = _Caller(user, role, old.says, {})
            return self.announce(f"{user} reconnected ({role})")
        self._calls[call_id] = _Caller(user, role, deque(), {})
        return self.announce(f"{user} {'reconnected' if again else 'joined'} ({role})")

    def leave(self, call_id: str) -> Message | None:
        """A call ended; returns the announcement (None: the call was not in)."""
        caller = self._calls.pop(call_id, None)
        if caller is None:
            return None
        return self.announce(f"{caller.name} left")

    def announce(self, text: str) -> Message:
        """A message from the robot itself (numbered and kept like any other)."""
        return self._add(self.robot, "robot", text[:MAX_TEXT])

    def say(self, call_id: str, say: Say, now: float) -> tuple[Said, Message | None]:
        """A user's ``say``: the answer to its call and, if accepted, the message for all.

        A repeat (same id) gets the same answer and no second message.
        """
        caller = self._calls.get(call_id)
        if caller is None:
            return Said(say.id, False, "not in the conference", Reason.UNKNOWN_CALL), None
        earlier = caller.answers.get(say.id)
        if earlier is not None:
            return earlier, None
        text = say.text.strip()
        message: Message | None = None
        while caller.says and caller.says[0] <= now - RATE_WINDOW:
            caller.says.popleft()
        if not text:
            said = Said(say.id, False, "nothing to say: the message is empty", Reason.EMPTY)
        elif len(text) > MAX_TEXT:
            said = Said(
                say.id, False, f"message longer than {MAX_TEXT} characters", Reason.TOO_LONG
            )
        elif len(caller.says) >= RATE_LIMIT:
            said = Said(
                say.id,
                False,
                f"too fast: at most {RATE_LIMIT} messages in {RATE_WINDOW:g} s",
                Reason.TOO_FAST,
            )
        else:
            caller.says.append(now)
            message = self._add(caller.name, "user", text)
            said = Said(say.id, True, "", Reason.OK)
        caller.answers[say.id] = said
        while len(caller.answers) > HISTORY:
            del caller.answers[next(iter(caller.answers))]
        return said, message

    def since(self, seq: int) -> list[Message]:
        """The messages after ``seq`` still held (older ones are gone for good)."""
        return [m for m in self._history if m.seq > seq]

    def roster(self, for_call: str, driving: str | None) -> Roster:
        """The roster as call ``for_call`` sees it; ``driving``: the call holding the drive.

        One entry per call: a user with two calls (a page and a terminal) is listed twice,
        and only the call that holds the drive is driving (one driver).
        """
        users = tuple(
            Member(c.name, c.role, call_id == driving, call_id == for_call)
            for call_id, c in self._calls.items()
        )
        return Roster(self._seq, users)

    def members(self) -> Iterable[tuple[str, str]]:
        """``(user, role)`` of each call."""
        return [(c.name, c.role) for c in self._calls.values()]

    def _add(self, sender: str, kind: str, text: str) -> Message:
        self._seq += 1
        message = Message(self._seq, sender, kind, text)
        self._history.append(message)
        return message


#: A ``say`` or ``since`` nobody answered is sent again after this long (s).
RESEND_AFTER = 0.3
