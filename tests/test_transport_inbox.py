"""The shared receive path, sans-IO: bounds in samples and bytes, drop-oldest, batches, counters."""

from __future__ import annotations

from telebot.channels.transports.base import ReceiveLimits, SubscriptionStats, TransportStats
from telebot.channels.transports.inbox import Inbox


def test_the_oldest_go_beyond_the_sample_bound_and_are_counted() -> None:
    inbox: Inbox[int] = Inbox(ReceiveLimits(max_samples=3), default_samples=99, default_bytes=99)
    for i in range(5):
        inbox.push(i, 1)
    assert (len(inbox), inbox.received, inbox.dropped) == (3, 5, 2)
    assert inbox.take() == [2, 3, 4]
    assert inbox.queued_bytes == 0


def test_the_oldest_go_beyond_the_byte_bound() -> None:
    inbox: Inbox[str] = Inbox(ReceiveLimits(), default_samples=99, default_bytes=10)
    for name in "abcd":
        inbox.push(name, 4)
    # 4 + 4 fit in 10 bytes, a third does not: each push drops the oldest until it fits.
    assert inbox.take() == ["c", "d"] and inbox.dropped == 2
    inbox.push("huge", 50)  # larger than the bound on its own: kept alone, not refused
    assert inbox.take() == ["huge"] and inbox.queued_bytes == 0


def test_payloads_over_max_payload_are_refused_and_counted() -> None:
    inbox: Inbox[bytes] = Inbox(ReceiveLimits(max_payload=4), default_samples=9, default_bytes=99)
    assert inbox.admits(4) and not inbox.admits(5)
    assert inbox.oversized == 1 and inbox.received == 0


def test_take_hands_out_at_most_a_batch_oldest_first() -> None:
    inbox: Inbox[int] = Inbox(ReceiveLimits(batch=4), default_samples=99, default_bytes=999)
    for i in range(10):
        inbox.push(i, 1)
    assert [inbox.take(), inbox.take(), inbox.take(), inbox.take()] == [
        [0, 1, 2, 3],
        [4, 5, 6, 7],
        [8, 9],
        [],
    ]


def test_report_adds_only_what_is_new_to_the_transport() -> None:
    inbox: Inbox[int] = Inbox(ReceiveLimits(max_samples=2), default_samples=9, default_bytes=99)
    stats, total = SubscriptionStats(), TransportStats(received=10)
    for i in range(3):
        inbox.push(i, 1)
    inbox.admits(1 << 40)  # no max_payload: any size is taken
    inbox.gated += 1
    inbox.report(stats, total)
    inbox.report(stats, total)  # twice: nothing counted twice
    assert stats == SubscriptionStats(received=3, dropped=1, oversized=0, gated=1)
    assert (total.received, total.dropped) == (13, 1)
    inbox.clear()
    assert len(inbox) == 0 and inbox.received == 3
