"""The robot's side of ``people``: :class:`RobotPeople` and :class:`PeopleService` (see the
service's overview in :mod:`telebot.services.people`).
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

from telebot.channels.channel import ReceivedDatagram
from telebot.channels.transports.base import Lane
from telebot.config import PeopleSettings
from telebot.errors import TelebotError
from telebot.robot.nav import normalize_angle
from telebot.robot.perception.runner import PeoplePerception
from telebot.robot.perception.tracks import PersonTrack
from telebot.services.base import HostService, RobotHost
from telebot.services.people.wire import (
    MAX_SEQ,
    PEOPLE,
    PeopleAlertMessage,
    PeopleUpdate,
    TrackInfo,
)

if TYPE_CHECKING:
    from telebot.channels.call import Call

__all__ = ["ALERT_REPEATS", "PeopleService", "RobotPeople"]

log = logging.getLogger(__name__)

#: Times each alert is sent (on consecutive stream ticks).
ALERT_REPEATS = 3


class RobotPeople(HostService[RobotHost]):
    """The ``people`` service on a robot: its people tracker, and each call's stream."""

    def __init__(self, host: RobotHost) -> None:
        super().__init__(host)
        #: Person detection and tracking (``[people]``), stepped with the robot.
        self.perception = PeoplePerception(host.nav, host.config.get("people", PeopleSettings))

    def tracks(self) -> list[PersonTrack]:
        """The people tracked now (what follow-me follows)."""
        return self.perception.tracks()

    def tick(self, now: float) -> None:
        """Look at the sensors' new data."""
        self.perception.step(now)

    def open(self, call: Call) -> PeopleService:
        """The ``people`` stream of ``call``."""
        return PeopleService(self.perception, self.host, call)

    def close(self) -> None:
        """Stop the detector thread."""
        self.perception.close()


class PeopleService:
    """The robot's ``people`` service on one call (see the module docstring)."""

    def __init__(self, perception: PeoplePerception, server: RobotHost, call: Call) -> None:
        self.perception = perception
        self.call = call
        self.channel = call.channel(PEOPLE, lane=Lane.DATA)
        self.channel.set_callback(self._on_datagram)
        self._period = 1.0 / self.perception.settings.stream_hz
        self._next = -math.inf
        self._seq = 0
        # Alerts raised since the call opened are sent; older ones are history.
        self._alert_after = self.perception.alerts[-1].seq if self.perception.alerts else 0
        self._repeats: dict[int, int] = {}
        self._cameras = {info.name: info.fov_deg for info in server.nav.cameras()}
        #: Datagrams from the user (nothing is expected of it): dropped.
        self.rejected = 0

    def tick(self, now: float) -> None:
        """Send the tracks (and new alerts) when due."""
        if now < self._next or not self.perception.settings.enabled:
            return
        self._next = now + self._period
        pose = self.perception.nav.pose().pose
        tracks = []
        for t in self.perception.tracks():
            dx, dy = t.x - pose.x, t.y - pose.y
            tracks.append(
                TrackInfo(
                    t.id,
                    t.x,
                    t.y,
                    t.vx,
                    t.vy,
                    t.confidence,
                    tuple(sorted(t.sources)),
                    math.hypot(dx, dy),
                    normalize_angle(math.atan2(dy, dx) - pose.yaw),
                )
            )
        self._seq = self._seq % MAX_SEQ + 1
        self._send(PeopleUpdate(self._seq, now, tuple(tracks), self._cameras).encode())
        for numbered in self.perception.alerts:
            if numbered.seq <= self._alert_after:
                continue
            sent = self._repeats.get(numbered.seq, 0)
            if sent >= ALERT_REPEATS:
                continue
            self._repeats[numbered.seq] = sent + 1
            alert = numbered.alert
            message = PeopleAlertMessage(
                numbered.seq, alert.kind, alert.track, alert.text, alert.distance, alert.bearing
            )
            self._send(message.encode())
        # Forget what fell out of the perception's window.
        oldest = self.perception.alerts[0].seq if self.perception.alerts else 0
        for seq in [s for s in self._repeats if s < oldest]:
            del self._repeats[seq]

    def close(self) -> None:
        """Nothing to end: the call's channels go with it."""
        self.channel.set_callback(None)

    def _on_datagram(self, datagram: ReceivedDatagram) -> None:
        self.rejected += 1
        self.channel.stats.rejected += 1

    def _send(self, text: str) -> None:
        if not self.call.active:
            return
        try:
            self.channel.send(text)
        except TelebotError as exc:  # the call ended under us: its end is reported apart
            log.debug("call %s: people not sent: %s", self.call.id, exc)
