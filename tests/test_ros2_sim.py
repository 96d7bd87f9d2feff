"""telebot-sim: the simulator as a ROS 2 / Nav2 robot in its own process, over rmw_zenoh.

Each test that moves the robot starts ``python -m telebot.apps.sim_cli`` (its own zenoh router
on a free port, the small map, a fast robot); the tests that never move it share one. They
talk to it as a ROS 2 node would, with :class:`Ros2Node`.
"""

from __future__ import annotations

import contextlib
import math
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from conftest import SLACK, Process, wait_until
from rig import FAST_SIM, child_env, write_config
from telebot.config import SimSettings
from telebot.robot.ros2.keys import Attachment, QoS
from telebot.robot.ros2.node import Ros2Node
from telebot.robot.sim.stack import SimNavStack
from telebot.rosmsg.types import TypeLibrary
from telebot.testing.net import free_port

#: action_msgs/GoalStatus codes.
SUCCEEDED, CANCELED, ABORTED = 4, 5, 6


class Sim:
    """A telebot-sim process and what a client needs to reach it."""

    def __init__(self, process: Process, endpoint: str) -> None:
        self.process = process
        self.endpoint = endpoint


@contextlib.contextmanager
def sim_process(folder: Path) -> Iterator[Sim]:
    """A telebot-sim serving the small map with a fast robot, stopped on exit."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = write_config(folder / "robot.toml", sim=FAST_SIM)
    process = Process(
        ["telebot.apps.sim_cli", "--config", str(config), "--listen", endpoint, "--map", "small"]
    )
    try:
        line = process.next_line(timeout=30)
        assert "serving map 'small' as ROS 2 robot on" in line, line
        yield Sim(process, endpoint)
    finally:
        process.stop(graceful=True)


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[Sim]:
    """A sim of the test's own: for a test that moves the robot (or kills a client)."""
    with sim_process(tmp_path) as value:
        yield value


@pytest.fixture(scope="module")
def still_sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Sim]:
    """One sim for the tests that never move its robot (it stays at the start place):
    a sim process started per test cost a few seconds each."""
    with sim_process(tmp_path_factory.mktemp("still_sim")) as value:
        yield value


def ros2_node(sim: Sim) -> Iterator[Ros2Node]:
    client = Ros2Node(name="sim_test", connect=[sim.endpoint])
    try:
        yield client
    finally:
        client.close()


@pytest.fixture
def node(sim: Sim) -> Iterator[Ros2Node]:
    """A ROS 2 node of this test's on its own sim."""
    yield from ros2_node(sim)


@pytest.fixture
def still_node(still_sim: Sim) -> Iterator[Ros2Node]:
    """A ROS 2 node of this test's on the shared sim whose robot never moves."""
    yield from ros2_node(still_sim)


def small_map() -> SimNavStack:
    return SimNavStack.from_settings(SimSettings(map="small"))


class Latest:
    """The latest message of a topic, and how many came (written on zenoh's threads)."""

    def __init__(self) -> None:
        self.msg: Any = None
        self.count = 0
        self.lock = threading.Lock()

    def __call__(self, msg: Any, _attachment: Attachment) -> None:
        with self.lock:
            self.msg = msg
            self.count += 1


def subscribe(node: Ros2Node, topic: str, type_name: str, qos: QoS | None = None) -> Latest:
    latest = Latest()
    mtype = node.library.message(type_name)
    if qos is None:
        node.subscribe(topic, mtype, latest)
    else:
        node.subscribe(topic, mtype, latest, qos=qos)
    return latest


def nav_goal(node: Ros2Node, x: float, y: float) -> Any:
    m = node.library.message
    return node.library.action("nav2_msgs/action/NavigateToPose").goal.make(
        pose=m("geometry_msgs/msg/PoseStamped").make(
            header=m("std_msgs/msg/Header").make(frame_id="map"),
            pose=m("geometry_msgs/msg/Pose").make(
                position=m("geometry_msgs/msg/Point").make(x=x, y=y),
                orientation=m("geometry_msgs/msg/Quaternion").make(w=1.0),
            ),
        )
    )


class GoalRecord:
    """What an action client heard about one goal."""

    def __init__(self) -> None:
        self.accepted: bool | None = None
        self.feedback: list[Any] = []
        self.status: int | None = None
        self.result: Any = None
        self.text = ""
        self.client: Any = None
        self.goal_id = b""

    def on_accepted(self, _goal_id: bytes, accepted: bool) -> None:
        self.accepted = accepted

    def on_feedback(self, feedback: Any) -> None:
        self.feedback.append(feedback)

    def on_result(self, status: int, result: Any, text: str) -> None:
        self.result, self.text = result, text
        self.status = status


def send(
    node: Ros2Node, goal: Any, action: str = "navigate_to_pose", type_name: str = "NavigateToPose"
) -> GoalRecord:
    record = GoalRecord()
    atype = node.library.action(f"nav2_msgs/action/{type_name}")
    record.client = node.action_client(action, atype)
    record.goal_id = record.client.send_goal(
        goal,
        on_accepted=record.on_accepted,
        on_feedback=record.on_feedback,
        on_result=record.on_result,
    )
    return record


async def test_map_reaches_a_late_joiner_with_the_grids_ros_values(still_node: Ros2Node) -> None:
    node = still_node
    # The sim published its map before this subscription existed: transient local.
    latest = subscribe(node, "map", "nav_msgs/msg/OccupancyGrid", QoS.transient_local(depth=1))
    await wait_until(lambda: latest.msg is not None, timeout=10 + SLACK)
    grid = small_map().map()
    msg = latest.msg
    assert (msg.info.width, msg.info.height) == (grid.width, grid.height)
    assert msg.info.resolution == pytest.approx(grid.resolution)
    assert (msg.info.origin.position.x, msg.info.origin.position.y) == pytest.approx(
        (grid.origin_x, grid.origin_y)
    )
    assert msg.header.frame_id == "map"
    assert np.array_equal(np.asarray(msg.data, dtype=np.int8), grid.data.reshape(-1))
    assert set(np.unique(msg.data)) <= {-1, *range(101)}


async def test_navigate_to_pose_moves_the_robot_with_feedback(node: Ros2Node) -> None:
    pose = subscribe(node, "amcl_pose", "geometry_msgs/msg/PoseWithCovarianceStamped")
    plan = subscribe(node, "plan", "nav_msgs/msg/Path")
    await wait_until(lambda: pose.msg is not None, timeout=10 + SLACK)
    start = pose.msg.pose.pose.position
    # room-a: through the door, 4.5 m from the start (room-b is a 9 m drive).
    room_a = small_map().places()["room-a"]
    record = send(node, nav_goal(node, room_a.x, room_a.y))
    await wait_until(lambda: len(record.feedback) > 2, timeout=10 + SLACK)
    # A zero velocity command (a teleop's, the stop stream of a daemon) leaves the goal alone,
    # as on a Nav2 robot whose controller publishes on cmd_vel too.
    twist = node.library.message("geometry_msgs/msg/Twist")
    cmd_vel = node.publisher("cmd_vel", twist)

    def ended() -> bool:
        cmd_vel.publish(twist.make())  # every 10 ms until the goal ends
        return record.status is not None

    await wait_until(ended, timeout=30 + SLACK)
    assert record.accepted is True
    assert record.status == SUCCEEDED, record.text
    assert record.feedback, "no feedback"
    assert any(fb.distance_remaining > 1.0 for fb in record.feedback)
    assert all(fb.current_pose.header.frame_id == "map" for fb in record.feedback)
    assert plan.count >= 1
    here = pose.msg.pose.pose.position
    assert math.hypot(here.x - room_a.x, here.y - room_a.y) < 0.3
    assert math.hypot(here.x - start.x, here.y - start.y) > 3.0


async def test_nav2s_speed_limit_topic_caps_a_navigation_goal(node: Ros2Node) -> None:
    """A daemon's speed cap (nav2_msgs/SpeedLimit on /speed_limit) holds for navigation too."""
    limit_type = node.library.message("nav2_msgs/msg/SpeedLimit")
    limits = node.publisher("speed_limit", limit_type, qos=QoS.transient_local())
    limits.publish(limit_type.make(percentage=False, speed_limit=0.3))  # the fast sim: 1.5
    speeds: list[float] = []

    def on_odom(msg: Any, _attachment: Attachment) -> None:
        speeds.append(abs(msg.twist.twist.linear.x))

    node.subscribe("odom", node.library.message("nav_msgs/msg/Odometry"), on_odom)
    room_b = small_map().places()["room-b"]
    record = send(node, nav_goal(node, room_b.x, room_b.y))
    await wait_until(lambda: len(speeds) > 60 and max(speeds) > 0.2, timeout=20 + SLACK)
    assert max(speeds) <= 0.3 + 1e-6
    # 0 is Nav2's "no limit": the top speed again.
    limits.publish(limit_type.make(percentage=False, speed_limit=0.0))
    await wait_until(lambda: max(speeds) > 0.5 or record.status is not None, timeout=20 + SLACK)
    assert max(speeds) > 0.5


async def test_a_goal_without_a_path_is_aborted_with_nav2s_reason(still_node: Ros2Node) -> None:
    node = still_node
    record = send(node, nav_goal(node, 500.0, 500.0))  # far outside the map
    await wait_until(lambda: record.status is not None, timeout=10 + SLACK)
    assert record.status == ABORTED
    assert record.result.error_code == 208  # ComputePathToPose NO_VALID_PATH
    assert "no path" in record.result.error_msg


async def test_cmd_vel_drives_and_the_base_stops_when_commands_stop(node: Ros2Node) -> None:
    odom = subscribe(node, "odom", "nav_msgs/msg/Odometry")
    twist_type = node.library.message("geometry_msgs/msg/Twist")
    vector = node.library.message("geometry_msgs/msg/Vector3")
    cmd_vel = node.publisher("cmd_vel", twist_type)
    await wait_until(lambda: odom.msg is not None, timeout=10 + SLACK)
    start = odom.msg.pose.pose.position.x
    forward = twist_type.make(linear=vector.make(x=0.3), angular=vector.make())

    def moving() -> bool:
        cmd_vel.publish(forward)  # every 10 ms while waiting: a teleop stream
        return odom.msg.twist.twist.linear.x > 0.2

    await wait_until(moving, timeout=10 + SLACK)
    stopped_sending = time.time()
    await wait_until(lambda: odom.msg.twist.twist.linear.x == 0.0, timeout=5 + SLACK)
    stamp = odom.msg.header.stamp
    # The base's own watchdog (0.5 s) and braking: the odometry says when it stood still.
    assert stamp.sec + stamp.nanosec * 1e-9 - stopped_sending < 0.5 + 1.0 + SLACK
    assert odom.msg.pose.pose.position.x > start + 0.1


async def test_killing_the_goals_client_stops_the_base(
    sim: Sim, node: Ros2Node, processes: list[Process]
) -> None:
    odom = subscribe(node, "odom", "nav_msgs/msg/Odometry")
    corridor = small_map().places()["corridor"]
    sender = Process(
        ["ros2_goal_proc", sim.endpoint, str(corridor.x), str(corridor.y)], env=child_env()
    )
    processes.append(sender)
    assert sender.next_line(timeout=30) == "accepted"
    await wait_until(
        lambda: odom.msg is not None and odom.msg.twist.twist.linear.x > 0.3, timeout=10 + SLACK
    )
    killed = time.time()
    sender.signal(signal.SIGKILL)
    await wait_until(lambda: odom.msg.twist.twist.linear.x == 0.0, timeout=5 + SLACK)
    # Stopped because the goal's client left, not for any other reason.
    await wait_until(lambda: "its action client left" in sim.process.stderr(), timeout=5 + SLACK)
    stamp = odom.msg.header.stamp
    assert stamp.sec + stamp.nanosec * 1e-9 - killed < 0.5 + SLACK
    # And it stays put: the goal was ended, not paused.
    x = odom.msg.pose.pose.position.x
    seen = odom.count
    await wait_until(lambda: odom.count > seen + 20, timeout=5 + SLACK)
    assert odom.msg.pose.pose.position.x == pytest.approx(x, abs=0.01)
    assert sim.process.popen.poll() is None


async def test_a_cancelled_goal_stops_the_robot_and_ends_canceled(node: Ros2Node) -> None:
    odom = subscribe(node, "odom", "nav_msgs/msg/Odometry")
    corridor = small_map().places()["corridor"]
    record = send(node, nav_goal(node, corridor.x, corridor.y))
    await wait_until(
        lambda: odom.msg is not None and odom.msg.twist.twist.linear.x > 0.3, timeout=10 + SLACK
    )
    record.client.cancel(record.goal_id)
    await wait_until(lambda: record.status is not None, timeout=5 + SLACK)
    assert record.status == CANCELED
    await wait_until(lambda: odom.msg.twist.twist.linear.x == 0.0, timeout=2 + SLACK)


async def settled(odom: Any) -> Any:
    """The odometry once the base is at rest: a behaviour's result may come before the
    odometry of its last control step (a loaded machine delays that message)."""

    def at_rest() -> bool:
        twist = odom.msg.twist.twist
        return bool(twist.linear.x == 0.0 and twist.angular.z == 0.0)

    await wait_until(at_rest, timeout=2 + SLACK)
    return odom.msg


async def test_drive_on_heading_and_spin_behaviours(node: Ros2Node) -> None:
    odom = subscribe(node, "odom", "nav_msgs/msg/Odometry")
    await wait_until(lambda: odom.msg is not None, timeout=10 + SLACK)
    m, lib = node.library.message, node.library
    drive_type = lib.action("nav2_msgs/action/DriveOnHeading")
    speeds: list[float] = []
    node.subscribe(
        "odom",
        lib.message("nav_msgs/msg/Odometry"),
        lambda msg, _att: speeds.append(abs(msg.twist.twist.linear.x)),
    )
    x0, y0 = odom.msg.pose.pose.position.x, odom.msg.pose.pose.position.y
    drive = send(
        node,
        drive_type.goal.make(target=m("geometry_msgs/msg/Point").make(x=1.0), speed=0.5),
        "drive_on_heading",
        "DriveOnHeading",
    )
    await wait_until(lambda: drive.status is not None, timeout=15 + SLACK)
    assert drive.status == SUCCEEDED, drive.result
    assert drive.feedback and drive.feedback[-1].distance_traveled > 0.0
    here = (await settled(odom)).pose.pose.position
    assert here.x - x0 == pytest.approx(1.0, abs=0.1)  # the start place faces +x
    assert here.y == pytest.approx(y0, abs=0.1)
    assert 0.3 < max(speeds) <= 0.5 + 1e-6  # the goal's speed caps a base good for 1.5 m/s
    spin = send(
        node,
        lib.action("nav2_msgs/action/Spin").goal.make(target_yaw=math.pi / 2),
        "spin",
        "Spin",
    )
    await wait_until(lambda: spin.status is not None, timeout=15 + SLACK)
    assert spin.status == SUCCEEDED, spin.result
    q = (await settled(odom)).pose.pose.orientation
    assert math.atan2(2 * q.w * q.z, 1 - 2 * q.z * q.z) == pytest.approx(math.pi / 2, abs=0.1)
    y1 = (await settled(odom)).pose.pose.position.y
    backup = send(
        node,
        lib.action("nav2_msgs/action/BackUp").goal.make(
            target=m("geometry_msgs/msg/Point").make(x=0.5), speed=0.3
        ),
        "backup",
        "BackUp",
    )
    await wait_until(lambda: backup.status is not None, timeout=15 + SLACK)
    assert backup.status == SUCCEEDED, backup.result
    assert (await settled(odom)).pose.pose.position.y - y1 == pytest.approx(
        -0.5, abs=0.1
    )  # facing +y
    # A speed and a target of opposite signs is Nav2's INVALID_INPUT.
    bad = send(
        node,
        drive_type.goal.make(target=m("geometry_msgs/msg/Point").make(x=1.0), speed=-0.5),
        "drive_on_heading",
        "DriveOnHeading",
    )
    await wait_until(lambda: bad.status is not None, timeout=10 + SLACK)
    assert bad.status == ABORTED
    assert bad.result.error_code == 724 and "opposite signs" in bad.result.error_msg


async def test_cameras_tf_battery_and_scan(still_node: Ros2Node) -> None:
    node = still_node
    camera = subscribe(node, "navcam/image/compressed", "sensor_msgs/msg/CompressedImage")
    tf = subscribe(node, "/tf", "tf2_msgs/msg/TFMessage")
    battery = subscribe(node, "battery_state", "sensor_msgs/msg/BatteryState")
    scan = subscribe(node, "scan", "sensor_msgs/msg/LaserScan")
    # Images are rendered only while someone subscribes: the sim sees us within a second.
    await wait_until(
        lambda: None not in (camera.msg, tf.msg, battery.msg, scan.msg), timeout=10 + SLACK
    )
    assert camera.msg.format == "jpeg"
    image = cv2.imdecode(np.asarray(camera.msg.data, dtype=np.uint8), cv2.IMREAD_COLOR)
    assert image is not None and image.shape == (480, 640, 3)
    (transform,) = tf.msg.transforms
    assert (transform.header.frame_id, transform.child_frame_id) == ("map", "base_link")
    start = small_map().places()["start"]
    assert transform.transform.translation.x == pytest.approx(start.x, abs=0.1)
    assert 0.0 < battery.msg.percentage <= 1.0 and battery.msg.present
    assert len(scan.msg.ranges) == 360 and scan.msg.angle_min == pytest.approx(-math.pi)
    assert np.isfinite(scan.msg.ranges).any()  # walls of the small map are within range


async def test_kilted_cmd_vel_is_twist_stamped(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = write_config(tmp_path / "robot.toml", sim=FAST_SIM)
    args = ["--config", str(config), "--listen", endpoint, "--distro", "kilted"]
    process = Process(["telebot.apps.sim_cli", *args])
    try:
        assert "serving map" in process.next_line(timeout=30)
        with Ros2Node(
            name="kilted_test", connect=[endpoint], library=TypeLibrary("kilted")
        ) as node:
            odom = subscribe(node, "odom", "nav_msgs/msg/Odometry")
            m = node.library.message
            stamped = m("geometry_msgs/msg/TwistStamped")
            cmd_vel = node.publisher("cmd_vel", stamped)
            forward = stamped.make(
                twist=m("geometry_msgs/msg/Twist").make(
                    linear=m("geometry_msgs/msg/Vector3").make(x=0.3)
                )
            )

            def moving() -> bool:
                cmd_vel.publish(forward)
                return odom.msg is not None and odom.msg.twist.twist.linear.x > 0.2

            await wait_until(moving, timeout=10 + SLACK)
    finally:
        process.stop(graceful=True)


def run_sim(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "telebot.apps.sim_cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def test_help_describes_the_two_ways_to_reach_zenoh() -> None:
    done = run_sim("--help")
    assert done.returncode == 0
    assert "--router" in done.stdout and "--listen" in done.stdout


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--map", "no-such-map"], "no-such-map"),
        (["--domain", "999"], "domain_id"),
        (["--distro", "humble"], "invalid choice"),
        (["--listen", "nonsense"], "cannot listen on nonsense"),
        (["--router", f"tcp/127.0.0.1:{free_port()}"], "no zenoh router at"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args: list[str], words: str, tmp_path: Path) -> None:
    # A short wait for the router that is not there (the default is 5 s): how long it
    # waits is not what this test is about.
    config = write_config(tmp_path / "robot.toml")
    config.write_text(config.read_text() + "[ros2]\nconnect_timeout = 1.0\n")
    done = run_sim("--config", str(config), "--map", "small", *args)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("telebot-sim: error:"), done.stderr
    assert words in lines[0]


def test_a_taken_port_is_a_clear_error(still_sim: Sim) -> None:
    sim = still_sim
    done = run_sim("--map", "small", "--listen", sim.endpoint)
    assert done.returncode == 2, done.stderr
    assert f"cannot listen on {sim.endpoint}" in done.stderr
