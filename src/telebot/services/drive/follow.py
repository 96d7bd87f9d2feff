"""Follow-me on the robot: the ``follow`` command runs :class:`~telebot.robot.follow.FollowController`.

One :class:`FollowService` per robot (one robot follows one person at a time). The drive
holder starts a follow with the chat command ``follow`` (the nearest person in front) or
``follow ID`` (a track id, as the page's people layer shows them); it ends with
``unfollow``, ``stop``, or by itself with a reason code and a sentence.

The follow rides the same safety path as every motion:

- starting it is a motion request to the safety supervisor (observers, non-holders, a
  disarmed robot, a stale or unmeasured link are refused, and the request is audited);
- each control cycle, *after* the supervisor's tick, the follow checks that the robot is
  still armed and that its call still holds the drive, and takes the speed cap of that
  moment (link quality included); any stop (a key, a button, ``stop``, the deadman, a
  dropped call, a release or take-over) disarms the robot, and the follow ends before it
  commands anything again;
- velocities go to the robot's own velocity interface (``drive``: the simulator's base,
  ``cmd_vel`` on a ROS 2 robot), which keeps its acceleration limits, obstacle guard and
  cmd_vel timeout; every end of a follow stops the robot.

:class:`FollowGoal` is the follow's :class:`~telebot.robot.nav.GoalHandle`, so the chat
session answers ``follow`` like any motion: an acknowledgement, then one final reply.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from telebot.config import FollowSettings
from telebot.reasons import Reason, Refusal
from telebot.robot.follow import (
    Drive,
    Ended,
    FollowController,
    Track,
    clearance_ahead,
    clearance_behind,
    pick_target,
)
from telebot.robot.nav import (
    Drivable,
    GoalRecord,
    GoalStatus,
    LaserSource,
    MotionLimits,
    NavStack,
    NavState,
    NavStatus,
    Pose2D,
)
from telebot.safety import SafetyState

__all__ = [
    "CallFollow",
    "FollowGoal",
    "FollowService",
    "TrackSource",
]

log = logging.getLogger(__name__)


@runtime_checkable
class TrackSource(Protocol):
    """Where the tracks come from (the people tracker's ``PeopleSource``)."""

    def tracks(self) -> Sequence[Track]:
        """The people tracked now (map frame)."""
        ...


class FollowGoal(GoalRecord):
    """A follow as a goal handle: active while following, then why it ended."""

    def __init__(self, service: FollowService, goal_id: int, target: int) -> None:
        super().__init__(goal_id, f"follow person {target}", None)
        self._service = service
        self.target_id = target

    def cancel(self) -> None:
        """End the follow (the robot stops)."""
        self._service.end_follow(self, GoalStatus.CANCELLED, "cancelled", Reason.CANCELLED)

    def _finish(self, status: GoalStatus, reason: str, code: str) -> None:
        self._end(status, reason, code)


class FollowService:
    """The robot's follow-me (module docstring); ``tick`` it after the safety supervisor's."""

    def __init__(
        self,
        nav: NavStack,
        settings: FollowSettings | None = None,
        *,
        people: TrackSource | None = None,
        safety_state: Callable[[], SafetyState] | None = None,
        watchdog_stops: Callable[[], int] | None = None,
        limits: MotionLimits | None = None,
    ) -> None:
        """``safety_state``: the supervisor's state now; ``watchdog_stops``: how many
        emergency stops the safety watchdog thread has asked for (its stop reaches the
        robot before the supervisor latches it: the follow must not drive on in between)."""
        self.nav = nav
        self.settings = settings if settings is not None else FollowSettings()
        #: The people tracker; None: ``follow`` is refused (``no_people_source``).
        self.people = people
        # None: no supervisor (tests of the services alone); roles then decide, as elsewhere.
        self._safety_state = safety_state
        self._watchdog_stops = watchdog_stops if watchdog_stops is not None else (lambda: 0)
        self._watchdog_mark = 0
        self.limits = limits if limits is not None else nav.motion_limits
        self._controller: FollowController | None = None
        self._goal: FollowGoal | None = None
        self._call: str | None = None
        self._next_id = 1
        #: The last command sent while following (for telemetry and tests).
        self.last_drive: Drive | None = None

    @property
    def goal(self) -> FollowGoal | None:
        """The running follow, if any."""
        return self._goal

    @property
    def controller(self) -> FollowController | None:
        """The running follow's controller, if any."""
        return self._controller

    def status(self, status: NavStatus) -> NavStatus:
        """The robot's status as users see it: ``moving: follow person N`` while following
        (also while it waits for a standing person), else ``status`` unchanged."""
        goal = self._goal
        if goal is None or status.state is NavState.BLOCKED:
            return status
        return NavStatus(NavState.MOVING, goal.description)

    # -- commands ---------------------------------------------------------------------

    def start(self, call_id: str | None, target: int | None, now: float) -> FollowGoal | Refusal:
        """Follow ``target`` (a track id; None: the nearest person in front) for ``call_id``.

        The caller has already had the motion allowed by the safety supervisor. Returns the
        running follow, or why not (nobody tracked, no such id, a robot without velocity
        commands or without a people tracker).
        """
        if not isinstance(self.nav, Drivable):
            return Refusal("this robot takes no velocity commands: it cannot follow", Reason.FAILED)
        if self.people is None:
            return Refusal("this robot tracks no people: it cannot follow", Reason.NO_PEOPLE_SOURCE)
        tracks = self._tracks()
        pose = self.nav.pose().pose
        if target is None:
            chosen = pick_target(tracks, pose, self.settings)
            if chosen is None:
                return Refusal(self._nobody(tracks, pose), Reason.NO_PERSON)
        else:
            chosen = next((t for t in tracks if t.id == target), None)
            if chosen is None:
                known = ", ".join(str(t.id) for t in sorted(tracks, key=lambda t: t.id))
                listed = f"tracked: {known}" if known else "nobody is tracked"
                return Refusal(
                    f"no tracked person with id {target} ({listed})", Reason.UNKNOWN_TRACK
                )
        current = self.nav.current_goal()
        if current is not None and not current.status.done:
            current.cancel()  # the follow replaces the running goal
        if self._goal is not None:
            self.end_follow(
                self._goal,
                GoalStatus.CANCELLED,
                "replaced by a new follow",
                Reason.REPLACED,
                stop=False,
            )
        self._controller = FollowController(
            chosen.id, self.settings, self.limits, now=now, velocity=self.nav.velocity()
        )
        goal = FollowGoal(self, self._next_id, chosen.id)
        self._next_id += 1
        self._goal, self._call = goal, call_id
        self._watchdog_mark = self._watchdog_stops()
        distance = math.hypot(chosen.x - pose.x, chosen.y - pose.y)
        log.info("following person %s (%.1f m away) for call %s", chosen.id, distance, call_id)
        return goal

    def unfollow(self) -> bool:
        """End the running follow (the robot stops); False when there was none."""
        goal = self._goal
        if goal is None:
            return False
        self.end_follow(goal, GoalStatus.CANCELLED, "stopped following", Reason.CANCELLED)
        return True

    def end_follow(
        self, goal: FollowGoal, status: GoalStatus, reason: str, code: str, *, stop: bool = True
    ) -> None:
        """End ``goal`` if it is the running follow; ``stop``: stop the robot too."""
        if goal is not self._goal:
            return
        self._goal = self._controller = self._call = None
        self.last_drive = None
        goal._finish(status, reason, code)
        log.info("follow of person %s ended: %s", goal.target_id, reason)
        if stop:
            try:
                self.nav.stop()
            except Exception:
                log.exception("stopping after the follow failed")

    # -- events -----------------------------------------------------------------------

    def call_ended(self, call_id: str) -> None:
        """A call ended: its follow ends too (the supervisor stops the robot as well)."""
        if self._goal is not None and self._call == call_id:
            self.end_follow(self._goal, GoalStatus.CANCELLED, "stopped: call ended", Reason.STOPPED)

    def safety_changed(self, state: SafetyState) -> None:
        """The supervisor's state changed: a stop or a hand-over ends the follow at once."""
        if self._goal is not None and self._safety_refusal(state) is not None:
            self._end_for_safety(state)

    def tick(self, now: float) -> None:
        """One control cycle: check the safety state, then command the next velocity."""
        goal, controller = self._goal, self._controller
        if goal is None or controller is None:
            return
        if self._watchdog_stops() != self._watchdog_mark:
            why = "stopped: the driver's link was silent (safety watchdog)"
            self.end_follow(goal, GoalStatus.CANCELLED, why, Reason.STOPPED)
            return
        cap = self.nav.speed_limit
        if self._safety_state is not None:
            state = self._safety_state()
            if self._safety_refusal(state) is not None:
                self._end_for_safety(state)
                return
            cap = min(cap, state.cap)
        current = self.nav.current_goal()
        if current is not None and not current.status.done:
            # The driver sent another motion: it replaces the follow (which must not stop it).
            self.end_follow(
                goal, GoalStatus.CANCELLED, "replaced by a new goal", Reason.REPLACED, stop=False
            )
            return
        pose = self.nav.pose().pose
        tracks = self._tracks()
        ahead, behind = self._clearance(pose, controller)
        update = controller.update(
            tracks,
            pose,
            cap=cap,
            now=now,
            clearance=ahead,
            behind=behind,
            blocked=self.nav.status().state is NavState.BLOCKED,
        )
        match update:
            case Ended(code, text):
                status = GoalStatus.FAILED
                self.end_follow(
                    goal, status, f"stopped following person {goal.target_id}: {text}", code
                )
            case Drive(linear, angular):
                assert isinstance(self.nav, Drivable)
                self.last_drive = update
                self.nav.drive(linear, angular)

    # -- internals --------------------------------------------------------------------

    def _tracks(self) -> list[Track]:
        if self.people is None:
            return []
        try:
            return list(self.people.tracks())
        except Exception:  # a broken tracker loses the person; it must not crash the loop
            log.exception("people tracks unavailable")
            return []

    def _safety_refusal(self, state: SafetyState) -> str | None:
        if not state.armed:
            return state.text or "stopped"
        if state.holder_call != self._call:
            return "the drive changed hands"
        return None

    def _end_for_safety(self, state: SafetyState) -> None:
        goal = self._goal
        if goal is None:
            return
        why = self._safety_refusal(state) or "stopped"
        self.end_follow(goal, GoalStatus.CANCELLED, f"stopped: {why}", Reason.STOPPED)

    def _clearance(self, pose: Pose2D, controller: FollowController) -> tuple[float, float]:
        """Free distance ahead and behind from the robot's laser, the followed person aside."""
        nav = self.nav
        if not isinstance(nav, LaserSource):
            # A base without a laser here guards itself ahead (collision monitor); it is
            # never backed off blind.
            return math.inf, 0.0
        try:
            scan = nav.laser_scan()
            if scan is None:
                return 0.0, 0.0  # fail safe: no scan yet, no driving
            angles = np.asarray(scan.angles, dtype=np.float64)
            ranges = np.asarray(scan.ranges, dtype=np.float64)
            hit = np.isfinite(ranges) & (ranges < scan.range_max)
            points = np.column_stack(
                (ranges[hit] * np.cos(angles[hit]), ranges[hit] * np.sin(angles[hit]))
            )
        except Exception:
            log.exception("laser scan unavailable")
            return 0.0, 0.0  # fail safe: no scan, no driving
        person = controller.person
        local: tuple[float, float] | None = None
        if person is not None:
            dx, dy = person[0] - pose.x, person[1] - pose.y
            c, s = math.cos(pose.yaw), math.sin(pose.yaw)
            local = (dx * c + dy * s, -dx * s + dy * c)
        radius = nav.motion_limits.robot_radius
        return clearance_ahead(points, radius, local), clearance_behind(points, radius, angles, hit)

    def _nobody(self, tracks: Sequence[Track], pose: Pose2D) -> str:
        if not tracks:
            return "nobody is tracked near the robot"
        nearest = min(tracks, key=lambda t: math.hypot(t.x - pose.x, t.y - pose.y))
        distance = math.hypot(nearest.x - pose.x, nearest.y - pose.y)
        return (
            f"nobody is tracked within {self.settings.start_range:g} m in front of the robot "
            f"(nearest: person {nearest.id}, {distance:.1f} m away): turn towards them, "
            f"or follow ID"
        )


class CallFollow:
    """One call's handle on the robot's follow-me (the chat session's ``follow`` hook)."""

    def __init__(self, service: FollowService, call_id: str, clock: Callable[[], float]) -> None:
        self._service = service
        self._call_id = call_id
        self._clock = clock

    def start(self, target: int | None) -> FollowGoal | Refusal:
        """Follow ``target`` (None: the nearest person in front) for this call."""
        return self._service.start(self._call_id, target, self._clock())

    def unfollow(self) -> bool:
        """End the running follow (the robot stops); False when there was none."""
        return self._service.unfollow()
