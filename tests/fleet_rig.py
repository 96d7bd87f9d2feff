"""A fleet in one process: several simulated robots and users on one memory hub.

Each robot is a SimNavStack on the small map with its SafetyDriver and RobotServer, on
its own hub node (its name), so a test can cut one robot's links (``hub.cut``) and read
each base's velocity directly. Users' homes know every robot; every robot lists every user.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Mapping
from dataclasses import dataclass
from pathlib import Path

from rig import GENEROUS_STALE_VIDEO, GENEROUS_TIMEOUT, services_without_media
from telebot.channels.call import RobotEndpoint, UserEndpoint
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import CallSettings, ServiceSettings, SimSettings
from telebot.identity import ContactBook, Identity, KnownRobots, Role
from telebot.robot.sim.stack import SimNavStack
from telebot.services.base import ServiceConfig
from telebot.services.robot import RobotServer
from telebot.services.safety.robot import SafetyDriver
from telebot.services.video.wire import VideoSettings

# No test here is about drop timing: a preempted process keeps its calls.
CALLS = CallSettings(timeout=GENEROUS_TIMEOUT)


@dataclass
class FleetRobot:
    """One robot of the fleet, running in this process."""

    name: str
    nav: SimNavStack
    safety: SafetyDriver
    server: RobotServer
    endpoint: RobotEndpoint


def make_homes(base: Path, robots: list[str], users: Mapping[str, Role]) -> None:
    """Keys for every robot (``base/robots/NAME``) and user (``base/users/NAME``)."""
    robot_ids = {name: Identity.generate(name) for name in robots}
    user_ids = {name: Identity.generate(name) for name in users}
    for name, identity in robot_ids.items():
        home = base / "robots" / name
        identity.save(home)
        contacts = ContactBook.load(home)
        for user, role in users.items():
            contacts.add(user, user_ids[user].public_key, role)
        contacts.save()
    for name, identity in user_ids.items():
        home = base / "users" / name
        identity.save(home)
        known = KnownRobots.load(home)
        for robot, robot_identity in robot_ids.items():
            known.add(robot, robot_identity.public_key)
        known.save()


def user_home(base: Path, user: str) -> Path:
    """The home of ``user`` made by :func:`make_homes`."""
    return base / "users" / user


@contextlib.asynccontextmanager
async def running_robot(base: Path, name: str, hub: MemoryHub) -> AsyncIterator[FleetRobot]:
    """Robot ``name`` (made by :func:`make_homes`) on ``hub`` as node ``name``, serving calls."""
    loop = asyncio.get_running_loop()
    settings = SimSettings(
        map="small",
        max_linear_speed=1.5,
        linear_accel=3.0,
        max_angular_speed=3.0,
        angular_accel=8.0,
        control_hz=50,
    )
    nav = SimNavStack.from_settings(settings, now=loop.time())
    safety = SafetyDriver(
        nav,
        timeout=GENEROUS_TIMEOUT,
        max_speed=settings.max_linear_speed,
        stale_video=GENEROUS_STALE_VIDEO,
    )
    server = RobotServer(
        nav,
        ServiceSettings(pose_hz=10.0),
        services=services_without_media(),
        control_hz=settings.control_hz,
        map_name="small",
        safety=safety,
        config=ServiceConfig(
            video=VideoSettings(width=160, height=120, max_fps=5, quality=50, min_quality=30),
        ),
    )
    await server.prepare()
    home = base / "robots" / name
    with safety:
        async with (
            MemoryTransport(hub, name) as transport,
            RobotEndpoint(
                transport, Identity.load(home), ContactBook.load(home), settings=CALLS
            ) as endpoint,
        ):
            server.attach(endpoint)
            runner = asyncio.create_task(server.run(), name=f"robot-{name}")
            try:
                yield FleetRobot(name, nav, safety, server, endpoint)
            finally:
                safety.stop(None, "test over")
                runner.cancel()
                await asyncio.gather(runner, return_exceptions=True)


@contextlib.asynccontextmanager
async def user_endpoint(base: Path, user: str, hub: MemoryHub) -> AsyncIterator[UserEndpoint]:
    """User ``user``'s endpoint on ``hub`` (node ``user``)."""
    home = user_home(base, user)
    async with (
        MemoryTransport(hub, user) as transport,
        UserEndpoint(
            transport, Identity.load(home), KnownRobots.load(home), settings=CALLS
        ) as endpoint,
    ):
        yield endpoint
