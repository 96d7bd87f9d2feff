"""The safety supervisor's driver: NavStack actions, the watchdog thread, chat gating, audit."""

from __future__ import annotations

import asyncio
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from conftest import ROBOT, Homes, memory_endpoints
from telebot.channels.proto.session import CallStats
from telebot.channels.transports.memory import MemoryHub
from telebot.config import SimSettings
from telebot.identity import Role
from telebot.reasons import Reason
from telebot.robot.grid import OccupancyGrid
from telebot.robot.nav import Pose2D
from telebot.robot.sim.stack import SimNavStack
from telebot.services.chat.robot import ChatSession
from telebot.services.chat.wire import ChatReply
from telebot.services.safety.robot import SafetyDriver


@dataclass
class FakeCall:
    """What the driver reads of a call: id, peer, role, last sign of life, link stats."""

    id: str
    peer: str
    role: Role
    last_heard: float = field(default_factory=time.monotonic)
    stats: CallStats = field(default_factory=lambda: CallStats(rtt=0.002))
    end: None = None


def room() -> SimNavStack:
    data = np.full((200, 240), -1, dtype=np.int8)
    data[10:-10, 10:-10] = 100
    data[14:-14, 14:-14] = 0
    grid = OccupancyGrid(data, 0.05, 0.0, 0.0)
    return SimNavStack(grid, {}, SimSettings(), start=Pose2D(3.0, 5.0, 0.0), now=time.monotonic())


def drive_for(nav: SimNavStack, seconds: float, driver: SafetyDriver, call: FakeCall) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        call.last_heard = time.monotonic()
        nav.step(time.monotonic())
        driver.tick()
        time.sleep(0.02)


def armed_driver(tmp_path: Path) -> tuple[SimNavStack, SafetyDriver, FakeCall]:
    nav = room()
    driver = SafetyDriver(nav, timeout=0.5, max_speed=0.5, audit_path=tmp_path / "audit.jsonl")
    alice = FakeCall("c1", "alice", Role.DRIVER)
    driver.join(alice)  # type: ignore[arg-type]
    driver.tick()
    assert driver.gate("c1").rearm() is None
    return nav, driver, alice


def test_the_robot_starts_stopped_with_a_zero_speed_cap(tmp_path: Path) -> None:
    nav = room()
    driver = SafetyDriver(nav, timeout=0.5, max_speed=0.5)
    assert nav.speed_limit == 0.0
    assert not driver.state().armed
    driver.close()


def test_the_watchdog_thread_stops_the_robot_while_the_event_loop_is_stuck(
    tmp_path: Path,
) -> None:
    nav, driver, alice = armed_driver(tmp_path)
    with driver:
        assert driver.gate("c1").motion("fwd 5") is None
        nav.forward(5.0)
        drive_for(nav, 1.0, driver, alice)
        assert nav.velocity().linear > 0.3
        # The driver goes silent and this "loop" is stuck: no tick, no step. Only the
        # watchdog thread can notice.
        deadline = time.monotonic() + 5.0
        while driver.watchdog_stops == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert driver.watchdog_stops == 1
        nav.step(time.monotonic())  # the loop comes back: the stop is acted on first
        assert nav.velocity().linear == 0.0
        assert nav.emergency_stops == 1
        driver.tick()
        assert not driver.state().armed
        assert "silent" in driver.state().text or "lost" in driver.state().text


def test_the_watchdog_leaves_a_live_driver_alone(tmp_path: Path) -> None:
    nav, driver, alice = armed_driver(tmp_path)
    with driver:
        driver.gate("c1").motion("fwd 5")
        nav.forward(5.0)
        drive_for(nav, 1.0, driver, alice)
        assert driver.watchdog_stops == 0
        assert nav.velocity().linear > 0.3


def test_chat_motion_needs_an_armed_robot_and_stop_latches(tmp_path: Path) -> None:
    nav = room()
    driver = SafetyDriver(nav, timeout=0.5, max_speed=0.5, audit_path=tmp_path / "audit.jsonl")
    alice = FakeCall("c1", "alice", Role.DRIVER)
    driver.join(alice)  # type: ignore[arg-type]
    driver.tick()
    replies: list[ChatReply] = []
    chat = ChatSession(nav, role=Role.DRIVER, send=replies.append, gate=driver.gate("c1"))

    def say(text: str) -> str:
        replies.clear()
        chat.handle_text(len(replies) + 1, text)
        return replies[-1].code

    assert say("fwd 1") == Reason.NOT_ARMED
    assert nav.current_goal() is None
    assert say("arm") == Reason.OK
    assert say("fwd 3") == Reason.ACCEPTED
    drive_for(nav, 0.5, driver, alice)
    assert nav.velocity().linear > 0.1
    assert say("stop") == Reason.OK
    assert nav.velocity().linear == 0.0
    assert not driver.state().armed
    assert say("fwd 1") == Reason.NOT_ARMED
    assert say("release") == Reason.OK
    assert say("arm") == Reason.NOT_HOLDER
    assert say("take") == Reason.OK
    driver.close()
    lines = [json.loads(line) for line in (tmp_path / "audit.jsonl").read_text().splitlines()]
    whats = [(line["what"], line["outcome"]) for line in lines]
    assert ("stop", "allowed") in whats
    assert [line["how"] for line in lines if line["what"] == "stop"] == ["chat"]
    assert ("rearm", "allowed") in whats
    assert any(what == "rearm" and outcome == "refused" for what, outcome in whats)
    assert all(line["t"] > 0 for line in lines)
    assert {line["who"] for line in lines} >= {"alice", "robot"}


def test_an_observer_may_stop_but_not_drive_or_arm(tmp_path: Path) -> None:
    nav, driver, _ = armed_driver(tmp_path)
    olga = FakeCall("c2", "olga", Role.OBSERVER)
    driver.join(olga)  # type: ignore[arg-type]
    replies: list[ChatReply] = []
    chat = ChatSession(nav, role=Role.OBSERVER, send=replies.append, gate=driver.gate("c2"))
    chat.handle_text(1, "fwd 1")
    assert replies[-1].code == Reason.OBSERVER
    assert replies[-1].text == "refused: olga is an observer: observers may not drive"
    refusals = [
        json.loads(line)
        for line in (tmp_path / "audit.jsonl").read_text().splitlines()
        if '"olga"' in line and '"refused"' in line
    ]
    assert [r["what"] for r in refusals] == ["motion: fwd 1"]  # refusals are audited too
    assert driver.gate("c2").rearm() is not None
    assert driver.state().armed
    chat.handle_text(2, "stop")
    assert replies[-1].text == "stopped"
    assert not driver.state().armed
    driver.close()


def test_chat_status_says_the_robot_is_latched_and_who_stopped_it(tmp_path: Path) -> None:
    nav, driver, _ = armed_driver(tmp_path)
    driver.join(FakeCall("c2", "olga", Role.OBSERVER))  # type: ignore[arg-type]
    replies: list[ChatReply] = []
    alice = ChatSession(nav, role=Role.DRIVER, send=replies.append, gate=driver.gate("c1"))
    olga = ChatSession(nav, role=Role.OBSERVER, send=replies.append, gate=driver.gate("c2"))

    def status() -> str:
        alice.handle_text(len(replies) + 1, "status")
        return replies[-1].text

    assert status() == "idle"  # armed, standing still
    olga.handle_text(100, "stop")
    assert status() == "stopped (latched: re-arm with arm): stop requested by olga (chat)"
    alice.handle_text(101, "arm")
    assert status() == "idle"
    driver.close()


def test_the_holder_leaving_stops_and_latches(tmp_path: Path) -> None:
    nav, driver, alice = armed_driver(tmp_path)
    driver.gate("c1").motion("fwd 5")
    nav.forward(5.0)
    drive_for(nav, 0.6, driver, alice)
    assert nav.velocity().linear > 0.1
    driver.leave(alice)  # type: ignore[arg-type]
    assert nav.velocity().linear == 0.0
    assert not driver.state().armed and driver.state().holder is None
    driver.close()


def test_usercam_is_refused_as_soon_as_a_goal_runs_even_before_the_base_moves(
    tmp_path: Path,
) -> None:
    nav, driver, _ = armed_driver(tmp_path)
    gate = driver.gate("c1")
    assert gate.motion("fwd 2") is None
    nav.forward(2.0)
    assert nav.velocity().linear == 0.0  # accepted, not yet moving
    refusal = gate.camera("usercam")
    assert refusal is not None and refusal.code == Reason.CAMERA_WHILE_MOVING
    nav.stop()
    assert gate.camera("usercam") is None
    driver.close()


async def test_a_failed_robot_step_stops_and_latches(tmp_path: Path) -> None:
    import asyncio

    from telebot.services.robot import RobotServer

    nav, driver, alice = armed_driver(tmp_path)
    driver.gate("c1").motion("fwd 5")
    nav.forward(5.0)
    drive_for(nav, 0.5, driver, alice)

    def broken(now: float) -> None:
        raise RuntimeError("simulated fault")

    nav.step = broken  # type: ignore[method-assign]
    server = RobotServer(nav, safety=driver)
    runner = asyncio.create_task(server.run())
    await asyncio.sleep(0.15)
    runner.cancel()
    await asyncio.gather(runner, return_exceptions=True)
    assert nav.velocity().linear == 0.0
    assert not driver.state().armed and "step failed" in driver.state().text
    driver.close()


async def test_a_call_whose_services_fail_is_hung_up_and_leaves_the_supervisor(
    tmp_path: Path, homes: Homes, monkeypatch: pytest.MonkeyPatch
) -> None:
    from telebot.services import robot

    def broken(*args: object) -> None:
        raise RuntimeError("simulated set-up fault")

    monkeypatch.setattr(robot, "CallServices", broken)
    nav = room()
    driver = SafetyDriver(nav, timeout=0.5, max_speed=0.5)
    server = robot.RobotServer(nav, safety=driver)
    hub = MemoryHub(seed=1)
    async with memory_endpoints(homes, hub) as (robot_endpoint, user_endpoint):
        server.attach(robot_endpoint)
        call = await user_endpoint.call(ROBOT)
        end = await asyncio.wait_for(call.wait_ended(), 5)
        assert end.kind == "hung_up" and end.by_peer and "could not be served" in end.detail
        await asyncio.sleep(0)  # one more turn, in case the server's end watcher has not run yet
        # No ghost: the call is gone from the endpoint and from the supervisor.
        assert robot_endpoint.calls == []
        assert driver.supervisor.participants() == () and driver.state().holder is None
    driver.close()


def open_paths() -> set[str]:
    """The files this process has open now."""
    fds = Path("/proc/self/fd")
    paths = set()
    for fd in fds.iterdir():
        try:
            paths.add(os.readlink(fd))
        except OSError:  # closed while listing
            continue
    return paths


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="lists open files through /proc")
async def test_a_robot_that_fails_to_start_closes_its_audit_log(
    tmp_path: Path, homes: Homes, monkeypatch: pytest.MonkeyPatch
) -> None:
    from telebot.apps import robot_daemon
    from telebot.config import RobotConfig

    async def broken(self: object) -> None:
        raise RuntimeError("simulated start-up fault")

    monkeypatch.setattr(robot_daemon.RobotServer, "prepare", broken)
    audit = tmp_path / "audit.jsonl"
    with pytest.raises(RuntimeError, match="start-up fault"):
        await robot_daemon.serve_robot(RobotConfig(), homes.robot, homes.contacts, home=tmp_path)
    assert audit.exists()  # it was opened (the start-up stop is audited) ...
    assert str(audit) not in open_paths()  # ... and closed again


def armed_at_100() -> tuple[list[float], SafetyDriver, FakeCall]:
    """A driver on a settable clock (``clock[0]``), alice armed at 100.0, heard then."""
    clock = [100.0]
    driver = SafetyDriver(room(), timeout=0.5, max_speed=0.5, clock=lambda: clock[0])
    alice = FakeCall("c1", "alice", Role.DRIVER, last_heard=100.0)
    driver.join(alice)  # type: ignore[arg-type]
    driver.tick()
    assert driver.gate("c1").rearm() is None and driver.state().armed
    return clock, driver, alice


def test_a_re_arm_whose_own_frame_brings_the_deadman_due_is_refused_and_the_stop_latches() -> None:
    # Armed, no control step since; the driver's `arm` (a page repeats it until it is
    # answered) arrives after a silence: taking its frame as a sign of life first finds the
    # deadman due and stops the robot. The request was sent before its driver knew of the
    # stop: refused, and the stop latches until the next `arm`.
    clock, driver, alice = armed_at_100()
    clock[0] = alice.last_heard = 101.0  # no tick in between
    refusal = driver.gate("c1").rearm()
    assert refusal is not None and refusal.code == Reason.LINK_SILENT, refusal
    assert refusal.text.startswith("the robot has just stopped: driver alice's link lost")
    assert not driver.state().armed and driver.state().code == Reason.LINK_SILENT
    clock[0] = alice.last_heard = 101.1
    assert driver.gate("c1").rearm() is None and driver.state().armed
    driver.close()


def test_a_re_arm_right_after_the_link_came_back_is_not_refused_on_a_stale_view() -> None:
    # The deadman stopped the robot; the driver's link is back (its arm request is itself a
    # sign of life) before the next control step has looked: one `arm` must do.
    clock, driver, alice = armed_at_100()
    clock[0] = 101.0
    driver.tick()
    state = driver.state()
    assert not state.armed and state.code == Reason.LINK_SILENT
    alice.last_heard = 101.0  # no tick in between
    assert driver.gate("c1").rearm() is None
    assert driver.state().armed
    driver.close()
