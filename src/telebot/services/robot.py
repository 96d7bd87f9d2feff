"""The robot side of telebot: steps the robot in real time and serves every call.

:class:`RobotServer` owns the navigation stack. One task runs at the control rate and steps
it if it is a :class:`~telebot.robot.nav.SteppedNavStack` (``loop.time()`` is the
simulation's clock; a robot that runs by itself is not stepped). Each call gets every
service of the server's :class:`~telebot.services.base.ServiceRegistry`
(:func:`~telebot.services.registry.robot_services`: ``core``, the :class:`CallServices` of chat, map, pose,
goals, telemetry and safety; ``video``; ``plan``, the planned path and named places;
``people``, tracked people and alerts; ``media``, two-way audio and the user's camera;
``drive``, driving by hand and follow-me …),
ticked on every cycle and closed when the call ends. Each service reads its settings from
its section of the server's :class:`~telebot.services.base.ServiceConfig`; the server
itself takes only the robot, its own ``[services]`` settings, its loop's rate, its map's
name, where events go and the safety supervisor. The map is encoded once per
:meth:`~telebot.robot.nav.NavStack.map_version` (:meth:`RobotServer.encoded_map`): a map
that changes (SLAM) is served fresh, and each call's telemetry carries the version so users
know to fetch it again. Every handler is guarded: garbage from one peer is dropped and
counted and never reaches the others or stops the robot's loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
from collections import OrderedDict
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar, cast

from telebot.channels.call import Call, RobotEndpoint
from telebot.channels.channel import Channel, ReceivedDatagram
from telebot.channels.transports.base import Lane
from telebot.config import MediaConfig, RelaySettings, ServiceSettings, VideoConfig
from telebot.errors import ProtocolError, TelebotError
from telebot.identity import Role
from telebot.reasons import Reason, Refusal
from telebot.rights import Right, may
from telebot.robot.nav import (
    GoalHandle,
    GoalStatus,
    NavStack,
    NavStatus,
    PoseNotifier,
    SteppedNavStack,
)
from telebot.safety import SafetyState
from telebot.services.base import (
    HostedServices,
    HostService,
    MotionService,
    OpenServices,
    RobotHost,
    ServiceConfig,
    ServiceRegistry,
)
from telebot.services.chat.robot import NO_SUPERVISOR, ChatSession, error_reason, goal_reason
from telebot.services.chat.wire import CHAT, ChatReply, decode_request
from telebot.services.drive.follow import CallFollow
from telebot.services.drive.robot import RobotDrive
from telebot.services.mapxfer import MAP
from telebot.services.mapxfer.robot import MapService
from telebot.services.mapxfer.wire import MAX_MAP_VERSION, EncodedMap, encode_map
from telebot.services.media.wire import CODEC_H264, CODEC_JPEG, CODEC_VP8, codec_id
from telebot.services.registry import robot_services
from telebot.services.safety.robot import SafetyDriver
from telebot.services.safety.wire import (
    SAFETY,
    InvalidSafetyRequest,
    SafetyAck,
    SafetyError,
    SafetyStatus,
    decode_safety_request,
)
from telebot.services.status.wire import (
    GOALS,
    POSE,
    TELEMETRY,
    GoalUpdate,
    PoseUpdate,
    Telemetry,
    decode_goal_command,
)
from telebot.services.video.sender import VideoSender
from telebot.services.video.wire import VideoSettings

__all__ = [
    "CallServices",
    "EventSink",
    "RobotServer",
    "RobotVideo",
    "SteppedNavStack",
    "may_drive",
    "robot_video_settings",
]

log = logging.getLogger(__name__)

_Request = TypeVar("_Request")

#: Requests (chat ids, goal ids) remembered per call, to answer repeats without re-running.
REMEMBERED = 256
#: While a goal runs, its status is repeated this often (s), so a lost update heals.
GOAL_STATUS_EVERY = 0.5
#: A robot that announces its poses (PoseNotifier) has each sent as it comes; the control
#: loop then sends one only when none went for this long (s), so that velocity and state
#: keep flowing while localisation is quiet (AMCL publishes only when the robot moves).
QUIET_POSE_EVERY = 0.25

EventSink = Callable[[dict[str, Any]], None]


def may_drive(role: Role | None) -> bool:
    """Whether a contact with ``role`` may move the robot (drivers and admins)."""
    return may(role, Right.DRIVE)


class CallServices:
    """The core services of one call: chat, map, pose, goals, telemetry and safety channels.

    A :class:`~telebot.services.base.CallService` (registered as ``core``): :meth:`tick`
    reports chat and goal progress and publishes pose and telemetry at their rates.
    """

    def __init__(self, server: RobotServer, call: Call) -> None:
        self.server = server
        self.call = call
        nav = server.nav
        self._chat_channel = call.channel(CHAT, lane=Lane.CONTROL)
        self._goals_channel = call.channel(GOALS, lane=Lane.CONTROL)
        self._pose_channel = call.channel(POSE, lane=Lane.DATA, latest_only=True)
        self._telemetry_channel = call.channel(TELEMETRY, lane=Lane.DATA, latest_only=True)
        self._safety_channel = call.channel(SAFETY, lane=Lane.CONTROL)
        self.gate = server.safety.gate(call.id) if server.safety is not None else None
        drive = server.hosted.get("drive")
        #: The robot's follow-me (None on a robot without the ``drive`` service).
        self.follow = drive.follow if isinstance(drive, RobotDrive) else None
        self.chat = ChatSession(
            nav,
            role=call.role,
            send=self._send_chat,
            user=call.peer,
            gate=self.gate,
            map_offer=server.encoded_map,
            relay=server.config.get("relay", RelaySettings),
            follow=CallFollow(self.follow, call.id, server.now) if self.follow else None,
        )
        self.map = MapService(call.channel(MAP, lane=Lane.BULK), server.encoded_map)
        # The first tick publishes both at once (a new user sees the robot straight away).
        self._next_pose = self._next_telemetry = -math.inf
        self._last_pose = -math.inf
        self._pose_timer: asyncio.TimerHandle | None = None
        # Lossy channels: a user repeats a request until it hears back, so the robot
        # answers a repeat with what it already said instead of running it twice.
        self._chat_replies: OrderedDict[int, list[str]] = OrderedDict()
        self._goals: OrderedDict[int, GoalHandle | GoalUpdate] = OrderedDict()
        self._goal_sent: dict[int, tuple[str, float]] = {}
        self._safety_acks: OrderedDict[int, str] = OrderedDict()
        self.rejected = 0
        self._chat_channel.set_callback(self._on_chat)
        self._goals_channel.set_callback(self._on_goal_command)
        self._safety_channel.set_callback(self._on_safety)

    # -- safety ---------------------------------------------------------------------

    def _on_safety(self, datagram: ReceivedDatagram) -> None:
        try:
            request = decode_safety_request(datagram.payload)
        except InvalidSafetyRequest as exc:
            # Unlike other channels, a bad safety request is answered (a client that never
            # hears back would repeat its stop for ever), and a stop is carried out anyway.
            self._count_rejected(self._safety_channel, exc)
            if exc.stop:
                self._stop(exc.how)
            self._send(self._safety_channel, SafetyError(str(exc), Reason.INVALID).encode())
            return
        earlier = self._safety_acks.get(request.id)
        if earlier is not None:
            if request.type == "stop":
                self._stop(request.how)  # a stop is never skipped, even when repeated
            self._send(self._safety_channel, earlier)
            return
        refusal: Refusal | None
        if request.type == "stop":
            self._stop(request.how)
            refusal = None
        elif self.gate is None:
            refusal = Refusal(NO_SUPERVISOR, Reason.NO_SUPERVISOR)
        elif request.type == "arm":
            refusal = self.gate.rearm()
        elif request.type == "take":
            refusal = self.gate.take()
        else:
            refusal = self.gate.release()
        if refusal is None:
            ack = SafetyAck(request.id, True, "", Reason.OK).encode()
        else:
            ack = SafetyAck(request.id, False, refusal.text, refusal.code).encode()
        _remember(self._safety_acks, request.id, ack)
        self.server.emit(
            {"event": "safety", "peer": self.call.peer, "type": request.type, "ok": refusal is None}
        )
        self._send(self._safety_channel, ack)

    def _stop(self, how: str) -> None:
        # Who stopped is the call's user; how (button, key, tab closed…) the user said.
        if self.gate is not None:
            self.gate.stop(how=how or "unspecified")
        else:
            self.server.halt_motion("stopped")  # no supervisor to end a follow-me or driving
            self.server.nav.stop()

    def send_safety_state(self, state: SafetyStatus) -> None:
        """Tell this call the safety state (on every change and once a second)."""
        self._send(self._safety_channel, state.encode())

    # -- chat -----------------------------------------------------------------------

    def _on_chat(self, datagram: ReceivedDatagram) -> None:
        request = self._decode(self._chat_channel, decode_request, datagram)
        if request is None:
            return
        earlier = self._chat_replies.get(request.id)
        if earlier is not None:
            for text in earlier:
                self._send(self._chat_channel, text)
            return
        _remember(self._chat_replies, request.id, [])
        self.server.emit({"event": "chat", "peer": self.call.peer, "text": request.text})
        self.chat.handle_text(request.id, request.text)

    def _send_chat(self, reply: ChatReply) -> None:
        text = reply.encode()
        replies = self._chat_replies.get(reply.id)
        if replies is not None:
            replies.append(text)
        self._send(self._chat_channel, text)
        for listener in self.server.chat_listeners:  # e.g. the media service speaks it
            try:
                listener(self.call, reply)
            except Exception:
                log.exception("chat reply listener failed")

    # -- goals ----------------------------------------------------------------------

    def _on_goal_command(self, datagram: ReceivedDatagram) -> None:
        command = self._decode(self._goals_channel, decode_goal_command, datagram)
        if command is None:
            return
        known = self._goals.get(command.id)
        if command.type == "query" or (command.type == "goal" and known is not None):
            self._send_goal_status(command.id, force=True)
            return
        if command.type == "cancel":
            if not may_drive(self.call.role):
                text = _OBSERVER
                if self.gate is not None:  # refused, and audited
                    text = str(self.gate.motion(f"cancel goal {command.id}") or text)
                refused = GoalUpdate(command.id, "refused", 0.0, text, Reason.OBSERVER)
                self._send(self._goals_channel, refused.encode())
                return
            if isinstance(known, GoalHandle):
                known.cancel()
            self._send_goal_status(command.id, force=True)
            return
        refusal: Refusal | None
        if self.gate is not None:  # it refuses observers too, and audits the refusal
            refusal = self.gate.motion(f"goal {command.x:g} {command.y:g}")
        else:
            observer = Refusal(_OBSERVER, Reason.OBSERVER)
            refusal = None if may_drive(self.call.role) else observer
        if refusal is not None:
            refused = GoalUpdate(command.id, "refused", 0.0, refusal.text, refusal.code)
            _remember(self._goals, command.id, refused)
        else:
            try:
                handle = self.server.nav.navigate_to(command.x, command.y, command.yaw)
            except TelebotError as exc:
                refused = GoalUpdate(command.id, "refused", 0.0, str(exc), error_reason(exc))
                _remember(self._goals, command.id, refused)
            else:
                _remember(self._goals, command.id, handle)
                self.server.emit({"event": "goal", "peer": self.call.peer, "id": command.id})
        self._send_goal_status(command.id, force=True)

    def _goal_update(self, goal_id: int) -> GoalUpdate:
        entry = self._goals.get(goal_id)
        if entry is None:
            return GoalUpdate(goal_id, "unknown", code=Reason.UNKNOWN_GOAL)
        if isinstance(entry, GoalUpdate):
            return entry
        if entry.status is GoalStatus.ACTIVE:
            return GoalUpdate(goal_id, "active", entry.progress, "", Reason.ACCEPTED)
        code = goal_reason(entry)
        return GoalUpdate(goal_id, str(entry.status), entry.progress, entry.reason, code)

    def _send_goal_status(self, goal_id: int, *, force: bool = False) -> None:
        update = self._goal_update(goal_id)
        now = self.server.now()
        last = self._goal_sent.get(goal_id)
        key = f"{update.status}:{update.progress:.2f}"
        if force or last is None or last[0] != key or now - last[1] >= GOAL_STATUS_EVERY:
            self._goal_sent[goal_id] = (key, now)
            self._send(self._goals_channel, update.encode())

    # -- periodic -------------------------------------------------------------------

    @property
    def video(self) -> VideoSender | None:
        """This call's video sender (from the ``video`` service), if one is registered."""
        return self.server.video_of(self.call.id)

    def tick(self, now: float | None = None) -> None:
        """After each robot step: chat reports, goal status changes; pose and telemetry
        at their rates (``now``: loop time; None reports chat and goals only)."""
        self.server._guarded(self.report)  # a failing report must not stop the pose stream
        if now is None:
            return
        settings = self.server.settings
        self.pose_due(now)
        if now >= self._next_telemetry:
            self._next_telemetry = max(self._next_telemetry + 1.0 / settings.telemetry_hz, now)
            self.server._guarded(self.publish_telemetry)
            self.server._guarded(self.send_safety_state, self.server.safety_status())

    def pose_due(self, now: float, *, fresh: bool = False) -> None:
        """Send the pose if it is due: at most ``pose_hz`` a second.

        ``fresh``: a new pose has just arrived (a PoseNotifier robot); it goes now, or as
        soon as the rate allows. Otherwise (the control loop's tick) a stepped robot's pose
        goes at ``pose_hz``, and a notifying robot's only after :data:`QUIET_POSE_EVERY`
        without one, so that the ticks do not use up the rate that fresh poses need.
        """
        interval = 1.0 / self.server.settings.pose_hz
        if fresh:
            if now >= self._last_pose + interval:
                self._send_pose(now)
            elif self._pose_timer is None:
                self._pose_timer = asyncio.get_running_loop().call_at(
                    self._last_pose + interval, self._deferred_pose
                )
        elif self.server.poses_pushed:
            if now >= self._last_pose + max(interval, QUIET_POSE_EVERY):
                self._send_pose(now)
        elif now >= self._next_pose:
            self._next_pose = max(self._next_pose + interval, now)
            self._send_pose(now)

    def _send_pose(self, now: float) -> None:
        self._last_pose = now
        self.server._guarded(self.publish_pose)

    def _deferred_pose(self) -> None:
        self._pose_timer = None
        self._send_pose(self.server.now())

    def close(self) -> None:
        """The call ended: end its map transfer."""
        if self._pose_timer is not None:
            self._pose_timer.cancel()
        self.map.close()

    def report(self) -> None:
        """Chat reports and goal status changes."""
        self.chat.poll()
        for goal_id, entry in list(self._goals.items()):
            if isinstance(entry, GoalHandle):
                self._send_goal_status(goal_id)
                if entry.status is not GoalStatus.ACTIVE:
                    # Freeze it: the final status is what repeats and queries get.
                    self._goals[goal_id] = self._goal_update(goal_id)
                    self._send_goal_status(goal_id, force=True)

    def _status(self, status: NavStatus) -> NavStatus:
        return self.follow.status(status) if self.follow is not None else status

    def publish_pose(self) -> None:
        """Send the pose estimate, velocity and state (latest only)."""
        nav = self.server.nav
        estimate = nav.pose()
        velocity = nav.velocity()
        # While following, the robot is moving even as it waits for the person: a key in
        # the terminal chat must stop it then too.
        status = self._status(nav.status())
        goal = nav.current_goal()
        cov = estimate.covariance
        update = PoseUpdate(
            t=estimate.stamp,
            x=estimate.pose.x,
            y=estimate.pose.y,
            yaw=estimate.pose.yaw,
            cov=(cov[0], cov[4], cov[8]),
            v=velocity.linear,
            w=velocity.angular,
            state=str(status.state),
            detail=status.detail,
            goal=goal.goal_id if goal is not None else None,
        )
        self._send(self._pose_channel, update.encode())

    def publish_telemetry(self) -> None:
        """Send battery, state, goal, camera, link quality and diagnostics."""
        nav = self.server.nav
        battery = nav.battery()
        status = self._status(nav.status())
        goal = nav.current_goal()
        rtt = self.call.stats.rtt
        safety = self.server.safety_status()
        video = self.video
        if video is not None and not video.watched:
            video = None
        telemetry = Telemetry(
            t=self.server.now(),
            battery=battery.percent,
            battery_low=battery.low,
            state=str(status.state),
            detail=status.detail,
            goal=goal.description if goal is not None else None,
            progress=goal.progress if goal is not None else None,
            camera=nav.active_camera,
            speed_limit=nav.speed_limit,
            rtt=rtt if rtt is not None and math.isfinite(rtt) else None,
            loss=self.call.stats.loss,
            role=str(self.call.role) if self.call.role is not None else "",
            diagnostics=dict(nav.diagnostics()),
            armed=safety.armed,
            stop_reason=safety.text,
            holder=safety.holder,
            video_fps=round(video.fps, 2) if video is not None else 0.0,
            video_width=video.width if video is not None else 0,
            video_height=video.height if video is not None else 0,
            video_quality=video.quality if video is not None else 0,
            map_version=self.server.map_version(),
            rx_dropped=self.call.receive_dropped,
        )
        self._send(self._telemetry_channel, telemetry.encode())

    def _decode(
        self,
        channel: Channel,
        decode: Callable[[str | bytes], _Request],
        datagram: ReceivedDatagram,
    ) -> _Request | None:
        """``decode(payload)``, or None for a datagram that is not a request (counted, logged)."""
        try:
            return decode(datagram.payload)
        except ProtocolError as exc:
            self._count_rejected(channel, exc)
            return None

    def _count_rejected(self, channel: Channel, exc: ProtocolError) -> None:
        self.rejected += 1
        channel.stats.rejected += 1
        log.debug("call %s: %s datagram rejected: %s", self.call.id, channel.name, exc)

    def _send(self, channel: Any, text: str) -> None:
        if not self.call.active:
            return
        try:
            channel.send(text)
        except TelebotError as exc:  # the call ended under us: its end is reported apart
            log.debug("call %s: not sent on %s: %s", self.call.id, channel.name, exc)


_OBSERVER = "observers may not drive: ask the driver"


class RobotVideo:
    """The ``video`` service of one call: a :class:`VideoSender` of the active camera."""

    def __init__(self, server: RobotServer, call: Call) -> None:
        settings = server.config.get("video", VideoSettings)
        self.sender = VideoSender.for_call(call, server.nav, settings)
        safety = server.safety
        if safety is not None:  # no driving blind: the supervisor follows the pictures
            self.sender.on_report = lambda report: safety.video_report(call, report)
        self.sender.start()

    def tick(self, now: float) -> None:
        """Nothing: the sender paces itself."""

    def close(self) -> None:
        """Stop sending."""
        self.sender.stop()


def robot_video_settings(
    video: VideoConfig, media: MediaConfig, *, simulated: bool
) -> VideoSettings:
    """The robot's ``[video]`` settings (:class:`RobotVideo`'s section) from the config's
    ``[video]`` and the codec settings of ``[media]``: the codecs (the configured one first,
    JPEG always last), bit rates, keyframe interval and stamping (``simulated``: a
    simulated robot's frames are stamped unless ``[media] stamp`` says)."""
    preferred = codec_id(media.codec)
    codecs = (preferred, *(c for c in (CODEC_H264, CODEC_VP8, CODEC_JPEG) if c != preferred))
    return VideoSettings(
        width=video.width,
        height=video.height,
        max_fps=video.max_fps,
        quality=video.quality,
        min_quality=min(30, video.quality),
        adaptive=video.adaptive,
        codecs=codecs,
        min_bitrate=media.min_bitrate,
        max_bitrate=media.max_bitrate,
        keyframe_interval=media.keyframe_interval,
        stamp=simulated if media.stamp is None else media.stamp,
    )


def _status(state: SafetyState) -> SafetyStatus:
    """The supervisor's state as the ``safety`` channel tells it."""
    return SafetyStatus(state.armed, state.text, state.holder, state.cap, state.blocked, state.code)


def _remember(table: OrderedDict[int, Any], key: int, value: Any) -> None:
    table[key] = value
    table.move_to_end(key)
    while len(table) > REMEMBERED:
        table.popitem(last=False)


class RobotServer:
    """Runs the robot: steps ``nav`` in real time and serves the services on each call."""

    def __init__(
        self,
        nav: NavStack,
        settings: ServiceSettings | None = None,
        *,
        control_hz: float = 20.0,
        map_name: str = "map",
        emit: EventSink | None = None,
        safety: SafetyDriver | None = None,
        services: ServiceRegistry[Any] | None = None,
        config: ServiceConfig | None = None,
    ) -> None:
        """``settings``: ``[services]`` (pose and telemetry rates); ``services``: what every
        call gets; ``config``: each service's section (``[video]``, ``[media]``,
        ``[relay]``, ``[people]``, ``[follow]``, ``[drive]``…; defaults where not given)."""
        self.nav = nav
        #: The robot's name (its identity's, from :meth:`attach` on).
        self.name = "robot"
        #: The services' settings, a section each.
        self.config = config if config is not None else ServiceConfig()
        #: What every call gets (:func:`~telebot.services.registry.robot_services` unless
        #: given); one registered later opens from the next call on.
        self.registry: ServiceRegistry[Any] = services if services is not None else robot_services()
        #: Called with (call, reply) for every chat reply sent (the media service speaks them).
        self.chat_listeners: list[Callable[[Call, ChatReply], None]] = []
        # Decided once: a robot that runs by itself has no step() and is not stepped.
        self._step = nav.step if isinstance(nav, SteppedNavStack) else None
        #: The safety supervisor's driver; None runs the robot without one (tests of the
        #: services alone): then nothing latches and roles alone decide who may drive.
        self.safety = safety
        self.settings = settings if settings is not None else ServiceSettings()
        self.control_hz = control_hz
        self.map_name = map_name
        self.emit: EventSink = emit if emit is not None else (lambda event: None)
        #: The core services of each call, by call id.
        self.services: dict[str, CallServices] = {}
        #: Every open service of each call, by call id.
        self.open: dict[str, OpenServices] = {}
        self._calls: dict[str, Call] = {}
        # New call id -> the same client's earlier call it replaced (see serve()).
        self._replaced: dict[str, str] = {}
        self._encoded: EncodedMap | None = None
        # A changed map being encoded in a worker thread, and a version that failed to encode.
        self._reencoding: asyncio.Future[EncodedMap] | None = None
        self._unencodable: int | None = None
        self._loop = asyncio.get_running_loop()
        self._pose_wakeup_pending = False
        #: Whether the robot announces its poses (then each is sent as it comes).
        self.poses_pushed = isinstance(nav, PoseNotifier)
        if isinstance(nav, PoseNotifier):
            # A robot whose poses arrive by themselves (ROS 2): send each one when it comes,
            # not at the next control cycle (up to 1/control_hz late), pose_hz still the cap.
            nav.add_pose_listener(self._pose_arrived)
        #: The services of this robot (each registered service once: see HostService).
        self.hosted: HostedServices[Any] = HostedServices(self.registry, self, start=False)
        self.hosted.start()  # kept first: a service may find those started before it
        if safety is not None:
            safety.on_state = self._broadcast_safety

    def _pose_arrived(self) -> None:
        """From any thread: wake the loop once to send the new pose (coalesced)."""
        if self._pose_wakeup_pending or self._loop.is_closed():
            return
        self._pose_wakeup_pending = True
        with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
            self._loop.call_soon_threadsafe(self._send_new_pose)

    def _send_new_pose(self) -> None:
        self._pose_wakeup_pending = False
        now = self.now()
        for services in list(self.services.values()):
            services.pose_due(now, fresh=True)

    def now(self) -> float:
        """The robot's clock (the event loop's)."""
        return self._loop.time()

    def service(self, name: str) -> HostService[Any] | None:
        """The robot's host service ``name``, if registered."""
        return self.hosted.get(name)

    def halt_motion(self, text: str) -> None:
        """Halt every :class:`~telebot.services.base.MotionService` (each guarded)."""
        for service in self.hosted:
            if isinstance(service, MotionService):
                with contextlib.suppress(Exception):
                    service.halt(text)

    def map_version(self) -> int:
        """The robot's map version as it travels (JSON-safe: wrapped into 0..2**53 − 1)."""
        return self.nav.map_version() & MAX_MAP_VERSION

    def encoded_map(self) -> EncodedMap:
        """The map, cropped and PNG-encoded once per map version (a SLAM map changes)."""
        version = self.map_version()  # before map(): see NavStack.map_version
        if self._encoded is None or self._encoded.version != version:
            self._encoded = encode_map(self.nav.map(), self.map_name, version=version)
        return self._encoded

    async def prepare(self) -> None:
        """Encode the map off the event loop before the first call needs it."""
        version = self.map_version()
        self._encoded = await asyncio.to_thread(
            encode_map, self.nav.map(), self.map_name, version=version
        )

    def _reencode_changed_map(self) -> None:
        """Encode a changed map in a worker thread, so a SLAM update does not stall the loop.

        Until it is done a call that asks for the map has it encoded on the loop instead.
        """
        if self._reencoding is not None or self._encoded is None:
            return
        version = self.map_version()
        if version in (self._encoded.version, self._unencodable):
            return
        grid = self.nav.map()
        future = self._loop.run_in_executor(
            None, functools.partial(encode_map, grid, self.map_name, version=version)
        )
        self._reencoding = future

        def done(future: asyncio.Future[EncodedMap]) -> None:
            self._reencoding = None
            if future.cancelled():
                return
            if (exc := future.exception()) is not None:
                self._unencodable = version
                log.warning("the changed map (version %s) cannot be encoded: %s", version, exc)
            elif version == self.map_version():  # else already stale: encode the next
                self._encoded = future.result()
                # Tell every call now (telemetry carries map_version), not at its next
                # telemetry tick up to a second later: users fetch the new map at once.
                for services in list(self.services.values()):
                    self._guarded(services.publish_telemetry)

        future.add_done_callback(done)

    def attach(self, endpoint: RobotEndpoint) -> None:
        """Serve every call ``endpoint`` answers from now on."""

        def on_call(call: Call) -> None:
            self.serve(call)

        self.name = endpoint.identity.name
        endpoint.on_call = on_call

    def video_of(self, call_id: str) -> VideoSender | None:
        """The video sender of call ``call_id``, if it has the ``video`` service."""
        opened = self.open.get(call_id)
        video = opened.get("video") if opened is not None else None
        return video.sender if isinstance(video, RobotVideo) else None

    def replaces(self, call_id: str) -> str | None:
        """The call that call ``call_id`` replaced (its client's previous call), if any."""
        return self._replaced.get(call_id)

    def _previous_call(self, call: Call) -> Call | None:
        """The earlier call of ``call``'s client (same user, same instance), if still here.

        A client calls again only once its own call has ended, so such a call is one the
        robot has not yet seen drop (the link failed one way first, or its timeout has not
        run out): it is dead, and the new call takes its place. Another client of the same
        user (a page beside a terminal) has another instance: a second call, not this.
        """
        if not call.peer_instance:
            return None
        for other in self._calls.values():
            if other.peer == call.peer and other.peer_instance == call.peer_instance:
                return other
        return None

    def serve(self, call: Call) -> CallServices | None:
        """Open every registered service on ``call``; returns its core services (if any).

        A call from the client of a call still here replaces that call: the drive passes
        to it (the robot stops and latches if it held the drive), the conference reads it
        as one reconnection, and the old call is hung up.
        """
        previous = self._previous_call(call)

        def on_end(_: asyncio.Future[Any]) -> None:
            # The supervisor hears first: a driver's hang-up must stop the robot whatever
            # happens in the clean-up after it.
            if self.safety is not None:
                self._guarded(self.safety.leave, call)
            self._calls.pop(call.id, None)
            self._replaced.pop(call.id, None)
            self.services.pop(call.id, None)
            opened = self.open.pop(call.id, None)
            if opened is not None:  # None: setting the services up failed
                opened.close()
            end = call.end
            self.emit(
                {
                    "event": "ended",
                    "id": call.id,
                    "peer": call.peer,
                    "kind": end.kind if end else "",
                    "detail": end.detail if end else "",
                }
            )
            log.info("call %s from %s ended: %s", call.id, call.peer, end)

        self._calls[call.id] = call
        if previous is not None:
            self._replaced[call.id] = previous.id
        if self.safety is not None:
            self.safety.join(call, replaces=previous)
        # Before the services: if setting them up fails, the endpoint hangs up, and the
        # call must still leave the supervisor (or it would hold the drive for good).
        asyncio.ensure_future(call.wait_ended()).add_done_callback(on_end)
        if previous is not None:
            # Its client has ended it already: what it still holds here (services, video,
            # the call's keys) goes now rather than at its timeout.
            log.info("call %s from %s replaces call %s", call.id, call.peer, previous.id)
            previous.hangup_now("replaced by a new call from the same client")
        opened = self.hosted.open(call)
        self.open[call.id] = opened
        services = opened.get("core")
        if not isinstance(services, CallServices):
            services = None
        else:
            self.services[call.id] = services
            if self.safety is not None:
                services.send_safety_state(self.safety_status())
        self.emit({"event": "call", "id": call.id, "peer": call.peer, "role": str(call.role)})
        log.info("call %s from %s (%s)", call.id, call.peer, call.role)
        return services

    def emergency_stop(self, reason: str) -> None:
        """Stop the robot now and latch the stop (every motion service halted first)."""
        # First: a follow must not drive again after the stop.
        self.halt_motion(f"stopped: {reason}")
        with contextlib.suppress(Exception):
            self.nav.stop()
        if self.safety is not None:
            with contextlib.suppress(Exception):
                self.safety.stop(None, reason)

    def safety_status(self) -> SafetyStatus:
        """The safety state as the users see it."""
        if self.safety is None:
            return SafetyStatus(True, "", None, self.nav.speed_limit, False, Reason.OK)
        return _status(self.safety.state())

    def _broadcast_safety(self, state: SafetyState) -> None:
        # A stop or a hand-over ends a follow (driving) before anyone hears of it.
        for service in self.hosted:
            if isinstance(service, MotionService):
                self._guarded(service.safety_changed, state)
        status = _status(state)
        for services in list(self.services.values()):
            self._guarded(services.send_safety_state, status)

    async def run(self) -> None:
        """Step the robot and run the services until cancelled."""
        period = 1.0 / self.control_hz
        next_step = self.now()
        try:
            while True:
                now = self.now()
                try:
                    if self._step is not None:
                        self._step(now)
                except Exception:
                    # Fail safe: a broken step must not leave the base driving, and the stop
                    # latches like any other (a new motion needs a re-arm).
                    log.exception("robot step failed: stopping the robot")
                    self.emergency_stop("robot step failed")
                if self.safety is not None:
                    try:
                        self.safety.tick()
                    except Exception:
                        log.exception("safety tick failed: stopping the robot")
                        self.emergency_stop("safety tick failed")
                self._guarded(self._reencode_changed_map)
                # After the supervisor's tick (a stop latched there ends a follow first), in
                # registration order: the people tracker's step before the drive's follow
                # and driving (the freshest tracks). Each guarded; the drive's own failures
                # stop the robot (emergency_stop).
                self.hosted.tick(now)
                for opened in list(self.open.values()):
                    opened.tick(now)  # each service guarded
                next_step += period
                delay = next_step - self.now()
                if delay < -period:  # we fell behind: do not try to catch up in a burst
                    next_step = self.now()
                    delay = 0.0
                await asyncio.sleep(max(delay, 0.0))
        finally:
            self.hosted.close()  # the people tracker's detector thread too

    @staticmethod
    def _guarded(action: Callable[..., None], *args: Any) -> None:
        try:
            action(*args)
        except Exception:
            log.exception("service handler failed")


if TYPE_CHECKING:  # the server is a host every robot-side service may run on
    from telebot.services.media.robot import MediaHost

    _SERVER = cast(RobotServer, None)
    _HOST: RobotHost = _SERVER
    _MEDIA_HOST: MediaHost = _SERVER
