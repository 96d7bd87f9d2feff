"""Robot adapters by name, python-can style (as :mod:`telebot.channels.transports`).

A robot adapter implements :class:`~telebot.robot.nav.NavStack` and
:class:`~telebot.robot.nav.EmergencyStoppable` (the safety watchdog stops it from its own
thread), and :class:`~telebot.robot.nav.SteppedNavStack` if the caller's clock drives it.
Built-in adapters are listed in :data:`BUILTIN_ROBOTS` as name -> (module, class) and imported
only when asked for; ``"sim"`` is the simulated robot, and ``"ros2"`` (ROS 2 over rmw_zenoh,
in ``robot/ros2/``, the one place in ``robot/`` that may import zenoh) is to come.
``telebot-robot run`` picks one with ``[robot] kind`` in ``configs/robot.toml`` or
``--robot NAME``. Third-party adapters register in the entry-point group ``telebot.robots``::

    [project.entry-points."telebot.robots"]
    mybase = "mypkg.base:MyBaseNavStack"

An adapter class is built with ``cls.from_config(config, base_dir=..., now=...)``, where
``config`` is the whole :class:`~telebot.config.RobotConfig` (``"sim"`` reads ``config.sim``,
a third party ``config.robot.options``), ``base_dir`` the config file's folder (for relative
paths) and ``now`` the caller's clock. The speed cap the new robot reports
(:attr:`~telebot.robot.nav.NavStack.speed_limit`) is taken as its top speed.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, cast

from telebot.config import RobotConfig
from telebot.errors import RobotError, UnknownRobot
from telebot.robot.nav import EmergencyStoppable, NavStack

__all__ = [
    "BUILTIN_ROBOTS",
    "ENTRY_POINT_GROUP",
    "create_robot",
    "get_robot_class",
    "known_robots",
    "missing_members",
]

ENTRY_POINT_GROUP = "telebot.robots"

BUILTIN_ROBOTS: dict[str, tuple[str, str]] = {
    "sim": ("telebot.robot.sim.stack", "SimNavStack"),
}


def _plugin_entry_points() -> dict[str, Any]:
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def known_robots() -> list[str]:
    """Names of every robot adapter that can be created: built-in and installed plug-ins."""
    return sorted(set(BUILTIN_ROBOTS) | set(_plugin_entry_points()))


def get_robot_class(name: str) -> type[Any]:
    """The adapter class registered as ``name``; imports its module on first use.

    Raises :class:`~telebot.errors.UnknownRobot` (listing the known names) for an unknown
    name, :class:`~telebot.errors.RobotError` for one that cannot be loaded.
    """
    if name in BUILTIN_ROBOTS:
        module_name, class_name = BUILTIN_ROBOTS[name]
        try:
            module = importlib.import_module(module_name)
        except ImportError as exc:
            raise RobotError(f"robot {name!r} cannot be imported: {exc}") from exc
        return cast(type[Any], getattr(module, class_name))
    plugins = _plugin_entry_points()
    if name in plugins:
        try:
            cls = plugins[name].load()
        except Exception as exc:  # a broken plug-in must not take the caller down
            raise RobotError(f"robot {name!r} failed to load: {exc}") from exc
        if not (isinstance(cls, type) and callable(getattr(cls, "from_config", None))):
            raise RobotError(f"robot {name!r} is not a class with a from_config() constructor")
        return cls
    raise UnknownRobot(f"unknown robot {name!r}; known robots: {', '.join(known_robots())}")


def missing_members(robot: object) -> list[str]:
    """What ``robot`` lacks of :class:`~telebot.robot.nav.EmergencyStoppable` (sorted names)."""
    required: set[str] = set()
    for proto in (EmergencyStoppable, NavStack):
        required.update(name for name in vars(proto) if not name.startswith("_"))
    return sorted(name for name in required if not hasattr(robot, name))


def create_robot(
    config: RobotConfig | None = None, *, base_dir: Path | None = None, now: float = 0.0
) -> EmergencyStoppable:
    """Build the robot adapter that ``config.robot.kind`` names (see the module docstring).

    Raises :class:`~telebot.errors.UnknownRobot`, or :class:`~telebot.errors.RobotError`
    when the adapter fails to load or lacks part of the interface (fail safe: a robot the
    watchdog cannot stop is not driven); the adapter's own errors (a bad map) pass through.
    """
    config = config if config is not None else RobotConfig()
    name = config.robot.kind
    cls = get_robot_class(name)
    robot = cls.from_config(config, base_dir=base_dir, now=now)
    missing = missing_members(robot)
    if missing:
        raise RobotError(f"robot {name!r} ({cls.__name__}) lacks {', '.join(missing)}")
    return cast(EmergencyStoppable, robot)
