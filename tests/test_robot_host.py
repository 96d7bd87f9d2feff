"""The robot host and its per-robot services: each service reads its own section of the
config, and the drive service (follow-me and driving by hand) keeps the robot fail safe."""

from __future__ import annotations

import asyncio
import wave
from pathlib import Path

import numpy as np
import pytest

from conftest import wait_until
from rig import robot_drive
from telebot.config import (
    DriveSettings,
    FollowSettings,
    MediaConfig,
    PeopleSettings,
    RelaySettings,
    VideoConfig,
)
from telebot.identity import Role
from telebot.robot.nav import GoalStatus
from telebot.robot.perception.tracks import PersonTrack
from telebot.services.base import MotionService, ServiceConfig
from telebot.services.drive.follow import FollowGoal
from telebot.services.media.audio import ToneSource, WavSink
from telebot.services.media.robot import RobotMedia
from telebot.services.media.wire import CODEC_H264, CODEC_JPEG, CODEC_VP8
from telebot.services.people.robot import RobotPeople
from telebot.services.registry import robot_services
from telebot.services.robot import RobotServer, robot_video_settings
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


async def test_media_is_a_robot_service_its_section_sets_up_and_the_robot_closes(
    tmp_path: Path,
) -> None:
    assert robot_services().names().index("media") < robot_services().names().index("drive")
    heard = tmp_path / "heard.wav"
    server = RobotServer(
        room(),
        config=ServiceConfig(
            media=MediaConfig(mic="tone:1000", speaker=f"wav:{heard}", voice="off")
        ),
    )
    media = server.service("media")  # registered like the others: no install step
    assert isinstance(media, RobotMedia)
    assert isinstance(media.mic.base, ToneSource) and media.mic.base.frequency == 1000
    assert isinstance(media.speaker, WavSink) and media.voice is None
    assert media._on_chat_reply in server.chat_listeners  # started: it hears chat replies
    media.speaker.write(np.zeros(960, dtype=np.int16))
    runner = asyncio.create_task(server.run(), name="robot-loop")
    await asyncio.sleep(0)  # the loop's first cycle: its end closes the services
    runner.cancel()
    await asyncio.gather(runner, return_exceptions=True)
    with wave.open(str(heard), "rb") as wav:  # closed with the robot: the WAV is finished
        assert wav.getnframes() == 960


def test_the_robots_video_takes_its_codec_settings_from_the_media_section() -> None:
    video = robot_video_settings(
        VideoConfig(width=320, quality=40),
        MediaConfig(codec="vp8", min_bitrate=100_000, max_bitrate=900_000),
        simulated=True,
    )
    assert (video.width, video.quality, video.min_quality) == (320, 40, 30)
    assert video.codecs == (CODEC_VP8, CODEC_H264, CODEC_JPEG)  # JPEG always last
    assert (video.min_bitrate, video.max_bitrate, video.keyframe_interval) == (
        100_000,
        900_000,
        3.0,
    )
    assert video.stamp  # a simulated robot stamps its frames unless [media] says
    assert not robot_video_settings(VideoConfig(), MediaConfig(), simulated=False).stamp
    assert not robot_video_settings(VideoConfig(), MediaConfig(stamp=False), simulated=True).stamp
    jpeg = robot_video_settings(VideoConfig(), MediaConfig(codec="jpeg"), simulated=False)
    assert jpeg.codecs == (CODEC_JPEG, CODEC_H264, CODEC_VP8)


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
