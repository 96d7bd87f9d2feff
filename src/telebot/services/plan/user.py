"""The user's side of ``plan``: :class:`PlanReceiver` (see the service's overview in
:mod:`telebot.services.plan`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING

from telebot.services.base import DatagramReceiver, is_newer
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


class PlanReceiver(DatagramReceiver[PlanUpdate | PlacesUpdate]):
    """The user's ``plan`` service on one call: new plans and places go to the callbacks."""

    def __init__(
        self,
        call: Call,
        on_plan: Callable[[PlanUpdate], None],
        on_places: Callable[[Mapping[str, Place]], None],
    ) -> None:
        super().__init__(call, PLAN, decode_plan_message)
        self._on_plan = on_plan
        self._on_places = on_places
        self._seq: int | None = None
        self._places: PlacesUpdate | None = None

    def deliver(self, message: PlanUpdate | PlacesUpdate) -> None:
        """A plan newer than the last one, or places that changed, to the callbacks."""
        if isinstance(message, PlanUpdate):
            # A repeat, or one overtaken by a newer plan on the lossy link: nothing new.
            if is_newer(self._seq, message.seq):
                self._seq = message.seq
                self._on_plan(message)
        elif message != self._places:
            self._places = message
            self._on_places({place.name: place for place in message.places})
