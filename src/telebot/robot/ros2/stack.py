"""``Ros2NavStack``: a ROS 2 / Nav2 robot behind the :class:`~telebot.robot.nav.NavStack` protocol.

The adapter ``"ros2"`` of :mod:`telebot.robot`. It joins the robot's zenoh network as one
ROS 2 node (:class:`~telebot.robot.ros2.node.Ros2Node`, a client of rmw_zenoh's router) and
maps Nav2's interfaces onto the protocol (names from ``[ros2]``, relative to its namespace):

===========================  =============================================================
NavStack                     ROS 2
===========================  =============================================================
``map()``                    ``/map`` ``nav_msgs/OccupancyGrid`` (transient local); each
                             map that differs (cells, resolution, origin) bumps
                             ``map_version()``, one republished unchanged does not
``pose()``                   ``/amcl_pose`` ``PoseWithCovarianceStamped``, or the tf
                             ``map`` → ``base_link`` chain of ``/tf`` + ``/tf_static``
``velocity()``               ``/odom`` ``nav_msgs/Odometry`` twist
``battery()``                ``/battery_state`` ``sensor_msgs/BatteryState`` (low < 20 %)
``laser_scan()``             ``/scan`` ``sensor_msgs/LaserScan`` (people detection)
``planned_path()``           ``/plan`` ``nav_msgs/Path`` while a navigation goal runs
``get_frame()``              ``sensor_msgs/CompressedImage`` topics of ``[ros2] cameras``,
                             subscribed while frames are asked for; ``navcam`` is black
                             when no topic is named so
``navigate_to()``            ``navigate_to_pose`` action (``nav2_msgs/NavigateToPose``);
                             progress from its feedback, Nav2's error text and code
``forward()``                ``drive_on_heading`` behaviour, speed ≤ the speed cap
``turn()``                   ``spin`` behaviour (REP-103: positive is counter-clockwise)
``GoalHandle.cancel()``      the action's ``cancel_goal`` with the goal's id
``stop()``,                  cancel every goal of the three actions, and zero velocity on
``emergency_stop()``         ``cmd_vel`` (Twist or TwistStamped) at ``stop_rate_hz`` for
                             ``stop_stream_s`` (a new motion ends the stream)
===========================  =============================================================

The adapter is not stepped: Nav2 runs by itself, and zenoh calls back on its own threads.
State is kept under one lock; every method may be called from any thread, and
:meth:`Ros2NavStack.emergency_stop` needs no event loop. Samples that do not map (a huge
or malformed map, a pose that is not finite) are dropped, counted, and logged with their
topic; Nav2 refusing or aborting a goal fails its handle with Nav2's words.
"""

from __future__ import annotations

import functools
import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from telebot.config import RobotConfig, Ros2Settings
from telebot.errors import (
    InvalidCommand,
    RobotError,
    RobotUnreachable,
    UnknownCamera,
)
from telebot.reasons import Reason
from telebot.robot.grid import OccupancyGrid
from telebot.robot.mapfile import CELL_OCCUPIED_MIN, load_places
from telebot.robot.nav import (
    DEFAULT_CONTROL_HZ,
    DEFAULT_FOV_DEG,
    NAVCAM,
    NO_SIGNAL_SIZE,
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
    normalize_angle,
    require_finite,
)
from telebot.robot.ros2.convert import (
    ScanData,
    TfTree,
    battery_from_msg,
    covariance_xy_yaw,
    duration_fields,
    grid_from_msg,
    nav2_reason,
    path_from_msg,
    pose_from_msg,
    quaternion_fields,
    scan_from_msg,
)
from telebot.robot.ros2.keys import EntityKind, GraphEntity, QoS, action_names
from telebot.robot.ros2.node import DEFAULT_QOS, ActionClient, Ros2Node, Subscription
from telebot.rosmsg.types import ActionType, MessageType, TypeLibrary, ros_type_name

__all__ = ["BATTERY_LOW_PERCENT", "Ros2Goal", "Ros2NavStack"]

log = logging.getLogger(__name__)

#: Charge (percent) below which the battery reports low.
BATTERY_LOW_PERCENT = 20.0
#: Longest relative move accepted (metres) and largest turn (radians), as the simulator.
MAX_RELATIVE_MOVE = 100.0
MAX_TURN = 2.0 * math.pi
#: A behaviour gets this much time beyond what its motion needs at the commanded speed (s).
TIME_ALLOWANCE_MARGIN = 10.0
#: A navigation goal whose feedback counted a new recovery within this long is "blocked" (s).
RECOVERY_HOLD = 5.0
#: Odometry speeds below these count as standing still (m/s, rad/s).
STILL_LINEAR, STILL_ANGULAR = 0.01, 0.02
#: Keep-alives per link lease (``[ros2] lease``, 0.5 s by default): the router drops a daemon
#: that froze (SIGSTOP, a hung machine) within the lease, and with it the liveliness of its
#: goals, so the base stops by itself (rmw_zenoh's default lease is 60 s). A daemon that
#: died has its TCP link closed by the kernel and is dropped at once anyway.
CLIENT_KEEP_ALIVE = 4
#: The lowest speed limit sent to Nav2 (m/s): its 0 means "no limit".
NAV2_SLOWEST_LIMIT = 0.01
#: A laser scan older than this (s) is no scan: people detection and follow-me's clearance
#: see nothing rather than a frozen picture (a laser publishes at 10–40 Hz).
SCAN_STALE = 1.0
#: Bytes of an OccupancyGrid message besides its cells (header, frame id, metadata): generous.
MAP_HEADER_BYTES = 4096
#: Start-up waits at least this long for Nav2 and the map once the router answered (s).
MIN_DISCOVERY = 0.5
#: A camera topic nobody asked a frame of for this long is unsubscribed (s).
CAMERA_IDLE = 5.0
#: How long close() waits for a running zero-velocity stream to finish (beyond its length, s).
CLOSE_GRACE = 0.5

# action_msgs/GoalStatus codes.
_STATUS_SUCCEEDED, _STATUS_CANCELED, _STATUS_ABORTED = 4, 5, 6

_NAVIGATE, _DRIVE, _SPIN = "navigate", "drive", "spin"


class Ros2Goal(GoalRecord):
    """A goal sent to one of Nav2's actions; implements :class:`~telebot.robot.nav.GoalHandle`.

    Its state changes on zenoh's threads (acceptance, feedback, result) and on the caller's
    (cancel, stop), always under the stack's lock; the first end it reaches is kept.
    """

    def __init__(
        self,
        stack: Ros2NavStack,
        goal_id: int,
        kind: str,
        description: str,
        target: Pose2D | None,
        amount: float = 0.0,
    ) -> None:
        super().__init__(goal_id, description, target)
        self._stack = stack
        self.kind = kind
        #: Distance (m) or angle (rad) a drive or spin covers; 0 for navigation.
        self.amount = amount
        #: The action goal's UUID (16 bytes), once sent.
        self.ros_id: bytes | None = None
        self.accepted = False
        #: Navigation feedback: the largest distance remaining seen, and recoveries.
        self.initial_remaining = 0.0
        self.planned = False
        self.recoveries = 0
        self.recovered_at = -math.inf

    def cancel(self) -> None:
        """Cancel the goal if it still runs: Nav2 gets a ``cancel_goal`` with its id."""
        self._stack._cancel_goal(self, "cancelled", Reason.CANCELLED)

    def _finish(self, status: GoalStatus, reason: str = "", code: Reason = Reason.FINISHED) -> bool:
        """End the goal (the caller holds the lock); False if it had ended already."""
        if self._status is not GoalStatus.ACTIVE:
            return False
        self._end(status, reason, code)
        return True


class _ZeroStream:
    """Zero velocity on the teleop topic: once at once, then at a rate until a deadline.

    :meth:`trigger` publishes one command in the caller's thread (the base hears the stop
    without waiting for a thread switch) and extends the stream; a thread of its own keeps
    publishing. :meth:`end` ends it early: a new motion must not be fought by zeros (a base
    or a twist_mux may take them for teleoperation that replaces the goal). Safe from any
    thread.
    """

    def __init__(self, publish: Callable[[], None], rate_hz: float, duration: float) -> None:
        self._publish = publish
        self._period = 1.0 / rate_hz
        self._duration = duration
        self._cond = threading.Condition()
        # Held around each publish, so that after end() returns no zero is still on its way.
        self._publishing = threading.Lock()
        self._until = 0.0
        self._closed = False
        self._thread: threading.Thread | None = None
        #: Zero commands published.
        self.sent = 0

    def trigger(self) -> None:
        """Publish zero velocity now and keep streaming it for the stream's duration."""
        with self._publishing:
            self._send()
        with self._cond:
            if self._closed:
                return
            self._until = time.monotonic() + self._duration
            if self._thread is None:
                self._thread = threading.Thread(
                    target=self._run, name="ros2-zero-velocity", daemon=True
                )
                self._thread.start()
            self._cond.notify_all()

    def end(self) -> None:
        """End a running stream now; no zero is published after this returns."""
        with self._cond:
            self._until = 0.0
            self._cond.notify_all()
        with self._publishing:
            pass

    @property
    def streaming(self) -> bool:
        """Whether a stream is running now."""
        with self._cond:
            return time.monotonic() < self._until

    def _send(self) -> None:
        try:
            self._publish()
            self.sent += 1
        except Exception as exc:  # a transport hiccup must not end the stream
            log.warning("zero velocity not published: %s", exc)

    def _run(self) -> None:
        next_at = time.monotonic() + self._period
        while True:
            with self._cond:
                while not self._closed and time.monotonic() >= self._until:
                    self._cond.wait()
                    next_at = time.monotonic() + self._period
                if self._closed:
                    return
                delay = next_at - time.monotonic()
                if delay > 0:
                    self._cond.wait(delay)
                    continue
            with self._publishing:
                if time.monotonic() < self._until:  # not ended meanwhile
                    self._send()
            next_at = max(next_at + self._period, time.monotonic())

    def close(self, wait: float) -> None:
        """Let a running stream go on for up to ``wait`` seconds, then end the thread."""
        deadline = time.monotonic() + wait
        with self._cond:
            while not self._closed and time.monotonic() < min(self._until, deadline):
                self._cond.wait(min(self._until, deadline) - time.monotonic())
            self._closed = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=1.0)


class _Camera:
    """The newest CompressedImage of one camera topic."""

    __slots__ = ("data", "fmt", "info", "name", "received", "stamp", "sub", "topic", "wanted_at")

    def __init__(self, name: str, topic: str) -> None:
        self.name = name
        self.topic = topic
        #: The subscription while someone asks for frames (None: not subscribed).
        self.sub: Subscription | None = None
        self.wanted_at = 0.0
        self.info: CameraInfo | None = None
        self.data: bytes = b""
        self.fmt = ""
        self.stamp = 0.0
        self.received = 0


def _decode_image(data: bytes) -> np.ndarray[Any, np.dtype[np.uint8]] | None:
    """A JPEG or PNG as a BGR uint8 image, or None if it does not decode."""
    if not data:
        return None
    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR)
    except cv2.error:
        return None
    if image is None or image.ndim != 3 or image.dtype != np.uint8:
        return None
    return np.ascontiguousarray(image)


class Ros2NavStack(NavStackBase):
    """A Nav2 robot over rmw_zenoh (see the module docstring). Build it with :meth:`from_config`."""

    def __init__(
        self,
        node: Ros2Node,
        settings: Ros2Settings,
        *,
        places: Mapping[str, Pose2D] | None = None,
    ) -> None:
        # Nav2 knows no radius or accelerations telebot could read: follow-me and driving
        # by hand plan with the defaults (the base's controller keeps its own limits).
        super().__init__(
            MotionLimits(
                max_linear_speed=settings.max_linear_speed,
                max_angular_speed=settings.max_angular_speed,
            ),
            places=places,
        )
        self._node = node
        self._settings = settings
        self._lib: TypeLibrary = node.library
        self._lock = threading.RLock()
        self._closed = False

        self._grid: OccupancyGrid | None = None
        self._map_version = 0
        self._maps_received = 0
        self._map_ready = threading.Event()
        self._map_at = 0.0
        self._pose: PoseEstimate | None = None
        self._pose_at = 0.0
        self._pose_listeners: list[Callable[[], None]] = []
        self._tf = TfTree()
        self._velocity = Velocity()
        self._odom_at = 0.0
        self._scan_at = 0.0
        self._scan_beams = 0
        self._scan: ScanData | None = None
        self._scan_good_at = -math.inf
        self._battery: Battery | None = None
        self._battery_at = 0.0
        self._path: tuple[Pose2D, ...] = ()
        self._dropped: dict[str, int] = {}
        self._closed_drops = 0  # of camera subscriptions closed when idle
        self._next_goal_id = 1
        self._goal: Ros2Goal | None = None
        self._last_goal: Ros2Goal | None = None
        self._stops = 0
        # A stop's cancel-alls not answered yet, and the goal sent after it, held until they
        # are: ROS 2 keeps no order between the cancel_goal and send_goal services, so a
        # goal sent at once could reach Nav2 first and be cancelled by the stop before it.
        self._cancels_unanswered = 0
        self._held: Callable[[], None] | None = None
        self._cameras: dict[str, _Camera] = {
            name.lower(): _Camera(name.lower(), topic) for name, topic in settings.cameras.items()
        }
        # The safety supervisor selects the navcam whenever the robot moves: a robot without
        # one still has it, showing black ("no signal"), rather than refuse to move.
        self._cameras.setdefault(NAVCAM, _Camera(NAVCAM, ""))

        lib = self._lib
        self._twist = lib.message("geometry_msgs/msg/Twist")
        self._twist_stamped = lib.message("geometry_msgs/msg/TwistStamped")
        self._header = lib.message("std_msgs/msg/Header")
        self._time = lib.message("builtin_interfaces/msg/Time")
        self._duration = lib.message("builtin_interfaces/msg/Duration")
        self._point = lib.message("geometry_msgs/msg/Point")
        self._quaternion = lib.message("geometry_msgs/msg/Quaternion")
        self._pose_msg = lib.message("geometry_msgs/msg/Pose")
        self._pose_stamped = lib.message("geometry_msgs/msg/PoseStamped")

        self._actions: dict[str, tuple[str, ActionType]] = {
            _NAVIGATE: (settings.navigate_action, lib.action("nav2_msgs/action/NavigateToPose")),
            _DRIVE: (settings.drive_action, lib.action("nav2_msgs/action/DriveOnHeading")),
            _SPIN: (settings.spin_action, lib.action("nav2_msgs/action/Spin")),
        }
        self._clients: dict[str, ActionClient] = {
            kind: node.action_client(name, atype) for kind, (name, atype) in self._actions.items()
        }
        cmd_type = self._twist_stamped if settings.twist_stamped else self._twist
        self._cmd_vel = node.publisher(settings.cmd_vel_topic, cmd_type)
        self._zero = _ZeroStream(self._publish_zero, settings.stop_rate_hz, settings.stop_stream_s)
        self._speed_limit_type = lib.message("nav2_msgs/msg/SpeedLimit")
        self._speed_limit_pub = node.publisher(
            settings.speed_limit_topic, self._speed_limit_type, qos=QoS.transient_local()
        )

        self._subscriptions: list[Subscription] = []
        latched = QoS.transient_local()
        # A map over the cell limit is dropped before it is decoded (one byte a cell).
        self._listen(
            settings.map_topic,
            "nav_msgs/msg/OccupancyGrid",
            self._on_map,
            qos=latched,
            max_bytes=settings.max_map_cells + MAP_HEADER_BYTES,
        )
        if settings.pose_topic:
            self._listen(
                settings.pose_topic,
                "geometry_msgs/msg/PoseWithCovarianceStamped",
                self._on_pose,
            )
        else:
            self._listen("/tf", "tf2_msgs/msg/TFMessage", self._on_tf)
            self._listen(
                "/tf_static",
                "tf2_msgs/msg/TFMessage",
                self._on_tf_static,
                qos=QoS.transient_local(depth=100),  # tf2's static broadcaster keeps 100
            )
        self._listen(settings.odom_topic, "nav_msgs/msg/Odometry", self._on_odom)
        self._listen(settings.scan_topic, "sensor_msgs/msg/LaserScan", self._on_scan)
        self._listen(settings.battery_topic, "sensor_msgs/msg/BatteryState", self._on_battery)
        self._listen(settings.plan_topic, "nav_msgs/msg/Path", self._on_plan)
        # A goal whose server leaves the graph (Nav2 crashed, the robot's router went away)
        # will never get a result: it fails at once rather than look active for ever.
        self._send_goal_names = {
            kind: node.resolve(action_names(name)["send_goal"])
            for kind, (name, _) in self._actions.items()
        }
        self._unwatch_graph = node.on_graph_change(self._on_graph_change)
        # Camera topics are subscribed while frames are asked for (see get_frame): a robot's
        # image streams cross the router only when someone watches.
        self._camera_lock = threading.Lock()
        self._camera_reaper: threading.Thread | None = None
        self._camera_wake = threading.Event()
        # The cap Nav2 has may be a lower one left by a daemon before us: say ours.
        self._publish_speed_limit()

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_config(
        cls, config: RobotConfig, *, base_dir: Path | None = None, now: float = 0.0
    ) -> Ros2NavStack:
        """Join the robot's ROS 2 graph as ``[ros2]`` says and wait for Nav2 and the map.

        Waits up to ``connect_timeout`` for the navigate_to_pose action server and a map.
        Raises :class:`~telebot.errors.RobotUnreachable` (one line naming what is missing:
        the router, the action server, the map topic, or a type hash that differs from the
        robot's) and :class:`~telebot.errors.ConfigError` for a bad places file.
        """
        del now  # Nav2 keeps its own time
        settings = config.ros2
        places: dict[str, Pose2D] = {}
        if settings.places_file is not None:
            path = settings.places_file
            if base_dir is not None and not path.is_absolute():
                path = base_dir / path
            places = load_places(path)
        routers = ", ".join(settings.router)
        started = time.monotonic()
        try:
            node = Ros2Node(
                name=settings.node_name,
                namespace=settings.namespace,
                domain_id=settings.domain_id,
                connect=settings.router,
                mode="client",
                library=TypeLibrary(settings.distro),
                connect_timeout=settings.connect_timeout,
                zenoh_options={
                    "transport/link/tx/lease": round(settings.lease * 1000),
                    "transport/link/tx/keep_alive": CLIENT_KEEP_ALIVE,
                },
            )
        except RobotUnreachable as exc:
            raise RobotUnreachable(
                f"no ROS 2 router at {routers}: is rmw_zenohd (or telebot-sim) running?"
            ) from exc
        try:
            stack = cls(node, settings, places=places)
        except BaseException:
            node.close()
            raise
        try:
            # connect_timeout bounds the whole start-up; discovery still gets a moment.
            elapsed = time.monotonic() - started
            stack.wait_ready(max(settings.connect_timeout - elapsed, MIN_DISCOVERY))
        except BaseException:
            stack.close()
            raise
        return stack

    def wait_ready(self, timeout: float) -> None:
        """Wait until Nav2's navigate_to_pose server and a map are there.

        Raises :class:`~telebot.errors.RobotUnreachable` naming the first thing missing
        after ``timeout`` seconds, or at once when the server is there with another type
        hash (another ROS 2 distro).
        """
        deadline = time.monotonic() + timeout
        while True:
            missing = self._missing()
            if missing is None:
                return
            if time.monotonic() >= deadline:
                raise RobotUnreachable(missing)
            time.sleep(0.02)

    def _missing(self) -> str | None:
        settings = self._settings
        name, atype = self._actions[_NAVIGATE]
        if not self._clients[_NAVIGATE].server_ready():
            service = action_names(name)["send_goal"]
            self._check_hash(
                EntityKind.SERVICE, service, atype.send_goal.type_hash, f"{name} action"
            )
            return (
                f"no Nav2 action server {name!r} ({atype.name}) in ROS domain "
                f"{settings.domain_id} after {settings.connect_timeout:g} s: is Nav2 running?"
            )
        if not self._map_ready.is_set():
            ours = self._lib.message("nav_msgs/msg/OccupancyGrid").type_hash
            self._check_hash(
                EntityKind.PUBLISHER, settings.map_topic, ours, f"{settings.map_topic} topic"
            )
            return (
                f"no map on topic {settings.map_topic!r} (nav_msgs/msg/OccupancyGrid) after "
                f"{settings.connect_timeout:g} s: is the map server (or SLAM) running?"
            )
        # The behaviours are optional (fwd and turn fail without them), but one of another
        # distro is a configuration mistake worth stopping for.
        for kind in (_DRIVE, _SPIN):
            name, atype = self._actions[kind]
            service = action_names(name)["send_goal"]
            self._check_hash(
                EntityKind.SERVICE, service, atype.send_goal.type_hash, f"{name} action"
            )
        return None

    def _check_hash(self, kind: EntityKind, name: str, ours: str, what: str) -> None:
        """RobotUnreachable if the graph has ``name`` of ``kind`` with another type hash.

        rmw_zenoh puts the hash in every key, so an endpoint of another distro's type is on
        the graph (its liveliness token says so) but never hears us, nor we it.
        """
        for entity in self._node.find(kind, name):
            if entity.type_hash and entity.type_hash != ours:
                raise RobotUnreachable(
                    f"the robot's {what} has type hash {entity.type_hash}, telebot's {ours} "
                    f"({self._settings.distro}): set [ros2] distro to the robot's ROS 2 distro"
                )

    def close(self) -> None:
        """Finish a running zero-velocity stream, then leave the ROS graph. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._unwatch_graph()
        self._camera_wake.set()
        self._zero.close(self._settings.stop_stream_s + CLOSE_GRACE)
        self._node.close()

    # ------------------------------------------------------------------ subscriptions

    def _listen(
        self,
        topic: str,
        type_name: str,
        handler: Callable[[Any, Any], None],
        *,
        qos: QoS | None = None,
        max_bytes: int | None = None,
    ) -> Subscription:
        mtype: MessageType = self._lib.message(type_name)
        full_name = self._node.resolve(topic)

        def callback(msg: Any, attachment: Any) -> None:
            if self._closed:
                return
            try:
                handler(msg, attachment)
            except (ValueError, TypeError, AttributeError) as exc:
                self._drop(full_name, str(exc))

        sub = self._node.subscribe(
            topic, mtype, callback, qos=qos if qos is not None else QoS(), max_bytes=max_bytes
        )
        self._subscriptions.append(sub)
        return sub

    def _drop(self, topic: str, why: str) -> None:
        with self._lock:
            count = self._dropped[topic] = self._dropped.get(topic, 0) + 1
        # Log the first few and then every hundredth: a peer sending garbage at a high
        # rate must not flood the log.
        if count <= 3 or count % 100 == 0:
            log.warning("dropped a message on %s (%d so far): %s", topic, count, why)

    def _on_map(self, msg: Any, _attachment: Any) -> None:
        grid = grid_from_msg(msg, max_cells=self._settings.max_map_cells)
        with self._lock:
            self._maps_received += 1
            self._map_at = time.monotonic()
            # SLAM nodes and map servers republish on a timer: an unchanged map keeps its
            # version (and snapshot), so no one re-encodes or re-downloads it.
            if self._grid is not None and self._grid.same_content(grid):
                return
            self._grid = grid
            self._map_version += 1
        self._map_ready.set()
        log.info(
            "map %dx%d @ %g m from %s (version %d)",
            grid.width,
            grid.height,
            grid.resolution,
            self._settings.map_topic,
            self._map_version,
        )

    def _on_pose(self, msg: Any, _attachment: Any) -> None:
        pose = pose_from_msg(msg.pose.pose)
        covariance = covariance_xy_yaw(msg.pose.covariance)
        now = time.monotonic()
        with self._lock:
            self._pose = PoseEstimate(pose, covariance, now)
            self._pose_at = now
        self._notify_pose()

    def _on_tf(self, msg: Any, _attachment: Any) -> None:
        self._take_tf(msg, static=False)

    def _on_tf_static(self, msg: Any, _attachment: Any) -> None:
        self._take_tf(msg, static=True)

    def _take_tf(self, msg: Any, *, static: bool) -> None:
        now = time.monotonic()
        settings = self._settings
        with self._lock:
            self._tf.update(msg.transforms, now, static=static)
            found = self._tf.lookup(settings.map_frame, settings.base_frame)
            if found is not None:
                pose, oldest = found
                stamp = now if math.isinf(oldest) else oldest
                self._pose = PoseEstimate(pose, (0.0,) * 9, stamp)
                self._pose_at = stamp
        if found is not None:
            self._notify_pose()

    # -- topics (the relay service's TopicSource)

    def topics(self) -> list[SourceTopic]:
        """Every topic published on the robot's zenoh network now (from the ROS graph),
        with its type and, when the type library knows it, its schema."""
        found: dict[str, str] = {}
        for entity in self._node.graph():
            if entity.kind == EntityKind.PUBLISHER and entity.topic and entity.dds_type:
                found.setdefault(entity.topic, entity.dds_type)
        return [
            SourceTopic(name, ros_type_name(dds), self._schema(ros_type_name(dds)))
            for name, dds in sorted(found.items())
        ]

    def _schema(self, type_name: str) -> str:
        try:
            return self._lib.schema_text(type_name)
        except Exception:  # a type the library does not know: relayed without a schema
            return ""

    def subscribe_topic(
        self, name: str, callback: Callable[[bytes, float], None]
    ) -> TopicSubscription:
        """Relay ``name``: ``callback(cdr, time.time())`` with each sample's bytes as they
        came (undecoded), from a zenoh thread. LookupError if nothing publishes it."""
        publishers = [
            e
            for e in self._node.graph()
            if e.kind == EntityKind.PUBLISHER and e.topic == name and e.dds_type and e.type_hash
        ]
        if not publishers:
            raise LookupError(f"nothing publishes {name} on the robot's network")
        first = min(publishers, key=lambda e: (e.dds_type or "", e.type_hash or ""))
        assert first.dds_type is not None and first.type_hash is not None
        # A latched topic (the map) is asked for its last message, as any late subscriber.
        latched = first.qos is not None and first.qos.is_transient_local
        qos = QoS.transient_local(depth=1) if latched else DEFAULT_QOS

        def deliver(data: bytes, _attachment: Any) -> None:
            callback(data, time.time())

        return self._node.subscribe_raw(
            name,
            first.dds_type,
            first.type_hash,
            deliver,
            qos=qos,
        )

    def add_pose_listener(self, listener: Callable[[], None]) -> None:
        """Call ``listener()`` after each new pose (from zenoh's thread): see PoseNotifier."""
        self._pose_listeners.append(listener)

    def _notify_pose(self) -> None:
        for listener in list(self._pose_listeners):
            try:
                listener()
            except Exception:  # a listener's bug must not cost the pose updates
                log.exception("pose listener failed")

    def _on_odom(self, msg: Any, _attachment: Any) -> None:
        twist = msg.twist.twist
        linear, angular = float(twist.linear.x), float(twist.angular.z)
        if not (math.isfinite(linear) and math.isfinite(angular)):
            raise ValueError("odometry velocity is not finite")
        # A base at rest reports a little noise; below these it stands still (the safety
        # supervisor and the camera rule ask whether the robot moves).
        linear = linear if abs(linear) > STILL_LINEAR else 0.0
        angular = angular if abs(angular) > STILL_ANGULAR else 0.0
        with self._lock:
            self._velocity = Velocity(linear, angular)
            self._odom_at = time.monotonic()

    def _on_scan(self, msg: Any, _attachment: Any) -> None:
        beams = len(msg.ranges)
        try:
            scan: ScanData | None = scan_from_msg(msg)
        except ValueError:
            scan = None  # counted as a scan for health; not looked at for people
        with self._lock:
            self._scan_beams = beams
            self._scan_at = time.monotonic()
            if scan is not None:
                self._scan = scan
                self._scan_good_at = self._scan_at

    def laser_scan(self) -> ScanData | None:
        """The latest good ``scan`` message (person detection, follow-me's clearance);
        None before the first and when none came for :data:`SCAN_STALE` seconds (a laser
        that stopped, or sends garbage, must not leave a frozen picture of free space)."""
        with self._lock:
            if time.monotonic() - self._scan_good_at > SCAN_STALE:
                return None
            return self._scan

    def _on_battery(self, msg: Any, _attachment: Any) -> None:
        battery = battery_from_msg(msg, BATTERY_LOW_PERCENT)
        with self._lock:
            self._battery = battery
            self._battery_at = time.monotonic()

    def _on_plan(self, msg: Any, _attachment: Any) -> None:
        path = path_from_msg(msg)
        with self._lock:
            self._path = path

    def _on_image(self, camera: _Camera, msg: Any, _attachment: Any) -> None:
        data = bytes(np.asarray(msg.data, dtype=np.uint8).tobytes())
        info = camera.info
        if info is None:
            image = _decode_image(data)
            if image is None:
                raise ValueError(f"not a JPEG or PNG image (format {msg.format!r})")
            info = CameraInfo(
                name=camera.name,
                width=int(image.shape[1]),
                height=int(image.shape[0]),
                fov_deg=DEFAULT_FOV_DEG,
                description=f"ROS 2 topic {camera.topic}",
            )
        with self._lock:
            camera.info = info
            camera.data = data
            camera.fmt = str(msg.format)
            camera.stamp = time.monotonic()
            camera.received += 1

    def _on_graph_change(self, entity: GraphEntity, alive: bool) -> None:
        if alive or entity.kind is not EntityKind.SERVICE:
            return
        with self._lock:
            goal = self._goal
        if goal is None or entity.topic != self._send_goal_names[goal.kind]:
            return
        if self._clients[goal.kind].server_ready():
            return  # another server of the action is still there
        name = self._actions[goal.kind][0]
        self._end(
            goal,
            GoalStatus.FAILED,
            f"{goal.description} failed: Nav2's {name} action server left the ROS graph",
            Reason.FAILED,
        )

    # ------------------------------------------------------------------ what it declares

    @property
    def control_hz(self) -> float:
        """:data:`~telebot.robot.nav.DEFAULT_CONTROL_HZ`: Nav2 runs by itself; follow-me
        and driving by hand send ``cmd_vel`` at this rate."""
        return DEFAULT_CONTROL_HZ

    # ------------------------------------------------------------------ NavStack: queries

    def map(self) -> OccupancyGrid:
        """The latest map received on the map topic."""
        with self._lock:
            grid = self._grid
        if grid is None:
            raise RobotError(f"no map received on {self._settings.map_topic!r} yet")
        return grid

    def map_version(self) -> int:
        """How many different maps have arrived (a map republished unchanged adds none).

        A map is its cells, resolution and origin; the message's header stamp is not.
        """
        with self._lock:
            return self._map_version

    def pose(self) -> PoseEstimate:
        """The latest pose (AMCL's, or tf's map → base frame); the origin before the first."""
        with self._lock:
            pose = self._pose
        if pose is None:
            return PoseEstimate(Pose2D(0.0, 0.0, 0.0), (0.0,) * 9, 0.0)
        return pose

    def velocity(self) -> Velocity:
        """The velocity of the latest odometry message (speeds below 1 cm/s, 0.02 rad/s: 0)."""
        with self._lock:
            return self._velocity

    def planned_path(self) -> tuple[Pose2D, ...]:
        """Nav2's global plan (the plan topic) while a navigation goal runs; else empty."""
        with self._lock:
            goal = self._goal
            if goal is None or goal.kind != _NAVIGATE:
                return ()
            return self._path

    def battery(self) -> Battery:
        """The latest battery state; 0 % and low until one arrives (fail safe)."""
        with self._lock:
            battery = self._battery
        return battery if battery is not None else Battery(percent=0.0, low=True)

    def current_goal(self) -> Ros2Goal | None:
        """The goal that is running, if any."""
        with self._lock:
            return self._goal

    def status(self) -> NavStatus:
        """Idle, moving, blocked (Nav2 recovering) or failed (the last goal's reason)."""
        now = time.monotonic()
        with self._lock:
            goal = self._goal
            velocity = self._velocity
            last = self._last_goal
        if goal is not None:
            if goal.kind == _NAVIGATE and now - goal.recovered_at < RECOVERY_HOLD:
                return NavStatus(
                    NavState.BLOCKED, f"Nav2 recovering ({goal.recoveries} recoveries)"
                )
            return NavStatus(NavState.MOVING, goal.description)
        if velocity != Velocity():
            return NavStatus(NavState.MOVING, "moving")
        if last is not None and last.status is GoalStatus.FAILED:
            return NavStatus(NavState.FAILED, last.reason)
        return NavStatus(NavState.IDLE)

    def set_speed_limit(self, linear: float) -> None:
        """Set the linear speed cap (never above ``[ros2] max_linear_speed``), applied to
        drive_on_heading and sent to Nav2's controller when it changes."""
        before = self._speed_limit
        super().set_speed_limit(linear)
        if self._speed_limit != before:
            self._publish_speed_limit()

    def _publish_speed_limit(self) -> None:
        """Tell Nav2's controller the cap (absolute, m/s), so navigation goals keep it too.

        To Nav2 a limit of 0 means *no* limit: a zero cap goes out as 1 cm/s (telebot starts
        no motion under a zero cap anyway).
        """
        self._speed_limit_pub.publish(
            self._speed_limit_type.make(
                header={"frame_id": self._settings.base_frame},
                percentage=False,
                speed_limit=max(self._speed_limit, NAV2_SLOWEST_LIMIT),
            )
        )

    def diagnostics(self) -> Mapping[str, str]:
        """Health values: router, Nav2, map, pose, odometry, scan, battery, drops."""
        now = time.monotonic()

        def age(at: float) -> str:
            return f"{now - at:.1f} s old" if at > 0 else "none yet"

        # Asked of zenoh and the graph before the state lock is taken: zenoh's threads
        # take that lock, so nothing holds it while calling into zenoh.
        router = self._router_state()
        action = self._settings.navigate_action
        nav2 = (
            f"{action} ready" if self._clients[_NAVIGATE].server_ready() else f"{action} not found"
        )
        dropped = self._node_drops()
        with self._lock:
            grid = self._grid
            values = {
                "router": router,
                "nav2": nav2,
                "map": (
                    f"{grid.width}x{grid.height} @ {grid.resolution:g} m, version "
                    f"{self._map_version} ({self._maps_received} received), "
                    f"{age(self._map_at)}"
                    if grid is not None
                    else "none yet"
                ),
                "pose": age(self._pose_at),
                "odom": age(self._odom_at),
                "scan": (
                    f"{self._scan_beams} beams, {age(self._scan_at)}"
                    if self._scan_at > 0
                    else "none yet"
                ),
                "battery": (
                    f"{self._battery.percent:.0f}%, {age(self._battery_at)}"
                    if self._battery is not None
                    else "none yet"
                ),
                "dropped": str(sum(self._dropped.values()) + dropped),
                "speed_limit": f"{self._speed_limit:g} m/s",
                "stops": str(self._stops),
            }
        return values

    def _router_state(self) -> str:
        endpoints = ", ".join(self._settings.router)
        try:
            routers = len(list(self._node.session.info.routers_zid()))
        except Exception:  # a closed or failing session: say so, never raise from telemetry
            return f"{endpoints}: no session"
        return f"{endpoints}: connected" if routers else f"{endpoints}: not connected"

    def _node_drops(self) -> int:
        return self._closed_drops + sum(sub.stats.dropped for sub in list(self._subscriptions))

    # ------------------------------------------------------------------ NavStack: cameras

    def cameras(self) -> tuple[CameraInfo, ...]:
        """The cameras of ``[ros2] cameras`` (size known from each one's first image, 0 × 0
        before), and ``navcam`` (black) if they have none of that name."""
        with self._lock:
            return tuple(
                camera.info
                if camera.info is not None
                else CameraInfo(
                    camera.name,
                    0,
                    0,
                    DEFAULT_FOV_DEG,
                    f"ROS 2 topic {camera.topic} (no image yet)"
                    if camera.topic
                    else "no camera topic in [ros2] cameras (black)",
                )
                for camera in self._cameras.values()
            )

    def _camera(self, name: str) -> _Camera:
        camera = self._cameras.get(name.strip().lower())
        if camera is None:
            known = ", ".join(self._cameras) or "none"
            raise UnknownCamera(f"unknown camera {name!r}; cameras: {known}")
        return camera

    def get_frame(self, camera: str | None = None) -> CameraFrame:
        """The newest image of ``camera`` decoded (black until its first image arrives).

        The camera's topic is subscribed from the first call on, and unsubscribed when no
        frame has been asked of it for :data:`CAMERA_IDLE` seconds.
        """
        cam = self._camera(camera if camera is not None else self._active_camera)
        if cam.topic:
            self._want_camera(cam)
        with self._lock:
            data, stamp, received, info = cam.data, cam.stamp, cam.received, cam.info
        image = _decode_image(data)
        if image is None:
            width, height = (info.width, info.height) if info is not None else NO_SIGNAL_SIZE
            image = np.zeros((height, width, 3), np.uint8)
        return CameraFrame(camera=cam.name, image=image, stamp=stamp, frame_id=received)

    def _want_camera(self, camera: _Camera) -> None:
        """Keep ``camera`` subscribed for :data:`CAMERA_IDLE` more seconds."""
        camera.wanted_at = time.monotonic()
        if camera.sub is not None:
            return
        # Its own lock, never the state lock: zenoh may call back (and so take the state
        # lock) while a subscription is declared or undeclared.
        with self._camera_lock:
            if camera.sub is not None or self._closed:
                return
            camera.sub = self._listen(
                camera.topic,
                "sensor_msgs/msg/CompressedImage",
                functools.partial(self._on_image, camera),
            )
            if self._camera_reaper is None:
                self._camera_reaper = threading.Thread(
                    target=self._reap_cameras, name="ros2-camera-idle", daemon=True
                )
                self._camera_reaper.start()

    def _reap_cameras(self) -> None:
        """Unsubscribe cameras nobody asked a frame of for :data:`CAMERA_IDLE` seconds."""
        while not self._camera_wake.wait(CAMERA_IDLE / 4):
            now = time.monotonic()
            with self._camera_lock:
                for camera in self._cameras.values():
                    sub = camera.sub
                    if sub is None or now - camera.wanted_at <= CAMERA_IDLE:
                        continue
                    camera.sub = None
                    self._subscriptions.remove(sub)
                    self._closed_drops += sub.stats.dropped
                    sub.close()

    # ------------------------------------------------------------------ NavStack: motion

    def navigate_to(
        self, x: float, y: float, yaw: float | None = None, *, label: str = ""
    ) -> Ros2Goal:
        """Send a NavigateToPose goal to ``(x, y)`` facing ``yaw`` (default: along the way)."""
        require_finite(x=x, y=y)
        if yaw is not None:
            require_finite(yaw=yaw)
        label = label or f"({x:.2f}, {y:.2f})"
        here = self.pose().pose
        if yaw is None:
            far = math.hypot(x - here.x, y - here.y) > 1e-3
            yaw = math.atan2(y - here.y, x - here.x) if far else here.yaw
        target = Pose2D(float(x), float(y), normalize_angle(yaw))
        goal = self._new_goal(_NAVIGATE, f"goto {label}", target)
        if goal.status is not GoalStatus.ACTIVE:
            return goal
        with self._lock:
            grid = self._grid
        if grid is not None:
            if not grid.contains(x, y):
                return self._fail_at_once(
                    goal, f"no path to {label}: outside the map", Reason.NO_PATH
                )
            if grid.value_at(x, y) >= CELL_OCCUPIED_MIN:
                return self._fail_at_once(
                    goal, f"no path to {label}: inside an obstacle", Reason.NO_PATH
                )
        settings = self._settings
        _, atype = self._actions[_NAVIGATE]
        message = atype.goal.make(
            pose=self._pose_stamped.make(
                header=self._header.make(frame_id=settings.map_frame, stamp=self._time.make()),
                pose=self._pose_msg.make(
                    position=self._point.make(x=float(x), y=float(y), z=0.0),
                    orientation=self._quaternion.make(**quaternion_fields(target.yaw)),
                ),
            ),
            behavior_tree="",
        )
        goal.initial_remaining = here.distance_to(target)
        return self._send(goal, message)

    def forward(self, metres: float) -> Ros2Goal:
        """DriveOnHeading ``metres`` (negative: backwards) at the speed cap."""
        require_finite(metres=metres)
        if abs(metres) > MAX_RELATIVE_MOVE:
            raise InvalidCommand(f"move of {metres} m is over the {MAX_RELATIVE_MOVE:g} m limit")
        here = self.pose().pose
        target = Pose2D(
            here.x + metres * math.cos(here.yaw), here.y + metres * math.sin(here.yaw), here.yaw
        )
        goal = self._new_goal(_DRIVE, f"forward {metres:.2f} m", target, abs(float(metres)))
        if goal.status is not GoalStatus.ACTIVE:
            return goal
        if metres == 0:
            with self._lock:
                goal._finish(GoalStatus.SUCCEEDED)
            return goal
        speed = self._speed_limit
        if speed <= 0:
            return self._fail_at_once(goal, "the speed limit is 0 m/s", Reason.FAILED)
        _, atype = self._actions[_DRIVE]
        message = atype.goal.make(
            target=self._point.make(x=float(metres), y=0.0, z=0.0),
            # Nav2 wants the speed's sign to match the target's.
            speed=math.copysign(speed, metres),
            time_allowance=self._duration.make(
                **duration_fields(abs(metres) / speed + TIME_ALLOWANCE_MARGIN)
            ),
        )
        return self._send(goal, message)

    def turn(self, radians: float) -> Ros2Goal:
        """Spin by ``radians`` (REP-103: positive is counter-clockwise)."""
        require_finite(radians=radians)
        if abs(radians) > MAX_TURN:
            raise InvalidCommand(f"turn of {math.degrees(radians):.0f}° is over one full turn")
        here = self.pose().pose
        target = Pose2D(here.x, here.y, normalize_angle(here.yaw + radians))
        goal = self._new_goal(
            _SPIN, f"turn {math.degrees(radians):.1f}°", target, abs(float(radians))
        )
        if goal.status is not GoalStatus.ACTIVE:
            return goal
        if radians == 0:
            with self._lock:
                goal._finish(GoalStatus.SUCCEEDED)
            return goal
        if self._speed_limit <= 0:
            return self._fail_at_once(goal, "the speed limit is 0 m/s", Reason.FAILED)
        _, atype = self._actions[_SPIN]
        allowance = abs(radians) / self._settings.max_angular_speed + TIME_ALLOWANCE_MARGIN
        message = atype.goal.make(
            target_yaw=float(radians),
            time_allowance=self._duration.make(**duration_fields(allowance)),
        )
        return self._send(goal, message)

    def drive(self, linear: float, angular: float) -> None:
        """One velocity command on ``cmd_vel`` (follow-me); repeat it at the control rate.

        The linear speed is clipped to the speed cap in force and the turn to ``[ros2]
        max_angular_speed``. It ends the zero stream of an earlier stop and cancels a
        running goal (manual driving replaces it, as on the simulator). A base stops by
        itself when the commands stop coming (its cmd_vel timeout); :meth:`stop` streams
        zeros.
        """
        require_finite(linear=linear, angular=angular)
        cap = self._speed_limit
        top_turn = self._settings.max_angular_speed
        linear = max(-cap, min(cap, float(linear)))
        angular = max(-top_turn, min(top_turn, float(angular)))
        with self._lock:
            goal = self._goal
        if goal is not None:
            self._end(goal, GoalStatus.CANCELLED, "replaced by manual driving", Reason.REPLACED)
            if goal.ros_id is not None:
                self._cancel_remote(goal)
        self._zero.end()
        twist = {"linear": {"x": linear}, "angular": {"z": angular}}
        if self._settings.twist_stamped:
            now = time.time()
            sec = math.floor(now)
            header = self._header.make(
                stamp=self._time.make(sec=int(sec), nanosec=int((now - sec) * 1e9)),
                frame_id=self._settings.base_frame,
            )
            self._cmd_vel.publish(self._twist_stamped.make(header=header, twist=twist))
        else:
            self._cmd_vel.publish(self._twist.make(**twist))

    def stop(self) -> None:
        """Stop now: cancel every goal of the three actions and stream zero velocity."""
        self._halt("stopped", Reason.STOPPED)

    def emergency_stop(self, reason: str) -> None:
        """Stop from any thread (the safety watchdog's): the same as :meth:`stop`, no loop."""
        self._halt(reason or "emergency stop", Reason.STOPPED)

    # ------------------------------------------------------------------ internals

    def _halt(self, why: str, code: Reason) -> None:
        # Zero velocity first: it reaches the base without waiting for Nav2.
        self._zero.trigger()
        with self._lock:
            self._stops += 1
            goal = self._goal
            if goal is not None:
                goal._finish(GoalStatus.CANCELLED, why, code)
                self._retire(goal)
            self._held = None  # a goal held behind an earlier stop ended with this one
        for kind, client in self._clients.items():
            with self._lock:
                self._cancels_unanswered += 1
            try:
                client.cancel_all(on_done=self._cancel_answered)
            except Exception as exc:  # one action's trouble must not keep the others running
                self._cancel_answered(-1, [], str(exc))
                log.warning("cancelling all %s goals failed: %s", self._actions[kind][0], exc)

    def _cancel_answered(self, code: int, canceling: list[bytes], why: str) -> None:
        """A stop's cancel-all was answered (or timed out): send a goal held behind it."""
        del code, canceling, why
        with self._lock:
            self._cancels_unanswered = max(0, self._cancels_unanswered - 1)
            held = self._held if self._cancels_unanswered == 0 else None
            if held is not None:
                self._held = None
        if held is not None:
            held()

    def _publish_zero(self) -> None:
        if self._settings.twist_stamped:
            now = time.time()
            sec = math.floor(now)
            header = self._header.make(
                stamp=self._time.make(sec=int(sec), nanosec=int((now - sec) * 1e9)),
                frame_id=self._settings.base_frame,
            )
            self._cmd_vel.publish(self._twist_stamped.make(header=header))
        else:
            self._cmd_vel.publish(self._twist.make())

    def _new_goal(
        self, kind: str, description: str, target: Pose2D | None, amount: float = 0.0
    ) -> Ros2Goal:
        with self._lock:
            goal = Ros2Goal(self, self._next_goal_id, kind, description, target, amount)
            self._next_goal_id += 1
        return goal

    def _fail_at_once(self, goal: Ros2Goal, reason: str, code: Reason) -> Ros2Goal:
        # A goal that cannot start leaves the running one alone.
        with self._lock:
            goal._finish(GoalStatus.FAILED, reason, code)
            if self._goal is None:
                self._last_goal = goal
        return goal

    def _retire(self, goal: Ros2Goal) -> None:
        """The goal has ended: it is no longer the current one (lock held)."""
        if self._goal is goal:
            self._goal = None
            self._last_goal = goal

    def _send(self, goal: Ros2Goal, message: Any) -> Ros2Goal:
        """Send ``goal`` to its action, replacing the running goal."""
        client = self._clients[goal.kind]
        if not client.server_ready():
            name = self._actions[goal.kind][0]
            return self._fail_at_once(
                goal,
                f"{goal.description} not possible: the robot has no Nav2 {name!r} action server",
                Reason.FAILED,
            )
        # A new motion ends the zero stream of an earlier stop (the driver re-armed and
        # moves on), or the base would take the zeros as someone else's command.
        self._zero.end()
        with self._lock:
            previous = self._goal
            if previous is not None:
                previous._finish(GoalStatus.CANCELLED, "replaced by a new goal", Reason.REPLACED)
                self._retire(previous)
            self._goal = goal
            self._path = ()
        # Nav2's servers preempt a running goal of their own action with a new one; a goal
        # of another action must be cancelled, or two servers would drive at once.
        if previous is not None and previous.kind != goal.kind and previous.ros_id is not None:
            self._cancel_remote(previous)

        def transmit() -> None:
            if goal.status.done:  # stopped or replaced while it was held
                return
            try:
                ros_id = client.send_goal(
                    message,
                    on_accepted=lambda gid, ok: self._on_accepted(goal, gid, ok),
                    on_feedback=lambda fb: self._on_feedback(goal, fb),
                    on_result=lambda status, result, text: self._on_result(
                        goal, status, result, text
                    ),
                )
            except Exception as exc:
                reason = f"{goal.description} not sent: {exc}"
                self._end(goal, GoalStatus.FAILED, reason, Reason.FAILED)
                return
            with self._lock:
                goal.ros_id = bytes(ros_id)

        with self._lock:
            hold = self._cancels_unanswered > 0
            if hold:
                self._held = transmit
        if not hold:
            transmit()
        return goal

    def _end(self, goal: Ros2Goal, status: GoalStatus, reason: str, code: Reason) -> None:
        with self._lock:
            if goal._finish(status, reason, code):
                self._retire(goal)

    def _on_accepted(self, goal: Ros2Goal, goal_id: bytes, accepted: bool) -> None:
        name = self._actions[goal.kind][0]
        if not accepted:
            self._end(
                goal,
                GoalStatus.FAILED,
                f"Nav2 rejected {goal.description}: the {name} server refused the goal",
                Reason.FAILED,
            )
            return
        with self._lock:
            goal.ros_id = bytes(goal_id)
            goal.accepted = True
            cancelled = goal.status is not GoalStatus.ACTIVE
        if cancelled:
            # Cancelled (or replaced, or stopped) before Nav2 accepted it: cancel it now.
            self._cancel_remote(goal)

    def _on_feedback(self, goal: Ros2Goal, feedback: Any) -> None:
        with self._lock:
            if goal.status is not GoalStatus.ACTIVE:
                return
            if goal.kind == _NAVIGATE:
                remaining = float(feedback.distance_remaining)
                # Nav2 reports 0 until it has a path: progress starts at the first real one.
                if math.isfinite(remaining) and remaining > 0:
                    goal.planned = True
                    goal.initial_remaining = max(goal.initial_remaining, remaining)
                if goal.planned and math.isfinite(remaining) and remaining >= 0:
                    goal._set_progress(1.0 - remaining / goal.initial_remaining)
                recoveries = int(feedback.number_of_recoveries)
                if recoveries > goal.recoveries:
                    goal.recoveries = recoveries
                    goal.recovered_at = time.monotonic()
            elif goal.kind == _DRIVE:
                goal._set_progress(abs(float(feedback.distance_traveled)) / goal.amount)
            else:
                goal._set_progress(abs(float(feedback.angular_distance_traveled)) / goal.amount)

    def _on_result(self, goal: Ros2Goal, status: int, result: Any, text: str) -> None:
        name = self._actions[goal.kind][0]
        if status == _STATUS_SUCCEEDED:
            self._end(goal, GoalStatus.SUCCEEDED, "", Reason.FINISHED)
        elif status == _STATUS_CANCELED:
            self._end(goal, GoalStatus.CANCELLED, f"cancelled by Nav2 ({name})", Reason.CANCELLED)
        elif status == _STATUS_ABORTED and result is not None:
            error_code = int(getattr(result, "error_code", 0))
            error_msg = str(getattr(result, "error_msg", "")).strip() or "no reason given"
            self._end(
                goal,
                GoalStatus.FAILED,
                f"Nav2 aborted {goal.description}: {error_msg} (error code {error_code})",
                nav2_reason(error_code),
            )
        else:
            why = text or f"status {status}"
            self._end(
                goal,
                GoalStatus.FAILED,
                f"{goal.description} failed: {name}: {why}",
                Reason.FAILED,
            )

    def _cancel_goal(self, goal: Ros2Goal, reason: str, code: Reason) -> None:
        with self._lock:
            if not goal._finish(GoalStatus.CANCELLED, reason, code):
                return
            self._retire(goal)
            known = goal.ros_id is not None
        if known:
            self._cancel_remote(goal)
        # Not sent yet: _on_accepted cancels it when Nav2 accepts it.

    def _cancel_remote(self, goal: Ros2Goal) -> None:
        ros_id = goal.ros_id
        if ros_id is None:
            return
        try:
            self._clients[goal.kind].cancel(ros_id)
        except Exception as exc:  # logged: the stop path (cancel all) still covers it
            log.warning("cancelling %s on %s failed: %s", goal, self._actions[goal.kind][0], exc)
