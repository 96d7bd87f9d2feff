"""The web UI (``telebot-user ui``) in a real browser: Debian's chromium driven by Playwright.

The robot runs in this process (SimNavStack + SafetyDriver + RobotServer on a memory hub),
so a test can read the base's velocity the moment it changes; the UI server bridges a
:class:`RobotClient` on the same hub to a headless chromium at ``/usr/bin/chromium``.
A screenshot of the page is saved under ``test-artifacts/``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import re
import shutil
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiohttp
import pytest
import pytest_asyncio

from conftest import ROBOT, USER
from rig import GENEROUS_STALE_VIDEO, GENEROUS_TIMEOUT, SLACK, services_without_media
from telebot.apps.web.server import WebUI
from telebot.channels.call import RobotEndpoint, UserEndpoint
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import CallSettings, ServiceSettings, SimSettings
from telebot.identity import ContactBook, Identity, KnownRobots, Role, create_paired_homes
from telebot.robot.grid import OccupancyGrid
from telebot.robot.sim.stack import SimNavStack
from telebot.services.base import ServiceConfig
from telebot.services.client import RobotClient
from telebot.services.robot import RobotServer
from telebot.services.safety.robot import SafetyDriver
from telebot.services.video.wire import VideoSettings

CHROMIUM = "/usr/bin/chromium"
ARTIFACTS = Path(__file__).resolve().parent.parent / "test-artifacts"

import playwright.async_api as playwright_api  # noqa: E402

# No silent skip: `make test` installs the browser first (.ci/install-browser), so a
# missing browser is a broken set-up and fails loudly here.
assert Path(CHROMIUM).exists(), "chromium missing: run .ci/install-browser"

#: The module's async tests share one event loop and one chromium (each page in a context
#: of its own): a browser started per test cost about a second each.
in_module_loop = pytest.mark.asyncio(loop_scope="module")

#: The module's chromium and the loop it runs in, while the module's tests run
#: (:func:`browser_page` starts one of its own anywhere else).
_shared: tuple[Any, asyncio.AbstractEventLoop] | None = None


@dataclass
class Rig:
    """The in-process robot, the user's client, the UI server and the base's stop log."""

    nav: SimNavStack
    safety: SafetyDriver
    client: RobotClient
    ui: WebUI
    #: The robot's audit log (JSON lines).
    audit: Path
    #: Wall-clock times (s) at which the base's velocity became zero by a stop.
    zeroed: list[float] = field(default_factory=list)
    #: The robot's server (its follow-me: ``rig.robot_drive(server).follow``).
    server: RobotServer | None = None

    def stops(self) -> list[tuple[str, str]]:
        """Who stopped the robot and how, from its audit log (a repeated stop once)."""
        lines = self.audit.read_text(encoding="utf-8").splitlines()
        records = [json.loads(line) for line in lines]
        return list(dict.fromkeys((r["who"], r["how"]) for r in records if r["what"] == "stop"))


def _watch_stops(nav: SimNavStack, zeroed: list[float]) -> None:
    """Stamp the moment each stop leaves the base at zero velocity."""
    original = nav.stop

    def stop() -> None:
        moving = nav.velocity().linear != 0.0 or nav.velocity().angular != 0.0
        original()
        velocity = nav.velocity()
        if moving and velocity.linear == 0.0 and velocity.angular == 0.0:
            zeroed.append(time.time())

    nav.stop = stop  # type: ignore[method-assign]


@contextlib.asynccontextmanager
async def robot_rig(
    base: Path, *, role: Role = Role.DRIVER, pose_hz: float = 20.0, max_linear_speed: float = 1.5
) -> AsyncIterator[Rig]:
    """A fast simulated robot on the small map, a user in a call with it, the UI served."""
    create_paired_homes(base, ROBOT, USER, role=role)
    robot_home, user_home = base / "robot", base / "user"
    loop = asyncio.get_running_loop()
    settings = SimSettings(
        map="small",
        max_linear_speed=max_linear_speed,
        linear_accel=3.0,
        max_angular_speed=3.0,
        angular_accel=8.0,
        control_hz=50,
    )
    nav = SimNavStack.from_settings(settings, now=loop.time())
    zeroed: list[float] = []
    _watch_stops(nav, zeroed)
    audit = base / "audit.jsonl"
    safety = SafetyDriver(
        nav,
        timeout=GENEROUS_TIMEOUT,
        max_speed=settings.max_linear_speed,
        stale_video=GENEROUS_STALE_VIDEO,
        audit_path=audit,
    )
    server = RobotServer(
        nav,
        ServiceSettings(pose_hz=pose_hz),
        services=services_without_media(),
        control_hz=settings.control_hz,
        map_name="small",
        safety=safety,
        config=ServiceConfig(
            video=VideoSettings(width=320, height=240, max_fps=15, quality=70, min_quality=30),
        ),
    )
    await server.prepare()
    hub = MemoryHub(seed=7)
    # No test here is about drop timing: a preempted process (a browser is busy) keeps its call.
    calls = CallSettings(timeout=GENEROUS_TIMEOUT)
    with safety:
        async with (
            MemoryTransport(hub, "robot") as robot_transport,
            MemoryTransport(hub, "user") as user_transport,
            RobotEndpoint(
                robot_transport,
                Identity.load(robot_home),
                ContactBook.load(robot_home),
                settings=calls,
            ) as endpoint,
            UserEndpoint(
                user_transport,
                Identity.load(user_home),
                KnownRobots.load(user_home),
                settings=calls,
            ) as user,
        ):
            server.attach(endpoint)
            runner = asyncio.create_task(server.run(), name="robot-loop")
            try:
                call = await user.call(ROBOT, timeout=10)
                client = RobotClient(call)
                async with WebUI(client, port=0, user=USER) as ui:
                    yield Rig(nav, safety, client, ui, audit, zeroed, server)
                with contextlib.suppress(Exception):
                    await call.hangup()
            finally:
                safety.stop(None, "test over")
                runner.cancel()
                await asyncio.gather(runner, return_exceptions=True)


async def launch_chromium(pw: Any) -> Any:
    """Debian's chromium, headless."""
    args = ["--no-sandbox"] if os.geteuid() == 0 else []
    return await pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=args)


@pytest_asyncio.fixture(scope="module", loop_scope="module", autouse=True)
async def _chromium() -> AsyncIterator[None]:
    """One chromium for this module's tests (see :data:`_shared`)."""
    global _shared
    async with playwright_api.async_playwright() as pw:
        browser = await launch_chromium(pw)
        _shared = (browser, asyncio.get_running_loop())
        try:
            yield
        finally:
            _shared = None
            await browser.close()


@pytest_asyncio.fixture(autouse=True, loop_scope="module")
async def _no_leaked_tasks() -> AsyncIterator[None]:
    """conftest's check, in the module's loop: no test leaves asyncio tasks behind it."""
    before = asyncio.all_tasks()
    yield
    await asyncio.sleep(0)
    leaked = [
        t for t in asyncio.all_tasks() - before if t is not asyncio.current_task() and not t.done()
    ]
    assert not leaked, f"test leaked tasks: {leaked}"


def shared_browser() -> Any | None:
    """The module's chromium (:func:`_chromium`, also imported by other modules) if this
    test runs in its loop, else None."""
    if _shared is not None and _shared[1] is asyncio.get_running_loop():
        return _shared[0]
    return None


@contextlib.asynccontextmanager
async def browser_page(url: str) -> AsyncIterator[Any]:
    """A headless chromium page at ``url`` (Debian's chromium: never a downloaded one), in
    a context of its own (so nothing is shared with another test's page)."""
    browser = shared_browser()
    if browser is not None:
        context = await browser.new_context(viewport={"width": 1280, "height": 800})
        try:
            page = await context.new_page()
            await page.goto(url)
            yield page
        finally:
            await context.close()
        return
    async with playwright_api.async_playwright() as pw:
        browser = await launch_chromium(pw)
        try:
            page = await browser.new_page(viewport={"width": 1280, "height": 800})
            await page.goto(url)
            yield page
        finally:
            await browser.close()


async def wait_for(predicate: Any, timeout: float = 10.0, what: str = "condition") -> None:
    """Poll ``predicate`` (sync or async) until true."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if asyncio.iscoroutine(value):
            value = await value
        if value:
            return
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.02)


async def page_ready(page: Any) -> None:
    """Wait until the page has the map drawn and a pose."""
    await page.wait_for_function(
        "() => window.telebotUI && window.telebotUI.mapReady() && window.telebotUI.state.pose",
        timeout=15000,
    )


async def arm(rig: Rig) -> None:
    ack = await rig.client.arm()
    assert ack.ok, ack.text


#: A top speed at which :func:`drive_forward`'s move lasts 20 s, for a test whose stop
#: comes from the page (a key, the page going away): on a loaded machine the page's steps
#: took over the 6 s of the fast robot's move, which had ended (nothing left to stop) when
#: the stop came.
LASTING_SPEED = 0.4


async def drive_forward(rig: Rig) -> None:
    """Start a long straight move (8 m: 6 s at the rig's usual speed) and wait until the
    base is moving."""
    await arm(rig)
    pose = rig.nav.pose().pose
    rig.ui._tasks.spawn(rig.client.goto(pose.x + 8.0, pose.y))  # along the bottom corridor
    await wait_for(lambda: rig.nav.velocity().linear > 0.3, what="the robot moving")


@pytest_asyncio.fixture(loop_scope="module")
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    async with robot_rig(tmp_path) as value:
        yield value


@in_module_loop
async def test_the_page_loads_and_shows_the_map(rig: Rig) -> None:
    async with browser_page(rig.ui.url) as page:
        await page_ready(page)
        assert await page.title() == f"telebot · {ROBOT}"
        # Sample the canvas: free cells are light, walls dark, and the robot is drawn blue.
        counts = await page.evaluate(
            """() => {
              const c = document.getElementById('map');
              const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
              let free = 0, wall = 0, blue = 0;
              for (let i = 0; i < d.length; i += 4) {
                const [r, g, b] = [d[i], d[i + 1], d[i + 2]];
                if (r > 240 && g > 240 && b > 240) free++;
                else if (r < 30 && g < 30 && b < 30) wall++;
                if (b > 200 && r < 120) blue++;
              }
              return {free, wall, blue, total: d.length / 4};
            }"""
        )
        assert counts["free"] > 0.1 * counts["total"], counts
        assert counts["wall"] > 0.005 * counts["total"], counts
        assert counts["blue"] > 20, counts
        # The status bar: role, who holds the drive, link and battery.
        assert "driver" in await page.inner_text("#role")
        await page.wait_for_function(
            "() => document.getElementById('battery').textContent.endsWith('%')"
        )
        await page.wait_for_function(
            "() => document.getElementById('link').textContent.includes('ms')"
        )
        assert await page.inner_text("#holder") == USER
        ARTIFACTS.mkdir(exist_ok=True)
        await page.screenshot(path=str(ARTIFACTS / "web_ui.png"))


@in_module_loop
async def test_the_page_follows_a_map_that_changes(rig: Rig) -> None:
    async with browser_page(rig.ui.url) as page:
        await page_ready(page)
        old = rig.ui.maps.map
        assert old is not None and old.version == 0
        grid = rig.nav.map()
        data = grid.data.copy()
        row, col = grid.cell_of(9.5, 4.0)
        data[row - 5 : row + 6, col - 5 : col + 6] = 100  # SLAM found a wall in room-b
        rig.nav.set_map(OccupancyGrid(data, grid.resolution, grid.origin_x, grid.origin_y))
        # Telemetry says the map changed; the UI fetches it again and tells the page.
        await page.wait_for_function(
            "() => window.telebotUI.state.map && window.telebotUI.state.map.version === 1"
            " && window.telebotUI.mapReady()",
            timeout=15000,
        )
        new = rig.ui.maps.map
        assert new is not None and new.version == 1 and new.sha256 != old.sha256
        assert new.grid.value_at(9.5, 4.0) == 100 and rig.ui.maps.refreshes == 1
        async with aiohttp.ClientSession() as http, http.get(rig.ui.url + "map.png") as response:
            assert await response.read() == new.png


@in_module_loop
async def test_a_click_moves_the_robot_there(rig: Rig) -> None:
    await arm(rig)
    async with browser_page(rig.ui.url) as page:
        await page_ready(page)
        await page.wait_for_function("() => window.telebotUI.state.safety?.armed")
        target = (4.0, 1.2)  # bottom corridor of the small map, in sight of "start"
        sx, sy = await page.evaluate(f"() => window.telebotUI.worldToScreen{target}")
        box = await page.locator("#map").bounding_box()
        await page.mouse.click(box["x"] + sx, box["y"] + sy)
        await page.wait_for_function(
            "() => window.telebotUI.state.goal?.status === 'succeeded'", timeout=20000
        )
        sent = await page.evaluate("() => window.telebotUI.state.goal")
        # The click's world point is the target, to within a screen pixel.
        scale = await page.evaluate(
            "() => { const a = window.telebotUI.screenToWorld(0, 0);"
            " const b = window.telebotUI.screenToWorld(1, 0); return b[0] - a[0]; }"
        )
        assert math.dist((sent["x"], sent["y"]), target) <= 1.5 * scale + 1e-6
        real = rig.nav.pose().pose
        # The goal's tolerance, plus what a loaded machine's late control steps let the base
        # run on past it (the simulator's watchdog design, tested in test_sim_stack).
        assert math.dist((real.x, real.y), (sent["x"], sent["y"])) < 0.3
        # The pose updates that follow bring the page to where the robot stopped.
        await page.wait_for_function(
            "([x, y]) => { const p = window.telebotUI.state.pose;"
            " return p && Math.hypot(p.x - x, p.y - y) < 0.1; }",
            arg=[real.x, real.y],
            timeout=5000,
        )
        # The text shows the page's pose (within 0.1 m of the robot's by now) to 2 decimals.
        shown = re.match(r"x (-?[0-9.]+) m", await page.inner_text("#pose-text"))
        assert shown is not None and abs(float(shown.group(1)) - real.x) < 0.1


@in_module_loop
async def test_a_click_to_goal_draws_the_planned_path_and_places_are_labelled(rig: Rig) -> None:
    await arm(rig)
    async with browser_page(rig.ui.url) as page:
        await page_ready(page)
        # Every named place of the map is labelled on it.
        await page.wait_for_function(
            "() => window.telebotUI.drawn.labels.length === 4", timeout=10000
        )
        labels = await page.evaluate("() => window.telebotUI.drawn.labels")
        assert sorted(labels) == sorted(rig.nav.places())
        assert "straight line" not in await page.content()
        await page.wait_for_function("() => window.telebotUI.state.safety?.armed")
        start = rig.nav.pose().pose
        room_b = rig.nav.places()["room-b"]  # round the walls from the start
        sx, sy = await page.evaluate(
            f"() => window.telebotUI.worldToScreen({room_b.x}, {room_b.y})"
        )
        box = await page.locator("#map").bounding_box()
        await page.mouse.click(box["x"] + sx, box["y"] + sy)
        await page.wait_for_function(
            "() => window.telebotUI.state.plan?.points.length > 2"
            " && window.telebotUI.drawn.plan >= 2",
            timeout=10000,
        )
        plan = await page.evaluate("() => window.telebotUI.state.plan")
        points = plan["points"]
        assert math.dist(points[0], (start.x, start.y)) < 0.2
        assert math.dist(points[-1], (room_b.x, room_b.y)) < 0.1  # the click, to a pixel
        assert plan["goal"] is not None
        # The polyline is on the canvas: the path's colour halfway along a drawn segment
        # well ahead of the robot (where nothing else is drawn over it), by the page's own
        # pose at that moment (on a loaded machine the robot may be far along by the time
        # a round trip from here would have looked).
        found = await page.wait_for_function(
            """() => {
              const ui = window.telebotUI, plan = ui.state.plan, p = ui.state.pose;
              if (!plan || !p || ui.drawn.plan < 2) return null;
              const pts = plan.points;
              let best = null, bestLen = 0;
              for (let i = pts.length - ui.drawn.plan; i + 1 < pts.length; i++) {
                const [ax, ay] = pts[i], [bx, by] = pts[i + 1];
                const len = Math.hypot(bx - ax, by - ay);
                if (len > bestLen && Math.hypot(ax - p.x, ay - p.y) > 1.5) { best = i; bestLen = len; }
              }
              if (best === null) return null;
              const [ax, ay] = pts[best], [bx, by] = pts[best + 1];
              const [sx, sy] = ui.worldToScreen((ax + bx) / 2, (ay + by) / 2);
              const dpr = window.devicePixelRatio || 1;
              const c = document.getElementById('map');
              return Array.from(c.getContext('2d').getImageData(
                Math.round(sx * dpr), Math.round(sy * dpr), 1, 1).data);
            }""",
            timeout=10000,
        )
        pixel = await found.json_value()
        assert pixel[:3] == [0, 160, 160], pixel
        ARTIFACTS.mkdir(exist_ok=True)
        await page.screenshot(path=str(ARTIFACTS / "web_ui_plan.png"))
        # When the goal ends the robot sends an empty plan and the page draws none. Ended
        # here by a stop, not by a 10 m drive to room-b: the page's arrival is
        # test_a_click_moves_the_robot_there's, the empty plan after one test_plan.py's.
        assert (await rig.client.stop()).ok
        await page.wait_for_function(
            "() => window.telebotUI.state.goal?.status === 'cancelled'", timeout=10000
        )
        await page.wait_for_function(
            "() => window.telebotUI.state.plan?.points.length === 0"
            " && window.telebotUI.drawn.plan === 0",
            timeout=10000,
        )


@in_module_loop
async def test_a_key_press_stops_the_robot(tmp_path: Path) -> None:
    async with (
        robot_rig(tmp_path, max_linear_speed=LASTING_SPEED) as rig,
        browser_page(rig.ui.url) as page,
    ):
        await page_ready(page)
        await drive_forward(rig)
        await page.locator("#map").focus()
        rig.zeroed.clear()  # only the stop this key causes counts
        await page.keyboard.press("k")
        await wait_for(lambda: rig.zeroed, timeout=2.0 + SLACK, what="the base stopped")
        pressed = (await page.evaluate("() => window.telebotUI.stats.keyTimes"))[-1] / 1000
        delay = rig.zeroed[0] - pressed
        # The page's clock (performance.timeOrigin + now()) and Python's time.time() are
        # both wall clock but may disagree by a millisecond or so: allow that much below 0.
        # The bound only shows that the key caused the stop; how fast it is (target:
        # p99 30 ms) is bench/ui.py's to measure, not a pass/fail test's on a shared machine.
        assert -0.005 <= delay < 0.5 + SLACK, f"stopped {delay * 1000:.1f} ms after the key"
        assert rig.nav.velocity().linear == 0.0
        assert rig.stops() == [(USER, "key")]  # the audit log says who, and how
        await page.wait_for_function("() => window.telebotUI.state.safety?.armed === false")
        assert "stopped" in await page.inner_text("#safety")
        # Re-arm from the page.
        await page.click("#arm")
        await page.wait_for_function("() => window.telebotUI.state.safety?.armed === true")


@in_module_loop
async def test_escape_in_the_chat_input_stops_but_typing_does_not(tmp_path: Path) -> None:
    async with (
        robot_rig(tmp_path, max_linear_speed=LASTING_SPEED) as rig,
        browser_page(rig.ui.url) as page,
    ):
        await page_ready(page)
        await drive_forward(rig)
        await page.fill("#chat-input", "")
        await page.type("#chat-input", "hello")
        await asyncio.sleep(0.1)
        assert rig.nav.velocity().linear > 0.0 and not rig.zeroed
        await page.keyboard.press("Escape")
        await wait_for(lambda: rig.zeroed, timeout=2.0 + SLACK, what="the base stopped")
        assert rig.stops() == [(USER, "key")]


@in_module_loop
async def test_a_chat_command_round_trip(rig: Rig) -> None:
    async with browser_page(rig.ui.url) as page:
        await page_ready(page)
        await page.fill("#chat-input", "where")
        await page.press("#chat-input", "Enter")
        await page.wait_for_function(
            "() => window.telebotUI.state.chat.some(m => m.final)", timeout=10000
        )
        replies = await page.evaluate("() => window.telebotUI.state.chat")
        assert replies[-1]["ok"], replies
        log_text = await page.inner_text("#chat-log")
        assert "> where" in log_text and replies[-1]["text"] in log_text


@in_module_loop
async def test_video_frames_arrive_and_the_camera_switches(rig: Rig) -> None:
    async with browser_page(rig.ui.url) as page:
        await page_ready(page)
        await page.wait_for_function("() => window.telebotUI.state.frames >= 5", timeout=10000)
        # Each frame replaces the image's source: its size is 0 until that one decodes.
        # Read in the same turn as the check: the next frame's source resets the size to 0.
        decoded = await page.wait_for_function(
            "() => { const v = document.getElementById('video');"
            " return v.naturalWidth > 0 && [v.naturalWidth, v.naturalHeight]; }"
        )
        size = await decoded.json_value()
        # The camera's 320 × 240, or scaled down by the rate control on a loaded machine.
        assert 0 < size[0] <= 320 and size[0] * 3 == size[1] * 4, size
        first = await page.evaluate("() => window.telebotUI.state.camera")
        other = "usercam" if first == "navcam" else "navcam"
        await page.click(f"#{other}")
        await page.wait_for_function(
            f"() => window.telebotUI.state.camera === '{other}'", timeout=10000
        )
        assert int(await page.inner_text("#fps")) > 0


@in_module_loop
async def test_closing_the_page_while_driving_stops_the_robot(tmp_path: Path) -> None:
    async with (
        robot_rig(tmp_path, max_linear_speed=LASTING_SPEED) as rig,
        browser_page(rig.ui.url) as page,
    ):
        await page_ready(page)
        await drive_forward(rig)
        await page.close()
        await wait_for(lambda: rig.zeroed, timeout=3.0 + SLACK, what="the base stopped")
        assert rig.nav.velocity().linear == 0.0
        await wait_for(lambda: rig.stops(), timeout=3.0 + SLACK, what="the stop in the audit log")
        # The page stops the robot itself as it goes (pagehide), and the server stops it when
        # the page's socket closes: whichever comes first is alice's. (Chromium may tear the
        # page down before its last message leaves: seen in two full runs of the suite. The
        # pagehide stop on its own: test_browser_e2e.py and test_web_port.py.)
        who, how = rig.stops()[0]
        assert who == USER and how in ("page_hidden", "tab_closed"), rig.stops()


@in_module_loop
async def test_a_page_that_dies_while_driving_is_stopped_by_the_client(tmp_path: Path) -> None:
    async with (
        robot_rig(tmp_path, max_linear_speed=LASTING_SPEED) as rig,
        browser_page(rig.ui.url) as page,
    ):
        await page_ready(page)
        cdp = await page.context.new_cdp_session(page)
        await drive_forward(rig)
        # The renderer crashes: no pagehide, no last message; only its websocket goes.
        # (Page.crash never answers: its page is gone.)
        with contextlib.suppress(Exception):
            await asyncio.wait_for(cdp.send("Page.crash"), timeout=1.0)
        await wait_for(lambda: rig.zeroed, timeout=3.0 + SLACK, what="the base stopped")
        assert rig.ui.close_stops == 1
        assert rig.nav.velocity().linear == 0.0
        await wait_for(lambda: rig.stops(), timeout=3.0 + SLACK, what="the stop in the audit log")
        assert rig.stops() == [(USER, "tab_closed")]


@in_module_loop
async def test_an_observer_sees_the_page_with_driving_disabled_and_may_stop(
    tmp_path: Path,
) -> None:
    async with robot_rig(tmp_path, role=Role.OBSERVER) as rig, browser_page(rig.ui.url) as page:
        await page_ready(page)
        assert "observer" in await page.inner_text("#role")
        for button in ("arm", "take", "navcam", "usercam"):
            assert await page.is_disabled(f"#{button}")
        assert await page.is_enabled("#stop")
        # A click on the map is no goal for an observer.
        box = await page.locator("#map").bounding_box()
        await page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
        await asyncio.sleep(0.2)
        assert await page.evaluate("() => window.telebotUI.state.goal") is None
        await page.click("#stop")
        await page.wait_for_function("() => window.telebotUI.state.safety?.armed === false")


def test_install_browser_script_is_idempotent() -> None:
    script = Path(__file__).resolve().parent.parent / ".ci" / "install-browser"
    assert os.access(script, os.X_OK)
    if shutil.which("bash") and Path(CHROMIUM).exists():
        import subprocess

        result = subprocess.run([str(script)], capture_output=True, text=True, timeout=30)
        assert result.returncode == 0, result.stderr
