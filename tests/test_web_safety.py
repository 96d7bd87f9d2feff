"""The page's safety marks (issue 26 §3), driven through a stand-in port in chromium (as
tests/test_web_port.py): a picture that stopped moving is marked frozen at once (and not
when no video comes at all); a robot that stopped itself (the deadman after a silent link,
a dropped call, a frozen picture) gets one sentence and one big Re-arm for the drive
holder, while a stop someone made shows the plain stopped state; and the robot's REPORTs
on the user's camera (`uplink_report`) set the page's upload bit rate.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import AsyncIterator
from typing import Any

from test_web_phone import phone_page
from test_web_port import FAKE_PORT, feed, jpeg_bytes, sent
from test_web_setup import start_page_server

# _chromium: one chromium for the module; _no_leaked_tasks: the leak check in its loop.
from test_web_ui import (
    _chromium,  # noqa: F401
    _no_leaked_tasks,  # noqa: F401
    in_module_loop,
)

HELLO = {
    "type": "hello",
    "robot": "guiabot",
    "user": "alice",
    "role": "driver",
    "may_drive": True,
    "map": None,
}


def safety(armed: bool, text: str = "", holder: str | None = "alice", **more: Any) -> dict:
    """A §18 state as the port passes it on (``code`` only when given: older robots)."""
    return {
        "type": "safety",
        "armed": armed,
        "text": text,
        "holder": holder,
        "cap": 0.5 if armed else 0.0,
        "blocked": False,
        **more,
    }


@contextlib.asynccontextmanager
async def fake_port_page() -> AsyncIterator[Any]:
    """The robot page on a stand-in port, greeted as alice, a driver."""
    async with start_page_server() as url, phone_page("about:blank") as page:
        await page.add_init_script(FAKE_PORT)  # before app.js runs
        await page.goto(url + "call")
        await page.wait_for_function("() => window.fake && window.fake.h")
        await feed(page, HELLO)
        yield page


async def show_picture(page: Any, frame_id: int) -> dict[str, Any]:
    """Show one JPEG picture; return the frozen mark right after it (``shown``, ``marks``).

    Read in the same turn of the page's loop as the picture: no later picture comes, so
    half a second on (a preempted page or test on a loaded machine) it is frozen again.
    """
    value: dict[str, Any] = await page.evaluate(
        """([bytes, id]) => {
             window.fake.h.media(
               {kind: "video", codec: "jpeg", key: true, frame_id: id, camera: "navcam",
                capture_time: Date.now() / 1000}, new Uint8Array(bytes));
             return {shown: !document.getElementById('frozen').hidden,
                     marks: window.telebotUI.frozen.marks};
           }""",
        [jpeg_bytes(64, 48), frame_id],
    )
    return value


async def alert(page: Any) -> dict[str, Any]:
    value: dict[str, Any] = await page.evaluate(
        """() => ({shown: !document.getElementById('alert').hidden,
                   text: document.getElementById('alert-text').textContent,
                   arm: !document.getElementById('alert-arm').hidden,
                   armEnabled: !document.getElementById('alert-arm').disabled,
                   safety: document.getElementById('safety').textContent})"""
    )
    return value


@in_module_loop
async def test_a_picture_that_stops_is_marked_frozen_until_the_next_one() -> None:
    async with fake_port_page() as page:
        # No video at all (none yet): a second of checks, and no mark.
        await page.wait_for_function("() => window.telebotUI.frozen.checks >= 10")
        assert await page.is_hidden("#frozen")
        assert await page.evaluate("() => window.telebotUI.frozen.marks") == 0
        await show_picture(page, 0)
        # No next picture: marked, with how long it has stood still (at least 0.5 s).
        await page.wait_for_function("() => !document.getElementById('frozen').hidden")
        text = await page.inner_text("#frozen")
        found = re.fullmatch(r"picture frozen — (\d+(?:\.\d)?) s", text)
        assert found and float(found.group(1)) >= 0.5, text
        # It counts up while the picture stays frozen.
        await page.wait_for_function(
            "(t) => document.getElementById('frozen').textContent !== t", arg=text
        )
        # The next picture clears it at once; the freeze was marked once.
        assert await show_picture(page, 1) == {"shown": False, "marks": 1}


@in_module_loop
async def test_a_self_stop_offers_one_rearm_and_a_users_stop_the_plain_state() -> None:
    async with fake_port_page() as page:
        await feed(page, safety(True))
        assert not (await alert(page))["shown"]
        # The deadman after a link blip: one sentence, one big Re-arm, for the holder.
        deadman = "driver alice's link lost: silent 0.45 s (deadman)"
        await feed(page, safety(False, deadman, code="link_silent"))
        a = await alert(page)
        assert a["shown"] and a["arm"] and a["armEnabled"], a
        assert a["text"].startswith("Your link went silent") and "re-arm" in a["text"], a
        assert "stopped itself" in a["text"] and a["safety"] == "stopped"
        button = await page.locator("#alert-arm").bounding_box()
        assert button is not None and button["height"] >= 40, button
        await page.tap("#alert-arm")
        assert await sent(page, "arm") == [{"type": "arm"}]
        await feed(page, safety(True))
        assert not (await alert(page))["shown"]
        # A stop the user made: the plain stopped state, no banner.
        await feed(page, safety(False, "stop requested by alice (key)", code="stopped"))
        a = await alert(page)
        assert not a["shown"] and a["safety"] == "stopped", a
        # A frozen picture (the robot's stale-video lockout), and a dropped call.
        await feed(page, safety(False, "video frozen for 1.0 s", code="video_stale"))
        a = await alert(page)
        assert a["shown"] and a["arm"] and a["text"].startswith("Your video froze"), a
        await feed(page, safety(False, "driver alice dropped", code="dropped"))
        assert (await alert(page))["text"].startswith("Your call dropped")
        # A robot without the state's code: told apart by its text.
        await feed(page, safety(False, "driver alice's link lost"))
        assert (await alert(page))["text"].startswith("Your link went silent")
        await feed(page, safety(False, deadman))
        assert (await alert(page))["text"].startswith("Your link went silent")
        await feed(page, safety(False, "stop requested by alice (button)"))
        assert not (await alert(page))["shown"]
        # Another driver's call dropped and the drive is free: said, but re-arm needs the
        # drive first.
        await feed(page, safety(False, "driver bob dropped", holder=None, code="dropped"))
        a = await alert(page)
        assert a["shown"] and not a["arm"] and a["text"].startswith("bob's call dropped"), a
        assert "take the drive" in a["text"]
        # Someone else holds the drive: not this page's business.
        await feed(page, safety(False, "driver bob's link lost", holder="bob", code="link_silent"))
        assert not (await alert(page))["shown"]
        # The chat log says each self-stop once.
        log = await page.inner_text("#chat-log")
        assert log.count("Your link went silent") == 2, log  # the fallback's is the same


@in_module_loop
async def test_the_robots_reports_of_loss_lower_the_upload_rate() -> None:
    async with fake_port_page() as page:
        start = await page.evaluate("() => window.telebotMedia.stats.sendBitrate")
        assert start == 600000
        # Reports every 200 ms, a fifth of the fragments lost (as the port passes them on).
        for i in range(1, 16):
            await feed(
                page,
                {
                    "type": "uplink_report",
                    "receiver_ms": 1000 + 200 * i,
                    "highest_seq": 10 * i,
                    "fragments": 8 * i,
                    "bytes": 8000 * i,
                    "frames": 8 * i,
                    "dropped": 0,
                    "queue_delay_ms": 5,
                },
            )
        s = await page.evaluate("() => window.telebotMedia.stats")
        assert s["uplinkReports"] == 15 and s["uplinkLoss"] > 0.1, s
        assert 150000 <= s["sendBitrate"] < start, s
