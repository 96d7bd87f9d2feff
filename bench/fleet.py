"""A fleet behind one telebot router: presence listing, stop under load, router cost per robot.

Everything on this machine, over mutual TLS on loopback, with the ACL on:

- one ``telebot-router run`` process (zenoh-python router mode), certificates made by
  ``telebot.router.certs`` for every robot and user;
- N lightweight simulated robots: robot 0 (the one stopped in B) alone in a child process,
  as a real robot has its own computer, the others :data:`PER_PROCESS` per child process
  (a hundred Python processes would not fit on a 2-core machine; each robot has its own
  zenoh session, its own certificate and its own ``RobotServer`` with the ``core`` services
  only: the small map, a 10 Hz control loop, 32 laser beams, no camera service at all), added
  in steps so that N = 10, 50, 100 are measured in one run;
- M observer processes (users with the observer role) that call every robot of the first 50
  between them (one zenoh session per process, one call per robot), so that each of those
  robots streams its pose at 10 Hz (and telemetry at 1 Hz, heartbeats at 20 Hz both ways);
- one driver in this process who stops robot 0 :data:`STOPS` times, re-arming in between.

The other robots and the observers stand for machines elsewhere, so their processes run at
``nice 10`` (``FLEET_NICE``): the router, robot 0 and the driver, which a real deployment
would have to itself, get the CPU first.

Measured:

A. Presence listing time at N = 10, 50, 100: from opening a new session of the driver's
   (TLS handshake included), watching ``{ns}/presence/robot/*/*`` with history, until all
   N robots are seen (:data:`LISTINGS` runs, median and worst). Raw zenoh: a bare
   zenoh-python session (an ``admin:`` certificate, which the ACL lets do anything) and a
   liveliness subscriber with history, through the same router, same run.
B. Stop → acknowledgement at N = 50 while the 50 robots stream to their observers: p50/p99 of
   ``await client.stop()`` (the request on the CONTROL lane, the robot's ack back), robot 0
   reached through the router. Raw zenoh: a put/subscribe ping-pong through the same router
   with the CONTROL lane's QoS, between two bare sessions in this process (``admin:``).
C. Router cost: its resident memory (``/proc/PID/status`` VmRSS) with no client, and at each
   N (idle robots, then 50 streamed calls); CPU (user + system time from ``/proc/PID/stat``)
   over the stop series, as a share of one core, per robot and per streamed call. Also the
   CPU share of the robot and observer processes, which is what runs out first here.

Run: ``python bench/fleet.py`` (about a minute). Targets: listing of 100 robots <= 1 s, stop
p99 <= 20 ms at N = 50, router memory <= 2 MB per robot. The last line is
``RESULT list100_ms=... stop_p99_ms_n50=... router_mb_per_robot=...`` (memory per robot:
router RSS at N = 100 with 50 streamed calls minus its RSS with no client, over 100).
``--quick``: N = 1 and 4 (4 streamed calls, one observer process), 5 stops, one listing,
short settling waits (a check that it runs; the RESULT keys keep their names).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from _child import Child
from router_rig import RouterRig
from telebot.channels.call import RobotEndpoint
from telebot.channels.transports.base import Lane
from telebot.channels.transports.zenoh import (
    LANE_QOS,
    ZenohTransport,
    build_zenoh_config,
)
from telebot.config import AppConfig, CallSettings, SimSettings, ZenohSettings
from telebot.errors import TelebotError
from telebot.identity import ContactBook, Identity, KnownRobots, Role
from telebot.robot.sim.stack import SimNavStack
from telebot.services.base import ServiceRegistry
from telebot.services.client import RobotClient, connect
from telebot.services.robot import CallServices, RobotServer
from telebot.services.safety.robot import SafetyDriver

STEPS = (10, 50, 100)
#: Robots per child process: 100 Python processes would not fit on a 2-core machine.
PER_PROCESS = 25
#: Observer processes, and how many robots (the first ones) they call between them.
OBSERVERS = 2
OBSERVED = 50
STOPS = 200
LISTINGS = 5
PINGS = 500
ROUTER_SETTLE = 1.0  # s after the router's start before its memory with no client is read
CALLS_SETTLE = 2.0  # s for the observers' calls to settle (maps offered, first poses)
DRIVER = "driver"
OBSERVER = "obs"
#: Generous for a loaded machine: a preempted process must not drop its calls.
CALL_TIMEOUT = 2.0
LIGHT_SIM = SimSettings(map="small", control_hz=10, laser_beams=32)
TARGET_LIST_MS = 1000.0
TARGET_STOP_MS = 20.0
TARGET_MB = 2.0


def robot_name(i: int) -> str:
    return f"robot-{i:03d}"


def pct(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q / 100 * (len(ordered) - 1)))]


def proc_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def proc_cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


# -- children ---------------------------------------------------------------------------------


async def robots_child(base: Path, endpoint: str, first: int, count: int) -> None:
    """``count`` robots from ``first``, each with its own session; 'ready' when all are up."""
    loop = asyncio.get_running_loop()
    router = RouterRig.existing(base, endpoint)
    registry: ServiceRegistry[RobotServer] = ServiceRegistry()
    registry.register("core", CallServices)
    async with contextlib.AsyncExitStack() as stack:
        runners = []
        for i in range(first, first + count):
            name = robot_name(i)
            home = base / name
            nav = SimNavStack.from_settings(LIGHT_SIM, now=loop.time())
            safety = stack.enter_context(SafetyDriver(nav, timeout=CALL_TIMEOUT, max_speed=1.0))
            server = RobotServer(
                nav, control_hz=LIGHT_SIM.control_hz, safety=safety, services=registry
            )
            await server.prepare()
            transport = await stack.enter_async_context(
                ZenohTransport(router.zenoh(router.client("robot", name)))
            )
            endpoint_ = await stack.enter_async_context(
                RobotEndpoint(
                    transport,
                    Identity.load(home),
                    ContactBook.load(home),
                    settings=CallSettings(timeout=CALL_TIMEOUT),
                )
            )
            server.attach(endpoint_)
            runners.append(asyncio.create_task(server.run()))
        print(json.dumps({"ready": count, "pid": os.getpid()}), flush=True)
        try:
            await asyncio.to_thread(sys.stdin.read)
        finally:
            for task in runners:
                task.cancel()
            await asyncio.gather(*runners, return_exceptions=True)
    print(json.dumps({"done": True}), flush=True)


async def observers_child(base: Path, endpoint: str, index: int, names: list[str]) -> None:
    """A user process with one session and one observer call per robot of ``names``."""
    router = RouterRig.existing(base, endpoint)
    user = f"{OBSERVER}{index}"
    config = AppConfig.model_validate(
        {
            "transport": {"zenoh": router.zenoh(router.client("user", user))},
            "call": CallSettings(timeout=CALL_TIMEOUT),
        }
    )
    poses = 0

    async def follow(client: RobotClient) -> None:
        nonlocal poses
        async for _ in client.poses():
            poses += 1

    async with contextlib.AsyncExitStack() as stack:
        transport = await stack.enter_async_context(ZenohTransport(config.transport.zenoh))
        clients: list[RobotClient] = []
        failed: list[str] = []
        for name in names:  # one at a time: a loaded machine answers a burst of calls late
            try:
                clients.append(
                    await stack.enter_async_context(
                        connect(name, home=base / user, config=config, transport=transport)
                    )
                )
            except (TelebotError, TimeoutError) as exc:
                failed.append(f"{name}: {exc}")
        followers = [asyncio.create_task(follow(c)) for c in clients]
        ready = {"ready": len(clients), "failed": failed, "pid": os.getpid()}
        print(json.dumps(ready), flush=True)
        try:
            await asyncio.to_thread(sys.stdin.read)
        finally:
            for task in followers:
                task.cancel()
            await asyncio.gather(*followers, return_exceptions=True)
    print(json.dumps({"poses": poses}), flush=True)


# -- the measuring side -------------------------------------------------------------------------


def make_fleet(base: Path, n: int) -> RouterRig:
    """Certificates and homes: N robots, the driver, the observers; raw-zenoh admin."""
    router = RouterRig(base)
    driver = Identity.generate(DRIVER)
    driver.save(base / DRIVER)
    observers = [Identity.generate(f"{OBSERVER}{i}") for i in range(OBSERVERS)]
    for observer in observers:
        observer.save(base / observer.name)
        router.issue("user", observer.name)
    router.issue("user", DRIVER)
    router.issue("admin", "raw")
    knowns = {who: KnownRobots.load(base / who) for who in [DRIVER, *(o.name for o in observers)]}
    for i in range(n):
        name = robot_name(i)
        robot = Identity.generate(name)
        robot.save(base / name)
        book = ContactBook.load(base / name)
        book.add(DRIVER, driver.public_key, Role.DRIVER)
        for observer in observers:
            book.add(observer.name, observer.public_key, Role.OBSERVER)
        book.save()
        for known in knowns.values():
            known.add(name, robot.public_key)
        router.issue("robot", name)
    for known in knowns.values():
        known.save()
    return router


async def list_telebot(settings: ZenohSettings, n: int) -> float:
    """ms from opening a session to seeing ``n`` robot presence tokens."""
    t0 = time.perf_counter()
    seen: set[str] = set()
    done = asyncio.Event()

    def on_presence(key: str, alive: bool) -> None:
        if alive:
            seen.add(key)
            if len(seen) >= n:
                done.set()

    async with ZenohTransport(settings) as transport:
        transport.watch_presence("telebot/presence/robot/*/*", on_presence)
        await asyncio.wait_for(done.wait(), 30)
        return (time.perf_counter() - t0) * 1000


def list_raw(settings: ZenohSettings, n: int) -> float:
    """The same with a bare zenoh-python session and liveliness subscriber (a thread)."""
    import threading

    import zenoh

    t0 = time.perf_counter()
    seen: set[str] = set()
    done = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        seen.add(str(sample.key_expr))
        if len(seen) >= n:
            done.set()

    session = zenoh.open(build_zenoh_config(settings))
    try:
        sub = session.liveliness().declare_subscriber(
            "telebot/presence/robot/*/*", on_sample, history=True
        )
        done.wait(30)
        elapsed = (time.perf_counter() - t0) * 1000
        sub.undeclare()
    finally:
        session.close()
    return elapsed


def raw_ping(settings: ZenohSettings, count: int) -> list[float]:
    """Round trips (ms) of a CONTROL-QoS put answered by a second session, via the router."""
    import threading

    import zenoh

    qos = LANE_QOS[Lane.CONTROL]
    a = zenoh.open(build_zenoh_config(settings))
    b = zenoh.open(build_zenoh_config(settings))
    try:
        pong = b.declare_publisher("bench/pong", **qos)
        b.declare_subscriber("bench/ping", lambda s: pong.put(s.payload.to_bytes()))
        got = threading.Event()
        a.declare_subscriber("bench/pong", lambda s: got.set())
        ping = a.declare_publisher("bench/ping", **qos)
        rtts = []
        for i in range(count + 20):
            got.clear()
            t0 = time.perf_counter()
            ping.put(i.to_bytes(8, "big") + bytes(56))
            if not got.wait(2):
                continue
            if i >= 20:  # warm-up
                rtts.append((time.perf_counter() - t0) * 1000)
            time.sleep(0.005)
        return rtts
    finally:
        a.close()
        b.close()


async def stop_series(router: RouterRig, base: Path) -> tuple[list[float], list[str]]:
    config = AppConfig.model_validate(
        {
            "transport": {"zenoh": router.zenoh(router.client("user", DRIVER))},
            "call": CallSettings(timeout=CALL_TIMEOUT),
        }
    )
    latencies: list[float] = []
    failures: list[str] = []
    async with connect(robot_name(0), home=base / DRIVER, config=config, timeout=60) as client:
        for _ in range(STOPS):
            try:
                ack = await client.arm()
                if not ack.ok:
                    raise RuntimeError(f"arm refused: {ack.text}")
                await asyncio.sleep(0.02)
                t0 = time.perf_counter()
                ack = await client.stop()
                latencies.append((time.perf_counter() - t0) * 1000)
                if not ack.ok:
                    raise RuntimeError(f"stop not acknowledged: {ack.text}")
            except (TelebotError, TimeoutError, RuntimeError) as exc:
                # A starved machine can drop the call: the client calls again by itself.
                failures.append(str(exc))
                await asyncio.sleep(0.5)
    return latencies, failures


def cpu_share(pids: list[int], before: dict[int, float], seconds: float) -> float:
    return sum(proc_cpu_s(p) - before[p] for p in pids) / seconds


async def main() -> None:
    n_max = STEPS[-1]
    with tempfile.TemporaryDirectory(prefix="telebot-fleet-") as tmp:
        base = Path(tmp)
        print(f"fleet: {n_max} robots' certificates and homes ...", flush=True)
        router = make_fleet(base, n_max)
        router.start()
        assert router.process is not None
        rpid = router.process.pid
        children: list[Child] = []
        robot_pids: list[int] = []
        observer_pids: list[int] = []
        raw = router.zenoh(router.client("admin", "raw"))
        user = router.zenoh(router.client("user", DRIVER))
        results: dict[str, Any] = {}
        try:
            await asyncio.sleep(ROUTER_SETTLE)
            rss0 = proc_rss_mb(rpid)
            print(f"router: pid {rpid}, {rss0:.1f} MB with no client", flush=True)
            started = 0
            for n in STEPS:
                while started < n:
                    # Robot 0, the one stopped in B, has a process of its own, as a real
                    # robot has its own computer; the others share processes.
                    count = 1 if started == 0 else min(PER_PROCESS, n - started)
                    child = Child(
                        __file__, "robots", tmp, router.endpoint, str(started), str(count)
                    )
                    children.append(child)
                    ready = json.loads(await asyncio.to_thread(child.next_line, 180))
                    robot_pids.append(ready["pid"])
                    started += count
                telebot_ms = [await list_telebot(user, n) for _ in range(LISTINGS)]
                raw_ms = [await asyncio.to_thread(list_raw, raw, n) for _ in range(LISTINGS)]
                rss = proc_rss_mb(rpid)
                results[f"list{n}"] = statistics.median(telebot_ms)
                results[f"rss{n}"] = rss
                print(
                    f"A. N={n:3d}: listing {statistics.median(telebot_ms):6.1f} ms median, "
                    f"{max(telebot_ms):6.1f} worst (raw zenoh {statistics.median(raw_ms):6.1f} / "
                    f"{max(raw_ms):6.1f}); router {rss:.1f} MB "
                    f"({(rss - rss0) / n:.2f} MB/robot, idle)",
                    flush=True,
                )
                if n == OBSERVED:
                    share = [robot_name(i) for i in range(OBSERVED)]
                    for k in range(OBSERVERS):
                        names = share[k::OBSERVERS]
                        child = Child(__file__, "observers", tmp, router.endpoint, str(k), *names)
                        children.append(child)
                        ready = json.loads(await asyncio.to_thread(child.next_line, 300))
                        observer_pids.append(ready["pid"])
                        for failure in ready["failed"]:
                            print(f"   observer {k} could not call {failure}", flush=True)
                    await asyncio.sleep(CALLS_SETTLE)
                    pids = [rpid, *robot_pids, *observer_pids]
                    before = {p: proc_cpu_s(p) for p in pids}
                    t0 = time.perf_counter()
                    stops, stop_failures = await stop_series(router, base)
                    seconds = time.perf_counter() - t0
                    router_cpu = cpu_share([rpid], before, seconds)
                    robots_cpu = cpu_share(robot_pids, before, seconds)
                    observers_cpu = cpu_share(observer_pids, before, seconds)
                    rss_streaming = proc_rss_mb(rpid)
                    rtts = await asyncio.to_thread(raw_ping, raw, PINGS)
                    results["stop_p99"] = pct(stops, 99)
                    results["cpu"] = (router_cpu / n, robots_cpu / n, observers_cpu / OBSERVED)
                    results["rss_streaming50"] = rss_streaming
                    print(
                        f"B. N={n}, {OBSERVED} calls streaming: stop->ack p50 "
                        f"{pct(stops, 50):.2f} ms, p99 {pct(stops, 99):.2f} ms, max "
                        f"{max(stops):.2f} ms ({len(stops)} stops, {len(stop_failures)} "
                        "failed); raw zenoh CONTROL round "
                        f"trip p50 {pct(rtts, 50):.2f} ms, p99 {pct(rtts, 99):.2f} ms",
                        flush=True,
                    )
                    print(
                        f"C. N={n}: router CPU {router_cpu * 100:.1f} % of a core "
                        f"({router_cpu * 100 / n:.2f} % per robot/streamed call), "
                        f"{rss_streaming:.1f} MB ({(rss_streaming - rss0) / n:.2f} MB/robot); "
                        f"robot processes {robots_cpu * 100:.0f} % "
                        f"({robots_cpu * 100 / n:.2f} % per robot), observer processes "
                        f"{observers_cpu * 100:.0f} % ({observers_cpu * 100 / OBSERVED:.2f} % "
                        f"per call); machine has {os.cpu_count()} cores, load "
                        f"{os.getloadavg()[0]:.1f}",
                        flush=True,
                    )
            mb_per_robot = (results[f"rss{n_max}"] - rss0) / n_max
            print(
                f"C. N={n_max} ({OBSERVED} streamed calls): router {results[f'rss{n_max}']:.1f} MB, "
                f"{mb_per_robot:.2f} MB per robot",
                flush=True,
            )
        finally:
            stats = [c.close() for c in reversed(children)]
            router.stop()
        router_per, robot_per, observer_per = results["cpu"]
        cores = os.cpu_count() or 1
        per_core = 1 / max(router_per, 1e-9)
        per_gb = 1024 / max(mb_per_robot, 1e-9)
        router_limit = "CPU" if per_core < per_gb else "memory"
        print(
            f"runs out first here: CPU of the simulated robots and their observers "
            f"({robot_per * 100:.1f} % of a core per streaming robot + {observer_per * 100:.1f} % "
            f"per observer call: about {cores / (robot_per + observer_per + router_per):.0f} "
            f"streaming robots fill this machine's {cores} cores with the router); the router "
            f"itself runs out of {router_limit} first: about {per_core:.0f} streaming robots per "
            f"core, {per_gb:.0f} robots per GB",
            flush=True,
        )
        poses = sum(int(s.get("poses", 0)) for s in stats if isinstance(s.get("poses", 0), int))
        print(f"observers received {poses} poses in all", flush=True)
        verdicts = [
            ("listing of 100", results[f"list{n_max}"] <= TARGET_LIST_MS),
            ("stop p99 at N=50", results["stop_p99"] <= TARGET_STOP_MS),
            ("router MB per robot", mb_per_robot <= TARGET_MB),
        ]
        print("targets: " + ", ".join(f"{k} {'met' if ok else 'MISSED'}" for k, ok in verdicts))
        print(
            f"RESULT list100_ms={results[f'list{n_max}']:.1f} "
            f"stop_p99_ms_n50={results['stop_p99']:.2f} router_mb_per_robot={mb_per_robot:.3f}"
        )


def child_main(argv: list[str]) -> None:
    # Each robot logs its supervisor's start-up stop: a hundred lines of noise here.
    logging.basicConfig(level=logging.ERROR)
    kind, base, endpoint, *rest = argv
    # The robots other than robot 0 stand for robots on computers of their own, and the
    # observers for users elsewhere: on this one machine they run at a lower priority, so
    # that what a real deployment shares with them (the router, robot 0 and its driver)
    # is not starved by load that would be on other machines (B measures the stop, not
    # the 2-core machine's run queue). Set FLEET_NICE=0 to run them all at one priority.
    background = kind != "robots" or int(rest[0]) != 0
    if background:
        os.nice(int(os.environ.get("FLEET_NICE", "10")))
    if kind == "robots":
        asyncio.run(robots_child(Path(base), endpoint, int(rest[0]), int(rest[1])))
    else:
        asyncio.run(observers_child(Path(base), endpoint, int(rest[0]), rest[1:]))


if __name__ == "__main__":
    if sys.argv[1:2] == ["--child"]:
        child_main(sys.argv[2:])
    else:
        parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
        parser.add_argument("--quick", action="store_true", help="N = 1 and 4, 5 stops")
        if parser.parse_args().quick:
            STEPS, OBSERVERS, OBSERVED, STOPS, LISTINGS, PINGS = (1, 4), 1, 4, 5, 1, 10
            ROUTER_SETTLE, CALLS_SETTLE = 0.2, 0.5
        asyncio.run(main())
