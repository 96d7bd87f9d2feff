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
import contextlib
import logging
from collections.abc import AsyncIterator, Callable
from pathlib import Path

from telebot.channels.transports.base import Transport
from telebot.channels.transports.zenoh import ZenohTransport
from telebot.config import GatewaySettings
from telebot.gateway.admission import ContactsAdmitter
from telebot.gateway.server import Gateway
from telebot.gateway.thread import THREAD_NAME, GatewayThread
from telebot.gateway.tls import local_hosts, self_signed, server_context
from telebot.identity import ContactBook

__all__ = ["GATEWAY_DIR", "THREAD_NAME", "GatewayThread", "robot_gateway", "robot_tls_files"]

log = logging.getLogger(__name__)

#: Under the robot's home: the self-signed certificate made when none is configured.
GATEWAY_DIR = "gateway"


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
        # The robot's calls' data rides its data session when it has one (a client of a
        # router on QUIC): the gateway's must too, or the two would meet only through the
        # router, whose access control lets neither through.
        thread = GatewayThread(transport.session, make, transport.data_session)
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
