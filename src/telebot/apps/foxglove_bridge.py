"""Foxglove and MCAP: one bridge from a connected robot to Foxglove channels, two sinks.

:class:`FoxgloveBridge` follows a :class:`~telebot.services.client.RobotClient` and logs
what reaches the user as Foxglove messages (``foxglove-sdk`` schemas) on channels of its own
:class:`foxglove.Context`. That context feeds a Foxglove WebSocket server
(``telebot-user foxglove``: the Foxglove app at ``ws://localhost:8765`` shows the robot live),
an MCAP file (``telebot-user record``, ``--record`` on ``ui`` and ``chat``), or both: the
same channels go to both, so a recording holds exactly what Foxglove showed.

Channels (topic — schema)::

    /map                foxglove.Grid            the robot's map as its map transfer gives it
                                                 (``getmap``): cropped to the known cells,
                                                 trinary int8 (-1 unknown, 0 free, 100
                                                 occupied); again when it changes
    /pose               foxglove.PoseInFrame     the robot's pose in "map"
    /tf                 foxglove.FrameTransforms map → base_link, so panels can follow it
    /plan               foxglove.PosesInFrame    the planned path (empty: none)
    /camera             foxglove.CompressedImage the robot's video (JPEG as sent, never
                                                 re-encoded; frame_id: the camera's name)
    /telebot/telemetry  telebot.Telemetry        battery, state, link, video settings
    /telebot/safety     telebot.SafetyEvent      safety state changes, and this user's
                                                 stop / arm / take / release with their acks
    /telebot/goal       telebot.GoalEvent        goals sent and their updates
    /telebot/chat       telebot.ChatEvent        chat commands and the robot's replies
    /telebot/commands   telebot.Command          every command this user gave (chat, goal,
                                                 safety), in order
    /telebot/connection telebot.ConnectionEvent  the call dropped / came back / ended
    TOPIC (relayed)     ros2msg schema, cdr      a robot topic relayed over the call

The JSON channels' schemas (``jsonschema``, named ``telebot.*``) come from
:mod:`telebot.services.schemas`, as the robot's own call recordings' do.

Goals from Foxglove: a client that advertises ``/goal_pose`` (the 3D panel's "publish pose"
tool; ``geometry_msgs/msg/PoseStamped`` in ``json`` or ``cdr``) drives the robot through
:meth:`RobotClient.goto`, the normal goal path, so the robot's supervisor rules hold (a
driver only, armed, within its speed cap).

Driving by hand from Foxglove: a client that advertises the teleop topic (``/cmd_vel`` by
default; ``--teleop-topic``) with ``geometry_msgs/Twist`` (the Teleop panel's schema name;
also ``geometry_msgs/msg/Twist`` and the ``TwistStamped`` types, ``json`` or ``cdr``)
drives the robot through :meth:`RobotClient.drive` (docs/protocol.md §27): ``linear.x``
and ``angular.z`` of each message, held for 1.5 periods of the panel's publish rate
(``--teleop-rate``, default 10 Hz), so that the robot drives smoothly while a direction
is held and stops within that hold plus the robot's ``[drive] stale_after`` once the
panel goes quiet (the panel sends nothing on release unless its "stop on release" is on;
a zero Twist releases at once).

Commands from Foxglove: the server advertises the services ``/telebot/arm``,
``/telebot/stop``, ``/telebot/take``, ``/telebot/release`` and ``/telebot/cancel`` (the
app's Service Call panel calls them; request ``{}``, response ``{"ok", "text", "code"}``,
schema ``telebot.Trigger``): the web page's buttons. They go to the robot as the page's do,
so its supervisor decides (anyone may stop; arm, take and release are a driver's; cancel
ends the running goal).

The map follows the robot's through :class:`~telebot.followers.MapFollower` (fetched again
when telemetry's ``map_version`` changes, and across reconnections), as the web page's
does. The commands around the bridge (``telebot-user foxglove``, ``record``: argument
checks, wiring, exit codes) are :mod:`telebot.apps.foxglove_cli`.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import functools
import json
import logging
import math
import sys
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from types import TracebackType
from typing import Any, Self

import foxglove
from foxglove.channels import (
    CompressedImageChannel,
    FrameTransformsChannel,
    GridChannel,
    LaserScanChannel,
    PoseInFrameChannel,
    PosesInFrameChannel,
)
from foxglove.messages import (
    CompressedImage,
    FrameTransform,
    FrameTransforms,
    Grid,
    LaserScan,
    PackedElementField,
    PackedElementFieldNumericType,
    Pose,
    PoseInFrame,
    PosesInFrame,
    Quaternion,
    Timestamp,
    Vector2,
    Vector3,
)
from foxglove.websocket import (
    Capability,
    ChannelView,
    Client,
    ClientChannel,
    MessageSchema,
    ServerListener,
    Service,
    ServiceRequest,
    ServiceSchema,
    WebSocketServer,
)

from telebot.apps.tasks import BackgroundTasks
from telebot.errors import CallEnded, RelayRefused, TelebotError, UnknownTopic, excerpt
from telebot.followers import MapFollower
from telebot.rights import Right, may
from telebot.services.client import ConnectionEvent, RobotClient
from telebot.services.mapxfer.user import MapDownload
from telebot.services.plan.wire import PlanUpdate
from telebot.services.relay.wire import RelayedMessage, TopicInfo
from telebot.services.safety.wire import SafetyAck, SafetyStatus
from telebot.services.schemas import BRIDGE_SCHEMAS, TRIGGER_REQUEST, TRIGGER_RESULT, schema_bytes
from telebot.services.status.wire import PoseUpdate
from telebot.services.video.wire import CompleteFrame

__all__ = [
    "COMMANDS",
    "GOAL_TOPIC",
    "TELEOP_RATE",
    "TELEOP_TOPIC",
    "FoxgloveBridge",
    "goal_from_pose_stamped",
    "recording",
    "teleop_hold",
    "velocity_from_twist",
]

log = logging.getLogger(__name__)

#: The topic Foxglove's 3D panel publishes goals on (as RViz's "2D Goal Pose").
GOAL_TOPIC = "/goal_pose"
#: The topic Foxglove's Teleop panel publishes on, unless ``--teleop-topic`` says another.
TELEOP_TOPIC = "/cmd_vel"
#: The Teleop panel's publish rate (Hz) the hold of each message is matched to
#: (``--teleop-rate``; the panel's own default is 1 Hz: set it to this).
TELEOP_RATE = 10.0
#: The rates ``--teleop-rate`` takes: below 2 Hz a release would take over a second to stop.
TELEOP_RATES = (2.0, 50.0)
_TWIST = frozenset({"geometry_msgs/Twist", "geometry_msgs/msg/Twist"})
_TWIST_STAMPED = frozenset({"geometry_msgs/TwistStamped", "geometry_msgs/msg/TwistStamped"})
#: At most one log line per this many seconds for bad teleop messages (a panel publishes
#: at 10 Hz: one a message would flood the log); each is counted all the same.
_TELEOP_LOG_EVERY = 5.0
#: A held direction repeated after its hold ran out, but within this (s): a panel
#: publishing too slowly (not a new press); said once after a few in a row.
_SLOW_GAP = 1.6
_SLOW_WARN_AFTER = 3
#: The frame of the map, the pose and the plan.
MAP_FRAME = "map"
#: The robot's body frame (``/tf`` carries map → base_link).
BASE_FRAME = "base_link"
#: What a Foxglove client may call as a service ``/telebot/NAME``: the web page's buttons.
COMMANDS = ("arm", "stop", "take", "release", "cancel")
#: How long a service call waits for the robot's answer (s) before it answers "no answer".
COMMAND_TIMEOUT = 10.0
_NO_ANSWER = "no answer from the robot"
#: What a command service says when the robot did it (its ack carries no words then).
_DONE = {"arm": "armed", "stop": "stopped", "take": "you hold the drive", "release": "released"}
LASER_SCAN = "sensor_msgs/msg/LaserScan"


def _stamp(seconds: float) -> Timestamp:
    return Timestamp.from_epoch_secs(max(0.0, seconds))


def _yaw_quaternion(yaw: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0))


def _pose(x: float, y: float, yaw: float) -> Pose:
    return Pose(position=Vector3(x=x, y=y, z=0.0), orientation=_yaw_quaternion(yaw))


def _yaw_of(qx: float, qy: float, qz: float, qw: float) -> float:
    return math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def _json_schema(schema: dict[str, Any]) -> foxglove.Schema:
    return foxglove.Schema(name=schema["title"], encoding="jsonschema", data=schema_bytes(schema))


def _safety_event(state: SafetyStatus) -> dict[str, Any]:
    """A safety state as ``/telebot/safety`` logs it (``telebot.SafetyEvent``: the words
    under ``reason`` as on the wire)."""
    return {
        "event": "state",
        "armed": state.armed,
        "reason": state.text,
        "holder": state.holder,
        "cap": state.cap,
        "blocked": state.blocked,
        "code": state.code,
    }


def _result(ok: bool, text: str, code: str = "") -> dict[str, Any]:
    """A command service's response (``telebot.TriggerResult``)."""
    return {"ok": ok, "text": text, "code": code}


def goal_from_pose_stamped(
    data: bytes, encoding: str, schema_name: str = ""
) -> tuple[float, float, float | None]:
    """``(x, y, yaw)`` of a ``geometry_msgs/PoseStamped`` as a Foxglove client publishes it
    (``json`` or ``cdr``); ValueError naming what was wrong otherwise. A zero quaternion
    (no heading given) gives yaw None."""
    if encoding == "json":
        try:
            msg = json.loads(data)
            pose = msg["pose"]
            position, orientation = pose["position"], pose.get("orientation") or {}
            x, y = float(position["x"]), float(position["y"])
            q = [float(orientation.get(k, 0.0)) for k in ("x", "y", "z", "w")]
        except (
            ValueError,
            KeyError,
            TypeError,
            AttributeError,
            OverflowError,
            RecursionError,
        ) as exc:
            # Quoted short: the exception may hold the whole (huge) value it choked on.
            # (AttributeError: a list or number where an object belongs; OverflowError: an
            # integer too big for a float; RecursionError: JSON nested deeper than Python's
            # parser goes.)
            raise ValueError(f"not a JSON PoseStamped ({excerpt(repr(exc))})") from None
    elif encoding == "cdr":
        from telebot.rosmsg.types import TypeLibrary

        try:
            msg = TypeLibrary().message("geometry_msgs/msg/PoseStamped").deserialize(data)
        except TelebotError as exc:
            raise ValueError(f"not a CDR PoseStamped ({excerpt(str(exc))})") from None
        position, orientation = msg.pose.position, msg.pose.orientation
        x, y = float(position.x), float(position.y)
        q = [float(orientation.x), float(orientation.y), float(orientation.z), float(orientation.w)]
    else:
        raise ValueError(f"unsupported encoding {excerpt(repr(encoding), 40)} (use json or cdr)")
    if not all(math.isfinite(v) for v in (x, y, *q)):
        raise ValueError("a goal needs finite numbers")
    if not any(q):
        return x, y, None
    return x, y, _yaw_of(*q)


def teleop_hold(rate: float) -> float:
    """How long one Teleop message drives (s): 1.5 periods of the panel's publish ``rate``
    (Hz), so one late message is no stutter, and at least 0.1 s."""
    return max(0.1, 1.5 / rate)


def _vector(value: Any, what: str) -> tuple[float, float, float]:
    if not isinstance(value, dict):
        raise ValueError(f"{what} is not an object")
    numbers = []
    for axis in ("x", "y", "z"):
        number = value.get(axis, 0.0)
        if isinstance(number, bool) or not isinstance(number, int | float):
            raise ValueError(f"{what}.{axis} is not a number")
        numbers.append(float(number))
    return numbers[0], numbers[1], numbers[2]


def velocity_from_twist(data: bytes, encoding: str, schema_name: str = "") -> tuple[float, float]:
    """``(linear.x, angular.z)`` of a ``geometry_msgs/Twist`` (or ``TwistStamped``) as a
    Foxglove client publishes it (``json`` or ``cdr``); ValueError naming what was wrong
    otherwise (a short line whatever the input). The other components are ignored: the
    robot drives forward and turns."""
    stamped = schema_name in _TWIST_STAMPED
    if schema_name and not stamped and schema_name not in _TWIST:
        raise ValueError(
            f"schema {excerpt(repr(schema_name), 40)} is not geometry_msgs/Twist "
            "or geometry_msgs/TwistStamped"
        )
    if encoding == "json":
        try:
            msg = json.loads(data)
            if not isinstance(msg, dict):
                raise ValueError("not an object")
            # The schema name says which; without one, the shape does.
            twist = msg["twist"] if stamped or (not schema_name and "twist" in msg) else msg
            if not isinstance(twist, dict):
                raise ValueError("twist is not an object")
            linear = _vector(twist["linear"], "linear")
            angular = _vector(twist["angular"], "angular")
        except (ValueError, KeyError, TypeError, OverflowError, RecursionError) as exc:
            # Quoted short: the exception may hold the whole (huge) value it choked on.
            # (OverflowError: an integer too big for a float.)
            raise ValueError(f"not a JSON Twist ({excerpt(repr(exc))})") from None
        x, z = linear[0], angular[2]
    elif encoding == "cdr":
        from telebot.rosmsg.types import TypeLibrary

        name = "geometry_msgs/msg/TwistStamped" if stamped else "geometry_msgs/msg/Twist"
        try:
            msg = TypeLibrary().message(name).deserialize(data)
        except TelebotError as exc:
            raise ValueError(f"not a CDR {name} ({excerpt(str(exc))})") from None
        twist = msg.twist if stamped else msg
        x, z = float(twist.linear.x), float(twist.angular.z)
    else:
        raise ValueError(f"unsupported encoding {excerpt(repr(encoding), 40)} (use json or cdr)")
    if not (math.isfinite(x) and math.isfinite(z)):
        raise ValueError("a Twist needs finite numbers")
    return x, z


class _Listener(ServerListener):
    """The WebSocket server's callbacks (they run on the SDK's threads): client channels
    advertised, and their messages handed to the event loop."""

    def __init__(self, bridge: FoxgloveBridge) -> None:
        self._bridge = bridge
        self._lock = threading.Lock()
        self._channels: dict[tuple[int, int], ClientChannel] = {}

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        log.info("Foxglove client %s subscribed to %s", client.id, channel.topic)
        self._bridge._subscribed_from_thread(channel.topic, +1)

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        self._bridge._subscribed_from_thread(channel.topic, -1)

    def on_client_advertise(self, client: Client, channel: ClientChannel) -> None:
        with self._lock:
            self._channels[(client.id, channel.id)] = channel

    def on_client_unadvertise(self, client: Client, client_channel_id: int) -> None:
        with self._lock:
            self._channels.pop((client.id, client_channel_id), None)

    def on_message_data(self, client: Client, client_channel_id: int, data: bytes) -> None:
        with self._lock:
            channel = self._channels.get((client.id, client_channel_id))
        if channel is None:
            return
        self._bridge._from_thread(channel.topic, channel.encoding, channel.schema_name, bytes(data))


class FoxgloveBridge:
    """A connected robot's streams as Foxglove channels, to a WebSocket server and/or MCAP.

    ``async with FoxgloveBridge(client, port=8765, mcap=Path("s.mcap")) as bridge:``. ``port``
    None: no server (0: any free port, :attr:`port` says which); ``mcap`` None: no file.
    ``topics`` are robot topics to relay (needs the robot's relay service).
    ``teleop_topic`` is where a Twist drives the robot, ``teleop_rate`` (Hz) the Teleop
    panel's publish rate its hold is matched to (ValueError outside :data:`TELEOP_RATES`).
    Opening the sinks raises OSError (port taken, file not writable) before anything else
    starts.
    """

    def __init__(
        self,
        client: RobotClient,
        *,
        host: str = "127.0.0.1",
        port: int | None = None,
        mcap: Path | None = None,
        topics: Sequence[str] = (),
        map_timeout: float = 120.0,
        teleop_topic: str = TELEOP_TOPIC,
        teleop_rate: float = TELEOP_RATE,
    ) -> None:
        low, high = TELEOP_RATES
        if not low <= teleop_rate <= high:
            raise ValueError(f"teleop rate must be {low:g} to {high:g} Hz, not {teleop_rate!r}")
        self.client = client
        self.host = host
        self.port = port
        self.mcap = mcap
        self.topics = list(topics)
        self.context = foxglove.Context()
        #: Messages logged per topic (the progress line shows them).
        self.counts: dict[str, int] = {}
        #: Goals received from Foxglove clients, and those refused (bad data, observer).
        self.goals_received = 0
        self.goals_refused = 0
        #: Where the Teleop panel publishes, and how long each of its messages drives.
        self.teleop_topic = teleop_topic
        self.teleop_hold = teleop_hold(teleop_rate)
        #: Teleop (Twist) messages received, and those refused (bad data, observer).
        self.teleop_received = 0
        self.teleop_refused = 0
        self._driving = False
        self._teleop_logged = -math.inf
        #: The last Teleop command and when it came; how often one came too late.
        self._teleop_last = -math.inf
        self._teleop_command = (0.0, 0.0)
        self._teleop_slow = 0
        self._teleop_warned = False
        #: The robot's map, fetched again when it changes (logged on ``/map`` as it arrives).
        self.maps = MapFollower(client, timeout=map_timeout)
        self.maps.on_map.append(self._log_map)
        self._server: WebSocketServer | None = None
        self._writer: foxglove.MCAPWriter | None = None
        self._tasks = BackgroundTasks("Foxglove bridge", expected=(CallEnded,))
        self._video: Callable[[], None] | None = None
        self._relayed: dict[str, foxglove.Channel] = {}
        self._lasers: dict[str, LaserScanChannel] = {}
        #: Foxglove clients subscribed, per topic.
        self._subscribers: dict[str, int] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._closing = False
        ctx = self.context
        self._map = GridChannel("/map", context=ctx)
        self._pose = PoseInFrameChannel("/pose", context=ctx)
        self._tf = FrameTransformsChannel("/tf", context=ctx)
        self._plan = PosesInFrameChannel("/plan", context=ctx)
        self._camera = CompressedImageChannel("/camera", context=ctx)
        self._json = {
            name: foxglove.Channel(
                f"/telebot/{name}",
                schema=_json_schema(schema),
                message_encoding="json",
                context=ctx,
            )
            for name, schema in BRIDGE_SCHEMAS.items()
        }

    # -- lifecycle --------------------------------------------------------------------

    async def start(self) -> None:
        """Open the sinks, then follow the robot's streams."""
        self._loop = asyncio.get_running_loop()
        if self.mcap is not None:
            try:
                self._writer = foxglove.open_mcap(
                    self.mcap, allow_overwrite=True, context=self.context
                )
            except OSError as exc:
                raise OSError(
                    exc.errno, f"cannot write {self.mcap}: {exc.strerror or exc}"
                ) from exc
        if self.port is not None:
            try:
                self._server = foxglove.start_server(
                    name=f"telebot {self.client.robot}",
                    host=self.host,
                    port=self.port,
                    capabilities=[Capability.ClientPublish, Capability.Services],
                    supported_encodings=["json", "cdr"],
                    server_listener=_Listener(self),
                    services=self._services(),
                    context=self.context,
                )
            except RuntimeError as exc:  # the SDK's FoxgloveError: bind failed
                self._close_writer()
                raise OSError(f"cannot serve on {self.host}:{self.port}: {exc}") from exc
            self.port = self._server.port
        client = self.client
        client.on_activity.append(self._on_activity)
        client.on_connection.append(self._on_connection)
        self._video_wanted()
        for pump in (
            self._pump_pose,
            self._pump_plan,
            self._pump_safety,
            self._pump_telemetry,
        ):
            self._tasks.spawn(pump())
        self.maps.start()
        for topic in self.topics:
            self._tasks.spawn(self._relay(topic))
        # What is already known: a new recording starts with it.
        if (safety := client.latest_safety.value) is not None:
            self._log_json("safety", _safety_event(safety))
        if (plan := client.plan) is not None:
            self._log_plan(plan)

    @property
    def map(self) -> MapDownload | None:
        """The newest map that arrived (``None`` until one has)."""
        return self.maps.map

    @property
    def url(self) -> str:
        """The WebSocket address for the Foxglove app ("" without a server)."""
        if self._server is None:
            return ""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    async def close(self) -> None:
        """Stop following, stop the server, finish the MCAP file; idempotent."""
        if self._closing:
            return
        self._closing = True
        if self._driving:  # no more Teleop messages will come: stop now, not on staleness
            self._release()
        with contextlib.suppress(ValueError):
            self.client.on_activity.remove(self._on_activity)
        with contextlib.suppress(ValueError):
            self.client.on_connection.remove(self._on_connection)
        if self._video is not None:
            self._video()
            self._video = None
        await self.maps.aclose()
        await self._tasks.cancel_all()
        if self._server is not None:
            self._server.stop()
            self._server = None
        self._close_writer()

    def _close_writer(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    async def __aenter__(self) -> Self:
        try:
            await self.start()
        except BaseException:
            await self.close()
            raise
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    def _count(self, topic: str) -> None:
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def _log_json(self, name: str, message: Mapping[str, Any]) -> None:
        self._json[name].log(dict(message))
        self._count(f"/telebot/{name}")

    # -- streams ----------------------------------------------------------------------

    async def _pump_pose(self) -> None:
        latest = self.client.latest_pose
        while True:
            self._log_pose(await latest.next())

    def _log_pose(self, pose: PoseUpdate) -> None:
        now = time.time()
        stamp = _stamp(now)
        self._pose.log(
            PoseInFrame(timestamp=stamp, frame_id=MAP_FRAME, pose=_pose(pose.x, pose.y, pose.yaw))
        )
        self._count("/pose")
        self._tf.log(
            FrameTransforms(
                transforms=[
                    FrameTransform(
                        timestamp=stamp,
                        parent_frame_id=MAP_FRAME,
                        child_frame_id=BASE_FRAME,
                        translation=Vector3(x=pose.x, y=pose.y, z=0.0),
                        rotation=_yaw_quaternion(pose.yaw),
                    )
                ]
            )
        )
        self._count("/tf")

    async def _pump_plan(self) -> None:
        latest = self.client.latest_plan
        while True:
            self._log_plan(await latest.next())

    def _log_plan(self, plan: PlanUpdate) -> None:
        points = list(plan.points)
        poses = []
        for i, (x, y) in enumerate(points):
            # Each pose faces the next point (the last keeps its predecessor's heading).
            j = min(i + 1, len(points) - 1)
            k = j - 1 if j == i else i
            yaw = math.atan2(points[j][1] - points[k][1], points[j][0] - points[k][0])
            poses.append(_pose(x, y, yaw if j != k else 0.0))
        self._plan.log(PosesInFrame(timestamp=_stamp(time.time()), frame_id=MAP_FRAME, poses=poses))
        self._count("/plan")

    async def _pump_safety(self) -> None:
        latest = self.client.latest_safety
        while True:
            state = await latest.next()
            self._log_json("safety", _safety_event(state))

    async def _pump_telemetry(self) -> None:
        latest = self.client.latest_telemetry
        while True:
            telemetry = await latest.next()
            self._log_json("telemetry", asdict(telemetry))

    def _log_map(self, download: MapDownload) -> None:
        grid = download.grid
        self._map.log(
            Grid(
                timestamp=_stamp(time.time()),
                frame_id=MAP_FRAME,
                pose=_pose(grid.origin_x, grid.origin_y, 0.0),
                column_count=grid.width,
                cell_size=Vector2(x=grid.resolution, y=grid.resolution),
                row_stride=grid.width,
                cell_stride=1,
                fields=[
                    PackedElementField(
                        name="occupancy", offset=0, type=PackedElementFieldNumericType.Int8
                    )
                ],
                data=grid.data.tobytes(),
            )
        )
        self._count("/map")

    def _video_wanted(self) -> None:
        """Ask the robot for video while it is recorded or a Foxglove client shows it."""
        wanted = self._writer is not None or self._subscribers.get("/camera", 0) > 0
        if wanted and self._video is None and not self._closing:
            self._video = self.client.video_feed.subscribe(self._on_frame)
        elif not wanted and self._video is not None:
            self._video()
            self._video = None

    def _on_frame(self, frame: CompleteFrame) -> None:
        # The JPEG as the robot sent it: Foxglove decodes it, nothing is re-encoded here.
        self._camera.log(
            CompressedImage(
                timestamp=_stamp(frame.capture_time),
                frame_id=frame.camera,
                data=frame.data,
                format="jpeg",
            )
        )
        self._count("/camera")

    def _on_activity(self, kind: str, fields: Mapping[str, Any]) -> None:
        message = {"kind": kind, **fields}
        if kind in ("chat", "goal", "safety"):
            self._log_json("commands", message)
        if kind.startswith("chat"):
            self._log_json("chat", message)
        elif kind.startswith("goal"):
            self._log_json("goal", message)
        elif kind.startswith("safety"):
            self._log_json("safety", {"event": kind, **fields})

    def _on_connection(self, event: ConnectionEvent) -> None:
        self._log_json(
            "connection",
            {"state": event.state, "detail": event.detail, "seconds": event.seconds},
        )

    # -- relayed topics -----------------------------------------------------------------

    def add_relayed(self, info: TopicInfo) -> foxglove.Channel:
        """A channel for a relayed robot topic (its ros2msg schema, ``cdr`` messages)."""
        channel = self._relayed.get(info.name)
        if channel is None:
            schema = foxglove.Schema(
                name=info.type, encoding="ros2msg", data=info.schema.encode("utf-8")
            )
            channel = foxglove.Channel(
                info.name, schema=schema, message_encoding=info.encoding, context=self.context
            )
            self._relayed[info.name] = channel
        return channel

    def log_relayed(self, info: TopicInfo, message: RelayedMessage) -> None:
        """Log one relayed message (bytes as the robot had them) on its topic's channel; a
        ``sensor_msgs/msg/LaserScan`` also as a ``foxglove.LaserScan`` on ``/foxglove<topic>``."""
        self.add_relayed(info).log(message.data)
        self._count(info.name)
        if info.type == LASER_SCAN:
            self._log_laser(info.name, message)

    def _log_laser(self, topic: str, message: RelayedMessage) -> None:
        from telebot.rosmsg.types import TypeLibrary

        try:
            scan = TypeLibrary().message(LASER_SCAN).deserialize(message.data)
        except TelebotError as exc:
            log.warning("a LaserScan on %s did not decode: %s", topic, exc)
            return
        channel = self._lasers.get(topic)
        if channel is None:
            channel = self._lasers[topic] = LaserScanChannel(
                f"/foxglove{topic}", context=self.context
            )
        count = len(scan.ranges)
        channel.log(
            LaserScan(
                timestamp=Timestamp(int(scan.header.stamp.sec), int(scan.header.stamp.nanosec)),
                frame_id=str(scan.header.frame_id),
                pose=_pose(0.0, 0.0, 0.0),
                start_angle=float(scan.angle_min),
                end_angle=float(scan.angle_min + scan.angle_increment * max(count - 1, 0)),
                ranges=[float(r) for r in scan.ranges],
                intensities=[float(i) for i in scan.intensities],
            )
        )
        self._count(f"/foxglove{topic}")

    async def _relay(self, topic: str) -> None:
        try:
            async with self.client.relay(topic) as stream:
                self.add_relayed(stream.info)
                async for message in stream:
                    self.log_relayed(stream.info, message)
        except (UnknownTopic, RelayRefused) as exc:
            log.error("cannot relay %s: %s", topic, exc)
            self._log_json("connection", {"state": "relay_refused", "detail": str(exc)})
        except (TelebotError, TimeoutError) as exc:
            log.error("the relay of %s ended: %s", topic, exc)

    # -- goals from Foxglove -------------------------------------------------------------

    def _from_thread(self, topic: str, encoding: str, schema_name: str, data: bytes) -> None:
        loop = self._loop
        if loop is None or self._closing:
            return
        with contextlib.suppress(RuntimeError):  # the loop has closed: nothing to do
            loop.call_soon_threadsafe(self._on_client_message, topic, encoding, schema_name, data)

    def _subscribed_from_thread(self, topic: str, change: int) -> None:
        loop = self._loop
        if loop is None or self._closing:
            return
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(self._on_subscribed, topic, change)

    def _on_subscribed(self, topic: str, change: int) -> None:
        if self._closing:
            return
        self._subscribers[topic] = max(0, self._subscribers.get(topic, 0) + change)
        if topic == "/camera":
            self._video_wanted()
        if change < 0:
            return
        # The server keeps no latched messages: a client that subscribes late would never
        # see the map (sent once) or a standing plan, so they are logged again for it.
        if topic == "/map" and self.map is not None:
            self._log_map(self.map)
        elif topic == "/plan" and (plan := self.client.plan) is not None:
            self._log_plan(plan)

    def _on_client_message(self, topic: str, encoding: str, schema_name: str, data: bytes) -> None:
        if self._closing:
            return
        if topic == self.teleop_topic:
            self._on_teleop(encoding, schema_name, data)
        elif topic == GOAL_TOPIC:
            self._on_goal(encoding, schema_name, data)

    def _on_goal(self, encoding: str, schema_name: str, data: bytes) -> None:
        self.goals_received += 1
        try:
            x, y, yaw = goal_from_pose_stamped(data, encoding, schema_name)
        except ValueError as exc:
            self._refuse_goal(str(exc))
            return
        if not may(self.client.call.role, Right.DRIVE):
            self._refuse_goal("observers may not send goals")
            return
        log.info("goal from Foxglove: (%.2f, %.2f)", x, y)
        self._tasks.spawn(self.client.goto(x, y, yaw))

    def _refuse_goal(self, text: str) -> None:
        # Said to every Foxglove client and recorded: a few hundred bytes at most, whatever
        # the client sent.
        text = excerpt(text)
        self.goals_refused += 1
        log.warning("a goal from Foxglove was refused: %s", text)
        self._log_json("goal", {"kind": "refused", "text": text})

    # -- driving by hand from Foxglove (the Teleop panel) ---------------------------------

    def _on_teleop(self, encoding: str, schema_name: str, data: bytes) -> None:
        self.teleop_received += 1
        try:
            linear, angular = velocity_from_twist(data, encoding, schema_name)
        except ValueError as exc:
            self._refuse_teleop(f"a Twist on {self.teleop_topic} was refused: {exc}")
            return
        if not may(self.client.call.role, Right.DRIVE):
            self._refuse_teleop(f"{self.teleop_topic}: observers may not drive")
            return
        if linear == 0.0 and angular == 0.0:
            self._release()
            return
        self._check_rate((linear, angular))
        # The robot clamps to its limits and its speed cap, and says why it does not move
        # (not armed, not the holder, ...) in its drive_state.
        self.client.drive(linear, angular, hold=self.teleop_hold)
        self._driving = True

    def _check_rate(self, command: tuple[float, float]) -> None:
        """Say once if the panel publishes slower than the hold: a held direction arriving
        again after its hold ran out (the robot lurches and stops between messages; the
        panel's own default rate is 1 Hz)."""
        now = time.monotonic()
        gap = now - self._teleop_last
        if command != self._teleop_command or gap > _SLOW_GAP:
            pass  # a new press, not a repeat
        elif gap <= self.teleop_hold:
            self._teleop_slow = 0  # in time: a late one now and then is jitter
        else:
            self._teleop_slow += 1
            if self._teleop_slow == _SLOW_WARN_AFTER and not self._teleop_warned:
                self._teleop_warned = True
                log.warning(
                    "Teleop messages on %s arrive every %.1f s: set the panel's publish rate "
                    "to %g Hz (or pass --teleop-rate), or the robot stops between them",
                    self.teleop_topic,
                    gap,
                    round(1.5 / self.teleop_hold),
                )
        self._teleop_last, self._teleop_command = now, command

    def _release(self) -> None:
        self._driving = False
        self.client.drive(0.0, 0.0)

    def _refuse_teleop(self, text: str) -> None:
        self.teleop_refused += 1
        if self._driving:  # fail safe: what the user meant is unknown
            self._release()
        now = time.monotonic()
        if now - self._teleop_logged >= _TELEOP_LOG_EVERY:
            self._teleop_logged = now
            log.warning("%s (%d refused so far)", excerpt(text), self.teleop_refused)

    # -- commands from Foxglove (services) -------------------------------------------------

    def _services(self) -> list[Service]:
        schema = ServiceSchema(
            "telebot.Trigger",
            request=MessageSchema(encoding="json", schema=_json_schema(TRIGGER_REQUEST)),
            response=MessageSchema(encoding="json", schema=_json_schema(TRIGGER_RESULT)),
        )
        return [
            Service(f"/telebot/{what}", schema=schema, handler=self._on_service_call)
            for what in COMMANDS
        ]

    def _on_service_call(self, request: ServiceRequest) -> bytes:
        # On one of the SDK's threads (one per call, so a slow arm holds up no stop): the
        # command runs on the event loop, this thread waits for its outcome, in short waits
        # so that a bridge that closes never waits for it.
        return json.dumps(self._command_from_thread(request.service_name, request.payload)).encode()

    def _command_from_thread(self, service: str, payload: bytes) -> dict[str, Any]:
        closing = _result(False, "the bridge is closing")
        loop = self._loop
        if loop is None or self._closing or loop.is_closed():
            return closing
        command = self.command(service.removeprefix("/telebot/"), bytes(payload))
        try:
            future = asyncio.run_coroutine_threadsafe(command, loop)
        except RuntimeError:  # the loop closed just now
            command.close()
            return closing
        deadline = time.monotonic() + COMMAND_TIMEOUT + 5.0
        while True:
            try:
                return future.result(timeout=0.25)
            except concurrent.futures.CancelledError:
                return closing
            except concurrent.futures.TimeoutError:
                if self._closing or time.monotonic() > deadline:
                    future.cancel()
                    return closing if self._closing else _result(False, _NO_ANSWER)

    async def command(self, what: str, payload: bytes = b"{}") -> dict[str, Any]:
        """Do command ``what`` (one of :data:`COMMANDS`) as the web page's button does and
        return ``{"ok", "text", "code"}`` (``telebot.TriggerResult``): the robot's answer,
        or why it was not asked. ``payload``: the request, ``{}`` (or nothing); a stop
        stops whatever came with it."""
        if what not in COMMANDS:
            return _result(False, f"unknown command {excerpt(what, 40)!r}: one of {COMMANDS}")
        if what != "stop" and (problem := _trigger_problem(payload)) is not None:
            return _result(False, f"{what}: {problem}")
        client = self.client
        try:
            async with asyncio.timeout(COMMAND_TIMEOUT):
                if what == "cancel":
                    chat = await client.chat("cancel")
                    return _result(chat.ok, chat.replies[-1] if chat.replies else "", chat.code)
                actions: dict[str, Callable[[], Awaitable[SafetyAck]]] = {
                    "stop": functools.partial(client.stop, how="button"),
                    "arm": client.arm,
                    "take": client.take_drive,
                    "release": client.release_drive,
                }
                ack = await actions[what]()
        except TimeoutError:
            return _result(False, _NO_ANSWER)
        except TelebotError as exc:
            return _result(False, str(exc))
        return _result(ack.ok, ack.text or (_DONE[what] if ack.ok else f"{what} refused"), ack.code)


def _trigger_problem(payload: bytes) -> str | None:
    """Why ``payload`` is not a command service's request (``{}`` or empty), or None."""
    if not payload.strip():
        return None
    try:
        request = json.loads(payload)
    except (ValueError, RecursionError):
        return f"the request is not JSON ({excerpt(repr(payload[:400]))}): send {{}}"
    if request != {}:
        return f"the request takes no fields ({excerpt(json.dumps(request))}): send {{}}"
    return None


@contextlib.asynccontextmanager
async def recording(client: RobotClient, path: Path | None) -> AsyncIterator[FoxgloveBridge | None]:
    """``--record FILE`` of ``ui`` and ``chat``: an MCAP of the call while the block runs."""
    if path is None:
        yield None
        return
    async with FoxgloveBridge(client, mcap=path) as bridge:
        yield bridge
    print(f"recorded to {path} ({sum(bridge.counts.values())} messages)", file=sys.stderr)
