"""Driving by hand on the page (static/drive.js) in Debian's chromium: the arrow keys and
WASD, a gamepad (the Gamepad API, faked by an init script) with its deadman button, and
the on-screen joystick of a touch phone (390 × 844).

Most tests drive the page through a stand-in port (as test_web_port.py: it records what
the page sends, as a gateway-served page's port would get it); one drives the simulated
robot through the local ``telebot-user ui`` (server.py) and reads the base's velocity.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp

from rig import SLACK
from test_web_phone import LANDSCAPE, PORTRAIT, box, inside, overlap
from test_web_setup import start_page_server

# _chromium: one chromium for the module; _no_leaked_tasks: the leak check in its loop.
from test_web_ui import (
    _chromium,  # noqa: F401
    _no_leaked_tasks,  # noqa: F401
    arm,
    browser_page,
    in_module_loop,
    page_ready,
    robot_rig,
    shared_browser,
    wait_for,
)

FAKE_PORT = """
window.fake = { sent: [], h: null };
window.telebotPort = {
  connect(h) { window.fake.h = h; h.open(); },
  send(m) { window.fake.sent.push(m); return true; },
  sendMedia() { return true; },
};
"""

#: A gamepad in the standard mapping, its stick and buttons set by the test.
FAKE_GAMEPAD = """
window.fakePad = { id: "test pad", index: 0, connected: true, mapping: "standard",
  axes: [0, 0, 0, 0], buttons: Array.from({length: 17}, () => ({pressed: false, value: 0})) };
Object.defineProperty(navigator, "getGamepads",
  { value: () => [window.fakePad, null, null, null], configurable: true });
"""


def hello(may_drive: bool = True) -> dict[str, Any]:
    return {
        "type": "hello",
        "robot": "guiabot",
        "user": "alice",
        "role": "driver" if may_drive else "observer",
        "may_drive": may_drive,
        "map": None,
    }


@contextlib.asynccontextmanager
async def port_page(*, phone: bool = False, init: str = "") -> AsyncIterator[Any]:
    """The robot page (as a gateway serves it) on the stand-in port, said hello to."""
    browser = shared_browser()
    assert browser is not None, "run in the module's loop"
    options: dict[str, Any] = (
        {"viewport": PORTRAIT, "has_touch": True, "is_mobile": True, "device_scale_factor": 2}
        if phone
        else {"viewport": {"width": 1280, "height": 800}}
    )
    async with start_page_server() as url:
        context = await browser.new_context(**options)
        try:
            page = await context.new_page()
            await page.add_init_script(FAKE_PORT + init)  # before app.js runs
            await page.goto(url + "call")
            await page.wait_for_function("() => window.fake.h && window.telebotUI.drive")
            await feed(page, hello())
            yield page
        finally:
            await context.close()


async def feed(page: Any, message: dict[str, Any]) -> None:
    await page.evaluate("(m) => window.fake.h.message(m)", message)


async def sent(page: Any, kind: str) -> list[dict[str, Any]]:
    value: list[dict[str, Any]] = await page.evaluate(
        "(t) => window.fake.sent.filter((m) => m.type === t)", kind
    )
    return value


async def ticks_pass(page: Any, n: int = 4) -> None:
    """Wait until the page's 20 Hz timer has run ``n`` more times (anything it would send
    by then has been sent)."""
    start = await page.evaluate("() => window.telebotUI.drive.ticks")
    await page.wait_for_function(f"() => window.telebotUI.drive.ticks >= {start + n}")


async def wait_drive(page: Any, condition: str) -> None:
    """Wait until the page has sent a drive message ``m`` for which ``condition`` holds."""
    await page.wait_for_function(
        f"() => window.fake.sent.some((m) => m.type === 'drive' && ({condition}))"
    )


def zero(m: dict[str, Any]) -> bool:
    return m["linear"] == 0 and m["angular"] == 0


@in_module_loop
async def test_arrow_keys_and_wasd_drive_while_held_and_keyup_releases() -> None:
    async with port_page() as page:
        await page.keyboard.down("ArrowUp")
        # Held: sent again and again (20 Hz), forward at the page's full speed.
        await page.wait_for_function(
            "() => window.fake.sent.filter((m) => m.type === 'drive').length >= 4"
        )
        assert all(
            m == {"type": "drive", "linear": 0.5, "angular": 0} for m in await sent(page, "drive")
        )
        await page.keyboard.down("a")  # and turn left (counter-clockwise)
        await wait_drive(page, "m.linear === 0.5 && m.angular === 1")
        await page.keyboard.up("ArrowUp")
        await wait_drive(page, "m.linear === 0 && m.angular === 1")
        await page.keyboard.up("a")
        await wait_drive(page, "m.linear === 0 && m.angular === 0")
        await ticks_pass(page)
        drives = await sent(page, "drive")
        # One release, the last message: nothing after it.
        assert zero(drives[-1]) and sum(zero(m) for m in drives) == 1, drives[-3:]
        assert await sent(page, "stop") == [], "a drive key never stops"
        # Held while the window loses the focus (its keyup goes elsewhere): released.
        await page.keyboard.down("s")
        await wait_drive(page, "m.linear === -0.5")
        await page.evaluate("() => window.dispatchEvent(new Event('blur'))")
        await page.wait_for_function(
            "() => { const d = window.fake.sent.filter((m) => m.type === 'drive');"
            " return d[d.length - 1].linear === 0; }"
        )
        await ticks_pass(page)
        await page.keyboard.up("s")
        drives = await sent(page, "drive")
        assert zero(drives[-1]) and sum(zero(m) for m in drives) == 2, drives[-3:]
        # The robot's answers are shown.
        state = {"type": "drive_state", "seq": 9, "active": True, "code": "ok", "text": ""}
        await feed(page, {**state, "linear": 0.3, "angular": -0.5, "cap": 0.42})
        assert (await page.inner_text("#drive-state")).startswith("driving 0.30 m/s")
        text = "the robot is stopped: re-arm it"
        await feed(
            page,
            {**state, "active": False, "code": "not_armed", "text": text}
            | {"linear": 0, "angular": 0, "cap": 0},
        )
        assert await page.inner_text("#drive-state") == f"refused: {text}"
        await feed(
            page, {**state, "active": False, "code": "stale", "linear": 0, "angular": 0, "cap": 0}
        )
        assert (await page.inner_text("#drive-state")).startswith("stale")


@in_module_loop
async def test_any_other_key_stops_and_drive_keys_in_the_chat_box_do_not_drive() -> None:
    async with port_page() as page:
        await page.keyboard.down("ArrowUp")
        await wait_drive(page, "m.linear === 0.5")
        await page.keyboard.press("x")
        await page.wait_for_function("() => window.fake.sent.some((m) => m.type === 'stop')")
        await ticks_pass(page)
        after = await page.evaluate(
            "() => window.fake.sent.slice(window.fake.sent.findIndex((m) => m.type === 'stop'))"
        )
        assert after == [{"type": "stop", "how": "key"}], "nothing goes out after the stop"
        await page.keyboard.up("ArrowUp")
        # Typing in the chat box: the keys are the box's (no drive, no stop).
        await page.focus("#chat-input")
        for key in ("ArrowUp", "w", "ArrowLeft"):
            await page.keyboard.press(key)
        await ticks_pass(page)
        assert len(await sent(page, "stop")) == 1
        assert await page.input_value("#chat-input") == "w"
        # An observer's drive keys stop, as every key does.
        await page.evaluate("() => document.activeElement.blur()")
        await feed(page, hello(may_drive=False))
        count = len(await sent(page, "drive"))
        await page.keyboard.press("ArrowUp")
        await page.wait_for_function(
            "() => window.fake.sent.filter((m) => m.type === 'stop').length === 2"
        )
        assert len(await sent(page, "drive")) == count


@in_module_loop
async def test_the_gamepad_drives_only_while_its_deadman_button_is_held() -> None:
    async with port_page(init=FAKE_GAMEPAD) as page:
        # Stick forward and a little right, the deadman not held: nothing.
        await page.evaluate("() => { window.fakePad.axes[0] = 0.5; window.fakePad.axes[1] = -1; }")
        await ticks_pass(page)
        assert await sent(page, "drive") == []
        # RB held (the deadman): drives, forward and clockwise, at 20 Hz.
        await page.evaluate("() => { window.fakePad.buttons[5] = {pressed: true, value: 1}; }")
        await page.wait_for_function(
            "() => window.fake.sent.filter((m) => m.type === 'drive').length >= 3"
        )
        first = (await sent(page, "drive"))[0]
        assert first["linear"] == 0.5 and -1 < first["angular"] < 0, first
        # Let go of the deadman with the stick still pushed: released, then nothing.
        await page.evaluate("() => { window.fakePad.buttons[5] = {pressed: false, value: 0}; }")
        await wait_drive(page, "m.linear === 0 && m.angular === 0")
        await ticks_pass(page)
        drives = await sent(page, "drive")
        assert zero(drives[-1]) and sum(zero(m) for m in drives) == 1


@in_module_loop
async def test_the_touch_joystick_drives_and_lifting_the_finger_releases() -> None:
    async with port_page(phone=True) as page:
        joystick, stop = await box(page, "#joystick"), await box(page, "#stop")
        # On the phone's screen beside STOP: not over it, STOP still on top at its centre.
        assert inside(joystick, PORTRAIT) and not overlap(joystick, stop), (joystick, stop)
        assert joystick["width"] >= 80, joystick
        cx, cy = stop["x"] + stop["width"] / 2, stop["y"] + stop["height"] / 2
        assert await page.evaluate(f"() => document.elementFromPoint({cx}, {cy}).id") == "stop"
        x = joystick["x"] + joystick["width"] / 2
        y = joystick["y"] + joystick["height"] / 2
        cdp = await page.context.new_cdp_session(page)

        async def touch(kind: str, points: list[dict[str, float]]) -> None:
            await cdp.send("Input.dispatchTouchEvent", {"type": kind, "touchPoints": points})

        await touch("touchStart", [{"x": x, "y": y}])
        await touch("touchMove", [{"x": x, "y": y - joystick["height"] / 2}])  # full forward
        await wait_drive(page, "m.linear === 0.5 && m.angular === 0")
        await touch("touchMove", [{"x": x + joystick["width"] / 2, "y": y}])  # turn right
        await wait_drive(page, "m.linear === 0 && m.angular === -1")
        assert await sent(page, "stop") == []
        await touch("touchEnd", [])
        await wait_drive(page, "m.linear === 0 && m.angular === 0")
        await ticks_pass(page)
        drives = await sent(page, "drive")
        assert zero(drives[-1]) and sum(zero(m) for m in drives) == 1
        # Landscape: still on screen, clear of STOP.
        await page.set_viewport_size(LANDSCAPE)
        await page.wait_for_function(f"() => window.innerWidth === {LANDSCAPE['width']}")
        joystick, stop = await box(page, "#joystick"), await box(page, "#stop")
        assert inside(joystick, LANDSCAPE) and not overlap(joystick, stop), (joystick, stop)
        # An observer has no joystick.
        await feed(page, hello(may_drive=False))
        await page.wait_for_selector("#joystick", state="hidden")


@in_module_loop
async def test_keys_drive_the_simulated_robot_through_the_local_client(tmp_path: Path) -> None:
    """End to end through ``telebot-user ui`` (server.py): held, the robot moves; let go,
    it stops at once, still armed (a release is no stop); bad drive messages get one line."""
    async with robot_rig(tmp_path) as rig, browser_page(rig.ui.url) as page:
        await arm(rig)
        await page_ready(page)
        await page.wait_for_function("() => window.telebotUI.state.safety?.armed")
        start = rig.nav.pose().pose
        await page.keyboard.down("ArrowUp")
        try:
            await wait_for(lambda: rig.nav.velocity().linear > 0.2, timeout=10 + SLACK)
        except AssertionError:
            shown = await page.inner_text("#drive-state")
            raise AssertionError(f"not driving: {rig.client.drive_state}; page: {shown}") from None
        await page.wait_for_function(
            "() => document.getElementById('drive-state').textContent.startsWith('driving')"
        )
        # Forward (+x on the small map's bottom corridor) while held.
        await wait_for(lambda: rig.nav.pose().pose.x - start.x > 0.1, what="the robot moving on")
        await page.keyboard.up("ArrowUp")
        await wait_for(lambda: rig.nav.velocity().linear == 0.0, what="the robot stopped")
        await page.wait_for_function(
            "() => document.getElementById('drive-state').textContent === 'released'"
        )
        assert rig.safety.state().armed and rig.stops() == [], "a release neither stops nor latches"
        # Bad drive messages from a page: one line each, the call goes on.
        async with aiohttp.ClientSession() as http, http.ws_connect(rig.ui.url + "ws") as ws:
            for bad in ({"type": "drive", "linear": "fast", "angular": 0}, {"type": "drive"}):
                await ws.send_json(bad)
                reply: dict[str, Any] = {}
                while reply.get("type") != "error":  # past the greeting, pictures, poses
                    msg = await ws.receive(timeout=10 + SLACK)
                    reply = json.loads(msg.data) if msg.type == aiohttp.WSMsgType.TEXT else {}
                assert reply["text"] == "a drive needs finite numbers linear, angular", reply
            assert rig.safety.state().armed  # (closing this armed page stops it: the old rule)
