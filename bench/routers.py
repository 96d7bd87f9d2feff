"""Two linked routers: what the second router adds to a stop and to a raw round trip.

Everything on this machine, over mutual TLS on loopback, with the ACL on both routers:

- a site router and a cloud router (two ``telebot-router run`` processes sharing one CA,
  the site one started with ``--peer-router`` to the cloud one: docs/protocol.md §22.5);
- one robot daemon (``telebot-robot run``, the small simulated robot), a client of the
  site router;
- two users in this process, both drivers of the robot: ``near`` connected to the site
  router (the baseline: one router between user and robot) and ``far`` connected to the
  cloud router (two routers: cloud → site → robot and back).

Measured, interleaved (one near, one far, ...) so that the machine's load hits both alike:

A. Stop → acknowledgement: ``await client.stop()`` (the request on the CONTROL lane, the
   robot's ack back), :data:`STOPS` times per user; p50 and p99, and far/near ratios.
B. Raw zenoh round trip: a CONTROL-QoS put answered by a second bare session (``admin:``
   certificates) that sits on the site router, from a session on the site router (one
   router) and from one on the cloud router (two routers), :data:`PINGS` each.

Run: ``python bench/routers.py`` (about half a minute; ``--quick``: 5 stops and 5 round trips
each, a check that it runs). The last line is
``RESULT stop_p50_ms_one=... stop_p50_ms_two=... stop_added_p50_ms=... stop_ratio_p50=...
stop_p99_ms_one=... stop_p99_ms_two=... raw_added_p50_ms=... raw_ratio_p50=...``.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from rig import Process
from router_rig import RouterRig
from telebot.channels.transports.base import Lane
from telebot.channels.transports.zenoh import LANE_QOS, build_zenoh_config
from telebot.config import AppConfig, CallSettings, ZenohSettings
from telebot.identity import ContactBook, Identity, KnownRobots, Role
from telebot.services.client import RobotClient, connect

ROBOT = "guiabot"
STOPS = int(os.environ.get("ROUTERS_STOPS", "200"))
PINGS = int(os.environ.get("ROUTERS_PINGS", "300"))
CALL_TIMEOUT = 5.0


def pct(values: list[float], q: float) -> float:
    """The ``q``-th percentile (nearest rank) of ``values``."""
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q / 100 * (len(ordered) - 1)))]


def setup(base: Path) -> tuple[RouterRig, RouterRig]:
    """The two router directories (one CA), the robot's and the users' identities."""
    cloud = RouterRig(base / "cloud")
    site = RouterRig(base / "site", ca=cloud)
    robot = Identity.generate(ROBOT)
    robot.save(base / ROBOT)
    book = ContactBook.load(base / ROBOT)
    for name in ("near", "far"):
        user = Identity.generate(name)
        user.save(base / name)
        known = KnownRobots.load(base / name)
        known.add(ROBOT, robot.public_key)
        known.save()
        book.add(name, user.public_key, Role.DRIVER)
    book.save()
    site.issue("robot", ROBOT)
    site.issue("user", "near")
    cloud.issue("user", "far")
    site.issue("admin", "bench")
    cloud.issue("admin", "bench")
    return site, cloud


def app_config(rig: RouterRig, user: str) -> AppConfig:
    settings = rig.zenoh(rig.client("user", user))
    return AppConfig.model_validate(
        {"transport": {"zenoh": settings}, "call": CallSettings(timeout=CALL_TIMEOUT)}
    )


async def stop_series(base: Path, site: RouterRig, cloud: RouterRig) -> dict[str, list[float]]:
    """Stop → ack times (ms), near and far interleaved."""
    results: dict[str, list[float]] = {"one": [], "two": []}
    async with (
        connect(ROBOT, home=base / "near", config=app_config(site, "near"), timeout=60) as near,
        connect(ROBOT, home=base / "far", config=app_config(cloud, "far"), timeout=60) as far,
    ):
        clients: list[tuple[str, RobotClient]] = [("one", near), ("two", far)]
        for _ in range(10):  # warm-up
            for _, client in clients:
                await client.stop()
        for i in range(STOPS):
            for key, client in clients if i % 2 else clients[::-1]:
                t0 = time.perf_counter()
                ack = await client.stop()
                results[key].append((time.perf_counter() - t0) * 1000)
                if not ack.ok:
                    raise RuntimeError(f"stop not acknowledged: {ack.text}")
                await asyncio.sleep(0.01)
    return results


def raw_pings(site: RouterRig, cloud: RouterRig) -> dict[str, list[float]]:
    """Round trips (ms) of a CONTROL-QoS put to a session on the site router, answered."""
    import zenoh

    def session(rig: RouterRig) -> Any:
        settings: ZenohSettings = rig.zenoh(rig.client("admin", "bench"))
        return zenoh.open(build_zenoh_config(settings))

    qos = LANE_QOS[Lane.CONTROL]
    echo, near, far = session(site), session(site), session(cloud)
    try:
        # Each asker has its own pong key, so that only its own answer counts.
        pongs = {
            k: echo.declare_publisher(f"telebot/bench/pong/{k}", **qos) for k in ("one", "two")
        }
        echo.declare_subscriber(
            "telebot/bench/ping/*",
            lambda s: pongs[str(s.key_expr).rsplit("/", 1)[1]].put(s.payload.to_bytes()),
        )
        got = threading.Event()
        near.declare_subscriber("telebot/bench/pong/one", lambda _s: got.set())
        far.declare_subscriber("telebot/bench/pong/two", lambda _s: got.set())
        pings = {"one": near.declare_publisher("telebot/bench/ping/one", **qos)}
        pings["two"] = far.declare_publisher("telebot/bench/ping/two", **qos)
        results: dict[str, list[float]] = {"one": [], "two": []}
        for i in range(PINGS + 20):
            for key in ("one", "two") if i % 2 else ("two", "one"):
                got.clear()
                t0 = time.perf_counter()
                pings[key].put(i.to_bytes(8, "big") + bytes(56))
                if not got.wait(2):
                    continue
                if i >= 20:  # warm-up (the cloud session's route settles)
                    results[key].append((time.perf_counter() - t0) * 1000)
                time.sleep(0.005)
        return results
    finally:
        for s in (echo, near, far):
            s.close()


async def main() -> None:
    logging.basicConfig(level=logging.ERROR)
    with tempfile.TemporaryDirectory(prefix="bench-routers-") as tmp:
        base = Path(tmp)
        site, cloud = setup(base)
        robot: Process | None = None
        try:
            cloud.start()
            site.start(extra=("--peer-router", cloud.endpoint))
            config = site.write_robot_config(
                base / "robot.toml", site.client("robot", ROBOT), timeout=CALL_TIMEOUT
            )
            robot = Process(
                [
                    *("telebot.apps.robot_cli", "run", "--home", str(base / ROBOT)),
                    *("--config", str(config), "--events"),
                ]
            )
            line = robot.next_line(timeout=60)
            if '"ready"' not in line:
                raise RuntimeError(f"the robot did not start: {line}")
            print("robot ready; stops ...", file=sys.stderr, flush=True)
            stops = await stop_series(base, site, cloud)
            print("raw round trips ...", file=sys.stderr, flush=True)
            raw = await asyncio.to_thread(raw_pings, site, cloud)
        finally:
            if robot is not None:
                robot.stop()
            site.stop()
            cloud.stop()
    print(f"{'':28} {'one router':>12} {'two routers':>12} {'added':>8} {'ratio':>6}")
    figures: dict[str, float] = {}
    for name, series in (("stop -> ack", stops), ("raw round trip", raw)):
        for q in (50, 99):
            one, two = pct(series["one"], q), pct(series["two"], q)
            print(
                f"{name + f' p{q} (ms)':28} {one:12.2f} {two:12.2f} {two - one:8.2f} "
                f"{two / one:6.2f}"
            )
            figures[f"{name}{q}"] = one
            figures[f"{name}{q}two"] = two
    print(
        f"samples: {len(stops['one'])}+{len(stops['two'])} stops, "
        f"{len(raw['one'])}+{len(raw['two'])} raw round trips"
    )
    s50, s50b = figures["stop -> ack50"], figures["stop -> ack50two"]
    s99, s99b = figures["stop -> ack99"], figures["stop -> ack99two"]
    r50, r50b = figures["raw round trip50"], figures["raw round trip50two"]
    print(
        f"RESULT stop_p50_ms_one={s50:.2f} stop_p50_ms_two={s50b:.2f} "
        f"stop_added_p50_ms={s50b - s50:.2f} stop_ratio_p50={s50b / s50:.2f} "
        f"stop_p99_ms_one={s99:.2f} stop_p99_ms_two={s99b:.2f} "
        f"raw_added_p50_ms={r50b - r50:.2f} raw_ratio_p50={r50b / r50:.2f}"
    )


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="5 stops and 5 round trips each")
    if parser.parse_args().quick:
        STOPS, PINGS = 5, 5
    asyncio.run(main())
