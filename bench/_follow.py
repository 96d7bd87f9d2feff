"""Follow-me distance error: the scripted walk of ``tests/follow_walk.py``, measured.

Run ``python bench/_follow.py`` (about 15 s; the simulation runs on a fast clock, no
sleeping). A simulated person (two legs in the laser, a figure in the cameras) walks at
0.4 m/s from room A through its door, 7 m east along the corridor and through room B's
door, then stands; the robot follows it through
:class:`~telebot.services.drive.follow.FollowService` on ``[follow]``'s defaults (1.2 m behind,
0.5 m/s at most). Twice: tracked by the robot's own people tracker (laser legs and the HOG
camera detector, :class:`~telebot.robot.perception.runner.PeoplePerception`, the figure
that counts), and tracked without error (the controller alone). ``bench/people.py``
imports :func:`measure_follow_error` for its RESULT line.

Printed for each: the mean absolute error of the robot–person distance against 1.2 m on
the corridor's straight stretch (both on it, the robot 1 m past the corner), its worst
value, the closest approach, and how long after the person stopped the robot stood still.
The last line is ``follow_err_m=…`` (with the tracker).
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from follow_walk import Walk, WalkResult
from telebot.config import FollowSettings, PeopleSettings

__all__ = ["measure_follow_error", "run_follow_walk"]

#: Simulated seconds: the walk takes about 30 s, then the person stands.
WALK_SECONDS = 34.0


def run_follow_walk(settings: FollowSettings | None = None, *, tracker: bool = True) -> WalkResult:
    """The whole scripted walk, followed; every control cycle's distance and speed.

    ``tracker``: the robot's own people tracker (else the simulation's truth)."""
    perception = PeopleSettings() if tracker else None
    return Walk(settings, perception=perception).run(WALK_SECONDS)


def measure_follow_error(settings: FollowSettings | None = None, *, tracker: bool = True) -> float:
    """Mean absolute follow-distance error on the straight stretch (m)."""
    settings = settings if settings is not None else FollowSettings()
    result = run_follow_walk(settings, tracker=tracker)
    straight = result.straight_distances()
    if not straight:
        raise RuntimeError(f"the robot never followed onto the straight stretch ({result.ended})")
    return statistics.fmean(abs(d - settings.distance) for d in straight)


def report(label: str, settings: FollowSettings, *, tracker: bool) -> float:
    """Run the walk once, print what happened, and return the mean error."""
    started = time.perf_counter()
    result = run_follow_walk(settings, tracker=tracker)
    wall = time.perf_counter() - started
    straight = result.straight_distances()
    errors = [abs(d - settings.distance) for d in straight]
    stopped = result.stopped_within()
    print(
        f"{label}: simulated {result.t[-1]:.1f} s in {wall:.2f} s wall; "
        f"follow ended: {result.ended or 'no'}"
    )
    print(
        f"  straight stretch: {len(straight)} cycles, distance {min(straight):.2f} … "
        f"{max(straight):.2f} m (target {settings.distance:g} m), mean error "
        f"{statistics.fmean(errors):.3f} m, worst {max(errors):.3f} m"
    )
    print(
        f"  closest approach {result.min_distance:.2f} m (limit {settings.min_distance:g} m); "
        f"stood still {stopped if stopped is None else round(stopped, 2)} s after the person "
        f"stopped; collisions {result.collisions}"
    )
    return statistics.fmean(errors)


def main() -> None:
    """Print the measurements and the figure."""
    settings = FollowSettings()
    report("truth tracks (the controller alone)", settings, tracker=False)
    error = report("the robot's people tracker", settings, tracker=True)
    print(f"follow_err_m={error:.3f}")


if __name__ == "__main__":
    main()
