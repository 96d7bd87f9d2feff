"""The service seam: hosts, per-host services and per-call services.

A *host* is the robot (:class:`~telebot.services.robot.RobotServer`) or a user's client
(:class:`~telebot.services.client.RobotClient`); a service sees it only through
:class:`RobotHost` or :class:`ClientHost` (plus, where a service needs more, a Protocol of
its own that extends one). Both hosts hold a :class:`ServiceRegistry`, name → service in
registration order (the built-ins and plug-ins: :mod:`telebot.services.registry`).
``registry.start(host)`` makes each service once for the host: a :class:`HostService`
subclass (per-robot or per-client state, Nav2-plugin style: start, tick, open a call,
close) or a plain factory ``(host, call) -> CallService`` (nothing per host). When a call
comes up the host opens every service on it; each returns the call's
:class:`CallService`, which opens its channels. The host ticks the per-host services and
every open per-call one (the robot at its control rate, the user at :data:`CLIENT_TICK`)
and closes the per-call ones when the call ends. A new service is one folder plus one
registration line; in code, one :meth:`ServiceRegistry.register` call::

    class Echo:                                    # one per call
        def __init__(self, host: RobotHost, call: Call) -> None:
            self.channel = call.channel("echo")
            self.channel.set_callback(lambda d: self.channel.send(d.payload))

        def tick(self, now: float) -> None: ...    # loop time; periodic work goes here
        def close(self) -> None: ...               # the call ended (or the host closes)

    services = robot_services()                    # telebot.services.registry
    services.register("echo", Echo)
    server = RobotServer(nav, services=services)

A service's settings are its section of the robot's config (``[drive]``, ``[relay]``…): the
robot holds one :class:`ServiceConfig` and each service reads its own section from it
(``host.config.get("drive", DriveSettings)``), so the robot takes no argument per service.
A service that moves the robot (driving by hand, follow-me) is a :class:`MotionService`
too: the robot halts it before an emergency stop and tells it every safety change.

On the user's side a call may be replaced: when the link drops, the client calls the
robot again (see :mod:`telebot.services.client`) and opens every registered service on
the new call after closing the old call's. So what a user subscribes to (``async for``
iterators, callbacks) lives in the per-client service or on the host, and a per-call
service only moves bytes between its channels and them: subscribers keep working across
calls.

Every call of a service's method is guarded: an exception is logged and does not reach
the other services, the host's loop or the call. A factory that raises while a call is
being opened closes the services already opened on it and is raised to the host (the
robot then hangs the call up: a call served by half its services must not stay up).
"""

from __future__ import annotations

import asyncio
import importlib
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Generic, Literal, Protocol, TypeVar, cast, runtime_checkable

from telebot.channels.transports.base import Lane
from telebot.errors import ProtocolError

if TYPE_CHECKING:
    from telebot.channels.call import Call
    from telebot.channels.channel import ReceivedDatagram
    from telebot.robot.nav import NavStack

__all__ = [
    "CLIENT_TICK",
    "CallService",
    "ClientHost",
    "DatagramReceiver",
    "HostService",
    "HostedServices",
    "MotionService",
    "OpenServices",
    "RobotHost",
    "ServiceConfig",
    "ServiceFactory",
    "ServiceRegistry",
    "ServiceSpec",
    "is_newer",
]

log = logging.getLogger(__name__)

#: How often (s) the user's side ticks the services of its call.
CLIENT_TICK = 0.05

Host = TypeVar("Host", contravariant=True)
H = TypeVar("H")
T = TypeVar("T")


class ServiceConfig:
    """The services' settings by config section (``[video]``, ``[relay]``, ``[drive]``…).

    A service reads its own section with :meth:`get`; a section not given is the settings
    class's defaults. ``ServiceConfig(drive=DriveSettings(stale_after=0.5))``.
    """

    def __init__(self, **sections: object) -> None:
        self._sections = dict(sections)

    def get(self, section: str, kind: type[T]) -> T:
        """Section ``section`` (a ``kind``; ``kind()`` when not given).

        A section of another type is a TypeError naming it (a wiring mistake, not input).
        """
        value = self._sections.get(section)
        if value is None:
            return kind()
        if not isinstance(value, kind):
            raise TypeError(
                f"[{section}] is a {type(value).__name__}, the service wants a {kind.__name__}"
            )
        return value

    def sections(self) -> list[str]:
        """The sections given."""
        return list(self._sections)


class RobotHost(Protocol):
    """What a robot-side service may use of the robot (:class:`~telebot.services.robot.RobotServer`
    is one): never more, so a service runs on any host that gives these."""

    #: The robot's navigation stack.
    nav: NavStack
    #: The robot's name (its identity's, once it answers calls).
    name: str
    #: Where robot events go (``{"event": ..., ...}``: the daemon's JSON lines).
    emit: Callable[[dict[str, Any]], None]
    #: The safety supervisor's driver (:class:`~telebot.services.safety.robot.SafetyDriver`),
    #: None on a robot run without one.
    safety: Any
    #: The services' settings, a section each (see :class:`ServiceConfig`).
    config: ServiceConfig

    def now(self) -> float:
        """The robot's clock (the event loop's)."""
        ...

    def service(self, name: str) -> HostService[Any] | None:
        """The robot's host service ``name``, if registered (one service's use of another)."""
        ...

    def emergency_stop(self, reason: str) -> None:
        """Stop the robot now and latch the stop (every :class:`MotionService` halted first)."""
        ...

    def safety_status(self) -> Any:
        """The safety state as users see it (:class:`~telebot.services.safety.wire.SafetyStatus`)."""
        ...

    def encoded_map(self) -> Any:
        """The map, encoded once per version (:class:`~telebot.services.mapxfer.wire.EncodedMap`)."""
        ...

    def replaces(self, call_id: str) -> str | None:
        """The call that call ``call_id`` replaced (its client's previous call), if any."""
        ...


class ClientHost(Protocol):
    """What a user-side service may use of the user's client
    (:class:`~telebot.services.client.RobotClient` is one)."""

    #: Datagrams from the robot that did not decode (a service counts its own here).
    rejected: int

    @property
    def robot(self) -> str:
        """The robot's name."""
        ...

    async def live_call(self) -> Call:
        """The call once it is up, waiting out a reconnection (CallEnded once none will come)."""
        ...

    async def answer(self, answers: asyncio.Queue[T], wait: float, call: Call) -> T:
        """The next of ``answers`` within ``wait`` s (TimeoutError), CallEnded if ``call`` ends."""
        ...

    def service(self, name: str) -> CallService | None:
        """The service ``name`` open on the current call, if any."""
        ...


class HostService(Generic[H]):
    """A service once per host (one robot, one user's client), beside its per-call objects.

    As Nav2 configures a plug-in with narrow handles and then activates it: made with the
    host's narrow interface (:class:`RobotHost` or :class:`ClientHost`), :meth:`start` ed
    once, :meth:`tick` ed with the host, :meth:`open` ed on every call, :meth:`close` d with
    the host. State that outlives one call (a robot's conference room, a user's video feed)
    lives here, never in a module global. The defaults do nothing.
    """

    def __init__(self, host: H) -> None:
        self.host = host

    def start(self) -> None:
        """Begin (once, before the first call)."""

    def tick(self, now: float) -> None:
        """Periodic per-host work (``now``: loop time)."""

    def open(self, call: Call) -> CallService | None:
        """This service on ``call`` (None: nothing per call)."""
        return None

    def close(self) -> None:
        """The host is closing."""


@runtime_checkable
class MotionService(Protocol):
    """A robot's host service that moves the robot (driving by hand and follow-me).

    Fail-safe hooks the robot calls, each guarded: :meth:`halt` before it stops the robot
    (an emergency, or a stop with no supervisor to latch it), so the service cannot drive
    again after the stop; :meth:`safety_changed` on every change of the supervisor's state,
    before anyone hears of it.
    """

    def halt(self, text: str) -> None:
        """End every motion this service commands (``text``: why, as users read it)."""
        ...

    def safety_changed(self, state: Any) -> None:
        """The supervisor's state changed (a :class:`~telebot.safety.SafetyState`)."""
        ...


class _PerCall(HostService[H]):
    """A per-call factory as a host service (a service with no per-host state)."""

    def __init__(self, host: H, factory: ServiceFactory[H]) -> None:
        super().__init__(host)
        self.factory = factory

    def open(self, call: Call) -> CallService:
        return self.factory(self.host, call)


Message = TypeVar("Message")


class DatagramReceiver(Generic[Message]):
    """A user-side per-call service that only listens: each datagram of its one channel is
    decoded and handed to :meth:`deliver`; one that does not decode is counted in
    :attr:`rejected` (and the channel's stats) and dropped. Subclasses write ``deliver``."""

    def __init__(
        self,
        call: Call,
        channel: str,
        decode: Callable[[str | bytes], Message],
        *,
        lane: Lane = Lane.DATA,
    ) -> None:
        self.channel = call.channel(channel, lane=lane)
        self.channel.set_callback(self._on_datagram)
        self._decode = decode
        self._name = channel
        #: Datagrams that did not decode (dropped).
        self.rejected = 0

    def deliver(self, message: Message) -> None:
        """Hand on one decoded message (the subclass's part)."""
        raise NotImplementedError

    def tick(self, now: float) -> None:
        """Nothing periodic: the robot streams and repeats."""

    def close(self) -> None:
        """Deliver nothing more from this call."""
        self.channel.set_callback(None)

    def _on_datagram(self, datagram: ReceivedDatagram) -> None:
        try:
            message = self._decode(datagram.payload)
        except ProtocolError as exc:
            self.rejected += 1
            self.channel.stats.rejected += 1
            log.debug("%s datagram dropped: %s", self._name, exc)
            return
        self.deliver(message)


def is_newer(newest: int | None, seq: int) -> bool:
    """Whether ``seq`` is newer than ``newest`` (None: nothing seen yet) on a lossy,
    reordering channel: a repeat or one overtaken is not, and a seq that wrapped round to
    a small number is (it cannot be 2**31 behind)."""
    return newest is None or not (newest >= seq and newest - seq < 2**31)


@dataclass(frozen=True, slots=True)
class ServiceSpec:
    """A service's two sides, each a :class:`ServiceFactory`, a :class:`HostService` class, or
    ``"module:attribute"`` naming one (imported on first use); None: no such side.

    This is what a plug-in's ``telebot.services`` entry point names (see
    :mod:`telebot.services.registry`).
    """

    robot: object = None
    user: object = None

    def side(self, which: Literal["robot", "user"]) -> object:
        """The robot or user side (still a name if not yet loaded)."""
        return self.robot if which == "robot" else self.user


def load(factory: object) -> object:
    """``factory`` itself, or the object a ``"module:attribute"`` string names."""
    if not isinstance(factory, str):
        return factory
    module, _, attribute = factory.partition(":")
    return getattr(importlib.import_module(module), attribute)


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


class HostedServices(Generic[H]):
    """The services of one host (made by :meth:`ServiceRegistry.start`), by name.

    ``start=False`` makes none yet: the host keeps this first and then calls :meth:`start`,
    so that a service starting may find the ones started before it (``host.service(name)``).
    """

    def __init__(self, registry: ServiceRegistry[H], host: H, *, start: bool = True) -> None:
        self._registry = registry
        self._host = host
        self._services: dict[str, HostService[H]] = {}
        self.closed = False
        if start:
            self.start()

    def start(self) -> None:
        """Make and start every registered service (a failing one is raised, the others
        closed)."""
        try:
            self.catch_up()
        except BaseException:
            self.close()
            raise

    def catch_up(self) -> None:
        """Start the services registered since (in registration order)."""
        for name in self._registry.names():
            if name not in self._services:
                service = self._registry.make(name, self._host)
                self._services[name] = service
                service.start()

    def get(self, name: str) -> HostService[H] | None:
        """The host service ``name``, if registered."""
        return self._services.get(name)

    def __iter__(self) -> Iterator[HostService[H]]:
        return iter(list(self._services.values()))

    def names(self) -> list[str]:
        """The names, in registration order."""
        return list(self._services)

    def open(self, call: Call) -> OpenServices:
        """Open every registered service on ``call``; if one fails, close the others and raise."""
        self.catch_up()
        opened: dict[str, CallService] = {}
        try:
            for name in self._registry.names():  # an unregistered one opens no more
                service = self._services[name]
                per_call = service.open(call)
                if per_call is not None:
                    opened[name] = per_call
        except BaseException:
            OpenServices(call, opened).close()
            raise
        return OpenServices(call, opened)

    def tick(self, now: float) -> None:
        """Tick every host service (each guarded)."""
        for name, service in list(self._services.items()):
            _guarded(name, "tick", service.tick, now)

    def close(self) -> None:
        """Close every host service (each guarded, in reverse order); idempotent."""
        if self.closed:
            return
        self.closed = True
        for name, service in reversed(list(self._services.items())):
            _guarded(name, "close", service.close)


class ServiceRegistry(Generic[H]):
    """Name → service for hosts of type ``H``; opened in registration order.

    A service is a :class:`ServiceFactory` (per call), a :class:`HostService` subclass (per
    host, opening its per-call objects), or ``"module:attribute"`` naming either, imported
    when a host starts (so a registry of built-ins imports nothing until used).
    """

    def __init__(self) -> None:
        self._factories: dict[str, object] = {}

    def register(self, name: str, factory: object, *, replace: bool = False) -> None:
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

    def start(self, host: H) -> HostedServices[H]:
        """Make and start every service for ``host`` (a failing one is raised, the others
        closed); services registered later start when the host opens its next call."""
        return HostedServices(self, host)

    def make(self, name: str, host: H) -> HostService[H]:
        """The host service ``name`` for ``host``, loaded if given by name (not started)."""
        loaded = load(self._factories[name])
        if isinstance(loaded, type) and issubclass(loaded, HostService):
            return cast("HostService[H]", loaded(host))
        if callable(loaded):
            return _PerCall(host, cast("ServiceFactory[H]", loaded))
        raise TypeError(f"service {name!r} is neither a factory nor a HostService")

    def open(self, host: H, call: Call) -> OpenServices:
        """Open every registered service on ``call`` for a host that keeps no host services
        (each per-host service is made for this call alone)."""
        return self.start(host).open(call)


def _guarded(name: str, what: str, action: Callable[..., None], *args: float) -> None:
    try:
        action(*args)
    except Exception:
        log.exception("service %r: %s failed", name, what)
