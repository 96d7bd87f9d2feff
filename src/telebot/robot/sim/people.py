"""Simulated people: walkers on scripted paths, two legs for the laser, a figure for the cameras.

A :class:`Walker` is a script: waypoints in the map frame, a walking speed, a pause (standing
still) at any waypoint, and it stops at the last one. Its state is a pure function of the time
since it was added (:meth:`Walker.state_at`), so a run is deterministic and a test can ask
where anybody will be.

For the laser a person is two legs: circles of :data:`LEG_RADIUS` at laser height, side by side
:data:`LEG_GAP` apart when standing, and swinging fore and aft in anti-phase while walking
(one full gait cycle every :data:`STRIDE` metres), as a leg detector sees them. Legs are
ordinary :class:`~telebot.robot.sim.world.Obstacle` circles, so the laser, the robot's physics
guard and its obstacle stop treat them like any other obstacle.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable
from dataclasses import dataclass, field

from telebot.robot.sim.world import Obstacle

__all__ = [
    "LEG_GAP",
    "LEG_RADIUS",
    "STRIDE",
    "PersonState",
    "PersonTruth",
    "Walker",
    "Waypoint",
    "legs_of",
]

#: Radius of a leg at laser height (metres).
LEG_RADIUS = 0.06
#: Distance between the two legs' centres, side to side (metres).
LEG_GAP = 0.22
#: Distance walked in one full gait cycle (two steps), metres.
STRIDE = 1.3
#: How far a leg swings ahead of (and behind) the hip at laser height while walking (metres).
SWING = 0.1
#: Height of the legs as obstacles (for the cameras, which draw people as figures anyway).
LEG_HEIGHT = 0.9
#: Walking speeds accepted (metres a second): slow shuffle to a brisk walk.
MIN_SPEED, MAX_SPEED = 0.1, 2.5


@dataclass(frozen=True, slots=True)
class Waypoint:
    """A point of a walker's path (map frame) and how long it stands there on arrival."""

    x: float
    y: float
    #: Seconds standing still here once arrived (at the last waypoint it stands for good).
    pause: float = 0.0

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.x, self.y, self.pause)):
            raise ValueError("waypoint coordinates and pause must be finite")
        if self.pause < 0:
            raise ValueError(f"waypoint pause must be ≥ 0, not {self.pause}")


@dataclass(frozen=True, slots=True)
class PersonState:
    """Where a walker is at one moment (map frame)."""

    x: float
    y: float
    #: Facing (radians, CCW from +x): the way it walks, or last walked.
    yaw: float
    vx: float
    vy: float
    walking: bool
    #: Metres walked so far (sets the gait phase).
    travelled: float


@dataclass(frozen=True, slots=True)
class PersonTruth:
    """Ground truth of a simulated person, for tests and benchmarks."""

    id: int
    x: float
    y: float
    yaw: float
    vx: float
    vy: float
    walking: bool
    legs: tuple[Obstacle, Obstacle]
    walker: Walker
    #: Metres walked so far (the gait phase, for the cameras' figure).
    travelled: float = 0.0


def _segments(points: tuple[Waypoint, ...]) -> tuple[tuple[float, float, float], ...]:
    """Per segment: length, heading, and the pause at its far end."""
    out = []
    for a, b in itertools.pairwise(points):
        length = math.hypot(b.x - a.x, b.y - a.y)
        out.append((length, math.atan2(b.y - a.y, b.x - a.x), b.pause))
    return tuple(out)


@dataclass(frozen=True, slots=True)
class Walker:
    """A scripted person (see the module docstring).

    ``start_delay`` seconds standing at the first waypoint (plus its ``pause``) before walking;
    ``yaw`` is the facing while nothing sets it (a walker with one waypoint stands there
    facing ``yaw``). ``shirt_bgr`` and ``trousers_bgr`` colour the figure in the cameras.
    ``loop``: from the last waypoint it walks back to the first (pausing there its
    ``pause``) and round again, for ever, instead of standing at the last.
    """

    waypoints: tuple[Waypoint, ...]
    speed: float = 1.2
    start_delay: float = 0.0
    yaw: float = 0.0
    height: float = 1.75
    shirt_bgr: tuple[int, int, int] = (150, 60, 30)
    trousers_bgr: tuple[int, int, int] = (40, 35, 30)
    loop: bool = False
    _segs: tuple[tuple[float, float, float], ...] = field(
        init=False, repr=False, compare=False, default=()
    )

    def __post_init__(self) -> None:
        if not self.waypoints:
            raise ValueError("a walker needs at least one waypoint")
        if not (math.isfinite(self.speed) and MIN_SPEED <= self.speed <= MAX_SPEED):
            raise ValueError(
                f"walking speed must be {MIN_SPEED:g} … {MAX_SPEED:g} m/s, not {self.speed}"
            )
        if not (math.isfinite(self.start_delay) and self.start_delay >= 0):
            raise ValueError(f"start delay must be ≥ 0 s, not {self.start_delay}")
        if not (math.isfinite(self.yaw) and math.isfinite(self.height)):
            raise ValueError("walker yaw and height must be finite")
        if not 1.0 <= self.height <= 2.2:
            raise ValueError(f"walker height must be 1.0 … 2.2 m, not {self.height}")
        points = (*self.waypoints, self.waypoints[0]) if self.loop else self.waypoints
        segs = _segments(points)
        if self.loop and not any(length > 0 for length, _, _ in segs):
            raise ValueError("a looping walker needs two different waypoints")
        object.__setattr__(self, "_segs", segs)

    @classmethod
    def along(
        cls,
        points: Iterable[tuple[float, float] | tuple[float, float, float]],
        *,
        speed: float = 1.2,
        **kwargs: object,
    ) -> Walker:
        """A walker through ``(x, y)`` or ``(x, y, pause_s)`` points; keywords as the class."""
        waypoints = tuple(Waypoint(*p) for p in points)
        return cls(waypoints, speed, **kwargs)  # type: ignore[arg-type]

    @classmethod
    def standing(cls, x: float, y: float, yaw: float = 0.0, **kwargs: object) -> Walker:
        """A person standing at ``(x, y)`` facing ``yaw`` for good."""
        return cls((Waypoint(x, y),), yaw=yaw, **kwargs)  # type: ignore[arg-type]

    @property
    def duration(self) -> float:
        """Seconds from being added to arriving at the last waypoint (for good); a loop
        never arrives: infinite."""
        if self.loop:
            return math.inf
        total = self.start_delay + self.waypoints[0].pause
        for length, _, pause in self._segs[:-1]:
            total += length / self.speed + pause
        if self._segs:
            total += self._segs[-1][0] / self.speed
        return total

    def state_at(self, elapsed: float) -> PersonState:
        """Where the walker is ``elapsed`` seconds after it was added."""
        first = self.waypoints[0]
        yaw = self._segs[0][1] if self._segs else self.yaw
        t = elapsed - self.start_delay - first.pause
        x, y, travelled = first.x, first.y, 0.0
        if t <= 0.0:
            return PersonState(x, y, yaw, 0.0, 0.0, False, 0.0)
        if self.loop:
            # One round: every segment walked and every pause stood, the first's last.
            period = sum(length / self.speed + pause for length, _, pause in self._segs)
            laps = math.floor(t / period)
            t -= laps * period
            travelled = laps * sum(length for length, _, _ in self._segs)
        last = -1 if self.loop else len(self._segs) - 1
        for index, (length, heading, pause) in enumerate(self._segs):
            walk = length / self.speed
            yaw = heading if length > 0 else yaw
            if t < walk:
                frac = t * self.speed
                c, s = math.cos(heading), math.sin(heading)
                return PersonState(
                    x + frac * c,
                    y + frac * s,
                    yaw,
                    self.speed * c,
                    self.speed * s,
                    True,
                    travelled + frac,
                )
            t -= walk
            travelled += length
            end = self.waypoints[(index + 1) % len(self.waypoints)]
            x, y = end.x, end.y
            if index == last:
                break
            if t < pause:
                return PersonState(x, y, yaw, 0.0, 0.0, False, travelled)
            t -= pause
        return PersonState(x, y, yaw, 0.0, 0.0, False, travelled)


def legs_of(state: PersonState) -> tuple[Obstacle, Obstacle]:
    """The two legs (laser height circles) of a person in ``state``."""
    c, s = math.cos(state.yaw), math.sin(state.yaw)
    # Walking, one leg is ahead while the other is behind, sinusoidally along the gait;
    # standing, they are side by side.
    swing = SWING * math.sin(2.0 * math.pi * state.travelled / STRIDE) if state.walking else 0.0
    half = LEG_GAP / 2.0
    left = Obstacle(
        state.x + swing * c - half * s,
        state.y + swing * s + half * c,
        LEG_RADIUS,
        LEG_HEIGHT,
    )
    right = Obstacle(
        state.x - swing * c + half * s,
        state.y - swing * s - half * c,
        LEG_RADIUS,
        LEG_HEIGHT,
    )
    return left, right
