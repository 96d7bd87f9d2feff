"""A ``safety`` request the robot cannot read is answered with one error line, never silence,
and a ``stop`` among them still stops the robot (docs/protocol.md §18).

The in-process robot of ``rig.robot_on_hub`` over a real call on the memory hub; the requests
are raw JSON on the call's ``safety`` channel, as a client written from the protocol sends them.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

from conftest import ROBOT, wait_until
from rig import FAST_SIM, GENEROUS_TIMEOUT, SLACK, robot_on_hub, user_on_hub
from telebot.channels.channel import ReceivedDatagram
from telebot.channels.transports import Lane
from telebot.channels.transports.memory import MemoryHub
from telebot.reasons import Reason
from telebot.robot.nav import Velocity
from telebot.services.client import RobotClient
from telebot.services.safety.wire import SAFETY, SafetyError, decode_safety_reply

BAD_IDS: list[Any] = ["7", 7.5, 7.0, -1, 2**32, None, True, [7]]


async def test_a_bad_safety_id_gets_an_error_line_and_a_bad_stop_still_stops(
    tmp_path: Path,
) -> None:
    hub = MemoryHub(seed=5)
    async with (
        robot_on_hub(tmp_path, hub, timeout=GENEROUS_TIMEOUT, sim=FAST_SIM) as (nav, safety, _, _),
        user_on_hub(tmp_path, hub) as user,
    ):
        call = await user.call(ROBOT)
        client = RobotClient(call)
        assert (await client.arm()).ok
        replies = client.chat_replies("fwd 3", timeout=30)
        assert (await anext(replies)).code == Reason.ACCEPTED
        await wait_until(lambda: nav.velocity().linear > 0.2)

        # From here on this test reads the safety channel itself (the client's acks are done).
        answers: asyncio.Queue[dict[str, Any]] = asyncio.Queue()

        def on_safety(datagram: ReceivedDatagram) -> None:
            message = json.loads(datagram.payload)
            if message["type"] != "state":
                answers.put_nowait(message)

        channel = call.channel(SAFETY, lane=Lane.CONTROL)
        channel.set_callback(on_safety)

        async def answer_to(request: str) -> dict[str, Any]:
            channel.send(request)
            return await asyncio.wait_for(answers.get(), 5.0 + SLACK)

        # A stop whose id is a string (a JS client's habit): the robot stops all the same,
        # latches, and says what was wrong in one line with a reason code.
        error = await answer_to('{"type": "stop", "id": "7", "how": "key"}')
        assert error == {
            "type": "error",
            "ok": False,
            "reason": "safety: 'id' must be an integer in 0..4294967295",
            "code": Reason.INVALID,
        }
        # The client library reads it too (and logs it: its own requests always decode).
        assert decode_safety_reply(json.dumps(error)) == SafetyError(error["reason"], "invalid")
        await wait_until(lambda: nav.velocity() == Velocity())
        assert not safety.supervisor.armed
        assert "alice (key)" in safety.state().text  # who and how, as for a valid stop

        # Every bad id of every request type: an error, and nothing else happens.
        for kind in ("stop", "arm", "take", "release"):
            for bad in BAD_IDS:
                message = json.dumps({"type": kind, "id": bad})
                error = await answer_to(message)
                assert (error["type"], error["ok"], error["code"]) == ("error", False, "invalid")
                assert "'id' must be an integer in 0..4294967295" in error["reason"], message
        error = await answer_to('{"type": "arm"}')
        assert error["reason"] == "safety: 'id' must be an integer in 0..4294967295"
        assert not safety.supervisor.armed  # no bad arm armed it

        # Not a request at all: the error names it in one short line, quoting little of it.
        error = await answer_to(json.dumps({"type": "x" * 20000, "id": 1}))
        assert error["code"] == "invalid" and "unknown type" in error["reason"]
        assert len(error["reason"]) < 120 and "\n" not in error["reason"]
        error = await answer_to("stop please")
        assert error["code"] == "invalid" and error["reason"].startswith("safety: not JSON")
        channel.send(b"\x00" * 100)
        error = await asyncio.wait_for(answers.get(), 5.0 + SLACK)
        assert error["reason"] == "safety: expected a JSON text datagram, got 100 bytes"

        # The edges of the range are valid ids, and a valid request still gets its ack.
        for good in (0, 2**32 - 1):
            ack = await answer_to(json.dumps({"type": "arm", "id": good}))
            assert (ack["type"], ack["id"], ack["ok"]) == ("ack", good, True)
        assert safety.supervisor.armed
        await replies.aclose()
