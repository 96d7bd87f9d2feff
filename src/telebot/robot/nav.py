"""The ``NavStack`` protocol: the one interface the rest of telebot uses to talk to a robot.

The simulated robot (:mod:`telebot.robot.sim`) implements it, and a real robot adapter (ROS 2
over zenoh) will implement the same calls. Nothing here knows about simulation.

Conventions (ROS REP-103): x forward, y left, yaw counter-clockwise, metres and radians, in
the map frame. The chat command ``turn X`` (degrees, positive to the right, as in the paper)
is translated by the chat service, not here: :meth:`NavStack.turn` takes REP-103 radians.

Every method is non-blocking: commands start work and return a :class:`GoalHandle` whose
``status`` the caller polls (or awaits through its service), and queries return the adapter's
latest state. A motion request the robot cannot act on (a goal inside a wall, no path)
returns a handle that has already failed, with the reason, and the robot does not move.
Numbers that are not finite raise :class:`~telebot.errors.InvalidCommand`.

The map may change while the robot runs (a SLAM robot's map grows): :meth:`NavStack.map`
returns an immutable snapshot, and :meth:`NavStack.map_version` changes whenever a new one
is in place, so whoever keeps the map encoded or downloaded knows when to refresh it. A map
republished unchanged (same cells, resolution and origin) is not a new one.

Every adapter also declares what the rest of telebot must know of it (no guessing from
its settings or its registry name): :attr:`NavStack.motion_limits` (top speeds, radius,
accelerations: follow-me and driving by hand plan within them), :attr:`NavStack.control_hz`
(the daemon's control loop rate), :attr:`NavStack.map_name` (the map's name as users see
it) and :attr:`NavStack.simulated`. :class:`NavStackBase` gives an adapter all of it but
the essentials (:meth:`~NavStack.map`, :meth:`~NavStack.pose`,
:meth:`~NavStack.navigate_to`, :meth:`~NavStack.stop`) with sensible defaults, as
python-can's ``BusABC`` does for a CAN interface; :mod:`telebot.testing.navstack` is the
contract suite an adapter runs to see what it does and what it lacks.

More abilities, each its own protocol, say how the daemon runs an adapter:

- :class:`EmergencyStoppable` (required by ``telebot-robot run``): ``emergency_stop`` may be
  called from any thread, the safety watchdog's, and needs no event loop to act.
- :class:`SteppedNavStack` (optional): an adapter driven by the caller's clock (the
  simulator) has ``step(now)``, which the daemon calls at its control rate; an adapter that
  runs by itself (a real robot's stack) has none and is not stepped.
- :class:`LaserSource` (optional): an adapter with a 2-D laser gives its latest scan, for
  person detection (:mod:`telebot.robot.perception`).
- :class:`Drivable` (optional): an adapter that takes velocity commands (``cmd_vel``) can
  follow a person and be driven by hand.
- :class:`PoseNotifier` (optional): an adapter whose poses arrive by themselves (a real
  robot's localisation) says when a new one is in, so the daemon sends it to users at once
  instead of at its next poll.

Adapters are chosen by name (``[robot] kind`` in the config, ``telebot-robot run --robot``)
through the registry in :mod:`telebot.robot`.
"""

from __future__ import annotations

import abc
import enum
import itertools
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from types import MappingProxyType
from typing import TYPE_CHECKING, Protocol, runtime_checkable

from telebot.errors import InvalidCommand, RobotError, UnknownCamera, UnknownPlace
from telebot.reasons import Reason

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

    from telebot.robot.grid import OccupancyGrid

__all__ = [
    "DEFAULT_CONTROL_HZ",
    "NAVCAM",
    "Battery",
    "CameraFrame",
    "CameraInfo",
    "Drivable",
    "EmergencyStoppable",
    "GoalHandle",
    "GoalRecord",
    "GoalStatus",
    "LaserScanLike",
    "LaserSource",
    "MotionLimits",
    "NavStack",
    "NavStackBase",
    "NavState",
    "NavStatus",
    "Pose2D",
    "PoseEstimate",
    "PoseNotifier",
    "RefusedGoal",
    "SourceTopic",
    "SteppedNavStack",
    "TopicSource",
    "TopicSubscription",
    "Velocity",
    "find_place",
    "normalize_angle",
    "require_finite",
]

#: The control loop rate (Hz) of an adapter that does not say otherwise.
DEFAULT_CONTROL_HZ = 20.0
#: The camera the safety supervisor selects while the robot moves (``telebot.safety.NAVCAM``;
#: the robot layer may not import it): every adapter has one, black if need be.
NAVCAM = "navcam"
#: Size of the black picture of a camera that has shown nothing (pixels).
NO_SIGNAL_SIZE = (320, 240)
#: Field of view reported for a camera that does not say (degrees).
DEFAULT_FOV_DEG = 60.0


def normalize_angle(angle: float) -> float:
    """``angle`` wrapped into ``[-π, π)``."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def require_finite(**values: float) -> None:
    """Raise :class:`InvalidCommand` naming the first argument that is not a finite number."""
    for name, value in values.items():
        if not isinstance(value, int | float) or not math.isfinite(value):
            raise InvalidCommand(f"{name} must be a finite number, not {value!r}")


@dataclass(frozen=True, slots=True)
class Pose2D:
    """A planar pose in the map frame: metres and radians (REP-103)."""

    x: float
    y: float
    yaw: float = 0.0

    def distance_to(self, other: Pose2D) -> float:
        """Euclidean distance between the two positions, in metres."""
        return math.hypot(other.x - self.x, other.y - self.y)


@dataclass(frozen=True, slots=True)
class PoseEstimate:
    """The localisation estimate: pose, 3×3 covariance over (x, y, yaw), and its time."""

    pose: Pose2D
    covariance: tuple[float, ...]
    stamp: float


@dataclass(frozen=True, slots=True)
class Velocity:
    """Base velocity: linear (m/s, forward positive) and angular (rad/s, CCW positive)."""

    linear: float = 0.0
    angular: float = 0.0


class NavState(enum.StrEnum):
    """What the base is doing."""

    IDLE = "idle"
    MOVING = "moving"
    BLOCKED = "blocked"
    FAILED = "failed"


@dataclass(frozen=True, slots=True)
class NavStatus:
    """The base's state and, when blocked or failed, why (``"obstacle ahead"``)."""

    state: NavState
    detail: str = ""

    def __str__(self) -> str:
        return f"{self.state}: {self.detail}" if self.detail else str(self.state)


class GoalStatus(enum.StrEnum):
    """Where a navigation goal or relative move stands."""

    ACTIVE = "active"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"

    @property
    def done(self) -> bool:
        """Whether the goal has finished (any way other than still running)."""
        return self is not GoalStatus.ACTIVE


@runtime_checkable
class GoalHandle(Protocol):
    """A running (or finished) navigation goal or relative move."""

    @property
    def goal_id(self) -> int:
        """Unique number of this goal within the adapter."""
        ...

    @property
    def description(self) -> str:
        """What was asked, in words (``"goto lab"``, ``"forward 2.00 m"``)."""
        ...

    @property
    def target(self) -> Pose2D | None:
        """The pose the goal ends at, when known."""
        ...

    @property
    def status(self) -> GoalStatus:
        """Current status."""
        ...

    @property
    def progress(self) -> float:
        """Fraction done, 0 … 1."""
        ...

    @property
    def reason(self) -> str:
        """Why it failed or was cancelled, in words; empty otherwise."""
        ...

    @property
    def code(self) -> str:
        """How it ended, as a reason code of :class:`telebot.reasons.Reason`.

        ``finished``, ``obstacle``, ``stopped``, ``cancelled``, ``replaced``, ``no_path``,
        ``battery_empty`` or ``failed``; empty while active. Services decide on this, never
        on the wording of :attr:`reason` (a real robot's navigation stack has its own).
        """
        ...

    def cancel(self) -> None:
        """Cancel the goal if it is still running (the robot stops)."""
        ...


class GoalRecord:
    """What every :class:`GoalHandle` reports, kept for an adapter's goal class to extend.

    A subclass adds what its robot needs and :meth:`cancel`; it ends the goal with
    :meth:`_end` and reports progress with :meth:`_set_progress` (which never goes back).
    """

    def __init__(self, goal_id: int, description: str, target: Pose2D | None) -> None:
        self._id = goal_id
        self._description = description
        self._target = target
        self._status = GoalStatus.ACTIVE
        self._progress = 0.0
        self._reason = ""
        self._code = ""

    @property
    def goal_id(self) -> int:
        """Unique number of this goal within the adapter."""
        return self._id

    @property
    def description(self) -> str:
        """What was asked, in words."""
        return self._description

    @property
    def target(self) -> Pose2D | None:
        """The pose the goal ends at, when known (a turn's: its heading where it started)."""
        return self._target

    @property
    def status(self) -> GoalStatus:
        """Current status."""
        return self._status

    @property
    def progress(self) -> float:
        """Fraction done, 0 … 1."""
        return self._progress

    @property
    def reason(self) -> str:
        """Why it failed or was cancelled, in words; empty otherwise."""
        return self._reason

    @property
    def code(self) -> str:
        """How it ended, as a :class:`~telebot.reasons.Reason` code; empty while active."""
        return self._code

    def cancel(self) -> None:
        """Cancel the goal if it is still running (the robot stops)."""
        raise NotImplementedError

    def _end(self, status: GoalStatus, reason: str, code: str) -> None:
        self._status = status
        self._reason = reason
        self._code = str(code)
        if status is GoalStatus.SUCCEEDED:
            self._progress = 1.0

    def _set_progress(self, value: float) -> None:
        if math.isfinite(value):
            self._progress = max(self._progress, min(max(value, 0.0), 1.0))

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self._id} {self._description!r} {self._status}>"


class RefusedGoal(GoalRecord):
    """A goal that failed before it started (the robot did not move): what an adapter
    returns for a motion it cannot make. Numbered 0: it never ran."""

    def __init__(self, description: str, reason: str, code: str = Reason.FAILED) -> None:
        super().__init__(0, description, None)
        self._end(GoalStatus.FAILED, reason, code)

    def cancel(self) -> None:
        """Nothing to cancel: the goal never ran."""


@dataclass(frozen=True, slots=True)
class MotionLimits:
    """What the base can do (SI units, all positive): follow-me and driving by hand plan
    within these, and the speed cap (:attr:`NavStack.speed_limit`) never exceeds
    ``max_linear_speed``.

    ``robot_radius`` is the round base's (or the circle around it): the clearance kept to
    what the laser sees. The accelerations are what the base brakes and speeds up with.
    """

    max_linear_speed: float = 0.5
    max_angular_speed: float = 1.0
    robot_radius: float = 0.25
    linear_accel: float = 0.5
    angular_accel: float = 2.0

    def __post_init__(self) -> None:
        for field in fields(self):
            value = getattr(self, field.name)
            if not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
                raise RobotError(
                    f"motion limit {field.name} must be a positive number, not {value!r}"
                )


@dataclass(frozen=True, slots=True)
class CameraInfo:
    """A camera the robot has."""

    name: str
    width: int
    height: int
    fov_deg: float
    description: str = ""


@dataclass(frozen=True, slots=True, eq=False)
class CameraFrame:
    """One picture: BGR ``uint8`` image of shape (height, width, 3), its camera and time."""

    camera: str
    image: npt.NDArray[np.uint8]
    stamp: float
    frame_id: int


@dataclass(frozen=True, slots=True)
class Battery:
    """Battery state: charge in percent, and whether it is low."""

    percent: float
    low: bool
    charging: bool = False


class NavStack(Protocol):
    """The one interface telebot uses to drive a robot (see the module docstring)."""

    @property
    def motion_limits(self) -> MotionLimits:
        """What the base can do: top speeds, radius, accelerations."""
        ...

    @property
    def control_hz(self) -> float:
        """The rate (Hz) of the daemon's control loop for this robot: a stepped adapter is
        stepped at it, and follow-me and driving by hand command the base at it."""
        ...

    @property
    def map_name(self) -> str:
        """The map's name as users see it (the name of the map they download)."""
        ...

    @property
    def simulated(self) -> bool:
        """Whether the robot is a simulation (its pictures are rendered): then video
        frames carry their numbers unless ``[media] stamp`` says otherwise."""
        ...

    def map(self) -> OccupancyGrid:
        """The robot's map (occupancy grid, resolution, origin): a snapshot never changed later."""
        ...

    def map_version(self) -> int:
        """A number that changes whenever :meth:`map` returns a new map (a counter, a stamp).

        A map that never changes may keep any one number, and a map republished with the
        same content (cells, resolution, origin) should keep it: each new number makes every
        user re-download the map. Read it *before* :meth:`map`: a
        map fetched after the version is at least that new, so a cache keyed by the version
        may refresh once too often but never keeps an old map under a new version.
        """
        ...

    def pose(self) -> PoseEstimate:
        """The latest localisation estimate."""
        ...

    def velocity(self) -> Velocity:
        """The base's current velocity."""
        ...

    def navigate_to(
        self, x: float, y: float, yaw: float | None = None, *, label: str = ""
    ) -> GoalHandle:
        """Plan and drive to ``(x, y)``, then face ``yaw`` if given (replaces any running goal).

        ``label`` names the goal in messages (``"no path to lab: …"``); default: the point.
        """
        ...

    def navigate_to_place(self, name: str) -> GoalHandle:
        """Drive to a named place; raises :class:`~telebot.errors.UnknownPlace`."""
        ...

    def forward(self, metres: float) -> GoalHandle:
        """Drive straight ``metres`` (negative: backwards)."""
        ...

    def turn(self, radians: float) -> GoalHandle:
        """Turn in place by ``radians`` (REP-103: positive is counter-clockwise, to the left)."""
        ...

    def stop(self) -> None:
        """Stop now: cancel the running goal and bring the base to rest."""
        ...

    def places(self) -> Mapping[str, Pose2D]:
        """Named places of the map."""
        ...

    def planned_path(self) -> tuple[Pose2D, ...]:
        """The global plan the robot follows now, in the map frame; empty when it has none.

        From where the robot was when it planned (or replanned) to the goal, each pose
        facing along the path (the last one the goal's heading, when it has one). Relative
        moves and turns have no plan. Callers compare plans by equality; an adapter that
        returns the same tuple object while its plan is unchanged makes that cheap.
        """
        ...

    def cameras(self) -> tuple[CameraInfo, ...]:
        """The robot's cameras."""
        ...

    @property
    def active_camera(self) -> str:
        """Name of the selected camera."""
        ...

    def select_camera(self, name: str) -> None:
        """Select a camera; raises :class:`~telebot.errors.UnknownCamera`."""
        ...

    def get_frame(self, camera: str | None = None) -> CameraFrame:
        """A fresh frame from ``camera`` (default: the active one)."""
        ...

    def battery(self) -> Battery:
        """Battery state."""
        ...

    def status(self) -> NavStatus:
        """Idle / moving / blocked by obstacle / failed, with why."""
        ...

    def current_goal(self) -> GoalHandle | None:
        """The goal that is running, if any."""
        ...

    @property
    def speed_limit(self) -> float:
        """The linear speed cap in force (m/s), never above the configured maximum."""
        ...

    def set_speed_limit(self, linear: float) -> None:
        """Lower (or restore, up to the configured maximum) the linear speed cap."""
        ...

    def diagnostics(self) -> Mapping[str, str]:
        """Named health values (``{"laser": "ok", …}``) for telemetry."""
        ...

    def close(self) -> None:
        """Let go of what the adapter holds (a connection, threads); idempotent. The daemon
        calls it last, after its stop has reached the base."""
        ...


@runtime_checkable
class Drivable(Protocol):
    """A robot that takes velocity commands (``cmd_vel``); repeated, or its base stops."""

    def drive(self, linear: float, angular: float) -> None:
        """Command this velocity (m/s, rad/s; REP-103) until the next command."""
        ...


@runtime_checkable
class SteppedNavStack(NavStack, Protocol):
    """A NavStack driven by the caller's clock (the simulated robot): the daemon steps it."""

    def step(self, now: float) -> None:
        """Advance to ``now`` (the event loop's time under the daemon)."""
        ...


class EmergencyStoppable(NavStack, Protocol):
    """A NavStack that can be stopped from any thread (the safety watchdog's)."""

    def emergency_stop(self, reason: str) -> None:
        """Stop as soon as possible; safe to call from any thread, needs no event loop."""
        ...


@runtime_checkable
class PoseNotifier(Protocol):
    """A NavStack that says when a new pose estimate has arrived (see the module docstring)."""

    def add_pose_listener(self, listener: Callable[[], None]) -> None:
        """Call ``listener()`` (from any thread, without arguments) after each new pose."""
        ...


@dataclass(frozen=True, slots=True)
class SourceTopic:
    """A topic a :class:`TopicSource` can hand out: its name (``/scan``), ROS type
    (``sensor_msgs/msg/LaserScan``) and schema (ros2msg text with dependencies, or ``""``)."""

    name: str
    type: str
    schema: str = ""


class TopicSubscription(Protocol):
    """A subscription made by :meth:`TopicSource.subscribe_topic`."""

    def close(self) -> None:
        """Deliver nothing more (idempotent, from any thread)."""
        ...


@runtime_checkable
class TopicSource(Protocol):
    """A robot whose topics can be relayed to users as CDR (the ``relay`` service)."""

    def topics(self) -> list[SourceTopic]:
        """The topics there are now."""
        ...

    def subscribe_topic(
        self, name: str, callback: Callable[[bytes, float], None]
    ) -> TopicSubscription:
        """Call ``callback(cdr, stamp)`` with each message of ``name`` (CDR with its 4-byte
        encapsulation header; ``stamp`` is ``time.time()`` when it came), from any thread.
        Raises LookupError for a topic that is not there."""
        ...


class LaserScanLike(Protocol):
    """A planar laser scan in the robot frame (REP-103), as a ROS ``LaserScan`` has it."""

    @property
    def angles(self) -> npt.NDArray[np.float64]:
        """Beam angles (radians, CCW from the heading), increasing."""
        ...

    @property
    def ranges(self) -> npt.NDArray[np.float64]:
        """Metres; ``range_max`` or more, ``inf`` or NaN where nothing was hit."""
        ...

    @property
    def range_max(self) -> float:
        """The scanner's range (metres)."""
        ...


@runtime_checkable
class LaserSource(Protocol):
    """An adapter that has a 2-D laser: its latest scan (None before the first one)."""

    def laser_scan(self) -> LaserScanLike | None:
        """The latest scan; the same object until a new one is in."""
        ...


def find_place(places: Mapping[str, Pose2D], name: str) -> Pose2D:
    """The pose of place ``name`` (case-insensitive, spaces around ignored).

    Raises :class:`~telebot.errors.UnknownPlace` listing the known places.
    """
    key = name.strip().lower()
    for place, pose in places.items():
        if place.lower() == key:
            return pose
    known = ", ".join(sorted(places)) or "none"
    raise UnknownPlace(f"unknown place {name!r}; known places: {known}")


class NavStackBase(abc.ABC):
    """A :class:`NavStack` with sensible defaults for all but the essentials.

    As python-can's ``BusABC`` asks an interface for two methods and supplies the rest, a
    subclass writes :meth:`map`, :meth:`pose`, :meth:`navigate_to` and :meth:`stop`, and
    passes its :class:`MotionLimits` (and named places) to ``__init__``. Everything else
    has a default that says honestly what the robot lacks: no relative moves or turns (a
    failed goal), no plan, no odometry (at rest), a black ``navcam``, a battery nobody
    measured (0 %, low: fail safe), no diagnostics. :meth:`emergency_stop` calls
    :meth:`stop`: override it when that is not safe from any thread. Override what the
    robot has; :mod:`telebot.testing.navstack` reports which defaults an adapter keeps.
    """

    def __init__(
        self, motion_limits: MotionLimits, *, places: Mapping[str, Pose2D] | None = None
    ) -> None:
        self._motion_limits = motion_limits
        self._places = {name.strip().lower(): pose for name, pose in (places or {}).items()}
        self._speed_limit = motion_limits.max_linear_speed
        self._active_camera = NAVCAM
        self._black_frames = itertools.count(1)

    # -- the essentials

    @abc.abstractmethod
    def map(self) -> OccupancyGrid:
        """The robot's map: a snapshot never changed later."""

    @abc.abstractmethod
    def pose(self) -> PoseEstimate:
        """The latest localisation estimate."""

    @abc.abstractmethod
    def navigate_to(
        self, x: float, y: float, yaw: float | None = None, *, label: str = ""
    ) -> GoalHandle:
        """Drive to ``(x, y)`` (replacing any running goal); a goal the robot cannot
        reach fails at once, with why, and the robot does not move."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop now: cancel the running goal and bring the base to rest."""

    # -- what the adapter declares

    @property
    def motion_limits(self) -> MotionLimits:
        """The limits given to ``__init__``."""
        return self._motion_limits

    @property
    def control_hz(self) -> float:
        """:data:`DEFAULT_CONTROL_HZ`."""
        return DEFAULT_CONTROL_HZ

    @property
    def map_name(self) -> str:
        """``"map"``."""
        return "map"

    @property
    def simulated(self) -> bool:
        """False: a real robot."""
        return False

    # -- defaults

    def map_version(self) -> int:
        """0: a map that never changes."""
        return 0

    def velocity(self) -> Velocity:
        """At rest (a robot without odometry)."""
        return Velocity()

    def navigate_to_place(self, name: str) -> GoalHandle:
        """:meth:`navigate_to` the place of :meth:`places` named ``name`` (case-insensitive)."""
        pose = find_place(self.places(), name)
        return self.navigate_to(pose.x, pose.y, pose.yaw, label=name.strip().lower())

    def forward(self, metres: float) -> GoalHandle:
        """A failed goal: this robot drives no relative moves."""
        require_finite(metres=metres)
        return RefusedGoal(
            f"forward {metres:.2f} m", f"{type(self).__name__} cannot drive relative moves"
        )

    def turn(self, radians: float) -> GoalHandle:
        """A failed goal: this robot does not turn on the spot."""
        require_finite(radians=radians)
        return RefusedGoal(
            f"turn {math.degrees(radians):.1f}°", f"{type(self).__name__} cannot turn on the spot"
        )

    def emergency_stop(self, reason: str) -> None:
        """:meth:`stop` (override it unless stop() is safe from any thread)."""
        del reason
        self.stop()

    def places(self) -> Mapping[str, Pose2D]:
        """The places given to ``__init__`` (lower-case names)."""
        return MappingProxyType(self._places)

    def planned_path(self) -> tuple[Pose2D, ...]:
        """No plan."""
        return ()

    def cameras(self) -> tuple[CameraInfo, ...]:
        """One black ``navcam`` (the safety supervisor selects it while the robot moves)."""
        width, height = NO_SIGNAL_SIZE
        return (CameraInfo(NAVCAM, width, height, DEFAULT_FOV_DEG, "no camera (black)"),)

    @property
    def active_camera(self) -> str:
        """The selected camera's name (``navcam`` at first)."""
        return self._active_camera

    def select_camera(self, name: str) -> None:
        """Select the camera of :meth:`cameras` named ``name`` (case-insensitive)."""
        self._active_camera = self._camera_info(name).name

    def _camera_info(self, name: str) -> CameraInfo:
        key = name.strip().lower()
        cameras = self.cameras()
        for info in cameras:
            if info.name.lower() == key:
                return info
        known = ", ".join(info.name for info in cameras) or "none"
        raise UnknownCamera(f"unknown camera {name!r}; cameras: {known}")

    def get_frame(self, camera: str | None = None) -> CameraFrame:
        """A black picture of the camera's size, stamped with the pose's time."""
        import numpy as np  # here: a client that imports this module needs no numpy

        info = self._camera_info(camera if camera is not None else self._active_camera)
        width, height = (info.width, info.height) if info.width > 0 else NO_SIGNAL_SIZE
        image = np.zeros((height, width, 3), np.uint8)
        stamp = self.pose().stamp
        return CameraFrame(info.name, image, stamp, next(self._black_frames))

    def battery(self) -> Battery:
        """Not measured: 0 % and low (fail safe: nobody trusts a charge nobody measured)."""
        return Battery(percent=0.0, low=True)

    def status(self) -> NavStatus:
        """Moving while :meth:`current_goal` runs or the base moves; else idle."""
        goal = self.current_goal()
        if goal is not None and goal.status is GoalStatus.ACTIVE:
            return NavStatus(NavState.MOVING, goal.description)
        if self.velocity() != Velocity():
            return NavStatus(NavState.MOVING, "moving")
        return NavStatus(NavState.IDLE)

    def current_goal(self) -> GoalHandle | None:
        """None (override to report the running goal)."""
        return None

    @property
    def speed_limit(self) -> float:
        """The linear speed cap in force (m/s)."""
        return self._speed_limit

    def set_speed_limit(self, linear: float) -> None:
        """Set the linear speed cap; never above ``motion_limits.max_linear_speed``.

        The cap is kept here: a subclass applies :attr:`speed_limit` to its motions.
        """
        require_finite(linear=linear)
        if linear < 0:
            raise InvalidCommand(f"speed limit must be ≥ 0, not {linear}")
        self._speed_limit = min(float(linear), self._motion_limits.max_linear_speed)

    def diagnostics(self) -> Mapping[str, str]:
        """None."""
        return {}

    def close(self) -> None:
        """Nothing to let go of (the default holds nothing)."""
        return
