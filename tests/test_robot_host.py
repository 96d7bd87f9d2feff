"""The robot host and its per-robot services: each service reads its own section of the
config, and the drive service (follow-me and driving by hand) keeps the robot fail safe."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from conftest import wait_until
from rig import robot_drive
from telebot.config import DriveSettings, FollowSettings, PeopleSettings, RelaySettings
from telebot.identity import Role
from telebot.robot.nav import GoalStatus
from telebot.robot.perception.tracks import PersonTrack
from telebot.services.base import MotionService, ServiceConfig
from telebot.services.drive.follow import FollowGoal
from telebot.services.people.robot import RobotPeople
from telebot.services.robot import RobotServer
from telebot.services.safety.robot import SafetyDriver
from test_supervision import FakeCall, room


def test_a_section_not_given_is_its_defaults_and_a_wrong_one_is_named() -> None:
    config = ServiceConfig(drive=DriveSettings(stale_after=0.7))
    assert config.get("drive", DriveSettings).stale_after == 0.7
    assert config.get("follow", FollowSettings) == FollowSettings()
    with pytest.raises(TypeError, match=r"\[drive\] is a DriveSettings"):
        config.get("drive", RelaySettings)


async def test_each_service_reads_its_own_section_of_the_robots_config() -> None:
    server = RobotServer(
        room(),
        config=ServiceConfig(
            drive=DriveSettings(stale_after=0.7),
            follow=FollowSettings(distance=2.0),
            people=PeopleSettings(camera_hz=0.0),
        ),
    )
    try:
        drive = robot_drive(server)
        assert isinstance(drive, MotionService)
        assert drive.drive.settings.stale_after == 0.7
        assert drive.follow.settings.distance == 2.0
        people = server.service("people")
        assert isinstance(people, RobotPeople)
        assert people.perception.settings.camera_hz == 0.0
        assert drive.follow.people is people  # follow-me follows the people service's tracks
    finally:
        server.hosted.close()


@pytest.mark.parametrize("part", ["follow", "drive"])
async def test_a_failing_drive_tick_stops_the_robot_and_latches(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, part: str
) -> None:
    nav = room()
    # A deadman far longer than the test: the only stop here is the one the failure makes.
    safety = SafetyDriver(nav, timeout=60.0, max_speed=0.5, audit_path=tmp_path / "audit.jsonl")
    safety.join(FakeCall("c1", "alice", Role.DRIVER))  # type: ignore[arg-type]
    safety.tick()
    assert safety.gate("c1").rearm() is None
    server = RobotServer(nav, safety=safety)
    drive = robot_drive(server)

    def broken(now: float) -> None:
        raise RuntimeError("simulated fault")

    monkeypatch.setattr(getattr(drive, part), "tick", broken)
    assert safety.gate("c1").motion("fwd 5") is None
    nav.forward(5.0)
    runner = asyncio.create_task(server.run())
    try:
        what = "follow-me failed" if part == "follow" else "driving by hand failed"
        await wait_until(lambda: what in safety.state().text)
        assert not safety.state().armed
        await wait_until(lambda: nav.velocity().linear == 0.0)
    finally:
        runner.cancel()
        await asyncio.gather(runner, return_exceptions=True)
        safety.close()


async def test_an_emergency_stop_ends_a_follow_first_even_without_a_supervisor() -> None:
    nav = room()  # the robot at (3, 5) facing east
    server = RobotServer(nav)  # no supervisor: nothing latches, the drive service must halt
    try:
        follow = robot_drive(server).follow

        class People:
            def tracks(self) -> list[PersonTrack]:
                return [PersonTrack(1, 4.5, 5.0, 0.0, 0.0, 1.0, 0.0, 0.0, frozenset({"laser"}))]

        follow.people = People()
        started = follow.start("c1", None, server.now())
        assert isinstance(started, FollowGoal) and follow.goal is started
        server.emergency_stop("simulated fault")
        assert follow.goal is None and started.status is GoalStatus.CANCELLED
        follow.tick(server.now())  # nothing left to drive
        assert nav.velocity().linear == 0.0
    finally:
        server.hosted.close()
