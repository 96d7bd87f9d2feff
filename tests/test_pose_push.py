"""A robot whose poses arrive by themselves (PoseNotifier) has each sent at once, pose_hz the cap."""

from __future__ import annotations

import asyncio
import math
import threading
from collections.abc import Callable
from types import SimpleNamespace

from conftest import wait_until
from telebot.config import RobotConfig, ServiceSettings
from telebot.robot import create_robot
from telebot.robot.nav import PoseNotifier
from telebot.robot.sim.stack import SimNavStack
from telebot.services.robot import QUIET_POSE_EVERY, CallServices, RobotServer


class NotifyingRobot:
    """A simulated robot that also tells its listeners when a pose arrives (as ROS 2 does)."""

    def __init__(self) -> None:
        config = RobotConfig.model_validate({"sim": {"map": "small"}})
        self.sim = create_robot(config)
        assert isinstance(self.sim, SimNavStack)
        self.listeners: list[Callable[[], None]] = []

    def add_pose_listener(self, listener: Callable[[], None]) -> None:
        self.listeners.append(listener)

    def __getattr__(self, name: str) -> object:
        return getattr(self.sim, name)


class RecordingServices:
    """Stands in for a call's services: records when its pose was offered."""

    def __init__(self) -> None:
        self.offered: list[float] = []

    def pose_due(self, now: float, *, fresh: bool = False) -> None:
        if fresh:
            self.offered.append(now)


async def test_a_new_pose_from_another_thread_is_offered_to_every_call_at_once() -> None:
    robot = NotifyingRobot()
    assert isinstance(robot, PoseNotifier)
    server = RobotServer(robot, ServiceSettings(pose_hz=10))  # type: ignore[arg-type]
    assert robot.listeners == [server._pose_arrived]
    calls = [RecordingServices(), RecordingServices()]
    server.services.update({"a": calls[0], "b": calls[1]})  # type: ignore[dict-item]

    thread = threading.Thread(target=robot.listeners[0])
    thread.start()
    thread.join()
    await wait_until(lambda: all(call.offered for call in calls))
    assert [len(call.offered) for call in calls] == [1, 1]

    # Many poses before the loop runs wake it once (coalesced), not once each.
    for _ in range(50):
        robot.listeners[0]()
    await wait_until(lambda: len(calls[0].offered) == 2)
    assert [len(call.offered) for call in calls] == [2, 2]


async def test_a_robot_without_pose_notices_is_not_asked_for_them() -> None:
    config = RobotConfig.model_validate({"sim": {"map": "small"}})
    sim = create_robot(config)
    assert not isinstance(sim, PoseNotifier)
    RobotServer(sim)  # no add_pose_listener needed


async def test_fresh_poses_keep_to_pose_hz_and_the_newest_is_sent_when_the_rate_allows() -> None:
    loop = asyncio.get_running_loop()
    sent: list[float] = []
    services = object.__new__(CallServices)  # only its pose pacing is under test
    services.server = SimpleNamespace(  # type: ignore[assignment]
        settings=ServiceSettings(pose_hz=10),
        poses_pushed=True,
        now=loop.time,
        _guarded=lambda action, *args: action(*args),
    )
    services._last_pose = services._next_pose = -math.inf
    services._pose_timer = None
    services.publish_pose = lambda: sent.append(loop.time())  # type: ignore[method-assign]

    start = loop.time()
    services.pose_due(start, fresh=True)
    assert len(sent) == 1  # the first goes at once
    services.pose_due(start + 0.01, fresh=True)
    services.pose_due(start + 0.02, fresh=True)
    assert len(sent) == 1  # within 1/pose_hz: deferred, once
    await wait_until(lambda: len(sent) == 2)
    assert sent[1] - sent[0] >= 0.1 - 1e-3
    # The control loop's ticks do not spend the rate while poses come by themselves...
    services.pose_due(sent[1] + 0.15)
    assert len(sent) == 2
    # ...but keep the stream alive when they stop.
    services.pose_due(sent[1] + QUIET_POSE_EVERY)
    assert len(sent) == 3
