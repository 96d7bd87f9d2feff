"""The safety supervisor: every rule with explicit times, then a stateful Hypothesis model."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule

from telebot.errors import ConfigError
from telebot.identity import Role
from telebot.reasons import Reason
from telebot.safety import (
    CAP_STEP,
    LOCAL,
    NAVCAM,
    WATCHING_WINDOW,
    Action,
    Audit,
    AuditRecord,
    Decision,
    SafetySupervisor,
    SelectCamera,
    SetSpeedCap,
    StateChanged,
    Stop,
)

TIMEOUT = 0.5
MAX = 0.5
RTT = 0.01


def stops(actions: Sequence[Action]) -> list[Stop]:
    return [a for a in actions if isinstance(a, Stop)]


def audits(actions: Sequence[Action]) -> list[AuditRecord]:
    return [a.record for a in actions if isinstance(a, Audit)]


def caps(actions: Sequence[Action]) -> list[float]:
    return [a.linear for a in actions if isinstance(a, SetSpeedCap)]


def beat(
    sup: SafetySupervisor, call: str, now: float, rtt: float | None = RTT, loss: float = 0.0
) -> list[Action]:
    return sup.heartbeat(call, now, rtt=rtt, loss=loss)


def supervisor(**kwargs: float | bool) -> SafetySupervisor:
    sup = SafetySupervisor(now=0.0, **kwargs)  # type: ignore[arg-type]
    sup.tick(0.0)  # take the start-up actions out of the way
    return sup


def driving(now: float = 1.0, **kwargs: float | bool) -> SafetySupervisor:
    """Alice joined as driver, her link is fresh, and she re-armed the robot."""
    sup = supervisor(**kwargs)
    sup.join("a", "alice", Role.DRIVER, now)
    beat(sup, "a", now)
    assert sup.rearm("a", now).allowed
    return sup


# -- start and latch ---------------------------------------------------------------------


def test_starts_disarmed_and_its_first_actions_stop_the_robot() -> None:
    sup = SafetySupervisor(now=5.0)
    assert not sup.armed
    assert sup.stop_reason == "not armed since start"
    assert sup.holder is None and sup.speed_cap(5.0) == 0.0
    first = sup.join("a", "alice", Role.DRIVER, 5.0)
    # Whatever the NavStack was doing before a (re)start, it stops, and with a zero cap.
    assert isinstance(first[0], Stop)
    assert caps(first) == [0.0]
    assert [r.what for r in audits(first)] == ["start", "join"]
    again = sup.tick(5.1)
    assert stops(again) == [] and caps(again) == []


def test_motion_is_refused_until_the_holder_rearms() -> None:
    sup = supervisor()
    sup.join("a", "alice", Role.DRIVER, 1.0)
    beat(sup, "a", 1.0)
    refused = sup.request_motion("a", 1.0, "fwd 2")
    assert not refused.allowed
    assert refused.code == Reason.NOT_ARMED and "not armed since start" in refused.text
    assert not any(isinstance(a, SelectCamera) for a in refused.actions)
    rearmed = sup.rearm("a", 1.0)
    assert rearmed.allowed and sup.armed
    # Re-arming starts nothing: no camera switch, no motion, just the cap and the news.
    assert caps(rearmed.actions) == [MAX]
    assert not stops(rearmed.actions)
    assert any(isinstance(a, StateChanged) and a.state.armed for a in rearmed.actions)
    assert sup.request_motion("a", 1.0, "fwd 2").allowed


def test_navcam_is_selected_when_motion_is_allowed_and_only_when_needed() -> None:
    sup = driving()
    first = sup.request_motion("a", 1.0, "fwd 1")
    assert SelectCamera(NAVCAM) in first.actions
    second = sup.request_motion("a", 1.0, "fwd 1")
    assert SelectCamera(NAVCAM) not in second.actions
    assert sup.request_camera("a", "usercam", False, 1.0).allowed
    third = sup.request_motion("a", 1.0, "turn 90")
    assert SelectCamera(NAVCAM) in third.actions


def test_only_the_holder_may_rearm() -> None:
    sup = supervisor()
    sup.join("a", "alice", Role.DRIVER, 1.0)
    sup.join("b", "bob", Role.DRIVER, 1.0)
    sup.join("o", "olga", Role.OBSERVER, 1.0)
    for call in "abo":
        beat(sup, call, 1.0)
    assert sup.holder == "alice" and sup.holder_call == "a"
    bob = sup.rearm("b", 1.0)
    assert not bob.allowed and bob.code == Reason.NOT_HOLDER
    assert bob.text == "the drive is held by alice"
    olga = sup.rearm("o", 1.0)
    assert not olga.allowed and olga.code == Reason.OBSERVER
    assert not sup.rearm("x", 1.0).allowed
    assert not sup.armed
    assert sup.rearm("a", 1.0).allowed


def test_rearm_needs_a_live_link() -> None:
    sup = supervisor()
    sup.join("a", "alice", Role.DRIVER, 1.0)
    refused = sup.rearm("a", 1.0 + TIMEOUT)
    assert not refused.allowed and refused.code == Reason.LINK_SILENT and not sup.armed


def test_observers_are_refused_everything_but_stop() -> None:
    sup = driving()
    sup.join("o", "olga", Role.OBSERVER, 1.0)
    beat(sup, "o", 1.0)
    for decision in (
        sup.request_motion("o", 1.0, "fwd 1"),
        sup.request_camera("o", "usercam", False, 1.0),
        sup.rearm("o", 1.0),
        sup.take_drive("o", 1.0),
        sup.release_drive("o", 1.0),
    ):
        assert not decision.allowed and decision.code == Reason.OBSERVER
        assert not stops(decision.actions)
    assert sup.armed
    stop = sup.request_stop("o", 1.0)
    assert stop.allowed and stops(stop.actions) and not sup.armed
    assert sup.stop_reason == "stop requested by olga"


def test_stop_is_idempotent_and_latches() -> None:
    sup = driving()
    first = sup.request_stop("a", 1.1, "stop key")
    assert first.allowed and not sup.armed
    assert first.actions[0] == Stop("stop key by alice")
    assert caps(first.actions) == [0.0]
    # A repeated stop stops again (nothing is lost by it) and changes nothing else.
    second = sup.request_stop("a", 1.2)
    assert second.allowed and stops(second.actions) == [Stop("stop requested by alice")]
    assert not any(isinstance(a, StateChanged) for a in second.actions)
    assert caps(second.actions) == []
    assert sup.stop_reason == "stop key by alice"
    assert "already stopped" in second.audit.detail
    # Latched: time and fresh heartbeats do not restart anything.
    for t in (1.3, 1.4, 2.0):
        beat(sup, "a", t)
        assert not stops(sup.tick(t)) and not sup.armed and sup.speed_cap(t) == 0.0
    assert not sup.request_motion("a", 2.0, "fwd 1").allowed
    assert sup.rearm("a", 2.0).allowed


@pytest.mark.parametrize("how", ["button", "key", "tab_closed", "chat"])
def test_a_stop_records_who_stopped_and_how(how: str) -> None:
    sup = driving()
    stop = sup.request_stop("a", 1.1, how=how)
    assert stop.actions[0] == Stop(f"stop requested by alice ({how})")
    assert sup.stop_reason == f"stop requested by alice ({how})"
    assert stop.audit.who == "alice" and stop.audit.how == how
    assert json.loads(stop.audit.to_json())["how"] == how
    # Records of other kinds carry no "how" at all.
    assert "how" not in json.loads(sup.rearm("a", 1.2).audit.to_json())


def test_stops_from_the_robot_itself_and_from_unknown_calls_are_honoured() -> None:
    sup = driving()
    local = sup.request_stop(None, 1.0, "SIGTERM")
    assert local.allowed and stops(local.actions) and local.audit.who == LOCAL
    assert sup.stop_reason == "SIGTERM by robot"
    sup.rearm("a", 1.0)
    # An unknown call id is a bookkeeping fault; refusing its stop would never be safer.
    ghost = sup.request_stop("ghost", 1.0)
    assert ghost.allowed and stops(ghost.actions) and not sup.armed
    assert ghost.audit.who == "unknown call ghost"


@pytest.mark.parametrize(("how", "words"), [("hung_up", "hung up"), ("dropped", "dropped")])
def test_the_holder_leaving_stops_latches_and_frees_the_drive(how: str, words: str) -> None:
    sup = driving()
    actions = sup.leave("a", how, 1.2)  # type: ignore[arg-type]
    assert isinstance(actions[0], Stop) and actions[0].text == f"driver alice {words}"
    assert not sup.armed and sup.holder is None and sup.participant("a") is None
    record = audits(actions)[-1]
    assert record.who == "alice" and record.outcome == "stopped"


def test_an_observer_leaving_does_not_stop() -> None:
    sup = driving()
    sup.join("o", "olga", Role.OBSERVER, 1.0)
    actions = sup.leave("o", "dropped", 1.1)
    assert not stops(actions) and sup.armed
    assert audits(actions)[-1].outcome == "noted"


def test_deadman_fires_at_the_timeout_and_not_before() -> None:
    sup = driving(now=1.0)
    beat(sup, "a", 1.0, rtt=0.0)
    before = sup.tick(1.0 + TIMEOUT - 1e-6)
    assert not stops(before) and sup.armed and sup.speed_cap(1.0 + TIMEOUT - 1e-6) > 0
    at = sup.tick(1.0 + TIMEOUT)
    reason = "driver alice's link lost: silent 0.50 s (deadman)"
    assert isinstance(at[0], Stop) and at[0].text == reason
    assert sup.state().code == Reason.LINK_SILENT and sup.stop_code == Reason.LINK_SILENT
    assert not sup.armed and sup.speed_cap(1.0 + TIMEOUT) == 0.0 and sup.state().cap == 0.0
    # The cap announced just before was already rounded down to 0.
    assert caps(before) == [0.0] and caps(at) == []
    assert audits(at)[-1].what == "deadman" and audits(at)[-1].outcome == "stopped"
    # The holder keeps the drive (the call may come back): it must re-arm.
    assert sup.holder == "alice"
    beat(sup, "a", 1.6)
    assert not sup.request_motion("a", 1.6, "fwd 1").allowed
    assert sup.rearm("a", 1.6).allowed


def test_a_late_heartbeat_does_not_hide_a_missed_deadman() -> None:
    sup = driving(now=1.0)
    # No tick came in time (a busy loop): the next event, a heartbeat, still latches.
    actions = beat(sup, "a", 1.7)
    assert stops(actions) and not sup.armed


def test_a_call_that_reappears_after_a_drop_stays_disarmed() -> None:
    sup = driving()
    sup.request_motion("a", 1.0, "goto lab")
    sup.leave("a", "dropped", 1.5)
    back = sup.join("a2", "alice", Role.DRIVER, 2.0)
    beat(sup, "a2", 2.0)
    assert sup.holder == "alice" and not sup.armed
    assert not any(isinstance(a, SelectCamera) for a in back)
    for t in (2.0, 2.1, 3.0):
        beat(sup, "a2", t)
        assert not sup.tick(t) or not sup.armed
        assert sup.speed_cap(t) == 0.0
    assert not sup.request_motion("a2", 3.0, "goto lab").allowed


def test_a_call_replaced_by_its_client_s_next_one_hands_over_the_drive_stopped() -> None:
    # Alice's link failed one way: her client called again while her old call lingers
    # here (not yet timed out), and the robot was moving on the old call.
    sup = driving()
    assert sup.request_motion("a", 1.0, "goto lab").allowed
    sup.join("b", "bob", Role.DRIVER, 1.0)
    actions = sup.join("a2", "alice", Role.DRIVER, 1.1, replaces="a")
    # Fail safe: the robot stops and latches; the new call holds the drive, disarmed.
    assert isinstance(actions[0], Stop) and not sup.armed
    assert sup.stop_reason == "driver alice called again (the old call is replaced)"
    assert sup.holder_call == "a2" and sup.holder == "alice"
    assert [p.call_id for p in sup.participants()] == ["b", "a2"]
    (record,) = audits(actions)
    assert (record.who, record.what, record.outcome) == ("alice", "join", "stopped")
    assert "replaces call a" in record.detail and "holds the drive" in record.detail
    # Nothing moves until the new call re-arms (its link measured first).
    assert sup.request_motion("a2", 1.1, "goto lab").code == Reason.NOT_ARMED
    beat(sup, "a2", 1.2)
    assert sup.rearm("a2", 1.2).allowed and sup.request_motion("a2", 1.2, "goto lab").allowed
    # The old call's end, when the robot notices it, is only noted: it drives nothing now.
    ended = sup.leave("a", "dropped", 1.5)
    assert not stops(ended) and sup.armed and sup.holder_call == "a2"
    assert [(r.what, r.outcome, r.detail) for r in audits(ended)] == [
        ("drop", "noted", "replaced by call a2")
    ]
    # Only the same user's call is replaced: bob naming alice's call replaces nothing.
    sup.join("b2", "bob", Role.DRIVER, 1.6, replaces="a2")
    assert sup.holder_call == "a2" and sup.armed


def test_replacing_a_call_that_did_not_drive_changes_nothing_of_the_drive() -> None:
    sup = driving()
    sup.join("b", "bob", Role.DRIVER, 1.0)
    actions = sup.join("b2", "bob", Role.DRIVER, 1.1, replaces="b")
    assert not stops(actions) and sup.armed and sup.holder_call == "a"
    assert [p.call_id for p in sup.participants()] == ["a", "b2"]
    assert not stops(sup.leave("b", "dropped", 1.2)) and sup.armed


def test_a_user_s_second_call_observes_and_may_take_the_drive_from_the_first() -> None:
    sup = driving()
    sup.join("a2", "alice", Role.DRIVER, 1.0)  # another client of alice's (no replaces)
    beat(sup, "a2", 1.0)
    assert sup.holder_call == "a" and sup.armed
    refused = sup.request_motion("a2", 1.0, "goto lab")
    assert refused.code == Reason.NOT_HOLDER
    assert refused.text.startswith("your other call holds the drive")
    taken = sup.take_drive("a2", 1.1)
    assert taken.allowed and isinstance(taken.actions[0], Stop) and not sup.armed
    assert sup.holder_call == "a2" and "taken from alice's call a" in taken.audit.detail
    assert sup.stop_reason == "alice took the drive to another call"
    assert sup.rearm("a2", 1.1).allowed


def test_an_admin_takeover_stops_and_latches() -> None:
    sup = driving()
    sup.join("z", "zoe", Role.ADMIN, 1.0)
    sup.join("b", "bob", Role.DRIVER, 1.0)
    beat(sup, "z", 1.0)
    refused = sup.take_drive("b", 1.0)
    assert not refused.allowed and refused.code == Reason.DRIVE_HELD
    assert refused.text.startswith("the drive is held by alice")
    taken = sup.take_drive("z", 1.1)
    assert taken.allowed and taken.audit.detail == "taken over from alice"
    assert isinstance(taken.actions[0], Stop) and not sup.armed
    assert sup.holder == "zoe" and sup.state().holder_role is Role.ADMIN
    lost = sup.request_motion("a", 1.1, "fwd 1")
    assert not lost.allowed and lost.text == "the drive is held by zoe"
    assert sup.rearm("z", 1.1).allowed and sup.request_motion("z", 1.1, "fwd 1").allowed


def test_release_stops_and_frees_the_drive_for_another_driver() -> None:
    sup = driving()
    sup.join("b", "bob", Role.DRIVER, 1.0)
    assert not sup.release_drive("b", 1.0).allowed
    released = sup.release_drive("a", 1.1)
    assert released.allowed and stops(released.actions)
    assert not sup.armed and sup.holder is None
    free = sup.request_motion("b", 1.1, "fwd 1")
    assert not free.allowed and free.code == Reason.NOT_HOLDER
    assert sup.take_drive("b", 1.2).allowed and sup.holder == "bob" and not sup.armed
    assert sup.take_drive("b", 1.2).text == "already yours"


def test_usercam_while_moving_is_refused_unless_configured() -> None:
    sup = driving()
    refused = sup.request_camera("a", "usercam", True, 1.0)
    assert not refused.allowed and refused.code == Reason.CAMERA_WHILE_MOVING
    assert not any(isinstance(a, SelectCamera) for a in refused.actions)
    assert sup.request_camera("a", NAVCAM, True, 1.0).allowed
    still = sup.request_camera("a", "usercam", False, 1.0)
    assert still.allowed and SelectCamera("usercam") in still.actions
    relaxed = driving(usercam_while_moving=True)
    assert relaxed.request_camera("a", "usercam", True, 1.0).allowed


def test_speed_cap_shrinks_with_age_rtt_and_loss() -> None:
    sup = driving(now=1.0)
    beat(sup, "a", 1.0, rtt=0.0)
    assert sup.speed_cap(1.0) == MAX
    # delay = age + rtt; full speed up to the grace (0.1 s), 0 at the timeout.
    assert sup.speed_cap(1.0625) == MAX
    assert sup.speed_cap(1.3) == pytest.approx(MAX * 0.5)
    assert sup.speed_cap(1.0 + TIMEOUT) == 0.0
    ages = [sup.speed_cap(1.0 + 0.01 * i) for i in range(60)]
    assert ages == sorted(ages, reverse=True) and ages[-1] == 0.0
    beat(sup, "a", 1.0, rtt=0.2)
    assert sup.speed_cap(1.0) == pytest.approx(MAX * 0.75)
    assert sup.speed_cap(1.3) == 0.0  # age 0.3 + rtt 0.2 reaches the timeout
    beat(sup, "a", 1.0, rtt=0.0, loss=0.25)
    assert sup.speed_cap(1.0) == pytest.approx(MAX * 0.5)
    beat(sup, "a", 1.0, rtt=0.0, loss=0.5)
    assert sup.speed_cap(1.0) == 0.0
    unmeasured = driving(now=1.0)
    beat(unmeasured, "a", 1.0, rtt=None)
    assert unmeasured.speed_cap(1.0) == 0.0
    refused = unmeasured.request_motion("a", 1.0, "fwd 1")
    assert not refused.allowed and refused.code == Reason.RTT_UNMEASURED


def test_speed_cap_is_zero_when_disarmed_and_too_poor_a_link_refuses_motion() -> None:
    sup = driving()
    sup.request_stop("a", 1.0)
    assert sup.speed_cap(1.0) == 0.0
    sup.rearm("a", 1.0)
    beat(sup, "a", 1.0, rtt=0.6)
    refused = sup.request_motion("a", 1.0, "fwd 1")
    assert not refused.allowed and refused.code == Reason.LINK_POOR


@settings(max_examples=200, deadline=None)
@given(
    age=st.floats(0, 1),
    more_age=st.floats(0, 1),
    rtt=st.floats(0, 1),
    more_rtt=st.floats(0, 1),
    loss=st.floats(0, 1),
    more_loss=st.floats(0, 1),
)
def test_a_worse_link_never_raises_the_cap(
    age: float, more_age: float, rtt: float, more_rtt: float, loss: float, more_loss: float
) -> None:
    def cap(a: float, r: float, lo: float) -> float:
        sup = driving(now=1.0)
        beat(sup, "a", 1.0, rtt=r, loss=min(1.0, lo))
        return sup.speed_cap(1.0 + a)

    base = cap(age, rtt, loss)
    assert 0.0 <= base <= MAX
    assert cap(age + more_age, rtt, loss) <= base
    assert cap(age, rtt + more_rtt, loss) <= base
    assert cap(age, rtt, loss + more_loss) <= base
    if age >= TIMEOUT:
        assert base == 0.0


def test_cap_announcements_are_rounded_down_and_not_repeated() -> None:
    sup = driving(now=1.0)
    beat(sup, "a", 1.0, rtt=0.0)
    assert caps(sup.tick(1.0625)) == []  # still within the grace: unchanged
    announced = caps(sup.tick(1.2345))
    assert len(announced) == 1 and announced[0] <= sup.speed_cap(1.2345)
    assert announced[0] == pytest.approx(math.floor(sup.speed_cap(1.2345) / CAP_STEP) * CAP_STEP)
    assert caps(sup.tick(1.2345)) == []


def test_obstacles_are_noted_not_latched() -> None:
    sup = driving()
    blocked = sup.obstacle(True, 1.0)
    assert not stops(blocked) and sup.armed and sup.state().blocked
    assert audits(blocked)[-1].detail == "obstacle ahead"
    assert sup.obstacle(True, 1.0) == []  # no news, no record
    allowed = sup.request_motion("a", 1.0, "turn 90")
    assert allowed.allowed and allowed.audit.detail == "obstacle ahead"
    assert audits(sup.obstacle(False, 1.0))[-1].detail == "obstacle cleared"


def test_every_command_is_audited_with_who_when_and_outcome() -> None:
    sup = supervisor()
    sup.join("a", "alice", Role.DRIVER, 1.0)
    beat(sup, "a", 1.0)
    decisions: list[Decision] = [
        sup.request_motion("a", 1.25, "fwd 2"),
        sup.rearm("a", 1.25),
        sup.request_motion("a", 1.25, "fwd 2"),
        sup.request_camera("a", "usercam", True, 1.25),
        sup.take_drive("a", 1.25),
        sup.request_stop("a", 1.25),
        sup.release_drive("a", 1.25),
    ]
    outcomes = [d.audit.outcome for d in decisions]
    assert outcomes == ["refused", "allowed", "allowed", "refused", "allowed", "allowed", "allowed"]
    for d in decisions:
        assert d.audit.who == "alice" and d.audit.role == "driver" and d.audit.call == "a"
        assert d.audit.t == 1.25
        assert Audit(d.audit) in d.actions
    line = decisions[0].audit.to_json()
    assert "\n" not in line
    assert json.loads(line) == {
        "t": 1.25,
        "who": "alice",
        "role": "driver",
        "call": "a",
        "what": "motion: fwd 2",
        "outcome": "refused",
        "detail": decisions[0].text,
    }


def test_unknown_call_ids_are_refused() -> None:
    sup = driving()
    for decision in (
        sup.request_motion("x", 1.0, "fwd 1"),
        sup.request_camera("x", NAVCAM, False, 1.0),
        sup.rearm("x", 1.0),
        sup.take_drive("x", 1.0),
        sup.release_drive("x", 1.0),
    ):
        assert not decision.allowed and decision.code == Reason.UNKNOWN_CALL
        assert decision.audit.who == "unknown call x"
    left = sup.leave("x", "hung_up", 1.0)
    assert audits(left)[-1].outcome == "refused" and sup.armed
    assert beat(sup, "x", 1.0) == [] and sup.participant("x") is None


def test_a_call_joining_twice_is_refused_and_stops_if_it_was_driving() -> None:
    sup = driving()
    actions = sup.join("a", "mallory", Role.ADMIN, 1.0)
    assert stops(actions) and not sup.armed
    assert audits(actions)[-1].outcome == "refused"
    p = sup.participant("a")
    assert p is not None and p.user == "alice" and p.role is Role.DRIVER


def test_a_clock_fault_stops_and_time_never_runs_backwards() -> None:
    sup = driving(now=1.0)
    fault = sup.request_motion("a", math.nan, "fwd 1")
    assert not fault.allowed and stops(fault.actions) and not sup.armed
    assert sup.speed_cap(math.inf) == 0.0
    assert stops(sup.tick(math.nan))
    sup = driving(now=1.0)
    sup.tick(2.0)  # the deadman fired at 2.0 …
    assert not sup.armed
    # … so a later command stamped earlier is handled at 2.0, and a sign of life stamped
    # 1.2 is as old as its stamp says: the link is still stale.
    beat(sup, "a", 1.2)
    refused = sup.rearm("a", 1.2)
    assert not refused.allowed and refused.audit.t == 2.0 and refused.code == Reason.LINK_SILENT


def test_actions_put_the_stop_first() -> None:
    sup = driving()
    sup.join("z", "zoe", Role.ADMIN, 1.0)
    for actions in (
        sup.take_drive("z", 1.0).actions,
        sup.release_drive("z", 1.0).actions,
    ):
        assert isinstance(actions[0], Stop)
        assert isinstance(actions[-1], Audit)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"timeout": 0.0},
        {"timeout": math.nan},
        {"max_speed": -1.0},
        {"grace": 0.5},
        {"grace": -0.1},
        {"stale_video": -0.5},
        {"stale_video": math.nan},
        {"now": math.inf},
    ],
)
def test_bad_settings_are_config_errors(kwargs: dict[str, float]) -> None:
    with pytest.raises(ConfigError):
        SafetySupervisor(**{"now": 0.0, **kwargs})  # type: ignore[arg-type]


# -- no driving blind: the stale-video lockout ----------------------------------------------

STALE = 1.0


def watched(now: float = 1.0, frames: int = 10, **kwargs: float | bool) -> SafetySupervisor:
    """Alice drives (armed) and watches the robot's video: her first report came at ``now``."""
    sup = driving(now, stale_video=STALE, **kwargs)
    sup.video_report("a", frames, now)
    return sup


def live(sup: SafetySupervisor, start: float, end: float) -> list[Action]:
    """Alice's heartbeats keep coming every 50 ms from ``start`` up to ``end`` (her link
    stays fresh, so only the video term moves the cap); every action on the way."""
    t = start
    actions: list[Action] = []
    while t < end - 1e-9:
        t = min(end, t + 0.05)
        actions += beat(sup, "a", t)
        actions += sup.tick(t)
    return actions


def test_a_frozen_picture_lowers_the_cap_and_then_stops_a_moving_robot() -> None:
    sup = watched()
    sup.motion(True, 1.0)
    live(sup, 1.0, 1.0 + STALE / 2)
    assert sup.speed_cap(1.0 + STALE / 2) == MAX  # no new picture for stale/2: full speed
    live(sup, 1.5, 1.75)
    assert sup.speed_cap(1.75) == pytest.approx(MAX / 2)  # halfway down to 0
    before = live(sup, 1.75, 1.0 + STALE - 0.05)
    assert sup.armed and not stops(before)
    at = live(sup, 1.95, 1.0 + STALE)
    assert stops(at) and not sup.armed
    state = sup.state()
    assert state.code == Reason.VIDEO_STALE and sup.stop_code == "video_stale"
    assert state.text == "video frozen for 1.0 s: the robot stopped itself"
    record = audits(at)[-1]
    assert (record.what, record.outcome, record.who) == ("video_stale", "stopped", "alice")
    # Latched: fresh pictures do not restart it, a re-arm does (and starts nothing).
    sup.video_report("a", 11, 2.05)
    live(sup, 2.0, 2.1)
    assert not sup.armed and not sup.request_motion("a", 2.1, "fwd 1").allowed
    assert sup.rearm("a", 2.1).allowed and sup.speed_cap(2.1) == MAX


def test_a_re_arm_in_the_step_that_stops_a_blind_robot_is_refused_and_it_stays_latched() -> None:
    # Found by test_supervisor_model: the re-arm came at the instant the frozen picture
    # stopped the moving robot; it re-armed in the same step, so the stop did not latch.
    sup = watched()
    sup.motion(True, 1.0)
    live(sup, 1.0, 1.0 + STALE - 0.05)
    assert sup.armed  # her last heartbeat came 50 ms before the picture is STALE old
    decision = sup.rearm("a", 1.0 + STALE)
    assert stops(decision.actions) and not decision.allowed and not sup.armed
    assert decision.code == Reason.VIDEO_STALE
    assert (
        decision.text
        == "the robot has just stopped: video frozen for 1.0 s: the robot stopped itself;"
        " arm again to drive on"
    )
    assert sup.stop_code == Reason.VIDEO_STALE
    assert ("rearm", "refused") in [(r.what, r.outcome) for r in audits(decision.actions)]
    # A re-arm made after the stop is an ordinary one.
    assert sup.rearm("a", 1.0 + STALE + 0.01).allowed


def test_at_rest_a_frozen_picture_only_lowers_the_cap_and_fresh_frames_restore_it() -> None:
    sup = watched()
    actions = live(sup, 1.0, 1.0 + 2 * STALE - 0.1)  # long frozen, but the robot stands
    assert sup.armed and sup.speed_cap(2.9) == 0.0 and not stops(actions)
    refused = sup.request_motion("a", 2.9, "fwd 1")
    assert not refused.allowed and refused.code == Reason.VIDEO_STALE
    assert "frozen" in refused.text
    # The next report whose counter grew: a new picture, the cap is back at once.
    actions = sup.video_report("a", 11, 2.9)
    assert sup.speed_cap(2.9) == MAX and caps(actions) == [MAX]
    assert sup.request_motion("a", 2.9, "fwd 1").allowed


def test_starting_to_move_on_a_frozen_picture_stops_at_once() -> None:
    sup = watched()
    live(sup, 1.0, 1.0 + STALE + 0.2)
    assert sup.armed  # at rest: no latch
    actions = sup.motion(True, 2.2)
    assert stops(actions) and sup.stop_code == Reason.VIDEO_STALE


def test_fresh_frames_keep_a_moving_robot_at_full_speed() -> None:
    sup = watched()
    sup.motion(True, 1.0)
    t, frames = 1.0, 10
    while t < 4.0:  # reports every 0.2 s, each with new frames
        live(sup, t, t + 0.2)
        t += 0.2
        frames += 3
        sup.video_report("a", frames, t)
        assert sup.armed and sup.speed_cap(t) == MAX
    # A report without new frames counts as no picture: the age runs from the last new one.
    live(sup, t, t + 0.7)
    sup.video_report("a", frames, t + 0.7)
    assert sup.speed_cap(t + 0.7) < MAX


def test_a_holder_not_watching_video_is_not_subject_to_the_rule() -> None:
    sup = driving(1.0, stale_video=STALE)  # no video report at all
    sup.motion(True, 1.0)
    live(sup, 1.0, 4.0)
    assert sup.armed and sup.speed_cap(4.0) == MAX
    # Neither is a watcher who is not the holder: an observer's frozen picture.
    sup.join("o", "olga", Role.OBSERVER, 4.0)
    sup.video_report("o", 5, 4.0)
    live(sup, 4.0, 6.0)
    assert sup.armed and sup.speed_cap(6.0) == MAX


def test_bye_ends_the_rule_and_so_do_reports_that_stop_coming() -> None:
    sup = watched()
    sup.motion(True, 1.0)
    live(sup, 1.0, 1.6)
    assert sup.speed_cap(1.6) < MAX
    actions = sup.video_report("a", 10, 1.6, bye=True)  # she closed the video
    assert caps(actions) == [MAX]
    live(sup, 1.6, 4.0)
    assert sup.armed and sup.speed_cap(4.0) == MAX
    # Watching again starts afresh (the first report is a fresh picture) ...
    sup.video_report("a", 10, 4.0)
    live(sup, 4.0, 4.4)
    assert sup.speed_cap(4.4) == MAX
    # ... and so does one after reports stopped for 2 s (the robot stopped streaming).
    sup.motion(False, 4.4)
    live(sup, 4.4, 6.5)
    assert sup.armed and sup.speed_cap(6.5) == MAX  # not watching any more
    sup.video_report("a", 10, 6.5)
    assert sup.speed_cap(6.5) == MAX


def test_stale_video_zero_turns_the_rule_off_and_counters_wrap() -> None:
    sup = driving(1.0, stale_video=0.0)
    sup.video_report("a", 3, 1.0)
    sup.motion(True, 1.0)
    live(sup, 1.0, 3.0)
    assert sup.armed and sup.speed_cap(3.0) == MAX
    # u32 counters wrap: 2**32 - 1 -> 2 is three new frames, not an old report.
    sup = watched(frames=2**32 - 1)
    sup.motion(True, 1.0)
    live(sup, 1.0, 1.9)
    sup.video_report("a", 2, 1.9)
    assert sup.speed_cap(1.9) == MAX
    live(sup, 1.9, 2.2)
    assert sup.armed


def test_stop_codes_say_who_or_what_stopped_the_robot() -> None:
    sup = SafetySupervisor(now=0.0)
    assert sup.state().code == Reason.STARTED
    sup = driving()
    assert sup.state().code == Reason.OK
    sup.request_stop("a", 1.1)
    assert sup.state().code == Reason.STOPPED
    sup.tick(3.0)  # the deadman while stopped keeps the first reason
    assert sup.state().code == Reason.STOPPED
    for how, code in (("dropped", Reason.DROPPED), ("hung_up", Reason.HUNG_UP)):
        sup = driving()
        sup.leave("a", how, 1.1)  # type: ignore[arg-type]
        assert sup.state().code == code
    sup = driving()
    sup.release_drive("a", 1.1)
    assert sup.state().code == Reason.HANDED_OVER


# -- the stateful model --------------------------------------------------------------------

CALLS = ("a", "b", "o", "z", "ghost")
ROLES = {"a": Role.DRIVER, "b": Role.DRIVER, "o": Role.OBSERVER, "z": Role.ADMIN}
DRIVING = {Role.DRIVER, Role.ADMIN}


def role_of(call: str) -> Role:
    """The role of ``call`` or of the call it replaced (``a'`` is ``a`` called again)."""
    return ROLES.get(call.rstrip("'"), Role.OBSERVER)


# Mostly the small steps of a live call, so that the robot gets armed and driven, with
# steps onto and around the deadman's edge and some long silences.
STEPS = st.one_of(
    st.sampled_from([0.0, 0.01, 0.05, 0.05, 0.1]),
    st.sampled_from([TIMEOUT - 1e-9, TIMEOUT, TIMEOUT + 1e-9]),
    st.floats(0.0, 0.8),
)
# Mostly good links, sometimes unmeasured or bad ones.
GOOD_RTT = st.floats(0.0, 0.05)
RTTS = st.one_of(GOOD_RTT, GOOD_RTT, GOOD_RTT, st.none(), st.floats(0.0, 0.7))
LOSSES = st.one_of(st.just(0.0), st.floats(0.0, 0.1), st.floats(0.0, 1.0))


MODEL_STALE = 0.3


class SupervisorModel(RuleBasedStateMachine):
    """Random sequences of events; after each, the robot may move only when it is safe."""

    def __init__(self) -> None:
        super().__init__()
        self.now = 0.0
        # A picture goes stale sooner than the deadman fires, so that short runs get there.
        self.sup = SafetySupervisor(now=0.0, stale_video=MODEL_STALE)
        self.joined: set[str] = set()
        # Kept by the test from what it fed in, not read back from the supervisor.
        self.heard: dict[str, float] = {}
        self.latched = True  # it starts stopped
        self.was_armed = False
        self.announced: float | None = None  # the cap in force in the NavStack
        # Video: per call, when its last report came and when its picture was last new
        # (None: not watching); whether the NavStack says the robot moves.
        self.reported: dict[str, float] = {}
        self.fresh: dict[str, float | None] = {}
        self.moving = False
        self.frames: dict[str, int] = {}

    def blind(self) -> bool:
        """The holder watches video and its picture is ``stale_video`` old by now."""
        holder = self.sup.holder_call
        fresh = self.fresh.get(holder) if holder is not None else None
        return (
            holder is not None
            and fresh is not None
            and self.now - self.reported[holder] < WATCHING_WINDOW
            and self.now - fresh >= MODEL_STALE
        )

    def advance(self, dt: float) -> None:
        """Time passes; a holder silent for the timeout by now must be latched."""
        self.now += dt
        holder = self.sup.holder_call
        if holder is not None and self.now - self.heard[holder] >= TIMEOUT:
            self.latched = True
        if self.moving and self.blind():  # no driving blind
            self.latched = True

    def check(self, actions: Sequence[Action], *, rearmed: bool = False) -> None:
        """Stops latch; nothing but an allowed re-arm by the holder arms."""
        if stops(actions):
            assert not self.sup.armed
            self.latched = True
        if self.was_armed and not self.sup.armed:
            assert stops(actions), "disarmed without telling the NavStack to stop"
        if not self.was_armed and self.sup.armed:
            assert rearmed, "armed by something other than a re-arm"
        if self.latched:
            assert not self.sup.armed
        for cap in caps(actions):
            self.announced = cap
        # The NavStack's limit never exceeds what is safe now (stops announce 0 at once).
        assert self.announced is not None
        assert self.announced <= self.sup.speed_cap(self.now) + 1e-12
        self.was_armed = self.sup.armed

    def safe_to_move(self) -> bool:
        holder = self.sup.holder_call
        return (
            self.sup.armed
            and holder is not None
            and holder in self.joined
            and role_of(holder) in DRIVING
            and self.now - self.heard[holder] < TIMEOUT
        )

    @rule(dt=STEPS)
    def tick(self, dt: float) -> None:
        self.advance(dt)
        self.check(self.sup.tick(self.now))

    @rule(call=st.sampled_from(CALLS))
    def join(self, call: str) -> None:
        role = ROLES.get(call, Role.OBSERVER)
        actions = self.sup.join(call, call.upper(), role, self.now)
        if call not in self.joined:
            self.joined.add(call)
            self.fresh.pop(call, None)  # a new call: not watching yet
            self.heard[call] = self.now
        self.check(actions)

    @precondition(lambda self: bool(self.joined))
    @rule(data=st.data())
    def reconnect(self, data: st.DataObject) -> None:
        # A client calls again before the robot saw its call drop: the new call (same
        # user) replaces the old one, which never arms; the drive goes along, stopped.
        old = data.draw(st.sampled_from(sorted(self.joined)))
        new = old + "'"
        while new in self.joined:  # call ids are never reused: a'' follows a'
            new += "'"
        held = self.sup.holder_call == old
        actions = self.sup.join(new, old.rstrip("'").upper(), role_of(old), self.now, replaces=old)
        self.joined.discard(old)
        self.joined.add(new)
        self.heard[new] = self.now
        if held:
            assert stops(actions) and self.sup.holder_call == new
        self.check(actions)
        # The old call's end comes later and is only noted.
        holder = self.sup.holder_call
        assert not stops(self.sup.leave(old, "dropped", self.now))
        assert self.sup.holder_call == holder

    @rule(call=st.sampled_from(CALLS), dropped=st.booleans())
    def leave(self, call: str, dropped: bool) -> None:
        holder = self.sup.holder_call
        actions = self.sup.leave(call, "dropped" if dropped else "hung_up", self.now)
        if call in self.joined and call == holder:
            assert stops(actions) and self.sup.holder_call is None
        self.joined.discard(call)
        self.fresh.pop(call, None)
        self.check(actions)

    @rule(call=st.sampled_from(CALLS), rtt=RTTS, loss=LOSSES)
    def heartbeat(self, call: str, rtt: float | None, loss: float) -> None:
        actions = self.sup.heartbeat(call, self.now, rtt=rtt, loss=loss)
        if call in self.joined:
            self.heard[call] = self.now
        self.check(actions)

    @precondition(lambda self: self.sup.holder_call is not None)
    @rule(dt=STEPS, rtt=RTTS, loss=LOSSES)
    def holder_lives(self, dt: float, rtt: float | None, loss: float) -> None:
        # Time passes and the holder's heartbeat arrives: mostly soon, sometimes after a
        # silence that must latch even though no tick came in between.
        holder = self.sup.holder_call
        assert holder is not None
        self.advance(dt)
        self.heartbeat(holder, rtt, loss)

    @rule(call=st.one_of(st.none(), st.sampled_from(CALLS)))
    def stop(self, call: str | None) -> None:
        decision = self.sup.request_stop(call, self.now)
        assert decision.allowed and stops(decision.actions)
        self.check(decision.actions)

    @precondition(lambda self: self.sup.holder_call is not None)
    @rule(rtt=GOOD_RTT, watching=st.booleans())
    def holder_drives(self, rtt: float, watching: bool) -> None:
        # The holder, on a live link, re-arms if need be and drives (watching the video
        # or not): the paths that make the robot move, which the other rules then disturb.
        holder = self.sup.holder_call
        assert holder is not None
        self.heartbeat(holder, rtt, 0.0)
        if watching:
            self.video_report(holder, grew=True, bye=False)
        if not self.sup.armed:
            self.rearm(holder)
        self.motion(holder)
        if self.sup.armed:
            self.moves(True)

    @rule(call=st.sampled_from(CALLS))
    def motion(self, call: str) -> None:
        decision = self.sup.request_motion(call, self.now, "fwd 1")
        if decision.allowed:
            assert self.safe_to_move() and self.sup.holder_call == call
            assert self.sup.speed_cap(self.now) > 0
        self.check(decision.actions)

    @rule(call=st.sampled_from(CALLS), camera=st.sampled_from([NAVCAM, "usercam"]))
    def camera(self, call: str, camera: str) -> None:
        decision = self.sup.request_camera(call, camera, self.sup.armed, self.now)
        if decision.allowed:
            assert self.sup.holder_call == call
            assert camera == NAVCAM or not self.sup.armed
        self.check(decision.actions)

    @rule(call=st.sampled_from(CALLS))
    def rearm(self, call: str) -> None:
        holder = self.sup.holder_call
        decision = self.sup.rearm(call, self.now)
        if decision.allowed:
            assert call == holder and role_of(call) in DRIVING
            self.latched = False
        self.check(decision.actions, rearmed=decision.allowed)

    @rule(call=st.sampled_from(CALLS))
    def take(self, call: str) -> None:
        holder = self.sup.holder_call
        decision = self.sup.take_drive(call, self.now)
        if decision.allowed:
            assert ROLES[call] in DRIVING and self.sup.holder_call == call
            if holder not in (None, call):
                # An admin takes over; a user takes it from their own other call.
                own = holder is not None and holder.rstrip("'") == call
                assert (ROLES[call] is Role.ADMIN or own) and stops(decision.actions)
        self.check(decision.actions)

    @rule(call=st.sampled_from(CALLS))
    def release(self, call: str) -> None:
        decision = self.sup.release_drive(call, self.now)
        if decision.allowed:
            assert self.sup.holder_call is None and stops(decision.actions)
        self.check(decision.actions)

    @precondition(lambda self: self.sup.armed)
    @rule(blocked=st.booleans())
    def obstacle(self, blocked: bool) -> None:
        actions = self.sup.obstacle(blocked, self.now)
        # An obstacle only caps the speed. The one stop that may come with it is the rule
        # every evaluation applies, no driving blind (Hypothesis found: driving, the picture
        # goes stale, the stop, a re-arm before the NavStack reports rest, then an obstacle).
        assert not stops(actions) or (self.moving and self.blind())
        self.check(actions)

    @rule(who=st.sampled_from(["holder", *CALLS]), grew=st.booleans(), bye=st.booleans())
    def video_report(self, who: str, grew: bool, bye: bool) -> None:
        call = self.sup.holder_call if who == "holder" else who
        if call is None:
            return
        frames = self.frames[call] = self.frames.get(call, 0) + (1 if grew else 0)
        actions = self.sup.video_report(call, frames, self.now, bye=bye)
        if call in self.joined:
            lapsed = self.now - self.reported.get(call, -math.inf) >= WATCHING_WINDOW
            if bye:
                self.fresh[call] = None
            elif grew or lapsed or self.fresh.get(call) is None:
                self.fresh[call] = self.now
            if not bye:
                self.reported[call] = self.now
        self.check(actions)

    @rule(moving=st.booleans())
    def moves(self, moving: bool) -> None:
        self.moving = moving
        if moving and self.blind():
            self.latched = True
        self.check(self.sup.motion(moving, self.now))

    @invariant()
    def moves_only_when_safe(self) -> None:
        if self.sup.speed_cap(self.now) > 0:
            assert self.safe_to_move()
            assert not self.blind()
        assert 0.0 <= self.sup.speed_cap(self.now) <= MAX
        if self.latched:
            assert not self.sup.armed


# Generating a step is slow on a loaded CI machine: that is no failure of the supervisor.
SupervisorModel.TestCase.settings = settings(
    max_examples=300,
    stateful_step_count=50,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
test_supervisor_model = SupervisorModel.TestCase
