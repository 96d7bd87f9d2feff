"""The simulated navigation stack on the 4000 × 4000 default map: plan, simulate, render.

Run ``.venv/bin/python bench/nav.py`` (well under a minute after the map is cached;
generating the map the first time adds a few seconds). What it measures:

A. Global planning. The costmap is built once (its build time is reported). Then plans
   between far corners of the explored part of the map: for each corner of the building's
   bounding box, the free cell nearest to it, and every pair of those (plus the named
   places farthest apart), each planned ``PLAN_REPEATS`` times; p50 and p99 over all.
B. Simulation speed. ``SimNavStack`` drives a long goal (the two places farthest apart)
   stepped at 20 Hz (laser scan, localisation and controller every step) for
   ``SIM_SECONDS`` of simulated time; speed-up = simulated seconds ÷ wall seconds.
C. Camera render. ``Renderer.render`` of a 640 × 480 navcam and usercam frame at poses
   along the route of B; p50 and p99.

Baselines: the targets of the issue (plan ≤ 250 ms p50, simulation ≥ 20× real time,
render ≤ 10 ms). Each line prints the ratio to its target (for time, target ÷ measured:
above 1 means within the target). The last line is ``RESULT ...`` for scripts.
``--quick``: one plan per pair, 5 simulated seconds, 5 frames (a check that it runs).
"""

from __future__ import annotations

import argparse
import itertools
import math
import statistics
import sys
import time

import numpy as np

from telebot.config import SimSettings
from telebot.robot.mapfile import load_map, load_places, places_path_for
from telebot.robot.nav import Pose2D
from telebot.robot.sim.building import resolve_map
from telebot.robot.sim.camera import Renderer, default_cameras
from telebot.robot.sim.planner import Costmap
from telebot.robot.sim.stack import SimNavStack

PLAN_REPEATS = 3
SIM_SECONDS = 120.0
RENDER_FRAMES = 60
TARGET_PLAN_MS = 250.0
TARGET_SPEEDUP = 20.0
TARGET_RENDER_MS = 10.0


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


def corner_cells(
    costmap: Costmap, grid_bounds: tuple[float, float, float, float]
) -> list[tuple[float, float]]:
    """Free points nearest each corner of the building's bounding box (searched inward)."""
    x0, x1, y0, y1 = grid_bounds
    corners = []
    for cx, cy in ((x0, y0), (x1, y0), (x0, y1), (x1, y1)):
        found = None
        for step in range(1, 400):
            d = step * 0.1
            for fx, fy in ((d, 0.0), (0.0, d), (d, d), (d / 2, d), (d, d / 2)):
                x = cx + math.copysign(fx, (x0 + x1) / 2 - cx)
                y = cy + math.copysign(fy, (y0 + y1) / 2 - cy)
                if costmap.is_free(x, y):
                    found = (x, y)
                    break
            if found:
                break
        if found is None:
            raise SystemExit(f"no free cell near corner ({cx:.1f}, {cy:.1f})")
        corners.append(found)
    return corners


def main() -> int:
    global PLAN_REPEATS, SIM_SECONDS, RENDER_FRAMES
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick", action="store_true", help="one plan each, 5 s simulated, 5 frames"
    )
    if parser.parse_args().quick:
        PLAN_REPEATS, SIM_SECONDS, RENDER_FRAMES = 1, 5.0, 5
    settings = SimSettings()
    t0 = time.perf_counter()
    yaml_path = resolve_map(settings.map)
    grid = load_map(yaml_path)
    places = load_places(places_path_for(yaml_path))
    load_s = time.perf_counter() - t0
    bounds = grid.known_bounds()
    assert bounds is not None
    r0, r1, c0, c1 = bounds
    known = float(np.count_nonzero(grid.data != -1)) / grid.data.size
    print(
        f"map: {yaml_path} {grid.width}x{grid.height} @ {grid.resolution} m, "
        f"known {known:.1%}, loaded in {load_s:.2f} s"
    )

    # A. planning
    t0 = time.perf_counter()
    costmap = Costmap.from_grid(grid, settings.robot_radius)
    build_s = time.perf_counter() - t0
    (x0, y0), (x1, y1) = grid.center_of(r0, c0), grid.center_of(r1 - 1, c1 - 1)
    corners = corner_cells(costmap, (x0, x1, y0, y1))
    far_a, far_b = max(
        itertools.combinations(places, 2), key=lambda ab: places[ab[0]].distance_to(places[ab[1]])
    )
    pairs = list(itertools.combinations(corners, 2))
    pairs.append(((places[far_a].x, places[far_a].y), (places[far_b].x, places[far_b].y)))
    plan_ms: list[float] = []
    lengths: list[float] = []
    for start, goal in pairs:
        for _ in range(PLAN_REPEATS):
            t0 = time.perf_counter()
            path = costmap.plan(start, goal)
            plan_ms.append((time.perf_counter() - t0) * 1000)
        lengths.append(path.length)
    plan_p50 = statistics.median(plan_ms)
    print(
        f"A. costmap build {build_s * 1000:.0f} ms; {len(pairs)} far plans × {PLAN_REPEATS}: "
        f"p50 {plan_p50:.1f} ms, p99 {percentile(plan_ms, 99):.1f} ms, "
        f"paths {min(lengths):.0f}–{max(lengths):.0f} m; "
        f"target {TARGET_PLAN_MS:.0f} ms → ratio {TARGET_PLAN_MS / plan_p50:.2f}"
    )

    # B. simulation speed
    start_pose = places[far_a]
    stack = SimNavStack(grid, places, settings, start=start_pose, map_name=settings.map)
    goal = stack.navigate_to_place(far_b)
    steps = int(SIM_SECONDS * 20)
    poses: list[Pose2D] = []
    t0 = time.perf_counter()
    for i in range(steps):
        stack.step(stack.now + 0.05)
        if i % (steps // RENDER_FRAMES) == 0:
            poses.append(stack.true_pose)
    wall = time.perf_counter() - t0
    speedup = stack.now / wall
    print(
        f"B. simulated {stack.now:.0f} s ({steps} steps at 20 Hz, laser {settings.laser_beams} "
        f"beams) in {wall:.2f} s wall: {speedup:.0f}× real time; goal {goal.status} "
        f"{goal.progress:.0%} of {far_a}→{far_b}; target {TARGET_SPEEDUP:.0f}× → ratio "
        f"{speedup / TARGET_SPEEDUP:.2f}"
    )

    # C. camera render
    renderer = Renderer(grid)
    render_ms: list[float] = []
    for camera in default_cameras(640, 480):
        renderer.render(poses[0], camera)  # warm-up
        for pose in poses:
            t0 = time.perf_counter()
            image = renderer.render(pose, camera)
            render_ms.append((time.perf_counter() - t0) * 1000)
        assert image.shape == (480, 640, 3)
    render_p50 = statistics.median(render_ms)
    print(
        f"C. render 640x480 ({len(render_ms)} frames, navcam + usercam): p50 {render_p50:.2f} ms, "
        f"p99 {percentile(render_ms, 99):.2f} ms; target {TARGET_RENDER_MS:.0f} ms → ratio "
        f"{TARGET_RENDER_MS / render_p50:.2f}"
    )

    ok = plan_p50 <= TARGET_PLAN_MS and speedup >= TARGET_SPEEDUP and render_p50 <= TARGET_RENDER_MS
    print("targets:", "PASS" if ok else "MISS")
    print(f"RESULT plan_ms_p50={plan_p50:.1f} sim_speedup={speedup:.1f} render_ms={render_p50:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
