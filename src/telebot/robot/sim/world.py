"""Things in the simulated world besides the map: dynamic obstacles (a person in a corridor)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from telebot.robot.grid import OccupancyGrid

__all__ = ["Obstacle", "obstacle_mask"]


@dataclass(frozen=True, slots=True)
class Obstacle:
    """A round obstacle standing on the floor at ``(x, y)`` (metres, map frame)."""

    x: float
    y: float
    radius: float = 0.25
    #: Height in metres, for the cameras.
    height: float = 1.7

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.x, self.y, self.radius, self.height)):
            raise ValueError("obstacle position and size must be finite")
        if self.radius <= 0 or self.height <= 0:
            raise ValueError("obstacle radius and height must be positive")


def obstacle_mask(
    grid: OccupancyGrid, obstacles: tuple[Obstacle, ...] | list[Obstacle]
) -> npt.NDArray[np.bool_]:
    """Boolean mask, shaped like ``grid.data``, of the cells the obstacles cover."""
    mask = np.zeros(grid.data.shape, dtype=bool)
    res = grid.resolution
    for obs in obstacles:
        row_c, col_c = grid.cell_of(obs.x, obs.y)
        reach = math.ceil(obs.radius / res) + 1
        r0, r1 = max(row_c - reach, 0), min(row_c + reach + 1, grid.height)
        c0, c1 = max(col_c - reach, 0), min(col_c + reach + 1, grid.width)
        if r0 >= r1 or c0 >= c1:
            continue
        rows = np.arange(r0, r1)[:, None]
        cols = np.arange(c0, c1)[None, :]
        xs = grid.origin_x + (cols + 0.5) * res
        ys = grid.origin_y + (rows + 0.5) * res
        mask[r0:r1, c0:c1] |= (xs - obs.x) ** 2 + (ys - obs.y) ** 2 <= obs.radius**2
    return mask
