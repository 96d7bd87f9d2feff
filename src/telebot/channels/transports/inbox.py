"""The bounded receive path every transport shares: one :class:`Inbox` per subscription.

A transport's receiving side (zenoh's reader thread, the memory hub's arrival timer) calls
:meth:`Inbox.admits` with a payload's size before copying it (a payload over
``max_payload`` is counted as oversized and never copied), then :meth:`Inbox.push` with
the item. The inbox holds at most ``max_samples`` items and ``max_bytes`` bytes: beyond
either it drops the oldest, counted in ``dropped``. The event-loop side takes at most
``batch`` items per turn with :meth:`Inbox.take` and hands them to the subscription's
callback; the rest waits for the next turn, so that one flooded subscription cannot hold
the loop while another (a call's control frames) waits.

Sans-IO: no clock, no loop, no I/O; the transport decides when to push and when to take.
It may push on one thread and take on another without a lock: deque appends and pops are
atomic, each counter is written by one side only (the producer writes everything but
``bytes_out``, which the consumer writes), and queued bytes are what came in minus what
left either way. So :meth:`take` tolerates finding the queue emptier than it was (the
producer dropped the oldest meanwhile).
"""

from __future__ import annotations

import collections
import sys
from typing import Generic, TypeVar

from telebot.channels.transports.base import ReceiveLimits, SubscriptionStats, TransportStats

__all__ = ["Inbox"]

Item = TypeVar("Item")


class Inbox(Generic[Item]):
    """A subscription's queue, bounded in items and bytes, dropping the oldest; counted.

    ``limits`` gives the bounds; a bound it leaves at None is the transport's default
    (``default_samples``, ``default_bytes``; a payload bound left at None admits any size).
    """

    __slots__ = (
        "_queue",
        "batch",
        "bytes_dropped",
        "bytes_in",
        "bytes_out",
        "dropped",
        "gated",
        "max_bytes",
        "max_payload",
        "max_samples",
        "oversized",
        "received",
    )

    def __init__(self, limits: ReceiveLimits, *, default_samples: int, default_bytes: int) -> None:
        self.max_samples = limits.max_samples or default_samples
        self.max_bytes = limits.max_bytes or default_bytes
        self.max_payload = limits.max_payload or sys.maxsize
        self.batch = limits.batch
        self._queue: collections.deque[tuple[Item, int]] = collections.deque()
        #: Items pushed (queued for delivery), ever.
        self.received = 0
        #: Of those, dropped because the consumer fell behind (oldest first).
        self.dropped = 0
        #: Payloads refused by :meth:`admits`: larger than ``max_payload``.
        self.oversized = 0
        #: Payloads the subscription's gate refused (counted here by the transport).
        self.gated = 0
        self.bytes_in = 0  # producer
        self.bytes_dropped = 0  # producer
        self.bytes_out = 0  # consumer

    def __len__(self) -> int:
        return len(self._queue)

    @property
    def queued_bytes(self) -> int:
        """Bytes in the queue now."""
        return self.bytes_in - self.bytes_dropped - self.bytes_out

    def admits(self, size: int) -> bool:
        """Whether a payload of ``size`` bytes may be taken at all; counts it oversized if not."""
        if size > self.max_payload:
            self.oversized += 1
            return False
        return True

    def push(self, item: Item, size: int) -> None:
        """Queue ``item`` (``size`` payload bytes), dropping the oldest beyond the bounds."""
        queue = self._queue
        # Inline, not queued_bytes: this runs for every sample of a flood.
        if queue and (
            len(queue) >= self.max_samples
            or self.bytes_in - self.bytes_dropped - self.bytes_out + size > self.max_bytes
        ):
            self._make_room(size)
        self.bytes_in += size
        self.received += 1
        queue.append((item, size))

    def _make_room(self, size: int) -> None:
        queue = self._queue
        while queue and (
            len(queue) >= self.max_samples or self.queued_bytes + size > self.max_bytes
        ):
            try:
                _, old_size = queue.popleft()
            except IndexError:  # the consumer took it meanwhile
                return
            self.dropped += 1
            self.bytes_dropped += old_size

    def take(self) -> list[Item]:
        """Up to ``batch`` items, oldest first (the consumer's side)."""
        pop = self._queue.popleft
        items: list[Item] = []
        for _ in range(min(len(self._queue), self.batch)):
            try:
                item, size = pop()
            except IndexError:  # the producer dropped the oldest meanwhile
                break
            # Counted as it leaves, so the producer never sees bytes that are already gone.
            self.bytes_out += size
            items.append(item)
        return items

    def clear(self) -> None:
        """Forget everything queued (the subscription closed); counters stay."""
        self._queue.clear()

    def report(self, stats: SubscriptionStats, total: TransportStats) -> None:
        """Copy the counters into the subscription's ``stats`` and add what is new to the
        transport's ``total`` (call it on the loop, after each take)."""
        received, dropped, oversized = self.received, self.dropped, self.oversized
        total.received += received - stats.received
        total.dropped += dropped - stats.dropped
        total.oversized += oversized - stats.oversized
        stats.received, stats.dropped, stats.oversized = received, dropped, oversized
        stats.gated = self.gated
