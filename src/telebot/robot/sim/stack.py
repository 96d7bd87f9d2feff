"""``SimNavStack``: the simulated robot behind the :class:`~telebot.robot.nav.NavStack` protocol.

Stepping model: the caller passes the time to :meth:`SimNavStack.step` — ``loop.time()``
under the daemon, any increasing numbers in tests. Each step is one control cycle: the
laser scans, localisation updates, the controller computes one velocity command and hands
it to the base, and the base then moves in fixed sub-steps up to ``now``. A long gap between
steps is what a stalled control loop looks like, and the base's ``cmd_vel`` watchdog stops
the robot ``cmd_vel_timeout`` into it, exactly as on a real base.

Deterministic: the same map, settings, seed, calls and step times give the same run.

The registry of :mod:`telebot.robot` knows it as ``"sim"`` (:meth:`SimNavStack.from_config`
reads ``[sim]``). :meth:`SimNavStack.set_map` replaces the map while it runs, as a SLAM
robot's map changes, and bumps :meth:`SimNavStack.map_version`.
"""

from __future__ import annotations

import enum
import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import MappingProxyType
from typing import Literal

import numpy as np
import numpy.typing as npt

from telebot.config import RobotConfig, SimSettings
from telebot.errors import (
    ConfigError,
    InvalidCommand,
    MapError,
    NoPath,
    RobotError,
    UnknownCamera,
)
from telebot.reasons import Reason
from telebot.robot.grid import OccupancyGrid
from telebot.robot.mapfile import load_map, load_places, places_path_for
from telebot.robot.nav import (
    Battery,
    CameraFrame,
    CameraInfo,
    GoalRecord,
    GoalStatus,
    MotionLimits,
    NavStackBase,
    NavState,
    NavStatus,
    Pose2D,
    PoseEstimate,
    SourceTopic,
    TopicSubscription,
    Velocity,
    find_place,
    normalize_angle,
    require_finite,
)
from telebot.robot.sim.building import resolve_map
from telebot.robot.sim.camera import CameraModel, Renderer, default_cameras
from telebot.robot.sim.controller import (
    DiffDriveBase,
    Limits,
    PathTracker,
    rotate_command,
    straight_command,
)
from telebot.robot.sim.laser import Laser, LaserScan
from telebot.robot.sim.people import PersonTruth, Walker, Waypoint, legs_of
from telebot.robot.sim.planner import Costmap
from telebot.robot.sim.world import Obstacle
from telebot.rosmsg.topics import SimTopics

__all__ = ["SimGoal", "SimNavStack"]

#: Longest relative move accepted (metres) and largest turn (radians).
MAX_RELATIVE_MOVE = 100.0
MAX_TURN = 2.0 * math.pi
#: Time constant of the localisation error's random walk (seconds).
NOISE_TIME_CONSTANT = 2.0
#: Replans a blocked path goal makes without getting anywhere before it gives up: a new
#: plan from the same spot that the laser blocks again will not do better the next time.
REPLANS_IN_PLACE = 2


class _Kind(enum.Enum):
    PATH = "path"
    STRAIGHT = "straight"
    ROTATE = "rotate"


class SimGoal(GoalRecord):
    """A goal of the simulated robot; implements :class:`~telebot.robot.nav.GoalHandle`."""

    def __init__(
        self,
        stack: SimNavStack,
        goal_id: int,
        kind: _Kind,
        description: str,
        target: Pose2D | None,
    ) -> None:
        super().__init__(goal_id, description, target)
        self._stack = stack
        self.kind = kind
        # Geometry of the motion, filled in by the stack.
        self.tracker: PathTracker | None = None
        #: The tracker's path as poses (see :meth:`SimNavStack.planned_path`).
        self.plan: tuple[Pose2D, ...] = ()
        self.final_yaw: float | None = None
        self.aligning = False
        self.start = Pose2D(0.0, 0.0, 0.0)
        self.distance = 0.0
        self.angle = 0.0
        self.turned = 0.0
        self.last_yaw = 0.0
        self.blocked_since: float | None = None
        self.replans = 0
        # Where the base was at the first of a run of blocked timeouts, and how many
        # timeouts in a row found it still there (within its radius): measured from the
        # first, so creeping a little each time does not count as getting anywhere.
        self.stuck_at: Pose2D | None = None
        self.stuck_count = 0

    @property
    def blocked(self) -> bool:
        """Whether an obstacle is holding this goal up right now."""
        return self.blocked_since is not None

    def cancel(self) -> None:
        """Cancel the goal if it is still running; the robot stops."""
        self._stack._cancel_goal(self, "cancelled", Reason.CANCELLED)

    def _finish(self, status: GoalStatus, reason: str = "", code: Reason = Reason.FINISHED) -> None:
        self._end(status, reason, code)
        self.blocked_since = None


class SimNavStack(NavStackBase):
    """A simulated differential-drive robot on a ROS map (see the module docstring)."""

    def __init__(
        self,
        grid: OccupancyGrid,
        places: Mapping[str, Pose2D] | None = None,
        settings: SimSettings | None = None,
        *,
        start: Pose2D | None = None,
        now: float = 0.0,
        map_name: str = "map",
    ) -> None:
        self._settings = settings = settings if settings is not None else SimSettings()
        super().__init__(
            MotionLimits(
                max_linear_speed=settings.max_linear_speed,
                max_angular_speed=settings.max_angular_speed,
                robot_radius=settings.robot_radius,
                linear_accel=settings.linear_accel,
                angular_accel=settings.angular_accel,
            ),
            places=places,
        )
        # The relay's topic source, made when first asked for (it loads the ROS types).
        self._topics: SimTopics | None = None
        self._grid = grid
        self._map_version = 0
        self._map_name = map_name
        self._limits = Limits(
            linear_speed=settings.max_linear_speed,
            angular_speed=settings.max_angular_speed,
            linear_accel=settings.linear_accel,
            angular_accel=settings.angular_accel,
        )
        self._costmap = Costmap.from_grid(grid, settings.robot_radius)
        self._laser = Laser(grid, beams=settings.laser_beams, range_max=settings.laser_range)
        self._renderer: Renderer | None = None  # built on the first frame: tests rarely need it
        self._cameras: dict[str, CameraModel] = {
            model.name: model
            for model in default_cameras(settings.camera_width, settings.camera_height)
        }
        self._active_camera = next(iter(self._cameras))  # navcam
        self._frame_id = 0

        if start is None:
            if not self._places:
                raise RobotError("the map has no places: give a start pose")
            start = next(iter(self._places.values()))
        require_finite(x=start.x, y=start.y, yaw=start.yaw)
        if not self._costmap.is_free(start.x, start.y):
            raise RobotError(
                f"start pose ({start.x:.2f}, {start.y:.2f}) is not free space on the map"
            )
        self._base = DiffDriveBase(
            limits=self._limits,
            cmd_vel_timeout=settings.cmd_vel_timeout,
            pose=Pose2D(start.x, start.y, normalize_angle(start.yaw)),
        )
        self._now = float(now)
        self._rng = np.random.default_rng(settings.seed)
        self._noise = np.zeros(3)
        self._sigma = np.array(
            [
                settings.position_noise,
                settings.position_noise,
                math.radians(settings.heading_noise_deg),
            ]
        )
        self._obstacles: dict[int, Obstacle] = {}
        self._next_obstacle_id = 1
        # Simulated people: id -> (walker, time added); their legs as of the last step.
        self._people: dict[int, tuple[Walker, float]] = {}
        self._people_now: tuple[PersonTruth, ...] = ()
        self._next_person_id = 1
        self._next_goal_id = 1
        self._goal: SimGoal | None = None
        self._last_goal: SimGoal | None = None
        self._teleop = False
        self._teleop_blocked = False
        self._battery = 100.0
        self._collisions = 0
        # What the physics guard refused the last step's move for, and which way the
        # base was driving (+1 forward, -1 backward), if it did.
        self._refused: tuple[Literal["wall", "obstacle"], float] | None = None
        self._emergency_requests = 0
        self._emergency_reason = ""
        #: Emergency stops acted on (see :meth:`emergency_stop`).
        self.emergency_stops = 0
        self._scan: LaserScan = self._laser.scan(self._base.pose, ())
        # Obstacles or people added or removed since the scan was taken.
        self._world_changed = False

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_settings(
        cls, settings: SimSettings | None = None, *, base_dir: Path | None = None, now: float = 0.0
    ) -> SimNavStack:
        """Load the map and places named by ``settings`` (relative paths from ``base_dir``).

        Raises :class:`~telebot.errors.MapError` or :class:`~telebot.errors.ConfigError`
        naming the file at fault, :class:`~telebot.errors.UnknownPlace` for a bad ``start``.
        """
        settings = settings if settings is not None else SimSettings()
        yaml_path = resolve_map(settings.map, base_dir)
        grid = load_map(yaml_path)
        if settings.places is not None:
            places_file = settings.places
            if base_dir is not None and not places_file.is_absolute():
                places_file = base_dir / places_file
            places = load_places(places_file)
        else:
            default_places = places_path_for(yaml_path)
            places = load_places(default_places) if default_places.exists() else {}
        start = None
        if settings.start is not None:
            start = find_place(places, settings.start)
        stack = cls(grid, places, settings, start=start, now=now, map_name=settings.map)
        if start is None and not places:
            raise MapError(f"{yaml_path}: the map has no places file: set sim.start")
        for walker in walkers_of(settings, grid):
            stack.add_person(walker)
        return stack

    @classmethod
    def from_config(
        cls, config: RobotConfig, *, base_dir: Path | None = None, now: float = 0.0
    ) -> SimNavStack:
        """The robot adapter ``"sim"`` of the registry: :meth:`from_settings` of ``config.sim``."""
        return cls.from_settings(config.sim, base_dir=base_dir, now=now)

    # ------------------------------------------------------------------ what it declares

    @property
    def control_hz(self) -> float:
        """``[sim] control_hz``: the daemon steps the simulation at this rate."""
        return self._settings.control_hz

    @property
    def map_name(self) -> str:
        """The map's name: a built-in map's, or its YAML file's stem."""
        return Path(self._map_name).stem

    @property
    def simulated(self) -> bool:
        """True."""
        return True

    # ------------------------------------------------------------------ NavStack: queries

    def map(self) -> OccupancyGrid:
        """The occupancy grid."""
        return self._grid

    def map_version(self) -> int:
        """0 for the map the robot started on, one more after each :meth:`set_map`."""
        return self._map_version

    def set_map(self, grid: OccupancyGrid) -> None:
        """Replace the map, as a SLAM robot's map changes (the simulated world changes too).

        The costmap, laser and cameras use the new map from the next step on; a running goal
        keeps its path (the laser still stops the base before a new wall) and replans on the
        new map when it is blocked. :meth:`map_version` goes up by one, unless the map is
        the one in place (same cells, resolution and origin): then nothing changes.
        """
        if grid.same_content(self._grid):
            return
        costmap = Costmap.from_grid(grid, self._settings.robot_radius)
        laser = Laser(grid, beams=self._settings.laser_beams, range_max=self._settings.laser_range)
        self._grid, self._costmap, self._laser = grid, costmap, laser
        self._renderer = None
        self._map_version += 1

    def pose(self) -> PoseEstimate:
        """The localisation estimate: true pose plus bounded, slowly varying noise."""
        var = self._sigma**2
        return PoseEstimate(
            pose=self._estimate(),
            covariance=(var[0], 0.0, 0.0, 0.0, var[1], 0.0, 0.0, 0.0, var[2]),
            stamp=self._now,
        )

    def velocity(self) -> Velocity:
        """The base's current velocity."""
        return self._base.velocity

    def planned_path(self) -> tuple[Pose2D, ...]:
        """The running goal's path as the planner made it (again, after a replan).

        Empty while no goal with a path runs (idle, relative moves and turns, after a stop
        or cancel). The same tuple is returned until the path changes.
        """
        goal = self._goal
        return goal.plan if goal is not None else ()

    def battery(self) -> Battery:
        """Battery charge; it drains with time and faster with motion."""
        return Battery(
            percent=round(self._battery, 2),
            low=self._battery < self._settings.battery_low_percent,
        )

    def current_goal(self) -> SimGoal | None:
        """The running goal, if any."""
        return self._goal

    def status(self) -> NavStatus:
        """Idle, moving, blocked by an obstacle, or failed (with the last goal's reason)."""
        goal = self._goal
        if goal is not None:
            if goal.blocked:
                return NavStatus(NavState.BLOCKED, "obstacle ahead")
            return NavStatus(NavState.MOVING, goal.description)
        if self._teleop and self._teleop_blocked:
            return NavStatus(NavState.BLOCKED, "obstacle ahead")
        if self._teleop and self._base.velocity != Velocity():
            return NavStatus(NavState.MOVING, "manual driving")
        last = self._last_goal
        if not self._teleop and last is not None and last.status is GoalStatus.FAILED:
            return NavStatus(NavState.FAILED, last.reason)
        if self._base.velocity != Velocity():
            return NavStatus(NavState.MOVING, "braking")
        return NavStatus(NavState.IDLE)

    def diagnostics(self) -> Mapping[str, str]:
        """Health values for telemetry."""
        grid = self._grid
        hits = int(np.count_nonzero(self._scan.ranges < self._scan.range_max))
        return {
            "map": f"{self._map_name} {grid.width}x{grid.height} @ {grid.resolution:g} m",
            "laser": f"ok, {hits}/{len(self._scan.ranges)} beams hit",
            "localisation": f"ok, sigma {self._settings.position_noise:g} m",
            "base_watchdog": f"{self._base.watchdog_trips} stop(s) on stale commands",
            "collisions": str(self._collisions),
            "obstacles": str(len(self._obstacles)),
            "speed_limit": f"{self._speed_limit:g} m/s",
            "battery": f"{self._battery:.1f}%",
        }

    # ------------------------------------------------------------------ NavStack: cameras

    def cameras(self) -> tuple[CameraInfo, ...]:
        """The two cameras: ``navcam`` (forward, for driving) and ``usercam`` (for people)."""
        return tuple(
            CameraInfo(m.name, m.width, m.height, m.fov_deg, m.description)
            for m in self._cameras.values()
        )

    def get_frame(self, camera: str | None = None) -> CameraFrame:
        """Render what ``camera`` (default: the active one) sees from the true pose now."""
        model = self._camera(camera if camera is not None else self._active_camera)
        if self._renderer is None:
            self._renderer = Renderer(self._grid)
        image = self._renderer.render(
            self._base.pose, model, tuple(self._obstacles.values()), self._people_now
        )
        self._frame_id += 1
        return CameraFrame(camera=model.name, image=image, stamp=self._now, frame_id=self._frame_id)

    def _camera(self, name: str) -> CameraModel:
        model = self._cameras.get(name.strip().lower())
        if model is None:
            known = ", ".join(self._cameras)
            raise UnknownCamera(f"unknown camera {name!r}; cameras: {known}")
        return model

    # ------------------------------------------------------------------ NavStack: motion

    def navigate_to(
        self, x: float, y: float, yaw: float | None = None, *, label: str = ""
    ) -> SimGoal:
        """Plan from the estimated pose to ``(x, y)`` and drive there; face ``yaw`` if given."""
        require_finite(x=x, y=y)
        if yaw is not None:
            require_finite(yaw=yaw)
        label = label or f"({x:.2f}, {y:.2f})"
        target = Pose2D(x, y, normalize_angle(yaw) if yaw is not None else math.nan)
        goal = self._new_goal(_Kind.PATH, f"goto {label}", target)
        if goal.status is not GoalStatus.ACTIVE:
            return goal
        here = self._estimate()
        try:
            path = self._costmap.plan((here.x, here.y), (x, y))
        except NoPath as exc:
            return self._fail_at_once(goal, f"no path to {label}: {exc}", Reason.NO_PATH)
        goal.final_yaw = None if yaw is None else normalize_angle(yaw)
        _follow(goal, path.waypoints)
        return self._start(goal)

    def forward(self, metres: float) -> SimGoal:
        """Drive straight ``metres`` along the current heading (negative: backwards)."""
        require_finite(metres=metres)
        if abs(metres) > MAX_RELATIVE_MOVE:
            raise InvalidCommand(f"move of {metres} m is over the {MAX_RELATIVE_MOVE:g} m limit")
        here = self._estimate()
        target = Pose2D(
            here.x + metres * math.cos(here.yaw), here.y + metres * math.sin(here.yaw), here.yaw
        )
        goal = self._new_goal(_Kind.STRAIGHT, f"forward {metres:.2f} m", target)
        if goal.status is not GoalStatus.ACTIVE:
            return goal
        goal.start = here
        goal.distance = float(metres)
        return self._start(goal)

    def turn(self, radians: float) -> SimGoal:
        """Turn on the spot by ``radians`` (REP-103: positive is counter-clockwise)."""
        require_finite(radians=radians)
        if abs(radians) > MAX_TURN:
            raise InvalidCommand(f"turn of {math.degrees(radians):.0f}° is over one full turn")
        here = self._estimate()
        target = Pose2D(here.x, here.y, normalize_angle(here.yaw + radians))
        goal = self._new_goal(_Kind.ROTATE, f"turn {math.degrees(radians):.1f}°", target)
        if goal.status is not GoalStatus.ACTIVE:
            return goal
        goal.angle = float(radians)
        goal.last_yaw = here.yaw
        return self._start(goal)

    def stop(self) -> None:
        """Stop now: the running goal is cancelled and the base brakes within one tick."""
        if self._goal is not None:
            self._end_goal(self._goal, GoalStatus.CANCELLED, "stopped", Reason.STOPPED)
        self._teleop = False
        self._base.halt()

    def emergency_stop(self, reason: str) -> None:
        """Stop from any thread (a safety watchdog's): acted on before anything else moves.

        Only a request counter moves here, and only callers of this method write it (the
        stepping side writes its own "handled" counter), so no request is lost and no lock
        is needed; the next :meth:`step` stops the robot before it integrates any motion.
        A stalled caller means no steps, and without steps the simulated base does not move.
        """
        self._emergency_reason = reason or "emergency stop"
        self._emergency_requests += 1

    def cancel(self) -> None:
        """Cancel the running goal, if any (the robot stops)."""
        if self._goal is not None:
            self._cancel_goal(self._goal, "cancelled", Reason.CANCELLED)

    def drive(self, linear: float, angular: float) -> None:
        """Manual velocity command (teleoperation); repeat it, or the base watchdog stops it.

        Replaces any running goal. The laser still stops the base before an obstacle.
        """
        require_finite(linear=linear, angular=angular)
        if self._goal is not None:
            self._end_goal(
                self._goal, GoalStatus.CANCELLED, "replaced by manual driving", Reason.REPLACED
            )
        self._teleop = True
        self._base.set_command(Velocity(float(linear), float(angular)), self._now)

    # ------------------------------------------------------------------ simulation only

    @property
    def now(self) -> float:
        """Simulation time of the last step."""
        return self._now

    @property
    def settings(self) -> SimSettings:
        """The settings the robot was built with."""
        return self._settings

    @property
    def true_pose(self) -> Pose2D:
        """Where the robot really is (the estimate in :meth:`pose` is noisy)."""
        return self._base.pose

    @property
    def collisions(self) -> int:
        """Sub-steps in which the base would have touched something and was held back."""
        return self._collisions

    def laser_scan(self) -> LaserScan:
        """The latest laser scan, taken at the end of the last step (where :meth:`pose` is)."""
        return self._scan

    def add_obstacle(self, obstacle: Obstacle) -> int:
        """Put a dynamic obstacle in the world; returns its id for :meth:`remove_obstacle`."""
        obstacle_id = self._next_obstacle_id
        self._next_obstacle_id += 1
        self._obstacles[obstacle_id] = obstacle
        self._world_changed = True
        return obstacle_id

    def remove_obstacle(self, obstacle_id: int) -> None:
        """Take a dynamic obstacle away (unknown ids are ignored)."""
        if self._obstacles.pop(obstacle_id, None) is not None:
            self._world_changed = True

    @property
    def obstacles(self) -> Mapping[int, Obstacle]:
        """The dynamic obstacles by id."""
        return MappingProxyType(self._obstacles)

    def add_person(self, walker: Walker) -> int:
        """Put a walker in the world, starting its script now; returns its id."""
        person_id = self._next_person_id
        self._next_person_id += 1
        self._people[person_id] = (walker, self._now)
        self._update_people(self._now)
        self._world_changed = True
        return person_id

    def remove_person(self, person_id: int) -> None:
        """Take a person out of the world (unknown ids are ignored)."""
        if self._people.pop(person_id, None) is not None:
            self._update_people(self._now)
            self._world_changed = True

    def people_truth(self) -> tuple[PersonTruth, ...]:
        """Where the simulated people really are, as of the last step (ground truth)."""
        return self._people_now

    def _update_people(self, now: float) -> None:
        truths = []
        for person_id, (walker, added) in self._people.items():
            state = walker.state_at(now - added)
            truths.append(
                PersonTruth(
                    id=person_id,
                    x=state.x,
                    y=state.y,
                    yaw=state.yaw,
                    vx=state.vx,
                    vy=state.vy,
                    walking=state.walking,
                    legs=legs_of(state),
                    walker=walker,
                    travelled=state.travelled,
                )
            )
        self._people_now = tuple(truths)

    def _world_obstacles(self) -> tuple[Obstacle, ...]:
        """Everything round in the world: the obstacles and every person's two legs."""
        legs = tuple(leg for person in self._people_now for leg in person.legs)
        return (*self._obstacles.values(), *legs)

    def set_battery(self, percent: float) -> None:
        """Set the charge (for tests and demonstrations)."""
        require_finite(percent=percent)
        self._battery = min(max(float(percent), 0.0), 100.0)

    # -- topics (the relay service's TopicSource)

    def topics(self) -> list[SourceTopic]:
        """The simulator's streams as ROS 2 topics (see :mod:`telebot.rosmsg.topics`)."""
        return self._topic_source().topics()

    def subscribe_topic(
        self, name: str, callback: Callable[[bytes, float], None]
    ) -> TopicSubscription:
        """Call ``callback(cdr, stamp)`` with each message of topic ``name``, from :meth:`step`."""
        return self._topic_source().subscribe_topic(name, callback)

    def _topic_source(self) -> SimTopics:
        if self._topics is None:
            self._topics = SimTopics(self)
        return self._topics

    def step(self, now: float) -> None:
        """Run one control cycle at ``now`` and move the base up to ``now``."""
        self._step(now)
        if self._topics is not None:
            self._topics.step(now)

    def _step(self, now: float) -> None:
        require_finite(now=now)
        requests = self._emergency_requests
        if requests != self.emergency_stops:
            self.emergency_stops = requests
            self.stop()
        dt_total = now - self._now
        if dt_total <= 0:
            return
        self._update_localisation(dt_total)
        if self._people:
            self._update_people(now)
        obstacles = self._world_obstacles()
        if self._world_changed:
            # Obstacles or people came or went since the last scan: the control of this
            # step sees them.
            self._scan = self._laser.scan(self._base.pose, obstacles)
        if self._goal is not None:
            self._control(self._goal, self._now)
        self._teleop_blocked = False
        if self._teleop:
            self._guard_teleop()
        self._move(now, obstacles)
        # The scan is taken where the base is at ``now``, the time of :meth:`pose`: a scan
        # placed in the map with a pose it was not taken at shifts everything it saw by the
        # distance driven since (a braking robot then sees standing people walk at it).
        self._scan = self._laser.scan(self._base.pose, obstacles)
        self._world_changed = False

    # ------------------------------------------------------------------ internals

    def _estimate(self) -> Pose2D:
        pose = self._base.pose
        return Pose2D(
            pose.x + float(self._noise[0]),
            pose.y + float(self._noise[1]),
            normalize_angle(pose.yaw + float(self._noise[2])),
        )

    def _update_localisation(self, dt: float) -> None:
        # A mean-reverting random walk, clipped at three standard deviations: the error
        # drifts slowly like AMCL's rather than jumping every cycle, and stays bounded.
        decay = math.exp(-dt / NOISE_TIME_CONSTANT)
        kick = self._sigma * math.sqrt(1.0 - decay * decay)
        self._noise = self._noise * decay + self._rng.normal(0.0, 1.0, 3) * kick
        self._noise = np.clip(self._noise, -3.0 * self._sigma, 3.0 * self._sigma)

    def _new_goal(self, kind: _Kind, description: str, target: Pose2D | None) -> SimGoal:
        goal = SimGoal(self, self._next_goal_id, kind, description, target)
        self._next_goal_id += 1
        if self._battery <= 0.0:
            return self._fail_at_once(goal, "battery empty", Reason.BATTERY_EMPTY)
        return goal

    def _fail_at_once(self, goal: SimGoal, reason: str, code: Reason) -> SimGoal:
        # A goal that cannot start leaves the running one alone: a typo must not stop a
        # robot that is driving somewhere sensible.
        goal._finish(GoalStatus.FAILED, reason, code)
        if self._goal is None:
            self._last_goal = goal
        return goal

    def _start(self, goal: SimGoal) -> SimGoal:
        if self._goal is not None:
            self._end_goal(
                self._goal, GoalStatus.CANCELLED, "replaced by a new goal", Reason.REPLACED
            )
        self._teleop = False
        self._goal = goal
        return goal

    def _end_goal(
        self, goal: SimGoal, status: GoalStatus, reason: str = "", code: Reason = Reason.FINISHED
    ) -> None:
        goal._finish(status, reason, code)
        if self._goal is goal:
            self._goal = None
            self._last_goal = goal
            # Brake within the acceleration limits; stop() additionally halts at once.
            self._base.set_command(Velocity(), self._now)

    def _cancel_goal(self, goal: SimGoal, reason: str, code: Reason) -> None:
        if goal.status is GoalStatus.ACTIVE:
            self._end_goal(goal, GoalStatus.CANCELLED, reason, code)
            self._base.halt()

    def _control(self, goal: SimGoal, now: float) -> None:
        """One control cycle for ``goal``: a command for the base, or the goal's end."""
        here = self._estimate()
        limits = self._limits
        settings = self._settings
        remaining = math.inf
        if goal.kind is _Kind.ROTATE or goal.aligning:
            if goal.kind is _Kind.ROTATE:
                goal.turned += normalize_angle(here.yaw - goal.last_yaw)
                goal.last_yaw = here.yaw
                error = goal.angle - goal.turned
                goal._set_progress(1.0 - abs(error) / max(abs(goal.angle), 1e-9))
            else:
                assert goal.final_yaw is not None
                error = normalize_angle(goal.final_yaw - here.yaw)
            if abs(error) <= math.radians(settings.yaw_tolerance_deg) and (
                abs(self._base.velocity.angular) < 0.05
            ):
                self._end_goal(goal, GoalStatus.SUCCEEDED)
                return
            command = Velocity(0.0, rotate_command(error, limits))
        elif goal.kind is _Kind.STRAIGHT:
            command, remaining = straight_command(here, goal.start, goal.distance, limits)
            goal._set_progress(1.0 - abs(remaining) / max(abs(goal.distance), 1e-9))
            if abs(remaining) <= settings.goal_tolerance:
                self._end_goal(goal, GoalStatus.SUCCEEDED)
                return
        else:
            tracker = goal.tracker
            assert tracker is not None
            gx, gy = tracker.goal
            if math.hypot(gx - here.x, gy - here.y) <= settings.goal_tolerance:
                goal._set_progress(1.0)
                if goal.final_yaw is None:
                    self._end_goal(goal, GoalStatus.SUCCEEDED)
                    return
                goal.aligning = True
                self._control(goal, now)
                return
            remaining = tracker.remaining(here)
            if tracker.length > 0:
                goal._set_progress(1.0 - remaining / tracker.length)
            command = tracker.command(here, limits)

        if command.linear != 0.0 or self._base.velocity.linear != 0.0:
            direction = math.copysign(1.0, command.linear or self._base.velocity.linear)
            blocked, static = self._front_blocked(direction, remaining)
            refused = self._refused
            if refused is not None and refused[1] == direction:
                # The physics stopped the base going this way: the laser missed something.
                blocked, static = True, static or refused[0] == "wall"
            if blocked:
                # Turning on the spot keeps the disc where it is: keep turning towards
                # the path, so a base facing a wall beside its goal can still face away.
                # But not while it still rolls: turning then bends its braking path out
                # of the strip the laser found clear, towards what is beside it.
                rolling = self._base.velocity.linear != 0.0
                command = Velocity(0.0, 0.0 if rolling else command.angular)
                if goal.blocked_since is None:
                    goal.blocked_since = now
                if goal.kind is _Kind.STRAIGHT and static:
                    # A wall does not move away: say so now rather than wait.
                    self._end_goal(
                        goal, GoalStatus.FAILED, "stopped: obstacle ahead", Reason.OBSTACLE
                    )
                    return
                if now - goal.blocked_since >= settings.blocked_timeout:
                    self._blocked_too_long(goal, here)
                    return
            else:
                goal.blocked_since = None
        self._base.set_command(command, now)

    def _blocked_too_long(self, goal: SimGoal, here: Pose2D) -> None:
        if goal.kind is not _Kind.PATH or goal.tracker is None:
            self._end_goal(goal, GoalStatus.FAILED, "stopped: obstacle ahead", Reason.OBSTACLE)
            return
        stuck = goal.stuck_at
        if stuck is None or math.hypot(here.x - stuck.x, here.y - stuck.y) >= (
            self._settings.robot_radius
        ):
            goal.stuck_at, goal.stuck_count = here, 1
        else:
            goal.stuck_count += 1
        if goal.stuck_count > REPLANS_IN_PLACE:
            waited = goal.stuck_count * self._settings.blocked_timeout
            self._end_goal(
                goal,
                GoalStatus.FAILED,
                f"stopped: obstacle ahead, no way past it ({waited:g} s blocked in one place)",
                Reason.OBSTACLE,
            )
            return
        costmap = self._costmap.with_obstacles(self._world_obstacles())
        try:
            path = costmap.plan((here.x, here.y), goal.tracker.goal)
        except NoPath as exc:
            self._end_goal(
                goal,
                GoalStatus.FAILED,
                f"stopped: obstacle ahead, no way around ({exc})",
                Reason.OBSTACLE,
            )
            return
        _follow(goal, path.waypoints)
        goal.blocked_since = None
        goal.replans += 1

    def _front_blocked(self, direction: float, remaining: float) -> tuple[bool, bool]:
        """Whether a laser hit lies in the area the base will sweep before it can stop.

        Returns ``(blocked, static)``; ``static`` when a blocking hit is on a map wall.
        """
        settings = self._settings
        speed = abs(self._base.velocity.linear)
        reach = braking_speed_distance(speed, settings.linear_accel) + settings.stop_margin
        # Near the goal only the distance still to drive matters, so a goal just in front
        # of a wall is reachable.
        reach = max(min(reach, remaining), 0.0)
        radius = settings.robot_radius
        points = self._scan.points()
        if points.size == 0:
            return False, False
        # The area the base's disc sweeps ahead while it drives ``reach``: a strip as wide
        # as the base, ended by the disc where it stops (a box there would also take in
        # walls beside a goal that the base never comes near). Against walls that disc is
        # allowed half a map cell of overlap, as the planner is: it measures clearance
        # between cell centres, so a goal it accepts can be that close to a wall's corner.
        ahead = points[:, 0] * direction
        side = np.abs(points[:, 1])
        in_strip = (ahead <= reach) & (side < radius)
        to_end = np.hypot(ahead - reach, side)
        in_end = to_end < radius - 0.5 * self._grid.resolution
        pose = self._base.pose
        cos_y, sin_y = math.cos(pose.yaw), math.sin(pose.yaw)

        def on_person(px: float, py: float) -> bool:
            """Whether the hit at ``(px, py)`` (base frame) is on a dynamic obstacle."""
            wx = pose.x + px * cos_y - py * sin_y
            wy = pose.y + px * sin_y + py * cos_y
            return self._near_dynamic_obstacle(wx, wy)

        for index in np.flatnonzero((to_end < radius) & ~in_end & (ahead > 0.0)):
            in_end[index] = on_person(*points[index])  # people get no slack
        mask = (ahead > 0.0) & (in_strip | in_end)
        mask |= self._on_arc(points, direction, reach)
        if not mask.any():
            return False, False
        static = any(not on_person(px, py) for px, py in points[mask])
        return True, static

    def _on_arc(
        self, points: npt.NDArray[np.float64], direction: float, reach: float
    ) -> npt.NDArray[np.bool_]:
        """Hits the disc would come nearer to and touch braking from its present turn.

        The strip ahead is the sweep of a base driving straight. A base that turns as it
        drives (round a path's corner) sweeps its disc sideways, onto what is beside the
        strip, and turning the strip onto something close beside it finds it already
        within the braking distance. So the way the base takes if it brakes now (speed
        and turn both stopping within their limits, as a blocked base does), then
        straight on along its last heading, is checked too, up to the same ``reach``.
        """
        velocity = self._base.velocity
        limits = self._limits
        none = np.zeros(len(points), dtype=bool)
        if velocity.linear == 0.0 or velocity.angular == 0.0 or reach <= 0.0:
            return none
        speed, turn = abs(velocity.linear), velocity.angular
        until = max(speed / limits.linear_accel, abs(turn) / limits.angular_accel)
        t = np.linspace(0.0, until, max(2, math.ceil(until / 0.01) + 1))
        dt = np.diff(t)
        v = np.maximum(speed - limits.linear_accel * t[:-1], 0.0)
        w = np.sign(turn) * np.maximum(abs(turn) - limits.angular_accel * t[:-1], 0.0)
        heading = np.concatenate([[0.0], np.cumsum(w * dt)])
        step = v * dt
        xs = np.concatenate([[0.0], np.cumsum(direction * step * np.cos(heading[:-1]))])
        ys = np.concatenate([[0.0], np.cumsum(direction * step * np.sin(heading[:-1]))])
        along = np.concatenate([[0.0], np.cumsum(step)])
        # Then straight on for the rest of ``reach`` (the stop margin).
        rest = max(reach - float(along[-1]), 0.0)
        extra = np.linspace(0.0, rest, max(2, math.ceil(rest / 0.02) + 1))[1:]
        xs = np.concatenate([xs, xs[-1] + direction * extra * math.cos(heading[-1])])
        ys = np.concatenate([ys, ys[-1] + direction * extra * math.sin(heading[-1])])
        along = np.concatenate([along, along[-1] + extra])
        keep = along <= reach + 1e-12
        xs, ys = xs[keep], ys[keep]
        if len(xs) < 2:
            return none
        radius = self._settings.robot_radius
        gaps = np.hypot(points[:, 0, None] - xs[None, :], points[:, 1, None] - ys[None, :])
        # As at the strip's end, the disc where the base stops may overlap a wall by half a
        # cell (the planner's slack); on the way there it may overlap nothing.
        limit = np.full(len(xs), radius)
        limit[-1] = radius - 0.5 * self._grid.resolution
        touched = (gaps[:, 1:] < limit[None, 1:]).any(axis=1)
        closer = gaps[:, 1:].min(axis=1) < gaps[:, 0]
        hits: npt.NDArray[np.bool_] = touched & closer
        return hits

    def _near_dynamic_obstacle(self, x: float, y: float) -> bool:
        tolerance = 2.0 * self._grid.resolution
        return any(
            math.hypot(x - obs.x, y - obs.y) <= obs.radius + tolerance
            for obs in self._world_obstacles()
        )

    def _guard_teleop(self) -> None:
        command = self._base.command
        direction = command.linear or self._base.velocity.linear
        if direction == 0.0:
            return
        blocked, _ = self._front_blocked(math.copysign(1.0, direction), math.inf)
        if blocked:
            self._teleop_blocked = True
            # Keep the command's time: being blocked must not refresh the watchdog. The
            # obstacle is beyond the braking distance, so the normal deceleration suffices.
            self._base.command = Velocity(0.0, command.angular)

    def _move(self, now: float, obstacles: Sequence[Obstacle]) -> None:
        dt_max = 1.0 / self._settings.control_hz
        settings = self._settings
        while self._now < now - 1e-12:
            dt = min(dt_max, now - self._now)
            t = self._now + dt
            target = self._base.target(t, self._speed_limit)
            before = self._base.pose
            after = self._base.advance(target, dt, self._speed_limit)
            if self._pose_allowed(before, after, obstacles):
                self._base.commit(after)
                self._refused = None
            else:
                self._collisions += 1
                what: Literal["wall", "obstacle"] = "wall" if self._in_wall(after) else "obstacle"
                self._refused = (what, math.copysign(1.0, target.linear))
                # The turn is kept: turning on the spot does not move the disc.
                self._base.commit(Pose2D(before.x, before.y, after.yaw))
                self._base.halt()
            speed_share = abs(self._base.velocity.linear) / settings.max_linear_speed
            idle_rate = 100.0 / (settings.battery_idle_hours * 3600.0)
            moving_rate = 100.0 / (settings.battery_moving_hours * 3600.0)
            drain = idle_rate + max(moving_rate - idle_rate, 0.0) * speed_share
            self._battery = max(self._battery - drain * dt, 0.0)
            self._now = t
        self._now = now
        if self._battery <= 0.0 and (self._goal is not None or self._teleop):
            if self._goal is not None:
                self._end_goal(self._goal, GoalStatus.FAILED, "battery empty", Reason.BATTERY_EMPTY)
            self._teleop = False
            self._base.halt()

    def _in_wall(self, pose: Pose2D) -> bool:
        costmap = self._costmap
        return not costmap.is_free(pose.x, pose.y) and costmap.touches_wall(pose.x, pose.y)

    def _pose_allowed(self, before: Pose2D, after: Pose2D, obstacles: Sequence[Obstacle]) -> bool:
        """Physics guard: the base never moves into a wall or an obstacle.

        Against walls, a pose is refused when the base's disc overlaps one *and* the
        planner's test (:meth:`Costmap.is_free`) refuses it too. The planner measures
        between cell centres, so it can refuse a point a few centimetres clear of a wall
        (the base drifting that far off a path in a tight passage touches nothing), and
        at a corner it can pass one a centimetre or so inside (its paths stay drivable).
        """
        if self._in_wall(after) and not self._in_wall(before):
            return False
        radius = self._settings.robot_radius
        for obs in obstacles:
            gap_after = math.hypot(after.x - obs.x, after.y - obs.y) - obs.radius - radius
            if gap_after < 0:
                gap_before = math.hypot(before.x - obs.x, before.y - obs.y) - obs.radius - radius
                if gap_after < gap_before:
                    return False
        return True


def _follow(goal: SimGoal, waypoints: npt.NDArray[np.float64]) -> None:
    """Make ``goal`` track ``waypoints``, and keep them as its plan (poses along the path)."""
    goal.tracker = PathTracker(waypoints)
    headings = np.arctan2(np.diff(waypoints[:, 1]), np.diff(waypoints[:, 0]))
    last = (
        goal.final_yaw
        if goal.final_yaw is not None
        else (float(headings[-1]) if len(headings) else 0.0)
    )
    yaws = [*map(float, headings), last]
    goal.plan = tuple(
        Pose2D(float(x), float(y), yaw) for (x, y), yaw in zip(waypoints, yaws, strict=True)
    )


def walkers_of(settings: SimSettings, grid: OccupancyGrid) -> list[Walker]:
    """The ``[[sim.walkers]]`` of ``settings`` as walkers, checked against the map.

    Raises :class:`~telebot.errors.ConfigError` naming the walker and the waypoint when a
    waypoint, or the straight line walked to it, is not free space on ``grid``.
    """
    walkers = []
    for index, entry in enumerate(settings.walkers):
        name = f"sim.walkers[{index}]"
        points = [Waypoint(p[0], p[1], p[2] if len(p) == 3 else 0.0) for p in entry.waypoints]
        for number, point in enumerate(points):
            if not _free(grid, point.x, point.y):
                raise ConfigError(
                    f"{name}: waypoint {number} ({point.x:g}, {point.y:g}) is not free space "
                    f"on map {settings.map!r}"
                )
        legs = list(itertools.pairwise(points))
        if entry.loop:
            legs.append((points[-1], points[0]))
        for a, b in legs:
            blocked = _first_blocked(grid, a, b)
            if blocked is not None:
                raise ConfigError(
                    f"{name}: the way from ({a.x:g}, {a.y:g}) to ({b.x:g}, {b.y:g}) goes "
                    f"through a wall at ({blocked[0]:.2f}, {blocked[1]:.2f})"
                )
        walkers.append(
            Walker(
                tuple(points),
                entry.speed,
                start_delay=entry.start_delay,
                loop=entry.loop,
            )
        )
    return walkers


def _free(grid: OccupancyGrid, x: float, y: float) -> bool:
    row, col = grid.cell_of(x, y)
    return grid.contains_cell(row, col) and 0 <= int(grid.data[row, col]) < 50


def _first_blocked(grid: OccupancyGrid, a: Waypoint, b: Waypoint) -> tuple[float, float] | None:
    """The first point on the line from ``a`` to ``b`` that is not free space, or None."""
    length = math.hypot(b.x - a.x, b.y - a.y)
    steps = max(math.ceil(length / (grid.resolution / 2.0)), 1)
    for i in range(steps + 1):
        x = a.x + (b.x - a.x) * i / steps
        y = a.y + (b.y - a.y) * i / steps
        if not _free(grid, x, y):
            return x, y
    return None


def braking_speed_distance(speed: float, accel: float) -> float:
    """Distance needed to stop from ``speed`` at deceleration ``accel``."""
    return speed * speed / (2.0 * accel)
