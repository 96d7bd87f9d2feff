"""Tracked people: what the perception publishes and what follow-me and the alerts consume.

Sans-IO: plain data and a protocol. Times are the caller's loop time (``loop.time()`` on the
robot, any numbers in tests); positions and velocities are in the map frame (REP-103).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

__all__ = ["SOURCES", "PeopleSource", "PersonTrack"]

#: The sensors a track can be seen by.
SOURCES = frozenset({"laser", "camera"})


@dataclass(frozen=True, slots=True)
class PersonTrack:
    """One tracked person, as of ``last_seen``.

    ``id`` stays the same for as long as the tracker keeps the person; ``confidence`` is
    0 … 1; ``sources`` says which sensors saw the person recently (``"laser"``,
    ``"camera"``).
    """

    id: int
    #: Map frame, metres.
    x: float
    y: float
    #: Map frame, metres a second.
    vx: float
    vy: float
    confidence: float
    #: Loop time of the first and latest detection.
    first_seen: float
    last_seen: float
    sources: frozenset[str] = frozenset({"laser"})

    def __post_init__(self) -> None:
        values = (self.x, self.y, self.vx, self.vy, self.confidence, self.first_seen)
        if not all(math.isfinite(v) for v in (*values, self.last_seen)):
            raise ValueError(f"person track {self.id}: position, velocity and times must be finite")
        if not 0.0 <= self.confidence <= 1.0:
            raise ValueError(f"person track {self.id}: confidence {self.confidence} is not in 0..1")
        unknown = self.sources - SOURCES
        if unknown:
            raise ValueError(f"person track {self.id}: unknown sources {sorted(unknown)}")

    @property
    def speed(self) -> float:
        """Speed over ground, metres a second."""
        return math.hypot(self.vx, self.vy)

    def distance_to(self, x: float, y: float) -> float:
        """Distance from ``(x, y)`` (map frame) to the person, metres."""
        return math.hypot(self.x - x, self.y - y)


@runtime_checkable
class PeopleSource(Protocol):
    """Anything that knows where the people around the robot are (the tracker, a fake)."""

    def tracks(self) -> Sequence[PersonTrack]:
        """The current confirmed tracks (tentative ones are left out)."""
        ...
