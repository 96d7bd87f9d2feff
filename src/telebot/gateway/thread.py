"""A :class:`~telebot.gateway.server.Gateway` on a thread of its own, with its own asyncio
loop and its own transport over an open zenoh session: browser traffic (TLS, websockets,
JSON, budgets) never runs on the loop of the process that serves it (the robot's control
loop, the router's), and its CPU can be measured on its own (bench/browser.py reads the
threads named :data:`THREAD_NAME` under ``/proc/PID/task``).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import threading
from collections.abc import Callable

from telebot.channels.transports.base import Transport
from telebot.channels.transports.zenoh import ZenohTransport, name_os_thread
from telebot.gateway.server import Gateway

__all__ = ["THREAD_NAME", "GatewayThread"]

log = logging.getLogger(__name__)

#: The gateway thread's name, also given to the OS (``/proc/PID/task/TID/comm``, at most
#: 15 bytes) so that its CPU can be told apart from the robot's or the router's (bench/browser.py).
THREAD_NAME = "telebot-gateway"


class GatewayThread:
    """A :class:`Gateway` on a thread of its own, with its own loop and its own transport
    over an open zenoh ``session`` (and its owner's ``data_session`` for calls' data keys,
    if it has one: ``[transport.zenoh] data_session``). :meth:`start` returns once it
    listens (OSError if it cannot); :meth:`stop` closes it and joins the thread."""

    def __init__(
        self,
        session: object,
        make: Callable[[Transport], Gateway],
        data_session: object | None = None,
    ) -> None:
        self._session = session
        self._data_session = data_session
        self._make = make
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._started: concurrent.futures.Future[Gateway] = concurrent.futures.Future()
        self._thread = threading.Thread(target=self._run, name=THREAD_NAME, daemon=True)
        self.gateway: Gateway | None = None

    async def start(self) -> Gateway:
        self._thread.start()
        self.gateway = await asyncio.wrap_future(self._started)
        return self.gateway

    async def stop(self) -> None:
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None:
            with contextlib.suppress(RuntimeError):  # its loop already ended
                loop.call_soon_threadsafe(stop.set)
        await asyncio.to_thread(self._thread.join, 10.0)

    def _run(self) -> None:
        name_os_thread(THREAD_NAME)
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # reported to start() if it has not returned yet
            if not self._started.done():
                self._started.set_exception(exc)
            else:
                log.error("gateway: its thread ended: %s", exc)

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        transport = ZenohTransport(reader_name=THREAD_NAME)
        await transport.adopt(self._session, self._data_session)  # type: ignore[arg-type]
        try:
            gateway = self._make(transport)
            await gateway.start()
            try:
                self._started.set_result(gateway)
                await self._stop.wait()
            finally:
                await gateway.close()
        finally:
            await transport.close()
