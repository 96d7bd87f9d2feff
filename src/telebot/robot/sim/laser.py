"""A simulated 2-D laser scanner: rays cast through the occupancy grid and past round obstacles.

The map is solid where it is occupied (≥ 50) *and* where it is unknown (-1), and so is
everything outside the grid: unexplored space is where the walls are, and a robot that sees
through it would plan through it. Dynamic obstacles (people, :class:`Obstacle`) are cylinders
intersected analytically, so they are exact, not rasterised.

The ray casting (:class:`RayCaster`, shared with the cameras) is an exact grid traversal (DDA)
done with numpy over all rays at once: a ray enters a new cell only where it crosses a vertical
grid line (x crossing) or a horizontal one (y crossing), so the first solid cell is the nearest
solid one among the cells entered at the x crossings and at the y crossings, computed
separately, with no sorting and no per-ray Python loop. Rays advance in distance windows that
double each round, so short rays (most of them, indoors) cost little and long ones take a
logarithmic number of rounds.

A pose that is outside the map or inside a solid cell reads range 0 on every beam: the sensor is
inside something solid, and 0 is the honest reading (it is also what makes a planner stop).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from telebot.robot.grid import OccupancyGrid
from telebot.robot.nav import Pose2D
from telebot.robot.sim.world import Obstacle

__all__ = [
    "CELL_FREE",
    "CELL_OCCUPIED",
    "CELL_UNKNOWN",
    "OCCUPIED_THRESHOLD",
    "SIDE_INSIDE",
    "SIDE_NONE",
    "SIDE_X",
    "SIDE_Y",
    "Laser",
    "LaserScan",
    "RayCaster",
    "RayHits",
    "intersect_circles",
]

#: Map values at or above this are walls: the midpoint of the 0 … 100 occupancy scale.
OCCUPIED_THRESHOLD = 50

#: Cell classes of :attr:`RayCaster.cells` (and :attr:`RayHits.kind`).
CELL_FREE = 0
CELL_OCCUPIED = 1
CELL_UNKNOWN = 2  # unknown in the map, or outside it

#: Which kind of grid line the ray crossed into the cell it hit (:attr:`RayHits.side`): an x
#: crossing means it hit a face whose normal is along ±x, a y crossing one along ±y.
SIDE_NONE = -1  # nothing hit within range
SIDE_X = 0
SIDE_Y = 1
SIDE_INSIDE = 2  # the ray started inside a solid cell (or outside the grid)

# Cells of solid padding around the grid: one is enough for the traversal to stop at the
# grid's edge, the second absorbs floating-point rounding of a ray grazing a corner.
_PAD = 2
# The first window a ray is checked over, in cells; it doubles every round.
_FIRST_WINDOW = 24.0
_BIG = 1e30


@dataclass(frozen=True, slots=True, eq=False)
class RayHits:
    """Where a bundle of rays hit the map, in metres from the ray origin.

    ``distance`` is ``max_range`` for a ray that hit nothing, and 0 for a ray that starts
    inside a solid cell. ``side`` is :data:`SIDE_X`, :data:`SIDE_Y`, :data:`SIDE_NONE` or
    :data:`SIDE_INSIDE`; ``kind`` the class of the hit cell (:data:`CELL_OCCUPIED` or
    :data:`CELL_UNKNOWN`; :data:`CELL_FREE` when nothing was hit).
    """

    distance: npt.NDArray[np.float64]
    side: npt.NDArray[np.int8]
    kind: npt.NDArray[np.uint8]


class RayCaster:
    """Casts many rays at once through an occupancy grid (see the module docstring).

    The grid is immutable, so the solid/free classification (with a solid border, which makes
    "outside the map" solid without bounds checks in the inner loop) is computed once here.
    """

    __slots__ = ("_height", "_ox", "_oy", "_res", "_stride", "_width", "cells")

    def __init__(self, grid: OccupancyGrid) -> None:
        data = grid.data
        cells = np.full(
            (grid.height + 2 * _PAD, grid.width + 2 * _PAD), CELL_UNKNOWN, dtype=np.uint8
        )
        inner = cells[_PAD:-_PAD, _PAD:-_PAD]
        inner[...] = CELL_FREE
        inner[data >= OCCUPIED_THRESHOLD] = CELL_OCCUPIED
        inner[data < 0] = CELL_UNKNOWN
        cells.flags.writeable = False
        #: Padded cell classes (``CELL_*``); cell (row, col) of the grid is at
        #: ``[row + 2, col + 2]``.
        self.cells: npt.NDArray[np.uint8] = cells
        self._stride = cells.shape[1]
        self._width = grid.width
        self._height = grid.height
        self._res = grid.resolution
        self._ox = grid.origin_x
        self._oy = grid.origin_y

    def cast(
        self,
        x: float,
        y: float,
        directions: npt.NDArray[np.float64],
        max_range: float,
    ) -> RayHits:
        """Cast rays from world ``(x, y)`` along ``directions`` (world radians, CCW from +x).

        Each ray stops at the first solid cell it enters (or at ``max_range`` metres). From a
        point outside the grid or inside a solid cell every ray reads 0.
        """
        n = directions.shape[0]
        if not (math.isfinite(x) and math.isfinite(y) and bool(np.isfinite(directions).all())):
            raise ValueError("ray origin and directions must be finite")
        res = self._res
        gx = (x - self._ox) / res
        gy = (y - self._oy) / res
        c0 = math.floor(gx)
        r0 = math.floor(gy)
        inside = 0 <= r0 < self._height and 0 <= c0 < self._width
        start_kind = int(self.cells[r0 + _PAD, c0 + _PAD]) if inside else CELL_UNKNOWN
        if start_kind != CELL_FREE:
            return RayHits(
                distance=np.zeros(n),
                side=np.full(n, SIDE_INSIDE, dtype=np.int8),
                kind=np.full(n, start_kind, dtype=np.uint8),
            )
        max_t = max_range / res
        t_hit = np.full(n, max_t)
        side = np.full(n, SIDE_NONE, dtype=np.int8)
        kind = np.full(n, CELL_FREE, dtype=np.uint8)
        if n:
            dx = np.cos(directions)
            dy = np.sin(directions)
            self._traverse(gx, gy, c0, r0, dx, dy, max_t, t_hit, side, kind)
        return RayHits(t_hit * res, side, kind)

    def _traverse(
        self,
        gx: float,
        gy: float,
        c0: int,
        r0: int,
        dx: npt.NDArray[np.float64],
        dy: npt.NDArray[np.float64],
        max_t: float,
        t_hit: npt.NDArray[np.float64],
        side: npt.NDArray[np.int8],
        kind: npt.NDArray[np.uint8],
    ) -> None:
        """Fill ``t_hit`` (cells), ``side`` and ``kind`` for the rays that hit within ``max_t``."""
        flat = self.cells.reshape(-1)
        stride = self._stride
        # Per axis: the step direction, the ray parameter of the first grid-line crossing and
        # the spacing of the next ones. An axis the ray does not move along never crosses.
        sx = np.sign(dx)
        sy = np.sign(dy)
        with np.errstate(divide="ignore"):
            inv_x = np.where(dx != 0.0, 1.0 / np.abs(dx), _BIG)
            inv_y = np.where(dy != 0.0, 1.0 / np.abs(dy), _BIG)
        fx = gx - c0  # position within the start cell, 0 … 1
        fy = gy - r0
        tx0 = np.where(dx > 0, 1.0 - fx, fx) * inv_x
        ty0 = np.where(dy > 0, 1.0 - fy, fy) * inv_y
        tx0[dx == 0.0] = _BIG
        ty0[dy == 0.0] = _BIG
        # Flat index (padded array) of the start cell; the k-th x crossing enters column
        # c0 + (k+1)·sx, the k-th y crossing row r0 + (k+1)·sy.
        base = (r0 + _PAD) * stride + (c0 + _PAD)

        active = np.arange(dx.shape[0])
        lo = 0.0
        window = _FIRST_WINDOW
        while active.size and lo < max_t:
            hi = min(lo + window, max_t)
            a_dx, a_dy = dx[active], dy[active]
            a_sx, a_sy = sx[active], sy[active]
            a_ix, a_iy = inv_x[active], inv_y[active]
            a_tx0, a_ty0 = tx0[active], ty0[active]
            best = np.full(active.size, np.inf)
            best_side = np.full(active.size, SIDE_NONE, dtype=np.int8)
            best_idx = np.zeros(active.size, dtype=np.intp)
            for axis in (SIDE_X, SIDE_Y):
                # An x crossing enters the next column (stepping along the row); the row it
                # enters is found from where the ray is. A y crossing is the transpose.
                if axis == SIDE_X:
                    t0, inv, step = a_tx0, a_ix, a_sx
                    other_pos, other_start, other_dir = gy, r0, a_dy
                    along_scale, other_scale = 1, stride
                else:
                    t0, inv, step = a_ty0, a_iy, a_sy
                    other_pos, other_start, other_dir = gx, c0, a_dx
                    along_scale, other_scale = stride, 1
                # Crossings k with lo ≤ t_k < hi, where t_k = t0 + k·inv.
                k_first = np.maximum(np.ceil((lo - t0) / inv), 0.0)
                count = math.ceil((hi - lo) * float(np.max(1.0 / inv))) + 1
                k = k_first[:, None] + np.arange(count, dtype=np.float64)
                t = t0[:, None] + k * inv[:, None]
                valid = t < hi
                # Clamp so that crossings past the window (never used) stay near the grid.
                t = np.minimum(t, hi)
                other = np.floor(other_pos + t * other_dir[:, None]) - other_start
                idx = (
                    base
                    + ((k + 1.0) * (step * along_scale)[:, None]).astype(np.intp)
                    + (other * other_scale).astype(np.intp)
                )
                solid = np.take(flat, idx, mode="clip").astype(bool) & valid
                first = np.argmax(solid, axis=1)
                rows = np.arange(active.size)
                found = solid[rows, first]
                t_first = np.where(found, t[rows, first], np.inf)
                better = t_first < best
                best = np.where(better, t_first, best)
                best_side = np.where(better, np.int8(axis), best_side)
                best_idx = np.where(better, idx[rows, first], best_idx)
            hit = np.isfinite(best)
            done = active[hit]
            t_hit[done] = best[hit]
            side[done] = best_side[hit]
            kind[done] = flat[best_idx[hit]]
            active = active[~hit]
            lo = hi
            window *= 2.0


def intersect_circles(
    x: float,
    y: float,
    directions: npt.NDArray[np.float64],
    obstacles: Sequence[Obstacle],
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.intp]]:
    """Distance along each ray from ``(x, y)`` to the nearest obstacle circle, and its index.

    ``inf`` and -1 where a ray misses every obstacle; 0 where the origin is inside one.
    """
    n = directions.shape[0]
    if not obstacles:
        return np.full(n, np.inf), np.full(n, -1, dtype=np.intp)
    centres = np.array([(o.x - x, o.y - y) for o in obstacles], dtype=np.float64)
    radii = np.array([o.radius for o in obstacles], dtype=np.float64)
    dx = np.cos(directions)[:, None]
    dy = np.sin(directions)[:, None]
    # |o + t·d - c|² = r²  →  t² - 2bt + c = 0 with b = d·c, c = |c|² - r².
    b = dx * centres[:, 0] + dy * centres[:, 1]
    c = (centres**2).sum(axis=1) - radii**2
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        root = np.sqrt(disc)
    near = b - root
    inside = c <= 0.0
    t = np.where(inside, 0.0, np.where((disc >= 0.0) & (near >= 0.0), near, np.inf))
    which = np.argmin(t, axis=1)
    rows = np.arange(n)
    best = t[rows, which]
    return best, np.where(np.isfinite(best), which, -1)


@dataclass(frozen=True, slots=True, eq=False)
class LaserScan:
    """One 360° scan in the robot frame (REP-103: angle 0 is straight ahead, CCW positive)."""

    #: Beam angles relative to the robot's heading, radians, CCW, covering 360°.
    angles: npt.NDArray[np.float64]
    #: Metres; ``range_max`` where nothing was hit within range, 0 from inside something solid.
    ranges: npt.NDArray[np.float64]
    range_max: float

    def points(self) -> npt.NDArray[np.float64]:
        """``(K, 2)`` robot-frame x, y of the beams that hit something (range < range_max)."""
        hit = self.ranges < self.range_max
        r = self.ranges[hit]
        a = self.angles[hit]
        return np.stack((r * np.cos(a), r * np.sin(a)), axis=1)


class Laser:
    """A simulated 360° planar laser on the robot (see the module docstring).

    Beams are evenly spaced and in increasing angle, as in a ROS ``LaserScan`` with
    ``angle_min = -π``: beam ``i`` points at ``(i - beams // 2) · 2π / beams`` from the robot's
    heading, so beam ``beams // 2`` looks straight ahead (exactly angle 0) and, for 360 beams,
    beam 270 looks to the left (+π/2). Ranges are exact to the cell boundary of the map (so
    within one cell of the true wall) and exact for obstacles.
    """

    __slots__ = ("_angles", "_caster", "beams", "range_max")

    def __init__(self, grid: OccupancyGrid, *, beams: int = 360, range_max: float = 10.0) -> None:
        if beams < 1:
            raise ValueError(f"a laser needs at least one beam, not {beams}")
        if not (math.isfinite(range_max) and range_max > 0):
            raise ValueError(f"range_max must be a positive number, not {range_max}")
        self.beams = beams
        self.range_max = float(range_max)
        self._caster = RayCaster(grid)
        # Integer offsets so that the straight-ahead beam is exactly 0, not -π + π ± ε.
        angles = (np.arange(beams, dtype=np.float64) - beams // 2) * (2.0 * math.pi / beams)
        angles.flags.writeable = False
        self._angles = angles

    @property
    def angles(self) -> npt.NDArray[np.float64]:
        """Beam angles relative to the heading (read-only)."""
        return self._angles

    def scan(self, pose: Pose2D, obstacles: Sequence[Obstacle] = ()) -> LaserScan:
        """The scan seen from ``pose`` with ``obstacles`` in the world."""
        world = self._angles + pose.yaw
        hits = self._caster.cast(pose.x, pose.y, world, self.range_max)
        ranges = hits.distance
        if obstacles and hits.side[0] != SIDE_INSIDE:
            t_obs, _ = intersect_circles(pose.x, pose.y, world, obstacles)
            ranges = np.minimum(ranges, t_obs)
        ranges = np.minimum(ranges, self.range_max)
        ranges.flags.writeable = False
        return LaserScan(angles=self._angles, ranges=ranges, range_max=self.range_max)
