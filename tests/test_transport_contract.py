"""The transport contract (telebot.testing.transport) on every transport: memory (on the
virtual clock), zenoh (two sessions in this process), and ``loopback``, a transport
written here in one file from the shipped parts (Inbox, the contract) as a plug-in would."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from typing import ClassVar, Self

import pytest

from telebot.channels.transports import Transport
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
    gate_passes,
)
from telebot.channels.transports.inbox import Inbox
from telebot.channels.transports.memory import MemoryHub, MemoryTransport, key_matches
from telebot.config import TransportSettings, ZenohSettings
from telebot.errors import TransportError
from telebot.testing.clock import run_virtual
from telebot.testing.net import free_port
from telebot.testing.transport import CHECKS, Check, Contract

# --------------------------------------------------------------------------- loopback


class _Bus:
    """Every open loopback transport of the process (one event loop)."""

    transports: ClassVar[list[LoopbackTransport]] = []


class _LoopbackPublisher(Publisher):
    def __init__(self, transport: LoopbackTransport, key: str) -> None:
        self._transport, self.key = transport, key

    def put(self, payload: bytes) -> None:
        self._transport._check_open()
        self._transport.stats.published += 1
        for peer in list(_Bus.transports):
            for sub in list(peer._subs):
                sub._offer(Sample(self.key, bytes(payload)))

    def close(self) -> None:
        pass


class _LoopbackSubscription(Subscription):
    def __init__(
        self,
        transport: LoopbackTransport,
        pattern: str,
        callback: SampleBatchCallback,
        limits: ReceiveLimits,
    ) -> None:
        self._transport, self.pattern, self._callback = transport, pattern, callback
        self.inbox: Inbox[Sample] = Inbox(limits, default_samples=1024, default_bytes=1 << 20)
        self.stats = SubscriptionStats()
        self._scheduled = False

    def _offer(self, sample: Sample) -> None:
        if not key_matches(self.pattern, sample.key):
            return
        if self.inbox.admits(len(sample.payload)):
            if self.gate is not None and not gate_passes(self.gate, sample.payload):
                self.inbox.gated += 1
            else:
                self.inbox.push(sample, len(sample.payload))
        if not self._scheduled:
            self._scheduled = True
            asyncio.get_running_loop().call_soon(self._drain)

    def _drain(self) -> None:
        self._scheduled = False
        batch = self.inbox.take()
        if len(self.inbox) and self in self._transport._subs:
            self._scheduled = True
            asyncio.get_running_loop().call_soon(self._drain)
        self.inbox.report(self.stats, self._transport.stats)
        if batch and self in self._transport._subs:
            with contextlib.suppress(Exception):  # a consumer's bug ends nothing
                self._callback(batch)

    def close(self) -> None:
        if self in self._transport._subs:
            self._transport._subs.remove(self)
        self.inbox.clear()


class _LoopbackPresence(Presence):
    def __init__(self, transport: LoopbackTransport, key: str) -> None:
        self._transport, self.key = transport, key

    def close(self) -> None:
        if self in self._transport._tokens:
            self._transport._tokens.remove(self)
            LoopbackTransport._announce(self.key, False)


class _LoopbackWatch(Subscription):
    def __init__(
        self, transport: LoopbackTransport, pattern: str, callback: PresenceCallback
    ) -> None:
        self._transport, self.pattern, self.callback = transport, pattern, callback
        self.stats = SubscriptionStats()

    def close(self) -> None:
        if self in self._transport._watches:
            self._transport._watches.remove(self)


class LoopbackTransport(Transport):
    """Frames to every open loopback transport of the process, itself included."""

    name = "loopback"

    def __init__(self) -> None:
        super().__init__()
        self._state = "new"
        self._subs: list[_LoopbackSubscription] = []
        self._watches: list[_LoopbackWatch] = []
        self._tokens: list[_LoopbackPresence] = []

    @classmethod
    def from_settings(cls, settings: TransportSettings) -> Self:
        return cls()

    async def open(self) -> None:
        if self._state != "new":
            raise TransportError(f"loopback transport is {self._state}")
        self._state = "open"
        _Bus.transports.append(self)

    async def close(self) -> None:
        if self._state == "open":
            _Bus.transports.remove(self)
            for token in list(self._tokens):
                token.close()
        self._state = "closed"
        self._subs.clear()
        self._watches.clear()

    def _check_open(self) -> None:
        if self._state != "open":
            raise TransportError(f"loopback transport is {self._state}")

    def publisher(self, key: str, lane: Lane = Lane.DATA) -> Publisher:
        self._check_open()
        return _LoopbackPublisher(self, key)

    def subscribe(
        self,
        pattern: str,
        callback: SampleBatchCallback,
        *,
        limits: ReceiveLimits | None = None,
    ) -> Subscription:
        self._check_open()
        sub = _LoopbackSubscription(self, pattern, callback, limits or ReceiveLimits())
        self._subs.append(sub)
        return sub

    def declare_presence(self, key: str) -> Presence:
        self._check_open()
        token = _LoopbackPresence(self, key)
        self._tokens.append(token)
        self._announce(key, True)
        return token

    def watch_presence(self, pattern: str, callback: PresenceCallback) -> Subscription:
        self._check_open()
        watch = _LoopbackWatch(self, pattern, callback)
        self._watches.append(watch)
        loop = asyncio.get_running_loop()
        for peer in _Bus.transports:
            for token in peer._tokens:
                if key_matches(pattern, token.key):
                    loop.call_soon(watch.callback, token.key, True)
        return watch

    @staticmethod
    def _announce(key: str, alive: bool) -> None:
        loop = asyncio.get_running_loop()
        for peer in _Bus.transports:
            for watch in peer._watches:
                if key_matches(watch.pattern, key):
                    loop.call_soon(watch.callback, key, alive)


# --------------------------------------------------------------------------- pairs


@contextlib.asynccontextmanager
async def loopback_pair() -> AsyncIterator[tuple[Transport, Transport]]:
    async with LoopbackTransport() as receiver, LoopbackTransport() as sender:
        yield receiver, sender


@contextlib.asynccontextmanager
async def memory_pair() -> AsyncIterator[tuple[Transport, Transport]]:
    hub = MemoryHub(seed=1)
    hub.set_link("sender", "receiver", latency=0.01)  # a link that takes time
    async with (
        MemoryTransport(hub, "receiver") as receiver,
        MemoryTransport(hub, "sender") as sender,
    ):
        yield receiver, sender


@contextlib.asynccontextmanager
async def zenoh_pair() -> AsyncIterator[tuple[Transport, Transport]]:
    from telebot.channels.transports.zenoh import ZenohTransport

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    listen = ZenohSettings(listen=[endpoint], multicast_scouting=False)
    connect = ZenohSettings(connect=[endpoint], multicast_scouting=False)
    async with ZenohTransport(listen) as receiver, ZenohTransport(connect) as sender:
        yield receiver, sender


IDS = {check: check.__name__.removeprefix("check_") for check in CHECKS}


@pytest.mark.parametrize("check", CHECKS, ids=IDS.get)
def test_loopback_passes_the_contract(check: Check) -> None:
    run_virtual(check(loopback_pair, Contract()))


@pytest.mark.parametrize("check", CHECKS, ids=IDS.get)
def test_memory_passes_the_contract_on_the_virtual_clock(check: Check) -> None:
    run_virtual(check(memory_pair, Contract()))


@pytest.mark.parametrize("check", CHECKS, ids=IDS.get)
async def test_zenoh_passes_the_contract(check: Check) -> None:
    await check(zenoh_pair, Contract(burst_at_once=False))


def test_a_transport_without_the_bound_fails_the_contract() -> None:
    """The suite catches a transport whose inbox does not drop the oldest."""

    class Unbounded(LoopbackTransport):
        def subscribe(
            self,
            pattern: str,
            callback: SampleBatchCallback,
            *,
            limits: ReceiveLimits | None = None,
        ) -> Subscription:
            asked = limits or ReceiveLimits()
            unbounded = ReceiveLimits(max_payload=asked.max_payload, batch=asked.batch)
            return super().subscribe(pattern, callback, limits=unbounded)

    @contextlib.asynccontextmanager
    async def pair() -> AsyncIterator[tuple[Transport, Transport]]:
        async with Unbounded() as receiver, Unbounded() as sender:
            yield receiver, sender

    from telebot.testing.transport import check_bounded_inbox_drops_oldest_by_samples

    with pytest.raises(AssertionError, match="not the newest"):
        run_virtual(check_bounded_inbox_drops_oldest_by_samples(pair, Contract()))
