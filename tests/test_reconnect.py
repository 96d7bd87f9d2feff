"""Calls come back by themselves: a user client calls the robot again after a drop.

In this process on the memory hub (the link cut for 2 s and healed), and over zenoh with
the robot daemon in its own process and the user reaching it through a TCP proxy that is
stopped and started again. Every test checks the safety side too: the robot latched
stopped at the drop, stays so after the reconnection, and the old goal is never resumed.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import random
import signal
import uuid
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from conftest import ROBOT, USER, wait_until
from loopback_proxy import TcpProxy
from rig import REAL_TIMEOUT, SLACK, Daemon
from rig import robot_on_hub as rig_robot_on_hub
from telebot.apps.user_client import chat_session
from telebot.apps.web.server import WebUI
from telebot.channels.call import Call, RobotEndpoint
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import (
    AppConfig,
    MemorySettings,
    ReconnectSettings,
    ServiceSettings,
    TransportSettings,
)
from telebot.errors import CallEnded
from telebot.robot.nav import Velocity
from telebot.robot.sim.stack import SimNavStack
from telebot.services.base import ServiceRegistry
from telebot.services.client import ConnectionEvent, RobotClient, backoff_delay, connect
from telebot.services.robot import RobotServer
from telebot.services.safety.robot import SafetyDriver
from telebot.services.video.wire import VideoSettings

#: How long the link stays cut (the issue's Wi-Fi blip).
OUTAGE = 2.0
FAST = ReconnectSettings(base=0.05, cap=0.5)


@dataclass
class Rig:
    """A simulated robot served on a memory hub, and a user connected with ``connect``."""

    hub: MemoryHub
    nav: SimNavStack
    safety: SafetyDriver
    server: RobotServer
    endpoint: RobotEndpoint
    client: RobotClient
    events: list[tuple[float, ConnectionEvent]] = field(default_factory=list)

    def moving(self) -> bool:
        return self.nav.velocity() != Velocity()


def robot_on_hub(
    base: Path, hub: MemoryHub, robot_services: ServiceRegistry[RobotServer] | None = None
) -> contextlib.AbstractAsyncContextManager[
    tuple[SimNavStack, SafetyDriver, RobotServer, RobotEndpoint]
]:
    """The rig's small-map robot on ``hub`` with the product's call timeout (the drops are
    what this file is about), poses at 20 Hz and a small video."""
    return rig_robot_on_hub(
        base,
        hub,
        robot_services,
        timeout=REAL_TIMEOUT,
        services=ServiceSettings(pose_hz=20.0),
        video=VideoSettings(width=160, height=120, max_fps=10, quality=60, min_quality=30),
    )


@contextlib.asynccontextmanager
async def rig(
    base: Path,
    *,
    robot_services: ServiceRegistry[RobotServer] | None = None,
    user_services: ServiceRegistry[RobotClient] | None = None,
) -> AsyncIterator[Rig]:
    hub = MemoryHub(seed=3)
    async with (
        robot_on_hub(base, hub, robot_services) as (nav, safety, server, endpoint),
        MemoryTransport(hub, "user") as transport,
        connect(
            ROBOT,
            home=base / "user",
            config=AppConfig(reconnect=FAST),
            transport=transport,
            services=user_services,
        ) as client,
    ):
        loop = asyncio.get_running_loop()
        rig = Rig(hub, nav, safety, server, endpoint, client)
        client.on_connection.append(lambda event: rig.events.append((loop.time(), event)))
        yield rig
        hub.heal("robot", "user")  # let the hang-up through


def times(rig: Rig, state: str) -> list[float]:
    return [t for t, event in rig.events if event.state == state]


async def blip(hub: MemoryHub, seconds: float = OUTAGE) -> float:
    """Cut the link both ways for ``seconds`` (the scenario's length, not a wait for
    something to happen); returns the loop time of the heal."""
    hub.cut("robot", "user")
    await asyncio.sleep(seconds)
    hub.heal("robot", "user")
    return asyncio.get_running_loop().time()


async def test_a_dropped_call_comes_back_with_its_streams_and_the_robot_stays_stopped(
    tmp_path: Path,
) -> None:
    async with rig(tmp_path) as r:
        client, loop = r.client, asyncio.get_running_loop()
        assert (await client.arm()).ok
        poses: list[float] = []  # loop times of the poses one `async for` got

        async def follow() -> None:
            async for _ in client.poses():
                poses.append(loop.time())

        follower = asyncio.create_task(follow())
        goal = asyncio.create_task(client.goto(9.5, 4.0))  # room-b, across the map
        await wait_until(r.moving)
        first = client.call
        outage = asyncio.create_task(blip(r.hub))
        # The drop: the goal in flight fails here, the robot stops and latches.
        with pytest.raises(CallEnded):
            await asyncio.wait_for(goal, 5 + SLACK)
        await wait_until(lambda: bool(times(r, "reconnecting")))
        await wait_until(lambda: not r.safety.state().armed and not r.moving())
        assert r.nav.current_goal() is None
        healed = await outage
        await wait_until(lambda: bool(times(r, "reconnected")), timeout=10)
        await wait_until(lambda: any(t > healed for t in poses), timeout=10)
        back = next(t for t in poses if t > healed)
        # The issue asks for a pose within 1 s of the heal; SLACK more for a loaded machine.
        assert back - healed < 1.0 + SLACK, f"first pose {back - healed:.2f} s after the heal"
        assert client.call is not first and client.call.active and client.reconnects == 1
        event = next(e for _, e in r.events if e.state == "reconnected")
        assert str(event).startswith("reconnected after ") and event.seconds > OUTAGE / 2
        assert not follower.done()  # the library user's `async for` went on
        # Still stopped: the robot says so on the new call, and the goal was not resumed.
        await wait_until(
            lambda: client.latest_safety.value is not None and not client.latest_safety.value.armed
        )
        status = await client.pose()
        assert status.goal is None and not r.moving() and not r.safety.state().armed
        # No ghost: the robot serves exactly the new call.
        assert [call.id for call in r.endpoint.calls] == [client.call.id]
        assert list(r.server.open) == [client.call.id] and list(r.server.services) == [
            client.call.id
        ]
        # The driver re-arms deliberately, and requests work on the new call.
        assert (await client.arm()).ok
        assert r.nav.current_goal() is None
        assert (await client.chat("where?")).ok
        # The others heard the drop, then one reconnection (not a new user joining).
        back = f"{USER} reconnected (driver)"
        await wait_until(lambda: (ROBOT, "robot", back) in _said(client))
        news = [text for _, _, text in _said(client) if text.startswith(f"{USER} ")]
        assert [text for text in news if not text.endswith(" the drive")][-2:] == [
            f"{USER} left",
            back,
        ]
        follower.cancel()
        await asyncio.gather(follower, return_exceptions=True)


#: The robot's call timeout in the test below: the old call lingers on the robot long
#: after the user's side dropped it (the issue saw 0.4 s; here the window cannot close
#: before the new call comes, however slow the machine).
LINGER = 8.0


async def test_a_call_back_before_the_robot_saw_the_drop_replaces_it_with_its_drive(
    tmp_path: Path,
) -> None:
    hub = MemoryHub(seed=3)
    async with (
        rig_robot_on_hub(tmp_path, hub, timeout=LINGER) as (nav, safety, server, endpoint),
        MemoryTransport(hub, "user") as transport,
        connect(
            ROBOT, home=tmp_path / "user", config=AppConfig(reconnect=FAST), transport=transport
        ) as client,
    ):
        events: list[ConnectionEvent] = []
        client.on_connection.append(events.append)
        await wait_until(lambda: client.conference.roster is not None)
        assert (await client.arm()).ok
        goal = asyncio.create_task(client.goto(9.5, 4.0))
        await wait_until(lambda: nav.velocity() != Velocity())
        first = client.call
        # The link fails one way: the user hears nothing more and drops its call at once
        # (the robot's presence is gone), while the robot still has the old call.
        hub.link("robot", "user").up = False
        with pytest.raises(CallEnded):
            await asyncio.wait_for(goal, 5 + SLACK)
        await wait_until(lambda: any(e.state == "reconnecting" for e in events))
        assert first.id in [call.id for call in endpoint.calls]  # not dropped on the robot
        hub.link("robot", "user").up = True
        await wait_until(lambda: client.reconnects == 1)
        # The new call took the old one's place, with its drive: the robot stopped and
        # latched at once (it was moving on a link that is gone), and the old call is gone.
        await wait_until(lambda: safety.state().holder_call == client.call.id)
        state = safety.state()
        assert not state.armed and state.holder == USER
        assert state.text == f"driver {USER} called again (the old call is replaced)"
        await wait_until(lambda: nav.velocity() == Velocity())
        assert nav.current_goal() is None  # cancelled, not resumed
        await wait_until(lambda: [call.id for call in endpoint.calls] == [client.call.id])
        assert list(server.open) == [client.call.id]
        # Everyone hears one reconnection; the roster lists the user once, driving.
        back = (ROBOT, "robot", f"{USER} reconnected (driver)")
        await wait_until(lambda: back in _said(client))
        await wait_until(lambda: _roster(client) == [(USER, "driver", True, True)])
        # The driver gets the robot back with a deliberate arm.
        assert (await client.arm()).ok
        goal = asyncio.create_task(client.goto(9.5, 4.0))
        await wait_until(lambda: nav.velocity() != Velocity())
        assert (await client.stop()).ok
        await asyncio.gather(goal, return_exceptions=True)
        # No "left" for the replaced call, then or later.
        assert not any(text.endswith(" left") for _, _, text in _said(client))


def _said(client: RobotClient) -> list[tuple[str, str, str]]:
    return [(m.sender, m.kind, m.text) for m in client.conference.messages]


def _roster(client: RobotClient) -> list[tuple[str, str, bool, bool]]:
    roster = client.conference.roster
    return [] if roster is None else [(m.name, m.role, m.driving, m.you) for m in roster.users]


async def drain(iterator: AsyncIterator[Any]) -> None:
    """Read ``iterator`` until it raises (within 5 s)."""
    async with asyncio.timeout(5):
        while True:
            await anext(iterator)


async def test_a_hangup_is_not_redialled_and_iterators_end(tmp_path: Path) -> None:
    async with rig(tmp_path) as r:
        poses = r.client.poses()
        await anext(poses)
        robot_call = r.endpoint.calls[0]
        await robot_call.hangup("robot going home")
        with pytest.raises(CallEnded):
            await drain(poses)
        assert r.client.finished and r.client.reconnects == 0
        assert [e.state for _, e in r.events] == ["ended"]


async def test_reconnection_off_ends_the_client_at_the_drop(tmp_path: Path) -> None:
    hub = MemoryHub(seed=4)
    async with (
        robot_on_hub(tmp_path, hub),
        MemoryTransport(hub, "user") as transport,
        connect(ROBOT, home=tmp_path / "user", transport=transport, reconnect=False) as client,
    ):
        hub.cut("robot", "user")
        end = await asyncio.wait_for(client.wait_finished(), 5 + SLACK)
        assert end.kind == "dropped"
        hub.heal("robot", "user")
        with pytest.raises(CallEnded):
            await client.pose()
        assert client.reconnects == 0


async def test_a_robot_that_refuses_the_new_call_ends_the_client(tmp_path: Path) -> None:
    async with rig(tmp_path) as r:
        r.hub.cut("robot", "user")
        await wait_until(lambda: bool(times(r, "reconnecting")))
        assert r.endpoint.contacts.remove(USER)  # the admin took alice off meanwhile
        r.hub.heal("robot", "user")
        end = await asyncio.wait_for(r.client.wait_finished(), 10)
        assert end.kind == "dropped" and r.client.reconnects == 0
        last = r.events[-1][1]
        assert last.state == "ended" and "not in the contact list" in last.detail
        with pytest.raises(CallEnded):
            await r.client.chat("where?")


def test_the_back_off_doubles_up_to_its_cap_with_jitter() -> None:
    settings = ReconnectSettings(base=0.1, cap=2.0)
    rng = random.Random(1)
    for attempt, ceiling in [(0, 0.1), (1, 0.2), (3, 0.8), (5, 2.0), (60, 2.0)]:
        delays = [backoff_delay(attempt, settings, rng) for _ in range(200)]
        assert all(ceiling / 2 <= d <= ceiling for d in delays), attempt
        assert max(delays) - min(delays) > ceiling / 4  # jittered, not in step


# -- the service seam: a toy service on both sides ------------------------------------------


@dataclass
class ToyLog:
    """What the toy services saw: (side, what, call id)."""

    entries: list[tuple[str, str, str]] = field(default_factory=list)
    ticks: dict[str, int] = field(default_factory=dict)

    def of(self, side: str, what: str) -> list[str]:
        return [call for s, w, call in self.entries if s == side and w == what]


class Toy:
    """A service that echoes on the robot and counts on the user's side."""

    def __init__(self, log: ToyLog, side: str, call: Call) -> None:
        self.log, self.side, self.call = log, side, call
        self.channel = call.channel("toy")
        self.heard: list[str | bytes] = []
        self.channel.set_callback(self._on_datagram)
        log.entries.append((side, "open", call.id))

    def _on_datagram(self, datagram: Any) -> None:
        self.heard.append(datagram.payload)
        if self.side == "robot":
            self.channel.send(b"echo:" + bytes(datagram.payload))

    def tick(self, now: float) -> None:
        self.log.ticks[self.call.id + self.side] = (
            self.log.ticks.get(self.call.id + self.side, 0) + 1
        )

    def close(self) -> None:
        self.log.entries.append((self.side, "close", self.call.id))


async def test_a_registered_service_opens_ticks_closes_and_reopens_with_the_call(
    tmp_path: Path,
) -> None:
    from telebot.services import registry

    log = ToyLog()
    robot_services = registry.robot_services()
    robot_services.register("toy", lambda server, call: Toy(log, "robot", call))
    user_services = registry.user_services()
    user_services.register("toy", lambda client, call: Toy(log, "user", call))
    async with rig(tmp_path, robot_services=robot_services, user_services=user_services) as r:
        first = r.client.call.id
        assert log.of("robot", "open") == log.of("user", "open") == [first]
        await wait_until(lambda: log.ticks.get(first + "robot", 0) > 2)
        await wait_until(lambda: log.ticks.get(first + "user", 0) > 2)
        user_toy = r.client.services["toy"]
        assert isinstance(user_toy, Toy)
        user_toy.channel.send(b"1")
        await wait_until(lambda: user_toy.heard == [b"echo:1"])
        await blip(r.hub)
        await wait_until(lambda: r.client.reconnects == 1, timeout=10)
        second = r.client.call.id
        assert second != first
        # The old call's services closed on both sides, the new call's opened.
        await wait_until(lambda: log.of("robot", "close") == [first])
        assert log.of("user", "close") == [first]
        assert log.of("robot", "open") == log.of("user", "open") == [first, second]
        assert r.server.open[second].names() == [
            "core",
            "video",
            "plan",
            "relay",
            "conference",
            "people",
            "media",
            "drive",
            "toy",
        ]
        new_toy = r.client.services["toy"]
        assert isinstance(new_toy, Toy) and new_toy is not user_toy
        new_toy.channel.send(b"2")
        await wait_until(lambda: new_toy.heard == [b"echo:2"])
        await wait_until(lambda: log.ticks.get(second + "user", 0) > 2)
    assert log.of("user", "close") == [first, second]
    assert log.of("robot", "close") == [first, second]


def test_the_registry_refuses_a_second_name_and_unwinds_a_failed_open() -> None:
    closed: list[str] = []

    class Ok:
        def __init__(self, host: object, call: object) -> None:
            pass

        def tick(self, now: float) -> None:
            pass

        def close(self) -> None:
            closed.append("ok")

    def broken(host: object, call: object) -> Ok:
        raise RuntimeError("no")

    registry: ServiceRegistry[object] = ServiceRegistry()
    registry.register("ok", Ok)
    with pytest.raises(ValueError, match="already registered"):
        registry.register("ok", Ok)
    registry.register("broken", broken)
    with pytest.raises(RuntimeError):
        registry.open(object(), object())  # type: ignore[arg-type]
    assert closed == ["ok"]
    with pytest.raises(KeyError, match="registered: ok, broken"):
        registry.unregister("nope")


# -- the web UI -----------------------------------------------------------------------------


async def test_the_page_shows_the_reconnection_and_gets_pose_and_video_again(
    tmp_path: Path,
) -> None:
    async with (
        rig(tmp_path) as r,
        WebUI(r.client, port=0, user=USER) as ui,
        aiohttp.ClientSession() as http,
        http.ws_connect(ui.url.replace("http", "ws") + "ws") as ws,
    ):
        loop = asyncio.get_running_loop()
        got: list[tuple[float, str, dict[str, Any]]] = []

        async def read() -> None:
            async for msg in ws:
                if msg.type == aiohttp.WSMsgType.TEXT:
                    data = json.loads(msg.data)
                    got.append((loop.time(), data["type"], data))
                elif msg.type == aiohttp.WSMsgType.BINARY:
                    got.append((loop.time(), "frame", {}))

        reader = asyncio.create_task(read())
        try:
            await wait_until(lambda: any(kind == "frame" for _, kind, _ in got), timeout=10)
            healed = await blip(r.hub)
            await wait_until(lambda: ui.connection["state"] == "reconnected", timeout=10)

            def after_heal(wanted: str) -> bool:
                return any(t > healed and kind == wanted for t, kind, _ in got)

            await wait_until(lambda: after_heal("frame") and after_heal("pose"), timeout=10)
            states = [m["state"] for _, kind, m in got if kind == "connection"]
            assert states[0] == "connected" and states[-2:] == ["reconnecting", "reconnected"]
            back = next(t for t, kind, _ in got if t > healed and kind == "pose")
            assert back - healed < 1.0 + SLACK, f"pose {back - healed:.2f} s after the heal"
            assert ui.maps.map is not None and not r.safety.state().armed
        finally:
            reader.cancel()
            await asyncio.gather(reader, return_exceptions=True)


# -- the chat command -----------------------------------------------------------------------


@pytest.fixture
def hub_name() -> Iterator[str]:
    name = f"reconnect-{uuid.uuid4().hex}"
    yield name
    MemoryHub._registry.pop(name, None)


async def test_chat_says_reconnecting_and_carries_on_with_the_next_command(
    tmp_path: Path, hub_name: str, capsys: pytest.CaptureFixture[str]
) -> None:
    hub = MemoryHub.named(hub_name)
    config = AppConfig(
        transport=TransportSettings(
            kind="memory", memory=MemorySettings(hub=hub_name, node="user")
        ),
        reconnect=FAST,
    )
    async with robot_on_hub(tmp_path, hub) as (nav, safety, _, _):
        script = io.StringIO("arm\nfwd 3\nwhere?\n")

        async def blip_while_moving() -> None:
            await wait_until(lambda: nav.velocity() != Velocity(), timeout=20)
            await blip(hub)

        outage = asyncio.create_task(blip_while_moving())
        status = await chat_session(
            ROBOT, home=tmp_path / "user", config=config, timeout=60, map_dir=tmp_path, stdin=script
        )
        await outage
        assert not safety.state().armed
    out, err = capsys.readouterr()
    lines = out.splitlines()
    assert status == 1  # fwd 3 did not finish
    assert "! fwd 3: interrupted, the call dropped (not resent)" in lines
    assert lines[-2] == "> where?" and lines[-1].startswith("x ")
    assert "[reconnecting… (" in err and "[reconnected after " in err


# -- zenoh: the robot daemon in its own process, the user through a TCP proxy ---------------


@pytest.mark.zenoh
async def test_over_zenoh_the_call_comes_back_when_the_proxy_does(
    tmp_path: Path, processes: list[Any]
) -> None:
    # The product's call timeout: the cut must drop the call on both sides.
    daemon = Daemon(tmp_path, observer=None, timeout=REAL_TIMEOUT)
    await asyncio.to_thread(daemon.start)
    processes.append(daemon.events)
    proxy = TcpProxy(daemon.port)
    await proxy.start()
    config = proxy.client_config(FAST.model_dump())
    loop = asyncio.get_running_loop()
    events: list[tuple[float, ConnectionEvent]] = []
    try:
        async with connect(ROBOT, home=daemon.user_home, config=config, timeout=20) as client:
            client.on_connection.append(lambda event: events.append((loop.time(), event)))
            assert (await client.arm()).ok
            poses: list[float] = []

            async def follow() -> None:
                async for _ in client.poses():
                    poses.append(loop.time())

            follower = asyncio.create_task(follow())
            try:
                replies = client.chat_replies("fwd 3")
                assert (await anext(replies)).text == "Forward command received"
                first = client.call
                await proxy.stop()
                with pytest.raises(CallEnded):
                    async for _ in replies:
                        pass
                await wait_until(lambda: any(e.state == "reconnecting" for _, e in events))
                await asyncio.sleep(OUTAGE)  # the outage itself
                await proxy.start()
                healed = loop.time()
                await wait_until(lambda: client.reconnects == 1, timeout=20)
                await wait_until(lambda: any(t > healed for t in poses), timeout=10)
                back = next(t for t in poses if t > healed)
                assert back - healed < 1.0 + SLACK, f"first pose {back - healed:.2f} s after"
                assert client.call is not first and not follower.done()
                await wait_until(
                    lambda: (
                        client.latest_safety.value is not None
                        and not client.latest_safety.value.armed
                    )
                )
                pose = await client.pose()
                assert pose.goal is None and pose.v == 0.0  # stopped, nothing resumed
                stopped = await client.telemetry()
                assert not stopped.armed and stopped.stop_reason
            finally:
                follower.cancel()
                await asyncio.gather(follower, return_exceptions=True)
    finally:
        if proxy._server is not None:
            await proxy.stop()


@pytest.mark.zenoh
async def test_over_zenoh_a_call_back_before_the_robot_saw_the_drop_gets_the_drive_back(
    tmp_path: Path, processes: list[Any]
) -> None:
    # The robot's call timeout is long, the user's the product's: when the robot's process
    # stalls (a loaded machine), the user drops its call and calls again while the robot,
    # once it runs again, still has the old call (the 0.4 s window, made wide).
    daemon = Daemon(tmp_path, observer=None, timeout=LINGER)
    await asyncio.to_thread(daemon.start)
    processes.append(daemon.events)
    events: list[ConnectionEvent] = []
    async with daemon.connect(call_timeout=REAL_TIMEOUT, timeout=20) as client:
        client.on_connection.append(events.append)
        await wait_until(lambda: client.conference.roster is not None)
        assert (await client.arm()).ok
        replies = client.chat_replies("fwd 3")
        assert (await anext(replies)).text == "Forward command received"
        first = client.call
        daemon.events.signal(signal.SIGSTOP)
        try:
            await wait_until(lambda: any(e.state == "reconnecting" for e in events))
        finally:
            daemon.events.signal(signal.SIGCONT)
        with pytest.raises(CallEnded):
            async for _ in replies:
                pass
        await wait_until(lambda: client.reconnects == 1, timeout=20)
        # The robot hung the old call up for the new one, which holds the drive, stopped.
        ended = await daemon.call_ended(first.id)
        assert (ended["kind"], ended["detail"]) == (
            "hung_up",
            "replaced by a new call from the same client",
        )
        stopped = await client.telemetry()
        assert not stopped.armed and stopped.holder == USER
        assert stopped.stop_reason == f"driver {USER} called again (the old call is replaced)"
        joined = [r for r in daemon.audit() if r["what"] == "join" and r["call"] == client.call.id]
        assert f"replaces call {first.id}" in joined[0]["detail"], joined
        # The driver drives again after a deliberate arm.
        assert (await client.arm()).ok
        assert (await client.chat("fwd 0.2")).ok
        # One reconnection in the conference, no "left" for the old call.
        back = (ROBOT, "robot", f"{USER} reconnected (driver)")
        await wait_until(lambda: back in _said(client))
        assert _roster(client) == [(USER, "driver", True, True)]
        assert not any(text.endswith(" left") for _, _, text in _said(client))


async def test_in_a_browser_the_page_says_reconnecting_and_resumes_without_a_reload(
    tmp_path: Path,
) -> None:
    from test_web_ui import browser_page, page_ready

    async with (
        rig(tmp_path) as r,
        WebUI(r.client, port=0, user=USER) as ui,
        browser_page(ui.url) as page,
    ):
        await page_ready(page)
        await page.wait_for_function("() => window.telebotUI.state.frames > 0", timeout=10_000)
        r.hub.cut("robot", "user")
        await page.wait_for_function(
            "() => document.getElementById('conn').textContent === 'reconnecting…'",
            timeout=10_000,
        )
        await asyncio.sleep(OUTAGE)  # the outage itself
        before = await page.evaluate(
            "() => [window.telebotUI.state.frames, window.telebotUI.state.pose.t]"
        )
        r.hub.heal("robot", "user")
        await page.wait_for_function(
            "() => document.getElementById('conn').textContent.startsWith('reconnected after')",
            timeout=10_000,
        )
        # Same page, no reload: video frames and poses come again.
        await page.wait_for_function(
            "([frames, t]) => window.telebotUI.state.frames > frames"
            " && window.telebotUI.state.pose.t > t",
            arg=before,
            timeout=10_000,
        )
        assert await page.evaluate("() => window.telebotUI.mapReady()")
        assert not r.safety.state().armed
        await page.wait_for_function(
            "() => document.getElementById('safety').textContent === 'stopped'", timeout=10_000
        )
