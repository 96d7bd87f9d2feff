"""The browser client through the robot's gateway and through the router's, against the
local web UI in the same run.

One robot (``telebot-robot run``, the simulator on the small map, its camera 640 × 480,
H.264 at up to 30 fps) and one headless Chromium (Debian's ``/usr/bin/chromium``, driven by
Playwright; a fake camera and microphone, so the page sends both as a user would). Three ways
to the same robot (the same home and key), one after the other:

- **local** (the baseline): the daemon listening on zenoh on loopback, ``telebot-user ui
  guiabot`` in its own process (the Python client holds the key and the call) and the page
  it serves;
- **robot gateway**: the same daemon with ``[gateway]`` on 127.0.0.1 over HTTPS (the
  self-signed certificate it makes); the page it serves at ``https://127.0.0.1:PORT/``, the
  protocol in the page (the bundle, ``static/telebot-client.js``) over the gateway's
  WebTransport session (HTTP/3 over QUIC, the page's default; docs/protocol.md §26.5). The browser's key is made in the page and registered the way a nurse would:
  ``telebot-robot invite nurse --role driver`` prints a link, the start page opens it, makes
  the key and accepts the invite (the gateway redeems it);
- **router gateway**: ``telebot-router run DIR --listen tls/… --gateway 127.0.0.1:PORT`` in
  its own process (a CA and the router's certificate made by ``certs.init_ca``, as
  tests/router_rig.py), the daemon restarted as a TLS client of the router (its own client
  certificate, no ``[gateway]``), the page served by the router's gateway. The browser's key
  (user ``ward``) is made in the router's start page, which shows its contact line; the
  admins add that line with ``telebot-router gateway-user add DIR ward LINE`` and
  ``telebot-robot contacts add ward LINE --role driver`` before the daemon starts; the robot's
  line (``telebot-robot pubkey``) is pasted into the page to pin it.

Every certificate is trusted by the browser context (``ignore_https_errors``), as a device
that installed it.

Measured, in each way where it has a meaning:

1. call up → first video frame drawn: from opening the robot page (navigation start) to the
   first picture decoded and drawn (polled each animation frame, so ± one frame). Through
   a gateway this includes loading the bundle, admission, the call's handshake and the
   first keyframe; locally the call is already up in the Python process, so the baseline
   is the floor (page, websocket, keyframe request). Median of the samples. Target ≤ 1.0 s.
2. handshake p50: in the page, ``call.stats.handshakeMs`` (web/src/call.js: first HELLO
   sent → WELCOME checked and the keys derived) over repeated calls on one admitted link;
   the whole ``Endpoint.call`` time is printed too, against the Python client's
   ``UserEndpoint.call`` over zenoh (another user, the daemon's observer) as the baseline.
   Target ≤ 50 ms.
3. key press → robot at rest p99: the robot drives along a corridor (re-armed and sent a
   goal from the page), a key is pressed on the page; from the keydown (the page's wall
   clock) to the robot's audit record of that stop (``t``: the daemon's CLOCK_MONOTONIC,
   the step in which the simulated base was set to zero velocity), both converted to this
   machine's wall clock. Target p99 ≤ 30 ms. The re-arm is tried a few times before a
   press (a page still repeating the last stop until acked can undo one).
4. capture → picture decoded p50/p99 (glass to glass): the capture time the robot stamps in
   each frame's header to the page drawing it (``telebotMedia.stats.glassMs``, as
   bench/_media_browser.py), the robot standing still. Targets 30 / 60 ms.
5. the gateway's CPU per 30 fps call, measured directly in both deployments: each gateway
   runs on threads of its own (its asyncio loop and its subscriptions' reader threads, all
   named ``telebot-gateway`` in the OS: src/telebot/gateway/thread.py), in the daemon or in
   the router process; utime + stime of those threads (/proc/PID/task) during the glass
   window, scaled to 30 frames/s by the frames the page drew. zenoh's own threads (shared
   with the robot, or the router's routing) are not in it; the whole daemon's difference
   between the local and the robot-gateway ways, and the whole router process, are printed
   beside it as cross-checks. Target ≤ 5 % of a core.
6. the bundle's size gzipped (level 9): ``static/telebot-client.js`` as served.

A step that fails (no picture, the robot never armed, …) makes that way's figures of that
step ``nan``, is reported in one line (``FAILED``), and the run goes on.

Prints a table (target, local, robot gateway, router gateway, the RESULT figure, its ratio to
local, PASS/MISS) and ends with ``RESULT first_frame_ms=… handshake_ms_p50=… stop_p99_ms=…
glass_p50_ms=… glass_p99_ms=… gateway_cpu_pct=… bundle_kb=…``: for each figure the worse of
the robot's gateway and the router's gateway (``nan`` where either could not be measured);
the line before it says which deployment each came from. ``--quick``: a few samples of each
and no router column (the RESULT figures are then the robot gateway's, and the output says
so; ``--router`` adds it back); about 25 s on an idle machine.

Run: ``.venv/bin/python bench/browser.py [--quick [--router]]`` (needs playwright and
/usr/bin/chromium: ``make install-debian``).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import gzip
import json
import logging
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiohttp
import playwright.async_api as playwright_api

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from fake_media import chromium_media_args
from rig import FAST_SIM, GENEROUS_TIMEOUT, OBSERVER, ROBOT, Daemon, Process
from router_rig import RouterRig
from telebot.channels.call import UserEndpoint
from telebot.channels.transports import create_transport
from telebot.identity import Identity, KnownRobots
from telebot.testing.net import free_port

ROOT = Path(__file__).resolve().parent.parent
CHROMIUM = "/usr/bin/chromium"
BUNDLE = ROOT / "src" / "telebot" / "apps" / "web" / "static" / "telebot-client.js"
NURSE = "nurse"  # the robot gateway's browser user (by invite)
WARD = "ward"  # the router gateway's browser user (added by the admins)
CORRIDOR_Y = 1.2
ENDS = (1.0, 9.0)
FPS = 30.0
ARM_TRIES = 4
SIM = {**FAST_SIM, "camera_width": 640, "camera_height": 480}

TARGETS = {  # name: (target, unit)
    "first_frame_ms": (1000.0, "ms"),
    "handshake_ms_p50": (50.0, "ms"),
    "stop_p99_ms": (30.0, "ms"),
    "glass_p50_ms": (30.0, "ms"),
    "glass_p99_ms": (60.0, "ms"),
    "gateway_cpu_pct": (5.0, "%"),
}
KEYS = (*TARGETS, "bundle_kb")
NAN = float("nan")
#: The steps of a way, and the figures a failure of each makes nan.
STEPS = {
    "setup": KEYS[:-1],
    "handshakes": ("handshake_ms_p50",),
    "first frame": ("first_frame_ms",),
    "key presses": ("stop_p99_ms",),
    "glass and CPU": ("glass_p50_ms", "glass_p99_ms", "gateway_cpu_pct"),
}


def pct(values: list[float], q: float) -> float:
    """Nearest-rank percentile (``q`` in 0..100); nan for no values."""
    if not values:
        return NAN
    ordered = sorted(values)
    return ordered[max(1, math.ceil(q / 100 * len(ordered))) - 1]


def one_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:400] if text else type(exc).__name__


@dataclass
class Way:
    """What one way to the robot (local, robot gateway, router gateway) measured."""

    name: str
    first_frame: list[float] = field(default_factory=list)  # ms
    handshake: list[float] = field(default_factory=list)  # ms, the page's stat
    call: list[float] = field(default_factory=list)  # ms, the whole call()
    stop: list[float] = field(default_factory=list)  # ms
    glass: list[float] = field(default_factory=list)  # ms
    cpu_pct: float = NAN  # the daemon's CPU during the glass window, % of a core
    main_pct: float = NAN  # its main thread's
    gateway_pct: float = NAN  # the gateway threads' (measured directly, daemon or router)
    router_pct: float = NAN  # the whole router process's (router way only)
    fps: float = NAN  # pictures the page drew per second in that window
    failed: dict[str, str] = field(default_factory=dict)  # step: what went wrong, one line
    skipped: str = ""  # why this way did not run at all
    console: list[str] = field(default_factory=list)  # the page's errors (for a failure)

    async def step(self, name: str, run: Callable[[], Awaitable[None]]) -> bool:
        """Run one step; a failure is recorded in one line (not raised). True if it ran."""
        try:
            await run()
        except Exception as exc:
            self.failed[name] = one_line(exc)
            return False
        return True


# --------------------------------------------------------------------------- processes


def cpu_seconds(pid: int, tid: int | None = None) -> float:
    """utime + stime of process ``pid`` (all threads), or of its thread ``tid``."""
    path = f"/proc/{pid}/stat" if tid is None else f"/proc/{pid}/task/{tid}/stat"
    with open(path, encoding="ascii") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def gateway_cpu_seconds(pid: int) -> float:
    """utime + stime of the threads of ``pid`` a gateway runs on (its loop and its
    subscriptions' readers, named ``telebot-gateway`` in the OS:
    src/telebot/gateway/thread.py), in a robot daemon or in a router."""
    total = 0.0
    for tid in os.listdir(f"/proc/{pid}/task"):
        with (
            contextlib.suppress(OSError),
            open(f"/proc/{pid}/task/{tid}/comm", encoding="ascii") as f,
        ):
            if f.read().strip().startswith("telebot-gatewa"):
                total += cpu_seconds(pid, int(tid))
    return total


def audit_lines(home: Path) -> list[dict[str, Any]]:
    path = home / "audit.jsonl"
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line]


def cli(module: str, *args: str) -> str:
    """``python -m telebot.apps.MODULE ARGS`` to its end: its stdout (RuntimeError with its
    last stderr line if it fails)."""
    run = subprocess.run(
        [sys.executable, "-m", f"telebot.apps.{module}", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )
    if run.returncode != 0:
        last = (run.stderr.strip().splitlines() or ["no output"])[-1]
        raise RuntimeError(f"{module} {args[0]} failed: {last}")
    return run.stdout


async def start_daemon(base: Path) -> tuple[Daemon, int]:
    daemon = Daemon(base, timeout=5.0, sim=SIM)
    port = free_port()
    config = daemon.robot_config
    config.write_text(
        config.read_text()
        + f'[video]\nmax_fps = {FPS}\n[gateway]\nlisten = "127.0.0.1"\nport = {port}\n'
    )
    await asyncio.to_thread(daemon.start)
    return daemon, port


def invite_link(daemon: Daemon, port: int, name: str = NURSE) -> str:
    """``telebot-robot invite NAME --role driver``: the link it prints."""
    out = cli(
        "robot_cli",
        "invite",
        name,
        "--role",
        "driver",
        "--url",
        f"https://127.0.0.1:{port}/",
        "--no-qr",
        "--home",
        str(daemon.robot_home),
    )
    return next(line for line in out.splitlines() if line.startswith("https://"))


async def python_calls(daemon: Daemon, n: int, way: Way) -> None:
    """The Python client's ``UserEndpoint.call`` time (ms), ``n`` calls over zenoh."""
    home = daemon.observer_home
    config = daemon.config()
    async with (
        create_transport(config.transport) as transport,
        UserEndpoint(
            transport, Identity.load(home), KnownRobots.load(home), settings=config.call
        ) as user,
    ):
        for _ in range(n):
            started = time.perf_counter()
            call = await user.call(ROBOT, timeout=10)
            way.call.append((time.perf_counter() - started) * 1000)
            await call.hangup()


# --------------------------------------------------------------------------- the page


async def first_frame(page: Any, url: str) -> float:
    """Open the robot page at ``url``; ms from navigation start to the first picture drawn."""
    await page.goto(url)
    try:
        handle = await page.wait_for_function(
            "() => window.telebotMedia && window.telebotMedia.stats.videoDecoded > 0"
            " && performance.now()",
            polling="raf",
            timeout=20_000,
        )
    except playwright_api.TimeoutError:
        raise RuntimeError(f"no picture within 20 s; {await what_page_says(page)}") from None
    return float(await handle.json_value())


async def what_page_says(page: Any) -> str:
    """The page's connection line, last chat lines and video counters (for a failure)."""
    said = await page.evaluate(
        """() => {
          const text = (id) => ((document.getElementById(id) || {}).textContent || "").trim();
          const s = (window.telebotMedia || {}).stats || {};
          const log = text("chat-log").split("\\n").slice(-3).join(" / ");
          const ui = window.telebotUI || { state: {} };
          return `conn: ${text("conn")}; role: ${text("role")}; pose: ${!!ui.state.pose};`
            + ` chat: ${log}; video decoded ${s.videoDecoded},`
            + ` errors ${s.videoErrors}, codec '${s.codec}'`;
        }"""
    )
    return " ".join(str(said).split())


async def page_state(page: Any, expr: str) -> Any:
    return await page.evaluate(f"() => {{ const ui = window.telebotUI; return {expr}; }}")


async def wait_page(page: Any, condition: str, timeout: float, what: str) -> None:
    try:
        await page.wait_for_function(
            f"() => {{ const ui = window.telebotUI; return {condition}; }}",
            timeout=timeout * 1000,
        )
    except playwright_api.TimeoutError:
        raise RuntimeError(f"timed out waiting for {what}; {await what_page_says(page)}") from None


async def arm(page: Any) -> None:
    """Re-arm the robot from the page, up to :data:`ARM_TRIES` times (a stop the page is
    still repeating until acked, or a lost message, can undo or lose one)."""
    for attempt in range(1, ARM_TRIES + 1):
        await page.evaluate("() => window.telebotUI.send({type: 'arm'})")
        try:
            await wait_page(page, "ui.state.safety && ui.state.safety.armed", 5, "armed")
            return
        except RuntimeError as exc:
            if attempt == ARM_TRIES:
                raise RuntimeError(f"not armed after {ARM_TRIES} tries: {exc}") from None


async def goal_far_end(page: Any, x: float) -> None:
    """From the page, a goal at the corridor's end away from ``x`` (the robot's x)."""
    target = ENDS[1] if x < sum(ENDS) / 2 else ENDS[0]
    await page.evaluate(
        f"() => window.telebotUI.send({{type: 'goal', x: {target}, y: {CORRIDOR_Y}}})"
    )


async def stops(page: Any, home: Path, who: str, presses: int, out: list[float]) -> None:
    """Key press → robot at rest (ms), ``presses`` times, into ``out``; ``home`` is the
    robot's (its audit log), ``who`` the page's user."""
    await wait_page(
        page, "ui && ui.mapReady() && ui.state.pose && ui.state.mayDrive", 60, "the map and pose"
    )
    await page.locator("#map").focus()
    for i in range(presses):
        x = float(await page_state(page, "ui.state.pose.x"))
        for attempt in range(3):
            await arm(page)
            await goal_far_end(page, x)
            try:
                await wait_page(page, "Math.abs(ui.state.pose.v) > 0.2", 10, f"moving ({i})")
                break
            except RuntimeError:
                if attempt == 2:
                    raise
        before = len(audit_lines(home))
        offset = time.time() - time.monotonic()  # wall - monotonic, this machine
        await page.keyboard.press("x")  # not a drive key (WASD, arrows drive)
        pressed = float((await page_state(page, "ui.stats.keyTimes"))[-1])
        deadline = time.monotonic() + 10
        record = None
        while record is None:
            new = audit_lines(home)[before:]
            record = next(
                (r for r in new if r["what"] == "stop" and r["who"] == who and r.get("how")), None
            )
            if record is None:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"no stop in the robot's audit log after press {i}")
                await asyncio.sleep(0.02)
        out.append((record["t"] + offset) * 1000 - pressed)
        await wait_page(page, "Math.abs(ui.state.pose.v) < 0.01", 10, "at rest on the page")


async def glass_and_cpu(
    page: Any, seconds: float, way: Way, daemon_pid: int, router_pid: int | None = None
) -> None:
    """Glass to glass over ``seconds``, and meanwhile the daemon's CPU and the gateway
    threads' (in the router process if ``router_pid``, else in the daemon)."""
    await page.wait_for_function(
        "() => window.telebotMedia.stats.videoDecoded >= 10", timeout=30_000
    )
    await page.evaluate("() => { window.telebotMedia.stats.glassMs.length = 0; }")
    decoded0 = await page.evaluate("() => window.telebotMedia.stats.videoDecoded")
    gw_pid = router_pid if router_pid is not None else daemon_pid
    gw0 = gateway_cpu_seconds(gw_pid)
    router0 = cpu_seconds(router_pid) if router_pid is not None else NAN
    cpu0, main0, t0 = cpu_seconds(daemon_pid), cpu_seconds(daemon_pid, daemon_pid), time.monotonic()
    await asyncio.sleep(seconds)
    cpu1, main1, t1 = cpu_seconds(daemon_pid), cpu_seconds(daemon_pid, daemon_pid), time.monotonic()
    router1 = cpu_seconds(router_pid) if router_pid is not None else NAN
    gw1 = gateway_cpu_seconds(gw_pid)
    decoded1 = await page.evaluate("() => window.telebotMedia.stats.videoDecoded")
    way.glass = [float(v) for v in await page.evaluate("() => window.telebotMedia.stats.glassMs")]
    way.cpu_pct = (cpu1 - cpu0) / (t1 - t0) * 100
    way.main_pct = (main1 - main0) / (t1 - t0) * 100
    way.gateway_pct = (gw1 - gw0) / (t1 - t0) * 100
    way.router_pct = (router1 - router0) / (t1 - t0) * 100
    way.fps = (decoded1 - decoded0) / (t1 - t0)


@contextlib.asynccontextmanager
async def chromium(base: Path) -> AsyncIterator[Any]:
    args = chromium_media_args(base)
    if os.geteuid() == 0:
        args.append("--no-sandbox")
    async with playwright_api.async_playwright() as pw:
        browser = await pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=args)
        try:
            yield browser
        finally:
            await browser.close()


@contextlib.asynccontextmanager
async def gateway_page(browser: Any, way: Way) -> AsyncIterator[Any]:
    """A page in a new context that trusts the gateway's certificate; its errors and failed
    responses go to ``way.console``."""
    context = await browser.new_context(
        viewport={"width": 1280, "height": 800}, ignore_https_errors=True
    )
    try:
        page = await context.new_page()
        page.on("console", lambda m: way.console.append(f"{m.type}: {m.text}"))
        page.on("pageerror", lambda e: way.console.append(f"pageerror: {e}"))
        page.on(
            "response",
            lambda r: way.console.append(f"HTTP {r.status} {r.url}") if r.status >= 400 else None,
        )
        yield page
    finally:
        await context.close()


async def local_way(browser: Any, daemon: Daemon, n: dict[str, Any], way: Way) -> None:
    """The baseline: ``telebot-user ui`` in its own process and its page."""
    port = free_port()
    ui = Process(
        [
            "telebot.apps.user_cli",
            "ui",
            ROBOT,
            "--port",
            str(port),
            "--home",
            str(daemon.user_home),
            "--config",
            str(daemon.user_config),
            "--connect",
            daemon.endpoint,
        ]
    )
    url = f"http://127.0.0.1:{port}/"

    async def served() -> None:
        deadline = time.monotonic() + 60
        async with aiohttp.ClientSession() as http:
            while True:
                with contextlib.suppress(aiohttp.ClientError):
                    async with http.get(url) as response:
                        if response.status == 200:
                            return
                if time.monotonic() > deadline or ui.popen.poll() is not None:
                    raise RuntimeError(f"telebot-user ui did not serve its page: {ui.stderr()}")
                await asyncio.sleep(0.1)

    try:
        if not await way.step("setup", served):
            return
        context = await browser.new_context(viewport={"width": 1280, "height": 800})
        try:
            page = await context.new_page()
            await measure_page(page, url, daemon.robot_home, daemon.driver, n, way, daemon.pid)
        finally:
            await context.close()
    finally:
        ui.stop(graceful=True)


async def measure_page(
    page: Any,
    url: str,
    home: Path,
    who: str,
    n: dict[str, Any],
    way: Way,
    daemon_pid: int,
    router_pid: int | None = None,
) -> None:
    """First frames at ``url``, key presses, glass and CPU: each a step of ``way``."""

    async def frames() -> None:
        for _ in range(n["frames"]):
            way.first_frame.append(await first_frame(page, url))

    if not await way.step("first frame", frames):
        with contextlib.suppress(Exception):  # the page the other steps use, if it loads
            await page.goto(url)
    await way.step("key presses", lambda: stops(page, home, who, n["presses"], way.stop))
    await way.step(
        "glass and CPU", lambda: glass_and_cpu(page, n["seconds"], way, daemon_pid, router_pid)
    )


HANDSHAKES_JS = """
async ([robot, n]) => {
  const t = window.telebot;
  const keys = await t.Keys.open();
  const me = await keys.me();
  const robotKey = await keys.robotKey(robot);
  const url = new URL("gateway", location.href);
  url.protocol = "wss:";
  const link = await t.connectGateway(url.href, { name: me.name, privateKey: me.privateKey, publicKey: me.publicKey });
  const endpoint = new t.Endpoint({ link, name: me.name, privateKey: me.privateKey });
  const out = [];
  try {
    for (let i = 0; i < n; i++) {
      const t0 = performance.now();
      const call = await endpoint.call(robot, robotKey);
      out.push([call.stats.handshakeMs, performance.now() - t0]);
      await call.hangup();
      // A call declares a few subscriptions, a token and a watch; the gateway allows 10
      // declarations a second (bursts of 64) and cuts a link past that ("flood",
      // protocol §26.3): back to back, the 16th call in a second was cut.
      await new Promise((resolve) => setTimeout(resolve, 500));
    }
  } finally {
    await endpoint.close();
    link.close();
  }
  return out;
}
"""


async def handshakes(page: Any, n: int, way: Way) -> None:
    pairs = await page.evaluate(HANDSHAKES_JS, [ROBOT, n])
    way.handshake = [float(h) for h, _ in pairs]
    way.call = [float(c) for _, c in pairs]


async def setup_error(page: Any) -> None:
    error = await page.evaluate("() => window.telebotSetup.error")
    if error:
        raise RuntimeError(f"the start page says: {error}")


async def enrol(
    page: Any, daemon: Daemon, port: int, name: str = NURSE, timeout: float = 30.0
) -> None:
    """A nurse's first visit: ``telebot-robot invite NAME`` for the gateway at
    ``https://127.0.0.1:PORT/``, the link opened, a key made in the page, the invite
    accepted (the gateway redeems it) and the robot pinned."""
    link = await asyncio.to_thread(invite_link, daemon, port, name)
    await page.goto(link, timeout=timeout * 1000)
    await page.wait_for_selector("#create-key", state="visible", timeout=timeout * 1000)
    await page.fill("#new-name", name)
    await page.click("#create-key")
    await page.wait_for_function(
        "() => !document.getElementById('accept-invite').disabled", timeout=timeout * 1000
    )
    await page.click("#accept-invite")
    await page.wait_for_function(
        "() => window.telebotSetup && (window.telebotSetup.error"
        " || window.telebotSetup.robots.some((r) => r.name === 'guiabot'"
        " && window.telebotSetup.invite === null))",
        timeout=timeout * 1000,
    )
    await setup_error(page)


async def robot_gateway_way(
    browser: Any, daemon: Daemon, gateway_port: int, n: dict[str, Any], way: Way
) -> None:
    """The browser client through the daemon's gateway, the key registered by an invite."""
    async with gateway_page(browser, way) as page:
        if not await way.step("setup", lambda: enrol(page, daemon, gateway_port)):
            return
        await way.step("handshakes", lambda: handshakes(page, n["calls"], way))
        url = f"https://127.0.0.1:{gateway_port}/call?robot={ROBOT}"
        await measure_page(page, url, daemon.robot_home, NURSE, n, way, daemon.pid)


async def router_gateway_way(
    browser: Any, base: Path, robot_home: Path, n: dict[str, Any], way: Way
) -> None:
    """The browser client through ``telebot-router run``'s gateway; the robot daemon (the
    same home as before) a TLS client of the router."""
    rig = RouterRig(base)
    cert = rig.issue("robot", ROBOT)
    port = free_port()
    robot: Process | None = None
    try:
        async with gateway_page(browser, way) as page:

            async def setup() -> None:
                nonlocal robot
                await asyncio.to_thread(rig.start, extra=("--gateway", f"127.0.0.1:{port}"))
                # The browser user makes the key in the router's start page, which shows its
                # contact line, and pins the robot from the robot's line.
                await page.goto(f"https://127.0.0.1:{port}/")
                await page.wait_for_selector("#create-key", state="visible", timeout=30_000)
                await page.fill("#new-name", WARD)
                await page.click("#create-key")
                await page.wait_for_function(
                    "() => window.telebotSetup && window.telebotSetup.line", timeout=30_000
                )
                await setup_error(page)
                line = str(await page.evaluate("() => window.telebotSetup.line"))
                robot_line = (
                    await asyncio.to_thread(cli, "robot_cli", "pubkey", "--home", str(robot_home))
                ).strip()
                await page.fill("#pin-line", robot_line)
                await page.click("#pin")
                await page.wait_for_function(
                    "() => window.telebotSetup.error"
                    " || window.telebotSetup.robots.some((r) => r.name === 'guiabot')",
                    timeout=30_000,
                )
                await setup_error(page)
                # The admins: the router's gateway users, the robot's contacts.
                await asyncio.to_thread(
                    cli, "router_cli", "gateway-user", "add", str(rig.dir), WARD, line
                )
                await asyncio.to_thread(
                    cli,
                    "robot_cli",
                    "contacts",
                    "add",
                    WARD,
                    line,
                    "--role",
                    "driver",
                    "--home",
                    str(robot_home),
                )
                config = rig.write_robot_config(
                    base / "robot-router.toml",
                    cert,
                    timeout=GENEROUS_TIMEOUT,
                    sim=SIM,
                    extra=f"[video]\nmax_fps = {FPS}",
                )
                robot = Process(
                    [
                        "telebot.apps.robot_cli",
                        "run",
                        "--home",
                        str(robot_home),
                        "--config",
                        str(config),
                        "--events",
                    ]
                )
                try:
                    ready = await asyncio.to_thread(robot.next_line, 60)
                except AssertionError:
                    raise RuntimeError(f"the robot did not start: {robot.stderr()}") from None
                if '"ready"' not in ready:
                    raise RuntimeError(f"the robot did not start: {ready}")

            if not await way.step("setup", setup):
                return
            assert robot is not None and rig.process is not None
            await way.step("handshakes", lambda: handshakes(page, n["calls"], way))
            url = f"https://127.0.0.1:{port}/call?robot={ROBOT}"
            await measure_page(page, url, robot_home, WARD, n, way, robot.pid, rig.process.pid)
    finally:
        if robot is not None:
            robot.stop(graceful=True)
        rig.stop()


async def bench(quick: bool, router: bool) -> tuple[Way, Way, Way]:
    """The three ways, one after the other: (local, robot gateway, router gateway)."""
    n: dict[str, Any] = (
        {"frames": 1, "calls": 5, "presses": 3, "seconds": 2.0}
        if quick
        else {"frames": 5, "calls": 30, "presses": 100, "seconds": 10.0}
    )
    local, robot, routed = Way("local"), Way("robot gateway"), Way("router gateway")
    if not router:
        routed.skipped = "skipped in quick mode (--router adds it)"
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        daemon, port = await start_daemon(base)
        try:
            assert OBSERVER  # the Python baseline's caller (not the page's driver)
            await local.step("calls", lambda: python_calls(daemon, n["calls"], local))
            async with chromium(base) as browser:
                await local_way(browser, daemon, n, local)
                await robot_gateway_way(browser, daemon, port, n, robot)
                daemon.stop(graceful=True)
                if router:
                    await router_gateway_way(browser, base, daemon.robot_home, n, routed)
        finally:
            daemon.stop(graceful=True)
    return local, robot, routed


# --------------------------------------------------------------------------- the report


def bundle_kb() -> float:
    return len(gzip.compress(BUNDLE.read_bytes(), compresslevel=9)) / 1000


def figures(way: Way, gateway: bool) -> dict[str, float]:
    """The RESULT figures of one way (``gateway_cpu_pct`` only for a gateway way); nan for
    what a failed step or a skipped way did not measure."""
    cpu = NAN
    if gateway and way.fps > 0:
        cpu = way.gateway_pct * FPS / way.fps
    out = {
        "first_frame_ms": statistics.median(way.first_frame) if way.first_frame else NAN,
        "handshake_ms_p50": pct(way.handshake, 50),
        "stop_p99_ms": pct(way.stop, 99),
        "glass_p50_ms": pct(way.glass, 50),
        "glass_p99_ms": pct(way.glass, 99),
        "gateway_cpu_pct": cpu,
        "bundle_kb": bundle_kb() if gateway and not way.skipped else NAN,
    }
    for step in way.failed:
        for key in STEPS.get(step, ()):
            out[key] = NAN
    if way.skipped:
        out = dict.fromkeys(out, NAN)
    return out


def worse(robot: dict[str, float], router: dict[str, float] | None) -> dict[str, tuple[float, str]]:
    """Per figure the worse (higher) of the two gateways and which it was; nan, and the one
    that did not measure it, when either is nan; the robot's alone when the router's column
    was skipped."""
    out: dict[str, tuple[float, str]] = {}
    for key, a in robot.items():
        if router is None:
            out[key] = (a, "robot")
        elif math.isnan(a) or math.isnan(router[key]):
            out[key] = (NAN, "robot" if math.isnan(a) else "router")
        elif a == router[key]:
            out[key] = (a, "both")
        else:
            out[key] = (a, "robot") if a > router[key] else (router[key], "router")
    return out


def report(local: Way, robot: Way, routed: Way) -> dict[str, float]:
    base, mine = figures(local, False), figures(robot, True)
    theirs = None if routed.skipped else figures(routed, True)
    result = worse(mine, theirs)
    print("details:")
    for way in (local, robot, routed):
        if way.skipped:
            print(f"  {way.name}: {way.skipped}")
            continue
        print(
            f"  {way.name}: first frame {[round(v) for v in way.first_frame]} ms; "
            f"call() p50 {pct(way.call, 50):.1f} ms p99 {pct(way.call, 99):.1f} ms "
            f"(n={len(way.call)}); stop n={len(way.stop)} p50 {pct(way.stop, 50):.1f} ms "
            f"max {max(way.stop, default=NAN):.1f} ms; glass n={len(way.glass)}; "
            f"daemon CPU {way.cpu_pct:.1f} % (main thread {way.main_pct:.1f} %) at "
            f"{way.fps:.1f} pictures/s drawn"
        )
    print(
        f"  robot gateway CPU = its own threads in the daemon {robot.gateway_pct:.1f} % x 30 / "
        f"{robot.fps:.1f} fps (measured directly); cross-check, whole daemon robot-gateway way"
        f" - local way: {robot.cpu_pct - local.cpu_pct:+.1f} %, main thread "
        f"{robot.main_pct - local.main_pct:+.1f} %"
    )
    if not routed.skipped:
        print(
            f"  router gateway CPU = its own threads in the router process "
            f"{routed.gateway_pct:.1f} % x 30 / {routed.fps:.1f} fps (measured directly); "
            f"the whole router process {routed.router_pct:.1f} % (zenoh routing the robot's "
            "video to the gateway's session included)"
        )
    print(f"  bundle {BUNDLE.stat().st_size / 1000:.1f} kB, gzipped {bundle_kb():.1f} kB")
    for way in (local, robot, routed):
        for step, reason in way.failed.items():
            print(f"  {way.name.upper()} WAY FAILED at {step}: {reason}")
        if way.failed:
            for line in way.console[-8:]:
                print(f"    {way.name} page console: {line[:300]}")
    print(
        f"{'figure':<18} {'target':>9} {'local':>9} {'robot gw':>9} {'router gw':>9} "
        f"{'RESULT':>9} {'res/local':>9}  verdict"
    )
    for name in KEYS:
        target, unit = TARGETS.get(name, (NAN, "kB"))
        value = result[name][0]
        loc = base[name]
        r = value
        if name == "handshake_ms_p50":  # no handshake stat in the Python client: call() times
            loc = pct(local.call, 50)
            calls = [pct(robot.call, 50)] + ([] if theirs is None else [pct(routed.call, 50)])
            r = NAN if any(math.isnan(c) for c in calls) else max(calls)
        ratio = r / loc if loc and not math.isnan(loc) else NAN
        router_text = "skipped" if theirs is None else f"{theirs[name]:.1f}"
        verdict = "" if math.isnan(target) else ("PASS" if value <= target else "MISS")
        shown = f"{target:>7g}{unit:<2}" if not math.isnan(target) else f"{'':>9}"
        print(
            f"{name:<18} {shown} {loc:>9.1f} {mine[name]:>9.1f} {router_text:>9} "
            f"{value:>9.1f} {ratio:>9.2f}  {verdict}"
        )
    print(
        "  (handshake's local column and ratio: the whole call() of the Python client and of "
        "the page; res/local above 1 = the gateway way slower)"
    )
    if theirs is None:
        print(
            "RESULT figures from the robot's gateway only (the router column "
            f"{routed.skipped.split(' (')[0]})"
        )
    else:
        print(
            "RESULT figures: the worse of robot gateway and router gateway per figure ("
            + ", ".join(f"{k} {result[k][1]}" for k in KEYS)
            + ")"
        )
    return {k: v for k, (v, _) in result.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--quick",
        action="store_true",
        help="a few samples of each, without the router column (about 25 s)",
    )
    parser.add_argument("--router", action="store_true", help="with --quick: the router column too")
    args = parser.parse_args()
    logging.getLogger("telebot").setLevel(logging.ERROR)
    started = time.monotonic()
    local, robot, routed = asyncio.run(bench(args.quick, router=not args.quick or args.router))
    result = report(local, robot, routed)
    print(f"run took {time.monotonic() - started:.1f} s; load average {os.getloadavg()[0]:.1f}")
    print("RESULT " + " ".join(f"{k}={result[k]:.2f}" for k in KEYS))
    return 0


if __name__ == "__main__":
    sys.exit(main())
