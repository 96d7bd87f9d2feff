"""The robot's side of ``relay``: :class:`RelayService` (see the service's overview in
:mod:`telebot.services.relay`).
"""

from __future__ import annotations

import asyncio
import contextlib
import difflib
import logging
import math
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from typing import TYPE_CHECKING

from telebot.channels.channel import ReceivedDatagram
from telebot.channels.transports.base import Lane
from telebot.config import RelaySettings
from telebot.errors import CallEnded, ProtocolError, TelebotError
from telebot.reasons import Reason
from telebot.robot.nav import SourceTopic, TopicSource, TopicSubscription
from telebot.safety import Audit, AuditRecord
from telebot.services.base import RobotHost
from telebot.services.relay.wire import (
    MAX_DATA,
    RELAY,
    RELAY_DATA,
    ListRequest,
    RelayEnded,
    RelayRefusal,
    Started,
    StartRequest,
    Stopped,
    StopRequest,
    TopicInfo,
    allowed_topic,
    decode_relay_message,
    encode_topic_list,
    fragment_message,
)

if TYPE_CHECKING:
    from telebot.channels.call import Call

__all__ = ["MAX_BACKLOG", "QUEUE", "RelayService", "near_topics"]

log = logging.getLogger(__name__)

#: Messages a relay holds while they are not due yet (without *latest only*).
QUEUE = 16
#: A message whose fragments would wait longer than this (s) for the byte budget is dropped.
MAX_BACKLOG = 1.0
#: The byte budget may be spent ahead by this long (s): a small burst goes at once.
BURST = 0.05
#: Request answers remembered per call (a repeated request gets the same answer).
REMEMBERED = 64
#: How often (s) a call with relays checks that their topics are still there.
TOPIC_CHECK_EVERY = 1.0


def near_topics(name: str, names: list[str], limit: int = 5) -> list[str]:
    """Topic names close to ``name``: similar spellings first, then names containing it."""
    near = difflib.get_close_matches(name, names, n=limit, cutoff=0.5)
    stem = name.strip("/").lower()
    for other in names:
        if len(near) >= limit:
            break
        if stem and stem in other.lower() and other not in near:
            near.append(other)
    return near


class _Relay:
    """One relay of one topic on one call."""

    def __init__(
        self,
        stream: int,
        info: TopicInfo,
        period: float,
        latest_only: bool,
        wake: Callable[[], None],
    ) -> None:
        self.stream = stream
        self.info = info
        self.period = period
        self.latest_only = latest_only
        self._wake = wake
        self._lock = threading.Lock()
        self._queue: deque[tuple[bytes, float]] = deque(maxlen=1 if latest_only else QUEUE)
        self.subscription: TopicSubscription | None = None
        self.next_due = -math.inf
        self.message_id = 0
        self.sent = 0
        self._dropped = 0
        self.closed = False

    @property
    def dropped(self) -> int:
        """Messages not sent: over the queue, the rate or the byte budget."""
        with self._lock:
            return self._dropped

    def drop(self) -> None:
        """Count one more message dropped."""
        with self._lock:
            self._dropped += 1

    def offer(self, data: bytes, stamp: float) -> None:
        """From the source's thread: queue the message (dropping the oldest) and wake."""
        if self.closed:
            return
        with self._lock:
            if len(self._queue) == self._queue.maxlen:
                self._dropped += 1
            self._queue.append((data, stamp))
        self._wake()

    def take(self) -> tuple[bytes, float] | None:
        """The next message to send, if any."""
        with self._lock:
            return self._queue.popleft() if self._queue else None

    def pending(self) -> bool:
        """Whether messages wait."""
        with self._lock:
            return bool(self._queue)


class RelayService:
    """The robot's ``relay`` service on one call (see the module docstring)."""

    def __init__(self, server: RobotHost, call: Call) -> None:
        self.call = call
        self.server = server
        self.settings = server.config.get("relay", RelaySettings)
        nav = server.nav
        self.source: TopicSource | None = nav if isinstance(nav, TopicSource) else None
        self.control = call.channel(RELAY, lane=Lane.DATA)
        self.data = call.channel(RELAY_DATA, lane=Lane.BULK)
        self.control.set_callback(self._on_datagram)
        self.data.set_callback(self._on_data)
        self._loop = asyncio.get_running_loop()
        self.relays: dict[int, _Relay] = {}
        self._next_stream = 1
        self._answers: OrderedDict[int, str] = OrderedDict()
        self._small: deque[bytes] = deque()
        self._large: deque[bytes] = deque()
        self._large_bytes = 0
        self._tokens = 0.0
        self._refilled = self._loop.time()
        self._seq = 0
        self._wake_pending = False
        self._wake_lock = threading.Lock()
        self._timer: asyncio.TimerHandle | None = None
        self._closed = False
        self._next_topic_check = -math.inf
        #: Datagrams from the user that did not decode (dropped).
        self.rejected = 0

    # -- the service seam

    def tick(self, now: float) -> None:
        """Send what is due (a safety net: arrivals and timers normally do it), and end
        the relays whose topic is gone (every :data:`TOPIC_CHECK_EVERY` seconds)."""
        self._pump()
        if self.relays and now >= self._next_topic_check:
            self._next_topic_check = now + TOPIC_CHECK_EVERY
            self._end_vanished()

    def _end_vanished(self) -> None:
        """End each relay whose topic the robot no longer has: its user's stream ends."""
        if self.source is None:
            return
        try:
            names = {t.name for t in self.source.topics()}
        except Exception:  # a listing that failed says nothing about the topics
            log.exception("the robot's topics cannot be listed")
            return
        for stream, relay in list(self.relays.items()):
            if relay.info.name not in names:
                self.end_stream(stream, f"{relay.info.name} is gone: the topic's source closed")

    def close(self) -> None:
        """End every relay of the call."""
        self._closed = True
        self.control.set_callback(None)
        self.data.set_callback(None)
        if self._timer is not None:
            self._timer.cancel()
        for relay in list(self.relays.values()):
            self._end(relay)
        self.relays.clear()
        self._small.clear()
        self._large.clear()

    # -- requests

    def _on_data(self, datagram: ReceivedDatagram) -> None:
        self.rejected += 1
        self.data.stats.rejected += 1

    def _on_datagram(self, datagram: ReceivedDatagram) -> None:
        try:
            message = decode_relay_message(datagram.payload)
        except ProtocolError as exc:
            self.rejected += 1
            self.control.stats.rejected += 1
            log.debug("call %s: relay request dropped: %s", self.call.id, exc)
            return
        if isinstance(message, ListRequest):
            for part in encode_topic_list(message.id, self._topic_infos()):
                self._send(part)
        elif isinstance(message, StartRequest | StopRequest):
            answer = self._answers.get(message.id)
            if answer is None:
                answer = (
                    self._start(message)
                    if isinstance(message, StartRequest)
                    else self._stop(message)
                )
                self._answers[message.id] = answer
                while len(self._answers) > REMEMBERED:
                    self._answers.popitem(last=False)
            self._send(answer)
        else:
            self.rejected += 1
            self.control.stats.rejected += 1

    def _topics(self) -> list[SourceTopic]:
        if self.source is None:
            return []
        try:
            return self.source.topics()
        except Exception:
            log.exception("the robot's topics cannot be listed")
            return []

    def _topic_infos(self) -> list[TopicInfo]:
        role = self.call.role
        return [
            TopicInfo(t.name, t.type, t.schema)
            for t in sorted(self._topics(), key=lambda t: t.name)
            if allowed_topic(self.settings, role, t.name)
        ]

    def _start(self, request: StartRequest) -> str:
        topics = {t.name: t for t in self._topics()}
        name = request.topic if request.topic.startswith("/") else "/" + request.topic
        topic = topics.get(name)
        role = self.call.role
        if topic is None:
            near = near_topics(name, sorted(topics))
            hint = f"; did you mean {', '.join(near)}?" if near else ""
            text = f"no topic {request.topic!r} to relay{hint}"
            return RelayRefusal(request.id, Reason.UNKNOWN_TOPIC, text, tuple(near)).encode()
        if not allowed_topic(self.settings, role, name):
            text = f"{role or 'this caller'}s may not relay {name} (the robot's [relay] config)"
            self._audit(f"relay {name}", "refused", text)
            return RelayRefusal(request.id, Reason.TOPIC_NOT_ALLOWED, text).encode()
        if len(self.relays) >= self.settings.max_relays:
            text = f"this call already has {len(self.relays)} relays (the robot allows that many)"
            return RelayRefusal(request.id, Reason.TOO_MANY_RELAYS, text).encode()
        assert self.source is not None  # a topic was found
        rate = min(request.rate or self.settings.max_rate, self.settings.max_rate)
        stream = self._next_stream
        self._next_stream = self._next_stream % (2**31 - 1) + 1
        info = TopicInfo(topic.name, topic.type, topic.schema)
        relay = _Relay(stream, info, 1.0 / rate, request.latest_only, self._wake)
        try:
            relay.subscription = self.source.subscribe_topic(name, relay.offer)
        except Exception as exc:
            log.warning("call %s: relay of %s failed: %s", self.call.id, name, exc)
            return RelayRefusal(request.id, Reason.FAILED, f"cannot relay {name}: {exc}").encode()
        self.relays[stream] = relay
        self._audit(f"relay {name}", "allowed", f"stream {stream}")
        log.info("call %s: relaying %s as stream %d at ≤ %g/s", self.call.id, name, stream, rate)
        return Started(request.id, stream, info).encode()

    def _stop(self, request: StopRequest) -> str:
        relay = self.relays.pop(request.stream, None)
        if relay is None:
            return Stopped(request.id, request.stream).encode()
        self._end(relay)
        return Stopped(request.id, relay.stream, relay.sent, relay.dropped).encode()

    def _end(self, relay: _Relay) -> None:
        relay.closed = True
        if relay.subscription is not None:
            with contextlib.suppress(Exception):
                relay.subscription.close()

    def _audit(self, what: str, outcome: str, detail: str) -> None:
        safety = self.server.safety
        if safety is None:
            return
        role = self.call.role
        record = AuditRecord(
            time.time(),
            self.call.peer,
            role.value if role is not None else "",
            self.call.id,
            what,
            "refused" if outcome == "refused" else "allowed",
            detail,
        )
        try:
            safety.apply([Audit(record)])
        except Exception:
            log.exception("relay audit record not written")

    # -- sending

    def _wake(self) -> None:
        """From any thread: run :meth:`_pump` on the loop soon (once, however many wake)."""
        with self._wake_lock:
            if self._wake_pending:
                return
            self._wake_pending = True
        with contextlib.suppress(RuntimeError):  # the loop is closing
            self._loop.call_soon_threadsafe(self._woken)

    def _woken(self) -> None:
        with self._wake_lock:
            self._wake_pending = False
        self._pump()

    def _pump(self) -> None:
        if self._closed:
            return
        now = self._loop.time()
        budget = self.settings.max_bytes_per_second
        self._tokens = min(self._tokens + (now - self._refilled) * budget, budget * BURST)
        self._refilled = now
        next_at = math.inf
        for relay in list(self.relays.values()):
            while relay.pending():
                if now < relay.next_due:
                    if relay.latest_only:  # the newest waits for its turn
                        next_at = min(next_at, relay.next_due)
                    else:  # over the rate: dropped (messages are looked at as they come)
                        while relay.take() is not None:
                            relay.drop()
                    break
                item = relay.take()
                if item is None:
                    break
                self._queue_message(relay, *item)
                relay.next_due = max(relay.next_due + relay.period, now - relay.period)
                if relay.next_due <= now:
                    relay.next_due = now + relay.period
        self._flush(budget)
        if self._large:
            next_at = min(next_at, now + max(-self._tokens, 0.0) / budget + 0.001)
        self._schedule(next_at, now)

    def _queue_message(self, relay: _Relay, data: bytes, stamp: float) -> None:
        budget = self.settings.max_bytes_per_second
        if not data or len(data) > MAX_DATA or self._large_bytes + len(data) > budget * MAX_BACKLOG:
            relay.drop()
            return
        relay.message_id += 1
        hold = min(max(3.0 * len(data) / budget, relay.period, 0.2), 1.0)
        try:
            fragments = fragment_message(
                relay.stream, relay.message_id, stamp, data, seq=self._seq, interval=hold
            )
        except ValueError:
            relay.drop()
            return
        self._seq = (self._seq + len(fragments)) % 2**32
        relay.sent += 1
        if len(fragments) == 1:
            self._small.append(fragments[0])
        else:
            self._large.extend(fragments)
            self._large_bytes += sum(len(f) for f in fragments)

    def _flush(self, budget: float) -> None:
        # Small messages first and at once (they may overdraw the budget: large ones wait).
        while self._small:
            datagram = self._small.popleft()
            self._tokens -= len(datagram)
            if not self._send_data(datagram):
                return
        while self._large and self._tokens > 0:
            datagram = self._large.popleft()
            self._large_bytes -= len(datagram)
            self._tokens -= len(datagram)
            if not self._send_data(datagram):
                return

    def _schedule(self, at: float, now: float) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if at < math.inf:
            self._timer = self._loop.call_later(max(at - now, 0.0), self._pump)

    def _send_data(self, datagram: bytes) -> bool:
        try:
            self.data.send(datagram)
        except CallEnded:
            self._small.clear()
            self._large.clear()
            return False
        except TelebotError as exc:
            log.debug("call %s: relay datagram not sent: %s", self.call.id, exc)
        return True

    def _send(self, text: str) -> None:
        if not self.call.active:
            return
        try:
            self.control.send(text)
        except TelebotError as exc:
            log.debug("call %s: relay answer not sent: %s", self.call.id, exc)

    def end_stream(self, stream: int, why: str) -> None:
        """End relay ``stream`` from the robot's side (its source is gone) and tell the user."""
        relay = self.relays.pop(stream, None)
        if relay is not None:
            self._end(relay)
            self._send(RelayEnded(stream, why).encode())
