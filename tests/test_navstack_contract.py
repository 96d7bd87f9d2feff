"""The NavStack contract suite (:mod:`telebot.testing.navstack`) on in-process adapters.

The simulator passes all of it; ``DiffDrive``, the skeleton of a new adapter (this one file
is all it took: :class:`~telebot.robot.nav.NavStackBase` supplies the rest), passes the
required part and is told what it lacks; an adapter whose stop does not stop is caught.
(The ROS 2 adapter runs the suite against telebot-sim in test_ros2_contract.py.)
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from rig import FAST_SIM
from telebot.config import SimSettings
from telebot.errors import RobotError
from telebot.reasons import Reason
from telebot.robot.grid import OccupancyGrid
from telebot.robot.nav import (
    GoalRecord,
    GoalStatus,
    MotionLimits,
    NavStackBase,
    Pose2D,
    PoseEstimate,
    RefusedGoal,
    Velocity,
    normalize_angle,
    require_finite,
)
from telebot.robot.sim.stack import SimNavStack
from telebot.services.drive.follow import FollowService
from telebot.services.drive.robot import DriveService
from telebot.testing.navstack import (
    OPTIONAL,
    NavStackContract,
    Subject,
    check_optional,
    run_required,
)

# --------------------------------------------------------------------------- a new adapter


class DiffDriveGoal(GoalRecord):
    """A goal of :class:`DiffDrive`."""

    def __init__(self, base: DiffDrive, goal_id: int, description: str, target: Pose2D) -> None:
        super().__init__(goal_id, description, target)
        self._base = base
        self.distance = 0.0

    def cancel(self) -> None:
        """Cancel it; the base stops."""
        self._base._end(self, GoalStatus.CANCELLED, "cancelled", Reason.CANCELLED)


class DiffDrive(NavStackBase):
    """The skeleton of a differential-drive adapter: a 10 m room with walls round it, and a
    base that turns towards its goal and drives straight there at the speed cap."""

    def __init__(self) -> None:
        super().__init__(MotionLimits(max_linear_speed=0.5, max_angular_speed=1.0))
        cells = np.zeros((200, 200), dtype=np.int8)
        cells[0, :] = cells[-1, :] = cells[:, 0] = cells[:, -1] = 100
        self._grid = OccupancyGrid(cells, 0.05, 0.0, 0.0)
        self._pose = Pose2D(5.0, 5.0, 0.0)
        self._velocity = Velocity()
        self._goal: DiffDriveGoal | None = None
        self._ids = 0
        self._now = 0.0

    def map(self) -> OccupancyGrid:
        return self._grid

    def pose(self) -> PoseEstimate:
        return PoseEstimate(self._pose, (0.0,) * 9, self._now)

    def velocity(self) -> Velocity:
        return self._velocity

    def current_goal(self) -> DiffDriveGoal | None:
        return self._goal

    def navigate_to(
        self, x: float, y: float, yaw: float | None = None, *, label: str = ""
    ) -> GoalRecord:
        require_finite(x=x, y=y, **({} if yaw is None else {"yaw": yaw}))
        name = label or f"({x:.2f}, {y:.2f})"
        if not self._grid.contains(x, y) or self._grid.value_at(x, y) >= 50:
            return RefusedGoal(f"goto {name}", f"no path to {name}: not free", Reason.NO_PATH)
        if self._goal is not None:
            self._end(self._goal, GoalStatus.CANCELLED, "replaced", Reason.REPLACED)
        self._ids += 1
        self._goal = DiffDriveGoal(self, self._ids, f"goto {name}", Pose2D(x, y))
        self._goal.distance = self._pose.distance_to(Pose2D(x, y))
        return self._goal

    def stop(self) -> None:
        if self._goal is not None:
            self._end(self._goal, GoalStatus.CANCELLED, "stopped", Reason.STOPPED)
        self._velocity = Velocity()

    def _end(self, goal: DiffDriveGoal, status: GoalStatus, why: str, code: Reason) -> None:
        if goal.status is GoalStatus.ACTIVE:
            goal._end(status, why, code)
        if self._goal is goal:
            self._goal, self._velocity = None, Velocity()

    def step(self, now: float) -> None:
        """Drive towards the goal until ``now``."""
        dt, self._now = now - self._now, now
        goal, here = self._goal, self._pose
        if goal is None or goal.target is None or dt <= 0:
            return
        left = here.distance_to(goal.target)
        if left < 0.02:
            self._end(goal, GoalStatus.SUCCEEDED, "", Reason.FINISHED)
            return
        heading = math.atan2(goal.target.y - here.y, goal.target.x - here.x)
        error = normalize_angle(heading - here.yaw)
        turn = max(-1.0, min(1.0, 3.0 * error))
        speed = min(self.speed_limit, left / dt) if abs(error) < 0.2 else 0.0
        yaw = normalize_angle(here.yaw + turn * dt)
        self._pose = Pose2D(
            here.x + speed * dt * math.cos(yaw), here.y + speed * dt * math.sin(yaw), yaw
        )
        self._velocity = Velocity(speed, turn)
        goal._set_progress(1.0 - left / max(goal.distance, 1e-9))


class TestDiffDrive(NavStackContract):
    @pytest.fixture
    def subject(self) -> Subject:
        return Subject(DiffDrive())

    async def test_optional(self, subject: Subject) -> None:
        """The suite tells the skeleton what it lacks, and what that costs."""
        report = await check_optional(subject)
        assert report.failed == {}
        assert report.has == ["odometry", "stepped by the caller's clock"]
        assert set(report.lacks) == set(OPTIONAL) - set(report.has)
        assert "no follow-me" in report.lacks["velocity commands"]
        assert "lacks relative moves" in str(report)


class StopLess(DiffDrive):
    """An adapter whose stop forgets the goal but leaves the base driving to it."""

    def stop(self) -> None:
        self._velocity = Velocity()


async def test_an_adapter_whose_stop_does_not_stop_fails_the_required_part() -> None:
    with pytest.raises(AssertionError, match=r"check_stop: stop\(\) ends the goal"):
        await run_required(Subject(StopLess()))


# --------------------------------------------------------------------------- the simulator


class TestSimulator(NavStackContract):
    @pytest.fixture
    def subject(self) -> Subject:
        return Subject(SimNavStack.from_settings(SimSettings(**FAST_SIM)))

    async def test_optional(self, subject: Subject) -> None:
        """The simulator has every optional ability but pose notifications, and each works."""
        report = await check_optional(subject)
        assert report.failed == {}
        assert list(report.lacks) == ["pose notifications"]


# --------------------------------------------------------------------------- declarations


def test_motion_limits_are_positive_numbers() -> None:
    assert MotionLimits().robot_radius == 0.25
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(RobotError, match="motion limit max_angular_speed"):
            MotionLimits(max_angular_speed=bad)


class Slow(DiffDrive):
    """An adapter with limits of its own (and no settings to guess them from)."""

    def __init__(self) -> None:
        super().__init__()
        self._motion_limits = MotionLimits(0.3, 0.6, robot_radius=0.4, linear_accel=0.2)


def test_follow_me_and_driving_by_hand_plan_within_the_declared_limits() -> None:
    nav = Slow()
    assert FollowService(nav).limits == DriveService(nav).limits == nav.motion_limits
    assert SimNavStack.from_settings(SimSettings(**FAST_SIM)).motion_limits == MotionLimits(
        max_linear_speed=1.5, max_angular_speed=3.0, linear_accel=3.0, angular_accel=8.0
    )
