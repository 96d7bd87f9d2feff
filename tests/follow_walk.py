"""A scripted walker on the small map, followed by the robot: one set-up for tests and bench.

The walker starts in room A just in front of the robot, walks south out of room A's door
into the corridor, east along the corridor, north through room B's door, and stops in
room B: two rooms, two doors and a 7 m straight stretch. It stands in the simulation as a
round obstacle (the laser sees it, the base cannot drive into it) and is tracked without
error (:class:`TruthTracks`) unless a track source is given: this measures the follow
controller, not the detector. The simulation is stepped with a fast clock (numbers, no
sleeping) through :class:`~telebot.services.follow.FollowService`, the robot's own path.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from telebot.config import FollowSettings, SimSettings
from telebot.robot.nav import Pose2D
from telebot.robot.sim.stack import SimNavStack
from telebot.robot.sim.world import Obstacle
from telebot.services.follow import FollowService

#: Where the robot starts: in room A, facing south towards the walker and the door.
ROBOT_START = Pose2D(2.5, 4.4, -math.pi / 2)
#: The walker's route: room A → door A → corridor → door B → room B (metres, map frame).
ROUTE = ((2.5, 3.2), (2.5, 1.2), (9.5, 1.2), (9.5, 3.9))
#: The corridor leg, where the distance is measured once both are on it for good.
STRAIGHT = (ROUTE[1], ROUTE[2])
#: Walking speed (m/s), within the robot's 0.5 m/s.
WALK_SPEED = 0.4
PERSON_RADIUS = 0.2
CONTROL_HZ = 20.0


@dataclass(frozen=True, slots=True)
class TrackedPerson:
    """A track as the people tracker reports it (the fields follow-me reads)."""

    id: int
    x: float
    y: float
    vx: float
    vy: float
    last_seen: float


class Walker:
    """A person walking a route at a steady speed, standing still at its end."""

    def __init__(
        self, route: Sequence[tuple[float, float]], speed: float, start_at: float = 1.0
    ) -> None:
        self.route = list(route)
        self.speed = speed
        self.start_at = start_at
        self.x, self.y = self.route[0]
        self.vx = self.vy = 0.0
        self._leg = 1
        #: When the walker reached the end of its route (None while it walks).
        self.stopped_at: float | None = None

    @property
    def leg(self) -> int:
        """Index of the route point the walker heads for (len(route) once it stands)."""
        return self._leg

    def advance(self, now: float, dt: float) -> None:
        """Walk on for ``dt`` seconds (ending at ``now``)."""
        self.vx = self.vy = 0.0
        if now < self.start_at or self._leg >= len(self.route):
            return
        left = self.speed * dt
        while left > 1e-12 and self._leg < len(self.route):
            tx, ty = self.route[self._leg]
            gap = math.hypot(tx - self.x, ty - self.y)
            if gap <= left:
                self.x, self.y = tx, ty
                left -= gap
                self._leg += 1
                if self._leg == len(self.route):
                    self.stopped_at = now
            else:
                ux, uy = (tx - self.x) / gap, (ty - self.y) / gap
                self.x += ux * left
                self.y += uy * left
                self.vx, self.vy = ux * self.speed, uy * self.speed
                left = 0.0


class TruthTracks:
    """Tracks straight from the simulation's truth (id 1 is the walker)."""

    def __init__(self, walker: Walker, clock: Callable[[], float]) -> None:
        self.walker = walker
        self.clock = clock
        #: Replaces the reported position when set (a detector error: a jumping track).
        self.override: tuple[float, float] | None = None
        self.visible = True

    def tracks(self) -> list[TrackedPerson]:
        """The walker's track, if visible."""
        if not self.visible:
            return []
        w = self.walker
        x, y = self.override if self.override is not None else (w.x, w.y)
        return [TrackedPerson(1, x, y, w.vx, w.vy, self.clock())]


@dataclass
class WalkResult:
    """What happened, one row per control cycle."""

    t: list[float] = field(default_factory=list)
    distance: list[float] = field(default_factory=list)
    speed: list[float] = field(default_factory=list)
    straight: list[bool] = field(default_factory=list)
    walker_stopped_at: float | None = None
    collisions: int = 0
    ended: str = ""
    code: str = ""

    @property
    def min_distance(self) -> float:
        """Closest the robot came to the walker (centre to centre, m)."""
        return min(self.distance)

    def straight_distances(self) -> list[float]:
        """The distances on the straight stretch."""
        return [d for d, s in zip(self.distance, self.straight, strict=True) if s]

    def stopped_within(self) -> float | None:
        """Seconds from the walker stopping until the robot stood still (None: never)."""
        if self.walker_stopped_at is None:
            return None
        for t, v in zip(self.t, self.speed, strict=True):
            if t >= self.walker_stopped_at and abs(v) < 0.01:
                return t - self.walker_stopped_at
        return None


class Walk:
    """The robot, the walker and the follow service, stepped together."""

    def __init__(
        self, settings: FollowSettings | None = None, sim: SimSettings | None = None
    ) -> None:
        self.now = 0.0
        self.nav = SimNavStack.from_settings(
            sim if sim is not None else SimSettings(map="small", control_hz=CONTROL_HZ)
        )
        # from_settings starts at the map's first place: put the robot where the walk starts.
        self.nav = SimNavStack(
            self.nav.map(), self.nav.places(), self.nav.settings, start=ROBOT_START
        )
        self.walker = Walker(ROUTE, WALK_SPEED)
        self.people = TruthTracks(self.walker, lambda: self.now)
        self.service = FollowService(self.nav, settings, people=self.people)
        self._obstacle = self.nav.add_obstacle(self._body())
        self.result = WalkResult()

    def _body(self) -> Obstacle:
        return Obstacle(self.walker.x, self.walker.y, PERSON_RADIUS)

    def step(self) -> None:
        """One control cycle: the walker moves, the follow service commands, the sim moves."""
        dt = 1.0 / CONTROL_HZ
        self.now += dt
        self.walker.advance(self.now, dt)
        self.nav.remove_obstacle(self._obstacle)
        self._obstacle = self.nav.add_obstacle(self._body())
        # The daemon's order: the robot steps, then the follow commands the next cycle.
        self.nav.step(self.now)
        self.service.tick(self.now)
        robot = self.nav.true_pose
        w = self.walker
        r = self.result
        r.t.append(self.now)
        r.distance.append(math.hypot(w.x - robot.x, w.y - robot.y))
        r.speed.append(self.nav.velocity().linear)
        (sx, sy), (ex, _) = STRAIGHT
        # Both on the corridor leg, and the robot settled behind the corner (1 m past it).
        on_leg = w.leg == 2 and abs(w.y - sy) < 1e-6 and w.x < ex
        r.straight.append(on_leg and robot.x > sx + 1.0 and abs(robot.y - sy) < 0.3)
        r.walker_stopped_at = w.stopped_at
        r.collisions = self.nav.collisions

    def run(self, seconds: float) -> WalkResult:
        """Follow for ``seconds`` of simulated time (or until the follow ends)."""
        started = self.service.start("call", None, self.now)
        if not hasattr(started, "status"):
            raise AssertionError(f"follow refused: {started}")
        goal = self.service.goal
        assert goal is not None
        while self.now < seconds and not goal.status.done:
            self.step()
        if goal.status.done:
            self.result.ended, self.result.code = goal.reason, goal.code
        return self.result


def walk(seconds: float = 34.0, settings: FollowSettings | None = None) -> WalkResult:
    """The whole scripted walk, followed (about 30 s of walking, then standing)."""
    return Walk(settings).run(seconds)
