"""The user's side of ``relay``: :class:`RelayReceiver` and :class:`TopicStream` (see the
service's overview in :mod:`telebot.services.relay`).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import math
import secrets
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING

from telebot.channels.channel import ReceivedDatagram
from telebot.channels.transports.base import Lane
from telebot.errors import ProtocolError, TelebotError
from telebot.services.relay.wire import (
    RELAY,
    RELAY_DATA,
    ListRequest,
    RelayedMessage,
    RelayEnded,
    RelayRefusal,
    Started,
    Stopped,
    StopRequest,
    TopicInfo,
    TopicList,
    decode_relay_message,
    relay_reassembler,
    stream_of,
)
from telebot.services.video.wire import CODEC_CDR, Reassembler, parse_fragment

if TYPE_CHECKING:
    from telebot.channels.call import Call

__all__ = ["RelayReceiver", "TopicStream"]

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- the user's side

#: Messages a :class:`TopicStream` holds for a slow reader (the oldest is dropped beyond).
STREAM_QUEUE = 64
#: How often an unanswered relay request is sent again (s).
RELAY_RESEND = 0.3
#: Data for a stream this side does not know is answered with a stop at most this often (s).
STRAY_STOP_EVERY = 1.0


class TopicStream:
    """One relayed topic on the user's side: ``async for message in stream`` yields
    :class:`~telebot.services.relay.wire.RelayedMessage` until the relay or its call ends.

    Made by :meth:`RobotClient.relay <telebot.services.client.RobotClient.relay>`.
    """

    def __init__(self, info: TopicInfo, stream: int, call: Call, *, latest_only: bool) -> None:
        #: The topic: name, type, schema, encoding.
        self.info = info
        #: The robot's number of this relay.
        self.stream = stream
        self.call = call
        self._queue: deque[RelayedMessage] = deque(maxlen=1 if latest_only else STREAM_QUEUE)
        self._changed = asyncio.Event()
        self._ended = False
        #: Why the relay ended ("" while it runs).
        self.end_reason = ""
        #: Messages received, and dropped here because the reader was slow.
        self.received = 0
        self.dropped = 0
        #: Messages lost on the way (fragments missing), as the reassembler counts them.
        self.incomplete = 0

    @property
    def ended(self) -> bool:
        """Whether no more messages will come."""
        return self._ended

    def deliver(self, message: RelayedMessage) -> None:
        """Queue one message for the reader (on the loop)."""
        if self._ended:
            return
        if len(self._queue) == self._queue.maxlen:
            self.dropped += 1
        self._queue.append(message)
        self.received += 1
        self._changed.set()

    def end(self, why: str) -> None:
        """No more messages: the reader's iteration ends once the queue is empty."""
        if not self._ended:
            self._ended = True
            self.end_reason = why
            self._changed.set()

    def __aiter__(self) -> TopicStream:
        return self

    async def __anext__(self) -> RelayedMessage:
        while not self._queue:
            if self._ended:
                raise StopAsyncIteration
            self._changed.clear()
            await self._changed.wait()
        return self._queue.popleft()


class RelayReceiver:
    """The user's ``relay`` service on one call: answers to requests go to waiters,
    data is reassembled per stream and delivered to its :class:`TopicStream`."""

    def __init__(self, call: Call) -> None:
        self.call = call
        self.control = call.channel(RELAY, lane=Lane.DATA)
        self.data = call.channel(RELAY_DATA, lane=Lane.BULK)
        self.control.set_callback(self._on_control)
        self.data.set_callback(self._on_data)
        self._loop = asyncio.get_running_loop()
        self.waiters: dict[int, asyncio.Queue[object]] = {}
        #: Start requests in flight: id -> latest_only (the stream is made as the answer
        #: comes, before any of its data can be taken for a stray stream's).
        self.pending_starts: dict[int, bool] = {}
        self.streams: dict[int, TopicStream] = {}
        self._reassemblers: dict[int, Reassembler] = {}
        self._stray_stops: dict[int, float] = {}
        self._ids = itertools.count(secrets.randbelow(2**31))
        #: Datagrams that did not decode (dropped).
        self.rejected = 0
        # Streams end with their call, whether or not the client closes its services.
        self._watch = asyncio.ensure_future(call.wait_ended())
        self._watch.add_done_callback(lambda _: self._end_streams())

    def tick(self, now: float) -> None:
        """Drop partial messages whose time is up."""
        for reassembler in self._reassemblers.values():
            reassembler.poll(now)

    def close(self) -> None:
        """The call ended: every stream of it ends."""
        self.control.set_callback(None)
        self.data.set_callback(None)
        self._watch.cancel()
        self._end_streams()

    def _end_streams(self) -> None:
        for stream in list(self.streams.values()):
            stream.end("the call ended")
        self.streams.clear()

    def next_id(self) -> int:
        """A fresh request id."""
        return next(self._ids) % 2**32

    def send(self, text: str) -> None:
        """Send a request (CallEnded once the call is over)."""
        self.control.send(text)

    def _on_control(self, datagram: ReceivedDatagram) -> None:
        try:
            message = decode_relay_message(datagram.payload)
        except ProtocolError as exc:
            self.rejected += 1
            self.control.stats.rejected += 1
            log.debug("relay answer dropped: %s", exc)
            return
        if isinstance(message, RelayEnded):
            stream = self.streams.pop(message.stream, None)
            if stream is not None:
                stream.end(message.text or "the robot ended the relay")
            return
        if isinstance(message, TopicList | Started | RelayRefusal | Stopped):
            waiter = self.waiters.get(message.id)
            if waiter is not None:
                latest = self.pending_starts.get(message.id)
                if (
                    isinstance(message, Started)
                    and latest is not None
                    and message.stream not in self.streams
                ):
                    self.streams[message.stream] = TopicStream(
                        message.info, message.stream, self.call, latest_only=latest
                    )
                waiter.put_nowait(message)
            elif isinstance(message, Started) and message.stream not in self.streams:
                # A start whose waiter gave up: end the relay nobody reads.
                self._stop_stray(message.stream)
            return
        self.rejected += 1

    def _on_data(self, datagram: ReceivedDatagram) -> None:
        now = self._loop.time()
        try:
            frag = parse_fragment(datagram.payload, codec=CODEC_CDR)
        except ProtocolError:
            self.rejected += 1
            self.data.stats.rejected += 1
            return
        number = stream_of(frag.camera)
        stream = self.streams.get(number) if number is not None else None
        if stream is None or number is None:
            if number is not None:
                self._stop_stray(number)
            return
        reassembler = self._reassemblers.get(number)
        if reassembler is None:
            reassembler = self._reassemblers[number] = relay_reassembler()
        reassembler.poll(now)
        complete = reassembler.on_fragment(frag, now)
        stream.incomplete = reassembler.stats.incomplete
        if complete is not None:
            stream.deliver(
                RelayedMessage(
                    stream.info.name, stream.info.type, complete.data, complete.capture_time
                )
            )

    def _stop_stray(self, number: int) -> None:
        now = self._loop.time()
        if now - self._stray_stops.get(number, -math.inf) < STRAY_STOP_EVERY:
            return
        self._stray_stops[number] = now
        with contextlib.suppress(TelebotError):
            self.send(StopRequest(self.next_id(), number).encode())

    def forget(self, stream: TopicStream) -> None:
        """The reader is done with ``stream``: deliver nothing more to it."""
        self.streams.pop(stream.stream, None)
        self._reassemblers.pop(stream.stream, None)
        stream.end("closed")

    async def request(self, text_of: Callable[[int], str], timeout: float) -> object:
        """Send a request (again every :data:`RELAY_RESEND` s) until its first answer."""
        request_id = self.next_id()
        text = text_of(request_id)
        queue: asyncio.Queue[object] = asyncio.Queue()
        self.waiters[request_id] = queue
        try:
            async with asyncio.timeout(timeout):
                while True:
                    self.send(text)
                    try:
                        async with asyncio.timeout(RELAY_RESEND):
                            return await queue.get()
                    except TimeoutError:
                        continue
        finally:
            self.waiters.pop(request_id, None)

    async def topics(self, timeout: float) -> list[TopicInfo]:
        """The robot's relayable topics (every part of the answer)."""
        request_id = self.next_id()
        text = ListRequest(request_id).encode()
        queue: asyncio.Queue[object] = asyncio.Queue()
        self.waiters[request_id] = queue
        parts: dict[int, tuple[TopicInfo, ...]] = {}
        try:
            async with asyncio.timeout(timeout):
                while True:
                    self.send(text)
                    try:
                        async with asyncio.timeout(RELAY_RESEND):
                            while True:
                                answer = await queue.get()
                                if not isinstance(answer, TopicList):
                                    continue
                                parts[answer.part] = answer.topics
                                if len(parts) == answer.parts:
                                    return [t for i in sorted(parts) for t in parts[i]]
                    except TimeoutError:
                        parts.clear()  # ask again for all of it
        finally:
            self.waiters.pop(request_id, None)
