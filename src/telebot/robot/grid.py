"""The occupancy grid: the robot's map, as ROS ``nav_msgs/OccupancyGrid`` defines it.

``data[row, col]`` holds -1 (unknown), 0 (free) … 100 (occupied). Row 0 is the row of cells
nearest the map origin (the *bottom* row of the map_server image), so cell ``(row, col)``
covers world ``x ∈ [ox + col·res, ox + (col+1)·res)`` and ``y ∈ [oy + row·res, oy + (row+1)·res)``.
The origin is the world pose of cell (0, 0)'s lower-left corner; like most ROS tools we
support only an unrotated origin (yaw 0), which is what every SLAM package writes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ["FREE", "OCCUPIED", "UNKNOWN", "OccupancyGrid"]

UNKNOWN = -1
FREE = 0
OCCUPIED = 100


@dataclass(frozen=True, slots=True, eq=False)
class OccupancyGrid:
    """A 2-D occupancy grid with its georeference (resolution in metres per cell, origin)."""

    data: npt.NDArray[np.int8]
    resolution: float
    origin_x: float
    origin_y: float

    def __post_init__(self) -> None:
        if self.data.ndim != 2 or self.data.dtype != np.int8:
            raise ValueError("occupancy grid data must be a 2-D int8 array")
        if not (math.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(f"map resolution must be a positive number, not {self.resolution}")
        if not (math.isfinite(self.origin_x) and math.isfinite(self.origin_y)):
            raise ValueError("map origin must be finite")
        # Frozen in fact, not only in name: planners and renderers share this array.
        self.data.flags.writeable = False

    def same_content(self, other: OccupancyGrid) -> bool:
        """Whether ``other`` is the same map: cells, resolution and origin (size included).

        What a map's version stands for: a map republished unchanged (a SLAM node or a
        map server publishing on a timer, with a new header stamp) is the same content.
        """
        return (
            self.resolution == other.resolution
            and self.origin_x == other.origin_x
            and self.origin_y == other.origin_y
            and self.data.shape == other.data.shape
            and bool(np.array_equal(self.data, other.data))
        )

    @property
    def height(self) -> int:
        """Number of rows (cells along y)."""
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        """Number of columns (cells along x)."""
        return int(self.data.shape[1])

    @property
    def size_m(self) -> tuple[float, float]:
        """World extent (width, height) in metres."""
        return self.width * self.resolution, self.height * self.resolution

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """The ``(row, col)`` of the cell containing world point ``(x, y)`` (may be outside)."""
        col = math.floor((x - self.origin_x) / self.resolution)
        row = math.floor((y - self.origin_y) / self.resolution)
        return row, col

    def center_of(self, row: int, col: int) -> tuple[float, float]:
        """World ``(x, y)`` of the centre of cell ``(row, col)``."""
        return (
            self.origin_x + (col + 0.5) * self.resolution,
            self.origin_y + (row + 0.5) * self.resolution,
        )

    def contains_cell(self, row: int, col: int) -> bool:
        """Whether ``(row, col)`` lies inside the grid."""
        return 0 <= row < self.height and 0 <= col < self.width

    def contains(self, x: float, y: float) -> bool:
        """Whether world point ``(x, y)`` lies inside the grid."""
        return self.contains_cell(*self.cell_of(x, y))

    def value_at(self, x: float, y: float) -> int:
        """Occupancy at world ``(x, y)``; points outside the grid count as unknown."""
        row, col = self.cell_of(x, y)
        if not self.contains_cell(row, col):
            return UNKNOWN
        return int(self.data[row, col])

    def known_bounds(self) -> tuple[int, int, int, int] | None:
        """``(row0, row1, col0, col1)`` (half-open) bounding every known cell, or None."""
        known = self.data != UNKNOWN
        rows = np.flatnonzero(known.any(axis=1))
        if rows.size == 0:
            return None
        cols = np.flatnonzero(known.any(axis=0))
        return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1

    def crop(self, row0: int, row1: int, col0: int, col1: int) -> OccupancyGrid:
        """The sub-grid of rows ``row0:row1`` and columns ``col0:col1``, georeferenced."""
        if not (0 <= row0 < row1 <= self.height and 0 <= col0 < col1 <= self.width):
            raise ValueError(f"crop {row0}:{row1}, {col0}:{col1} is outside the grid")
        return OccupancyGrid(
            data=np.ascontiguousarray(self.data[row0:row1, col0:col1]),
            resolution=self.resolution,
            origin_x=self.origin_x + col0 * self.resolution,
            origin_y=self.origin_y + row0 * self.resolution,
        )
