"""The conference service: many users, one robot (the paper's robot teleconferencing).

Every call to a robot opens the ``conference`` channel (protocol:
:mod:`telebot.services.conference.wire`, ``docs/protocol.md`` §20). On the robot one
:class:`Conference` per :class:`~telebot.services.robot.RobotServer` (its *room*) knows
every call: it pushes the roster (who is watching, who drives) to each call when it
changes and once a second, relays each user's ``say`` to every call with the sender's name,
and announces what everyone should know (who joined, reconnected, left, holds the drive,
stopped the robot). Replies to a chat command still go only to its sender (the ``chat`` channel).

On the user's side :class:`ConferenceState` (``client.conference``) outlives reconnections:
the latest roster, the messages heard, listeners, and :meth:`ConferenceState.say`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from telebot.channels.channel import ReceivedDatagram
from telebot.channels.transports.base import Lane
from telebot.errors import CallEnded, ProtocolError, TelebotError
from telebot.services.base import ClientHost, HostService
from telebot.services.conference.wire import (
    CONFERENCE,
    HISTORY,
    RESEND_AFTER,
    Message,
    Roster,
    Said,
    Say,
    Since,
    decode_conference_reply,
)

if TYPE_CHECKING:
    from telebot.channels.call import Call

__all__ = ["ConferenceReceiver", "ConferenceState"]

log = logging.getLogger(__name__)


class ConferenceState(HostService[ClientHost]):
    """What a user's client knows of the conference, across reconnections (the user side's
    per-client service: it opens a :class:`ConferenceReceiver` on each call).

    ``roster``: the latest :class:`Roster` (None before the first); ``messages``: the
    last :data:`KEEP` messages heard (users' and the robot's), in the robot's order; listeners in ``on_message`` and
    ``on_roster`` are called on the event loop with each new one.
    """

    def __init__(self, client: ClientHost) -> None:
        super().__init__(client)
        self._client = client
        self.roster: Roster | None = None
        self.messages: list[Message] = []
        self.on_message: list[Callable[[Message], None]] = []
        self.on_roster: list[Callable[[Roster], None]] = []
        self._floor: int | None = None  # every message up to this seq is seen
        self._seen: set[int] = set()
        self._top = 0
        self._asked = -math.inf
        self._said: dict[int, asyncio.Queue[Said]] = {}
        self._ids = 0

    def open(self, call: Call) -> ConferenceReceiver:
        """Hear the conference on ``call``."""
        return ConferenceReceiver(self, call)

    # -- from the channel -------------------------------------------------------------

    def deliver(self, payload: str | bytes, now: float) -> str | None:
        """One datagram from the robot; returns a ``since`` request to send, if one is due."""
        try:
            message = decode_conference_reply(payload)
        except ProtocolError:
            self._client.rejected += 1
            return None
        if isinstance(message, Said):
            waiter = self._said.get(message.id)
            if waiter is not None:
                waiter.put_nowait(message)
            return None
        if isinstance(message, Roster):
            if self._floor is None or message.seq < self._floor:  # first, or robot restarted
                self._floor = message.seq
                self._seen.clear()
            self._top = max(self._top, message.seq)
            # What the robot no longer holds is gone: do not ask for it forever.
            self._floor = max(self._floor, message.seq - HISTORY)
            self.roster = message
            self._advance()
            for on_roster in list(self.on_roster):
                _call(on_roster, message)
            return self._missing(now)
        if self._floor is None:
            self._floor = message.seq - 1
        if message.seq <= self._floor or message.seq in self._seen:
            return None
        self._seen.add(message.seq)
        self._top = max(self._top, message.seq)
        self._advance()
        self.messages.append(message)
        if len(self.messages) > 1 and self.messages[-2].seq > message.seq:
            self.messages.sort(key=lambda m: m.seq)  # one asked for again: in its place
        del self.messages[:-KEEP]
        for listener in list(self.on_message):
            _call(listener, message)
        return self._missing(now)

    def _advance(self) -> None:
        assert self._floor is not None
        while self._floor + 1 in self._seen:
            self._floor += 1
            self._seen.discard(self._floor)
        self._seen = {seq for seq in self._seen if seq > self._floor}

    def _missing(self, now: float) -> str | None:
        if self._floor is None or self._floor >= self._top or now - self._asked < RESEND_AFTER:
            return None
        self._asked = now
        return Since(self._floor).encode()

    def due(self, now: float) -> str | None:
        """A ``since`` to send again while messages are missing (from the service's tick)."""
        return self._missing(now)

    # -- the user's API ---------------------------------------------------------------

    async def say(self, text: str, *, timeout: float = 5.0) -> Said:
        """Say ``text`` to everyone in the robot's calls; the robot's answer (``ok``, code).

        Repeated until answered; raises TimeoutError after ``timeout`` s and
        :class:`~telebot.errors.CallEnded` when the call ends first.
        """
        client = self._client
        self._ids = (self._ids + 1) % 2**32
        say_id = self._ids
        answers: asyncio.Queue[Said] = asyncio.Queue()
        self._said[say_id] = answers
        payload = Say(say_id, text).encode()
        try:
            async with asyncio.timeout(timeout):
                await client.live_call()  # waits out a reconnection
                receiver = client.service(CONFERENCE)
                if not isinstance(receiver, ConferenceReceiver):
                    raise TelebotError("this client has no conference service registered")
                while True:
                    receiver.send(payload)
                    try:
                        return await client.answer(answers, RESEND_AFTER, receiver.call)
                    except TimeoutError:
                        continue
        finally:
            self._said.pop(say_id, None)


def _call(listener: Callable[[Any], None], value: Any) -> None:
    try:
        listener(value)
    except Exception:
        log.exception("conference listener failed")


class ConferenceReceiver:
    """The user's ``conference`` service on one call: feeds ``client.conference``."""

    def __init__(self, state: ConferenceState, call: Call) -> None:
        self.call = call
        self.state = state
        self._loop = asyncio.get_running_loop()
        self.channel = call.channel(CONFERENCE, lane=Lane.CONTROL)
        self.channel.set_callback(self._on_datagram)

    def _on_datagram(self, datagram: ReceivedDatagram) -> None:
        request = self.state.deliver(datagram.payload, self._loop.time())
        if request is not None:
            self.send(request)

    def send(self, text: str) -> None:
        """Send on this call (raises CallEnded once it is over)."""
        if not self.call.active:
            raise CallEnded("the call ended", self.call.end.kind if self.call.end else "")
        self.channel.send(text)

    def tick(self, now: float) -> None:
        """Ask again for missing messages."""
        request = self.state.due(now)
        if request is not None and self.call.active:
            with contextlib.suppress(TelebotError):
                self.channel.send(request)

    def close(self) -> None:
        """Deliver nothing more from this call."""
        self.channel.set_callback(None)


#: Messages a user's client keeps.
KEEP = 500
