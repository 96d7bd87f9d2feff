"""Motion control of a differential-drive base: path following, straight moves, turns.

Pure functions of (pose, velocity, goal geometry) → the velocity to command next. The base
model (:class:`DiffDriveBase`) applies the speed and acceleration limits and the
``cmd_vel`` watchdog, and integrates the pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from telebot.robot.nav import Pose2D, Velocity, normalize_angle

__all__ = [
    "DiffDriveBase",
    "Limits",
    "PathTracker",
    "braking_speed",
    "rotate_command",
    "straight_command",
]

#: Heading error beyond which the base turns on the spot before driving on (radians).
ROTATE_IN_PLACE_ABOVE = math.radians(40.0)
#: Distance ahead on the path the pure-pursuit controller steers towards (metres).
LOOKAHEAD = 0.6
#: Proportional gain of heading corrections (1/s).
HEADING_GAIN = 2.5
#: Share of the base's deceleration a path plans to brake with into its goal. The rest
#: is reserve: the base answers a command one control step late, and the way left
#: shrinks faster than the base drives while it cuts the path's last corner.
BRAKING_SHARE = 0.8


@dataclass(frozen=True, slots=True)
class Limits:
    """Speed and acceleration limits of the base (SI units)."""

    linear_speed: float
    angular_speed: float
    linear_accel: float
    angular_accel: float


def braking_speed(distance: float, accel: float) -> float:
    """Highest speed from which the base can still stop within ``distance``."""
    return math.sqrt(2.0 * accel * max(distance, 0.0))


def rotate_command(heading_error: float, limits: Limits) -> float:
    """Angular velocity that turns through ``heading_error`` and stops there without overshoot."""
    # Braking-limited: |w| ≤ sqrt(2·α·|err|) so the turn decelerates into the target.
    magnitude = min(
        HEADING_GAIN * abs(heading_error),
        braking_speed(abs(heading_error), limits.angular_accel),
        limits.angular_speed,
    )
    return math.copysign(magnitude, heading_error)


def straight_command(
    pose: Pose2D, start: Pose2D, distance: float, limits: Limits
) -> tuple[Velocity, float]:
    """Command for driving ``distance`` metres along ``start``'s heading (negative: backwards).

    Returns the velocity and the signed distance still to go along the line.
    """
    ux, uy = math.cos(start.yaw), math.sin(start.yaw)
    along = (pose.x - start.x) * ux + (pose.y - start.y) * uy
    remaining = distance - along
    lateral = -(pose.x - start.x) * uy + (pose.y - start.y) * ux
    direction = 1.0 if remaining >= 0 else -1.0
    speed = min(limits.linear_speed, braking_speed(abs(remaining), limits.linear_accel))
    # Steer back onto the line: heading error plus a term for the sideways offset, whose
    # sign flips when reversing so the correction still converges.
    heading_error = normalize_angle(start.yaw - pose.yaw) - direction * 1.5 * lateral
    angular = max(-limits.angular_speed, min(limits.angular_speed, HEADING_GAIN * heading_error))
    return Velocity(direction * speed, angular), remaining


@dataclass(slots=True)
class PathTracker:
    """Pure-pursuit tracking of a planned path, with progress measured along it."""

    waypoints: npt.NDArray[np.float64]
    _cumulative: npt.NDArray[np.float64] = field(init=False)
    _index: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        steps = np.hypot(*np.diff(self.waypoints, axis=0).T) if len(self.waypoints) > 1 else []
        self._cumulative = np.concatenate([[0.0], np.cumsum(steps)])

    @property
    def length(self) -> float:
        """Path length in metres."""
        return float(self._cumulative[-1])

    @property
    def goal(self) -> tuple[float, float]:
        """The path's last point."""
        return float(self.waypoints[-1, 0]), float(self.waypoints[-1, 1])

    def travelled(self, pose: Pose2D) -> float:
        """Distance along the path to the point nearest ``pose`` (searched ahead only)."""
        # Search a window ahead of the last match only, so a path that doubles back near
        # itself cannot make progress jump.
        hi = min(self._index + 40, len(self.waypoints))
        window = self.waypoints[self._index : hi]
        dists = np.hypot(window[:, 0] - pose.x, window[:, 1] - pose.y)
        self._index += int(np.argmin(dists))
        # Project onto the nearer of the segments before and after the nearest waypoint:
        # the one after alone would put a base still short of that waypoint on it, and
        # progress would jump by a segment at a time (braking into the goal needs it smooth).
        best_along, best_gap = float(self._cumulative[self._index]), math.inf
        for first in (self._index - 1, self._index):
            if first < 0 or first + 1 >= len(self.waypoints):
                continue
            ax, ay = self.waypoints[first]
            bx, by = self.waypoints[first + 1]
            seg = math.hypot(bx - ax, by - ay)
            if seg <= 0:
                continue
            t = ((pose.x - ax) * (bx - ax) + (pose.y - ay) * (by - ay)) / (seg * seg)
            t = max(0.0, min(1.0, t))
            gap = math.hypot(pose.x - (ax + t * (bx - ax)), pose.y - (ay + t * (by - ay)))
            if gap < best_gap:
                best_along, best_gap = float(self._cumulative[first]) + t * seg, gap
        return best_along

    def remaining(self, pose: Pose2D) -> float:
        """Distance still to drive along the path from ``pose``."""
        return max(self.length - self.travelled(pose), math.hypot(*_delta(pose, self.goal)))

    def command(self, pose: Pose2D, limits: Limits) -> Velocity:
        """Pure-pursuit velocity towards the lookahead point, braking into the goal."""
        travelled = self.travelled(pose)
        target_s = min(travelled + LOOKAHEAD, self.length)
        idx = int(np.searchsorted(self._cumulative, target_s))
        idx = min(max(idx, 0), len(self.waypoints) - 1)
        if idx == 0:
            tx, ty = self.goal
        else:
            # Interpolate between the waypoints around the lookahead distance.
            s0, s1 = self._cumulative[idx - 1], self._cumulative[idx]
            t = 0.0 if s1 <= s0 else (target_s - s0) / (s1 - s0)
            p0, p1 = self.waypoints[idx - 1], self.waypoints[idx]
            tx, ty = float(p0[0] + t * (p1[0] - p0[0])), float(p0[1] + t * (p1[1] - p0[1]))
        dx, dy = tx - pose.x, ty - pose.y
        distance = math.hypot(dx, dy)
        alpha = normalize_angle(math.atan2(dy, dx) - pose.yaw)
        if abs(alpha) > ROTATE_IN_PLACE_ABOVE:
            return Velocity(0.0, rotate_command(alpha, limits))
        # Pure pursuit cuts corners, so near a corner the base drives less than the path
        # length: brake for the way it takes (straight to the lookahead point, then along
        # the path), or a corner just before the goal carries it past the goal.
        to_go = min(self.remaining(pose), distance + self.length - target_s)
        speed = min(
            limits.linear_speed * max(math.cos(alpha), 0.0),
            braking_speed(to_go, BRAKING_SHARE * limits.linear_accel),
        )
        # Pure pursuit: curvature 2·sin(α)/L through the lookahead point.
        curvature = 2.0 * math.sin(alpha) / max(distance, 1e-3)
        # Regulated pure pursuit: slow down where the curve would need more than the
        # angular limit, instead of cutting the corner.
        if abs(speed * curvature) > limits.angular_speed:
            speed = limits.angular_speed / abs(curvature)
        angular = max(-limits.angular_speed, min(limits.angular_speed, speed * curvature))
        return Velocity(speed, angular)


def _delta(pose: Pose2D, point: tuple[float, float]) -> tuple[float, float]:
    return point[0] - pose.x, point[1] - pose.y


@dataclass(slots=True)
class DiffDriveBase:
    """The simulated base: follows velocity commands within its limits, stops on a stale one.

    Like ros2_controllers' ``cmd_vel_timeout``: a command older than ``cmd_vel_timeout``
    is replaced by zero, so a dead control loop cannot leave the robot driving.
    """

    limits: Limits
    cmd_vel_timeout: float
    pose: Pose2D
    velocity: Velocity = field(default_factory=Velocity)
    command: Velocity = field(default_factory=Velocity)
    command_time: float = -math.inf
    watchdog_trips: int = 0
    _watchdog_tripped: bool = False

    def set_command(self, command: Velocity, now: float) -> None:
        """A new velocity command; it holds until ``cmd_vel_timeout`` after ``now``."""
        self.command = command
        self.command_time = now
        self._watchdog_tripped = False

    def halt(self) -> None:
        """Stop at once (the simulated brakes act within one tick) and drop the command."""
        self.command = Velocity()
        self.velocity = Velocity()

    def target(self, now: float, speed_cap: float) -> Velocity:
        """The command in force at ``now``: zero when stale, clamped to the caps."""
        if now - self.command_time > self.cmd_vel_timeout:
            if not self._watchdog_tripped and self.command != Velocity():
                self.watchdog_trips += 1
            self._watchdog_tripped = True
            return Velocity()
        cap = min(speed_cap, self.limits.linear_speed)
        return Velocity(
            max(-cap, min(cap, self.command.linear)),
            max(-self.limits.angular_speed, min(self.limits.angular_speed, self.command.angular)),
        )

    def advance(self, target: Velocity, dt: float, speed_cap: float) -> Pose2D:
        """Accelerate towards ``target`` within the limits; return the pose after ``dt``.

        The caller decides whether the new pose is free before committing it with
        :meth:`commit`.
        """
        lin = _approach(self.velocity.linear, target.linear, self.limits.linear_accel * dt)
        ang = _approach(self.velocity.angular, target.angular, self.limits.angular_accel * dt)
        # The cap is hard: a lowered cap brakes at once rather than within the accel limit.
        cap = min(speed_cap, self.limits.linear_speed)
        lin = max(-cap, min(cap, lin))
        self.velocity = Velocity(lin, ang)
        return _integrate(self.pose, lin, ang, dt)

    def commit(self, pose: Pose2D) -> None:
        """Accept the pose computed by :meth:`advance`."""
        self.pose = pose


def _approach(current: float, target: float, max_change: float) -> float:
    if target > current:
        return min(target, current + max_change)
    return max(target, current - max_change)


def _integrate(pose: Pose2D, linear: float, angular: float, dt: float) -> Pose2D:
    """Exact unicycle motion over ``dt`` at constant velocity."""
    yaw = pose.yaw
    if abs(angular) < 1e-9:
        return Pose2D(
            pose.x + linear * dt * math.cos(yaw), pose.y + linear * dt * math.sin(yaw), yaw
        )
    radius = linear / angular
    new_yaw = yaw + angular * dt
    return Pose2D(
        pose.x + radius * (math.sin(new_yaw) - math.sin(yaw)),
        pose.y - radius * (math.cos(new_yaw) - math.cos(yaw)),
        normalize_angle(new_yaw),
    )
