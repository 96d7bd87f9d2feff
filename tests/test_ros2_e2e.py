"""The base outlives its daemon: telebot-sim stops by itself when the daemon dies or freezes.

Three processes on loopback, as on a real robot: ``telebot-sim`` (the base and Nav2, its own
zenoh router), ``telebot-robot run --robot ros2`` (the daemon, a client of that router) and
this test (the user, and a probe node that watches ``/odom`` as a ROS tool would).
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from conftest import wait_until
from rig import SLACK, Daemon, Process, start_telebot_sim
from telebot.robot.ros2.node import Ros2Node
from telebot.rosmsg.types import TypeLibrary

pytestmark = [pytest.mark.zenoh, pytest.mark.timeout(180)]


@dataclass
class Odometry:
    """What the probe heard on /odom: (time.monotonic(), linear, angular) samples."""

    samples: list[tuple[float, float, float]]
    lock: threading.Lock

    def moving(self) -> bool:
        with self.lock:
            return bool(self.samples) and abs(self.samples[-1][1]) > 0.05

    def still_since(self, after: float) -> float | None:
        """The first sample after ``after`` with the base at rest, if any."""
        with self.lock:
            for at, linear, angular in self.samples:
                if at >= after and abs(linear) < 0.01 and abs(angular) < 0.02:
                    return at
        return None


@dataclass
class Robot:
    daemon: Daemon
    sim: Process
    odom: Odometry


@contextlib.asynccontextmanager
async def ros2_robot(tmp_path: Path) -> AsyncIterator[Robot]:
    """telebot-sim on a free port, the daemon driving it, and a probe on /odom."""
    daemon = Daemon(tmp_path)
    sim, router = start_telebot_sim(daemon)
    probe: Ros2Node | None = None
    try:
        daemon.start()
        library = TypeLibrary("jazzy")
        probe = Ros2Node(name="probe", connect=[router], library=library)
        odom = Odometry([], threading.Lock())

        def on_odom(msg: Any, _attachment: Any) -> None:
            twist = msg.twist.twist
            with odom.lock:
                odom.samples.append((time.monotonic(), twist.linear.x, twist.angular.z))

        probe.subscribe("odom", library.message("nav_msgs/msg/Odometry"), on_odom)
        yield Robot(daemon, sim, odom)
    finally:
        if probe is not None:
            probe.close()
        daemon.stop()
        sim.stop(graceful=True)


async def drive_then(robot: Robot, act: Callable[[], None]) -> float:
    """Arm, start a long goal, and once the base moves do ``act``; its time.monotonic()."""
    async with robot.daemon.connect() as user:
        assert (await user.arm()).ok
        replies = user.chat_replies("goto room-b", timeout=60)
        async for reply in replies:
            assert reply.text == "Goto command received"
            break
        await wait_until(robot.odom.moving, timeout=30)
        acted = time.monotonic()
        act()
        await replies.aclose()
    return acted


async def test_kill_9_of_the_daemon_mid_goal_stops_the_base_within_half_a_second(
    tmp_path: Path,
) -> None:
    async with ros2_robot(tmp_path) as robot:
        killed = await drive_then(robot, lambda: robot.daemon.events.signal(signal.SIGKILL))
        await wait_until(lambda: robot.odom.still_since(killed) is not None, timeout=10)
        stopped = robot.odom.still_since(killed)
        assert stopped is not None and stopped - killed <= 0.5 + SLACK
        assert robot.sim.popen.poll() is None  # the base lives on


async def test_a_frozen_daemon_is_dropped_by_its_lease_and_the_base_stops(
    tmp_path: Path,
) -> None:
    async with ros2_robot(tmp_path) as robot:
        frozen = await drive_then(robot, lambda: robot.daemon.events.signal(signal.SIGSTOP))
        try:
            await wait_until(lambda: robot.odom.still_since(frozen) is not None, timeout=15)
            stopped = robot.odom.still_since(frozen)
            # The daemon's link lease is 0.5 s (rmw_zenoh's default, 60 s, would keep going).
            assert stopped is not None and stopped - frozen <= 1.0 + SLACK
        finally:
            robot.daemon.events.signal(signal.SIGCONT)
