"""The topic relay under load: relay latency of small messages, and stops while it runs.

Run ``.venv/bin/python bench/relay.py`` (about a minute on 2 cores). Processes on one machine,
zenoh over TCP on 127.0.0.1, as ``bench/ros2.py``: ``telebot-sim`` (the ROS 2 robot, its own
router), ``telebot-robot run --robot ros2`` (the daemon) and this process: the user (a
``RobotClient`` on a call to the daemon) and a ROS node on the router that publishes

- ``/bench_scan``: a 360-beam ``sensor_msgs/LaserScan`` at 10 Hz (~1.5 KB), its header stamp
  the publisher's ``time.monotonic()``;
- ``/bench_cloud``: a 1 MB ``sensor_msgs/PointCloud2`` at 2 Hz (32 fragments per message).

The user relays both (``robot.relay``). Measured at the same time:

- **Relay latency** of each scan: the user's receipt minus the stamp (publisher -> router ->
  daemon -> call -> user). The *added* latency is that minus the raw zenoh hop a ROS tool on
  the router would have had (``put -> subscriber`` through the same router, median).
- **Stop**: the robot drives a goal; ``await robot.stop()``; the latency is the probe's
  receipt of the first zero ``/cmd_vel`` (user -> daemon -> safety -> adapter -> router ->
  probe), as in ``bench/ros2.py`` C.

Percentiles are nearest-rank; targets: added relay latency p99 <= 20 ms, stop p99 <= 20 ms.
- **Recording**: ``bench/record.py`` runs after the rest (its own robot, 30 fps video): the
  CPU, in percent of one core, that recording the session as MCAP adds (target <= 10 %).

The last line (``RESULT ...``) is for scripts. ``--quick``: 5 raw samples, 1 stop, no
recording (``bench/record.py --quick`` checks that one) (a check that it runs).
"""

from __future__ import annotations

import argparse
import asyncio
import math
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from rig import Daemon, start_telebot_sim
from ros2 import measure_stops, percentile, raw_zenoh, summary  # bench/ros2.py
from telebot.robot.ros2.node import Ros2Node
from telebot.rosmsg.types import TypeLibrary

TARGETS_MS = {"relay_added": 20.0, "stop": 20.0}
CLOUD_BYTES = 1_000_000


def publish(node: Ros2Node, library: TypeLibrary, stop: threading.Event) -> dict[str, int]:
    """Publish the scan at 10 Hz and the cloud at 2 Hz until ``stop``; counts."""
    scan_type = library.message("sensor_msgs/msg/LaserScan")
    cloud_type = library.message("sensor_msgs/msg/PointCloud2")
    scans = node.publisher("/bench_scan", scan_type)
    clouds = node.publisher("/bench_cloud", cloud_type)
    ranges = np.linspace(0.5, 5.0, 360, dtype=np.float32)
    cloud_cdr = cloud_type.serialize(
        cloud_type.make(
            height=1,
            width=CLOUD_BYTES // 16,
            point_step=16,
            row_step=CLOUD_BYTES,
            data=np.random.default_rng(1).integers(0, 255, CLOUD_BYTES, dtype=np.uint8),
            is_dense=True,
        )
    )
    counts = {"scans": 0, "clouds": 0}
    tick = 0
    next_at = time.monotonic()
    while not stop.is_set():
        now = time.monotonic()
        sec = math.floor(now)
        stamp = {"sec": int(sec), "nanosec": int((now - sec) * 1e9)}
        scans.publish(
            scan_type.make(
                header={"stamp": stamp, "frame_id": "laser"},
                angle_min=-math.pi,
                angle_max=math.pi,
                angle_increment=2 * math.pi / 360,
                range_max=10.0,
                ranges=ranges,
            )
        )
        counts["scans"] += 1
        if tick % 5 == 0:
            clouds.publish_cdr(cloud_cdr)
            counts["clouds"] += 1
        tick += 1
        next_at += 0.1
        stop.wait(max(0.0, next_at - time.monotonic()))
    return counts


async def relay_latencies(robot: Any, library: TypeLibrary, out: list[float]) -> None:
    """Relay /bench_scan and append each message's latency (ms) to ``out``."""
    scan_type = library.message("sensor_msgs/msg/LaserScan")
    async with robot.relay("/bench_scan") as scans:
        async for message in scans:
            now = time.monotonic()
            stamp = scan_type.deserialize(message.data).header.stamp
            out.append((now - (stamp.sec + stamp.nanosec / 1e9)) * 1000)


async def cloud_count(robot: Any, counts: dict[str, int], two: asyncio.Event) -> None:
    """Relay /bench_cloud and count whole messages (``two`` set at the second)."""
    async with robot.relay("/bench_cloud") as clouds:
        async for message in clouds:
            assert len(message.data) > CLOUD_BYTES
            counts["clouds"] += 1
            if counts["clouds"] >= 2:
                two.set()


async def main_async(args: argparse.Namespace) -> int:
    with tempfile.TemporaryDirectory(prefix="telebot-bench-relay-") as tmp:
        base = Path(tmp)
        daemon = Daemon(base)
        sim, router = start_telebot_sim(
            daemon, ros2={"stop_stream_s": 0.3}, tables="[services]\npose_hz = 50.0\n"
        )
        node: Ros2Node | None = None
        stop = threading.Event()
        try:
            daemon.start()
            library = TypeLibrary("jazzy")
            node = Ros2Node(name="bench_lidar", connect=[router], library=library)
            print(f"telebot-sim on {router}; daemon on {daemon.endpoint}", flush=True)
            raw_put, _ = await asyncio.to_thread(raw_zenoh, router, args.samples)
            print(summary("baseline: raw zenoh put->sub", raw_put))
            publisher = asyncio.create_task(asyncio.to_thread(publish, node, library, stop))
            async with daemon.connect() as robot:
                for _ in range(100):  # the daemon's node learns of ours through the graph
                    names = {t.name for t in await robot.topics()}
                    if {"/bench_scan", "/bench_cloud"} <= names:
                        break
                    await asyncio.sleep(0.1)
                latencies: list[float] = []
                received = {"clouds": 0}
                two = asyncio.Event()
                relays = [
                    asyncio.create_task(relay_latencies(robot, library, latencies)),
                    asyncio.create_task(cloud_count(robot, received, two)),
                ]
                started = time.monotonic()
                await asyncio.wait_for(two.wait(), 30)  # both relays run
                latencies.clear()  # from here on, under load
                stops = await measure_stops(robot, node, library, args.stops)
                seconds = time.monotonic() - started
                for task in relays:
                    task.cancel()
                await asyncio.gather(*relays, return_exceptions=True)
            stop.set()
            sent = await publisher
            raw_p50 = percentile(raw_put, 50)
            added = [max(0.0, value - raw_p50) for value in latencies]
            print(summary("relay: scan publisher -> user", latencies))
            print(summary("relay: added over raw put p50", added, TARGETS_MS["relay_added"]))
            print(summary("stop -> zero /cmd_vel (relaying)", stops, TARGETS_MS["stop"]))
            print(
                f"clouds: {received['clouds']} of 1 MB relayed in {seconds:.0f} s "
                f"(published {sent['clouds']}); scans published {sent['scans']}, "
                f"relayed {len(latencies)} under load"
            )
        finally:
            stop.set()
            if node is not None:
                node.close()
            daemon.stop(graceful=True)
            sim.stop(graceful=True)
    if args.quick:
        print("recording: left out of a quick run")
        record_cpu = "n/a"
    else:
        record_cpu = recording_cost()
    print(
        f"RESULT relay_p99_ms={percentile(added, 99):.2f} "
        f"stop_p99_ms={percentile(stops, 99):.2f} record_cpu_pct={record_cpu}"
    )
    return 0


def recording_cost() -> str:
    """``bench/record.py``'s record_cpu_pct (its own robot and call, after ours ended)."""
    result = subprocess.run(
        [sys.executable, str(Path(__file__).with_name("record.py"))],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    print(result.stdout, end="")
    for line in reversed(result.stdout.splitlines()):
        if line.startswith("RESULT "):
            fields = dict(item.split("=", 1) for item in line.split()[1:])
            return fields.get("record_cpu_pct", "na")
    print(f"bench/record.py gave no RESULT: {result.stderr.strip()[-300:]}")
    return "na"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=100, help="raw zenoh samples")
    parser.add_argument("--stops", type=int, default=20, help="stops measured")
    parser.add_argument("--quick", action="store_true", help="--samples 5 --stops 1, no recording")
    args = parser.parse_args()
    if args.quick:
        args.samples, args.stops = 5, 1
    return asyncio.run(main_async(args))


if __name__ == "__main__":
    sys.exit(main())
