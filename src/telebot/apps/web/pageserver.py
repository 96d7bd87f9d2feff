"""The base of the local pages' servers: the robot's page, the fleet page, the robot's screen.

Each serves ``static/`` (package data: no build step, nothing fetched from the internet),
one HTML page and a websocket on ``host:port`` (port 0 picks a free one), owns its
background tasks and ends them on exit. :class:`PageServer` is that part once; a page adds
its routes (:meth:`PageServer.routes`) and what its websocket says.
"""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from importlib import resources
from pathlib import Path
from types import TracebackType
from typing import Any, Self

from aiohttp import WSMsgType, web

from telebot.apps.tasks import EXPECTED_ENDINGS, BackgroundTasks

__all__ = ["STATIC", "PageServer"]

#: Where the pages' files are (shipped as package data).
STATIC = resources.files("telebot.apps.web") / "static"


class PageServer:
    """An aiohttp server of one local page: ``async with Page(...) as page: print(page.url)``.

    A subclass adds its routes in :meth:`routes` (``/static/`` is added here) and may
    extend :meth:`start` and :meth:`close`; ``owner`` names its tasks in the log.
    """

    def __init__(
        self,
        *,
        host: str,
        port: int,
        owner: str,
        expected: tuple[type[BaseException], ...] = EXPECTED_ENDINGS,
    ) -> None:
        self.host = host
        self.port = port
        self._tasks = BackgroundTasks(owner, expected=expected)
        self._runner: web.AppRunner | None = None

    @property
    def url(self) -> str:
        """The page's address."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def routes(self, router: web.UrlDispatcher) -> None:
        """Add the page's routes (a subclass's part)."""
        raise NotImplementedError

    async def serve(self) -> None:
        """Listen on ``host:port`` (OSError if the address is taken, nothing left open)."""
        app = web.Application()
        self.routes(app.router)
        app.router.add_static("/static/", Path(str(STATIC)), show_index=False)
        self._runner = web.AppRunner(app, handle_signals=False, access_log=None)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.host, self.port)
        try:
            await site.start()
        except OSError:
            await self._runner.cleanup()
            self._runner = None
            raise
        if self.port == 0:
            sockets = getattr(site._server, "sockets", None) or []
            self.port = int(sockets[0].getsockname()[1])

    async def stop_serving(self) -> None:
        """Close the server and end every task of the page; idempotent."""
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        await self._tasks.cancel_all()

    async def start(self) -> None:
        """Serve the page (a subclass may start more)."""
        await self.serve()

    async def close(self) -> None:
        """Close the server (a subclass closes its pages first)."""
        await self.stop_serving()

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    # -- helpers for the pages ------------------------------------------------------------

    @staticmethod
    def html(name: str) -> web.Response:
        """``static/NAME`` as the page's HTML (never cached: the page is this version's)."""
        text = (STATIC / name).read_text(encoding="utf-8")
        return web.Response(
            text=text, content_type="text/html", headers={"Cache-Control": "no-store"}
        )

    @staticmethod
    async def accept(
        request: web.Request, *, heartbeat: float, max_msg_size: int
    ) -> web.WebSocketResponse:
        """Accept a page's websocket: pinged every ``heartbeat`` s (a page silent for twice
        that is gone), messages up to ``max_msg_size`` bytes.

        No permessage-deflate (as the gateway's): most of what goes out is video and sound,
        compressed already, and deflating it took the event loop's time 30 pictures a
        second for nothing (seen at the top of a busy test worker's stack)."""
        ws = web.WebSocketResponse(heartbeat=heartbeat, max_msg_size=max_msg_size, compress=False)
        await ws.prepare(request)
        return ws

    @staticmethod
    async def received(ws: web.WebSocketResponse) -> AsyncIterator[str | bytes]:
        """The page's text (``str``) and binary (``bytes``) messages until it goes away."""
        async for msg in ws:
            if msg.type == WSMsgType.TEXT or msg.type == WSMsgType.BINARY:
                yield msg.data
            elif msg.type == WSMsgType.ERROR:
                break

    def send_json(self, ws: web.WebSocketResponse, message: dict[str, Any]) -> None:
        """``message`` to one websocket, without waiting (dropped if it closed)."""
        if not ws.closed:
            self._tasks.spawn(ws.send_str(json.dumps(message)))

    def send_all(self, sockets: list[web.WebSocketResponse], message: dict[str, Any]) -> None:
        """``message`` to every open websocket of ``sockets``, encoded once."""
        text = json.dumps(message)
        for ws in sockets:
            if not ws.closed:
                self._tasks.spawn(ws.send_str(text))
