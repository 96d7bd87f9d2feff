"""The page's port (static/app.js): the same page driven by a port object instead of its
websocket, as a gateway-served page is driven by the in-browser client (web/src/page-port.js).
Here a stand-in port in the page records what the page sends and feeds it §19 messages as
objects and a JPEG picture as a parsed ``{header, data}``; chromium on a phone viewport.
"""

from __future__ import annotations

import base64
import io
import math
from typing import Any

from PIL import Image

from test_web_phone import phone_page
from test_web_setup import start_page_server

FAKE_PORT = """
window.fake = { sent: [], h: null };
window.telebotPort = {
  connect(h) { window.fake.h = h; h.open(); },
  send(m) { window.fake.sent.push(m); return true; },
  sendMedia() { return true; },
};
"""


def png_data_url(width: int, height: int) -> str:
    out = io.BytesIO()
    Image.new("L", (width, height), 255).save(out, "PNG")
    return "data:image/png;base64," + base64.b64encode(out.getvalue()).decode()


def jpeg_bytes(width: int, height: int) -> list[int]:
    out = io.BytesIO()
    Image.new("RGB", (width, height), (200, 30, 30)).save(out, "JPEG")
    return list(out.getvalue())


async def feed(page: Any, message: dict[str, Any]) -> None:
    await page.evaluate("(m) => window.fake.h.message(m)", message)


async def sent(page: Any, kind: str) -> list[dict[str, Any]]:
    value: list[dict[str, Any]] = await page.evaluate(
        "(t) => window.fake.sent.filter((m) => m.type === t)", kind
    )
    return value


async def test_the_page_runs_on_a_port_object_messages_media_goals_and_stops() -> None:
    async with start_page_server() as url, phone_page("about:blank") as page:
        await page.add_init_script(FAKE_PORT)  # before app.js runs
        await page.goto(url + "call")
        await page.wait_for_function("() => window.fake && window.fake.h")
        # On open the page says what it decodes, as on a websocket.
        assert (await sent(page, "media"))[0]["decode"]
        the_map = {
            "url": png_data_url(200, 100),
            "resolution": 0.05,
            "origin_x": 0.0,
            "origin_y": 0.0,
            "width": 200,
            "height": 100,
            "version": 0,
        }
        await feed(
            page,
            {
                "type": "hello",
                "robot": "guiabot",
                "user": "alice",
                "role": "driver",
                "may_drive": True,
                "map": the_map,
            },
        )
        pose = {
            "type": "pose",
            "x": 1.0,
            "y": 1.0,
            "yaw": 0.0,
            "v": 0.0,
            "w": 0.0,
            "state": "idle",
            "detail": "",
            "goal": None,
            "t": 0,
            "recv": 0,
        }
        await feed(page, pose)
        await feed(
            page,
            {
                "type": "safety",
                "armed": True,
                "text": "",
                "holder": "alice",
                "cap": 1.0,
                "blocked": False,
            },
        )
        await page.wait_for_function("() => window.telebotUI.mapReady()")
        assert await page.title() == "telebot · guiabot"
        # A JPEG picture as {header, data}: shown.
        await page.evaluate(
            """(bytes) => window.fake.h.media(
                     {kind: "video", codec: "jpeg", key: true, frame_id: 0, camera: "navcam",
                      capture_time: Date.now() / 1000}, new Uint8Array(bytes))""",
            jpeg_bytes(64, 48),
        )
        await page.wait_for_function("() => document.getElementById('video').naturalWidth === 64")
        assert await page.evaluate("() => window.telebotUI.state.camera") == "navcam"
        # A tap on the map: the goal goes out through the port.
        target = (6.0, 2.5)
        sx, sy = await page.evaluate(f"() => window.telebotUI.worldToScreen{target}")
        box = await page.locator("#map").bounding_box()
        await page.touchscreen.tap(box["x"] + sx, box["y"] + sy)
        await page.wait_for_function("() => window.fake.sent.some((m) => m.type === 'goal')")
        goal = (await sent(page, "goal"))[0]
        assert math.dist((goal["x"], goal["y"]), target) < 0.1 and goal["yaw"] is None
        # Hidden while armed: the stop goes out through the port too.
        await page.evaluate(
            """() => { Object.defineProperty(document, 'visibilityState',
                     {value: 'hidden', configurable: true});
                   document.dispatchEvent(new Event('visibilitychange')); }"""
        )
        assert await sent(page, "stop") == [{"type": "stop", "how": "page_hidden"}]
