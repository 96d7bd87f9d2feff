"""ROS 2 messages mapped to telebot's robot types (robot/ros2/convert.py): no network."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from telebot.reasons import Reason
from telebot.robot.mapfile import load_map
from telebot.robot.nav import Pose2D
from telebot.robot.ros2.convert import (
    TfTree,
    battery_from_msg,
    compose,
    covariance_xy_yaw,
    duration_fields,
    grid_from_msg,
    nav2_reason,
    path_from_msg,
    pose_from_msg,
    quaternion_fields,
    scan_from_msg,
    yaw_of,
)
from telebot.rosmsg.types import TypeLibrary


def ros2_data() -> Path:
    """The ROS 2 fixtures the tests carry (``tests/data/ros2``; SOURCES.md names their origin)."""
    return Path(__file__).resolve().parent / "data" / "ros2"


LIB = TypeLibrary("jazzy")


def msg(name: str, **fields: Any) -> Any:
    return LIB.message(name).make(**fields)


def wire(name: str, message: Any) -> Any:
    """``message`` after a CDR round trip, as a subscriber gets it."""
    mtype = LIB.message(name)
    return mtype.deserialize(mtype.serialize(message))


def ros_pose(x: float, y: float, yaw: float) -> Any:
    return msg(
        "geometry_msgs/msg/Pose",
        position=msg("geometry_msgs/msg/Point", x=x, y=y, z=0.0),
        orientation=msg("geometry_msgs/msg/Quaternion", **quaternion_fields(yaw)),
    )


def occupancy_msg(
    data: np.ndarray[Any, Any], width: int, height: int, *, resolution: float = 0.05, yaw: float = 0
) -> Any:
    info = msg(
        "nav_msgs/msg/MapMetaData",
        resolution=resolution,
        width=width,
        height=height,
        origin=ros_pose(-10.0, -5.0, yaw),
    )
    return msg("nav_msgs/msg/OccupancyGrid", info=info, data=np.asarray(data, dtype=np.int8))


def test_a_real_nav2_map_survives_cdr_and_converts_cell_for_cell() -> None:
    yaml_path = ros2_data() / "maps" / "tb3_sandbox.yaml"
    grid = load_map(yaml_path)
    sent = occupancy_msg(grid.data.reshape(-1), grid.width, grid.height)
    got = grid_from_msg(wire("nav_msgs/msg/OccupancyGrid", sent), max_cells=10**8)
    assert (got.width, got.height) == (grid.width, grid.height)
    assert np.array_equal(got.data, grid.data)
    assert got.resolution == pytest.approx(0.05)
    assert (got.origin_x, got.origin_y) == (-10.0, -5.0)
    # Row 0 is the row at the origin in both: cell (0, 0) is at the origin's corner.
    assert got.cell_of(-10.0 + 0.01, -5.0 + 0.01) == (0, 0)


@pytest.mark.parametrize(
    ("width", "height", "cells", "kwargs", "needle"),
    [
        (100, 100, 10_000, {}, "over the limit of 9999"),
        (0, 5, 0, {}, "empty"),
        (4, 4, 15, {}, "carries 15"),
        (2, 2, 4, {"resolution": 0.0}, "resolution"),
        (2, 2, 4, {"yaw": 0.5}, "rotated"),
    ],
)
def test_a_bad_or_huge_map_is_refused_with_why(
    width: int, height: int, cells: int, kwargs: dict[str, Any], needle: str
) -> None:
    message = occupancy_msg(np.zeros(cells), width, height, **kwargs)
    with pytest.raises(ValueError, match=needle):
        grid_from_msg(message, max_cells=9_999)


def test_pose_covariance_path_and_quaternions() -> None:
    stamped = msg(
        "geometry_msgs/msg/PoseWithCovarianceStamped",
        pose=msg(
            "geometry_msgs/msg/PoseWithCovariance",
            pose=ros_pose(1.5, -2.0, 2.5),
            covariance=np.arange(36, dtype=np.float64),
        ),
    )
    got = wire("geometry_msgs/msg/PoseWithCovarianceStamped", stamped)
    pose = pose_from_msg(got.pose.pose)
    assert (pose.x, pose.y) == (1.5, -2.0) and pose.yaw == pytest.approx(2.5)
    assert covariance_xy_yaw(got.pose.covariance) == (0, 1, 5, 6, 7, 11, 30, 31, 35)
    path = msg(
        "nav_msgs/msg/Path",
        poses=[
            msg("geometry_msgs/msg/PoseStamped", pose=ros_pose(i, 2 * i, 0.1 * i)) for i in range(4)
        ],
    )
    poses = path_from_msg(wire("nav_msgs/msg/Path", path))
    assert [(p.x, p.y) for p in poses] == [(0, 0), (1, 2), (2, 4), (3, 6)]
    assert poses[3].yaw == pytest.approx(0.3)
    for yaw in (-3.0, -1.0, 0.0, 1.0, 3.1):
        q = msg("geometry_msgs/msg/Quaternion", **quaternion_fields(yaw))
        assert yaw_of(q) == pytest.approx(yaw)
    with pytest.raises(ValueError, match="not finite"):
        pose_from_msg(ros_pose(math.nan, 0.0, 0.0))
    assert duration_fields(2.25) == {"sec": 2, "nanosec": 250_000_000}


@pytest.mark.parametrize(
    ("fields", "percent", "low", "charging"),
    [
        ({"percentage": 0.55}, 55.0, False, False),
        ({"percentage": 0.15, "power_supply_status": 1}, 15.0, True, True),
        ({"percentage": 87.0}, 87.0, False, False),  # a driver that sends percent
        ({"percentage": math.nan, "charge": 1.0, "capacity": 4.0}, 25.0, False, False),
    ],
)
def test_battery_state(fields: dict[str, Any], percent: float, low: bool, charging: bool) -> None:
    battery = battery_from_msg(
        wire("sensor_msgs/msg/BatteryState", msg("sensor_msgs/msg/BatteryState", **fields)), 20.0
    )
    assert (battery.percent, battery.low, battery.charging) == (percent, low, charging)


def test_a_battery_state_without_any_charge_is_refused() -> None:
    with pytest.raises(ValueError, match="no percentage"):
        battery_from_msg(msg("sensor_msgs/msg/BatteryState", percentage=math.nan), 20.0)


def transform(parent: str, child: str, x: float, y: float, yaw: float) -> Any:
    return msg(
        "geometry_msgs/msg/TransformStamped",
        header=msg("std_msgs/msg/Header", frame_id=parent),
        child_frame_id=child,
        transform=msg(
            "geometry_msgs/msg/Transform",
            translation=msg("geometry_msgs/msg/Vector3", x=x, y=y),
            rotation=msg("geometry_msgs/msg/Quaternion", **quaternion_fields(yaw)),
        ),
    )


def test_tf_chains_map_odom_base_link() -> None:
    tree = TfTree()
    assert tree.lookup("map", "base_link") is None
    tree.update([transform("odom", "base_footprint", 0, 0, 0)], 1.0, static=True)
    tree.update([transform("map", "odom", 1.0, 0.0, math.pi / 2)], 2.0)
    tree.update([transform("odom", "base_link", 2.0, 0.0, 0.0)], 3.0)
    found = tree.lookup("map", "base_link")
    assert found is not None
    pose, oldest = found
    # base_link is 2 m along odom's x, which points along map's y.
    assert (pose.x, pose.y) == pytest.approx((1.0, 2.0))
    assert pose.yaw == pytest.approx(math.pi / 2)
    assert oldest == 2.0
    assert tree.lookup("/map", "base_footprint") is not None
    assert compose(Pose2D(0, 0, math.pi), Pose2D(1, 0, 0)).x == pytest.approx(-1.0)
    # A loop in a broken tree ends the lookup.
    tree.update([transform("a", "b", 0, 0, 0), transform("b", "a", 0, 0, 0)], 4.0)
    assert tree.lookup("map", "a") is None


def test_nav2_error_codes_map_to_reasons() -> None:
    assert nav2_reason(208) is Reason.NO_PATH  # ComputePathToPose NO_VALID_PATH
    assert nav2_reason(204) is Reason.NO_PATH  # GOAL_OUTSIDE_MAP
    assert nav2_reason(723) is Reason.OBSTACLE  # DriveOnHeading COLLISION_AHEAD
    assert nav2_reason(9000) is Reason.FAILED


def test_a_laser_scan_message_becomes_scan_data_for_people_detection() -> None:
    ranges = np.array([1.0, math.inf, 0.01, 50.0, math.nan, 2.5], dtype=np.float32)
    scan = scan_from_msg(
        wire(
            "sensor_msgs/msg/LaserScan",
            msg(
                "sensor_msgs/msg/LaserScan",
                angle_min=0.5,
                angle_max=-0.5,
                angle_increment=-0.2,
                range_min=0.05,
                range_max=10.0,
                ranges=ranges,
            ),
        )
    )
    # A clockwise scanner comes out in increasing angles; readings out of range are inf.
    assert scan.angles == pytest.approx([-0.5, -0.3, -0.1, 0.1, 0.3, 0.5])
    assert list(scan.ranges) == [2.5, math.inf, math.inf, math.inf, math.inf, 1.0]
    assert scan.range_max == 10.0
    with pytest.raises(ValueError, match="angle_increment"):
        scan_from_msg(msg("sensor_msgs/msg/LaserScan", angle_increment=0.0, range_max=10.0))
