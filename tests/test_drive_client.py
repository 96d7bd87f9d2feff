"""Driving by hand end to end, in process: ``RobotClient.drive`` against the simulated robot
daemon (``rig.robot_on_hub``: the real RobotServer, supervisor and drive service) over a real
call on the memory transport. The robot moves forward while the client drives and stops
after the release; a client that stops calling ``drive`` stops the robot by itself.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from conftest import ROBOT, wait_until
from rig import FAST_SIM, GENEROUS_TIMEOUT, robot_on_hub, user_on_hub
from telebot.channels.transports.memory import MemoryHub
from telebot.reasons import Reason
from telebot.robot.nav import Velocity
from telebot.robot.sim.stack import SimNavStack
from telebot.services.client import (
    DRIVE_EVERY,
    QUICK_REPEATS,
    RELEASE_REPEATS,
    STOP_REPEAT,
    ClientDrive,
    RobotClient,
)
from telebot.services.safety.robot import SafetyDriver


@contextlib.asynccontextmanager
async def driving(tmp_path: Path) -> AsyncIterator[tuple[SimNavStack, SafetyDriver, RobotClient]]:
    """An armed simulated robot and a started client."""
    hub = MemoryHub(seed=3)
    async with (
        robot_on_hub(tmp_path, hub, timeout=GENEROUS_TIMEOUT, sim=FAST_SIM) as (nav, safety, _, _),
        user_on_hub(tmp_path, hub) as user,
    ):
        client = RobotClient(await user.call(ROBOT))
        client.start()
        try:
            assert (await client.arm()).ok
            # Not a test of a call just set up (its round trip unmeasured: see test_drive.py).
            await wait_until(lambda: safety.state().cap > 0)
            yield nav, safety, client
        finally:
            await client.aclose()


def sent_commands(client: RobotClient) -> list[dict[str, object]]:
    """Record every drive command the client sends from now on."""
    drive = client.services.get("drive")
    assert isinstance(drive, ClientDrive)
    sent: list[dict[str, object]] = []
    send = drive.channel.send

    def recording(payload: str | bytes) -> None:
        assert isinstance(payload, str)
        sent.append(json.loads(payload))
        send(payload)

    drive.channel.send = recording  # type: ignore[method-assign]
    return sent


async def test_the_robot_drives_forward_while_held_and_stops_on_release(tmp_path: Path) -> None:
    async with driving(tmp_path) as (nav, safety, client):
        start = nav.true_pose

        async def hold_the_key() -> None:
            while True:  # as the terminal chat does on each key repeat
                client.drive(0.3, 0.0, hold=0.6)
                await asyncio.sleep(0.1)

        holder = asyncio.create_task(hold_the_key())
        try:
            await wait_until(lambda: nav.velocity().linear > 0.2)
            await wait_until(lambda: client.drive_state is not None and client.drive_state.active)
            state = client.drive_state
            assert state is not None and state.code == Reason.OK
            assert 0 < state.linear <= 0.3 + 1e-9 and state.cap > 0
            await wait_until(
                lambda: math.hypot(nav.true_pose.x - start.x, nav.true_pose.y - start.y) > 0.2
            )
        finally:
            holder.cancel()
        client.drive(0.0, 0.0)
        await wait_until(lambda: nav.velocity() == Velocity())
        moved = nav.true_pose
        ahead = (moved.x - start.x) * math.cos(start.yaw) + (moved.y - start.y) * math.sin(
            start.yaw
        )
        assert ahead > 0.15  # it went forward
        await wait_until(
            lambda: client.drive_state is not None and client.drive_state.code == Reason.RELEASED
        )
        assert not client.drive_state.active
        assert safety.state().armed  # a release is no stop: nothing latched
        for _ in range(5):
            await asyncio.sleep(0.05)
            assert nav.velocity() == Velocity()


async def test_a_client_that_stops_calling_drive_stops_the_robot_by_itself(
    tmp_path: Path,
) -> None:
    async with driving(tmp_path) as (nav, safety, client):
        sent = sent_commands(client)
        client.drive(0.4, 0.0)  # once, hold 0.25 s: then silence
        await wait_until(lambda: nav.velocity().linear > 0.1)
        await wait_until(
            lambda: client.drive_state is not None and client.drive_state.code == Reason.STALE
        )
        await wait_until(lambda: nav.velocity() == Velocity())
        assert safety.state().armed
        # At 20 Hz for at most the hold: 0.25 s is 5 commands at most, all alike.
        assert 1 <= len(sent) <= 5
        assert all(m["linear"] == 0.4 and m["type"] == "drive" for m in sent)
        seqs = [m["seq"] for m in sent]
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)


async def test_release_is_sent_four_times_and_stop_ends_the_repeating(tmp_path: Path) -> None:
    async with driving(tmp_path) as (nav, safety, client):
        sent = sent_commands(client)
        client.drive(0.3, 0.2, hold=0.3)
        client.drive(0.0, 0.0)  # a release replaces the repeating at once
        await asyncio.sleep(0.4)
        assert [(m["linear"], m["angular"]) for m in sent] == [(0.3, 0.2)] + [
            (0.0, 0.0)
        ] * RELEASE_REPEATS

        sent.clear()
        client.drive(0.3, 0.0, hold=30.0)
        await wait_until(lambda: len(sent) >= 2)
        ack = await client.stop(how="key")
        assert ack.ok
        count = len(sent)
        await asyncio.sleep(0.3)
        assert len(sent) == count  # no command after the stop
        assert not safety.state().armed
        await wait_until(lambda: nav.velocity() == Velocity())


async def test_drive_refuses_numbers_that_are_not_finite(tmp_path: Path) -> None:
    async with driving(tmp_path) as (_, _, client):
        for bad in (math.nan, math.inf, -math.inf):
            with pytest.raises(ValueError, match="finite"):
                client.drive(bad, 0.0)
            with pytest.raises(ValueError, match="finite"):
                client.drive(0.0, bad)
        with pytest.raises(ValueError, match="hold"):
            client.drive(0.1, 0.0, hold=-1)


async def test_an_arm_waits_for_the_clients_own_stop_so_its_repeats_cannot_undo_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The stop's first three acks are lost, so its copies go at 0, 20, 40 and 90 ms, and
    # the arm is asked for at once: sent before the stop's ack, the arm would be undone by
    # the copies that follow it (each stops and disarms the robot again).
    async with driving(tmp_path) as (_nav, safety, client):
        next_ack = client._next
        stop_acks = 0
        stop_queue: asyncio.Queue[Any] | None = None

        async def lossy_stop_acks(queue: asyncio.Queue[Any], wait: float, call: Any) -> Any:
            nonlocal stop_acks, stop_queue
            stop_queue = queue if stop_queue is None else stop_queue  # the stop waits first
            if queue is stop_queue:
                stop_acks += 1
                if stop_acks <= 3:
                    await asyncio.sleep(wait)
                    raise TimeoutError
            return await next_ack(queue, wait, call)

        monkeypatch.setattr(client, "_next", lossy_stop_acks)
        stop = asyncio.create_task(client.stop(how="key"))
        await asyncio.sleep(0)  # the stop's first copy is sent
        arm = await client.arm()
        stop_ended_first = stop.done()
        assert (await stop).ok
        assert arm.ok, arm.text
        await asyncio.sleep(4 * STOP_REPEAT)  # nothing of the stop is still on its way
        assert safety.state().armed, "a copy of the stop undid the arm"
        assert stop_ended_first
        assert stop_acks == 4

        # A stop asked for while the arm waits (the user saw something) is not undone by
        # the arm: the arm is not sent at all.
        stop_queue, stop_acks = None, 0
        first = asyncio.create_task(client.stop(how="key"))
        await asyncio.sleep(0)
        waiting_arm = asyncio.create_task(client.arm())
        await asyncio.sleep(0.005)
        assert (await client.stop(how="button")).ok  # acknowledged before the first one
        assert (await first).ok
        refused = await waiting_arm
        assert not refused.ok and refused.code == "stopped", refused
        await asyncio.sleep(4 * STOP_REPEAT)
        assert not safety.state().armed, "the arm undid a later stop"


async def test_the_first_repeats_of_a_release_and_of_a_stop_come_sooner(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The schedules the client asks its event loop for (not wall-clock timings): a lost
    # first copy costs 20 ms, then the usual period.
    async with driving(tmp_path) as (nav, safety, client):
        loop = asyncio.get_running_loop()
        delays: list[float] = []
        call_later = loop.call_later

        def recording(delay: float, callback: Any, *args: Any) -> asyncio.TimerHandle:
            if getattr(callback, "__name__", "") == "_send_drive":
                delays.append(delay)
            return call_later(delay, callback, *args)

        monkeypatch.setattr(loop, "call_later", recording)
        client.drive(0.0, 0.0)
        await asyncio.sleep(0.3)
        assert delays == [*QUICK_REPEATS, DRIVE_EVERY][: RELEASE_REPEATS - 1]
        monkeypatch.undo()

        # Every ack of the stop is lost until its fourth copy: the waits between copies.
        waits: list[float] = []
        next_ack = client._next
        copies = 0

        async def lossy_acks(queue: asyncio.Queue[Any], wait: float, call: Any) -> Any:
            nonlocal copies
            copies += 1
            if copies <= 3:
                waits.append(wait)
                await asyncio.sleep(wait)
                raise TimeoutError
            return await next_ack(queue, wait, call)

        monkeypatch.setattr(client, "_next", lossy_acks)
        assert (await client.stop(how="key")).ok
        assert waits == [*QUICK_REPEATS, STOP_REPEAT]
        assert not safety.state().armed
        await wait_until(lambda: nav.velocity() == Velocity())
