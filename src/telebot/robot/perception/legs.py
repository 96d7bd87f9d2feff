"""Laser leg detection (sans-IO): people as pairs of leg-sized clusters in a 2-D scan.

The approach of ROS's ``leg_detector`` / ``leg_tracker``, without their trained classifier:

1. **Segment** the scan: consecutive beams belong to one cluster while their points are
   less than ``jump + jump_per_m · range`` apart (a person in front of a wall is split from
   it, and so is a leg from the chair beside it).
2. **Leg-like clusters**: narrow (``min_width`` … ``max_width`` end to end), in range, and
   *in front* of both neighbours (each neighbouring beam reads farther, or nothing): a leg
   occludes what is behind it, whereas the end of a wall or a corner continues into it.
3. **Pair** legs closest first while they are ``max_pair_gap`` apart or less: a person is the
   midpoint. A lone leg is a person too, at lower confidence (the other leg is hidden behind
   it when someone walks across the beam). Two legs merged into one cluster (far away, or
   together) are a cluster up to ``max_merged_width`` wide.

Points that a ``static`` test says are on the map (walls, furniture of the map) are dropped
before pairing: the robot knows its map, and a door's jamb is as narrow as a leg.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ["Leg", "LegDetector", "LegParams", "PersonCandidate"]


@dataclass(frozen=True, slots=True)
class LegParams:
    """Tuning of :class:`LegDetector` (metres)."""

    jump: float = 0.08
    jump_per_m: float = 0.03
    min_width: float = 0.0
    max_width: float = 0.22
    max_merged_width: float = 0.22
    max_pair_gap: float = 0.5
    min_range: float = 0.15
    max_range: float = 8.0


@dataclass(frozen=True, slots=True)
class Leg:
    """A leg-like cluster: centre (sensor frame, metres), width, beams in it."""

    x: float
    y: float
    width: float
    beams: int


@dataclass(frozen=True, slots=True)
class PersonCandidate:
    """A person seen by the laser: position in the sensor frame and how sure (0 … 1)."""

    x: float
    y: float
    confidence: float
    legs: int


class LegDetector:
    """Finds people in one scan (see the module docstring). Pure: no state between scans."""

    def __init__(self, params: LegParams | None = None) -> None:
        self.params = params if params is not None else LegParams()

    def legs(
        self,
        angles: npt.NDArray[np.float64],
        ranges: npt.NDArray[np.float64],
        range_max: float,
    ) -> list[Leg]:
        """The leg-like clusters of a scan (beams in increasing angle, ranges in metres).

        Non-finite, negative and out-of-range readings count as "nothing there".
        """
        p = self.params
        angles = np.asarray(angles, dtype=np.float64)
        ranges = np.asarray(ranges, dtype=np.float64)
        n = len(ranges)
        if n < 3 or len(angles) != n:
            return []
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(ranges) & (ranges >= p.min_range) & (ranges < min(range_max, 1e9))
        r = np.where(valid, ranges, np.inf)
        # Whether the beams cover the whole circle: then the last beam neighbours the first.
        step = float(np.median(np.diff(angles))) if n > 1 else 0.0
        closed = abs(n * step - 2.0 * math.pi) < 1.5 * abs(step)
        nxt = np.roll(r, -1)
        finite_r = np.where(valid, ranges, 0.0)
        xs = finite_r * np.cos(angles)
        ys = finite_r * np.sin(angles)
        # Neighbouring beams join when their points are close: a range jump (something in
        # front of something else) or a wide gap between them splits clusters.
        gap = np.hypot(xs - np.roll(xs, -1), ys - np.roll(ys, -1))
        with np.errstate(invalid="ignore"):
            limit = p.jump + p.jump_per_m * np.minimum(r, nxt)
            joined = valid & np.roll(valid, -1) & (gap < limit)
        if not closed:
            joined[-1] = False
        # Cluster starts: valid beams not joined to the previous one.
        starts = np.flatnonzero(valid & ~np.roll(joined, 1))
        if starts.size == 0:
            return []  # nothing seen, or one cluster all round (inside a ring)
        out: list[Leg] = []
        for start in starts:
            end = start
            count = 1
            while joined[end % n] and count < n:
                end += 1
                count += 1
            first, last = start % n, end % n
            if r[first] > p.max_range:
                continue
            width = math.hypot(xs[last] - xs[first], ys[last] - ys[first])
            if width > p.max_merged_width:
                continue
            # In front of both neighbours (a neighbour that sees nothing is far away).
            before, after = (first - 1) % n, (last + 1) % n
            if not closed and (first == 0 or last == n - 1):
                continue
            if r[before] <= r[first] or r[after] <= r[last]:
                continue
            idx = np.arange(start, end + 1) % n
            # The centre of a leg is about half a radius behind its visible surface.
            cx, cy = float(xs[idx].mean()), float(ys[idx].mean())
            dist = math.hypot(cx, cy)
            back = min(width, p.max_width) / 4.0
            if dist > 0:
                cx, cy = cx + back * cx / dist, cy + back * cy / dist
            out.append(Leg(cx, cy, width, count))
        return out

    def people(
        self,
        angles: npt.NDArray[np.float64],
        ranges: npt.NDArray[np.float64],
        range_max: float,
        *,
        static: Callable[[float, float], bool] | None = None,
    ) -> list[PersonCandidate]:
        """People in a scan, sensor frame; ``static(x, y)`` drops clusters on the map."""
        p = self.params
        legs = self.legs(angles, ranges, range_max)
        if static is not None:
            legs = [leg for leg in legs if not static(leg.x, leg.y)]
        singles = [leg for leg in legs if leg.width <= p.max_width]
        merged = [leg for leg in legs if leg.width > p.max_width]
        out = [PersonCandidate(leg.x, leg.y, 0.6, 2) for leg in merged]
        # Closest pairs first.
        pairs = []
        for i, a in enumerate(singles):
            for j in range(i + 1, len(singles)):
                b = singles[j]
                gap = math.hypot(a.x - b.x, a.y - b.y)
                if gap <= p.max_pair_gap:
                    pairs.append((gap, i, j))
        pairs.sort()
        used: set[int] = set()
        for _, i, j in pairs:
            if i in used or j in used:
                continue
            used.update((i, j))
            a, b = singles[i], singles[j]
            out.append(PersonCandidate((a.x + b.x) / 2.0, (a.y + b.y) / 2.0, 0.8, 2))
        for i, leg in enumerate(singles):
            if i not in used:
                out.append(PersonCandidate(leg.x, leg.y, 0.4, 1))
        return out
