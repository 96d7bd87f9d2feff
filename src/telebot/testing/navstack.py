"""The NavStack contract suite: what every robot adapter must do, and what it may lack.

A new adapter (:class:`~telebot.robot.nav.NavStackBase` makes one short) runs this suite to
see that telebot can drive it, and which optional abilities it has. With pytest, subclass
:class:`NavStackContract` in a test module and give it a fixture ``subject`` that returns
a :class:`Subject` (the adapter, freshly made or at rest)::

    import pytest
    from telebot.testing.navstack import NavStackContract, Subject

    class TestMyBase(NavStackContract):
        @pytest.fixture
        def subject(self) -> Subject:
            return Subject(MyBaseNavStack(...))

The **required part** (:data:`REQUIRED`) fails the test run when the adapter breaks it:
its declarations (motion limits, control rate, map name) are sane, it has a map and a
pose on it, a reachable goal is accepted and reached, an unreachable one fails with a
reason and a reason code while the robot stays put, ``stop`` and ``emergency_stop`` (from
another thread) end a running goal and bring the base to rest, the speed cap stays within
the motion limits, numbers that are not finite and unknown places or cameras are refused
with telebot's errors, and the safety supervisor's ``navcam`` is there.

The **optional part** (:func:`check_optional`) never fails for what an adapter lacks: it
returns a :class:`Report` that names what it has (and checks that each works) and what it
lacks (relative moves, turns, velocity commands, a laser, pose notifications, topics for
the relay, a plan, odometry, a battery, cameras, diagnostics). A failure there is an ability
the adapter claims but that does not work.

Each check is also a plain coroutine function taking a :class:`Subject`, for use without
pytest. A stepped adapter (:class:`~telebot.robot.nav.SteppedNavStack`, the simulator) is
stepped by the suite on its own clock (:attr:`Subject.now`), so the suite runs as fast as
the adapter computes; any other runs in real time and the suite polls it.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from telebot.errors import InvalidCommand, UnknownCamera, UnknownPlace
from telebot.reasons import Reason
from telebot.robot import missing_members
from telebot.robot.nav import (
    NAVCAM,
    CameraFrame,
    Drivable,
    EmergencyStoppable,
    GoalHandle,
    GoalStatus,
    LaserSource,
    MotionLimits,
    NavStackBase,
    NavState,
    Pose2D,
    PoseEstimate,
    PoseNotifier,
    SteppedNavStack,
    TopicSource,
    Velocity,
)

__all__ = [
    "OPTIONAL",
    "REQUIRED",
    "NavStackContract",
    "Report",
    "Subject",
    "check_optional",
    "nearby_free_point",
    "run_required",
]

#: How far from the target a reached goal may leave the robot (m): Nav2's default
#: xy_goal_tolerance is 0.25.
GOAL_TOLERANCE = 0.3
#: How far a robot that must stay put may seem to move (m): localisation noise.
STILL_TOLERANCE = 0.1
#: How long a robot at rest must hold its pose before a motion check starts (s).
SETTLE = 0.25
#: Distance (m) of the goal :func:`nearby_free_point` looks for.
GOAL_DISTANCE = 1.0
#: How long a stop may take to end the running goal (s): a stop acts within a control
#: cycle or two, never by letting the goal run on to its end.
STOP_WITHIN = 1.0


@dataclass
class Subject:
    """The adapter under test and what the suite needs to know of it.

    ``reachable``: a point the robot can drive to from where it is when a test starts
    (default: a free point about a metre away on its map, :func:`nearby_free_point`).
    ``timeout``: seconds one motion may take (the adapter's own time when stepped).
    ``now``: a stepped adapter's clock, the time it was made at (the suite advances it).
    """

    nav: EmergencyStoppable
    reachable: Pose2D | None = None
    timeout: float = 30.0
    now: float = 0.0

    @property
    def stepped(self) -> bool:
        """Whether the suite steps the adapter (it is a SteppedNavStack)."""
        return isinstance(self.nav, SteppedNavStack)

    @property
    def period(self) -> float:
        """One control cycle (s)."""
        return 1.0 / self.nav.control_hz

    async def advance(self, seconds: float) -> None:
        """Let ``seconds`` pass: step a stepped adapter through them, else sleep."""
        if not isinstance(self.nav, SteppedNavStack):
            await asyncio.sleep(seconds)
            return
        end = self.now + seconds
        while self.now < end - 1e-9:
            self.now = min(self.now + self.period, end)
            self.nav.step(self.now)
        await asyncio.sleep(0)

    async def wait_for(
        self, condition: Callable[[], bool], what: str, within: float | None = None
    ) -> None:
        """Advance one control cycle at a time until ``condition()``; AssertionError naming
        ``what`` after ``within`` seconds (default :attr:`timeout`; the adapter's time when
        it is stepped)."""
        limit = self.timeout if within is None else within
        waited = 0.0
        while not condition():
            if waited > limit:
                raise AssertionError(f"{what}: not within {limit:g} s")
            await self.advance(self.period)
            waited += self.period

    async def at_rest(self) -> None:
        """Stop the robot and wait until it stands (the start of each motion check): no
        velocity, and a pose that holds still for :data:`SETTLE` seconds (a robot whose
        pose arrives on its own topic may report rest before its last pose came)."""
        self.nav.stop()
        await self.wait_for(lambda: self.nav.velocity() == Velocity(), "the base comes to rest")
        waited = 0.0
        while True:
            before = self.nav.pose().pose
            await self.advance(SETTLE)
            if self.nav.pose().pose.distance_to(before) < STILL_TOLERANCE / 4:
                return
            waited += SETTLE
            if waited > self.timeout:
                raise AssertionError(f"the pose settles: not within {self.timeout:g} s")

    def target(self) -> Pose2D:
        """Where a reachable goal goes now (see the class docstring)."""
        if self.reachable is not None:
            return self.reachable
        return nearby_free_point(self.nav)


def nearby_free_point(nav: EmergencyStoppable, distance: float = GOAL_DISTANCE) -> Pose2D:
    """A free point ``distance`` from the robot in a straight line that is free too (with
    the robot's radius around it) on its map: a goal any planner reaches. Tries headings
    from straight ahead round; AssertionError if there is none."""
    grid = nav.map()
    here = nav.pose().pose
    radius = nav.motion_limits.robot_radius
    step = max(grid.resolution, 0.02)

    def free(x: float, y: float) -> bool:
        for dx, dy in ((0, 0), (radius, 0), (-radius, 0), (0, radius), (0, -radius)):
            if not grid.contains(x + dx, y + dy) or not 0 <= grid.value_at(x + dx, y + dy) < 50:
                return False
        return True

    for k in range(16):
        heading = here.yaw + (k + 1) // 2 * (1 if k % 2 else -1) * math.pi / 8
        points = max(int(distance / step), 1)
        line = [
            (here.x + i * step * math.cos(heading), here.y + i * step * math.sin(heading))
            for i in range(1, points + 1)
        ]
        if all(free(x, y) for x, y in line):
            x, y = line[-1]
            return Pose2D(x, y, heading)
    raise AssertionError(f"no free straight line of {distance:g} m around the robot's pose")


def _status(goal: GoalHandle) -> GoalStatus:
    """The goal's status now (a call, so that a type checker does not hold it constant)."""
    return goal.status


def _finite(*values: float) -> bool:
    return all(isinstance(v, int | float) and math.isfinite(v) for v in values)


# --------------------------------------------------------------------------- required


async def check_declarations(subject: Subject) -> None:
    """It has every NavStack member, and declares sane limits, control rate and map name."""
    nav = subject.nav
    missing = missing_members(nav)
    assert missing == [], f"the adapter lacks {', '.join(missing)}"
    limits = nav.motion_limits
    assert isinstance(limits, MotionLimits), f"motion_limits is {limits!r}, not MotionLimits"
    hz = nav.control_hz
    assert _finite(hz) and hz > 0, f"control_hz is {hz!r}"
    assert isinstance(nav.map_name, str) and nav.map_name.strip(), f"map_name {nav.map_name!r}"
    assert isinstance(nav.simulated, bool), f"simulated is {nav.simulated!r}"
    cap = nav.speed_limit
    assert _finite(cap) and 0 < cap <= limits.max_linear_speed, (
        f"speed_limit {cap!r} is not within (0, max_linear_speed={limits.max_linear_speed:g}]"
    )


async def check_map(subject: Subject) -> None:
    """A map with cells, and a version that stays while the map does."""
    nav = subject.nav
    version = nav.map_version()
    grid = nav.map()
    assert grid.width > 0 and grid.height > 0, f"the map is {grid.width}x{grid.height}"
    assert _finite(grid.resolution) and grid.resolution > 0, f"resolution {grid.resolution!r}"
    assert isinstance(version, int), f"map_version() is {version!r}, not an int"
    assert nav.map_version() == version, "map_version() changed with the same map"


async def check_pose(subject: Subject) -> None:
    """A finite pose on the map, with a 3x3 covariance."""
    nav = subject.nav
    estimate = nav.pose()
    assert isinstance(estimate, PoseEstimate), f"pose() is {estimate!r}"
    pose = estimate.pose
    assert _finite(pose.x, pose.y, pose.yaw), f"pose {pose} is not finite"
    assert len(estimate.covariance) == 9 and _finite(*estimate.covariance), "covariance"
    assert nav.map().contains(pose.x, pose.y), f"the robot at {pose} is off its map"


async def check_bad_numbers_are_refused(subject: Subject) -> None:
    """Numbers that are not finite raise InvalidCommand, and the robot does not move."""
    nav = subject.nav
    await subject.at_rest()
    for call in (
        lambda: nav.navigate_to(math.nan, 0.0),
        lambda: nav.navigate_to(0.0, math.inf),
        lambda: nav.navigate_to(0.0, 0.0, math.nan),
        lambda: nav.forward(math.nan),
        lambda: nav.turn(math.inf),
        lambda: nav.set_speed_limit(math.nan),
        lambda: nav.set_speed_limit(-1.0),
    ):
        try:
            call()
        except InvalidCommand:
            continue
        raise AssertionError("a number that is not finite (or a negative cap) was accepted")
    assert nav.current_goal() is None, "a refused command left a goal running"


async def check_unknown_names_are_refused(subject: Subject) -> None:
    """An unknown place raises UnknownPlace, an unknown camera UnknownCamera."""
    nav = subject.nav
    try:
        nav.navigate_to_place("no such place, surely")
    except UnknownPlace:
        pass
    else:
        raise AssertionError("an unknown place was accepted")
    try:
        nav.select_camera("no such camera, surely")
    except UnknownCamera:
        pass
    else:
        raise AssertionError("an unknown camera was accepted")


async def check_navcam(subject: Subject) -> None:
    """``navcam`` is there (the safety supervisor selects it while moving) and gives frames."""
    nav = subject.nav
    names = [info.name for info in nav.cameras()]
    assert NAVCAM in names, f"no {NAVCAM} among the cameras {names}"
    nav.select_camera(NAVCAM)
    assert nav.active_camera == NAVCAM
    frame = nav.get_frame()
    assert isinstance(frame, CameraFrame) and frame.camera == NAVCAM, f"frame {frame!r}"
    image = frame.image
    assert image.ndim == 3 and image.shape[2] == 3 and str(image.dtype) == "uint8", (
        f"the frame is {image.shape} {image.dtype}, not BGR uint8"
    )


async def check_speed_cap(subject: Subject) -> None:
    """The speed cap follows set_speed_limit and never exceeds max_linear_speed."""
    nav = subject.nav
    top = nav.motion_limits.max_linear_speed
    try:
        nav.set_speed_limit(top / 2)
        assert nav.speed_limit == top / 2, f"cap {nav.speed_limit} after setting {top / 2}"
        nav.set_speed_limit(top * 10)
        assert nav.speed_limit == top, f"cap {nav.speed_limit} above max_linear_speed {top}"
    finally:
        nav.set_speed_limit(top)


async def check_unreachable_goal_fails(subject: Subject) -> None:
    """A goal off the map fails (at once or soon) with a reason and a code; no motion."""
    nav = subject.nav
    await subject.at_rest()
    grid = nav.map()
    before = nav.pose().pose
    outside_x = grid.origin_x + grid.width * grid.resolution + 50.0
    goal = nav.navigate_to(outside_x, grid.origin_y - 50.0, label="nowhere")
    await subject.wait_for(lambda: goal.status.done, "the goal off the map ends")
    assert goal.status is GoalStatus.FAILED, f"the goal off the map ended {goal.status}"
    assert goal.reason.strip(), "the failed goal gives no reason"
    assert goal.code in set(Reason), f"the failed goal's code {goal.code!r} is no Reason"
    assert goal.code != Reason.FINISHED, "a failed goal's code says finished"
    await subject.advance(0.5)
    moved = nav.pose().pose.distance_to(before)
    assert moved < STILL_TOLERANCE, f"the robot moved {moved:.2f} m for a goal it refused"


async def check_goal_is_reached(subject: Subject) -> None:
    """A reachable goal is active, shows as the current goal, and is reached."""
    nav = subject.nav
    await subject.at_rest()
    target = subject.target()
    goal = nav.navigate_to(target.x, target.y, label="contract")
    assert isinstance(goal, GoalHandle), f"navigate_to returned {goal!r}"
    assert _status(goal) is GoalStatus.ACTIVE, f"a reachable goal is {goal.status}: {goal.reason}"
    assert nav.current_goal() is goal, "the running goal is not current_goal()"
    assert nav.status().state is not NavState.IDLE, "idle while a goal runs"
    await subject.wait_for(lambda: goal.status.done, "the reachable goal ends")
    assert goal.status is GoalStatus.SUCCEEDED, f"the goal {goal.status}: {goal.reason}"
    assert goal.code == Reason.FINISHED, f"a reached goal's code is {goal.code!r}"
    assert goal.progress == 1.0, f"a reached goal's progress is {goal.progress}"
    off = nav.pose().pose.distance_to(target)
    assert off <= GOAL_TOLERANCE, f"the goal was reached {off:.2f} m from its target"
    await subject.wait_for(lambda: nav.current_goal() is None, "current_goal() clears")


async def _stops(subject: Subject, halt: Callable[[], Awaitable[None]], how: str) -> None:
    nav = subject.nav
    await subject.at_rest()
    target = subject.target()
    goal = nav.navigate_to(target.x, target.y, label="contract")
    assert _status(goal) is GoalStatus.ACTIVE, f"a reachable goal is {goal.status}: {goal.reason}"
    await subject.advance(subject.period * 3)
    await halt()
    await subject.wait_for(lambda: goal.status.done, f"{how} ends the goal", STOP_WITHIN)
    assert goal.status is not GoalStatus.SUCCEEDED, f"{how}: the goal ran on to its end"
    assert goal.code == Reason.STOPPED, f"{how}: the goal's code is {goal.code!r}"
    await subject.wait_for(lambda: nav.current_goal() is None, f"{how} clears current_goal()")
    await subject.wait_for(lambda: nav.velocity() == Velocity(), f"{how} brings the base to rest")


async def check_stop(subject: Subject) -> None:
    """``stop()`` ends a running goal (code ``stopped``) and brings the base to rest."""

    async def halt() -> None:
        subject.nav.stop()

    await _stops(subject, halt, "stop()")


async def check_emergency_stop(subject: Subject) -> None:
    """``emergency_stop()`` from another thread, no event loop there, does as much."""

    async def halt() -> None:
        await asyncio.to_thread(subject.nav.emergency_stop, "contract suite")

    await _stops(subject, halt, "emergency_stop() from a thread")


Check = Callable[[Subject], Awaitable[None]]

#: The required part, in order: every adapter passes all of it.
REQUIRED: tuple[Check, ...] = (
    check_declarations,
    check_map,
    check_pose,
    check_bad_numbers_are_refused,
    check_unknown_names_are_refused,
    check_navcam,
    check_speed_cap,
    check_unreachable_goal_fails,
    check_goal_is_reached,
    check_stop,
    check_emergency_stop,
)


async def run_required(subject: Subject) -> None:
    """Run every check of :data:`REQUIRED`; the first that fails raises AssertionError."""
    for check in REQUIRED:
        try:
            await check(subject)
        except AssertionError as exc:
            raise AssertionError(f"{check.__name__}: {exc}") from exc


# --------------------------------------------------------------------------- optional


@dataclass
class Report:
    """What the optional part found: abilities the adapter has (and that work), those it
    lacks (and what that costs), and those it claims that failed."""

    adapter: str
    has: list[str] = field(default_factory=list)
    lacks: dict[str, str] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)

    def __str__(self) -> str:
        lines = [f"{self.adapter}: has {', '.join(self.has) or 'nothing optional'}"]
        lines += [f"  lacks {name}: {cost}" for name, cost in self.lacks.items()]
        lines += [f"  FAILED {name}: {why}" for name, why in self.failed.items()]
        return "\n".join(lines)


def _inherited(nav: object, name: str) -> bool:
    """Whether ``nav`` keeps NavStackBase's default for ``name``."""
    if not isinstance(nav, NavStackBase):
        return False
    return getattr(type(nav), name) is getattr(NavStackBase, name)


async def _relative_move(subject: Subject) -> None:
    await subject.at_rest()
    goal = subject.nav.forward(0.0)
    await subject.wait_for(lambda: goal.status.done, "forward(0) ends")
    assert goal.status is GoalStatus.SUCCEEDED, f"forward(0) {goal.status}: {goal.reason}"


async def _turn(subject: Subject) -> None:
    await subject.at_rest()
    before = subject.nav.pose().pose.yaw
    goal = subject.nav.turn(0.5)
    await subject.wait_for(lambda: goal.status.done, "turn(0.5) ends")
    assert goal.status is GoalStatus.SUCCEEDED, f"turn(0.5) {goal.status}: {goal.reason}"
    turned = math.remainder(subject.nav.pose().pose.yaw - before, math.tau)
    assert abs(turned - 0.5) < 0.15, f"turn(0.5) turned {turned:.2f} rad"


async def _drive(subject: Subject) -> None:
    nav = subject.nav
    assert isinstance(nav, Drivable)
    await subject.at_rest()
    nav.drive(0.0, 0.0)
    await subject.at_rest()


async def _laser(subject: Subject) -> None:
    nav = subject.nav
    assert isinstance(nav, LaserSource)
    await subject.advance(subject.period)
    scan = nav.laser_scan()
    if scan is not None:
        assert len(scan.angles) == len(scan.ranges) > 0, "a scan without beams"
        assert _finite(scan.range_max) and scan.range_max > 0, f"range_max {scan.range_max}"


async def _topics(subject: Subject) -> None:
    # Only a topic that is not there: listing them may load a whole ROS type store.
    nav = subject.nav
    assert isinstance(nav, TopicSource)
    try:
        nav.subscribe_topic("/no/such/topic/surely", lambda data, stamp: None)
    except LookupError:
        return
    raise AssertionError("subscribing to a topic that is not there did not raise LookupError")


async def _nothing(subject: Subject) -> None:
    del subject


# name -> (has it?, a check that it works, what lacking it costs)
_Optional = tuple[Callable[[Any], bool], Check, str]

#: The optional part: each ability, how to tell the adapter has it, and what lacking costs.
OPTIONAL: dict[str, _Optional] = {
    "relative moves": (
        lambda nav: not _inherited(nav, "forward"),
        _relative_move,
        "the chat's `forward`/`back` commands fail",
    ),
    "turns": (
        lambda nav: not _inherited(nav, "turn"),
        _turn,
        "the chat's `turn` command fails",
    ),
    "velocity commands": (
        lambda nav: isinstance(nav, Drivable),
        _drive,
        "no follow-me, no driving by hand (Drivable.drive)",
    ),
    "laser": (
        lambda nav: isinstance(nav, LaserSource),
        _laser,
        "no people detection from legs; follow-me backs off blind-safe (LaserSource)",
    ),
    "pose notifications": (
        lambda nav: isinstance(nav, PoseNotifier),
        _nothing,
        "poses reach users at the next control cycle (PoseNotifier)",
    ),
    "topics": (
        lambda nav: isinstance(nav, TopicSource),
        _topics,
        "nothing for the relay service (TopicSource)",
    ),
    "planned path": (
        lambda nav: not _inherited(nav, "planned_path"),
        _nothing,
        "users see no plan",
    ),
    "odometry": (
        lambda nav: not _inherited(nav, "velocity"),
        _nothing,
        "velocity() is always at rest",
    ),
    "battery": (
        lambda nav: not _inherited(nav, "battery"),
        _nothing,
        "the battery reads 0 % and low",
    ),
    "cameras": (
        lambda nav: not _inherited(nav, "cameras"),
        _nothing,
        "users see a black navcam",
    ),
    "diagnostics": (
        lambda nav: not _inherited(nav, "diagnostics"),
        _nothing,
        "telemetry has no health values",
    ),
    "stepped by the caller's clock": (
        lambda nav: isinstance(nav, SteppedNavStack),
        _nothing,
        "runs by itself (not a lack)",
    ),
}


async def check_optional(subject: Subject) -> Report:
    """Find which optional abilities the adapter has, check each works; never raises for
    what it lacks (see :class:`Report`)."""
    nav = subject.nav
    report = Report(type(nav).__name__)
    for name, (has, check, cost) in OPTIONAL.items():
        if not has(nav):
            report.lacks[name] = cost
            continue
        try:
            await check(subject)
        except AssertionError as exc:
            report.failed[name] = str(exc)
        else:
            report.has.append(name)
    return report


# --------------------------------------------------------------------------- pytest


class NavStackContract:
    """The suite as pytest tests: subclass it and give a ``subject`` fixture (module
    docstring). One test per required check; ``test_optional`` prints the
    :class:`Report` and fails only for an ability the adapter claims that does not work."""

    async def test_declarations(self, subject: Subject) -> None:
        """:func:`check_declarations`."""
        await check_declarations(subject)

    async def test_map(self, subject: Subject) -> None:
        """:func:`check_map`."""
        await check_map(subject)

    async def test_pose(self, subject: Subject) -> None:
        """:func:`check_pose`."""
        await check_pose(subject)

    async def test_bad_numbers_are_refused(self, subject: Subject) -> None:
        """:func:`check_bad_numbers_are_refused`."""
        await check_bad_numbers_are_refused(subject)

    async def test_unknown_names_are_refused(self, subject: Subject) -> None:
        """:func:`check_unknown_names_are_refused`."""
        await check_unknown_names_are_refused(subject)

    async def test_navcam(self, subject: Subject) -> None:
        """:func:`check_navcam`."""
        await check_navcam(subject)

    async def test_speed_cap(self, subject: Subject) -> None:
        """:func:`check_speed_cap`."""
        await check_speed_cap(subject)

    async def test_unreachable_goal_fails(self, subject: Subject) -> None:
        """:func:`check_unreachable_goal_fails`."""
        await check_unreachable_goal_fails(subject)

    async def test_goal_is_reached(self, subject: Subject) -> None:
        """:func:`check_goal_is_reached`."""
        await check_goal_is_reached(subject)

    async def test_stop(self, subject: Subject) -> None:
        """:func:`check_stop`."""
        await check_stop(subject)

    async def test_emergency_stop(self, subject: Subject) -> None:
        """:func:`check_emergency_stop`."""
        await check_emergency_stop(subject)

    async def test_optional(self, subject: Subject) -> None:
        """:func:`check_optional`: prints what the adapter has and lacks."""
        report = await check_optional(subject)
        print(report)
        assert report.failed == {}, str(report)
