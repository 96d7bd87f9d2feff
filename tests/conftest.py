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
from rig import GENEROUS_TIMEOUT, ROBOT, SLACK, USER, Process, write_config
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
#: Source text of a test module whose tests start processes, daemons or browsers: each of
#: its tests likely takes seconds where a unit test takes milliseconds.
HEAVY = re.compile(r"\b(Process|Daemon|subprocess|chromium|browser_page|phone_page)\b")
#: How many unit tests one test of such a module is worth, for the order work is handed out.
HEAVY_WEIGHT = 20


def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """``--dist loadgroup`` (``make test``): a module that defines a module-scoped fixture
    (a daemon, a router, a browser) or imports one (test_web_ui's chromium, ``_chromium``)
    runs whole on one worker, which starts it once rather than once on each; every other
    test is scheduled on its own, filling the workers in between. Work is handed out
    biggest first (its tests counted, those of modules that start processes or browsers
    as :data:`HEAVY_WEIGHT` each), so that the run ends with quick unit tests that even
    out the two workers rather than with one worker's long browser test.

    (xdist's own loadgroup reads ``xdist_group`` marks into node ids, which pytest 9 no
    longer lets it change; the modules are found by their source instead.)
    """
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    root = config.rootpath
    shared: dict[str, bool] = {}
    heavy: dict[str, bool] = {}

    def read(path: str) -> None:
        if path not in shared:
            source = ""
            with contextlib.suppress(OSError):
                source = (root / path).read_text("utf-8")
            shared[path] = SHARED_RIG.search(source) is not None
            heavy[path] = HEAVY.search(source) is not None

    def weight(unit: tuple[str, dict[str, bool]]) -> int:
        path = unit[0].split("::", 1)[0]
        read(path)
        return len(unit[1]) * (HEAVY_WEIGHT if heavy[path] else 1)

    class SharedModuleScheduling(LoadScopeScheduling):
        ordered = False

        def _split_scope(self, nodeid: str) -> str:
            path = nodeid.split("::", 1)[0]
            read(path)
            return path if shared[path] else nodeid

        def _assign_work_unit(self, node: Any) -> None:
            if not self.ordered:  # the first time: the queue is built, none handed out yet
                self.ordered = True
                units = sorted(self.workqueue.items(), key=weight, reverse=True)
                self.workqueue.clear()
                self.workqueue.update(units)
            super()._assign_work_unit(node)

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
