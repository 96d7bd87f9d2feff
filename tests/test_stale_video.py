"""No driving blind, end to end in one process: a driver whose picture freezes gets the robot
stopped (the supervisor's rule itself is tested with plain numbers in test_safety.py)."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncGenerator
from pathlib import Path

import pytest

from conftest import wait_until
from rig import GENEROUS_TIMEOUT, ROBOT, SLACK, robot_on_hub, user_on_hub
from telebot.apps.user_client import _say_self_stops
from telebot.channels.channel import ReceivedDatagram
from telebot.channels.transports.memory import MemoryHub
from telebot.config import RobotConfig, SafetySettings, load_toml
from telebot.errors import ConfigError
from telebot.reasons import Reason
from telebot.robot.nav import Velocity
from telebot.services.chat.wire import ChatReply
from telebot.services.client import RobotClient
from telebot.services.video.receiver import VideoFeedService
from telebot.services.video.wire import CompleteFrame, VideoSettings

#: The product's stale-video lockout (rigs default to a generous one).
PRODUCT_STALE_VIDEO = SafetySettings().stale_video


async def first_reply(client: RobotClient, command: str) -> ChatReply:
    """The first reply to ``command`` (a motion's acknowledgement); the motion runs on."""
    replies = client.chat_replies(command)
    assert isinstance(replies, AsyncGenerator)  # closed here, not left to the GC
    async with contextlib.aclosing(replies):
        return await anext(replies)


async def test_a_driver_whose_video_freezes_while_driving_gets_the_robot_stopped(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # The user's video receiver stops taking fragments (the bulk lane lost them, the
    # decoder hung): its reports keep coming, but their frames counter no longer grows.
    frozen = False
    take = VideoFeedService._on_datagram

    def on_datagram(self: VideoFeedService, datagram: ReceivedDatagram) -> None:
        if not frozen:
            take(self, datagram)

    monkeypatch.setattr(VideoFeedService, "_on_datagram", on_datagram)
    hub = MemoryHub(seed=7)
    # Small pictures, so a loaded machine cannot freeze the video by itself; a generous
    # call timeout (and deadman), so a preempted test process does not stop it either.
    video = VideoSettings(width=160, height=120, max_fps=15.0)
    async with (
        robot_on_hub(
            tmp_path, hub, timeout=GENEROUS_TIMEOUT, video=video, stale_video=PRODUCT_STALE_VIDEO
        ) as (nav, safety, _, _),
        user_on_hub(tmp_path, hub) as user,
    ):
        assert safety.supervisor.stale_video == 1.0  # the product's default
        call = await user.call(ROBOT)
        client = RobotClient(call)
        _say_self_stops(client)  # what the terminal chat says (telebot-user chat)
        shown: list[CompleteFrame] = []
        unsubscribe = client.video_feed.subscribe(shown.append)
        try:
            await wait_until(lambda: len(shown) >= 3)
            assert (await client.arm(timeout=30)).ok
            reply = await first_reply(client, "fwd 4")
            assert reply.ok and not reply.final, reply.text
            await wait_until(lambda: nav.velocity().linear > 0.2)
            assert safety.state().armed  # fresh pictures: driving on
            frozen = True
            await wait_until(lambda: not safety.state().armed)
            state = safety.state()
            assert state.code == Reason.VIDEO_STALE, state.text
            assert state.text == "video frozen for 1.0 s: the robot stopped itself"
            await wait_until(lambda: nav.velocity() == Velocity())
            # The driver hears why, with the code a page or a program offers the re-arm on.
            await wait_until(
                lambda: (s := client.latest_safety.value) is not None and s.code == "video_stale"
            )
            latest = client.latest_safety.value
            assert latest is not None and latest.stopped_itself
            said = capsys.readouterr().err.splitlines()
            hint = "[the robot stopped itself: video frozen for 1.0 s. Type 'arm' to drive on.]"
            assert said.count(hint) == 1, said
            # Pictures again (the robot hears of them with the next report, at most 0.2 s
            # later): one re-arm and the driver may move on.
            frozen = False
            holder = safety.supervisor.participant(call.id)
            assert holder is not None
            stale_at = holder.video_fresh

            def fresh_again() -> bool:
                p = safety.supervisor.participant(call.id)
                return p is not None and p.video_fresh > stale_at

            await wait_until(fresh_again, timeout=20 + SLACK)
            assert (await client.arm(timeout=30)).ok
            await wait_until(lambda: safety.state().cap > 0, timeout=20 + SLACK)
            reply = await first_reply(client, "fwd 1")
            assert reply.ok, reply.text
        finally:
            unsubscribe()
            await call.hangup()


@pytest.mark.parametrize(
    ("value", "words"),
    [("-1", "greater than or equal to 0"), ("'soon'", "number"), ("nan", "")],
)
def test_a_bad_stale_video_setting_is_one_line_naming_the_key(
    tmp_path: Path, value: str, words: str
) -> None:
    path = tmp_path / "robot.toml"
    path.write_text(f"[safety]\nstale_video = {value}\n")
    with pytest.raises(ConfigError) as error:
        load_toml(path, RobotConfig)
    text = str(error.value)
    assert "safety.stale_video" in text and words in text and "\n" not in text, text
    path.write_text("[safety]\nstale_video = 0\n")  # 0 turns the rule off: valid
    assert load_toml(path, RobotConfig).safety.stale_video == 0.0
