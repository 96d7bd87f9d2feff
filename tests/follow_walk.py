"""A scripted walker on the small map, followed by the robot: one set-up for tests and bench.

The walker starts in room A just in front of the robot, walks south out of room A's door
into the corridor, east along the corridor, north through room B's door, and stops in
room B: two rooms, two doors and a 7 m straight stretch. It is a simulated person
(:class:`~telebot.robot.sim.people.Walker`: two legs in the laser, a figure in the
cameras; the base cannot drive into it) and is tracked without error
(:class:`TruthTracks`): this measures the follow controller, not the detector. The
simulation is stepped with a fast clock (numbers, no sleeping) through
:class:`~telebot.services.drive.follow.FollowService`, the robot's own path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from telebot.config import FollowSettings, PeopleSettings, SimSettings
from telebot.reasons import Refusal
from telebot.robot.nav import Pose2D
from telebot.robot.perception.runner import PeoplePerception
from telebot.robot.perception.tracks import PersonTrack
from telebot.robot.sim.people import Walker
from telebot.robot.sim.stack import SimNavStack
from telebot.services.drive.follow import FollowService

#: Where the robot starts: in room A, facing south towards the walker and the door.
ROBOT_START = Pose2D(2.5, 4.4, -math.pi / 2)
#: The walker's route: room A → door A → corridor → door B → room B (metres, map frame).
ROUTE = ((2.5, 3.2), (2.5, 1.2), (9.5, 1.2), (9.5, 3.9))
#: The corridor leg, where the distance is measured once both are on it for good.
STRAIGHT = (ROUTE[1], ROUTE[2])
#: Walking speed (m/s), within the robot's 0.5 m/s.
WALK_SPEED = 0.4
#: The walker stands this long before setting off (s).
START_DELAY = 1.0
CONTROL_HZ = 20.0


class TruthTracks:
    """Tracks straight from the simulation's truth (a perfect people tracker)."""

    def __init__(self, nav: SimNavStack) -> None:
        self.nav = nav
        #: Replaces the reported position when set (a detector error: a jumping track).
        self.override: tuple[float, float] | None = None
        self.visible = True

    def tracks(self) -> list[PersonTrack]:
        """Every simulated person's track, if visible."""
        if not self.visible:
            return []
        now = self.nav.now
        out = []
        for p in self.nav.people_truth():
            x, y = self.override if self.override is not None else (p.x, p.y)
            out.append(PersonTrack(p.id, x, y, p.vx, p.vy, 1.0, 0.0, now, frozenset({"laser"})))
        return out


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
        self,
        settings: FollowSettings | None = None,
        sim: SimSettings | None = None,
        *,
        perception: PeopleSettings | None = None,
    ) -> None:
        """``perception``: track the walker with the robot's own people tracker (laser legs
        and the HOG camera detector) instead of the simulation's truth."""
        self.now = 0.0
        base = SimNavStack.from_settings(
            sim if sim is not None else SimSettings(map="small", control_hz=CONTROL_HZ)
        )
        self.nav = SimNavStack(base.map(), base.places(), base.settings, start=ROBOT_START)
        self.walker = Walker.along(ROUTE, speed=WALK_SPEED, start_delay=START_DELAY)
        self.person = self.nav.add_person(self.walker)
        self.people = TruthTracks(self.nav)
        self.perception = (
            PeoplePerception(self.nav, perception, threaded=False)
            if perception is not None
            else None
        )
        source = self.perception if self.perception is not None else self.people
        self.service = FollowService(self.nav, settings, people=source)
        self.result = WalkResult()

    @property
    def walker_at(self) -> tuple[float, float]:
        """Where the walker is now (ground truth)."""
        truth = self.nav.people_truth()[0]
        return truth.x, truth.y

    def step(self) -> None:
        """One control cycle, in the daemon's order: the world and the robot move, then
        the follow service commands the next cycle."""
        self.now += 1.0 / CONTROL_HZ
        self.nav.step(self.now)
        if self.perception is not None:
            self.perception.step(self.now)
        self.service.tick(self.now)
        robot = self.nav.true_pose
        wx, wy = self.walker_at
        r = self.result
        r.t.append(self.now)
        r.distance.append(math.hypot(wx - robot.x, wy - robot.y))
        r.speed.append(self.nav.velocity().linear)
        (sx, sy), (ex, _) = STRAIGHT
        # Both on the corridor leg, and the robot settled behind the corner (1 m past it).
        on_leg = abs(wy - sy) < 1e-6 and sx < wx < ex
        r.straight.append(on_leg and robot.x > sx + 1.0 and abs(robot.y - sy) < 0.3)
        if self.now >= self.walker.duration and r.walker_stopped_at is None:
            r.walker_stopped_at = self.walker.duration
        r.collisions = self.nav.collisions

    def run(self, seconds: float) -> WalkResult:
        """Follow until ``seconds`` of simulated time (or until the follow ends).

        With the robot's own tracker, the follow starts once it has confirmed the walker
        (it is refused until then, as the driver's ``follow`` would be).
        """
        started = self.service.start("call", None, self.now)
        while isinstance(started, Refusal) and self.perception is not None and self.now < 5.0:
            self.step()
            started = self.service.start("call", None, self.now)
        if isinstance(started, Refusal):
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
