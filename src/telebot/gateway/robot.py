"""The robot's own gateway (``[gateway]`` of ``telebot-robot run``): admitting its contacts
and invites, with its certificate or a self-signed one.

Browsers are untrusted traffic: the gateway never runs on the robot's control loop. It has a
thread of its own with its own asyncio loop (TLS, websockets, JSON, budgets all happen there)
and its own transport over the daemon's zenoh session (its own subscriptions, reader threads
and publishers; zenoh's lanes put a stop ahead of video), so a stop from any user waits
behind no browser's frames on the robot's loop. A redeemed invite reaches the daemon's
contact book through ``call_soon_threadsafe`` on the daemon's loop, before the browser is
told it is admitted.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import threading
from collections.abc import AsyncIterator, Callable
from pathlib import Path

from telebot.channels.transports.base import Transport
from telebot.channels.transports.zenoh import ZenohTransport, name_os_thread
from telebot.config import GatewaySettings
from telebot.gateway.admission import ContactsAdmitter
from telebot.gateway.server import Gateway
from telebot.gateway.tls import local_hosts, self_signed, server_context
from telebot.identity import ContactBook

__all__ = ["GATEWAY_DIR", "THREAD_NAME", "GatewayThread", "robot_gateway", "robot_tls_files"]

log = logging.getLogger("telebot.gateway")

#: Under the robot's home: the self-signed certificate made when none is configured.
GATEWAY_DIR = "gateway"
#: The gateway thread's name, also given to the OS (``/proc/PID/task/TID/comm``, at most
#: 15 bytes) so that its CPU can be told apart from the robot's (bench/browser.py).
THREAD_NAME = "telebot-gateway"


def robot_tls_files(settings: GatewaySettings, home: Path) -> tuple[Path, Path]:
    """The certificate and key to serve: configured, or self-signed under the home (made
    once, and said where)."""
    if settings.cert is not None and settings.key is not None:
        return home / settings.cert, home / settings.key
    hosts = local_hosts()
    if settings.listen not in ("0.0.0.0", "::", ""):
        hosts.append(settings.listen)
    cert, key, made = self_signed(home / GATEWAY_DIR, hosts)
    if made:
        log.warning(
            "gateway: made a self-signed certificate %s for %s; browsers warn until it is "
            "trusted (install it on the device, or set [gateway] cert and key)",
            cert,
            ", ".join(hosts),
        )
    return cert, key


class GatewayThread:
    """A :class:`Gateway` on a thread of its own, with its own loop and its own transport
    over an open zenoh ``session``. :meth:`start` returns once it listens (OSError if it
    cannot); :meth:`stop` closes it and joins the thread."""

    def __init__(self, session: object, make: Callable[[Transport], Gateway]) -> None:
        self._session = session
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
        await transport.adopt(self._session)  # type: ignore[arg-type]
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


@contextlib.asynccontextmanager
async def robot_gateway(
    settings: GatewaySettings | None,
    transport: Transport,
    contacts: ContactBook,
    home: Path,
    namespace: str,
) -> AsyncIterator[Gateway | None]:
    """Serve the gateway while inside, if ``settings`` ask for it; an address already
    taken is a warning (the robot runs on without its gateway).

    Over zenoh it runs on its own thread (:class:`GatewayThread`); over another transport
    (the in-process one of tests) on this loop."""
    if settings is None or not settings.enabled:
        yield None
        return
    cert, key = robot_tls_files(settings, home)
    context = server_context(cert, key)
    loop = asyncio.get_running_loop()

    def hand_over(fn: Callable[[], None]) -> None:
        loop.call_soon_threadsafe(fn)

    def make(over: Transport) -> Gateway:
        return Gateway(
            over,
            ContactsAdmitter(contacts, home, hand_over=hand_over),
            namespace=namespace,
            host=settings.listen,
            port=settings.port,
            ssl_context=context,
        )

    if isinstance(transport, ZenohTransport):
        thread = GatewayThread(transport.session, make)
        try:
            gateway = await thread.start()
        except OSError as exc:
            log.warning("gateway: cannot listen on %s:%s: %s", settings.listen, settings.port, exc)
            yield None
            return
        try:
            yield gateway
        finally:
            await thread.stop()
        return
    gateway = make(transport)
    try:
        await gateway.start()
    except OSError as exc:
        log.warning("gateway: cannot listen on %s:%s: %s", settings.listen, settings.port, exc)
        yield None
        return
    try:
        yield gateway
    finally:
        await gateway.close()
