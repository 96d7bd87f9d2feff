"""Follow-me distance error: the scripted walk of ``tests/follow_walk.py``, measured.

Run ``python bench/_follow.py`` (a few seconds; the simulation runs on a fast clock, no
sleeping). A simulated person (two legs in the laser) walks at 0.4 m/s from room A through
its door, 7 m east along the corridor and through room B's door, then stands; the robot
follows it through :class:`~telebot.services.follow.FollowService` on ``[follow]``'s
defaults (1.2 m behind, 0.5 m/s at most), tracked without error so that the controller is
what is measured. ``bench/people.py`` imports :func:`measure_follow_error` for its RESULT
line (there the tracks may come from the people tracker).

Printed: the mean absolute error of the robot–person distance against 1.2 m on the
corridor's straight stretch (both on it, the robot 1 m past the corner), its worst value,
the closest approach, and how long after the person stopped the robot stood still.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from follow_walk import Walk, WalkResult
from telebot.config import FollowSettings

__all__ = ["measure_follow_error", "run_follow_walk"]

#: Simulated seconds: the walk takes about 30 s, then the person stands.
WALK_SECONDS = 34.0


def run_follow_walk(settings: FollowSettings | None = None) -> WalkResult:
    """The whole scripted walk, followed; every control cycle's distance and speed."""
    return Walk(settings).run(WALK_SECONDS)


def measure_follow_error(settings: FollowSettings | None = None) -> float:
    """Mean absolute follow-distance error on the straight stretch (m)."""
    settings = settings if settings is not None else FollowSettings()
    result = run_follow_walk(settings)
    straight = result.straight_distances()
    if not straight:
        raise RuntimeError(f"the robot never followed onto the straight stretch ({result.ended})")
    return statistics.fmean(abs(d - settings.distance) for d in straight)


def main() -> None:
    """Print the measurements and the figure."""
    settings = FollowSettings()
    started = time.perf_counter()
    result = run_follow_walk(settings)
    wall = time.perf_counter() - started
    straight = result.straight_distances()
    errors = [abs(d - settings.distance) for d in straight]
    stopped = result.stopped_within()
    print(
        f"simulated {result.t[-1]:.1f} s in {wall:.2f} s wall; follow ended: {result.ended or 'no'}"
    )
    print(
        f"straight stretch: {len(straight)} cycles, distance {min(straight):.2f} … "
        f"{max(straight):.2f} m (target {settings.distance:g} m), "
        f"worst error {max(errors):.3f} m"
    )
    print(
        f"closest approach {result.min_distance:.2f} m (limit {settings.min_distance:g} m); "
        f"stood still {stopped if stopped is None else round(stopped, 2)} s after the person "
        f"stopped; collisions {result.collisions}"
    )
    print(f"follow_err_m={statistics.fmean(errors):.3f}")


if __name__ == "__main__":
    main()
