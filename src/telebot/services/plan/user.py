"""The user's side of ``plan``: :class:`PlanReceiver` (see the service's overview in
:mod:`telebot.services.plan`).
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
