"""Transports by name, python-can style.

Built-in transports are listed in :data:`BUILTIN_TRANSPORTS` as name -> (module, class)
and imported only when asked for, so ``import telebot`` never imports zenoh. Third-party
transports register in the entry-point group ``telebot.transports``::

    [project.entry-points."telebot.transports"]
    mylink = "mypkg.transport:MyLinkTransport"

A transport class is built with ``cls.from_settings(settings)``, where ``settings`` is the
:class:`~telebot.config.TransportSettings`. A transport declares its own settings: a
built-in its ``[transport.<section>]`` table (:attr:`Transport.section`), a plug-in the
model of its ``[transport.options]`` (:attr:`Transport.options_model`, read back with
:func:`plugin_options`), and each its command-line flags (:attr:`Transport.cli_options`),
which the command lines add from here (:func:`declared_cli_options`, :func:`apply_cli_option`).
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ValidationError

from telebot.channels.transports.base import (
    CliOption,
    Lane,
    Presence,
    Publisher,
    Sample,
    Subscription,
    Transport,
    TransportStats,
)
from telebot.config import TransportSettings, format_validation_error
from telebot.errors import ConfigError, TransportError, UnknownTransport
from telebot.registry import Registry

__all__ = [
    "BUILTIN_TRANSPORTS",
    "ENTRY_POINT_GROUP",
    "CliOption",
    "Lane",
    "Presence",
    "Publisher",
    "Sample",
    "Subscription",
    "Transport",
    "TransportStats",
    "apply_cli_option",
    "create_transport",
    "declared_cli_options",
    "get_transport_class",
    "known_transports",
    "plugin_options",
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
    """Build (not yet open) the transport that ``settings.kind`` names; a plug-in's
    ``[transport.options]`` are checked against its declared model first."""
    settings = settings or TransportSettings()
    cls = get_transport_class(settings.kind)
    plugin_options(cls, settings)
    return cls.from_settings(settings)


def plugin_options(cls: type[Transport], settings: TransportSettings) -> BaseModel | None:
    """``settings.options`` validated as ``cls.options_model`` (None if it declares none);
    a bad or unknown key is a one-line ConfigError naming it."""
    if cls.options_model is None:
        return None
    try:
        return cls.options_model.model_validate(settings.options)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, "transport.options")) from exc


def declared_cli_options() -> list[tuple[str, CliOption]]:
    """(transport name, flag) for every flag a transport declares: the built-ins', then
    those of installed plug-ins that load (one that does not is reported when chosen).

    A flag declared twice is a TransportError: two transports cannot share one.
    """
    found: list[tuple[str, CliOption]] = []
    owners: dict[str, str] = {}
    for name in [*BUILTIN_TRANSPORTS, *sorted(set(known_transports()) - set(BUILTIN_TRANSPORTS))]:
        try:
            cls = get_transport_class(name)
        except TransportError:
            if name in BUILTIN_TRANSPORTS:
                raise
            continue
        for option in cls.cli_options:
            if option.flag in owners:
                raise TransportError(
                    f"transports {owners[option.flag]!r} and {name!r} both declare {option.flag}"
                )
            owners[option.flag] = name
            found.append((name, option))
    return found


def apply_cli_option(settings: TransportSettings, name: str, option: CliOption, value: Any) -> None:
    """Set what ``option`` of transport ``name`` was given on the command line: a field of
    its ``[transport.<section>]``, validated (pydantic's ValidationError), or a plug-in's
    ``[transport.options]`` key (checked when the transport is created)."""
    section = get_transport_class(name).section
    if section is None:
        settings.options[option.setting] = value
    else:
        setattr(getattr(settings, section), option.setting, value)
