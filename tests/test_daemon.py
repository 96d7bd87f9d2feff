"""The robot daemon end to end: ``telebot-robot run`` in its own process, users over zenoh.

One daemon per module (on the small map, with a fast robot so the moves take a second or
two), driven through the library (:func:`telebot.connect`) and the ``telebot-user``
command, each in separate processes over zenoh on loopback.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import math
import signal
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from rig import FAST_SIM, ROBOT, SLACK, Daemon
from telebot.identity import Identity, KnownRobots
from telebot.reasons import Reason
from telebot.robot.mapfile import load_map, places_path_for
from telebot.robot.sim.building import resolve_map
from telebot.services.client import RobotClient
from telebot.services.mapxfer.wire import decode_map

pytestmark = pytest.mark.zenoh


#: The small map's places and one more, a short way along the corridor from the start and
#: facing another way: a goto there arrives (heading and all) in a second or two, where
#: room-b, round the walls, is a 9 m drive each way.
NEAR_PLACE = "corridor-west"
PLACES = (
    places_path_for(resolve_map("small")).read_text()
    + f"\n[places.{NEAR_PLACE}]\nx = 2.5\ny = 1.2\nyaw_deg = 90.0\n"
)


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    """alice drives, olga observes; no test here is about drop timing (generous timeout)."""
    base = tmp_path_factory.mktemp("daemon")
    places = base / "places.toml"
    places.write_text(PLACES)
    daemon = Daemon(base, sim={**FAST_SIM, "places": str(places)})
    daemon.start()
    yield daemon
    daemon.stop()


@pytest.fixture
async def robot(daemon: Daemon) -> AsyncIterator[RobotClient]:
    async with daemon.connect() as client:
        stopped = await client.stop()  # every test starts from a robot at rest...
        assert stopped.ok
        armed = await client.arm()  # ...that alice (holding the drive) re-arms
        assert armed.ok, armed.text
        yield client


async def settled_pose(robot: RobotClient) -> tuple[float, float, float]:
    """The pose once the robot stands still."""
    for _ in range(50):
        pose = await robot.pose()
        if pose.v == 0 and pose.w == 0:
            return pose.x, pose.y, pose.yaw
    raise AssertionError("the robot did not come to rest")


def yaw_change(before: float, after: float) -> float:
    return math.degrees((after - before + math.pi) % (2 * math.pi) - math.pi)


async def test_fwd_moves_the_robot_two_metres(robot: RobotClient) -> None:
    x0, y0, yaw0 = await settled_pose(robot)
    result = await robot.chat("fwd 2", timeout=30)
    assert result.replies == ["Forward command received", "finished moving"]
    assert result.ok
    x1, y1, _ = await settled_pose(robot)
    # The daemon's loop runs the simulator's controller: on a loaded machine a late control
    # step lets the base run on with its last command, up to the base's watchdog (0.5 s at
    # 0.5 m/s, by design: tests/test_sim_stack.py), so the bound is wider than the 2 cm the
    # controller reaches on an idle machine, and still tells 2 m from 1.5 or 2.5.
    assert math.hypot(x1 - x0, y1 - y0) == pytest.approx(2.0, abs=0.3)
    # Along the heading it had, not sideways.
    along = (x1 - x0) * math.cos(yaw0) + (y1 - y0) * math.sin(yaw0)
    assert along == pytest.approx(2.0, abs=0.3)
    back = await robot.chat("fwd -2", timeout=30)
    assert back.ok


@pytest.mark.parametrize(
    ("command", "expected"),
    [("turn 90", -90.0), ("turn -45", 45.0), ("left", 90.0), ("right", -90.0)],
)
async def test_turns_follow_the_paper_positive_is_to_the_right(
    robot: RobotClient, command: str, expected: float
) -> None:
    _, _, yaw0 = await settled_pose(robot)
    result = await robot.chat(command, timeout=30)
    assert result.replies == ["Turn command received", "finished moving"]
    _, _, yaw1 = await settled_pose(robot)
    assert yaw_change(yaw0, yaw1) == pytest.approx(expected, abs=3.0)


async def test_goto_a_place_arrives_and_where_reports_the_pose(robot: RobotClient) -> None:
    places = await robot.chat("places")
    assert "room-b" in places.final_text and NEAR_PLACE in places.final_text
    result = await robot.chat(f"goto {NEAR_PLACE}", timeout=60)
    assert result.replies[0] == "Goto command received"
    assert result.replies[-1] == "finished moving" and result.ok
    x, y, _ = await settled_pose(robot)
    # The place (the module's places file). The sim stops within 5 cm when its control steps
    # come on time; a late step on a loaded machine lets the base run on with its last
    # command (see test_fwd_moves_the_robot_two_metres), hence the wider bound.
    assert math.hypot(x - 2.5, y - 1.2) < 0.2
    where = await robot.chat("where?")
    assert where.ok
    assert f"x {x:.2f} m" in where.final_text or abs(float(where.final_text.split()[1]) - x) < 0.05
    # The place faces 90°; the controller stops within its yaw tolerance (2°), and the
    # reply rounds to whole degrees.
    heading = float(where.final_text.rsplit("heading", 1)[1].strip().rstrip("°"))
    assert abs(heading - 90.0) <= 3.0
    back = await robot.chat("goto start", timeout=60)
    assert back.ok


async def test_goal_through_the_goals_channel(robot: RobotClient) -> None:
    updates: list[str] = []
    final = await robot.goto(
        3.0, 5.2, 0.0, timeout=60, on_update=lambda u: updates.append(u.status)
    )
    assert final.status == "succeeded", final.text
    x, y, _ = await settled_pose(robot)
    assert math.hypot(x - 3.0, y - 5.2) < 0.2  # as in the goto test: late steps run on
    assert updates[0] == "active"
    refused = await robot.goto(999.0, 999.0, timeout=10)
    assert refused.status == "failed" and refused.code == Reason.NO_PATH
    assert refused.text.startswith("no path to (999.00, 999.00): ")


async def test_cameras_switch_and_telemetry_says_which(robot: RobotClient) -> None:
    assert (await robot.chat("usercam")).ok
    for _ in range(5):
        telemetry = await robot.telemetry()
        if telemetry.camera == "usercam":
            break
    assert telemetry.camera == "usercam"
    assert (await robot.chat("NAVCAM")).ok
    for _ in range(5):
        telemetry = await robot.telemetry()
        if telemetry.camera == "navcam":
            break
    assert telemetry.camera == "navcam"
    assert telemetry.battery > 0 and telemetry.role == "driver"
    assert telemetry.rtt is not None and telemetry.rtt < 1.0 + SLACK
    assert "laser" in telemetry.diagnostics


async def test_getmap_gives_the_cropped_grid_exactly(robot: RobotClient) -> None:
    result = await robot.chat("getmap")
    assert result.ok and result.attachment == "map"
    download = await robot.get_map()
    grid = load_map(resolve_map("small"))
    bounds = grid.known_bounds()
    assert bounds is not None
    expected = grid.crop(*bounds)
    got = decode_map(download.png, download.resolution, download.origin_x, download.origin_y)
    assert np.array_equal(got.data, expected.data)
    assert (got.origin_x, got.origin_y) == pytest.approx((expected.origin_x, expected.origin_y))
    image = cv2.imdecode(np.frombuffer(download.png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image.shape == expected.data.shape


async def test_chat_answers_info_commands_and_refuses_bad_ones(robot: RobotClient) -> None:
    assert "battery" in (await robot.chat("battery")).final_text
    assert (await robot.chat("status")).ok
    assert "fwd" in (await robot.chat("help")).final_text
    unknown = await robot.chat("xyz")
    assert not unknown.ok and unknown.final_text == "unknown command 'xyz' — try help"
    usage = await robot.chat("fwd lots")
    assert not usage.ok and usage.final_text.startswith("usage: fwd")


async def test_an_observer_may_not_drive_but_may_stop(daemon: Daemon) -> None:
    async with daemon.connect(daemon.observer_home) as olga:
        refused = await olga.chat("fwd 1")
        assert not refused.ok and refused.code == Reason.OBSERVER
        # The text the docs (protocol.md §14.3) give for it:
        assert refused.final_text == "refused: olga is an observer: observers may not drive"
        goal = await olga.goto(3.0, 5.2)
        assert goal.status == "refused" and goal.code == Reason.OBSERVER
        assert (await olga.stop()).ok
        assert (await olga.chat("where?")).ok
        refused_arm = await olga.arm()
        assert not refused_arm.ok and refused_arm.code == Reason.OBSERVER


async def test_garbage_on_every_channel_is_dropped_and_the_daemon_keeps_serving(
    robot: RobotClient,
) -> None:
    for name in ("chat", "goals", "map", "pose", "telemetry", "nonsense"):
        channel = (
            robot.call.channel(name)
            if name not in robot.call.channels
            else robot.call.channels[name]
        )
        for junk in (b"\x00\xff" * 10, "not json", '{"id": "x"}', "[]", '{"type": "goal"}'):
            channel.send(junk)
    await asyncio.sleep(0.3)
    assert (await robot.chat("where?")).ok


def test_send_exit_codes(daemon: Daemon, tmp_path: Path) -> None:
    stranger = tmp_path / "stranger"
    Identity.generate("mallory").save(stranger)
    known = KnownRobots.load(stranger)
    known.add(ROBOT, Identity.load(daemon.robot_home).public_key)
    known.save()
    # The commands that leave the robot as it is run beside the ones that drive it, each a
    # process of its own: a process started one after another cost seconds each.
    with concurrent.futures.ThreadPoolExecutor() as pool:
        offline_run = pool.submit(daemon.user_cli, "send", "nobody", "where?", timeout=30)
        refused_run = pool.submit(daemon.user_cli, "send", ROBOT, "where?", home=stranger)
        usage_run = pool.submit(daemon.user_cli, "send", ROBOT)
        ok = daemon.user_cli("send", "--arm", ROBOT, "turn", "10")
        assert ok.returncode == 0, ok.stderr
        assert ok.stdout.splitlines() == ["Turn command received", "finished moving"]
        # Its call ended, so the robot latched stopped: without --arm a motion is refused.
        latched = daemon.user_cli("send", ROBOT, "turn", "10")
        assert latched.returncode == 1
        assert latched.stdout.startswith("! refused:") and "arm" in latched.stdout
        failed = daemon.user_cli("send", "--arm", ROBOT, "goto", "999", "999")
        assert failed.returncode == 1
        assert "no path to" in failed.stdout
        offline, refused, usage = offline_run.result(), refused_run.result(), usage_run.result()
    assert offline.returncode == 2
    assert offline.stderr.count("\n") == 1 and "nobody" in offline.stderr
    assert refused.returncode == 2
    assert "not in the contact list" in refused.stderr
    assert usage.returncode == 2


def test_piped_chat_runs_each_command_to_its_end(daemon: Daemon, tmp_path: Path) -> None:
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "telebot.apps.user_cli",
            "chat",
            ROBOT,
            "--home",
            str(daemon.user_home),
            "--config",
            str(daemon.user_config),
            "--connect",
            daemon.endpoint,
            "--map-dir",
            str(tmp_path),
        ],
        input="arm\nwhere?\n  TURN   20 \nturn -20\ngetmap\n",
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[:3] == ["> arm", "armed: send a motion command to move", "> where?"]
    assert lines.count("finished moving") == 2
    assert (tmp_path / f"{ROBOT}-map.png").exists() and (tmp_path / f"{ROBOT}-map.yaml").exists()
    assert load_map(tmp_path / f"{ROBOT}-map.yaml").data.shape[0] > 0


def test_getmap_and_where_commands(daemon: Daemon, tmp_path: Path) -> None:
    out = tmp_path / "maps" / "small.png"
    with concurrent.futures.ThreadPoolExecutor() as pool:  # two processes side by side
        where_run = pool.submit(daemon.user_cli, "where", ROBOT)
        result = daemon.user_cli("getmap", ROBOT, "-o", str(out))
        where = where_run.result()
    assert result.returncode == 0, result.stderr
    reloaded = load_map(out.with_suffix(".yaml"))
    grid = load_map(resolve_map("small"))
    bounds = grid.known_bounds()
    assert bounds is not None
    assert np.array_equal(reloaded.data, grid.crop(*bounds).data)
    assert where.returncode == 0, where.stderr
    assert where.stdout.startswith("x ") and "heading" in where.stdout


def test_sigterm_stops_the_robot_hangs_up_and_exits_within_two_seconds(tmp_path: Path) -> None:
    daemon = Daemon(tmp_path, observer=None)
    try:
        daemon.start()

        async def drive_and_wait() -> tuple[str, float]:
            async with daemon.connect() as robot:
                assert (await robot.arm()).ok
                async for reply in robot.chat_replies("fwd 5"):
                    assert reply.text == "Forward command received"
                    break
                await asyncio.sleep(0.5)
                started = time.monotonic()
                daemon.events.signal(signal.SIGTERM)
                end = await robot.call.wait_ended()
                return end.detail, time.monotonic() - started

        detail, seconds = asyncio.run(drive_and_wait())
        assert detail == "robot shutting down"
        assert seconds < 2.0 + SLACK
        daemon.events.popen.wait(timeout=2.0 + SLACK)
        assert daemon.events.popen.returncode in (0, 143)
        events = []
        while not daemon.events.lines.empty():
            events.append(daemon.events.lines.get())
        assert any('"stopping"' in line for line in events)
    finally:
        daemon.stop()


async def test_video_follows_the_camera_switch_and_moving_forces_the_navcam(
    robot: RobotClient,
) -> None:
    assert (await robot.chat("usercam")).ok
    async with robot.video() as video:
        async with asyncio.timeout(10):
            async for frame in video:
                if frame.camera == "usercam":
                    break
        assert frame.image.shape == (480, 640, 3)
        usercam_image = frame.image
        # Moving switches the driver's video to the navcam, and usercam is refused meanwhile.
        replies = robot.chat_replies("fwd 1.5", timeout=30)
        assert (await anext(replies)).code == Reason.ACCEPTED
        # Asked at once: the 1.5 s move must still be running (a loaded machine is slow).
        refused = await robot.chat("usercam")
        assert not refused.ok and refused.code == Reason.CAMERA_WHILE_MOVING
        async with asyncio.timeout(10):
            async for frame in video:
                if frame.camera == "navcam":
                    break
        assert not np.array_equal(frame.image, usercam_image)
        async for reply in replies:
            assert reply.ok, reply.text
        await replies.aclose()
    telemetry = await robot.telemetry()
    assert telemetry.camera == "navcam"
    back = await robot.chat("fwd -1.5", timeout=30)
    assert back.ok
