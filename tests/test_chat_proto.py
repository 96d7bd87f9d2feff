"""Chat, sans-IO: parsing every command of Table I (and ours), usage errors, message format."""

from __future__ import annotations

import json
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from telebot.errors import ProtocolError
from telebot.services.chat.wire import (
    HELP_TEXT,
    MAX_REPLY_TEXT,
    MAX_REQUEST_TEXT,
    USAGE,
    BatteryQuery,
    Cancel,
    ChatReply,
    ChatRequest,
    Command,
    CommandError,
    Forward,
    GetMap,
    GotoPlace,
    GotoPoint,
    Help,
    Left,
    NavCam,
    Places,
    Right,
    Status,
    Stop,
    Turn,
    UserCam,
    Where,
    decode_reply,
    decode_request,
    encode_request,
    parse_command,
)

# ---------------------------------------------------------------------------- parsing

PARSES: list[tuple[str, Command]] = [
    # Table I, as the paper writes it.
    ("goto lab", GotoPlace("lab")),
    ("getmap", GetMap()),
    ("where?", Where()),
    ("fwd 5", Forward(5.0)),
    ("turn 30", Turn(30.0)),
    ("left", Left()),
    ("right", Right()),
    ("navcam", NavCam()),
    ("usercam", UserCam()),
    # Ours.
    ("stop", Stop()),
    ("cancel", Cancel()),
    ("places", Places()),
    ("status", Status()),
    ("battery", BatteryQuery()),
    ("help", Help()),
    # goto: places keep their case and inner words; points are map-frame metres.
    ("goto Room-A", GotoPlace("Room-A")),
    ("goto 101", GotoPlace("101")),
    ("goto  room   101 ", GotoPlace("room 101")),
    ("go to kitchen", GotoPlace("kitchen")),
    ("GO TO kitchen", GotoPlace("kitchen")),
    ("navigate lab", GotoPlace("lab")),
    ("goto 1.5 -2", GotoPoint(1.5, -2.0, None)),
    ("goto 1.5 -2 90", GotoPoint(1.5, -2.0, 90.0)),
    ("goto .5 +3. -1e1", GotoPoint(0.5, 3.0, -10.0)),
    ("goto \u22121 2", GotoPoint(-1.0, 2.0, None)),
    # Spacing and case.
    ("  FWD   2  ", Forward(2.0)),
    ("Fwd\t-0.5", Forward(-0.5)),
    ("fwd 0", Forward(0.0)),
    ("fwd 100", Forward(100.0)),
    ("fwd -100", Forward(-100.0)),
    ("forward 3", Forward(3.0)),
    ("fwd 2m", Forward(2.0)),
    ("fwd 2 metres", Forward(2.0)),
    ("fwd 1.5 M", Forward(1.5)),
    ("back 2", Forward(-2.0)),
    ("backward -2", Forward(-2.0)),
    ("turn -45", Turn(-45.0)),
    ("TURN 90°", Turn(90.0)),
    ("turn 90 deg", Turn(90.0)),
    ("turn 360", Turn(360.0)),
    ("turn -360 degrees", Turn(-360.0)),
    ("rotate 10", Turn(10.0)),
    ("turn left", Left()),
    ("Turn Right", Right()),
    ("LEFT", Left()),
    ("where", Where()),
    ("WHERE?", Where()),
    ("where am i?", Where()),
    ("where are you", Where()),
    ("pose", Where()),
    ("get map", GetMap()),
    ("map", GetMap()),
    ("GetMap", GetMap()),
    ("nav cam", NavCam()),
    ("user cam", UserCam()),
    ("NavCam", NavCam()),
    ("halt", Stop()),
    (" STOP ", Stop()),
    ("STOP!!", Stop()),
    ("stop.", Stop()),
    ("abort", Cancel()),
    ("status?", Status()),
    ("?", Help()),
    ("commands", Help()),
    ("help fwd", Help("fwd")),
    ("help forward", Help("fwd")),
    ("help back", Help("fwd")),
    ("help where?", Help("where?")),
    ("help go to", Help("goto")),
    ("HELP Turn", Help("turn")),
]


@pytest.mark.parametrize(("text", "expected"), PARSES)
def test_every_command_and_alias_parses(text: str, expected: Command) -> None:
    assert parse_command(text) == expected


def test_the_parsed_numbers_are_plain_floats_without_negative_zero() -> None:
    command = parse_command("fwd -0")
    assert isinstance(command, Forward)
    assert math.copysign(1.0, command.metres) == 1.0
    assert type(command.metres) is float


USAGE_ERRORS: list[tuple[str, str]] = [
    ("goto", "goto"),
    ("goto 1 2 3 4", "goto"),
    ("goto 1 x", "goto"),
    ("goto 1 2 x", "goto"),
    ("fwd", "fwd"),
    ("fwd x", "fwd"),
    ("fwd 1 2", "fwd"),
    ("fwd 2 km", "fwd"),
    ("fwd 100.01", "fwd"),
    ("fwd -101", "fwd"),
    ("fwd 1_0", "fwd"),
    ("fwd 0x10", "fwd"),
    ("back", "fwd"),
    ("back 101", "fwd"),
    ("turn", "turn"),
    ("turn 361", "turn"),
    ("turn -360.5", "turn"),
    ("turn up", "turn"),
    ("turn left 45", "turn"),
    ("left 45", "left"),
    ("right now", "right"),
    ("getmap please", "getmap"),
    ("where lab", "where?"),
    ("navcam 2", "navcam"),
    ("usercam x", "usercam"),
    ("stop it", "stop"),
    ("cancel all", "cancel"),
    ("places x", "places"),
    ("status x", "status"),
    ("battery x", "battery"),
]


@pytest.mark.parametrize(("text", "name"), USAGE_ERRORS)
def test_bad_arguments_answer_with_the_usage_line(text: str, name: str) -> None:
    with pytest.raises(CommandError) as info:
        parse_command(text)
    assert str(info.value) == USAGE[name]


@pytest.mark.parametrize(
    ("text", "name"),
    [
        ("fwd nan", "fwd"),
        ("fwd NaN", "fwd"),
        ("fwd inf", "fwd"),
        ("fwd -inf", "fwd"),
        ("fwd infinity", "fwd"),
        ("fwd 1e999", "fwd"),
        ("turn 1e999", "turn"),
        ("turn -1e999", "turn"),
        ("turn nan", "turn"),
        ("goto 1e999 2", "goto"),
        ("goto 1 nan", "goto"),
        ("goto 1 2 inf", "goto"),
    ],
)
def test_numbers_that_are_not_finite_answer_with_the_usage_line(text: str, name: str) -> None:
    with pytest.raises(CommandError) as info:
        parse_command(text)
    assert str(info.value) == USAGE[name]


def test_the_limits_are_in_the_usage_lines() -> None:
    assert "100 m" in USAGE["fwd"]
    assert "360°" in USAGE["turn"]
    assert "positive to the right" in USAGE["turn"]


def test_an_unknown_command_answers_with_the_exact_text() -> None:
    with pytest.raises(CommandError) as info:
        parse_command("xyz")
    assert str(info.value) == "unknown command 'xyz' — try help"


def test_an_unknown_command_is_echoed_as_typed_and_shortened() -> None:
    with pytest.raises(CommandError) as info:
        parse_command("  Jump  3 ")
    assert str(info.value) == "unknown command 'Jump' — try help"
    with pytest.raises(CommandError) as info:
        parse_command("a" * 500)
    assert str(info.value) == "unknown command '" + "a" * 31 + "…' — try help"


def test_help_on_an_unknown_command_says_so() -> None:
    with pytest.raises(CommandError) as info:
        parse_command("help fly")
    assert str(info.value) == "unknown command 'fly' — try help"


@pytest.mark.parametrize("text", ["", "   ", "\t\n"])
def test_an_empty_line_asks_for_help(text: str) -> None:
    with pytest.raises(CommandError) as info:
        parse_command(text)
    assert str(info.value) == "empty command — try help"


def test_command_error_is_a_protocol_error_and_a_value_error() -> None:
    with pytest.raises(ProtocolError):
        parse_command("xyz")
    with pytest.raises(ValueError, match="unknown command"):
        parse_command("xyz")


def test_usage_covers_table_one_and_help_lists_every_usage_line() -> None:
    table_one = {"goto", "getmap", "where?", "fwd", "turn", "left", "right", "navcam", "usercam"}
    ours = {"stop", "cancel", "places", "topics", "status", "battery", "help"}
    ours |= {"arm", "take", "release", "follow", "unfollow"}
    assert set(USAGE) == table_one | ours
    for line in USAGE.values():
        assert line.startswith("usage: ")
        assert line.removeprefix("usage: ") in HELP_TEXT


def test_every_help_topic_is_a_usage_key() -> None:
    for name in USAGE:
        command = parse_command(f"help {name}")
        assert command == Help(name)


def test_commands_are_frozen_value_objects() -> None:
    command = parse_command("fwd 2")
    with pytest.raises(AttributeError):
        command.metres = 3.0  # type: ignore[misc, union-attr]
    assert {parse_command("fwd 2"), parse_command("FWD 2")} == {Forward(2.0)}


def outcome(text: str) -> Command | CommandError:
    """The command, or the CommandError (any other exception escapes and fails the test)."""
    try:
        return parse_command(text)
    except CommandError as exc:
        return exc


@given(st.text(max_size=60))
def test_any_text_parses_or_raises_command_error(text: str) -> None:
    result = outcome(text)
    if isinstance(result, CommandError):
        assert str(result)
    else:
        assert type(result).__module__ == "telebot.services.chat.wire"


_WORDS = st.sampled_from(
    ["goto", "go", "to", "fwd", "turn", "left", "right", "where?", "help", "back", "map", "m"]
)
_TOKENS = st.one_of(
    _WORDS,
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-1000, 1000).map(str),
    st.sampled_from(["nan", "inf", "-", "°", "1e999", ".", "+.", "e5", "\u2212"]),
)


@given(st.lists(_TOKENS, max_size=5))
def test_command_like_lines_parse_to_finite_in_range_numbers(tokens: list[str]) -> None:
    result = outcome(" ".join(tokens))
    if isinstance(result, CommandError):
        assert str(result).startswith(("usage: ", "unknown command", "empty command"))
        return
    match result:
        case Forward(metres):
            assert math.isfinite(metres) and abs(metres) <= 100
        case Turn(degrees):
            assert math.isfinite(degrees) and abs(degrees) <= 360
        case GotoPoint(x, y, yaw):
            assert all(math.isfinite(v) for v in (x, y, 0.0 if yaw is None else yaw))
        case _:
            pass


# ---------------------------------------------------------------------------- messages


def test_a_request_round_trips() -> None:
    payload = encode_request(7, "fwd 2")
    assert json.loads(payload) == {"id": 7, "text": "fwd 2"}
    assert decode_request(payload) == ChatRequest(7, "fwd 2")


@given(st.integers(0, 2**32 - 1), st.text(max_size=MAX_REQUEST_TEXT))
def test_any_valid_request_round_trips(request_id: int, text: str) -> None:
    assert decode_request(encode_request(request_id, text)) == ChatRequest(request_id, text)


def test_a_reply_round_trips_with_and_without_attachment() -> None:
    plain = ChatReply(3, "finished moving", final=True, ok=True, seq=1)
    assert json.loads(plain.encode()) == {
        "id": 3,
        "seq": 1,
        "text": "finished moving",
        "final": True,
        "ok": True,
    }
    assert decode_reply(plain.encode()) == plain
    with_map = ChatReply(4, "sending map: 280 x 200 cells at 0.05 m", attachment="map")
    assert json.loads(with_map.encode())["attachment"] == "map"
    assert decode_reply(with_map.encode()) == with_map
    notice = ChatReply(5, "blocked: obstacle ahead", final=False, ok=False, seq=2)
    assert decode_reply(notice.encode()) == notice


def test_a_reply_keeps_unicode_and_shortens_huge_texts() -> None:
    reply = ChatReply(1, "heading 90° — ok")
    assert "°" in reply.encode()  # not \u-escaped: smaller datagrams
    assert decode_reply(reply.encode()).text == "heading 90° — ok"
    huge = decode_reply(ChatReply(2, "é" * (MAX_REPLY_TEXT * 3)).encode())
    assert len(huge.text) == MAX_REPLY_TEXT
    assert huge.text.endswith("…")
    assert len(ChatReply(2, "é" * (MAX_REPLY_TEXT * 3)).encode().encode()) < 32768


def test_unknown_keys_are_ignored_for_newer_peers() -> None:
    assert decode_request('{"id": 1, "text": "stop", "lang": "en"}') == ChatRequest(1, "stop")
    payload = '{"id": 1, "seq": 0, "text": "x", "final": true, "ok": true, "v": 2}'
    assert decode_reply(payload) == ChatReply(1, "x")


@pytest.mark.parametrize(
    "payload",
    [
        b'{"id": 1, "text": "stop"}',
        "",
        "not json",
        "[1, 2]",
        '"stop"',
        "{}",
        '{"text": "stop"}',
        '{"id": -1, "text": "stop"}',
        '{"id": 4294967296, "text": "stop"}',
        '{"id": 1.5, "text": "stop"}',
        '{"id": true, "text": "stop"}',
        '{"id": "1", "text": "stop"}',
        '{"id": 1}',
        '{"id": 1, "text": 5}',
        '{"id": 1, "text": null}',
        '{"id": NaN, "text": "stop"}',
        '{"id": 1, "text": "' + "x" * (MAX_REQUEST_TEXT + 1) + '"}',
        "[" * 100_000,
    ],
)
def test_garbage_requests_raise_protocol_error(payload: str | bytes) -> None:
    with pytest.raises(ProtocolError):
        decode_request(payload)


@pytest.mark.parametrize(
    "payload",
    [
        b"{}",
        "nope",
        '{"id": 1, "seq": 0, "text": "x", "final": true}',
        '{"id": 1, "seq": 0, "text": "x", "ok": true}',
        '{"id": 1, "seq": 0, "text": "x", "final": 1, "ok": true}',
        '{"id": 1, "seq": 0, "text": "x", "final": true, "ok": "yes"}',
        '{"id": 1, "seq": 0, "final": true, "ok": true}',
        '{"id": 1, "text": "x", "final": true, "ok": true}',
        '{"id": 1, "seq": -1, "text": "x", "final": true, "ok": true}',
        '{"seq": 0, "text": "x", "final": true, "ok": true}',
        '{"id": 1, "seq": 0, "text": "x", "final": true, "ok": true, "attachment": 3}',
    ],
)
def test_garbage_replies_raise_protocol_error(payload: str | bytes) -> None:
    with pytest.raises(ProtocolError):
        decode_reply(payload)


@pytest.mark.parametrize(
    ("request_id", "text"),
    [(-1, "stop"), (2**32, "stop"), (True, "stop"), (1, "x" * (MAX_REQUEST_TEXT + 1))],
)
def test_encode_request_refuses_what_the_robot_would_drop(request_id: int, text: str) -> None:
    with pytest.raises(ProtocolError):
        encode_request(request_id, text)
