"""The robot's call recorder (``[recording]``): every call into MCAP files.

A simulated robot with its safety supervisor on the memory transport records a call in
which the user chats, sends a goal and stops the robot; the files read back with the
``mcap`` package's reader (the same JSON-schema / JSON channels Foxglove reads). Files
finished at a call's end and by age (readable while the robot runs), one channel per topic
over several calls, rotation, a failing disk and the daemon's ``[recording]`` table are
tested on their own.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections import Counter
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any, cast

import pytest
from mcap.exceptions import McapError
from mcap.reader import make_reader

from conftest import wait_until
from rig import FAST_SIM, GENEROUS_TIMEOUT, ROBOT, USER, Daemon, robot_on_hub
from telebot.channels.call import Call, UserEndpoint
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import CallSettings, ServiceSettings
from telebot.identity import Identity, KnownRobots
from telebot.services.client import RobotClient
from telebot.services.recording import Recorder
from telebot.services.registry import robot_services
from telebot.services.safety.robot import SafetyDriver


@contextlib.asynccontextmanager
async def recorded_robot(
    base: Path, recorder: Recorder, *, pose_hz: float = 10.0
) -> AsyncIterator[tuple[SafetyDriver, RobotClient, UserEndpoint]]:
    """A simulated robot whose calls ``recorder`` records, and a driver's client in a call
    (and the driver's endpoint, for more calls)."""
    services = robot_services()
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
            yield safety, client, user_endpoint
        finally:
            await call.hangup()
            # The robot's end of the call closes its services: the recorder hears the end.
            await wait_until(lambda: recorder.calls == 0)


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


def finished(directory: Path) -> dict[Path, list[tuple[str, dict[str, Any]]]]:
    """The files an ``mcap`` reader accepts now (finished), with their (topic, JSON) messages."""
    found = {}
    for path in files(directory):
        try:
            summary, messages = read(path)
        except McapError:  # being written: no summary and footer yet
            continue
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == len(messages)
        found[path] = [(topic, data) for topic, data, *_ in messages]
    return found


async def test_a_call_reads_back_with_chat_goal_stop_and_who_stopped(tmp_path: Path) -> None:
    recorder = Recorder(tmp_path / "rec")
    recorder.start()
    async with recorded_robot(tmp_path, recorder) as (_, client, _):
        assert (await client.arm()).ok
        replies = [reply.text async for reply in client.chat_replies("where")]
        assert replies
        update = await client.goto(2.0, 1.2, timeout=20)
        assert update.status == "succeeded", update
        await client.pose()  # a few poses and a telemetry went out meanwhile
        assert (await client.stop(how="button")).ok
    await asyncio.to_thread(recorder.close)

    # The call's file, finished at its end (a stop's audit record after it may begin another).
    path = files(tmp_path / "rec")[0]
    summary, messages = read(path)
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == len(messages)
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
        if topic.startswith(f"/{USER}/"):  # each user's channels say whose they are
            direction = "in" if topic.endswith("/in") else "out"
            assert metadata == {
                "peer": USER,
                "stream": topic.split("/")[2],
                "direction": direction,
            }, metadata
    assert [e["event"] for e in by_topic["/calls"]] == ["start", "end"]
    assert by_topic["/calls"][0]["peer"] == USER and by_topic["/calls"][0]["role"] == "driver"
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


async def test_each_call_end_finishes_the_file_with_one_channel_per_topic(tmp_path: Path) -> None:
    directory = tmp_path / "rec"
    recorder = Recorder(directory)
    recorder.start()
    async with (
        recorded_robot(tmp_path, recorder) as (_, first, endpoint),
        # The same user's second client (another program): its call is a second call beside
        # the first (a call again from the same client would replace the first).
        UserEndpoint(
            endpoint.transport,
            Identity.load(tmp_path / "user"),
            KnownRobots.load(tmp_path / "user"),
            settings=CallSettings(timeout=GENEROUS_TIMEOUT),
        ) as other_client,
    ):
        second = RobotClient(await other_client.call(ROBOT))
        assert [reply.text async for reply in first.chat_replies("where")]
        assert [reply.text async for reply in second.chat_replies("status")]
        await first.pose()
        await second.pose()
        await first.call.hangup()
        await wait_until(lambda: recorder.calls == 1 and recorder.files_done >= 1)
        # The robot records on (the second call): the first file is complete and readable.
        path = files(directory)[0]
        summary, messages = read(path)
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == len(messages) > 0
        topics = Counter(channel.topic for channel in summary.channels.values())
        assert topics[f"/{USER}/pose"] == 1 and set(topics.values()) == {1}, topics
        assert {f"/{USER}/chat/in", f"/{USER}/chat", "/calls"} <= topics.keys()
        calls = [data for topic, data, *_ in messages if topic == "/calls"]
        assert [c["event"] for c in calls] == ["start", "start", "end"]
        assert calls[2]["call"] == first.call.id
        assert {c["call"] for c in calls} == {first.call.id, second.call.id}
        asked = {data["text"] for topic, data, *_ in messages if topic == f"/{USER}/chat/in"}
        assert asked == {"where", "status"}  # both calls' commands on the one channel
        await second.call.hangup()
        await wait_until(lambda: recorder.calls == 0 and recorder.files_done >= 2)
        ends = [
            data["call"]
            for messages in finished(directory).values()
            for topic, data in messages
            if topic == "/calls" and data["event"] == "end"
        ]
        assert ends == [first.call.id, second.call.id]
    await asyncio.to_thread(recorder.close)


async def test_a_long_call_is_finished_every_max_seconds(tmp_path: Path) -> None:
    directory = tmp_path / "rec"
    recorder = Recorder(directory, max_seconds=0.5)
    recorder.start()
    async with recorded_robot(tmp_path, recorder) as _:
        await wait_until(lambda: recorder.files_done >= 3)
        assert recorder.calls == 1  # the call goes on
        done = finished(directory)
        assert len(done) >= 3
        for messages in done.values():  # each with the call's poses
            assert f"/{USER}/pose" in {topic for topic, _ in messages}
    await asyncio.to_thread(recorder.close)


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
    with caplog.at_level(logging.ERROR, logger="telebot.services.recording"):
        async with recorded_robot(tmp_path, recorder) as (_, client, _):
            await wait_until(lambda: not recorder.enabled)
            assert (await client.arm()).ok
            replies = [reply.text async for reply in client.chat_replies("where")]
            assert replies
            assert (await client.stop(how="key")).ok
    await asyncio.to_thread(recorder.close)
    lines = [r for r in caplog.records if r.name == "telebot.services.recording"]
    assert len(lines) == 1, [r.getMessage() for r in lines]
    assert "recording off" in lines[0].getMessage() and "not-a-dir" in lines[0].getMessage()


async def test_the_daemon_records_beside_the_audit_log_readable_after_each_call(
    tmp_path: Path,
) -> None:
    daemon = Daemon(tmp_path, observer=None)
    with daemon.robot_config.open("a") as config:
        config.write("[recording]\nenabled = true\n")
    daemon.start()
    try:
        for text in ("where", "status"):  # two calls, one after the other
            async with daemon.connect() as client:
                replies = [reply.text async for reply in client.chat_replies(text)]
                assert replies
                await client.pose()

        def messages() -> list[tuple[str, dict[str, Any]]]:
            return [m for found in finished(daemon.robot_home).values() for m in found]

        # The robot runs on, and what it recorded of both calls is readable.
        await wait_until(
            lambda: [m["event"] for t, m in messages() if t == "/calls"].count("end") == 2
        )
        assert daemon.events.popen.poll() is None
        topics = {topic for topic, _ in messages()}
        assert {"/calls", f"/{USER}/chat/in", f"/{USER}/chat", f"/{USER}/pose"} <= topics
        asked = [m["text"] for t, m in messages() if t == f"/{USER}/chat/in"]
        # Each copy received is recorded: a request left unanswered for 0.3 s on a busy
        # machine is sent again, so "where" may be there twice, but in its place.
        assert list(dict.fromkeys(asked)) == ["where", "status"]
    finally:
        daemon.stop(graceful=True)
    assert (daemon.robot_home / "audit.jsonl").exists()


class _FakeCall:
    """What a RecordingService reads of a call."""

    id = "c0ffee"
    peer = USER
    role = None
    end = None
    tap: Any = None


def test_the_oldest_files_go_past_keep_bytes(tmp_path: Path) -> None:
    for number in range(1, 5):
        (tmp_path / f"calls-{number:06d}.mcap").write_bytes(bytes(3000))
    with Recorder(tmp_path, keep_bytes=7000, streams=["chat"]) as recorder:
        call = _FakeCall()
        service = recorder.service(None, cast(Call, call))
        call.tap("chat", False, '{"id": 1, "text": "where"}')
        service.close()
    assert [path.name for path in files(tmp_path)] == [
        "calls-000003.mcap",
        "calls-000004.mcap",
        "calls-000005.mcap",
    ]


def test_a_file_deleted_by_someone_else_does_not_end_the_recording(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # An operator (or a cleanup job) deletes an old file between the listing and the size:
    # the recorder prunes the rest and records on.
    (tmp_path / "calls-000001.mcap").write_bytes(bytes(3000))
    gone = tmp_path / "calls-000000.mcap"  # listed, then deleted before its size is read
    with Recorder(tmp_path, keep_bytes=1000, streams=["chat"]) as recorder:
        listing = recorder._existing
        monkeypatch.setattr(recorder, "_existing", lambda: [(0, gone), *listing()])
        for n in (1, 2):
            call = _FakeCall()
            service = recorder.service(None, cast(Call, call))
            call.tap("chat", False, f'{{"id": {n}, "text": "where"}}')
            service.close()
    assert [path.name for path in files(tmp_path)] == ["calls-000003.mcap"]
    assert "where" in {
        data["text"]
        for _, messages in finished(tmp_path).items()
        for t, data in messages
        if t.endswith("/chat/in")
    }


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
