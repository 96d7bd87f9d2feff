"""The transport registry: built-ins by name, plug-ins by entry point, clear errors."""

from __future__ import annotations

from importlib.metadata import EntryPoint
from typing import Any

import pytest

from telebot.channels import transports
from telebot.channels.transports import create_transport, get_transport_class, known_transports
from telebot.channels.transports.memory import MemoryTransport
from telebot.config import TransportSettings
from telebot.errors import TransportError, UnknownTransport


class PluginTransport(MemoryTransport):
    """A stand-in third-party transport (a subclass is the least a plug-in can be)."""

    name = "carrier-pigeon"


def fake_entry_points(monkeypatch: pytest.MonkeyPatch, target: str) -> None:
    entry = EntryPoint(name="carrier-pigeon", value=target, group=transports.ENTRY_POINT_GROUP)

    def select(group: str) -> list[EntryPoint]:
        return [entry] if group == transports.ENTRY_POINT_GROUP else []

    monkeypatch.setattr(transports, "entry_points", select)


def test_builtins_are_known_and_created_by_name() -> None:
    assert {"memory", "zenoh"} <= set(known_transports())
    assert get_transport_class("memory") is MemoryTransport
    transport = create_transport(TransportSettings(kind="memory"))
    assert isinstance(transport, MemoryTransport)


def test_unknown_name_lists_the_known_ones() -> None:
    with pytest.raises(
        UnknownTransport, match=r"unknown transport 'smoke'; known transports: .*memory.*zenoh"
    ):
        get_transport_class("smoke")
    with pytest.raises(LookupError):  # UnknownTransport is also a LookupError
        create_transport(TransportSettings(kind="smoke"))


def test_entry_point_plugin_is_found_and_created(monkeypatch: pytest.MonkeyPatch) -> None:
    fake_entry_points(monkeypatch, f"{__name__}:PluginTransport")
    assert "carrier-pigeon" in known_transports()
    assert get_transport_class("carrier-pigeon") is PluginTransport
    assert isinstance(create_transport(TransportSettings(kind="carrier-pigeon")), PluginTransport)


@pytest.mark.parametrize(
    ("target", "message"),
    [
        (f"{__name__}:NOT_A_CLASS", "not a telebot Transport subclass"),
        ("no_such_module_xyz:Thing", "failed to load"),
    ],
)
def test_broken_plugins_give_a_clear_error(
    monkeypatch: pytest.MonkeyPatch, target: str, message: str
) -> None:
    fake_entry_points(monkeypatch, target)
    with pytest.raises(TransportError, match=message):
        get_transport_class("carrier-pigeon")


NOT_A_CLASS: Any = object()
