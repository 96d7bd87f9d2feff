"""Safety end to end: the deadman, the latch and the stop key, across processes and on a lossy link.

Most tests share a ``telebot-robot run`` daemon (``tests/rig.py``: the small map, a fast
robot) and reach it over zenoh on loopback: the deadman tests one with the product's call
timeout, the others one with a generous timeout (a preempted process keeps its calls). The
driver that gets frozen or killed is a separate process (``tests/safety_driver_proc.py``),
and an observer in this process watches the robot's velocity through its pose stream
(10 Hz, ``v`` and ``w``) and the safety state. Pose stamps and audit records carry the
robot's ``time.monotonic()``, the same clock as this process's on Linux, so they are
compared with the moment a signal was sent: what is timed is when the robot stopped, not
when this process heard of it.

The bounds are the requirement, not a benchmark: stopped within the deadman time plus a
margin for the control step and a loaded CI machine (``SLACK``) — far below zenoh's 10 s
lease, which a stop that waited for the link to be declared lost would need.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import signal
import subprocess
import sys
import time
from collections.abc import AsyncGenerator, AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from rig import (
    FAST_SIM,
    GENEROUS_TIMEOUT,
    OBSERVER,
    REAL_TIMEOUT,
    ROBOT,
    SLACK,
    USER,
    Daemon,
    Process,
    child_env,
    robot_on_hub,
)
from telebot.channels.call import UserEndpoint
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import CallSettings
from telebot.errors import CallEnded
from telebot.identity import Identity, KnownRobots
from telebot.reasons import Reason
from telebot.robot.nav import Velocity
from telebot.robot.sim.stack import SimNavStack
from telebot.services import client as client_module
from telebot.services.chat.wire import ChatReply
from telebot.services.client import RobotClient
from telebot.services.safety.robot import SafetyDriver
from telebot.services.safety.wire import SafetyStatus
from telebot.services.status.wire import PoseUpdate

#: The default call timeout: the robot must be stopped within it of the driver going silent
#: (the deadman itself fires one heartbeat earlier, see robot_daemon.deadman_time) (s).
TIMEOUT = REAL_TIMEOUT
#: Slack on top of it: the control step (0.05 s) and the watchdog period (0.01 s), rounded
#: up, and SLACK for a loaded 2-core CI machine.
MARGIN = 0.1 + SLACK
#: zenoh's default lease (s): what a stop relying on the link being declared dead would take.
DEFAULT_LEASE = 10.0

#: The far ends of the small map's corridor: a goto from one to the other takes seconds.
FAR_PLACES = {"start": (1.0, 1.2), "corridor": (10.5, 1.2)}


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    """The robot of the tests that are not about drop timing: a generous call timeout."""
    daemon = Daemon(tmp_path_factory.mktemp("safety"))
    daemon.start()
    yield daemon
    daemon.stop()


@pytest.fixture(scope="module")
def deadman(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    """The robot of the deadman tests: the product's call timeout, which they are about."""
    daemon = Daemon(tmp_path_factory.mktemp("deadman"), timeout=TIMEOUT)
    daemon.start()
    yield daemon
    daemon.stop()


@pytest.fixture
async def observer(daemon: Daemon) -> AsyncIterator[RobotClient]:
    """olga, who may only watch (and stop), in this process."""
    async with daemon.connect(daemon.observer_home) as client:
        yield client


@pytest.fixture
async def watcher(deadman: Daemon) -> AsyncIterator[RobotClient]:
    """olga watching the deadman robot; her own side of the call is generous."""
    async with deadman.connect(deadman.observer_home, call_timeout=GENEROUS_TIMEOUT) as client:
        yield client


def start_driver(
    daemon: Daemon, processes: list[Process], *, lease_ms: int | None = None
) -> Process:
    """alice in her own process (tests/safety_driver_proc.py): arms and drives far."""
    config = daemon.write_user_config(f"driver{len(processes)}.toml", lease_ms=lease_ms)
    process = Process(
        [
            "safety_driver_proc",
            "--home",
            str(daemon.user_home),
            "--config",
            str(config),
            "--connect",
            daemon.endpoint,
            "--robot",
            ROBOT,
        ],
        env=child_env(),
    )
    processes.append(process)
    return process


async def arm(client: RobotClient, patience: float = 5.0 + SLACK) -> None:
    """Re-arm; an earlier call of alice's may still hold the drive for a moment."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + patience
    while True:
        ack = await client.arm()
        if ack.ok:
            return
        assert loop.time() < deadline, ack.text
        if ack.code == Reason.NOT_HOLDER:
            await client.take_drive()
        await asyncio.sleep(0.1)


async def first_reply(client: RobotClient, command: str, timeout: float | None = None) -> ChatReply:
    """The first reply to ``command`` (a motion's acknowledgement); the motion runs on."""
    replies = client.chat_replies(command, timeout=timeout)
    assert isinstance(replies, AsyncGenerator)  # closed here, not left to the GC
    async with contextlib.aclosing(replies):
        return await anext(replies)


async def drive_far(client: RobotClient) -> None:
    """Start a goto to the farther end of the corridor; return once it is acknowledged."""
    here = await client.pose()
    target = max(FAR_PLACES, key=lambda name: math.dist(FAR_PLACES[name], (here.x, here.y)))
    reply = await first_reply(client, f"goto {target}")
    assert reply.ok and not reply.final, reply.text


def still(pose: PoseUpdate) -> bool:
    return pose.v == 0 and pose.w == 0


async def next_pose(
    client: RobotClient, check: Callable[[PoseUpdate], bool], timeout: float
) -> PoseUpdate:
    """The first pose update that passes ``check``."""
    async with asyncio.timeout(timeout):
        while True:
            pose = await client.pose()
            if check(pose):
                return pose


async def safety_state(
    client: RobotClient, check: Callable[[SafetyStatus], bool], timeout: float = 3.0 + SLACK
) -> SafetyStatus:
    """The first safety state (the latest known, then each new one) that passes ``check``."""
    async with asyncio.timeout(timeout):
        state = client.latest_safety.value
        while state is None or not check(state):
            state = await client.latest_safety.next()
        return state


async def assert_at_rest(client: RobotClient, seconds: float, *, armed: bool | None) -> None:
    """Every pose for ``seconds`` of the robot's clock shows the robot at rest, and the
    armed state is ``armed`` (None: either).

    Measured by the poses' own stamps, not by how many came: a stalled observer gets
    only the newest pose (the stream is latest-only). So that a move between two poses
    seen cannot hide, every pose must also be where the first was (to within the
    localisation noise's bounds, 3 × 1 cm on each axis for each of the two).
    """
    first = await client.pose()
    pose = first
    while True:
        assert still(pose), pose
        assert math.hypot(pose.x - first.x, pose.y - first.y) < 0.1, (first, pose)
        if pose.t - first.t >= seconds:
            break
        pose = await client.pose()
    state = client.latest_safety.value
    assert state is not None and armed in (None, state.armed), state


# -- a frozen or killed driver -------------------------------------------------------------


async def freeze_or_kill(
    daemon: Daemon, observer: RobotClient, driver: Process, sig: signal.Signals
) -> tuple[str, float]:
    """Wait until the driver drives, send ``sig``, assert the robot stops in time.

    In time by the robot's own records, not by when this process heard of it: the audit
    record of the stop and the stamps of the poses that still showed motion.
    Returns the driver's call id and when the signal was sent (monotonic clock).
    """
    connected = await driver.wait_event("connected", timeout=30)
    call_id = str(connected["call"])
    await driver.wait_event("moving", timeout=30)
    await next_pose(observer, lambda p: abs(p.v) > 0.05, timeout=5 + SLACK)  # seen moving too
    sent = time.monotonic()
    driver.signal(sig)
    moving: list[PoseUpdate] = []
    async with asyncio.timeout(DEFAULT_LEASE):
        while not still(pose := await observer.pose()):
            moving.append(pose)
    # The pose stamps are the robot's clock: no pose showed the base moving after the bound.
    late = [p for p in moving if p.t - sent > TIMEOUT + MARGIN]
    assert not late, f"the robot still moved {late[-1].t - sent:.2f} s after {sig.name}"
    # The robot recorded the stop (the deadman's, or the drop's) within the bound.
    stops = [
        r
        for r in daemon.audit()
        if r["call"] == call_id and r["outcome"] == "stopped" and r["t"] >= sent
    ]
    assert stops, f"no stop of alice's call recorded after {sig.name}"
    assert stops[0]["t"] - sent <= TIMEOUT + MARGIN, stops[0]
    return call_id, sent


@pytest.mark.zenoh
@pytest.mark.parametrize("lease_ms", [None, 3_600_000], ids=["default-lease", "one-hour-lease"])
async def test_a_frozen_driver_stops_the_robot_within_the_timeout(
    deadman: Daemon, watcher: RobotClient, processes: list[Process], lease_ms: int | None
) -> None:
    daemon, observer = deadman, watcher
    driver = start_driver(daemon, processes, lease_ms=lease_ms)
    call_id, frozen_at = await freeze_or_kill(daemon, observer, driver, signal.SIGSTOP)
    state = await safety_state(observer, lambda s: not s.armed)
    assert "alice" in state.text and ("link lost" in state.text or "dropped" in state.text)
    # With a one-hour lease zenoh never declares alice gone: the call's heartbeats do.
    ended = await daemon.call_ended(call_id)
    assert ended["kind"] == "dropped" and "nothing from alice" in ended["detail"]
    # The deadman (not a later event) stopped it, and the audit log says so.
    deadman = [
        r for r in daemon.audit() if r["what"] == "deadman" and r["t"] >= frozen_at and r["call"]
    ]
    assert [(r["who"], r["outcome"]) for r in deadman] == [(USER, "stopped")]
    assert deadman[0]["t"] - frozen_at <= TIMEOUT + MARGIN


@pytest.mark.zenoh
async def test_a_killed_driver_stops_the_robot(
    deadman: Daemon, watcher: RobotClient, processes: list[Process]
) -> None:
    daemon, observer = deadman, watcher
    driver = start_driver(daemon, processes)
    call_id, _ = await freeze_or_kill(daemon, observer, driver, signal.SIGKILL)
    # Disarmed, and the dead call's drive freed.
    state = await safety_state(observer, lambda s: not s.armed and s.holder is None)
    assert "alice" in state.text
    ended = await daemon.call_ended(call_id)
    assert ended["kind"] == "dropped"


@pytest.mark.zenoh
async def test_a_thawed_driver_finds_the_robot_stopped_until_it_is_re_armed(
    deadman: Daemon, watcher: RobotClient, processes: list[Process]
) -> None:
    daemon, observer = deadman, watcher
    driver = start_driver(daemon, processes, lease_ms=3_600_000)
    call_id, _ = await freeze_or_kill(daemon, observer, driver, signal.SIGSTOP)
    await daemon.call_ended(call_id)  # the robot gave the frozen call up...
    driver.signal(signal.SIGCONT)  # ...and then the link heals
    ended = await driver.wait_event("ended", timeout=10)
    assert ended["kind"] == "dropped"  # the thawed driver's call is gone, not resumed
    await assert_at_rest(observer, 1.0, armed=False)
    # Only someone holding the drive can arm it again: alice, calling anew.
    async with daemon.connect() as alice:
        state = await safety_state(alice, lambda s: s.holder == USER)
        assert not state.armed
        refused = await alice.chat("fwd 0.3")
        assert not refused.ok and refused.code == Reason.NOT_ARMED
        await arm(alice)
        armed_at = time.monotonic()
        assert (await safety_state(observer, lambda s: s.armed)).armed
        # Re-arming starts nothing: the cancelled goto does not come back.
        await next_pose(observer, lambda p: p.t > armed_at, timeout=2 + SLACK)
        await assert_at_rest(observer, 0.5, armed=None)
        moved = await alice.chat("fwd 0.3", timeout=30)
        # This rig keeps the real 0.5 s deadman: on a loaded machine alice's own heartbeats
        # may fall silent (while she waits, or mid-drive), and the deadman stops her (its
        # job, recorded as such), which is not the cancelled goto coming back. Then re-arm
        # and drive again.
        for _ in range(2):
            tripped = [r for r in daemon.audit() if r["what"] == "deadman" and r["t"] >= armed_at]
            if moved.ok or not tripped:
                break
            await arm(alice)
            armed_at = time.monotonic()
            moved = await alice.chat("fwd 0.3", timeout=30)
        assert moved.ok, moved.replies
        assert (await alice.stop()).ok


# -- observers -------------------------------------------------------------------------------


@pytest.mark.zenoh
async def test_an_observer_cannot_drive_but_its_stop_stops_a_moving_robot(
    daemon: Daemon, observer: RobotClient
) -> None:
    async with daemon.connect() as alice:
        assert (await alice.stop()).ok
        await arm(alice)
        refused = await observer.chat("fwd 1")
        assert not refused.ok and refused.code == Reason.OBSERVER
        goal = await observer.goto(3.0, 5.2, timeout=10)
        assert goal.status == "refused" and goal.code == Reason.OBSERVER
        for ack in (await observer.arm(), await observer.take_drive()):
            assert not ack.ok and ack.code == Reason.OBSERVER
        await drive_far(alice)
        # The refusals stopped nothing: alice's robot drives...
        await next_pose(observer, lambda p: abs(p.v) > 0.05, timeout=10)
        ack = await observer.stop()
        acked = time.monotonic()
        assert ack.ok
        # ...until olga's stop, acknowledged after the base halted: every pose stamped
        # (robot clock) after the acknowledgement shows it at rest.
        after = await next_pose(observer, lambda p: p.t > acked, timeout=2 + SLACK)
        assert still(after), after
        state = await safety_state(alice, lambda s: not s.armed)
        assert OBSERVER in state.text
        again = await alice.chat("fwd 1")
        assert not again.ok and again.code == Reason.NOT_ARMED


# -- a data flood ----------------------------------------------------------------------------
# These two load the whole machine (two CPU burners and a flooding process for 5 s): marked
# solo, make test runs them alone after the rest. Beside them a browser test's Chromium or
# gateway went silent for 2 s, and its call dropped in the middle of its goal.

#: How long the flooding user floods (s): 2.5 of the rig's generous call timeouts.
FLOOD_SECONDS = 5.0


@contextlib.contextmanager
def cpu_burners(count: int = 2) -> Iterator[None]:
    """``count`` processes spinning on the CPU (a busy CI machine), killed on exit."""
    burners = [subprocess.Popen([sys.executable, "-c", "while 1: pass"]) for _ in range(count)]
    try:
        yield
    finally:
        for burner in burners:
            burner.kill()
            burner.wait()


@pytest.mark.zenoh
@pytest.mark.solo
async def test_a_data_flood_drops_no_call_and_its_stop_still_reaches_the_base(
    daemon: Daemon, processes: list[Process]
) -> None:
    """olga floods 32 KB datagrams for 5 s from her own process on a machine kept busy;
    alice, in a call of her own, drives and then stops the robot: neither call drops,
    the stop reaches the base, and the robot counts (and tells olga) what it dropped."""
    config = daemon.write_user_config("flooder.toml")
    async with daemon.connect() as alice:
        alice_call = alice.call.id
        assert (await alice.stop()).ok
        await arm(alice)
        with cpu_burners():
            flooder = Process(
                [
                    "flood_proc",
                    "--home",
                    str(daemon.observer_home),
                    "--config",
                    str(config),
                    "--connect",
                    daemon.endpoint,
                    "--robot",
                    ROBOT,
                    "--seconds",
                    str(FLOOD_SECONDS),
                ],
                env=child_env(),
            )
            processes.append(flooder)
            await flooder.wait_event("flooding", timeout=30)
            await drive_far(alice)
            await next_pose(alice, lambda p: abs(p.v) > 0.05, timeout=10)
            ack = await alice.stop()
            acked = time.monotonic()
            assert ack.ok, ack.text
            # Every pose stamped (robot clock) after the acknowledgement shows it at rest.
            after = await next_pose(alice, lambda p: p.t > acked, timeout=5)
            assert still(after), after
            done = await flooder.wait_event("done", timeout=FLOOD_SECONDS + 30)
        # Neither call dropped: the flooder's is the one it started with, and so is alice's.
        assert done["reconnects"] == 0 and done["active"], done
        assert done["call"] == done["first_call"], done
        assert alice.reconnects == 0 and alice.call.id == alice_call and alice.call.active
        assert (await alice.chat("where?")).ok
        # The drops are counted: by the robot, which told the flooding call so.
        assert done["sent"] > 0 and done["rx_dropped"] > 0, done
        print(done)


@pytest.mark.zenoh
@pytest.mark.solo
async def test_forged_frames_on_a_calls_control_key_drop_no_call(
    daemon: Daemon, processes: list[Process]
) -> None:
    """A stranger who sniffed alice's call keys floods the robot's CONTROL key of her call
    with forged frames, 20,000 a second for 5 s, on a machine kept busy by two CPU
    burners: they fail authentication and are refused before they are queued, and her
    heartbeats still get through, so neither side drops the call. (The rig's generous
    call timeout, as for the data flood above: on a machine this loaded a stall of the
    whole process may outlast 0.5 s with no flood at all. That forgeries cannot push a
    heartbeat out of the queue is test_call_keys.py's, exactly.)"""
    async with daemon.connect() as alice:
        call = alice.call.id
        assert (await alice.stop()).ok
        with cpu_burners():
            forger = Process(
                [
                    "flood_proc",
                    "--forge",
                    call,
                    "--user",
                    daemon.driver,
                    "--connect",
                    daemon.endpoint,
                    "--robot",
                    ROBOT,
                    "--rate",
                    "20000",
                    "--seconds",
                    str(FLOOD_SECONDS),
                ],
                env=child_env(),
            )
            processes.append(forger)
            await forger.wait_event("flooding", timeout=30)
            done = await forger.wait_event("done", timeout=FLOOD_SECONDS + 30)
        assert done["sent"] >= 0.5 * 20_000 * FLOOD_SECONDS, done  # it did flood
        assert alice.reconnects == 0 and alice.call.id == call and alice.call.active
        assert (await alice.chat("where?")).ok
        events = []
        while not daemon.events.lines.empty():
            events.append(daemon.events.lines.get_nowait())
        # The robot's side did not drop it either (it would have said "ended").
        assert not [e for e in events if '"ended"' in e and call in e], events


# -- the audit log ---------------------------------------------------------------------------


@pytest.mark.zenoh
async def test_the_audit_log_says_who_did_what_and_what_came_of_it(
    daemon: Daemon, observer: RobotClient
) -> None:
    since = time.monotonic()
    async with daemon.connect() as alice:
        assert (await alice.stop(how="button")).ok
        refused = await alice.chat("fwd 0.2")
        assert not refused.ok
        await arm(alice)
        assert (await alice.chat("fwd 0.2", timeout=30)).ok
        assert (await observer.stop(how="key")).ok
    records = [r for r in daemon.audit() if r["t"] >= since]
    for record in records:
        fields = {"t", "who", "role", "call", "what", "outcome", "detail"}
        assert set(record) == (fields | {"how"} if record["what"] == "stop" else fields)
    # Who stopped, and how: the STOP button, a key (a closed tab would say "tab_closed").
    stops = [(r["who"], r["how"]) for r in records if r["what"] == "stop"]
    assert list(dict.fromkeys(stops)) == [(USER, "button"), (OBSERVER, "key")]  # repeats once
    seen = {(r["who"], r["role"], r["what"].split(":")[0], r["outcome"]) for r in records}
    assert (USER, "driver", "stop", "allowed") in seen
    assert (USER, "driver", "motion", "refused") in seen
    assert (USER, "driver", "rearm", "allowed") in seen
    assert (USER, "driver", "motion", "allowed") in seen
    assert (OBSERVER, "observer", "stop", "allowed") in seen
    motion = next(
        r for r in records if r["what"].startswith("motion") and r["outcome"] == "allowed"
    )
    assert motion["what"] == "motion: fwd 0.2" and motion["call"]
    refusal = next(
        r for r in records if r["what"].startswith("motion") and r["outcome"] == "refused"
    )
    assert "re-arm" in refusal["detail"]
    # In the order they happened.
    assert [r["t"] for r in records] == sorted(r["t"] for r in records)


# -- the daemon itself killed ----------------------------------------------------------------


@pytest.mark.zenoh
async def test_a_killed_daemon_comes_back_disarmed(tmp_path: Path) -> None:
    # The user learns of the kill within the call timeout: the product's, which this is about.
    daemon = Daemon(tmp_path, timeout=TIMEOUT)
    daemon.start()
    try:
        async with daemon.connect() as alice:
            for attempt in range(1, 4):
                try:
                    await arm(alice)
                    await drive_far(alice)
                    await next_pose(alice, lambda p: abs(p.v) > 0.05, timeout=10)
                    break
                except CallEnded:
                    # On a loaded machine the product's 0.5 s can lapse before the kill too:
                    # the client calls back (the robot stays stopped), and this starts again.
                    if attempt == 3:
                        raise
            killed = time.monotonic()
            # The simulated base lives inside the daemon process, so "the base stops" is
            # trivially true here: nothing is left to move it. What can be checked is that
            # the user learns at once, and that a restart does not resume the motion.
            daemon.events.signal(signal.SIGKILL)
            end = await asyncio.wait_for(alice.call.wait_ended(), DEFAULT_LEASE)
            assert end.kind == "dropped"
            assert time.monotonic() - killed <= TIMEOUT + MARGIN
        daemon.stop()
        # The rest is not about timing: a loaded machine must not drop the call.
        daemon.set_timeout(GENEROUS_TIMEOUT)
        daemon.start()  # the same home, so the same audit log
        async with daemon.connect() as alice:
            state = await safety_state(alice, lambda s: s.holder == USER)
            assert not state.armed and state.text == "not armed since start"
            refused = await alice.chat("fwd 0.3")
            assert not refused.ok and refused.code == Reason.NOT_ARMED
            assert "not armed since start" in refused.final_text
            assert still(await alice.pose())
            await arm(alice)
            assert (await alice.chat("fwd 0.3", timeout=30)).ok
        starts = [r for r in daemon.audit() if r["what"] == "start"]
        assert [(r["who"], r["outcome"]) for r in starts] == [("robot", "stopped")] * 2
    finally:
        daemon.stop()


# -- the memory transport at 20 % loss -------------------------------------------------------


REPEATS = 30
LOSS = 0.2


@dataclass
class LossyRobot:
    """A robot (SimNavStack + SafetyDriver + RobotServer) and a user in this process."""

    hub: MemoryHub
    nav: SimNavStack
    safety: SafetyDriver
    client: RobotClient


@pytest.fixture
async def lossy(tmp_path: Path) -> AsyncIterator[LossyRobot]:
    # Not about drop timing: a generous call timeout (and deadman), so that a preempted
    # test process does not drop the call.
    hub = MemoryHub(seed=5)
    settings = CallSettings(timeout=GENEROUS_TIMEOUT)
    async with (
        robot_on_hub(tmp_path, hub, timeout=GENEROUS_TIMEOUT, sim=FAST_SIM) as (nav, safety, _, _),
        MemoryTransport(hub, "user") as transport,
        UserEndpoint(
            transport,
            Identity.load(tmp_path / "user"),
            KnownRobots.load(tmp_path / "user"),
            settings=settings,
        ) as user_endpoint,
    ):
        call = await user_endpoint.call(ROBOT)
        hub.set_link("robot", "user", loss=LOSS)  # both ways, once the call is up
        try:
            yield LossyRobot(hub, nav, safety, RobotClient(call))
        finally:
            hub.set_link("robot", "user", loss=0.0)  # let the hang-up through
            await call.hangup()
            await asyncio.sleep(0.05)


async def test_a_stop_at_20_percent_loss_is_never_lost(
    lossy: LossyRobot, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The arm and the motion before each stop are asked again every 50 ms rather than the
    # client's 300 ms: a lost one (a third of them, at this loss) costs a 20th of a second,
    # not a third. The stop, what is tested here, repeats every 50 ms as ever (STOP_REPEAT).
    monkeypatch.setattr(client_module, "RESEND_AFTER", client_module.STOP_REPEAT)
    client, nav = lossy.client, lossy.nav
    loop = asyncio.get_running_loop()
    stopped = 0
    for i in range(2 * REPEATS):
        if stopped == REPEATS:
            break
        assert (await client.arm(timeout=10)).ok
        # Towards the middle of the corridor, so no run ends at a wall.
        metres = 2 if nav.true_pose.x < 5.0 else -2
        reply = await first_reply(client, f"fwd {metres}", timeout=10)
        assert reply.ok, (i, reply.text)
        if reply.final:
            # The acknowledgement was lost and, on a busy machine, the short move was
            # over before a repeated request was answered: nothing moving to stop.
            continue
        async with asyncio.timeout(5):
            while True:  # polled: the NavStack has no change notification
                if nav.velocity() != Velocity():
                    break
                await asyncio.sleep(0.01)
        sent = loop.time()
        ack = await client.stop(timeout=10)
        took = loop.time() - sent
        assert ack.ok, (i, ack.text)
        # Checked on the NavStack itself, straight after the acknowledgement.
        assert nav.velocity() == Velocity(), i
        assert nav.current_goal() is None and not lossy.safety.supervisor.armed
        # Repeated every 50 ms: 40 rounds lost in a row is absurd.
        assert took < 2.0 + SLACK, (i, took)
        stopped += 1
    assert stopped == REPEATS, f"only {stopped} of {2 * REPEATS} moves were seen moving"
    # The link really was lossy, both ways.
    assert lossy.hub.link_stats("user", "robot").lost > 0
    assert lossy.hub.link_stats("robot", "user").lost > 0
