"""The robot's own gateway (``[gateway]`` of ``telebot-robot run``): over the daemon's
transport, admitting its contacts and invites, with its certificate or a self-signed one."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import AsyncIterator
from pathlib import Path

from telebot.channels.transports.base import Transport
from telebot.config import GatewaySettings
from telebot.gateway.admission import ContactsAdmitter
from telebot.gateway.server import Gateway
from telebot.gateway.tls import local_hosts, self_signed, server_context
from telebot.identity import ContactBook

__all__ = ["GATEWAY_DIR", "robot_gateway", "robot_tls_files"]

log = logging.getLogger("telebot.gateway")

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
    taken is a warning (the robot runs on without its gateway)."""
    if settings is None or not settings.enabled:
        yield None
        return
    cert, key = robot_tls_files(settings, home)
    gateway = Gateway(
        transport,
        ContactsAdmitter(contacts, home),
        namespace=namespace,
        host=settings.listen,
        port=settings.port,
        ssl_context=server_context(cert, key),
    )
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
