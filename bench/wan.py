"""telebot across the networks people really have: Wi-Fi that roams, 4G, another continent.

Run ``.venv/bin/python bench/wan.py`` (about 15 minutes; ``--quick``: one row of seconds).

One robot, ``telebot-robot run`` with the simulator (the small map, a fast base: 1.5 m/s,
3 m/s²; its camera 640 × 480, the default video) in its own process, the product's call
timeout (0.5 s) and deadman; one user in this process (``telebot.connect``: a zenoh client,
the product's reconnection; on QUIC two sessions, the calls' data on the second, the
product's default ``data_session``; ``--one-session``: one, for comparison). Between them a network emulator
(:class:`telebot.netem.NetemProxy`, on loopback, in this process on its own thread): the
user's zenoh session connects to the proxy, the proxy to the robot's listening endpoint, and
every byte or datagram crosses the profile's one-way delay, jitter, loss, bandwidth cap and
outages (seeded: every run loses the same packets; on TCP, whose connections share the
link's loss draws, as the connections' reads interleave). Rows:

- ``lan`` (the baseline, through the same proxy) and the profiles ``wifi``, ``4g``,
  ``intercontinental``, ``bad`` on the link telebot uses across the internet, ``quic/``
  (what ``telebot-router`` offers: QUIC over UDP with TLS, the robot listening with a
  certificate from a CA made as ``telebot-router init`` makes one, the user trusting that
  CA; telebot's lanes go as QUIC datagrams, zenoh's mixed reliability);
- ``4g`` on ``tcp/`` (zenoh's default link on a LAN; the proxy in TCP mode: a lost segment
  is retransmitted after TCP's timeout and holds up everything behind it) and ``udp/``
  (zenoh's datagram link: a lost datagram is gone; no TLS);
- every profile but ``lan`` in a **browser** (``PROFILE/browser``): the nurse's or the relative's
  way, a headless Chromium (bench/browser.py's) on the robot's own gateway (``[gateway]``),
  by WebTransport (HTTP/3 over QUIC, the page's default: a proxy in UDP mode in front of the
  gateway's UDP port, the page's ``/webtransport`` offer pointed at it) and HTTPS for the
  page itself (a proxy in TCP mode); ``4g/browser-ws`` is the same page on its fallback,
  two WebSockets (TCP; no WebTransport offered). The page's
  key made by an invite, as a nurse would. Measured: key press → robot at rest (a key that
  is not a drive key, pressed while the robot drives to a goal; bench/browser.py's
  ``stops``), glass to glass in the page (the robot's capture time to the page's
  decoding) and, meanwhile, the deadman's false trips while the page drives the robot to
  goals (re-armed after any stop); the other columns are the Python client's and print ``-``.

Figures of each row (times on this machine's ``CLOCK_MONOTONIC``, shared by both processes;
"minus one-way delay": the profile's mean one-way delay is taken off, so a figure is what
telebot and the link's losses add to the speed of light):

- **stop**: armed, ``fwd ±3`` by chat (towards the middle of the corridor, its first reply
  awaited), 0.1 s of driving, then ``t0`` and ``client.stop()``; the robot's audit record of
  the stop (``t``: the supervisor's step in which the base was halted) minus ``t0``. p99
  minus one-way delay; target ≤ 20 ms. Where the robot refuses to drive (its supervisor
  finds the link too slow) the robot is stopped at rest, and the row says so.
- **release**: hand driving (``client.drive``) until the base moves at > 0.2 m/s, then
  ``t0`` and ``client.drive(0, 0)``; the robot's audit record of the end of driving by hand
  (``released``, written right after the base was halted) minus ``t0``. p99 minus one-way
  delay; target ≤ 30 ms. ``n/a`` when the client has no ``drive`` (before issue 26 §4).
- **glass**: the user watches the video the whole time; glass to glass is the robot's
  capture time of a picture to its decoding here (both wall clocks of this machine), over
  the "watch" window. p50 and p99 minus one-way delay; target p99 ≤ 80 ms.
- **false trips**: during the watch window the robot is armed and driving (``fwd ±3`` again
  and again, re-armed after any stop): deadman latches (audit ``deadman``/``stopped``) with
  no real fault (the link only jitters, loses or roams: nothing is cut), scaled to an hour
  of that window; targets 0 on ``wifi``, ≤ 1 on ``4g``. Calls dropped in that window are
  counted too.
- **silence max** (the issue's heartbeat gaps): the longest time in that window in which
  the user heard nothing authentic from the robot (no heartbeat, pose or frame: the call's
  ``last_heard``, read every 10 ms, across reconnections). Past the call timeout (0.5 s)
  the call drops; on QUIC a loss burst that takes a whole flight stalls every lane until
  QUIC's probe timeout, which doubles each time.
- **late frames at 10 % loss**: the row's profile losing 10 % of its packets at random
  (its bursts off) for a new call through a second proxy, the video watched for a while: the share of the frames
  shown (decoded here) more than 150 ms after capture plus the one-way delay; target ≤ 1 %.
  The share of frames never shown (lost, or skipped until the next keyframe) is printed
  beside it.
- **reconnect**: the proxy forces a 3 s outage (``NetemProxy.outage``); from its end (the
  heal) to the first pose of the new call. p99; target ≤ 1 s. In a browser row both of the
  page's proxies (UDP and TCP) are out, and the first pose is the page's (``page_reconnects``).

Each figure's ratio to the ``lan`` row is printed (how much the network costs). A sample
that fails (a dropped call, a refusal, a record that never came) is counted in the row's
line and tried again (up to as many failures as samples); a call that cannot be opened is
tried three times; a phase that fails altogether makes its figures ``nan`` and is reported
in one line (``FAILED``); the run goes on. The last line is ``RESULT stop_p99_ms=… glass_p99_ms=…
late_frames_pct=… reconnect_p99_ms=… false_trips_wifi_h=… false_trips_4g_h=…
release_p99_ms=…``: each the worst profile on the default link (the baseline aside; the
``4g`` rows on ``tcp/`` and ``udp/`` compare links and are in the table, not in RESULT); the
table above it has them all.

``--quick``: one sample of each phase, half a second of each window (the trip figures then
come from seconds of driving: noise), a 1 s outage, and only the row ``4g`` (a check that it
runs: every phase, no ratios; ``--quick --row lan --row 4g`` adds the baseline); ``--row
PROFILE/LINK`` (repeatable) measures only those rows.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import dataclasses
import itertools
import json
import logging
import math
import sys
import tempfile
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import browser  # bench/browser.py: Chromium, the page's enrolment, its stops
from safety import MIDDLE_X, arm, start_motion  # bench/safety.py: the stop path's helpers

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from rig import FAST_SIM, REAL_TIMEOUT, Daemon
from telebot.config import AppConfig, SafetySettings
from telebot.errors import TelebotError
from telebot.netem import PROFILES, NetemProxy, Profile
from telebot.router import certs
from telebot.services.client import RobotClient, connect
from telebot.testing.net import free_port

#: The browser's way to the robot: Chromium (the page's own client, web/src) on the robot's
#: gateway, by WebTransport (HTTP/3 over QUIC: the proxy in UDP mode), the page's default.
BROWSER = "browser"
#: The same page kept on its fallback, two WebSockets (TCP: the proxy in TCP mode).
BROWSER_WS = "browser-ws"
BROWSERS = (BROWSER, BROWSER_WS)
LINKS = ("tcp", "udp", "quic", BROWSER, BROWSER_WS)
#: What a browser row measures (its other columns print ``-``).
BROWSER_FIGURES = (
    "stop_p99_ms",
    "glass_p50_ms",
    "glass_p99_ms",
    "reconnect_p99_ms",
    "false_trips_h",
)
#: The link across the internet (``telebot-router``'s): every profile is measured on it.
DEFAULT_LINK = "quic"
BASELINE = "lan"
#: (profile, link) rows, the baseline first.
ROWS: tuple[tuple[str, str], ...] = (
    (BASELINE, DEFAULT_LINK),
    ("wifi", DEFAULT_LINK),
    ("4g", DEFAULT_LINK),
    ("intercontinental", DEFAULT_LINK),
    ("bad", DEFAULT_LINK),
    ("4g", "tcp"),
    ("4g", "udp"),
    ("wifi", BROWSER),
    ("4g", BROWSER),
    ("intercontinental", BROWSER),
    ("bad", BROWSER),
    ("4g", BROWSER_WS),
)
#: The rows of a quick run: one profile (every phase; the baseline's row would double it).
QUICK_ROWS: tuple[tuple[str, str], ...] = (("4g", DEFAULT_LINK),)
#: Profiles whose watch window is long: the false-trip figures (and the baseline's).
TRIP_PROFILES = (BASELINE, "wifi", "4g")
LATE_LOSS = 0.10
LATE_MS = 150.0
#: Driving time before each stop (s).
MOTION = 0.1
SEED = 26
#: Tries to open a call (zenoh's session, the call's set-up) and each one's time limit (s).
CALL_TRIES = 3
CALL_TIMEOUT = 15.0
#: How long a release waits for the robot's record of it (s): none comes when driving had
#: ended before (a stall longer than ``[drive] stale_after``).
RELEASE_WAIT = 3.0
NAN = math.nan
TARGETS = {  # RESULT key: (target, what)
    "stop_p99_ms": (20.0, "stop p99 - delay"),
    "glass_p99_ms": (80.0, "glass p99 - delay"),
    "late_frames_pct": (1.0, "late frames %"),
    "reconnect_p99_ms": (1000.0, "reconnect p99"),
    "false_trips_wifi_h": (0.0, "false trips/h wifi"),
    "false_trips_4g_h": (1.0, "false trips/h 4g"),
    "release_p99_ms": (30.0, "release p99 - delay"),
}
#: The figures taken minus the profile's mean one-way delay: over many samples of one
#: packet each, the link's own spread puts their p99 this far up (:func:`spread_p99_ms`).
MINUS_DELAY = ("stop_p99_ms", "glass_p99_ms", "release_p99_ms")


def spread_p99_ms(profile: str) -> float:
    """How far above its mean the profile's one-way delay is at its 99th percentile, ms
    (the delay is uniform in delay +- jitter): what the link alone adds to a large sample's
    p99 minus the mean delay (a few samples' p99, their maximum, sits a little lower)."""
    return 0.98 * PROFILES[profile].jitter * 1000


@dataclass(frozen=True)
class Amounts:
    """How much of each phase a row measures."""

    stops: int
    releases: int
    watch_s: float
    trip_watch_s: float
    late_s: float
    outages: int
    outage_s: float


FULL = Amounts(
    stops=20, releases=12, watch_s=30.0, trip_watch_s=40.0, late_s=8.0, outages=5, outage_s=3.0
)
#: One of each, shortest: the outage still outlasts the call timeout, so the call drops.
QUICK = Amounts(
    stops=1, releases=1, watch_s=0.5, trip_watch_s=0.5, late_s=0.5, outages=1, outage_s=1.0
)


# -- pure helpers (tests/test_bench_wan.py) ---------------------------------------------------


def pct(values: list[float], q: float) -> float:
    """Nearest-rank percentile (``q`` in 0..100); nan for no values."""
    if not values:
        return NAN
    ordered = sorted(values)
    return ordered[max(1, math.ceil(q / 100 * len(ordered))) - 1]


def late_share(latencies_ms: list[float], delay_ms: float, limit_ms: float = LATE_MS) -> float:
    """The share (0..1) of frames shown more than ``limit_ms`` after capture plus the
    one-way delay; nan for no frames."""
    if not latencies_ms:
        return NAN
    return sum(1 for ms in latencies_ms if ms - delay_ms > limit_ms) / len(latencies_ms)


def never_shown(frame_ids: list[int]) -> tuple[int, int]:
    """(frames sent, frames never shown) from the numbers of the frames shown, in the order
    shown (consecutive numbers: a gap is a frame that was lost or skipped)."""
    if not frame_ids:
        return 0, 0
    sent = max(frame_ids) - min(frame_ids) + 1
    return sent, sent - len(set(frame_ids))


def longest_silence(heard: list[float], start: float, end: float) -> float:
    """The longest time (s) from ``start`` to ``end`` in which nothing was heard, from the
    moments something was (``heard``, any order; repeats and moments outside the window are
    ignored): the gaps between them, and the silence still running at ``end``. nan for an
    empty window."""
    if end <= start:
        return NAN
    moments = sorted({t for t in heard if start <= t <= end})
    edges = [start, *moments, end]
    return max(b - a for a, b in itertools.pairwise(edges))


def per_hour(count: int, seconds: float) -> float:
    """``count`` events in ``seconds`` scaled to an hour; nan for no time measured."""
    return count * 3600.0 / seconds if seconds > 0 else NAN


def worst(values: list[float]) -> float:
    """The largest of ``values`` that were measured (nan if none was)."""
    measured = [v for v in values if not math.isnan(v)]
    return max(measured) if measured else NAN


def ratio(value: float, base: float) -> str:
    """``value`` as a multiple of the baseline's (``-`` where it has no meaning)."""
    if math.isnan(value) or math.isnan(base) or base <= 0:
        return "-"
    return f"{value / base:.1f}x"


def parse_row(text: str) -> tuple[str, str]:
    """``PROFILE/LINK`` (``--row``); ValueError naming what is wrong."""
    name, sep, link = text.partition("/")
    if not sep:
        link = DEFAULT_LINK
    if name not in PROFILES:
        raise ValueError(f"unknown profile {name!r} (known: {', '.join(PROFILES)})")
    if link not in LINKS:
        raise ValueError(f"unknown link {link!r} (known: {', '.join(LINKS)})")
    return name, link


def with_loss(profile: Profile, loss: float) -> Profile:
    """``profile`` losing ``loss`` of its packets at random (no bursts: ``loss`` is the whole
    mean loss), for the late-frames phase."""
    return dataclasses.replace(
        profile, name=f"{profile.name}+{loss:.0%} loss", loss=loss, burst=None
    )


@dataclass
class Row:
    """What one (profile, link) row measured; times in ms."""

    profile: str
    link: str
    delay_ms: float = 0.0
    stop: list[float] = field(default_factory=list)
    release: list[float] = field(default_factory=list)
    glass: list[float] = field(default_factory=list)
    late: list[float] = field(default_factory=list)  # frames shown at 10 % loss
    late_expected: int = 0
    late_lost: int = 0
    late_drops: int = 0
    reconnect: list[float] = field(default_factory=list)
    trips: int = 0
    drive_seconds: float = 0.0
    silence: list[float] = field(default_factory=list)  # longest of each watch window
    drops: int = 0
    failed: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return f"{self.profile}/{self.link}"

    def figures(self) -> dict[str, float]:
        """The row's figures under the RESULT keys (and a few more), nan where unmeasured."""
        late = late_share(self.late, self.delay_ms)
        never = self.late_lost / self.late_expected if self.late_expected else NAN
        return {
            "stop_p99_ms": pct(self.stop, 99) - self.delay_ms,
            "stop_p50_ms": pct(self.stop, 50) - self.delay_ms,
            "glass_p99_ms": pct(self.glass, 99) - self.delay_ms,
            "glass_p50_ms": pct(self.glass, 50) - self.delay_ms,
            "late_frames_pct": late * 100,
            "never_shown_pct": never * 100,
            "reconnect_p99_ms": pct(self.reconnect, 99),
            "false_trips_h": per_hour(self.trips, self.drive_seconds),
            "silence_max_ms": worst(self.silence) * 1000,
            "release_p99_ms": pct(self.release, 99) - self.delay_ms,
        }


def result_rows(rows: list[Row]) -> list[Row]:
    """The rows the RESULT and the targets take: the profiles on the default link (the
    other links' rows compare links, to choose the default), the baseline aside. Without
    such rows (``--row 4g/tcp``): the rows measured, the baseline aside if others are."""
    profiles = [r for r in rows if r.profile != BASELINE and r.link == DEFAULT_LINK]
    return profiles or [r for r in rows if r.profile != BASELINE] or rows


def result_fields(rows: list[Row], drive: bool) -> dict[str, float]:
    """The RESULT figures: each the worst profile's (:func:`result_rows`)."""
    others = result_rows(rows)
    figures = [r.figures() for r in others]

    def trips(profile: str) -> float:
        return worst(
            [
                f["false_trips_h"]
                for r, f in zip(others, figures, strict=True)
                if r.profile == profile
            ]
        )

    return {
        "stop_p99_ms": worst([f["stop_p99_ms"] for f in figures]),
        "glass_p99_ms": worst([f["glass_p99_ms"] for f in figures]),
        "late_frames_pct": worst([f["late_frames_pct"] for f in figures]),
        "reconnect_p99_ms": worst([f["reconnect_p99_ms"] for f in figures]),
        "false_trips_wifi_h": trips("wifi"),
        "false_trips_4g_h": trips("4g"),
        "release_p99_ms": worst([f["release_p99_ms"] for f in figures]) if drive else NAN,
    }


def result_line(fields: dict[str, float], drive: bool) -> str:
    """``RESULT key=value ...`` (``n/a`` for the release figure without hand driving)."""
    parts = []
    for key, value in fields.items():
        text = "n/a" if key == "release_p99_ms" and not drive else f"{value:.1f}"
        parts.append(f"{key}={text}")
    return "RESULT " + " ".join(parts)


# -- the robot, the links, the proxies -------------------------------------------------------


class WanDaemon(Daemon):
    """The tests' robot daemon (``tests/rig.py``) listening on ``link`` (TLS for QUIC)."""

    def __init__(self, base: Path, link: str) -> None:
        # The product's call timeout (deadman) and stale-video lockout: they are measured here.
        super().__init__(
            base,
            observer=None,
            timeout=REAL_TIMEOUT,
            sim=FAST_SIM,
            stale_video=SafetySettings().stale_video,
        )
        self.link = link
        #: The link the robot's zenoh listens on (a browser reaches the gateway instead).
        self.zenoh_link = "tcp" if link in BROWSERS else link
        self.ca: Path | None = None
        self.gateway_port: int | None = None
        if link in BROWSERS:
            self.gateway_port = free_port()
            with self.robot_config.open("a") as config:
                config.write(f'[gateway]\nlisten = "127.0.0.1"\nport = {self.gateway_port}\n')
        if link == "quic":
            # A CA and a certificate for 127.0.0.1, made as ``telebot-router init`` does.
            tls = base / "tls"
            certs.init_ca(tls, [])
            self.ca = tls / "ca.pem"
            with self.robot_config.open("a") as config:
                config.write(
                    "[transport.zenoh.options]\n"
                    f'"transport/link/tls/listen_certificate" = "{tls / "router.pem"}"\n'
                    f'"transport/link/tls/listen_private_key" = "{tls / "router.key"}"\n'
                )

    def start(self, ready_timeout: float = 60.0, *, port: int | None = None) -> None:
        free = free_port() if self.zenoh_link == "tcp" else free_port("udp")
        super().start(ready_timeout, port=port if port is not None else free)

    @property
    def endpoint(self) -> str:
        return f"{self.zenoh_link}/127.0.0.1:{self.port}"


@contextlib.contextmanager
def proxy_to(daemon: WanDaemon, profile: Profile, seed: int) -> Iterator[NetemProxy]:
    """A NetemProxy on loopback (a free port) in front of ``daemon``'s listening endpoint."""
    with NetemProxy(profile, f"{daemon.link}/127.0.0.1:0", daemon.endpoint, seed) as proxy:
        yield proxy


#: ``[transport.zenoh]`` keys the user's config gets besides (``--one-session``).
USER_ZENOH: dict[str, Any] = {}


def user_config(daemon: WanDaemon, proxy: NetemProxy) -> AppConfig:
    """The user's config: a zenoh client that reaches the robot only through ``proxy``
    (a peer could find the robot's own endpoint behind its back), the product's call
    timeout and reconnection."""
    options: dict[str, Any] = {}
    if daemon.ca is not None:
        options["transport/link/tls/root_ca_certificate"] = str(daemon.ca)
    zenoh = {
        "mode": "client",
        "connect": [proxy.endpoint],
        "multicast_scouting": False,
        "options": options,
    }
    zenoh.update(USER_ZENOH)
    return AppConfig.model_validate(
        {"transport": {"zenoh": zenoh}, "call": {"timeout": REAL_TIMEOUT}}
    )


class AuditTail:
    """The robot's audit log from now on, read as it grows."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.offset = path.stat().st_size if path.exists() else 0
        self.records: list[dict[str, Any]] = []

    def read(self) -> list[dict[str, Any]]:
        """Records written since the last read (complete lines only)."""
        if not self.path.exists():
            return []
        with self.path.open("rb") as log:
            log.seek(self.offset)
            data = log.read()
        end = data.rfind(b"\n") + 1
        self.offset += end
        new = [json.loads(line) for line in data[:end].splitlines() if line.strip()]
        self.records += new
        return new

    async def wait(self, match: Callable[[dict[str, Any]], bool], timeout: float) -> dict[str, Any]:
        """The first record (from those read so far on) that passes ``match``."""
        deadline = time.monotonic() + timeout
        seen = 0
        while True:
            self.read()
            for record in self.records[seen:]:
                if match(record):
                    return record
            seen = len(self.records)
            if time.monotonic() > deadline:
                raise RuntimeError("no such record in the robot's audit log")
            await asyncio.sleep(0.01)


# -- the phases ------------------------------------------------------------------------------


class Watcher:
    """The user watches the robot's video across reconnections: every frame's arrival (this
    machine's monotonic clock), glass-to-glass latency (ms) and frame number."""

    def __init__(self, client: RobotClient) -> None:
        self.client = client
        self.frames: list[tuple[float, float, int, str]] = []
        self.receiver = client.video()
        self._task: asyncio.Task[None] | None = None

    async def __aenter__(self) -> Watcher:
        await self.receiver.__aenter__()
        self._task = asyncio.create_task(self._run())
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self._task is not None
        self._task.cancel()
        await asyncio.gather(self._task, return_exceptions=True)
        await self.receiver.__aexit__(None, None, None)

    async def _run(self) -> None:
        async for frame in self.receiver:
            call = self.client.call.id  # frame numbers start again on each call
            self.frames.append((time.monotonic(), frame.latency * 1000, frame.frame_id, call))

    def between(self, start: float, end: float) -> list[tuple[float, int, str]]:
        """(latency ms, frame number, call) of the frames shown from ``start`` to ``end``."""
        return [(ms, n, call) for t, ms, n, call in self.frames if start <= t <= end]

    async def first_frames(self, count: int, timeout: float) -> None:
        async with asyncio.timeout(timeout):
            while len(self.frames) < count:  # noqa: ASYNC110  (a frame wakes nobody)
                await asyncio.sleep(0.02)


async def ready(client: RobotClient) -> None:
    """Armed, the drive held (a reconnected call re-takes it)."""
    await arm(client, patience=20.0)


async def collect(
    row: Row, what: str, count: int, one: Callable[[], Awaitable[float]]
) -> list[float]:
    """``count`` samples of ``one()`` (ms). A sample that fails (a dropped call, a refusal,
    a record that never came) is counted in the row's notes and tried again, up to
    ``count`` failures in all."""
    values: list[float] = []
    failures: collections.Counter[str] = collections.Counter()
    while len(values) < count and failures.total() < count:
        try:
            values.append(await one())
        except (RuntimeError, TelebotError, TimeoutError) as exc:
            failures[one_line(exc)[:120]] += 1
    for reason, times in failures.items():
        row.notes.append(f"{what}: {times} failed ({reason})")
    return values


async def measure_stops(
    client: RobotClient, audit: AuditTail, row: Row, count: int, me: str
) -> None:
    refused = ""

    async def one() -> float:
        nonlocal refused
        await ready(client)
        try:
            await start_motion(client)
        except RuntimeError as exc:  # refused (a link too poor to drive): stop it at rest
            refused = str(exc)
        await asyncio.sleep(MOTION)
        t0 = time.monotonic()
        ack = await client.stop(timeout=10)
        if not ack.ok:
            raise RuntimeError(f"stop not acknowledged: {ack.text}")
        record = await audit.wait(
            lambda r: r["what"] == "stop" and r["t"] >= t0 and r["who"] == me, 10
        )
        return (record["t"] - t0) * 1000

    row.stop += await collect(row, "stops", count, one)
    if refused:
        row.notes.append(f"stops of a robot at rest: {refused}")


async def measure_releases(client: RobotClient, audit: AuditTail, row: Row, count: int) -> None:
    drive: Callable[..., None] = client.drive

    async def one() -> float:
        await ready(client)
        pose = client.latest_pose.value or await client.pose()
        linear = 1.0 if pose.x < MIDDLE_X else -1.0
        deadline = time.monotonic() + 10
        while True:
            drive(linear, 0.0)
            await asyncio.sleep(0.05)
            now = client.latest_pose.value
            if now is not None and abs(now.v) > 0.2:
                break
            if time.monotonic() > deadline:
                raise RuntimeError(f"the base did not move by hand ({client.drive_state})")
        moving = time.monotonic()
        await asyncio.sleep(0.1)
        drive(linear, 0.0)
        t0 = time.monotonic()
        drive(0.0, 0.0)
        try:
            record = await audit.wait(
                lambda r: (
                    r["what"].startswith("drive by hand: end")
                    and r["t"] >= t0
                    and str(r.get("detail", "")).startswith("released")
                ),
                RELEASE_WAIT,
            )
        except RuntimeError:
            # Say how driving ended instead (stale, stopped by the deadman, ...), if it did.
            ends = [
                r
                for r in audit.records
                if r["what"].startswith("drive by hand: end") and r["t"] >= moving
            ]
            if not ends:
                raise
            early = t0 - ends[-1]["t"]
            when = "before" if early >= 0 else "after"
            raise RuntimeError(
                f"driving ended {abs(early):.2f} s {when} the release, not by it: "
                f"{ends[-1].get('detail', '')}"
            ) from None
        finally:
            await asyncio.sleep(0.3)  # at rest: the next press starts from standstill
        return (record["t"] - t0) * 1000

    row.release += await collect(row, "releases", count, one)


async def keep_driving(client: RobotClient, until: float) -> None:
    """Armed and driving (``fwd ±3`` again and again) until ``until``; re-armed after any
    stop. Refusals and a dropped call only cost a moment."""
    while time.monotonic() < until:
        try:
            safety = client.latest_safety.value
            if safety is None or not safety.armed:
                await ready(client)
            await start_motion(client)
        except (RuntimeError, TelebotError, TimeoutError):
            await asyncio.sleep(1.0)  # refused (a poor link), or a call coming back
            continue
        await asyncio.sleep(min(1.5, max(0.0, until - time.monotonic())))


async def measure_watch(
    client: RobotClient, watcher: Watcher, audit: AuditTail, row: Row, seconds: float
) -> None:
    """Glass to glass, and the deadman's trips, while the robot drives for ``seconds``."""
    await ready(client)
    audit.read()
    first = len(audit.records)
    drops = client.reconnects
    start = time.monotonic()
    heard: list[float] = []

    async def listen() -> None:
        # The call's last_heard (the loop's clock, time.monotonic) every 10 ms: the moments
        # anything authentic came from the robot, to 10 ms, across reconnections.
        while True:
            heard.append(client.call.last_heard)
            await asyncio.sleep(0.01)

    listener = asyncio.create_task(listen())
    try:
        await keep_driving(client, start + seconds)
    finally:
        listener.cancel()
        await asyncio.gather(listener, return_exceptions=True)
    end = time.monotonic()
    row.silence.append(longest_silence(heard, start, end))
    audit.read()
    window = audit.records[first:]
    row.glass += [ms for ms, _, _ in watcher.between(start, end)]
    note_trips(row, window)
    row.drive_seconds += end - start
    row.drops += client.reconnects - drops
    with contextlib.suppress(TelebotError):
        await client.stop()


def note_trips(row: Row, records: list[dict[str, Any]]) -> None:
    """The deadman's latches among the robot's audit ``records``: counted, and why, noted."""
    trips = [r for r in records if r["what"] == "deadman" and r["outcome"] == "stopped"]
    row.trips += len(trips)
    row.notes += [f"deadman: {r['detail']}" for r in trips]


async def measure_reconnects(
    client: RobotClient, proxy: NetemProxy, row: Row, outages: int, seconds: float
) -> None:
    loop = asyncio.get_running_loop()
    poses: list[tuple[float, int]] = []

    async def follow() -> None:
        async for _ in client.poses():
            poses.append((loop.time(), client.reconnects))

    follower = asyncio.create_task(follow())
    try:
        for outage in range(1, outages + 1):
            await client.pose(timeout=30)
            before = client.reconnects
            proxy.outage(seconds)
            healed = loop.time() + seconds
            async with asyncio.timeout(60):
                while not any(t > healed and n > before for t, n in poses):  # noqa: ASYNC110
                    await asyncio.sleep(0.005)  # a pose wakes nobody: poll for it
            back = next(t for t, n in poses if t > healed and n > before)
            row.reconnect.append((back - healed) * 1000)
            if outage < outages:
                await asyncio.sleep(0.5)  # the new call settles before the next outage
    finally:
        follower.cancel()
        await asyncio.gather(follower, return_exceptions=True)


@contextlib.asynccontextmanager
async def call_robot(daemon: WanDaemon, config: AppConfig, row: Row) -> AsyncIterator[RobotClient]:
    """``telebot.connect`` to the robot, tried :data:`CALL_TRIES` times: over a lossy link
    zenoh's session or the call's set-up can fail (each failure is noted in the row)."""
    for attempt in range(1, CALL_TRIES + 1):
        stack = contextlib.AsyncExitStack()
        try:
            client = await stack.enter_async_context(
                connect(daemon.robot, home=daemon.user_home, config=config, timeout=CALL_TIMEOUT)
            )
        except TelebotError as exc:
            await stack.aclose()
            row.notes.append(f"call attempt {attempt} failed: {one_line(exc)}")
            if attempt == CALL_TRIES:
                raise
            continue
        async with stack:
            yield client
        return


def one_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:300] if text else type(exc).__name__


async def phase(row: Row, name: str, run: Awaitable[None]) -> None:
    """Run one phase; a failure is noted in the row (its figures stay unmeasured)."""
    try:
        await run
    except Exception as exc:
        text = one_line(exc)
        row.failed[name] = text
        print(f"  {row.name}: {name} FAILED: {text}", flush=True)


async def measure_row(
    daemon: WanDaemon, profile: Profile, row: Row, amounts: Amounts, drive: bool
) -> None:
    """Every phase of one row through proxies with ``profile``."""
    watch_s = amounts.trip_watch_s if row.profile in TRIP_PROFILES else amounts.watch_s
    if row.link in BROWSERS:
        await measure_browser_row(daemon, profile, row, amounts, watch_s)
        return
    audit = AuditTail(daemon.robot_home / "audit.jsonl")
    with proxy_to(daemon, profile, SEED) as proxy:
        config = user_config(daemon, proxy)
        await phase(
            row, "call", calling(daemon, config, row, audit, proxy, amounts, drive, watch_s)
        )
    lossy = with_loss(profile, LATE_LOSS)
    with proxy_to(daemon, lossy, SEED + 1) as proxy:
        config = user_config(daemon, proxy)
        await phase(row, "late frames", late_frames(daemon, config, row, amounts.late_s))


async def calling(
    daemon: WanDaemon,
    config: AppConfig,
    row: Row,
    audit: AuditTail,
    proxy: NetemProxy,
    amounts: Amounts,
    drive: bool,
    watch_s: float,
) -> None:
    """The phases of one call on the row's profile: stops, releases, watch, outages."""
    async with call_robot(daemon, config, row) as client, Watcher(client) as watcher:
        await phase(row, "first picture", watcher.first_frames(5, 60))
        stops = measure_stops(client, audit, row, amounts.stops, daemon.driver)
        await phase(row, "stops", stops)
        if drive:
            await phase(row, "releases", measure_releases(client, audit, row, amounts.releases))
        await phase(row, "watch", measure_watch(client, watcher, audit, row, watch_s))
        await phase(
            row,
            "reconnects",
            measure_reconnects(client, proxy, row, amounts.outages, amounts.outage_s),
        )
        with contextlib.suppress(TelebotError):
            await client.stop()


async def measure_browser_row(
    daemon: WanDaemon, profile: Profile, row: Row, amounts: Amounts, watch_s: float
) -> None:
    """The browser's row: a nurse's page (bench/browser.py: a key made in the page by an
    invite) through proxies with ``profile`` in front of the robot's gateway (TCP for the
    page and its WebSockets, UDP for its WebTransport; ``browser-ws`` rows get no
    WebTransport offer, so the page keeps to its WebSockets); key presses that stop the
    driving robot (``browser.stops``), then the video watched while the page drives
    (:func:`page_drive`)."""
    assert daemon.gateway_port is not None
    name = "nurse-" + row.profile  # one key per row: each row's page makes its own
    want = "webtransport" if row.link == BROWSER else "websocket"
    with (
        NetemProxy(
            profile, "tcp/127.0.0.1:0", f"tcp/127.0.0.1:{daemon.gateway_port}", SEED
        ) as proxy,
        NetemProxy(
            profile, "udp/127.0.0.1:0", f"udp/127.0.0.1:{daemon.gateway_port}", SEED
        ) as datagrams,
        tempfile.TemporaryDirectory(prefix="telebot-bench-wan-page-") as tmp,
    ):
        port = int(proxy.endpoint.rpartition(":")[2])
        udp_port = int(datagrams.endpoint.rpartition(":")[2])
        way = browser.Way(row.name)  # collects the page's console and failed responses
        async with (
            browser.chromium(Path(tmp)) as chromium,
            browser.gateway_page(chromium, way) as page,
        ):
            await page.route("**/webtransport", offer_through(udp_port, row.link))
            url = f"https://127.0.0.1:{port}/call?robot={daemon.robot}"
            await phase(row, "setup", browser.enrol(page, daemon, port, name, timeout=60))
            if not row.failed:
                await phase(row, "call", page.goto(url, timeout=60_000))
            if not row.failed:
                await phase(row, "link", page_link_is(page, want))
            if not row.failed:
                stops = browser.stops(page, daemon.robot_home, name, amounts.stops, row.stop)
                await phase(row, "stops", stops)
                await phase(row, "watch", page_watch(page, daemon.robot_home, watch_s, row))
                outages = page_reconnects(
                    page, (proxy, datagrams), row, amounts.outages, amounts.outage_s
                )
                await phase(row, "outages", outages)
            if row.failed:  # what the page said may tell why
                row.notes += way.console[-3:]


def offer_through(udp_port: int, link: str) -> Callable[[Any], Awaitable[None]]:
    """A route for the page's ``/webtransport``: the gateway's offer with the UDP proxy's
    port (so the page's QUIC goes through the emulator), or none for a ``browser-ws`` row."""

    async def route(request: Any) -> None:
        if link == BROWSER_WS:
            await request.fulfill(status=404, json={"error": "off for this row"})
            return
        response = await request.fetch()
        offer = await response.json()
        offer["port"] = udp_port
        await request.fulfill(response=response, json=offer)

    return route


async def page_link_is(page: Any, kind: str) -> None:
    """The page's call reaches the gateway the way the row measures, or the phase fails."""
    deadline = time.monotonic() + 60
    while (found := await page.evaluate("() => window.telebotPort.linkKind()")) is None:
        if time.monotonic() > deadline:
            raise RuntimeError("the page opened no link to its gateway in 60 s")
        await asyncio.sleep(0.2)
    if found != kind:
        raise RuntimeError(f"the page's link is {found}, not {kind}")


#: In the page: the wall-clock time (ms) of each pose it shows, with the page's count of
#: reconnections then (``window.benchPoses``, the last 1,000).
POSES_JS = """() => {
  const ui = window.telebotUI;
  window.benchPoses = [];
  ui.hooks.message.push((m) => {
    if (m.type !== "pose") return;
    window.benchPoses.push([Date.now(), ui.stats.reconnected]);
    if (window.benchPoses.length > 1000) window.benchPoses.shift();
  });
}"""


async def page_reconnects(
    page: Any, proxies: tuple[NetemProxy, ...], row: Row, outages: int, seconds: float
) -> None:
    """As :func:`measure_reconnects`, for the page: ``seconds`` of outage on all its
    ``proxies`` at once (the network gone), then from the heal to the first pose the page
    shows on its new call."""
    await page.evaluate(POSES_JS)
    for outage in range(1, outages + 1):
        await page.wait_for_function("() => window.benchPoses.length > 0", timeout=60_000)
        before = int(await browser.page_state(page, "ui.stats.reconnected"))
        for proxy in proxies:
            proxy.outage(seconds)
        healed_ms = (time.time() + seconds) * 1000
        back = (
            "([healed, before]) => { const p = window.benchPoses.find(([t, n]) =>"
            " t > healed && n > before); return p ? p[0] : null; }"
        )
        handle = await page.wait_for_function(
            back, arg=[healed_ms, before], timeout=60_000, polling=5
        )
        row.reconnect.append(float(await handle.json_value()) - healed_ms)
        if outage < outages:
            await asyncio.sleep(0.5)  # the new call settles before the next outage
            await page.evaluate("() => { window.benchPoses.length = 0; }")


async def page_watch(page: Any, home: Path, seconds: float, row: Row) -> None:
    """Glass to glass in the page while it drives the robot; either failing ends both (its
    error is the phase's)."""
    try:
        async with asyncio.TaskGroup() as group:
            group.create_task(page_glass(page, seconds, row))
            group.create_task(page_drive(page, home, seconds, row))
    except ExceptionGroup as failed:
        raise failed.exceptions[0] from None


async def page_drive(page: Any, home: Path, seconds: float, row: Row) -> None:
    """The page drives the robot for ``seconds`` (goals from one end of the corridor to the
    other, re-armed after any stop, as a nurse would): the deadman's trips, from the robot's
    audit log (no real fault here: the link only jitters, loses or roams)."""
    audit = AuditTail(home / "audit.jsonl")
    reconnected = int(await browser.page_state(page, "ui.stats.reconnected"))
    start = time.monotonic()
    while time.monotonic() - start < seconds:
        armed, moving, x = await browser.page_state(
            page,
            "[!!(ui.state.safety && ui.state.safety.armed), Math.abs(ui.state.pose.v) > 0.05,"
            " ui.state.pose.x]",
        )
        if not armed:
            await page.evaluate("() => window.telebotUI.send({type: 'arm'})")
        elif not moving:
            await browser.goal_far_end(page, x)
        await asyncio.sleep(0.5)
    row.drive_seconds += time.monotonic() - start
    row.drops += int(await browser.page_state(page, "ui.stats.reconnected")) - reconnected
    note_trips(row, audit.read())
    await page.evaluate("() => window.telebotUI.send({type: 'stop'})")


async def page_glass(page: Any, seconds: float, row: Row) -> None:
    """Glass to glass in the page over ``seconds``: the robot's capture time of each picture
    to its decoding in the page (``telebotMedia.stats.glassMs``, both this machine's wall
    clock)."""
    await page.wait_for_function(
        "() => window.telebotMedia.stats.videoDecoded >= 10", timeout=60_000
    )
    await page.evaluate("() => { window.telebotMedia.stats.glassMs.length = 0; }")
    await asyncio.sleep(seconds)
    glass = await page.evaluate("() => window.telebotMedia.stats.glassMs")
    row.glass += [float(ms) for ms in glass]


async def late_frames(daemon: WanDaemon, config: AppConfig, row: Row, seconds: float) -> None:
    """The video on a new call at 10 % loss: frames shown, late, never shown."""
    async with call_robot(daemon, config, row) as client, Watcher(client) as watcher:
        await watcher.first_frames(5, 60)
        start = time.monotonic()
        await asyncio.sleep(seconds)
        shown = watcher.between(start, time.monotonic())
        row.late += [ms for ms, _, _ in shown]
        row.late_drops = client.reconnects
        for call in {c for _, _, c in shown}:
            sent, lost = never_shown([n for _, n, c in shown if c == call])
            row.late_expected += sent
            row.late_lost += lost


# -- the report ------------------------------------------------------------------------------


def fmt(value: float, digits: int = 1) -> str:
    return "nan" if math.isnan(value) else f"{value:.{digits}f}"


def row_line(row: Row, amounts: Amounts) -> str:
    """What a row measured, in counts, with its notes and failed phases."""
    trips = (
        f"{row.trips} trips in {row.drive_seconds:.0f} s of driving, " if row.drive_seconds else ""
    )
    if row.link in BROWSERS:
        counted = (
            f"{len(row.stop)} key presses, {len(row.glass)} frames watched in the page"
            + (f", {trips}{row.drops} calls dropped while driving" if trips else "")
            + (f", {len(row.reconnect)} outages of {amounts.outage_s:g} s" if row.reconnect else "")
        )
    else:
        counted = (
            f"{len(row.stop)} stops, {len(row.release)} releases, "
            f"{len(row.glass)} frames watched, {len(row.late)} at {LATE_LOSS:.0%} loss "
            f"({row.late_lost} of {row.late_expected} never shown, {row.late_drops} calls "
            "dropped), "
            f"{len(row.reconnect)} outages of {amounts.outage_s:g} s; {trips}{row.drops} calls "
            f"dropped while driving, longest silence {fmt(row.figures()['silence_max_ms'], 0)} ms"
        )
    return (
        f"{row.name} ({row.seconds:.0f} s): {counted}"
        + "".join(f"; {note}" for note in row.notes)
        + "".join(f"; {name} FAILED: {why}" for name, why in row.failed.items())
    )


def report(rows: list[Row], drive: bool, amounts: Amounts, seconds: float) -> list[str]:
    base = next((r.figures() for r in rows if r.profile == BASELINE), None)
    columns = (
        ("stop p99", "stop_p99_ms"),
        ("glass p50", "glass_p50_ms"),
        ("glass p99", "glass_p99_ms"),
        ("late %", "late_frames_pct"),
        ("unshown %", "never_shown_pct"),
        ("reconn p99", "reconnect_p99_ms"),
        ("trips/h", "false_trips_h"),
        ("silence max", "silence_max_ms"),
        ("release p99", "release_p99_ms"),
    )
    head = f"{'row':>24} | {'delay':>5} | " + " | ".join(f"{c:>11}" for c, _ in columns)
    lines = [
        "",
        "Figures in ms minus the profile's mean one-way delay (stop, glass, release); late % "
        f"at {LATE_LOSS:.0%} loss: frames shown > {LATE_MS:g} ms after capture + delay, of those "
        "shown (unshown %: never shown); reconnect: heal -> first pose; trips/h: deadman "
        "latches with no real fault per hour of driving; silence max: the longest time the user "
        "heard nothing from the robot while it drove (the call timeout is "
        f"{REAL_TIMEOUT * 1000:.0f} ms). (xN): ratio to the lan row.",
        head,
        "-" * len(head),
    ]
    for row in rows:
        figures = row.figures()
        cells = []
        for _, key in columns:
            value = figures[key]
            if row.link in BROWSERS and key not in BROWSER_FIGURES:
                cells.append(f"{'-':>11}")
                continue
            if key == "release_p99_ms" and not drive:
                cells.append(f"{'n/a':>11}")
                continue
            digits = 2 if key == "false_trips_h" else 1
            text = fmt(value, digits)
            if base is not None and row.profile != BASELINE and key != "false_trips_h":
                r = ratio(value, base[key])
                text += f" ({r})" if r != "-" else ""
            cells.append(f"{text:>11}")
        lines.append(f"{row.name:>24} | {row.delay_ms:>5.0f} | " + " | ".join(cells))
    lines.append("")
    for row in rows:
        lines.append(row_line(row, amounts))
    if not drive:
        lines.append("release: n/a (needs drive): this client has no RobotClient.drive yet")
    fields = result_fields(rows, drive)
    taken = result_rows(rows)
    lines += ["", "Targets and RESULT: the worst of " + ", ".join(r.name for r in taken)]
    for key, (target, what) in TARGETS.items():
        value = fields[key]
        if key == "release_p99_ms" and not drive:
            lines.append(f"target {what} <= {target:g}: n/a (needs drive)")
            continue
        ok = not math.isnan(value) and value <= target
        verdict = "PASS" if ok else ("nan" if math.isnan(value) else "MISS")
        line = f"target {what} <= {target:g}: worst profile {fmt(value)} {verdict}"
        if verdict == "MISS" and key in MINUS_DELAY:
            row = next(r for r in taken if r.figures()[key] == value)
            line += (
                f" ({row.name}; the link alone: one-way delay p99 "
                f"{spread_p99_ms(row.profile):.0f} ms above its mean)"
            )
        lines.append(line)
    mode = "quick" if amounts == QUICK else "full"
    lines.append(f"({mode} run, took {seconds:.0f} s)")
    lines.append(result_line(fields, drive))
    return lines


def run_rows(selected: list[tuple[str, str]], amounts: Amounts) -> tuple[list[Row], bool]:
    drive = hasattr(RobotClient, "drive")
    rows: list[Row] = []
    for link in LINKS:  # one robot per link, the rows of that link in order
        mine = [(p, lk) for p, lk in selected if lk == link]
        if not mine:
            continue
        with tempfile.TemporaryDirectory(prefix="telebot-bench-wan-") as tmp:
            daemon = WanDaemon(Path(tmp), link)
            daemon.start()
            try:
                for name, _ in mine:
                    profile = PROFILES[name]
                    row = Row(name, link, delay_ms=profile.delay * 1000)
                    print(f"{row.name} ...", flush=True)
                    started = time.monotonic()
                    asyncio.run(measure_row(daemon, profile, row, amounts, drive))
                    row.seconds = time.monotonic() - started
                    rows.append(row)
            finally:
                daemon.stop(graceful=True)
    order = {key: i for i, key in enumerate(selected)}
    rows.sort(key=lambda r: order[(r.profile, r.link)])
    return rows, drive


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a few seconds, row 4g only")
    parser.add_argument(
        "--row",
        action="append",
        default=[],
        metavar="PROFILE/LINK",
        help="measure only this row (repeatable), e.g. 4g/udp",
    )
    parser.add_argument(
        "--one-session",
        action="store_true",
        help="the Python user's zenoh on one session (data_session = false): the comparison "
        "for its default on QUIC, a second session for the calls' data",
    )
    args = parser.parse_args()
    if args.one_session:
        USER_ZENOH["data_session"] = False
    try:
        selected = [parse_row(text) for text in args.row] or list(
            QUICK_ROWS if args.quick else ROWS
        )
    except ValueError as exc:
        parser.error(f"--row: {exc}")
    logging.basicConfig(level=logging.ERROR)  # reconnections and stops are logged as warnings
    started = time.monotonic()
    rows, drive = run_rows(selected, QUICK if args.quick else FULL)
    print("\n".join(report(rows, drive, QUICK if args.quick else FULL, time.monotonic() - started)))


if __name__ == "__main__":
    main()
