"""The robot's call recorder (``[recording]``): every call into rotating MCAP files.

A simulated robot with its safety supervisor on the memory transport records a call in
which the user chats, sends a goal and stops the robot; the files read back with the
``mcap`` package's reader (the same JSON-schema / JSON channels Foxglove reads). Rotation,
a failing disk and the daemon's ``[recording]`` table are tested on their own.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any, cast

import pytest
from mcap.reader import make_reader

from conftest import wait_until
from rig import FAST_SIM, GENEROUS_TIMEOUT, ROBOT, USER, Daemon, robot_on_hub
from telebot.channels.call import Call, UserEndpoint
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import CallSettings, ServiceSettings
from telebot.identity import Identity, KnownRobots
from telebot.services.client import RobotClient
from telebot.services.recording import Recorder
from telebot.services.robot import default_robot_services
from telebot.services.supervision import SafetyDriver


@contextlib.asynccontextmanager
async def recorded_robot(
    base: Path, recorder: Recorder, *, pose_hz: float = 10.0
) -> AsyncIterator[tuple[SafetyDriver, RobotClient]]:
    """A simulated robot whose calls ``recorder`` records, and a driver's client in a call."""
    services = default_robot_services()
    services.register("recording", recorder.service)
    hub = MemoryHub(seed=3)
    async with (
        robot_on_hub(
            base,
            hub,
            services,
            timeout=GENEROUS_TIMEOUT,
            sim=FAST_SIM,
            services=ServiceSettings(pose_hz=pose_hz),
        ) as (_, safety, _, _),
        MemoryTransport(hub, "user") as transport,
        UserEndpoint(
            transport,
            Identity.load(base / "user"),
            KnownRobots.load(base / "user"),
            settings=CallSettings(timeout=GENEROUS_TIMEOUT),
        ) as user_endpoint,
    ):
        safety.on_audit = recorder.audit
        call = await user_endpoint.call(ROBOT)
        client = RobotClient(call)
        try:
            yield safety, client
        finally:
            await call.hangup()
            # The robot's end of the call closes its services: the recorder hears the end.
            await wait_until(lambda: recorder._topics.keys() <= {"audit", "calls"})


def read(path: Path) -> tuple[Any, list[tuple[str, dict[str, Any], dict[str, str], int]]]:
    """The file's summary and its messages: (topic, decoded JSON, channel metadata, log time)."""
    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        messages = [
            (channel.topic, json.loads(message.data), dict(channel.metadata), message.log_time)
            for _, channel, message in reader.iter_messages(log_time_order=False)
        ]
    return summary, messages


def files(directory: Path) -> list[Path]:
    return sorted(directory.glob("calls-*.mcap"))


async def test_a_call_reads_back_with_chat_goal_stop_and_who_stopped(tmp_path: Path) -> None:
    recorder = Recorder(tmp_path / "rec")
    recorder.start()
    async with recorded_robot(tmp_path, recorder) as (_, client):
        assert (await client.arm()).ok
        replies = [reply.text async for reply in client.chat_replies("where")]
        assert replies
        update = await client.goto(2.0, 1.2, timeout=20)
        assert update.status == "succeeded", update
        await client.pose()  # a few poses and a telemetry went out meanwhile
        assert (await client.stop(how="button")).ok
    await asyncio.to_thread(recorder.close)

    [path] = files(tmp_path / "rec")
    summary, messages = read(path)
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == len(messages) == recorder.written
    assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
    assert {c.message_encoding for c in summary.channels.values()} == {"json"}
    for schema in summary.schemas.values():
        assert json.loads(schema.data)["type"] == "object"
    # Log times in file order never go back (one writer, one clock).
    times = [t for *_, t in messages]
    assert times == sorted(times)

    by_topic: dict[str, list[dict[str, Any]]] = {}
    for topic, data, metadata, _ in messages:
        by_topic.setdefault(topic, []).append(data)
        if topic.startswith(f"/{USER}/"):  # each call's channels say whose call it is
            assert metadata["peer"] == USER and metadata["role"] == "driver", metadata
    assert [e["event"] for e in by_topic["/calls"]] == ["start", "end"]
    assert by_topic["/calls"][0]["peer"] == USER
    assert len(by_topic[f"/{USER}/pose"]) >= 3
    assert by_topic[f"/{USER}/telemetry"]
    assert {"id", "text"} <= by_topic[f"/{USER}/chat/in"][0].keys()
    assert "where" in [m["text"] for m in by_topic[f"/{USER}/chat/in"]]
    assert {m["text"] for m in by_topic[f"/{USER}/chat"]} >= set(replies)
    goals_in = by_topic[f"/{USER}/goals/in"]
    assert any(m["type"] == "goal" and m["x"] == 2.0 for m in goals_in)
    assert any(m["status"] == "succeeded" for m in by_topic[f"/{USER}/goals"])
    assert by_topic[f"/{USER}/plan"]
    safety_in = by_topic[f"/{USER}/safety/in"]
    assert {"type": "stop", "how": "button"}.items() <= safety_in[-1].items()
    states = [m for m in by_topic[f"/{USER}/safety"] if m["type"] == "state"]
    assert states[-1]["armed"] is False and any(m["armed"] for m in states)  # armed, latched
    # The stop's audit record: who stopped the robot, how, and that it did.
    stops = [r for r in by_topic["/safety/audit"] if r["what"] == "stop"]
    assert stops and stops[-1]["who"] == USER and stops[-1]["how"] == "button"
    assert "rearm" in [r["what"] for r in by_topic["/safety/audit"]], by_topic["/safety/audit"]


async def test_files_rotate_by_size_and_only_the_newest_are_kept(tmp_path: Path) -> None:
    directory = tmp_path / "rec"
    directory.mkdir()
    (directory / "calls-000007.mcap").write_bytes(b"an old recording")  # numbering goes on
    recorder = Recorder(directory, max_bytes=4096, keep=3)
    recorder.start()
    async with recorded_robot(tmp_path, recorder, pose_hz=100) as _:
        await wait_until(lambda: recorder.files_done >= 4, timeout=30)
    await asyncio.to_thread(recorder.close)

    kept = files(directory)
    assert len(kept) == 3
    numbers = [int(p.stem.split("-")[1]) for p in kept]
    assert numbers == list(range(numbers[0], numbers[0] + 3)) and numbers[0] > 8
    for path in kept:  # every one a finished MCAP with its summary, not too far past the size
        summary, messages = read(path)
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == len(messages) > 0
        assert path.stat().st_size < 3 * 4096
    # The full ones are the call's poses (the last may hold only its end).
    for path in kept[:-1]:
        assert f"/{USER}/pose" in {topic for topic, *_ in read(path)[1]}


async def test_an_unwritable_directory_logs_one_line_and_the_call_goes_on(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("a file where the folder should be")
    recorder = Recorder(blocker / "rec")
    recorder.start()
    with caplog.at_level(logging.ERROR, logger="telebot.recording"):
        async with recorded_robot(tmp_path, recorder) as (_, client):
            await wait_until(lambda: not recorder.enabled)
            assert (await client.arm()).ok
            replies = [reply.text async for reply in client.chat_replies("where")]
            assert replies
            assert (await client.stop(how="key")).ok
    await asyncio.to_thread(recorder.close)
    lines = [r for r in caplog.records if r.name == "telebot.recording"]
    assert len(lines) == 1, [r.getMessage() for r in lines]
    assert "recording off" in lines[0].getMessage() and "not-a-dir" in lines[0].getMessage()


async def test_the_daemon_records_beside_the_audit_log(tmp_path: Path) -> None:
    daemon = Daemon(tmp_path, observer=None)
    with daemon.robot_config.open("a") as config:
        config.write("[recording]\nenabled = true\n")
    daemon.start()
    try:
        async with daemon.connect() as client:
            replies = [reply.text async for reply in client.chat_replies("where")]
            assert replies
            await client.pose()
    finally:
        daemon.stop(graceful=True)  # SIGTERM: the recorder finishes its file
    [path] = files(daemon.robot_home)
    assert (daemon.robot_home / "audit.jsonl").exists()
    _, messages = read(path)
    topics = {topic for topic, *_ in messages}
    assert {"/calls", f"/{USER}/chat/in", f"/{USER}/chat", f"/{USER}/pose"} <= topics, topics
    assert [m["event"] for topic, m, *_ in messages if topic == "/calls"] == ["start", "end"]


class _FakeCall:
    """What a RecordingService reads of a call."""

    id = "c0ffee"
    peer = USER
    role = None
    end = None
    tap: Any = None


def test_only_the_configured_streams_are_kept_and_user_garbage_is_not(tmp_path: Path) -> None:
    with Recorder(tmp_path, streams=["chat"]) as recorder:
        call = _FakeCall()
        service = recorder.service(None, cast(Call, call))
        assert call.tap is not None
        call.tap("chat", False, '{"id": 1, "text": "where"}')
        call.tap("chat", False, "not json")  # what the services drop, the recording drops
        call.tap("chat", False, b"[1, 2]")
        call.tap("chat", True, '{"id": 1, "seq": 0, "text": "at (1, 1)", "final": true}')
        call.tap("pose", True, '{"t": 0, "x": 1}')  # not a recorded stream
        service.close()
        assert call.tap is None
    [path] = files(tmp_path)
    _, messages = read(path)
    assert [(topic, data.get("text", data.get("event"))) for topic, data, *_ in messages] == [
        ("/calls", "start"),
        (f"/{USER}/chat/in", "where"),
        (f"/{USER}/chat", "at (1, 1)"),
        ("/calls", "end"),
    ]
