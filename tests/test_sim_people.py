"""Simulated people: scripted walkers, their legs in the laser, ground truth from the sim."""

from __future__ import annotations

import math

import numpy as np
import pytest

from telebot.config import SimSettings
from telebot.robot.grid import OccupancyGrid
from telebot.robot.nav import NavState, Pose2D
from telebot.robot.sim.people import LEG_RADIUS, Walker, Waypoint, legs_of
from telebot.robot.sim.stack import SimNavStack

TICK = 0.05


def open_room() -> SimNavStack:
    res = 0.05
    data = np.full((200, 240), -1, dtype=np.int8)
    data[10:-10, 10:-10] = 100
    data[14:-14, 14:-14] = 0
    grid = OccupancyGrid(data, res, 0.0, 0.0)
    return SimNavStack(grid, {}, SimSettings(), start=Pose2D(3.0, 5.0, 0.0))


def run(stack: SimNavStack, seconds: float) -> None:
    end = stack.now + seconds
    while stack.now < end - 1e-9:
        stack.step(stack.now + TICK)


def beam_range(stack: SimNavStack, angle: float) -> float:
    scan = stack.laser_scan()
    index = int(np.argmin(np.abs(np.angle(np.exp(1j * (scan.angles - angle))))))
    return float(scan.ranges[index])


def test_a_walker_follows_its_waypoints_pauses_and_stops_at_the_end() -> None:
    walker = Walker.along([(0.0, 0.0), (2.4, 0.0, 3.0), (2.4, 1.2)], speed=1.2)
    assert walker.duration == pytest.approx(2.0 + 3.0 + 1.0)
    mid = walker.state_at(1.0)
    assert (mid.x, mid.y, mid.walking) == (pytest.approx(1.2), pytest.approx(0.0), True)
    assert (mid.vx, mid.vy) == (pytest.approx(1.2), pytest.approx(0.0))
    paused = walker.state_at(3.5)
    assert (paused.x, paused.y, paused.walking, paused.vx) == (2.4, 0.0, False, 0.0)
    turning = walker.state_at(5.5)
    assert turning.y == pytest.approx(0.6) and turning.yaw == pytest.approx(math.pi / 2)
    end = walker.state_at(100.0)
    assert (end.x, end.y, end.walking) == (2.4, 1.2, False)
    assert end.yaw == pytest.approx(math.pi / 2)  # still facing the way it came
    delayed = Walker.along([(0, 0), (1, 0)], start_delay=2.0)
    assert delayed.state_at(1.9).x == 0.0 and delayed.state_at(2.5).x > 0.0


def test_legs_are_two_circles_side_by_side_standing_and_swinging_walking() -> None:
    standing = Walker.standing(1.0, 2.0, yaw=0.0).state_at(5.0)
    left, right = legs_of(standing)
    assert left.radius == right.radius == LEG_RADIUS
    assert (left.x, right.x) == (pytest.approx(1.0), pytest.approx(1.0))
    assert left.y > right.y and math.hypot(left.x - right.x, left.y - right.y) == pytest.approx(
        0.22
    )
    walker = Walker.along([(0, 0), (10, 0)], speed=1.3)
    gaps, ahead = [], []
    for t in np.linspace(0.1, 5.0, 50):
        a, b = legs_of(walker.state_at(float(t)))
        gaps.append(math.hypot(a.x - b.x, a.y - b.y))
        ahead.append(a.x - b.x)
    assert min(gaps) >= 0.2 and max(gaps) <= 0.3
    assert min(ahead) < -0.1 and max(ahead) > 0.1  # the legs take turns in front


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"waypoints": ()}, "at least one waypoint"),
        ({"waypoints": (Waypoint(0, 0),), "speed": 9.0}, "walking speed"),
        ({"waypoints": (Waypoint(0, 0),), "start_delay": -1.0}, "start delay"),
        ({"waypoints": (Waypoint(0, 0),), "height": 3.0}, "height"),
    ],
)
def test_bad_walkers_are_refused_with_a_clear_error(kwargs: dict[str, object], words: str) -> None:
    with pytest.raises(ValueError, match=words):
        Walker(**kwargs)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="finite"):
        Waypoint(math.nan, 0.0)


def test_the_laser_sees_a_walker_and_the_truth_follows_the_script() -> None:
    stack = open_room()
    assert beam_range(stack, 0.0) > 7.0  # the far wall
    pid = stack.add_person(Walker.along([(5.0, 7.0), (5.0, 3.0)], speed=1.0))
    truth = stack.people_truth()
    assert [p.id for p in truth] == [pid] and (truth[0].x, truth[0].y) == (5.0, 7.0)
    run(stack, 2.0)  # the walker is straight ahead of the robot now, 2 m away
    (person,) = stack.people_truth()
    assert person.walking and person.y == pytest.approx(5.0, abs=0.06)
    assert person.vy == pytest.approx(-1.0)
    assert beam_range(stack, 0.0) == pytest.approx(2.0 - LEG_RADIUS, abs=0.12)
    run(stack, 3.0)  # stopped at the end, out of the beam
    (person,) = stack.people_truth()
    assert (person.x, person.y, person.walking) == (5.0, 3.0, False)
    assert beam_range(stack, 0.0) > 7.0
    leg = person.legs[0]
    here = stack.true_pose
    towards = math.atan2(leg.y - here.y, leg.x - here.x)
    assert beam_range(stack, towards) == pytest.approx(
        math.hypot(leg.x - here.x, leg.y - here.y) - LEG_RADIUS, abs=0.15
    )
    stack.remove_person(pid)
    stack.remove_person(pid)  # unknown ids are ignored
    assert stack.people_truth() == ()
    run(stack, 0.1)
    assert beam_range(stack, towards) > 2.9


def test_a_standing_person_stops_the_robot_like_an_obstacle() -> None:
    stack = open_room()
    goal = stack.navigate_to(10.0, 5.0)
    stack.add_person(Walker.standing(6.0, 5.0, yaw=math.pi))
    run(stack, 15.0)
    assert stack.status().state is NavState.BLOCKED
    assert stack.velocity().linear == 0.0 and not goal.status.done
    assert stack.true_pose.x < 6.0 - 0.06 - 0.25
    assert stack.collisions == 0
