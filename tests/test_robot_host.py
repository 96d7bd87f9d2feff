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
from telebot.services.base import MotionService, ServiceConfig
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
