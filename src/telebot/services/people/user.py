"""The user's side of ``people``: :class:`PeopleReceiver` (see the service's overview in
:mod:`telebot.services.people`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from telebot.services.base import DatagramReceiver, is_newer
from telebot.services.people.wire import (
    PEOPLE,
    PeopleAlertMessage,
    PeopleUpdate,
    decode_people_message,
)

if TYPE_CHECKING:
    from telebot.channels.call import Call

__all__ = ["PeopleReceiver"]


class PeopleReceiver(DatagramReceiver[PeopleUpdate | PeopleAlertMessage]):
    """The user's ``people`` service on one call: updates and alerts go to the callbacks."""

    def __init__(
        self,
        call: Call,
        on_update: Callable[[PeopleUpdate], None],
        on_alert: Callable[[PeopleAlertMessage], None],
    ) -> None:
        super().__init__(call, PEOPLE, decode_people_message)
        self._on_update = on_update
        self._on_alert = on_alert
        self._seq: int | None = None
        self._alerts_seen: set[int] = set()

    def deliver(self, message: PeopleUpdate | PeopleAlertMessage) -> None:
        """An update newer than the last one, and each alert once, to the callbacks."""
        if isinstance(message, PeopleUpdate):
            # Older than the newest seen (reordered on the lossy link): stale.
            if is_newer(self._seq, message.seq):
                self._seq = message.seq
                self._on_update(message)
            return
        if message.seq in self._alerts_seen:
            return  # a repeat
        self._alerts_seen.add(message.seq)
        if len(self._alerts_seen) > 256:
            self._alerts_seen = {s for s in self._alerts_seen if s > message.seq - 128}
        self._on_alert(message)
