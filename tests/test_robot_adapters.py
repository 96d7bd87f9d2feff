"""The robot-adapter seam: optional stepping, and a map that changes (SLAM) followed to the user.

The robot runs in this process (SimNavStack + RobotServer on a memory hub); a user calls it
with :class:`RobotClient`. :meth:`SimNavStack.set_map` stands in for a SLAM update.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from dataclasses import dataclass
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from conftest import ROBOT, Homes, memory_endpoints, wait_until
from telebot.channels.call import UserEndpoint
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import RobotConfig, ServiceSettings, SimSettings
from telebot.robot.grid import OccupancyGrid
from telebot.robot.nav import GoalStatus, SteppedNavStack
from telebot.robot.sim.stack import SimNavStack
from telebot.services.client import RobotClient
from telebot.services.robot import RobotServer

OCCUPIED = 100


def with_wall(grid: OccupancyGrid, x: float, y: float, half: float = 0.3) -> OccupancyGrid:
    """``grid`` with a square block of wall (side 2·``half`` m) centred on ``(x, y)``."""
    data = grid.data.copy()
    row0, col0 = grid.cell_of(x - half, y - half)
    row1, col1 = grid.cell_of(x + half, y + half)
    data[row0 : row1 + 1, col0 : col1 + 1] = OCCUPIED
    return OccupancyGrid(data, grid.resolution, grid.origin_x, grid.origin_y)


def small_sim(now: float = 0.0) -> SimNavStack:
    return SimNavStack.from_settings(SimSettings(map="small"), now=now)


# --------------------------------------------------------------------------- the simulator


def test_set_map_bumps_the_version_and_the_robot_plans_on_the_new_map() -> None:
    nav = small_sim()
    assert nav.map_version() == 0
    first = nav.navigate_to_place("room-b")
    assert first.status is GoalStatus.ACTIVE  # reachable on the original map
    nav.stop()
    nav.set_map(with_wall(nav.map(), 9.5, 4.0))  # SLAM found a wall where room-b is
    assert nav.map_version() == 1
    assert nav.map().value_at(9.5, 4.0) == OCCUPIED
    nav.set_map(with_wall(nav.map(), 9.5, 4.0))  # the same map again (SLAM republishes)
    assert nav.map_version() == 1
    goal = nav.navigate_to_place("room-b")
    assert goal.status is GoalStatus.FAILED and "no path to room-b" in goal.reason


# --------------------------------------------------------------------------- in a call


class Unstepped:
    """A robot that runs by itself: every NavStack call but no ``step`` (it is never stepped)."""

    def __init__(self, inner: SimNavStack) -> None:
        self._inner = inner

    def __getattr__(self, name: str) -> Any:
        if name == "step":
            raise AttributeError(name)
        return getattr(self._inner, name)


@dataclass
class Rig:
    nav: SimNavStack
    server: RobotServer
    client: RobotClient
    hub: MemoryHub


@contextlib.asynccontextmanager
async def robot_in_a_call(
    homes: Homes, nav: Any, *, telemetry_hz: float = 20.0
) -> AsyncIterator[Rig]:
    """``nav`` served by a RobotServer (telemetry at 20 Hz) to a user on a memory hub."""
    hub = MemoryHub(seed=3)
    server = RobotServer(nav, ServiceSettings(telemetry_hz=telemetry_hz), map_name="small")
    await server.prepare()
    async with memory_endpoints(homes, hub) as (robot_endpoint, user_endpoint):
        server.attach(robot_endpoint)
        runner = asyncio.create_task(server.run(), name="robot-loop")
        try:
            call = await user_endpoint.call(ROBOT)
            inner = nav._inner if isinstance(nav, Unstepped) else nav
            yield Rig(inner, server, RobotClient(call), hub)
            await call.hangup()
        finally:
            runner.cancel()
            await asyncio.gather(runner, return_exceptions=True)


async def test_a_robot_without_step_is_served_and_never_stepped(
    homes: Homes, caplog: pytest.LogCaptureFixture
) -> None:
    nav = Unstepped(small_sim(now=0.0))
    assert not isinstance(nav, SteppedNavStack)
    async with robot_in_a_call(homes, nav) as rig:
        telemetry = await rig.client.telemetry(timeout=5)
        assert telemetry.state == "idle" and telemetry.map_version == 0
        await rig.client.telemetry(timeout=5)  # several cycles of the robot's loop later
        assert rig.nav.now == 0.0  # a stepped SimNavStack would be at the loop's time
    # Not a step that failed (and stopped the robot) either: no step was tried.
    assert [r.getMessage() for r in caplog.records if r.levelname == "ERROR"] == []


async def test_the_map_follows_a_slam_update_during_a_call(homes: Homes) -> None:
    loop = asyncio.get_running_loop()
    async with robot_in_a_call(homes, small_sim(now=loop.time())) as rig:
        client, nav = rig.client, rig.nav
        before = await client.get_map(timeout=10)
        assert before.version == 0 and (await client.telemetry(timeout=5)).map_version == 0
        assert before.grid.value_at(9.5, 4.0) == 0  # free

        nav.set_map(with_wall(nav.map(), 9.5, 4.0))
        # The robot re-encodes the new map by itself, off the loop...
        await wait_until(
            lambda: rig.server._encoded is not None and rig.server._encoded.version == 1
        )
        # ...and tells the user, who fetches it again.
        await wait_until_async(lambda: client.telemetry(timeout=5), lambda t: t.map_version == 1)
        after = await client.get_map(timeout=10)
        assert after.version == 1 and after.sha256 != before.sha256
        assert after.grid.value_at(9.5, 4.0) == OCCUPIED


async def test_a_new_map_is_announced_at_once_not_at_the_next_telemetry_tick(
    homes: Homes,
) -> None:
    loop = asyncio.get_running_loop()
    # Telemetry every 20 s: only the announcement of the new map can bring version 1 sooner.
    async with robot_in_a_call(homes, small_sim(now=loop.time()), telemetry_hz=0.05) as rig:
        first = await rig.client.telemetry(timeout=5)  # sent when the call opened
        assert first.map_version == 0
        with contextlib.suppress(TimeoutError):  # and any other sent as the call opened
            while True:
                await rig.client.telemetry(timeout=1.0)
        rig.nav.set_map(with_wall(rig.nav.map(), 9.5, 4.0))
        announced = await rig.client.telemetry(timeout=10)
        assert announced.map_version == 1


async def test_a_transfer_under_way_when_the_map_changes_ends_with_what_it_offered(
    homes: Homes,
) -> None:
    loop = asyncio.get_running_loop()
    async with robot_in_a_call(homes, small_sim(now=loop.time())) as rig:
        client, nav = rig.client, rig.nav
        rig.hub.set_link("robot", "user", latency=0.3)  # the offer and chunks take a while
        fetch = asyncio.create_task(client.get_map(timeout=10))
        (services,) = rig.server.services.values()
        await wait_until(lambda: services.map.sender.active)  # the robot has offered
        nav.set_map(with_wall(nav.map(), 9.5, 4.0))
        old = await fetch
        assert old.version == 0 and old.grid.value_at(9.5, 4.0) == 0  # whole and hash-checked
        rig.hub.set_link("robot", "user", latency=0.0)
        await wait_until(lambda: not services.map.sender.active)  # the user's "done" arrived
        new = await client.get_map(timeout=10)
        assert new.version == 1 and new.grid.value_at(9.5, 4.0) == OCCUPIED


async def wait_until_async(fetch: Any, condition: Any, attempts: int = 100) -> None:
    """Await ``fetch()`` until ``condition`` holds for its result."""
    for _ in range(attempts):
        if condition(await fetch()):
            return
    raise AssertionError("condition not met")


def test_with_wall_marks_the_block() -> None:
    # Guard the helper the tests above rely on.
    grid = small_sim().map()
    walled = with_wall(grid, 9.5, 4.0, half=0.1)
    changed = np.argwhere(walled.data != grid.data)
    assert changed.size and walled.value_at(9.5, 4.0) == OCCUPIED
    assert walled.value_at(9.5, 3.5) == grid.value_at(9.5, 3.5)


@pytest.mark.parametrize("version", [0, 2**53 + 5])
async def test_map_versions_travel_json_safe(homes: Homes, version: int) -> None:
    # Started at the loop's time, as the server steps it: a sim left at 0 spent seconds
    # catching up the machine's uptime in its first step.
    nav = small_sim(now=asyncio.get_running_loop().time())
    nav.map_version = lambda: version  # type: ignore[method-assign]
    async with robot_in_a_call(homes, nav) as rig:
        telemetry = await rig.client.telemetry(timeout=5)
        download = await rig.client.get_map(timeout=10)
        assert telemetry.map_version == download.version == version % 2**53


# --------------------------------------------------------------------------- the daemon


class TinCan(Unstepped):
    """A plug-in robot adapter that runs by itself (no ``step``), found by entry point; it
    declares its own control rate and map name (the simulator inside has others)."""

    control_hz = 12.5
    map_name = "tin-can"

    @classmethod
    def from_config(cls, config: Any, *, base_dir: Any = None, now: float = 0.0) -> TinCan:
        return cls(SimNavStack.from_settings(SimSettings(map="small"), now=now))


async def test_the_daemon_runs_the_robot_its_config_names(
    homes: Homes, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import telebot.registry
    import telebot.robot
    from telebot.apps.robot_daemon import serve_robot

    entry = EntryPoint(
        name="tin-can", value=f"{__name__}:TinCan", group=telebot.robot.ENTRY_POINT_GROUP
    )
    monkeypatch.setattr(
        telebot.registry,
        "entry_points",
        lambda group: [entry] if group == telebot.robot.ENTRY_POINT_GROUP else [],
    )
    import telebot.apps.robot_daemon

    servers: list[RobotServer] = []

    class Recorded(RobotServer):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            servers.append(self)

    monkeypatch.setattr(telebot.apps.robot_daemon, "RobotServer", Recorded)
    hub_name = f"daemon-{id(tmp_path)}"
    config = RobotConfig.model_validate(
        {"robot": {"kind": "tin-can"}, "transport": {"kind": "memory", "memory": {"hub": hub_name}}}
    )
    events: list[dict[str, Any]] = []
    stop = asyncio.Event()
    daemon = asyncio.create_task(
        serve_robot(
            config, homes.robot, homes.contacts, home=tmp_path, emit=events.append, stop=stop
        )
    )
    try:
        await wait_until(lambda: any(e["event"] == "ready" for e in events), timeout=20)
        (ready,) = [e for e in events if e["event"] == "ready"]
        assert ready["kind"] == "tin-can" and ready["map"] == "tin-can"
        # The loop runs at the adapter's rate, not at [sim] control_hz (20 Hz).
        (server,) = servers
        assert server.control_hz == 12.5 != config.sim.control_hz
        async with (
            MemoryTransport(MemoryHub.named(hub_name), "user") as transport,
            UserEndpoint(transport, homes.user, homes.known) as user,
        ):
            client = RobotClient(await user.call(ROBOT))
            telemetry = await client.telemetry(timeout=5)
            # Served (not stepped: TinCan has no step), and disarmed at start.
            assert telemetry.state == "idle" and not telemetry.armed
            assert (await client.get_map(timeout=10)).name == "tin-can"
            await client.call.hangup()
    finally:
        stop.set()
        await daemon
