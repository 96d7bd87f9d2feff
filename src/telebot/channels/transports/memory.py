"""The in-process transport: a hub of nodes joined by seeded, lossy links.

This is a real feature, not a test fake: every test and benchmark can run the lossy link
of the paper (loss, latency, reordering, a bandwidth cap, cuts) deterministically::

    hub = MemoryHub(seed=7)
    hub.set_link("robot", "user", loss=0.3, latency=0.05, jitter=0.02)
    async with MemoryTransport(hub, "robot") as robot, MemoryTransport(hub, "user") as user:
        ...

Model:

* A frame published by node A goes to every node that has a subscription matching its
  key. Each direction A->B is a :class:`LinkConditions` with its own ``random.Random``
  seeded from (hub seed, A, B), so a run with the same seed loses the same frames. A node
  always receives its own frames, unimpaired.
* Each link draws the same random numbers for every frame whatever the conditions, so
  changing e.g. the latency does not change which frames are lost.
* Conditions apply when a frame is published: a frame already in flight still arrives
  after the link is cut or slowed down, as on a real wire.
* ``set_profile`` plays a named network (telebot.netem: Wi-Fi, 4G, ...) on a link instead
  of hand-set conditions, with the same model as the loopback proxy of real zenoh links.
* Lanes are recorded on the publisher but not modelled: all lanes share one link.
* A hub lives in one thread; a transport opened on another event loop still gets its
  callbacks on its own loop (hand-over with ``call_soon_threadsafe``).
* Frames that arrive go through each subscription's
  :class:`~telebot.channels.transports.inbox.Inbox`, the receive path zenoh uses too:
  bounded in samples and bytes (``ReceiveLimits``, else ``queue_size`` / ``queue_bytes``,
  zenoh's defaults), dropping the oldest, at most ``batch`` samples per loop turn. So a
  flood is a deterministic in-process test.
* Every time is the event loop's (``loop.time()``, ``loop.call_at``): on
  :class:`telebot.testing.clock.VirtualClockLoop` latencies and bandwidth queues take no
  wall time and are exact.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import hashlib
import heapq
import itertools
import math
import random
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Self

from telebot.channels.transports.base import (
    Lane,
    Presence,
    PresenceCallback,
    Publisher,
    ReceiveLimits,
    Sample,
    SampleBatchCallback,
    Subscription,
    SubscriptionStats,
    Transport,
    gate_passes,
)
from telebot.channels.transports.inbox import Inbox
from telebot.config import TransportSettings
from telebot.errors import TransportError
from telebot.netem.model import LinkModel, LinkQueue, Profile
from telebot.netem.model import profile as netem_profile

__all__ = [
    "LinkConditions",
    "LinkStats",
    "MemoryHub",
    "MemoryTransport",
    "key_matches",
]


# --------------------------------------------------------------------------- key expressions


@functools.lru_cache(maxsize=4096)  # called for every frame x subscription: keys repeat
def key_matches(pattern: str, key: str) -> bool:
    """Whether the concrete ``key`` matches the zenoh-style ``pattern``.

    Chunks are separated by ``/``; ``*`` matches exactly one chunk and ``**`` zero or
    more chunks (so ``a/**`` matches ``a`` itself).
    """
    chunks = key.split("/")
    # The set of key positions the pattern prefix read so far can end at.
    positions = {0}
    for part in pattern.split("/"):
        if part == "**":
            positions = set(range(min(positions), len(chunks) + 1))
        else:
            positions = {
                i + 1 for i in positions if i < len(chunks) and (part == "*" or part == chunks[i])
            }
        if not positions:
            return False
    return len(chunks) in positions


def _check_key_expr(expr: str, *, wildcards: bool) -> None:
    if not expr or any(chunk == "" for chunk in expr.split("/")):
        raise TransportError(f"invalid key expression {expr!r}: empty chunk")
    for chunk in expr.split("/"):
        if "*" in chunk and (not wildcards or chunk not in ("*", "**")):
            what = "a wildcard" if not wildcards else "'*' or '**' as a whole chunk"
            raise TransportError(f"invalid key expression {expr!r}: only {what} allowed here")


# --------------------------------------------------------------------------- link model


@dataclass
class LinkConditions:
    """The conditions of one direction of a link; changes apply to later frames.

    Every assignment is validated, so a bad value fails where it is set, naming the field.
    """

    #: Probability in [0, 1] that a frame is lost.
    loss: float = 0.0
    #: One-way delay, seconds.
    latency: float = 0.0
    #: Each frame gets an extra uniform(0, jitter) delay, seconds: this reorders frames.
    jitter: float = 0.0
    #: Bytes per second (None = unlimited); frames queue behind each other.
    bandwidth: float | None = None
    #: A frame that would wait longer than this in the bandwidth queue is dropped.
    max_queue_delay: float = 1.0
    #: False = link cut: every frame is lost and the source's presence tokens vanish.
    up: bool = True
    # Set by the hub: cutting or healing a link changes which presence tokens are visible.
    _on_up_change: Callable[[], None] | None = field(
        default=None, init=False, repr=False, compare=False
    )

    def __setattr__(self, name: str, value: Any) -> None:
        if not name.startswith("_"):
            value = _validate_condition(name, value)
        changed = name == "up" and getattr(self, "up", value) != value
        super().__setattr__(name, value)
        if changed and self._on_up_change is not None:
            self._on_up_change()


_CONDITION_FIELDS = tuple(
    f.name for f in dataclasses.fields(LinkConditions) if not f.name.startswith("_")
)


def _validate_condition(name: str, value: Any) -> Any:
    if name == "up":
        if not isinstance(value, bool):
            raise ValueError(f"link condition 'up' must be a bool, got {value!r}")
        return value
    if name == "bandwidth" and value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or math.isnan(value):
        raise ValueError(f"link condition {name!r} must be a number, got {value!r}")
    if name == "loss" and not 0.0 <= value <= 1.0:
        raise ValueError(f"link condition 'loss' must be in [0, 1], got {value!r}")
    if name == "bandwidth" and not (value > 0 and math.isfinite(value)):
        raise ValueError(f"link condition 'bandwidth' must be > 0 or None, got {value!r}")
    if name in ("latency", "jitter", "max_queue_delay") and not (
        value >= 0 and math.isfinite(value)
    ):
        raise ValueError(f"link condition {name!r} must be >= 0 seconds, got {value!r}")
    return float(value)


@dataclass(slots=True)
class LinkStats:
    """Counters of one direction of a link; ``sent == delivered + lost + in_flight``."""

    sent: int = 0
    delivered: int = 0
    #: Every frame that did not arrive: random loss, link down, tail drop, closed receiver.
    lost: int = 0
    #: Of ``lost``: dropped because the bandwidth queue was longer than ``max_queue_delay``.
    tail_dropped: int = 0

    @property
    def in_flight(self) -> int:
        """Frames sent that have neither arrived nor been lost yet."""
        return self.sent - self.delivered - self.lost


class _Link:
    """One direction of a link: conditions, random stream, counters, bandwidth queue.

    With a netem profile set (:meth:`MemoryHub.set_profile`) the profile's
    :class:`~telebot.netem.model.LinkModel` decides each frame's fate instead of the
    conditions (a cut link still loses everything).
    """

    __slots__ = ("conditions", "model", "queue", "rng", "stats")

    def __init__(self, seed: int, src: str, dst: str, on_up_change: Callable[[], None]) -> None:
        # hashlib, not hash(): str hashes are randomised per process.
        digest = hashlib.sha256(f"{seed}\0{src}\0{dst}".encode()).digest()
        self.rng = random.Random(int.from_bytes(digest[:8], "big"))
        self.conditions = LinkConditions()
        self.conditions._on_up_change = on_up_change
        self.stats = LinkStats()
        self.queue = LinkQueue()  # the bandwidth queue (loop clock)
        self.model: LinkModel | None = None

    def transmit(self, size: int, now: float) -> float | None:
        """The delay of a frame of ``size`` bytes sent at ``now``, or None if it is lost."""
        if self.model is not None:
            return self._transmit_model(self.model, size, now)
        cond = self.conditions
        self.stats.sent += 1
        # Always draw both numbers so one frame's fate does not shift the next ones'.
        lose, spread = self.rng.random(), self.rng.random()
        if not cond.up:
            self.stats.lost += 1
            return None
        delay = cond.latency + spread * cond.jitter
        if cond.bandwidth is not None:
            left = self.queue.admit(size / cond.bandwidth, now, cond.max_queue_delay)
            if left is None:
                self.stats.lost += 1
                self.stats.tail_dropped += 1
                return None
            delay += left - now
        if lose < cond.loss:  # lost on the wire, after it used its share of bandwidth
            self.stats.lost += 1
            return None
        return delay

    def _transmit_model(self, model: LinkModel, size: int, now: float) -> float | None:
        self.stats.sent += 1
        tail_dropped = model.stats.tail_dropped
        arrival = model.transmit(size, now)  # drawn even when cut: fates do not shift
        if arrival is None or not self.conditions.up:
            self.stats.lost += 1
            self.stats.tail_dropped += model.stats.tail_dropped - tail_dropped
            return None
        return arrival - now


class MemoryHub:
    """An in-process network: nodes (open memory transports) joined by directional links."""

    _registry: ClassVar[dict[str, MemoryHub]] = {}

    def __init__(self, seed: int = 0) -> None:
        self.seed = seed
        self._links: dict[tuple[str, str], _Link] = {}
        self._nodes: dict[str, MemoryTransport] = {}
        self._names = itertools.count(1)

    @classmethod
    def named(cls, name: str) -> MemoryHub:
        """The process-wide hub called ``name``, created (seed 0) on first use."""
        hub = cls._registry.get(name)
        if hub is None:
            hub = cls._registry[name] = cls()
        return hub

    @property
    def nodes(self) -> list[str]:
        """Names of the nodes currently attached (open transports)."""
        return list(self._nodes)

    def link(self, src: str, dst: str) -> LinkConditions:
        """The conditions of direction ``src`` -> ``dst``; mutate them to change the link."""
        return self._link(src, dst).conditions

    def link_stats(self, src: str, dst: str) -> LinkStats:
        """The live counters of direction ``src`` -> ``dst``."""
        return self._link(src, dst).stats

    def set_link(self, a: str, b: str, **fields: Any) -> None:
        """Set the same condition fields on both directions ``a`` -> ``b`` and ``b`` -> ``a``."""
        unknown = sorted(set(fields) - set(_CONDITION_FIELDS))
        if unknown:
            known = ", ".join(_CONDITION_FIELDS)
            raise ValueError(f"unknown link condition {', '.join(unknown)}; known: {known}")
        LinkConditions(**fields)  # validate everything before changing anything
        for src, dst in ((a, b), (b, a)):
            conditions = self.link(src, dst)
            for name, value in fields.items():
                setattr(conditions, name, value)

    def set_profile(
        self, a: str, b: str, profile: Profile | str | None, *, seed: int | None = None
    ) -> None:
        """Play a netem profile (or its name) on the link between ``a`` and ``b``.

        ``a`` is the side on the profiled network: ``a`` -> ``b`` is its "up" direction
        (``rate_up``), ``b`` -> ``a`` its "down". Both directions share one outage
        schedule, whose clock starts at the first frame. ``seed`` defaults to the hub's.
        While a profile is set it replaces the link's conditions, except that a cut link
        (:meth:`cut`) still loses everything; ``None`` goes back to the conditions.
        """
        if isinstance(profile, str):
            profile = netem_profile(profile)
        if profile is None:
            up = down = None
        else:
            up, down = LinkModel.pair(profile, self.seed if seed is None else seed)
        self._link(a, b).model = up
        self._link(b, a).model = down

    def outage(self, a: str, b: str, seconds: float, now: float) -> None:
        """Force an outage of ``seconds`` from ``now`` (loop clock) on a profiled link."""
        model = self._link(a, b).model
        if model is None:
            raise ValueError(f"no netem profile on the link {a!r} - {b!r}: set_profile first")
        model.schedule.force(now, seconds)

    def cut(self, a: str, b: str) -> None:
        """Cut the link both ways: every frame lost, presence lost both ways."""
        self.set_link(a, b, up=False)

    def heal(self, a: str, b: str) -> None:
        """Bring the link back up both ways: frames flow and presence reappears."""
        self.set_link(a, b, up=True)

    # -- used by MemoryTransport

    def _link(self, src: str, dst: str) -> _Link:
        if src == dst:
            raise ValueError(f"node {src!r} has no link to itself (its own frames are unimpaired)")
        link = self._links.get((src, dst))
        if link is None:
            link = self._links[(src, dst)] = _Link(self.seed, src, dst, self._refresh_presence)
        return link

    def _new_node_name(self) -> str:
        while True:
            name = f"node-{next(self._names)}"
            if name not in self._nodes:
                return name

    def _attach(self, transport: MemoryTransport) -> None:
        if transport.node in self._nodes:
            raise TransportError(f"memory hub already has an open node {transport.node!r}")
        self._nodes[transport.node] = transport

    def _detach(self, transport: MemoryTransport) -> None:
        if self._nodes.get(transport.node) is transport:
            del self._nodes[transport.node]
        self._refresh_presence()

    def _visible(self, src: str, dst: str) -> bool:
        link = self._links.get((src, dst))
        return src == dst or link is None or link.conditions.up

    def _refresh_presence(self) -> None:
        # Recompute what every watcher should see and report the difference: one rule
        # covers tokens declared and closed, links cut and healed, nodes leaving.
        tokens = [(t.key, node) for node, tr in self._nodes.items() for t in tr._tokens]
        for watcher_node, transport in self._nodes.items():
            for watch in transport._watches:
                now_seen = {
                    key
                    for key, node in tokens
                    if key_matches(watch.pattern, key) and self._visible(node, watcher_node)
                }
                for key in sorted(watch.seen - now_seen):
                    transport._post(transport._fire_presence, watch, key, False)
                for key in sorted(now_seen - watch.seen):
                    transport._post(transport._fire_presence, watch, key, True)
                watch.seen = now_seen


# --------------------------------------------------------------------------- handles


class _MemoryPublisher(Publisher):
    def __init__(self, transport: MemoryTransport, key: str, lane: Lane) -> None:
        self._transport = transport
        self.key = key
        #: Recorded only: the memory transport does not model lane priorities.
        self.lane = lane
        self._closed = False

    def put(self, payload: bytes) -> None:
        if self._closed:
            raise TransportError(f"publisher on {self.key!r} is closed")
        self._transport._publish(self.key, bytes(payload))  # copy: callers reuse buffers

    def close(self) -> None:
        self._closed = True


class _MemorySubscription(Subscription):
    def __init__(
        self,
        transport: MemoryTransport,
        pattern: str,
        callback: SampleBatchCallback,
        limits: ReceiveLimits,
    ) -> None:
        self._transport = transport
        self.pattern = pattern
        self.callback = callback
        self.limits = limits
        #: The bounded queue between the frames' arrival and the callback.
        self.inbox: Inbox[Sample] = Inbox(
            limits,
            default_samples=transport.queue_size,
            default_bytes=transport.queue_bytes,
        )
        self.stats = SubscriptionStats()
        self.closed = False
        self._drain_scheduled = False

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.inbox.clear()
            self._transport._subs.remove(self)

    def _deliver(self) -> None:
        """Loop: hand up to ``limits.batch`` queued samples to the callback; the rest on
        the next turn, after other callbacks had theirs."""
        self._drain_scheduled = False
        transport = self._transport
        batch = self.inbox.take()
        if len(self.inbox) and not self.closed:
            self._drain_scheduled = True
            assert transport._loop is not None
            transport._loop.call_soon(self._deliver)
        self.inbox.report(self.stats, transport.stats)
        if self.closed or not batch:
            return
        try:
            self.callback(batch)
        except Exception as exc:  # one faulty consumer must not starve the others
            assert transport._loop is not None
            transport._loop.call_exception_handler(
                {"message": f"subscription callback on {self.pattern!r} failed", "exception": exc}
            )


class _MemoryWatch(Subscription):
    def __init__(
        self, transport: MemoryTransport, pattern: str, callback: PresenceCallback
    ) -> None:
        self._transport = transport
        self.pattern = pattern
        self.callback = callback
        self.seen: set[str] = set()  # keys last reported alive
        self.stats = SubscriptionStats()  # presence changes are not samples: stays zero
        self.closed = False

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._transport._watches.remove(self)


class _MemoryPresence(Presence):
    def __init__(self, transport: MemoryTransport, key: str) -> None:
        self._transport = transport
        self.key = key
        self.closed = False

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._transport._tokens.remove(self)
            self._transport.hub._refresh_presence()


# --------------------------------------------------------------------------- transport

#: Default bounds of a subscription's queue (zenoh's defaults: ``[transport.zenoh]``).
DEFAULT_QUEUE_SIZE = 4096
DEFAULT_QUEUE_BYTES = 8 << 20
#: Frames in flight to one node at most (the link's delay line); beyond, the oldest drops.
_MAX_IN_FLIGHT = 65536

# In-flight frames of a node, ordered by arrival time then by send order (the sequence
# number keeps equal arrival times first-in first-out, which the loop's timers do not).
_Arrival = tuple[float, int, Sample, LinkStats | None]


class MemoryTransport(Transport):
    """A node of a :class:`MemoryHub`; frames travel through the hub's link conditions."""

    name = "memory"
    section = "memory"

    def __init__(
        self,
        hub: MemoryHub | None = None,
        node: str | None = None,
        *,
        queue_size: int = DEFAULT_QUEUE_SIZE,
        queue_bytes: int = DEFAULT_QUEUE_BYTES,
    ) -> None:
        """Join ``hub`` (default: the hub named "default") as ``node`` (default: unique name).

        ``queue_size`` and ``queue_bytes`` bound each subscription's queue (its
        :class:`~telebot.channels.transports.inbox.Inbox`) unless its ``ReceiveLimits``
        say otherwise: beyond either the oldest sample is dropped and counted in
        ``stats.dropped``, as on zenoh (same defaults).
        """
        super().__init__()
        self._hub = hub if hub is not None else MemoryHub.named("default")
        self._node = node if node is not None else self._hub._new_node_name()
        #: Default bounds of a subscription's queue, in samples and bytes.
        self.queue_size = queue_size
        self.queue_bytes = queue_bytes
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread = 0
        self._closed = False
        self._subs: list[_MemorySubscription] = []
        self._watches: list[_MemoryWatch] = []
        self._tokens: list[_MemoryPresence] = []
        self._in_flight: list[_Arrival] = []
        self._seq = itertools.count()
        self._wakeup: asyncio.Handle | None = None
        self._wakeup_at = math.inf

    @classmethod
    def from_settings(cls, settings: TransportSettings) -> Self:
        """A transport on the hub ``settings.memory.hub`` as node ``settings.memory.node``."""
        return cls(MemoryHub.named(settings.memory.hub), settings.memory.node)

    @property
    def node(self) -> str:
        """This transport's node name on the hub."""
        return self._node

    @property
    def hub(self) -> MemoryHub:
        """The hub this transport belongs to."""
        return self._hub

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open" if self._loop else "unopened"
        return f"<MemoryTransport node={self._node!r} {state}>"

    async def open(self) -> None:
        """Attach to the hub; callbacks will run on the current event loop."""
        if self._closed:
            raise TransportError(f"memory transport {self._node!r} is closed; make a new one")
        if self._loop is not None:
            raise TransportError(f"memory transport {self._node!r} is already open")
        self._hub._attach(self)
        self._loop = asyncio.get_running_loop()
        self._thread = threading.get_ident()

    async def close(self) -> None:
        """Detach from the hub: nothing more is delivered, tokens vanish. Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._wakeup is not None:
            self._wakeup.cancel()
            self._wakeup = None
        for *_, stats in self._in_flight:
            if stats is not None:
                stats.lost += 1
        self._in_flight.clear()
        for sub in self._subs:
            sub.closed = True
            sub.inbox.clear()
        for watch in self._watches:
            watch.closed = True
        for token in self._tokens:
            token.closed = True
        self._subs.clear()
        self._watches.clear()
        self._tokens.clear()
        if self._loop is not None:
            self._hub._detach(self)

    def publisher(self, key: str, lane: Lane = Lane.DATA) -> Publisher:
        """A publisher on the concrete ``key``; ``lane`` is recorded but not modelled."""
        self._check_open()
        _check_key_expr(key, wildcards=False)
        return _MemoryPublisher(self, key, lane)

    def subscribe(
        self,
        pattern: str,
        callback: SampleBatchCallback,
        *,
        limits: ReceiveLimits | None = None,
    ) -> Subscription:
        """Call ``callback`` on the loop with batches of samples whose key matches ``pattern``.

        ``limits`` bound the subscription's queue as on zenoh (see
        :class:`~telebot.channels.transports.inbox.Inbox`): larger payloads than
        ``max_payload`` are dropped and counted as oversized, the oldest samples beyond
        ``max_samples`` or ``max_bytes`` as dropped, and at most ``batch`` samples are
        delivered per loop turn.
        """
        self._check_open()
        _check_key_expr(pattern, wildcards=True)
        sub = _MemorySubscription(self, pattern, callback, limits or ReceiveLimits())
        self._subs.append(sub)
        return sub

    def declare_presence(self, key: str) -> Presence:
        """A token on ``key``, visible to nodes whose link from this node is up."""
        self._check_open()
        _check_key_expr(key, wildcards=False)
        token = _MemoryPresence(self, key)
        self._tokens.append(token)
        self._hub._refresh_presence()
        return token

    def watch_presence(self, pattern: str, callback: PresenceCallback) -> Subscription:
        """Report visible tokens matching ``pattern`` (existing ones first) on the loop."""
        self._check_open()
        _check_key_expr(pattern, wildcards=True)
        watch = _MemoryWatch(self, pattern, callback)
        self._watches.append(watch)
        self._hub._refresh_presence()  # reports the existing tokens: the history
        return watch

    # -- internals

    def _check_open(self) -> asyncio.AbstractEventLoop:
        if self._closed:
            raise TransportError(f"memory transport {self._node!r} is closed")
        if self._loop is None:
            raise TransportError(f"memory transport {self._node!r} is not open; call open() first")
        return self._loop

    def _post(self, fn: Callable[..., None], *args: Any) -> None:
        """Run ``fn(*args)`` soon on this transport's loop, from whichever thread."""
        assert self._loop is not None
        if threading.get_ident() == self._thread:
            self._loop.call_soon(fn, *args)
        else:
            self._loop.call_soon_threadsafe(fn, *args)

    def _publish(self, key: str, payload: bytes) -> None:
        now = self._check_open().time()
        self.stats.published += 1
        sample = Sample(key, payload)
        for node, dest in list(self._hub._nodes.items()):
            # Like zenoh, frames only travel to nodes that subscribed to them.
            if not any(key_matches(sub.pattern, key) for sub in dest._subs):
                continue
            if dest is self:
                self._arrive(now, sample, None)
                continue
            link = self._hub._link(self._node, node)
            delay = link.transmit(len(payload), now)
            if delay is None:
                continue
            if threading.get_ident() == dest._thread:
                dest._arrive(now + delay, sample, link.stats)
            else:
                dest._post(dest._arrive, now + delay, sample, link.stats)

    def _arrive(self, due: float, sample: Sample, stats: LinkStats | None) -> None:
        """Queue a frame arriving at ``due`` (loop clock); never calls back synchronously."""
        if self._closed or self._loop is None:
            if stats is not None:
                stats.lost += 1
            return
        if len(self._in_flight) >= _MAX_IN_FLIGHT:
            *_, oldest_stats = heapq.heappop(self._in_flight)
            if oldest_stats is not None:
                oldest_stats.delivered += 1  # it crossed the link; the consumer fell behind
            self.stats.dropped += 1
        heapq.heappush(self._in_flight, (due, next(self._seq), sample, stats))
        self._arm(due)

    def _arm(self, due: float) -> None:
        assert self._loop is not None
        if self._wakeup is not None:
            if self._wakeup_at <= due:
                return
            self._wakeup.cancel()
        self._wakeup_at = due
        if due <= self._loop.time():
            self._wakeup = self._loop.call_soon(self._drain)
        else:
            self._wakeup = self._loop.call_at(due, self._drain)

    def _drain(self) -> None:
        """Queue every frame that has arrived in its subscriptions' inboxes, and deliver
        each subscription's first batch in this turn."""
        assert self._loop is not None
        # The loop may fire a timer a hair before its time: what it was armed for is due.
        limit = max(self._loop.time(), self._wakeup_at)
        self._wakeup = None
        touched: dict[_MemorySubscription, None] = {}  # in order of first arrival
        in_flight = self._in_flight
        while in_flight and in_flight[0][0] <= limit:
            _, _, sample, stats = heapq.heappop(in_flight)
            if stats is not None:
                stats.delivered += 1
            size = len(sample.payload)
            for sub in self._subs:
                if key_matches(sub.pattern, sample.key):
                    touched[sub] = None
                    if not sub.inbox.admits(size):
                        continue
                    if sub.gate is not None and not gate_passes(sub.gate, sample.payload):
                        sub.inbox.gated += 1
                        continue
                    sub.inbox.push(sample, size)
        if in_flight:
            self._arm(in_flight[0][0])
        for sub in touched:
            if not sub._drain_scheduled:  # else its next batch is already on its way
                sub._deliver()

    def _fire_presence(self, watch: _MemoryWatch, key: str, alive: bool) -> None:
        if watch.closed or self._closed:
            return
        try:
            watch.callback(key, alive)
        except Exception as exc:
            assert self._loop is not None
            self._loop.call_exception_handler(
                {"message": f"presence callback on {watch.pattern!r} failed", "exception": exc}
            )
