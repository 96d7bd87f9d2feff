"""Reason codes on the wire and in the docs, and the one table of role rights."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from telebot.errors import ProtocolError
from telebot.identity import Role
from telebot.reasons import DESCRIPTIONS, Reason
from telebot.rights import RIGHTS, Right, may, rights_of
from telebot.services.chat.wire import ChatReply, decode_reply
from telebot.services.safety.wire import (
    STOP_HOWS,
    SafetyAck,
    SafetyRequest,
    decode_safety_reply,
    decode_safety_request,
)
from telebot.services.status.wire import GoalUpdate, decode_goal_update

PROTOCOL = Path(__file__).resolve().parent.parent / "docs" / "protocol.md"


# -- the rights table ----------------------------------------------------------------------


def test_the_rights_table() -> None:
    table = {role: {right: may(role, right) for right in Right} for role in Role}
    assert table == {
        Role.OBSERVER: {
            Right.OBSERVE: True,
            Right.STOP: True,
            Right.DRIVE: False,
            Right.CAMERA: False,
            Right.TAKE_OVER: False,
        },
        Role.DRIVER: {
            Right.OBSERVE: True,
            Right.STOP: True,
            Right.DRIVE: True,
            Right.CAMERA: True,
            Right.TAKE_OVER: False,
        },
        Role.ADMIN: dict.fromkeys(Right, True),
    }
    assert set(RIGHTS) == set(Role)


@pytest.mark.parametrize("role", [None, "pilot", "", "DRIVER"])
def test_an_unknown_role_has_the_observer_s_rights(role: str | None) -> None:
    assert rights_of(role) == RIGHTS[Role.OBSERVER]


def test_every_role_may_stop() -> None:
    # A stop button that depends on one's role is not a safety feature.
    assert all(may(role, Right.STOP) for role in [*Role, None, "nonsense"])


# -- codes in the docs ---------------------------------------------------------------------


def test_every_code_is_described_and_documented_in_protocol_md() -> None:
    assert set(DESCRIPTIONS) == set(Reason)
    text = PROTOCOL.read_text(encoding="utf-8")
    section = text[text.index("### 13.1 Reason codes") : text.index("## 14.")]
    documented = set(re.findall(r"^\| `([a-z_]+)` \|", section, re.MULTILINE))
    assert documented == {code.value for code in Reason}


def test_every_stop_how_is_documented_in_protocol_md() -> None:
    text = PROTOCOL.read_text(encoding="utf-8")
    section = text[text.index("## 18. Safety") : text.index("## 19.")]
    for how in [*STOP_HOWS, "chat", "unspecified"]:
        assert f"`{how}`" in section, how


# -- codes on the wire ---------------------------------------------------------------------


def test_a_chat_reply_carries_its_code() -> None:
    reply = ChatReply(7, "refused: …", ok=False, code=Reason.NOT_ARMED)
    message = json.loads(reply.encode())
    assert message["code"] == "not_armed"
    assert decode_reply(reply.encode()) == reply


def test_goal_updates_and_safety_acks_carry_text_and_code_apart() -> None:
    update = GoalUpdate(3, "failed", 0.5, "no path to (1.00, 2.00): inside an obstacle", "no_path")
    message = json.loads(update.encode())
    assert message["reason"] == update.text and message["code"] == "no_path"
    assert decode_goal_update(update.encode()) == update
    ack = SafetyAck(4, False, "the drive is held by bob", Reason.NOT_HOLDER)
    message = json.loads(ack.encode())
    assert message["reason"] == ack.text and message["code"] == "not_holder"
    assert decode_safety_reply(ack.encode()) == ack


def test_messages_of_a_robot_without_codes_still_decode() -> None:
    assert decode_reply('{"id":1,"seq":0,"text":"x","final":true,"ok":true}').code == ""
    old_goal = '{"type":"status","id":1,"status":"failed","progress":0,"reason":"why"}'
    assert decode_goal_update(old_goal) == GoalUpdate(1, "failed", 0.0, "why", "")
    old_ack = '{"type":"ack","id":1,"ok":false,"reason":"why"}'
    assert decode_safety_reply(old_ack) == SafetyAck(1, False, "why", "")


def test_an_unknown_code_is_kept_and_a_bad_one_refused() -> None:
    newer = '{"id":1,"seq":0,"text":"x","final":true,"ok":false,"code":"too_windy"}'
    assert decode_reply(newer).code == "too_windy"
    for bad in ('"code":5', '"code":null', '"code":"' + "x" * 65 + '"'):
        with pytest.raises(ProtocolError, match="'code'"):
            decode_reply('{"id":1,"seq":0,"text":"x","final":true,"ok":false,' + bad + "}")


def test_a_stop_says_how_and_is_never_dropped_for_a_bad_how() -> None:
    stop = SafetyRequest("stop", 9, "button")
    assert json.loads(stop.encode()) == {"type": "stop", "id": 9, "how": "button"}
    assert decode_safety_request(stop.encode()) == stop
    for how in ('"how":7', '"how":"Not A Word!"', '"how":"' + "x" * 40 + '"'):
        decoded = decode_safety_request('{"type":"stop","id":9,' + how + "}")
        assert decoded == SafetyRequest("stop", 9, "")
    # Only stops say how.
    assert "how" not in json.loads(SafetyRequest("arm", 1, "button").encode())
