"""A robot's state as ROS 2 messages: one place for ``telebot-sim`` and the relay.

:class:`SimMessages` builds the messages a Nav2 robot publishes (map, amcl_pose, odom, tf,
plan, scan, battery, compressed camera images) from telebot's robot types
(:mod:`telebot.robot.nav`), as the simulator has them.
:class:`~telebot.robot.ros2.simrobot.SimRobotServer` publishes them on rmw_zenoh; the
simulator's topic source (:mod:`telebot.rosmsg.topics`) serializes them to CDR for the
``relay`` service. No zenoh here: only :class:`~telebot.rosmsg.types.TypeLibrary`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from telebot.robot.nav import (
    Battery,
    LaserScanLike,
    Pose2D,
    PoseEstimate,
    Velocity,
    normalize_angle,
)

if TYPE_CHECKING:
    from telebot.robot.grid import OccupancyGrid
    from telebot.rosmsg.types import TypeLibrary

__all__ = ["BATTERY_HZ", "CAMERA_HZ", "JPEG_QUALITY", "SCAN_HZ", "SimMessages"]

#: Rates (Hz) of what is not sent every control step.
SCAN_HZ = 10.0
BATTERY_HZ = 1.0
CAMERA_HZ = 5.0
#: JPEG quality of the camera topics.
JPEG_QUALITY = 80


class SimMessages:
    """Builds the simulated robot's ROS messages (``wall``: the stamp, Unix seconds)."""

    def __init__(self, lib: TypeLibrary, *, map_frame: str = "map", base_frame: str = "base_link"):
        self.lib = lib
        self.map_frame = map_frame
        self.base_frame = base_frame
        m = lib.message
        self.t_header = m("std_msgs/msg/Header")
        self.t_time = m("builtin_interfaces/msg/Time")
        self.t_duration = m("builtin_interfaces/msg/Duration")
        self.t_pose = m("geometry_msgs/msg/Pose")
        self.t_point = m("geometry_msgs/msg/Point")
        self.t_quat = m("geometry_msgs/msg/Quaternion")
        self.t_vector3 = m("geometry_msgs/msg/Vector3")
        self.t_twist = m("geometry_msgs/msg/Twist")
        self.t_pose_stamped = m("geometry_msgs/msg/PoseStamped")
        self.t_pose_cov = m("geometry_msgs/msg/PoseWithCovariance")
        self.t_pose_cov_stamped = m("geometry_msgs/msg/PoseWithCovarianceStamped")
        self.t_twist_cov = m("geometry_msgs/msg/TwistWithCovariance")
        self.t_transform = m("geometry_msgs/msg/Transform")
        self.t_transform_stamped = m("geometry_msgs/msg/TransformStamped")
        self.t_tf = m("tf2_msgs/msg/TFMessage")
        self.t_odom = m("nav_msgs/msg/Odometry")
        self.t_map = m("nav_msgs/msg/OccupancyGrid")
        self.t_map_info = m("nav_msgs/msg/MapMetaData")
        self.t_path = m("nav_msgs/msg/Path")
        self.t_scan = m("sensor_msgs/msg/LaserScan")
        self.t_battery = m("sensor_msgs/msg/BatteryState")
        self.t_image = m("sensor_msgs/msg/CompressedImage")

    # -- parts

    def stamp(self, wall: float) -> Any:
        """A ``builtin_interfaces/Time`` of ``wall``."""
        sec = math.floor(wall)
        return self.t_time.make(sec=int(sec), nanosec=int((wall - sec) * 1e9))

    def duration(self, seconds: float) -> Any:
        """A ``builtin_interfaces/Duration`` (negative ones are 0)."""
        seconds = max(seconds, 0.0)
        sec = math.floor(seconds)
        return self.t_duration.make(sec=int(sec), nanosec=int((seconds - sec) * 1e9))

    def header(self, frame: str, wall: float) -> Any:
        """A ``std_msgs/Header``."""
        return self.t_header.make(stamp=self.stamp(wall), frame_id=frame)

    def quaternion(self, yaw: float) -> Any:
        """A rotation by ``yaw`` about z."""
        return self.t_quat.make(x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0))

    def pose(self, pose: Pose2D) -> Any:
        """A ``geometry_msgs/Pose`` on the ground plane."""
        yaw = pose.yaw if math.isfinite(pose.yaw) else 0.0
        return self.t_pose.make(
            position=self.t_point.make(x=pose.x, y=pose.y, z=0.0),
            orientation=self.quaternion(yaw),
        )

    def pose_stamped(self, pose: Pose2D, wall: float) -> Any:
        """A ``PoseStamped`` in the map frame."""
        return self.t_pose_stamped.make(
            header=self.header(self.map_frame, wall), pose=self.pose(pose)
        )

    # -- whole messages

    def map(self, grid: OccupancyGrid, wall: float) -> Any:
        """The ``nav_msgs/OccupancyGrid``."""
        info = self.t_map_info.make(
            map_load_time=self.stamp(wall),
            resolution=grid.resolution,
            width=grid.width,
            height=grid.height,
            origin=self.pose(Pose2D(grid.origin_x, grid.origin_y, 0.0)),
        )
        return self.t_map.make(
            header=self.header(self.map_frame, wall),
            info=info,
            data=np.ascontiguousarray(grid.data.reshape(-1), dtype=np.int8),
        )

    def amcl_pose(self, estimate: PoseEstimate, wall: float) -> Any:
        """The localisation estimate (``PoseWithCovarianceStamped``)."""
        c = estimate.covariance
        covariance = np.zeros(36, dtype=np.float64)
        # (x, y, yaw) of the 3x3 go to rows/columns 0, 1 and 5 of ROS's 6x6.
        for i, row in enumerate((0, 1, 5)):
            for j, col in enumerate((0, 1, 5)):
                covariance[row * 6 + col] = c[i * 3 + j]
        pose_cov = self.t_pose_cov.make(pose=self.pose(estimate.pose), covariance=covariance)
        return self.t_pose_cov_stamped.make(header=self.header(self.map_frame, wall), pose=pose_cov)

    def odom(self, truth: Pose2D, velocity: Velocity, wall: float) -> Any:
        """The odometry (``nav_msgs/Odometry``: true pose and velocity)."""
        twist = self.t_twist.make(
            linear=self.t_vector3.make(x=velocity.linear, y=0.0, z=0.0),
            angular=self.t_vector3.make(x=0.0, y=0.0, z=velocity.angular),
        )
        return self.t_odom.make(
            header=self.header("odom", wall),
            child_frame_id=self.base_frame,
            pose=self.t_pose_cov.make(pose=self.pose(truth)),
            twist=self.t_twist_cov.make(twist=twist),
        )

    def tf(self, here: Pose2D, wall: float) -> Any:
        """``/tf``: map -> base_link."""
        transform = self.t_transform_stamped.make(
            header=self.header(self.map_frame, wall),
            child_frame_id=self.base_frame,
            transform=self.t_transform.make(
                translation=self.t_vector3.make(x=here.x, y=here.y, z=0.0),
                rotation=self.quaternion(here.yaw),
            ),
        )
        return self.t_tf.make(transforms=[transform])

    def path(self, plan: tuple[Pose2D, ...], wall: float) -> Any:
        """The plan (``nav_msgs/Path``), oriented along the path as Nav2's planners do."""
        poses = []
        for i, point in enumerate(plan):
            nxt = plan[i + 1] if i + 1 < len(plan) else point
            prev = plan[i - 1] if i > 0 else point
            yaw = math.atan2(nxt.y - prev.y, nxt.x - prev.x) if len(plan) > 1 else point.yaw
            poses.append(self.pose_stamped(Pose2D(point.x, point.y, normalize_angle(yaw)), wall))
        return self.t_path.make(header=self.header(self.map_frame, wall), poses=poses)

    def scan(self, scan: LaserScanLike, wall: float) -> Any:
        """The laser (``sensor_msgs/LaserScan``)."""
        beams = len(scan.angles)
        ranges = scan.ranges.astype(np.float32)
        # REP-117: a beam that hit nothing within range reads +inf.
        ranges[scan.ranges >= scan.range_max] = np.inf
        return self.t_scan.make(
            header=self.header(self.base_frame, wall),
            angle_min=float(scan.angles[0]),
            angle_max=float(scan.angles[-1]),
            angle_increment=2.0 * math.pi / beams,
            time_increment=0.0,
            scan_time=1.0 / SCAN_HZ,
            range_min=0.0,
            range_max=scan.range_max,
            ranges=ranges,
            intensities=np.zeros(0, dtype=np.float32),
        )

    def battery(self, battery: Battery, wall: float) -> Any:
        """The battery (``sensor_msgs/BatteryState``)."""
        nan = math.nan
        return self.t_battery.make(
            header=self.header(self.base_frame, wall),
            voltage=nan,
            temperature=nan,
            current=nan,
            charge=nan,
            capacity=nan,
            design_capacity=nan,
            percentage=battery.percent / 100.0,
            power_supply_status=1 if battery.charging else 2,  # CHARGING / DISCHARGING
            power_supply_health=1,  # GOOD
            power_supply_technology=2,  # LION
            present=True,
            cell_voltage=np.zeros(0, dtype=np.float32),
            cell_temperature=np.zeros(0, dtype=np.float32),
            location="base",
            serial_number="",
        )

    def image(self, camera: str, picture: Any, wall: float) -> Any | None:
        """A camera picture (BGR) as ``sensor_msgs/CompressedImage`` (None if JPEG fails)."""
        ok, jpeg = cv2.imencode(".jpg", picture, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            return None
        return self.t_image.make(
            header=self.header(f"{camera}_optical_frame", wall),
            format="jpeg",
            data=np.frombuffer(jpeg.tobytes(), dtype=np.uint8),
        )
