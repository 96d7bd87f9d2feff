"""The gateway's start page (static/gateway.html, web/src/setup.js) on a phone in chromium:
make a key, see its contact line and QR code, pin robots (pasted line; invite link), KEY
MISMATCH for a second key, and the call button opening the robot page.

The page is served here as a gateway serves it (``/`` the start page, ``/static/`` the
files, ``/call`` the robot page); it runs the committed bundle (static/telebot-client.js).
There is no gateway behind it: an invite accepted here cannot be redeemed, and the page
must then pin nothing. An invite redeemed through a real robot's gateway is
tests/test_browser_e2e.py's.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

from aiohttp import web

from test_web_phone import phone_page

STATIC = Path(__file__).resolve().parent.parent / "src" / "telebot" / "apps" / "web" / "static"
ROBOT_KEY = "uoS2y5C4ipVqEcWt6Ph1pcpGVUtFZQk0MdHdIrl4x2w"
OTHER_KEY = "hSDwCYkwp1R0i33ctD73Wg2_Og0mOBr066SpjqqbTmo"


@contextlib.asynccontextmanager
async def start_page_server() -> AsyncIterator[str]:
    """``/``: gateway.html, ``/call``: index.html, ``/static/``: the files (as a gateway)."""

    def serve(name: str) -> Any:
        async def handler(_request: web.Request) -> web.FileResponse:
            return web.FileResponse(STATIC / name)

        return handler

    app = web.Application()
    app.router.add_get("/", serve("gateway.html"))
    app.router.add_get("/call", serve("index.html"))
    app.router.add_static("/static/", STATIC)
    runner = web.AppRunner(app)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    port = runner.addresses[0][1]
    try:
        yield f"http://127.0.0.1:{port}/"
    finally:
        await runner.cleanup()


async def setup_state(page: Any) -> dict[str, Any]:
    value: dict[str, Any] = await page.evaluate(
        "() => ({line: window.telebotSetup.line, robots: window.telebotSetup.robots,"
        " error: window.telebotSetup.error, invite: window.telebotSetup.invite})"
    )
    return value


async def test_a_key_is_made_shown_and_kept_and_robots_are_pinned() -> None:
    async with start_page_server() as url, phone_page(url) as page:
        await page.wait_for_selector("#create-key", state="visible")
        await page.fill("#new-name", "nurse_ann")
        await page.tap("#create-key")
        await page.wait_for_selector("#contact-line", state="visible")
        line = await page.inner_text("#contact-line")
        assert re.fullmatch(r"telebot-x25519 [A-Za-z0-9_-]{43} nurse_ann", line), line
        assert await page.locator("#qr svg").count() == 1
        # Kept in IndexedDB: the same key after a reload.
        await page.reload()
        await page.wait_for_selector("#contact-line", state="visible")
        assert await page.inner_text("#contact-line") == line
        # Pin a robot from its line; the same name with another key is KEY MISMATCH.
        await page.fill("#pin-line", f"telebot-x25519 {ROBOT_KEY} guiabot")
        await page.tap("#pin")
        await page.wait_for_selector("li[data-robot=guiabot]")
        await page.fill("#pin-line", f"telebot-x25519 {OTHER_KEY} guiabot")
        await page.tap("#pin")
        await page.wait_for_function("() => window.telebotSetup.error.length > 0")
        state = await setup_state(page)
        assert state["error"].startswith("KEY MISMATCH: robot guiabot"), state["error"]
        assert "KEY MISMATCH" in await page.inner_text("#setup-error")
        assert [(r["name"], r["key"]) for r in state["robots"]] == [("guiabot", ROBOT_KEY)]
        # A bad line: one line of error, nothing pinned.
        await page.fill("#pin-line", "not a robot line")
        await page.tap("#pin")
        await page.wait_for_function("() => !window.telebotSetup.error.startsWith('KEY')")
        assert "\n" not in (await setup_state(page))["error"]
        # The call button opens the robot page for it.
        await page.tap("li[data-robot=guiabot] .call")
        await page.wait_for_url(re.compile(r"/call\?robot=guiabot$"))


async def test_an_invite_that_cannot_be_redeemed_pins_nothing() -> None:
    async with start_page_server() as url:
        link = f"{url}#invite=tok_1&robot=wardbot&key={ROBOT_KEY}"
        async with phone_page(link) as page:
            await page.wait_for_selector("#invite", state="visible")
            assert await page.inner_text("#invite-robot") == "wardbot"
            # No key yet: accept waits for one.
            assert await page.is_disabled("#accept-invite")
            await page.fill("#new-name", "bob")
            await page.tap("#create-key")
            await page.wait_for_function("() => !document.getElementById('accept-invite').disabled")
            await page.tap("#accept-invite")
            # No gateway answers: one line says so, the robot pinned for it is unpinned,
            # and the invite stays (in the address too) to be tried again.
            await page.wait_for_function("() => window.telebotSetup.error.length > 0")
            state = await setup_state(page)
            assert "gateway" in state["error"] and "\n" not in state["error"], state["error"]
            assert state["robots"] == []
            assert state["invite"] is not None and state["invite"]["robot"] == "wardbot"
            assert "invite=tok_1" in page.url
            assert await page.is_enabled("#accept-invite")
            await page.goto(f"{url}#invite=x&robot=wardbot&key=short")
            await page.wait_for_function("() => window.telebotSetup.error.startsWith('the invite')")
            assert "invite link" in (await setup_state(page))["error"]
