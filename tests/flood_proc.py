"""Child process of the flood tests: a user in a call who floods 32 KB datagrams.

Calls the robot with the library (:func:`telebot.services.client.connect`), then sends
32,768-byte datagrams on the channel ``flood`` (DATA lane) as fast as it can for
``--seconds``, yielding to its event loop only every few datagrams (so its heartbeats and
the robot's telemetry still get through). It prints one JSON object per line::

    {"event": "connected", "call": ID}
    {"event": "flooding"}
    {"event": "done", "sent": N, "rx_dropped": D, "reconnects": R, "call": ID, "active": true}

``rx_dropped`` is the largest count of this call's frames the robot says (telemetry) it
dropped unread; ``reconnects`` counts calls that dropped and came back (0: never dropped).

    python -m flood_proc --home HOME --config user.toml --connect tcp/127.0.0.1:7447
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from pathlib import Path
from typing import Any

from telebot.config import AppConfig, load_toml
from telebot.errors import TelebotError
from telebot.services.client import connect

DATAGRAM = 32_768
#: Datagrams sent between two yields to the loop.
BURST = 16


def say(event: str, **fields: Any) -> None:
    print(json.dumps({"event": event, **fields}), flush=True)


async def flood(robot: str, home: Path, config: AppConfig, seconds: float) -> int:
    async with connect(robot, home=home, config=config, timeout=10) as client:
        first_call = client.call.id
        say("connected", call=first_call)
        rx_dropped = 0

        def on_telemetry() -> None:
            nonlocal rx_dropped
            telemetry = client.latest_telemetry.value
            if telemetry is not None:
                rx_dropped = max(rx_dropped, telemetry.rx_dropped)

        loop = asyncio.get_running_loop()
        payload = bytes(DATAGRAM)
        sent = errors = 0
        say("flooding")
        end = loop.time() + seconds
        while loop.time() < end:
            channel = client.call.channel("flood")  # the current call's, after a reconnect too
            for _ in range(BURST):
                try:
                    channel.send(payload)
                    sent += 1
                except TelebotError:
                    errors += 1
            on_telemetry()
            await asyncio.sleep(0)
        # The robot's count after the flood: the next telemetry (sent at 2 Hz by default).
        await client.telemetry()
        await client.telemetry()
        on_telemetry()
        say(
            "done",
            sent=sent,
            errors=errors,
            rx_dropped=rx_dropped,
            reconnects=client.reconnects,
            call=client.call.id,
            first_call=first_call,
            active=client.call.active,
        )
    return 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--home", type=Path, required=True, help="the user's home")
    parser.add_argument("--config", type=Path, required=True, help="the user's TOML config")
    parser.add_argument("--connect", required=True, help="the robot's zenoh endpoint")
    parser.add_argument("--robot", default="guiabot")
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    config = load_toml(args.config, AppConfig)
    config.transport.zenoh.connect = [args.connect]
    sys.exit(asyncio.run(flood(args.robot, args.home, config, args.seconds)))


if __name__ == "__main__":
    main()
