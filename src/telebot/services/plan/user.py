"""The ``plan`` service: the robot's planned path and named places, for the user's map view.

On the robot, :class:`PlanService` (registered as ``plan`` by
:func:`~telebot.services.registry.robot_services`) sends each call a ``plan`` message
as soon as the plan changes (a new goal, a replan, the goal's end: then an empty one) and
again every :data:`PLAN_EVERY` seconds, so a lost one heals and a user who joins sees the
plan at once; and the ``places`` at the call's start, on change and every
:data:`PLACES_EVERY` seconds. The plan is read from the NavStack and simplified once per
change for every call (:class:`PlanSource`, shared per NavStack).

On the user's side, :class:`PlanReceiver` hands new plans and places to the client
(:attr:`RobotClient.latest_plan <telebot.services.client.RobotClient.latest_plan>`);
repeats and plans older than the newest seen (reordered on the lossy link) are dropped.
Wire format: :mod:`telebot.services.plan.wire` and ``docs/protocol.md`` §16.4.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING

from telebot.channels.channel import ReceivedDatagram
from telebot.channels.transports.base import Lane
from telebot.errors import ProtocolError
from telebot.services.plan.wire import (
    PLAN,
    Place,
    PlacesUpdate,
    PlanUpdate,
    decode_plan_message,
)

if TYPE_CHECKING:
    from telebot.channels.call import Call

__all__ = ["PlanReceiver"]

log = logging.getLogger(__name__)


class PlanReceiver:
    """The user's ``plan`` service on one call: new plans and places go to the callbacks."""

    def __init__(
        self,
        call: Call,
        on_plan: Callable[[PlanUpdate], None],
        on_places: Callable[[Mapping[str, Place]], None],
    ) -> None:
        self.channel = call.channel(PLAN, lane=Lane.DATA)
        self.channel.set_callback(self._on_datagram)
        self._on_plan = on_plan
        self._on_places = on_places
        self._seq: int | None = None
        self._places: PlacesUpdate | None = None
        #: Datagrams that did not decode (dropped).
        self.rejected = 0

    def tick(self, now: float) -> None:
        """Nothing periodic: the robot repeats."""

    def close(self) -> None:
        """Deliver nothing more from this call."""
        self.channel.set_callback(None)

    def _on_datagram(self, datagram: ReceivedDatagram) -> None:
        try:
            message = decode_plan_message(datagram.payload)
        except ProtocolError as exc:
            self.rejected += 1
            self.channel.stats.rejected += 1
            log.debug("plan datagram dropped: %s", exc)
            return
        if isinstance(message, PlanUpdate):
            # A repeat, or one overtaken by a newer plan on the lossy link: nothing new.
            # (A seq that wrapped round to 1 is new: it cannot be that far behind.)
            seq = self._seq
            if seq is not None and seq >= message.seq and seq - message.seq < 2**31:
                return
            self._seq = message.seq
            self._on_plan(message)
        elif message != self._places:
            self._places = message
            self._on_places({place.name: place for place in message.places})
