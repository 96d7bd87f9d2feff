"""The transport and robot registries: built-ins by name, plug-ins by entry point, clear errors."""

from __future__ import annotations

from importlib.metadata import EntryPoint
from typing import Any

import pytest

import telebot.registry
import telebot.robot
from telebot.channels import transports
from telebot.channels.transports import create_transport, get_transport_class, known_transports
from telebot.channels.transports.memory import MemoryTransport
from telebot.config import RobotConfig, TransportSettings
from telebot.errors import RobotError, TransportError, UnknownRobot, UnknownTransport
from telebot.robot import create_robot, get_robot_class, known_robots
from telebot.robot.nav import SteppedNavStack
from telebot.robot.sim.stack import SimNavStack


class PluginTransport(MemoryTransport):
    """A stand-in third-party transport (a subclass is the least a plug-in can be)."""

    name = "carrier-pigeon"


def fake_entry_points(monkeypatch: pytest.MonkeyPatch, target: str) -> None:
    entry = EntryPoint(name="carrier-pigeon", value=target, group=transports.ENTRY_POINT_GROUP)

    def select(group: str) -> list[EntryPoint]:
        return [entry] if group == transports.ENTRY_POINT_GROUP else []

    monkeypatch.setattr(telebot.registry, "entry_points", select)


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


# --------------------------------------------------------------------------- robots


class PluginRobot(SimNavStack):
    """A stand-in third-party robot adapter."""


class StopLessRobot:
    """A would-be adapter the safety watchdog could not stop."""

    @classmethod
    def from_config(cls, config: RobotConfig, **_: Any) -> StopLessRobot:
        return cls()


def small_robot(kind: str) -> RobotConfig:
    return RobotConfig.model_validate({"robot": {"kind": kind}, "sim": {"map": "small"}})


def fake_robot_entry_points(monkeypatch: pytest.MonkeyPatch, target: str) -> None:
    entry = EntryPoint(name="tin-can", value=target, group=telebot.robot.ENTRY_POINT_GROUP)

    def select(group: str) -> list[EntryPoint]:
        return [entry] if group == telebot.robot.ENTRY_POINT_GROUP else []

    monkeypatch.setattr(telebot.registry, "entry_points", select)


def test_the_sim_robot_is_known_and_created_from_sim_settings() -> None:
    assert "sim" in known_robots()
    assert get_robot_class("sim") is SimNavStack
    assert RobotConfig().robot.kind == "sim"  # the default
    robot = create_robot(small_robot("sim"), now=5.0)
    assert isinstance(robot, SimNavStack) and isinstance(robot, SteppedNavStack)
    assert robot.now == 5.0 and robot.map().width == 280  # [sim] map = "small" (14 m at 5 cm)


def test_an_unknown_robot_lists_the_known_ones() -> None:
    with pytest.raises(UnknownRobot, match=r"unknown robot 'tin-can'; known robots: ros2, sim"):
        get_robot_class("tin-can")
    with pytest.raises(LookupError):  # also a LookupError, and a RobotError
        create_robot(small_robot("tin-can"))


def test_a_robot_plugin_is_found_and_created(monkeypatch: pytest.MonkeyPatch) -> None:
    fake_robot_entry_points(monkeypatch, f"{__name__}:PluginRobot")
    assert known_robots() == ["ros2", "sim", "tin-can"]
    assert isinstance(create_robot(small_robot("tin-can")), PluginRobot)


@pytest.mark.parametrize(
    ("target", "message"),
    [
        (f"{__name__}:NOT_A_CLASS", "not a class with a from_config"),
        ("no_such_module_xyz:Thing", "failed to load"),
        (f"{__name__}:StopLessRobot", r"lacks .*emergency_stop.*map_version"),
    ],
)
def test_broken_robot_plugins_give_a_clear_error(
    monkeypatch: pytest.MonkeyPatch, target: str, message: str
) -> None:
    fake_robot_entry_points(monkeypatch, target)
    with pytest.raises(RobotError, match=message):
        create_robot(small_robot("tin-can"))
