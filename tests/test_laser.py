"""The simulated laser: ranges to walls, the angle convention, obstacles, unknown space."""

from __future__ import annotations

import math

import numpy as np
import pytest

from telebot.robot.grid import OCCUPIED, UNKNOWN, OccupancyGrid
from telebot.robot.nav import Pose2D
from telebot.robot.sim.laser import Laser, RayCaster
from telebot.robot.sim.world import Obstacle

RES = 0.05
CELL = RES  # "accurate to one cell"


def room() -> OccupancyGrid:
    """Free x ∈ [1, 7), y ∈ [1, 5) inside 0.1 m walls, unknown all round (8 m × 6 m grid)."""
    data = np.full((120, 160), UNKNOWN, dtype=np.int8)
    data[18:102, 18:142] = OCCUPIED
    data[20:100, 20:140] = 0
    return OccupancyGrid(data, RES, 0.0, 0.0)


# From (3, 2.5): east wall face at x = 7 (4 m), west x = 1 (2 m), north y = 5 (2.5 m),
# south y = 1 (1.5 m).
X, Y = 3.0, 2.5
WALLS = {0.0: 4.0, math.pi / 2: 2.5, math.pi: 2.0, -math.pi / 2: 1.5}


def expected_range(world_angle: float) -> float:
    """Distance from (X, Y) to the room's walls along ``world_angle``."""
    c, s = math.cos(world_angle), math.sin(world_angle)
    ts = []
    if c > 1e-12:
        ts.append((7.0 - X) / c)
    if c < -1e-12:
        ts.append((1.0 - X) / c)
    if s > 1e-12:
        ts.append((5.0 - Y) / s)
    if s < -1e-12:
        ts.append((1.0 - Y) / s)
    return min(ts)


def beam_towards(scan_angles: np.ndarray, angle: float) -> int:
    """Index of the beam nearest ``angle`` (robot frame)."""
    diff = np.abs((scan_angles - angle + math.pi) % (2 * math.pi) - math.pi)
    return int(np.argmin(diff))


def test_beam_count_and_angle_convention() -> None:
    laser = Laser(room(), beams=360)
    scan = laser.scan(Pose2D(X, Y, 0.0))
    assert scan.angles.shape == (360,) and scan.ranges.shape == (360,)
    # Increasing, evenly spaced, covering the full circle, beam 180 exactly straight ahead.
    steps = np.diff(scan.angles)
    assert np.allclose(steps, 2 * math.pi / 360)
    assert scan.angles[0] == pytest.approx(-math.pi)
    assert scan.angles[180] == 0.0
    assert scan.angles[270] == pytest.approx(math.pi / 2)
    # Angle 0 looks along the robot's +x (east here: the far wall), +π/2 to its left (north).
    assert scan.ranges[180] == pytest.approx(4.0, abs=CELL)
    assert scan.ranges[270] == pytest.approx(2.5, abs=CELL)
    assert scan.ranges[90] == pytest.approx(1.5, abs=CELL)
    assert scan.ranges[0] == pytest.approx(2.0, abs=CELL)


@pytest.mark.parametrize("yaw", [0.0, 0.7, math.pi / 2, -2.0, math.pi])
def test_ranges_to_walls_within_one_cell_in_every_direction(yaw: float) -> None:
    laser = Laser(room(), beams=72)
    scan = laser.scan(Pose2D(X, Y, yaw))
    expected = np.array([expected_range(yaw + a) for a in scan.angles])
    assert np.max(np.abs(scan.ranges - expected)) <= CELL


@pytest.mark.parametrize(("world_angle", "distance"), WALLS.items())
def test_the_heading_rotates_the_scan(world_angle: float, distance: float) -> None:
    # Whatever the robot's yaw, the beam pointing at a wall reads that wall's distance.
    laser = Laser(room())
    for yaw in (0.0, 1.0, -2.5):
        scan = laser.scan(Pose2D(X, Y, yaw))
        i = beam_towards(scan.angles, world_angle - yaw)
        assert scan.ranges[i] == pytest.approx(distance, abs=CELL)


def test_points_are_in_the_robot_frame() -> None:
    scan = Laser(room()).scan(Pose2D(X, Y, math.pi / 2))  # facing north
    points = scan.points()
    assert points.shape == (360, 2)  # every beam hits a wall in a closed room
    ahead = points[180]
    # North wall 2.5 m ahead, in the robot frame: (2.5, 0).
    assert ahead == pytest.approx((2.5, 0.0), abs=CELL)
    left = points[270]  # robot's left is west: the wall 2 m away
    assert left == pytest.approx((0.0, 2.0), abs=CELL)


def test_obstacle_circle_at_the_right_range() -> None:
    laser = Laser(room())
    person = Obstacle(5.0, 2.5, radius=0.3)
    scan = laser.scan(Pose2D(X, Y, 0.0), [person])
    # Straight ahead: the circle's near edge, exactly (analytic), not a cell boundary.
    assert scan.ranges[180] == pytest.approx(2.0 - 0.3, abs=1e-9)
    # A beam 5° off centre meets the circle further out, still short of the wall.
    a = math.radians(5.0)
    b = 2.0 * math.cos(a)
    expected = b - math.sqrt(b * b - (4.0 - 0.09))
    assert scan.ranges[185] == pytest.approx(expected, abs=1e-9)
    # Beams that miss it see the wall behind, and without the obstacle the beam sees the wall.
    assert scan.ranges[200] == pytest.approx(expected_range(math.radians(20)), abs=CELL)
    assert laser.scan(Pose2D(X, Y, 0.0)).ranges[180] == pytest.approx(4.0, abs=CELL)
    # Behind the robot an obstacle is seen by the rear beams only.
    behind = laser.scan(Pose2D(X, Y, 0.0), [Obstacle(2.0, 2.5, radius=0.2)])
    assert behind.ranges[0] == pytest.approx(0.8, abs=1e-9)
    assert behind.ranges[180] == pytest.approx(4.0, abs=CELL)


def test_unknown_space_is_solid() -> None:
    # No walls at all: free x ∈ [1, 4), unknown beyond; the beam stops where unknown starts.
    data = np.full((60, 100), UNKNOWN, dtype=np.int8)
    data[20:40, 20:80] = 0
    grid = OccupancyGrid(data, RES, 0.0, 0.0)
    scan = Laser(grid).scan(Pose2D(2.0, 1.5, 0.0))
    assert scan.ranges[180] == pytest.approx(2.0, abs=CELL)  # to x = 4
    assert scan.ranges[0] == pytest.approx(1.0, abs=CELL)  # to x = 1
    assert scan.ranges[270] == pytest.approx(0.5, abs=CELL)  # to y = 2


def test_outside_the_grid_is_solid_and_range_max_is_reported_for_misses() -> None:
    grid = OccupancyGrid(np.zeros((40, 40), dtype=np.int8), RES, 0.0, 0.0)  # 2 m, all free
    scan = Laser(grid, range_max=10.0).scan(Pose2D(0.5, 1.0, 0.0))
    assert scan.ranges[180] == pytest.approx(1.5, abs=CELL)  # the grid's east edge
    short = Laser(grid, beams=8, range_max=0.3).scan(Pose2D(1.0, 1.0, 0.0))
    assert np.all(short.ranges == 0.3)
    assert short.points().shape == (0, 2)


@pytest.mark.parametrize(
    "pose",
    [Pose2D(-5.0, 2.0, 0.0), Pose2D(100.0, -3.0, 1.0), Pose2D(1e9, 1e9, 0.0)],
    ids=["west", "far", "huge"],
)
def test_a_pose_outside_the_map_reads_zero(pose: Pose2D) -> None:
    laser = Laser(room(), beams=90)
    scan = laser.scan(pose, [Obstacle(0.0, 0.0)])
    assert scan.ranges.shape == (90,)
    assert np.all(scan.ranges == 0.0)


def test_a_pose_inside_a_wall_reads_zero() -> None:
    scan = Laser(room(), beams=90).scan(Pose2D(0.95, 2.5, 0.0))  # in the west wall
    assert np.all(scan.ranges == 0.0)


def test_a_pose_on_a_cell_corner_and_axis_aligned_beams() -> None:
    # Grid-aligned positions and beams are the degenerate case of the traversal.
    scan = Laser(room(), beams=4).scan(Pose2D(3.0, 3.0, 0.0))
    assert scan.ranges == pytest.approx([2.0, 2.0, 4.0, 2.0], abs=CELL)


def test_non_finite_poses_are_refused() -> None:
    with pytest.raises(ValueError, match="finite"):
        Laser(room()).scan(Pose2D(math.nan, 1.0, 0.0))


def test_matches_a_brute_force_march_on_a_cluttered_map() -> None:
    rng = np.random.default_rng(42)
    data = np.zeros((200, 200), dtype=np.int8)
    for _ in range(60):
        r, c = rng.integers(0, 195, size=2)
        h, w = rng.integers(1, 6, size=2)
        data[r : r + h, c : c + w] = rng.choice([OCCUPIED, UNKNOWN])
    grid = OccupancyGrid(data, RES, -3.0, 2.0)
    caster = RayCaster(grid)
    poses = 0
    while poses < 15:
        x, y = rng.uniform(-3.0, 7.0), rng.uniform(2.0, 12.0)
        if grid.value_at(x, y) != 0:
            continue
        poses += 1
        angles = rng.uniform(-math.pi, math.pi, size=30)
        got = caster.cast(x, y, angles, 6.0).distance
        # Reference: march in 1 mm steps and stop at the first solid cell.
        ts = np.arange(0.0, 6.0, 0.001)[None, :]
        cols = np.floor((x + ts * np.cos(angles)[:, None] + 3.0) / RES).astype(int)
        rows = np.floor((y + ts * np.sin(angles)[:, None] - 2.0) / RES).astype(int)
        inside = (rows >= 0) & (rows < 200) & (cols >= 0) & (cols < 200)
        values = np.where(inside, data[rows.clip(0, 199), cols.clip(0, 199)], UNKNOWN)
        solid = (values >= 50) | (values < 0)
        first = np.argmax(solid, axis=1)
        reference = np.where(solid.any(axis=1), ts[0, first], 6.0)
        assert np.max(np.abs(got - reference)) <= 0.002
