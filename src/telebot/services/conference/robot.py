"""The conference service: many users, one robot (the paper's robot teleconferencing).

Every call to a robot opens the ``conference`` channel (protocol:
:mod:`telebot.services.conference.wire`, ``docs/protocol.md`` §20). On the robot one
:class:`ConferenceRoom` per robot (its per-robot service) knows
every call: it pushes the roster (who is watching, who drives) to each call when it
changes and once a second, relays each user's ``say`` to every call with the sender's name,
and announces what everyone should know (who joined, reconnected, left, holds the drive,
stopped the robot). Replies to a chat command still go only to its sender (the ``chat`` channel).

On the user's side :class:`ConferenceState` (``client.conference``) outlives reconnections:
the latest roster, the messages heard, listeners, and :meth:`ConferenceState.say`.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

from telebot.channels.channel import ReceivedDatagram
from telebot.channels.transports.base import Lane
from telebot.errors import ProtocolError, TelebotError
from telebot.services.base import HostService, RobotHost
from telebot.services.conference.wire import (
    CONFERENCE,
    RESEND_AFTER,
    Conference,
    Message,
    Since,
    decode_conference_request,
)

if TYPE_CHECKING:
    from telebot.channels.call import Call

__all__ = ["ROSTER_EVERY", "ConferenceRoom", "RobotConference"]

log = logging.getLogger(__name__)

#: The roster is pushed to every call this often (s), besides on each change.
ROSTER_EVERY = 1.0
#: Clients whose call dropped, remembered so that their next call reads as a reconnection.
_DROPS_KEPT = 64


class ConferenceRoom(HostService[RobotHost]):
    """One robot's conference (its per-robot service): the sans-IO :class:`Conference` and
    each call's :class:`RobotConference`, which it opens."""

    def __init__(self, server: RobotHost) -> None:
        super().__init__(server)
        self.server = server
        self.conference = Conference()
        self.calls: dict[str, RobotConference] = {}
        self._tick_at = -math.inf
        self._next_roster = -math.inf
        self._holder: str | None = None
        self._holder_call: str | None = None
        self._armed: bool | None = None
        #: Clients (user, instance) whose call dropped: their next call is a reconnection.
        self.dropped: dict[tuple[str, str], None] = {}

    def holder_call(self) -> str | None:
        """The call holding the drive (None: free, or no supervisor)."""
        return self.server.safety.state().holder_call if self.server.safety is not None else None

    def broadcast(self, message: Message) -> None:
        text = message.encode()
        for service in list(self.calls.values()):
            service.send(text)

    def push_roster(self) -> None:
        driving = self.holder_call()
        for call_id, service in list(self.calls.items()):
            service.send(self.conference.roster(call_id, driving).encode())

    def tick(self, now: float) -> None:
        """Once per robot cycle (the robot's tick and every call's have the same ``now``): announce drive
        and stop changes, and push the roster when it changed or is due."""
        if now == self._tick_at:
            return
        self._tick_at = now
        changed = False
        if self.server.safety is not None:
            status = self.server.safety_status()
            holder_call = self.holder_call()
            if holder_call != self._holder_call:
                # The drive moved to another call: the roster says which; the news is only
                # for another user (a reconnection keeps the drive with the same user).
                self._holder_call = holder_call
                changed = True
            if status.holder != self._holder:
                self._holder = status.holder
                text = f"{status.holder} holds the drive" if status.holder else "the drive is free"
                self.broadcast(self.conference.announce(text))
                changed = True
            if status.armed != self._armed:
                was, self._armed = self._armed, status.armed
                if was is not None:  # not at start-up: only real changes are news
                    text = "armed" if status.armed else f"stopped: {status.text or 'stopped'}"
                    self.broadcast(self.conference.announce(text))
        if changed or now >= self._next_roster:
            self._next_roster = now + ROSTER_EVERY
            self.push_roster()

    def open(self, call: Call) -> RobotConference:
        """The room on ``call``: the caller joins."""
        self.conference.robot = self.server.name  # known once the robot answers calls
        return RobotConference(self, call)

    def announce(self, text: str) -> None:
        """Tell every user in the robot's calls ``text``, from the robot."""
        self.broadcast(self.conference.announce(text))


class RobotConference:
    """The robot's ``conference`` service on one call (registered as ``conference``)."""

    def __init__(self, room: ConferenceRoom, call: Call) -> None:
        self.server = server = room.server
        self.call = call
        self.room = room
        self.channel = call.channel(CONFERENCE, lane=Lane.CONTROL)
        self.channel.set_callback(self._on_datagram)
        self.rejected = 0
        self._since_at = -math.inf
        role = str(call.role) if call.role is not None else "observer"
        # A call that replaces its client's previous one (RobotServer.serve) reads as one
        # reconnection: the old call leaves the room without a "left" after this "joined".
        replaces = server.replaces(call.id)
        if replaces is not None:
            old = self.room.calls.pop(replaces, None)
            if old is not None:
                old.channel.set_callback(None)
        again = self._client in self.room.dropped
        self.room.dropped.pop(self._client, None)
        self.room.calls[call.id] = self
        self.room.broadcast(
            self.room.conference.join(call.id, call.peer, role, replaces=replaces, again=again)
        )
        self.room.push_roster()

    @property
    def _client(self) -> tuple[str, str]:
        """Who called: the user and its client instance (one per client process)."""
        return self.call.peer, self.call.peer_instance

    def _on_datagram(self, datagram: ReceivedDatagram) -> None:
        try:
            request = decode_conference_request(datagram.payload)
        except ProtocolError as exc:
            self.rejected += 1
            self.channel.stats.rejected += 1
            log.debug("call %s: conference datagram dropped: %s", self.call.id, exc)
            return
        conference = self.room.conference
        if isinstance(request, Since):
            # One small request makes up to HISTORY answers: at most one per RESEND_AFTER.
            now = self.server.now()
            if now - self._since_at < RESEND_AFTER * 0.8:
                return
            self._since_at = now
            for message in conference.since(request.seq):
                self.send(message.encode())
            return
        said, spoken = conference.say(self.call.id, request, self.server.now())
        if spoken is not None:
            self.server.emit({"event": "say", "peer": self.call.peer, "text": spoken.text})
            self.room.broadcast(spoken)
        self.send(said.encode())

    def send(self, text: str) -> None:
        """Send ``text`` on this call's channel (nothing once the call is over)."""
        if not self.call.active:
            return
        try:
            self.channel.send(text)
        except TelebotError as exc:
            log.debug("call %s: conference not sent: %s", self.call.id, exc)

    def tick(self, now: float) -> None:
        """Drive/stop announcements and the roster (once per robot cycle for all calls)."""
        self.room.tick(now)

    def close(self) -> None:
        """The call ended: everyone else hears who left."""
        self.channel.set_callback(None)
        if self.room.calls.pop(self.call.id, None) is None:
            return
        left = self.room.conference.leave(self.call.id)
        if left is not None:
            self.room.broadcast(left)
        end = self.call.end
        if end is not None and end.kind == "dropped" and self.call.peer_instance:
            dropped = self.room.dropped
            dropped[self._client] = None
            while len(dropped) > _DROPS_KEPT:  # clients that never came back
                del dropped[next(iter(dropped))]
        self.room.push_roster()
