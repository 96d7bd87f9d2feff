"""Calls over a transport: a user calls a robot by name (Skype's call), asyncio side.

The protocol logic is in :mod:`telebot.channels.proto` (sans-IO); this module moves its
frames over a :class:`~telebot.channels.transports.base.Transport` and keeps time.

Key expressions (``ns`` is the namespace, ``telebot`` by default; ``{base}`` is
``{ns}/robot/{robot}`` for a robot and ``{ns}/user/{user}/{instance}`` for a user client;
``{sender}`` is the name of the side that publishes on the key, so that a router's access
control can let each side publish only on keys that name it)::

    {base}/in/{sender}                         handshake frames (HELLO, WELCOME, RETRY)
    {base}/call/{sender}/{call_id}/ctl         one call's CONTROL frames (heartbeats, stop,
                                               chat, goals, safety, hang-up)
    {base}/call/{sender}/{call_id}/data        one call's DATA and BULK frames
    {ns}/presence/robot/{robot}/{public_key}   presence token of a robot
    {ns}/presence/user/{user}/{instance}       presence token of a user client

A robot also listens on ``{base}/in``, the handshake key of protocol version 1, only to
answer an older client's HELLO with a refusal that names the version it must upgrade to.

Every key has its own subscription with its own bounded queue (:data:`HANDSHAKE_LIMITS`,
:data:`CONTROL_LIMITS`, :data:`DATA_LIMITS`): a flood of data can only drop that call's
own data, never its heartbeats or a stop, never another call's frames, and a stranger
flooding a robot's handshake key delays no call. The queues are bounded in bytes too, and
a payload larger than any frame is dropped before it is copied.

A call ends when either side hangs up, or drops when the peer's presence token
disappears or nothing authentic arrived from it for ``CallSettings.timeout``.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import time
from asyncio import FIRST_COMPLETED
from collections import Counter
from collections.abc import AsyncIterator, Callable, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Literal, Self

from telebot.channels.channel import Channel, DatagramTap, ReceivedDatagram
from telebot.channels.proto.answering import Accept, Answering, Ignore, Reply
from telebot.channels.proto.frames import (
    INSTANCE_LEN,
    LEGACY_VERSION,
    MAX_FRAME,
    VERSION,
    Bundle,
    Coalescer,
    DataFrame,
    Datagram,
    Hangup,
    Hello,
    Retry,
    Welcome,
    decode_frame,
    encode_hangup,
    validate_name,
)
from telebot.channels.proto.noise import InitiatorHandshake, Suite
from telebot.channels.proto.session import (
    CallSession,
    CallStats,
    describe_suites,
    finish_call,
    start_call,
)
from telebot.channels.suites import suite_preference
from telebot.channels.transports.base import (
    CONTROL_KEY_SUFFIX,
    DATA_KEY_SUFFIX,
    Lane,
    Presence,
    Publisher,
    ReceiveLimits,
    Sample,
    Subscription,
    Transport,
)
from telebot.config import CallSettings
from telebot.errors import (
    CallError,
    CallRejected,
    CallTimeout,
    IncompatiblePeer,
    ProtocolError,
    TelebotError,
)
from telebot.identity import ContactBook, Identity, KnownRobots, Role, decode_key, encode_key

__all__ = [
    "DEFAULT_NAMESPACE",
    "Call",
    "CallEnd",
    "EndpointStats",
    "RobotEndpoint",
    "RobotPresence",
    "UserEndpoint",
]

log = logging.getLogger(__name__)

DEFAULT_NAMESPACE = "telebot"
#: How often a caller repeats its HELLO while waiting (a lossy link may eat it).
HELLO_RETRY_INTERVAL = 0.25
#: How many times a HANGUP is sent (it is not acknowledged; the peer's timeout is the backstop).
HANGUP_REPEATS = 3
#: How long after its last hang-up a closing endpoint withdraws its presence. zenoh
#: sends the withdrawal at its control priority, above every lane, so without the pause
#: it can overtake the hang-up and the peer sees a drop instead.
HANGUP_GRACE = 0.05
_TIMER_SLACK = 0.001  # fire just after a deadline, never just before it
#: The handshake key: small frames only (a HELLO is under 2.5 KB), a short queue.
HANDSHAKE_LIMITS = ReceiveLimits(max_samples=256, max_bytes=1 << 20, max_payload=4096, batch=64)
#: A call's CONTROL key: its own queue, so data never pushes a heartbeat or a stop out.
CONTROL_LIMITS = ReceiveLimits(max_samples=512, max_bytes=4 << 20, max_payload=MAX_FRAME, batch=64)
#: A call's DATA key: the transport's queue bounds (count and bytes); frames beyond them
#: are this call's own loss (counted in :attr:`Call.receive_dropped`).
DATA_LIMITS = ReceiveLimits(max_payload=MAX_FRAME, batch=32)
#: Frames kept for a call being set up that arrive before its WELCOME is handled.
_EARLY_FRAMES = 64


@dataclass(frozen=True, slots=True)
class CallEnd:
    """Why a call ended. ``kind`` is "hung_up" or "dropped"; ``by_peer`` who ended it."""

    kind: Literal["hung_up", "dropped"]
    by_peer: bool
    detail: str

    def __str__(self) -> str:
        if self.kind == "hung_up":
            who = "by the peer" if self.by_peer else "here"
            return f"was hung up {who}: {self.detail}"
        return f"dropped: {self.detail}"


class Call:
    """An established, authenticated call with one peer; open channels with :meth:`channel`."""

    #: On a robot: the caller's instance (16 hex digits, from the authenticated HELLO): the
    #: user's client process, the same for all its calls ("" on a user's side).
    peer_instance: str = ""

    def __init__(
        self,
        endpoint: _Endpoint,
        session: CallSession,
        *,
        peer: str,
        role: Role | None,
        peer_base: str,
        peer_presence: str,
        inbox: _CallInbox,
    ) -> None:
        self._endpoint = endpoint
        self._session = session
        #: The other side's name: a contact's name on a robot, the robot's name on a user.
        self.peer = peer
        #: The role of the user in this call (the contact's role, as the robot granted it).
        self.role = role
        call_keys = f"{peer_base}/call/{endpoint.identity.name}/{session.call_id.hex()}"
        self._peer_keys = {
            Lane.CONTROL: call_keys + CONTROL_KEY_SUFFIX,
            Lane.DATA: call_keys + DATA_KEY_SUFFIX,
            Lane.BULK: call_keys + DATA_KEY_SUFFIX,
        }
        self._publishers: dict[Lane, Publisher] = {}
        # DATA and BULK datagrams sent after the first of a loop turn wait here until
        # the end of that turn, then go out together (one BUNDLE: one seal, one publish).
        self._outboxes: dict[Lane, Coalescer] = {Lane.DATA: Coalescer(), Lane.BULK: Coalescer()}
        self._flush_handle: asyncio.Handle | None = None
        self._channels: dict[str, Channel] = {}
        self._loop = asyncio.get_running_loop()
        self._timer: asyncio.TimerHandle | None = None
        self._ended: asyncio.Future[CallEnd] = self._loop.create_future()
        self.end: CallEnd | None = None
        #: Called with the name of a channel that received a datagram but is not open
        #: here; it may open it with :meth:`channel`, otherwise the datagram is dropped.
        self.on_unopened_channel: Callable[[str], None] | None = None
        #: Datagrams for channels not open here (and not opened by the hook above).
        self.unrouted = 0
        #: Sees every datagram the channels send and deliver (the robot's call recorder);
        #: None (no cost but a check) unless something records the call.
        self.tap: DatagramTap | None = None
        self._presence_watch = endpoint.transport.watch_presence(
            peer_presence, self._on_peer_presence
        )
        self._inbox = inbox
        self._schedule()

    def __repr__(self) -> str:
        state = "active" if self.end is None else str(self.end)
        return f"<Call {self.id} with {self.peer!r} {state}>"

    @property
    def id(self) -> str:
        """The call id, as hex."""
        return self._session.call_id.hex()

    @property
    def stats(self) -> CallStats:
        """Frame counters, rejections by reason, round-trip time and loss."""
        return self._session.stats

    @property
    def suite(self) -> Suite:
        """The cipher suite the two ends agreed for this call."""
        return self._session.suite

    @property
    def receive_dropped(self) -> int:
        """Frames from the peer dropped on this side before they were read: over this
        call's receive queue (the peer sends faster than it is served) or larger than
        any frame."""
        return self._inbox.dropped

    @property
    def last_heard(self) -> float:
        """Event-loop time of the peer's last authentic frame (a plain float: any thread may read it)."""
        return self._session.last_heard

    @property
    def active(self) -> bool:
        """True until the call is hung up or dropped."""
        return self.end is None

    def channel(
        self,
        name: str,
        *,
        lane: Lane = Lane.DATA,
        latest_only: bool = False,
        queue_size: int = 256,
    ) -> Channel:
        """The channel called ``name``, opened now if it is not open yet.

        ``lane`` sets the QoS of what this side sends (CONTROL for stop, BULK for
        video); ``latest_only`` keeps only the newest undelivered datagram.
        """
        existing = self._channels.get(name)
        if existing is not None:
            if existing.lane != lane or existing.latest_only != latest_only:
                raise ValueError(f"channel {name!r} is already open with other options")
            return existing
        channel = Channel(self, name, lane=lane, latest_only=latest_only, queue_size=queue_size)
        self._channels[name] = channel
        return channel

    @property
    def channels(self) -> dict[str, Channel]:
        """The open channels by name."""
        return dict(self._channels)

    async def hangup(self, reason: str = "hung up") -> None:
        """End the call and tell the peer why; idempotent."""
        self.hangup_now(reason)
        await asyncio.sleep(0)  # let the transport flush before a caller closes it

    def hangup_now(self, reason: str = "hung up") -> None:
        """:meth:`hangup` for code that cannot await (signal handlers, callbacks)."""
        if self.end is not None:
            return
        try:
            self._flush()  # what was sent before the hang-up goes out before it
            frame = self._session.seal(encode_hangup(reason))
            for _ in range(HANGUP_REPEATS):
                self._put(frame, Lane.CONTROL)
        except TelebotError as exc:  # the peer's own timeout will notice instead
            log.warning("call %s: hang-up not sent: %s", self.id, exc)
        finally:  # ended here whatever happened on the way out
            self._endpoint._last_hangup = self._loop.time()
            self._finish(CallEnd("hung_up", by_peer=False, detail=reason))

    async def wait_ended(self) -> CallEnd:
        """Wait until the call ends; returns why."""
        return await asyncio.shield(self._ended)

    # -- plumbing used by channels and the endpoint -------------------------------

    def send_plaintext(self, plaintext: bytes, lane: Lane) -> None:
        """Seal the DATAGRAM ``plaintext`` into a DATA frame and publish it on ``lane``.

        CONTROL datagrams (a stop) go out at once, one frame each. So does the first
        DATA or BULK datagram of an event-loop turn; the ones that follow it in the same
        turn are gathered and go out at the end of the turn, all those of one lane in
        one BUNDLE frame. A lone datagram therefore waits for nothing, and a burst of
        small ones costs one seal and one publish instead of one each.
        """
        outbox = self._outboxes.get(lane)
        if outbox is None or self._flush_handle is None:
            self._put(self._session.seal(plaintext), lane)
            if outbox is not None:  # this turn has begun sending: gather what follows
                self._flush_handle = self._loop.call_soon(self._flush)
            return
        full = outbox.add(plaintext)
        if full is not None:
            self._put(self._session.seal(full), lane)

    def _flush(self) -> None:
        """Send what the outboxes gathered (loop callback, and before a hang-up)."""
        if self._flush_handle is not None:
            self._flush_handle.cancel()
            self._flush_handle = None
        for lane, outbox in self._outboxes.items():
            message = outbox.take()  # (an ended call emptied them and cancelled this)
            if message is None:
                continue
            try:
                self._put(self._session.seal(message), lane)
            except TelebotError as exc:  # lossy: the datagrams are lost, as on a bad link
                self._session.stats.send_failures += 1
                log.warning("call %s: datagrams not sent: %s", self.id, exc)

    def _put(self, frame: bytes, lane: Lane) -> None:
        publisher = self._publishers.get(lane)
        if publisher is None:
            publisher = self._endpoint.transport.publisher(self._peer_keys[lane], lane)
            self._publishers[lane] = publisher
        publisher.put(frame)

    def _on_frame(self, frame: DataFrame) -> None:
        now = self._loop.time()
        message = self._session.open(frame, now)  # raises on forged / replayed / malformed
        # type() checks rather than match: this runs for every frame of a flood.
        if type(message) is Datagram:
            self._route(message, now)
        elif type(message) is Bundle:
            for datagram in message.datagrams:
                if self.end is not None:  # a handler hung up: the rest is for nobody
                    return
                self._route(datagram, now)
        elif type(message) is Hangup:
            self._finish(CallEnd("hung_up", by_peer=True, detail=message.reason or "hung up"))
        # else a heartbeat: the session already took what it needs

    def _route(self, datagram: Datagram, now: float) -> None:
        """Hand ``datagram`` to its channel (opening it through the hook if need be)."""
        name = datagram.channel
        channel = self._channels.get(name)
        if channel is None and self.on_unopened_channel is not None:
            self.on_unopened_channel(name)
            channel = self._channels.get(name)
        if channel is None:
            self.unrouted += 1
            return
        channel._deliver(ReceivedDatagram(name, self.peer, datagram.payload, now))

    def _on_peer_presence(self, key: str, alive: bool) -> None:
        if not alive and self.end is None:
            self._finish(CallEnd("dropped", by_peer=True, detail=f"{self.peer} went offline"))

    def _schedule(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
        when = self._session.next_deadline() + _TIMER_SLACK
        self._timer = self._loop.call_at(when, self._on_timer)

    def _on_timer(self) -> None:
        self._timer = None
        if self.end is not None:
            return
        now = self._loop.time()
        if self._session.timed_out(now):
            silence = now - self._session.last_heard
            self._finish(
                CallEnd(
                    "dropped", by_peer=True, detail=f"nothing from {self.peer} for {silence:.2f} s"
                )
            )
            return
        if self._session.heartbeat_due(now):
            try:
                self._put(self._session.seal_heartbeat(now), Lane.CONTROL)
            except TelebotError as exc:  # a failing transport ends the call by timeout
                log.warning("call %s: heartbeat not sent: %s", self.id, exc)
        self._schedule()

    def _finish(self, end: CallEnd) -> None:
        if self.end is not None:
            return
        self.end = end
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._flush_handle is not None:  # unsent datagrams die with the call
            self._flush_handle.cancel()
            self._flush_handle = None
        for outbox in self._outboxes.values():
            outbox.take()
        self._presence_watch.close()
        self._inbox.close()
        for publisher in self._publishers.values():
            publisher.close()
        self._publishers.clear()
        for channel in self._channels.values():
            channel._wake()
        self._ended.set_result(end)
        self._endpoint._forget(self)
        log.info("call %s with %s %s", self.id, self.peer, end)


class _CallInbox:
    """The two subscriptions of one call on this side (CONTROL and DATA keys).

    Opened before the peer can send on them: by a robot before it answers a HELLO, by a
    user before its first HELLO (its WELCOME and the robot's first frames travel on
    different keys, so a few frames may be read before the WELCOME: they wait here).
    Anything that is not a DATA frame of this call is counted and dropped before any
    cryptography.

    The CONTROL key's subscription has a gate (:meth:`CallSession.authentic`, run on the
    transport's receiving thread): once the call is up, only frames that authenticate
    are queued there, so a flood of forged frames on it (a stranger who sniffed the
    call's keys) costs one failed AEAD each off the event loop, and never pushes a
    heartbeat or a stop out of the queue. They are counted as ``forged``.
    """

    def __init__(self, endpoint: _Endpoint, call_id: bytes, peer: str) -> None:
        self.call_id = call_id
        self._call: Call | None = None
        self._early: list[Sample] = []
        self._early_dropped = 0
        self._closed = False
        self._gated_seen = 0  # forged CONTROL frames already counted in the call's stats
        keys = f"{endpoint.base}/call/{peer}/{call_id.hex()}"
        transport = endpoint.transport
        control = transport.subscribe(
            keys + CONTROL_KEY_SUFFIX, self._on_samples, limits=CONTROL_LIMITS
        )
        control.gate = self._authentic
        self._subscriptions = [control]
        try:
            self._subscriptions.append(
                transport.subscribe(keys + DATA_KEY_SUFFIX, self._on_samples, limits=DATA_LIMITS)
            )
        except BaseException:
            self.close()
            raise

    @property
    def owner(self) -> Call | None:
        """The call this inbox delivers to (None while the call is being set up)."""
        return self._call

    @property
    def dropped(self) -> int:
        """Samples dropped before they were read (queue bounds, oversized payloads, and
        early frames beyond what is kept for a call being set up)."""
        queues = sum(sub.stats.dropped + sub.stats.oversized for sub in self._subscriptions)
        return queues + self._early_dropped

    def _authentic(self, payload: bytes) -> bool:
        """Transport thread: whether a CONTROL frame may be queued (any, while set up)."""
        call = self._call
        return call is None or call._session.authentic(payload)

    def attach(self, call: Call) -> None:
        """Deliver to ``call`` from now on, starting with what arrived early."""
        self._call = call
        early, self._early = self._early, []
        if early:
            self._on_samples(early)

    def _on_samples(self, samples: Sequence[Sample]) -> None:
        call = self._call
        if call is None:
            room = max(0, _EARLY_FRAMES - len(self._early))
            self._early.extend(samples[:room])
            self._early_dropped += max(0, len(samples) - room)
            return
        rejected = call._session.stats.rejected
        gated = self._subscriptions[0].stats.gated
        if gated != self._gated_seen:
            rejected["forged"] += gated - self._gated_seen
            self._gated_seen = gated
        call_id = self.call_id
        for sample in samples:
            if call.end is not None:  # a handler ended the call: the rest is for nobody
                return
            try:
                frame = decode_frame(sample.payload)
            except ProtocolError:
                rejected["malformed"] += 1
                continue
            if type(frame) is not DataFrame or frame.call_id != call_id:
                rejected["not_this_call"] += 1
                continue
            # Not contextlib.suppress: it costs more than the rest of a small frame.
            try:
                call._on_frame(frame)
            except ProtocolError:  # forged, replayed, malformed: counted by the session
                pass
            except Exception:  # a bug must not take the endpoint down with it
                rejected["internal_error"] += 1
                log.exception("call %s: error handling a frame on %s", call.id, sample.key)

    def close(self) -> None:
        """Stop listening; idempotent."""
        if self._closed:
            return
        self._closed = True
        self._early.clear()
        for sub in self._subscriptions:
            sub.close()


@dataclass(slots=True)
class EndpointStats:
    """What an endpoint refused, by reason (frames that never reached a call)."""

    rejected: Counter[str]

    def __init__(self) -> None:
        self.rejected = Counter()


class _Endpoint:
    """What robot and user endpoints share: the inbox, dispatch to calls, presence."""

    def __init__(
        self,
        transport: Transport,
        identity: Identity,
        *,
        settings: CallSettings | None = None,
        namespace: str = DEFAULT_NAMESPACE,
    ) -> None:
        self.transport = transport
        self.identity = identity
        self.settings = settings or CallSettings()
        #: The cipher suites this end accepts, preferred first (from ``settings.cipher``).
        self.suites = suite_preference(self.settings.cipher)
        self.namespace = namespace
        self.stats = EndpointStats()
        self._calls: dict[bytes, Call] = {}
        self._subscription: Subscription | None = None
        self._presence: Presence | None = None
        self._closed = False
        self._last_hangup = -math.inf  # event-loop time of the last HANGUP sent
        self._incompatible_seen: set[str] = set()  # warned about once each

    # Subclasses name their key prefix, handshake inbox and presence keys. The inbox is
    # a prefix: peers publish on ``{inbox}/{their name}``.
    base: str
    inbox: str
    presence_key: str
    #: Whether to listen on the version-1 handshake key ``{inbox}`` too (a robot does,
    #: to tell older clients to upgrade).
    _legacy_inbox = False

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    async def start(self) -> None:
        """Listen on the inbox and announce presence (the transport must be open)."""
        # ``in/**`` also matches ``in`` itself (zenoh's ``**`` is zero or more chunks).
        pattern = f"{self.inbox}/**" if self._legacy_inbox else f"{self.inbox}/*"
        self._subscription = self.transport.subscribe(
            pattern, self._on_samples, limits=HANDSHAKE_LIMITS
        )
        self._presence = self.transport.declare_presence(self.presence_key)

    async def close(self, reason: str = "shutting down") -> None:
        """Hang up every call, withdraw presence and stop listening; idempotent.

        The calls are hung up before the first await, and no call is set up once
        ``close`` is called (a robot refuses it: "<robot> is shutting down").
        Presence is withdrawn :data:`HANGUP_GRACE` after the last hang-up this
        endpoint sent, and is withdrawn even if ``close`` is cancelled meanwhile.
        """
        if self._closed:
            return
        self._closed = True
        try:
            for call in list(self._calls.values()):
                try:
                    call.hangup_now(reason)
                except Exception:  # one call's fault must not leave the others up
                    log.exception("call %s: hang-up failed", call.id)
            # Also after a call hung up just before close (a one-shot client).
            pause = self._last_hangup + HANGUP_GRACE - asyncio.get_running_loop().time()
            if pause > 0:
                await asyncio.sleep(pause)
        finally:
            if self._presence is not None:
                self._presence.close()
            if self._subscription is not None:
                self._subscription.close()

    @property
    def closed(self) -> bool:
        """True once :meth:`close` was called."""
        return self._closed

    @property
    def calls(self) -> list[Call]:
        """The calls that are up now."""
        return list(self._calls.values())

    def _new_call(
        self,
        session: CallSession,
        *,
        peer: str,
        role: Role | None,
        peer_base: str,
        peer_presence: str,
        inbox: _CallInbox,
    ) -> Call:
        try:
            call = Call(
                self,
                session,
                peer=peer,
                role=role,
                peer_base=peer_base,
                peer_presence=peer_presence,
                inbox=inbox,
            )
        except BaseException:
            inbox.close()
            raise
        self._calls[session.call_id] = call
        # Only now: frames that came early (a HANGUP among them) may end the call, and an
        # ended call must be forgotten, not registered after it ended.
        inbox.attach(call)
        return call

    def _forget(self, call: Call) -> None:
        self._calls.pop(bytes.fromhex(call.id), None)

    def _on_samples(self, samples: Sequence[Sample]) -> None:
        """Handshake frames; a call's frames come on its own keys (:class:`_CallInbox`)."""
        prefix = f"{self.inbox}/"
        for sample in samples:
            # The sender's name is the key's last chunk (None: the version-1 key).
            sender = sample.key[len(prefix) :] if sample.key.startswith(prefix) else None
            if sender is not None and "/" in sender:
                self.stats.rejected["not_a_handshake_key"] += 1
                continue
            try:
                self._on_handshake(sample.payload, sender)
            except IncompatiblePeer as exc:
                # A peer of another version: say so once (its HELLO repeats 4 times a
                # second), then count it like any other frame that does not decode.
                self.stats.rejected[type(exc).__name__] += 1
                if str(exc) not in self._incompatible_seen and len(self._incompatible_seen) < 64:
                    self._incompatible_seen.add(str(exc))
                    log.warning("dropped a frame on %s: %s", sample.key, exc)
            except ProtocolError as exc:
                # Garbage, forgeries and replays are counted and dropped, never raised.
                self.stats.rejected[type(exc).__name__] += 1
                log.debug("dropped a frame on %s: %s", sample.key, exc)
            except Exception:  # a bug must not take the endpoint down with it
                self.stats.rejected["internal_error"] += 1
                log.exception("error handling a frame on %s", sample.key)

    def _on_handshake(self, data: bytes, sender: str | None) -> None:
        """A frame from ``sender``'s handshake key (raises ProtocolError if it is garbage)."""
        raise NotImplementedError


# --------------------------------------------------------------------------------------


class RobotEndpoint(_Endpoint):
    """A robot that answers calls from its contacts.

    ``async with RobotEndpoint(transport, identity, contacts) as robot:`` then
    ``async for call in robot.incoming():`` or set :attr:`on_call`.

    How to answer each HELLO (the answer cache, replays, call-id reuse) is decided by
    :class:`~telebot.channels.proto.answering.Answering` (sans-IO); this class moves the
    frames and starts the calls it accepts.
    """

    _legacy_inbox = True

    def __init__(
        self,
        transport: Transport,
        identity: Identity,
        contacts: ContactBook,
        *,
        settings: CallSettings | None = None,
        namespace: str = DEFAULT_NAMESPACE,
    ) -> None:
        settings = settings or CallSettings()
        # Before the base class sets ``suites``: the policy holds them (see the property).
        self._answering = Answering(
            identity.name,
            identity.private_key,
            contacts,
            suites=suite_preference(settings.cipher),
            heartbeat_interval=1.0 / settings.heartbeat_hz,
            timeout=settings.timeout,
        )
        super().__init__(transport, identity, settings=settings, namespace=namespace)
        self.contacts = contacts
        self.base = f"{namespace}/robot/{identity.name}"
        self.inbox = f"{self.base}/in"
        self.presence_key = (
            f"{namespace}/presence/robot/{identity.name}/{encode_key(identity.public_key)}"
        )
        #: Called with each new call (on the loop); if unset, calls queue for :meth:`incoming`.
        self.on_call: Callable[[Call], None] | None = None
        self._incoming: asyncio.Queue[Call] = asyncio.Queue(maxsize=64)

    @property
    def suites(self) -> tuple[Suite, ...]:
        """The cipher suites this robot accepts, preferred first (from ``settings.cipher``)."""
        return self._answering.suites

    @suites.setter
    def suites(self, suites: Sequence[Suite]) -> None:
        self._answering.suites = tuple(suites)

    async def incoming(self) -> AsyncIterator[Call]:
        """Each call as it is answered."""
        while True:
            yield await self._incoming.get()

    async def close(self, reason: str = "shutting down") -> None:
        """:meth:`_Endpoint.close`; a HELLO that comes meanwhile is refused."""
        self._answering.close()
        await super().close(reason)

    def _forget(self, call: Call) -> None:
        super()._forget(call)
        self._answering.ended(bytes.fromhex(call.id))

    def _on_handshake(self, data: bytes, sender: str | None) -> None:
        decision = self._answering.receive(data, sender, asyncio.get_running_loop().time())
        match decision:
            case Ignore(code):
                self.stats.rejected[code] += 1
            case Reply(hello, frame, code, warning):
                if code is not None:
                    self.stats.rejected[code] += 1
                if warning is not None:
                    log.warning("%s", warning)
                self._reply(hello, frame)
            case Accept():
                try:
                    self._start(decision)
                except BaseException:  # no call came of it: its repeats get silence
                    self._answering.ended(decision.hello.call_id)
                    raise

    def _start(self, accept: Accept) -> None:
        """Start the call ``accept`` describes and hand it over."""
        hello, contact, session = accept.hello, accept.contact, accept.session
        role = Role(contact.role)
        instance = hello.instance.hex()
        # Listening on the call's keys before the WELCOME goes out: the user sends on
        # them once it has the WELCOME.
        call = self._new_call(
            session,
            peer=contact.name,
            role=role,
            peer_base=f"{self.namespace}/user/{hello.caller}/{instance}",
            peer_presence=f"{self.namespace}/presence/user/{hello.caller}/{instance}",
            inbox=_CallInbox(self, hello.call_id, hello.caller),
        )
        call.peer_instance = instance
        self._reply(hello, accept.welcome)
        log.info(
            "answered call %s from %s (%s, %s)",
            call.id,
            contact.name,
            role.value,
            session.suite.label,
        )
        if self.on_call is not None:
            try:
                self.on_call(call)
            except Exception:  # a call nobody serves must not stay up
                log.exception("serving call %s from %s failed; hanging up", call.id, contact.name)
                call.hangup_now("robot error: the call could not be served")
        elif self._incoming.full():
            self.stats.rejected["incoming_queue_full"] += 1
            call.hangup_now("robot busy")
        else:
            self._incoming.put_nowait(call)

    def _reply(self, hello: Hello, frame: bytes) -> None:
        """Send ``frame`` to the handshake inbox of the caller of ``hello``."""
        inbox = f"{self.namespace}/user/{hello.caller}/{hello.instance.hex()}/in"
        if hello.version != LEGACY_VERSION:  # version 1 clients listen on ``…/in`` itself
            inbox = f"{inbox}/{self.identity.name}"
        publisher = self.transport.publisher(inbox, Lane.CONTROL)
        try:
            publisher.put(frame)
        finally:
            publisher.close()


def _check_robot_key(robot: str, known: bytes, tokens: dict[str, bool]) -> None:
    """CallError if ``robot`` is online only with keys other than the ``known`` one.

    ``tokens`` maps the last chunk of the robot's presence keys (its public key) to
    whether the token is alive.
    """
    expected = encode_key(known)
    alive = {key for key, up in tokens.items() if up}
    others = sorted(key for key in alive - {expected} if _is_key(key))
    if others and expected not in alive:
        raise CallError(
            f"KEY MISMATCH: robot {robot} is online with key {others[0]} but known_robots "
            f"has {expected}; if its key changed on purpose, replace it with "
            f"'telebot-user known add {robot} KEY'"
        )


def _is_key(text: str) -> bool:
    try:
        decode_key(text)
    except ValueError:
        return False
    return True


@dataclass(frozen=True, slots=True)
class RobotPresence:
    """A robot seen online: its name, its key, and whether this user trusts that key."""

    name: str
    public_key: bytes
    trusted: bool


class UserEndpoint(_Endpoint):
    """A user client that calls robots by name: ``call = await user.call("guiabot")``."""

    def __init__(
        self,
        transport: Transport,
        identity: Identity,
        known_robots: KnownRobots,
        *,
        settings: CallSettings | None = None,
        namespace: str = DEFAULT_NAMESPACE,
    ) -> None:
        super().__init__(transport, identity, settings=settings, namespace=namespace)
        self.known_robots = known_robots
        self.instance = os.urandom(INSTANCE_LEN)
        self.base = f"{namespace}/user/{identity.name}/{self.instance.hex()}"
        self.inbox = f"{self.base}/in"
        self.presence_key = f"{namespace}/presence/user/{identity.name}/{self.instance.hex()}"
        self._pending: dict[bytes, tuple[InitiatorHandshake, asyncio.Future[Call]]] = {}
        # The keys of a call being set up, listened on before its first HELLO goes out.
        self._pending_inbox: dict[bytes, _CallInbox] = {}
        self._pending_robot: dict[bytes, str] = {}
        # The HELLO each pending call repeats (another one after a RETRY).
        self._pending_hello: dict[bytes, bytes] = {}
        # Per robot called, the keys of the next call to it, listened on ahead of time
        # (:meth:`_listen_ahead`).
        self._next_inbox: dict[str, _CallInbox] = {}

    async def close(self, reason: str = "shutting down") -> None:
        """:meth:`_Endpoint.close`; a call still being set up fails with CallError."""
        for _, future in self._pending.values():
            if not future.done():
                future.set_exception(CallError("the user endpoint closed while calling"))
        try:
            await super().close(reason)
        finally:
            for inbox in self._next_inbox.values():
                inbox.close()
            self._next_inbox.clear()

    def _listen_ahead(self, robot: str) -> None:
        """Listen now on the keys of the next call to ``robot`` (a new random call id).

        A call that drops with the link (Wi-Fi roaming, a tunnel, a 4G dead spot) is
        redialled on keys whose subscription reached the robot's side while the link was
        good, so the new call is answered as soon as the link is back. A subscription
        made during the outage reaches the other side only with the link's own
        retransmission, after TCP's or QUIC's backoff (seconds), or never on zenoh's
        ``udp/`` link; until then nothing of the new call comes back.
        """
        if self._closed or robot in self._next_inbox:
            return
        try:
            self._next_inbox[robot] = _CallInbox(self, os.urandom(8), robot)
        except TelebotError as exc:  # the next call subscribes then; this one is up
            log.info("listening ahead for the next call to %s failed: %s", robot, exc)

    async def call(self, robot: str, *, timeout: float | None = None) -> Call:
        """Call ``robot``; returns the call once the robot accepted it.

        Raises CallRejected with the robot's reason, CallTimeout if it does not answer,
        or CallError when the robot is not in known_robots, or is online with another key
        than the one known_robots holds ("KEY MISMATCH", at once: it could not answer).
        """
        validate_name(robot, "robot name")
        if self._closed:
            raise CallError("this user endpoint is closed")
        robot_key = self.known_robots.get(robot)
        if robot_key is None:
            raise CallError(
                f"{robot} is not a known robot: add its public key with "
                f"'telebot-user known add {robot} KEY'"
            )
        timeout = self.settings.connect_timeout if timeout is None else timeout
        # Keys listened on since the last call to this robot came up, if there are.
        inbox = self._next_inbox.pop(robot, None)
        call_id = inbox.call_id if inbox is not None else os.urandom(8)
        hello, handshake = start_call(
            self.identity.private_key,
            robot_key,
            caller=self.identity.name,
            instance=self.instance,
            call_id=call_id,
            wall_time_ns=time.time_ns(),
            offers=self.suites,
        )
        future: asyncio.Future[Call] = asyncio.get_running_loop().create_future()
        self._pending[call_id] = (handshake, future)
        self._pending_robot[call_id] = robot
        self._pending_hello[call_id] = hello.encode()
        publisher: Publisher | None = None
        watch: Subscription | None = None
        try:
            if inbox is None:
                inbox = _CallInbox(self, call_id, robot)
            self._pending_inbox[call_id] = inbox
            publisher = self.transport.publisher(self._hello_key(robot), Lane.CONTROL)
            # A robot online under this name with another key cannot read the HELLO and
            # never answers: its presence token (which carries its key) tells at once.
            tokens: dict[str, bool] = {}
            # A token of the robot's coming alive (the robot started, or the link to it is
            # back after an outage) sends the next HELLO at once, not up to
            # HELLO_RETRY_INTERVAL later: a redialled call comes back that much sooner.
            appeared = asyncio.Event()
            prefix = f"{self.namespace}/presence/robot/{robot}/"

            def on_presence(key: str, alive: bool) -> None:
                tokens[key.removeprefix(prefix)] = alive
                if alive:
                    appeared.set()

            watch = self.transport.watch_presence(f"{prefix}*", on_presence)
            hellos = 0
            async with asyncio.timeout(timeout):
                while True:
                    publisher.put(self._pending_hello[call_id])
                    hellos += 1
                    appeared.clear()
                    # While the first HELLO waits, the watch reports the tokens already
                    # there: no news, so only later appearances cut a wait short.
                    waiters: list[asyncio.Future[Any]] = [future]
                    if hellos > 1:
                        waiters.append(asyncio.ensure_future(appeared.wait()))
                    try:
                        await asyncio.wait(
                            waiters, timeout=HELLO_RETRY_INTERVAL, return_when=FIRST_COMPLETED
                        )
                    finally:
                        for waiter in waiters[1:]:
                            waiter.cancel()
                    if future.done():
                        call = future.result()  # or the robot's refusal, raised
                        self._listen_ahead(robot)  # while the link is good
                        return call
                    _check_robot_key(robot, robot_key, tokens)
        except BaseException as exc:
            # No WELCOME may complete this call any more (the await below would let one).
            self._pending.pop(call_id, None)
            # Answered, but the caller gave up (cancelled) at that very moment: end the
            # call rather than leave it running unseen.
            if future.done() and not future.cancelled() and future.exception() is None:
                future.result().hangup_now("call set-up cancelled")
            if not isinstance(exc, TimeoutError):
                raise
            online = robot in {p.name for p in await self.robots_online(wait=0.0)}
            hint = (
                # A version-1 robot listens on another key and never sees the HELLO.
                f"it is online but did not answer: does it run telebot protocol version {VERSION}?"
                if online
                else "is it online?"
            )
            if self.transport.unanswered_hint:
                hint += f" {self.transport.unanswered_hint}"
            raise CallTimeout(
                f"robot {robot} did not answer within {timeout:g} s ({hint})"
            ) from None
        finally:
            if watch is not None:
                watch.close()
            if publisher is not None:
                publisher.close()
            if inbox is not None:  # closed by now if a call took it over and ended
                owner = inbox.owner
                if owner is None or owner.end is not None:
                    inbox.close()
            self._pending.pop(call_id, None)
            self._pending_inbox.pop(call_id, None)
            self._pending_robot.pop(call_id, None)
            self._pending_hello.pop(call_id, None)

    def _on_retry(self, retry: Retry) -> None:
        """The robot picked another cipher suite: write the HELLO again with it."""
        pending = self._pending.get(retry.call_id)
        if pending is None or pending[1].done():
            self.stats.rejected["unexpected_retry"] += 1
            return
        handshake, future = pending
        if retry.suite == handshake.suite:  # the answer to an earlier copy of the HELLO
            return
        robot = self._pending_robot[retry.call_id]
        if retry.suite not in self.suites:  # the robot picks among the offers: a forgery
            self.stats.rejected["unexpected_retry"] += 1
            return
        if handshake.suite != self.suites[0]:
            # A robot's pick never changes, so one of the RETRYs was forged; the
            # handshake would fail anyway, so say why now rather than time out.
            future.set_exception(
                CallError(
                    f"cipher suite negotiation with {robot} failed: it asked for "
                    f"{handshake.suite.label}, then {describe_suites([retry.suite])}"
                )
            )
            return
        robot_key = self.known_robots.get(robot)
        assert robot_key is not None  # call() checked it
        hello, new_handshake = start_call(
            self.identity.private_key,
            robot_key,
            caller=self.identity.name,
            instance=self.instance,
            call_id=retry.call_id,
            wall_time_ns=time.time_ns(),
            offers=self.suites,
            suite=Suite(retry.suite),
        )
        log.debug("%s picked cipher suite %s: calling again", robot, new_handshake.suite.label)
        self._pending[retry.call_id] = (new_handshake, future)
        self._pending_hello[retry.call_id] = frame = hello.encode()
        publisher = self.transport.publisher(self._hello_key(robot), Lane.CONTROL)
        try:
            publisher.put(frame)
        finally:
            publisher.close()

    def _hello_key(self, robot: str) -> str:
        """Where this user's HELLOs to ``robot`` go: the robot's inbox, under our name."""
        return f"{self.namespace}/robot/{robot}/in/{self.identity.name}"

    def _on_handshake(self, data: bytes, sender: str | None) -> None:
        frame = decode_frame(data)
        if isinstance(frame, DataFrame):
            self.stats.rejected["data_on_handshake_key"] += 1
            return
        robot = self._pending_robot.get(frame.call_id)
        if robot is not None and sender != robot:  # an answer comes on in/{the robot}
            self.stats.rejected["sender_mismatch"] += 1
            return
        if isinstance(frame, Retry):
            self._on_retry(frame)
            return
        if not isinstance(frame, Welcome):
            raise ProtocolError("a user client does not take HELLO frames")
        pending = self._pending.get(frame.call_id)
        if pending is None or pending[1].done():
            self.stats.rejected["unexpected_welcome"] += 1
            return
        handshake, future = pending
        answer, keys = finish_call(handshake, frame)  # raises if not from the robot
        robot = self._pending_robot[frame.call_id]
        if answer.robot != robot:  # authentic, so the robot itself is misconfigured
            future.set_exception(
                CallError(f"the robot with {robot}'s key answered as {answer.robot!r}")
            )
            return
        if not answer.accepted:
            future.set_exception(CallRejected(answer.reason or f"{robot} refused the call"))
            return
        try:
            role: Role | None = Role(answer.role)
        except ValueError:
            role = None
        session = CallSession(
            frame.call_id,
            keys,
            heartbeat_interval=1.0 / self.settings.heartbeat_hz,
            timeout=self.settings.timeout,
            now=asyncio.get_running_loop().time(),
        )
        call = self._new_call(
            session,
            peer=robot,
            role=role,
            peer_base=f"{self.namespace}/robot/{robot}",
            peer_presence=f"{self.namespace}/presence/robot/{robot}/{encode_key(self.known_robots.get(robot) or b'')}",
            inbox=self._pending_inbox[frame.call_id],
        )
        future.set_result(call)

    async def robots_online(self, wait: float = 1.0) -> list[RobotPresence]:
        """Robots whose presence tokens are seen within ``wait`` seconds."""
        seen: dict[str, RobotPresence] = {}
        prefix = f"{self.namespace}/presence/robot/"

        def on_presence(key: str, alive: bool) -> None:
            name, _, key_text = key.removeprefix(prefix).partition("/")
            try:
                public_key = decode_key(key_text)
            except ValueError:
                return  # not a telebot robot token
            if alive:
                trusted = self.known_robots.get(name) == public_key
                seen[name] = RobotPresence(name, public_key, trusted)
            else:
                seen.pop(name, None)

        watch = self.transport.watch_presence(f"{prefix}*/*", on_presence)
        try:
            await asyncio.sleep(wait)
            if not seen:  # history arrives asynchronously: give it one more loop turn
                await asyncio.sleep(0.05)
        finally:
            watch.close()
        return sorted(seen.values(), key=lambda p: p.name)
