"""One user, many robots: the fleet page (in Chromium), stop all, and connect() to several.

Three simulated robots and the user run in this process on one memory hub (tests/fleet_rig.py);
a robot is made unreachable by losing every frame between it and the user (its presence
stays: the call is up but nothing answers), or made to vanish by cutting its link.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp

from conftest import wait_until
from fleet_rig import FleetRobot, make_homes, running_robot, user_endpoint, user_home
from telebot.apps.web.fleet import FleetUI
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.identity import Role
from telebot.services.client import RobotClient, connect
from test_web_ui import ARTIFACTS, browser_page

ROBOTS = ["bot1", "bot2", "bot3"]


@contextlib.asynccontextmanager
async def fleet_rig(
    base: Path, hub: MemoryHub, *, stop_timeout: float = 2.0, watch: bool = True
) -> AsyncIterator[tuple[FleetUI, dict[str, FleetRobot]]]:
    make_homes(base, ROBOTS, {"alice": Role.DRIVER, "bob": Role.OBSERVER})
    async with contextlib.AsyncExitStack() as stack:
        robots = {
            name: await stack.enter_async_context(running_robot(base, name, hub)) for name in ROBOTS
        }
        endpoint = await stack.enter_async_context(user_endpoint(base, "alice", hub))
        fleet = await stack.enter_async_context(
            FleetUI(endpoint, port=0, stop_timeout=stop_timeout, watch=watch)
        )
        yield fleet, robots


def _called(fleet: FleetUI, names: list[str]) -> bool:
    return all(
        (r := fleet.robots.get(n)) is not None
        and r.client is not None
        and r.client.latest_telemetry.value is not None
        and r.client.latest_safety.value is not None
        for n in names
    )


async def _drive(fleet: FleetUI, robot: FleetRobot) -> None:
    client = fleet.robots[robot.name].client
    assert client is not None
    ack = await client.arm()
    assert ack.ok, ack.text
    pose = robot.nav.pose().pose
    fleet._tasks.spawn(client.goto(pose.x + 8.0, pose.y))  # along the bottom corridor


async def test_the_fleet_page_lists_opens_two_and_stops_all(tmp_path: Path) -> None:
    hub = MemoryHub(seed=5)
    async with (
        # A generous stop timeout: a loaded machine must not make a reachable robot late.
        # bot3's call drops after 2 s of silence: it is reported then.
        fleet_rig(tmp_path, hub, stop_timeout=5.0) as (fleet, robots),
        browser_page(fleet.url) as page,
    ):
        # Every robot online is listed with what its call tells: battery, state, driver.
        await page.wait_for_function(
            "() => { const r = window.telebotFleet.state.robots;"
            " return r.length === 3 && r.every(x => x.battery !== null && x.armed !== null); }",
            timeout=15000,
        )
        rows = await page.evaluate("() => window.telebotFleet.state.robots")
        assert [r["name"] for r in rows] == ROBOTS
        assert all(r["role"] == "driver" and r["online"] and not r["open"] for r in rows)
        # Watching does not hold the drive: nobody drives until a robot is opened.
        await page.wait_for_function(
            "() => window.telebotFleet.state.robots.every(x => x.holder === null)",
            timeout=10000,
        )
        assert "%" in await page.inner_text("#row-bot2")

        for name in ("bot1", "bot2"):
            await page.click(f"#open-{name}")
        for name in ("bot1", "bot2"):
            await page.wait_for_selector(f"#frame-{name} iframe")
            frame = await _frame(page, f"robot-{name}")
            await frame.wait_for_function(
                "() => window.telebotUI && window.telebotUI.mapReady()"
                " && window.telebotUI.state.pose",
                timeout=15000,
            )
            assert await frame.inner_text("#robot-name") == name
            # Opening took the drive: this user holds it, on its own call.
            await frame.wait_for_function(
                "() => document.getElementById('holder').textContent === 'alice'", timeout=10000
            )
        await page.wait_for_function(
            "() => window.telebotFleet.state.robots.filter(x => x.open).length === 2"
        )
        # Many users, one robot: bob watches bot1; alice's bot1 page shows him in the call
        # and his message, and her "say" in the chat box reaches him.
        frame = await _frame(page, "robot-bot1")
        async with user_endpoint(tmp_path, "bob", hub) as bob_end:
            bob = RobotClient(await bob_end.call("bot1", timeout=10))
            bob.start()
            try:
                await frame.wait_for_function(
                    "() => document.getElementById('roster').textContent.includes('bob')",
                    timeout=10000,
                )
                assert "alice (you) · driver · driving" in await frame.inner_text("#roster")
                assert (await bob.say("hello from bob")).ok
                await frame.wait_for_function(
                    "() => document.getElementById('chat-log').textContent"
                    ".includes('[bob] hello from bob')",
                    timeout=10000,
                )
                await frame.fill("#chat-input", "say hi bob")
                await frame.press("#chat-input", "Enter")
                await wait_until(
                    lambda: any(
                        (m.sender, m.text) == ("alice", "hi bob") for m in bob.conference.messages
                    )
                )
            finally:
                await bob.hangup()
                await bob.aclose()
        for name in ("bot1", "bot2"):
            await _drive(fleet, robots[name])
        await wait_until(
            lambda: all(robots[n].nav.velocity().linear > 0.3 for n in ("bot1", "bot2")),
            timeout=15.0,
        )
        # bot3 becomes unreachable: everything between it and the user is lost.
        hub.set_link("bot3", "alice", loss=1.0)
        await page.click("#stop-all")
        await wait_until(
            lambda: all(robots[n].nav.velocity().linear == 0.0 for n in ("bot1", "bot2"))
        )
        assert not robots["bot1"].safety.state().armed and not robots["bot2"].safety.state().armed
        await page.wait_for_function("() => window.telebotFleet.state.stopAll !== null")
        results = {
            r["robot"]: r for r in await page.evaluate("() => window.telebotFleet.state.stopAll")
        }
        assert results["bot1"]["ok"] and results["bot2"]["ok"]
        assert not results["bot3"]["ok"] and "did not answer" in results["bot3"]["text"]
        shown = await page.inner_text("#stop-result")
        assert "bot1 stopped" in shown and "bot3: did not answer" in shown
        ARTIFACTS.mkdir(exist_ok=True)
        await page.screenshot(path=str(ARTIFACTS / "fleet.png"), full_page=True)


async def _frame(page: Any, name: str) -> Any:
    for _ in range(500):
        frame = page.frame(name=name)
        if frame is not None and frame.url.endswith("/"):
            return frame
        await asyncio.sleep(0.02)
    raise AssertionError(f"no frame {name}")


async def test_bad_names_a_vanished_robot_and_stop_all_say_why(tmp_path: Path) -> None:
    hub = MemoryHub(seed=9)
    async with fleet_rig(tmp_path, hub, stop_timeout=2.0) as (fleet, robots):
        await wait_until(lambda: _called(fleet, ROBOTS), timeout=15.0)
        async with aiohttp.ClientSession() as http:
            for path, text in (
                ("robot/ghost/", "no robot named 'ghost' is online"),
                ("robot/bad..name/", "robot name"),
            ):
                async with http.get(fleet.url + path) as response:
                    assert response.status == 404
                    body = await response.text()
                    assert text in body and body.count("\n") == 1, body
            async with http.get(fleet.url + "robot/bot1", allow_redirects=False) as response:
                assert response.status == 302 and response.headers["Location"] == "/robot/bot1/"
            async with http.get(fleet.url + "robot/bot1/static/../fleet.py") as response:
                assert response.status == 404
            async with http.ws_connect(fleet.url + "fleet/ws") as ws:
                await ws.send_json({"type": "open", "robot": "ghost"})
                await ws.send_json({"type": "open"})
                await ws.send_str("garbage")
                errors = []
                while len(errors) < 3:
                    message = await ws.receive_json(timeout=5)
                    if message["type"] == "error":
                        errors.append(message["text"])
                assert any("cannot open ghost: no robot named 'ghost'" in e for e in errors)
                assert any("'robot' must be a name" in e for e in errors)
                assert any("not a JSON message" in e for e in errors)
            # Opening by address works too, and the page is the single-robot page.
            async with http.get(fleet.url + "robot/bot2/") as response:
                assert response.status == 200 and "app.js" in await response.text()
            assert fleet.robots["bot2"].ui is not None

        # Closing a robot's page while it moves stops it (nobody watches it any more).
        assert await fleet.open("bot1") is None
        await _drive(fleet, robots["bot1"])
        await wait_until(lambda: robots["bot1"].nav.velocity().linear > 0.3, timeout=10.0)
        await fleet.close_robot("bot1")
        await wait_until(lambda: robots["bot1"].nav.velocity().linear == 0.0)
        assert not robots["bot1"].safety.state().armed and fleet.robots["bot1"].ui is None

        # bot2 vanishes while open: listed offline, its client reconnecting; stop all
        # still stops the others and names bot2 as not answering.
        hub.cut("bot2", "alice")
        await wait_until(lambda: not fleet.robots["bot2"].online)
        await wait_until(
            lambda: "reconnecting" in str(fleet.robots["bot2"].summary()["connection"])
        )
        results = {r["robot"]: r for r in await fleet.stop_all()}
        assert results["bot1"]["ok"] and results["bot3"]["ok"]
        assert not results["bot2"]["ok"] and "did not answer" in results["bot2"]["text"]
        # It comes back: the same client calls it again and the page is still open.
        hub.heal("bot2", "alice")
        await wait_until(
            lambda: fleet.robots["bot2"].summary()["connection"] == "connected", timeout=15.0
        )
        assert fleet.robots["bot2"].ui is not None


async def test_a_fleet_page_that_does_not_watch_calls_a_robot_only_when_opened(
    tmp_path: Path,
) -> None:
    async with fleet_rig(tmp_path, MemoryHub(seed=4), watch=False) as (fleet, robots):
        await wait_until(lambda: all(n in fleet.robots for n in ROBOTS))
        await wait_until(lambda: all(fleet.robots[n].trusted for n in ROBOTS))
        # Listed by name only: no call, so nothing but presence is known.
        row = fleet.robots["bot2"].summary()
        assert row["online"] and not row["called"] and row["battery"] is None
        assert all(not robot.endpoint.calls for robot in robots.values())
        assert await fleet.open("bot2") is None
        client = fleet.robots["bot2"].client
        assert client is not None and fleet.robots["bot2"].ui is not None
        await wait_until(lambda: fleet.robots["bot2"].summary()["battery"] is not None)
        assert not robots["bot1"].endpoint.calls and not robots["bot3"].endpoint.calls


async def test_connect_works_for_several_robots_in_one_program(tmp_path: Path) -> None:
    hub = MemoryHub(seed=2)
    make_homes(tmp_path, ["bot1", "bot2"], {"alice": Role.DRIVER})
    home = user_home(tmp_path, "alice")
    async with (
        running_robot(tmp_path, "bot1", hub) as bot1,
        running_robot(tmp_path, "bot2", hub) as bot2,
        MemoryTransport(hub, "alice") as transport,
        connect("bot1", home=home, transport=transport, timeout=10) as one,
        connect("bot2", home=home, transport=transport, timeout=10) as two,
    ):
        assert (one.robot, two.robot) == ("bot1", "bot2")
        # Each call is its own: moving one robot leaves the other where it is.
        assert (await one.arm()).ok and (await two.arm()).ok
        start = bot2.nav.pose().pose
        assert (await one.chat("fwd 0.5", timeout=15)).ok
        assert bot1.nav.pose().pose.x > start.x + 0.4
        assert abs(bot2.nav.pose().pose.x - start.x) < 0.1  # localisation noise only
        assert bot2.nav.velocity().linear == 0.0
        poses = await asyncio.gather(one.pose(), two.pose())
        assert poses[0].x > poses[1].x + 0.4
        stops = await asyncio.gather(one.stop(), two.stop())
        assert all(ack.ok for ack in stops)


async def test_telebot_user_ui_without_a_robot_serves_the_fleet_page(tmp_path: Path) -> None:
    from telebot.apps.web.fleet import serve_fleet
    from telebot.config import AppConfig

    hub_name = f"fleet-{tmp_path.name}"
    hub = MemoryHub.named(hub_name)
    make_homes(tmp_path, ["bot1", "bot2"], {"alice": Role.DRIVER})
    config = AppConfig.model_validate(
        {"transport": {"kind": "memory", "memory": {"hub": hub_name, "node": "alice"}}}
    )
    said: list[str] = []
    stop = asyncio.Event()
    async with running_robot(tmp_path, "bot1", hub), running_robot(tmp_path, "bot2", hub):
        serving = asyncio.create_task(
            serve_fleet(
                home=user_home(tmp_path, "alice"),
                config=config,
                port=0,
                stop=stop,
                announce=said.append,
            )
        )
        try:
            await wait_until(lambda: bool(said) or serving.done())
            url = said[0].split()[1]
            async with aiohttp.ClientSession() as http:
                async with http.get(url) as response:
                    assert "fleet.js" in await response.text()
                async with http.ws_connect(url + "fleet/ws") as ws:
                    while True:
                        message = await ws.receive_json(timeout=10)
                        robots = message.get("robots", [])
                        if message["type"] == "fleet" and sum(r["called"] for r in robots) == 2:
                            break
            assert [r["name"] for r in robots] == ["bot1", "bot2"]
        finally:
            stop.set()
            assert await serving == 0


def test_ui_record_needs_a_robot_name(tmp_path: Path, capsys: Any) -> None:
    from telebot.apps.user_cli import main

    code = main(["ui", "--record", str(tmp_path / "x.mcap"), "--home", str(tmp_path)])
    assert code == 2
    assert capsys.readouterr().err.strip() == "telebot-user: error: --record needs a robot name"
