"""The services seam: built-ins load by name, and a plug-in service is one folder plus one
entry-point line (tests/plugins/battery_plugin), read by a user as ``client.battery``."""

from __future__ import annotations

from pathlib import Path

import pytest

from conftest import ROBOT, wait_until
from rig import robot_on_hub
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.errors import ConfigError
from telebot.services import registry
from telebot.services.base import HostService, ServiceRegistry, load
from telebot.services.client import connect

PLUGINS = Path(__file__).resolve().parent / "plugins"


def install_battery(monkeypatch: pytest.MonkeyPatch, where: Path) -> None:
    """Install the battery plug-in as pip would: its code on the path, and a dist-info
    whose entry_points.txt holds the one registration line."""
    monkeypatch.syspath_prepend(str(PLUGINS))
    info = where / "battery_plugin-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: battery-plugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[telebot.services]\nbattery = battery_plugin:SERVICE\n")
    monkeypatch.syspath_prepend(str(where))


@pytest.mark.parametrize("side", ["robot", "user"])
def test_every_built_in_service_loads_by_name(side: str) -> None:
    for name in registry.BUILTINS:
        factory = registry.spec(name).side(side)  # type: ignore[arg-type]
        if factory is None:
            continue
        loaded = load(factory)
        assert callable(loaded) or issubclass(loaded, HostService), (name, side)


def test_an_unknown_service_is_a_one_line_error_naming_the_known_ones() -> None:
    with pytest.raises(ConfigError, match=r"unknown service 'batery'; known services: .*relay"):
        registry.spec("batery")


def test_a_broken_plug_in_is_left_out_and_the_robot_still_gets_the_built_ins(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    info = tmp_path / "broken-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: broken\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[telebot.services]\nbroken = no_such_module:SERVICE\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    names = registry.robot_services().names()
    assert "broken" not in names and names[:2] == ["core", "video"]


async def test_a_plug_in_service_reaches_the_user_as_a_client_attribute(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    install_battery(monkeypatch, tmp_path / "site")
    robot_side: ServiceRegistry[object] = registry.robot_services()
    user_side: ServiceRegistry[object] = registry.user_services()
    assert robot_side.names()[-1] == user_side.names()[-1] == "battery"
    hub = MemoryHub(seed=5)
    async with (
        robot_on_hub(tmp_path, hub, robot_side) as (_, _, server, _),
        MemoryTransport(hub, "user") as transport,
        connect(ROBOT, home=tmp_path / "user", transport=transport, services=user_side) as client,
    ):
        await wait_until(lambda: client.battery.percent is not None)
        assert 0 < client.battery.percent <= 100
        # One gauge per robot, whatever the calls.
        assert server.hosted.get("battery") is not None
