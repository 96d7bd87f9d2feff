"""Shared fixtures: identities and homes, free ports, robot and user processes."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from hypothesis import settings

from telebot.channels.call import RobotEndpoint, UserEndpoint
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import CallSettings
from telebot.identity import ContactBook, Identity, KnownRobots, create_paired_homes

# No per-example time limit: on a shared 2-core machine one preempted example would fail
# a property test ("DeadlineExceeded") for no fault of the code. Speed is the benchmarks'.
settings.register_profile("telebot", deadline=None)
settings.load_profile("telebot")

ROBOT = "guiabot"
USER = "alice"


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


async def wait_until(condition: Callable[[], bool], timeout: float = 5.0) -> None:
    """Wait until ``condition()`` holds, checking every 10 ms; AssertionError after ``timeout``.

    Waiting on the condition itself, never a fixed sleep: a loaded machine is slow.
    """
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met within {timeout} s")
        await asyncio.sleep(0.01)


@dataclass
class Homes:
    """A robot home and a user home that know each other."""

    robot_home: Path
    user_home: Path
    robot: Identity
    user: Identity

    @property
    def contacts(self) -> ContactBook:
        return ContactBook.load(self.robot_home)

    @property
    def known(self) -> KnownRobots:
        return KnownRobots.load(self.user_home)


@pytest.fixture
def homes(tmp_path: Path) -> Homes:
    robot, user = create_paired_homes(tmp_path, ROBOT, USER)
    robot_home, user_home = tmp_path / "robot", tmp_path / "user"
    return Homes(robot_home, user_home, robot, user)


@contextlib.asynccontextmanager
async def memory_endpoints(
    homes: Homes, hub: MemoryHub, settings: CallSettings | None = None
) -> AsyncIterator[tuple[RobotEndpoint, UserEndpoint]]:
    """The robot's and the user's endpoints on ``hub`` (nodes "robot" and "user"), started."""
    async with (
        MemoryTransport(hub, "robot") as robot_transport,
        MemoryTransport(hub, "user") as user_transport,
        RobotEndpoint(robot_transport, homes.robot, homes.contacts, settings=settings) as robot,
        UserEndpoint(user_transport, homes.user, homes.known, settings=settings) as user,
    ):
        yield robot, user


def write_config(path: Path, *, lease_ms: int | None = None, timeout: float | None = None) -> Path:
    """A telebot TOML config for loopback tests: no multicast scouting."""
    lines = ["[transport.zenoh]", "multicast_scouting = false"]
    if lease_ms is not None:
        lines += ["[transport.zenoh.options]", f'"transport/link/tx/lease" = {lease_ms}']
    if timeout is not None:
        lines += ["[call]", f"timeout = {timeout}"]
    path.write_text("\n".join(lines) + "\n")
    return path


class Process:
    """A telebot command in a child process; its stdout lines are read by a thread."""

    def __init__(self, args: list[str], env: dict[str, str] | None = None) -> None:
        self.popen = subprocess.Popen(
            [sys.executable, "-m", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, **(env or {})},
        )
        self.lines: queue.Queue[str] = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self.lines.put(line.rstrip("\n"))

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

    def stderr(self) -> str:
        if self.popen.poll() is None:
            return "(still running)"
        assert self.popen.stderr is not None
        return self.popen.stderr.read()

    def signal(self, sig: signal.Signals) -> None:
        self.popen.send_signal(sig)

    def stop(self) -> None:
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGCONT)
            self.popen.kill()
        self.popen.wait(timeout=10)
        self._reader.join(timeout=5)
        for pipe in (self.popen.stdout, self.popen.stderr):
            if pipe is not None:
                pipe.close()


@pytest.fixture
def processes() -> Iterator[list[Process]]:
    """Child processes started by a test; all killed when it ends."""
    started: list[Process] = []
    yield started
    for process in started:
        process.stop()


@pytest.fixture(autouse=True)
async def _no_leaked_tasks() -> AsyncIterator[None]:
    """Fail a test that leaves asyncio tasks running behind it."""
    before = asyncio.all_tasks()
    yield
    await asyncio.sleep(0)
    leaked = [
        t for t in asyncio.all_tasks() - before if t is not asyncio.current_task() and not t.done()
    ]
    assert not leaked, f"test leaked tasks: {leaked}"
