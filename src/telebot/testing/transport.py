"""The transport contract: what every :class:`~telebot.channels.transports.Transport` must do.

A transport (built-in or a plug-in of the ``telebot.transports`` entry-point group) runs
these checks against itself, as httpx ships ``MockTransport`` for its users' tests. Each
check is a coroutine function taking a :data:`PairFactory` (two transports of the kind
under test that reach each other, opened and closed by the factory) and a
:class:`Contract` (what the transport under test promises beyond the minimum); it raises
``AssertionError`` naming what is wrong. With pytest::

    from telebot.testing.transport import CHECKS, Contract

    @pytest.mark.parametrize("check", CHECKS, ids=lambda check: check.__name__)
    async def test_my_transport(check) -> None:
        await check(my_pair, Contract())

What is checked: frames by key and by pattern, in order, copied; ``max_payload``
refusal, counted; the bounded inbox (samples and bytes, drop-oldest, counted, batches of
at most ``batch``); a gate; a callback that raises; presence; close and use-after-close.
A transport gets all of the receive path by keeping each subscription's samples in a
:class:`~telebot.channels.transports.inbox.Inbox`.

The checks wait with the event loop's clock (``asyncio.timeout``), so an in-process
transport may run them on :func:`telebot.testing.clock.run_virtual`.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from contextlib import AbstractAsyncContextManager
from dataclasses import dataclass

from telebot.channels.transports import Sample, Transport
from telebot.channels.transports.base import Publisher, ReceiveLimits
from telebot.errors import TransportError

__all__ = [
    "CHECKS",
    "Check",
    "Contract",
    "PairFactory",
    "Recorder",
    "check_bounded_inbox_drops_oldest_by_bytes",
    "check_bounded_inbox_drops_oldest_by_samples",
    "check_callback_errors_do_not_end_a_subscription",
    "check_close_semantics",
    "check_gate_refuses_before_queueing",
    "check_max_payload_is_refused_and_counted",
    "check_pattern_subscriptions",
    "check_presence",
    "check_send_and_receive",
]

#: Two open transports that reach each other: (receiver, sender), closed on exit.
PairFactory = Callable[[], AbstractAsyncContextManager[tuple[Transport, Transport]]]


@dataclass(frozen=True)
class Contract:
    """What the transport under test promises beyond the minimum.

    ``burst_at_once``: frames published in one loop turn are all queued before the
    receiver's next turn (an in-process transport); then a flood's drops are exact.
    Otherwise (a network) frames may arrive spread over turns or be lost on the way, and
    the checks accept any loss as long as what arrives is in order, ends with the
    newest frame and adds up with the counters. ``timeout``: seconds (loop clock) any
    one wait may take.
    """

    burst_at_once: bool = True
    timeout: float = 10.0


Check = Callable[[PairFactory, Contract], Awaitable[None]]

_WARM_UP = b"\x00warm-up"
_WARMED_UP = b"\x00warmed-up"


class Recorder:
    """A subscription callback recording its batches; waits on the loop's clock."""

    def __init__(self) -> None:
        self.batches: list[list[Sample]] = []
        #: Whether the warm-up's end marker came (see :func:`_warm_up`).
        self.warm = False
        self._changed = asyncio.Event()

    def __call__(self, batch: Sequence[Sample]) -> None:
        self.batches.append([s for s in batch if s.payload not in (_WARM_UP, _WARMED_UP)])
        self.warm = self.warm or any(s.payload == _WARMED_UP for s in batch)
        self._changed.set()

    @property
    def samples(self) -> list[Sample]:
        """Every sample received, warm-ups left out."""
        return [sample for batch in self.batches for sample in batch]

    @property
    def payloads(self) -> list[bytes]:
        """Every payload received, warm-ups left out."""
        return [sample.payload for sample in self.samples]

    async def wait_for(self, condition: Callable[[], bool], timeout: float, what: str) -> None:
        """Wait until ``condition()``; AssertionError naming ``what`` after ``timeout`` s."""
        try:
            async with asyncio.timeout(timeout):
                while not condition():
                    self._changed.clear()
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(0.05):
                            await self._changed.wait()
        except TimeoutError:
            raise AssertionError(f"{what} within {timeout} s") from None


async def _warm_up(publisher: Publisher, recorder: Recorder, contract: Contract) -> None:
    """Publish until the subscription sees frames (declarations may take a while to
    reach the peer), then one end marker: what follows it is the check proper."""
    async with asyncio.timeout(contract.timeout):
        while not recorder.batches:
            publisher.put(_WARM_UP)
            recorder._changed.clear()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(0.05):
                    await recorder._changed.wait()
    publisher.put(_WARMED_UP)
    await recorder.wait_for(lambda: recorder.warm, contract.timeout, "the warm-up did not end")
    recorder.batches.clear()


@contextlib.asynccontextmanager
async def _subscribed(
    pair: PairFactory,
    contract: Contract,
    key: str,
    limits: ReceiveLimits | None = None,
) -> AsyncIterator[tuple[Transport, Transport, Recorder, Publisher]]:
    async with pair() as (receiver, sender):
        recorder = Recorder()
        subscription = receiver.subscribe(key, recorder, limits=limits)
        publisher = sender.publisher(key)
        await _warm_up(publisher, recorder, contract)
        yield receiver, sender, recorder, publisher
        subscription.close()


async def check_send_and_receive(pair: PairFactory, contract: Contract) -> None:
    """Frames arrive in order, on their key, counted on both ends, copied at ``put``."""
    key = "telebot-contract/send"
    async with _subscribed(pair, contract, key) as (receiver, sender, recorder, publisher):
        published, received = sender.stats.published, receiver.stats.received
        buffer = bytearray(b"first")
        publisher.put(bytes(buffer))
        publisher.put(b"second")
        publisher.put(b"")
        await recorder.wait_for(
            lambda: len(recorder.samples) >= 3, contract.timeout, "3 frames did not arrive"
        )
        buffer[:] = b"xxxxx"  # a caller reusing its buffer changes nothing received
        assert recorder.payloads == [b"first", b"second", b""], recorder.payloads
        assert all(sample.key == key for sample in recorder.samples)
        assert all(isinstance(sample.payload, bytes) for sample in recorder.samples)
        assert sender.stats.published - published == 3, sender.stats
        assert receiver.stats.received - received == 3, receiver.stats


async def check_pattern_subscriptions(pair: PairFactory, contract: Contract) -> None:
    """``*`` matches one chunk, ``**`` any; each sample carries its own key."""
    async with pair() as (receiver, sender):
        one, many = Recorder(), Recorder()
        receiver.subscribe("telebot-contract/pattern/*/x", one)
        receiver.subscribe("telebot-contract/pattern/**", many)
        keys = ["telebot-contract/pattern/a/x", "telebot-contract/pattern/a/y"]
        publishers = [sender.publisher(key) for key in keys]
        # Both keys until each has got through once: subscriptions may take time to spread.
        async with asyncio.timeout(contract.timeout):
            while not ({s.key for s in many.samples} >= set(keys) and one.samples):
                for publisher in publishers:
                    publisher.put(b"p")
                await asyncio.sleep(0.05)
        assert {s.key for s in one.samples} == {keys[0]}, one.samples[:3]
        assert {s.key for s in many.samples} == set(keys)


async def check_max_payload_is_refused_and_counted(pair: PairFactory, contract: Contract) -> None:
    """A payload over ``max_payload`` is dropped and counted as oversized; one at it passes."""
    limits = ReceiveLimits(max_payload=1000)
    key = "telebot-contract/payload"
    async with _subscribed(pair, contract, key, limits) as (receiver, _, recorder, publisher):
        oversized = receiver.stats.oversized
        publisher.put(bytes(1001))
        publisher.put(b"a" * 1000)
        await recorder.wait_for(
            lambda: len(recorder.samples) >= 1,
            contract.timeout,
            "the 1000-byte frame did not arrive",
        )
        await recorder.wait_for(
            lambda: receiver.stats.oversized > oversized,
            contract.timeout,
            "the 1001-byte frame was not counted as oversized",
        )
        assert recorder.payloads == [b"a" * 1000]
        assert receiver.stats.oversized - oversized == 1, receiver.stats


async def _flood(
    pair: PairFactory,
    contract: Contract,
    key: str,
    limits: ReceiveLimits,
    count: int,
    size: int,
    kept: int,
) -> None:
    """Publish ``count`` frames of ``size`` bytes in one loop turn into a subscription
    that keeps ``kept`` of them; check what arrives and the counters."""
    async with pair() as (receiver, sender):
        recorder = Recorder()
        subscription = receiver.subscribe(key, recorder, limits=limits)
        publisher = sender.publisher(key)
        await _warm_up(publisher, recorder, contract)
        stats = subscription.stats
        received, dropped, total_dropped = stats.received, stats.dropped, receiver.stats.dropped
        sent = [b"%06d" % i + bytes(size - 6) for i in range(count)]
        for index, payload in enumerate(sent):  # one turn: the receiver's loop takes none
            publisher.put(payload)
            if not contract.burst_at_once and index % 10 == 9:
                # A network's own threads (not this loop) send what was put so far: put
                # faster than they can, it drops frames, the newest among them, before
                # any inbox sees them (a loaded machine's zenoh did).
                time.sleep(0.002)  # noqa: ASYNC251  (the loop must stay blocked)
        await recorder.wait_for(
            lambda: bool(recorder.samples) and recorder.payloads[-1] == sent[-1],
            contract.timeout,
            "the newest frame of the flood did not arrive (an inbox must drop the oldest)",
        )
        got = recorder.payloads
        sizes = [len(batch) for batch in recorder.batches]
        assert max(sizes) <= limits.batch, f"batches larger than {limits.batch}: {sizes}"
        indices = [sent.index(payload) for payload in got]
        assert indices == sorted(set(indices)), "frames arrived out of order or twice"
        new_dropped = stats.dropped - dropped
        assert stats.received - received == len(got) + new_dropped, (
            f"counters do not add up: {len(got)} delivered, {stats}"
        )
        assert receiver.stats.dropped - total_dropped >= new_dropped, receiver.stats
        if contract.burst_at_once:
            assert got == sent[-kept:], f"kept {len(got)} frames, not the newest {kept}"
            assert new_dropped == count - kept, stats
            assert len(recorder.batches) == -(-kept // limits.batch), "batches not full"
        subscription.close()


async def check_bounded_inbox_drops_oldest_by_samples(
    pair: PairFactory, contract: Contract
) -> None:
    """A flood beyond ``max_samples`` keeps the newest, drops and counts the oldest, and
    arrives in batches of at most ``batch``."""
    limits = ReceiveLimits(max_samples=64, batch=16)
    await _flood(pair, contract, "telebot-contract/flood", limits, count=200, size=16, kept=64)


async def check_bounded_inbox_drops_oldest_by_bytes(pair: PairFactory, contract: Contract) -> None:
    """A flood beyond ``max_bytes`` keeps the newest that fit, drops and counts the rest."""
    limits = ReceiveLimits(max_bytes=10_000, batch=8)
    await _flood(pair, contract, "telebot-contract/bytes", limits, count=100, size=1000, kept=10)


async def check_gate_refuses_before_queueing(pair: PairFactory, contract: Contract) -> None:
    """A subscription's gate sees each payload; what it refuses is counted, not delivered."""
    key = "telebot-contract/gate"
    async with pair() as (receiver, sender):
        recorder = Recorder()
        subscription = receiver.subscribe(key, recorder)
        subscription.gate = lambda payload: not payload.startswith(b"bad")
        publisher = sender.publisher(key)
        await _warm_up(publisher, recorder, contract)
        publisher.put(b"bad")
        publisher.put(b"good")
        await recorder.wait_for(
            lambda: len(recorder.samples) >= 1, contract.timeout, "the good frame did not arrive"
        )
        await recorder.wait_for(
            lambda: subscription.stats.gated == 1,
            contract.timeout,
            "the refused frame was not counted in stats.gated",
        )
        assert recorder.payloads == [b"good"], recorder.payloads


async def check_callback_errors_do_not_end_a_subscription(
    pair: PairFactory, contract: Contract
) -> None:
    """A callback that raises gets the next batches all the same."""
    key = "telebot-contract/raises"
    async with pair() as (receiver, sender):
        recorder = Recorder()

        def explosive(batch: Sequence[Sample]) -> None:
            recorder(batch)
            if any(sample.payload == b"boom" for sample in batch):
                raise RuntimeError("a consumer's bug (expected by the transport contract)")

        receiver.subscribe(key, explosive)
        publisher = sender.publisher(key)
        await _warm_up(publisher, recorder, contract)
        publisher.put(b"boom")
        await recorder.wait_for(lambda: b"boom" in recorder.payloads, contract.timeout, "no boom")
        publisher.put(b"after")
        await recorder.wait_for(
            lambda: b"after" in recorder.payloads,
            contract.timeout,
            "a raising callback ended the subscription",
        )


async def check_presence(pair: PairFactory, contract: Contract) -> None:
    """A token is seen alive by a matching watch (history included), then gone."""
    async with pair() as (watcher, owner):
        events: list[tuple[str, bool]] = []
        changed = asyncio.Event()

        def on_presence(key: str, alive: bool) -> None:
            events.append((key, alive))
            changed.set()

        key = "telebot-contract/presence/a"
        token = owner.declare_presence(key)
        watch = watcher.watch_presence("telebot-contract/presence/*", on_presence)
        async with asyncio.timeout(contract.timeout):
            while (key, True) not in events:
                changed.clear()
                await changed.wait()
        token.close()
        async with asyncio.timeout(contract.timeout):
            while (key, False) not in events:
                changed.clear()
                await changed.wait()
        assert events == [(key, True), (key, False)], events
        watch.close()
        token.close()  # idempotent


async def check_close_semantics(pair: PairFactory, contract: Contract) -> None:
    """A closed subscription delivers nothing more (even frames already queued); closing
    twice is fine; a closed transport refuses use with TransportError and cannot reopen."""
    key = "telebot-contract/close"
    async with pair() as (receiver, sender):
        recorder = Recorder()
        subscription = receiver.subscribe(key, recorder)
        publisher = sender.publisher(key)
        await _warm_up(publisher, recorder, contract)
        publisher.put(b"queued")
        subscription.close()
        subscription.close()
        publisher.put(b"later")
        # A frame published after the close reaching a fresh subscription shows that
        # the closed one had its chance to (wrongly) deliver.
        witness = Recorder()
        receiver.subscribe(key, witness)
        async with asyncio.timeout(contract.timeout):
            while b"witness" not in witness.payloads:
                publisher.put(b"witness")
                # Cleared each turn: a frame that is not the witness ("later", which a
                # fresh subscription may see) must not leave the wait below returning at
                # once, a loop that never yields and so never hears the witness.
                witness._changed.clear()
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(0.05):
                        await witness._changed.wait()
        assert recorder.payloads == [], f"a closed subscription delivered {recorder.payloads}"
        await receiver.close()
        await receiver.close()  # idempotent
        for use in (
            lambda: receiver.publisher(key),
            lambda: receiver.subscribe(key, recorder),
            lambda: receiver.declare_presence(key),
            lambda: receiver.watch_presence(key, lambda k, alive: None),
        ):
            try:
                use()
            except TransportError:
                continue
            raise AssertionError("a closed transport did not refuse with TransportError")
        try:
            await receiver.open()
        except TransportError:
            pass
        else:
            raise AssertionError("a closed transport opened again")


#: Every check, in a sensible order.
CHECKS: tuple[Check, ...] = (
    check_send_and_receive,
    check_pattern_subscriptions,
    check_max_payload_is_refused_and_counted,
    check_bounded_inbox_drops_oldest_by_samples,
    check_bounded_inbox_drops_oldest_by_bytes,
    check_gate_refuses_before_queueing,
    check_callback_errors_do_not_end_a_subscription,
    check_presence,
    check_close_semantics,
)
