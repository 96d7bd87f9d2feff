"""ROS 2 messages to telebot's robot types, and back: pure functions, no I/O.

Messages are the objects :class:`~telebot.rosmsg.types.MessageType` makes and decodes
(attribute access by ROS field name). Everything here follows REP-103 (metres, radians,
yaw counter-clockwise) and REP-105 (``map`` → ``odom`` → ``base_link``). A message that
cannot be mapped raises :class:`ValueError` with one line saying why; the caller drops it
and names the topic.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from telebot.reasons import Reason
from telebot.robot.grid import OccupancyGrid
from telebot.robot.nav import Battery, Pose2D, normalize_angle

__all__ = [
    "ORIGIN_YAW_TOLERANCE",
    "ScanData",
    "TfTree",
    "battery_from_msg",
    "compose",
    "covariance_xy_yaw",
    "duration_fields",
    "grid_from_msg",
    "nav2_reason",
    "path_from_msg",
    "pose_from_msg",
    "quaternion_fields",
    "scan_from_msg",
    "yaw_of",
]

#: A map origin rotated by less than this (radians) is float noise from a quaternion.
ORIGIN_YAW_TOLERANCE = 1e-3

#: ``power_supply_status`` of sensor_msgs/BatteryState that means charging.
_POWER_SUPPLY_STATUS_CHARGING = 1

#: Nav2 error codes (Jazzy/Kilted numbering, ``nav2_msgs/action``) that mean "no path":
#: ComputePathToPose START/GOAL_OUTSIDE_MAP, START/GOAL_OCCUPIED, TIMEOUT, NO_VALID_PATH.
_NO_PATH_CODES = frozenset(range(203, 209)) | frozenset(range(303, 309))
#: Behaviours' COLLISION_AHEAD: Spin 703, BackUp 713, DriveOnHeading 723.
_OBSTACLE_CODES = frozenset({703, 713, 723})


def yaw_of(q: Any) -> float:
    """Yaw (rotation about z, radians) of a ``geometry_msgs/Quaternion``."""
    x, y, z, w = float(q.x), float(q.y), float(q.z), float(q.w)
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quaternion_fields(yaw: float) -> dict[str, float]:
    """The fields of a ``geometry_msgs/Quaternion`` for a rotation of ``yaw`` about z."""
    return {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2.0), "w": math.cos(yaw / 2.0)}


def duration_fields(seconds: float) -> dict[str, int]:
    """The fields of a ``builtin_interfaces/Duration`` of ``seconds`` (≥ 0)."""
    whole = math.floor(max(seconds, 0.0))
    return {"sec": int(whole), "nanosec": int((max(seconds, 0.0) - whole) * 1e9)}


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def pose_from_msg(pose: Any) -> Pose2D:
    """A ``geometry_msgs/Pose`` projected on the ground plane; ValueError if not finite."""
    p, q = pose.position, pose.orientation
    x, y = float(p.x), float(p.y)
    if not _finite(x, y, float(q.x), float(q.y), float(q.z), float(q.w)):
        raise ValueError("pose is not finite")
    if float(q.x) == float(q.y) == float(q.z) == float(q.w) == 0.0:
        raise ValueError("pose has a zero quaternion")
    return Pose2D(x, y, normalize_angle(yaw_of(q)))


def covariance_xy_yaw(covariance: Iterable[float]) -> tuple[float, ...]:
    """The 3×3 (x, y, yaw) block of a row-major 6×6 pose covariance, row-major."""
    c = [float(v) for v in covariance]
    if len(c) != 36:
        raise ValueError(f"pose covariance has {len(c)} values, not 36")
    picked = tuple(c[row * 6 + col] for row in (0, 1, 5) for col in (0, 1, 5))
    if not _finite(*picked):
        raise ValueError("pose covariance is not finite")
    return picked


def grid_from_msg(msg: Any, *, max_cells: int) -> OccupancyGrid:
    """A ``nav_msgs/OccupancyGrid`` as an :class:`OccupancyGrid`.

    Both store rows from the origin outwards, so the data reshapes as it is. ValueError
    (one line) for a map over ``max_cells`` cells, an empty or inconsistent one, a bad
    resolution or origin, or a rotated origin (unsupported, as for map files).
    """
    info = msg.info
    width, height = int(info.width), int(info.height)
    cells = width * height
    if cells > max_cells:
        raise ValueError(f"map of {width}x{height} cells is over the limit of {max_cells}")
    if cells == 0:
        raise ValueError(f"map of {width}x{height} cells is empty")
    data = np.asarray(msg.data)
    if data.size != cells:
        raise ValueError(f"map says {width}x{height} cells but carries {data.size}")
    resolution = float(info.resolution)
    if not (math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"map resolution {resolution} is not a positive number")
    origin = info.origin
    ox, oy = float(origin.position.x), float(origin.position.y)
    if not _finite(ox, oy):
        raise ValueError("map origin is not finite")
    q = origin.orientation
    if not (float(q.x) == float(q.y) == float(q.z) == float(q.w) == 0.0):
        yaw = yaw_of(q)
        if not math.isfinite(yaw) or abs(yaw) > ORIGIN_YAW_TOLERANCE:
            raise ValueError(f"map origin is rotated (yaw {yaw:g} rad): not supported")
    # A copy: the grid is shared read-only and must not alias the message's buffer.
    grid = np.array(data, dtype=np.int8).reshape(height, width)
    return OccupancyGrid(data=grid, resolution=resolution, origin_x=ox, origin_y=oy)


def path_from_msg(msg: Any) -> tuple[Pose2D, ...]:
    """The poses of a ``nav_msgs/Path``; ValueError if one is not finite."""
    return tuple(pose_from_msg(stamped.pose) for stamped in msg.poses)


def battery_from_msg(msg: Any, low_percent: float) -> Battery:
    """A ``sensor_msgs/BatteryState`` as :class:`Battery`; ValueError without a charge.

    ``percentage`` is 0 … 1 in ROS; drivers that send 0 … 100 are common, so a value
    above 1 is read as percent. Without a percentage, charge / capacity is used.
    """
    fraction = float(msg.percentage)
    if not math.isfinite(fraction):
        charge, capacity = float(msg.charge), float(msg.capacity)
        if not (_finite(charge, capacity) and capacity > 0):
            raise ValueError("battery state has no percentage and no charge/capacity")
        fraction = charge / capacity
    percent = fraction if fraction > 1.0 else fraction * 100.0
    percent = min(max(percent, 0.0), 100.0)
    charging = int(msg.power_supply_status) == _POWER_SUPPLY_STATUS_CHARGING
    return Battery(percent=round(percent, 2), low=percent < low_percent, charging=charging)


@dataclass(frozen=True, slots=True, eq=False)
class ScanData:
    """A ``sensor_msgs/LaserScan`` as :class:`~telebot.robot.nav.LaserScanLike` (people)."""

    angles: npt.NDArray[np.float64]
    ranges: npt.NDArray[np.float64]
    range_max: float


def scan_from_msg(msg: Any) -> ScanData:
    """A ``sensor_msgs/LaserScan`` as :class:`ScanData`; readings outside the scanner's
    ``range_min`` … ``range_max`` become ``inf`` (nothing there). ValueError when malformed.

    The scan is taken as seen from the base's centre, facing its heading (a laser mounted
    off-centre or turned is off by that much).
    """
    ranges = np.asarray(msg.ranges, dtype=np.float64)
    start, step = float(msg.angle_min), float(msg.angle_increment)
    low, high = float(msg.range_min), float(msg.range_max)
    if not (_finite(start, step, high) and step != 0.0 and high > 0.0 and ranges.ndim == 1):
        raise ValueError("laser scan with a bad angle_min, angle_increment or range_max")
    angles = start + step * np.arange(len(ranges), dtype=np.float64)
    if step < 0:  # a scanner turning the other way: increasing angles, as the detector wants
        angles, ranges = angles[::-1], ranges[::-1]
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(ranges) | (ranges < (low if math.isfinite(low) else 0.0))
        bad |= ranges > high
    ranges = np.where(bad, np.inf, ranges)
    return ScanData(np.ascontiguousarray(angles), np.ascontiguousarray(ranges), high)


def nav2_reason(error_code: int) -> Reason:
    """The reason code for a Nav2 result ``error_code`` (an aborted goal)."""
    if error_code in _NO_PATH_CODES:
        return Reason.NO_PATH
    if error_code in _OBSTACLE_CODES:
        return Reason.OBSTACLE
    return Reason.FAILED


def compose(a: Pose2D, b: Pose2D) -> Pose2D:
    """Pose ``b`` (given in frame ``a``) in ``a``'s parent frame."""
    cos_a, sin_a = math.cos(a.yaw), math.sin(a.yaw)
    return Pose2D(
        a.x + cos_a * b.x - sin_a * b.y,
        a.y + sin_a * b.x + cos_a * b.y,
        normalize_angle(a.yaw + b.yaw),
    )


@dataclass(frozen=True, slots=True)
class _Edge:
    parent: str
    pose: Pose2D  # the child frame in the parent frame
    stamp: float  # when it arrived (caller's clock)


def _frame(name: str) -> str:
    # tf2 rejects a leading slash, but ROS 1 bridges still send one.
    return str(name).lstrip("/")


class TfTree:
    """The planar transforms of ``/tf`` and ``/tf_static``, child → parent, newest only.

    Not thread-safe on its own: the caller holds its lock around :meth:`update` and
    :meth:`lookup`.
    """

    #: Longest chain followed (a loop in a broken tf tree must not hang the lookup).
    MAX_DEPTH = 32

    def __init__(self) -> None:
        self._edges: dict[str, _Edge] = {}

    def update(self, transforms: Iterable[Any], now: float, *, static: bool = False) -> int:
        """Take the ``geometry_msgs/TransformStamped`` list of a TFMessage; returns how many.

        ``static`` transforms (``/tf_static``) never age: they do not count in the arrival
        time :meth:`lookup` reports.
        """
        taken = 0
        for stamped in transforms:
            t = stamped.transform
            translation, rotation = t.translation, t.rotation
            try:
                x, y = float(translation.x), float(translation.y)
                q = (float(rotation.x), float(rotation.y), float(rotation.z), float(rotation.w))
                if not _finite(x, y, *q) or q == (0.0, 0.0, 0.0, 0.0):
                    continue
                yaw = yaw_of(rotation)
            except (TypeError, ValueError, AttributeError):
                continue
            child, parent = _frame(stamped.child_frame_id), _frame(stamped.header.frame_id)
            if not child or not parent or child == parent:
                continue
            stamp = math.inf if static else now
            self._edges[child] = _Edge(parent, Pose2D(x, y, normalize_angle(yaw)), stamp)
            taken += 1
        return taken

    def lookup(self, target: str, source: str) -> tuple[Pose2D, float] | None:
        """Pose of frame ``source`` in frame ``target`` and the oldest arrival time on the way
        (infinite if every transform on it is static).

        None when the chain from ``source`` up to ``target`` is not (yet) known.
        """
        target, frame = _frame(target), _frame(source)
        pose = Pose2D(0.0, 0.0, 0.0)
        oldest = math.inf
        for _ in range(self.MAX_DEPTH):
            if frame == target:
                return pose, oldest
            edge = self._edges.get(frame)
            if edge is None:
                return None
            pose = compose(edge.pose, pose)
            oldest = min(oldest, edge.stamp)
            frame = edge.parent
        return None
