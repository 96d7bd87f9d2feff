"""Shared fixtures: identities and homes, free ports, robot and user processes."""

from __future__ import annotations

import asyncio
import contextlib
import re
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from hypothesis import settings

# The rig (tests/rig.py, also used by bench/) holds the process helpers; re-exported here.
from rig import GENEROUS_TIMEOUT, ROBOT, SLACK, USER, Process, free_port, write_config
from telebot.channels.call import RobotEndpoint, UserEndpoint
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import CallSettings
from telebot.identity import ContactBook, Identity, KnownRobots, create_paired_homes

__all__ = [
    "ROBOT",
    "SLACK",
    "USER",
    "Homes",
    "Process",
    "free_port",
    "memory_endpoints",
    "wait_until",
    "write_config",
]

# No per-example time limit: on a shared 2-core machine one preempted example would fail
# a property test ("DeadlineExceeded") for no fault of the code. Speed is the benchmarks'.
settings.register_profile("telebot", deadline=None)
settings.load_profile("telebot")


async def wait_until(condition: Callable[[], bool], timeout: float = 5.0 + SLACK) -> None:
    """Wait until ``condition()`` holds, checking every 10 ms; AssertionError after ``timeout``.

    Waiting on the condition itself, never a fixed sleep: a loaded machine is slow.
    """
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met within {timeout} s")
        await asyncio.sleep(0.01)


#: Source text of a test module whose tests share a module-scoped rig: one defined there,
#: or test_web_ui's chromium imported (tests/test_web_phone.py, test_web_drive.py, ...).
SHARED_RIG = re.compile(r'scope="module"|^\s*(from test_web_ui import )?_chromium\b', re.MULTILINE)


def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """``--dist loadgroup`` (``make test``): a module that defines a module-scoped fixture
    (a daemon, a router, a browser) or imports one (test_web_ui's chromium, ``_chromium``)
    runs whole on one worker, which starts it once rather than once on each; every other
    test is scheduled on its own, filling the workers in between. xdist hands out the
    biggest groups first.

    (xdist's own loadgroup reads ``xdist_group`` marks into node ids, which pytest 9 no
    longer lets it change; the modules are found by their source instead.)
    """
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    root = config.rootpath
    shared: dict[str, bool] = {}

    class SharedModuleScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = nodeid.split("::", 1)[0]
            if path not in shared:
                with contextlib.suppress(OSError):
                    source = (root / path).read_text("utf-8")
                    shared[path] = SHARED_RIG.search(source) is not None
            return path if shared.get(path) else nodeid

    return SharedModuleScheduling(config, log)


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
    """The robot's and the user's endpoints on ``hub`` (nodes "robot" and "user"), started.

    ``settings`` default to the rig's generous call timeout: a test about drop timing says so.
    """
    if settings is None:
        settings = CallSettings(timeout=GENEROUS_TIMEOUT)
    async with (
        MemoryTransport(hub, "robot") as robot_transport,
        MemoryTransport(hub, "user") as user_transport,
        RobotEndpoint(robot_transport, homes.robot, homes.contacts, settings=settings) as robot,
        UserEndpoint(user_transport, homes.user, homes.known, settings=settings) as user,
    ):
        yield robot, user


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
