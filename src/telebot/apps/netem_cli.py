"""``telebot-netem``: play a network profile (Wi-Fi, 4G, ...) between two zenoh endpoints.

A loopback proxy (:class:`telebot.netem.NetemProxy`): it listens on ``--listen``, forwards
to ``--to`` through the profile's delay, jitter, loss, bandwidth cap and outages, and runs
until SIGINT or SIGTERM. Point a robot's or a user's ``--connect`` at the ``--listen``
endpoint (README "Network emulator").
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from collections.abc import Callable

from telebot.apps.common import EXIT_OK, EXIT_USAGE, new_parser, run, stop_on_signals
from telebot.errors import ConfigError
from telebot.netem import PROFILES, NetemProxy, Profile, parse_endpoint, profile
from telebot.netem.proxy import CUT_AFTER

PROG = "telebot-netem"


def _profile_arg(text: str) -> Profile:
    try:
        return profile(text)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def _endpoint_arg(listen: bool) -> Callable[[str], str]:
    def check(text: str) -> str:
        try:
            parse_endpoint(text, listen=listen)
        except ConfigError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from exc
        return text

    return check


def _seconds_arg(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"expected seconds > 0, got {text[:40]!r}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The ``telebot-netem`` argument parser."""
    parser = new_parser(
        PROG,
        "Relay zenoh links on this machine through an emulated network: delay, jitter, "
        "random and burst loss, a bandwidth cap and outages (README 'Network emulator').",
    )
    parser.add_argument(
        "profile",
        type=_profile_arg,
        metavar="PROFILE",
        help=f"the network to play: {', '.join(PROFILES)}",
    )
    parser.add_argument(
        "--listen",
        required=True,
        type=_endpoint_arg(listen=True),
        metavar="ENDPOINT",
        help="where to listen, e.g. tcp/127.0.0.1:7448 (udp/ and quic/ relay datagrams, "
        "tcp/ and tls/ byte streams); connect zenoh here",
    )
    parser.add_argument(
        "--to",
        required=True,
        type=_endpoint_arg(listen=False),
        metavar="ENDPOINT",
        help="the endpoint to forward to, of the same kind, e.g. tcp/127.0.0.1:7447",
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="seed of the random losses (default: 0)"
    )
    parser.add_argument(
        "--cut-after",
        type=_seconds_arg,
        default=CUT_AFTER,
        metavar="SECONDS",
        help="an outage longer than this resets TCP connections "
        f"(default: {CUT_AFTER:g}, zenoh's default lease)",
    )
    parser.add_argument(
        "--events",
        action="store_true",
        help="print a JSON 'ready' line on stdout when listening (docs/events.md)",
    )
    return parser


async def _serve(args: argparse.Namespace) -> int:
    proxy = NetemProxy(
        args.profile, listen=args.listen, target=args.to, seed=args.seed, cut_after=args.cut_after
    )
    proxy.start()  # TransportError (one line, exit 2) if it cannot listen
    stop = asyncio.Event()
    try:
        with stop_on_signals(stop):
            if args.events:
                ready = {
                    "event": "ready",
                    "profile": proxy.profile.name,
                    "listen": proxy.endpoint,
                    "to": str(proxy.target),
                    "seed": proxy.seed,
                }
                print(json.dumps(ready), flush=True)
            else:
                print(
                    f"{PROG}: {proxy.profile.name} from {proxy.endpoint} to {proxy.target} "
                    f"({proxy.profile.description or 'custom'})",
                    flush=True,
                )
            await stop.wait()
    finally:
        proxy.close()
    return EXIT_OK


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``telebot-netem``."""
    args = build_parser().parse_args(argv)
    try:
        NetemProxy(args.profile, args.listen, args.to)  # endpoints of different kinds
    except ConfigError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE

    async def main_run() -> int:
        return await _serve(args)

    return run(PROG, main_run, args.log_level)


if __name__ == "__main__":
    sys.exit(main())
