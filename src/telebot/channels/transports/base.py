"""The small interface every transport implements.

A transport moves opaque byte frames by key and reports peer presence; it knows nothing
of calls, channels or cryptography. Keys are zenoh-style key expressions
(``telebot/robot/guiabot/in``); patterns may use ``*`` (one chunk) and ``**`` (any chunks).

Threading contract: every callback a transport invokes (``subscribe``'s batch callback,
``watch_presence``'s callback) runs on the asyncio event loop the transport was opened
on, never on a foreign thread. Received samples are delivered in batches, so a burst
costs one loop wake-up, through a bounded queue that drops the oldest sample when the
consumer falls behind (counted in :attr:`TransportStats.dropped`).

Each subscription may carry :class:`ReceiveLimits`: its own queue bound in samples *and*
bytes, and the largest payload it takes. A payload over the limit is dropped before it
is copied out of the transport (it cannot be an authentic frame), and a subscription
hands at most ``batch`` samples to its callback per event-loop turn, so that one flooded
subscription cannot hold the loop while another (a call's control frames) waits.
:class:`~telebot.channels.transports.inbox.Inbox` is that receive path, for every
transport to use; :mod:`telebot.testing.transport` checks that a transport keeps it.
"""

from __future__ import annotations

import abc
import enum
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import TYPE_CHECKING, ClassVar, Self

from pydantic import BaseModel

from telebot.channels.proto.frames import CALL_ID_LEN

if TYPE_CHECKING:
    from telebot.config import TransportSettings

__all__ = [
    "CliOption",
    "Lane",
    "Presence",
    "Publisher",
    "ReceiveLimits",
    "Sample",
    "Subscription",
    "SubscriptionStats",
    "Transport",
    "TransportStats",
    "gate_passes",
]

_log = logging.getLogger(__name__)


def gate_passes(gate: Callable[[bytes], bool], payload: bytes) -> bool:
    """A subscription gate's verdict on ``payload``; a gate that raises lets the payload
    through (the receiver, which authenticates everything anyway, decides)."""
    try:
        return gate(payload)
    except Exception:
        _log.exception("subscription gate raised; the payload is delivered")
        return True


#: How a call's data key ends (``{base}/call/{sender}/{call_id}/data``: its DATA and BULK
#: frames: pose, video, sound; telebot.channels.call).
DATA_KEY_SUFFIX = "/data"
#: How a call's CONTROL key ends (heartbeats, stops).
CONTROL_KEY_SUFFIX = "/ctl"


def is_call_data_key(key: str) -> bool:
    """Whether ``key`` is a call's data key, ``…/call/{sender}/{call_id}/data``, or a
    pattern over such keys (the call id ``*``): what a transport may carry apart from the
    rest (``[transport.zenoh] data_session``). Not a handshake key such as
    ``{ns}/robot/R/in/data`` (a user named ``data``): its call id chunk is not one."""
    chunks = key.split("/")
    if len(chunks) < 5 or chunks[-4] != "call" or "/" + chunks[-1] != DATA_KEY_SUFFIX:
        return False
    call_id = chunks[-2]
    return call_id == "*" or (
        len(call_id) == 2 * CALL_ID_LEN and all(c in "0123456789abcdef" for c in call_id)
    )


class Lane(enum.Enum):
    """Quality of service of a publisher: which traffic may delay which.

    CONTROL  stop, heartbeats, call set-up: highest priority, sent at once (express).
    DATA     ordinary channels (chat, pose, goals): normal priority.
    BULK     video and file chunks: lowest priority, dropped first under congestion,
             so that bulk can never delay a stop.
    """

    CONTROL = "control"
    DATA = "data"
    BULK = "bulk"


@dataclass(slots=True)
class Sample:
    """One received frame: the key it was published on and its bytes.

    Not frozen: one is built for every frame received, and a frozen dataclass takes
    several times longer to build.
    """

    key: str
    payload: bytes


@dataclass(slots=True)
class TransportStats:
    """Counters of one transport instance."""

    published: int = 0
    received: int = 0
    dropped: int = 0  # received but discarded because the consumer fell behind
    oversized: int = 0  # discarded uncopied: over a subscription's ``max_payload``


@dataclass(frozen=True, slots=True)
class ReceiveLimits:
    """Bounds of one subscription's receive path (see the module docstring).

    ``max_samples`` and ``max_bytes`` bound the queue between the transport's threads and
    the loop (the oldest sample is dropped beyond either); ``max_payload`` is the largest
    payload taken at all (larger ones are dropped uncopied, counted as oversized);
    ``batch`` is the most samples delivered per callback, the rest following on the next
    loop turn. ``None`` for a bound means the transport's default.
    """

    max_samples: int | None = None
    max_bytes: int | None = None
    max_payload: int | None = None
    batch: int = 256

    def __post_init__(self) -> None:
        for name in ("max_samples", "max_bytes", "max_payload"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ValueError(f"ReceiveLimits.{name} must be at least 1, not {value}")
        if self.batch < 1:
            raise ValueError(f"ReceiveLimits.batch must be at least 1, not {self.batch}")


@dataclass(slots=True)
class SubscriptionStats:
    """Counters of one subscription (also summed into the transport's stats)."""

    received: int = 0  # samples delivered or queued for delivery
    dropped: int = 0  # queued, then discarded because the consumer fell behind
    oversized: int = 0  # discarded uncopied: larger than ``ReceiveLimits.max_payload``
    gated: int = 0  # refused by the subscription's ``gate`` before they were queued


#: A check of a payload before it is queued: False drops it (see :attr:`Subscription.gate`).
Gate = Callable[[bytes], bool]
SampleBatchCallback = Callable[[Sequence[Sample]], None]
PresenceCallback = Callable[[str, bool], None]


@dataclass(frozen=True, slots=True)
class CliOption:
    """A command-line flag a transport declares: every command that connects has it.

    ``flag`` (``--listen``) sets ``setting``, a field of the transport's settings (its
    ``[transport.<section>]`` table, or for a plug-in its ``[transport.options]``), over
    what the config file says; ``repeatable`` flags collect a list (``action="append"``).
    """

    flag: str
    setting: str
    help: str
    metavar: str | None = None
    repeatable: bool = False


class Publisher(abc.ABC):
    """Publishes frames on one key with the QoS of one lane."""

    @abc.abstractmethod
    def put(self, payload: bytes) -> None:
        """Send ``payload``; never blocks (frames are dropped under congestion)."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the publisher; idempotent."""


class Subscription(abc.ABC):
    """A live subscription or presence watch; ``close()`` stops callbacks."""

    #: This subscription's own counters (a presence watch leaves them at zero).
    stats: SubscriptionStats
    #: If set, each payload is passed to it before it is queued, on whatever thread
    #: receives it (the zenoh reader thread), and only those it returns True for are
    #: queued and delivered (the others count in ``stats.gated``). So a check that is
    #: cheap and needs no state the loop changes (a call's AEAD) keeps what fails it out
    #: of the bounded queue, where it would push genuine frames out.
    gate: Gate | None = None

    @abc.abstractmethod
    def close(self) -> None:
        """Stop delivering; idempotent."""


class Presence(abc.ABC):
    """A presence token: while it exists, watchers of a matching pattern see it alive."""

    @abc.abstractmethod
    def close(self) -> None:
        """Withdraw the token; watchers see it gone. Idempotent."""


class Transport(abc.ABC):
    """Moves opaque frames by key and reports peer presence.

    Use as ``async with transport:``; :meth:`open` binds it to the running loop.
    """

    #: Registry name of the transport ("zenoh", "memory", ...).
    name: str = ""
    #: What on the path may silently drop frames (a router's access control), added to
    #: "did not answer" errors; empty when nothing does.
    unanswered_hint: str = ""
    #: A built-in's own table of the config file, ``[transport.<section>]`` (a field of
    #: :class:`~telebot.config.TransportSettings`); None: a plug-in, whose table is
    #: ``[transport.options]``.
    section: ClassVar[str | None] = None
    #: A plug-in's declared options: ``[transport.options]`` is validated with this model
    #: when the transport is created (:func:`~telebot.channels.transports.create_transport`),
    #: a bad value being one line naming its key; None: passed through unchecked.
    options_model: ClassVar[type[BaseModel] | None] = None
    #: The command-line flags that set this transport's settings (see :class:`CliOption`).
    cli_options: ClassVar[tuple[CliOption, ...]] = ()

    def __init__(self) -> None:
        self.stats = TransportStats()

    @classmethod
    @abc.abstractmethod
    def from_settings(cls, settings: TransportSettings) -> Self:
        """Build an unopened transport from the validated settings."""

    @abc.abstractmethod
    async def open(self) -> None:
        """Connect; after this the other methods may be called."""

    @abc.abstractmethod
    async def close(self) -> None:
        """Undeclare everything and disconnect; bounded in time, never hangs; idempotent."""

    @abc.abstractmethod
    def publisher(self, key: str, lane: Lane = Lane.DATA) -> Publisher:
        """Declare a publisher on ``key`` with the QoS of ``lane``."""

    @abc.abstractmethod
    def subscribe(
        self,
        pattern: str,
        callback: SampleBatchCallback,
        *,
        limits: ReceiveLimits | None = None,
    ) -> Subscription:
        """Deliver samples on keys matching ``pattern`` to ``callback`` on the loop, in batches.

        ``limits`` bounds this subscription's queue and payloads (default: the transport's
        own queue bound, any payload size, batches of 256).
        """

    @abc.abstractmethod
    def declare_presence(self, key: str) -> Presence:
        """Announce a presence token on ``key``."""

    @abc.abstractmethod
    def watch_presence(self, pattern: str, callback: PresenceCallback) -> Subscription:
        """Call ``callback(key, alive)`` for tokens matching ``pattern``.

        Tokens that already exist are reported alive at once (history), then every
        appearance and disappearance as it happens.
        """

    async def __aenter__(self) -> Self:
        await self.open()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()
