"""The flooding children of ``bench/channels.py`` D (``bench/_survival.py``), in a module of
their own: they start in a fraction of the time ``_survival.py`` (the tests' rig) takes to
import, and a flood's set-up is not what D measures.

``_flooders.py --child flood PORT ROBOT HOME SECONDS``: D1, a user in a call of its own (the
identity in HOME) who floods ROBOT with 32 KB datagrams for SECONDS.
``_flooders.py --child stranger PORT ROBOT USER CALL_ID SECONDS in|call``: D2 and D3, a raw
zenoh peer in no call that floods ROBOT's handshake key (``in``), or that and USER's call
CALL_ID's keys (``call``), with junk for SECONDS.

Each prints ``ready`` once flooding, then, when its stdin closes, one JSON line of counters.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import zenoh

from telebot.channels.transports.zenoh import build_zenoh_config
from telebot.config import AppConfig, ZenohSettings
from telebot.errors import TelebotError
from telebot.services.client import connect

DATAGRAM = 32_768
BURST = 16  # datagrams the flooder sends between two yields to its loop


def peer_config(endpoint: str) -> AppConfig:
    """A zenoh peer that connects to ``endpoint`` only (no scouting)."""
    settings = ZenohSettings(connect=[endpoint], multicast_scouting=False)
    return AppConfig.model_validate({"transport": {"zenoh": settings}})


async def flood_child(port: int, robot: str, home: Path, seconds: float) -> None:
    """A user in a call of its own who floods 32 KB datagrams."""
    config = peer_config(f"tcp/127.0.0.1:{port}")
    async with connect(robot, home=home, config=config, timeout=20) as client:
        first = client.call.id
        payload = os.urandom(DATAGRAM)
        loop = asyncio.get_running_loop()
        sent = 0
        print("ready", flush=True)
        end = loop.time() + seconds
        while loop.time() < end:
            channel = client.call.channel("flood")
            for _ in range(BURST):
                with contextlib.suppress(TelebotError):
                    channel.send(payload)
                    sent += 1
            await asyncio.sleep(0)
        await client.telemetry()
        telemetry = await client.telemetry()
        counters = {
            "sent": sent,
            "rx_dropped": telemetry.rx_dropped,
            "reconnects": client.reconnects,
            "active": client.call.active and client.call.id == first,
        }
    await asyncio.to_thread(sys.stdin.read)
    print(json.dumps(counters), flush=True)


def stranger_child(
    port: int, robot: str, user: str, call_id: str, seconds: float, where: str
) -> None:
    """A raw zenoh peer in no call that floods ``robot``'s handshake key (``where`` "in")
    or that and ``user``'s call ``call_id``'s keys ("call") with junk."""
    settings = ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    session = zenoh.open(build_zenoh_config(settings))
    base = f"telebot/robot/{robot}"
    keys = [f"{base}/in/mallory"]
    if where == "call":
        keys += [f"{base}/call/{user}/{call_id}/ctl", f"{base}/call/{user}/{call_id}/data"]
    publishers = [session.declare_publisher(key) for key in keys]
    header = b"\x02\x03" + bytes.fromhex(call_id)
    junk = [
        os.urandom(200),  # garbage
        b"\x02\x03" + os.urandom(6),  # a truncated DATA frame
        header + os.urandom(8 + 100),  # alice's call id, no valid seal
        header + os.urandom(8 + 16_000),
    ]
    huge = os.urandom(1 << 20)
    sent = 0
    sent_bytes = 0
    print("ready", flush=True)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for publisher in publishers:
            for payload in junk:
                publisher.put(payload)
                sent += 1
                sent_bytes += len(payload)
        if sent % 400 < len(publishers) * len(junk):  # now and then, a megabyte
            for publisher in publishers:
                publisher.put(huge)
                sent += 1
                sent_bytes += len(huge)
    session.close()
    sys.stdin.read()
    print(json.dumps({"sent": sent, "mb": sent_bytes / 1e6}), flush=True)


def run_child(args: Sequence[str]) -> None:
    kind = args[0]
    if kind == "flood":
        asyncio.run(flood_child(int(args[1]), args[2], Path(args[3]), float(args[4])))
    elif kind == "stranger":
        stranger_child(int(args[1]), args[2], args[3], args[4], float(args[5]), args[6])
    else:
        raise SystemExit(f"unknown child {kind!r}")


def _main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == "--child":
        run_child(sys.argv[2:])
        return
    raise SystemExit("run bench/channels.py (this module holds the flooders of its section D)")


if __name__ == "__main__":
    _main()
