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

With ``--forge CALL_ID --user NAME``, it is instead a stranger in no call (a bare zenoh
session) that sniffed a live call's keys: it publishes forged DATA frames (the call's
header, fresh counters just ahead of any the call used, random ciphertext; most the
size of a heartbeat, some of 1 KB) on the robot's CONTROL key of NAME's call, paced at
``--rate`` frames per second, and prints ``{"event": "flooding"}`` then
``{"event": "done", "sent": N}``.
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


def forge(robot: str, user: str, call_id: str, connect: str, rate: float, seconds: float) -> int:
    """Publish forged frames on ``user``'s call ``call_id`` with ``robot`` at ``rate``/s."""
    import os
    import time

    import zenoh

    from telebot.channels.proto.frames import DataFrame
    from telebot.channels.transports.base import Lane
    from telebot.channels.transports.zenoh import LANE_QOS, build_zenoh_config
    from telebot.config import ZenohSettings

    settings = ZenohSettings(connect=[connect], multicast_scouting=False)
    session = zenoh.open(build_zenoh_config(settings))
    key = f"telebot/robot/{robot}/call/{user}/{call_id}/ctl"
    publisher = session.declare_publisher(key, **LANE_QOS[Lane.CONTROL])
    call = bytes.fromhex(call_id)
    bodies = [os.urandom(41) for _ in range(15)] + [os.urandom(1000)]
    counter = 1_000  # ahead of the call's own counters (a stranger can read them)
    sent = 0
    tick = 0.01  # a burst every 10 ms
    say("flooding")
    start = time.monotonic()
    while (now := time.monotonic()) < start + seconds:
        due = int((now - start) * rate) - sent
        for _ in range(max(0, due)):
            counter += 1
            header = DataFrame.make_header(call, counter)
            publisher.put(header + bodies[counter % len(bodies)])
            sent += 1
        time.sleep(tick)
    session.close()
    say("done", sent=sent, seconds=round(time.monotonic() - start, 2))
    return 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--home", type=Path, help="the user's home (not with --forge)")
    parser.add_argument("--config", type=Path, help="the user's TOML config (not with --forge)")
    parser.add_argument("--connect", required=True, help="the robot's zenoh endpoint")
    parser.add_argument("--robot", default="guiabot")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--forge", metavar="CALL_ID", help="forge frames on this call's keys")
    parser.add_argument("--user", default="alice", help="whose call --forge floods")
    parser.add_argument("--rate", type=float, default=20_000.0, help="forged frames per second")
    args = parser.parse_args()
    if args.forge:
        sys.exit(forge(args.robot, args.user, args.forge, args.connect, args.rate, args.seconds))
    if args.home is None or args.config is None:
        parser.error("--home and --config are required (unless --forge)")
    config = load_toml(args.config, AppConfig)
    config.transport.zenoh.connect = [args.connect]
    sys.exit(asyncio.run(flood(args.robot, args.home, config, args.seconds)))


if __name__ == "__main__":
    main()
