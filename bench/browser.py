"""The browser client through the robot's gateway, against the local web UI in the same run.

One robot daemon (``telebot-robot run``, the simulator on the small map, its camera
640 × 480, H.264 at up to 30 fps, ``[gateway]`` on 127.0.0.1 over HTTPS with the
self-signed certificate it makes) in its own process, and one headless Chromium (Debian's
``/usr/bin/chromium``, driven by Playwright; a fake camera and microphone, so the page sends
both as a user would). Two ways to the same robot, one after the other:

- **local** (the baseline): ``telebot-user ui guiabot`` in its own process (the Python
  client holds the key and the call, over zenoh on loopback) and the page it serves;
- **gateway**: the page served by the daemon's gateway at ``https://127.0.0.1:PORT/``,
  the protocol in the page (the bundle, ``static/telebot-client.js``) over the gateway's
  WebSocket. The browser's key is made in the page and registered the way a nurse would:
  ``telebot-robot invite nurse --role driver`` prints a link, the start page opens it,
  makes the key and accepts the invite (the gateway redeems it). The certificate is
  trusted by the browser context (``ignore_https_errors``), as a device that installed it.

Measured, in each way where it has a meaning:

1. call up → first video frame drawn: from opening the robot page (navigation start) to the
   first picture decoded and drawn (polled each animation frame, so ± one frame). Through
   the gateway this includes loading the bundle, admission, the call's handshake and the
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
   machine's wall clock. Target p99 ≤ 30 ms.
4. capture → picture decoded p50/p99 (glass to glass): the capture time the robot stamps in
   each frame's header to the page drawing it (``telebotMedia.stats.glassMs``, as
   bench/_media_browser.py), the robot standing still. Targets 30 / 60 ms.
5. the gateway's CPU per 30 fps call: the robot's gateway runs in the daemon on threads of
   its own (its asyncio loop, and its subscriptions' reader threads, all named
   ``telebot-gateway`` in the OS), so it is measured directly: utime + stime of those
   threads (/proc/PID/task) during the glass window, scaled to 30 frames/s by the frames the
   page drew. zenoh's own threads (shared with the robot) are not in it; the whole daemon's
   difference between the two ways is printed beside it as a cross-check (noisy: the two
   windows are seconds apart on a shared machine). Target ≤ 5 % of a core.
6. the bundle's size gzipped (level 9): ``static/telebot-client.js`` as served.

Prints a table (target, local, gateway, gateway ÷ local, PASS/MISS) and ends with
``RESULT first_frame_ms=… handshake_ms_p50=… stop_p99_ms=… glass_p50_ms=… glass_p99_ms=…
gateway_cpu_pct=… bundle_kb=…`` (the gateway way's figures; ``nan`` for what could not be
measured). ``--quick``: a few samples of each (under 30 s on an idle machine).

Run: ``.venv/bin/python bench/browser.py [--quick]`` (needs playwright and
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
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiohttp
import playwright.async_api as playwright_api

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from fake_media import chromium_media_args
from rig import FAST_SIM, OBSERVER, ROBOT, Daemon, Process, free_port
from telebot.channels.call import UserEndpoint
from telebot.channels.transports import create_transport
from telebot.identity import Identity, KnownRobots

ROOT = Path(__file__).resolve().parent.parent
CHROMIUM = "/usr/bin/chromium"
BUNDLE = ROOT / "src" / "telebot" / "apps" / "web" / "static" / "telebot-client.js"
NURSE = "nurse"
CORRIDOR_Y = 1.2
ENDS = (1.0, 9.0)
FPS = 30.0

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


def pct(values: list[float], q: float) -> float:
    """Nearest-rank percentile (``q`` in 0..100); nan for no values."""
    if not values:
        return NAN
    ordered = sorted(values)
    return ordered[max(1, math.ceil(q / 100 * len(ordered))) - 1]


@dataclass
class Way:
    """What one way to the robot (local or gateway) measured."""

    first_frame: list[float] = field(default_factory=list)  # ms
    handshake: list[float] = field(default_factory=list)  # ms, the page's stat
    call: list[float] = field(default_factory=list)  # ms, the whole call()
    stop: list[float] = field(default_factory=list)  # ms
    glass: list[float] = field(default_factory=list)  # ms
    cpu_pct: float = NAN  # the daemon's CPU during the glass window, % of a core
    main_pct: float = NAN  # its main thread's
    gateway_pct: float = NAN  # its gateway threads' (measured directly)
    fps: float = NAN  # pictures the page drew per second in that window
    failed: str = ""  # what went wrong, one line


# --------------------------------------------------------------------------- the daemon


def cpu_seconds(pid: int, tid: int | None = None) -> float:
    """utime + stime of process ``pid`` (all threads), or of its thread ``tid``."""
    path = f"/proc/{pid}/stat" if tid is None else f"/proc/{pid}/task/{tid}/stat"
    with open(path, encoding="ascii") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def gateway_cpu_seconds(pid: int) -> float:
    """utime + stime of the threads of ``pid`` the robot's gateway runs on (its loop and its
    subscriptions' readers, named ``telebot-gateway`` in the OS: src/telebot/gateway/robot.py)."""
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


async def start_daemon(base: Path) -> tuple[Daemon, int]:
    sim = {**FAST_SIM, "camera_width": 640, "camera_height": 480}
    daemon = Daemon(base, timeout=5.0, sim=sim)
    port = free_port()
    config = daemon.robot_config
    config.write_text(
        config.read_text()
        + f'[video]\nmax_fps = {FPS}\n[gateway]\nlisten = "127.0.0.1"\nport = {port}\n'
    )
    await asyncio.to_thread(daemon.start)
    return daemon, port


def invite_link(daemon: Daemon, port: int) -> str:
    """``telebot-robot invite nurse --role driver``: the link it prints."""
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "telebot.apps.robot_cli",
            "invite",
            NURSE,
            "--role",
            "driver",
            "--url",
            f"https://127.0.0.1:{port}/",
            "--no-qr",
            "--home",
            str(daemon.robot_home),
        ],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    ).stdout
    return next(line for line in out.splitlines() if line.startswith("https://"))


async def python_calls(daemon: Daemon, n: int) -> list[float]:
    """The Python client's ``UserEndpoint.call`` time (ms), ``n`` calls over zenoh."""
    home = daemon.observer_home
    config = daemon.config()
    times: list[float] = []
    async with (
        create_transport(config.transport) as transport,
        UserEndpoint(
            transport, Identity.load(home), KnownRobots.load(home), settings=config.call
        ) as user,
    ):
        for _ in range(n):
            started = time.perf_counter()
            call = await user.call(ROBOT, timeout=10)
            times.append((time.perf_counter() - started) * 1000)
            await call.hangup()
    return times


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
    return str(said)


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


async def stops(page: Any, daemon: Daemon, who: str, presses: int) -> list[float]:
    """Key press → robot at rest (ms), ``presses`` times."""
    await wait_page(
        page, "ui && ui.mapReady() && ui.state.pose && ui.state.mayDrive", 60, "the map and pose"
    )
    await page.locator("#map").focus()
    times: list[float] = []
    for i in range(presses):
        x = float(await page_state(page, "ui.state.pose.x"))
        target = ENDS[1] if x < sum(ENDS) / 2 else ENDS[0]
        for attempt in range(3):
            await page.evaluate("() => window.telebotUI.send({type: 'arm'})")
            await wait_page(page, "ui.state.safety && ui.state.safety.armed", 10, "armed")
            await page.evaluate(
                f"() => window.telebotUI.send({{type: 'goal', x: {target}, y: {CORRIDOR_Y}}})"
            )
            try:
                await wait_page(page, "Math.abs(ui.state.pose.v) > 0.2", 10, f"moving ({i})")
                break
            except RuntimeError:
                if attempt == 2:
                    raise
        before = len(audit_lines(daemon.robot_home))
        offset = time.time() - time.monotonic()  # wall - monotonic, this machine
        await page.keyboard.press("s")
        pressed = float((await page_state(page, "ui.stats.keyTimes"))[-1])
        deadline = time.monotonic() + 10
        record = None
        while record is None:
            new = audit_lines(daemon.robot_home)[before:]
            record = next(
                (r for r in new if r["what"] == "stop" and r["who"] == who and r.get("how")), None
            )
            if record is None:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"no stop in the robot's audit log after press {i}")
                await asyncio.sleep(0.02)
        times.append((record["t"] + offset) * 1000 - pressed)
        await wait_page(page, "Math.abs(ui.state.pose.v) < 0.01", 10, "at rest on the page")
    return times


async def glass_and_cpu(page: Any, daemon: Daemon, seconds: float, way: Way) -> None:
    """Glass to glass over ``seconds``, and the daemon's CPU meanwhile."""
    await page.wait_for_function(
        "() => window.telebotMedia.stats.videoDecoded >= 10", timeout=30_000
    )
    await page.evaluate("() => { window.telebotMedia.stats.glassMs.length = 0; }")
    decoded0 = await page.evaluate("() => window.telebotMedia.stats.videoDecoded")
    pid = daemon.pid
    gw0 = gateway_cpu_seconds(pid)
    cpu0, main0, t0 = cpu_seconds(pid), cpu_seconds(pid, pid), time.monotonic()
    await asyncio.sleep(seconds)
    cpu1, main1, t1 = cpu_seconds(pid), cpu_seconds(pid, pid), time.monotonic()
    gw1 = gateway_cpu_seconds(pid)
    decoded1 = await page.evaluate("() => window.telebotMedia.stats.videoDecoded")
    way.glass = [float(v) for v in await page.evaluate("() => window.telebotMedia.stats.glassMs")]
    way.cpu_pct = (cpu1 - cpu0) / (t1 - t0) * 100
    way.main_pct = (main1 - main0) / (t1 - t0) * 100
    way.gateway_pct = (gw1 - gw0) / (t1 - t0) * 100
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


async def local_way(browser: Any, daemon: Daemon, n: dict[str, int], way: Way) -> None:
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
    try:
        deadline = time.monotonic() + 60
        async with aiohttp.ClientSession() as http:
            while True:
                with contextlib.suppress(aiohttp.ClientError):
                    async with http.get(url) as response:
                        if response.status == 200:
                            break
                if time.monotonic() > deadline or ui.popen.poll() is not None:
                    raise RuntimeError(f"telebot-user ui did not serve its page: {ui.stderr()}")
                await asyncio.sleep(0.1)
        context = await browser.new_context(viewport={"width": 1280, "height": 800})
        try:
            page = await context.new_page()
            for _ in range(n["frames"]):
                way.first_frame.append(await first_frame(page, url))
            way.stop = await stops(page, daemon, daemon.driver, n["presses"])
            await glass_and_cpu(page, daemon, n["seconds"], way)
        finally:
            await context.close()
    finally:
        ui.stop(graceful=True)


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
    }
  } finally {
    await endpoint.close();
    link.close();
  }
  return out;
}
"""


async def gateway_way(
    browser: Any, daemon: Daemon, gateway_port: int, n: dict[str, int], way: Way
) -> None:
    """The browser client through the daemon's gateway, the key registered by an invite."""
    link = await asyncio.to_thread(invite_link, daemon, gateway_port)
    context = await browser.new_context(
        viewport={"width": 1280, "height": 800}, ignore_https_errors=True
    )
    try:
        page = await context.new_page()
        console: list[str] = []
        page.on("console", lambda m: console.append(f"{m.type}: {m.text}"))
        page.on("pageerror", lambda e: console.append(f"pageerror: {e}"))
        page.on(
            "response",
            lambda r: console.append(f"HTTP {r.status} {r.url}") if r.status >= 400 else None,
        )
        step = "the start page"
        try:
            await page.goto(link)
            await page.wait_for_selector("#create-key", state="visible", timeout=30_000)
            await page.fill("#new-name", NURSE)
            await page.click("#create-key")
            step = "accepting the invite"
            await page.wait_for_function(
                "() => !document.getElementById('accept-invite').disabled", timeout=30_000
            )
            await page.click("#accept-invite")
            await page.wait_for_function(
                "() => window.telebotSetup && (window.telebotSetup.error"
                " || window.telebotSetup.robots.some((r) => r.name === 'guiabot'"
                " && window.telebotSetup.invite === null))",
                timeout=30_000,
            )
            error = await page.evaluate("() => window.telebotSetup.error")
            if error:
                raise RuntimeError(error)
            step = "calls from the page (handshakes)"
            pairs = await page.evaluate(HANDSHAKES_JS, [ROBOT, n["calls"]])
            way.handshake = [float(h) for h, _ in pairs]
            way.call = [float(c) for _, c in pairs]
            step = "the robot page"
            url = f"https://127.0.0.1:{gateway_port}/call?robot={ROBOT}"
            for _ in range(n["frames"]):
                way.first_frame.append(await first_frame(page, url))
            step = "key presses"
            way.stop = await stops(page, daemon, NURSE, n["presses"])
            step = "glass and CPU"
            await glass_and_cpu(page, daemon, n["seconds"], way)
        except Exception as exc:  # reported as the gateway way's failure, in one line
            text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            way.failed = f"{step}: {text}"
            for line in console[-8:]:
                print(f"  gateway page console: {line[:300]}")
    finally:
        await context.close()


async def bench(quick: bool) -> tuple[Way, Way]:
    """Both ways against one daemon: (local, gateway)."""
    n = (
        {"frames": 1, "calls": 5, "presses": 3, "seconds": 2.0}
        if quick
        else {"frames": 5, "calls": 30, "presses": 100, "seconds": 10.0}
    )
    local, gateway = Way(), Way()
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        daemon, port = await start_daemon(base)
        try:
            assert OBSERVER  # the Python baseline's caller (not the page's driver)
            local.call = await python_calls(daemon, n["calls"])
            async with chromium(base) as browser:
                await local_way(browser, daemon, n, local)
                await gateway_way(browser, daemon, port, n, gateway)
        finally:
            daemon.stop(graceful=True)
    return local, gateway


# --------------------------------------------------------------------------- the report


def bundle_kb() -> float:
    return len(gzip.compress(BUNDLE.read_bytes(), compresslevel=9)) / 1000


def figures(way: Way, baseline: Way | None) -> dict[str, float]:
    """The RESULT figures of one way (``gateway_cpu_pct`` against ``baseline``)."""
    cpu = NAN
    if baseline is not None and way.fps > 0:
        cpu = way.gateway_pct * FPS / way.fps
    return {
        "first_frame_ms": statistics.median(way.first_frame) if way.first_frame else NAN,
        "handshake_ms_p50": pct(way.handshake, 50),
        "stop_p99_ms": pct(way.stop, 99),
        "glass_p50_ms": pct(way.glass, 50),
        "glass_p99_ms": pct(way.glass, 99),
        "gateway_cpu_pct": cpu,
        "bundle_kb": bundle_kb(),
    }


def report(local: Way, gateway: Way) -> dict[str, float]:
    mine, base = figures(gateway, local), figures(local, None)
    print("details:")
    for name, way in (("local", local), ("gateway", gateway)):
        print(
            f"  {name}: first frame {[round(v) for v in way.first_frame]} ms; "
            f"call() p50 {pct(way.call, 50):.1f} ms p99 {pct(way.call, 99):.1f} ms "
            f"(n={len(way.call)}); stop n={len(way.stop)} p50 {pct(way.stop, 50):.1f} ms "
            f"max {max(way.stop, default=NAN):.1f} ms; glass n={len(way.glass)}; "
            f"daemon CPU {way.cpu_pct:.1f} % (main thread {way.main_pct:.1f} %) at "
            f"{way.fps:.1f} pictures/s drawn"
        )
    print(
        f"  gateway CPU = its own threads {gateway.gateway_pct:.1f} % x 30 / {gateway.fps:.1f} "
        f"fps (measured directly); cross-check, whole daemon gateway way - local way: "
        f"{gateway.cpu_pct - local.cpu_pct:+.1f} %, main thread {gateway.main_pct - local.main_pct:+.1f} %"
    )
    print(f"  bundle {BUNDLE.stat().st_size / 1000:.1f} kB, gzipped {mine['bundle_kb']:.1f} kB")
    if gateway.failed:
        print(f"  GATEWAY WAY FAILED at {gateway.failed}")
    print(f"{'figure':<18} {'target':>9} {'local':>9} {'gateway':>9} {'gw/local':>9}  verdict")
    rows = [*TARGETS.items(), ("bundle_kb", (NAN, "kB"))]
    for name, (target, unit) in rows:
        g, loc = mine[name], base[name]
        if name == "handshake_ms_p50":  # no handshake stat in the Python client: call() times
            loc, ratio_of = pct(local.call, 50), pct(gateway.call, 50)
        else:
            ratio_of = g
        ratio = ratio_of / loc if loc and not math.isnan(loc) else NAN
        if name in ("gateway_cpu_pct", "bundle_kb"):
            loc, ratio = NAN, NAN
        verdict = "" if math.isnan(target) else ("MISS" if not g <= target else "PASS")
        print(
            f"{name:<18} {target:>7g}{unit:<2} {loc:>9.1f} {g:>9.1f} {ratio:>9.2f}  {verdict}"
            if not math.isnan(target)
            else f"{name:<18} {'':>9} {loc:>9.1f} {g:>9.1f} {ratio:>9.2f}"
        )
    print(
        "  (handshake's local column and ratio: the whole call() of the Python client and of "
        "the page; gw/local above 1 = the gateway way slower)"
    )
    return mine


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a few samples of each (< 30 s)")
    args = parser.parse_args()
    logging.getLogger("telebot").setLevel(logging.ERROR)
    started = time.monotonic()
    local, gateway = asyncio.run(bench(args.quick))
    mine = report(local, gateway)
    print(f"run took {time.monotonic() - started:.1f} s")
    print("RESULT " + " ".join(f"{k}={mine[k]:.2f}" for k in KEYS))
    return 0


if __name__ == "__main__":
    sys.exit(main())
