"""People alerts for the remote user (sans-IO): someone approaching, someone at the screen.

:class:`AlertWatcher` is fed the robot's pose and the confirmed tracks at each update and
returns the new alerts:

* ``approaching``: a track comes within ``alert_distance`` of the robot while closing in
  (its velocity points at the robot at :data:`CLOSING_SPEED` or more): "person approaching
  from the left, 2.1 m". Once per track until it has gone :data:`REARM_MARGIN` beyond the
  distance again.
* ``screen``: a track stands (slower than :data:`STANDING_SPEED`) within ``screen_distance``
  in front of the usercam (within :data:`SCREEN_HALF_ANGLE` of the heading, which the usercam
  faces) for ``screen_seconds``: "someone is in front of the screen". Once per track until
  it leaves.

The side is the bearing from the robot's heading: ahead within ±30°, behind beyond ±150°,
left or right between.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from telebot.robot.nav import Pose2D, normalize_angle
from telebot.robot.perception.tracks import PersonTrack

__all__ = ["APPROACHING", "SCREEN", "AlertWatcher", "PeopleAlert", "side_of"]

APPROACHING = "approaching"
SCREEN = "screen"
#: Metres a second towards the robot that count as approaching.
CLOSING_SPEED = 0.15
#: A track must go this much (m) beyond a distance before it can alert again.
REARM_MARGIN = 0.5
#: Slower than this (m/s) a person stands.
STANDING_SPEED = 0.3
#: Half the angle in front of the usercam that counts as "in front of the screen".
SCREEN_HALF_ANGLE = math.radians(35.0)


@dataclass(frozen=True, slots=True)
class PeopleAlert:
    """One alert: its kind, the track, the text for people, distance (m) and bearing (rad)."""

    kind: str
    track: int
    text: str
    distance: float
    bearing: float


def side_of(bearing: float) -> str:
    """Where ``bearing`` (radians from the heading, left positive) is: words for people."""
    deg = math.degrees(normalize_angle(bearing))
    if abs(deg) <= 30.0:
        return "ahead"
    if abs(deg) >= 150.0:
        return "behind"
    return "the left" if deg > 0 else "the right"


class AlertWatcher:
    """Turns tracks into alerts (see the module docstring)."""

    def __init__(
        self, alert_distance: float, screen_distance: float, screen_seconds: float
    ) -> None:
        self.alert_distance = alert_distance
        self.screen_distance = screen_distance
        self.screen_seconds = screen_seconds
        self._near: set[int] = set()  # tracks alerted as approaching, not re-armed yet
        self._standing_since: dict[int, float] = {}
        self._at_screen: set[int] = set()

    def update(self, now: float, pose: Pose2D, tracks: Sequence[PersonTrack]) -> list[PeopleAlert]:
        """The alerts that ``tracks`` raise at ``now`` with the robot at ``pose``."""
        alerts: list[PeopleAlert] = []
        seen: set[int] = set()
        for track in tracks:
            seen.add(track.id)
            dx, dy = track.x - pose.x, track.y - pose.y
            distance = math.hypot(dx, dy)
            bearing = normalize_angle(math.atan2(dy, dx) - pose.yaw)
            closing = -(track.vx * dx + track.vy * dy) / max(distance, 1e-6)
            if track.id in self._near:
                if distance > self.alert_distance + REARM_MARGIN:
                    self._near.discard(track.id)
            elif distance <= self.alert_distance and closing >= CLOSING_SPEED:
                self._near.add(track.id)
                text = f"person approaching from {side_of(bearing)}, {distance:.1f} m"
                if side_of(bearing) == "ahead":
                    text = f"person approaching ahead, {distance:.1f} m"
                alerts.append(PeopleAlert(APPROACHING, track.id, text, distance, bearing))
            in_front = (
                distance <= self.screen_distance
                and abs(bearing) <= SCREEN_HALF_ANGLE
                and track.speed < STANDING_SPEED
            )
            if not in_front:
                self._standing_since.pop(track.id, None)
                leaving = distance > self.screen_distance + REARM_MARGIN
                if leaving or abs(bearing) > SCREEN_HALF_ANGLE:
                    self._at_screen.discard(track.id)
                continue
            since = self._standing_since.setdefault(track.id, now)
            if track.id not in self._at_screen and now - since >= self.screen_seconds:
                self._at_screen.add(track.id)
                alerts.append(
                    PeopleAlert(
                        SCREEN, track.id, "someone is in front of the screen", distance, bearing
                    )
                )
        # Forget tracks that are gone.
        self._near &= seen
        self._at_screen &= seen
        for gone in set(self._standing_since) - seen:
            del self._standing_since[gone]
        return alerts
