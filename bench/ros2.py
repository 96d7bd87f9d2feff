"""The ROS 2 robot over rmw_zenoh: goal acceptance, pose, stop and map latencies.

Run ``.venv/bin/python bench/ros2.py`` (about 2 minutes on 2 cores). Processes on one machine,
zenoh over TCP on 127.0.0.1 with multicast scouting off:

- ``telebot-sim``: the simulator as a ROS 2 / Nav2 robot, its own zenoh router (as
  ``rmw_zenohd``) on a free port, the small map and a fast base;
- ``telebot-robot run --robot ros2``: the daemon, a client of that router (``[ros2]``), pose
  stream capped at 50 Hz, zero velocity streamed for 0.3 s on a stop;
- this process: the user (``RobotClient`` on a call to the daemon, on the daemon's own zenoh
  port) and a probe, a :class:`~telebot.robot.ros2.node.Ros2Node` on the router that sees
  what a ROS 2 tool would (``/amcl_pose``, ``/cmd_vel``) and sends what one would
  (``navigate_to_pose`` goals, a new ``/map``).

Baseline, in the same run on the same router: two raw zenoh client sessions, a 100-byte
``put`` to a subscriber (one hop through the router, as ROS topics here) and a ``get`` to a
queryable (a ROS service call's round trip).

A. **Goal → accepted**: the probe's action client sends ``navigate_to_pose`` goals to
   ``telebot-sim`` (the same client code the ROS 2 adapter uses); the time from the request to
   the accepted reply. Each goal is cancelled before the next.
B. **Pose**: while the robot drives, each ``/amcl_pose`` the probe hears is matched (by its
   x, y) with the pose update the user gets through the daemon; the latency is the user's
   receipt minus the probe's (the probe's own hop is the baseline's ``put``).
C. **Stop → zero velocity**: the robot drives a goal; ``t0 = time.monotonic()`` and
   ``await robot.stop()``; the latency is the probe's receipt of the first zero ``/cmd_vel``
   after ``t0`` (user → daemon → safety → adapter → router → probe).
D. **Map**: the probe publishes a new 4000 × 4000 ``/map`` (transient local, as map_server);
   the time until the user has it as a PNG: the daemon converts and re-encodes it, announces
   the new version in telemetry, and the user downloads it (``get_map``).

Percentiles are nearest-rank; each target line prints target ÷ measured (above 1 = within the
target); PASS/MISS is informational. The last line (``RESULT ...``) is for scripts.
``--quick``: ``--samples 5 --stops 1 --maps 1`` and a 1000 × 1000 map (a check that it
runs).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from rig import Daemon, start_telebot_sim
from telebot.robot.ros2.keys import QoS
from telebot.robot.ros2.node import Ros2Node
from telebot.rosmsg.types import TypeLibrary

TARGETS_MS = {"goal_ack": 20.0, "pose": 20.0, "stop": 10.0, "map": 300.0}
MAP_SIZE = 4000


def percentile(values: Sequence[float], q: float) -> float:
    """Nearest-rank percentile."""
    ordered = sorted(values)
    rank = max(1, math.ceil(q / 100 * len(ordered)))
    return ordered[rank - 1]


def summary(name: str, values_ms: Sequence[float], target: float | None = None) -> str:
    p50, p99 = percentile(values_ms, 50), percentile(values_ms, 99)
    line = f"{name:<34} n={len(values_ms):<4} p50={p50:7.2f} ms  p99={p99:7.2f} ms"
    if target is not None:
        verdict = "PASS" if p99 <= target else "MISS"
        line += f"  target p99<={target:g} ms: {target / p99:5.2f}x {verdict}"
    return line


# --------------------------------------------------------------------------- baseline


def raw_zenoh(endpoint: str, samples: int) -> tuple[list[float], list[float]]:
    """Raw zenoh through the same router: put -> subscriber and get -> queryable (ms)."""

    def session() -> zenoh.Session:
        config = zenoh.Config()
        config.insert_json5("mode", '"client"')
        config.insert_json5("connect/endpoints", f'["{endpoint}"]')
        config.insert_json5("scouting/multicast/enabled", "false")
        return zenoh.open(config)

    a, b = session(), session()
    try:
        arrived = threading.Event()
        received_at = [0.0]

        def on_sample(_sample: zenoh.Sample) -> None:
            received_at[0] = time.monotonic()
            arrived.set()

        sub = b.declare_subscriber("bench/raw/put", on_sample)
        queryable = b.declare_queryable(
            "bench/raw/get", lambda query: query.reply(query.key_expr, b"x" * 100)
        )
        payload = b"x" * 100
        puts: list[float] = []
        for _ in range(samples + 20):  # the first ones warm the routes
            arrived.clear()
            t0 = time.monotonic()
            a.put("bench/raw/put", payload)
            if arrived.wait(2.0):
                puts.append((received_at[0] - t0) * 1000)
            time.sleep(0.005)
        gets: list[float] = []
        for _ in range(samples + 20):
            t0 = time.monotonic()
            replies = list(a.get("bench/raw/get", timeout=2.0))
            if replies:
                gets.append((time.monotonic() - t0) * 1000)
            time.sleep(0.005)
        sub.undeclare()
        queryable.undeclare()
        return puts[20:], gets[20:]
    finally:
        a.close()
        b.close()


# --------------------------------------------------------------------------- A: goals


def goal_acks(probe: Ros2Node, library: TypeLibrary, goals: int) -> list[float]:
    """navigate_to_pose request -> accepted, from the probe's action client (ms)."""
    action = library.action("nav2_msgs/action/NavigateToPose")
    client = probe.action_client("navigate_to_pose", action)
    deadline = time.monotonic() + 30
    while not client.server_ready():
        if time.monotonic() > deadline:
            raise SystemExit("bench: telebot-sim's navigate_to_pose never appeared")
        time.sleep(0.05)
    latencies: list[float] = []
    for i in range(goals + 5):
        accepted = threading.Event()
        at = [0.0, 0.0]

        def on_accepted(
            _goal_id: bytes, ok: bool, at: list[float] = at, accepted: threading.Event = accepted
        ) -> None:
            at[1] = time.monotonic()
            at[0] = 1.0 if ok else 0.0
            accepted.set()

        # Small goals around the start, alternating so the robot stays in the free area.
        x = 1.5 + 0.2 * (i % 2)
        goal = action.goal.make(
            pose={"header": {"frame_id": "map"}, "pose": {"position": {"x": x, "y": 1.5}}}
        )
        goal.pose.pose.orientation.w = 1.0
        t0 = time.monotonic()
        goal_id = client.send_goal(goal, on_accepted=on_accepted, timeout=5.0)
        if not accepted.wait(10.0) or at[0] != 1.0:
            raise SystemExit(f"bench: goal {i} was not accepted")
        if i >= 5:  # the first ones warm the routes
            latencies.append((at[1] - t0) * 1000)
        done = threading.Event()
        client.cancel(goal_id, lambda *_, done=done: done.set())
        done.wait(5.0)
    return latencies


# --------------------------------------------------------------------------- B, C, D


async def farther_place(robot: Any) -> str:
    """room-b or start, whichever is farther from the robot (a stop can leave it anywhere)."""
    here = await robot.pose()
    places = robot.places
    return max(
        ("room-b", "start"),
        key=lambda name: math.hypot(places[name].x - here.x, places[name].y - here.y),
    )


async def wait_moving(robot: Any) -> None:
    async for pose in robot.poses():
        if abs(pose.v) > 0.05:
            return


async def main_async(args: argparse.Namespace) -> int:
    with tempfile.TemporaryDirectory(prefix="telebot-bench-ros2-") as tmp:
        base = Path(tmp)
        daemon = Daemon(base)
        sim, router = start_telebot_sim(
            daemon, ros2={"stop_stream_s": 0.3}, tables="[services]\npose_hz = 50.0\n"
        )
        probe: Ros2Node | None = None
        try:
            daemon.start()
            library = TypeLibrary("jazzy")
            probe = Ros2Node(name="bench_probe", connect=[router], library=library)
            print(f"telebot-sim on {router}; daemon on {daemon.endpoint}", flush=True)

            raw_put, raw_get = await asyncio.to_thread(raw_zenoh, router, args.samples)
            print(summary("baseline: raw zenoh put->sub", raw_put))
            print(summary("baseline: raw zenoh get->reply", raw_get))

            acks = await asyncio.to_thread(goal_acks, probe, library, args.samples)
            print(summary("A goal -> accepted", acks, TARGETS_MS["goal_ack"]))
            print(f"  ratio to raw get p99: {percentile(acks, 99) / percentile(raw_get, 99):.2f}")

            async with daemon.connect() as robot:
                poses = await measure_poses(robot, probe, library, args.samples * 2)
                print(summary("B ROS pose -> user", poses, TARGETS_MS["pose"]))
                print(
                    f"  ratio to raw put p99: {percentile(poses, 99) / percentile(raw_put, 99):.2f}"
                )
                stops = await measure_stops(robot, probe, library, args.stops)
                print(summary("C stop -> zero /cmd_vel", stops, TARGETS_MS["stop"]))
                print(
                    f"  ratio to raw put p99: {percentile(stops, 99) / percentile(raw_put, 99):.2f}"
                )
                maps = await measure_maps(robot, probe, library, args.maps)
                print(
                    f"D /map {MAP_SIZE}x{MAP_SIZE} -> user has PNG: n={len(maps)} "
                    f"median={percentile(maps, 50):.0f} ms max={max(maps):.0f} ms  "
                    f"target<={TARGETS_MS['map']:g} ms: "
                    f"{TARGETS_MS['map'] / percentile(maps, 50):.2f}x "
                    f"{'PASS' if percentile(maps, 50) <= TARGETS_MS['map'] else 'MISS'}"
                )
            print(
                f"RESULT goal_ack_p99_ms={percentile(acks, 99):.2f} "
                f"pose_p99_ms={percentile(poses, 99):.2f} stop_p99_ms={percentile(stops, 99):.2f} "
                f"map_ms={percentile(maps, 50):.0f} raw_put_p99_ms={percentile(raw_put, 99):.2f} "
                f"raw_get_p99_ms={percentile(raw_get, 99):.2f}"
            )
            return 0
        finally:
            if probe is not None:
                probe.close()
            daemon.stop(graceful=True)
            sim.stop(graceful=True)


async def measure_poses(robot: Any, probe: Ros2Node, library: TypeLibrary, n: int) -> list[float]:
    """While the robot drives back and forth: /amcl_pose at the probe -> at the user (ms)."""
    heard: dict[tuple[float, float], float] = {}
    lock = threading.Lock()

    def on_pose(msg: Any, _attachment: Any) -> None:
        now = time.monotonic()
        position = msg.pose.pose.position
        with lock:
            heard.setdefault((round(position.x, 6), round(position.y, 6)), now)

    sub = probe.subscribe(
        "amcl_pose", library.message("geometry_msgs/msg/PoseWithCovarianceStamped"), on_pose
    )
    latencies: list[float] = []
    try:
        await robot.arm()
        leg = 0
        while len(latencies) < n:
            target = ("room-b", "start")[leg % 2]
            leg += 1
            drive = asyncio.create_task(robot.chat(f"goto {target}", timeout=120))
            async for pose in robot.poses():
                received = time.monotonic()
                with lock:
                    at = heard.get((round(pose.x, 6), round(pose.y, 6)))
                if at is not None and abs(pose.v) > 0.05:
                    latencies.append((received - at) * 1000)
                if drive.done() or len(latencies) >= n:
                    break
            reply = await drive if drive.done() else None
            if reply is not None and not reply.ok:
                raise SystemExit(f"bench: goto {target} failed: {reply.replies}")
            if not drive.done():
                await robot.stop()
                await drive
                await robot.arm()
    finally:
        sub.close()
    await robot.stop()
    return latencies


async def measure_stops(robot: Any, probe: Ros2Node, library: TypeLibrary, n: int) -> list[float]:
    """robot.stop() while driving -> the first zero /cmd_vel the probe hears (ms)."""
    zeros: list[float] = []
    lock = threading.Lock()

    def on_cmd_vel(msg: Any, _attachment: Any) -> None:
        now = time.monotonic()
        twist = getattr(msg, "twist", msg)  # TwistStamped or Twist
        if twist.linear.x == 0.0 and twist.angular.z == 0.0:
            with lock:
                zeros.append(now)

    sub = probe.subscribe("cmd_vel", library.message("geometry_msgs/msg/Twist"), on_cmd_vel)
    latencies: list[float] = []
    try:
        while len(latencies) < n:
            await robot.arm()
            target = await farther_place(robot)
            replies = robot.chat_replies(f"goto {target}", timeout=120)
            first = None
            async for first in replies:  # noqa: B007 (the first reply is kept)
                break
            try:
                await asyncio.wait_for(wait_moving(robot), 30)
            except TimeoutError:
                telemetry = await robot.telemetry(timeout=5)
                later = []
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(3):
                        async for reply in replies:
                            later.append(reply.text)
                raise SystemExit(
                    f"bench: the robot did not move after 'goto {target}' "
                    f"(replies {first!r} {later}; state {telemetry.state} {telemetry.detail!r})"
                ) from None
            await asyncio.sleep(0.4)  # past the previous stop's zero stream (0.3 s)
            t0 = time.monotonic()
            assert (await robot.stop()).ok
            deadline = time.monotonic() + 5
            first = None
            while first is None and time.monotonic() < deadline:
                with lock:
                    first = next((t for t in zeros if t >= t0), None)
                if first is None:
                    await asyncio.sleep(0.002)
            if first is None:
                raise SystemExit("bench: no zero /cmd_vel after a stop")
            latencies.append((first - t0) * 1000)
            async for _ in replies:  # the goal's end
                pass
    finally:
        sub.close()
    return latencies


def random_map(rng: np.random.Generator) -> np.ndarray[Any, np.dtype[np.int8]]:
    """A 4000 × 4000 map: free inside, walls round it, a few random walls and unknown."""
    grid = np.full((MAP_SIZE, MAP_SIZE), -1, dtype=np.int8)
    grid[200:-200, 200:-200] = 0
    grid[200:-200, 200:210] = grid[200:-200, -210:-200] = 100
    grid[200:210, 200:-200] = grid[-210:-200, 200:-200] = 100
    for _ in range(20):
        row, col = rng.integers(300, MAP_SIZE - 300, size=2)
        grid[row : row + 10, col : col + 400] = 100
    return grid


async def measure_maps(robot: Any, probe: Ros2Node, library: TypeLibrary, n: int) -> list[float]:
    """A new /map from the probe -> the user has it as a PNG (ms)."""
    mtype = library.message("nav_msgs/msg/OccupancyGrid")
    publisher = probe.publisher("map", mtype, qos=QoS.transient_local())
    rng = np.random.default_rng(7)
    latencies: list[float] = []
    try:
        version = (await robot.telemetry(timeout=10)).map_version
        for _ in range(n):
            cells = random_map(rng)
            message = mtype.make(
                header={"frame_id": "map"},
                info={
                    "resolution": 0.05,
                    "width": MAP_SIZE,
                    "height": MAP_SIZE,
                    "origin": {"position": {"x": -100.0, "y": -100.0}},
                },
                data=cells.reshape(-1),
            )
            message.info.origin.orientation.w = 1.0
            t0 = time.monotonic()
            publisher.publish(message)
            while True:
                telemetry = await robot.telemetry(timeout=30)
                if telemetry.map_version != version:
                    break
            got = await robot.get_map(timeout=60)
            elapsed = (time.monotonic() - t0) * 1000
            if got.version == version:
                raise SystemExit("bench: the user got the old map")
            version = got.version
            latencies.append(elapsed)
            print(f"  map {len(latencies)}: {elapsed:.0f} ms ({got.grid.width}x{got.grid.height})")
    finally:
        publisher.close()
    return latencies


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=100, help="goals and raw samples")
    parser.add_argument("--stops", type=int, default=30, help="stops measured")
    parser.add_argument("--maps", type=int, default=5, help="maps published")
    parser.add_argument(
        "--quick", action="store_true", help="--samples 5 --stops 1 --maps 1, a 1000 x 1000 map"
    )
    args = parser.parse_args()
    if args.quick:
        global MAP_SIZE
        args.samples, args.stops, args.maps, MAP_SIZE = 5, 1, 1, 1000
    return asyncio.run(main_async(args))


if __name__ == "__main__":
    sys.exit(main())
