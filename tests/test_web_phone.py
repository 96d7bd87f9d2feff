"""The web page on a phone: Debian's chromium at 390 × 844 with touch (Playwright's
``is_mobile`` and ``has_touch``), against the local ``telebot-user ui`` (the robot and the
client in this process on a memory hub, as in test_web_ui.py).

Layout (map, video and STOP in view without scrolling, portrait and landscape), a tap on
the map is a goal the robot reaches, a touch on the video while the robot moves stops it,
and a page hidden or frozen while it drives stops it (``how``: ``page_hidden``).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import playwright.async_api as playwright_api

from conftest import USER
from rig import SLACK

# _chromium: one chromium for the module; _no_leaked_tasks: the leak check in its loop.
from test_web_ui import (
    ARTIFACTS,
    LASTING_SPEED,
    Rig,
    _chromium,  # noqa: F401
    _no_leaked_tasks,  # noqa: F401
    arm,
    drive_forward,
    in_module_loop,
    launch_chromium,
    page_ready,
    robot_rig,
    shared_browser,
    wait_for,
)

PORTRAIT = {"width": 390, "height": 844}
LANDSCAPE = {"width": 844, "height": 390}


@contextlib.asynccontextmanager
async def phone_page(url: str) -> AsyncIterator[Any]:
    """A headless chromium page at ``url`` that is a phone: 390 × 844, touch, mobile (in
    the module's chromium when the test runs in its loop, else in one of its own)."""
    browser = shared_browser()
    if browser is not None:
        context = await browser.new_context(
            viewport=PORTRAIT, has_touch=True, is_mobile=True, device_scale_factor=2
        )
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
            context = await browser.new_context(
                viewport=PORTRAIT, has_touch=True, is_mobile=True, device_scale_factor=2
            )
            page = await context.new_page()
            await page.goto(url)
            yield page
        finally:
            await browser.close()


async def box(page: Any, selector: str, timeout: float = 10.0) -> dict[str, float]:
    """Where ``selector`` is on the page, once it is displayed (a page shows some parts
    only after its first messages: the joystick once it knows it may drive)."""
    locator = page.locator(selector)
    try:
        await locator.wait_for(state="visible", timeout=timeout * 1000)
    except Exception as exc:  # playwright's TimeoutError
        raise AssertionError(f"{selector} is not displayed within {timeout:g} s") from exc
    value = await locator.bounding_box()
    assert value is not None, f"{selector} is not displayed"
    return dict(value)


def inside(b: dict[str, float], size: dict[str, int]) -> bool:
    return (
        b["x"] >= 0
        and b["y"] >= 0
        and b["x"] + b["width"] <= size["width"] + 0.5
        and b["y"] + b["height"] <= size["height"] + 0.5
    )


def overlap(a: dict[str, float], b: dict[str, float]) -> bool:
    return not (
        a["x"] + a["width"] <= b["x"]
        or b["x"] + b["width"] <= a["x"]
        or a["y"] + a["height"] <= b["y"]
        or b["y"] + b["height"] <= a["y"]
    )


@in_module_loop
async def test_map_video_and_stop_are_in_view_in_portrait_and_landscape(tmp_path: Path) -> None:
    async with robot_rig(tmp_path) as rig, phone_page(rig.ui.url) as page:
        await page_ready(page)
        await page.wait_for_function("() => window.telebotUI.state.frames >= 2", timeout=15000)
        ARTIFACTS.mkdir(exist_ok=True)
        for name, size in (("portrait", PORTRAIT), ("landscape", LANDSCAPE)):
            await page.set_viewport_size(size)
            await page.wait_for_function(
                f"() => window.innerWidth === {size['width']}"
                f" && document.getElementById('map').clientWidth > 0"
            )
            # Nothing scrolled: what is checked is what the phone shows on opening.
            assert await page.evaluate("() => [window.scrollX, window.scrollY]") == [0, 0]
            stop, map_, video = (
                await box(page, "#stop"),
                await box(page, "#map"),
                await box(page, "#video"),
            )
            for what, b in (("STOP", stop), ("map", map_), ("video", video)):
                assert inside(b, size), f"{name}: {what} not all in view: {b}"
            # A STOP a thumb finds (at least 10 mm: ~ 40 CSS px), over neither map nor video.
            assert stop["width"] >= 80 and stop["height"] >= 80, (name, stop)
            assert not overlap(stop, map_) and not overlap(stop, video), (name, stop)
            # The map and the picture are big enough to use, not slivers.
            assert map_["width"] >= 0.45 * size["width"] and map_["height"] >= 150, (name, map_)
            assert video["height"] >= 150, (name, video)
            # STOP is on top where it is (nothing covers it): a tap there reaches it.
            cx, cy = stop["x"] + stop["width"] / 2, stop["y"] + stop["height"] / 2
            top = await page.evaluate(f"() => document.elementFromPoint({cx}, {cy}).id")
            assert top == "stop", (name, top)
            await page.screenshot(path=str(ARTIFACTS / f"web_phone_{name}.png"))


@in_module_loop
async def test_a_tap_on_the_map_is_a_goal_the_robot_reaches(tmp_path: Path) -> None:
    async with robot_rig(tmp_path) as rig, phone_page(rig.ui.url) as page:
        await arm(rig)
        await page_ready(page)
        await page.wait_for_function("() => window.telebotUI.state.safety?.armed")
        target = (4.0, 1.2)  # bottom corridor of the small map, in sight of "start"
        sx, sy = await page.evaluate(f"() => window.telebotUI.worldToScreen{target}")
        b = await box(page, "#map")
        await page.touchscreen.tap(b["x"] + sx, b["y"] + sy)
        await page.wait_for_function(
            "() => window.telebotUI.state.goal?.status === 'succeeded'", timeout=30000
        )
        sent = await page.evaluate("() => window.telebotUI.state.goal")
        assert sent["yaw"] is None  # a tap: no heading
        scale = await page.evaluate(
            "() => { const a = window.telebotUI.screenToWorld(0, 0);"
            " const b = window.telebotUI.screenToWorld(1, 0); return b[0] - a[0]; }"
        )
        assert math.dist((sent["x"], sent["y"]), target) <= 1.5 * scale + 1e-6
        real = rig.nav.pose().pose
        assert math.dist((real.x, real.y), (sent["x"], sent["y"])) < 0.15


async def stopped_by(rig: Rig, how: str) -> None:
    await wait_for(lambda: rig.zeroed, timeout=3.0 + SLACK, what="the base stopped")
    assert rig.nav.velocity().linear == 0.0
    await wait_for(lambda: rig.stops(), timeout=3.0 + SLACK, what="the stop in the audit log")
    assert rig.stops()[-1] == (USER, how), rig.stops()


@in_module_loop
async def test_touching_the_video_or_stop_while_moving_stops_the_robot(tmp_path: Path) -> None:
    async with (
        robot_rig(tmp_path, max_linear_speed=LASTING_SPEED) as rig,
        phone_page(rig.ui.url) as page,
    ):
        await page_ready(page)
        await page.wait_for_function("() => window.telebotUI.state.frames >= 1", timeout=15000)
        # At rest, a touch on the video is just a touch.
        await page.tap("#video")
        assert await page.evaluate("() => window.telebotUI.stats.keyTimes.length") == 0
        await drive_forward(rig)
        await page.wait_for_function("() => window.telebotUI.state.pose?.v > 0.1")
        rig.zeroed.clear()
        await page.tap("#video")
        await stopped_by(rig, "touch")
        await drive_forward(rig)
        rig.zeroed.clear()
        await page.tap("#stop")
        await stopped_by(rig, "button")


HIDE = """() => {
  Object.defineProperty(document, 'visibilityState', {value: 'hidden', configurable: true});
  Object.defineProperty(document, 'hidden', {value: true, configurable: true});
  document.dispatchEvent(new Event('visibilitychange'));
}"""
SHOW = """() => {
  Object.defineProperty(document, 'visibilityState', {value: 'visible', configurable: true});
  Object.defineProperty(document, 'hidden', {value: false, configurable: true});
  document.dispatchEvent(new Event('visibilitychange'));
}"""


@in_module_loop
async def test_a_page_hidden_or_frozen_while_driving_stops_the_robot(tmp_path: Path) -> None:
    async with (
        robot_rig(tmp_path, max_linear_speed=LASTING_SPEED) as rig,
        phone_page(rig.ui.url) as page,
    ):
        await page_ready(page)
        await page.wait_for_function("() => window.telebotUI.state.safety")
        # Disarmed and at rest: hiding the page stops nothing (the robot cannot move).
        await page.evaluate(HIDE)
        await page.evaluate(SHOW)
        assert await page.evaluate("() => window.telebotUI.stats.hides") == ["hidden"]
        assert await page.evaluate("() => window.telebotUI.stats.keyTimes.length") == 0
        # Driving: another app in front (visibilitychange to hidden).
        await drive_forward(rig)
        await page.wait_for_function("() => window.telebotUI.mightMove()")
        rig.zeroed.clear()
        await page.evaluate(HIDE)
        await stopped_by(rig, "page_hidden")
        await page.evaluate(SHOW)
        # Driving: the phone freezes the page (the lifecycle event a locked phone's browser
        # fires; CDP's setWebLifecycleState freezes only a background page, so it is
        # dispatched here as the browser would).
        await drive_forward(rig)
        await page.wait_for_function("() => window.telebotUI.state.safety?.armed")
        rig.zeroed.clear()
        await page.evaluate("() => document.dispatchEvent(new Event('freeze'))")
        await stopped_by(rig, "page_hidden")
        assert await page.evaluate("() => window.telebotUI.stats.hides") == [
            "hidden",
            "hidden",
            "frozen",
        ]
