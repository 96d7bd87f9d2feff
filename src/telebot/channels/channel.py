"""Channels: named datagram streams inside a call (Skype's App2App streams)."""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from telebot.channels.proto.frames import encode_datagram, validate_channel_name
from telebot.channels.transports.base import Lane
from telebot.errors import CallEnded, DatagramTooLarge

__all__ = ["Channel", "ChannelStats", "DatagramTap", "ReceivedDatagram"]

log = logging.getLogger(__name__)


@dataclass(slots=True)
class ReceivedDatagram:
    """A datagram as a receiver gets it.

    Not frozen: one is built for every datagram received, and a frozen dataclass takes
    several times longer to build.
    """

    channel: str
    #: The sender's name as this side knows it (a contact's name, or the robot's name).
    sender: str
    payload: str | bytes
    #: Event-loop time at which it was handed to the channel.
    received_at: float


@dataclass(slots=True)
class ChannelStats:
    """Counters of one channel."""

    sent: int = 0
    received: int = 0
    #: Received but discarded: the receiver fell behind (queue full, or latest-only).
    dropped: int = 0
    #: Refused by this channel: a send that was too large or came after the call ended.
    rejected: int = 0


class _CallEnd(Protocol):
    """Why the call ended, as a channel reports it (``telebot.channels.call.CallEnd``: the
    channel does not import the call, which imports it)."""

    @property
    def kind(self) -> str: ...


class _CallLink(Protocol):
    """What a channel needs from its call (kept narrow so the two stay decoupled)."""

    @property
    def end(self) -> _CallEnd | None: ...

    def send_plaintext(self, plaintext: bytes, lane: Lane) -> None: ...

    @property
    def tap(self) -> DatagramTap | None: ...


DatagramCallback = Callable[[ReceivedDatagram], None]
#: Sees every datagram a call's channels send or deliver: (channel name, sent, payload).
#: Runs on the event loop for each datagram, so it must be quick and must not raise.
DatagramTap = Callable[[str, bool, "str | bytes"], None]


class Channel:
    """A named, lossy datagram stream inside a call.

    Send ``str`` or ``bytes`` of at most 32,768 bytes with :meth:`send`. Receive with a
    callback (:meth:`set_callback`) or ``async for datagram in channel``; iteration ends
    when the call ends. A *latest only* channel keeps just the newest undelivered
    datagram, so a receiver that falls behind skips to the present (pose, video).
    """

    def __init__(
        self,
        call: _CallLink,
        name: str,
        *,
        lane: Lane = Lane.DATA,
        latest_only: bool = False,
        queue_size: int = 256,
    ) -> None:
        if queue_size < 1:
            raise ValueError("queue_size must be at least 1")
        self._call = call
        self.name = name
        self._name_bytes = validate_channel_name(name)
        self.lane = lane
        self.latest_only = latest_only
        self._queue: deque[ReceivedDatagram] = deque(maxlen=1 if latest_only else queue_size)
        self._waiter: asyncio.Future[None] | None = None
        self._callback: DatagramCallback | None = None
        self.stats = ChannelStats()

    def __repr__(self) -> str:
        return f"<Channel {self.name!r} lane={self.lane.value} latest_only={self.latest_only}>"

    def send(self, payload: str | bytes) -> None:
        """Send one datagram; raises DatagramTooLarge (before any I/O) or CallEnded."""
        end = self._call.end
        if end is not None:
            self.stats.rejected += 1
            raise CallEnded(f"cannot send on {self.name!r}: the call {end}", end.kind)
        try:
            plaintext = encode_datagram(self._name_bytes, payload)
        except DatagramTooLarge:
            self.stats.rejected += 1
            raise
        self._call.send_plaintext(plaintext, self.lane)
        self.stats.sent += 1
        tap = self._call.tap
        if tap is not None:
            tap(self.name, True, payload)

    def set_callback(self, callback: DatagramCallback | None) -> None:
        """Deliver datagrams to ``callback`` (on the event loop) instead of the queue."""
        self._callback = callback
        while callback is not None and self._queue:
            self._invoke(callback, self._queue.popleft())

    async def receive(self) -> ReceivedDatagram:
        """The next datagram; raises CallEnded once the call ended and nothing is left."""
        while not self._queue:
            end = self._call.end
            if end is not None:
                raise CallEnded(f"channel {self.name!r} closed: the call {end}", end.kind)
            self._waiter = asyncio.get_running_loop().create_future()
            try:
                await self._waiter
            finally:
                self._waiter = None
        return self._queue.popleft()

    def __aiter__(self) -> Channel:
        return self

    async def __anext__(self) -> ReceivedDatagram:
        try:
            return await self.receive()
        except CallEnded:
            raise StopAsyncIteration from None

    # -- used by the call ------------------------------------------------------------

    def _deliver(self, datagram: ReceivedDatagram) -> None:
        self.stats.received += 1
        tap = self._call.tap
        if tap is not None:
            tap(self.name, False, datagram.payload)
        if self._callback is not None:
            self._invoke(self._callback, datagram)
            return
        if len(self._queue) == self._queue.maxlen:
            self.stats.dropped += 1  # deque drops the oldest for us
        self._queue.append(datagram)
        self._wake()

    def _invoke(self, callback: DatagramCallback, datagram: ReceivedDatagram) -> None:
        try:
            callback(datagram)
        except Exception:  # one bad handler must not break the call for everyone else
            log.exception("handler of channel %r failed", self.name)

    def _wake(self) -> None:
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)
