"""People walking in the simulator, set in the config: ``[[sim.walkers]]``.

So that follow-me and the people alerts can be tried with ``telebot-robot run`` alone: the
config's walkers walk in the daemon's simulator, its laser sees them and its ``people``
stream tracks them; a walker the map or the model refuses stops the daemon at start with
one line naming it.
"""

from __future__ import annotations

import math
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from rig import GENEROUS_TIMEOUT, Daemon
from telebot.config import RobotConfig, SimSettings, WalkerSettings, load_toml
from telebot.errors import ConfigError
from telebot.robot.sim.people import Walker
from telebot.robot.sim.stack import SimNavStack

#: A walker in the small map's corridor, in front of the robot at its start place (1, 1.2).
CORRIDOR = """
[[sim.walkers]]
waypoints = [[3.0, 1.2, 1.0], [8.0, 1.2, 1.0]]   # [x, y] or [x, y, pause_s]
speed = 0.8
loop = true
"""


def test_a_looping_walker_goes_round_for_ever() -> None:
    walker = Walker.along([(0.0, 0.0, 1.0), (2.0, 0.0)], speed=1.0, loop=True)
    assert walker.duration == math.inf
    # Round: 1 s pause at the first, 2 s out, 2 s back: 5 s a lap.
    for lap in range(3):
        start = lap * 5.0
        assert walker.state_at(start + 0.5).x == 0.0 and not walker.state_at(start + 0.5).walking
        out = walker.state_at(start + 2.0)
        assert (out.x, out.vx, out.walking) == (pytest.approx(1.0), pytest.approx(1.0), True)
        back = walker.state_at(start + 4.0)
        assert (back.x, back.vx) == (pytest.approx(1.0), pytest.approx(-1.0))
    with pytest.raises(ValueError, match="two different waypoints"):
        Walker.along([(1.0, 1.0), (1.0, 1.0)], loop=True)


def test_configured_walkers_walk_in_the_simulator(tmp_path: Path) -> None:
    config = tmp_path / "robot.toml"
    config.write_text('[sim]\nmap = "small"\n' + CORRIDOR)
    sim = load_toml(config, RobotConfig).sim
    stack = SimNavStack.from_settings(sim)
    (person,) = stack.people_truth()
    assert (person.x, person.y, person.walking) == (3.0, 1.2, False)
    while stack.now < 4.0:
        stack.step(stack.now + 0.05)
    (person,) = stack.people_truth()
    assert person.walking and 5.0 < person.x < 6.0
    # The laser sees the legs in front of the robot.
    scan = stack.laser_scan()
    assert float(scan.ranges[len(scan.ranges) // 2 - 8 : len(scan.ranges) // 2 + 8].min()) < 5.0


@pytest.mark.parametrize(
    ("walker", "error"),
    [
        # (6, 0) is in the corridor's south wall.
        ({"waypoints": [[3.0, 1.2], [6.0, 0.0]]}, "waypoint 1 (6, 0) is not free space"),
        # From the corridor straight into room A, through its wall.
        (
            {"waypoints": [[1.0, 1.2], [1.0, 5.0]]},
            "the way from (1, 1.2) to (1, 5) goes through a wall",
        ),
    ],
)
def test_a_walker_in_a_wall_is_a_clear_error(walker: dict[str, object], error: str) -> None:
    sim = SimSettings(map="small", walkers=[WalkerSettings.model_validate(walker)])
    with pytest.raises(ConfigError, match=r"sim\.walkers\[0\]") as caught:
        SimNavStack.from_settings(sim)
    assert error in str(caught.value) and "\n" not in str(caught.value)


@pytest.mark.zenoh
async def test_the_daemon_s_people_stream_sees_a_configured_walker_walk(tmp_path: Path) -> None:
    daemon = Daemon(tmp_path)
    with daemon.robot_config.open("a") as config:
        config.write(CORRIDOR)
    daemon.start()
    try:
        async with daemon.connect() as robot:
            xs: list[float] = []
            speeds: list[float] = []
            async for update in robot.people_updates():
                for track in update.tracks:
                    xs.append(track.x)
                    speeds.append(math.hypot(track.vx, track.vy))
                # Seen walking: along the corridor over a metre, at about its pace.
                if xs and max(xs) - min(xs) > 1.0 and max(speeds) > 0.4:
                    break
            assert all(abs(t.y - 1.2) < 0.3 for t in update.tracks)
    finally:
        daemon.stop()


@pytest.mark.parametrize(
    ("table", "error"),
    [
        ("waypoints = [[3.0, 1.2]]\nspeed = -1.0", "sim.walkers.0.speed"),
        ("waypoints = [[3.0, 1.2], [6.0, 0.0]]", "sim.walkers[0]: waypoint 1 (6, 0)"),
        ("waypoints = [[3.0]]", "waypoint 0 must be [x, y] or [x, y, pause_s]"),
        ("waypoints = [[3.0, 1.2]]\npace = 1.0", "sim.walkers.0.pace: unknown key"),
    ],
)
def test_a_bad_walker_stops_the_daemon_with_one_line(
    tmp_path: Path, table: str, error: str
) -> None:
    daemon = Daemon(tmp_path)  # the homes and a config; not started
    with daemon.robot_config.open("a") as config:
        config.write(f"\n[[sim.walkers]]\n{table}\n")
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "telebot.apps.robot_cli",
            "run",
            "--home",
            str(daemon.robot_home),
            "--config",
            str(daemon.robot_config),
            "--listen",
            "tcp/127.0.0.1:0",
        ],
        capture_output=True,
        text=True,
        timeout=GENEROUS_TIMEOUT + 60,
    )
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2, done.stderr
    assert len(lines) == 1 and error in lines[0], done.stderr
    assert "Traceback" not in done.stderr


def test_the_example_walker_of_the_shipped_config_walks_on_the_building_map() -> None:
    """configs/robot.toml's commented ``[[sim.walkers]]``, uncommented, is a valid walker in
    front of the robot at its start place (as README says: ``arm``, then ``follow``)."""
    text = (Path(__file__).resolve().parents[1] / "configs" / "robot.toml").read_text()
    start = text.index("# [[sim.walkers]]")
    block = []
    for line in text[start:].splitlines():
        if not line.startswith("# "):
            break
        block.append(line[2:])
    sim = RobotConfig.model_validate(tomllib.loads("[sim]\n" + "\n".join(block))).sim
    assert len(sim.walkers) == 1 and sim.walkers[0].loop
    stack = SimNavStack.from_settings(sim)
    (person,) = stack.people_truth()
    robot = stack.true_pose
    bearing = math.atan2(person.y - robot.y, person.x - robot.x) - robot.yaw
    assert math.hypot(person.x - robot.x, person.y - robot.y) <= 3.5
    assert abs(math.remainder(bearing, math.tau)) < math.radians(30)
