"""Child process of the safety end-to-end tests: a driver that moves the robot and then idles.

Calls the robot with the library (:func:`telebot.services.client.connect`), re-arms it
(taking the drive if it is free), starts a long goto to whichever of the small map's
``start`` and ``corridor`` is farther away, and once the robot's pose shows it driving
prints ``{"event": "moving", ...}``. Then it does nothing but keep the call open (the call
sends its heartbeats by itself), so that the test can freeze it (SIGSTOP) or kill it.
When the call ends it prints ``{"event": "ended", "kind": ...}`` and exits.

Every line on stdout is one JSON object with an ``event`` key (``connected``, ``armed``,
``moving``, ``ended``, ``error``)::

    python -m safety_driver_proc --home HOME --config user.toml --connect tcp/127.0.0.1:7447
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import sys
from collections.abc import AsyncGenerator
from pathlib import Path
from typing import Any

from telebot.config import AppConfig, load_toml
from telebot.reasons import Reason
from telebot.services.chat.wire import ChatReply
from telebot.services.client import RobotClient, connect

#: Far ends of the small map's corridor: a goto between them is several metres long.
PLACES = {"start": (1.0, 1.2), "corridor": (10.5, 1.2)}
#: How long to keep trying to re-arm while an earlier call still holds the drive (s).
ARM_PATIENCE = 10.0


def say(event: str, **fields: Any) -> None:
    print(json.dumps({"event": event, **fields}), flush=True)


async def arm(client: RobotClient) -> None:
    """Re-arm, waiting for an earlier call that still holds the drive to be dropped."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + ARM_PATIENCE
    while True:
        ack = await client.arm()
        if ack.ok:
            return
        if ack.code == Reason.NOT_HOLDER:  # the drive was released: take it, then arm
            await client.take_drive()
        if loop.time() > deadline:
            raise RuntimeError(f"arm refused: {ack.text}")
        await asyncio.sleep(0.1)


async def first_reply(client: RobotClient, command: str, timeout: float | None = None) -> ChatReply:
    """The first reply to ``command`` (a motion's acknowledgement); the motion runs on."""
    replies = client.chat_replies(command, timeout=timeout)
    assert isinstance(replies, AsyncGenerator)  # closed here, not left to the GC
    async with contextlib.aclosing(replies):
        return await anext(replies)


async def drive(robot: str, home: Path, config: AppConfig) -> int:
    async with connect(robot, home=home, config=config, timeout=10) as client:
        say("connected", call=client.call.id)
        await arm(client)
        say("armed")
        here = await client.pose()
        target = max(PLACES, key=lambda name: math.dist(PLACES[name], (here.x, here.y)))
        reply = await first_reply(client, f"goto {target}")
        if not reply.ok or reply.final:
            say("error", text=reply.text)
            return 1
        async with asyncio.timeout(15):
            while True:
                pose = await client.pose()
                if abs(pose.v) > 0.05:
                    break
        say("moving", target=target, v=pose.v, t=pose.t)
        end = await client.call.wait_ended()
        say("ended", kind=end.kind, detail=end.detail)
    return 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--home", type=Path, required=True, help="the user's home")
    parser.add_argument("--config", type=Path, required=True, help="the user's TOML config")
    parser.add_argument("--connect", required=True, help="the robot's zenoh endpoint")
    parser.add_argument("--robot", default="guiabot")
    args = parser.parse_args()
    config = load_toml(args.config, AppConfig)
    config.transport.zenoh.connect = [args.connect]
    sys.exit(asyncio.run(drive(args.robot, args.home, config)))


if __name__ == "__main__":
    main()
