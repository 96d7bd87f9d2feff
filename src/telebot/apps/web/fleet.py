"""The fleet page (``telebot-user ui`` without a robot name): one user, many robots.

:class:`FleetUI` watches the robots' presence and lists every robot online. Presence shows
only a name and a public key, so everything else on the list (battery, state, who drives,
link quality, the user's role) comes from a **call**: the fleet page calls each robot
online whose key the user trusts (at most :data:`MAX_CALLS`), as ``telebot-user ui ROBOT``
would, and the robot's contact list decides as always (a robot that refuses says why on
the list; an unknown key is listed with no call). Such a *watch* call gives up a drive the
robot handed it on joining (the robot is latched stopped then, so this moves nothing):
watching a fleet must not keep the drive from other drivers. Opening a robot takes the
drive when it is free.

Opening a robot serves its page (the single-robot page, unchanged) under
``/robot/NAME/`` on this same server, on the robot's own call: each opened robot has its
own call, its own STOP, its own websocket; the fleet page shows them side by side in
frames. ``stop all`` stops every robot the user has a call with, all at once, and reports
each robot's answer; one that does not answer within :data:`STOP_ALL_TIMEOUT` is reported
and does not hold up the others.

Fleet websocket (``/fleet/ws``, JSON; docs/protocol.md §21). The page sends ``open``,
``close`` (``robot``: a name) and ``stop_all``, typed in :mod:`telebot.apps.web.messages`::

    server → page
      {"type": "hello", "user"}
      {"type": "fleet", "robots": [{"name", "online", "trusted", "called", "open",
        "url", "role", "battery", "battery_low", "state", "armed", "holder", "rtt",
        "loss", "connection", "problem"}, ...]}         on change and every 0.5 s
      {"type": "opened", "robot", "url"} | {"type": "closed", "robot"}
      {"type": "stopped", "robot", "ok", "text"}         each robot's answer to stop all
      {"type": "stop_all", "results": [{"robot", "ok", "text"}, ...]}
      {"type": "error", "text"}                          a one-line reason
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, assert_never

from aiohttp import web

from telebot.apps.web.messages import (
    FLEET_PAGE,
    CloseRobot,
    OpenRobot,
    PageMessageError,
    StopAll,
    parse_page_message,
)
from telebot.apps.web.pageserver import STATIC, PageServer
from telebot.apps.web.server import WS_HEARTBEAT, WebUI
from telebot.channels.call import UserEndpoint
from telebot.channels.proto.frames import validate_name
from telebot.channels.transports.base import Subscription
from telebot.config import AppConfig, ReconnectSettings
from telebot.errors import CallRejected, TelebotError
from telebot.identity import decode_key
from telebot.rights import Right, may
from telebot.services.client import ConnectionEvent, RobotClient

__all__ = ["LIST_EVERY", "MAX_CALLS", "STOP_ALL_TIMEOUT", "FleetRobot", "FleetUI", "serve_fleet"]

log = logging.getLogger(__name__)

#: A robot that has not acknowledged ``stop all`` within this long (s) is reported.
STOP_ALL_TIMEOUT = 2.0
#: The robot list goes to the fleet pages this often (s).
LIST_EVERY = 0.5
#: Robots the fleet page calls at most (more are listed by name only).
MAX_CALLS = 32
#: Seconds to wait for a robot to answer a call.
CALL_TIMEOUT = 10.0


@dataclass
class FleetRobot:
    """One robot of the fleet page: what presence says, and the call if there is one."""

    name: str
    online: bool = False
    trusted: bool = False
    client: RobotClient | None = None
    ui: WebUI | None = None
    #: Why there is no call (refused, unknown key, ended), one line; "" when fine.
    problem: str = ""
    #: The user opened it: open it again on the next call if this one ends.
    wanted: bool = False
    calling: asyncio.Task[None] | None = field(default=None, repr=False)

    @property
    def url(self) -> str:
        """Where the robot's own page is, relative to the fleet page."""
        return f"robot/{self.name}/"

    def summary(self) -> dict[str, Any]:
        """The robot as the fleet list shows it (what presence and the call tell)."""
        client = self.client
        row: dict[str, Any] = {
            "name": self.name,
            "online": self.online,
            "trusted": self.trusted,
            "called": client is not None,
            "open": self.ui is not None,
            "url": self.url,
            "problem": self.problem,
            "role": None,
            "battery": None,
            "battery_low": False,
            "state": None,
            "armed": None,
            "holder": None,
            "rtt": None,
            "loss": None,
            "connection": None,
        }
        if client is None:
            return row
        row["role"] = str(client.call.role) if client.call.role is not None else None
        if (telemetry := client.latest_telemetry.value) is not None:
            row["battery"] = round(telemetry.battery, 1)
            row["battery_low"] = telemetry.battery_low
            row["state"] = telemetry.state
        if (pose := client.latest_pose.value) is not None:
            row["state"] = pose.state
        if (safety := client.latest_safety.value) is not None:
            row["armed"] = safety.armed
            row["holder"] = safety.holder
        stats = client.call.stats
        row["rtt"] = stats.rtt
        row["loss"] = stats.loss
        event = client.latest_connection.value
        row["connection"] = str(event) if event is not None else "connected"
        if event is not None and event.state == "reconnected":
            row["connection"] = "connected"
        return row


class FleetUI(PageServer):
    """The fleet page: ``async with FleetUI(endpoint, port=8080) as fleet: print(fleet.url)``.

    ``endpoint`` is the user's open :class:`~telebot.channels.call.UserEndpoint` (the caller
    owns it); every call made here is hung up on exit. ``user``: this user's name as robots
    know it. ``reconnect``: how each robot's client calls again after a drop.
    """

    def __init__(
        self,
        endpoint: UserEndpoint,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        user: str = "",
        reconnect: ReconnectSettings | None = None,
        call_timeout: float = CALL_TIMEOUT,
        max_calls: int = MAX_CALLS,
        stop_timeout: float = STOP_ALL_TIMEOUT,
        watch: bool = True,
    ) -> None:
        super().__init__(host=host, port=port, owner="fleet")
        self.endpoint = endpoint
        self.user = user or endpoint.identity.name
        self.reconnect = reconnect if reconnect is not None else ReconnectSettings()
        self.call_timeout = call_timeout
        self.max_calls = max_calls
        self.stop_timeout = stop_timeout
        #: Call every trusted robot online (False: only those opened; see FleetSettings).
        self.watch = watch
        #: Every robot seen online (or called), by name.
        self.robots: dict[str, FleetRobot] = {}
        self.pages: set[web.WebSocketResponse] = set()
        self._watch: Subscription | None = None
        self._closing = False
        self._prefix = f"{endpoint.namespace}/presence/robot/"

    # -- lifecycle --------------------------------------------------------------------

    def routes(self, router: web.UrlDispatcher) -> None:
        """The fleet page, its websocket and each opened robot's page."""
        router.add_get("/", self._index)
        router.add_get("/fleet/ws", self._websocket)
        router.add_get("/robot/{name}", self._robot_bare)
        router.add_get("/robot/{name}/{tail:.*}", self._robot_page)

    async def start(self) -> None:
        """Serve the page and start watching presence."""
        await self.serve()
        self._watch = self.endpoint.transport.watch_presence(
            f"{self._prefix}*/*", self._on_presence
        )
        self._tasks.spawn(self._pump_list())
        log.info("fleet page at %s", self.url)

    async def close(self) -> None:
        """Close the pages, hang up every call, end every task; idempotent."""
        if self._closing:
            return
        self._closing = True
        if self._watch is not None:
            self._watch.close()
        for ws in list(self.pages):
            with contextlib.suppress(Exception):
                await ws.close()
        for robot in self.robots.values():
            if robot.calling is not None:
                robot.calling.cancel()
            if robot.ui is not None:
                await robot.ui.close()
                robot.ui = None
            if robot.client is not None:
                await _hang_up(robot.client)
                robot.client = None
        await self.stop_serving()

    # -- presence and calls -----------------------------------------------------------

    def _on_presence(self, key: str, alive: bool) -> None:
        name, _, key_text = key.removeprefix(self._prefix).partition("/")
        try:
            validate_name(name)
            public_key = decode_key(key_text)
        except ValueError:
            return  # not a telebot robot's token
        if self._closing:
            return
        robot = self.robots.get(name)
        if robot is None:
            robot = self.robots[name] = FleetRobot(name)
        robot.online = alive
        if not alive:
            return
        known = self.endpoint.known_robots.get(name)
        robot.trusted = known == public_key
        if known is None:
            robot.problem = f"unknown robot: add its key with 'telebot-user known add {name}'"
        elif not robot.trusted:
            robot.problem = "KEY MISMATCH: online with another key than the one you trust"
        elif robot.client is None and robot.calling is None and (self.watch or robot.wanted):
            if sum(r.client is not None for r in self.robots.values()) >= self.max_calls:
                robot.problem = f"not called: the fleet page calls at most {self.max_calls}"
                return
            robot.calling = self._tasks.spawn(self._call(robot))

    async def _call(self, robot: FleetRobot) -> None:
        try:
            call = await self.endpoint.call(robot.name, timeout=self.call_timeout)
        except CallRejected as exc:
            robot.problem = f"refused the call: {exc}"
            return
        except (TelebotError, TimeoutError) as exc:
            robot.problem = str(exc) or "did not answer"
            return
        finally:
            robot.calling = None
        if self._closing:
            call.hangup_now("fleet page closed")
            return
        client = RobotClient(call)
        client.start(self.endpoint, self.reconnect)
        robot.client = client
        robot.problem = ""

        def on_connection(event: ConnectionEvent) -> None:
            self._on_connection(robot, client, event)

        client.on_connection.append(on_connection)
        if robot.wanted:  # it was open when its last call ended: open it again
            await self.open(robot.name)
        else:
            await self._watch_only(robot, client)
        self._broadcast_list()

    def _on_connection(
        self, robot: FleetRobot, client: RobotClient, event: ConnectionEvent
    ) -> None:
        if event.state == "reconnected" and robot.ui is None:
            self._tasks.spawn(self._watch_only(robot, client))
        if event.state != "ended" or robot.client is not client or self._closing:
            return
        # No more calls on this client: the robot left, refused or we gave up. A new call
        # is made when its presence comes back.
        robot.problem = event.detail or "the call ended"
        robot.client = None
        ui, robot.ui = robot.ui, None
        self._tasks.spawn(self._retire(ui, client))
        if (
            robot.online
            and robot.trusted
            and robot.calling is None
            and (self.watch or robot.wanted)
        ):
            robot.calling = self._tasks.spawn(self._call(robot))

    async def _retire(self, ui: WebUI | None, client: RobotClient) -> None:
        if ui is not None:
            await ui.close()
        await client.aclose()

    async def _watch_only(self, robot: FleetRobot, client: RobotClient) -> None:
        """Give up a drive the robot handed this watch call on joining (see module doc)."""
        with contextlib.suppress(TimeoutError, TelebotError):
            safety = client.latest_safety.value
            if safety is None:
                async with asyncio.timeout(3.0):
                    safety = await client.latest_safety.next()
            if safety.holder == self.user and robot.ui is None:
                await client.release_drive(timeout=3.0)

    # -- open and close ---------------------------------------------------------------

    def problem_of(self, name: str) -> str | None:
        """Why robot ``name`` cannot be opened now (None: it can)."""
        try:
            validate_name(name, "robot name")
        except ValueError as exc:
            return str(exc)
        robot = self.robots.get(name)
        if robot is None or (not robot.online and robot.client is None):
            return f"no robot named {name!r} is online"
        if robot.client is None and (self.watch or robot.calling is not None or not robot.trusted):
            return f"{name}: {robot.problem or 'calling…'}"
        return None

    async def open(self, name: str) -> str | None:
        """Open robot ``name``'s page; None, or why it cannot be opened (one line)."""
        problem = self.problem_of(name)
        if problem is not None:
            return problem
        robot = self.robots[name]
        robot.wanted = True
        if robot.client is None:  # not watched: call it now (it opens when the call is up)
            robot.problem = ""
            robot.calling = self._tasks.spawn(self._call(robot))
            await asyncio.shield(robot.calling)
            return None if robot.client is not None else f"{name}: {robot.problem}"
        client = robot.client
        if robot.ui is None:
            ui = WebUI(client, host=self.host, port=self.port, user=self.user)
            ui.follow()
            robot.ui = ui
            # Opening means driving: take the drive if nobody holds it.
            safety = client.latest_safety.value
            if may(client.call.role, Right.DRIVE) and (safety is None or safety.holder is None):
                with contextlib.suppress(TimeoutError, TelebotError):
                    await client.take_drive(timeout=3.0)
        self._broadcast({"type": "opened", "robot": name, "url": robot.url})
        self._broadcast_list()
        return None

    async def close_robot(self, name: str) -> None:
        """Close robot ``name``'s page (its call stays: it is still listed); a robot that
        moves or is armed is stopped first."""
        robot = self.robots.get(name)
        if robot is None:
            return
        robot.wanted = False
        ui, robot.ui = robot.ui, None
        if ui is not None:
            # As when a robot's page closes (WebUI): a robot that may move with nobody
            # watching it any more is stopped first.
            safety = ui.client.latest_safety.value
            if ui.may_drive and (ui.moving() or (safety is not None and safety.armed)):
                log.warning("%s closed while it might move: stopping it", name)
                with contextlib.suppress(TimeoutError, TelebotError):
                    await ui.client.stop(how="tab_closed", timeout=self.stop_timeout)
            await ui.close()
        self._broadcast({"type": "closed", "robot": name})
        self._broadcast_list()

    # -- stop all ---------------------------------------------------------------------

    async def stop_all(self) -> list[dict[str, Any]]:
        """Stop every robot with a call, all at once; each robot's answer, by name.

        A robot that does not acknowledge within ``stop_timeout`` is reported as not
        answering; the others are not held up by it.
        """
        targets = [
            (name, robot.client)
            for name, robot in sorted(self.robots.items())
            if robot.client is not None and not robot.client.finished
        ]

        async def one(name: str, client: RobotClient) -> dict[str, Any]:
            try:
                ack = await client.stop(how="button", timeout=self.stop_timeout)
            except TimeoutError:
                text = f"did not answer within {self.stop_timeout:g} s"
                result = {"robot": name, "ok": False, "text": text}
            except TelebotError as exc:  # the call dropped under the stop, or has ended
                result = {"robot": name, "ok": False, "text": f"did not answer: {exc}"}
            except Exception as exc:  # anything else: still report it, never lose the others
                log.exception("stop all: %s", name)
                result = {"robot": name, "ok": False, "text": f"stop failed: {exc}"}
            else:
                result = {"robot": name, "ok": ack.ok, "text": ack.text or "stopped"}
            self._broadcast({"type": "stopped", **result})
            return result

        results = list(await asyncio.gather(*(one(name, c) for name, c in targets)))
        for result in results:
            if not result["ok"]:
                log.warning("stop all: %s %s", result["robot"], result["text"])
        self._broadcast({"type": "stop_all", "results": results})
        return results

    # -- HTTP -------------------------------------------------------------------------

    async def _index(self, request: web.Request) -> web.StreamResponse:
        return self.html("fleet.html")

    async def _robot_bare(self, request: web.Request) -> web.StreamResponse:
        # The page's URLs are relative: it must be at ".../NAME/", with the slash.
        raise web.HTTPFound(f"/robot/{request.match_info['name']}/")

    async def _robot_page(self, request: web.Request) -> web.StreamResponse:
        name, tail = request.match_info["name"], request.match_info["tail"]
        if tail.startswith("static/"):
            return _static_file(tail.removeprefix("static/"))
        problem = self.problem_of(name)
        if problem is None and tail == "":
            problem = await self.open(name)  # a robot's address opens it
        robot = self.robots.get(name)
        if problem is not None or robot is None or robot.ui is None:
            text = problem or f"{name} is not open: open it on the fleet page"
            return web.Response(status=404, text=text + "\n", content_type="text/plain")
        return await robot.ui.handle(request, tail)

    async def _websocket(self, request: web.Request) -> web.StreamResponse:
        ws = await self.accept(request, heartbeat=WS_HEARTBEAT, max_msg_size=1 << 16)
        self.pages.add(ws)
        try:
            await ws.send_json({"type": "hello", "user": self.user})
            await ws.send_json(self._list())
            async for data in self.received(ws):
                if isinstance(data, str):
                    self._on_message(ws, data)
                else:
                    self._send(ws, {"type": "error", "text": "the fleet page sends no binary"})
        finally:
            self.pages.discard(ws)
        return ws

    def _on_message(self, ws: web.WebSocketResponse, text: str) -> None:
        try:
            msg = parse_page_message(text, FLEET_PAGE)
        except PageMessageError as exc:
            self._send(ws, {"type": "error", "text": str(exc)})
            return
        match msg:
            case StopAll():
                self._tasks.spawn(self.stop_all())  # first, without waiting for anything else
            case OpenRobot(robot=name):
                self._tasks.spawn(self._open_for(ws, name))
            case CloseRobot(robot=name):
                self._tasks.spawn(self.close_robot(name))
            case _:
                assert_never(msg)

    async def _open_for(self, ws: web.WebSocketResponse, name: str) -> None:
        problem = await self.open(name)
        if problem is not None:
            self._send(ws, {"type": "error", "text": f"cannot open {name}: {problem}"})

    # -- sending ----------------------------------------------------------------------

    def _list(self) -> dict[str, Any]:
        return {
            "type": "fleet",
            "robots": [robot.summary() for _, robot in sorted(self.robots.items())],
        }

    def _broadcast_list(self) -> None:
        self._broadcast(self._list())

    def _send(self, ws: web.WebSocketResponse, message: dict[str, Any]) -> None:
        self.send_json(ws, message)

    def _broadcast(self, message: dict[str, Any]) -> None:
        self.send_all(list(self.pages), message)

    async def _pump_list(self) -> None:
        while True:
            await asyncio.sleep(LIST_EVERY)
            if self.pages:
                self._broadcast_list()


def _static_file(name: str) -> web.StreamResponse:
    """A file of ``static/`` by its plain name (no folders: nothing else is served)."""
    if "/" in name or "\\" in name or name.startswith("."):
        return web.Response(status=404, text="no such file\n")
    path = Path(str(STATIC)) / name
    if not path.is_file():
        return web.Response(status=404, text="no such file\n")
    return web.FileResponse(path)


async def _hang_up(client: RobotClient) -> None:
    client._closing = True  # no reconnection after this hang-up
    with contextlib.suppress(TelebotError):
        await client.call.hangup()
    await client.aclose()


async def serve_fleet(
    *,
    home: Path,
    config: AppConfig,
    host: str = "127.0.0.1",
    port: int = 8080,
    stop: asyncio.Event | None = None,
    announce: Callable[[str], None] = print,
) -> int:
    """``telebot-user ui`` without a robot: serve the fleet page until Ctrl-C / SIGTERM.

    Robots opened on the page that still move when the client exits are stopped.
    """
    from telebot.apps.common import EXIT_OK, stop_on_signals
    from telebot.channels.transports import create_transport
    from telebot.identity import Identity, KnownRobots

    stop = stop or asyncio.Event()
    identity = Identity.load(home)
    known = KnownRobots.load(home)
    async with (
        create_transport(config.transport) as transport,
        UserEndpoint(
            transport, identity, known, settings=config.call, namespace=config.namespace
        ) as endpoint,
        FleetUI(
            endpoint,
            host=host,
            port=port,
            user=identity.name,
            reconnect=config.reconnect,
            call_timeout=config.call.connect_timeout or CALL_TIMEOUT,
            max_calls=config.fleet.max_calls,
            stop_timeout=config.fleet.stop_timeout,
            watch=config.fleet.watch,
        ) as fleet,
    ):
        announce(f"open {fleet.url} in a browser (the fleet page); Ctrl-C to quit")
        with stop_on_signals(stop):
            await stop.wait()
        moving = [
            r.client
            for r in fleet.robots.values()
            if r.ui is not None and r.client is not None and r.ui.may_drive and r.ui.moving()
        ]
        for client in moving:
            print(f"[stopping {client.robot}: it moves]", file=sys.stderr)
        await asyncio.gather(
            *(c.stop(how="exit", timeout=2.0) for c in moving), return_exceptions=True
        )
    return EXIT_OK
