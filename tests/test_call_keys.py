"""A call's own keys: what a robot does with a live call's id in a new HELLO, and how a
call being set up ends up when its first frames hang it up."""

from __future__ import annotations

import time

from conftest import ROBOT, Homes, memory_endpoints, wait_until
from telebot.channels.proto.session import start_call
from telebot.channels.transports import Lane
from telebot.channels.transports.memory import MemoryHub


async def test_a_live_call_id_in_a_new_hello_makes_no_second_call(homes: Homes) -> None:
    """Once a call's answer has left the robot's cache, a fresh HELLO (a new timestamp,
    so not a replay) that reuses the live call's id is refused, not a second call on the
    same keys."""
    async with memory_endpoints(homes, MemoryHub(seed=1)) as (robot, user):
        call = await user.call(ROBOT)
        await wait_until(lambda: len(robot.calls) == 1)
        robot._answered.clear()  # as after 256 other HELLOs
        hello, _ = start_call(
            homes.user.private_key,
            homes.robot.public_key,
            caller=homes.user.name,
            instance=user.instance,
            call_id=bytes.fromhex(call.id),
            wall_time_ns=time.time_ns(),
        )
        publisher = user.transport.publisher(f"telebot/robot/{ROBOT}/in", Lane.CONTROL)
        publisher.put(hello.encode())
        publisher.close()
        await wait_until(lambda: robot.stats.rejected["call_id_reused"] == 1)
        assert [c.id for c in robot.calls] == [call.id]
        assert call.active


async def test_a_call_hung_up_by_its_first_frames_is_not_kept(homes: Homes) -> None:
    """The robot answers and hangs up at once ("robot busy"): the HANGUP may be read
    before the WELCOME is handled. The user's call then ends and is not left among the
    endpoint's calls."""
    async with memory_endpoints(homes, MemoryHub(seed=1)) as (robot, user):
        robot.on_call = lambda call: call.hangup_now("robot busy")
        call = await user.call(ROBOT)
        await wait_until(lambda: call.end is not None)
        assert call.end is not None and call.end.kind == "hung_up"
        assert "robot busy" in call.end.detail
        assert user.calls == []
