"""The service seam: a :class:`CallService` is opened on a call, ticked, and closed with it.

Both ends hold a :class:`ServiceRegistry`: a name → factory table, in registration order.
When a call comes up, every registered factory is called with the *host* (the
:class:`~telebot.services.robot.RobotServer` on the robot, the
:class:`~telebot.services.client.RobotClient` on the user's side) and the call; it opens
its channels and returns the call's service object. The host then ticks every open
service (the robot at its control rate, the user at :data:`CLIENT_TICK`) and closes
them all when the call ends. A new service (audio, relay, follow-me) is one module with a
factory plus one :meth:`ServiceRegistry.register` line::

    class Echo:                                    # one per call
        def __init__(self, host: RobotServer, call: Call) -> None:
            self.channel = call.channel("echo")
            self.channel.set_callback(lambda d: self.channel.send(d.payload))

        def tick(self, now: float) -> None: ...    # loop time; periodic work goes here
        def close(self) -> None: ...               # the call ended (or the host closes)

    server = RobotServer(nav, services=default_robot_services())
    server.registry.register("echo", Echo)

On the user's side a call may be replaced: when the link drops, the client calls the
robot again (see :mod:`telebot.services.client`) and opens every registered service on
the new call after closing the old call's. So what a user subscribes to (``async for``
iterators, callbacks) lives on the host, and a service only moves bytes between its
channels and the host: subscribers keep working across calls.

Every call of a service's method is guarded: an exception is logged and does not reach
the other services, the host's loop or the call. A factory that raises while a call is
being opened closes the services already opened on it and is raised to the host (the
robot then hangs the call up: a call served by half its services must not stay up).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Generic, Protocol, TypeVar

if TYPE_CHECKING:
    from telebot.channels.call import Call

__all__ = [
    "CLIENT_TICK",
    "CallService",
    "OpenServices",
    "ServiceFactory",
    "ServiceRegistry",
]

log = logging.getLogger("telebot.services")

#: How often (s) the user's side ticks the services of its call.
CLIENT_TICK = 0.05

Host = TypeVar("Host", contravariant=True)
H = TypeVar("H")


class CallService(Protocol):
    """One service on one call, made by a :class:`ServiceFactory` when the call opens."""

    def tick(self, now: float) -> None:
        """Periodic work (event-loop time ``now``); the host calls it while the call is up."""
        ...

    def close(self) -> None:
        """The call ended or the host is closing: stop timers, tell the peer if useful."""
        ...


class ServiceFactory(Protocol[Host]):
    """Opens a service on ``call`` for ``host`` (a class whose ``__init__`` takes both)."""

    def __call__(self, host: Host, call: Call, /) -> CallService:
        """The service's per-call object, its channels opened on ``call``."""
        ...


class OpenServices:
    """The services open on one call, by name, in registration order."""

    def __init__(self, call: Call, services: dict[str, CallService]) -> None:
        self.call = call
        self._services = services
        self.closed = False

    def __getitem__(self, name: str) -> CallService:
        return self._services[name]

    def __contains__(self, name: object) -> bool:
        return name in self._services

    def __iter__(self) -> Iterator[CallService]:
        return iter(list(self._services.values()))

    def __len__(self) -> int:
        return len(self._services)

    def get(self, name: str) -> CallService | None:
        """The service called ``name``, or None when it is not registered."""
        return self._services.get(name)

    def names(self) -> list[str]:
        """The names of the open services."""
        return list(self._services)

    def tick(self, now: float) -> None:
        """Tick every service (each guarded); nothing once closed."""
        if self.closed:
            return
        for name, service in list(self._services.items()):
            _guarded(name, "tick", service.tick, now)

    def close(self) -> None:
        """Close every service (each guarded, in reverse order); idempotent."""
        if self.closed:
            return
        self.closed = True
        for name, service in reversed(list(self._services.items())):
            _guarded(name, "close", service.close)


class ServiceRegistry(Generic[H]):
    """Name → :class:`ServiceFactory` for hosts of type ``H``; opened in registration order."""

    def __init__(self) -> None:
        self._factories: dict[str, ServiceFactory[H]] = {}

    def register(self, name: str, factory: ServiceFactory[H], *, replace: bool = False) -> None:
        """Open ``factory`` on every call from now on under ``name``.

        Registering a taken name is a ValueError unless ``replace`` (which keeps its place).
        """
        if not name:
            raise ValueError("a service needs a name")
        if name in self._factories and not replace:
            raise ValueError(f"a service named {name!r} is already registered")
        self._factories[name] = factory

    def unregister(self, name: str) -> None:
        """Stop opening ``name`` on new calls (KeyError naming the known ones if unknown)."""
        if name not in self._factories:
            raise KeyError(f"no service named {name!r}; registered: {', '.join(self._factories)}")
        del self._factories[name]

    def names(self) -> list[str]:
        """The registered names, in the order services are opened."""
        return list(self._factories)

    def __contains__(self, name: object) -> bool:
        return name in self._factories

    def copy(self) -> ServiceRegistry[H]:
        """A registry with the same factories (to extend without changing this one)."""
        other: ServiceRegistry[H] = ServiceRegistry()
        other._factories = dict(self._factories)
        return other

    def open(self, host: H, call: Call) -> OpenServices:
        """Open every registered service on ``call``; if one fails, close the others and raise."""
        opened: dict[str, CallService] = {}
        try:
            for name, factory in self._factories.items():
                opened[name] = factory(host, call)
        except BaseException:
            OpenServices(call, opened).close()
            raise
        return OpenServices(call, opened)


def _guarded(name: str, what: str, action: Callable[..., None], *args: float) -> None:
    try:
        action(*args)
    except Exception:
        log.exception("service %r: %s failed", name, what)
