"""Transports by name, python-can style.

Built-in transports are listed in :data:`BUILTIN_TRANSPORTS` as name -> (module, class)
and imported only when asked for, so ``import telebot`` never imports zenoh. Third-party
transports register in the entry-point group ``telebot.transports``::

    [project.entry-points."telebot.transports"]
    mylink = "mypkg.transport:MyLinkTransport"

A transport class is built with ``cls.from_settings(settings)``, where ``settings`` is the
:class:`~telebot.config.TransportSettings` (a third party reads ``settings.options``).
"""

from __future__ import annotations

from telebot.channels.transports.base import (
    Lane,
    Presence,
    Publisher,
    Sample,
    Subscription,
    Transport,
    TransportStats,
)
from telebot.config import TransportSettings
from telebot.errors import TransportError, UnknownTransport
from telebot.registry import Registry

__all__ = [
    "BUILTIN_TRANSPORTS",
    "ENTRY_POINT_GROUP",
    "Lane",
    "Presence",
    "Publisher",
    "Sample",
    "Subscription",
    "Transport",
    "TransportStats",
    "create_transport",
    "get_transport_class",
    "known_transports",
]

ENTRY_POINT_GROUP = "telebot.transports"

BUILTIN_TRANSPORTS: dict[str, tuple[str, str]] = {
    "zenoh": ("telebot.channels.transports.zenoh", "ZenohTransport"),
    "memory": ("telebot.channels.transports.memory", "MemoryTransport"),
}


_REGISTRY: Registry[Transport] = Registry(
    what="transport",
    group=ENTRY_POINT_GROUP,
    builtins=BUILTIN_TRANSPORTS,
    accepts=lambda cls: isinstance(cls, type) and issubclass(cls, Transport),
    shape="a telebot Transport subclass",
    error=TransportError,
    unknown=UnknownTransport,
)


def known_transports() -> list[str]:
    """Names of every transport that can be created: built-in and installed plug-ins."""
    return _REGISTRY.known()


def get_transport_class(name: str) -> type[Transport]:
    """The transport class registered as ``name``; imports its module on first use."""
    return _REGISTRY.get(name)


def create_transport(settings: TransportSettings | None = None) -> Transport:
    """Build (not yet open) the transport that ``settings.kind`` names."""
    settings = settings or TransportSettings()
    cls = get_transport_class(settings.kind)
    return cls.from_settings(settings)
