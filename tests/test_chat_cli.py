"""``telebot-user chat`` as people run it: the command in its own process, fed through a pipe
(a script with pauses) or a terminal (a pty), the robot daemon in another, over zenoh.

What ``chat --help`` promises is what these tests check: piped commands run one after the
other within ``--timeout``, pauses included; the call lives on while the script pauses; the
conference shows on stderr while the chat waits for input.
"""

from __future__ import annotations

import asyncio
import io
import math
import os
import re
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import pytest

from conftest import wait_until
from rig import ROBOT, SLACK, Daemon, Process
from telebot.apps.user_cli import main
from telebot.apps.user_client import (
    DRIVE_BACK,
    DRIVE_FORWARD,
    DRIVE_TURN,
    SHOWN_CHARS,
    _Motions,
    chat_session,
    drive_keys,
    where,
)
from telebot.services.chat.wire import MAX_REQUEST_TEXT
from telebot.services.conference.wire import MAX_TEXT
from telebot.services.safety.wire import LATCHED
from telebot.services.status.wire import PoseUpdate

pytestmark = pytest.mark.zenoh


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    """alice drives, olga observes (the rig's generous call timeout: no test here is about
    drop timing). One pose a second: a pose that lags a goal's end lags it visibly."""
    daemon = Daemon(tmp_path_factory.mktemp("chat"))
    with daemon.robot_config.open("a") as config:
        config.write("[services]\npose_hz = 1\n")
    daemon.start()
    yield daemon
    daemon.stop()


def chat(daemon: Daemon, *args: str, stdin: int = subprocess.PIPE) -> Process:
    """``telebot-user chat ROBOT ARGS`` as alice, in its own process."""
    return Process(
        [
            "telebot.apps.user_cli",
            "chat",
            ROBOT,
            *args,
            "--home",
            str(daemon.user_home),
            "--config",
            str(daemon.user_config),
            "--connect",
            daemon.endpoint,
        ],
        stdin=stdin,
    )


async def reply(process: Process, timeout: float = 20.0) -> str:
    """The next stdout line, awaited without blocking this test's loop (its calls beat)."""
    return await asyncio.to_thread(process.next_line, timeout + SLACK)


def chat_help(capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit):
        main(["chat", "--help"])
    return " ".join(capsys.readouterr().out.split())


async def test_a_paced_piped_script_keeps_its_call_and_shows_the_conference_while_idle(
    daemon: Daemon, processes: list[Process], capsys: pytest.CaptureFixture[str]
) -> None:
    promise = chat_help(capsys)
    assert "their messages, the robot's announcements and who is in the call show on stderr" in (
        promise
    )
    assert "pauses in the input included" in promise
    alice = chat(daemon)
    processes.append(alice)
    alice.write("arm\n")
    assert await reply(alice, 60) == "> arm"
    assert (await reply(alice)).startswith("armed:")
    armed = time.monotonic()
    # While the script pauses, the chat waits for its next line: the conference still shows.
    assert daemon.observer is not None
    async with daemon.connect(daemon.observer_home) as olga:
        await wait_until(lambda: "olga (observer)" in alice.stderr(), timeout=10 + SLACK)
        assert (await olga.say("hello from the hall")).ok
        await wait_until(lambda: "[olga] hello from the hall" in alice.stderr())
    # A pause longer than the call's timeout: without heartbeats the call would drop and
    # the robot would latch stopped.
    await asyncio.sleep(max(0.0, armed + daemon.timeout + 1.0 - time.monotonic()))
    alice.write("where?\n")
    assert await reply(alice) == "> where?"
    assert (await reply(alice)).startswith("x ")
    await asyncio.sleep(1.0)
    alice.write("fwd 0.5\n")  # still armed: no re-arm needed
    assert [await reply(alice) for _ in range(3)] == [
        "> fwd 0.5",
        "Forward command received",
        "finished moving",
    ]
    assert alice.popen.stdin is not None
    alice.popen.stdin.close()
    assert await asyncio.to_thread(alice.popen.wait, 30) == 0, alice.stderr()
    assert "interrupted" not in alice.stderr() and "reconnecting" not in alice.stderr()
    alices = [r for r in daemon.audit() if r.get("who") == daemon.driver]
    assert not [r for r in alices if r["what"] in ("deadman", "drop")], alices


async def test_the_timeout_fires_while_a_piped_chat_waits_for_input(
    daemon: Daemon, processes: list[Process]
) -> None:
    # (--timeout runs from the call's set-up on: a second is as good as three here.)
    waiting = chat(daemon, "--timeout", "1")
    processes.append(waiting)
    # Nothing is written and the pipe stays open: the chat waits for a line that never comes.
    code = await asyncio.to_thread(waiting.popen.wait, 40)
    errors = waiting.stderr().splitlines()
    assert code == 2, errors
    assert errors[-1] == "telebot-user: error: chat did not finish within 1 s (--timeout)"
    assert not any("Traceback" in line for line in errors)


async def until_line(process: Process, needle: str, timeout: float = 20.0) -> list[str]:
    """The stdout lines up to the first that contains ``needle``."""
    lines: list[str] = []
    while not lines or needle not in lines[-1]:
        lines.append(await reply(process, timeout))
    return lines


async def leave_with_ctrl_d(chat_process: Process, keyboard: int) -> None:
    """Ctrl-D on an empty line leaves; the chat exits 0. On a loaded machine the chat's
    newest pose may still be one from before a stop (they come once a second here): then
    the key stops the robot (the paper's rule, and the chat says so) and the next leaves."""
    for _ in range(3):
        os.write(keyboard, b"\x04")
        try:
            left = await asyncio.to_thread(chat_process.popen.wait, 10)
            break
        except subprocess.TimeoutExpired:
            await until_line(chat_process, "[key pressed: stopping]", 5)
    assert left == 0, chat_process.stderr()


async def test_on_a_terminal_a_key_stops_a_motion_after_its_end_is_a_command_and_status_says_latched(
    daemon: Daemon, processes: list[Process], capsys: pytest.CaptureFixture[str]
) -> None:
    keyboard, terminal = os.openpty()
    try:
        alice = chat(daemon, stdin=terminal)
    finally:
        os.close(terminal)
    processes.append(alice)
    try:
        os.write(keyboard, b"arm\r")
        await until_line(alice, "armed:", 60)
        os.write(keyboard, b"fwd 1.5\r")
        await until_line(alice, "Forward command received")
        # Typed at once on seeing the reply: the newest pose (one a second here) was sent
        # while the robot still moved, but the goal has ended: this is a command.
        lines = await until_line(alice, "finished moving")
        ended = time.monotonic()
        os.write(keyboard, b"where?\r")
        lines += await until_line(alice, "heading")
        assert not [line for line in lines if "key pressed" in line], lines
        # A pose at rest has come by now (the next key is a command because of it, not of
        # the second after the end: on a loaded machine where? alone can take longer).
        await asyncio.sleep(max(0.0, ended + 2.2 - time.monotonic()))
        # While a motion runs, any key stops the robot (the paper's rule), however new the
        # pose: the motion's acknowledgement is enough.
        os.write(keyboard, b"fwd 3\r")
        await until_line(alice, "Forward command received")
        pressed = time.monotonic()  # the robot's audit stamps are this clock too
        os.write(keyboard, b"x")
        await until_line(alice, "[key pressed: stopping]")
        await until_line(alice, "stopped")
        # Stopped is not idle: the latch, and who stopped the robot, show in the status.
        os.write(keyboard, b"status\r")
        lines = await until_line(alice, "latched")
        assert lines[-1].endswith(f"{LATCHED}: stop requested by {daemon.driver} (key)"), lines
        await leave_with_ctrl_d(alice, keyboard)
    finally:
        os.close(keyboard)
    # The one key stop (a stop is sent again until acknowledged: each copy is audited).
    stops = [r["t"] for r in daemon.audit() if r["what"] == "stop" and r.get("how") == "key"]
    assert stops and min(stops) >= pressed, (stops, pressed)
    # ...and in `telebot-user where`, from another call after this one hung up.
    capsys.readouterr()
    assert await where(ROBOT, home=daemon.user_home, config=daemon.config(), timeout=10) == 0
    said = capsys.readouterr().out
    assert said.startswith("x ")
    assert said.endswith(f"; {LATCHED}: stop requested by {daemon.driver} (key)\n"), said


def parse_xy(line: str) -> tuple[float, float]:
    """x and y (m) of a pose line: "… x 2.50 m, y 4.40 m, heading 90° …"."""
    match = re.search(r"x (-?[0-9.]+) m, y (-?[0-9.]+) m", line)
    assert match is not None, line
    return float(match.group(1)), float(match.group(2))


async def test_on_a_terminal_tab_drives_with_the_arrow_keys_and_any_other_key_stops(
    daemon: Daemon, processes: list[Process]
) -> None:
    keyboard, terminal = os.openpty()
    try:
        alice = chat(daemon, stdin=terminal)
    finally:
        os.close(terminal)
    processes.append(alice)
    try:
        os.write(keyboard, b"arm\r")
        await until_line(alice, "armed:", 60)
        os.write(keyboard, b"where?\r")
        before = parse_xy((await until_line(alice, "heading"))[-1])
        # Tab: drive mode. The up arrow, as a held key's auto-repeat sends it.
        os.write(keyboard, b"\t")
        await until_line(alice, "[drive mode:")
        moved = 0.0
        deadline = time.monotonic() + 60 + SLACK
        while moved < 0.2:
            assert time.monotonic() < deadline, "the robot did not move"
            for _ in range(10):
                os.write(keyboard, b"\x1b[A")
                await asyncio.sleep(0.05)
            # Escape leaves drive mode (a release: the robot stops, stays armed) …
            os.write(keyboard, b"\x1b")
            await until_line(alice, "[drive mode off]")
            os.write(keyboard, b"where?\r")
            after = parse_xy((await until_line(alice, "heading"))[-1])
            moved = math.dist(before, after)
            os.write(keyboard, b"\t")
            await until_line(alice, "[drive mode:")
        # … and any other key in drive mode is a safety stop (it latches).
        os.write(keyboard, b"\x1b[A")
        os.write(keyboard, b"x")
        await until_line(alice, "[key pressed: stopping; drive mode off]")
        os.write(keyboard, b"status\r")
        await until_line(alice, "latched")
        await leave_with_ctrl_d(alice, keyboard)
    finally:
        os.close(keyboard)
    records = daemon.audit()
    assert any(r["what"] == "motion: drive by hand" and r["outcome"] == "allowed" for r in records)
    ends = [r["detail"] for r in records if r["what"] == "drive by hand: end"]
    assert any(d.startswith("released") for d in ends), ends
    assert any(r["what"] == "stop" and r.get("how") == "key" for r in records)


def test_chat_help_tells_how_to_drive_by_hand(capsys: pytest.CaptureFixture[str]) -> None:
    promise = chat_help(capsys)
    assert "Tab turns drive mode on" in promise and "arrow keys or WASD" in promise
    assert "Escape or Enter leaves drive mode" in promise


def test_drive_mode_keys() -> None:
    assert drive_keys("\x1b[A\x1bOA") == [("drive", DRIVE_FORWARD, 0.0)] * 2
    assert drive_keys("wasd") == [
        ("drive", DRIVE_FORWARD, 0.0),
        ("drive", 0.0, DRIVE_TURN),
        ("drive", -DRIVE_BACK, 0.0),
        ("drive", 0.0, -DRIVE_TURN),
    ]
    assert drive_keys("\x1b[D\x1b[C\x1b[B") == [
        ("drive", 0.0, DRIVE_TURN),
        ("drive", 0.0, -DRIVE_TURN),
        ("drive", -DRIVE_BACK, 0.0),
    ]
    assert drive_keys("\x1b") == [("leave", 0.0, 0.0)]
    assert drive_keys("\r") == [("leave", 0.0, 0.0)]
    for other in (" ", "x", "\x1b[15~", "\x04", "1"):
        assert drive_keys(other) == [("stop", 0.0, 0.0)], other


async def test_a_line_too_long_gets_one_short_line_and_the_script_goes_on(
    daemon: Daemon, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    script = io.StringIO("x" * 200_000 + "\nsay " + "y" * 200_000 + "\nwhere?\n")
    status = await chat_session(
        ROBOT,
        home=daemon.user_home,
        config=daemon.config(),
        timeout=60,
        map_dir=tmp_path,
        stdin=script,
    )
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert status == 1  # the long lines failed
    assert lines[:2] == [
        "> " + "x" * SHOWN_CHARS + "…",
        f"! chat request: text is longer than {MAX_REQUEST_TEXT} characters",
    ]
    assert lines[2] == "> say " + "y" * (SHOWN_CHARS - 4) + "…"
    assert lines[3] == f"! say refused: message longer than {MAX_TEXT} characters"
    assert lines[4] == "> where?" and lines[5].startswith("x ")
    assert len(out) < 1000


def test_after_its_own_motion_the_terminal_goes_by_goals_not_by_the_rolling_base() -> None:
    latest = SimpleNamespace(value=None)
    clock = [0.0]
    motions = _Motions(SimpleNamespace(latest_pose=latest), clock=lambda: clock[0])  # type: ignore[arg-type]

    def pose(v: float, state: str, goal: int | None = None) -> PoseUpdate:
        latest.value = PoseUpdate(0.0, 1.0, 1.0, 0.0, (0.0, 0.0, 0.0), v, 0.0, state, "", goal)
        motions.on_pose(latest.value)
        return latest.value

    assert not motions.moving()
    motions.started()  # "Forward command received"
    assert motions.moving()  # even before any pose says so
    pose(0.8, "moving", goal=5)
    motions.ended()  # "finished moving": the newest pose was sent before that
    assert not motions.moving()
    pose(0.2, "moving")  # the base rolls to rest after the goal's end: a key is a command
    assert not motions.moving()
    pose(0.0, "idle")
    assert not motions.moving()
    pose(0.5, "moving")  # then someone else drives it (a follow from the page)...
    assert motions.moving()
    pose(0.0, "idle", goal=7)  # ...or sends a goal: any key stops the robot
    assert motions.moving()


def test_after_its_own_motion_the_exceptions_end_in_time() -> None:
    # Odometry that never reads exactly zero, or poses that stop coming: a key is a
    # command only for a moment after "finished moving", then it stops the robot again.
    latest = SimpleNamespace(value=None)
    clock = [0.0]
    motions = _Motions(SimpleNamespace(latest_pose=latest), clock=lambda: clock[0])  # type: ignore[arg-type]
    latest.value = PoseUpdate(0.0, 1.0, 1.0, 0.0, (0.0, 0.0, 0.0), 0.8, 0.0, "moving", "", 5)
    motions.started()
    motions.ended()
    assert not motions.moving()  # the pose of before the end
    clock[0] = _Motions.STALE_AT_MOST + 0.01
    assert motions.moving()  # no newer pose came: that one names a goal, in doubt it moves
    noisy = PoseUpdate(0.5, 1.0, 1.0, 0.0, (0.0, 0.0, 0.0), 0.001, 0.0, "idle", "", None)
    latest.value = noisy
    motions.on_pose(noisy)
    assert not motions.moving()  # settling: the base may still creep
    clock[0] = _Motions.SETTLE_AT_MOST + 0.01
    assert motions.moving()  # it never read zero: after a second, a key stops it


async def test_after_the_robot_stopped_itself_chat_says_so_and_how_to_drive_on(
    tmp_path: Path, processes: list[Process]
) -> None:
    # A robot of its own: this test trips the deadman, which the module's robot must not log.
    daemon = Daemon(tmp_path)
    daemon.start()
    try:
        alice = chat(daemon)
        processes.append(alice)
        alice.write("arm\n")
        assert await reply(alice, 60) == "> arm"
        assert (await reply(alice)).startswith("armed:")
        # A blip: the chat freezes (its heartbeats stop) past the deadman time.
        os.kill(alice.pid, signal.SIGSTOP)
        try:
            await wait_until(
                lambda: any(r["what"] == "deadman" for r in daemon.audit()),
                timeout=daemon.timeout + 10 + SLACK,
            )
        finally:
            os.kill(alice.pid, signal.SIGCONT)
        deadman = daemon.timeout - 1 / 20  # call.timeout minus one heartbeat (at 20 Hz)
        hint = (
            f"[the robot stopped itself: driver {daemon.driver}'s link lost: silent "
            f"{deadman:.2f} s (deadman). Type 'arm' to drive on.]"
        )
        await wait_until(lambda: hint in alice.stderr(), timeout=20 + SLACK)
        assert alice.stderr().count(hint) == 1, alice.stderr()  # said once, not every second
    finally:
        daemon.stop()
