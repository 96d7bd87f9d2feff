"""Robot adapters by name, python-can style (as :mod:`telebot.channels.transports`).

A robot adapter implements :class:`~telebot.robot.nav.NavStack` and
:class:`~telebot.robot.nav.EmergencyStoppable` (the safety watchdog stops it from its own
thread), and :class:`~telebot.robot.nav.SteppedNavStack` if the caller's clock drives it;
deriving from :class:`~telebot.robot.nav.NavStackBase` leaves four methods to write, and
:mod:`telebot.testing.navstack` is the contract suite it runs.
Built-in adapters are listed in :data:`BUILTIN_ROBOTS` as name -> (module, class) and imported
only when asked for; ``"sim"`` is the simulated robot, and ``"ros2"`` a ROS 2 / Nav2 robot over rmw_zenoh
(``robot/ros2/``, the one place in ``robot/`` that may import zenoh).
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

from pathlib import Path
from typing import Any, cast

from telebot.config import RobotConfig
from telebot.errors import RobotError, UnknownRobot
from telebot.registry import Registry
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
    "ros2": ("telebot.robot.ros2.stack", "Ros2NavStack"),
}


_REGISTRY: Registry[Any] = Registry(
    what="robot",
    group=ENTRY_POINT_GROUP,
    builtins=BUILTIN_ROBOTS,
    accepts=lambda cls: isinstance(cls, type) and callable(getattr(cls, "from_config", None)),
    shape="a class with a from_config() constructor",
    error=RobotError,
    unknown=UnknownRobot,
)


def known_robots() -> list[str]:
    """Names of every robot adapter that can be created: built-in and installed plug-ins."""
    return _REGISTRY.known()


def get_robot_class(name: str) -> type[Any]:
    """The adapter class registered as ``name``; imports its module on first use.

    Raises :class:`~telebot.errors.UnknownRobot` (listing the known names) for an unknown
    name, :class:`~telebot.errors.RobotError` for one that cannot be loaded.
    """
    return _REGISTRY.get(name)


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
