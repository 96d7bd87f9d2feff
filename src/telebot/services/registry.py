"""The services every robot and every user's client gets, by name: built-in and plug-in.

A service is a :class:`~telebot.services.base.ServiceSpec`: its robot side and its user
side, each a per-call factory or a :class:`~telebot.services.base.HostService` class,
named as ``"module:attribute"`` and imported only when a host starts (so ``import telebot``
and ``telebot.connect`` load no service code). Built-ins are listed below in the order
they open on a call; each folder's ``__init__`` holds its ``SERVICE``. Plug-ins come from
the entry-point group ``telebot.services`` (python-can style, the same
:class:`~telebot.registry.Registry` as transports and robots) and open after the built-ins::

    # pyproject.toml of a plug-in
    [project.entry-points."telebot.services"]
    battery = "telebot_battery:SERVICE"      # SERVICE = ServiceSpec(robot=..., user=...)

On the user's side a service's per-client object is an attribute of the client
(``client.battery``). A plug-in that cannot be loaded is logged and left out: it never
keeps the robot or the client from starting.
"""

from __future__ import annotations

import logging
from typing import Any, Literal, cast

from telebot.errors import ConfigError
from telebot.registry import Registry
from telebot.services.base import ServiceRegistry, ServiceSpec

__all__ = ["ENTRY_POINT_GROUP", "SERVICES", "robot_services", "spec", "user_services"]

log = logging.getLogger(__name__)

#: The entry-point group plug-in services are found in.
ENTRY_POINT_GROUP = "telebot.services"

#: The core of every call (chat, goals, pose, telemetry, map, safety), part of the hosts.
CORE = ServiceSpec(
    robot="telebot.services.robot:CallServices", user="telebot.services.client:ClientCore"
)

#: Built-in services in the order they open: name -> (module, attribute of its ServiceSpec).
BUILTINS: dict[str, tuple[str, str]] = {
    "core": ("telebot.services.registry", "CORE"),
    "video": ("telebot.services.video", "SERVICE"),
    "plan": ("telebot.services.plan", "SERVICE"),
    "relay": ("telebot.services.relay", "SERVICE"),
    "conference": ("telebot.services.conference", "SERVICE"),
    "people": ("telebot.services.people", "SERVICE"),
    "media": ("telebot.services.media", "SERVICE"),
    "drive": ("telebot.services.drive", "SERVICE"),
}

#: Every service by name: the built-ins, then the installed plug-ins.
SERVICES: Registry[ServiceSpec] = Registry(
    what="service",
    group=ENTRY_POINT_GROUP,
    builtins=BUILTINS,
    accepts=lambda spec: isinstance(spec, ServiceSpec),
    shape="a telebot.services.base.ServiceSpec",
    error=ConfigError,
    unknown=ConfigError,
)


def spec(name: str) -> ServiceSpec:
    """The service called ``name`` (ConfigError naming the known ones if there is none)."""
    return cast(ServiceSpec, SERVICES.get(name))


def _side(side: Literal["robot", "user"]) -> ServiceRegistry[Any]:
    registry: ServiceRegistry[Any] = ServiceRegistry()
    plugins = [name for name in SERVICES.known() if name not in BUILTINS]
    for name in [*BUILTINS, *plugins]:
        try:
            factory = spec(name).side(side)
        except ConfigError as exc:  # a broken plug-in: said, and left out
            log.error("%s", exc)
            continue
        if factory is not None:
            registry.register(name, factory)
    return registry


def robot_services() -> ServiceRegistry[Any]:
    """The robot's services: the built-ins and every installed plug-in with a robot side."""
    return _side("robot")


def user_services() -> ServiceRegistry[Any]:
    """The user's services: the built-ins and every installed plug-in with a user side."""
    return _side("user")
