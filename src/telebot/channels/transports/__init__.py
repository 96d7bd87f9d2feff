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

import importlib
from importlib.metadata import entry_points
from typing import Any, cast

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


def _plugin_entry_points() -> dict[str, Any]:
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def known_transports() -> list[str]:
    """Names of every transport that can be created: built-in and installed plug-ins."""
    return sorted(set(BUILTIN_TRANSPORTS) | set(_plugin_entry_points()))


def get_transport_class(name: str) -> type[Transport]:
    """The transport class registered as ``name``; imports its module on first use."""
    if name in BUILTIN_TRANSPORTS:
        module_name, class_name = BUILTIN_TRANSPORTS[name]
        try:
            module = importlib.import_module(module_name)
        except ImportError as exc:
            raise TransportError(f"transport {name!r} cannot be imported: {exc}") from exc
        return cast(type[Transport], getattr(module, class_name))
    plugins = _plugin_entry_points()
    if name in plugins:
        try:
            cls = plugins[name].load()
        except Exception as exc:  # a broken plug-in must not take the caller down
            raise TransportError(f"transport {name!r} failed to load: {exc}") from exc
        if not (isinstance(cls, type) and issubclass(cls, Transport)):
            raise TransportError(f"transport {name!r} is not a telebot Transport subclass")
        return cls
    raise UnknownTransport(
        f"unknown transport {name!r}; known transports: {', '.join(known_transports())}"
    )


def create_transport(settings: TransportSettings | None = None) -> Transport:
    """Build (not yet open) the transport that ``settings.kind`` names."""
    settings = settings or TransportSettings()
    cls = get_transport_class(settings.kind)
    return cls.from_settings(settings)
