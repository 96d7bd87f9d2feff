"""``telebot-sim``: the simulated robot as a ROS 2 / Nav2 robot in its own process.

It serves the simulator's map, pose, odometry, laser, battery, plan, cameras and Nav2's action
servers over rmw_zenoh (see :mod:`telebot.robot.ros2.simrobot`). By default it is its own zenoh
router, as ``rmw_zenohd`` is, listening on the ``[ros2] router`` endpoints of the config
(``tcp/127.0.0.1:7447``), so ``telebot-robot run --robot ros2`` with the same config drives it;
``--router`` joins an existing router instead. Runs until SIGINT or SIGTERM.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from telebot.apps.common import (
    EXIT_OK,
    EXIT_USAGE,
    Parser,
    new_parser,
    run,
    stop_on_signals,
)
from telebot.config import RobotConfig, format_validation_error, load_toml
from telebot.errors import ConfigError, MapError, RobotError, RobotUnreachable

PROG = "telebot-sim"
#: The ROS node name of the simulated robot.
NODE_NAME = "telebot_sim"


def build_parser() -> Parser:
    """The argument parser of telebot-sim."""
    parser = new_parser(
        PROG,
        "The simulated robot as a ROS 2 / Nav2 robot over rmw_zenoh: serves /map, /amcl_pose, "
        "/odom, /tf, /scan, /battery_state, /plan, camera images, /cmd_vel and the "
        "navigate_to_pose, drive_on_heading, spin and backup actions. Runs its own zenoh "
        "router (like rmw_zenohd) unless --router is given. Stops on SIGINT/SIGTERM.",
    )
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help="robot TOML config: [sim] sets up the simulator, [ros2] the names, domain, "
        "distro and router endpoint (default: built-in defaults)",
    )
    where = parser.add_mutually_exclusive_group()
    where.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="run a zenoh router listening here (repeatable; default: [ros2] router of the "
        "config, tcp/127.0.0.1:7447)",
    )
    where.add_argument(
        "--router",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="join the zenoh router at ENDPOINT (e.g. rmw_zenohd's tcp/127.0.0.1:7447) as a "
        "client instead of running one (repeatable)",
    )
    parser.add_argument(
        "--domain", type=int, default=None, metavar="N", help="ROS_DOMAIN_ID (default: 0)"
    )
    parser.add_argument(
        "--namespace", default=None, metavar="NS", help="ROS namespace of the robot's topics"
    )
    parser.add_argument(
        "--map",
        default=None,
        metavar="MAP",
        help="map: 'building' (default), 'small' or a ROS map_server YAML file "
        "(overrides sim.map of the config)",
    )
    parser.add_argument(
        "--distro",
        choices=["jazzy", "kilted"],
        default=None,
        help="ROS 2 distro whose message types to speak (default: jazzy)",
    )
    parser.add_argument(
        "--stamped",
        action="store_true",
        default=None,
        help="/cmd_vel carries TwistStamped (Kilted's default) rather than Twist",
    )
    return parser


def _config(args: argparse.Namespace) -> RobotConfig:
    """The robot config with the command line's overrides; ConfigError on bad values."""
    config = load_toml(args.config, RobotConfig) if args.config else RobotConfig()
    updates: dict[str, Any] = {}
    if args.domain is not None:
        updates["domain_id"] = args.domain
    if args.namespace is not None:
        updates["namespace"] = args.namespace
    if args.distro is not None:
        updates["distro"] = args.distro
    if args.stamped:
        updates["cmd_vel_stamped"] = True
    if args.router:
        updates["router"] = list(args.router)
    try:
        for key, value in updates.items():
            setattr(config.ros2, key, value)
        if args.map is not None:
            config.sim.map = args.map
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, "command line")) from exc
    return config


async def serve(args: argparse.Namespace) -> int:
    """Open the router (or join one), the node and the simulator, and serve until a signal."""
    import zenoh

    from telebot.robot.ros2.node import Ros2Node
    from telebot.robot.ros2.simrobot import SimRobotServer, open_router
    from telebot.robot.sim.stack import SimNavStack
    from telebot.rosmsg.types import TypeLibrary

    config = _config(args)
    ros2 = config.ros2
    base_dir = args.config.parent if args.config and args.map is None else None
    loop = asyncio.get_running_loop()
    try:
        stack = SimNavStack.from_config(config, base_dir=base_dir, now=loop.time())
    except (MapError, RobotError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE

    router: zenoh.Session | None = None
    if args.router:
        connect = list(ros2.router)
        where = ", ".join(connect)
    else:
        listen = list(args.listen) or list(ros2.router)
        router = await asyncio.to_thread(open_router, listen)
        # The node joins its own router as a client, as a ROS node joins rmw_zenohd.
        connect = [_local(endpoint) for endpoint in listen]
        where = ", ".join(listen)
    try:
        node = await asyncio.to_thread(
            lambda: Ros2Node(
                name=NODE_NAME,
                namespace=ros2.namespace,
                domain_id=ros2.domain_id,
                connect=connect,
                mode="client",
                library=TypeLibrary(ros2.distro),
                connect_timeout=ros2.connect_timeout,
            )
        )
        try:
            server = SimRobotServer(stack, node, ros2)
            # One line on stdout when everything is up: people and scripts wait for it.
            print(
                f"{PROG}: serving map {config.sim.map!r} as ROS 2 robot on {where} "
                f"(domain {ros2.domain_id})",
                flush=True,
            )
            stop = asyncio.Event()
            with stop_on_signals(stop):
                await server.run(stop)
        finally:
            await asyncio.to_thread(node.close)
    finally:
        if router is not None:
            await asyncio.to_thread(router.close)
    return EXIT_OK


def _local(endpoint: str) -> str:
    """Where a client on this machine reaches a router listening on ``endpoint``."""
    for wildcard in ("0.0.0.0", "[::]"):
        if f"/{wildcard}:" in endpoint:
            return endpoint.replace(wildcard, "127.0.0.1", 1)
    return endpoint


def main(argv: list[str] | None = None) -> int:
    """Entry point of telebot-sim."""
    args = build_parser().parse_args(argv)

    async def command() -> int:
        try:
            return await serve(args)
        except RobotUnreachable as exc:  # cannot listen, or no router to join
            print(f"{PROG}: error: {exc}", file=sys.stderr)
            return EXIT_USAGE

    return run(PROG, command, args.log_level)


if __name__ == "__main__":
    sys.exit(main())
