"""Shared fixtures: identities and homes, free ports, robot and user processes."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

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


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook reads the marks
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Keep a module's tests on one xdist worker when they share a module-scoped fixture.

    ``make test`` runs ``pytest -n 2 --dist loadgroup``: these tests are one group per module,
    so the daemon, router or browser the module shares is started once rather than once on
    each worker, and each group goes to a worker whole, the biggest groups first (xdist's
    order); every other test is scheduled on its own, filling the workers in between. The
    mark does nothing without ``--dist loadgroup``.
    """
    for item in items:
        info = getattr(item, "_fixtureinfo", None)
        if info is None:
            continue
        if any(defs and defs[-1].scope == "module" for defs in info.name2fixturedefs.values()):
            item.add_marker(pytest.mark.xdist_group(item.path.stem))


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
