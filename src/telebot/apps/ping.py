"""Ping a robot through a call: round-trip times and loss of real datagrams.

Needs a robot that echoes (``telebot-robot echo``). Each datagram carries its sequence
number and send time, so late, lost and reordered replies are all told apart.
"""

from __future__ import annotations

import asyncio
import contextlib
import statistics
import struct
from dataclasses import dataclass, field

from telebot.channels.call import Call
from telebot.channels.channel import ReceivedDatagram
from telebot.channels.proto.frames import MAX_DATAGRAM

__all__ = ["PingResult", "ping", "throughput"]

_HEADER = struct.Struct(">Id")  # sequence number, send time (loop clock)
PING_CHANNEL = "ping"


@dataclass
class PingResult:
    """What a ping run measured."""

    size: int
    sent: int = 0
    received: int = 0
    rtts: list[float] = field(default_factory=list)
    elapsed: float = 0.0

    @property
    def loss(self) -> float:
        """Share of datagrams with no echo."""
        return 1.0 - self.received / self.sent if self.sent else 0.0

    def percentile(self, q: float) -> float:
        """The ``q``-th percentile round-trip time in seconds (nan with no replies)."""
        if not self.rtts:
            return float("nan")
        ordered = sorted(self.rtts)
        return ordered[min(len(ordered) - 1, int(q / 100 * len(ordered)))]

    def summary(self) -> str:
        """One line for people."""
        if not self.rtts:
            return f"{self.size} B: {self.sent} sent, 0 received (100% loss)"
        return (
            f"{self.size} B: {self.sent} sent, {self.received} received ({self.loss:.1%} loss), "
            f"rtt p50 {self.percentile(50) * 1e3:.2f} ms, p99 {self.percentile(99) * 1e3:.2f} ms, "
            f"mean {statistics.fmean(self.rtts) * 1e3:.2f} ms"
        )


def _payload(seq: int, now: float, size: int) -> bytes:
    head = _HEADER.pack(seq, now)
    return head + bytes(max(0, size - len(head)))


async def ping(
    call: Call, *, count: int = 20, size: int = 64, interval: float = 0.05, wait: float = 1.0
) -> PingResult:
    """Send ``count`` datagrams of ``size`` bytes ``interval`` apart; collect the echoes."""
    if not _HEADER.size <= size <= MAX_DATAGRAM:
        raise ValueError(f"size must be between {_HEADER.size} and {MAX_DATAGRAM} bytes")
    loop = asyncio.get_running_loop()
    result = PingResult(size)
    seen: set[int] = set()
    channel = call.channel(PING_CHANNEL)
    done = asyncio.Event()

    def on_echo(datagram: ReceivedDatagram) -> None:
        if not isinstance(datagram.payload, bytes) or len(datagram.payload) < _HEADER.size:
            return
        seq, sent_at = _HEADER.unpack_from(datagram.payload)
        if seq in seen or seq >= result.sent:
            return
        seen.add(seq)
        result.received += 1
        result.rtts.append(datagram.received_at - sent_at)
        if result.received == count:
            done.set()

    channel.set_callback(on_echo)
    start = loop.time()
    try:
        for seq in range(count):
            result.sent += 1
            channel.send(_payload(seq, loop.time(), size))
            if seq + 1 < count:
                await asyncio.sleep(interval)
        if not done.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(done.wait(), wait)
    finally:
        channel.set_callback(None)
        result.elapsed = loop.time() - start
    return result


async def throughput(
    call: Call, *, size: int, duration: float = 1.0, window: int = 64
) -> tuple[float, float]:
    """Echoed datagrams per second and loss, keeping at most ``window`` in flight."""
    loop = asyncio.get_running_loop()
    channel = call.channel(f"{PING_CHANNEL}/{size}")
    in_flight = asyncio.Semaphore(window)
    received = 0
    sent = 0

    def on_echo(datagram: ReceivedDatagram) -> None:
        nonlocal received
        received += 1
        in_flight.release()

    channel.set_callback(on_echo)
    payload = bytes(size)
    start = loop.time()
    try:
        while loop.time() - start < duration:
            try:
                await asyncio.wait_for(in_flight.acquire(), 0.2)
            except TimeoutError:  # lost datagrams: let the window refill
                for _ in range(window // 4):
                    in_flight.release()
                continue
            channel.send(payload)
            sent += 1
        await asyncio.sleep(0.2)
    finally:
        channel.set_callback(None)
    elapsed = loop.time() - start
    return received / elapsed, (1 - received / sent if sent else 0.0)
