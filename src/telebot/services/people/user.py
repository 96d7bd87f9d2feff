"""The ``people`` service: tracked people and alerts about them, robot → user at 5 Hz.

On the robot, :class:`PeopleService` (registered as ``people`` by
:func:`~telebot.services.registry.robot_services`) sends each call a ``people`` message
``stream_hz`` times a second (``[people]`` of the config) with the confirmed tracks of the
robot's :class:`~telebot.robot.perception.runner.PeoplePerception`, and each new alert a few
times (:data:`ALERT_REPEATS`, same ``seq``: the channel is lossy). The perception itself runs
once per robot, from the server's control loop, not per call.

On the user's side, :class:`PeopleReceiver` hands updates and each alert once to the client
(:meth:`RobotClient.people <telebot.services.client.RobotClient.people>`,
:meth:`~telebot.services.client.RobotClient.people_alerts`). Wire format:
:mod:`telebot.services.people.wire` and ``docs/protocol.md`` (the ``people`` channel).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

from telebot.channels.channel import ReceivedDatagram
from telebot.channels.transports.base import Lane
from telebot.errors import ProtocolError
from telebot.services.people.wire import (
    PEOPLE,
    PeopleAlertMessage,
    PeopleUpdate,
    decode_people_message,
)

if TYPE_CHECKING:
    from telebot.channels.call import Call

__all__ = ["PeopleReceiver"]

log = logging.getLogger(__name__)


class PeopleReceiver:
    """The user's ``people`` service on one call: updates and alerts go to the callbacks."""

    def __init__(
        self,
        call: Call,
        on_update: Callable[[PeopleUpdate], None],
        on_alert: Callable[[PeopleAlertMessage], None],
    ) -> None:
        self.channel = call.channel(PEOPLE, lane=Lane.DATA)
        self.channel.set_callback(self._on_datagram)
        self._on_update = on_update
        self._on_alert = on_alert
        self._seq: int | None = None
        self._alerts_seen: set[int] = set()
        #: Datagrams that did not decode (dropped).
        self.rejected = 0

    def tick(self, now: float) -> None:
        """Nothing periodic: the robot streams."""

    def close(self) -> None:
        """Deliver nothing more from this call."""
        self.channel.set_callback(None)

    def _on_datagram(self, datagram: ReceivedDatagram) -> None:
        try:
            message = decode_people_message(datagram.payload)
        except ProtocolError as exc:
            self.rejected += 1
            self.channel.stats.rejected += 1
            log.debug("people datagram dropped: %s", exc)
            return
        if isinstance(message, PeopleUpdate):
            # Older than the newest seen (reordered on the lossy link): stale.
            seq = self._seq
            if seq is not None and seq >= message.seq and seq - message.seq < 2**31:
                return
            self._seq = message.seq
            self._on_update(message)
            return
        if message.seq in self._alerts_seen:
            return  # a repeat
        self._alerts_seen.add(message.seq)
        if len(self._alerts_seen) > 256:
            self._alerts_seen = {s for s in self._alerts_seen if s > message.seq - 128}
        self._on_alert(message)
