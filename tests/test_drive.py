"""Driving by hand (the ``drive`` channel, protocol §27): the robot's service on the safety path.

Everything runs on a fast clock (numbers, no sleeping): a simulated robot in an empty room
is stepped with the real safety driver, follow service and drive service in the daemon's
order; the call's channel is a list of what the robot sent.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from telebot.channels.proto.session import CallStats
from telebot.config import DriveSettings, RobotConfig, SimSettings, load_toml
from telebot.errors import ConfigError
from telebot.identity import Role
from telebot.reasons import Reason
from telebot.robot.grid import OccupancyGrid
from telebot.robot.nav import GoalStatus, MotionLimits, Pose2D
from telebot.robot.perception.tracks import PersonTrack
from telebot.robot.sim.stack import SimNavStack
from telebot.robot.sim.world import Obstacle
from telebot.services.drive.follow import FollowService
from telebot.services.drive.robot import CallDrive, DriveService
from telebot.services.drive.wire import (
    DriveCommand,
    DriveState,
    InvalidDriveCommand,
    NotADriveCommand,
    decode_drive_command,
    decode_drive_state,
    seq_newer,
)
from telebot.services.safety.robot import SafetyDriver

DT = 0.05


def open_room() -> OccupancyGrid:
    """A walled empty room 12 m x 10 m."""
    res = 0.05
    data = np.full((200, 240), -1, dtype=np.int8)
    data[10:-10, 10:-10] = 100
    data[14:-14, 14:-14] = 0
    return OccupancyGrid(data, res, 0.0, 0.0)


@dataclass
class FakeCall:
    """What the safety driver and the drive service read of a call."""

    id: str
    peer: str
    role: Role
    last_heard: float = 0.0
    stats: CallStats = field(default_factory=lambda: CallStats(rtt=0.002))
    end: None = None
    active: bool = True
    channels: dict[str, FakeChannel] = field(default_factory=dict)

    def channel(self, name: str, **_: Any) -> FakeChannel:
        self.channels[name] = FakeChannel(name)
        return self.channels[name]


@dataclass
class _Stats:
    rejected: int = 0


class FakeChannel:
    """Records what is sent; ``receive`` hands a payload to the service's callback."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.sent: list[str] = []
        self.stats = _Stats()
        self.callback: Any = None

    def set_callback(self, callback: Any) -> None:
        self.callback = callback

    def send(self, payload: str) -> None:
        self.sent.append(payload)

    def receive(self, payload: str | bytes) -> None:
        @dataclass
        class Datagram:
            payload: str | bytes

        self.callback(Datagram(payload))


class Rig:
    """A simulated robot with the real supervisor, follow and drive services, fast clock."""

    def __init__(self, *, supervisor: bool = True) -> None:
        self.clock = 0.0
        self.nav = SimNavStack(open_room(), {}, SimSettings(), start=Pose2D(3.0, 5.0, 0.0))
        self.safety = (
            SafetyDriver(self.nav, timeout=0.5, max_speed=0.5, clock=lambda: self.clock)
            if supervisor
            else None
        )
        self.follow = FollowService(
            self.nav,
            people=None,
            safety_state=self.safety.state if self.safety is not None else None,
        )
        self.drive = DriveService(self.nav, DriveSettings(), safety=self.safety, follow=self.follow)
        if self.safety is not None:
            self.safety.on_state = lambda state: self.drive.safety_changed(state, self.clock)
        self.calls: dict[str, tuple[FakeCall, CallDrive]] = {}
        self.heartbeats = True
        self.seq = 100

    def now(self) -> float:
        return self.clock

    def join(self, call_id: str = "c1", role: Role = Role.DRIVER) -> CallDrive:
        call = FakeCall(call_id, f"user-{call_id}", role, last_heard=self.clock)
        if self.safety is not None:
            self.safety.join(call)  # type: ignore[arg-type]
        service = CallDrive(self.drive, call, self.now)  # type: ignore[arg-type]
        self.calls[call_id] = (call, service)
        return service

    def arm(self, call_id: str = "c1") -> None:
        assert self.safety is not None
        self.step()
        assert self.safety.gate(call_id).rearm() is None

    def send(
        self, linear: float, angular: float = 0.0, call_id: str = "c1", seq: int | None = None
    ) -> None:
        if seq is None:
            self.seq += 1
            seq = self.seq
        self.sent_at = self.clock
        payload = DriveCommand(seq, linear, angular).encode()
        self.calls[call_id][0].channels["drive"].receive(payload)

    def raw(self, payload: str | bytes, call_id: str = "c1") -> None:
        self.calls[call_id][0].channels["drive"].receive(payload)

    def step(self) -> None:
        self.clock += DT
        if self.heartbeats:
            for call, _ in self.calls.values():
                call.last_heard = self.clock
        self.nav.step(self.clock)
        if self.safety is not None:
            self.safety.tick()  # the supervisor first, as in RobotServer.run
        self.follow.tick(self.clock)
        self.drive.tick(self.clock)
        for _, service in self.calls.values():
            service.tick(self.clock)

    def hold(
        self, linear: float, angular: float = 0.0, seconds: float = 1.0, call_id: str = "c1"
    ) -> None:
        """The user holds a key: a command every step (20 Hz)."""
        for _ in range(round(seconds / DT)):
            self.send(linear, angular, call_id)
            self.step()

    def states(self, call_id: str = "c1") -> list[DriveState]:
        return [decode_drive_state(p) for p in self.calls[call_id][0].channels["drive"].sent]

    def last(self, call_id: str = "c1") -> DriveState:
        return self.states(call_id)[-1]


def audited(rig: Rig) -> list[Any]:
    """Collect the audit records of ``rig`` from now on."""
    records: list[Any] = []
    assert rig.safety is not None
    rig.safety.on_audit = records.append
    return records


# -- the wire format ------------------------------------------------------------------------


def test_commands_and_states_round_trip_and_seq_is_serial() -> None:
    command = DriveCommand(41, 0.3, -0.5)
    assert json.loads(command.encode()) == {
        "type": "drive",
        "seq": 41,
        "linear": 0.3,
        "angular": -0.5,
    }
    assert decode_drive_command(command.encode()) == command
    assert DriveCommand(1, 0, 0).release and not command.release
    state = DriveState(41, True, Reason.OK, "", 0.3, -0.5, 0.42)
    assert json.loads(state.encode()) == {
        "type": "drive_state",
        "seq": 41,
        "active": True,
        "code": "ok",
        "reason": "",
        "linear": 0.3,
        "angular": -0.5,
        "cap": 0.42,
    }
    assert decode_drive_state(state.encode()) == state
    assert seq_newer(5, 4) and not seq_newer(4, 5) and not seq_newer(4, 4)
    assert seq_newer(0, 2**32 - 1) and not seq_newer(2**32 - 1, 0)


@pytest.mark.parametrize(
    ("payload", "says"),
    [
        ("not json at all " + "x" * 500, "not JSON"),
        ("[1, 2]", "JSON object"),
        ('{"seq": 1, "linear": 0, "angular": 0}', "'type' is missing"),
        ('{"type": 7, "seq": 1, "linear": 0, "angular": 0}', "'type' must be"),
        ('{"type": "drive", "linear": 0, "angular": 0}', "'seq'"),
        ('{"type": "drive", "seq": -1, "linear": 0, "angular": 0}', "'seq'"),
        ('{"type": "drive", "seq": 1.5, "linear": 0, "angular": 0}', "'seq'"),
        ('{"type": "drive", "seq": 1, "angular": 0}', "'linear'"),
        ('{"type": "drive", "seq": 1, "linear": "fast", "angular": 0}', "'linear'"),
        ('{"type": "drive", "seq": 1, "linear": 1e999, "angular": 0}', "'linear'"),
        ('{"type": "drive", "seq": 1, "linear": 0, "angular": true}', "'angular'"),
    ],
)
def test_bad_commands_are_one_line_naming_what_is_wrong(payload: str, says: str) -> None:
    with pytest.raises(InvalidDriveCommand) as caught:
        decode_drive_command(payload)
    text = str(caught.value)
    assert says in text and "\n" not in text and len(text) < 140


def test_other_message_types_are_not_commands() -> None:
    with pytest.raises(NotADriveCommand):
        decode_drive_command('{"type": "drive_state", "seq": 1}')


# -- the robot's service ----------------------------------------------------------------------


def test_driving_needs_an_armed_robot_and_the_drive() -> None:
    rig = Rig()
    rig.join("c1")
    rig.join("c2")  # a second driver: an observer while c1 holds the drive
    rig.join("c3", Role.OBSERVER)
    rig.step()
    rig.send(0.3)
    assert rig.last().code == Reason.NOT_ARMED and not rig.last().active
    rig.send(0.3, call_id="c2")
    assert rig.last("c2").code == Reason.NOT_HOLDER
    rig.send(0.3, call_id="c3")
    assert rig.last("c3").code == Reason.OBSERVER
    rig.hold(0.3, seconds=0.5, call_id="c3")
    assert rig.nav.velocity().linear == 0.0 and rig.drive.driver is None
    rig.arm()
    rig.hold(0.3, seconds=1.0)
    assert rig.last().active and rig.last().code == Reason.OK
    assert rig.nav.velocity().linear > 0.2


def test_a_held_refused_key_is_not_audited_twenty_times_a_second() -> None:
    rig = Rig()
    rig.join("c1")
    records = audited(rig)
    rig.hold(0.3, seconds=2.0)
    refused = [r for r in records if r.what == "motion: drive by hand"]
    assert 1 <= len(refused) <= 3
    assert all(r.outcome == "refused" for r in refused)


def test_start_and_end_are_audited_not_each_command() -> None:
    rig = Rig()
    rig.join("c1")
    rig.arm()
    records = audited(rig)
    rig.hold(0.3, seconds=1.0)
    rig.send(0.0)
    rig.step()
    drives = [(r.what, r.outcome) for r in records if "drive by hand" in r.what]
    assert drives == [("motion: drive by hand", "allowed"), ("drive by hand: end", "noted")]
    assert "released" in records[-1].detail


def test_speeds_are_clamped_to_the_robot_s_limits_and_the_speed_cap() -> None:
    rig = Rig()
    call = rig.join("c1")
    rig.arm()
    rig.hold(5.0, 9.0, seconds=0.3)
    state = rig.last()
    assert (
        state.active and state.linear == pytest.approx(0.5) and state.angular == pytest.approx(1.0)
    )
    # A slow link lowers the supervisor's cap: the commanded speed follows it.
    rig.calls["c1"][0].stats = CallStats(rtt=0.25)
    rig.hold(5.0, 0.0, seconds=2.0)
    assert rig.safety is not None
    cap = rig.safety.state().cap
    assert 0.05 < cap < 0.4
    assert rig.drive.commanded[0] <= cap + 1e-9
    assert rig.nav.velocity().linear <= cap + 0.01
    states = rig.states()
    assert states[-1].cap <= cap + 0.01
    assert call.seq == rig.seq


def test_no_fresh_command_for_stale_after_stops_the_robot_not_latched() -> None:
    rig = Rig()
    rig.join("c1")
    rig.arm()
    rig.hold(0.4, seconds=1.5)
    assert rig.nav.velocity().linear > 0.3
    while rig.drive.driver is not None:
        rig.step()
        assert rig.clock - rig.sent_at < 1.0
    # Stopped stale_after (0.3 s) after the last command, within a control cycle.
    assert 0.3 - 1e-9 <= rig.clock - rig.sent_at <= 0.3 + DT + 1e-9
    assert rig.last().code == Reason.STALE and not rig.last().active
    for _ in range(5):
        rig.step()
    assert rig.nav.velocity().linear == 0.0
    assert rig.safety is not None and rig.safety.state().armed  # not latched
    rig.hold(0.3, seconds=0.5)  # the key again: it drives again
    assert rig.last().active and rig.nav.velocity().linear > 0.1


def test_release_stops_at_once_without_latching() -> None:
    rig = Rig()
    rig.join("c1")
    rig.arm()
    rig.hold(0.5, seconds=1.5)
    assert rig.nav.velocity().linear > 0.4
    rig.send(0.0, 0.0)
    assert rig.last().code == Reason.RELEASED and not rig.last().active
    rig.step()
    assert rig.nav.velocity().linear == 0.0  # within one control cycle, not braking
    assert rig.safety is not None and rig.safety.state().armed
    rig.hold(0.3, seconds=0.5)
    assert rig.last().active and rig.last().code == Reason.OK


def test_a_reordered_old_command_never_undoes_a_newer_one() -> None:
    rig = Rig()
    call = rig.join("c1")
    rig.arm()
    rig.send(0.4, seq=10)
    rig.step()
    rig.send(0.0, seq=11)  # released …
    rig.send(0.4, seq=10)  # … and an old command arrives late: ignored
    rig.send(0.4, seq=9)
    for _ in range(3):
        rig.step()
    assert rig.drive.driver is None and rig.nav.velocity().linear == 0.0
    assert call.seq == 11 and call.dropped == 2
    # Wrapping round 2**32 is newer.
    rig.send(0.3, seq=2**31)
    rig.send(0.3, seq=2**32 - 1)
    rig.send(0.3, seq=0)
    assert call.seq == 0 and rig.drive.driver is call


def test_a_goal_ends_driving_and_driving_cancels_a_goal() -> None:
    rig = Rig()
    rig.join("c1")
    rig.arm()
    rig.hold(0.3, seconds=0.5)
    goal = rig.nav.navigate_to(8.0, 5.0)
    rig.step()
    assert rig.last().code == Reason.REPLACED and rig.drive.driver is None
    assert goal.status is GoalStatus.ACTIVE
    # The tail of the held key does not take over again: the user must let go first.
    rig.hold(0.3, seconds=0.2)
    assert goal.status is GoalStatus.ACTIVE and rig.drive.driver is None
    rig.send(0.0)
    rig.hold(0.3, seconds=0.3)  # a new press: driving replaces the goal
    assert goal.status is GoalStatus.CANCELLED and goal.code == Reason.REPLACED
    assert rig.last().active


def test_a_release_just_after_a_goal_leaves_the_goal_running() -> None:
    rig = Rig()
    rig.join("c1")
    rig.arm()
    rig.hold(0.3, seconds=0.5)
    goal = rig.nav.navigate_to(8.0, 5.0)  # before the next control cycle …
    rig.send(0.0)  # … the key is let go
    assert rig.last().code == Reason.REPLACED
    rig.step()
    assert goal.status is GoalStatus.ACTIVE


def test_a_follow_ends_driving_and_driving_ends_a_follow() -> None:
    rig = Rig()
    rig.join("c1")
    rig.arm()

    class People:
        def tracks(self) -> list[PersonTrack]:
            return [PersonTrack(1, 4.5, 5.0, 0.0, 0.0, 1.0, 0.0, rig.clock, frozenset({"laser"}))]

    rig.follow.people = People()
    rig.hold(0.2, seconds=0.3)
    started = rig.follow.start("c1", None, rig.clock)
    assert not isinstance(started, type(None)) and rig.follow.goal is not None
    rig.step()
    assert rig.last().code == Reason.REPLACED and rig.drive.driver is None
    rig.send(0.0)
    rig.hold(0.3, seconds=0.2)
    assert rig.follow.goal is None and rig.last().active
    assert started.status is GoalStatus.CANCELLED  # type: ignore[union-attr]


@pytest.mark.parametrize("how", ["key", "chat", "deadman", "release_drive", "hangup"])
def test_any_stop_ends_driving_and_the_robot_stays_stopped(how: str) -> None:
    rig = Rig()
    call = rig.join("c1")
    rig.arm()
    rig.hold(0.5, seconds=1.0)
    assert rig.nav.velocity().linear > 0.3
    assert rig.safety is not None
    if how == "key":
        rig.safety.gate("c1").stop(how="key")
    elif how == "chat":
        rig.safety.gate("c1").stop("stop requested", how="chat")
    elif how == "deadman":
        rig.heartbeats = False
        for _ in range(12):
            rig.send(0.5)  # commands that never arrive count for nothing: only the link
            rig.step()
    elif how == "release_drive":
        rig.safety.gate("c1").release()
    else:
        call.close()
    if how != "hangup":
        assert rig.last().code == Reason.STOPPED and not rig.last().active
    assert rig.drive.driver is None
    rig.heartbeats = True
    for _ in range(10):
        if how != "hangup":
            rig.send(0.5)
        rig.step()
        assert rig.drive.driver is None
    assert rig.nav.velocity().linear == 0.0


def test_invalid_messages_are_answered_and_stop_driving() -> None:
    rig = Rig()
    call = rig.join("c1")
    rig.arm()
    rig.hold(0.4, seconds=1.0)
    assert rig.last().active
    rig.raw('{"type": "drive", "seq": 1000, "linear": "' + "A" * 5000 + '", "angular": 0}')
    state = rig.last()
    assert state.code == Reason.INVALID and not state.active and "'linear'" in state.text
    rig.step()
    assert rig.nav.velocity().linear == 0.0 and rig.drive.driver is None
    assert rig.safety is not None and rig.safety.state().armed  # not latched
    for garbage in (b"\x00\xff", "A" * 100_000, "[]", "{", '{"type": null}'):
        rig.raw(garbage)
        assert rig.last().code == Reason.INVALID and len(rig.last().text) < 200
    before = len(rig.states())
    rig.raw('{"type": "hello"}')  # another type: dropped and counted, not answered
    assert len(rig.states()) == before and call.dropped == 1
    rig.hold(0.3, seconds=0.3)
    assert rig.last().active


def test_driving_into_an_obstacle_stops_before_it_and_turning_stays_allowed() -> None:
    rig = Rig()
    rig.join("c1")
    rig.arm()
    rig.nav.add_obstacle(Obstacle(4.5, 5.0, 0.2))
    for _ in range(60):
        rig.send(0.5)
        rig.step()
    pose = rig.nav.true_pose
    assert pose.x < 4.5 - 0.2 - 0.25  # never touched it
    assert rig.nav.collisions == 0
    assert rig.last().code == Reason.OBSTACLE and rig.last().active
    assert rig.nav.velocity().linear == 0.0
    rig.hold(0.0, 1.0, seconds=0.5)  # turning on the spot away from it
    assert rig.last().code == Reason.OK and rig.nav.velocity().angular > 0.3


@dataclass
class Scan:
    angles: Any
    ranges: Any
    range_max: float = 10.0


class LaserBase:
    """A base with a laser and no obstacle guard of its own: what the drive service does
    is all that keeps it off an obstacle."""

    def __init__(self, ahead: float, rear_view: bool = True) -> None:
        angles = np.linspace(-np.pi, np.pi, 360, endpoint=False)
        ranges = np.full(360, np.inf)
        ranges[np.abs(angles) < 0.05] = ahead  # a wall straight ahead at ``ahead`` m
        behind = np.abs(angles) > np.pi - 0.3
        # A wall 5 m behind, or a masked-off sector that brings nothing back.
        ranges[behind] = 5.0 if rear_view else np.nan
        self.scan = Scan(angles, ranges)
        self.speed_limit = 0.5
        self.motion_limits = MotionLimits()
        self.commands: list[tuple[float, float]] = []

    def laser_scan(self) -> Scan:
        return self.scan

    def drive(self, linear: float, angular: float) -> None:
        self.commands.append((linear, angular))

    def stop(self) -> None:
        self.commands.append((0.0, 0.0))

    def current_goal(self) -> None:
        return None

    def status(self) -> Any:
        from telebot.robot.nav import NavState, NavStatus

        return NavStatus(NavState.IDLE)


@pytest.mark.parametrize(
    ("ahead", "code"),
    [
        (5.0, Reason.OK),  # far: the speed asked for
        (0.45, Reason.OK),  # near: only what it can brake from in the room left
        (0.3, Reason.OBSTACLE),  # within the braking margin: no driving ahead
    ],
)
def test_with_a_laser_it_brakes_before_what_it_sees(ahead: float, code: str) -> None:
    nav = LaserBase(ahead)

    drive = DriveService(nav)  # type: ignore[arg-type]
    call = FakeCall("c1", "alice", Role.DRIVER)
    CallDrive(drive, call, lambda: 0.0)  # type: ignore[arg-type]
    call.channels["drive"].receive(DriveCommand(1, 0.4, 0.5).encode())
    sent, turn = nav.commands[-1]
    if ahead > 1:
        assert sent == pytest.approx(0.4)
    elif code == Reason.OK:
        assert 0.0 < sent < 0.4  # slowed down
    else:
        assert sent == 0.0
    assert turn == 0.5  # turning stays allowed
    state = decode_drive_state(call.channels["drive"].sent[-1])
    assert state.active and state.code == code
    # Reversing: allowed where the laser sees free space behind, never blind.
    call.channels["drive"].receive(DriveCommand(2, -0.2, 0.0).encode())
    assert nav.commands[-1][0] == pytest.approx(-0.2)
    blind = LaserBase(5.0, rear_view=False)
    drive.nav = blind  # type: ignore[assignment]
    call.channels["drive"].receive(DriveCommand(3, -0.2, 0.0).encode())
    assert blind.commands[-1][0] == 0.0
    assert decode_drive_state(call.channels["drive"].sent[-1]).code == Reason.OBSTACLE


def test_without_a_supervisor_observers_are_refused_by_role() -> None:
    rig = Rig(supervisor=False)
    rig.join("c1", Role.OBSERVER)
    rig.hold(0.3, seconds=0.3)
    assert rig.last().code == Reason.OBSERVER and rig.nav.velocity().linear == 0.0
    rig.join("c2")
    rig.hold(0.3, seconds=0.5, call_id="c2")
    assert rig.last("c2").active and rig.nav.velocity().linear > 0.1


def test_the_drive_state_repeats_at_5_hz_while_active() -> None:
    rig = Rig()
    rig.join("c1")
    rig.arm()
    rig.hold(0.3, seconds=2.0)
    active = [s for s in rig.states() if s.active]
    assert 8 <= len(active) <= 12  # 2 s at 5 Hz, plus the first
    assert active[-1].seq == rig.seq


def test_a_state_that_ends_driving_is_sent_three_times_then_no_more() -> None:
    """The lane is lossy: one lost ``released`` must not leave the page saying "driving"."""
    rig = Rig()
    rig.join("c1")
    rig.arm()
    rig.hold(0.3, seconds=0.5)
    before = len(rig.states())
    rig.send(0.0, 0.0)
    for _ in range(round(2.0 / DT)):
        rig.step()
    ended = rig.states()[before:]
    assert [s.code for s in ended] == [Reason.RELEASED] * 3
    assert len({s.seq for s in ended}) == 1 and not any(s.active for s in ended)


def test_the_drive_config_section(tmp_path: Path) -> None:
    assert RobotConfig().drive.stale_after == 0.3
    path = tmp_path / "robot.toml"
    path.write_text("[drive]\nstale_after = 0\n")
    with pytest.raises(ConfigError, match="stale_after"):
        load_toml(path, RobotConfig)
