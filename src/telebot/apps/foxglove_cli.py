"""``telebot-user foxglove`` and ``telebot-user record``: the commands around the bridge.

The bridge itself (:class:`~telebot.apps.foxglove_bridge.FoxgloveBridge`: a client's
streams as Foxglove channels, goals, teleop and command services) is
:mod:`telebot.apps.foxglove_bridge`; this module checks the command's arguments (port
free, output file writable: a one-line error and exit code 2), calls the robot, wires the
bridge to a server and/or an MCAP file, shows the recording's progress and returns the
exit code.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TextIO

from telebot.apps.common import EXIT_OK, EXIT_USAGE, stop_on_signals
from telebot.apps.foxglove_bridge import TELEOP_RATE, TELEOP_TOPIC, FoxgloveBridge
from telebot.channels.transports.base import Transport
from telebot.config import AppConfig
from telebot.services.client import connect

__all__ = ["Progress", "check_output_file", "check_port", "record_session", "serve_foxglove"]


def check_output_file(path: Path) -> str | None:
    """Why ``path`` cannot be written as a recording (one line), or None if it can."""
    if path.is_dir():
        return f"{path} is a folder, not a file"
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        return f"cannot write {path}: no folder {parent}"
    if not os.access(parent, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        return f"cannot write {path}: permission denied"
    return None


def check_port(host: str, port: int) -> str | None:
    """Why ``host:port`` cannot be served on (one line), or None if it was free a moment ago."""
    if port == 0:
        return None
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except OSError as exc:
        return f"cannot serve on {host}:{port}: {exc.strerror or exc}"
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as sock:
        # As the server will: a port in TIME_WAIT is free, one with a listener is not.
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(address)
        except OSError as exc:
            return f"cannot serve on {host}:{port}: {exc.strerror or exc}"
    return None


class Progress:
    """The recording's progress on stderr: one line rewritten on a terminal, a line every
    :attr:`every` seconds otherwise, and a summary at the end."""

    def __init__(self, bridge: FoxgloveBridge, stream: TextIO = sys.stderr) -> None:
        self.bridge = bridge
        self.stream = stream
        self.tty = stream.isatty()
        self.every = 0.5 if self.tty else 10.0
        self.started = time.monotonic()

    def line(self) -> str:
        """``12.3 s, 456 messages (camera 300, pose 120, …), 1.2 MB``."""
        counts = self.bridge.counts
        total = sum(counts.values())
        top = sorted(counts.items(), key=lambda kv: -kv[1])[:4]
        parts = ", ".join(f"{topic.rsplit('/', 1)[-1]} {n}" for topic, n in top)
        size = ""
        if self.bridge.mcap is not None:
            with contextlib.suppress(OSError):
                size = f", {self.bridge.mcap.stat().st_size / 1e6:.1f} MB"
        elapsed = time.monotonic() - self.started
        return f"{elapsed:.1f} s, {total} messages ({parts}){size}"

    async def run(self) -> None:
        """Show the line until cancelled."""
        while True:
            await asyncio.sleep(self.every)
            if self.tty:
                self.stream.write(f"\r\033[Krecording: {self.line()}")
            else:
                self.stream.write(f"recording: {self.line()}\n")
            self.stream.flush()

    def finish(self, text: str) -> None:
        if self.tty:
            self.stream.write("\r\033[K")
        print(text, file=self.stream, flush=True)


def _usage_error(text: str) -> int:
    print(f"telebot-user: error: {text}", file=sys.stderr)
    return EXIT_USAGE


async def serve_foxglove(
    robot: str,
    *,
    home: Path,
    config: AppConfig,
    host: str = "127.0.0.1",
    port: int = 8765,
    topics: Sequence[str] = (),
    record: Path | None = None,
    stop: asyncio.Event | None = None,
    announce: Callable[[str], None] = print,
    transport: Transport | None = None,
    teleop_topic: str = TELEOP_TOPIC,
    teleop_rate: float = TELEOP_RATE,
) -> int:
    """``telebot-user foxglove``: call ``robot`` and serve it to Foxglove until Ctrl-C
    (or ``stop``); ``transport``: an open one to share (default: one from ``config``)."""
    if (problem := check_port(host, port)) is not None:
        return _usage_error(problem)
    if record is not None and (problem := check_output_file(record)) is not None:
        return _usage_error(problem)
    stop = stop or asyncio.Event()
    async with connect(
        robot, home=home, config=config, timeout=config.call.connect_timeout, transport=transport
    ) as client:
        bridge = FoxgloveBridge(
            client,
            host=host,
            port=port,
            mcap=record,
            topics=topics,
            teleop_topic=teleop_topic,
            teleop_rate=teleop_rate,
        )
        try:
            await bridge.start()
        except OSError as exc:
            await bridge.close()
            return _usage_error(str(exc))
        try:
            client.on_connection.append(lambda event: print(f"[{event}]", file=sys.stderr))
            announce(
                f"Foxglove: open a connection to {bridge.url} (role {client.call.role}); "
                "Ctrl-C to quit"
            )
            with stop_on_signals(stop):
                await stop.wait()
        finally:
            await bridge.close()
    return EXIT_OK


async def record_session(
    robot: str,
    output: Path,
    *,
    home: Path,
    config: AppConfig,
    duration: float | None = None,
    topics: Sequence[str] = (),
    stop: asyncio.Event | None = None,
    stream: TextIO = sys.stderr,
    transport: Transport | None = None,
    announce: Callable[[str], None] = print,
) -> int:
    """``telebot-user record``: write an MCAP of the robot's streams until ``duration`` s
    have passed or Ctrl-C; the file is finished (summary, index) either way."""
    if (problem := check_output_file(output)) is not None:
        return _usage_error(problem)
    stop = stop or asyncio.Event()
    async with connect(
        robot, home=home, config=config, timeout=config.call.connect_timeout, transport=transport
    ) as client:
        bridge = FoxgloveBridge(client, mcap=output, topics=topics)
        try:
            await bridge.start()
        except OSError as exc:
            await bridge.close()
            return _usage_error(str(exc))
        until = f"for {duration:g} s" if duration else "until Ctrl-C"
        announce(f"recording {robot} to {output} {until}")
        sys.stdout.flush()
        progress = Progress(bridge, stream)
        shown = asyncio.ensure_future(progress.run())
        try:
            with stop_on_signals(stop):
                ended = asyncio.ensure_future(client.wait_finished())
                stopped = asyncio.ensure_future(stop.wait())
                try:
                    await asyncio.wait(
                        {ended, stopped}, timeout=duration, return_when=asyncio.FIRST_COMPLETED
                    )
                finally:
                    ended.cancel()
                    stopped.cancel()
        finally:
            shown.cancel()
            await asyncio.gather(shown, return_exceptions=True)
            summary = progress.line()
            await bridge.close()
        progress.finish(f"recorded {output}: {summary}")
    return EXIT_OK
