"""The user side as a library: ``async with telebot.connect("guiabot") as robot: ...``.

:class:`RobotClient` wraps a call to a telebot robot and speaks its services: chat
(Table I commands), goals, pose, telemetry and map transfer. Requests on lossy channels are
repeated until the robot answers; the robot answers a repeat with what it already said,
so nothing runs twice.

Services are opened from a :class:`~telebot.services.base.ServiceRegistry`
(:func:`~telebot.services.registry.user_services`: ``core``, the channels above, and ``video``). What a
user subscribes to lives on the client, not on the call: :attr:`RobotClient.latest_pose`,
:meth:`RobotClient.poses`, :attr:`RobotClient.plan`, :meth:`RobotClient.plans`,
:attr:`RobotClient.places`, :meth:`RobotClient.video`, the video feed.

Reconnecting: a client made by :func:`connect` calls the robot again when its call drops
(:class:`~telebot.config.ReconnectSettings`: back-off with jitter, capped) and re-opens
every registered service on the new call, so ``async for pose in robot.poses()`` and
video iterators go on. Requests are bound to the call they started on: one in flight at
the drop raises :class:`~telebot.errors.CallEnded` and is never sent on the next call
(a goal is never resumed; the robot latched stopped at the drop and stays so until its
driver re-arms it); a request made while reconnecting waits for the new call. Listeners
in :attr:`RobotClient.on_connection` hear each :class:`ConnectionEvent`.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import math
import random
import secrets
from collections.abc import AsyncGenerator, AsyncIterator, Awaitable, Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Generic, Literal, TypeVar, cast

from telebot.channels.call import Call, CallEnd, UserEndpoint
from telebot.channels.channel import Channel, ReceivedDatagram
from telebot.channels.transports import create_transport
from telebot.channels.transports.base import Lane, Transport
from telebot.config import AppConfig, ReconnectSettings, default_home
from telebot.errors import (
    CallEnded,
    CallError,
    CallRejected,
    CallTimeout,
    ProtocolError,
    RelayRefused,
    TelebotError,
    UnknownTopic,
)
from telebot.identity import Identity, KnownRobots
from telebot.reasons import Reason
from telebot.services.base import (
    CLIENT_TICK,
    CallService,
    ClientHost,
    HostedServices,
    OpenServices,
    ServiceRegistry,
)
from telebot.services.chat.wire import CHAT, ChatReply, decode_reply, encode_request
from telebot.services.conference.user import ConferenceState
from telebot.services.conference.wire import Said
from telebot.services.drive.wire import DRIVE, DriveCommand, DriveState, decode_drive_state
from telebot.services.mapxfer import MAP
from telebot.services.media.user import AudioReceiver, UserMedia
from telebot.services.people.user import PeopleReceiver
from telebot.services.people.wire import PeopleAlertMessage, PeopleUpdate, TrackInfo
from telebot.services.plan.user import PlanReceiver
from telebot.services.plan.wire import Place, PlanUpdate
from telebot.services.registry import user_services
from telebot.services.relay.user import RelayReceiver, TopicStream
from telebot.services.relay.wire import (
    RelayedMessage,
    RelayRefusal,
    Started,
    StartRequest,
    StopRequest,
    TopicInfo,
)
from telebot.services.safety.wire import (
    SAFETY,
    RequestType,
    SafetyAck,
    SafetyError,
    SafetyRequest,
    SafetyStatus,
    decode_safety_reply,
)
from telebot.services.status.wire import (
    GOALS,
    POSE,
    TELEMETRY,
    GoalCommand,
    GoalUpdate,
    PoseUpdate,
    Telemetry,
    decode_goal_update,
    decode_pose,
    decode_telemetry,
)
from telebot.services.video.receiver import VideoFeed, VideoFeedService, VideoReceiver
from telebot.services.video.stream import video_channel

if TYPE_CHECKING:
    from telebot.services.mapxfer.user import MapDownload

__all__ = [
    "ChatResult",
    "ClientCore",
    "ClientDrive",
    "ConnectionEvent",
    "DriveState",
    "RelayedMessage",
    "RobotClient",
    "TopicInfo",
    "TopicStream",
    "backoff_delay",
    "connect",
]

log = logging.getLogger(__name__)

T = TypeVar("T")

#: A request nobody answered is sent again after this long (s).
RESEND_AFTER = 0.3
#: How often a motion refused because the robot has not measured the call's round trip
#: yet (just after set-up; code ``rtt_unmeasured``) is asked again (every 0.1 s).
UNMEASURED_RETRIES = 20
#: A stop is repeated this often (s) until the robot acknowledges it …
STOP_REPEAT = 0.05
#: … after its first repeats, and a release's, which come sooner (s after the one before):
#: a lossy link mostly loses one datagram at a time, and a lost stop or release then
#: costs 20 ms, not a whole period (20 ms apart, so QUIC never packs two copies in one
#: packet, and the browser's 20 ms tick keeps the same schedule).
QUICK_REPEATS = (0.02, 0.02)
#: While waiting for the end of a long-running request, ask again this often (s), so a
#: lost final answer is recovered.
REFRESH_AFTER = 2.0
#: Driving by hand: a held command is sent this often (s), 20 Hz …
DRIVE_EVERY = 0.05
#: … and a release (a zero command) this many times: at once, then after
#: :data:`QUICK_REPEATS`, then every :data:`DRIVE_EVERY` (0, 20, 40 and 90 ms).
RELEASE_REPEATS = 4


@dataclass(slots=True)
class ChatResult:
    """All replies to one chat command; ``ok`` is the final reply's verdict.

    ``code`` is the final reply's reason code (:class:`~telebot.reasons.Reason`:
    ``"finished"``, ``"not_armed"``, ``"observer"``, …): decide on it, never on the text.
    """

    command: str
    replies: list[str] = field(default_factory=list)
    ok: bool = False
    attachment: str | None = None
    code: str = ""

    @property
    def final_text(self) -> str:
        """The last reply (the outcome)."""
        return self.replies[-1] if self.replies else ""


class _Latest(Generic[T]):
    """The newest value of a stream, and waiters for the next one."""

    def __init__(self) -> None:
        self.value: T | None = None
        self._changed = asyncio.Event()

    def set(self, value: T) -> None:
        self.value = value
        self._changed.set()
        self._changed = asyncio.Event()

    async def next(self) -> T:
        changed = self._changed
        await changed.wait()
        assert self.value is not None
        return self.value


@dataclass(frozen=True, slots=True)
class ConnectionEvent:
    """A change of the client's link to its robot.

    ``state``: ``reconnecting`` (the call dropped; ``detail`` says why), ``reconnected``
    (a new call is up; ``seconds`` since the drop was noticed, ``attempts`` made) or
    ``ended`` (no more calls: hung up, refused, or given up; ``detail`` says why).
    """

    state: Literal["reconnecting", "reconnected", "ended"]
    detail: str = ""
    seconds: float = 0.0
    attempts: int = 0

    def __str__(self) -> str:
        if self.state == "reconnecting":
            return f"reconnecting… ({self.detail})" if self.detail else "reconnecting…"
        if self.state == "reconnected":
            return f"reconnected after {self.seconds:.1f} s"
        return f"disconnected: {self.detail}"


def backoff_delay(attempt: int, settings: ReconnectSettings, rng: random.Random) -> float:
    """Seconds to wait before reconnection attempt ``attempt`` (0 first).

    ``base`` doubled per attempt, capped at ``cap``, shortened by a random share of up to
    a half (jitter, so that many clients dropped together do not call back in step).
    """
    ceiling = min(settings.cap, settings.base * 2.0 ** min(attempt, 32))
    return ceiling * (1.0 - 0.5 * rng.random())


class ClientCore:
    """The ``core`` service of a user client on one call: chat, goals, pose, telemetry,
    map and safety channels, delivering to the client's waiters and latest values."""

    def __init__(self, client: RobotClient, call: Call) -> None:
        self.call = call
        self.chat = call.channel(CHAT, lane=Lane.CONTROL)
        self.goals = call.channel(GOALS, lane=Lane.CONTROL)
        self.pose = call.channel(POSE, lane=Lane.DATA, latest_only=True)
        self.telemetry = call.channel(TELEMETRY, lane=Lane.DATA, latest_only=True)
        self.map: Channel = call.channel(MAP, lane=Lane.BULK)
        self.safety = call.channel(SAFETY, lane=Lane.CONTROL)
        self.chat.set_callback(client._on_chat)
        self.goals.set_callback(client._on_goal)
        self.pose.set_callback(client._on_pose)
        self.telemetry.set_callback(client._on_telemetry)
        self.safety.set_callback(client._on_safety)

    def tick(self, now: float) -> None:
        """Nothing periodic: requests repeat themselves."""

    def close(self) -> None:
        """Deliver nothing more from this call."""
        for channel in (self.chat, self.goals, self.pose, self.telemetry, self.safety):
            channel.set_callback(None)


class ClientDrive:
    """The ``drive`` service of a user client on one call: sends the client's drive
    commands (:meth:`RobotClient.drive`) and keeps the robot's ``drive_state``."""

    def __init__(self, client: RobotClient, call: Call) -> None:
        self.call = call
        self.channel = call.channel(DRIVE, lane=Lane.CONTROL)
        self._client = client
        self.channel.set_callback(self._on_state)

    def _on_state(self, datagram: ReceivedDatagram) -> None:
        try:
            state = decode_drive_state(datagram.payload)
        except ProtocolError:
            self._client.rejected += 1
            return
        self._client.latest_drive.set(state)

    def tick(self, now: float) -> None:
        """Nothing periodic: the client repeats its commands itself."""

    def close(self) -> None:
        """Deliver nothing more from this call."""
        self.channel.set_callback(None)


def open_video(client: RobotClient, call: Call) -> VideoFeedService:
    """The ``video`` service on ``call``: frames into the client's :attr:`~RobotClient.video_feed`."""
    return VideoFeedService(client.video_feed, call)


def open_plan(client: RobotClient, call: Call) -> PlanReceiver:
    """The ``plan`` service on ``call``: plans and places into the client's latest values."""
    return PlanReceiver(call, client.latest_plan.set, client.latest_places.set)


def open_people(client: RobotClient, call: Call) -> PeopleReceiver:
    """The ``people`` service on ``call``: tracks and alerts into the client."""
    return PeopleReceiver(call, client.latest_people.set, client.people_alert)


def open_relay(client: RobotClient, call: Call) -> RelayReceiver:
    """The ``relay`` service on ``call`` (its streams: :meth:`RobotClient.relay`)."""
    return RelayReceiver(call)


class RobotClient:
    """A call to a robot, with its services as methods (see the module docstring).

    ``RobotClient(call)`` follows that one call; :func:`connect` also starts it (:meth:`start`),
    which ticks the services and, with reconnection on, replaces a dropped call.
    """

    def __init__(self, call: Call, *, services: ServiceRegistry[Any] | None = None) -> None:
        self.call = call
        #: What each call of this client gets (:func:`~telebot.services.registry.user_services`
        #: unless given); each service's per-client object is an attribute (``client.battery``).
        self.registry: ServiceRegistry[Any] = services if services is not None else user_services()
        #: The robot's video across calls (``robot.video()`` and the web UI read it).
        self.video_feed = VideoFeed()
        #: The robot's audio and the user's microphone and camera across calls.
        self.media = UserMedia()
        #: Called with every :class:`ConnectionEvent` (on the event loop).
        self.on_connection: list[Callable[[ConnectionEvent], None]] = []
        #: Called with ``(kind, fields)`` for each thing this user asks and each answer it
        #: gets (on the event loop): ``chat`` / ``chat_reply``, ``goal`` / ``goal_update``,
        #: ``safety`` / ``safety_ack``. Recordings (``telebot-user record``) log them.
        self.on_activity: list[Callable[[str, Mapping[str, Any]], None]] = []
        #: The newest :class:`ConnectionEvent` (None while the first call is up).
        self.latest_connection: _Latest[ConnectionEvent] = _Latest()
        #: Calls that replaced a dropped one.
        self.reconnects = 0
        self._robot = call.peer
        self._loop = asyncio.get_running_loop()
        self._finished: asyncio.Future[CallEnd] = self._loop.create_future()
        self._supervisor: asyncio.Task[None] | None = None
        self._closing = False
        self._rng = random.Random()
        # Request ids start at a random point so a reconnecting client does not collide
        # with answers the robot still remembers from an earlier call.
        start = secrets.randbelow(2**31)
        self._chat_ids = itertools.count(start)
        self._goal_ids = itertools.count(start)
        self._safety_ids = itertools.count(start)
        self._safety_waiters: dict[int, asyncio.Queue[SafetyAck]] = {}
        # This client's stops still being repeated (each done when acknowledged or given up),
        # and how many stops it was asked for (an arm must not follow a later stop).
        self._stops_in_flight: set[asyncio.Future[None]] = set()
        self._stops_asked = 0
        #: The robot's safety state (armed, why stopped and its ``code``, who holds the
        #: drive); ``stopped_itself`` says a re-arm (:meth:`arm`) is all it takes to go on.
        self.latest_safety: _Latest[SafetyStatus] = _Latest()
        #: Called with every safety state as it comes (on a change and once a second).
        self.on_safety: list[Callable[[SafetyStatus], None]] = []
        self._chat_waiters: dict[int, asyncio.Queue[ChatReply]] = {}
        self._goal_waiters: dict[int, asyncio.Queue[GoalUpdate]] = {}
        self.latest_pose: _Latest[PoseUpdate] = _Latest()
        self.latest_telemetry: _Latest[Telemetry] = _Latest()
        #: The robot's planned path (new ones only; see :attr:`plan`, :meth:`plans`).
        self.latest_plan: _Latest[PlanUpdate] = _Latest()
        #: The robot's named places by name (see :attr:`places`).
        self.latest_places: _Latest[Mapping[str, Place]] = _Latest()
        #: The people the robot tracks (see :meth:`people`, :meth:`people_updates`).
        self.latest_people: _Latest[PeopleUpdate] = _Latest()
        #: The newest people alert (see :meth:`people_alerts`); callbacks get every one.
        self.latest_people_alert: _Latest[PeopleAlertMessage] = _Latest()
        self.on_people_alert: list[Callable[[PeopleAlertMessage], None]] = []
        #: Datagrams from the robot that did not decode (dropped).
        self.rejected = 0
        #: The robot's newest ``drive_state`` (see :attr:`drive_state`).
        self.latest_drive: _Latest[DriveState] = _Latest()
        # Driving by hand: the command being repeated, until when (loop time), how many
        # zero commands are still to go, and the repeat timer.
        self._drive_seq = secrets.randbelow(2**31)
        self._drive_command = (0.0, 0.0)
        self._drive_until = -math.inf
        self._drive_zeros = 0
        self._drive_timer: asyncio.TimerHandle | None = None
        # Fire-and-forget work (a relay's stop), kept referenced until done.
        self._background: set[asyncio.Future[Any]] = set()
        #: Each service once for this client (its state across calls), by name.
        self.hosted: HostedServices[Any] = self.registry.start(self)
        #: The services open on the current call.
        self.services: OpenServices = self.hosted.open(call)

    @property
    def robot(self) -> str:
        """The robot's name."""
        return self._robot

    @property
    def finished(self) -> bool:
        """True once no call will come any more (a client not started: its call ended)."""
        if self._supervisor is None:
            return self.call.end is not None
        return self._finished.done()

    # -- lifecycle ------------------------------------------------------------------

    def start(
        self, endpoint: UserEndpoint | None = None, reconnect: ReconnectSettings | None = None
    ) -> None:
        """Tick the services; with ``endpoint`` and ``reconnect.enabled``, call the robot
        again when the call drops. End with :meth:`aclose`."""
        if self._supervisor is None:
            self._supervisor = self._loop.create_task(
                self._supervise(endpoint, reconnect), name=f"client-{self.robot}"
            )

    async def aclose(self) -> None:
        """Stop reconnecting and close the services (a hang-up is :meth:`hangup`'s)."""
        self._closing = True
        self._end_driving()
        if self._supervisor is not None:
            self._supervisor.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._supervisor
        self.services.close()
        self.hosted.close()
        self.video_feed.end()
        self.media.end()
        # Relay stops still waiting for their acknowledgement: no call will answer them now.
        background = list(self._background)
        for task in background:
            task.cancel()
        await asyncio.gather(*background, return_exceptions=True)

    async def wait_finished(self) -> CallEnd:
        """Wait until no call will come any more (started clients; else the call's end)."""
        if self._supervisor is None:
            return await self.call.wait_ended()
        return await asyncio.shield(self._finished)

    async def _supervise(
        self, endpoint: UserEndpoint | None, settings: ReconnectSettings | None
    ) -> None:
        end: CallEnd | None = None
        try:
            while True:
                end = await self._serve(self.call)
                self.services.close()
                redial = (
                    endpoint is not None
                    and settings is not None
                    and settings.enabled
                    and end.kind == "dropped"
                    and not self._closing
                )
                if not redial:
                    self._finish(end, str(end))
                    return
                assert endpoint is not None and settings is not None
                if not await self._redial(endpoint, settings, end):
                    return
        finally:
            if not self._finished.done():  # cancelled (closing): no more calls either
                self._finish(end or CallEnd("hung_up", False, "client closed"), "client closed")

    async def _serve(self, call: Call) -> CallEnd:
        """Tick the services of ``call`` until it ends."""
        ended = asyncio.ensure_future(call.wait_ended())
        try:
            while True:
                self.services.tick(self._loop.time())
                done, _ = await asyncio.wait({ended}, timeout=CLIENT_TICK)
                if done:
                    return ended.result()
        finally:
            ended.cancel()

    async def _redial(
        self, endpoint: UserEndpoint, settings: ReconnectSettings, end: CallEnd
    ) -> bool:
        """Call the robot until a call is up (True) or it is no use (False, finished)."""
        started = self._loop.time()
        self._emit(ConnectionEvent("reconnecting", end.detail))
        log.warning("call with %s %s; reconnecting", self.robot, end)
        attempt = 0
        while True:
            await asyncio.sleep(backoff_delay(attempt, settings, self._rng))
            attempt += 1
            waited = self._loop.time() - started
            if self._closing:  # hung up while the link was down: no new call
                self._finish(end, "hung up while reconnecting")
                return False
            if settings.give_up_after and waited >= settings.give_up_after:
                self._finish(end, f"gave up reconnecting after {waited:.0f} s")
                return False
            try:
                call = await endpoint.call(self.robot)
            except CallTimeout as exc:  # not answering (yet): the link may still be down
                log.info("reconnection attempt %d: %s", attempt, exc)
                continue
            except CallRejected as exc:
                self._finish(end, f"{self.robot} refused the call: {exc}")
                return False
            except CallError as exc:
                if endpoint.closed:
                    self._finish(end, str(exc))
                    return False
                # A KEY MISMATCH or a failed negotiation: unauthenticated presence tokens
                # and RETRYs can fake both, so one is no reason to stop trying (a real one
                # repeats until give_up_after).
                log.warning("reconnection attempt %d: %s", attempt, exc)
                continue
            except TelebotError as exc:  # a transport hiccup
                log.info("reconnection attempt %d failed: %s", attempt, exc)
                continue
            try:
                self.services = self.hosted.open(call)
            except Exception:
                log.exception("opening the services on the new call failed")
                call.hangup_now("user error: the call could not be served")
                self._finish(end, "the services could not be opened on the new call")
                return False
            self.call = call
            self.reconnects += 1
            seconds = self._loop.time() - started
            log.warning("reconnected to %s after %.1f s", self.robot, seconds)
            self._emit(ConnectionEvent("reconnected", seconds=seconds, attempts=attempt))
            return True

    def _finish(self, end: CallEnd, detail: str) -> None:
        if self._finished.done():
            return
        self._finished.set_result(end)
        self.video_feed.end()
        self.media.end()
        self._emit(ConnectionEvent("ended", detail))

    def _note(self, kind: str, fields: Mapping[str, Any]) -> None:
        for listener in list(self.on_activity):
            try:
                listener(kind, fields)
            except Exception:
                log.exception("activity listener failed")

    def _emit(self, event: ConnectionEvent) -> None:
        self.latest_connection.set(event)
        for listener in list(self.on_connection):
            try:
                listener(event)
            except Exception:
                log.exception("connection listener failed")

    def _ended_error(self) -> CallEnded:
        end = self._finished.result() if self._finished.done() else self.call.end
        return CallEnded(f"the call with {self.robot} {end}", end.kind if end else "")

    def __getattr__(self, name: str) -> Any:
        # Only for names not found the usual way: a service's per-client object.
        hosted = self.__dict__.get("hosted")
        service = hosted.get(name) if hosted is not None else None
        if service is None:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        return service

    @property
    def conference(self) -> ConferenceState:
        """The robot's conference: roster, messages, ``say`` (lives across reconnections)."""
        state = self.hosted.get("conference")
        if not isinstance(state, ConferenceState):
            raise TelebotError("this client has no conference service registered")
        return state

    def service(self, name: str) -> CallService | None:
        """The service ``name`` open on the current call, if any."""
        return self.services.get(name)

    async def live_call(self) -> Call:
        """The call once it is up, waiting out a reconnection (CallEnded once none will come)."""
        return (await self._core()).call

    async def answer(self, answers: asyncio.Queue[T], wait: float, call: Call) -> T:
        """The next of ``answers`` within ``wait`` s (TimeoutError); CallEnded if ``call`` ends."""
        return await self._next(answers, wait, call)

    async def _core(self) -> ClientCore:
        """The core service of a live call, waiting out a reconnection."""
        while True:
            core = self.services.get("core")
            if self.call.active and not self.services.closed and isinstance(core, ClientCore):
                return core
            if self._supervisor is None or self._finished.done():
                if not isinstance(core, ClientCore):
                    raise TelebotError("this client has no core service registered")
                raise self._ended_error()
            await self._until_finished(self.latest_connection.next())

    async def _until_finished(self, awaitable: Awaitable[T]) -> T:
        """Await ``awaitable`` across reconnections; CallEnded once no call will come."""
        if self._supervisor is None:
            return await self._until_ended(awaitable, self.call)
        task: asyncio.Future[T] = asyncio.ensure_future(awaitable)
        waiting: set[asyncio.Future[Any]] = {task, self._finished}
        try:
            done, _ = await asyncio.wait(waiting, return_when=asyncio.FIRST_COMPLETED)
        finally:
            if not task.done():
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        if task in done:
            return task.result()
        raise self._ended_error()

    # -- chat -----------------------------------------------------------------------

    async def chat_replies(
        self, command: str, *, timeout: float | None = None
    ) -> AsyncGenerator[ChatReply, None]:
        """Send one chat command and yield each reply until the final one.

        Raises TimeoutError if the robot does not finish within ``timeout`` seconds and
        :class:`~telebot.errors.CallEnded` if the call ends first.
        """
        self._note("chat", {"command": command})
        async with asyncio.timeout(timeout):
            for attempt in range(UNMEASURED_RETRIES + 1):
                first = True
                async with contextlib.aclosing(self._one_request(command)) as replies:
                    async for reply in replies:
                        # Just after the call comes up the robot has not measured the link's
                        # round trip yet and refuses to start a motion: ask again shortly.
                        if (
                            first
                            and reply.final
                            and not reply.ok
                            and reply.code == Reason.RTT_UNMEASURED
                            and attempt < UNMEASURED_RETRIES
                        ):
                            break
                        first = False
                        self._note(
                            "chat_reply",
                            {
                                "command": command,
                                "text": reply.text,
                                "ok": reply.ok,
                                "final": reply.final,
                                "code": reply.code,
                            },
                        )
                        yield reply
                    else:
                        return
                await asyncio.sleep(RESEND_AFTER / 3)

    async def _one_request(self, command: str) -> AsyncGenerator[ChatReply, None]:
        core = await self._core()
        request_id = next(self._chat_ids) % 2**32
        replies: asyncio.Queue[ChatReply] = asyncio.Queue()
        self._chat_waiters[request_id] = replies
        seen: set[int] = set()
        payload = encode_request(request_id, command)
        try:
            self._send(core.chat, payload)
            wait = RESEND_AFTER
            while True:
                try:
                    reply = await self._next(replies, wait, core.call)
                except TimeoutError:
                    self._send(core.chat, payload)  # lost one way or the other: ask again
                    continue
                wait = REFRESH_AFTER
                if reply.seq in seen:
                    continue
                seen.add(reply.seq)
                yield reply
                if reply.final:
                    return
        finally:
            self._chat_waiters.pop(request_id, None)

    async def chat(
        self,
        command: str,
        *,
        timeout: float | None = None,
        on_reply: Callable[[ChatReply], None] | None = None,
    ) -> ChatResult:
        """Send a chat command and wait for its outcome (all replies are collected)."""
        result = ChatResult(command)
        async for reply in self.chat_replies(command, timeout=timeout):
            result.replies.append(reply.text)
            if on_reply is not None:
                on_reply(reply)
            if reply.final:
                result.ok = reply.ok
                result.attachment = reply.attachment
                result.code = reply.code
        return result

    async def stop(self, *, how: str = "api", timeout: float = 5.0) -> SafetyAck:
        """Stop the robot now (any participant may); repeated until the robot acknowledges.

        The stop goes on the ``safety`` channel (CONTROL lane) and is sent again after
        :data:`QUICK_REPEATS` (20 ms, 20 ms), then every :data:`STOP_REPEAT` seconds until
        acknowledged, so loss cannot eat it. The robot stays stopped (disarmed) until the
        drive holder re-arms it (:meth:`arm`). ``how``
        tells the robot's audit log how the user stopped (``"button"``, ``"key"``,
        ``"tab_closed"``, ``"exit"``, ``"api"``: see ``STOP_HOWS``). It also ends the
        repeating of :meth:`drive`.
        """
        self._end_driving()
        return await self._safety_request("stop", timeout, STOP_REPEAT, how, QUICK_REPEATS)

    async def arm(self, *, timeout: float = 5.0) -> SafetyAck:
        """Re-arm the robot after a stop (the drive holder only); ``ok`` False says why not.

        Sent once this client's own stops are acknowledged (or given up): a copy of a
        stop still being repeated would reach the robot after the arm and stop it again.
        ``timeout`` covers that wait. A stop asked for while the arm waited wins: the arm is
        not sent, and ``ok`` is False (code ``stopped``).
        """
        return await self._safety_request("arm", timeout, RESEND_AFTER)

    async def take_drive(self, *, timeout: float = 5.0) -> SafetyAck:
        """Take the drive (when free; an admin takes it over); after this client's own
        stops, like :meth:`arm`."""
        return await self._safety_request("take", timeout, RESEND_AFTER)

    async def release_drive(self, *, timeout: float = 5.0) -> SafetyAck:
        """Give the drive up (the robot stops)."""
        return await self._safety_request("release", timeout, RESEND_AFTER)

    async def _safety_request(
        self,
        kind: RequestType,
        timeout: float,
        repeat: float,
        how: str = "",
        first_repeats: tuple[float, ...] = (),
    ) -> SafetyAck:
        waits = itertools.chain(first_repeats, itertools.repeat(repeat))
        request_id = next(self._safety_ids) % 2**32
        acks: asyncio.Queue[SafetyAck] = asyncio.Queue()
        self._safety_waiters[request_id] = acks
        payload = SafetyRequest(kind, request_id, how).encode()
        noted = False
        stop_done: asyncio.Future[None] | None = None
        if kind == "stop":
            self._stops_asked += 1
            stop_done = self._loop.create_future()
            self._stops_in_flight.add(stop_done)
        stops_before = self._stops_asked
        try:
            async with asyncio.timeout(timeout):
                after_stops = kind in ("arm", "take")
                if after_stops and self._stops_in_flight:
                    await asyncio.wait(set(self._stops_in_flight))
                core = await self._core()
                if after_stops and self._stops_asked != stops_before:
                    # A stop asked for while this waited comes first and is not undone.
                    text = f"{kind} not sent: a stop was asked for after it"
                    return SafetyAck(request_id, False, text, Reason.STOPPED)
                while True:
                    try:
                        self._send(core.safety, payload)
                    except CallEnded:
                        raise
                    except TelebotError as exc:  # a transient send failure: keep trying
                        log.warning("%s not sent (%s); trying again", kind, exc)
                    if not noted:  # after the send: a stop never waits for listeners
                        noted = True
                        self._note("safety", {"request": kind, "how": how})
                    try:
                        ack = await self._next(acks, next(waits), core.call)
                    except TimeoutError:
                        continue  # lost one way or the other: say it again
                    self._note(
                        "safety_ack",
                        {"request": kind, "ok": ack.ok, "text": ack.text, "code": ack.code},
                    )
                    return ack
        finally:
            self._safety_waiters.pop(request_id, None)
            if stop_done is not None:
                self._stops_in_flight.discard(stop_done)
                stop_done.set_result(None)

    # -- driving by hand -------------------------------------------------------------

    def drive(self, linear: float, angular: float, *, hold: float = 0.25) -> None:
        """Drive by hand: command this velocity now (m/s, + forward; rad/s, + to the left).

        Never blocks. The command is sent at once and repeated every :data:`DRIVE_EVERY`
        (20 Hz, covering loss) for at most ``hold`` seconds, then no more: the robot stops
        by itself ``[drive] stale_after`` (0.3 s) later unless ``drive()`` is called again.
        Keep driving by calling it at 5 Hz or more while the user holds the key (a stuck
        caller stops the robot). ``drive(0, 0)`` releases: the robot stops at once (the
        zero command is sent 4 times, 0, 20, 40 and 90 ms after the call). :meth:`stop`
        also ends the repeating.
        What the robot makes of it arrives in :attr:`drive_state`. Raises ValueError on a
        number that is not finite (or a negative ``hold``). Safe to call from another
        thread (the sending runs on the client's event loop).
        """
        values = (linear, angular, hold)
        if not all(isinstance(v, int | float) and math.isfinite(v) for v in values):
            raise ValueError(
                f"drive: linear, angular and hold must be finite numbers, "
                f"not {linear!r}, {angular!r}, {hold!r}"
            )
        if hold < 0:
            raise ValueError(f"drive: hold must be >= 0 s, not {hold!r}")
        command = (float(linear), float(angular))
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is self._loop:
            self._start_driving(command, hold)
        else:
            self._loop.call_soon_threadsafe(self._start_driving, command, hold)

    @property
    def drive_state(self) -> DriveState | None:
        """The robot's newest ``drive_state`` (None before the first): ``active``, the code
        (``code``: ``ok``, ``released``, ``stale``, ``obstacle``, ``not_armed``, …), the
        velocity it commands now and the speed cap."""
        return self.latest_drive.value

    def _start_driving(self, command: tuple[float, float], hold: float) -> None:
        if command == (0.0, 0.0):
            self._drive_command = command
            self._drive_until = -math.inf
            self._drive_zeros = RELEASE_REPEATS
        else:
            self._drive_command = command
            self._drive_until = self._loop.time() + hold
            self._drive_zeros = 0
        if self._drive_timer is not None:
            self._drive_timer.cancel()
            self._drive_timer = None
        self._send_drive()

    def _send_drive(self) -> None:
        """Send the current command once and schedule the next, if any is due."""
        self._drive_timer = None
        now = self._loop.time()
        if self._drive_zeros > 0:
            self._drive_zeros -= 1
        elif now > self._drive_until:
            return  # held long enough: the robot stops by itself
        linear, angular = self._drive_command
        self._drive_seq = (self._drive_seq + 1) % 2**32
        drive = self.services.get("drive")
        if isinstance(drive, ClientDrive):
            try:
                drive.channel.send(DriveCommand(self._drive_seq, linear, angular).encode())
            except TelebotError as exc:  # no call right now: the robot stops by itself
                log.debug("drive command not sent: %s", exc)
        if self._drive_zeros > 0:
            sent = RELEASE_REPEATS - self._drive_zeros  # copies of the release so far
            wait = QUICK_REPEATS[sent - 1] if sent <= len(QUICK_REPEATS) else DRIVE_EVERY
            self._drive_timer = self._loop.call_later(wait, self._send_drive)
        elif now + DRIVE_EVERY < self._drive_until:
            self._drive_timer = self._loop.call_later(DRIVE_EVERY, self._send_drive)

    def _end_driving(self) -> None:
        """Send no more drive commands (a stop follows, or the client closes)."""
        if self._drive_timer is not None:
            self._drive_timer.cancel()
            self._drive_timer = None
        self._drive_until = -math.inf
        self._drive_zeros = 0

    # -- goals ----------------------------------------------------------------------

    async def goto(
        self,
        x: float,
        y: float,
        yaw: float | None = None,
        *,
        timeout: float | None = None,
        on_update: Callable[[GoalUpdate], None] | None = None,
    ) -> GoalUpdate:
        """Send a navigation goal (map frame, metres, radians) and wait until it ends.

        Returns the final status (``succeeded``, ``failed``, ``cancelled`` or ``refused``).
        """
        self._note("goal", {"x": x, "y": y, "yaw": yaw})
        async with asyncio.timeout(timeout):
            for attempt in range(UNMEASURED_RETRIES + 1):
                update = await self._one_goal(x, y, yaw, on_update)
                # Refused only because the robot has not measured the new call's round
                # trip yet (just after set-up): ask again shortly, as chat does.
                if not (update.status == "refused" and update.code == Reason.RTT_UNMEASURED):
                    return update
                if attempt < UNMEASURED_RETRIES:
                    await asyncio.sleep(RESEND_AFTER / 3)
            return update

    async def _one_goal(
        self,
        x: float,
        y: float,
        yaw: float | None,
        on_update: Callable[[GoalUpdate], None] | None,
    ) -> GoalUpdate:
        core = await self._core()
        goal_id = next(self._goal_ids) % 2**32
        updates: asyncio.Queue[GoalUpdate] = asyncio.Queue()
        self._goal_waiters[goal_id] = updates
        start = GoalCommand("goal", goal_id, x, y, yaw).encode()
        query = GoalCommand("query", goal_id).encode()
        try:
            # Bound to this call: a drop ends the goal here, and it is never sent on the
            # next call (the robot cancelled it when it latched at the drop).
            self._send(core.goals, start)
            heard = False
            while True:
                try:
                    wait = REFRESH_AFTER if heard else RESEND_AFTER
                    update = await self._next(updates, wait, core.call)
                except TimeoutError:
                    self._send(core.goals, query if heard else start)
                    continue
                if update.status == "unknown":
                    self._send(core.goals, start)  # the goal itself was lost
                    continue
                heard = True
                if not (update.status == "refused" and update.code == Reason.RTT_UNMEASURED):
                    self._note(
                        "goal_update",
                        {
                            "id": update.id,
                            "x": x,
                            "y": y,
                            "yaw": yaw,
                            "status": update.status,
                            "progress": update.progress,
                            "text": update.text,
                            "code": update.code,
                        },
                    )
                    if on_update is not None:
                        on_update(update)
                if update.final:
                    return update
        finally:
            self._goal_waiters.pop(goal_id, None)

    # -- streams --------------------------------------------------------------------

    async def pose(self, *, timeout: float | None = 5.0) -> PoseUpdate:
        """The next pose update from the robot (waits out a reconnection)."""
        async with asyncio.timeout(timeout):
            return await self._until_finished(self.latest_pose.next())

    async def poses(self) -> AsyncIterator[PoseUpdate]:
        """Pose updates as they come (latest only: a slow reader skips to the newest).

        They go on across reconnections and end (CallEnded) when no call will come.
        """
        while True:
            yield await self._until_finished(self.latest_pose.next())

    @property
    def plan(self) -> PlanUpdate | None:
        """The robot's latest planned path (``points`` empty: it has none), None before the
        first; it stays across reconnections until the new call brings one."""
        return self.latest_plan.value

    async def plans(self) -> AsyncIterator[PlanUpdate]:
        """Each new plan as it comes: a new goal's, a replan's, an empty one when the goal
        ends (latest only: a slow reader skips to the newest). Ends (CallEnded) with the
        client, as :meth:`poses` does."""
        while True:
            yield await self._until_finished(self.latest_plan.next())

    def people(self) -> tuple[TrackInfo, ...]:
        """The people the robot tracks now (its latest ``people`` message; empty before it)."""
        update = self.latest_people.value
        return update.tracks if update is not None else ()

    async def people_updates(self) -> AsyncIterator[PeopleUpdate]:
        """Each ``people`` message as it comes (5 Hz; latest only). Ends with the client."""
        while True:
            yield await self._until_finished(self.latest_people.next())

    async def people_alerts(self) -> AsyncIterator[PeopleAlertMessage]:
        """Alerts as they come ("person approaching from the left, 2.1 m"; latest only)."""
        while True:
            yield await self._until_finished(self.latest_people_alert.next())

    def people_alert(self, alert: PeopleAlertMessage) -> None:
        self.latest_people_alert.set(alert)
        for callback in list(self.on_people_alert):
            try:
                callback(alert)
            except Exception:
                log.exception("people alert callback failed")

    @property
    def places(self) -> Mapping[str, Place]:
        """The robot's named places by name (empty until the robot has sent them)."""
        return self.latest_places.value or {}

    async def telemetry(self, *, timeout: float | None = 5.0) -> Telemetry:
        """The next telemetry message from the robot."""
        async with asyncio.timeout(timeout):
            return await self._until_finished(self.latest_telemetry.next())

    async def get_map(
        self, *, timeout: float = 30.0, progress: Callable[[int, int], None] | None = None
    ) -> MapDownload:
        """Download the robot's map (cropped PNG with its georeference)."""
        # Imported here: the map transfer needs numpy, OpenCV and YAML, chat and poses don't.
        from telebot.services.mapxfer.user import fetch_map

        async with asyncio.timeout(timeout):
            core = await self._core()
        return await fetch_map(core.map, timeout=timeout, progress=progress)

    def video(self, **options: Any) -> VideoReceiver:
        """The robot's video: ``async with robot.video() as video: async for frame in video``.

        Frames are decoded BGR numpy images with camera, frame id and capture time; the
        robot sends video only while a receiver is open (it reports back every 0.2 s).
        On a started client (:func:`connect`) the frames go on across reconnections.
        """
        if self._supervisor is not None:
            return VideoReceiver(self.video_feed, **options)
        return VideoReceiver(video_channel(self.call), **options)

    def audio(self, **options: Any) -> AudioReceiver:
        """The robot's microphone: ``async with robot.audio() as audio: async for block in
        audio`` (:class:`~telebot.services.media.robot.AudioBlock`: 20 ms of 48 kHz mono int16).

        The robot sends audio only while a receiver is open.
        """
        return AudioReceiver(self.media, **options)

    def talk(self, mic: Any = None, camera: Any = None) -> None:
        """Send a microphone (``"wav:PATH"``, ``"tone:1000"``, ``"default"`` or an
        :class:`~telebot.services.media.audio.AudioSource`) and/or a camera (a function returning
        BGR pictures) to the robot while it asks for them; ``talk()`` stops both."""
        self.media.talk(mic=mic, camera=camera)

    # -- topic relay ------------------------------------------------------------------

    async def topics(self, *, timeout: float = 5.0) -> list[TopicInfo]:
        """The topics the robot would relay to this caller (name, type, schema)."""
        async with asyncio.timeout(timeout):
            receiver = await self._relay_receiver()
            return await self._until_ended(receiver.topics(timeout), receiver.call)

    def relay(
        self,
        topic: str,
        *,
        rate: float | None = None,
        latest_only: bool = False,
        timeout: float = 5.0,
    ) -> contextlib.AbstractAsyncContextManager[TopicStream]:
        """Relay a robot topic: ``async with robot.relay("/scan", rate=5) as scans:
        async for message in scans: ...`` (:class:`RelayedMessage`: CDR bytes as on the robot).

        ``rate``: at most this many messages per second (None: as they come, up to the
        robot's cap); ``latest_only``: the robot keeps only the newest unsent message. The
        relay ends when the block is left, and with the call it started on (iteration then
        stops). Raises :class:`~telebot.errors.UnknownTopic` (its message and ``near`` list
        near matches) or :class:`~telebot.errors.RelayRefused` (``code``: a reason code,
        ``"topic_not_allowed"`` when the caller's role may not relay it).
        """
        return self._relay_stream(topic, rate, latest_only, timeout)

    @contextlib.asynccontextmanager
    async def _relay_stream(
        self, topic: str, rate: float | None, latest_only: bool, timeout: float
    ) -> AsyncIterator[TopicStream]:
        async with asyncio.timeout(timeout):
            receiver = await self._relay_receiver()
        ids: list[int] = []

        def start(request_id: int) -> str:
            ids.append(request_id)
            receiver.pending_starts[request_id] = latest_only
            return StartRequest(request_id, topic, rate, latest_only).encode()

        try:
            answer = await self._until_ended(receiver.request(start, timeout), receiver.call)
        finally:
            for request_id in ids:
                receiver.pending_starts.pop(request_id, None)
        if isinstance(answer, RelayRefusal):
            if answer.code == Reason.UNKNOWN_TOPIC:
                raise UnknownTopic(answer.text, answer.near)
            raise RelayRefused(answer.text, answer.code)
        if not isinstance(answer, Started):
            raise ProtocolError(f"relay: unexpected answer {answer!r}")
        stream = receiver.streams.get(answer.stream)
        if stream is None:  # the call ended as the answer came
            stream = TopicStream(answer.info, answer.stream, receiver.call, latest_only=latest_only)
            stream.end("the call ended")
        try:
            yield stream
        finally:
            receiver.forget(stream)
            if receiver.call.active:
                stop = receiver.request(
                    lambda i: StopRequest(i, answer.stream).encode(), timeout=2.0
                )
                task = asyncio.ensure_future(stop)
                self._background.add(task)
                task.add_done_callback(self._background_done)

    def _background_done(self, task: asyncio.Future[Any]) -> None:
        self._background.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.debug("relay stop not acknowledged: %s", task.exception())

    async def _relay_receiver(self) -> RelayReceiver:
        await self._core()  # waits out a reconnection
        receiver = self.services.get("relay")
        if not isinstance(receiver, RelayReceiver):
            raise TelebotError("this client has no relay service registered")
        return receiver

    async def say(self, text: str, *, timeout: float = 5.0) -> Said:
        """Say ``text`` to every user in the robot's calls (:meth:`ConferenceState.say`)."""
        return await self.conference.say(text, timeout=timeout)

    async def hangup(self) -> None:
        """End the call (no reconnection follows)."""
        self._closing = True
        self._end_driving()
        await self.call.hangup()

    # -- plumbing -------------------------------------------------------------------

    def _send(self, channel: Channel, payload: str) -> None:
        channel.send(payload)  # raises CallEnded once the call is over

    async def _next(self, queue: asyncio.Queue[T], wait: float, call: Call) -> T:
        async with asyncio.timeout(wait):
            return await self._until_ended(queue.get(), call)

    async def _until_ended(self, awaitable: Awaitable[T], call: Call) -> T:
        """Await ``awaitable`` but raise CallEnded as soon as ``call`` ends."""
        task: asyncio.Future[T] = asyncio.ensure_future(awaitable)
        ended = asyncio.ensure_future(call.wait_ended())
        waiting: set[asyncio.Future[Any]] = {task, ended}
        try:
            done, _ = await asyncio.wait(waiting, return_when=asyncio.FIRST_COMPLETED)
        finally:
            ended.cancel()
            if not task.done():
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        if task in done:
            return task.result()
        end = call.end
        raise CallEnded(f"the call with {self.robot} {end}", end.kind if end else "")

    def _on_chat(self, datagram: ReceivedDatagram) -> None:
        try:
            reply = decode_reply(datagram.payload)
        except ProtocolError:
            self.rejected += 1
            return
        waiter = self._chat_waiters.get(reply.id)
        if waiter is not None:
            waiter.put_nowait(reply)

    def _on_goal(self, datagram: ReceivedDatagram) -> None:
        try:
            update = decode_goal_update(datagram.payload)
        except ProtocolError:
            self.rejected += 1
            return
        waiter = self._goal_waiters.get(update.id)
        if waiter is not None:
            waiter.put_nowait(update)

    def _on_pose(self, datagram: ReceivedDatagram) -> None:
        try:
            self.latest_pose.set(decode_pose(datagram.payload))
        except ProtocolError:
            self.rejected += 1

    def _on_safety(self, datagram: ReceivedDatagram) -> None:
        try:
            message = decode_safety_reply(datagram.payload)
        except ProtocolError:
            self.rejected += 1
            return
        if isinstance(message, SafetyStatus):
            self.latest_safety.set(message)
            for callback in list(self.on_safety):
                try:
                    callback(message)
                except Exception:  # one listener's fault must not hide the state from others
                    log.exception("safety state listener failed")
            return
        if isinstance(message, SafetyError):  # our own requests always decode: a robot's bug
            log.warning("the robot could not read a safety request: %s", message.text)
            return
        waiter = self._safety_waiters.get(message.id)
        if waiter is not None:
            waiter.put_nowait(message)

    def _on_telemetry(self, datagram: ReceivedDatagram) -> None:
        try:
            self.latest_telemetry.set(decode_telemetry(datagram.payload))
        except ProtocolError:
            self.rejected += 1


@contextlib.asynccontextmanager
async def connect(
    robot: str,
    *,
    home: Path | None = None,
    config: AppConfig | None = None,
    transport: Transport | None = None,
    timeout: float | None = None,
    reconnect: bool | None = None,
    services: ServiceRegistry[Any] | None = None,
) -> AsyncIterator[RobotClient]:
    """Call ``robot`` and yield a started :class:`RobotClient`; hangs up on exit.

    ``home`` holds the user's key and known robots (default: ``$TELEBOT_HOME`` or the
    user config dir); ``config`` the transport, call and reconnection settings (default:
    zenoh peer, reconnect on); pass an open ``transport`` to share one between several
    calls. ``reconnect`` overrides ``config.reconnect.enabled``; ``services`` replaces
    :func:`~telebot.services.registry.user_services`.
    """
    config = config if config is not None else AppConfig()
    home = home if home is not None else default_home("user")
    identity = Identity.load(home)
    known = KnownRobots.load(home)
    async with contextlib.AsyncExitStack() as stack:
        if transport is None:
            config.fit_lease()  # the call timeout may have changed since validation
            transport = await stack.enter_async_context(create_transport(config.transport))
        endpoint = await stack.enter_async_context(
            UserEndpoint(
                transport, identity, known, settings=config.call, namespace=config.namespace
            )
        )
        call = await endpoint.call(robot, timeout=timeout)
        settings = config.reconnect
        if reconnect is not None:
            settings = settings.model_copy(update={"enabled": reconnect})
        client = RobotClient(call, services=services)
        client.start(endpoint, settings)
        try:
            yield client
        finally:
            client._closing = True
            with contextlib.suppress(TelebotError):
                await client.call.hangup()
            await client.aclose()


if TYPE_CHECKING:  # the client is a host every user-side service may run on
    from telebot.services.media.user import MediaClient

    _CLIENT = cast(RobotClient, None)
    _HOST: ClientHost = _CLIENT
    _MEDIA_CLIENT: MediaClient = _CLIENT
