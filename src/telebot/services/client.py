"""The user side as a library: ``async with telebot.connect("guiabot") as robot: ...``.

:class:`RobotClient` wraps a call to a telebot robot and speaks its services: chat
(Table I commands), goals, pose, telemetry and map transfer. Requests on lossy channels are
repeated until the robot answers; the robot answers a repeat with what it already said,
so nothing runs twice.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import secrets
from collections.abc import AsyncGenerator, AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, TypeVar

from telebot.channels.call import Call, UserEndpoint
from telebot.channels.channel import Channel, ReceivedDatagram
from telebot.channels.transports import create_transport
from telebot.channels.transports.base import Lane, Transport
from telebot.config import AppConfig, default_home
from telebot.errors import CallEnded, ProtocolError, TelebotError
from telebot.identity import Identity, KnownRobots
from telebot.reasons import Reason
from telebot.services.mapxfer import MapDownload, fetch_map
from telebot.services.proto import CHAT, GOALS, MAP, POSE, TELEMETRY
from telebot.services.proto.chat import ChatReply, decode_reply, encode_request
from telebot.services.proto.safety import (
    SAFETY,
    RequestType,
    SafetyAck,
    SafetyRequest,
    SafetyStatus,
    decode_safety_reply,
)
from telebot.services.proto.status import (
    GoalCommand,
    GoalUpdate,
    PoseUpdate,
    Telemetry,
    decode_goal_update,
    decode_pose,
    decode_telemetry,
)
from telebot.services.video import VideoReceiver, video_channel

__all__ = ["ChatResult", "RobotClient", "connect"]

log = logging.getLogger("telebot.client")

T = TypeVar("T")

#: A request nobody answered is sent again after this long (s).
RESEND_AFTER = 0.3
#: How often a motion refused because the robot has not measured the call's round trip
#: yet (just after set-up; code ``rtt_unmeasured``) is asked again (every 0.1 s).
UNMEASURED_RETRIES = 20
#: A stop is repeated this often (s) until the robot acknowledges it.
STOP_REPEAT = 0.05
#: While waiting for the end of a long-running request, ask again this often (s), so a
#: lost final answer is recovered.
REFRESH_AFTER = 2.0


@dataclass(slots=True)
class ChatResult:
    """All replies to one chat command; ``ok`` is the final reply's verdict.

    ``reason`` is the final reply's code (:class:`~telebot.reasons.Reason`:
    ``"finished"``, ``"not_armed"``, ``"observer"``, …): decide on it, never on the text.
    """

    command: str
    replies: list[str] = field(default_factory=list)
    ok: bool = False
    attachment: str | None = None
    reason: str = ""

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


class RobotClient:
    """A call to a robot, with its services as methods (see the module docstring)."""

    def __init__(self, call: Call) -> None:
        self.call = call
        self._chat = call.channel(CHAT, lane=Lane.CONTROL)
        self._goals = call.channel(GOALS, lane=Lane.CONTROL)
        self._pose = call.channel(POSE, lane=Lane.DATA, latest_only=True)
        self._telemetry = call.channel(TELEMETRY, lane=Lane.DATA, latest_only=True)
        self._map: Channel = call.channel(MAP, lane=Lane.BULK)
        self._safety = call.channel(SAFETY, lane=Lane.CONTROL)
        # Request ids start at a random point so a reconnecting client does not collide
        # with answers the robot still remembers from an earlier call.
        start = secrets.randbelow(2**31)
        self._chat_ids = itertools.count(start)
        self._goal_ids = itertools.count(start)
        self._safety_ids = itertools.count(start)
        self._safety_waiters: dict[int, asyncio.Queue[SafetyAck]] = {}
        #: The robot's safety state (armed, why stopped, who holds the drive).
        self.latest_safety: _Latest[SafetyStatus] = _Latest()
        self._chat_waiters: dict[int, asyncio.Queue[ChatReply]] = {}
        self._goal_waiters: dict[int, asyncio.Queue[GoalUpdate]] = {}
        self.latest_pose: _Latest[PoseUpdate] = _Latest()
        self.latest_telemetry: _Latest[Telemetry] = _Latest()
        #: Datagrams from the robot that did not decode (dropped).
        self.rejected = 0
        self._chat.set_callback(self._on_chat)
        self._goals.set_callback(self._on_goal)
        self._pose.set_callback(self._on_pose)
        self._telemetry.set_callback(self._on_telemetry)
        self._safety.set_callback(self._on_safety)

    @property
    def robot(self) -> str:
        """The robot's name."""
        return self.call.peer

    # -- chat -----------------------------------------------------------------------

    async def chat_replies(
        self, command: str, *, timeout: float | None = None
    ) -> AsyncGenerator[ChatReply, None]:
        """Send one chat command and yield each reply until the final one.

        Raises TimeoutError if the robot does not finish within ``timeout`` seconds and
        :class:`~telebot.errors.CallEnded` if the call ends first.
        """
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
                            and reply.reason == Reason.RTT_UNMEASURED
                            and attempt < UNMEASURED_RETRIES
                        ):
                            break
                        first = False
                        yield reply
                    else:
                        return
                await asyncio.sleep(RESEND_AFTER / 3)

    async def _one_request(self, command: str) -> AsyncGenerator[ChatReply, None]:
        request_id = next(self._chat_ids) % 2**32
        replies: asyncio.Queue[ChatReply] = asyncio.Queue()
        self._chat_waiters[request_id] = replies
        seen: set[int] = set()
        payload = encode_request(request_id, command)
        try:
            self._send(self._chat, payload)
            wait = RESEND_AFTER
            while True:
                try:
                    reply = await self._next(replies, wait)
                except TimeoutError:
                    self._send(self._chat, payload)  # lost one way or the other: ask again
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
                result.reason = reply.reason
        return result

    async def stop(self, *, how: str = "api", timeout: float = 5.0) -> SafetyAck:
        """Stop the robot now (any participant may); repeated until the robot acknowledges.

        The stop goes on the ``safety`` channel (CONTROL lane) and is sent again every
        :data:`STOP_REPEAT` seconds until acknowledged, so loss cannot eat it. The robot
        stays stopped (disarmed) until the drive holder re-arms it (:meth:`arm`). ``how``
        tells the robot's audit log how the user stopped (``"button"``, ``"key"``,
        ``"tab_closed"``, ``"exit"``, ``"api"``: see ``STOP_HOWS``).
        """
        return await self._safety_request("stop", timeout, STOP_REPEAT, how)

    async def arm(self, *, timeout: float = 5.0) -> SafetyAck:
        """Re-arm the robot after a stop (the drive holder only); ``ok`` False says why not."""
        return await self._safety_request("arm", timeout, RESEND_AFTER)

    async def take_drive(self, *, timeout: float = 5.0) -> SafetyAck:
        """Take the drive (when free; an admin takes it over)."""
        return await self._safety_request("take", timeout, RESEND_AFTER)

    async def release_drive(self, *, timeout: float = 5.0) -> SafetyAck:
        """Give the drive up (the robot stops)."""
        return await self._safety_request("release", timeout, RESEND_AFTER)

    async def _safety_request(
        self, kind: RequestType, timeout: float, repeat: float, how: str = ""
    ) -> SafetyAck:
        request_id = next(self._safety_ids) % 2**32
        acks: asyncio.Queue[SafetyAck] = asyncio.Queue()
        self._safety_waiters[request_id] = acks
        payload = SafetyRequest(kind, request_id, how).encode()
        try:
            async with asyncio.timeout(timeout):
                while True:
                    try:
                        self._send(self._safety, payload)
                    except CallEnded:
                        raise
                    except TelebotError as exc:  # a transient send failure: keep trying
                        log.warning("%s not sent (%s); trying again", kind, exc)
                    try:
                        return await self._next(acks, repeat)
                    except TimeoutError:
                        continue  # lost one way or the other: say it again
        finally:
            self._safety_waiters.pop(request_id, None)

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
        async with asyncio.timeout(timeout):
            for attempt in range(UNMEASURED_RETRIES + 1):
                update = await self._one_goal(x, y, yaw, on_update)
                # Refused only because the robot has not measured the new call's round
                # trip yet (just after set-up): ask again shortly, as chat does.
                if not (update.status == "refused" and update.reason == Reason.RTT_UNMEASURED):
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
        goal_id = next(self._goal_ids) % 2**32
        updates: asyncio.Queue[GoalUpdate] = asyncio.Queue()
        self._goal_waiters[goal_id] = updates
        start = GoalCommand("goal", goal_id, x, y, yaw).encode()
        query = GoalCommand("query", goal_id).encode()
        try:
            self._send(self._goals, start)
            heard = False
            while True:
                try:
                    update = await self._next(updates, REFRESH_AFTER if heard else RESEND_AFTER)
                except TimeoutError:
                    self._send(self._goals, query if heard else start)
                    continue
                if update.status == "unknown":
                    self._send(self._goals, start)  # the goal itself was lost
                    continue
                heard = True
                if on_update is not None and not (
                    update.status == "refused" and update.reason == Reason.RTT_UNMEASURED
                ):
                    on_update(update)
                if update.final:
                    return update
        finally:
            self._goal_waiters.pop(goal_id, None)

    # -- streams --------------------------------------------------------------------

    async def pose(self, *, timeout: float | None = 5.0) -> PoseUpdate:
        """The next pose update from the robot."""
        async with asyncio.timeout(timeout):
            return await self._until_ended(self.latest_pose.next())

    async def poses(self) -> AsyncIterator[PoseUpdate]:
        """Pose updates as they come (latest only: a slow reader skips to the newest)."""
        while True:
            yield await self._until_ended(self.latest_pose.next())

    async def telemetry(self, *, timeout: float | None = 5.0) -> Telemetry:
        """The next telemetry message from the robot."""
        async with asyncio.timeout(timeout):
            return await self._until_ended(self.latest_telemetry.next())

    async def get_map(
        self, *, timeout: float = 30.0, progress: Callable[[int, int], None] | None = None
    ) -> MapDownload:
        """Download the robot's map (cropped PNG with its georeference)."""
        return await fetch_map(self._map, timeout=timeout, progress=progress)

    def video(self, **options: Any) -> VideoReceiver:
        """The robot's video: ``async with robot.video() as video: async for frame in video``.

        Frames are decoded BGR numpy images with camera, frame id and capture time; the
        robot sends video only while a receiver is open (it reports back every 0.2 s).
        """
        return VideoReceiver(video_channel(self.call), **options)

    async def hangup(self) -> None:
        """End the call."""
        await self.call.hangup()

    # -- plumbing -------------------------------------------------------------------

    def _send(self, channel: Channel, payload: str) -> None:
        channel.send(payload)  # raises CallEnded once the call is over

    async def _next(self, queue: asyncio.Queue[T], wait: float) -> T:
        async with asyncio.timeout(wait):
            return await self._until_ended(queue.get())

    async def _until_ended(self, awaitable: Awaitable[T]) -> T:
        """Await ``awaitable`` but raise CallEnded as soon as the call ends."""
        task: asyncio.Future[T] = asyncio.ensure_future(awaitable)
        ended = asyncio.ensure_future(self.call.wait_ended())
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
        end = self.call.end
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
) -> AsyncIterator[RobotClient]:
    """Call ``robot`` and yield a :class:`RobotClient`; hangs up on exit.

    ``home`` holds the user's key and known robots (default: ``$TELEBOT_HOME`` or the
    user config dir); ``config`` the transport and call settings (default: zenoh peer);
    pass an open ``transport`` to share one between several calls.
    """
    config = config if config is not None else AppConfig()
    home = home if home is not None else default_home("user")
    identity = Identity.load(home)
    known = KnownRobots.load(home)
    async with contextlib.AsyncExitStack() as stack:
        if transport is None:
            transport = await stack.enter_async_context(create_transport(config.transport))
        endpoint = await stack.enter_async_context(
            UserEndpoint(
                transport, identity, known, settings=config.call, namespace=config.namespace
            )
        )
        call = await endpoint.call(robot, timeout=timeout)
        client = RobotClient(call)
        try:
            yield client
        finally:
            with contextlib.suppress(TelebotError):
                await call.hangup()
