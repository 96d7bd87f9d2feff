"""The web UI's server: an aiohttp app that serves the page and bridges it to a call.

One :class:`WebUI` wraps one connected :class:`~telebot.services.client.RobotClient`
and serves ``static/`` (no build step, nothing fetched from the internet), the robot's map
as ``/map.png``, and a websocket at ``/ws`` (the page's URLs are relative, so the fleet
page serves the same page at ``/robot/NAME/`` through :meth:`WebUI.handle`). Any number of pages may be open; the robot
streams video while at least one is.

Websocket protocol (JSON text messages unless stated; docs/protocol.md §19). What the
page sends is typed in :mod:`telebot.apps.web.messages` (``stop``, ``arm``, ``take``,
``release``, ``goal``, ``drive``, ``chat``, ``say``, ``camera``, ``ping``, ``media``,
``keyframe``), parsed once and handled with ``match``; a bad one is answered with one
``error``. A machine-readable reason is ``code``, the words for people ``text``::

    client → page
      {"type": "hello", "robot", "user", "role", "may_drive", "map": MAP | null}
      {"type": "map", "url": "map.png", "resolution", "origin_x", "origin_y",
       "width", "height", "version"}                     when the map has arrived, and
                                                         again whenever it changed (SLAM)
      {"type": "pose", "x", "y", "yaw", "v", "w", "state", "detail", "goal", "t",
       "recv": UNIX_MS}                                  recv: when the client got it
      {"type": "telemetry", ...}                         the robot's Telemetry fields
      {"type": "safety", "armed", "text", "holder", "cap", "blocked", "code"}
      {"type": "link", "rtt": S | null, "loss": 0..1}    the call's heartbeats, every 0.5 s
      {"type": "connection", "state": "connected" | "reconnecting" | "reconnected"
       | "ended", "detail", "seconds"}                   the call to the robot dropped /
                                                         came back (seconds of outage) /
                                                         ended for good
      {"type": "goal", "x", "y", "yaw", "status", "progress", "text", "code"}
      {"type": "plan", "seq", "goal", "points": [[x, y], ...]}   the robot's planned path
                                                         (map frame; [] when it has none)
      {"type": "places", "places": [{"name", "x", "y", "yaw"}, ...]}   named places
      {"type": "people", "seq", "t", "cams": {NAME: FOV_DEG}, "tracks": [{"id", "x", "y",
       "vx", "vy", "c", "src", "r", "b"}, ...]}           tracked people (5 Hz; the
                                                         robot's ``people`` message)
      {"type": "people_alert", "kind", "id", "text", "distance", "bearing"}   once each
      {"type": "chat", "id", "text", "ok", "final", "code"}   replies, to the page that asked
      {"type": "ack", "what": "stop" | "arm" | ..., "ok", "text", "code"}
      {"type": "pong", "t"}
      {"type": "roster", "users": [{"name", "role", "driving", "you"}, ...]}   on change
      {"type": "msg", "seq", "from", "kind": "user" | "robot", "text"}   the conference's
                                                         messages (the last 50 on opening)
      {"type": "said", "id", "ok", "text", "code"}     the answer to this page's say
      {"type": "drive_state", "seq", "active", "code", "text", "linear", "angular",
       "cap"}                                            the robot's drive_state (§27)
      binary: video frame = 4-byte big-endian header length, UTF-8 JSON header
              {"kind": "video", "codec", "key", "camera", "frame_id", "capture_time"},
              then the picture as the robot sent it (JPEG, H.264, VP8: never decoded or
              re-encoded here); the robot's voice the same way with {"kind": "audio",
              "seq", "capture_time"} and an Opus packet

    Media (both ways; :mod:`telebot.apps.web.media_relay`, docs/protocol.md §19.1)::

      page → client {"type": "media", "decode": [...], "encode": [...]} | {"type": "keyframe"}
                    binary: the user's camera / microphone, as above
      client → page {"type": "media", "send", "codec", "note"} | {"type": "keyframe_request"}

Video comes from the client's video feed (:class:`~telebot.services.video.receiver.VideoFeed`,
subscribed while a page is open), so after a reconnection the map, pose and video resume
on the page without a reload; a motion that was running at the drop is reported failed,
and the robot stays stopped until re-armed.

The map follows the robot's (:class:`telebot.followers.MapFollower`, as the Foxglove
bridge's): when telemetry's ``map_version`` differs from the version of the map held here,
it is fetched again, ``/map.png`` serves the new one and the pages get a new ``map``
message (they reload the image).

Safety: a ``stop`` is handed to :meth:`RobotClient.stop` at once (before anything else
the message loop does). When a page's websocket closes (tab closed, browser crashed: the
websocket heartbeat notices within 2 s) while the robot moves and this user may drive,
the client stops the robot (a stop with ``how`` ``tab_closed``). ``text`` is for people;
``code`` the robot's reason code (``docs/protocol.md`` §13.1).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import sys
import time
from collections.abc import Callable, Coroutine, Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any, assert_never

from aiohttp import web

from telebot.apps.web.media_relay import MAX_PAGE_MESSAGE, MediaRelay, pack_media, video_header
from telebot.apps.web.messages import (
    ROBOT_PAGE,
    Arm,
    Camera,
    Chat,
    Drive,
    Goal,
    Keyframe,
    MediaCaps,
    PageMessageError,
    Ping,
    ReleaseDrive,
    RequestId,
    Say,
    Stop,
    TakeDrive,
    parse_page_message,
)
from telebot.apps.web.pageserver import PageServer
from telebot.config import AppConfig
from telebot.errors import CallEnded, TelebotError
from telebot.followers import MapFollower
from telebot.reasons import Reason
from telebot.rights import Right, may
from telebot.services.client import ConnectionEvent, RobotClient
from telebot.services.conference.wire import Message, Roster, say_text
from telebot.services.drive.wire import DriveState
from telebot.services.mapxfer.user import MapDownload
from telebot.services.people.wire import PeopleAlertMessage
from telebot.services.plan.wire import Place, PlanUpdate
from telebot.services.safety.wire import SafetyAck, SafetyStatus
from telebot.services.status.wire import GoalUpdate, PoseUpdate
from telebot.services.video.wire import CompleteFrame

__all__ = ["WebUI", "serve_ui"]

log = logging.getLogger(__name__)

#: Seconds between websocket pings; a page silent for twice this is taken as gone.
WS_HEARTBEAT = 1.0
#: Seconds between link-quality messages to the pages.
LINK_EVERY = 0.5


def _now_ms() -> float:
    return time.time() * 1000.0


class _Page:
    """One open page: its websocket and what it asked for."""

    def __init__(self, ws: web.WebSocketResponse) -> None:
        self.ws = ws
        self.sends: set[asyncio.Task[None]] = set()
        #: The video frame being sent; a new frame skips the page while it is (latest wins).
        self.frame: asyncio.Task[None] | None = None
        self.frames_skipped = 0
        #: It drives by hand now (its last drive command was not a release).
        self.driving = False


class WebUI(PageServer):
    """The web UI of one call: ``async with WebUI(client, port=8080) as ui: print(ui.url)``.

    ``client`` is an already-connected :class:`RobotClient` (the caller owns it); ``user``
    is this user's name as the robot knows it (to tell whether we hold the drive).
    ``port`` 0 picks a free port. Every task is owned here and ends on exit.
    """

    def __init__(
        self,
        client: RobotClient,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        user: str = "",
        map_timeout: float = 120.0,
    ) -> None:
        super().__init__(host=host, port=port, owner="web UI")
        self.client = client
        self.user = user
        #: The robot's map, fetched again when it changes and across reconnections.
        self.maps = MapFollower(client, timeout=map_timeout)
        self.pages: set[_Page] = set()
        #: Stops sent because a page closed while the robot moved (for tests and logs).
        self.close_stops = 0
        self._goal: dict[str, Any] | None = None
        #: Unsubscribes from the client's video feed (set while a page is open).
        self._video: Callable[[], None] | None = None
        self._closing = False
        self._last_roster: dict[str, Any] | None = None
        #: The codecs the video feed was subscribed with (re-subscribed when they change).
        self._video_codecs: tuple[int, ...] = ()
        #: Camera, microphone and the robot's voice (media_relay.py).
        self.media: MediaRelay[_Page] = MediaRelay(self, client)
        #: The newest connection state as the pages get it.
        self.connection: dict[str, Any] = {
            "type": "connection",
            "state": "connected",
            "detail": "",
            "seconds": 0.0,
        }

    # -- lifecycle --------------------------------------------------------------------

    @property
    def may_drive(self) -> bool:
        """Whether this user's role may drive (observers may only watch and stop)."""
        return may(self.client.call.role, Right.DRIVE)

    def routes(self, router: web.UrlDispatcher) -> None:
        """The page, its map and its websocket."""
        router.add_get("/", self._index)
        router.add_get("/map.png", self._map_png)
        router.add_get("/ws", self._websocket)

    async def start(self) -> None:
        """Serve the page and start following the robot's streams."""
        await self.serve()
        self.follow()
        log.info("web UI for %s at %s", self.client.robot, self.url)

    async def handle(self, request: web.Request, path: str) -> web.StreamResponse:
        """Serve ``path`` of the page (``""``, ``map.png``, ``ws``) for a server that hosts
        several pages under prefixes (the fleet page's ``/robot/NAME/``: the page's URLs
        are relative); anything else is a 404."""
        handlers = {"": self._index, "map.png": self._map_png, "ws": self._websocket}
        handler = handlers.get(path)
        if handler is None:
            return web.Response(status=404, text=f"no such page: {path}")
        return await handler(request)

    def follow(self) -> None:
        """Start following the robot's streams (:meth:`start` does; a host that serves
        the page itself through :meth:`handle` calls it instead)."""
        self.client.on_connection.append(self._on_connection)
        self.client.conference.on_message.append(self._on_conference_message)
        self.client.conference.on_roster.append(self._on_roster)
        self.client.on_people_alert.append(self._on_people_alert)
        self.maps.on_map.append(self._on_map)
        self.maps.on_error.append(self._on_map_error)
        self.maps.start()
        pumps = (
            self._pump_pose,
            self._pump_telemetry,
            self._pump_safety,
            self._pump_plan,
            self._pump_places,
            self._pump_people,
            self._pump_drive,
        )
        for pump in pumps:
            self._tasks.spawn(pump())
        self._tasks.spawn(self._pump_link())

    async def close(self) -> None:
        """Close the pages and the server, end every task; idempotent."""
        if self._closing:
            return
        self._closing = True
        self.media.close()
        await self.maps.aclose()
        with contextlib.suppress(ValueError):
            self.client.on_connection.remove(self._on_connection)
        with contextlib.suppress(ValueError):
            self.client.conference.on_message.remove(self._on_conference_message)
        with contextlib.suppress(ValueError):
            self.client.conference.on_roster.remove(self._on_roster)
        with contextlib.suppress(ValueError):
            self.client.on_people_alert.remove(self._on_people_alert)
        if self._video is not None:
            self._video()
            self._video = None
        for page in list(self.pages):
            with contextlib.suppress(Exception):
                await page.ws.close()
        await self.stop_serving()

    # -- HTTP -------------------------------------------------------------------------

    async def _index(self, request: web.Request) -> web.StreamResponse:
        return self.html("index.html")

    async def _map_png(self, request: web.Request) -> web.StreamResponse:
        if (download := self.maps.map) is None:
            return web.Response(status=503, text="the map has not arrived yet")
        return web.Response(body=download.png, content_type="image/png")

    def _map_message(self) -> dict[str, Any] | None:
        if (download := self.maps.map) is None:
            return None
        return {
            "type": "map",
            "url": "map.png",  # relative: the page may live under a prefix (fleet page)
            "resolution": download.resolution,
            "origin_x": download.origin_x,
            "origin_y": download.origin_y,
            "width": download.width,
            "height": download.height,
            "version": download.version,
        }

    def _on_map(self, download: MapDownload) -> None:
        """A map arrived (the first, or the robot's changed one): the pages show it."""
        message = self._map_message()
        if message is not None:
            self._broadcast(message)

    def _on_map_error(self, exc: Exception) -> None:
        self._broadcast({"type": "error", "text": f"the map did not arrive: {exc}"})

    # -- websocket --------------------------------------------------------------------

    async def _websocket(self, request: web.Request) -> web.StreamResponse:
        ws = await self.accept(request, heartbeat=WS_HEARTBEAT, max_msg_size=MAX_PAGE_MESSAGE)
        page = _Page(ws)
        self.pages.add(page)
        self._video_wanted()
        self.media.page_opened(page)
        try:
            await self._greet(page)
            async for data in self.received(ws):
                if isinstance(data, str):
                    self._on_message(page, data)
                else:
                    self.media.on_binary(page, data)
        finally:
            self.pages.discard(page)
            if page.driving:  # gone while driving by hand: released now, not 0.55 s later
                self.client.drive(0.0, 0.0)
            self.media.page_closed(page)
            self._video_wanted()
            self._page_closed()
        return ws

    async def _greet(self, page: _Page) -> None:
        client = self.client
        await page.ws.send_json(
            {
                "type": "hello",
                "robot": client.robot,
                "user": self.user,
                "role": str(client.call.role),
                "may_drive": self.may_drive,
                "map": self._map_message(),
            }
        )
        # What the page would otherwise wait up to a second for.
        if (pose := client.latest_pose.value) is not None:
            await page.ws.send_json(self._pose_message(pose, _now_ms()))
        if (safety := client.latest_safety.value) is not None:
            await page.ws.send_json(self._safety_message(safety))
        if (telemetry := client.latest_telemetry.value) is not None:
            await page.ws.send_json({"type": "telemetry", **asdict(telemetry)})
        if self._goal is not None:
            await page.ws.send_json(self._goal)
        if (plan := client.plan) is not None:
            await page.ws.send_json(self._plan_message(plan))
        if client.places:
            await page.ws.send_json(self._places_message(client.places))
        await page.ws.send_json(self.connection)
        if (roster := client.conference.roster) is not None:
            await page.ws.send_json(self._roster_message(roster))
        for message in client.conference.messages[-50:]:  # what was said before it opened
            await page.ws.send_json(self._conference_message(message))

    @staticmethod
    def _roster_message(roster: Roster) -> dict[str, Any]:
        return {"type": "roster", "users": [asdict(member) for member in roster.users]}

    @staticmethod
    def _conference_message(message: Message) -> dict[str, Any]:
        return {
            "type": "msg",
            "seq": message.seq,
            "from": message.sender,
            "kind": message.kind,
            "text": message.text,
        }

    def _on_conference_message(self, message: Message) -> None:
        self._broadcast(self._conference_message(message))

    def _on_roster(self, roster: Roster) -> None:
        message = self._roster_message(roster)
        if message != self._last_roster:  # pushed every second: tell the pages changes only
            self._last_roster = message
            self._broadcast(message)

    async def _say(self, page: _Page, request_id: RequestId, text: str) -> None:
        try:
            said = await self.client.say(text)
        except (TimeoutError, TelebotError) as exc:
            text = "no answer" if isinstance(exc, TimeoutError) else str(exc)
            self.send(
                page, {"type": "said", "id": request_id, "ok": False, "text": text, "code": ""}
            )
            return
        self.send(
            page,
            {
                "type": "said",
                "id": request_id,
                "ok": said.ok,
                "text": said.text,
                "code": said.code,
            },
        )

    def _on_connection(self, event: ConnectionEvent) -> None:
        self.connection = {
            "type": "connection",
            "state": event.state,
            "detail": str(event) if event.state != "reconnected" else "",
            "seconds": round(event.seconds, 2),
        }
        self._broadcast(self.connection)

    def _on_message(self, page: _Page, text: str) -> None:
        try:
            msg = parse_page_message(text, ROBOT_PAGE)
        except PageMessageError as exc:
            if exc.kind == Drive.TYPE and page.driving:
                # Fail safe: a page that says nonsense while it drives stops driving.
                page.driving = False
                self.client.drive(0.0, 0.0)
            self.send(page, {"type": "error", "text": str(exc)})
            return
        match msg:
            case Stop(how=how):
                # First and without waiting: the stop's datagram leaves in this loop turn.
                self._tasks.spawn(self._safety(page, "stop", how))
            case Arm() | TakeDrive() | ReleaseDrive():
                self._tasks.spawn(self._safety(page, msg.TYPE))
            case Goal(x=x, y=y, yaw=yaw):
                if not self.may_drive:
                    self.send(page, {"type": "error", "text": "observers may not send goals"})
                else:
                    self._tasks.spawn(self._run_goal(x, y, yaw))
            case Drive(linear=linear, angular=angular):
                self._on_drive(page, linear, angular)
            case Chat(id=request_id, text=line):
                if (said := say_text(line)) is not None:  # "say …": to everyone in the call
                    self._tasks.spawn(self._say(page, request_id, said))
                else:
                    self._tasks.spawn(self._chat(page, request_id, line))
            case Say(id=request_id, text=line):
                self._tasks.spawn(self._say(page, request_id, line))
            case Camera(id=request_id, name=name):
                self._tasks.spawn(self._chat(page, request_id, name))
            case Ping(t=t):
                self.send(page, {"type": "pong", "t": t})
            case MediaCaps() | Keyframe():
                self.media.on_message(page, msg)
            case _:
                assert_never(msg)

    def _on_drive(self, page: _Page, linear: float, angular: float) -> None:
        """Drive by hand (§27): the page sends this at 20 Hz while its user holds a key,
        the gamepad's stick or the joystick, and zeros once on release."""
        if not self.may_drive:
            self.send(page, {"type": "error", "text": "observers may not drive"})
            return
        page.driving = linear != 0.0 or angular != 0.0
        self.client.drive(linear, angular)

    async def _run_goal(self, x: float, y: float, yaw: float | None) -> None:
        def update(status: GoalUpdate) -> None:
            self._goal = {
                "type": "goal",
                "x": x,
                "y": y,
                "yaw": yaw,
                "status": status.status,
                "progress": status.progress,
                "text": status.text,
                "code": status.code,
            }
            self._broadcast(self._goal)

        update(GoalUpdate(0, "sent"))
        try:
            final = await self.client.goto(x, y, yaw, on_update=update)
        except CallEnded as exc:
            update(GoalUpdate(0, "failed", text=str(exc), code=Reason.FAILED))
            return
        update(final)

    async def _safety(self, page: _Page, kind: str, how: str = "button") -> None:
        client = self.client
        actions: dict[str, Callable[[], Coroutine[Any, Any, SafetyAck]]] = {
            "stop": functools.partial(client.stop, how=how),
            "arm": client.arm,
            "take": client.take_drive,
            "release": client.release_drive,
        }
        try:
            ack = await actions[kind]()
        except (TimeoutError, TelebotError) as exc:
            text = "no answer" if isinstance(exc, TimeoutError) else str(exc)
            self.send(page, {"type": "ack", "what": kind, "ok": False, "text": text, "code": ""})
            return
        self.send(
            page,
            {"type": "ack", "what": kind, "ok": ack.ok, "text": ack.text, "code": ack.code},
        )

    async def _chat(self, page: _Page, request_id: RequestId, text: str) -> None:
        text = text.strip()
        if not text:
            return
        try:
            async for reply in self.client.chat_replies(text, timeout=600.0):
                self.send(
                    page,
                    {
                        "type": "chat",
                        "id": request_id,
                        "text": reply.text,
                        "ok": reply.ok,
                        "final": reply.final,
                        "code": reply.code,
                    },
                )
        except TimeoutError:
            self.send(
                page,
                {"type": "chat", "id": request_id, "text": "timed out", "ok": False, "final": True},
            )

    def moving(self) -> bool:
        """Whether the robot moves, by its latest pose."""
        pose = self.client.latest_pose.value
        if pose is None:
            return False
        return pose.v != 0.0 or pose.w != 0.0 or pose.state == "moving"

    def _page_closed(self) -> None:
        if self._closing or not self.may_drive:
            return
        goal_active = self._goal is not None and self._goal["status"] in ("sent", "active")
        safety = self.client.latest_safety.value
        # Fail safe: an armed robot may be about to move (a chat motion just sent, a goal
        # blocked behind a person that will clear); with nobody watching, it must not.
        armed = safety is not None and safety.armed
        pose = self.client.latest_pose.value
        blocked = pose is not None and pose.state == "blocked"
        if self.moving() or goal_active or armed or blocked:
            log.warning("a page closed while the robot moved: stopping it")
            self.close_stops += 1
            self._tasks.spawn(self.client.stop(how="tab_closed"))

    # -- sending ----------------------------------------------------------------------

    def send(self, page: _Page, message: dict[str, Any]) -> None:
        """A JSON text message to ``page`` (dropped if it closed)."""
        if page.ws.closed:
            return
        task = self._tasks.spawn(page.ws.send_str(json.dumps(message)))
        page.sends.add(task)
        task.add_done_callback(page.sends.discard)

    def _broadcast(self, message: dict[str, Any]) -> None:
        self.send_all([page.ws for page in self.pages], message)

    def broadcast_audio(self, data: bytes) -> None:
        """An audio packet to every page: small and in order (video skips a busy page)."""
        for page in list(self.pages):
            if not page.ws.closed and len(page.sends) < 32:
                task = self._tasks.spawn(page.ws.send_bytes(data))
                page.sends.add(task)
                task.add_done_callback(page.sends.discard)

    def _broadcast_bytes(self, data: bytes) -> None:
        for page in list(self.pages):
            if page.ws.closed:
                continue
            if page.frame is not None and not page.frame.done():
                page.frames_skipped += 1  # a slow page gets fewer frames, never a queue
                continue
            page.frame = self._tasks.spawn(page.ws.send_bytes(data))

    # -- streams ----------------------------------------------------------------------

    @staticmethod
    def _pose_message(pose: PoseUpdate, recv_ms: float) -> dict[str, Any]:
        return {
            "type": "pose",
            "x": pose.x,
            "y": pose.y,
            "yaw": pose.yaw,
            "v": pose.v,
            "w": pose.w,
            "state": pose.state,
            "detail": pose.detail,
            "goal": pose.goal,
            "t": pose.t,
            "recv": recv_ms,
        }

    async def _pump_pose(self) -> None:
        latest = self.client.latest_pose
        while True:
            pose = await latest.next()
            self._broadcast(self._pose_message(pose, _now_ms()))

    async def _pump_telemetry(self) -> None:
        latest = self.client.latest_telemetry
        while True:
            telemetry = await latest.next()
            self._broadcast({"type": "telemetry", **asdict(telemetry)})

    @staticmethod
    def _plan_message(plan: PlanUpdate) -> dict[str, Any]:
        return {
            "type": "plan",
            "seq": plan.seq,
            "goal": plan.goal,
            "points": [[x, y] for x, y in plan.points],
        }

    @staticmethod
    def _places_message(places: Mapping[str, Place]) -> dict[str, Any]:
        return {
            "type": "places",
            "places": [{"name": p.name, "x": p.x, "y": p.y, "yaw": p.yaw} for p in places.values()],
        }

    async def _pump_plan(self) -> None:
        latest = self.client.latest_plan
        while True:
            self._broadcast(self._plan_message(await latest.next()))

    async def _pump_places(self) -> None:
        latest = self.client.latest_places
        while True:
            self._broadcast(self._places_message(await latest.next()))

    async def _pump_people(self) -> None:
        latest = self.client.latest_people
        while True:
            update = await latest.next()
            self._broadcast(json.loads(update.encode()))

    def _on_people_alert(self, alert: PeopleAlertMessage) -> None:
        message = json.loads(alert.encode())
        message["type"] = "people_alert"
        self._broadcast(message)

    async def _pump_drive(self) -> None:
        latest = self.client.latest_drive
        while True:
            self._broadcast(self._drive_message(await latest.next()))

    @staticmethod
    def _safety_message(state: SafetyStatus) -> dict[str, Any]:
        return {
            "type": "safety",
            "armed": state.armed,
            "text": state.text,
            "code": state.code,
            "holder": state.holder,
            "cap": state.cap,
            "blocked": state.blocked,
        }

    @staticmethod
    def _drive_message(state: DriveState) -> dict[str, Any]:
        """The robot's drive_state (§27) for the pages: its code, and its words as ``text``."""
        return {
            "type": "drive_state",
            "seq": state.seq,
            "active": state.active,
            "code": state.code,
            "text": state.text,
            "linear": round(state.linear, 3),
            "angular": round(state.angular, 3),
            "cap": round(state.cap, 3),
        }

    async def _pump_safety(self) -> None:
        latest = self.client.latest_safety
        while True:
            self._broadcast(self._safety_message(await latest.next()))

    async def _pump_link(self) -> None:
        while True:
            stats = self.client.call.stats
            self._broadcast({"type": "link", "rtt": stats.rtt, "loss": stats.loss})
            await asyncio.sleep(LINK_EVERY)

    def _video_wanted(self) -> None:
        """Receive video while at least one page is open."""
        if self.pages and self._video is None and not self._closing:
            self._video_codecs = self.media.codecs()
            self._video = self.client.video_feed.subscribe(
                self._on_frame, codecs=self._video_codecs
            )
        elif not self.pages and self._video is not None:
            self._video()
            self._video = None

    def codecs_changed(self) -> None:
        """The pages may decode other codecs now: ask the robot again when the list changed."""
        if self._video is not None and self.media.codecs() != self._video_codecs:
            self._video()
            self._video = None
        self._video_wanted()

    def _on_frame(self, frame: CompleteFrame) -> None:
        self._broadcast_bytes(pack_media(video_header(frame), frame.data))


async def serve_ui(
    robot: str,
    *,
    home: Path,
    config: AppConfig,
    host: str = "127.0.0.1",
    port: int = 8080,
    stop: asyncio.Event | None = None,
    announce: Callable[[str], None] = print,
    record: Path | None = None,
) -> int:
    """``telebot-user ui``: call ``robot``, serve the page until Ctrl-C / SIGTERM.

    ``config`` is the user's :class:`~telebot.config.AppConfig`. The robot is stopped
    if the client exits while it moves. ``record``: an MCAP file of the call (``--record``).
    """
    from telebot.apps.common import EXIT_OK, stop_on_signals
    from telebot.apps.foxglove_bridge import recording
    from telebot.identity import Identity
    from telebot.services.client import connect

    stop = stop or asyncio.Event()
    user = Identity.load(home).name
    timeout = config.call.connect_timeout
    async with (
        connect(robot, home=home, config=config, timeout=timeout) as client,
        recording(client, record),
        WebUI(client, host=host, port=port, user=user) as ui,
    ):
        client.on_connection.append(lambda event: print(f"[{event}]", file=sys.stderr))
        announce(f"open {ui.url} in a browser (role {client.call.role}); Ctrl-C to quit")
        with stop_on_signals(stop):
            await stop.wait()
        if ui.may_drive and ui.moving():
            with contextlib.suppress(TelebotError, TimeoutError):
                await client.stop(how="exit", timeout=2.0)
    return EXIT_OK
