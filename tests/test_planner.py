"""Costmap and global planner: inflation, collision-free paths, doors, NoPath reasons, speed."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from telebot.errors import NoPath
from telebot.robot.grid import OccupancyGrid
from telebot.robot.sim.building import generate_building
from telebot.robot.sim.planner import (
    INFLATION_DISTANCE,
    START_ESCAPE_DISTANCE,
    WAYPOINT_SPACING,
    Costmap,
    PlannedPath,
)
from telebot.robot.sim.world import Obstacle, obstacle_mask

RES = 0.05
RADIUS = 0.25

NO_PATH_REASONS = {
    "outside the map",
    "in unknown space",
    "inside an obstacle",
    "unreachable",
    "start is outside the map",
    "start is in unknown space",
    "start is inside an obstacle",
}


def grid_of(data: npt.NDArray[np.int8], res: float = RES) -> OccupancyGrid:
    return OccupancyGrid(np.ascontiguousarray(data, dtype=np.int8), res, 0.0, 0.0)


def cells(metres: float, res: float = RES) -> int:
    return round(metres / res)


def room(width_m: float = 8.0, height_m: float = 6.0) -> npt.NDArray[np.int8]:
    """A walled room (0.2 m walls) inside a 0.5 m unknown margin; world (0, 0) is a corner
    of the margin, so the room's floor spans x, y ∈ [0.7, width + 0.3] × [0.7, height + 0.3]."""
    rows, cols = cells(height_m + 1.0), cells(width_m + 1.0)
    data = np.full((rows, cols), -1, dtype=np.int8)
    m, w = cells(0.5), cells(0.2)
    data[m:-m, m:-m] = 100
    data[m + w : -m - w, m + w : -m - w] = 0
    return data


def two_rooms(door: bool = True) -> npt.NDArray[np.int8]:
    """Two 4 m × 6 m rooms side by side; the wall between them (x ∈ [4.7, 4.9]) has a 1 m
    door at y ∈ [2.5, 3.5] when ``door``."""
    data = room(8.2, 6.0)
    data[:, cells(4.7) : cells(4.9)] = np.maximum(data[:, cells(4.7) : cells(4.9)], 0)
    data[cells(0.5) : -cells(0.5), cells(4.7) : cells(4.9)] = 100
    if door:
        data[cells(2.5) : cells(3.5), cells(4.7) : cells(4.9)] = 0
    return data


def ring_corridor() -> npt.NDArray[np.int8]:
    """A 2 m wide corridor around a 4 m × 2 m block: two ways from west to east."""
    data = room(8.0, 6.0)
    data[cells(2.5) : cells(4.5), cells(2.5) : cells(6.5)] = 100
    return data


def samples(path: PlannedPath, step: float = RES / 2) -> npt.NDArray[np.float64]:
    """Points every ``step`` (at most) along every segment of ``path``."""
    out = [path.waypoints[:1]]
    for a, b in zip(path.waypoints[:-1], path.waypoints[1:], strict=True):
        n = max(math.ceil(math.hypot(*(b - a)) / step), 1)
        t = np.linspace(0.0, 1.0, n + 1)[1:, None]
        out.append(a + t * (b - a))
    return np.vstack(out)


def assert_collision_free(costmap: Costmap, path: PlannedPath, skip_first: bool = False) -> None:
    """Every point along every segment is free (the first segment may be an escape)."""
    if skip_first:
        path = PlannedPath(path.waypoints[1:], path.length)
    for x, y in samples(path):
        assert costmap.is_free(x, y), f"path touches an obstacle at ({x:.3f}, {y:.3f})"


def assert_well_formed(
    path: PlannedPath,
    start: tuple[float, float],
    goal: tuple[float, float],
    escaped: bool = False,
) -> None:
    wp = path.waypoints
    assert wp.ndim == 2 and wp.shape[1] == 2 and len(wp) >= 2
    assert tuple(wp[0]) == start and tuple(wp[-1]) == goal
    steps = np.hypot(*np.diff(wp, axis=0).T)
    assert path.length == pytest.approx(float(steps.sum()))
    if escaped:  # one straight segment back to free space, then the usual spacing
        assert steps[0] <= START_ESCAPE_DISTANCE + 1e-9
        steps = steps[1:]
    assert steps.size == 0 or steps.max() <= WAYPOINT_SPACING + 1e-9


def no_path_reason(costmap: Costmap, start: tuple[float, float], goal: tuple[float, float]) -> str:
    with pytest.raises(NoPath) as info:
        costmap.plan(start, goal)
    return str(info.value)


def plan_or_reason(
    costmap: Costmap, start: tuple[float, float], goal: tuple[float, float]
) -> PlannedPath | str:
    try:
        return costmap.plan(start, goal)
    except NoPath as exc:
        return str(exc)


# -- the costmap -------------------------------------------------------------------------------


def test_walls_unknown_and_the_inscribed_zone_are_not_free() -> None:
    costmap = Costmap.from_grid(grid_of(room()), RADIUS)
    assert costmap.is_free(4.0, 3.0)
    assert not costmap.is_free(0.6, 3.0)  # in the wall
    assert not costmap.is_free(0.2, 3.0)  # unknown margin
    assert not costmap.is_free(0.7 + RADIUS - 0.05, 3.0)  # robot would touch the wall
    assert costmap.is_free(0.7 + RADIUS + 0.05, 3.0)
    assert not costmap.is_free(-5.0, 3.0) and not costmap.is_free(math.nan, 3.0)
    assert costmap.clearance(1.3, 3.0) == pytest.approx(1.3 - 0.7, abs=RES)
    # Saturates where walls stop mattering.
    assert costmap.clearance(4.0, 3.0) == RADIUS + INFLATION_DISTANCE
    assert costmap.clearance(0.6, 3.0) == 0.0


def test_occupancy_threshold_is_fifty() -> None:
    data = room()
    data[cells(3.0) : cells(3.1), cells(4.0) : cells(4.1)] = 49
    data[cells(1.5) : cells(1.6), cells(2.0) : cells(2.1)] = 50
    costmap = Costmap.from_grid(grid_of(data), RADIUS)
    assert costmap.is_free(4.02, 3.02)
    assert not costmap.is_free(2.02, 1.52) and not costmap.is_free(2.02, 1.52 + RADIUS - 0.05)


def test_bad_radius_and_direct_construction_are_refused() -> None:
    grid = grid_of(room())
    with pytest.raises(ValueError, match="radius"):
        Costmap.from_grid(grid, 0.0)
    with pytest.raises(ValueError, match="radius"):
        Costmap.from_grid(grid, math.nan)
    with pytest.raises(TypeError):
        Costmap()


def test_a_grid_with_nothing_known_has_no_free_space() -> None:
    costmap = Costmap.from_grid(grid_of(np.full((20, 20), -1, dtype=np.int8)), RADIUS)
    assert not costmap.is_free(0.5, 0.5)
    assert no_path_reason(costmap, (0.5, 0.5), (0.6, 0.6)) == "in unknown space"


def test_with_obstacles_matches_a_rebuilt_costmap_and_leaves_the_original_alone() -> None:
    data = ring_corridor()
    base = Costmap.from_grid(grid_of(data), RADIUS)
    obstacles = [Obstacle(1.6, 3.5, 0.3), Obstacle(7.5, 1.2, 0.25), Obstacle(4.52, 5.01, 0.02)]
    added = base.with_obstacles(obstacles)
    # The same obstacles drawn into the grid and inflated from scratch.
    drawn = data.copy()
    grid = grid_of(data)
    mask = obstacle_mask(grid, obstacles)
    # A tiny obstacle still blocks the cell under its centre.
    row, col = grid.cell_of(4.52, 5.01)
    mask[row, col] = True
    drawn[mask] = 100
    rebuilt = Costmap.from_grid(grid_of(drawn), RADIUS)
    xs = (np.arange(data.shape[1]) + 0.5) * RES
    ys = (np.arange(data.shape[0]) + 0.5) * RES
    changed = 0
    for y in ys:
        for x in xs:
            assert added.is_free(x, y) == rebuilt.is_free(x, y), (x, y)
            assert added.clearance(x, y) == pytest.approx(rebuilt.clearance(x, y), abs=1e-4)
            changed += base.is_free(x, y) != added.is_free(x, y)
    assert changed > 100
    assert base.is_free(1.6, 3.5) and not added.is_free(1.6, 3.5)


def test_obstacles_off_the_known_map_change_nothing() -> None:
    base = Costmap.from_grid(grid_of(room()), RADIUS)
    added = base.with_obstacles([Obstacle(50.0, 50.0), Obstacle(-3.0, 2.0)])
    assert added.plan((2.0, 2.0), (6.0, 4.0)).length == base.plan((2.0, 2.0), (6.0, 4.0)).length


# -- paths ------------------------------------------------------------------------------------


def test_open_space_path_is_nearly_straight() -> None:
    costmap = Costmap.from_grid(grid_of(room(10.0, 8.0)), RADIUS)
    start, goal = (2.0, 2.0), (8.0, 6.5)
    path = costmap.plan(start, goal)
    assert_well_formed(path, start, goal)
    assert_collision_free(costmap, path)
    straight = math.dist(start, goal)
    assert path.length <= 1.3 * straight
    assert path.length <= 1.02 * straight  # in fact: open space is crossed in a line


def test_path_goes_around_a_wall() -> None:
    data = room(8.0, 6.0)
    # A wall from the floor's south edge up to y = 4.5, between start and goal.
    data[: cells(4.5), cells(4.0) : cells(4.2)] = np.maximum(
        data[: cells(4.5), cells(4.0) : cells(4.2)], 100
    )
    data[: cells(0.5), :] = -1
    costmap = Costmap.from_grid(grid_of(data), RADIUS)
    start, goal = (2.0, 1.5), (6.5, 1.5)
    path = costmap.plan(start, goal)
    assert_well_formed(path, start, goal)
    assert_collision_free(costmap, path)
    # Over the top of the wall, with the robot clear of its end.
    assert path.waypoints[:, 1].max() > 4.5 + RADIUS
    assert path.length < 2 * math.dist(start, goal) + 2 * 3.5


def test_path_goes_through_the_door_and_passes_it_centrally() -> None:
    costmap = Costmap.from_grid(grid_of(two_rooms()), RADIUS)
    start, goal = (1.5, 5.5), (8.0, 1.0)
    path = costmap.plan(start, goal)
    assert_well_formed(path, start, goal)
    assert_collision_free(costmap, path)
    # Where the path crosses the wall's middle line: within the door, near its centre.
    points = samples(path, 0.01)
    crossing = points[np.argmin(np.abs(points[:, 0] - 4.8))]
    assert abs(crossing[0] - 4.8) < 0.01
    assert abs(crossing[1] - 3.0) < 0.12


def test_path_keeps_to_the_middle_of_a_corridor() -> None:
    # A 2 m wide, 12 m long corridor (floor y ∈ [0.7, 2.7]).
    costmap = Costmap.from_grid(grid_of(room(12.0, 2.0)), RADIUS)
    start, goal = (1.5, 1.5), (11.5, 1.9)
    path = costmap.plan(start, goal)
    assert_collision_free(costmap, path)
    middle = samples(path)[:, 1]
    # Away from the ends the robot stays within a quarter metre of the centre line (y = 1.7).
    inner = samples(path)[:, 0]
    assert np.abs(middle[(inner > 3.0) & (inner < 10.0)] - 1.7).max() < 0.3


def test_path_rounds_a_corner_with_margin() -> None:
    # An L of two 1.6 m corridors: the turn must not be cut tight against the inner corner.
    data = room(6.0, 6.0)
    data[cells(2.8) : cells(6.4), cells(2.8) : cells(6.4)] = 100
    costmap = Costmap.from_grid(grid_of(data), RADIUS)
    path = costmap.plan((5.5, 1.5), (1.5, 5.5))
    assert_collision_free(costmap, path)
    clearances = [costmap.clearance(x, y) for x, y in samples(path)]
    assert min(clearances) >= RADIUS + 0.15


def test_no_door_means_unreachable() -> None:
    costmap = Costmap.from_grid(grid_of(two_rooms(door=False)), RADIUS)
    assert no_path_reason(costmap, (1.5, 3.0), (7.0, 3.0)) == "unreachable"


def test_goal_reasons() -> None:
    costmap = Costmap.from_grid(grid_of(room()), RADIUS)
    start = (2.0, 2.0)
    assert no_path_reason(costmap, start, (0.6, 3.0)) == "inside an obstacle"  # in the wall
    assert no_path_reason(costmap, start, (0.8, 3.0)) == "inside an obstacle"  # too close
    assert no_path_reason(costmap, start, (0.2, 3.0)) == "in unknown space"
    assert no_path_reason(costmap, start, (20.0, 3.0)) == "outside the map"
    assert no_path_reason(costmap, start, (-0.01, 3.0)) == "outside the map"
    assert no_path_reason(costmap, start, (math.nan, 3.0)) == "outside the map"
    assert no_path_reason(costmap, (20.0, 3.0), (4.0, 3.0)) == "start is outside the map"


def test_start_brushing_a_wall_escapes() -> None:
    costmap = Costmap.from_grid(grid_of(room()), RADIUS)
    start, goal = (0.8, 3.0), (6.0, 3.0)  # 0.1 m from the west wall: the body touches it
    assert not costmap.is_free(*start)
    path = costmap.plan(start, goal)
    assert_well_formed(path, start, goal, escaped=True)
    assert costmap.is_free(*path.waypoints[1])
    assert_collision_free(costmap, path, skip_first=True)


def test_start_deep_in_a_wall_or_unknown_is_refused() -> None:
    data = room()
    data[:, cells(0.5) : cells(1.2)] = np.maximum(data[:, cells(0.5) : cells(1.2)], 100)
    costmap = Costmap.from_grid(grid_of(data), RADIUS)
    assert no_path_reason(costmap, (0.6, 3.0), (6.0, 3.0)) == "start is inside an obstacle"
    assert no_path_reason(costmap, (0.1, 3.0), (6.0, 3.0)) == "start is in unknown space"


def test_start_never_escapes_through_a_thin_wall() -> None:
    # Next to a 0.1 m wall between the rooms: the nearest free cell is on the far side.
    data = two_rooms(door=False)
    data[cells(0.5) : -cells(0.5), cells(4.7) : cells(4.9)] = 0
    data[cells(0.5) : -cells(0.5), cells(4.75) : cells(4.85)] = 100
    costmap = Costmap.from_grid(grid_of(data), 0.1)
    # 0.05 m from the wall's east face, goal in the west room.
    reason = no_path_reason(costmap, (4.9, 3.0), (2.0, 3.0))
    assert reason == "unreachable"


def test_start_and_goal_identical_or_very_close() -> None:
    costmap = Costmap.from_grid(grid_of(room()), RADIUS)
    path = costmap.plan((3.0, 3.0), (3.0, 3.0))
    assert path.waypoints.tolist() == [[3.0, 3.0], [3.0, 3.0]] and path.length == 0.0
    path = costmap.plan((3.0, 3.0), (3.01, 3.02))
    assert len(path.waypoints) == 2 and path.length == pytest.approx(math.hypot(0.01, 0.02))


def test_waypoints_are_read_only() -> None:
    path = Costmap.from_grid(grid_of(room()), RADIUS).plan((2.0, 2.0), (6.0, 4.0))
    with pytest.raises(ValueError, match="read-only"):
        path.waypoints[0, 0] = 1.0


def test_an_obstacle_in_the_corridor_makes_the_path_go_around() -> None:
    base = Costmap.from_grid(grid_of(ring_corridor()), RADIUS)
    start, goal = (1.5, 3.5), (7.5, 3.5)
    before = base.plan(start, goal)
    # Block whichever side the first path took, with a person in the middle of it.
    side_y = 1.5 if before.waypoints[:, 1].min() < 2.5 else 5.5
    blocked = base.with_obstacles([Obstacle(4.5, side_y, 0.6)])
    after = blocked.plan(start, goal)
    assert_collision_free(blocked, after)
    took_south = after.waypoints[:, 1].min() < 2.5
    assert took_south == (side_y == 5.5)
    # Both sides blocked: no way round.
    both = base.with_obstacles([Obstacle(4.5, 1.5, 0.6), Obstacle(4.5, 5.5, 0.6)])
    assert no_path_reason(both, start, goal) == "unreachable"
    assert no_path_reason(both, start, (4.5, 5.5)) == "inside an obstacle"


def test_a_person_next_to_the_robot_still_lets_it_back_away() -> None:
    base = Costmap.from_grid(grid_of(room(12.0, 2.0)), RADIUS)
    # The robot stopped 0.45 m from a person: in the person's inscribed zone now.
    blocked = base.with_obstacles([Obstacle(5.0, 1.7, 0.25)])
    assert not blocked.is_free(4.55, 1.7)
    path = blocked.plan((4.55, 1.7), (1.5, 1.7))
    assert_collision_free(blocked, path, skip_first=True)


# -- random maps ------------------------------------------------------------------------------


@st.composite
def random_maps(draw: st.DrawFn) -> tuple[npt.NDArray[np.int8], list[tuple[float, float]]]:
    rows = draw(st.integers(20, 60))
    cols = draw(st.integers(20, 60))
    data = np.zeros((rows, cols), dtype=np.int8)
    for _ in range(draw(st.integers(0, 10))):
        r0, c0 = draw(st.integers(0, rows - 1)), draw(st.integers(0, cols - 1))
        h, w = draw(st.integers(1, 12)), draw(st.integers(1, 12))
        data[r0 : r0 + h, c0 : c0 + w] = draw(st.sampled_from([-1, 100, 60, 30]))
    # Mostly inside the map (Hypothesis favours the ends of a range), sometimes anywhere.
    inside = st.tuples(st.floats(0.05, cols * 0.1 - 0.05), st.floats(0.05, rows * 0.1 - 0.05))
    anywhere = st.tuples(st.floats(-0.5, cols * 0.1 + 0.5), st.floats(-0.5, rows * 0.1 + 0.5))
    points = draw(st.lists(st.one_of(inside, inside, inside, anywhere), min_size=4, max_size=4))
    return data, points


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(random_maps(), st.sampled_from([0.05, 0.1, 0.15, 0.3]))
def test_any_path_on_a_random_map_is_collision_free(
    case: tuple[npt.NDArray[np.int8], list[tuple[float, float]]], radius: float
) -> None:
    data, points = case
    costmap = Costmap.from_grid(grid_of(data, res=0.1), radius)
    for start, goal in ((points[0], points[1]), (points[2], points[3]), (points[0], points[3])):
        path = plan_or_reason(costmap, start, goal)
        if isinstance(path, str):
            assert path in NO_PATH_REASONS
            continue
        close = math.dist(start, goal) <= 0.1  # a two-point path, whatever lies between
        escaped = not costmap.is_free(*start) and not close
        assert_well_formed(path, start, goal, escaped=escaped)
        if not close:
            assert_collision_free(costmap, path, skip_first=escaped)


# -- the building -----------------------------------------------------------------------------


def test_building_plans_between_far_corners_and_to_every_place() -> None:
    grid, places = generate_building()
    costmap = Costmap.from_grid(grid, RADIUS)
    free = [(p.x, p.y) for p in places.values() if costmap.is_free(p.x, p.y)]
    assert len(free) == len(places), "every place must be free space"
    # Far corners: the free cells nearest the corners of the building's bounding box.
    row0, row1, col0, col1 = grid.known_bounds() or (0, 0, 0, 0)
    xs = (np.arange(col0, col1, 4) + 0.5) * grid.resolution + grid.origin_x
    ys = (np.arange(row0, row1, 4) + 0.5) * grid.resolution + grid.origin_y
    candidates = [(x, y) for y in ys[:: len(ys) // 40] for x in xs[:: len(xs) // 60]]
    corners = []
    for cx, cy in ((xs[0], ys[0]), (xs[-1], ys[-1]), (xs[0], ys[-1]), (xs[-1], ys[0])):
        nearest = sorted(candidates, key=lambda p: math.hypot(p[0] - cx, p[1] - cy))
        corners.append(next(p for p in nearest if costmap.is_free(*p)))
    for start, goal in ((corners[0], corners[1]), (corners[2], corners[3])):
        path = costmap.plan(start, goal)
        assert_well_formed(path, start, goal)
        assert_collision_free(costmap, path)
        assert path.length < 2.0 * math.dist(start, goal)
    home = free[0]
    for goal in free[1:]:
        path = costmap.plan(home, goal)
        assert_collision_free(costmap, path)


def test_touching_a_wall_is_exact_geometry_where_is_free_keeps_a_margin() -> None:
    costmap = Costmap.from_grid(grid_of(room()), RADIUS)
    # The floor starts at y = 0.7: a centre closer than the radius to it touches.
    x = 3.0
    assert costmap.touches_wall(x, 0.7 + RADIUS - 0.01)
    assert not costmap.touches_wall(x, 0.7 + RADIUS + 0.01)
    # Diagonally off a box's corner, exactly.
    grid = room()
    grid[cells(3.0) : cells(3.5), cells(3.0) : cells(3.5)] = 100  # a box, corner (3.5, 3.5)
    boxed = Costmap.from_grid(grid_of(grid), RADIUS)
    corner_x = corner_y = 3.5
    gap = RADIUS + 0.02
    px, py = corner_x + gap / math.sqrt(2), corner_y + gap / math.sqrt(2)
    assert not boxed.touches_wall(px, py)
    assert boxed.touches_wall(corner_x + 0.15, corner_y + 0.15)  # 0.21 m from the corner
    assert not boxed.touches_wall(corner_x + 0.18, corner_y + 0.18)  # 0.255 m
    # Off the known map (and non-numbers) always touch.
    assert costmap.touches_wall(-5.0, 3.0) and costmap.touches_wall(math.nan, 3.0)
