"""Recording: what an MCAP recording of a call costs the user's process, at 30 fps video.

Run ``.venv/bin/python bench/record.py`` (about 30 s). The robot is ``telebot-robot run`` in
a child process (the rig's :class:`~rig.Daemon`: zenoh on loopback, the small map, default
video: 640 × 480, up to 30 fps, JPEG quality 80). This process calls it, turns the robot in
place all along (every frame a new picture), keeps a video subscriber open (so the robot
sends video in both phases), and measures its own CPU time
(``time.process_time()``: every thread, the SDK's writer included) over ``DURATION`` seconds:

A. without recording;
B. with a :class:`~telebot.apps.foxglove_bridge.FoxgloveBridge` writing an MCAP file (what
   ``telebot-user record`` and ``--record`` do): map, pose, tf, plan, telemetry, safety and
   every video frame as ``foxglove.CompressedImage``.

The phases alternate (A B A B) so that drift in the machine's load falls on both. The
recording's cost is B − A in % of one core; target ≤ 10 %. The last line is
``RESULT record_cpu_pct=… fps=… mcap_mb_per_min=…``. ``--quick``: one round of half a
second each (a check that it runs).
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from rig import Daemon
from telebot.apps.foxglove_bridge import FoxgloveBridge
from telebot.services.client import RobotClient
from telebot.services.video.wire import CompleteFrame

WARMUP = 2.0
DURATION = 5.0
ROUNDS = 2
TARGET_PCT = 10.0


async def measure(seconds: float) -> float:
    """CPU seconds this process used over ``seconds`` of wall time."""
    start = time.process_time()
    await asyncio.sleep(seconds)
    return time.process_time() - start


async def turn_forever(client: RobotClient) -> None:
    while True:
        await client.chat("turn 180", timeout=30)


async def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        daemon = Daemon(base, observer=None)
        daemon.start()
        try:
            async with daemon.connect() as client:
                frames: list[int] = []

                def on_frame(frame: CompleteFrame) -> None:
                    frames.append(len(frame.data))

                unsubscribe = client.video_feed.subscribe(on_frame)
                # Turning in place all along: every frame is a new picture (a still robot's
                # identical frames would compress to nothing in the MCAP's chunks).
                assert (await client.arm(timeout=10)).ok
                turning = asyncio.ensure_future(turn_forever(client))
                await asyncio.sleep(WARMUP)  # video running, map fetched once
                idle: list[float] = []
                busy: list[float] = []
                size = 0
                for i in range(ROUNDS):
                    idle.append(await measure(DURATION))
                    out = base / f"bench-{i}.mcap"
                    async with FoxgloveBridge(client, mcap=out) as bridge:
                        before = len(frames)
                        busy.append(await measure(DURATION))
                        got = len(frames) - before
                        recorded = bridge.counts.get("/camera", 0)
                    size += out.stat().st_size
                turning.cancel()
                await asyncio.gather(turning, return_exceptions=True)
                await client.stop(timeout=5)
                unsubscribe()
        finally:
            daemon.stop()
    wall = DURATION * ROUNDS
    idle_pct = 100.0 * sum(idle) / wall
    busy_pct = 100.0 * sum(busy) / wall
    cost = busy_pct - idle_pct
    fps = got / DURATION
    mb_per_min = size / 1e6 / (wall / 60.0)  # minutes recorded: the B phases only
    jpeg_kb = sum(frames[-got:]) / max(got, 1) / 1e3
    print(f"A. not recording: {idle_pct:.1f} % of one core (client, zenoh, video reassembly)")
    print(
        f"B. recording:     {busy_pct:.1f} % of one core; {fps:.1f} fps arriving, "
        f"{recorded} frames recorded in the last {DURATION:g} s (JPEG {jpeg_kb:.1f} KB), "
        f"{mb_per_min:.1f} MB per minute recorded"
    )
    print(
        f"recording costs {cost:.1f} % of one core (target <= {TARGET_PCT:g} %): "
        f"target/measured {TARGET_PCT / max(cost, 0.01):.2f}"
    )
    print(f"RESULT record_cpu_pct={cost:.1f} fps={fps:.1f} mcap_mb_per_min={mb_per_min:.1f}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one round of half a second")
    if parser.parse_args().quick:
        WARMUP, DURATION, ROUNDS = 0.3, 0.5, 1
    asyncio.run(main())
