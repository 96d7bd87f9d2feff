"""Calls between real processes over zenoh on 127.0.0.1: freezes, kills and SIGTERM.

The drop must come from telebot's own heartbeats, not from zenoh's lease (10 s by
default): one test gives the frozen peer a one-hour lease, so only heartbeats can tell.
"""

from __future__ import annotations

import asyncio
import signal
import time
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from conftest import ROBOT, USER, Homes, Process, wait_until, write_config
from rig import REAL_TIMEOUT, SLACK
from telebot.apps.echo import echo_call
from telebot.channels.call import Call, RobotEndpoint, UserEndpoint
from telebot.channels.transports.zenoh import ZenohTransport
from telebot.config import CallSettings, ZenohSettings
from telebot.testing.net import free_port

pytestmark = pytest.mark.zenoh

#: The product's call timeout, which these tests are about: given explicitly to every end.
TIMEOUT = REAL_TIMEOUT
#: Detection must be close to the call timeout and far below zenoh's 10 s lease: within
#: this much more (a few heartbeat periods, and SLACK for a loaded 2-core CI machine).
MARGIN = 0.5 + SLACK


@pytest.fixture
async def robot_here(homes: Homes) -> AsyncIterator[tuple[RobotEndpoint, asyncio.Queue[Call], int]]:
    """A robot endpoint in this process, listening on a free port."""
    port = free_port()
    transport = ZenohTransport(
        ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    )
    await transport.open()
    robot = RobotEndpoint(
        transport, homes.robot, homes.contacts, settings=CallSettings(timeout=TIMEOUT)
    )
    await robot.start()
    calls: asyncio.Queue[Call] = asyncio.Queue()

    def on_call(call: Call) -> None:
        echo_call(call, robot, lambda event: None)
        calls.put_nowait(call)

    robot.on_call = on_call
    try:
        yield robot, calls, port
    finally:
        await robot.close()
        await transport.close()


def start_user_ping(
    homes: Homes, port: int, config: Path, processes: list[Process], count: int = 100_000
) -> Process:
    """``telebot-user ping`` holding a call open for ``count`` pings (a long time by default)."""
    process = Process(
        [
            "telebot.apps.user_cli",
            "ping",
            ROBOT,
            "--home",
            str(homes.user_home),
            "--config",
            str(config),
            "--connect",
            f"tcp/127.0.0.1:{port}",
            "--count",
            str(count),
            "--interval",
            "0.05",
        ]
    )
    processes.append(process)
    return process


async def timed_end(call: Call, limit: float) -> tuple[str, float]:
    started = time.monotonic()
    end = await asyncio.wait_for(call.wait_ended(), limit)
    return end.kind, time.monotonic() - started


@pytest.mark.parametrize("lease_ms", [None, 3_600_000], ids=["default-lease", "one-hour-lease"])
async def test_frozen_user_is_dropped_by_the_robot(
    homes: Homes,
    robot_here: tuple[RobotEndpoint, asyncio.Queue[Call], int],
    tmp_path: Path,
    processes: list[Process],
    lease_ms: int | None,
) -> None:
    _, calls, port = robot_here
    user = start_user_ping(
        homes,
        port,
        write_config(tmp_path / "user.toml", lease_ms=lease_ms, timeout=TIMEOUT),
        processes,
    )
    call = await asyncio.wait_for(calls.get(), 15)
    assert call.peer == USER
    # The call is live: pings flow (the channel opens with the first one).
    await wait_until(lambda: "ping" in call.channels and call.channels["ping"].stats.received > 0)
    user.signal(signal.SIGSTOP)
    kind, took = await timed_end(call, 10)
    assert kind == "dropped"
    assert took < TIMEOUT + MARGIN
    assert call.end is not None and "nothing from alice" in call.end.detail


async def test_killed_user_is_dropped_by_the_robot(
    homes: Homes,
    robot_here: tuple[RobotEndpoint, asyncio.Queue[Call], int],
    tmp_path: Path,
    processes: list[Process],
) -> None:
    robot, calls, port = robot_here
    user = start_user_ping(
        homes, port, write_config(tmp_path / "user.toml", timeout=TIMEOUT), processes
    )
    call = await asyncio.wait_for(calls.get(), 15)
    user.signal(signal.SIGKILL)
    kind, took = await timed_end(call, 10)
    assert kind == "dropped"
    assert took < TIMEOUT + MARGIN
    # the same user can call again at once, and gets a fresh call
    again = start_user_ping(
        homes, port, write_config(tmp_path / "user2.toml", timeout=TIMEOUT), processes
    )
    second = await asyncio.wait_for(calls.get(), 15)
    assert second.id != call.id
    assert [c.id for c in robot.calls] == [second.id]
    again.signal(signal.SIGKILL)


async def test_user_sigterm_hangs_up_and_exits_within_2s(
    homes: Homes,
    robot_here: tuple[RobotEndpoint, asyncio.Queue[Call], int],
    tmp_path: Path,
    processes: list[Process],
) -> None:
    _, calls, port = robot_here
    user = start_user_ping(
        homes, port, write_config(tmp_path / "user.toml", timeout=TIMEOUT), processes
    )
    call = await asyncio.wait_for(calls.get(), 15)
    answered = await asyncio.to_thread(user.next_line, 10)
    assert answered.startswith("call ") and "answered" in answered
    started = time.monotonic()
    user.signal(signal.SIGTERM)
    returncode = await asyncio.to_thread(user.popen.wait, 10)
    assert time.monotonic() - started < 2.0 + SLACK
    assert returncode == 128 + signal.SIGTERM
    end = await asyncio.wait_for(call.wait_ended(), 5)
    assert end.kind == "hung_up" and end.by_peer


async def test_a_user_that_hangs_up_and_exits_at_once_is_seen_hanging_up(
    homes: Homes,
    robot_here: tuple[RobotEndpoint, asyncio.Queue[Call], int],
    tmp_path: Path,
    processes: list[Process],
) -> None:
    # ping hangs up when done and closes its endpoint straight after: the withdrawal of
    # its presence must not overtake the hang-up.
    _, calls, port = robot_here
    user = start_user_ping(
        homes, port, write_config(tmp_path / "user.toml", timeout=TIMEOUT), processes, count=3
    )
    call = await asyncio.wait_for(calls.get(), 15)
    assert await asyncio.to_thread(user.popen.wait, 10) == 0
    end = await asyncio.wait_for(call.wait_ended(), 5)
    assert (end.kind, end.by_peer, end.detail) == ("hung_up", True, "ping done")


@pytest.fixture
async def robot_process(
    homes: Homes, tmp_path: Path, processes: list[Process]
) -> tuple[Process, int]:
    port = free_port()
    process = Process(
        [
            "telebot.apps.robot_cli",
            "echo",
            "--home",
            str(homes.robot_home),
            "--config",
            str(write_config(tmp_path / "robot.toml", lease_ms=3_600_000, timeout=TIMEOUT)),
            "--listen",
            f"tcp/127.0.0.1:{port}",
            "--events",
        ]
    )
    processes.append(process)
    await process.wait_event("ready")
    return process, port


@pytest.fixture
async def user_here(
    homes: Homes, robot_process: tuple[Process, int]
) -> AsyncIterator[UserEndpoint]:
    _, port = robot_process
    transport = ZenohTransport(
        ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    )
    await transport.open()
    user = UserEndpoint(transport, homes.user, homes.known, settings=CallSettings(timeout=TIMEOUT))
    await user.start()
    try:
        yield user
    finally:
        await user.close()
        await transport.close()


async def test_frozen_robot_with_one_hour_lease_is_dropped_by_the_user(
    robot_process: tuple[Process, int], user_here: UserEndpoint
) -> None:
    process, _ = robot_process
    call = await user_here.call(ROBOT)
    process.signal(signal.SIGSTOP)
    kind, took = await timed_end(call, 10)
    assert kind == "dropped"
    assert took < TIMEOUT + MARGIN
    process.signal(signal.SIGCONT)
    event = await process.wait_event("ended", timeout=10)  # the robot notices too, once thawed
    assert event["kind"] == "dropped"


async def test_robot_sigterm_hangs_up_and_exits_within_2s(
    robot_process: tuple[Process, int], user_here: UserEndpoint
) -> None:
    process, _ = robot_process
    call = await user_here.call(ROBOT)
    await process.wait_event("call")
    started = time.monotonic()
    process.signal(signal.SIGTERM)
    returncode = await asyncio.to_thread(process.popen.wait, 10)
    assert time.monotonic() - started < 2.0 + SLACK
    assert returncode == 0
    end = await asyncio.wait_for(call.wait_ended(), 5)
    assert end.kind == "hung_up" and end.by_peer and end.detail == "shutting down"
