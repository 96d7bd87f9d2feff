"""Driving by hand from Foxglove's Teleop panel through ``telebot-user foxglove``.

The panel (Foxglove / Lichtblick ``TeleopPanel``) advertises its topic with the schema name
``geometry_msgs/Twist`` in the first encoding of the server's list it supports (here
``json``), publishes the Twist once when a direction is pressed and then every 1/rate s
while it is held, and sends nothing when it is let go (unless its "stop on release" option
is on, which sends the stop button's Twist, zeros by default). These tests do the same with
the Foxglove WebSocket client of tests/test_foxglove.py against the bridge, and a simulated
robot daemon (``rig.robot_on_hub``: the real RobotServer, supervisor and drive service)
over a real call on the memory transport.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import os
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest

from conftest import wait_until
from rig import FAST_SIM, GENEROUS_TIMEOUT, ROBOT, robot_on_hub
from telebot.apps.foxglove_bridge import (
    TELEOP_RATE,
    TELEOP_TOPIC,
    FoxgloveBridge,
    teleop_hold,
    velocity_from_twist,
)
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import AppConfig, CallSettings
from telebot.identity import Role
from telebot.reasons import Reason
from telebot.robot.nav import Velocity
from telebot.robot.sim.stack import SimNavStack
from telebot.services.client import RobotClient, connect
from telebot.services.safety.robot import SafetyDriver
from test_foxglove import FoxgloveWsClient, ws_client

#: As the panel: its channel's schema name (ROS 1 style, whatever the robot runs).
PANEL_SCHEMA = "geometry_msgs/Twist"


def twist(linear_x: float = 0.0, angular_z: float = 0.0) -> bytes:
    """A Twist as the panel sends it in json: all six fields."""
    message = {
        "linear": {"x": linear_x, "y": 0, "z": 0},
        "angular": {"x": 0, "y": 0, "z": angular_z},
    }
    return json.dumps(message).encode()


@contextlib.asynccontextmanager
async def teleop_rig(
    base: Path,
) -> AsyncIterator[tuple[SimNavStack, SafetyDriver, RobotClient, FoxgloveBridge, FoxgloveWsClient]]:
    """An armed simulated robot, its user, the bridge and a Foxglove client."""
    hub = MemoryHub(seed=3)
    config = AppConfig(call=CallSettings(timeout=GENEROUS_TIMEOUT))
    async with (
        robot_on_hub(base, hub, timeout=GENEROUS_TIMEOUT, sim=FAST_SIM) as (nav, safety, _, _),
        MemoryTransport(hub, "user") as transport,
        connect(ROBOT, home=base / "user", config=config, transport=transport) as client,
        FoxgloveBridge(client, port=0) as bridge,
        ws_client(bridge.url) as fox,
    ):
        assert (await client.arm()).ok
        # Not a test of a call just set up (its round trip unmeasured: see test_drive.py).
        await wait_until(lambda: safety.state().cap > 0)
        yield nav, safety, client, bridge, fox


async def hold(fox: FoxgloveWsClient, channel: int, payload: bytes, rate: float) -> None:
    """Publish ``payload`` every 1/rate s until cancelled, as the panel while held."""
    while True:
        await fox.publish(channel, payload)
        await asyncio.sleep(1 / rate)


def state_is(client: RobotClient, reason: Reason) -> Callable[[], bool]:
    return lambda: client.drive_state is not None and client.drive_state.code == reason


async def test_holding_a_teleop_direction_drives_and_letting_go_stops(tmp_path: Path) -> None:
    async with teleop_rig(tmp_path) as (nav, safety, client, bridge, fox):
        start = nav.true_pose
        await fox.advertise(9, TELEOP_TOPIC, "json", PANEL_SCHEMA)
        holding = asyncio.ensure_future(hold(fox, 9, twist(0.3), TELEOP_RATE))
        try:
            await wait_until(lambda: nav.velocity().linear > 0.2)
            await wait_until(state_is(client, Reason.OK))
            await wait_until(
                lambda: math.hypot(nav.true_pose.x - start.x, nav.true_pose.y - start.y) > 0.3
            )
            state = client.drive_state
            assert state is not None and state.active and 0 < state.linear <= 0.3 + 1e-9
        finally:
            holding.cancel()
            await asyncio.gather(holding, return_exceptions=True)
        # Let go: the panel just stops publishing. The robot stops by itself, unlatched.
        await wait_until(lambda: nav.velocity() == Velocity())
        await wait_until(state_is(client, Reason.STALE))
        assert safety.state().armed
        moved = nav.true_pose
        ahead = (moved.x - start.x) * math.cos(start.yaw) + (moved.y - start.y) * math.sin(
            start.yaw
        )
        assert ahead > 0.25  # forward: linear.x
        assert bridge.teleop_received > 3 and bridge.teleop_refused == 0


async def test_twist_stamped_turns_and_a_zero_twist_releases_at_once(tmp_path: Path) -> None:
    from telebot.rosmsg.types import TypeLibrary

    stamped = TypeLibrary().message("geometry_msgs/msg/TwistStamped")
    turn = stamped.serialize(stamped.make(twist={"angular": {"z": 0.8}}))
    async with teleop_rig(tmp_path) as (nav, safety, client, bridge, fox):
        await fox.advertise(9, TELEOP_TOPIC, "cdr", "geometry_msgs/msg/TwistStamped")
        holding = asyncio.ensure_future(hold(fox, 9, turn, TELEOP_RATE))
        try:
            await wait_until(lambda: nav.velocity().angular > 0.3)  # angular.z: to the left
            assert abs(nav.velocity().linear) < 1e-9
        finally:
            holding.cancel()
            await asyncio.gather(holding, return_exceptions=True)
        # The panel's "stop on release" (its stop button's zeros), here as json TwistStamped.
        await fox.advertise(10, TELEOP_TOPIC, "json", "geometry_msgs/msg/TwistStamped")
        await fox.publish(10, json.dumps({"header": {}, "twist": json.loads(twist())}).encode())
        await wait_until(state_is(client, Reason.RELEASED))
        await wait_until(lambda: nav.velocity() == Velocity())
        assert safety.state().armed and bridge.teleop_refused == 0


async def test_bad_teleop_messages_are_counted_logged_short_and_stop_the_driving(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="telebot.apps.foxglove_bridge")
    bad: list[tuple[int, bytes]] = [
        (9, b"not json"),
        (9, os.urandom(2**20)),
        (9, b'{"linear": {"x": NaN}, "angular": {}}'),
        (9, json.dumps({"linear": {"x": "9" * 2**20}, "angular": {}}).encode()),
        (9, b"[1, 2]"),
        (10, twist(0.3)),  # a Twist under another schema name
        (11, b"\x00\x01"),  # not CDR
    ]
    async with teleop_rig(tmp_path) as (nav, safety, client, bridge, fox):
        await fox.advertise(9, TELEOP_TOPIC, "json", PANEL_SCHEMA)
        await fox.advertise(10, TELEOP_TOPIC, "json", "std_msgs/String")
        await fox.advertise(11, TELEOP_TOPIC, "cdr", "geometry_msgs/msg/Twist")
        holding = asyncio.ensure_future(hold(fox, 9, twist(0.3), TELEOP_RATE))
        try:
            await wait_until(lambda: nav.velocity().linear > 0.2)
        finally:
            holding.cancel()
            await asyncio.gather(holding, return_exceptions=True)
        # Garbage while driving: fail safe, the driving ends at once (a release).
        for channel, payload in bad:
            await fox.publish(channel, payload)
        await wait_until(lambda: bridge.teleop_refused == len(bad))
        await wait_until(state_is(client, Reason.RELEASED))
        await wait_until(lambda: nav.velocity() == Velocity())
        assert safety.state().armed  # the bridge is fine, the robot is fine
        # ... and a good message after it drives again.
        holding = asyncio.ensure_future(hold(fox, 9, twist(0.3), TELEOP_RATE))
        try:
            await wait_until(lambda: nav.velocity().linear > 0.2)
        finally:
            holding.cancel()
            await asyncio.gather(holding, return_exceptions=True)
    lines = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    # One short line, then quiet for a while (a panel at 10 Hz would flood the log).
    assert 1 <= len(lines) < len(bad), lines
    assert all(len(line) < 400 and "\n" not in line for line in lines), lines
    assert "Twist" in lines[0] and "/cmd_vel" in lines[0]


async def test_another_teleop_topic_and_an_observer(tmp_path: Path) -> None:
    """--teleop-topic moves the panel's topic; /cmd_vel is then nothing."""
    hub = MemoryHub(seed=3)
    config = AppConfig(call=CallSettings(timeout=GENEROUS_TIMEOUT))
    async with (
        robot_on_hub(tmp_path, hub, timeout=GENEROUS_TIMEOUT, sim=FAST_SIM) as (nav, safety, _, _),
        MemoryTransport(hub, "user") as transport,
        connect(ROBOT, home=tmp_path / "user", config=config, transport=transport) as client,
        FoxgloveBridge(client, port=0, teleop_topic="/teleop", teleop_rate=20) as bridge,
        ws_client(bridge.url) as fox,
    ):
        assert bridge.teleop_hold == pytest.approx(0.1)
        assert (await client.arm()).ok
        await wait_until(lambda: safety.state().cap > 0)
        await fox.advertise(9, TELEOP_TOPIC, "json", PANEL_SCHEMA)
        await fox.advertise(10, "/teleop", "json", PANEL_SCHEMA)
        await fox.publish(9, twist(0.3))
        holding = asyncio.ensure_future(hold(fox, 10, twist(0.3), 20))
        try:
            await wait_until(lambda: nav.velocity().linear > 0.2)
        finally:
            holding.cancel()
            await asyncio.gather(holding, return_exceptions=True)
        received = bridge.teleop_received
        # An observer may not drive: refused by the bridge, as its goals are.
        client.call.role = Role.OBSERVER  # as the robot would have granted
        await fox.publish(10, twist(0.3))
        await wait_until(lambda: bridge.teleop_refused == 1)
        assert bridge.teleop_received == received + 1


async def test_a_panel_publishing_slower_than_the_hold_is_told_to_speed_up(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="telebot.apps.foxglove_bridge")
    async with teleop_rig(tmp_path) as (_nav, _, _, bridge, fox):
        await fox.advertise(9, TELEOP_TOPIC, "json", PANEL_SCHEMA)
        holding = asyncio.ensure_future(hold(fox, 9, twist(0.3), 3))  # 3 Hz, hold 0.15 s
        try:
            await wait_until(lambda: any("publish rate" in r.getMessage() for r in caplog.records))
        finally:
            holding.cancel()
            await asyncio.gather(holding, return_exceptions=True)
        (line,) = [r.getMessage() for r in caplog.records if "publish rate" in r.getMessage()]
        assert "to 10 Hz" in line and TELEOP_TOPIC in line
        assert bridge.teleop_refused == 0


def test_an_integer_too_big_for_a_float_is_a_refused_goal_too() -> None:
    from telebot.apps.foxglove_bridge import goal_from_pose_stamped

    huge = b'{"pose": {"position": {"x": 1%s, "y": 0}}}' % (b"0" * 400)
    with pytest.raises(ValueError, match="PoseStamped"):
        goal_from_pose_stamped(huge, "json")


def test_twist_decoding() -> None:
    from telebot.rosmsg.types import TypeLibrary

    plain = TypeLibrary().message("geometry_msgs/msg/Twist")
    data = plain.serialize(plain.make(linear={"x": 0.5, "y": 9.0}, angular={"z": -1.0}))
    assert velocity_from_twist(data, "cdr", "geometry_msgs/Twist") == (0.5, -1.0)
    assert velocity_from_twist(twist(0.2, 0.4), "json", PANEL_SCHEMA) == (0.2, 0.4)
    assert velocity_from_twist(twist(0.2, 0.4), "json", "") == (0.2, 0.4)  # no schema name
    stamped: dict[str, Any] = {"header": {}, "twist": json.loads(twist(-0.1, 0))}
    for name in ("geometry_msgs/TwistStamped", "geometry_msgs/msg/TwistStamped", ""):
        assert velocity_from_twist(json.dumps(stamped).encode(), "json", name) == (-0.1, 0.0)
    assert velocity_from_twist(b'{"linear": {}, "angular": {}}', "json") == (0.0, 0.0)
    for payload, encoding, name in (
        (b"{}", "json", PANEL_SCHEMA),
        (b'{"linear": {"x": true}, "angular": {}}', "json", PANEL_SCHEMA),
        (b'{"linear": {"x": Infinity}, "angular": {}}', "json", PANEL_SCHEMA),
        (b'{"linear": {"x": 1%s}, "angular": {}}' % (b"0" * 400), "json", PANEL_SCHEMA),
        (twist(), "json", "geometry_msgs/msg/TwistStamped"),
        (twist(), "json", "geometry_msgs/msg/PoseStamped"),
        (twist(), "ros1", PANEL_SCHEMA),
        (b"\x00", "cdr", PANEL_SCHEMA),
    ):
        with pytest.raises(ValueError, match=r"Twist|encoding") as refused:
            velocity_from_twist(payload, encoding, name)
        assert len(str(refused.value)) < 300
    # The hold: 1.5 periods of the panel's rate, at least 0.1 s.
    assert teleop_hold(10) == pytest.approx(0.15) and teleop_hold(50) == 0.1
    assert teleop_hold(2) == pytest.approx(0.75)


@pytest.mark.parametrize(
    ("flag", "value", "says"),
    [
        ("--teleop-rate", "1", "2 to 50 Hz"),
        ("--teleop-rate", "nan", "2 to 50 Hz"),
        ("--teleop-rate", "fast", "invalid"),
        ("--teleop-topic", "cmd_vel", "a topic like /cmd_vel"),
        ("--teleop-topic", "/goal_pose", "the goal topic"),
    ],
)
def test_bad_teleop_flags_are_one_line_errors(
    flag: str, value: str, says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from telebot.apps import user_cli

    with pytest.raises(SystemExit) as ended:
        user_cli.build_parser().parse_args(["foxglove", ROBOT, flag, value])
    assert ended.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and flag in err[0] and says in err[0], err
    args = user_cli.build_parser().parse_args(["foxglove", ROBOT])  # the bridge's defaults
    assert (args.teleop_rate, args.teleop_topic) == (TELEOP_RATE, TELEOP_TOPIC)
