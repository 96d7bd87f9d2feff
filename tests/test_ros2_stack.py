"""The ROS 2 robot adapter against a fake Nav2 over real zenoh (a router on loopback).

The fake Nav2 is written with the node's own publishers and action servers, in this
process; :mod:`telebot.robot.ros2.stack` reaches it through a zenoh router, as it reaches
``rmw_zenohd`` on a robot.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import math
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
import zenoh

from conftest import SLACK, Homes, wait_until
from rig import Daemon, start_telebot_sim
from telebot.config import RobotConfig
from telebot.errors import InvalidCommand, RobotUnreachable
from telebot.identity import Role
from telebot.reasons import Reason, Refusal
from telebot.robot import create_robot
from telebot.robot.mapfile import places_path_for
from telebot.robot.nav import GoalStatus, NavState, PoseNotifier
from telebot.robot.perception.tracks import PersonTrack
from telebot.robot.ros2 import stack as stack_module
from telebot.robot.ros2.convert import quaternion_fields
from telebot.robot.ros2.keys import QoS
from telebot.robot.ros2.node import Ros2Node
from telebot.robot.ros2.stack import Ros2NavStack
from telebot.robot.sim.building import resolve_map
from telebot.services.drive.follow import FollowService
from telebot.services.drive.robot import CallDrive, DriveService
from telebot.services.drive.wire import DriveCommand, decode_drive_state
from telebot.testing.net import free_port
from test_drive import FakeCall

pytestmark = pytest.mark.zenoh

#: The fake map: 120 x 80 cells at 5 cm, origin (-3, -2); a wall at column 100.
MAP_W, MAP_H, RES, ORIGIN = 120, 80, 0.05, (-3.0, -2.0)
ZERO_GOAL = bytes(16)


@pytest.fixture
def router() -> Iterator[str]:
    """A zenoh router on a free loopback port (what rmw_zenohd is on a robot)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = zenoh.Config()
    config.insert_json5("mode", '"router"')
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(config)
    try:
        yield endpoint
    finally:
        session.close()


def fake_map() -> np.ndarray[Any, np.dtype[np.int8]]:
    data = np.zeros((MAP_H, MAP_W), dtype=np.int8)
    data[:, 100] = 100
    data[70:, :] = -1
    return data


class FakeNav2:
    """Nav2 as seen over rmw_zenoh: map, pose, odom, battery, plan, camera, three actions."""

    def __init__(self, endpoint: str, *, distro: str = "jazzy", stamped: bool = False) -> None:
        from telebot.rosmsg.types import TypeLibrary

        self.node = node = Ros2Node(
            name="fake_nav2", connect=[endpoint], mode="client", library=TypeLibrary(distro)
        )
        self.lib = lib = node.library
        self.m = lib.message
        self.map_pub = node.publisher(
            "map", self.m("nav_msgs/msg/OccupancyGrid"), qos=QoS.transient_local()
        )
        self.pose_pub = node.publisher(
            "amcl_pose", self.m("geometry_msgs/msg/PoseWithCovarianceStamped")
        )
        self.odom_pub = node.publisher("odom", self.m("nav_msgs/msg/Odometry"))
        self.battery_pub = node.publisher("battery_state", self.m("sensor_msgs/msg/BatteryState"))
        self.plan_pub = node.publisher("plan", self.m("nav_msgs/msg/Path"))
        self.camera_pub = node.publisher(
            "camera/front/compressed", self.m("sensor_msgs/msg/CompressedImage")
        )
        twist = "geometry_msgs/msg/TwistStamped" if stamped else "geometry_msgs/msg/Twist"
        self.cmd_vel: list[tuple[float, Any]] = []
        self.cmd_sub = node.subscribe(
            "cmd_vel", self.m(twist), lambda msg, _att: self.cmd_vel.append((time.monotonic(), msg))
        )
        self.accept = True
        self.goals: dict[str, list[tuple[bytes, Any]]] = {"navigate": [], "drive": [], "spin": []}
        self.cancels: list[bytes] = []
        self.servers = {
            kind: node.action_server(
                name,
                lib.action(f"nav2_msgs/action/{action}"),
                on_goal=lambda gid, goal, kind=kind: self._on_goal(kind, gid, goal),
                on_cancel=self._on_cancel,
            )
            for kind, name, action in (
                ("navigate", "navigate_to_pose", "NavigateToPose"),
                ("drive", "drive_on_heading", "DriveOnHeading"),
                ("spin", "spin", "Spin"),
            )
        }

    def _on_goal(self, kind: str, goal_id: bytes, goal: Any) -> bool:
        self.goals[kind].append((bytes(goal_id), goal))
        return self.accept

    def _on_cancel(self, goal_id: bytes) -> bool:
        self.cancels.append(bytes(goal_id))
        return True

    def close(self) -> None:
        self.node.close()

    # ---------------------------------------------------------------- messages

    def pose(self, x: float, y: float, yaw: float) -> Any:
        return self.m("geometry_msgs/msg/Pose").make(
            position=self.m("geometry_msgs/msg/Point").make(x=x, y=y),
            orientation=self.m("geometry_msgs/msg/Quaternion").make(**quaternion_fields(yaw)),
        )

    def publish_map(
        self, data: np.ndarray[Any, Any], width: int, height: int, *, stamp: int = 0
    ) -> None:
        info = self.m("nav_msgs/msg/MapMetaData").make(
            resolution=RES, width=width, height=height, origin=self.pose(*ORIGIN, 0.0)
        )
        time_msg = self.m("builtin_interfaces/msg/Time").make(sec=stamp)
        self.map_pub.publish(
            self.m("nav_msgs/msg/OccupancyGrid").make(
                header=self.m("std_msgs/msg/Header").make(frame_id="map", stamp=time_msg),
                info=info,
                data=np.asarray(data, dtype=np.int8).reshape(-1),
            )
        )

    def publish_state(self) -> None:
        covariance = np.zeros(36)
        covariance[0], covariance[7], covariance[35] = 0.01, 0.02, 0.03
        self.pose_pub.publish(
            self.m("geometry_msgs/msg/PoseWithCovarianceStamped").make(
                pose=self.m("geometry_msgs/msg/PoseWithCovariance").make(
                    pose=self.pose(1.0, 0.5, math.pi / 4), covariance=covariance
                )
            )
        )
        twist = self.m("geometry_msgs/msg/Twist").make(
            linear=self.m("geometry_msgs/msg/Vector3").make(x=0.25),
            angular=self.m("geometry_msgs/msg/Vector3").make(z=-0.5),
        )
        self.odom_pub.publish(
            self.m("nav_msgs/msg/Odometry").make(
                twist=self.m("geometry_msgs/msg/TwistWithCovariance").make(twist=twist)
            )
        )
        self.battery_pub.publish(self.m("sensor_msgs/msg/BatteryState").make(percentage=0.15))
        stamped = self.m("geometry_msgs/msg/PoseStamped")
        self.plan_pub.publish(
            self.m("nav_msgs/msg/Path").make(
                poses=[stamped.make(pose=self.pose(0.1 * i, 0.2 * i, 0.0)) for i in range(5)]
            )
        )

    def publish_image(self, image: np.ndarray[Any, Any]) -> None:
        ok, jpeg = cv2.imencode(".jpg", image)
        assert ok
        self.camera_pub.publish(
            self.m("sensor_msgs/msg/CompressedImage").make(
                format="jpeg", data=np.frombuffer(jpeg.tobytes(), dtype=np.uint8)
            )
        )


def config_for(endpoint: str, tmp_path: Path, **ros2: Any) -> RobotConfig:
    places = tmp_path / "places.toml"
    places.write_text("[places.lab]\nx = 2.0\ny = 1.0\nyaw_deg = 90.0\n")
    settings: dict[str, Any] = {
        "router": [endpoint],
        "connect_timeout": 5.0 + SLACK,
        "cameras": {"front": "camera/front/compressed"},
        "places_file": "places.toml",
        "max_map_cells": 50_000,
        # A loaded machine can starve the link's keep-alives past the default 0.5 s, and a
        # dropped link fails the running goal (test_ros2_e2e checks the default lease).
        "lease": 5.0,
    }
    settings.update(ros2)
    return RobotConfig.model_validate({"robot": {"kind": "ros2"}, "ros2": settings})


@pytest.fixture
def nav2(router: str) -> Iterator[FakeNav2]:
    fake = FakeNav2(router)
    fake.publish_map(fake_map(), MAP_W, MAP_H)
    try:
        yield fake
    finally:
        fake.close()


@pytest.fixture
def stack(router: str, nav2: FakeNav2, tmp_path: Path) -> Iterator[Ros2NavStack]:
    robot = Ros2NavStack.from_config(config_for(router, tmp_path), base_dir=tmp_path)
    try:
        yield robot
    finally:
        robot.close()


# --------------------------------------------------------------------------- state


async def test_the_map_arrives_converted_and_each_new_one_bumps_the_version(
    stack: Ros2NavStack, nav2: FakeNav2
) -> None:
    grid = stack.map()
    assert (grid.width, grid.height, grid.resolution) == (MAP_W, MAP_H, pytest.approx(RES))
    assert (grid.origin_x, grid.origin_y) == ORIGIN
    assert np.array_equal(grid.data, fake_map())
    assert grid.value_at(-3.0 + 100.5 * RES, 0.0) == 100  # the wall, in world coordinates
    version = stack.map_version()
    nav2.publish_map(np.zeros((10, 20), np.int8), 20, 10)
    await wait_until(lambda: stack.map_version() > version)
    assert (stack.map().width, stack.map().height) == (20, 10)


async def test_a_map_republished_unchanged_keeps_its_version_a_changed_cell_bumps_it_once(
    stack: Ros2NavStack, nav2: FakeNav2
) -> None:
    # A SLAM node or map server republishing on a timer: same cells, a new header stamp.
    def received() -> int:
        text = stack.diagnostics()["map"]
        return int(text.split("(")[1].split(" received")[0])

    async def republish(cells: Any, stamps: range) -> None:
        # One at a time, each until it is received: a burst may lose a sample on a loaded
        # machine (zenoh drops rather than blocks), and what counts is that every copy that
        # arrives is judged.
        for stamp in stamps:
            before = received()
            for _ in range(5):
                nav2.publish_map(cells, MAP_W, MAP_H, stamp=stamp)
                with contextlib.suppress(AssertionError):
                    await wait_until(lambda b=before: received() > b, timeout=2.0 + SLACK)
                    break
            else:
                raise AssertionError(f"map {stamp} never received")

    await wait_until(lambda: received() >= 1)
    version, first, start = stack.map_version(), stack.map(), received()
    await republish(fake_map(), range(1, 6))
    assert received() >= start + 5
    assert stack.map_version() == version
    assert stack.map() is first  # the same snapshot: nothing downstream re-encodes it

    changed = fake_map()
    changed[10, 10] = 100
    await republish(changed, range(6, 11))
    assert received() >= start + 10
    assert stack.map_version() == version + 1
    assert stack.map().value_at(-3.0 + 10.5 * RES, -2.0 + 10.5 * RES) == 100


async def test_a_huge_or_malformed_map_is_dropped_and_logged_with_its_topic(
    stack: Ros2NavStack, nav2: FakeNav2, caplog: pytest.LogCaptureFixture
) -> None:
    version = stack.map_version()
    with caplog.at_level(logging.WARNING):
        nav2.publish_map(np.zeros(300 * 300, np.int8), 300, 300)  # over max_map_cells
        nav2.publish_map(np.zeros(15, np.int8), 4, 4)  # says 16 cells, carries 15

        def logged() -> list[str]:
            return [r.getMessage() for r in caplog.records if "/map" in r.getMessage()]

        await wait_until(lambda: len(logged()) >= 2)
    assert any("90104-byte" in line for line in logged())
    assert any("4x4 cells but carries 15" in line for line in logged())
    assert stack.map_version() == version
    assert stack.map().width == MAP_W
    assert int(stack.diagnostics()["dropped"]) >= 2


async def test_pose_velocity_battery_and_plan_are_mapped(
    stack: Ros2NavStack, nav2: FakeNav2
) -> None:
    nav2.publish_state()
    await wait_until(lambda: stack.battery().percent == 15.0 and stack.pose().stamp > 0)
    await wait_until(lambda: stack.velocity().linear == 0.25)
    estimate = stack.pose()
    assert (estimate.pose.x, estimate.pose.y) == (1.0, 0.5)
    assert estimate.pose.yaw == pytest.approx(math.pi / 4)
    assert estimate.covariance[0] == 0.01 and estimate.covariance[4] == 0.02
    assert estimate.covariance[8] == 0.03
    assert stack.velocity().angular == -0.5
    assert stack.battery().low
    assert stack.status().state is NavState.MOVING  # odometry says it moves
    # The plan belongs to a navigation goal: none runs, so none is shown.
    assert stack.planned_path() == ()
    stack.navigate_to(2.0, 1.0)
    nav2.publish_state()
    await wait_until(lambda: len(stack.planned_path()) == 5)
    assert stack.planned_path()[4].x == pytest.approx(0.4)
    diagnostics = stack.diagnostics()
    assert diagnostics["nav2"] == "navigate_to_pose ready"
    assert diagnostics["router"].endswith(": connected")
    assert "120x80" in diagnostics["map"] and diagnostics["pose"] != "none yet"


async def test_each_new_pose_is_announced_to_listeners(stack: Ros2NavStack, nav2: FakeNav2) -> None:
    assert isinstance(stack, PoseNotifier)  # the daemon sends poses as they come
    heard: list[float] = []
    stack.add_pose_listener(lambda: heard.append(stack.pose().pose.x))
    nav2.publish_state()
    await wait_until(lambda: bool(heard))
    assert heard[-1] == pytest.approx(1.0)


async def test_garbage_and_impossible_values_are_dropped_and_counted(
    stack: Ros2NavStack, nav2: FakeNav2
) -> None:
    nav2.odom_pub.publish_cdr(b"\x00\x01\x00\x00garbage")  # not an Odometry
    await wait_until(lambda: stack.diagnostics()["dropped"] == "1")
    nav2.pose_pub.publish(
        nav2.m("geometry_msgs/msg/PoseWithCovarianceStamped").make(
            pose=nav2.m("geometry_msgs/msg/PoseWithCovariance").make(
                pose=nav2.pose(math.nan, 0.0, 0.0)
            )
        )
    )
    await wait_until(lambda: stack.diagnostics()["dropped"] == "2")
    assert stack.pose().stamp == 0  # no pose taken from it


async def test_without_a_pose_topic_the_pose_comes_from_tf(
    router: str, nav2: FakeNav2, tmp_path: Path
) -> None:
    robot = Ros2NavStack.from_config(config_for(router, tmp_path, pose_topic=""), base_dir=tmp_path)
    m = nav2.m
    tf_pub = nav2.node.publisher("/tf", m("tf2_msgs/msg/TFMessage"))

    def transform(parent: str, child: str, x: float, yaw: float) -> Any:
        return m("geometry_msgs/msg/TransformStamped").make(
            header=m("std_msgs/msg/Header").make(frame_id=parent),
            child_frame_id=child,
            transform=m("geometry_msgs/msg/Transform").make(
                translation=m("geometry_msgs/msg/Vector3").make(x=x),
                rotation=m("geometry_msgs/msg/Quaternion").make(**quaternion_fields(yaw)),
            ),
        )

    message = m("tf2_msgs/msg/TFMessage").make(
        transforms=[
            transform("map", "odom", 1.0, math.pi / 2),
            transform("odom", "base_link", 2.0, 0),
        ]
    )
    try:

        def located() -> bool:
            tf_pub.publish(message)
            return robot.pose().stamp > 0

        await wait_until(located)
        pose = robot.pose().pose
        assert (pose.x, pose.y) == (pytest.approx(1.0), pytest.approx(2.0))
        assert pose.yaw == pytest.approx(math.pi / 2)
    finally:
        robot.close()


async def test_a_camera_topic_gives_frames_and_is_subscribed_only_while_watched(
    stack: Ros2NavStack, nav2: FakeNav2, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(stack_module, "CAMERA_IDLE", 0.5)
    assert stack.active_camera == "navcam"  # black: the config names no navcam
    assert stack.get_frame().image.max() == 0
    assert nav2.camera_pub.subscriber_count() == 0  # nobody asked for the front camera
    stack.select_camera("FRONT")
    assert stack.get_frame().image.max() == 0  # subscribed now; no image yet
    image = np.zeros((48, 64, 3), np.uint8)
    image[:, :, 2] = 200  # red in BGR

    def arrived() -> bool:
        nav2.publish_image(image)
        return stack.cameras()[0].width == 64

    await wait_until(arrived)
    assert [(c.name, c.height) for c in stack.cameras()] == [("front", 48), ("navcam", 0)]
    frame = stack.get_frame()
    assert frame.camera == "front" and frame.image.shape == (48, 64, 3)
    assert abs(int(frame.image[24, 32, 2]) - 200) < 10 and frame.image[24, 32, 0] < 10
    # Nobody asks for frames any more: the topic is let go.
    await wait_until(lambda: nav2.camera_pub.subscriber_count() == 0)


# --------------------------------------------------------------------------- goals


async def test_a_goal_is_accepted_reports_progress_and_succeeds(
    stack: Ros2NavStack, nav2: FakeNav2
) -> None:
    handle = stack.navigate_to_place("lab")
    await wait_until(lambda: len(nav2.goals["navigate"]) == 1)
    goal_id, goal = nav2.goals["navigate"][0]
    assert goal.pose.header.frame_id == "map"
    assert (goal.pose.pose.position.x, goal.pose.pose.position.y) == (2.0, 1.0)
    assert goal.pose.pose.orientation.z == pytest.approx(math.sin(math.pi / 4))
    assert stack.current_goal() is handle and handle.status is GoalStatus.ACTIVE
    assert stack.status().state is NavState.MOVING
    server = nav2.servers["navigate"]
    feedback = nav2.lib.action("nav2_msgs/action/NavigateToPose").feedback_body
    # Nav2 says 0 m remaining until it has planned: that is no progress yet.
    server.publish_feedback(goal_id, feedback.make(distance_remaining=0.0))
    server.publish_feedback(goal_id, feedback.make(distance_remaining=4.0))
    server.publish_feedback(goal_id, feedback.make(distance_remaining=1.0))
    await wait_until(lambda: handle.progress >= 0.75)
    assert handle.progress == pytest.approx(0.75)
    result = nav2.lib.action("nav2_msgs/action/NavigateToPose").result
    server.succeed(goal_id, result.make())
    await wait_until(lambda: handle.status is GoalStatus.SUCCEEDED)
    assert handle.code == Reason.FINISHED and handle.progress == 1.0
    assert stack.current_goal() is None


async def test_nav2_rejecting_a_goal_fails_the_handle_with_its_reason(
    stack: Ros2NavStack, nav2: FakeNav2
) -> None:
    nav2.accept = False
    handle = stack.navigate_to(1.0, 1.0, label="desk")
    await wait_until(lambda: handle.status is GoalStatus.FAILED)
    assert "rejected" in handle.reason and "goto desk" in handle.reason
    assert handle.code == Reason.FAILED


async def test_nav2_aborting_a_goal_gives_its_error_text_and_code(
    stack: Ros2NavStack, nav2: FakeNav2
) -> None:
    handle = stack.navigate_to(1.0, 1.0)
    await wait_until(lambda: len(nav2.goals["navigate"]) == 1)
    goal_id, _ = nav2.goals["navigate"][0]
    result = nav2.lib.action("nav2_msgs/action/NavigateToPose").result
    nav2.servers["navigate"].abort(
        goal_id, result.make(error_code=208, error_msg="planner found no valid path")
    )
    await wait_until(lambda: handle.status is GoalStatus.FAILED)
    assert "planner found no valid path" in handle.reason and "208" in handle.reason
    assert handle.code == Reason.NO_PATH
    assert stack.status().state is NavState.FAILED


async def test_a_goal_fails_when_its_server_leaves_the_graph(
    stack: Ros2NavStack, nav2: FakeNav2
) -> None:
    handle = stack.navigate_to(1.0, 1.0)
    await wait_until(lambda: len(nav2.goals["navigate"]) == 1)
    nav2.servers["navigate"].close()  # Nav2 crashed
    await wait_until(lambda: handle.status is GoalStatus.FAILED)
    assert "left the ROS graph" in handle.reason and stack.current_goal() is None


def test_a_goal_in_a_wall_or_off_the_map_fails_at_once(stack: Ros2NavStack) -> None:
    wall = stack.navigate_to(-3.0 + 100.5 * RES, 0.0)
    outside = stack.navigate_to(50.0, 50.0)
    assert wall.status is GoalStatus.FAILED and "obstacle" in wall.reason
    assert outside.status is GoalStatus.FAILED and "outside the map" in outside.reason
    assert wall.code == outside.code == Reason.NO_PATH


async def test_cancel_sends_cancel_goal_with_the_goals_id(
    stack: Ros2NavStack, nav2: FakeNav2
) -> None:
    handle = stack.navigate_to(1.0, 1.0)
    await wait_until(lambda: len(nav2.goals["navigate"]) == 1)
    handle.cancel()
    assert handle.status is GoalStatus.CANCELLED and handle.code == Reason.CANCELLED
    await wait_until(lambda: len(nav2.cancels) == 1)
    assert nav2.cancels == [nav2.goals["navigate"][0][0]]
    assert stack.current_goal() is None


async def test_forward_and_turn_use_drive_on_heading_and_spin(
    stack: Ros2NavStack, nav2: FakeNav2
) -> None:
    stack.set_speed_limit(0.3)
    stack.forward(1.5)
    await wait_until(lambda: len(nav2.goals["drive"]) == 1)
    _, drive = nav2.goals["drive"][0]
    assert drive.target.x == 1.5 and drive.speed == pytest.approx(0.3)
    assert drive.time_allowance.sec >= 5
    back = stack.forward(-0.5)
    await wait_until(lambda: len(nav2.goals["drive"]) == 2)
    assert nav2.goals["drive"][1][1].speed == pytest.approx(-0.3)
    turn = stack.turn(math.pi / 2)  # REP-103: to the left
    await wait_until(lambda: len(nav2.goals["spin"]) == 1)
    assert nav2.goals["spin"][0][1].target_yaw == pytest.approx(math.pi / 2)
    # The spin replaced the drive, on another server: the drive was cancelled by its id.
    assert back.status is GoalStatus.CANCELLED and back.code == Reason.REPLACED
    await wait_until(lambda: nav2.goals["drive"][1][0] in nav2.cancels)
    assert stack.current_goal() is turn
    feedback = nav2.lib.action("nav2_msgs/action/Spin").feedback_body
    goal_id = nav2.goals["spin"][0][0]
    nav2.servers["spin"].publish_feedback(goal_id, feedback.make(angular_distance_traveled=0.8))
    await wait_until(lambda: turn.progress > 0.5)


def test_a_missing_behaviour_server_fails_the_move_at_once(
    router: str, nav2: FakeNav2, tmp_path: Path
) -> None:
    nav2.servers["drive"].close()  # a Nav2 without the drive_on_heading behaviour
    robot = Ros2NavStack.from_config(config_for(router, tmp_path), base_dir=tmp_path)
    try:
        running = robot.turn(1.0)
        move = robot.forward(1.0)
        assert move.status is GoalStatus.FAILED
        assert "no Nav2 'drive_on_heading' action server" in move.reason
        assert running.status is GoalStatus.ACTIVE  # the running goal goes on
    finally:
        robot.close()


async def test_the_speed_cap_goes_to_nav2s_speed_limit_topic(
    stack: Ros2NavStack, nav2: FakeNav2
) -> None:
    limits: list[tuple[bool, float]] = []
    nav2.node.subscribe(
        "speed_limit",
        nav2.m("nav2_msgs/msg/SpeedLimit"),
        lambda msg, _att: limits.append((bool(msg.percentage), float(msg.speed_limit))),
        qos=QoS.transient_local(),
    )
    await wait_until(lambda: bool(limits))  # the start-up cap, kept for late joiners
    assert limits[-1] == (False, 0.5)
    stack.set_speed_limit(0.2)
    await wait_until(lambda: limits[-1] == (False, 0.2))
    stack.set_speed_limit(0.0)  # Nav2's 0 would mean no limit: 1 cm/s instead
    await wait_until(lambda: limits[-1][1] == pytest.approx(0.01))


def test_no_motion_under_a_zero_speed_cap(stack: Ros2NavStack) -> None:
    stack.set_speed_limit(0.0)
    assert stack.forward(1.0).status is GoalStatus.FAILED
    assert stack.turn(1.0).status is GoalStatus.FAILED


# --------------------------------------------------------------------------- stopping


def zeros(nav2: FakeNav2) -> list[float]:
    times = []
    for at, msg in list(nav2.cmd_vel):
        twist = getattr(msg, "twist", msg)
        assert (twist.linear.x, twist.linear.y, twist.angular.z) == (0.0, 0.0, 0.0)
        times.append(at)
    return times


async def test_stop_cancels_every_goal_and_streams_zero_velocity_at_10_hz_or_more(
    stack: Ros2NavStack, nav2: FakeNav2
) -> None:
    handle = stack.navigate_to(1.0, 1.0)
    await wait_until(lambda: len(nav2.goals["navigate"]) == 1)
    stack.stop()
    assert handle.status is GoalStatus.CANCELLED and handle.code == Reason.STOPPED
    # Cancel all: the zero goal id (and zero stamp), on each of the three servers.
    await wait_until(lambda: len(nav2.cancels) >= 1)
    await wait_until(lambda: len(nav2.cmd_vel) >= 1)
    await wait_until(lambda: not stack._zero.streaming)
    await wait_until(lambda: len(nav2.cmd_vel) >= 10)
    times = zeros(nav2)
    # stop_stream_s = 1 at stop_rate_hz = 20: at least 10 in the stream's second.
    assert len(times) >= 10


def test_a_new_motion_ends_the_zero_stream_of_a_stop(stack: Ros2NavStack) -> None:
    stack.stop()
    assert stack._zero.streaming
    stack.forward(0.5)  # re-armed, the driver moves on: zeros would fight the motion
    assert not stack._zero.streaming


async def test_emergency_stop_works_from_another_thread_without_a_loop(
    router: str, tmp_path: Path
) -> None:
    nav2 = FakeNav2(router, stamped=True)
    nav2.publish_map(fake_map(), MAP_W, MAP_H)
    robot = Ros2NavStack.from_config(
        config_for(router, tmp_path, distro="jazzy", cmd_vel_stamped=True), base_dir=tmp_path
    )
    try:
        handle = robot.turn(1.0)
        await wait_until(lambda: len(nav2.goals["spin"]) == 1)
        thread = threading.Thread(target=robot.emergency_stop, args=("driver silent",))
        thread.start()
        thread.join()
        assert handle.status is GoalStatus.CANCELLED and handle.reason == "driver silent"
        await wait_until(lambda: len(nav2.cmd_vel) >= 3)
        header = nav2.cmd_vel[0][1].header
        assert header.frame_id == "base_link" and header.stamp.sec > 0  # TwistStamped
        zeros(nav2)
    finally:
        robot.close()
        nav2.close()


# --------------------------------------------------------------------------- start-up


def test_no_router_is_a_clear_error_quickly(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    started = time.monotonic()
    with pytest.raises(RobotUnreachable) as caught:
        Ros2NavStack.from_config(
            config_for(endpoint, tmp_path, connect_timeout=1.0), base_dir=tmp_path
        )
    assert str(caught.value) == (
        f"no ROS 2 router at {endpoint}: is rmw_zenohd (or telebot-sim) running?"
    )
    assert time.monotonic() - started < 1.0 + 2 * SLACK


def test_no_nav2_or_no_map_names_what_is_missing(router: str, tmp_path: Path) -> None:
    config = config_for(router, tmp_path, connect_timeout=1.0)
    with pytest.raises(RobotUnreachable, match="no Nav2 action server 'navigate_to_pose'"):
        Ros2NavStack.from_config(config, base_dir=tmp_path)
    nav2 = FakeNav2(router)  # the servers, but no map
    try:
        with pytest.raises(RobotUnreachable, match="no map on topic 'map'"):
            Ros2NavStack.from_config(config, base_dir=tmp_path)
    finally:
        nav2.close()


def test_another_action_type_on_the_server_names_both_hashes(router: str, tmp_path: Path) -> None:
    node = Ros2Node(name="odd_nav2", connect=[router])
    spin = node.library.action("nav2_msgs/action/Spin")
    navigate = node.library.action("nav2_msgs/action/NavigateToPose")
    server = node.action_server("navigate_to_pose", spin, on_goal=lambda gid, goal: True)
    try:
        with pytest.raises(RobotUnreachable) as caught:
            Ros2NavStack.from_config(
                config_for(router, tmp_path, connect_timeout=2.0 + SLACK), base_dir=tmp_path
            )
        text = str(caught.value)
        assert spin.send_goal.type_hash in text and navigate.send_goal.type_hash in text
        assert "[ros2] distro" in text and "\n" not in text
    finally:
        del server
        node.close()


def test_a_map_of_another_type_hash_names_both(router: str, tmp_path: Path) -> None:
    nav2 = FakeNav2(router)  # servers, and a map publisher that publishes nothing
    odd = Ros2Node(name="odd_map_server", connect=[router])
    path_type = odd.library.message("nav_msgs/msg/Path")
    odd.publisher("map", path_type)
    try:
        with pytest.raises(RobotUnreachable) as caught:
            Ros2NavStack.from_config(
                config_for(router, tmp_path, connect_timeout=2.0 + SLACK), base_dir=tmp_path
            )
        text = str(caught.value)
        assert text.startswith(f"the robot's map topic has type hash {path_type.type_hash}")
        assert odd.library.message("nav_msgs/msg/OccupancyGrid").type_hash in text
    finally:
        odd.close()
        nav2.close()


def test_the_registry_builds_it(router: str, nav2: FakeNav2, tmp_path: Path) -> None:
    robot = create_robot(config_for(router, tmp_path), base_dir=tmp_path)
    try:
        assert isinstance(robot, Ros2NavStack)
        assert robot.speed_limit == 0.5
        assert dict(robot.places())["lab"].x == 2.0
    finally:
        robot.close()


def test_telebot_robot_run_without_a_router_exits_2_with_one_line(
    homes: Homes, tmp_path: Path
) -> None:
    port = free_port()
    config = tmp_path / "robot.toml"
    config.write_text(
        f'[ros2]\nrouter = ["tcp/127.0.0.1:{port}"]\nconnect_timeout = 1.0\n'
        "[transport.zenoh]\nmulticast_scouting = false\n"
    )
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "telebot.apps.robot_cli",
            "run",
            "--robot",
            "ros2",
            "--home",
            str(homes.robot_home),
            "--config",
            str(config),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert lines == [
        f"telebot-robot: error: no ROS 2 router at tcp/127.0.0.1:{port}: "
        "is rmw_zenohd (or telebot-sim) running?"
    ]


# --------------------------------------------------------------------------- end to end


async def test_table_i_commands_drive_telebot_sim_across_processes(tmp_path: Path) -> None:
    """telebot-sim (its own router) and telebot-robot run --robot ros2, a user chatting."""
    daemon = Daemon(tmp_path)
    # The small map's places and one a short way along the corridor: a goto there takes a
    # second or two, where room-b, round the walls, is a 9 m drive.
    places = tmp_path / "places.toml"
    places.write_text(
        places_path_for(resolve_map("small")).read_text()
        + "\n[places.corridor-west]\nx = 3.5\ny = 1.2\nyaw_deg = 90.0\n"
    )
    sim, _ = start_telebot_sim(
        daemon,
        ros2={"max_linear_speed": 1.5, "max_angular_speed": 3.0, "places_file": str(places)},
        tables='[ros2.cameras]\nnavcam = "navcam/image/compressed"\n'
        'usercam = "usercam/image/compressed"\n',
    )
    try:
        daemon.start()
        async with daemon.connect() as robot:
            assert (await robot.stop()).ok
            assert (await robot.arm()).ok
            start = await robot.pose()
            forward = await robot.chat("fwd 1", timeout=60)
            assert forward.ok and forward.replies[-1] == "finished moving", forward.replies
            moved = await robot.pose()
            assert math.hypot(moved.x - start.x, moved.y - start.y) == pytest.approx(1.0, abs=0.15)
            turn = await robot.chat("turn 90", timeout=60)  # the paper's: to the right
            assert turn.ok, turn.replies
            turned = await robot.pose()
            change = math.degrees((turned.yaw - moved.yaw + math.pi) % (2 * math.pi) - math.pi)
            assert change == pytest.approx(-90.0, abs=5.0)
            goto = await robot.chat("goto corridor-west", timeout=90)
            assert goto.ok and goto.replies[-1] == "finished moving", goto.replies
            there = await robot.pose()
            assert math.hypot(there.x - 3.5, there.y - 1.2) < 0.3
            # A click on the map: a goal on the goals channel, with progress.
            updates: list[float] = []
            planned: list[int] = []

            def on_update(update: Any) -> None:
                updates.append(update.progress)
                plan = robot.plan
                planned.append(len(plan.points) if plan is not None else 0)

            final = await robot.goto(6.0, 1.2, timeout=90, on_update=on_update)
            assert final.status == "succeeded", final
            assert updates and max(updates) > 0.0
            # Nav2's /plan reaches the user as the planned path; the places too.
            assert max(planned) >= 2
            assert "room-b" in robot.places
            there = await robot.pose()
            assert math.hypot(there.x - 6.0, there.y - 1.2) < 0.3
            # stop while it drives: the goal ends "stopped" and the base comes to rest.
            replies = robot.chat_replies("goto start", timeout=90)
            async for reply in replies:
                assert reply.text == "Goto command received"
                break
            async for pose in robot.poses():
                if pose.v != 0:
                    break
            assert (await robot.stop()).ok
            texts = [reply.text async for reply in replies]
            assert texts and "stopped" in texts[-1], texts
            async for pose in robot.poses():
                if pose.v == 0 and pose.w == 0:
                    break
    finally:
        daemon.stop(graceful=True)
        sim.stop(graceful=True)


# --------------------------------------------------------------------------- follow-me


async def test_drive_publishes_cmd_vel_within_the_caps_and_replaces_a_goal(
    stack: Ros2NavStack, nav2: FakeNav2
) -> None:
    handle = stack.navigate_to(1.0, 1.0)
    await wait_until(lambda: len(nav2.goals["navigate"]) == 1)
    stack.set_speed_limit(0.3)
    stack.drive(0.8, 5.0)  # follow-me's velocity: clipped to the speed cap and top turn
    assert handle.status is GoalStatus.CANCELLED and handle.code == Reason.REPLACED
    await wait_until(lambda: len(nav2.cancels) >= 1)
    await wait_until(lambda: any(getattr(m, "twist", m).linear.x != 0.0 for _, m in nav2.cmd_vel))
    twist = next(getattr(m, "twist", m) for _, m in nav2.cmd_vel if getattr(m, "twist", m).linear.x)
    assert (twist.linear.x, twist.angular.z) == (pytest.approx(0.3), pytest.approx(1.0))
    # A stop streams zeros; the next velocity (after a re-arm) ends the stream.
    stack.stop()
    assert stack._zero.streaming
    stack.drive(0.1, 0.0)
    assert not stack._zero.streaming
    with pytest.raises(InvalidCommand):
        stack.drive(math.nan, 0.0)


async def test_follow_me_drives_a_ros2_robot_on_cmd_vel_once_its_laser_sees_the_way_clear(
    stack: Ros2NavStack, nav2: FakeNav2
) -> None:
    nav2.publish_state()  # the robot at (1.0, 0.5), heading 45°
    await wait_until(lambda: stack.pose().pose.x == pytest.approx(1.0))
    heading = math.pi / 4
    ux, uy = math.cos(heading), math.sin(heading)
    now = [0.0]

    class Ahead:
        """One person 2 m ahead, walking away at 0.3 m/s."""

        def tracks(self) -> list[PersonTrack]:
            x, y = 1.0 + ux * (2.0 + 0.3 * now[0]), 0.5 + uy * (2.0 + 0.3 * now[0])
            return [PersonTrack(4, x, y, 0.3 * ux, 0.3 * uy, 1.0, 0.0, now[0])]

    follow = FollowService(stack, people=Ahead())
    goal = follow.start("call", None, 0.0)
    assert not isinstance(goal, Refusal) and goal.description == "follow person 4"

    def tick_for(seconds: float) -> None:
        end = now[0] + seconds
        while now[0] < end:
            now[0] += 0.05
            follow.tick(now[0])

    def linear() -> list[float]:
        return [getattr(m, "twist", m).linear.x for _, m in list(nav2.cmd_vel)]

    # No scan yet: it does not drive ahead. Odometry says 0.25 m/s: it brakes from there
    # within its deceleration limit, never speeding up.
    tick_for(1.0)
    await wait_until(lambda: len(nav2.cmd_vel) >= 20)
    speeds = linear()
    assert speeds[0] <= 0.25 and all(b <= a for a, b in itertools.pairwise(speeds))
    assert speeds[-1] == 0.0
    nav2.cmd_vel.clear()
    scan = nav2.node.publisher("scan", nav2.m("sensor_msgs/msg/LaserScan"))
    scan.publish(
        nav2.m("sensor_msgs/msg/LaserScan").make(
            angle_min=-math.pi,
            angle_increment=math.pi / 180,
            range_min=0.1,
            range_max=10.0,
            ranges=np.full(360, np.inf, dtype=np.float32),
        )
    )
    await wait_until(lambda: stack.laser_scan() is not None)
    tick_for(0.5)
    await wait_until(lambda: max(linear(), default=0.0) > 0.1)
    assert max(linear()) <= stack.speed_limit + 1e-9
    follow.unfollow()  # the robot stops: zero velocity streams
    assert stack._zero.streaming


async def test_driving_by_hand_publishes_cmd_vel_within_the_cap_and_the_laser_s_room(
    stack: Ros2NavStack, nav2: FakeNav2
) -> None:
    """The ``drive`` service on a ROS 2 robot: cmd_vel, capped, braking before what the
    laser sees (no scan: no driving ahead), and a release streams zeros."""
    call = FakeCall("c1", "alice", Role.DRIVER)
    CallDrive(DriveService(stack), call, lambda: 0.0)  # type: ignore[arg-type]
    channel = call.channels["drive"]

    def linear() -> list[float]:
        return [getattr(m, "twist", m).linear.x for _, m in list(nav2.cmd_vel)]

    channel.receive(DriveCommand(1, 0.4, 0.5).encode())  # no scan yet
    assert decode_drive_state(channel.sent[-1]).code == Reason.OBSTACLE
    await wait_until(lambda: len(nav2.cmd_vel) >= 1)
    twist = getattr(nav2.cmd_vel[-1][1], "twist", nav2.cmd_vel[-1][1])
    assert (twist.linear.x, twist.angular.z) == (0.0, pytest.approx(0.5))
    ranges = np.full(360, 5.0, dtype=np.float32)
    ranges[178:183] = 0.4  # a wall 0.4 m straight ahead
    scan = nav2.node.publisher("scan", nav2.m("sensor_msgs/msg/LaserScan"))
    scan.publish(
        nav2.m("sensor_msgs/msg/LaserScan").make(
            angle_min=-math.pi,
            angle_increment=math.pi / 180,
            range_min=0.1,
            range_max=10.0,
            ranges=ranges,
        )
    )
    await wait_until(lambda: stack.laser_scan() is not None)
    nav2.cmd_vel.clear()
    stack.set_speed_limit(0.3)
    channel.receive(DriveCommand(2, 0.4, 0.0).encode())
    await wait_until(lambda: len(nav2.cmd_vel) >= 1)
    assert 0.0 < linear()[-1] < 0.3  # under the cap, and slowed for the wall
    assert decode_drive_state(channel.sent[-1]).active
    channel.receive(DriveCommand(3, -0.2, 0.0).encode())  # reversing: it sees 5 m free
    await wait_until(lambda: linear()[-1] == pytest.approx(-0.2))
    channel.receive(DriveCommand(4, 0.0, 0.0).encode())  # let go
    assert stack._zero.streaming
    assert decode_drive_state(channel.sent[-1]).code == Reason.RELEASED


async def test_a_scan_that_stopped_coming_is_no_scan(
    stack: Ros2NavStack, nav2: FakeNav2, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Follow-me and people detection must not plan on a frozen picture of free space.
    assert stack.laser_scan() is None
    scan = nav2.node.publisher("scan", nav2.m("sensor_msgs/msg/LaserScan"))
    scan.publish(
        nav2.m("sensor_msgs/msg/LaserScan").make(
            angle_min=-math.pi,
            angle_increment=math.pi / 180,
            range_min=0.1,
            range_max=10.0,
            ranges=np.full(360, 5.0, dtype=np.float32),
        )
    )
    await wait_until(lambda: stack.laser_scan() is not None)
    monkeypatch.setattr(stack_module, "SCAN_STALE", 0.0)  # as if SCAN_STALE seconds passed
    assert stack.laser_scan() is None
