"""The link model of the network emulator: sans-IO (no clock, no sockets).

A :class:`Profile` names the figures of a network (one-way delay, jitter, random and
burst loss, a bandwidth cap with a queue, an outage schedule); a :class:`LinkModel`
plays one direction of such a link packet by packet: ``transmit(size, now)`` says when
the packet arrives, or None when it is lost. The caller brings the clock (``now``, any
monotonic seconds) and does the I/O: :class:`telebot.netem.proxy.NetemProxy` on real
sockets, the memory transport's hub in process (``MemoryHub.set_profile``).

Everything random comes from ``random.Random`` streams seeded from (seed, direction), so
the same seed loses the same packets; every packet draws the same four numbers whatever
the profile, so changing e.g. the delay does not change which packets are lost.

Directions: a profile describes the access link of one side (the robot on 4G, the user on
hotel Wi-Fi). ``"up"`` is from that side into the network (``rate_up``), ``"down"`` is
towards it (``rate_down``).

Datagrams and streams: by default a link carries datagrams (UDP): a lost one is gone, a
full queue drops at its tail. Jitter changes the spacing of datagrams but not their order
(as queueing does on a real path: a datagram drawn to arrive before the one sent ahead of
it arrives just after it), except for the profile's ``reorder`` share, which arrive at
their own jittered time, possibly ahead of earlier ones. With ``ordered=True`` it carries one
TCP byte stream: nothing is lost or reordered, but a "lost" chunk arrives after TCP's
retransmission timeout (doubling on each further loss) and holds up every chunk behind it
(head-of-line blocking); an outage delays instead of losing; the queue never drops (the
sender is held back by flow control instead: see :meth:`LinkModel.backlog`). Several TCP
connections through one access link share one ordered model (its bandwidth queue, its loss
chain), each in order on its own (:class:`InOrder`): a retransmission holds up only its
own connection, and a picture queued on one still delays a key press sent on another.
"""

from __future__ import annotations

import hashlib
import math
import random
from dataclasses import dataclass, fields
from typing import Any, Literal

from telebot.errors import ConfigError

__all__ = [
    "MIN_RTO",
    "PROFILES",
    "Burst",
    "Direction",
    "InOrder",
    "LinkModel",
    "LinkQueue",
    "ModelStats",
    "OutageSchedule",
    "Outages",
    "Profile",
    "profile",
]

Direction = Literal["up", "down"]

#: TCP's minimum retransmission timeout (Linux: 200 ms), seconds.
MIN_RTO = 0.2
#: TCP's retransmission timeout stops doubling here (Linux: 120 s; 60 s is plenty here).
MAX_RTO = 60.0


def _check(name: str, value: float | None, *, low: float = 0.0, high: float = math.inf) -> None:
    if value is None:
        return
    if isinstance(value, bool) or not isinstance(value, int | float) or not low <= value <= high:
        raise ValueError(f"{name} must be a number in [{low}, {high}], got {value!r}")


@dataclass(frozen=True)
class Burst:
    """Burst loss: a Gilbert-Elliott chain, one step per packet.

    The link is either good or bad; each packet it moves good -> bad with probability
    ``enter`` and bad -> good with ``leave`` (so a bad spell lasts ``1 / leave`` packets
    on average), and a packet sent while bad is lost with probability ``loss``.
    """

    enter: float
    leave: float
    loss: float = 1.0

    def __post_init__(self) -> None:
        _check("burst enter", self.enter, high=1.0)
        _check("burst leave", self.leave, high=1.0)
        _check("burst loss", self.loss, high=1.0)
        if self.leave == 0.0:
            raise ValueError("burst leave must be > 0 (a bad spell that never ends)")

    @classmethod
    def of(cls, share: float, length: float, loss: float = 1.0) -> Burst:
        """Bursts that lose ``share`` of all packets, ``length`` packets long on average."""
        _check("burst share", share, high=loss * 0.999)
        _check("burst length", length, low=1.0)
        leave = 1.0 / length
        bad = share / loss if loss else 0.0  # the chain's long-run share of bad packets
        return cls(enter=bad * leave / (1.0 - bad), leave=leave, loss=loss)

    @property
    def bad_share(self) -> float:
        """The long-run share of packets sent while the link is bad."""
        return self.enter / (self.enter + self.leave)

    @property
    def mean_loss(self) -> float:
        """The long-run share of packets these bursts lose."""
        return self.bad_share * self.loss

    @property
    def mean_length(self) -> float:
        """The mean length of a bad spell, packets."""
        return 1.0 / self.leave


@dataclass(frozen=True)
class Outages:
    """An outage schedule: every ``period`` seconds, a gap of ``duration`` seconds.

    Where in the period the gaps fall (the phase) is drawn from the model's seed.
    """

    period: float
    duration: float

    def __post_init__(self) -> None:
        _check("outage period", self.period, low=1e-3)
        _check("outage duration", self.duration, high=self.period)


@dataclass(frozen=True)
class Profile:
    """The figures of a network, as seen by the side on it (see the module's Directions)."""

    name: str
    #: One-way delay, seconds.
    delay: float = 0.0
    #: Each packet's delay is uniform in ``delay +- jitter`` (never below 0), seconds;
    #: packets keep their order (see ``reorder``).
    jitter: float = 0.0
    #: The share of datagrams that may overtake earlier ones (streams never reorder).
    reorder: float = 0.0
    #: Random (independent) loss probability of each packet, on top of the bursts.
    loss: float = 0.0
    #: Burst loss (Gilbert-Elliott), or None for none.
    burst: Burst | None = None
    #: Bandwidth towards the side (bit/s), None = unlimited.
    rate_down: float | None = None
    #: Bandwidth from the side (bit/s), None = unlimited.
    rate_up: float | None = None
    #: The bandwidth queue holds this many seconds of traffic; datagrams beyond are dropped.
    queue: float = 0.2
    #: The outage schedule, or None for none.
    outages: Outages | None = None
    #: One line for people (the README's table).
    description: str = ""

    def __post_init__(self) -> None:
        _check("delay", self.delay)
        _check("jitter", self.jitter)
        _check("loss", self.loss, high=1.0)
        _check("reorder", self.reorder, high=1.0)
        _check("rate_down", self.rate_down, low=1.0)
        _check("rate_up", self.rate_up, low=1.0)
        _check("queue", self.queue)

    def rate(self, direction: Direction) -> float | None:
        """The bandwidth of ``direction``, bit/s (None = unlimited)."""
        return self.rate_up if direction == "up" else self.rate_down

    @property
    def mean_loss(self) -> float:
        """The long-run share of datagrams lost (random and burst loss; outages aside)."""
        burst = self.burst.mean_loss if self.burst is not None else 0.0
        return 1.0 - (1.0 - self.loss) * (1.0 - burst)

    @property
    def rto(self) -> float:
        """TCP's first retransmission timeout on this link: srtt + 4 rttvar, at least 200 ms."""
        return max(MIN_RTO, 2 * self.delay + 4 * self.jitter)


def _mbit(value: float) -> float:
    return value * 1e6


def _lossy(total: float, length: float) -> dict[str, Any]:
    """Loss fields losing ``total`` of the datagrams, half at random and half in bursts of
    ``length`` packets on average."""
    burst = Burst.of(total / 2, length)
    return {"loss": 1.0 - (1.0 - total) / (1.0 - burst.mean_loss), "burst": burst}


#: The named profiles (README "Network emulator"); of each loss figure (``mean_loss``), half
#: is random and half in bursts.
PROFILES: dict[str, Profile] = {
    p.name: p
    for p in (
        Profile("lan", description="a wired LAN: no delay, no loss"),
        Profile(
            "wifi",
            delay=0.005,
            jitter=0.003,
            **_lossy(0.005, length=4),
            outages=Outages(period=30.0, duration=0.3),
            description="office Wi-Fi: 5 +- 3 ms, 0.5 % loss, a 300 ms roaming gap every 30 s",
        ),
        Profile(
            "4g",
            delay=0.040,
            jitter=0.015,
            **_lossy(0.01, length=5),
            rate_down=_mbit(5),
            rate_up=_mbit(2),
            queue=0.3,
            description="a 4G dongle: 40 +- 15 ms, 1 % loss, 5 Mbit/s down, 2 Mbit/s up",
        ),
        Profile(
            "intercontinental",
            delay=0.160,
            jitter=0.010,
            **_lossy(0.005, length=4),
            description="another continent: 160 +- 10 ms, 0.5 % loss",
        ),
        Profile(
            "bad",
            delay=0.080,
            jitter=0.040,
            reorder=0.01,
            **_lossy(0.05, length=8),
            rate_down=_mbit(1),
            rate_up=_mbit(1),
            queue=0.5,
            description="a bad link: 80 +- 40 ms, 5 % loss, 1 Mbit/s, 1 % reordered",
        ),
    )
}


def profile(name: str) -> Profile:
    """The profile called ``name``; ConfigError naming the known ones."""
    try:
        return PROFILES[name]
    except (KeyError, TypeError):
        known = ", ".join(PROFILES)
        raise ConfigError(f"unknown network profile {str(name)[:40]!r}; known: {known}") from None


def _rng(seed: int, *labels: str) -> random.Random:
    # hashlib, not hash(): str hashes are randomised per process.
    digest = hashlib.sha256("\0".join([str(seed), *labels]).encode()).digest()
    return random.Random(int.from_bytes(digest[:8], "big"))


class LinkQueue:
    """A first-in first-out bandwidth queue: packets leave one after another at a rate.

    Shared by the netem model and the memory transport's link conditions.
    """

    __slots__ = ("busy_until",)

    def __init__(self) -> None:
        #: When the last packet admitted has left (the caller's clock).
        self.busy_until = -math.inf

    def wait(self, now: float) -> float:
        """How long a packet arriving at ``now`` waits before it starts leaving, seconds."""
        return max(0.0, self.busy_until - now)

    def admit(self, seconds: float, now: float, max_wait: float = math.inf) -> float | None:
        """Queue a packet that takes ``seconds`` to send; when it has left, or None if the
        queue is longer than ``max_wait`` (tail drop)."""
        start = max(now, self.busy_until)
        if start - now > max_wait:
            return None
        self.busy_until = start + seconds
        return self.busy_until


class OutageSchedule:
    """When a link is down: the profile's periodic gaps plus gaps forced by :meth:`force`.

    The periodic gaps start at ``origin + phase + k * period``: ``origin`` is the first
    ``now`` the schedule sees, ``phase`` is drawn from the seed. Both directions of a link
    share one schedule (:meth:`LinkModel.pair`): an outage cuts both ways.
    """

    def __init__(self, outages: Outages | None, seed: int = 0) -> None:
        self.outages = outages
        self.phase = _rng(seed, "outages").uniform(0.0, outages.period) if outages else 0.0
        self.origin: float | None = None
        self._forced: list[tuple[float, float]] = []

    def force(self, now: float, seconds: float) -> None:
        """A gap of ``seconds`` starting at ``now``."""
        _check("outage seconds", seconds)
        self._start(now)
        self._forced = [(s, e) for s, e in self._forced if e > now]
        self._forced.append((now, now + seconds))

    def gap_at(self, now: float) -> tuple[float, float] | None:
        """The (start, end) of the gap ``now`` falls in (overlapping gaps merged), or None."""
        origin = self._start(now)
        spans = [(s, e) for s, e in self._forced if s <= now < e]
        if self.outages is not None and self.outages.duration > 0:
            period = self.outages.period
            start = origin + self.phase + math.floor((now - origin - self.phase) / period) * period
            if start <= now < start + self.outages.duration:
                spans.append((start, start + self.outages.duration))
        if not spans:
            return None
        return min(s for s, _ in spans), max(e for _, e in spans)

    def next_gap(self, now: float) -> float:
        """When the next periodic gap starts at or after ``now`` (inf with no schedule)."""
        origin = self._start(now)
        if self.outages is None or self.outages.duration == 0:
            return math.inf
        period = self.outages.period
        return origin + self.phase + math.ceil((now - origin - self.phase) / period) * period

    def _start(self, now: float) -> float:
        if self.origin is None:
            self.origin = now
        return self.origin


@dataclass(slots=True)
class ModelStats:
    """Counters of one :class:`LinkModel`; ``lost`` includes the three kinds after it."""

    sent: int = 0
    #: Datagrams lost, whatever the cause.
    lost: int = 0
    #: Of ``lost``: lost in a bad spell of the burst chain (random loss aside).
    burst_lost: int = 0
    #: Of ``lost``: sent while the link was in an outage.
    outage_lost: int = 0
    #: Of ``lost``: dropped because the bandwidth queue was full.
    tail_dropped: int = 0
    #: Stream chunks (``ordered``) that needed at least one retransmission or outlived an
    #: outage: delivered late, holding up what followed.
    retransmitted: int = 0

    def as_dict(self) -> dict[str, int]:
        """The counters by name."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


class InOrder:
    """One TCP byte stream's order on an ordered :class:`LinkModel`: when its last chunk
    arrives (a chunk never arrives before the one sent ahead of it on the same stream)."""

    __slots__ = ("last_arrival",)

    def __init__(self) -> None:
        self.last_arrival = -math.inf


class LinkModel:
    """One direction of a link playing a :class:`Profile`, packet by packet (sans-IO)."""

    def __init__(
        self,
        profile: Profile,
        seed: int = 0,
        direction: Direction = "down",
        *,
        ordered: bool = False,
        schedule: OutageSchedule | None = None,
    ) -> None:
        """``ordered``: a TCP stream instead of datagrams (module docstring); ``schedule``:
        an outage schedule shared with the other direction (default: a new one)."""
        if direction not in ("up", "down"):
            raise ValueError(f"direction must be 'up' or 'down', got {direction!r}")
        self.profile = profile
        self.direction: Direction = direction
        self.ordered = ordered
        self.schedule = schedule if schedule is not None else OutageSchedule(profile.outages, seed)
        self.stats = ModelStats()
        self._rng = _rng(seed, direction)
        self._retry_rng = _rng(seed, direction, "retransmissions")
        self._queue = LinkQueue()
        self._bad = False  # the burst chain's state
        self._order = InOrder()  # datagrams' order, or the stream's when none is given

    @classmethod
    def pair(
        cls, profile: Profile, seed: int = 0, *, ordered: bool = False
    ) -> tuple[LinkModel, LinkModel]:
        """The (up, down) models of one link, sharing one outage schedule."""
        schedule = OutageSchedule(profile.outages, seed)
        return (
            cls(profile, seed, "up", ordered=ordered, schedule=schedule),
            cls(profile, seed, "down", ordered=ordered, schedule=schedule),
        )

    @property
    def last_arrival(self) -> float:
        """When the last packet kept in order arrives (-inf before any); on an ordered model,
        of the model's own stream (one given to :meth:`transmit` keeps its own)."""
        return self._order.last_arrival

    def backlog(self, now: float) -> float:
        """Seconds of traffic waiting in the bandwidth queue at ``now``.

        A stream's sender should stop feeding the link while this exceeds
        ``profile.queue`` (what TCP's flow control does).
        """
        return self._queue.wait(now)

    def transmit(self, size: int, now: float, stream: InOrder | None = None) -> float | None:
        """When a packet of ``size`` bytes sent at ``now`` arrives, or None if it is lost.

        ``stream``: on an ordered model, the byte stream the chunk belongs to (default: the
        model's own one), so that several streams share the link but not their order."""
        p = self.profile
        self.stats.sent += 1
        # Always the same five draws, so one packet's fate does not shift the next ones'.
        step, burst_draw, loss_draw, spread, overtake = (self._rng.random() for _ in range(5))
        if p.burst is not None:
            self._bad = step >= p.burst.leave if self._bad else step < p.burst.enter
        burst_lost = self._bad and p.burst is not None and burst_draw < p.burst.loss
        lost = burst_lost or loss_draw < p.loss
        delay = max(0.0, p.delay + (2.0 * spread - 1.0) * p.jitter)
        if self.ordered:
            order = stream if stream is not None else self._order
            return self._stream(size, now, lost, delay, order)
        if self.schedule.gap_at(now) is not None:
            self._lose(outage=True)
            return None
        departed = now
        rate = p.rate(self.direction)
        if rate is not None:
            left = self._queue.admit(size * 8 / rate, now, p.queue)
            if left is None:
                self._lose(tail=True)
                return None
            departed = left
        if lost:  # lost on the wire, after it used its share of the bandwidth
            self._lose(burst=burst_lost)
            return None
        if overtake < p.reorder:
            return departed + delay
        order = self._order
        order.last_arrival = max(departed + delay, order.last_arrival)
        return order.last_arrival

    def _lose(self, *, outage: bool = False, tail: bool = False, burst: bool = False) -> None:
        self.stats.lost += 1
        self.stats.outage_lost += outage
        self.stats.tail_dropped += tail
        self.stats.burst_lost += burst

    def _stream(self, size: int, now: float, lost: bool, delay: float, order: InOrder) -> float:
        p = self.profile
        departed = now
        rate = p.rate(self.direction)
        if rate is not None:
            left = self._queue.admit(size * 8 / rate, now)
            assert left is not None  # no max_wait: a stream queue never drops
            departed = left
        # Each try that is lost, or falls in an outage, is sent again one RTO later, the
        # RTO doubling each time (TCP's exponential backoff): after a long outage the data
        # resumes only at the first retry after the link came back, as on a real link.
        attempt, rto, late = departed, p.rto, False
        while lost or self.schedule.gap_at(attempt) is not None:
            late = True
            attempt += rto
            rto = min(2 * rto, MAX_RTO)
            lost = self._retry_rng.random() < p.mean_loss
        self.stats.retransmitted += late
        # A byte stream arrives in order: a late chunk holds up everything behind it.
        arrival = max(attempt + delay, order.last_arrival)
        order.last_arrival = arrival
        return arrival
