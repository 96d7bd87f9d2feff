"""The simulator as a ROS 2 / Nav2 robot: :class:`SimRobotServer` (``telebot-sim``).

A :class:`~telebot.robot.sim.stack.SimNavStack` in its own process, served over rmw_zenoh the
way a Nav2 robot serves itself, so that ``telebot-robot run --robot ros2`` (or any ROS 2 tool
on rmw_zenoh) drives it and the base outlives the daemon that drives it.

What it serves (names from ``[ros2]`` of the robot config, relative to its namespace):

- ``map`` (``nav_msgs/OccupancyGrid``, transient local: late joiners get it; sent again when
  the map changes), ``amcl_pose`` (``PoseWithCovarianceStamped``, the noisy estimate) and
  ``odom`` (``nav_msgs/Odometry``, the true pose and velocity) at the control rate, ``/tf``
  (``map`` -> ``base_link``), ``scan`` (``LaserScan``), ``battery_state`` (1 Hz), ``plan``
  (``nav_msgs/Path``, whenever the plan changes; empty when the goal ends), and each camera's
  ``<camera>/image/compressed`` (JPEG) while something subscribes to it.
- ``cmd_vel`` (``Twist``, or ``TwistStamped`` on Kilted / with ``cmd_vel_stamped``): manual
  driving. A moving command replaces a running goal (a zero one leaves it alone, as on a Nav2
  robot whose controller publishes there too), keeps the simulator's laser stop and speed
  caps, and the base stops by itself ``sim.cmd_vel_timeout`` (0.5 s) after the last command.
- The ``navigate_to_pose``, ``drive_on_heading``, ``spin`` and ``backup`` action servers, with
  feedback and results. A goal the simulator cannot start (no path) is accepted and aborted at
  once with Nav2's error code (and, on Kilted, its ``error_msg``), as Nav2 does.
- Fail safe: the running goal stops when the action client that sent it leaves the ROS graph
  (its liveliness token goes: a killed daemon's session link closes, and zenoh drops its
  tokens at once).

Threads: zenoh calls back on its own threads; every callback only hands its data to the event
loop (``loop.call_soon_threadsafe``), which alone touches the simulator.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import math
import re
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from telebot.config import Ros2Settings
from telebot.errors import InvalidCommand, RobotUnreachable, TelebotError
from telebot.reasons import Reason
from telebot.robot.nav import GoalStatus, Pose2D
from telebot.robot.ros2.keys import EntityKind, GraphEntity, QoS
from telebot.robot.ros2.node import GOAL_CANCELING, GOAL_UNKNOWN, ActionServer, Ros2Node
from telebot.robot.sim.stack import SimGoal, SimNavStack
from telebot.rosmsg.messages import BATTERY_HZ, CAMERA_HZ, SCAN_HZ, SimMessages
from telebot.rosmsg.types import ActionType, TypeLibrary

__all__ = ["SimRobotServer", "open_router", "router_config"]

log = logging.getLogger(__name__)

#: Rates (Hz) of what is not sent every control step.
FEEDBACK_HZ = 10.0
#: How often the camera topics' subscribers are looked up in the graph (s).
GRAPH_POLL_S = 1.0
#: Zenoh link lease the router announces (ms), and keep-alives per lease: its clients (the
#: telebot daemon) know within it that this robot is gone. The other way round, a client's
#: own announced lease says how soon the router drops a client that froze (its tokens with
#: it); a client whose process died has its TCP link closed by the kernel and is dropped
#: at once (measured: 4 ms on loopback).
ROUTER_LEASE_MS = 1000
ROUTER_KEEP_ALIVE = 4

#: Nav2's error codes used when the result type has no constant of that name: ComputePathToPose's
#: NO_VALID_PATH (the code bt_navigator forwards when planning fails), NavigateToPose's UNKNOWN.
NO_VALID_PATH = 208
NAV_UNKNOWN = 9000
#: How long a goal accepted by ``on_goal`` may take to be filed by its action server (s).
REGISTER_WAIT = 1.0


def router_config(listen: Iterable[str]) -> zenoh.Config:
    """A zenoh router's config like ``rmw_zenohd``'s, listening on ``listen``.

    Multicast scouting off (peers come by endpoint), timestamps on (transient-local caches
    need them), and a short link lease (see :data:`ROUTER_LEASE_MS`).
    """
    config = zenoh.Config()
    entries: dict[str, Any] = {
        "mode": "router",
        "listen/endpoints": list(listen),
        "scouting/multicast/enabled": False,
        "timestamping/enabled": {"router": True, "peer": True, "client": True},
        "transport/link/tx/lease": ROUTER_LEASE_MS,
        "transport/link/tx/keep_alive": ROUTER_KEEP_ALIVE,
    }
    for key, value in entries.items():
        config.insert_json5(key, json.dumps(value))
    return config


def open_router(listen: Iterable[str]) -> zenoh.Session:
    """Open a zenoh router listening on ``listen`` (rmw_zenohd's part).

    Raises :class:`~telebot.errors.RobotUnreachable` with zenoh's reason on one line when it
    cannot listen (port taken, bad endpoint).
    """
    endpoints = list(listen)
    try:
        return zenoh.open(router_config(endpoints))
    except zenoh.ZError as exc:
        raise RobotUnreachable(
            f"cannot listen on {', '.join(endpoints)}: {_zenoh_reason(exc)}"
        ) from exc


_RUST_LOCATION = re.compile(r"\s+at\s+\S+\.rs:\d+(:\d+)?\.?")
_JSON5_MESSAGE = re.compile(r'msg: "(.*?)(?<!\\)"')


def _zenoh_reason(exc: BaseException) -> str:
    """zenoh's error message on one line, without its Rust source locations."""
    text = _RUST_LOCATION.sub("", str(exc))
    match = _JSON5_MESSAGE.search(text)
    if match:
        text = match.group(1)
    return " ".join(text.split()) or type(exc).__name__


def _yaw_of(q: Any) -> float:
    """Yaw of a geometry_msgs/Quaternion (REP-103)."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _seconds(duration: Any) -> float:
    """A builtin_interfaces/Duration in seconds."""
    return float(duration.sec) + float(duration.nanosec) * 1e-9


def _field_names(msg: Any) -> set[str]:
    if dataclasses.is_dataclass(msg):
        return {f.name for f in dataclasses.fields(msg)}
    return set(getattr(msg, "__slots__", ()))


@dataclass
class _Goal:
    """An action goal the simulator runs, with what its server needs to answer it."""

    kind: str  # "navigate", "drive", "spin" or "backup"
    server: ActionServer
    goal_id: bytes
    started: float
    sim_goal: SimGoal | None = None
    time_allowance: float = 0.0
    #: The graph entities (liveliness keys) whose loss stops this goal: its client's.
    owners: frozenset[str] = frozenset()
    cancel_requested: bool = False
    #: Distance (m) or angle (rad) asked for, for feedback.
    amount: float = 0.0
    #: Speed (m/s) a drive_on_heading or backup goal asked for: its speed cap.
    speed: float = math.inf
    next_feedback: float = 0.0


@dataclass
class _Topics:
    """The publishers of the robot's topics."""

    map: Any
    amcl_pose: Any
    odom: Any
    tf: Any
    scan: Any
    battery: Any
    plan: Any
    cameras: dict[str, Any] = field(default_factory=dict)


class SimRobotServer:
    """A :class:`SimNavStack` served as a ROS 2 / Nav2 robot on a :class:`Ros2Node`.

    Build it, then ``await server.run(stop)``; it steps the simulator at its control rate on
    the running event loop until ``stop`` is set, and stops the base on the way out. The
    node is the caller's to close.
    """

    def __init__(self, stack: SimNavStack, node: Ros2Node, settings: Ros2Settings) -> None:
        self._stack = stack
        self._node = node
        self._settings = settings
        self._lib: TypeLibrary = node.library
        self._loop: asyncio.AbstractEventLoop | None = None
        self._goals: dict[bytes, _Goal] = {}
        self._map_version: int | None = None
        self._plan: tuple[Pose2D, ...] | None = None
        self._camera_wanted: dict[str, bool] = {}
        self._speed_limit = self._top_speed = stack.speed_limit
        #: Counters for logs and tests: velocity commands taken and refused, goals stopped
        #: because their client left.
        self.cmd_vel_count = 0
        self.cmd_vel_refused = 0
        self.orphaned_goals = 0
        self._msgs = SimMessages(
            self._lib, map_frame=settings.map_frame, base_frame=settings.base_frame
        )
        m = self._lib.message
        self._t_header = m("std_msgs/msg/Header")
        self._t_time = m("builtin_interfaces/msg/Time")
        self._t_duration = m("builtin_interfaces/msg/Duration")
        self._t_pose = m("geometry_msgs/msg/Pose")
        self._t_point = m("geometry_msgs/msg/Point")
        self._t_quat = m("geometry_msgs/msg/Quaternion")
        self._t_vector3 = m("geometry_msgs/msg/Vector3")
        self._t_twist = m("geometry_msgs/msg/Twist")
        self._t_pose_stamped = m("geometry_msgs/msg/PoseStamped")
        self._t_pose_cov = m("geometry_msgs/msg/PoseWithCovariance")
        self._t_pose_cov_stamped = m("geometry_msgs/msg/PoseWithCovarianceStamped")
        self._t_twist_cov = m("geometry_msgs/msg/TwistWithCovariance")
        self._t_transform = m("geometry_msgs/msg/Transform")
        self._t_transform_stamped = m("geometry_msgs/msg/TransformStamped")
        self._t_tf = m("tf2_msgs/msg/TFMessage")
        self._t_odom = m("nav_msgs/msg/Odometry")
        self._t_map = m("nav_msgs/msg/OccupancyGrid")
        self._t_map_info = m("nav_msgs/msg/MapMetaData")
        self._t_path = m("nav_msgs/msg/Path")
        self._t_scan = m("sensor_msgs/msg/LaserScan")
        self._t_battery = m("sensor_msgs/msg/BatteryState")
        self._t_image = m("sensor_msgs/msg/CompressedImage")
        stamped = settings.twist_stamped
        self._t_cmd_vel = m(
            "geometry_msgs/msg/TwistStamped" if stamped else "geometry_msgs/msg/Twist"
        )
        self._actions: dict[str, ActionType] = {
            "navigate": self._lib.action("nav2_msgs/action/NavigateToPose"),
            "drive": self._lib.action("nav2_msgs/action/DriveOnHeading"),
            "spin": self._lib.action("nav2_msgs/action/Spin"),
            "backup": self._lib.action("nav2_msgs/action/BackUp"),
        }
        self._action_names = {
            "navigate": settings.navigate_action,
            "drive": settings.drive_action,
            "spin": settings.spin_action,
            "backup": "backup",
        }
        self._topics = self._declare_topics()
        self._subscriptions: list[Any] = []
        self._servers: dict[str, ActionServer] = {}
        self._unregister_graph: Callable[[], None] = lambda: None

    # ------------------------------------------------------------------ set-up

    def _declare_topics(self) -> _Topics:
        node, s = self._node, self._settings
        latched = QoS.transient_local(depth=1)
        topics = _Topics(
            map=node.publisher(s.map_topic, self._t_map, qos=latched),
            amcl_pose=node.publisher(s.pose_topic or "amcl_pose", self._t_pose_cov_stamped),
            odom=node.publisher(s.odom_topic, self._t_odom),
            tf=node.publisher("/tf", self._t_tf),
            scan=node.publisher(s.scan_topic, self._t_scan),
            battery=node.publisher(s.battery_topic, self._t_battery),
            plan=node.publisher(s.plan_topic, self._t_path),
        )
        for camera in self._stack.cameras():
            topic = self.camera_topic(camera.name)
            topics.cameras[camera.name] = node.publisher(topic, self._t_image)
            self._camera_wanted[camera.name] = False
        return topics

    def camera_topic(self, camera: str) -> str:
        """The CompressedImage topic of ``camera``: ``[ros2] cameras`` or ``<camera>/image/compressed``."""
        return self._settings.cameras.get(camera, f"{camera}/image/compressed")

    def _start_io(self) -> None:
        node, s = self._node, self._settings

        def on_cmd_vel(msg: Any, _attachment: Any) -> None:
            twist = msg.twist if hasattr(msg, "twist") else msg
            linear, angular = float(twist.linear.x), float(twist.angular.z)
            self._post(self._on_cmd_vel, linear, angular)

        self._subscriptions.append(node.subscribe(s.cmd_vel_topic, self._t_cmd_vel, on_cmd_vel))

        def on_speed_limit(msg: Any, _attachment: Any) -> None:
            self._post(self._on_speed_limit, bool(msg.percentage), float(msg.speed_limit))

        self._subscriptions.append(
            node.subscribe(
                s.speed_limit_topic,
                self._lib.message("nav2_msgs/msg/SpeedLimit"),
                on_speed_limit,
                qos=QoS.transient_local(),
            )
        )
        for kind, name in self._action_names.items():
            self._servers[kind] = self._action_server(kind, name)

        def on_graph_change(entity: GraphEntity, appeared: bool) -> None:
            self._post(self._on_graph_change, entity, appeared)

        self._unregister_graph = node.on_graph_change(on_graph_change)

    def _post(self, callback: Callable[..., None], *args: Any) -> None:
        """Run ``callback(*args)`` on the event loop (from any thread); dropped once it closed."""
        loop = self._loop
        if loop is not None:
            with contextlib.suppress(RuntimeError):  # the loop closed: we are shutting down
                loop.call_soon_threadsafe(callback, *args)

    def _action_server(self, kind: str, name: str) -> ActionServer:
        def on_goal(goal_id: bytes, goal: Any) -> bool:
            # Accept here (zenoh's thread) and start in the loop: a goal the simulator
            # cannot start is then aborted with the reason, as Nav2 aborts one it cannot plan.
            self._post(self._start_goal, kind, goal_id, goal)
            return True

        def on_cancel(goal_id: bytes) -> bool:
            self._post(self._cancel_goal, goal_id)
            return True

        return self._node.action_server(
            name, self._actions[kind], on_goal=on_goal, on_cancel=on_cancel
        )

    # ------------------------------------------------------------------ running

    async def run(self, stop: asyncio.Event) -> None:
        """Serve until ``stop`` is set; the base is stopped and every goal ended on the way out."""
        loop = asyncio.get_running_loop()
        self._loop = loop
        self._start_io()
        period = 1.0 / self._stack.control_hz
        next_scan = next_battery = next_camera = next_graph = next_warning = loop.time()
        try:
            while not stop.is_set():
                now = loop.time()
                self._stack.step(now)
                try:
                    self._tick_goals(now)
                    wall = time.time()
                    self._publish_map(wall)
                    self._publish_pose(wall)
                    self._publish_plan(wall)
                    if now >= next_scan:
                        next_scan = now + 1.0 / SCAN_HZ
                        self._publish_scan(wall)
                    if now >= next_battery:
                        next_battery = now + 1.0 / BATTERY_HZ
                        self._publish_battery(wall)
                    if now >= next_graph:
                        next_graph = now + GRAPH_POLL_S
                        self._poll_camera_subscribers()
                    if now >= next_camera:
                        next_camera = now + 1.0 / CAMERA_HZ
                        self._publish_cameras(wall)
                except TelebotError as exc:
                    # The simulation goes on stepping (its base watchdog and laser keep it
                    # safe) whatever zenoh does; say what failed, once a second at most.
                    if now >= next_warning:
                        next_warning = now + 1.0
                        log.warning("publishing failed: %s", exc)
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), max(0.0, now + period - loop.time()))
        finally:
            self._shutdown()

    def _shutdown(self) -> None:
        self._unregister_graph()
        self._stack.stop()
        for goal in list(self._goals.values()):
            self._finish(goal, "abort", "the robot is shutting down", Reason.STOPPED)
        for sub in self._subscriptions:
            with contextlib.suppress(Exception):
                sub.close()

    # ------------------------------------------------------------------ velocity commands

    def _on_cmd_vel(self, linear: float, angular: float) -> None:
        if linear == 0.0 and angular == 0.0 and self._stack.current_goal() is not None:
            # As on a Nav2 robot, where the controller publishes on cmd_vel too: a zero
            # command does not end a goal (cancel_goal does). The stop a teleop or a
            # telebot daemon streams after cancelling must not end the next goal either.
            self.cmd_vel_count += 1
            return
        try:
            self._stack.drive(linear, angular)
        except InvalidCommand as exc:
            self.cmd_vel_refused += 1
            log.warning("%s: command dropped: %s", self._settings.cmd_vel_topic, exc)
            return
        self.cmd_vel_count += 1

    # ------------------------------------------------------------------ goals

    def _start_goal(self, kind: str, goal_id: bytes, msg: Any, waited: float = 0.0) -> None:
        loop = self._loop
        assert loop is not None
        server = self._servers[kind]
        if server.status(goal_id) == GOAL_UNKNOWN:
            # on_goal ran, but the server files the goal only once on_goal has returned:
            # start it then, so that its result is not lost.
            if waited < REGISTER_WAIT:
                loop.call_later(0.002, self._start_goal, kind, goal_id, msg, waited + 0.002)
            return
        owners = self._owners_of(kind, server.client_gid(goal_id))
        goal = _Goal(kind, server, goal_id, started=loop.time(), owners=owners)
        self._goals[goal_id] = goal
        if server.status(goal_id) == GOAL_CANCELING:  # cancelled before it could start
            self._finish(goal, "cancel", "cancelled", Reason.CANCELLED)
            return
        stack = self._stack
        try:
            if kind == "navigate":
                frame = str(msg.pose.header.frame_id).lstrip("/")
                if frame not in ("", self._settings.map_frame):
                    self._finish(
                        goal,
                        "abort",
                        f"goal frame {frame!r} is not the map frame {self._settings.map_frame!r}",
                        Reason.INVALID,
                    )
                    return
                p = msg.pose.pose
                goal.sim_goal = stack.navigate_to(
                    float(p.position.x), float(p.position.y), _yaw_of(p.orientation)
                )
            elif kind in ("drive", "backup"):
                distance = float(msg.target.x)
                speed = abs(float(msg.speed))
                if kind == "backup":
                    distance = -abs(distance)
                elif speed > 0 and distance * float(msg.speed) < 0:
                    raise InvalidCommand("speed and target have opposite signs")
                if float(msg.target.y) != 0.0 or float(msg.target.z) != 0.0:
                    raise InvalidCommand("only target.x (straight ahead) is supported")
                if not math.isfinite(speed) or speed <= 0:
                    raise InvalidCommand(f"speed must be positive, not {msg.speed}")
                goal.time_allowance = _seconds(msg.time_allowance)
                goal.amount = distance
                goal.speed = speed
                goal.sim_goal = stack.forward(distance)
            else:  # spin
                goal.time_allowance = _seconds(msg.time_allowance)
                goal.amount = float(msg.target_yaw)
                goal.sim_goal = stack.turn(goal.amount)
        except (InvalidCommand, TelebotError) as exc:
            self._finish(goal, "abort", str(exc), Reason.INVALID)
            return
        self._apply_speed_cap()
        sim_goal = goal.sim_goal
        if sim_goal.status is not GoalStatus.ACTIVE:
            self._finish(goal, "abort", sim_goal.reason, Reason(sim_goal.code or Reason.FAILED))
            return
        log.info("goal %s: %s", goal_id.hex()[:8], sim_goal.description)

    def _cancel_goal(self, goal_id: bytes) -> None:
        goal = self._goals.get(goal_id)
        if goal is None:
            return
        goal.cancel_requested = True
        if goal.sim_goal is not None:
            goal.sim_goal.cancel()
        self._tick_goals(self._loop.time() if self._loop else 0.0)

    def _tick_goals(self, now: float) -> None:
        self._tick_each_goal(now)
        self._apply_speed_cap()

    def _tick_each_goal(self, now: float) -> None:
        for goal in list(self._goals.values()):
            sim_goal = goal.sim_goal
            if sim_goal is None:
                continue
            if not goal.owners:
                # Its client was not in our view of the graph yet: look again.
                goal.owners = self._owners_of(goal.kind, goal.server.client_gid(goal.goal_id))
            status = sim_goal.status
            if status is GoalStatus.SUCCEEDED:
                self._finish(goal, "succeed", "", Reason.FINISHED)
            elif status is GoalStatus.CANCELLED and goal.cancel_requested:
                self._finish(goal, "cancel", "cancelled", Reason.CANCELLED)
            elif status.done:
                self._finish(goal, "abort", sim_goal.reason, Reason(sim_goal.code or "failed"))
            elif goal.time_allowance > 0 and now - goal.started > goal.time_allowance:
                sim_goal.cancel()
                self._finish(
                    goal,
                    "abort",
                    f"time allowance of {goal.time_allowance:g} s exceeded",
                    "timeout",
                )
            elif now >= goal.next_feedback:
                goal.next_feedback = now + 1.0 / FEEDBACK_HZ
                self._feedback(goal, now)

    def _on_speed_limit(self, percentage: bool, limit: float) -> None:
        """Nav2's controller takes a cap (m/s, or percent of the top speed); 0 = no limit."""
        top = self._top_speed
        if not math.isfinite(limit) or limit < 0:
            log.warning("%s: ignored a speed limit of %r", self._settings.speed_limit_topic, limit)
            return
        cap = top if limit == 0 else min(top, top * limit / 100.0 if percentage else limit)
        self._speed_limit = cap
        self._apply_speed_cap()

    def _apply_speed_cap(self) -> None:
        """The running goal's speed (drive_on_heading, backup) caps the base; else the top speed."""
        running = self._stack.current_goal()
        cap = self._speed_limit
        for goal in self._goals.values():
            if goal.sim_goal is running and running is not None:
                cap = min(cap, goal.speed)
        if cap != self._stack.speed_limit:
            self._stack.set_speed_limit(cap)

    def _finish(self, goal: _Goal, how: str, reason: str, code: str) -> None:
        """End ``goal`` on its action server: ``succeed``, ``cancel`` or ``abort``."""
        if self._goals.pop(goal.goal_id, None) is None:
            return
        if goal.sim_goal is not None and not goal.sim_goal.status.done:
            goal.sim_goal.cancel()
        result = self._result(goal, how, reason, code)
        if how != "succeed":
            log.info("goal %s %sed: %s", goal.goal_id.hex()[:8], how.rstrip("e"), reason)
        try:
            getattr(goal.server, how)(goal.goal_id, result)
        except TelebotError as exc:
            log.warning("goal %s: cannot send its result: %s", goal.goal_id.hex()[:8], exc)

    def _result(self, goal: _Goal, how: str, reason: str, code: str) -> Any:
        atype = self._actions[goal.kind]
        fields: dict[str, Any] = {}
        probe = atype.result.make()
        names = _field_names(probe)
        if how == "abort":
            fields["error_code"] = self._error_code(goal.kind, probe, code)
            fields["error_msg"] = reason
        if "total_elapsed_time" in names and self._loop is not None:
            fields["total_elapsed_time"] = self._duration(self._loop.time() - goal.started)
        return atype.result.make(**{k: v for k, v in fields.items() if k in names})

    @staticmethod
    def _error_code(kind: str, probe: Any, code: str) -> int:
        """Nav2's error code for a telebot reason code (the result type's constant if it has one)."""
        cls = type(probe)
        if kind == "navigate":
            if code == Reason.NO_PATH:
                return int(getattr(cls, "NO_VALID_PATH", NO_VALID_PATH))
            name = "TIMEOUT" if code == "timeout" else "UNKNOWN"
            return int(getattr(cls, name, NAV_UNKNOWN))
        name = {
            Reason.OBSTACLE: "COLLISION_AHEAD",
            Reason.INVALID: "INVALID_INPUT",
            "timeout": "TIMEOUT",
        }.get(code, "UNKNOWN")
        value: int | None = getattr(cls, name, None)
        if value is None:
            value = getattr(cls, "UNKNOWN", 1)
        return int(value or 0)

    def _feedback(self, goal: _Goal, now: float) -> None:
        sim_goal = goal.sim_goal
        assert sim_goal is not None
        atype = self._actions[goal.kind]
        progress = sim_goal.progress
        if goal.kind == "navigate":
            tracker = sim_goal.tracker
            length = tracker.length if tracker is not None else 0.0
            remaining = max(0.0, (1.0 - progress) * length)
            speed = max(self._stack.speed_limit, 1e-3)
            estimate = self._stack.pose()
            fb = atype.feedback_body.make(
                current_pose=self._pose_stamped(estimate.pose, time.time()),
                navigation_time=self._duration(now - goal.started),
                estimated_time_remaining=self._duration(remaining / speed),
                number_of_recoveries=min(sim_goal.replans, 32767),
                distance_remaining=remaining,
            )
        elif goal.kind == "spin":
            fb = atype.feedback_body.make(angular_distance_traveled=abs(goal.amount) * progress)
        else:
            fb = atype.feedback_body.make(distance_traveled=abs(goal.amount) * progress)
        goal.server.publish_feedback(goal.goal_id, fb)

    # ------------------------------------------------------------------ client liveliness

    def _owners_of(self, kind: str, gid: bytes | None) -> frozenset[str]:
        """Graph keys whose loss stops a goal of ``kind`` sent by the client ``gid``.

        rmw_zenoh names a request's client by its GID (a hash of the client's liveliness
        key) in the attachment: the owners are that client and its node. Without a GID that
        matches a client in the graph (not known, not seen yet, or not rmw_zenoh's), every
        client of the action is an owner: when in doubt, stop.
        """
        client = self._node.entity_by_gid(gid) if gid is not None else None
        if client is not None:
            return frozenset({client.key, _node_key(client)})
        clients = self._node.find(EntityKind.CLIENT, self._send_goal_service(kind))
        return frozenset(entity.key for entity in clients)

    def _send_goal_service(self, kind: str) -> str:
        return self._action_names[kind].rstrip("/") + "/_action/send_goal"

    def _on_graph_change(self, entity: GraphEntity, appeared: bool) -> None:
        if appeared:
            return
        keys = _loss_keys(entity)
        for goal in list(self._goals.values()):
            if keys & goal.owners:
                self.orphaned_goals += 1
                log.warning(
                    "goal %s: its action client left the ROS graph: stopping",
                    goal.goal_id.hex()[:8],
                )
                self._stack.stop()
                self._finish(goal, "abort", "the action client left", Reason.STOPPED)

    def _poll_camera_subscribers(self) -> None:
        for camera in self._camera_wanted:
            # Our own node has no subscription on it: any count is someone else's.
            self._camera_wanted[camera] = self._topics.cameras[camera].subscriber_count() > 0

    # ------------------------------------------------------------------ publishing

    def _duration(self, seconds: float) -> Any:
        return self._msgs.duration(seconds)

    def _pose_stamped(self, pose: Pose2D, wall: float) -> Any:
        return self._msgs.pose_stamped(pose, wall)

    def _publish_map(self, wall: float) -> None:
        version = self._stack.map_version()
        if version == self._map_version:
            return
        self._map_version = version
        grid = self._stack.map()
        self._topics.map.publish(self._msgs.map(grid, wall))
        log.info("published map %d: %d x %d cells", version, grid.width, grid.height)

    def _publish_pose(self, wall: float) -> None:
        stack, msgs = self._stack, self._msgs
        estimate = stack.pose()
        self._topics.amcl_pose.publish(msgs.amcl_pose(estimate, wall))
        self._topics.odom.publish(msgs.odom(stack.true_pose, stack.velocity(), wall))
        self._topics.tf.publish(msgs.tf(estimate.pose, wall))

    def _publish_plan(self, wall: float) -> None:
        plan = self._stack.planned_path()
        if plan is self._plan:
            return
        self._plan = plan
        self._topics.plan.publish(self._msgs.path(plan, wall))

    def _publish_scan(self, wall: float) -> None:
        self._topics.scan.publish(self._msgs.scan(self._stack.laser_scan(), wall))

    def _publish_battery(self, wall: float) -> None:
        self._topics.battery.publish(self._msgs.battery(self._stack.battery(), wall))

    def _publish_cameras(self, wall: float) -> None:
        for camera, wanted in self._camera_wanted.items():
            if not wanted:
                continue
            frame = self._stack.get_frame(camera)
            msg = self._msgs.image(camera, frame.image, wall)
            if msg is not None:
                self._topics.cameras[camera].publish(msg)


def _node_key(entity: GraphEntity) -> str:
    """What names the node that ``entity`` belongs to (its session's id and node id)."""
    return f"node:{entity.zid}/{entity.node_id}"


def _loss_keys(entity: GraphEntity) -> set[str]:
    """The owner keys that ``entity`` leaving the graph ends."""
    keys = {entity.key}
    if entity.kind == EntityKind.NODE:
        keys.add(_node_key(entity))
    return keys
