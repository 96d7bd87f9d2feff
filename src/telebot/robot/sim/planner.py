"""Global path planning on a costmap inflated by the robot's radius.

The :class:`Costmap` turns an :class:`~telebot.robot.grid.OccupancyGrid` into per-cell travel
weights for the robot's *centre*:

* **lethal** cells are occupied (value ≥ 50) or unknown (-1): we never plan through space
  nobody has seen;
* **inscribed** cells lie within ``robot_radius`` of a lethal cell: the centre may not be
  there, or the body would touch it. Lethal and inscribed cells weigh ``inf``;
* **inflated** cells lie within a further :data:`INFLATION_DISTANCE` of a lethal cell and
  weigh more the closer they are, so paths keep to the middle of corridors and pass doors
  centrally; every other cell weighs 1.

The clearance of a cell is the distance from its centre to the nearest lethal cell's centre
less half a cell, i.e. to that cell's near edge (``cv2.distanceTransform``, exact Euclidean,
no Python loops).

Planning is A* (``pyastar2d``, C++) done coarse-to-fine: a search on a 4×-downsampled grid
finds the route, a full-resolution search inside a band around that route makes it exact,
and a full-resolution search over the whole costmap stands behind both. The fine searches
are 4-connected so that every step of a raw path stays inside the two cells it joins. The
raw path is then smoothed by line-of-sight shortcuts that are checked against every cell the
shortcut touches and accepted only if they cost no more than the stretch they replace, and
finally cut into waypoints at most :data:`WAYPOINT_SPACING` apart for a pure-pursuit
controller.

Only the part of the grid that holds known cells is stored (the rest is lethal anyway): on
the default 4000 × 4000 building map that is ~90 m × 60 m, which keeps the arrays, the
searches and :meth:`Costmap.with_obstacles` small and fast.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
import pyastar2d

from telebot.errors import NoPath
from telebot.robot.grid import UNKNOWN, OccupancyGrid
from telebot.robot.sim.world import Obstacle

__all__ = [
    "INFLATION_DISTANCE",
    "INFLATION_WEIGHT",
    "LETHAL_OCCUPANCY",
    "START_ESCAPE_DISTANCE",
    "WAYPOINT_SPACING",
    "Costmap",
    "PlannedPath",
]

#: Occupancy values at or above this are obstacles.
LETHAL_OCCUPANCY = 50
#: How far beyond the robot's radius (metres) walls still add cost.
INFLATION_DISTANCE = 0.5
#: Extra weight of a cell that just clears a wall (a cell in the open weighs 1).
INFLATION_WEIGHT = 4.0
#: A start this close (metres) to free space is escaped from rather than refused: the robot
#: brushing a wall, or standing next to an obstacle added after it stopped.
START_ESCAPE_DISTANCE = 0.3
#: Largest gap (metres) between consecutive waypoints of a planned path.
WAYPOINT_SPACING = 0.25

# Downsampling factor of the coarse search, and the half-width (metres) of the band around
# the coarse route that the fine search may use. A 2 m band covers a corridor, so the fine
# search can still centre the path where the optimistic coarse route hugged a wall.
_COARSE = 4
_BAND = 1.0
# Cells within this (in cells) of a cell edge count as touching it, so a shortcut through a
# cell corner, or one that rounding could move across an edge, is checked on both sides.
_EDGE_EPS = 1e-4
# Shortcuts may be this much (relative) dearer than the stretch they replace: weights along a
# straight line and along a staircase are sampled differently, and exact ties are common.
_COST_TOLERANCE = 1e-3

_Cells = npt.NDArray[np.intp]
_Points = npt.NDArray[np.float64]
_Weights = npt.NDArray[np.float32]


@dataclass(frozen=True, slots=True, eq=False)
class PlannedPath:
    """A collision-free path for the robot's centre, in the map frame."""

    #: ``(N, 2)`` world ``x, y`` from start to goal (first = start, last = goal), N ≥ 2,
    #: read-only. Consecutive waypoints are at most :data:`WAYPOINT_SPACING` apart, except
    #: that a start in the inscribed zone is left by one straight segment (at most
    #: :data:`START_ESCAPE_DISTANCE`) to the nearest free cell; every later point is free.
    waypoints: npt.NDArray[np.float64]
    #: Metres along the waypoints.
    length: float


class Costmap:
    """Travel weights for the robot's centre over an occupancy grid; plans paths on them.

    Immutable: :meth:`with_obstacles` returns a new costmap. Build one with :meth:`from_grid`.
    """

    __slots__ = (
        "_coarse",
        "_col0",
        "_dist",
        "_grid",
        "_labels",
        "_radius",
        "_row0",
        "_weights",
    )

    _grid: OccupancyGrid
    _radius: float
    _row0: int
    _col0: int
    # Over the stored region (rows × cols, both multiples of _COARSE): distance in cells
    # from each cell centre to the nearest lethal cell centre; weights (inf = not allowed);
    # the min-pooled coarse weights; 4-connected component labels of the allowed cells.
    _dist: npt.NDArray[np.float32]
    _weights: _Weights
    _coarse: _Weights
    _labels: npt.NDArray[np.int32]

    def __init__(self) -> None:
        raise TypeError("build a Costmap with Costmap.from_grid(grid, robot_radius)")

    @classmethod
    def from_grid(cls, grid: OccupancyGrid, robot_radius: float) -> Costmap:
        """Inflate ``grid`` by ``robot_radius`` (metres) into a costmap."""
        if not (math.isfinite(robot_radius) and robot_radius > 0):
            raise ValueError(f"robot radius must be a positive number, not {robot_radius}")
        bounds = grid.known_bounds()
        row0, row1, col0, col1 = bounds if bounds is not None else (0, 1, 0, 1)
        rows = _round_up(row1 - row0, _COARSE)
        cols = _round_up(col1 - col0, _COARSE)
        # Everything outside the known bounds is unknown or off the map: lethal. Padding the
        # region to whole coarse cells adds only lethal cells.
        passable = np.zeros((rows, cols), dtype=np.uint8)
        known = grid.data[row0:row1, col0:col1]
        passable[: row1 - row0, : col1 - col0] = (known != UNKNOWN) & (known < LETHAL_OCCUPANCY)
        # A lethal frame, so cells on the region's edge see the unknown beyond it.
        framed = cv2.copyMakeBorder(passable, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
        dist = cv2.distanceTransform(framed, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]

        self = object.__new__(cls)
        self._grid = grid
        self._radius = float(robot_radius)
        self._row0, self._col0 = row0, col0
        # Capped just past the inflation reach: farther distances change nothing, and the
        # cap is what lets with_obstacles update a bounded window exactly.
        self._dist = np.minimum(dist, np.float32(self._cap_cells())).astype(np.float32)
        self._weights = self._weights_of(self._dist)
        self._coarse = _min_pool(self._weights)
        self._labels = _components(self._weights)
        return self

    @property
    def grid(self) -> OccupancyGrid:
        """The occupancy grid this costmap was built from (without added obstacles)."""
        return self._grid

    @property
    def robot_radius(self) -> float:
        """The robot's radius in metres."""
        return self._radius

    def with_obstacles(self, obstacles: Sequence[Obstacle]) -> Costmap:
        """A new costmap with ``obstacles`` added as lethal, inflated like walls.

        Only the neighbourhood of each obstacle is recomputed: adding lethal cells can only
        shorten distances, so the new distance is the minimum of the old one and the distance
        to the obstacle, and nothing farther than the inflation reach changes weight.
        """
        new = object.__new__(Costmap)
        new._grid, new._radius = self._grid, self._radius
        new._row0, new._col0 = self._row0, self._col0
        new._dist = self._dist.copy()
        new._weights = self._weights.copy()
        new._coarse = self._coarse.copy()
        res = self._grid.resolution
        rows, cols = self._dist.shape
        reach_m = self._radius + INFLATION_DISTANCE
        changed = False
        for obs in obstacles:
            u, v = self._to_cells(obs.x, obs.y)
            half = math.ceil((obs.radius + reach_m) / res) + 4  # past the distance cap
            r0, r1 = max(math.floor(v) - half, 0), min(math.floor(v) + half + 1, rows)
            c0, c1 = max(math.floor(u) - half, 0), min(math.floor(u) + half + 1, cols)
            if r0 >= r1 or c0 >= c1:
                continue  # wholly outside the known region, which is lethal anyway
            # Cells whose centre the obstacle covers (as world.obstacle_mask), and always
            # the cell under its centre, so a tiny obstacle is not lost between centres.
            vs = np.arange(r0, r1, dtype=np.float64)[:, None] + 0.5
            us = np.arange(c0, c1, dtype=np.float64)[None, :] + 0.5
            inside = (us - u) ** 2 + (vs - v) ** 2 <= (obs.radius / res) ** 2
            cv, cu = math.floor(v), math.floor(u)
            if r0 <= cv < r1 and c0 <= cu < c1:
                inside[cv - r0, cu - c0] = True
            if not inside.any():
                continue
            window = cv2.distanceTransform(
                (~inside).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE
            )
            np.minimum(new._dist[r0:r1, c0:c1], window, out=new._dist[r0:r1, c0:c1])
            new._weights[r0:r1, c0:c1] = self._weights_of(new._dist[r0:r1, c0:c1])
            # Whole coarse cells over the window.
            k0, k1 = r0 // _COARSE, -(-r1 // _COARSE)
            j0, j1 = c0 // _COARSE, -(-c1 // _COARSE)
            block = new._weights[k0 * _COARSE : k1 * _COARSE, j0 * _COARSE : j1 * _COARSE]
            new._coarse[k0:k1, j0:j1] = _min_pool(block)
            changed = True
        # Connectivity is global: one obstacle can cut a corridor. Labelling the region is a
        # few milliseconds on the building map.
        new._labels = _components(new._weights) if changed else self._labels
        return new

    def is_free(self, x: float, y: float) -> bool:
        """Whether the robot's centre may be at world ``(x, y)`` (clear of every obstacle)."""
        cell = self._region_cell(x, y)
        return cell is not None and bool(np.isfinite(self._weights[cell]))

    def touches_wall(self, x: float, y: float) -> bool:
        """Whether the robot's disc at world ``(x, y)`` overlaps a wall, unknown space or
        the outside of the map: exact geometry against the cells' squares.

        :meth:`is_free` is the planner's conservative test (it measures between cell
        centres, so it can refuse a point a few centimetres clear of every wall);
        this one is what touching means, for the simulated physics.
        """
        if not (math.isfinite(x) and math.isfinite(y)):
            return True
        u, v = self._to_cells(x, y)
        reach = self._radius / self._grid.resolution  # in cells
        row_lo, row_hi = math.floor(v - reach), math.floor(v + reach)
        col_lo, col_hi = math.floor(u - reach), math.floor(u + reach)
        rows, cols = self._dist.shape
        if row_lo < 0 or col_lo < 0 or row_hi >= rows or col_hi >= cols:
            return True  # the disc reaches past the known region, which is lethal
        window = self._dist[row_lo : row_hi + 1, col_lo : col_hi + 1]
        lethal_rows, lethal_cols = np.nonzero(window == 0)
        if lethal_rows.size == 0:
            return False
        # Distance from (u, v) to each lethal cell's square [col, col+1] x [row, row+1].
        cells_u = lethal_cols + col_lo
        cells_v = lethal_rows + row_lo
        du = np.maximum(np.maximum(cells_u - u, u - (cells_u + 1)), 0.0)
        dv = np.maximum(np.maximum(cells_v - v, v - (cells_v + 1)), 0.0)
        return bool(np.any(du * du + dv * dv < reach * reach))

    def clearance(self, x: float, y: float) -> float:
        """Distance (metres) from world ``(x, y)``'s cell to the nearest lethal cell's edge.

        0 in lethal cells and outside the known part of the map; at most ``robot_radius +
        INFLATION_DISTANCE`` (farther walls do not matter to planning).
        """
        cell = self._region_cell(x, y)
        if cell is None:
            return 0.0
        metres = max(float(self._dist[cell]) - 0.5, 0.0) * self._grid.resolution
        return min(metres, self._radius + INFLATION_DISTANCE)

    def plan(self, start: tuple[float, float], goal: tuple[float, float]) -> PlannedPath:
        """A smoothed collision-free path from ``start`` to ``goal`` (world metres).

        A start in the inscribed zone (the robot brushing a wall) is escaped from: the path
        first goes to the nearest free cell within :data:`START_ESCAPE_DISTANCE`.

        Raises :class:`~telebot.errors.NoPath` with the reason only: ``"outside the map"``,
        ``"in unknown space"``, ``"inside an obstacle"`` (the goal is in a wall or too close
        to one for the robot), ``"unreachable"``, ``"start is outside the map"``, ``"start is
        in unknown space"`` or ``"start is inside an obstacle"`` (farther than that from free
        space).
        """
        sx, sy = float(start[0]), float(start[1])
        gx, gy = float(goal[0]), float(goal[1])
        goal_cell = self._check_goal(gx, gy)
        start_cell, escaped = self._start_cell(sx, sy, goal_cell)
        res = self._grid.resolution
        if math.hypot(gx - sx, gy - sy) <= res:
            return _path_of(np.array([[sx, sy], [gx, gy]]))

        cells = self._search(start_cell, goal_cell)
        centres = cells[:, ::-1].astype(np.float64) + 0.5  # (u, v) = (col, row) + ½
        # From the exact start (or, escaping, the free cell's centre: the robot first backs
        # off there, in a straight line) to the exact goal.
        ends = [np.array([self._to_cells(gx, gy)])]
        if not escaped:
            ends.insert(0, np.array([self._to_cells(sx, sy)]))
        points = np.vstack([*ends[:-1], centres, ends[-1]])
        points = _shortcut(points, self._weights)
        world = np.empty_like(points)
        world[:, 0] = self._grid.origin_x + (points[:, 0] + self._col0) * res
        world[:, 1] = self._grid.origin_y + (points[:, 1] + self._row0) * res
        # Exact ends: the float round trip through cell coordinates must not move them.
        world[-1] = (gx, gy)
        if escaped:
            # The escape stays one segment, so a follower (or a test) can tell it apart.
            return _path_of(np.vstack([[sx, sy], _densify(world, WAYPOINT_SPACING)]))
        world[0] = (sx, sy)
        return _path_of(_densify(world, WAYPOINT_SPACING))

    # -- internals ------------------------------------------------------------------------

    def _cap_cells(self) -> float:
        """Stored distances (cells) stop here, a cell past the inflation reach."""
        return (self._radius + INFLATION_DISTANCE) / self._grid.resolution + 1.5

    def _weights_of(self, dist: npt.NDArray[np.float32]) -> _Weights:
        """Weights for distances ``dist`` (cells from centre to nearest lethal centre)."""
        res = self._grid.resolution
        clearance = (dist.astype(np.float64) - 0.5) * res
        closeness = np.clip(
            (self._radius + INFLATION_DISTANCE - clearance) / INFLATION_DISTANCE, 0, 1
        )
        weights = (1.0 + INFLATION_WEIGHT * closeness**2).astype(np.float32)
        weights[clearance < self._radius] = np.inf
        return weights

    def _to_cells(self, x: float, y: float) -> tuple[float, float]:
        """World ``(x, y)`` in continuous region cell coordinates ``(u, v)`` = (col, row)."""
        res = self._grid.resolution
        return (
            (x - self._grid.origin_x) / res - self._col0,
            (y - self._grid.origin_y) / res - self._row0,
        )

    def _region_cell(self, x: float, y: float) -> tuple[int, int] | None:
        """Region ``(row, col)`` of world ``(x, y)``, or None outside the stored region."""
        if not (math.isfinite(x) and math.isfinite(y)):
            return None
        u, v = self._to_cells(x, y)
        row, col = math.floor(v), math.floor(u)
        rows, cols = self._weights.shape
        if 0 <= row < rows and 0 <= col < cols:
            return row, col
        return None

    def _check_goal(self, x: float, y: float) -> tuple[int, int]:
        if not (math.isfinite(x) and math.isfinite(y)) or not self._grid.contains(x, y):
            raise NoPath("outside the map")
        if self._grid.value_at(x, y) == UNKNOWN:
            raise NoPath("in unknown space")
        cell = self._region_cell(x, y)
        if cell is None or not np.isfinite(self._weights[cell]):
            raise NoPath("inside an obstacle")
        return cell

    def _start_cell(
        self, x: float, y: float, goal: tuple[int, int]
    ) -> tuple[tuple[int, int], bool]:
        """The start's region cell, or the free cell it escapes to; and whether it escaped."""
        if not (math.isfinite(x) and math.isfinite(y)) or not self._grid.contains(x, y):
            raise NoPath("start is outside the map")
        target = self._labels[goal]
        cell = self._region_cell(x, y)
        if cell is not None and np.isfinite(self._weights[cell]):
            if self._labels[cell] != target:
                raise NoPath("unreachable")
            return cell, False
        # Back off in a straight line to the nearest allowed cell within reach that is
        # connected to the goal, without crossing a wall (a robot brushing one side of a thin
        # wall must not "escape" to the other side).
        u, v = self._to_cells(x, y)
        reach = START_ESCAPE_DISTANCE / self._grid.resolution
        rows, cols = self._weights.shape
        r0, r1 = max(math.floor(v - reach), 0), min(math.floor(v + reach) + 1, rows)
        c0, c1 = max(math.floor(u - reach), 0), min(math.floor(u + reach) + 1, cols)
        near: list[tuple[float, int, int]] = []
        if r0 < r1 and c0 < c1:
            vs = np.arange(r0, r1)[:, None] + 0.5
            us = np.arange(c0, c1)[None, :] + 0.5
            d2 = (us - u) ** 2 + (vs - v) ** 2
            free = np.isfinite(self._weights[r0:r1, c0:c1]) & (d2 <= reach**2)
            near = sorted((float(d2[a, b]), r0 + int(a), c0 + int(b)) for a, b in np.argwhere(free))
        cut_off = False
        for _, row, col in near:
            if not self._straight_without_walls((u, v), (row, col)):
                continue
            if self._labels[row, col] == target:
                return (row, col), True
            cut_off = True
        if cut_off:
            raise NoPath("unreachable")
        if self._grid.value_at(x, y) == UNKNOWN:
            raise NoPath("start is in unknown space")
        raise NoPath("start is inside an obstacle")

    def _straight_without_walls(self, start: tuple[float, float], cell: tuple[int, int]) -> bool:
        """Whether the segment from ``start`` (u, v) to ``cell``'s centre crosses no lethal
        cell besides the one ``start`` is in."""
        p = np.array(start)
        rows, cols = _touched(p, np.array([cell[1] + 0.5, cell[0] + 0.5]))
        height, width = self._dist.shape
        inside = (rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)
        own = (rows == math.floor(start[1])) & (cols == math.floor(start[0]))
        if not inside[~own].all():
            return False
        rows, cols = rows[~own], cols[~own]
        # Lethal cells are at distance 0 from themselves.
        return bool((self._dist[rows, cols] >= 0.5).all())

    def _search(self, start: tuple[int, int], goal: tuple[int, int]) -> _Cells:
        """Region cells ``(row, col)`` of a 4-connected path from ``start`` to ``goal``."""
        if start == goal:
            return np.array([start], dtype=np.intp)
        band = self._band(start, goal)
        if band is not None:
            (r0, c0), weights = band
            found = pyastar2d.astar_path(
                weights, (start[0] - r0, start[1] - c0), (goal[0] - r0, goal[1] - c0)
            )
            if found is not None:
                return np.asarray(found, dtype=np.intp) + np.array([r0, c0], dtype=np.intp)
        # The coarse route was optimistic (a gap only the downsampling opened): search it all.
        found = pyastar2d.astar_path(self._weights, start, goal)
        if found is None:  # cannot happen while the labels agree, but never return garbage
            raise NoPath("unreachable")
        return np.asarray(found, dtype=np.intp)

    def _band(
        self, start: tuple[int, int], goal: tuple[int, int]
    ) -> tuple[tuple[int, int], _Weights] | None:
        """Fine weights limited to a band around the coarse route, with their offset."""
        coarse = pyastar2d.astar_path(
            self._coarse,
            (start[0] // _COARSE, start[1] // _COARSE),
            (goal[0] // _COARSE, goal[1] // _COARSE),
            allow_diagonal=True,
        )
        if coarse is None:
            return None
        half = math.ceil(_BAND / self._grid.resolution) + _COARSE
        rows, cols = self._weights.shape
        route = np.asarray(coarse, dtype=np.int64) * _COARSE + _COARSE // 2
        r0 = max(int(route[:, 0].min()) - half, 0)
        r1 = min(int(route[:, 0].max()) + half + 1, rows)
        c0 = max(int(route[:, 1].min()) - half, 0)
        c1 = min(int(route[:, 1].max()) + half + 1, cols)
        mask = np.zeros((r1 - r0, c1 - c0), dtype=np.uint8)
        polyline = (route[:, ::-1] - np.array([c0, r0])).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(mask, [polyline], isClosed=False, color=1, thickness=2 * half + 1)
        # The ends lie within a coarse cell of the route, so inside the band; made certain.
        mask[start[0] - r0, start[1] - c0] = mask[goal[0] - r0, goal[1] - c0] = 1
        weights = np.where(mask.view(bool), self._weights[r0:r1, c0:c1], np.float32(np.inf))
        return (r0, c0), weights


def _round_up(n: int, multiple: int) -> int:
    return -(-max(n, 1) // multiple) * multiple


def _min_pool(weights: _Weights) -> _Weights:
    """Each ``_COARSE``² block's smallest weight: a coarse cell is open if any part is."""
    rows, cols = weights.shape
    blocks = weights.reshape(rows // _COARSE, _COARSE, cols // _COARSE, _COARSE)
    return np.ascontiguousarray(blocks.min(axis=(1, 3)))


def _components(weights: _Weights) -> npt.NDArray[np.int32]:
    """4-connected components of the allowed cells (label 0: not allowed), as A* moves."""
    allowed = np.isfinite(weights).astype(np.uint8)
    _, labels = cv2.connectedComponents(allowed, connectivity=4, ltype=cv2.CV_32S)
    return np.asarray(labels, dtype=np.int32)


def _touched(p: npt.NDArray[np.float64], q: npt.NDArray[np.float64]) -> tuple[_Cells, _Cells]:
    """Rows and columns of every cell the segment ``p``–``q`` touches (u, v coordinates).

    Exact supercover: the cells at both ends and on both sides of every grid line crossed,
    with a small tolerance so that passing through a corner checks all four cells there.
    """
    (u0, v0), (u1, v1) = p, q
    us: list[npt.NDArray[np.float64]] = [np.array([u0, u1])]
    vs: list[npt.NDArray[np.float64]] = [np.array([v0, v1])]
    if u0 != u1:
        ks = np.arange(math.ceil(min(u0, u1)), math.floor(max(u0, u1)) + 1, dtype=np.float64)
        us.append(ks)
        vs.append(v0 + (ks - u0) * ((v1 - v0) / (u1 - u0)))
    if v0 != v1:
        ks = np.arange(math.ceil(min(v0, v1)), math.floor(max(v0, v1)) + 1, dtype=np.float64)
        vs.append(ks)
        us.append(u0 + (ks - v0) * ((u1 - u0) / (v1 - v0)))
    u = np.concatenate(us)
    v = np.concatenate(vs)
    cols = np.floor(np.concatenate([u - _EDGE_EPS, u + _EDGE_EPS, u - _EDGE_EPS, u + _EDGE_EPS]))
    rows = np.floor(np.concatenate([v - _EDGE_EPS, v - _EDGE_EPS, v + _EDGE_EPS, v + _EDGE_EPS]))
    return rows.astype(np.intp), cols.astype(np.intp)


def _line_cost(
    weights: _Weights, p: npt.NDArray[np.float64], q: npt.NDArray[np.float64]
) -> tuple[float, float]:
    """``(cost, worst weight)`` of the straight move ``p``→``q``; inf if it touches a wall."""
    rows, cols = _touched(p, q)
    height, width = weights.shape
    if rows.min() < 0 or cols.min() < 0 or rows.max() >= height or cols.max() >= width:
        return math.inf, math.inf
    worst = float(weights[rows, cols].max())
    if not math.isfinite(worst):
        return math.inf, math.inf
    length = math.hypot(q[0] - p[0], q[1] - p[1])
    # The cost integral, sampled every half cell (the supercover over-counts corners).
    n = max(math.ceil(length * 2.0), 1)
    t = (np.arange(n, dtype=np.float64) + 0.5) / n
    su = p[0] + t * (q[0] - p[0])
    sv = p[1] + t * (q[1] - p[1])
    mean = float(weights[np.floor(sv).astype(np.intp), np.floor(su).astype(np.intp)].mean())
    return length * mean, worst


def _shortcut(points: _Points, weights: _Weights) -> _Points:
    """Greedy line-of-sight smoothing of a raw cell path (u, v coordinates).

    From each kept point, jump to the farthest later point the robot can drive to in a
    straight line that touches no forbidden cell, comes no closer to walls than the raw
    stretch it replaces (its worst weight is no higher) and costs no more than that stretch.
    The last two rules keep the path centred in corridors and doors: a bare line-of-sight
    rule would pull it tight against every corner it turns.
    """
    n = len(points)
    if n <= 2:
        return points
    rows = np.floor(points[:, 1]).astype(np.intp)
    cols = np.floor(points[:, 0]).astype(np.intp)
    w = weights[rows, cols].astype(np.float64)
    steps = np.hypot(*np.diff(points, axis=0).T)
    cum = np.concatenate([[0.0], np.cumsum(steps * (w[:-1] + w[1:]) * 0.5)])

    def ok(i: int, j: int) -> bool:
        cost, worst = _line_cost(weights, points[i], points[j])
        budget = (cum[j] - cum[i]) * (1.0 + _COST_TOLERANCE) + 1e-9
        return cost <= budget and worst <= float(w[i : j + 1].max()) * (1.0 + _COST_TOLERANCE)

    keep = [0]
    i = 0
    while i < n - 1:
        # Gallop to the first failing jump, then bisect for the farthest good one. (Success
        # is not monotonic in j; this finds a good jump, not always the farthest.)
        good, step = i + 1, 1
        bad = n
        while True:
            j = min(i + step * 2, n - 1)
            if j == good:
                break
            if ok(i, j):
                good, step = j, step * 2
                if j == n - 1:
                    break
            else:
                bad = j
                break
        while bad - good > 1:
            mid = (good + bad) // 2
            if ok(i, mid):
                good = mid
            else:
                bad = mid
        keep.append(good)
        i = good
    return points[keep]


def _densify(points: _Points, spacing: float) -> _Points:
    """``points`` with extra points on each segment so none is longer than ``spacing``."""
    seg = np.diff(points, axis=0)
    pieces = np.maximum(np.ceil(np.hypot(seg[:, 0], seg[:, 1]) / spacing), 1).astype(np.intp)
    owner = np.repeat(np.arange(len(seg)), pieces)
    # Fraction along its segment of each new point: 1/n, 2/n, …, n/n.
    first = np.cumsum(pieces) - pieces
    t = (np.arange(len(owner)) - first[owner] + 1) / pieces[owner]
    result = np.vstack([points[:1], points[owner] + t[:, None] * seg[owner]])
    result[-1] = points[-1]  # exact, not a + 1.0 · (b - a)
    return result


def _path_of(waypoints: _Points) -> PlannedPath:
    waypoints = np.ascontiguousarray(waypoints, dtype=np.float64)
    length = float(np.hypot(*np.diff(waypoints, axis=0).T).sum())
    # Shared with controllers and renderers: frozen like the grid.
    waypoints.flags.writeable = False
    return PlannedPath(waypoints=waypoints, length=length)
