"""The pages' messages, typed (src/telebot/apps/web/messages.py) and documented from the
types in docs/protocol.md §19, §19.2, §21. Sans-IO: no server, no browser."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from telebot.apps.web.messages import (
    FLEET_PAGE,
    ROBOT_PAGE,
    SCREEN_PAGE,
    Camera,
    Chat,
    CloseRobot,
    Drive,
    Goal,
    Keyframe,
    MediaCaps,
    OpenRobot,
    PageMessage,
    PageMessageError,
    Ping,
    ReleaseDrive,
    Say,
    Stop,
    StopAll,
    message_table,
    parse_page_message,
)
from telebot.apps.web.server import WebUI
from telebot.services.drive.wire import DriveState
from telebot.services.safety.wire import SafetyStatus

PROTOCOL = Path(__file__).resolve().parent.parent / "docs" / "protocol.md"


Kinds = tuple[type[PageMessage], ...]


def parse(message: object, kinds: Kinds = ROBOT_PAGE) -> PageMessage:
    return parse_page_message(json.dumps(message), kinds)


def test_each_page_message_parses_into_its_type() -> None:
    assert parse({"type": "stop", "how": "key"}) == Stop("key")
    assert parse({"type": "stop", "how": "whatever"}) == Stop("button"), "a stop is never refused"
    assert parse({"type": "stop"}) == Stop("button")
    assert parse({"type": "release"}) == ReleaseDrive()
    assert parse({"type": "goal", "x": 1, "y": 2.5, "yaw": None}) == Goal(1.0, 2.5, None)
    assert parse({"type": "goal", "x": 1, "y": 2, "yaw": 0.5}) == Goal(1.0, 2.0, 0.5)
    assert parse({"type": "drive", "linear": 0.3, "angular": -1}) == Drive(0.3, -1.0)
    assert parse({"type": "chat", "id": 3, "text": "fwd 1"}) == Chat(3, "fwd 1")
    assert parse({"type": "say", "id": "a", "text": "hi"}) == Say("a", "hi")
    assert parse({"type": "camera", "id": 4, "name": "usercam"}) == Camera(4, "usercam")
    assert parse({"type": "ping", "t": 12.5}) == Ping(12.5)
    media = {"type": "media", "decode": ["av1", "vp8", "jpeg", "vp8"], "encode": ["h264", 7]}
    assert parse(media) == MediaCaps(("vp8", "jpeg"), ("h264",)), "unknown codecs are left out"
    assert parse({"type": "keyframe"}) == Keyframe()
    assert parse({"type": "open", "robot": "bot1"}, FLEET_PAGE) == OpenRobot("bot1")
    assert parse({"type": "close", "robot": "bot1"}, FLEET_PAGE) == CloseRobot("bot1")
    assert parse({"type": "stop_all"}, FLEET_PAGE) == StopAll()
    assert parse({"type": "keyframe"}, SCREEN_PAGE) == Keyframe()


@pytest.mark.parametrize(
    ("message", "kinds", "error", "kind"),
    [
        ("garbage", ROBOT_PAGE, "not a JSON message with a type", ""),
        ([1, 2], ROBOT_PAGE, "not a JSON message with a type", ""),
        ({"no": "type"}, ROBOT_PAGE, "not a JSON message with a type", ""),
        ({"type": "fly"}, ROBOT_PAGE, "unknown message type 'fly'", ""),
        ({"type": "stop_all"}, ROBOT_PAGE, "unknown message type 'stop_all'", ""),
        ({"type": "goal", "x": 1, "y": 2}, FLEET_PAGE, "unknown message type 'goal'", ""),
        ({"type": "stop"}, SCREEN_PAGE, "unknown message type 'stop'", ""),
        ({"type": "goal", "x": "a", "y": 1}, ROBOT_PAGE, "a goal needs numbers x, y (and yaw)", "goal"),
        ({"type": "goal", "y": 1}, ROBOT_PAGE, "a goal needs numbers x, y (and yaw)", "goal"),
        ({"type": "goal", "x": 1e400, "y": 1}, ROBOT_PAGE, "a goal needs finite numbers", "goal"),
        ({"type": "drive", "linear": "fast", "angular": 0}, ROBOT_PAGE, "a drive needs finite numbers linear, angular", "drive"),
        ({"type": "drive", "linear": True, "angular": 0}, ROBOT_PAGE, "a drive needs finite numbers linear, angular", "drive"),
        ({"type": "drive"}, ROBOT_PAGE, "a drive needs finite numbers linear, angular", "drive"),
        ({"type": "camera", "id": 1, "name": "rearcam"}, ROBOT_PAGE, "camera: 'name' must be navcam or usercam", "camera"),
        ({"type": "chat", "id": [1], "text": "x"}, ROBOT_PAGE, "chat: 'id' must be a number, a text of at most 64 characters or null", "chat"),
        ('{"type": "say", "id": Infinity, "text": "x"}', ROBOT_PAGE, "say: 'id' must be a number, a text of at most 64 characters or null", "say"),
        ({"type": "ping", "t": "now"}, ROBOT_PAGE, "ping: 't' must be a finite number or null", "ping"),
        ({"type": "open"}, FLEET_PAGE, "open: 'robot' must be a name", "open"),
        ({"type": "close", "robot": 3}, FLEET_PAGE, "close: 'robot' must be a name", "close"),
    ],
)  # fmt: skip
def test_a_bad_page_message_is_one_line_naming_the_fault(
    message: object, kinds: Kinds, error: str, kind: str
) -> None:
    text = message if isinstance(message, str) else json.dumps(message)
    with pytest.raises(PageMessageError) as refused:
        parse_page_message(text, kinds)
    assert str(refused.value) == error
    assert refused.value.kind == kind


def test_a_huge_message_is_never_echoed_back() -> None:
    for message in ({"type": "x" * 1_000_000}, {"type": "chat", "id": "y" * 1_000_000}):
        with pytest.raises(PageMessageError) as refused:
            parse(message)
        assert len(str(refused.value)) < 200 and "\n" not in str(refused.value)
    with pytest.raises(PageMessageError, match="not a JSON message"):
        parse_page_message("[" * 100_000, ROBOT_PAGE)  # deeper than the JSON parser goes


def test_the_protocol_document_quotes_the_types() -> None:
    """docs/protocol.md §19, §19.2 and §21 list the page messages as the types define them:
    a field or a type added, renamed or removed on either side fails here."""
    text = PROTOCOL.read_text(encoding="utf-8")
    section19 = text[text.index("## 19. ") : text.index("### 19.1 ")]
    section19_2 = text[text.index("### 19.2 ") : text.index("## 20. ")]
    section21 = text[text.index("## 21. ") : text.index("## 22. ")]
    assert message_table(ROBOT_PAGE) in section19
    screen = "\n".join("  " + line for line in message_table(SCREEN_PAGE).splitlines())
    assert screen in section19_2
    assert message_table(FLEET_PAGE) in section21


def test_what_the_server_tells_a_page_calls_the_code_code_and_the_words_text() -> None:
    """§19: in a page's message the machine-readable reason is ``code`` and the words for
    people ``text`` (a robot's datagram calls its words ``reason``; the page's does not)."""
    state = SafetyStatus(False, "driver alice's link lost", "alice", 0.0, False, "link_silent")
    message = WebUI._safety_message(state)
    assert message["text"] == "driver alice's link lost" and message["code"] == "link_silent"
    drive = DriveState(9, False, "not_armed", "the robot is stopped: re-arm it", cap=0.5)
    message = WebUI._drive_message(drive)
    assert message["text"] == "the robot is stopped: re-arm it" and message["code"] == "not_armed"
    assert "reason" not in WebUI._safety_message(state) and "reason" not in message
