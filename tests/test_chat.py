"""ChatSession: the paper's chat commands driving a simulated robot, stepped in simulated time."""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from typing import Any

import pytest

from telebot.config import SimSettings
from telebot.errors import DatagramTooLarge
from telebot.identity import Role
from telebot.reasons import Reason
from telebot.robot.nav import GoalStatus, Pose2D
from telebot.robot.sim.stack import SimNavStack
from telebot.robot.sim.world import Obstacle
from telebot.services.chat.robot import FINISHED, OBSERVER_REFUSAL, UNBLOCK_POLLS, ChatSession
from telebot.services.chat.wire import HELP_TEXT, USAGE, ChatReply, encode_request
from telebot.services.mapxfer.wire import encode_map

TICK = 0.05


class Robot:
    """A simulated robot on the small map, a chat session on it, and the replies it sent."""

    def __init__(self, *, may_drive: bool = True) -> None:
        self.stack = SimNavStack.from_settings(SimSettings(map="small"))
        self.replies: list[ChatReply] = []
        role = Role.DRIVER if may_drive else Role.OBSERVER
        self.session = ChatSession(self.stack, role=role, send=self.replies.append, user="alice")
        self._next_id = 1

    def say(self, text: str) -> int:
        """Send ``text`` as a new request; returns its id."""
        request_id = self._next_id
        self._next_id += 1
        self.session.on_payload(encode_request(request_id, text))
        return request_id

    def to(self, request_id: int) -> list[ChatReply]:
        """The replies to one request, in order."""
        return [r for r in self.replies if r.id == request_id]

    def final(self, request_id: int) -> ChatReply | None:
        finals = [r for r in self.to(request_id) if r.final]
        assert len(finals) <= 1, f"more than one final reply: {finals}"
        return finals[0] if finals else None

    def ask(self, text: str) -> ChatReply:
        """Send a query and return its one, final reply."""
        request_id = self.say(text)
        (reply,) = self.to(request_id)
        assert reply.final
        return reply

    def run(self, seconds: float, until_final: int | None = None) -> None:
        """Step the robot at 20 Hz, polling the session each step, like the daemon does."""
        end = self.stack.now + seconds
        while self.stack.now < end - 1e-9:
            self.stack.step(self.stack.now + TICK)
            self.session.poll()
            if until_final is not None and self.final(until_final) is not None:
                return


@pytest.fixture
def robot() -> Robot:
    return Robot()


def yaw_change_deg(before: Pose2D, after: Pose2D) -> float:
    return math.degrees(math.remainder(after.yaw - before.yaw, math.tau))


# ---------------------------------------------------------------------------- motion


def test_fwd_is_acknowledged_then_reported_finished(robot: Robot) -> None:
    start = robot.stack.true_pose
    request = robot.say("fwd 2")
    assert [(r.text, r.final, r.ok) for r in robot.to(request)] == [
        ("Forward command received", False, True)
    ]
    robot.run(15, until_final=request)
    assert [(r.text, r.final, r.ok, r.seq) for r in robot.to(request)] == [
        ("Forward command received", False, True, 0),
        (FINISHED, True, True, 1),
    ]
    assert start.distance_to(robot.stack.true_pose) == pytest.approx(2.0, abs=0.1)
    assert robot.session.pending == 0


def test_turn_is_in_degrees_positive_to_the_right(robot: Robot) -> None:
    before = robot.stack.true_pose
    request = robot.say("turn 90")
    assert robot.to(request)[0].text == "Turn command received"
    robot.run(10, until_final=request)
    assert robot.final(request) == ChatReply(request, FINISHED, seq=1, code=Reason.FINISHED)
    # Clockwise: REP-103 yaw goes down.
    assert yaw_change_deg(before, robot.stack.true_pose) == pytest.approx(-90, abs=3)


@pytest.mark.parametrize(("command", "expected_deg"), [("left", 90), ("right", -90)])
def test_left_and_right_turn_a_quarter(robot: Robot, command: str, expected_deg: float) -> None:
    before = robot.stack.true_pose
    request = robot.say(command)
    assert robot.to(request)[0].text == "Turn command received"
    robot.run(10, until_final=request)
    assert robot.final(request) == ChatReply(request, FINISHED, seq=1, code=Reason.FINISHED)
    assert yaw_change_deg(before, robot.stack.true_pose) == pytest.approx(expected_deg, abs=3)


def test_goto_place_arrives(robot: Robot) -> None:
    request = robot.say("GoTo Room-A")
    assert robot.to(request)[0] == ChatReply(
        request, "Goto command received", final=False, code=Reason.ACCEPTED
    )
    robot.run(60, until_final=request)
    assert robot.final(request) == ChatReply(request, FINISHED, seq=1, code=Reason.FINISHED)
    place = robot.stack.places()["room-a"]
    assert robot.stack.true_pose.distance_to(place) < 0.15


def test_goto_point_arrives_facing_the_heading(robot: Robot) -> None:
    request = robot.say("goto 4 1.5 90")
    robot.run(40, until_final=request)
    assert robot.final(request) == ChatReply(request, FINISHED, seq=1, code=Reason.FINISHED)
    pose = robot.stack.true_pose
    assert pose.distance_to(Pose2D(4.0, 1.5)) < 0.15
    assert math.degrees(pose.yaw) == pytest.approx(90, abs=4)


def test_an_impossible_goto_fails_at_once_with_the_reason(robot: Robot) -> None:
    request = robot.say("goto 100 100")
    (reply,) = robot.to(request)
    assert reply.final and not reply.ok
    assert reply.text.startswith("no path to (100.00, 100.00)")
    assert robot.session.pending == 0
    assert robot.stack.current_goal() is None


def test_an_unknown_place_lists_the_known_ones(robot: Robot) -> None:
    reply = robot.ask("goto lab")
    assert not reply.ok
    assert "unknown place 'lab'" in reply.text
    assert "room-a" in reply.text and "corridor" in reply.text


def test_a_wall_ahead_ends_fwd_with_the_reason(robot: Robot) -> None:
    request = robot.say("fwd 50")
    robot.run(60, until_final=request)
    assert robot.final(request) == ChatReply(
        request, "stopped: obstacle ahead", ok=False, seq=1, code=Reason.OBSTACLE
    )


def test_a_person_in_the_way_gives_one_blocked_notice_then_the_move_finishes(
    robot: Robot,
) -> None:
    here = robot.stack.true_pose
    request = robot.say("fwd 2.5")
    robot.run(0.5)
    person = robot.stack.add_obstacle(Obstacle(here.x + 1.8, here.y, radius=0.2))
    robot.run(4)
    notices = [r for r in robot.to(request) if r.text.startswith("blocked")]
    assert notices == [
        ChatReply(
            request, "blocked: obstacle ahead", final=False, ok=False, seq=1, code=Reason.OBSTACLE
        )
    ]
    assert robot.final(request) is None
    robot.stack.remove_obstacle(person)
    robot.run(20, until_final=request)
    assert robot.final(request) == ChatReply(request, FINISHED, seq=2, code=Reason.FINISHED)
    assert here.distance_to(robot.stack.true_pose) == pytest.approx(2.5, abs=0.1)


def test_stop_during_a_move_ends_both_requests(robot: Robot) -> None:
    move = robot.say("fwd 5")
    robot.run(1)
    stop = robot.say("stop")
    assert robot.final(move) == ChatReply(move, "stopped", ok=False, seq=1, code=Reason.STOPPED)
    assert robot.final(stop) == ChatReply(stop, "stopped", code=Reason.OK)
    # The move's final reply comes before the stop's.
    assert [(r.id, r.text) for r in robot.replies[-2:]] == [(move, "stopped"), (stop, "stopped")]
    robot.run(1)
    assert robot.stack.velocity().linear == 0.0


def test_cancel_reports_the_cancelled_goal_and_nothing_when_idle(robot: Robot) -> None:
    assert robot.ask("cancel") == ChatReply(robot._next_id - 1, "nothing to cancel", code=Reason.OK)
    move = robot.say("fwd 3")
    robot.run(0.5)
    cancel = robot.say("cancel")
    assert robot.final(move) == ChatReply(move, "cancelled", ok=False, seq=1, code=Reason.CANCELLED)
    assert robot.final(cancel) == ChatReply(cancel, "cancelled", code=Reason.OK)
    assert robot.stack.current_goal() is None


def test_a_new_goal_replaces_the_running_one(robot: Robot) -> None:
    first = robot.say("fwd 3")
    robot.run(0.5)
    second = robot.say("left")
    assert robot.final(first) == ChatReply(
        first, "cancelled: replaced by a new goal", ok=False, seq=1, code=Reason.REPLACED
    )
    assert robot.to(second) == [
        ChatReply(second, "Turn command received", final=False, code=Reason.ACCEPTED)
    ]
    robot.run(10, until_final=second)
    assert robot.final(second) == ChatReply(second, FINISHED, seq=1, code=Reason.FINISHED)


def test_bad_numbers_answer_the_usage_line_and_do_not_move(robot: Robot) -> None:
    for text, name in [("fwd nan", "fwd"), ("turn 1e999", "turn"), ("fwd 101", "fwd")]:
        reply = robot.ask(text)
        assert reply == ChatReply(reply.id, USAGE[name], ok=False, code=Reason.USAGE)
    assert robot.stack.current_goal() is None


def test_an_unknown_command_says_try_help(robot: Robot) -> None:
    reply = robot.ask("dance")
    assert reply == ChatReply(
        reply.id, "unknown command 'dance' — try help", ok=False, code=Reason.UNKNOWN_COMMAND
    )


# ---------------------------------------------------------------------------- queries


def test_where_reports_the_pose_estimate_in_the_map_frame(robot: Robot) -> None:
    request = robot.say("left")
    robot.run(10, until_final=request)
    reply = robot.ask("Where?")
    match = re.fullmatch(r"x (-?\d+\.\d\d) m, y (-?\d+\.\d\d) m, heading (-?\d+)°", reply.text)
    assert match is not None, reply.text
    estimate = robot.stack.pose().pose
    assert float(match[1]) == pytest.approx(estimate.x, abs=0.005)
    assert float(match[2]) == pytest.approx(estimate.y, abs=0.005)
    assert int(match[3]) == round(math.degrees(estimate.yaw))
    assert int(match[3]) == pytest.approx(90, abs=3)


def test_places_lists_names_with_coordinates(robot: Robot) -> None:
    reply = robot.ask("places")
    assert reply.ok
    assert reply.text.startswith("places: ")
    assert "room-a (3.00, 5.20)" in reply.text
    assert "room-b (9.50, 4.00)" in reply.text


def test_status_shows_state_goal_and_progress(robot: Robot) -> None:
    assert robot.ask("status").text == "idle"
    robot.say("fwd 2")
    robot.run(2)
    text = robot.ask("status").text
    assert re.fullmatch(r"moving — forward 2\.00 m, \d+% done", text), text
    assert 0 < int(re.findall(r"(\d+)%", text)[0]) < 100
    robot.say("stop")
    robot.say("goto 100 100")
    assert robot.ask("status").text == "failed: no path to (100.00, 100.00): outside the map"


def test_battery_reports_percent_and_low(robot: Robot) -> None:
    assert robot.ask("battery").text == "battery 100%"
    robot.stack.set_battery(9.6)
    assert robot.ask("battery").text == "battery 10% (low)"


def test_cameras_switch(robot: Robot) -> None:
    assert robot.ask("usercam") == ChatReply(robot._next_id - 1, "usercam selected", code=Reason.OK)
    assert robot.stack.active_camera == "usercam"
    assert robot.ask("NAVCAM").text == "navcam selected"
    assert robot.stack.active_camera == "navcam"


def test_getmap_announces_the_map_the_map_channel_sends(robot: Robot) -> None:
    reply = robot.ask("getmap")
    assert reply.ok and reply.attachment == "map"
    # The map channel sends the map cropped to its known cells: that is the size to say.
    sent = encode_map(robot.stack.map())
    assert (sent.width, sent.height) != (robot.stack.map().width, robot.stack.map().height)
    assert reply.text == f"sending map: {sent.width} x {sent.height} cells at 0.05 m"


def test_help_lists_commands_and_explains_one(robot: Robot) -> None:
    assert robot.ask("help").text == HELP_TEXT
    assert robot.ask("help turn").text == USAGE["turn"]


# ---------------------------------------------------------------------------- roles


@pytest.mark.parametrize(
    "text", ["goto room-a", "goto 3 2", "fwd 1", "turn 90", "left", "right", "cancel", "usercam"]
)
def test_an_observer_may_not_drive_or_switch_cameras(text: str) -> None:
    robot = Robot(may_drive=False)
    reply = robot.ask(text)
    assert reply == ChatReply(reply.id, OBSERVER_REFUSAL, ok=False, code=Reason.OBSERVER)
    robot.run(1)
    assert robot.stack.current_goal() is None
    assert robot.stack.active_camera == "navcam"
    assert robot.stack.true_pose == Pose2D(1.0, 1.2, 0.0)


@pytest.mark.parametrize("text", ["where?", "places", "status", "battery", "getmap", "help"])
def test_an_observer_may_ask(text: str) -> None:
    reply = Robot(may_drive=False).ask(text)
    assert reply.ok


def test_an_observer_may_stop_a_driver_s_goal() -> None:
    driver = Robot()
    observer = ChatSession(driver.stack, role=Role.OBSERVER, send=driver.replies.append)
    move = driver.say("fwd 5")
    driver.run(1)
    observer.on_payload(encode_request(900, "stop"))
    assert driver.final(900) == ChatReply(900, "stopped", code=Reason.OK)
    driver.run(0.1)
    assert driver.final(move) == ChatReply(move, "stopped", ok=False, seq=1, code=Reason.STOPPED)
    assert driver.stack.current_goal() is None


# ---------------------------------------------------------------------------- robustness


@pytest.mark.parametrize(
    "payload", [b"\x00\x01", "", "fwd 2", "{}", '{"id": 1}', '{"id": -4, "text": "stop"}']
)
def test_garbage_is_counted_and_not_answered(robot: Robot, payload: str | bytes) -> None:
    robot.session.on_payload(payload)
    assert robot.session.rejected == 1
    assert robot.replies == []
    assert robot.stack.current_goal() is None


def test_a_failing_send_is_counted_and_does_not_raise() -> None:
    stack = SimNavStack.from_settings(SimSettings(map="small"))

    def send(reply: ChatReply) -> None:
        raise DatagramTooLarge("too big")

    session = ChatSession(stack, role=Role.DRIVER, send=send)
    session.on_payload(encode_request(1, "fwd 1"))
    session.poll()
    assert session.send_errors == 1
    assert session.pending == 1  # the goal is still tracked: its final reply will be tried


class BrokenNav:
    """A NavStack whose every call fails as a buggy adapter's would."""

    def __getattr__(self, name: str) -> Any:
        raise RuntimeError(f"adapter bug in {name}")


def test_a_broken_adapter_gives_an_error_reply_not_an_exception(
    caplog: pytest.LogCaptureFixture,
) -> None:
    replies: list[ChatReply] = []
    session = ChatSession(BrokenNav(), role=Role.DRIVER, send=replies.append)
    session.on_payload(encode_request(1, "where?"))
    session.poll()
    assert replies == [
        ChatReply(
            1,
            "internal error: the robot could not run that",
            ok=False,
            code=Reason.INTERNAL_ERROR,
        )
    ]
    assert "adapter bug in pose" in caplog.text


class FailingGoal:
    """A goal handle whose status cannot be read."""

    goal_id = 1

    @property
    def status(self) -> GoalStatus:
        raise RuntimeError("lost the goal")


class OneGoalNav:
    """Starts a goal that then breaks: poll must survive it."""

    def forward(self, metres: float) -> Any:
        return _ActiveGoal()

    def places(self) -> Mapping[str, Pose2D]:
        return {}


class _ActiveGoal:
    goal_id = 1
    status = GoalStatus.ACTIVE


def test_poll_survives_a_goal_that_breaks(caplog: pytest.LogCaptureFixture) -> None:
    replies: list[ChatReply] = []
    nav = OneGoalNav()
    session = ChatSession(nav, role=Role.DRIVER, send=replies.append)  # type: ignore[arg-type]
    session.on_payload(encode_request(1, "fwd 1"))
    assert replies == [ChatReply(1, "Forward command received", final=False, code=Reason.ACCEPTED)]
    session._motions[0].handle = FailingGoal()  # type: ignore[assignment]
    session.poll()
    assert "chat poll" in caplog.text
    assert robot_places_reply(session, replies) == "no named places on this map"


def robot_places_reply(session: ChatSession, replies: list[ChatReply]) -> str:
    session.handle_text(2, "places")
    return replies[-1].text


@pytest.mark.parametrize(
    ("clear_polls", "expected_notices"), [(UNBLOCK_POLLS // 3, 1), (UNBLOCK_POLLS * 2, 2)]
)
def test_a_new_blockage_gets_a_new_notice_after_a_clear_spell(
    robot: Robot, clear_polls: int, expected_notices: int
) -> None:
    # A robot edging past a person flickers between blocked and moving: a short clear
    # spell is the same blockage, a long one makes the next blockage news.
    here = robot.stack.true_pose
    request = robot.say("fwd 2.5")
    robot.run(0.5)
    person = robot.stack.add_obstacle(Obstacle(here.x + 1.8, here.y, radius=0.2))
    robot.run(3)
    robot.stack.remove_obstacle(person)
    robot.run(TICK * clear_polls)
    robot.stack.add_obstacle(Obstacle(here.x + 1.8, here.y, radius=0.2))
    robot.run(3)
    notices = [r for r in robot.to(request) if r.text == "blocked: obstacle ahead"]
    assert len(notices) == expected_notices
    assert [r.seq for r in robot.to(request)] == list(range(1 + expected_notices))
    assert robot.final(request) is None
