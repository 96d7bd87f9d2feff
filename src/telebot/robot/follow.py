"""Follow-me: the sans-IO controller that keeps the robot behind a walking person.

:class:`FollowController` is fed, once per control cycle, with the people tracks (anything
shaped like :class:`Track`: id, map-frame position and velocity, last time seen), the
robot's pose, the speed cap in force, what the laser says about the way ahead, and
``now``. It answers with a :class:`Drive` (the velocity to command) or, once, with an
:class:`Ended` (a reason code and a sentence). It imports no clock and no transport, so
every rule is tested with plain numbers.

Rules:

- **Follow the person's way, not the crow's.** The person's smoothed positions are kept as
  a trail of breadcrumbs and the robot steers along it, so it goes through the door the
  person took instead of cutting the corner into the wall.
- **Keep the distance** (``[follow] distance``, 1.2 m, measured along the trail): the
  speed is the person's speed plus a term that closes the gap, within the cap.
- **Never closer than ``min_distance``** (0.6 m): the speed is always low enough to brake
  before it, and a person inside it ends the follow ("person too close").
- **Stop when the person stops**, and turn on the spot to keep them in front (in the
  usercam's view). Then **settle at the distance**: braking from walking pace takes the
  robot nearer than ``distance`` (or it stopped further back), so once the person stands
  it moves until the straight-line distance, centre to centre, is within
  :data:`SETTLED` of ``distance``: forward along the trail, or slowly backwards (only where
  the laser sees the space behind it free). It moves again only when the distance leaves
  ``distance`` ± :data:`SETTLE_TOLERANCE`.
- **A jumping track never makes it lunge**: a measurement further than ``max_jump`` from
  where the person should be is ignored; the velocity changes only within the robot's
  acceleration limits; a person seen only jumping for ``lost_after`` is lost.
- **Obstacles**: the speed lets the robot brake before anything the laser sees ahead
  (besides the person); held up for ``obstacle_timeout`` while the person walks on, the
  follow ends ("obstacle").
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Protocol, TypeAlias

import numpy as np
import numpy.typing as npt

from telebot.config import FollowSettings
from telebot.reasons import Reason
from telebot.robot.nav import MotionLimits, Pose2D, Velocity, normalize_angle

__all__ = [
    "Drive",
    "Ended",
    "FollowController",
    "FollowUpdate",
    "Track",
    "clearance_ahead",
    "clearance_behind",
    "pick_target",
]

#: Breadcrumbs are dropped this far apart (m).
CRUMB_SPACING = 0.15
#: A breadcrumb the robot comes this near is passed (m).
CRUMB_REACHED = 0.35
#: The robot steers at the first breadcrumb at least this far away (m).
LOOKAHEAD = 0.6
#: Gain from distance error (m) to speed (m/s), and from heading error (rad) to turn (rad/s).
DISTANCE_GAIN = 0.8
HEADING_GAIN = 2.0
#: Heading error beyond which the robot turns on the spot before driving (rad).
TURN_IN_PLACE = math.radians(60.0)
#: Kept between the braking point and ``min_distance`` or an obstacle (m).
BRAKING_MARGIN = 0.1
#: Weight of a new measurement in the smoothed position and velocity (0 … 1).
SMOOTHING = 0.5
#: A standing person nearer or further than ``distance`` ± this (m, centre to centre) makes
#: the robot move to settle again …
SETTLE_TOLERANCE = 0.1
#: … until it is within this (m) of ``distance``.
SETTLED = 0.02
#: Settling speed: at least this (m/s), so that it ends, …
SETTLE_CREEP = 0.05
#: … and backwards at most this (m/s): the robot does not look where it reverses.
BACK_OFF_SPEED = 0.15
#: Beams this close to straight behind (rad) are what says the space behind is seen.
REAR_VIEW = math.radians(10.0)
#: An obstacle hold ends only after this long without one (s).
UNBLOCKED_AFTER = 0.5
#: Longest time step the controller integrates at once (s): a stalled loop must not turn
#: into one big velocity change.
MAX_DT = 0.2


class Track(Protocol):
    """What the controller needs of a person track (the people tracker's ``PersonTrack``)."""

    @property
    def id(self) -> int:
        """The track's id, stable while the person is tracked."""
        ...

    @property
    def x(self) -> float:
        """Position in the map frame (m)."""
        ...

    @property
    def y(self) -> float:
        """Position in the map frame (m)."""
        ...

    @property
    def vx(self) -> float:
        """Velocity in the map frame (m/s)."""
        ...

    @property
    def vy(self) -> float:
        """Velocity in the map frame (m/s)."""
        ...

    @property
    def last_seen(self) -> float:
        """When a detector last saw the person (the clock of ``now``)."""
        ...


@dataclass(frozen=True, slots=True)
class Drive:
    """Keep following: command this velocity now."""

    linear: float
    angular: float
    #: Straight-line distance to the person (m), as smoothed.
    distance: float
    #: Whether the person stands (the robot waits for them).
    waiting: bool = False


@dataclass(frozen=True, slots=True)
class Ended:
    """The follow is over: stop the robot, and tell the driver why."""

    code: Reason
    text: str


#: What :meth:`FollowController.update` answers.
FollowUpdate: TypeAlias = Drive | Ended


def pick_target(tracks: Iterable[Track], pose: Pose2D, settings: FollowSettings) -> Track | None:
    """The nearest person in front of the robot (within ``start_range`` and
    ``front_angle_deg`` either side of its heading), or None."""
    best: Track | None = None
    best_distance = math.inf
    half_angle = math.radians(settings.front_angle_deg)
    for track in tracks:
        dx, dy = track.x - pose.x, track.y - pose.y
        distance = math.hypot(dx, dy)
        if not math.isfinite(distance) or distance > settings.start_range:
            continue
        if abs(normalize_angle(math.atan2(dy, dx) - pose.yaw)) > half_angle:
            continue
        if distance < best_distance:
            best, best_distance = track, distance
    return best


def clearance_ahead(
    points: npt.NDArray[np.float64],
    radius: float,
    person: tuple[float, float] | None = None,
    person_radius: float = 0.35,
) -> float:
    """Free distance straight ahead of a round base (m), from laser hits in its own frame.

    ``points``: ``(N, 2)`` hits (x forward, y left) in the base frame; ``radius``: the
    base's; ``person``: the followed person's position in the same frame, whose own hits
    (legs, body) within ``person_radius`` do not count as obstacles. Infinite when clear.
    """
    if points.size == 0:
        return math.inf
    ahead = points[:, 0]
    mask = (ahead > 0.0) & (np.abs(points[:, 1]) < radius)
    if person is not None:
        near = np.hypot(points[:, 0] - person[0], points[:, 1] - person[1]) < person_radius
        mask &= ~near
    if not mask.any():
        return math.inf
    # The disc touches a hit at lateral offset s when its centre is sqrt(r² − s²) short of it.
    side = points[mask, 1]
    reach = points[mask, 0] - np.sqrt(np.maximum(radius * radius - side * side, 0.0))
    return max(float(reach.min()), 0.0)


def clearance_behind(
    points: npt.NDArray[np.float64],
    radius: float,
    angles: npt.NDArray[np.float64],
    returned: npt.NDArray[np.bool_],
) -> float:
    """Free distance straight behind a round base (m), as :func:`clearance_ahead` ahead.

    ``angles``: the beams of the scan the ``points`` came from; ``returned``: which of them
    hit something within range. The laser must see straight behind: with no beam within
    :data:`REAR_VIEW` of it, or one there that brought nothing back (a covered laser, a
    sector masked off, a reading too close to measure all look like that), nothing is
    known free: 0.
    """
    rear = np.abs(angles) >= math.pi - REAR_VIEW
    if not rear.any() or not returned[rear].all():
        return 0.0
    return clearance_ahead(-points, radius)


class FollowController:
    """Follows one track (see the module docstring); one instance per follow."""

    def __init__(
        self,
        target_id: int,
        settings: FollowSettings,
        limits: MotionLimits,
        *,
        now: float,
        velocity: Velocity | None = None,
    ) -> None:
        if settings.min_distance >= settings.distance:
            raise ValueError(
                f"follow min_distance ({settings.min_distance:g} m) must be below "
                f"distance ({settings.distance:g} m)"
            )
        self.target_id = target_id
        self.settings = settings
        self.limits = limits
        self._last = float(now)
        start = velocity if velocity is not None else Velocity()
        self._command = Velocity(start.linear, start.angular)
        # Smoothed position and velocity of the person; None until first seen.
        self._position: tuple[float, float] | None = None
        # The latest accepted measurement as it came: "too close" must not wait for smoothing.
        self._raw: tuple[float, float] | None = None
        self._velocity = (0.0, 0.0)
        self._seen = float(now)  # last accepted measurement (the start counts as one)
        self._last_stamp = -math.inf
        self._trail: deque[tuple[float, float]] = deque()
        self._held_since: float | None = None
        self._clear_since: float | None = None
        # Settling at the distance from a standing person: +1 forward, -1 backward, 0 not.
        self._settling = 0
        self._ended: Ended | None = None
        #: Measurements ignored as jumps (detector errors).
        self.jumps = 0

    @property
    def ended(self) -> Ended | None:
        """Why the follow ended, once it has."""
        return self._ended

    @property
    def person(self) -> tuple[float, float] | None:
        """The person's smoothed position, once seen."""
        return self._position

    @property
    def trail(self) -> Sequence[tuple[float, float]]:
        """The breadcrumbs the robot is still to pass (oldest first)."""
        return tuple(self._trail)

    def update(
        self,
        tracks: Iterable[Track],
        pose: Pose2D,
        *,
        cap: float,
        now: float,
        clearance: float = math.inf,
        behind: float = 0.0,
        blocked: bool = False,
    ) -> FollowUpdate:
        """One control cycle: the velocity to command, or why the follow ends.

        ``cap``: the linear speed cap in force (safety and link); ``clearance``: free
        distance ahead of the base, the person aside (:func:`clearance_ahead`); ``behind``:
        free distance behind it (:func:`clearance_behind`; 0, the default: unknown, it
        never backs off); ``blocked``: the robot reports an obstacle holding it up. Once
        ended, it stays ended and answers the same :class:`Ended`.
        """
        if self._ended is not None:
            return self._ended
        if not all(math.isfinite(v) for v in (now, pose.x, pose.y, pose.yaw)):
            return self._end(Reason.INVALID, "the robot's pose or clock is not a finite number")
        dt = min(max(now - self._last, 0.0), MAX_DT)
        self._last = max(self._last, now)
        self._observe(tracks, now, dt)
        if now - self._seen >= self.settings.lost_after or self._position is None:
            return self._end(Reason.LOST_PERSON, "lost the person")
        px, py = self._position
        distance = math.hypot(px - pose.x, py - pose.y)
        raw = self._raw if self._raw is not None else self._position
        if min(distance, math.dist(raw, (pose.x, pose.y))) < self.settings.min_distance:
            return self._end(Reason.PERSON_TOO_CLOSE, "person too close")
        self._update_trail(pose)
        linear, angular, wanted, waiting = self._wanted(pose, distance, cap, clearance, behind)
        held = (blocked or clearance <= BRAKING_MARGIN) and wanted
        if held:
            self._clear_since = None
            if self._held_since is None:
                self._held_since = now
            elif now - self._held_since >= self.settings.obstacle_timeout:
                return self._end(Reason.OBSTACLE, "obstacle")
            linear = 0.0
        elif self._held_since is not None:
            # A base held still flickers between blocked and clear (it is blocked only
            # while it tries to move): clear means clear for a while.
            if self._clear_since is None:
                self._clear_since = now
            elif now - self._clear_since >= UNBLOCKED_AFTER:
                self._held_since = self._clear_since = None
        command = self._limit(Velocity(linear, angular), dt)
        self._command = command
        return Drive(command.linear, command.angular, distance, waiting)

    # -- internals -------------------------------------------------------------------

    def _end(self, code: Reason, text: str) -> Ended:
        self._ended = Ended(code, text)
        self._command = Velocity()
        return self._ended

    def _observe(self, tracks: Iterable[Track], now: float, dt: float) -> None:
        """Take in the target's measurement, unless it is stale, a repeat or a jump."""
        track = next((t for t in tracks if t.id == self.target_id), None)
        if track is None:
            self._coast(dt)
            return
        values = (track.x, track.y, track.vx, track.vy, track.last_seen)
        if not all(math.isfinite(v) for v in values):
            self._coast(dt)
            return
        stamp = float(track.last_seen)
        if now - stamp >= self.settings.lost_after or stamp <= self._last_stamp:
            self._coast(dt)  # no new sighting: the tracker only predicts
            return
        vx, vy = float(track.vx), float(track.vy)
        if self._position is None:
            self._position, self._velocity = (float(track.x), float(track.y)), (vx, vy)
            self._raw = self._position
            self._seen, self._last_stamp = now, stamp
            return
        self._coast(dt)
        ex, ey = self._position
        if math.hypot(track.x - ex, track.y - ey) > self.settings.max_jump:
            self.jumps += 1
            return
        a = SMOOTHING
        self._raw = (float(track.x), float(track.y))
        self._position = (ex + a * (track.x - ex), ey + a * (track.y - ey))
        ovx, ovy = self._velocity
        self._velocity = (ovx + a * (vx - ovx), ovy + a * (vy - ovy))
        self._seen, self._last_stamp = now, stamp

    def _coast(self, dt: float) -> None:
        if self._position is None:
            return
        vx, vy = self._velocity
        x, y = self._position
        self._position = (x + vx * dt, y + vy * dt)

    def _update_trail(self, pose: Pose2D) -> None:
        assert self._position is not None
        trail = self._trail
        if not trail or math.dist(trail[-1], self._position) >= CRUMB_SPACING:
            trail.append(self._position)
        here = (pose.x, pose.y)
        while len(trail) >= 2 and (
            math.dist(here, trail[0]) < CRUMB_REACHED
            or math.dist(here, trail[1]) < math.dist(here, trail[0])
        ):
            trail.popleft()

    def _wanted(
        self, pose: Pose2D, distance: float, cap: float, clearance: float, behind: float
    ) -> tuple[float, float, bool, bool]:
        """(speed, turn) before the acceleration limits, whether the robot wants to move
        ahead (the person is far enough ahead), and whether it waits for a standing person."""
        settings, limits = self.settings, self.limits
        assert self._position is not None
        here = (pose.x, pose.y)
        # Along the trail: to the first crumb, crumb to crumb, last crumb to the person.
        points = [here, *self._trail, self._position]
        along = sum(math.dist(a, b) for a, b in itertools.pairwise(points))
        aim = next((c for c in self._trail if math.dist(here, c) >= LOOKAHEAD), self._position)
        speed = math.hypot(*self._velocity)
        waiting = speed < settings.standing_speed
        if waiting:
            linear = self._settle(distance - settings.distance)
            want = linear > 0.0
            aim = aim if want else self._position
        else:
            self._settling = 0
            gap = along - settings.distance
            want = gap > 0.0
            # Never backwards after a walking person: it only backs off from one standing.
            linear = max(speed + DISTANCE_GAIN * gap, 0.0)
        error = normalize_angle(math.atan2(aim[1] - pose.y, aim[0] - pose.x) - pose.yaw)
        top_turn = limits.max_angular_speed
        angular = max(-top_turn, min(top_turn, HEADING_GAIN * error))
        fastest = max(0.0, min(cap, settings.max_speed, limits.max_linear_speed))
        # Always slow enough to brake before min_distance and before what the laser sees;
        # backwards (away from the person), before what it sees behind.
        room = min(distance - settings.min_distance, clearance) - BRAKING_MARGIN
        # 0.8: the bound falls no faster than the acceleration limit lets the speed fall.
        top = min(fastest, math.sqrt(2.0 * 0.8 * limits.linear_accel * max(room, 0.0)))
        back_room = max(behind - BRAKING_MARGIN, 0.0)
        back = min(fastest, BACK_OFF_SPEED, math.sqrt(2.0 * 0.8 * limits.linear_accel * back_room))
        linear = max(-back, min(linear, top))
        if abs(error) >= TURN_IN_PLACE:
            linear = 0.0
        else:
            linear *= math.cos(error)
        return linear, angular, want, waiting

    def _settle(self, gap: float) -> float:
        """The speed that brings the robot to ``distance`` from a standing person, ``gap``
        (m) being how much further than that it is now (straight line, centre to centre)."""
        if self._settling == 0 and abs(gap) > SETTLE_TOLERANCE:
            self._settling = 1 if gap > 0.0 else -1
        if self._settling * gap <= SETTLED:
            self._settling = 0  # settled (or overshot: then it stops, never hunts)
            return 0.0
        return math.copysign(max(DISTANCE_GAIN * abs(gap), SETTLE_CREEP), gap)

    def _limit(self, wanted: Velocity, dt: float) -> Velocity:
        """The acceleration limits: no command differs from the last by more than allowed."""
        last = self._command
        dv = self.limits.linear_accel * dt
        dw = self.limits.angular_accel * dt
        linear = min(max(wanted.linear, last.linear - dv), last.linear + dv)
        angular = min(max(wanted.angular, last.angular - dw), last.angular + dw)
        return Velocity(linear, angular)
