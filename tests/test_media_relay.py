"""The web UI's media messages (``apps/web/media_relay.py``) and the robot screen's helpers."""

from __future__ import annotations

import json
import logging
import struct
import subprocess
import sys
from types import SimpleNamespace
from typing import Any, cast

import aiohttp
import pytest

from conftest import Homes
from telebot.apps.web.media_relay import MAX_VIDEO_FRAME, MediaRelay, pack_media, parse_media
from telebot.apps.web.screen import parse_screen_option, robot_screen
from telebot.channels.channel import ReceivedDatagram
from telebot.config import ScreenSettings
from telebot.services.video.wire import Report


def test_video_and_audio_round_trip() -> None:
    header = {"kind": "video", "codec": "vp8", "key": True, "frame_id": 7, "capture_time": 1.5}
    msg = parse_media(pack_media(header, b"\x01\x02"))
    assert (msg.kind, msg.codec, msg.key, msg.number, msg.capture_time, msg.data) == (
        "video",
        "vp8",
        True,
        7,
        1.5,
        b"\x01\x02",
    )
    audio = parse_media(pack_media({"kind": "audio", "seq": 2**32 - 1, "capture_time": 3}, b"x"))
    assert (audio.kind, audio.number, audio.data) == ("audio", 2**32 - 1, b"x")


def _raw(header: bytes, data: bytes = b"x") -> bytes:
    return struct.pack(">I", len(header)) + header + data


VIDEO = {"kind": "video", "codec": "h264", "key": False, "frame_id": 1, "capture_time": 0.0}


@pytest.mark.parametrize(
    ("message", "fault"),
    [
        (b"\x00\x00", "4-byte header length"),
        (struct.pack(">I", 5000) + b"{}", "header length"),
        (struct.pack(">I", 50) + b"{}", "header length"),
        (_raw(b"\xff\xfe"), "not JSON"),
        (_raw(b"[1, 2]"), "not a JSON object"),
        (_raw(json.dumps({**VIDEO, "codec": "jpeg"}).encode()), "not offered"),
        (_raw(json.dumps({**VIDEO, "codec": "av1"}).encode()), "not offered"),
        (_raw(json.dumps({**VIDEO, "key": 1}).encode()), "key must be"),
        (_raw(json.dumps({**VIDEO, "frame_id": -1}).encode()), "frame_id"),
        (_raw(json.dumps({**VIDEO, "frame_id": 2**32}).encode()), "frame_id"),
        (_raw(json.dumps({**VIDEO, "frame_id": True}).encode()), "frame_id"),
        (_raw(json.dumps({**VIDEO, "capture_time": "now"}).encode()), "capture_time"),
        (_raw(json.dumps({**VIDEO, "capture_time": -1}).encode()), "capture_time"),
        (_raw(json.dumps({**VIDEO, "capture_time": 10**400}).encode()), "capture_time"),
        (_raw(json.dumps(VIDEO).encode(), b""), "video frame must be"),
        (_raw(json.dumps(VIDEO).encode(), b"x" * (MAX_VIDEO_FRAME + 1)), "video frame must be"),
        (_raw(b'{"kind": "audio", "seq": 1, "capture_time": 1}', b"x" * 2000), "Opus packet"),
        (_raw(b'{"kind": "audio", "seq": 1.5, "capture_time": 1}'), "seq"),
        (_raw(b'{"kind": "text", "capture_time": 1}'), "unknown media kind"),
    ],
)
def test_garbage_is_one_clear_error(message: bytes, fault: str) -> None:
    with pytest.raises(ValueError, match=fault) as info:
        parse_media(message)
    assert "\n" not in str(info.value)


def test_nan_capture_time_is_refused() -> None:
    raw = b'{"kind": "audio", "seq": 1, "capture_time": NaN}'
    with pytest.raises(ValueError, match="finite"):
        parse_media(_raw(raw))


def test_screen_option() -> None:
    default = ScreenSettings()
    assert parse_screen_option("off", default).enabled is False
    assert parse_screen_option("0.0.0.0:9000", default) == ScreenSettings(host="0.0.0.0", port=9000)
    assert parse_screen_option(":9001", default).port == 9001
    assert parse_screen_option("9002", default) == ScreenSettings(port=9002)
    assert parse_screen_option("[::1]:9003", default).host == "::1"
    for bad in ("here", "host:port", "1:70000"):
        with pytest.raises(ValueError, match=r"HOST:PORT|port must be"):
            parse_screen_option(bad, default)


async def test_the_screen_is_served_and_a_taken_port_is_only_a_warning(
    caplog: pytest.LogCaptureFixture,
) -> None:
    async with robot_screen(ScreenSettings(port=0), None) as screen:
        assert screen is not None
        async with aiohttp.ClientSession() as http:
            async with http.get(screen.url) as response:
                assert response.status == 200 and "screen.js" in await response.text()
            async with http.get(screen.url + "static/media.js") as response:
                assert response.status == 200
        # A second robot on the same port: no screen, a warning, no exception.
        with caplog.at_level(logging.WARNING, logger="telebot.apps.web.screen"):
            async with robot_screen(ScreenSettings(port=screen.port), None) as other:
                assert other is None
        assert "robot screen not served" in caplog.text
    async with robot_screen(ScreenSettings(enabled=False), None) as off:
        assert off is None


def test_a_bad_screen_option_is_a_usage_error(homes: Homes) -> None:
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "telebot.apps.robot_cli",
            "run",
            "--home",
            str(homes.robot_home),
            "--screen",
            "somewhere",
        ],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip() == (
        "telebot-robot: error: --screen: expected HOST:PORT or off, got 'somewhere'"
    )


class _Sink:
    """A page server for the relay (the :class:`PageSink` it talks to): records what goes
    to the pages."""

    def __init__(self, pages: set[object]) -> None:
        self.pages = pages
        self.sent: list[tuple[object, dict[str, Any]]] = []
        self.audio: list[bytes] = []

    def send(self, page: object, message: dict[str, Any]) -> None:
        self.sent.append((page, message))

    def broadcast_audio(self, data: bytes) -> None:
        self.audio.append(data)

    def codecs_changed(self) -> None:
        pass


async def test_the_robots_reports_on_the_users_camera_go_to_the_sending_page() -> None:
    """Each REPORT of ``video/user`` reaches the page that sends the camera as an
    ``uplink_report`` (its encoder's bit rate follows it); a reordered one and a BYE do not."""
    page, other = object(), object()
    sink = _Sink({page, other})
    sent = sink.sent
    relay = MediaRelay(sink, cast(Any, SimpleNamespace()))  # the reports need no client
    relay.encode = {page: ("vp8",), other: ("vp8",)}
    relay.sender = page

    def report(receiver_ms: int, *, bye: bool = False) -> None:
        payload = Report(receiver_ms, 120, 100, 90000, 40, 3, 17, bye=bye, codecs=(4,)).encode()
        relay.uplink._on_report(ReceivedDatagram("video/user", "guiabot", payload, 0.0))

    report(5000)
    report(4000)  # reordered
    report(5200, bye=True)
    reports = [(p, m) for p, m in sent if m["type"] == "uplink_report"]
    assert reports == [
        (
            page,
            {
                "type": "uplink_report",
                "receiver_ms": 5000,
                "highest_seq": 120,
                "fragments": 100,
                "bytes": 90000,
                "frames": 40,
                "dropped": 3,
                "queue_delay_ms": 17,
            },
        )
    ]
