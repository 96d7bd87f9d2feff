"""Map transfer over real calls on the memory transport: MapService on the robot, fetch_map
on the user, through authenticated calls on a (lossy) MemoryHub."""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from conftest import ROBOT, Homes, memory_endpoints
from telebot.channels.call import Call
from telebot.channels.transports.memory import MemoryHub
from telebot.config import CallSettings
from telebot.errors import CallEnded, ProtocolError
from telebot.robot.grid import OccupancyGrid
from telebot.robot.mapfile import load_map
from telebot.services.mapxfer.robot import MapService, map_channel
from telebot.services.mapxfer.user import fetch_map
from telebot.services.mapxfer.wire import ALREADY_RUNNING, MAX_CHUNK_DATA, EncodedMap, encode_map


def noisy_grid(seed: int = 1) -> OccupancyGrid:
    """A 200 × 300 map of random cells in an unknown border: its PNG hardly compresses."""
    rng = np.random.default_rng(seed)
    data = np.full((240, 340), -1, dtype=np.int8)
    data[15:215, 25:325] = rng.choice(np.array([-1, 0, 100], dtype=np.int8), size=(200, 300))
    data[15, 25] = data[214, 324] = 0  # known corners: the crop is exactly the noisy block
    return OccupancyGrid(data, 0.05, -6.0, -4.0)


@dataclass
class Robot:
    """A robot endpoint that serves ``encoded`` on every call (unless ``serve`` is False)."""

    encoded: EncodedMap | None
    chunk_size: int = 512
    services: list[MapService] = field(default_factory=list)
    calls: list[Call] = field(default_factory=list)

    def on_call(self, call: Call) -> None:
        self.calls.append(call)
        encoded = self.encoded
        if encoded is not None:
            service = MapService.attach(call, lambda: encoded, chunk_size=self.chunk_size)
            self.services.append(service)


@dataclass
class Link:
    hub: MemoryHub
    robot: Robot
    call: Call


@contextlib.asynccontextmanager
async def linked(
    homes: Homes,
    encoded: EncodedMap | None,
    *,
    chunk_size: int = 512,
    settings: CallSettings | None = None,
) -> AsyncIterator[Link]:
    """A robot and a user on one memory hub, in a call; the robot serves ``encoded``."""
    hub = MemoryHub(seed=21)
    robot = Robot(encoded, chunk_size)
    async with memory_endpoints(homes, hub, settings) as (robot_endpoint, user):
        robot_endpoint.on_call = robot.on_call
        call = await user.call(ROBOT)
        try:
            yield Link(hub, robot, call)
        finally:
            for service in robot.services:
                service.close()
            await call.hangup()


NOISY = encode_map(noisy_grid(), name="lab")


@pytest.fixture
async def link(homes: Homes) -> AsyncIterator[Link]:
    async with linked(homes, NOISY) as value:
        yield value


@pytest.fixture
async def silent(homes: Homes) -> AsyncIterator[Link]:
    """A robot that does not serve maps."""
    async with linked(homes, None) as value:
        yield value


async def test_map_transfer_completes_with_the_same_bytes_at_30_percent_loss(link: Link) -> None:
    link.hub.set_link("robot", "user", loss=0.3)  # both directions
    # One chunk per loop turn, so one chunk per frame: the loss falls on single chunks
    # rather than on whole bursts (which travel in one BUNDLE frame).
    for service in link.robot.services:
        service.burst = 1
    seen: list[tuple[int, int]] = []
    download = await fetch_map(
        map_channel(link.call), timeout=20.0, progress=lambda r, t: seen.append((r, t))
    )
    assert download.png == NOISY.png and download.sha256 == NOISY.sha256
    grid = noisy_grid()
    assert np.array_equal(download.grid.data, grid.data[15:215, 25:325])
    assert (download.grid.origin_x, download.grid.origin_y) == (-6.0 + 25 * 0.05, -4.0 + 15 * 0.05)
    assert download.name == "lab" and (download.width, download.height) == (300, 200)
    # The link really lost chunks, and they were asked for again.
    assert download.resent > 0
    assert link.robot.services[0].sender.chunks_resent > 0
    assert link.hub.link_stats("robot", "user").lost > 0
    # Progress: in bytes, never backwards, ending at the whole map.
    assert len(seen) >= 2 and seen[-1] == (NOISY.size, NOISY.size)
    assert all(t == NOISY.size for _, t in seen)
    assert [r for r, _ in seen] == sorted(r for r, _ in seen)


async def test_loss_free_transfer_ends_the_robots_transfer(link: Link) -> None:
    download = await fetch_map(map_channel(link.call), timeout=5.0)
    assert download.png == NOISY.png and download.resent == 0 and download.rejected == 0
    service = link.robot.services[0]
    await asyncio.sleep(0.01)  # let the "done" messages arrive
    assert not service.sender.active and service.sender.completed == 1
    assert service.sender.chunks_sent == -(-NOISY.size // 512)
    # a second fetch in the same call works too
    again = await fetch_map(map_channel(link.call), timeout=5.0)
    assert again.png == NOISY.png


async def test_a_second_request_while_one_runs_is_refused_with_the_reason(link: Link) -> None:
    channel = map_channel(link.call)
    channel.send(json.dumps({"type": "get", "xfer": 1}))  # a transfer nobody finishes
    offer = await asyncio.wait_for(channel.receive(), 5.0)
    assert isinstance(offer.payload, str) and json.loads(offer.payload)["type"] == "offer"
    with pytest.raises(ProtocolError, match=ALREADY_RUNNING):
        await fetch_map(channel, timeout=5.0)
    assert link.robot.services[0].sender.refused == 1
    channel.send(json.dumps({"type": "cancel", "xfer": 1}))
    download = await fetch_map(channel, timeout=5.0)
    assert download.png == NOISY.png


async def test_garbage_on_the_map_channel_is_counted_and_breaks_nothing(link: Link) -> None:
    channel = map_channel(link.call)
    garbage: list[str | bytes] = [
        b"\x00" * 100,
        b"",
        "{",
        "[]",
        '{"type": "get", "xfer": "one"}',
        '{"type": "resend", "xfer": 5, "missing": [1]}',  # no such transfer
        "x" * 30_000,
    ]
    for payload in garbage:
        channel.send(payload)
    # and garbage from the robot's side, queued on the user's channel before the fetch
    robot_channel = map_channel(link.robot.calls[0])
    for payload in (b"\x01\x00", b"\x01" + b"\xff" * 20, "nonsense", '{"type":"offer"}'):
        robot_channel.send(payload)
    await asyncio.sleep(0.01)
    service = link.robot.services[0]
    assert service.rejected == len(garbage) and service.errors == 0
    download = await fetch_map(channel, timeout=5.0)
    assert download.png == NOISY.png
    # the resend for transfer 5 got an error reply, queued too: one more dropped datagram
    assert download.rejected == 5
    assert link.call.active


async def test_timeout_when_the_robot_does_not_serve_maps(silent: Link) -> None:
    channel = map_channel(silent.call)
    with pytest.raises(TimeoutError, match=r"did not answer \d+ map requests"):
        await fetch_map(channel, timeout=0.6)
    assert channel._callback is None  # the channel is handed back


async def test_a_timed_out_fetch_tells_the_robot_to_forget_it(homes: Homes) -> None:
    patient = CallSettings(timeout=5.0)  # the call outlives the silence below
    async with linked(homes, NOISY, settings=patient) as link:
        link.hub.link("robot", "user").loss = 1.0  # requests arrive, nothing comes back
        with pytest.raises(TimeoutError, match=r"not complete within 0\.5 s"):
            await fetch_map(map_channel(link.call), timeout=0.5)
        service = link.robot.services[0]
        await asyncio.sleep(0.01)
        assert service.sender.refused == 0 and service.sender.chunks_sent > 0
        assert not service.sender.active  # the cancel arrived: it is free for the next one


async def test_the_call_ending_ends_the_fetch(silent: Link) -> None:
    fetch = asyncio.create_task(fetch_map(map_channel(silent.call), timeout=5.0))
    await asyncio.sleep(0.05)
    silent.call.hangup_now("bye")
    with pytest.raises(CallEnded):
        await fetch


async def test_the_default_4000_map_round_trips_to_map_server_files(
    homes: Homes, tmp_path: Path
) -> None:
    from telebot.robot.sim.building import generate_building

    grid, _ = generate_building()
    async with linked(homes, encode_map(grid, "building"), chunk_size=MAX_CHUNK_DATA) as link:
        download = await fetch_map(map_channel(link.call), timeout=10.0)
    yaml_path = download.save(tmp_path / "map.png")
    assert yaml_path == tmp_path / "map.yaml"
    loaded = load_map(yaml_path)
    bounds = grid.known_bounds()
    assert bounds is not None
    expected = grid.crop(*bounds)
    assert np.array_equal(loaded.data, expected.data)
    assert (loaded.origin_x, loaded.origin_y) == (expected.origin_x, expected.origin_y)
    # the crop is what the paper promises: a small part of the 4000 × 4000 grid
    assert loaded.width * loaded.height < 0.2 * grid.width * grid.height
