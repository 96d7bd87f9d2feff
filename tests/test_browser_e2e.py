"""The whole browser path, for real: a phone's chromium, the robot's own gateway, the robot.

One rig for the module: ``telebot-robot run`` in its own process (the simulator, its
rendered camera as H.264, ``[gateway]`` on 127.0.0.1 with its self-signed certificate),
and Debian's chromium as a phone (390 × 844, touch, mobile), which trusts nothing it was
not told to: only the certificate warning is waved through (``ignore_https_errors``); the
page is still a secure context (https), as WebCodecs and IndexedDB keys need.

Each browser user starts from nothing: the start page (``/``) makes the key, the robot's
admin runs ``telebot-robot invite NAME --role ROLE --url …`` (the real command, in its own
process), the browser opens the printed link, which registers its key with the robot and
pins the robot's; the call button opens the robot page (``/call?robot=…``), whose client
(the bundle) calls the robot through the gateway, by WebTransport (HTTP/3 over QUIC, the
page's default; dave's browser, without it, by two websockets). alice drives: a tap on the map is a goal
the robot reaches, STOP stops it, and so do a touch on the video while it moves and the
page hidden while it moves; the touch joystick drives it by hand, and lifting the finger
releases it. When the network goes while alice drives (her page's
WebTransport sessions and websockets closed, new ones failing, until it comes back), the robot's deadman stops it,
her page says so at once, and once the call is back shows it latched with re-arm as the
one action. bob, invited as an observer in a second browser context, sees who drives,
cannot drive, and may stop.

What the robot did is read from the robot, not from the page: olga (an observer in this
process, over zenoh) follows its pose and safety state, and its audit log says who stopped
it and how.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import re
import sys
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import playwright.async_api as playwright_api
import pytest
import pytest_asyncio

from rig import FAST_SIM, GENEROUS_TIMEOUT, SLACK, Daemon
from telebot.services.client import RobotClient
from telebot.testing.net import free_port
from test_web_phone import PORTRAIT, box
from test_web_ui import ARTIFACTS, CHROMIUM

# The first test also sets the rig up (a daemon, chromium, alice's onboarding): more than
# the suite's 60 s may pass on a loaded machine before it is done.
pytestmark = [pytest.mark.asyncio(loop_scope="module"), pytest.mark.timeout(180)]

ROBOT = "guiabot"
#: The far ends of the small map's bottom corridor, and a point between them.
FAR_ENDS = ((1.0, 1.2), (10.5, 1.2))
NEAR_GOAL = (4.0, 1.2)
#: Generous: a loaded 2-core machine runs a robot, a video encoder and two browsers.
PAGE_MS = int((30 + 10 * SLACK) * 1000)
ROBOT_S = 30.0 + 10 * SLACK


#: In every page, before its scripts: ``window.testNetwork.cut()`` closes the page's
#: WebTransport sessions and websockets (its gateway link) and makes new ones fail at once,
#: as with the network gone, until ``restore()``.
NETWORK_SWITCH = """
(() => {
  const Real = window.WebSocket;
  const net = { offline: false, sockets: [] };
  net.cut = () => { net.offline = true; for (const s of net.sockets.splice(0)) s.close(); };
  net.restore = () => { net.offline = false; };
  window.testNetwork = net;
  window.WebSocket = class extends Real {
    constructor(...args) {
      if (net.offline) throw new DOMException("the network is gone (a test)", "NetworkError");
      super(...args);
      net.sockets.push(this);
    }
  };
  const RealTransport = window.WebTransport;
  net.sessions = [];
  net.cut = () => {
    net.offline = true;
    for (const s of net.sockets.splice(0)) s.close();
    for (const s of net.sessions.splice(0)) s.close();
  };
  window.WebTransport = class extends RealTransport {
    constructor(...args) {
      if (net.offline) throw new DOMException("the network is gone (a test)", "NetworkError");
      super(...args);
      net.sessions.push(this);
      this.closed.finally(() => { this.ended = true; }).catch(() => {});
    }
  };
})();
"""


#: In every page, before its scripts: the in-browser client's calls drop after
#: GENEROUS_TIMEOUT of silence, as the robot's and every rig user's do, not the product's
#: 0.5 s (a loaded machine stalls Chromium for longer: its call dropped and came back again
#: and again, and each call that replaced one latched the robot, refused the arm or failed
#: the goal). The page's Endpoint has no option for it: its ``call`` sets it.
GENEROUS_CALLS = (
    """
((timeout) => {
  let telebot;
  Object.defineProperty(window, "telebot", {
    configurable: true,
    get: () => telebot,
    set: (value) => {
      telebot = value;
      const call = value.Endpoint.prototype.call;
      value.Endpoint.prototype.call = function (...args) {
        this.timeout = timeout;
        return call.apply(this, args);
      };
    },
  });
})("""
    + repr(GENEROUS_TIMEOUT)
    + ");"
)


@dataclass
class User:
    """One browser user: a context of their own (their own IndexedDB) and its page."""

    name: str
    context: Any
    page: Any
    contact_line: str = ""
    link: str = ""
    pinned: list[dict[str, Any]] = field(default_factory=list)


@dataclass
class E2E:
    daemon: Daemon
    url: str
    browser: Any
    #: olga, an observer in this process: what the robot reports, independently of any page.
    monitor: RobotClient
    users: dict[str, User] = field(default_factory=dict)
    #: Errors the pages threw (none expected).
    page_errors: list[str] = field(default_factory=list)

    def stops(self) -> list[tuple[str, str]]:
        """Who stopped the robot and how, from its audit log, in order."""
        return [(r["who"], r["how"]) for r in self.daemon.audit() if r["what"] == "stop"]


async def poll(
    predicate: Callable[[], Any], what: str, timeout: float = ROBOT_S, every: float = 0.05
) -> Any:
    """Wait until ``predicate()`` is truthy (never a fixed sleep); its value."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")
        await asyncio.sleep(every)


async def invite(e2e: E2E, name: str, role: str) -> str:
    """``telebot-robot invite NAME --role ROLE --url URL`` as the robot's admin runs it;
    the link it prints."""
    command = Path(sys.executable).with_name("telebot-robot")
    proc = await asyncio.create_subprocess_exec(
        str(command),
        "invite",
        name,
        "--role",
        role,
        "--url",
        e2e.url,
        "--home",
        str(e2e.daemon.robot_home),
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    out, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode == 0, err.decode()
    links = [line for line in out.decode().splitlines() if line.startswith(e2e.url + "#invite=")]
    assert len(links) == 1, out.decode()
    return links[0]


async def join(e2e: E2E, name: str, role: str, *, init_script: str = "") -> User:
    """A new phone: make a key on the start page, open an invite, accept it, call
    (``init_script``: more of the page's world, set before its scripts)."""
    context = await e2e.browser.new_context(
        viewport=PORTRAIT,
        has_touch=True,
        is_mobile=True,
        device_scale_factor=2,
        ignore_https_errors=True,  # the robot's self-signed certificate; still https
    )
    await context.add_init_script(NETWORK_SWITCH)
    await context.add_init_script(GENEROUS_CALLS)
    if init_script:
        await context.add_init_script(init_script)
    page = await context.new_page()
    page.on("pageerror", lambda error: e2e.page_errors.append(f"{name}: {error}"))
    user = User(name, context, page)
    e2e.users[name] = user
    await page.goto(e2e.url)
    assert await page.evaluate("() => window.isSecureContext")
    await page.wait_for_selector("#create-key", state="visible")
    await page.fill("#new-name", name)
    await page.tap("#create-key")
    await page.wait_for_selector("#contact-line", state="visible")
    user.contact_line = await page.inner_text("#contact-line")
    user.link = await invite(e2e, name, role)
    await page.goto(user.link)
    await page.wait_for_selector("#invite", state="visible")
    await page.wait_for_function("() => !document.getElementById('accept-invite').disabled")
    await page.tap("#accept-invite")
    await page.wait_for_selector(f"li[data-robot={ROBOT}]", timeout=PAGE_MS)
    user.pinned = await page.evaluate("() => window.telebotSetup.robots")
    error = await page.evaluate("() => window.telebotSetup.error")
    assert error == "", error
    await page.tap(f"li[data-robot={ROBOT}] .call")
    await page.wait_for_url(re.compile(rf"/call\?robot={ROBOT}$"))
    await page.wait_for_function(
        "() => window.telebotUI && window.telebotUI.mapReady() && window.telebotUI.state.pose"
        " && window.telebotUI.state.role",
        timeout=PAGE_MS,
    )
    return user


@contextlib.asynccontextmanager
async def e2e_rig(base: Path) -> AsyncIterator[E2E]:
    # The daemon's own contacts: carol (a driver who never calls) and olga (an observer,
    # the monitor). alice and bob come by invites only.
    daemon = Daemon(
        base,
        driver="carol",
        observer="olga",
        sim={**FAST_SIM, "camera_width": 320, "camera_height": 240},
    )
    port = free_port()
    with daemon.robot_config.open("a") as config:
        config.write(
            "[video]\nwidth = 320\nheight = 240\nmax_fps = 15\n"
            "[screen]\nenabled = false\n"
            f'[gateway]\nlisten = "127.0.0.1"\nport = {port}\n'
        )
    await asyncio.to_thread(daemon.start)
    try:
        async with (
            daemon.connect(daemon.observer_home, timeout=30) as monitor,
            playwright_api.async_playwright() as pw,
        ):
            args = ["--no-sandbox"] if os.geteuid() == 0 else []
            browser = await pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=args)
            try:
                e2e = E2E(daemon, f"https://127.0.0.1:{port}/", browser, monitor)
                await join(e2e, "alice", "driver")
                yield e2e
            finally:
                await browser.close()
    finally:
        await asyncio.to_thread(daemon.stop)
        # Kept beside its audit log in pytest's tmp dir: what the daemon said, for a miss.
        (base / "daemon.stderr").write_text(daemon.process.stderr(), encoding="utf-8")


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def e2e(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[E2E]:
    async with e2e_rig(tmp_path_factory.mktemp("browser-e2e")) as value:
        yield value


# --- helpers on the robot and the pages ------------------------------------------------------


def at_rest(e2e: E2E) -> bool:
    pose = e2e.monitor.latest_pose.value
    return pose is not None and pose.v == 0.0 and pose.w == 0.0


def armed(e2e: E2E) -> bool | None:
    status = e2e.monitor.latest_safety.value
    return None if status is None else status.armed


async def tap_map(page: Any, x: float, y: float) -> None:
    """A finger on the map at world point (x, y)."""
    sx, sy = await page.evaluate("([x, y]) => window.telebotUI.worldToScreen(x, y)", [x, y])
    b = await box(page, "#map")
    await page.touchscreen.tap(b["x"] + sx, b["y"] + sy)


async def arm_from(page: Any) -> None:
    await page.tap("#arm")
    await page.wait_for_function("() => window.telebotUI.state.safety?.armed", timeout=PAGE_MS)


async def drive_far(e2e: E2E, page: Any) -> None:
    """Re-arm from alice's page and tap the far end of the corridor; wait until it moves."""
    await arm_from(page)
    await poll(lambda: armed(e2e), "the robot armed")
    pose = e2e.monitor.latest_pose.value
    assert pose is not None
    target = max(FAR_ENDS, key=lambda p: math.dist(p, (pose.x, pose.y)))
    await tap_map(page, *target)

    def moving() -> bool:
        now = e2e.monitor.latest_pose.value
        return now is not None and abs(now.v) > 0.3

    await poll(moving, "the robot moving")


async def stopped_by(e2e: E2E, who: str, how: str) -> None:
    """The robot comes to rest, latched (not armed), and its audit log says who and how."""
    await poll(lambda: at_rest(e2e), "the robot at rest")
    await poll(lambda: armed(e2e) is False, "the robot latched stopped")
    await poll(lambda: e2e.stops(), "a stop in the audit log")
    assert e2e.stops()[-1] == (who, how), e2e.stops()


# --- the tests ---------------------------------------------------------------------------------


async def test_a_new_phone_makes_a_key_redeems_an_invite_and_calls(e2e: E2E) -> None:
    alice = e2e.users["alice"]
    page = alice.page
    assert re.fullmatch(r"telebot-x25519 [A-Za-z0-9_-]{43} alice", alice.contact_line)
    # The invite pinned the robot's key (the one the daemon has) and registered alice's.
    robot_key = alice.link.split("key=", 1)[1]
    assert [(r["name"], r["key"], r["via"]) for r in alice.pinned] == [(ROBOT, robot_key, "invite")]
    contact = e2e.daemon.robot_home / "contacts.toml"
    assert alice.contact_line.split()[1] in contact.read_text()
    # The robot page: alice, a driver, in the call (the robot's roster says so).
    assert "driver" in await page.inner_text("#role")
    await page.wait_for_function(
        "() => (window.telebotUI.state.roster || []).some(u => u.name === 'alice' && u.you)",
        timeout=PAGE_MS,
    )
    # The map is drawn: free cells light, walls dark, the robot blue.
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
    # Video: pictures the browser decoded (WebCodecs H.264 here; JPEG where it has none).
    await page.wait_for_function(
        "() => window.telebotUI.state.frames >= 5 && window.telebotMedia"
        " && (window.telebotMedia.stats.videoDecoded >= 3"
        "     || document.getElementById('video').naturalWidth > 0)",
        timeout=PAGE_MS,
    )
    media = await page.evaluate("() => window.telebotMedia.stats")
    assert media["codec"] in ("h264", "vp8", "jpeg"), media["codec"]
    shown = "#video" if media["codec"] == "jpeg" else "#video-canvas"
    assert await page.is_visible(shown)
    # The picture is a picture (the simulator's corridor), not a blank canvas.
    spread = await page.evaluate(
        """(sel) => {
          const el = document.querySelector(sel);
          const c = document.createElement('canvas');
          c.width = 64; c.height = 48;
          const ctx = c.getContext('2d');
          ctx.drawImage(el, 0, 0, 64, 48);
          const d = ctx.getImageData(0, 0, 64, 48).data;
          let lo = 255, hi = 0;
          for (let i = 0; i < d.length; i += 4) {
            const l = (d[i] + d[i + 1] + d[i + 2]) / 3;
            lo = Math.min(lo, l); hi = Math.max(hi, l);
          }
          return hi - lo;
        }""",
        shown,
    )
    assert spread > 40, spread
    # The call runs on WebTransport to the gateway (HTTP/3 over QUIC: a lost packet of the
    # video holds up no stop; web/src/webtransport.js), two sessions (two QUIC connections:
    # pictures filling one's congestion window never hold back the other's heartbeats and
    # stops), no websocket open.
    assert await page.evaluate("() => window.telebotPort.linkKind()") == "webtransport"
    sessions = await page.evaluate(
        "() => window.testNetwork.sessions.filter((s) => !s.ended).length"
    )
    assert sessions == 2, sessions
    open_sockets = await page.evaluate(
        "() => window.testNetwork.sockets.filter((s) => s.readyState === WebSocket.OPEN).length"
    )
    assert open_sockets == 0, open_sockets
    ARTIFACTS.mkdir(exist_ok=True)
    await page.screenshot(path=str(ARTIFACTS / "browser_e2e_call.png"))


async def test_a_tap_on_the_map_is_a_goal_the_robot_reaches(e2e: E2E) -> None:
    page = e2e.users["alice"].page
    await arm_from(page)
    await tap_map(page, *NEAR_GOAL)
    await page.wait_for_function(
        "() => window.telebotUI.state.goal?.status === 'succeeded'", timeout=PAGE_MS
    )
    sent = await page.evaluate("() => window.telebotUI.state.goal")
    assert sent["yaw"] is None  # a tap: no heading
    scale = await page.evaluate(
        "() => { const a = window.telebotUI.screenToWorld(0, 0);"
        " const b = window.telebotUI.screenToWorld(1, 0); return b[0] - a[0]; }"
    )
    assert math.dist((sent["x"], sent["y"]), NEAR_GOAL) <= 1.5 * scale + 1e-6
    # The robot itself says it is there (olga's view of it, not the page's).
    await poll(lambda: at_rest(e2e), "the robot at rest at the goal")
    pose = e2e.monitor.latest_pose.value
    assert pose is not None
    assert math.dist((pose.x, pose.y), (sent["x"], sent["y"])) < 0.15, pose


async def test_stop_on_the_phone_stops_the_robot_and_latches(e2e: E2E) -> None:
    page = e2e.users["alice"].page
    await drive_far(e2e, page)
    await page.tap("#stop")
    await stopped_by(e2e, "alice", "button")
    await page.wait_for_function(
        "() => window.telebotUI.state.safety?.armed === false", timeout=PAGE_MS
    )
    # The robot's own reason names who stopped it.
    status = e2e.monitor.latest_safety.value
    assert status is not None and "alice" in status.text, status


async def test_touching_the_video_while_moving_stops_the_robot(e2e: E2E) -> None:
    page = e2e.users["alice"].page
    await drive_far(e2e, page)
    await page.wait_for_function("() => window.telebotUI.state.pose?.v > 0.1", timeout=PAGE_MS)
    shown = "#video-canvas" if await page.is_visible("#video-canvas") else "#video"
    await page.tap(shown)
    await stopped_by(e2e, "alice", "touch")


async def test_a_page_hidden_while_driving_stops_the_robot(e2e: E2E) -> None:
    page = e2e.users["alice"].page
    await drive_far(e2e, page)
    await page.evaluate("() => window.dispatchEvent(new PageTransitionEvent('pagehide'))")
    await stopped_by(e2e, "alice", "page_hidden")
    await page.evaluate("() => window.dispatchEvent(new PageTransitionEvent('pageshow'))")


async def test_the_phones_joystick_drives_through_the_gateway_and_lifting_releases(
    e2e: E2E,
) -> None:
    """Driving by hand in the in-browser client: the touch joystick (static/drive.js) turns
    the robot on the spot (whatever is ahead of it), and lifting the finger stops it, armed."""
    page = e2e.users["alice"].page
    await arm_from(page)
    await poll(lambda: armed(e2e), "the robot armed")
    stops = len(e2e.stops())
    b = await box(page, "#joystick")
    x, y = b["x"] + b["width"] / 2, b["y"] + b["height"] / 2
    cdp = await page.context.new_cdp_session(page)

    async def touch(kind: str, points: list[dict[str, float]]) -> None:
        await cdp.send("Input.dispatchTouchEvent", {"type": kind, "touchPoints": points})

    await touch("touchStart", [{"x": x, "y": y}])
    await touch("touchMove", [{"x": x + b["width"] / 2, "y": y}])  # full right: clockwise

    def turning() -> bool:
        pose = e2e.monitor.latest_pose.value
        return pose is not None and pose.w < -0.3

    await poll(turning, "the robot turning")
    await touch("touchEnd", [])
    await poll(lambda: at_rest(e2e), "the robot at rest")
    assert armed(e2e) and len(e2e.stops()) == stops, e2e.stops()  # released, not stopped
    await page.wait_for_function(
        "() => window.telebotUI.state.drive?.code === 'released'", timeout=PAGE_MS
    )


async def test_when_the_network_goes_the_deadman_stops_the_robot_and_the_page_says_so(
    e2e: E2E,
) -> None:
    page = e2e.users["alice"].page
    await drive_far(e2e, page)
    before = len(e2e.daemon.audit())
    await page.evaluate("() => window.testNetwork.cut()")
    # The page says at once what happens, while it calls again.
    await page.wait_for_function(
        "() => !document.getElementById('alert').hidden"
        " && document.getElementById('alert-text').textContent.includes("
        "'connection lost — the robot stopped itself (deadman)')",
        timeout=PAGE_MS,
    )
    assert await page.evaluate("() => window.telebotUI.state.call.state") == "reconnecting"
    assert await page.is_hidden("#alert-arm")
    await poll(lambda: at_rest(e2e), "the robot at rest")
    await poll(lambda: armed(e2e) is False, "the robot latched stopped")

    # Its deadman, or its call's own (the call dropped first): alice's silence stopped it.
    def stopped_itself() -> list[dict[str, Any]]:
        records = e2e.daemon.audit()[before:]
        return [
            r for r in records if r["what"] in ("deadman", "drop") and r["outcome"] == "stopped"
        ]

    try:
        # The first: the deadman's and the call's drop may both be written in one poll.
        record = (await poll(stopped_itself, "the robot stopping itself in its audit log"))[0]
    except AssertionError as error:
        raise AssertionError(f"{error}: {e2e.daemon.audit()[before:]}") from None
    assert record["who"] == "alice", record
    # The network is back: the call comes back, the robot is latched, re-arm is the action.
    await page.evaluate("() => window.testNetwork.restore()")
    await page.wait_for_function(
        "() => window.telebotUI.state.call.state === 'reconnected'"
        " && !document.getElementById('alert-arm').hidden",
        timeout=PAGE_MS,
    )
    text = await page.inner_text("#alert-text")
    # One sentence: the robot stopped itself (the state's code says so), re-arm drives on.
    assert "stopped itself" in text and "re-arm" in text, text
    assert await page.inner_text("#safety") == "stopped"
    assert await page.is_enabled("#alert-arm")
    assert armed(e2e) is False  # nothing re-armed it behind alice's back
    await page.tap("#alert-arm")
    await poll(lambda: armed(e2e), "the robot armed again")
    await page.wait_for_function("() => document.getElementById('alert').hidden", timeout=PAGE_MS)
    await page.tap("#stop")
    await poll(lambda: armed(e2e) is False, "the robot stopped again")


async def test_an_observer_sees_who_drives_cannot_drive_and_may_stop(e2e: E2E) -> None:
    bob = e2e.users.get("bob") or await join(e2e, "bob", "observer")
    page = bob.page
    assert "observer" in await page.inner_text("#role")
    # The roster: alice drives, bob watches.
    await page.wait_for_function(
        "() => { const r = window.telebotUI.state.roster || [];"
        " return r.some(u => u.name === 'alice' && u.driving)"
        " && r.some(u => u.name === 'bob' && u.you && !u.driving); }",
        timeout=PAGE_MS,
    )
    roster = await page.inner_text("#roster")
    assert "alice · driver · driving" in roster and "bob (you) · observer" in roster, roster
    for button in ("arm", "take", "release", "navcam", "usercam"):
        assert await page.is_disabled(f"#{button}"), button
    assert await page.is_enabled("#stop")
    # bob's tap on the map is no goal; a goal sent anyway is refused.
    await tap_map(page, *NEAR_GOAL)
    assert await page.evaluate("() => window.telebotUI.state.goal") is None
    await page.evaluate("() => window.telebotUI.send({type: 'goal', x: 4.0, y: 1.2, yaw: null})")
    await page.wait_for_function(
        "() => document.getElementById('chat-log').textContent"
        ".includes('observers may not send goals')",
        timeout=PAGE_MS,
    )
    assert await page.evaluate("() => window.telebotUI.state.goal") is None
    # While alice drives, bob may stop the robot.
    alice = e2e.users["alice"].page
    await drive_far(e2e, alice)
    await page.tap("#stop")
    await stopped_by(e2e, "bob", "button")
    await alice.wait_for_function(
        "() => window.telebotUI.state.safety?.armed === false", timeout=PAGE_MS
    )


async def test_a_browser_without_webtransport_calls_over_two_websockets(e2e: E2E) -> None:
    # A browser with no WebTransport (or a network that blocks UDP: the same fallback, after
    # its 5 s try) calls over the two websockets of protocol §26.2, and its stop stops.
    dave = await join(e2e, "dave", "observer", init_script="delete window.WebTransport;")
    page = dave.page
    assert await page.evaluate("() => window.telebotPort.linkKind()") == "websocket"
    open_sockets = await page.evaluate(
        "() => window.testNetwork.sockets.filter((s) => s.readyState === WebSocket.OPEN).length"
    )
    assert open_sockets == 2, open_sockets
    await page.wait_for_function("() => window.telebotUI.state.frames >= 3", timeout=PAGE_MS)
    await drive_far(e2e, e2e.users["alice"].page)
    await page.tap("#stop")
    await stopped_by(e2e, "dave", "button")


async def test_the_pages_threw_nothing(e2e: E2E) -> None:
    assert e2e.page_errors == []
