"""Child process of the zenoh transport tests: a peer in another process.

Listens on ``--listen``, echoes every sample received on ``test/<id>/ping`` back on
``test/<id>/pong``, optionally holds a presence token, prints ``ready`` once its
subscription and token are declared, and exits when its stdin closes (so that it never
outlives the test that started it).

    python tests/zenoh_peer_proc.py --listen tcp/127.0.0.1:7447 --id abc [--token KEY]
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from collections.abc import Sequence

from telebot.channels.transports.base import Lane, Sample
from telebot.channels.transports.zenoh import ZenohTransport
from telebot.config import ZenohSettings


async def run(listen: str, test_id: str, token: str | None) -> None:
    settings = ZenohSettings(listen=[listen], multicast_scouting=False)
    async with ZenohTransport(settings) as transport:
        pong = transport.publisher(f"test/{test_id}/pong", Lane.DATA)

        def echo(batch: Sequence[Sample]) -> None:
            for sample in batch:
                pong.put(sample.payload)

        transport.subscribe(f"test/{test_id}/ping", echo)
        if token is not None:
            transport.declare_presence(token)
        print("ready", flush=True)
        # Block until the parent closes our stdin (or kills us).
        await asyncio.to_thread(sys.stdin.buffer.read)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--listen", required=True)
    parser.add_argument("--id", required=True)
    parser.add_argument("--token")
    args = parser.parse_args()
    asyncio.run(run(args.listen, args.id, args.token))


if __name__ == "__main__":
    main()
