"""Client-level followers (telebot.followers) in this process on the memory hub.

:class:`MapFollower` fetches the map once, again when telemetry announces another
``map_version`` (one transfer at a time, never again for a version already held or one
that failed), and again on the next call when a drop cuts a transfer.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from conftest import ROBOT, wait_until
from rig import robot_on_hub
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import AppConfig, ReconnectSettings, ServiceSettings
from telebot.followers import MapFollower
from telebot.robot.grid import OccupancyGrid
from telebot.robot.sim.stack import SimNavStack
from telebot.services.client import ConnectionEvent, RobotClient, connect

#: Telemetry (which carries map_version) 20 times a second: many repeats in little time.
FAST_TELEMETRY = ServiceSettings(telemetry_hz=20.0)


@dataclass
class Rig:
    hub: MemoryHub
    nav: SimNavStack
    client: RobotClient
    events: list[ConnectionEvent] = field(default_factory=list)

    async def telemetries(self, count: int) -> None:
        """Wait for ``count`` more telemetry messages (each announces the map version)."""
        for _ in range(count):
            await self.client.telemetry(timeout=10)


@contextlib.asynccontextmanager
async def rig(base: Path) -> AsyncIterator[Rig]:
    hub = MemoryHub(seed=5)
    async with (
        robot_on_hub(base, hub, services=FAST_TELEMETRY) as (nav, _safety, _server, _endpoint),
        MemoryTransport(hub, "user") as transport,
        connect(
            ROBOT,
            home=base / "user",
            config=AppConfig(reconnect=ReconnectSettings(base=0.05, cap=0.5)),
            transport=transport,
        ) as client,
    ):
        r = Rig(hub, nav, client)
        client.on_connection.append(r.events.append)
        yield r
        hub.heal("robot", "user")  # let the hang-up through


def with_wall(grid: OccupancyGrid) -> OccupancyGrid:
    """``grid`` with a new wall (SLAM found one): another map, so another version."""
    data = grid.data.copy()
    row, col = grid.cell_of(9.5, 4.0)
    data[row - 5 : row + 6, col - 5 : col + 6] = 100
    return OccupancyGrid(data, grid.resolution, grid.origin_x, grid.origin_y)


def unknown(grid: OccupancyGrid) -> OccupancyGrid:
    """A map with no known cell: the robot cannot encode it and refuses to send it."""
    data = np.full_like(grid.data, -1)
    return OccupancyGrid(data, grid.resolution, grid.origin_x, grid.origin_y)


async def test_the_map_is_fetched_again_when_its_version_changes_and_only_then(
    tmp_path: Path,
) -> None:
    async with rig(tmp_path) as r, MapFollower(r.client) as maps:
        arrived: list[int] = []
        maps.on_map.append(lambda download: arrived.append(download.version))
        await wait_until(lambda: maps.map is not None, timeout=15)
        assert maps.map is not None
        old = maps.map
        # The same version announced again and again: no transfer.
        await r.telemetries(10)
        assert maps.fetches == 1 and maps.refreshes == 0
        r.nav.set_map(with_wall(r.nav.map()))
        await wait_until(lambda: maps.map is not None and maps.map.version == 1, timeout=15)
        new = maps.map
        assert new is not None and new.sha256 != old.sha256
        assert new.grid.value_at(9.5, 4.0) == 100
        await r.telemetries(10)
        assert maps.fetches == 2 and maps.refreshes == 1 and arrived[-1] == 1


async def test_a_map_the_robot_cannot_send_is_reported_once_and_the_next_one_arrives(
    tmp_path: Path,
) -> None:
    async with rig(tmp_path) as r, MapFollower(r.client) as maps:
        errors: list[Exception] = []
        maps.on_error.append(errors.append)
        await wait_until(lambda: maps.map is not None, timeout=15)
        good = r.nav.map()
        r.nav.set_map(unknown(good))  # version 1: the robot refuses to send it
        await wait_until(lambda: bool(errors), timeout=15)
        assert "map" in str(errors[0]) and maps.error is errors[0]
        # Version 1 is announced again and again: not asked for again (no fetch storm).
        await r.telemetries(10)
        assert maps.fetches == 2 and len(errors) == 1
        assert maps.map is not None and maps.map.version == 0  # the last good map stays
        r.nav.set_map(with_wall(good))  # version 2: a good map again
        await wait_until(lambda: maps.map is not None and maps.map.version == 2, timeout=15)
        assert maps.fetches == 3 and maps.error is None


async def test_a_transfer_cut_by_a_drop_is_made_again_on_the_next_call(tmp_path: Path) -> None:
    async with rig(tmp_path) as r:
        await r.client.telemetry(timeout=10)  # the call is up
        # A slow link, so the drop comes while the map request or its answer travels.
        r.hub.set_link("robot", "user", latency=0.3)
        async with MapFollower(r.client) as maps:
            await wait_until(lambda: maps.fetches == 1)
            r.hub.cut("robot", "user")
            await wait_until(lambda: any(e.state == "reconnecting" for e in r.events), timeout=15)
            r.nav.set_map(with_wall(r.nav.map()))  # changed during the outage
            r.hub.set_link("robot", "user", latency=0.0)
            r.hub.heal("robot", "user")
            await wait_until(lambda: maps.map is not None, timeout=20)
            assert maps.map is not None and maps.map.version == 1 and maps.error is None
            assert maps.fetches == 2 and any(e.state == "reconnected" for e in r.events)


async def test_the_map_changed_during_an_outage_is_fetched_after_the_reconnection(
    tmp_path: Path,
) -> None:
    async with rig(tmp_path) as r, MapFollower(r.client) as maps:
        await wait_until(lambda: maps.map is not None, timeout=15)
        r.hub.cut("robot", "user")
        await wait_until(lambda: any(e.state == "reconnecting" for e in r.events), timeout=15)
        r.nav.set_map(with_wall(r.nav.map()))
        r.hub.heal("robot", "user")
        await wait_until(lambda: maps.map is not None and maps.map.version == 1, timeout=20)
        assert maps.refreshes == 1


async def test_a_failed_version_is_asked_for_again_on_a_new_call(tmp_path: Path) -> None:
    async with rig(tmp_path) as r, MapFollower(r.client) as maps:
        errors: list[Exception] = []
        maps.on_error.append(errors.append)
        await wait_until(lambda: maps.map is not None, timeout=15)
        r.nav.set_map(unknown(r.nav.map()))
        await wait_until(lambda: len(errors) == 1, timeout=15)
        r.hub.cut("robot", "user")
        await wait_until(lambda: any(e.state == "reconnecting" for e in r.events), timeout=15)
        r.hub.heal("robot", "user")
        # The new call may deliver what the old one could not: one more try, not a loop.
        await wait_until(lambda: len(errors) == 2, timeout=20)
        await r.telemetries(10)
        assert len(errors) == 2 and maps.fetches == 3


async def test_closing_the_follower_stops_it(tmp_path: Path) -> None:
    async with rig(tmp_path) as r:
        listeners = len(r.client.on_connection)
        maps = MapFollower(r.client)
        maps.start()
        await wait_until(lambda: maps.map is not None, timeout=15)
        await maps.aclose()
        assert len(r.client.on_connection) == listeners
        r.nav.set_map(with_wall(r.nav.map()))
        await r.telemetries(5)
        await asyncio.sleep(0)
        assert maps.fetches == 1
