"""Transports declare their own settings and flags; the command lines read them from there."""

from __future__ import annotations

import argparse
from importlib.metadata import EntryPoint

import pytest
from pydantic import Field

import telebot.registry
from telebot.apps.common import add_connection_options, load_app_config, new_parser
from telebot.channels import transports
from telebot.channels.transports import (
    CliOption,
    create_transport,
    declared_cli_options,
    plugin_options,
)
from telebot.channels.transports.memory import MemoryTransport
from telebot.channels.transports.zenoh import ZenohTransport
from telebot.config import AppConfig, StrictModel, TransportSettings
from telebot.errors import ConfigError, TransportError


class PigeonOptions(StrictModel):
    """The declared options of a stand-in plug-in transport."""

    coop: str = "roof"
    birds: int = Field(default=3, ge=1, le=100)


class PigeonTransport(MemoryTransport):
    """A third-party transport that declares its options and a flag."""

    name = "carrier-pigeon"
    section = None
    options_model = PigeonOptions
    cli_options = (CliOption("--coop", "coop", "where the pigeons live", metavar="PLACE"),)


def fake_entry_points(monkeypatch: pytest.MonkeyPatch, target: str) -> None:
    entry = EntryPoint(name="carrier-pigeon", value=target, group=transports.ENTRY_POINT_GROUP)

    def select(group: str) -> list[EntryPoint]:
        return [entry] if group == transports.ENTRY_POINT_GROUP else []

    monkeypatch.setattr(telebot.registry, "entry_points", select)


def parser() -> argparse.ArgumentParser:
    top = new_parser("telebot-test", "test")
    add_connection_options(top)
    return top


def test_the_built_in_flags_are_the_transports_own() -> None:
    flags = [(name, option.flag) for name, option in declared_cli_options()]
    assert flags == [("zenoh", "--listen"), ("zenoh", "--connect")]
    assert [o.flag for o in ZenohTransport.cli_options] == ["--listen", "--connect"]
    args = parser().parse_args(["--listen", "tcp/127.0.0.1:1", "--connect", "tcp/127.0.0.1:2"])
    config = load_app_config(args, AppConfig)
    assert config.transport.zenoh.listen == ["tcp/127.0.0.1:1"]
    assert config.transport.zenoh.connect == ["tcp/127.0.0.1:2"]
    # Not given: the config file's (here the default) value stands.
    assert load_app_config(parser().parse_args([]), AppConfig).transport.zenoh.listen == []


def test_a_plugin_declares_its_options_and_flags(monkeypatch: pytest.MonkeyPatch) -> None:
    fake_entry_points(monkeypatch, f"{__name__}:PigeonTransport")
    args = parser().parse_args(["--coop", "barn", "--listen", "tcp/127.0.0.1:1"])
    config = load_app_config(args, AppConfig)
    assert config.transport.options == {"coop": "barn"}
    assert config.transport.zenoh.listen == ["tcp/127.0.0.1:1"]
    config.transport.kind = "carrier-pigeon"
    assert isinstance(create_transport(config.transport), PigeonTransport)
    options = plugin_options(PigeonTransport, config.transport)
    assert options == PigeonOptions(coop="barn", birds=3)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"birds": 0}, r"^transport\.options: birds: Input should be greater than or equal to 1$"),
        ({"bird": 3}, r"^transport\.options: bird: unknown key$"),
        ({"coop": ["a"]}, r"^transport\.options: coop: Input should be a valid string$"),
    ],
)
def test_a_plugins_bad_option_is_one_line_naming_the_key(
    monkeypatch: pytest.MonkeyPatch, options: dict[str, object], message: str
) -> None:
    fake_entry_points(monkeypatch, f"{__name__}:PigeonTransport")
    with pytest.raises(ConfigError, match=message):
        create_transport(TransportSettings(kind="carrier-pigeon", options=options))


class Squatter(MemoryTransport):
    name = "squatter"
    cli_options = (CliOption("--listen", "listen", "mine now"),)


def test_two_transports_cannot_declare_one_flag(monkeypatch: pytest.MonkeyPatch) -> None:
    fake_entry_points(monkeypatch, f"{__name__}:Squatter")
    with pytest.raises(TransportError, match="'zenoh' and 'carrier-pigeon' both declare --listen"):
        declared_cli_options()
