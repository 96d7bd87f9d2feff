"""Messages of the ``plan`` channel (robot → user, JSON text datagrams): the robot's planned
path and its named places, for a map view.

::

    {"type": "plan", "seq": 12, "goal": 7, "points": [[1.0, 1.2], [2.5, 1.2], [3.0, 5.2]]}
    {"type": "places", "places": [{"name": "lab", "x": 3.0, "y": 5.2, "yaw": 0.0}, ...]}

``plan``: the global plan the robot follows now (map frame, metres), simplified to at most
:data:`MAX_PLAN_POINTS` points; ``points`` is empty when the robot has no plan (idle, a
goal ended, a relative move). ``seq`` goes up by one each time the plan changes (a repeat
carries the same ``seq``), ``goal`` is the robot's number of the goal it belongs to (as in
``pose``) or null. ``places``: every named place of the map (``yaw`` in radians, or null).

Sans-IO: encoding, decoding and the path simplification (Douglas–Peucker).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from telebot.errors import ProtocolError
from telebot.services.messages import (
    MAX_MESSAGE,
    decode_object,
    encode_object,
    require_int,
)

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

__all__ = [
    "MAX_PLACES_TEXT",
    "MAX_PLAN_POINTS",
    "PLAN",
    "PLAN_TOLERANCE",
    "Place",
    "PlacesUpdate",
    "PlanUpdate",
    "decode_plan_message",
    "simplify_path",
]

#: The channel's name.
PLAN = "plan"
#: Most points a ``plan`` message carries (about 4 KB of JSON, far below a datagram's 32 KB).
MAX_PLAN_POINTS = 200
#: How far (m) the simplified path may stray from the planner's: under a map cell.
PLAN_TOLERANCE = 0.02
#: The simplification's tolerance grows up to this (m) to fit the point limit.
MAX_TOLERANCE = 1.0
#: Longer paths are thinned evenly before they are simplified (bounds the work).
MAX_INPUT_POINTS = 2000
#: Longest ``places`` message the robot sends (characters); places beyond it are left out.
MAX_PLACES_TEXT = 30_000
#: Largest ``seq`` (exact in JSON in any language).
MAX_SEQ = 2**53 - 1
#: Longest place name accepted.
MAX_NAME = 256

_Points = tuple[tuple[float, float], ...]


@dataclass(frozen=True, slots=True)
class PlanUpdate:
    """The robot's plan number ``seq`` for goal ``goal``: ``points`` (x, y), empty for none."""

    seq: int
    goal: int | None
    points: _Points

    def encode(self) -> str:
        """The datagram text (coordinates rounded to the millimetre)."""
        points = [[round(x, 3), round(y, 3)] for x, y in self.points]
        return encode_object({"type": "plan", "seq": self.seq, "goal": self.goal, "points": points})


@dataclass(frozen=True, slots=True)
class Place:
    """A named place: position (m) and heading (rad, or None) in the map frame."""

    name: str
    x: float
    y: float
    yaw: float | None = None


@dataclass(frozen=True, slots=True)
class PlacesUpdate:
    """The robot's named places."""

    places: tuple[Place, ...]

    def encode(self) -> str:
        """The datagram text: the places in order, as many as fit :data:`MAX_PLACES_TEXT`
        (a place a user would refuse, without a name or a finite position, is left out)."""
        head = '{"type":"places","places":['
        parts: list[str] = []
        size = len(head) + 2
        for place in self.places:
            if not (0 < len(place.name) <= MAX_NAME and _finite(place.x) and _finite(place.y)):
                continue
            yaw = place.yaw if place.yaw is not None and math.isfinite(place.yaw) else None
            part = encode_object(
                {
                    "name": place.name,
                    "x": round(place.x, 3),
                    "y": round(place.y, 3),
                    "yaw": None if yaw is None else round(yaw, 4),
                }
            )
            if size + len(part) + 1 > MAX_PLACES_TEXT:
                break
            parts.append(part)
            size += len(part) + 1
        return head + ",".join(parts) + "]}"


def decode_plan_message(payload: str | bytes) -> PlanUpdate | PlacesUpdate:
    """Parse a ``plan`` channel datagram; ProtocolError (one line) when malformed."""
    what = PLAN
    msg = decode_object(payload, what=what)
    kind = msg.get("type")
    if kind == "plan":
        goal = msg.get("goal")
        if goal is not None:
            goal = require_int(msg, "goal", what=what)
        points = msg.get("points")
        if not isinstance(points, list) or len(points) > MAX_MESSAGE // 6:
            raise ProtocolError("plan: 'points' must be a list of [x, y] pairs")
        return PlanUpdate(
            seq=require_int(msg, "seq", what=what, high=MAX_SEQ),
            goal=goal,
            points=tuple(_pair(point) for point in points),
        )
    if kind == "places":
        places = msg.get("places")
        if not isinstance(places, list):
            raise ProtocolError("places: 'places' must be a list")
        return PlacesUpdate(tuple(_place(entry) for entry in places))
    raise ProtocolError(f"plan: unknown type {kind!r}")


def _finite(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _pair(point: object) -> tuple[float, float]:
    if not (isinstance(point, list) and len(point) == 2 and all(_finite(v) for v in point)):
        raise ProtocolError("plan: each point must be [x, y], two finite numbers")
    return float(point[0]), float(point[1])


def _place(entry: object) -> Place:
    if not isinstance(entry, dict):
        raise ProtocolError("places: each place must be an object")
    name = entry.get("name")
    if not isinstance(name, str) or not 0 < len(name) <= MAX_NAME:
        raise ProtocolError(f"places: 'name' must be text of 1..{MAX_NAME} characters")
    x, y, yaw = entry.get("x"), entry.get("y"), entry.get("yaw")
    if not (_finite(x) and _finite(y)) or not (yaw is None or _finite(yaw)):
        raise ProtocolError(f"places: {name!r} needs finite numbers x, y (and yaw or null)")
    return Place(name, float(x), float(y), None if yaw is None else float(yaw))  # type: ignore[arg-type]


def simplify_path(
    points: Sequence[tuple[float, float]] | npt.NDArray[np.float64] | Iterable[tuple[float, float]],
    *,
    tolerance: float = PLAN_TOLERANCE,
    max_points: int = MAX_PLAN_POINTS,
) -> _Points:
    """``points`` with as few points as keep within ``tolerance`` (m) of the path
    (Douglas–Peucker), and at most ``max_points``.

    When more are needed the tolerance doubles (each pass simplifies the last one's
    result), up to :data:`MAX_TOLERANCE`; a path still too winding is then thinned evenly.
    A path of more than :data:`MAX_INPUT_POINTS` is thinned evenly first, so the work
    stays bounded. The first and last points are always kept; non-finite ones dropped.
    """
    import numpy as np

    if max_points < 2:
        raise ValueError("max_points must be at least 2")
    array = np.asarray(list(points) if not isinstance(points, np.ndarray) else points, float)
    if array.size == 0:
        return ()
    array = array.reshape(-1, 2)
    array = array[np.isfinite(array).all(axis=1)]
    if len(array) > MAX_INPUT_POINTS:
        array = array[_evenly(len(array), MAX_INPUT_POINTS)]
    if len(array) > 2:
        array = array[_douglas_peucker(array, tolerance)]
    while len(array) > max_points and tolerance < MAX_TOLERANCE:
        tolerance *= 2.0
        array = array[_douglas_peucker(array, tolerance)]
    if len(array) > max_points:
        array = array[_evenly(len(array), max_points)]
    return tuple((float(x), float(y)) for x, y in array)


def _evenly(count: int, wanted: int) -> npt.NDArray[np.intp]:
    """``wanted`` indices spread evenly over ``range(count)``, the first and last included."""
    import numpy as np

    return np.unique(np.linspace(0, count - 1, wanted).round().astype(np.intp))


def _douglas_peucker(points: npt.NDArray[np.float64], tolerance: float) -> npt.NDArray[np.intp]:
    """Indices of the points Douglas–Peucker keeps (iterative: long paths need no recursion)."""
    import numpy as np

    keep = np.zeros(len(points), dtype=bool)
    keep[0] = keep[-1] = True
    stack = [(0, len(points) - 1)]
    while stack:
        first, last = stack.pop()
        if last - first < 2:
            continue
        a, b = points[first], points[last]
        inner = points[first + 1 : last]
        # Distance to the segment, not its line: a path that doubles back beyond an end
        # must keep the turning point.
        ab = b - a
        squared = float(ab @ ab)
        t = np.zeros(len(inner)) if squared == 0.0 else ((inner - a) @ ab) / squared
        nearest = a + np.clip(t, 0.0, 1.0)[:, None] * ab
        dists = np.hypot(inner[:, 0] - nearest[:, 0], inner[:, 1] - nearest[:, 1])
        index = int(np.argmax(dists))
        if dists[index] > tolerance:
            middle = first + 1 + index
            keep[middle] = True
            stack.append((first, middle))
            stack.append((middle, last))
    return np.flatnonzero(keep)
