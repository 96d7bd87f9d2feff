"""A TCP relay on loopback that can be cut and restored: a Wi-Fi blip for zenoh.

Used by the reconnection tests and by ``bench/channels.py`` (section E). ``stop()``
aborts every relayed connection without a goodbye, as a dead link would; ``start()``
listens again on the same port.
"""

from __future__ import annotations

import asyncio
import contextlib
from typing import Any

from telebot.config import AppConfig
from telebot.testing.net import free_port


class TcpProxy:
    """A TCP relay on 127.0.0.1 to ``target``; :meth:`stop` cuts every connection."""

    def __init__(self, target: int) -> None:
        self.target = target
        self.port = free_port()
        self._server: asyncio.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._handlers: set[asyncio.Task[None]] = set()

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.port}"

    def client_config(self, reconnect: dict[str, Any]) -> AppConfig:
        """A user's config that reaches the robot only through this proxy.

        Client mode: a client connects only where it is told (a peer could find the
        robot's own port behind the proxy's back).
        """
        return AppConfig.model_validate(
            {
                "transport": {
                    "zenoh": {
                        "mode": "client",
                        "connect": [self.endpoint],
                        "multicast_scouting": False,
                    }
                },
                "reconnect": reconnect,
            }
        )

    async def start(self) -> None:
        self._server = await asyncio.start_server(
            self._handle, "127.0.0.1", self.port, reuse_address=True
        )

    async def stop(self) -> None:
        assert self._server is not None
        self._server.close()
        for writer in list(self._writers):
            writer.transport.abort()  # as a dead Wi-Fi link: no goodbye
        await self._server.wait_closed()
        await asyncio.gather(*self._handlers, return_exceptions=True)
        self._server = None

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._handlers.add(task)
        self._writers.add(writer)
        try:
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.target)
        except OSError:
            writer.transport.abort()
            return
        self._writers.add(up_writer)
        try:
            await asyncio.gather(_pipe(reader, up_writer), _pipe(up_reader, writer))
        finally:
            for w in (writer, up_writer):
                w.transport.abort()
                self._writers.discard(w)
            self._handlers.discard(task)


async def _pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    with contextlib.suppress(OSError, asyncio.IncompleteReadError):
        while data := await reader.read(65536):
            writer.write(data)
            await writer.drain()
    writer.transport.abort()
