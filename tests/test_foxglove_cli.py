"""``telebot-user record``, ``chat --record`` and ``foxglove`` as commands: against the robot
daemon (zenoh on loopback), and their one-line errors on bad input."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from conftest import wait_until
from rig import ROBOT, Daemon, Process
from telebot.apps.user_cli import build_parser
from telebot.testing.net import free_port
from test_foxglove import read_mcap, ws_client

pytestmark = pytest.mark.zenoh


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    daemon = Daemon(tmp_path_factory.mktemp("foxglove"))  # alice drives, olga observes
    daemon.start()
    yield daemon
    daemon.stop()


def user_args(daemon: Daemon) -> list[str]:
    return [
        "--home",
        str(daemon.user_home),
        "--config",
        str(daemon.user_config),
        "--connect",
        daemon.endpoint,
    ]


async def test_record_writes_an_mcap_while_the_robot_drives_and_ctrl_c_finishes_it(
    daemon: Daemon, tmp_path: Path, processes: list[Process]
) -> None:
    out = tmp_path / "session.mcap"
    # A second user of the same robot records (the observer's view: the driver's moves).
    args = user_args(daemon)
    args[1] = str(daemon.observer_home)
    recorder = Process(["telebot.apps.user_cli", "record", ROBOT, "-o", str(out), *args])
    processes.append(recorder)
    assert recorder.next_line(timeout=30).startswith(f"recording {ROBOT} to {out}")
    async with daemon.connect() as driver:
        assert (await driver.arm(timeout=10)).ok
        start = await driver.pose()
        assert (await driver.goto(start.x + 1.0, start.y, timeout=20)).status == "succeeded"
        assert (await driver.chat("where", timeout=10)).ok
        await driver.stop(timeout=10)
        await wait_until(lambda: out.stat().st_size > 0)
    recorder.signal(signal.SIGINT)  # Ctrl-C: the file is finished, exit 0
    assert recorder.popen.wait(timeout=20) == 0, recorder.stderr()
    assert f"recorded {out}:" in recorder.stderr()
    schemas, messages = read_mcap(out)
    assert schemas["/map"] == "foxglove.Grid" and schemas["/pose"] == "foxglove.PoseInFrame"
    for topic in ("/map", "/pose", "/plan", "/camera", "/telebot/telemetry", "/telebot/safety"):
        assert messages.get(topic), topic
    states = [json.loads(data) for _, data in messages["/telebot/safety"]]
    assert any(
        s["event"] == "state" and s["armed"] and s["holder"] == daemon.driver for s in states
    )


def test_chat_record_keeps_the_commands_replies_and_safety_events(
    daemon: Daemon, tmp_path: Path
) -> None:
    out = tmp_path / "chat.mcap"
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "telebot.apps.user_cli",
            "chat",
            ROBOT,
            "--record",
            str(out),
            *user_args(daemon),
        ],
        input="arm\nfwd 0.5\nwhere\nstop\n",
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    schemas, messages = read_mcap(out)
    chat = [json.loads(data) for _, data in messages["/telebot/chat"]]
    commands = [m["command"] for m in chat if m["kind"] == "chat"]
    assert commands == ["arm", "fwd 0.5", "where", "stop"]
    assert any(m["kind"] == "chat_reply" and m["command"] == "where" and m["final"] for m in chat)
    states = [json.loads(data) for _, data in messages["/telebot/safety"]]
    assert any(s["event"] == "state" and s["armed"] for s in states)
    assert any(s["event"] == "state" and not s["armed"] for s in states)
    assert messages.get("/pose") and schemas["/camera"] == "foxglove.CompressedImage"


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "telebot.apps.user_cli", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_bad_output_and_taken_port_are_one_line_errors(tmp_path: Path) -> None:
    home = ["--home", str(tmp_path / "home")]
    bad = _cli("record", ROBOT, "-o", str(tmp_path / "no" / "such" / "x.mcap"), *home)
    assert bad.returncode == 2
    assert (
        bad.stderr.strip()
        == f"telebot-user: error: cannot write {tmp_path}/no/such/x.mcap: no folder {tmp_path}/no/such"
    )
    folder = _cli("ui", ROBOT, "--record", str(tmp_path), *home)
    assert folder.returncode == 2 and "is a folder" in folder.stderr
    assert len(folder.stderr.strip().splitlines()) == 1
    with socket.socket() as taken:
        port = free_port()
        taken.bind(("127.0.0.1", port))
        taken.listen()
        busy = _cli("foxglove", ROBOT, "--port", str(port), *home)
    assert busy.returncode == 2
    assert busy.stderr.startswith(f"telebot-user: error: cannot serve on 127.0.0.1:{port}: ")
    assert len(busy.stderr.strip().splitlines()) == 1 and "Traceback" not in busy.stderr


async def test_an_observer_in_foxglove_may_stop_but_not_arm(
    daemon: Daemon, processes: list[Process]
) -> None:
    # The robot's name after --topics: the flag takes one topic, the name stays the robot's.
    args = user_args(daemon)
    args[1] = str(daemon.observer_home)
    port = free_port()
    command = ["telebot.apps.user_cli", "foxglove", "--topics", "/scan", ROBOT]
    fox = Process([*command, "--port", str(port), *args])
    processes.append(fox)
    announced = fox.next_line(timeout=30)
    assert f"ws://127.0.0.1:{port}" in announced and "role observer" in announced, announced
    async with ws_client(f"ws://127.0.0.1:{port}") as client:
        await wait_until(lambda: "/scan" in client.channels, timeout=20)  # relayed
        refused = await client.call("/telebot/arm")
        assert not refused["ok"] and refused["code"] == "observer", refused
        assert refused["text"] == "olga is an observer: observers may not re-arm"
        assert (await client.call("/telebot/stop"))["ok"]  # anyone may stop
    fox.signal(signal.SIGINT)
    assert fox.popen.wait(timeout=20) == 0, fox.stderr()


def test_topics_take_one_value_per_flag_and_the_robot_may_come_anywhere() -> None:
    parser = build_parser()
    for argv, topics in (
        (["foxglove", "--topics", "/scan", ROBOT], ["/scan"]),
        (["foxglove", ROBOT, "--topic", "/scan"], ["/scan"]),
        (["record", "--topic", "/scan", "--topic", "/odom", ROBOT, "-o", "x"], ["/scan", "/odom"]),
        (["record", "--topics", "/scan,/odom", "-o", "x", ROBOT], ["/scan", "/odom"]),
    ):
        args = parser.parse_args(argv)
        assert (args.robot, args.topics) == (ROBOT, topics), argv
    # The old list form: a one-line error that says what to do, not "robot required".
    old = _cli("foxglove", "--topics", "/scan", "/odom", ROBOT)
    assert old.returncode == 2 and len(old.stderr.strip().splitlines()) == 1
    assert "'/odom' is a topic, not a robot name: give one topic per --topic" in old.stderr
