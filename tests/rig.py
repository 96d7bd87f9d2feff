"""One rig for integration tests and benchmarks: a robot and its users, on zenoh or in memory.

- :class:`Daemon`: ``telebot-robot run`` in its own process (``--events``, zenoh on a free
  127.0.0.1 port, the small map and a fast robot by default) and the homes of its users: a
  driver (alice) and, optionally, an observer (olga), paired with the robot. It gives what a
  user needs to reach it (:attr:`Daemon.endpoint`, :meth:`Daemon.config`,
  :meth:`Daemon.connect`, :meth:`Daemon.user_cli`, config files for child processes) and what
  the robot recorded (:meth:`Daemon.audit`, :meth:`Daemon.call_ended`).
- :func:`robot_on_hub`: the same robot (SimNavStack, SafetyDriver, RobotServer) in this
  process on a memory hub.

Timing on a shared, loaded machine (CI runs on 2 cores; so do five engineers at once):

- **Call timeouts.** A process preempted for longer than the call timeout (0.5 s by default)
  drops its calls. A test that is not about drop timing therefore runs with
  :data:`GENEROUS_TIMEOUT`, on the robot and on every user the rig configures (heartbeats
  stay at 20 Hz); a test about the deadman or drop detection asks for :data:`REAL_TIMEOUT`
  explicitly (``Daemon(..., timeout=REAL_TIMEOUT)``).
- **Stale video.** Likewise a loaded machine stalls the robot's camera, encoder or a page's
  decoder for longer than the stale-video lockout (``[safety] stale_video``, 1 s), which
  stops a moving robot whose driver watches video: a :class:`Daemon` and
  :func:`robot_on_hub` run with :data:`GENEROUS_STALE_VIDEO` unless the test asks for the
  product's value.
- **Wall-clock bounds.** :data:`SLACK` is a number of seconds (``$TELEBOT_TEST_SLACK``,
  default 1.0) added to every wall-clock bound an integration test asserts, on top of the
  requirement and the product's own periods: ``TIMEOUT + 0.5 + SLACK``. Seconds, not a
  factor, because a loaded machine adds delays of its own (a preempted process, a late
  thread) rather than stretching the product's; set it higher on a slower machine. Short
  waits for something that must happen get it too.
- **What is timed.** Where a property is about time (how soon the base stopped after the
  driver froze), the test compares recorded times — audit records and pose stamps carry the
  robot's ``time.monotonic()``, which on Linux is this process's clock too — with the moment
  of the cause, not how long the test itself waited. The figures belong in ``bench/``.

This module needs no pytest: ``bench/`` imports it (with ``tests/`` on ``sys.path``).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import json
import os
import queue
import signal
import subprocess
import sys
import threading
from collections.abc import AsyncIterator, Mapping
from pathlib import Path
from typing import Any

from telebot.channels.call import RobotEndpoint, UserEndpoint
from telebot.channels.transports.base import Transport
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import (
    AppConfig,
    CallSettings,
    CipherChoice,
    ServiceSettings,
    SimSettings,
    ZenohSettings,
)
from telebot.identity import ContactBook, Identity, KnownRobots, Role, create_paired_homes
from telebot.robot.mapfile import places_path_for
from telebot.robot.sim.stack import SimNavStack, resolve_map
from telebot.services import registry as service_registry
from telebot.services.base import ServiceConfig, ServiceRegistry
from telebot.services.client import RobotClient, connect
from telebot.services.drive.robot import RobotDrive
from telebot.services.robot import RobotServer
from telebot.services.safety.robot import SafetyDriver
from telebot.services.video.wire import VideoSettings
from telebot.testing.net import free_port

ROBOT = "guiabot"
USER = "alice"
OBSERVER = "olga"
TESTS = Path(__file__).resolve().parent

#: Extra seconds for every wall-clock bound an integration test asserts (see the module doc).
SLACK = float(os.environ.get("TELEBOT_TEST_SLACK", "1.0"))
#: The product's call timeout (s): for tests about the deadman and drop detection.
REAL_TIMEOUT = CallSettings().timeout
#: The call timeout (s) of tests that are not about timing: a preempted process keeps its calls.
GENEROUS_TIMEOUT = 2.0
#: The stale-video lockout (s) of daemons in tests that are not about it (see the module doc).
GENEROUS_STALE_VIDEO = 5.0

#: The small map and a fast robot, so that moves take a second or two.
FAST_SIM: dict[str, Any] = {
    "map": "small",
    "max_linear_speed": 1.5,
    "linear_accel": 3.0,
    "max_angular_speed": 3.0,
    "angular_accel": 8.0,
}


def _toml_value(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    return repr(value)


def write_config(
    path: Path,
    *,
    lease_ms: int | None = None,
    timeout: float | None = None,
    sim: Mapping[str, Any] | None = None,
    stale_video: float | None = None,
) -> Path:
    """A telebot TOML config for loopback tests: no multicast scouting; optionally zenoh's
    link lease, the call timeout (s), the stale-video lockout (s) and a ``[sim]`` table."""
    lines = ["[transport.zenoh]", "multicast_scouting = false"]
    if lease_ms is not None:
        lines += ["[transport.zenoh.options]", f'"transport/link/tx/lease" = {lease_ms}']
    if timeout is not None:
        lines += ["[call]", f"timeout = {timeout}"]
    if stale_video is not None:
        lines += ["[safety]", f"stale_video = {stale_video}"]
    if sim:
        lines += ["[sim]", *(f"{key} = {_toml_value(value)}" for key, value in sim.items())]
    path.write_text("\n".join(lines) + "\n")
    return path


def child_env() -> dict[str, str]:
    """Environment for a child process that imports modules from ``tests/``."""
    path = os.pathsep.join(filter(None, [str(TESTS), os.environ.get("PYTHONPATH")]))
    return {"PYTHONPATH": path}


class Process:
    """A telebot command (``python -m ARGS``) in a child process.

    Its stdout lines are read by a thread into :attr:`lines`; its stderr by another, which
    keeps the last lines (a pipe nobody reads would block a chatty daemon once full).
    ``stdin``: ``subprocess.PIPE`` for a pipe to :meth:`write` to, or a file descriptor
    (a pty's end); None inherits this process's.
    """

    def __init__(
        self, args: list[str], env: dict[str, str] | None = None, *, stdin: int | None = None
    ) -> None:
        self.popen = subprocess.Popen(
            [sys.executable, "-m", *args],
            stdin=stdin,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, **(env or {})},
        )
        self.lines: queue.Queue[str] = queue.Queue()
        self._stderr: collections.deque[str] = collections.deque(maxlen=200)
        self._readers = [
            threading.Thread(target=self._read, daemon=True),
            threading.Thread(target=self._read_stderr, daemon=True),
        ]
        for reader in self._readers:
            reader.start()

    @property
    def pid(self) -> int:
        return self.popen.pid

    def _read(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self.lines.put(line.rstrip("\n"))

    def _read_stderr(self) -> None:
        assert self.popen.stderr is not None
        for line in self.popen.stderr:
            self._stderr.append(line)

    def next_line(self, timeout: float = 10.0) -> str:
        """The next stdout line (AssertionError if none comes in time)."""
        try:
            return self.lines.get(timeout=timeout)
        except queue.Empty:
            raise AssertionError(f"no output within {timeout} s; stderr: {self.stderr()}") from None

    async def next_event(self, timeout: float = 10.0) -> dict[str, Any]:
        """The next JSON event line, awaited without blocking the event loop."""
        line = await asyncio.to_thread(self.next_line, timeout)
        event: dict[str, Any] = json.loads(line)
        return event

    async def wait_event(self, name: str, timeout: float = 10.0) -> dict[str, Any]:
        """Skip events until one named ``name`` arrives."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            event = await self.next_event(max(0.01, deadline - loop.time()))
            if event.get("event") == name:
                return event

    def write(self, text: str) -> None:
        """Write ``text`` to the process's stdin pipe, at once."""
        assert self.popen.stdin is not None, "started without stdin=subprocess.PIPE"
        self.popen.stdin.write(text)
        self.popen.stdin.flush()

    def stderr(self) -> str:
        """The last lines the process wrote to stderr (all of them once it has exited)."""
        if self.popen.poll() is not None:
            self._readers[1].join(timeout=5)
        return "".join(self._stderr)

    def signal(self, sig: signal.Signals) -> None:
        self.popen.send_signal(sig)

    def stop(self, *, graceful: bool = False) -> None:
        """End the process: SIGTERM and a wait of 10 s first if ``graceful``, then SIGKILL."""
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGCONT)
            if graceful:
                self.popen.terminate()
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self.popen.wait(timeout=10)
            if self.popen.poll() is None:
                self.popen.kill()
        self.popen.wait(timeout=10)
        for reader in self._readers:
            reader.join(timeout=5)
        for pipe in (self.popen.stdin, self.popen.stdout, self.popen.stderr):
            if pipe is not None:
                with contextlib.suppress(OSError):  # stdin: a broken pipe on its flush
                    pipe.close()


class Daemon:
    """A robot daemon process (restartable on the same home) and what its users need.

    Homes under ``base``: ``robot`` (the daemon's), ``user`` (``driver``, a driver) and, if
    ``observer`` is given, one named after the observer. ``timeout`` is the call timeout
    of the robot and of every user configured here (:data:`GENEROUS_TIMEOUT` unless the test
    is about timing); ``stale_video`` the robot's stale-video lockout
    (:data:`GENEROUS_STALE_VIDEO` unless the test is about it); ``sim`` the ``[sim]`` table
    (:data:`FAST_SIM` by default). Call :meth:`start`; :meth:`stop` ends it.
    """

    def __init__(
        self,
        base: Path,
        *,
        robot: str = ROBOT,
        driver: str = USER,
        observer: str | None = OBSERVER,
        timeout: float = GENEROUS_TIMEOUT,
        sim: Mapping[str, Any] | None = None,
        stale_video: float = GENEROUS_STALE_VIDEO,
    ) -> None:
        create_paired_homes(base, robot, driver, role=Role.DRIVER)
        self.base = base
        self.robot = robot
        self.driver = driver
        self.robot_home = base / "robot"
        self.user_home = base / "user"
        self.observer = observer
        self.observer_home = base / (observer or "observer")
        if observer is not None:
            self.add_user(observer, Role.OBSERVER, self.observer_home)
        self._sim = FAST_SIM if sim is None else sim
        self._stale_video = stale_video
        self.robot_config = base / "robot.toml"
        self.set_timeout(timeout)
        self.port = 0
        self.process: Process | None = None
        #: The daemon's ``ready`` event (its first line) of the last start.
        self.ready: dict[str, Any] = {}

    def set_timeout(self, timeout: float) -> None:
        """The call timeout of the robot (from its next start), of ``user.toml`` and of the
        users connected with :meth:`connect` from now on."""
        self.timeout = timeout
        write_config(
            self.robot_config, timeout=timeout, sim=self._sim, stale_video=self._stale_video
        )
        self.user_config = self.write_user_config("user.toml")

    def add_user(self, name: str, role: Role, home: Path) -> Identity:
        """A new user with a home of its own, in the robot's contacts with ``role``."""
        user = Identity.generate(name)
        user.save(home)
        book = ContactBook.load(self.robot_home)
        book.add(name, user.public_key, role)
        book.save()
        known = KnownRobots.load(home)
        known.add(self.robot, Identity.load(self.robot_home).public_key)
        known.save()
        return user

    def start(self, ready_timeout: float = 60.0, *, port: int | None = None) -> None:
        """Start the daemon (again, on ``port`` or a new free one) and wait until it is ready."""
        self.port = port if port is not None else free_port()
        self.process = Process(
            [
                "telebot.apps.robot_cli",
                "run",
                "--home",
                str(self.robot_home),
                "--config",
                str(self.robot_config),
                "--listen",
                self.endpoint,
                "--events",
            ]
        )
        line = self.process.next_line(timeout=ready_timeout)
        assert '"ready"' in line, line
        self.ready = json.loads(line)

    def stop(self, *, graceful: bool = False) -> None:
        """Kill the daemon (SIGTERM first if ``graceful``)."""
        if self.process is not None:
            self.process.stop(graceful=graceful)

    @property
    def events(self) -> Process:
        """The daemon's process, whose stdout lines are its ``--events``."""
        assert self.process is not None, "the daemon was not started"
        return self.process

    @property
    def pid(self) -> int:
        return self.events.pid

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.port}"

    def config(self, timeout: float | None = None) -> AppConfig:
        """A user's config in this process: zenoh to the daemon, the rig's call timeout."""
        zenoh = ZenohSettings(connect=[self.endpoint], multicast_scouting=False)
        call = CallSettings(timeout=self.timeout if timeout is None else timeout)
        return AppConfig.model_validate({"transport": {"zenoh": zenoh}, "call": call})

    def connect(
        self, home: Path | None = None, *, timeout: float = 10, call_timeout: float | None = None
    ) -> contextlib.AbstractAsyncContextManager[RobotClient]:
        """A user in this process calls the robot (the driver unless ``home`` says who);
        ``call_timeout`` overrides the rig's for this user's side of the call."""
        return connect(
            self.robot,
            home=home or self.user_home,
            config=self.config(call_timeout),
            timeout=timeout,
        )

    def write_user_config(self, name: str, *, lease_ms: int | None = None) -> Path:
        """A user's config file under ``base`` (for a child process), the rig's call timeout."""
        return write_config(self.base / name, lease_ms=lease_ms, timeout=self.timeout)

    def user_cli(
        self, *args: str, home: Path | None = None, timeout: float = 60
    ) -> subprocess.CompletedProcess[str]:
        """``telebot-user ARGS --home ... --config ... --connect ...`` run to its end."""
        return subprocess.run(
            [
                sys.executable,
                "-m",
                "telebot.apps.user_cli",
                *args,
                "--home",
                str(home or self.user_home),
                "--config",
                str(self.user_config),
                "--connect",
                self.endpoint,
            ],
            capture_output=True,
            text=True,
            timeout=timeout,
        )

    async def call_ended(self, call_id: str, timeout: float = 10.0) -> dict[str, Any]:
        """The daemon's ``ended`` event of call ``call_id`` (earlier events are skipped)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            event = await self.events.wait_event("ended", max(0.01, deadline - loop.time()))
            if event["id"] == call_id:
                return event

    def audit(self) -> list[dict[str, Any]]:
        """The robot's audit log, one record per line (``t``: the robot's monotonic clock)."""
        lines = (self.robot_home / "audit.jsonl").read_text(encoding="utf-8").splitlines()
        return [json.loads(line) for line in lines]


def start_telebot_sim(
    daemon: Daemon, *, ros2: Mapping[str, Any] | None = None, tables: str = ""
) -> tuple[Process, str]:
    """Make ``daemon`` drive ``telebot-sim``: a ROS 2 robot in its own process, its own
    zenoh router on a free port, the daemon's ``[sim]`` with the small map's places.

    Appends ``[robot] kind = "ros2"`` and ``[ros2]`` (with the keys of ``ros2``) and then
    ``tables`` (more TOML tables) to the daemon's config, starts the sim with that config and
    waits until it serves. Returns its process and router endpoint; start the daemon next.
    """
    router = f"tcp/127.0.0.1:{free_port()}"
    places = places_path_for(resolve_map("small", None))
    settings = {"router": [router], "connect_timeout": 30.0, "places_file": str(places)}
    settings.update(ros2 or {})
    lines = ["[robot]", 'kind = "ros2"', "[ros2]"]
    for key, value in settings.items():
        text = json.dumps(value) if isinstance(value, list) else _toml_value(value)
        lines.append(f"{key} = {text}")
    with daemon.robot_config.open("a") as config:
        config.write("\n".join(lines) + "\n" + tables)
    sim = Process(["telebot.apps.sim_cli", "--config", str(daemon.robot_config)])
    try:
        line = sim.next_line(timeout=60)
        assert "serving map" in line, f"{line} {sim.stderr()}"
    except BaseException:
        sim.stop()
        raise
    return sim, router


def robot_drive(server: RobotServer) -> RobotDrive:
    """The robot's ``drive`` service: its follow-me (``.follow``) and driving (``.drive``)."""
    drive = server.service("drive")
    assert isinstance(drive, RobotDrive), drive
    return drive


def services_without_media() -> ServiceRegistry[RobotServer]:
    """The robot's registered services but ``media``, for in-process robots in tests that
    are not about sound or the user's camera: its microphone pump, voice (an espeak-ng run
    per chat reply) and camera decoding would only load the machine (tests/test_media*.py
    and the daemons have it)."""
    services = service_registry.robot_services()
    services.unregister("media")
    return services


@contextlib.asynccontextmanager
async def robot_on_hub(
    base: Path,
    hub: MemoryHub,
    robot_services: ServiceRegistry[RobotServer] | None = None,
    *,
    timeout: float = REAL_TIMEOUT,
    sim: Mapping[str, Any] | None = None,
    services: ServiceSettings | None = None,
    video: VideoSettings | None = None,
    cipher: CipherChoice = "auto",
    transport: Transport | None = None,
    stale_video: float = GENEROUS_STALE_VIDEO,
) -> AsyncIterator[tuple[SimNavStack, SafetyDriver, RobotServer, RobotEndpoint]]:
    """A simulated robot (small map) with its safety supervisor, answering on ``hub`` as
    "robot"; paired homes for ``ROBOT`` and ``USER`` (a driver) are made under ``base``.

    ``timeout`` is the robot's call timeout and its deadman time; ``sim`` the simulator's
    settings (a robot of 1 m/s by default); ``cipher`` its ``[call] cipher``;
    ``transport``: an unopened transport to answer on instead of ``hub`` (a zenoh one);
    ``stale_video`` its stale-video lockout (:data:`GENEROUS_STALE_VIDEO` unless the test is
    about it).
    """
    create_paired_homes(base, ROBOT, USER, role=Role.DRIVER)
    robot_home = base / "robot"
    loop = asyncio.get_running_loop()
    settings = SimSettings.model_validate(
        sim
        if sim is not None
        else {
            "map": "small",
            "max_linear_speed": 1.0,
            "linear_accel": 3.0,
            "max_angular_speed": 3.0,
        }
    )
    nav = SimNavStack.from_settings(settings, now=loop.time())
    safety = SafetyDriver(
        nav, timeout=timeout, max_speed=settings.max_linear_speed, stale_video=stale_video
    )
    server = RobotServer(
        nav,
        services if services is not None else ServiceSettings(),
        safety=safety,
        services=robot_services if robot_services is not None else services_without_media(),
        config=ServiceConfig(video=video),
    )
    await server.prepare()
    with safety:
        async with (
            transport if transport is not None else MemoryTransport(hub, "robot") as transport,
            RobotEndpoint(
                transport,
                Identity.load(robot_home),
                ContactBook.load(robot_home),
                settings=CallSettings(timeout=timeout, cipher=cipher),
            ) as endpoint,
        ):
            server.attach(endpoint)
            runner = asyncio.create_task(server.run(), name="robot-loop")
            try:
                yield nav, safety, server, endpoint
            finally:
                runner.cancel()
                await asyncio.gather(runner, return_exceptions=True)
    await asyncio.sleep(0.01)  # the server's call watchers see the calls end


@contextlib.asynccontextmanager
async def user_on_hub(base: Path, hub: MemoryHub) -> AsyncIterator[UserEndpoint]:
    """The user of the homes :func:`robot_on_hub` made under ``base``, on ``hub`` as
    "user", with the rig's generous call timeout."""
    async with (
        MemoryTransport(hub, "user") as transport,
        UserEndpoint(
            transport,
            Identity.load(base / "user"),
            KnownRobots.load(base / "user"),
            settings=CallSettings(timeout=GENEROUS_TIMEOUT),
        ) as user,
    ):
        yield user
