"""The zenoh transport: frames by key expression, presence by liveliness tokens.

Peer mode with the default settings needs no router: peers on one machine or one LAN
find each other by multicast scouting. Client mode with ``connect`` endpoints reaches
robots across networks through zenoh routers (TLS and ACL come from ``config_file`` or
``options``).

Threading. A subscription is declared with a zenoh *ring* channel (256 samples, the size
zenoh-python gives its own callback channel) and has one daemon reader thread. A ring,
not a FIFO: a full FIFO channel blocks the zenoh thread that delivers into it, and that
thread also serves other subscriptions (measured: one call flooding 32 KB datagrams
stalled another call's heartbeats until it dropped); a full ring drops its oldest
sample instead, so one flooded subscription never delays another.
The reader waits in ``recv()`` with the GIL released; when samples come it takes every
one already waiting under a single hold of the GIL, pushes the payloads into the
subscription's bounded :class:`~telebot.channels.transports.inbox.Inbox` (the receive
path every transport shares) and wakes the event loop once with
``call_soon_threadsafe``; everything else
happens on the loop. A callback per sample (zenoh's default) takes the GIL once per
sample, and a burst then costs a GIL hand-over between zenoh's thread and the loop
for every few samples; batching the hand-over is what lets the loop keep up with a
flood. The reader never waits on anything but the GIL, so a slow consumer costs
dropped samples (oldest first, counted in ``stats.dropped``; what the ring itself drops
when even the reader falls behind is not counted: zenoh does not say), never a stalled
zenoh thread.

Lifetime. Presence watches use callbacks, declared in zenoh's "background" mode:
dropping the Python object does *not* undeclare them, and their ``pyo3-closure`` thread
is not a daemon thread, so a watch that is never undeclared keeps the interpreter from
exiting. Subscribers, liveliness tokens and publishers, on the contrary, *are*
undeclared when the Python object is garbage collected. The transport therefore keeps
a reference to every entity it declared and undeclares them all in
:meth:`ZenohTransport.close`; undeclaring a subscriber closes its channel, which ends
its reader thread.

Memory. Payloads are copied out of zenoh on the reader thread and freed on the loop,
a burst at a time. glibc's default is to hand the freed top of a heap back to the
kernel as soon as 128 KB are free, so the next burst page-faults its buffers in again:
at 32 KB per sample that costs more than the copy, and a reader that falls behind once
stays behind (measured: 40,000 instead of 200,000 samples/s, from one run to the
next). Opening a transport therefore sets glibc's mmap and trim thresholds, once per
process (:func:`keep_freed_memory`).
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import json
import logging
import os
import platform
import re
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, Final, Protocol, Self, TypeVar

import zenoh

from telebot.channels.transports.base import (
    CliOption,
    Lane,
    Presence,
    PresenceCallback,
    Publisher,
    ReceiveLimits,
    Sample,
    SampleBatchCallback,
    Subscription,
    SubscriptionStats,
    Transport,
    gate_passes,
    is_call_data_key,
)
from telebot.channels.transports.inbox import Inbox
from telebot.config import DIAL_LEASE, TransportSettings, ZenohSettings
from telebot.errors import TransportError
from telebot.router.acl import with_quic_datagrams

__all__ = [
    "CONNECT_RETRY",
    "LANE_QOS",
    "LINK_LEASE_MS",
    "ZenohPresence",
    "ZenohPresenceWatch",
    "ZenohPublisher",
    "ZenohSubscription",
    "ZenohTransport",
    "build_zenoh_config",
    "keep_freed_memory",
    "reason_of",
    "tls_options",
]

logger = logging.getLogger(__name__)

_T = TypeVar("_T")
_PUT = zenoh.SampleKind.PUT
#: Samples zenoh may hold for a subscription's reader thread (zenoh's own default for
#: callbacks). Larger ones hold more shared-memory buffers and can starve a publisher.
_ZENOH_CHANNEL_SIZE = 256
#: A reader thread wakes the loop at least this often during a long burst.
_READ_BATCH = 256
#: How long closing a subscription waits for its reader thread to end (seconds).
READER_EXIT_TIMEOUT = 1.0
_E = TypeVar("_E", bound="_Entity")
#: glibc ``mallopt`` parameters (malloc.h) and the values :func:`keep_freed_memory` sets.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_TRIM_THRESHOLD = 64 << 20
#: glibc refuses more than half its heap size: 32 MB on 64-bit builds, 512 KB on 32-bit.
_MMAP_THRESHOLD = 32 << 20 if ctypes.sizeof(ctypes.c_void_p) == 8 else 512 << 10
#: Allocator settings a user may have chosen; :func:`keep_freed_memory` leaves them be.
_MALLOC_ENV = ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TOP_PAD_")
_allocator_tuned: bool | None = None  # None: not tried yet in this process

#: Publisher QoS of each lane, as keyword arguments of ``Session.declare_publisher``.
#: Every lane drops under congestion (a stale pose or video frame is worth nothing, and a
#: blocked publisher would block the event loop); CONTROL is sent first and at once
#: (express: not held back for batching), BULK last, so video can never delay a stop.
#: CONTROL and DATA are best effort: a call's channels are lossy datagrams by contract, and
#: what must arrive is repeated by telebot itself (stops until acknowledged,
#: heartbeats, resent requests). On a TCP link that changes nothing; on a QUIC link with
#: zenoh's mixed reliability (:func:`telebot.router.acl.with_quic_datagrams`) they go as
#: QUIC datagrams, so a lost packet no longer holds a stop or a heartbeat up until it is
#: retransmitted, and QUIC puts datagrams in a packet before any stream data. BULK (video,
#: sound, maps) stays on QUIC's reliable streams: QUIC queues datagrams first in first
#: out, up to a megabyte, without pushing back, so a video faster than a long or lossy
#: path (``bench/wan.py``'s intercontinental row) queued every heartbeat behind it (a
#: round trip of 0.6 s on a 0.32 s path, and the supervisor refused to drive).
LANE_QOS: Final[dict[Lane, dict[str, Any]]] = {
    Lane.CONTROL: {
        "priority": zenoh.Priority.REAL_TIME,
        "express": True,
        "congestion_control": zenoh.CongestionControl.DROP,
        "reliability": zenoh.Reliability.BEST_EFFORT,
    },
    Lane.DATA: {
        "priority": zenoh.Priority.DATA,
        "congestion_control": zenoh.CongestionControl.DROP,
        "reliability": zenoh.Reliability.BEST_EFFORT,
    },
    Lane.BULK: {
        "priority": zenoh.Priority.DATA_LOW,
        "congestion_control": zenoh.CongestionControl.DROP,
        "reliability": zenoh.Reliability.RELIABLE,
    },
}

#: How a session retries its ``connect`` endpoints when no config file or option says:
#: 100 ms, then doubling up to 0.5 s.
CONNECT_RETRY: Final[dict[str, Any]] = {
    "period_init_ms": 100,
    "period_max_ms": 500,
    "period_increase_factor": 2,
}

#: The link lease a session that dials (client mode, or ``connect`` endpoints and no
#: ``listen`` ones) announces when neither ``lease``, a config file nor an option says
#: (ms; zenoh's default, which the listening end keeps, is 10 s). The listening end (a
#: robot, a router) drops the link after this long without a word from the dialer (whose
#: keep-alives go every quarter of it); after an outage the dialer's first packet then
#: meets a reset and it dials afresh at once, instead of waiting out QUIC's or TCP's
#: retransmission back-off, which after a 3 s outage is seconds (bench/wan.py:
#: reconnection on 4G over QUIC 3.6-5.4 s -> 0.7 s).
#: Both ends at 1 s is slower (1.5 s): the dialer drops the link too and its own attempts
#: made during the outage back off. A call drops after 0.5 s of silence anyway.
LINK_LEASE_MS: Final = round(DIAL_LEASE * 1000)

# zenoh's messages end with the Rust source location and may wrap a JSON5 parser
# error; users need the reason only, on one line.
_RUST_LOCATION = re.compile(r"\s*\bat\s+\S+\.rs:\d+\.?")
_JSON5_MESSAGE = re.compile(r'msg:\s*"((?:[^"\\]|\\.)*)"')


def _reason(exc: BaseException) -> str:
    """The human part of a zenoh error message, on one line."""
    text = _RUST_LOCATION.sub("", str(exc))
    match = _JSON5_MESSAGE.search(text)
    if match:
        text = match.group(1).replace('\\"', '"')
    if text.startswith('Str("') and text.endswith('")'):
        text = text[5:-2]
    return " ".join(text.split()) or type(exc).__name__


def reason_of(exc: BaseException) -> str:
    """The human part of a zenoh error message, on one line (for other zenoh users)."""
    return _reason(exc)


def _insert(config: zenoh.Config, key: str, value: Any, what: str) -> None:
    try:
        config.insert_json5(key, json.dumps(value))
    except (zenoh.ZError, TypeError, ValueError) as exc:
        # TypeError/ValueError: json.dumps of a value TOML cannot produce but Python can.
        raise TransportError(f"zenoh {what} {value!r} rejected: {_reason(exc)}") from exc


def _insert_endpoints(config: zenoh.Config, key: str, endpoints: list[str], what: str) -> None:
    try:
        config.insert_json5(key, json.dumps(endpoints))
    except zenoh.ZError as exc:
        # zenoh names the malformed endpoint only in its own words; find it ourselves so
        # the message points at the one entry to fix.
        for endpoint in endpoints:
            try:
                zenoh.Config().insert_json5(key, json.dumps([endpoint]))
            except zenoh.ZError as one:
                raise TransportError(
                    f"zenoh {what} endpoint {endpoint!r} is invalid: {_reason(one)}"
                ) from exc
        raise TransportError(f"zenoh {what} endpoints {endpoints!r}: {_reason(exc)}") from exc


def build_zenoh_config(settings: ZenohSettings) -> zenoh.Config:
    """The ``zenoh.Config`` that ``settings`` describe; any zenoh error is a TransportError.

    The config file (if any) is loaded first; ``mode``, ``listen``, ``connect`` and
    ``multicast_scouting`` override it, and ``options`` (path -> value) are inserted last.
    Without a config file, ``connect/retry`` defaults to :data:`CONNECT_RETRY` and, for a
    session that dials, ``transport/link/tx/lease`` to :data:`LINK_LEASE_MS` (``lease``
    sets it for any session), unless an option sets them.
    Empty ``listen``/``connect`` lists keep zenoh's (or the file's) defaults.
    """
    if settings.config_file is not None:
        try:
            config = zenoh.Config.from_file(str(settings.config_file))
        except zenoh.ZError as exc:
            raise TransportError(
                f"cannot load zenoh config file {settings.config_file}: {_reason(exc)}"
            ) from exc
    else:
        config = zenoh.Config()
    _insert(config, "mode", settings.mode, "mode")
    # QUIC endpoints carry the lanes' best-effort frames as QUIC datagrams.
    if settings.listen:
        listen = [with_quic_datagrams(e) for e in settings.listen]
        _insert_endpoints(config, "listen/endpoints", listen, "listen")
    if settings.connect:
        connect = [with_quic_datagrams(e) for e in settings.connect]
        _insert_endpoints(config, "connect/endpoints", connect, "connect")
    _insert(config, "scouting/multicast/enabled", settings.multicast_scouting, "multicast_scouting")
    if settings.config_file is None and "connect/retry" not in settings.options:
        # After a blip, come back within half a second (zenoh's own default retries every
        # 1 s, then 2 s, 4 s): a call that reconnects is only as quick as its session.
        _insert(config, "connect/retry", CONNECT_RETRY, "connect/retry")
    lease = settings.lease
    if lease is None and settings.dials and settings.config_file is None:
        lease = settings.dial_lease  # LINK_LEASE_MS, or twice a long call timeout
    if lease is not None:
        _insert(config, "transport/link/tx/lease", round(lease * 1000), "lease")
    if settings.tls.enabled:
        for path, value in tls_options(settings).items():
            _insert(config, path, value, f"{path} =")
    for path, value in settings.options.items():
        _insert(config, path, value, f"option {path!r} =")
    return config


def data_session_config(settings: ZenohSettings) -> zenoh.Config:
    """The config of ``settings``' data session: the same mode, endpoints to dial,
    credentials and options (a peer keeps dialling every endpoint in the background, a
    client gives up as the first session does), but it neither listens nor scouts: a
    listening endpoint, even zenoh's default, belongs to the first session, and what the
    first finds by scouting it reaches without the data."""
    config = build_zenoh_config(
        settings.model_copy(update={"listen": [], "multicast_scouting": False})
    )
    _insert(config, "listen/endpoints", [], "listen")
    _insert(config, "scouting/gossip/enabled", False, "gossip")
    return config


def tls_options(settings: ZenohSettings) -> dict[str, Any]:
    """The zenoh config paths of ``settings.tls`` (mutual TLS); TransportError if unusable.

    All three files must be set and exist: a missing one is named by its key, here,
    rather than found by zenoh as a failed handshake.
    """
    tls = settings.tls
    files: dict[str, Path | None] = {"ca": tls.ca, "cert": tls.cert, "key": tls.key}
    for name, path in files.items():
        if path is None:
            raise TransportError(
                f"transport.zenoh.tls.{name} is not set (ca, cert and key go together)"
            )
    for name, path in files.items():
        if path is not None and not path.is_file():
            raise TransportError(f"transport.zenoh.tls.{name}: no such file {path}")
    assert tls.ca is not None and tls.cert is not None and tls.key is not None
    return {
        "transport/link/tls/root_ca_certificate": str(tls.ca),
        "transport/link/tls/connect_certificate": str(tls.cert),
        "transport/link/tls/connect_private_key": str(tls.key),
        "transport/link/tls/enable_mtls": True,
    }


def _cert_name(path: Path) -> str:
    """The common name of the certificate in ``path`` (as the router's ACL sees it)."""
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    try:
        cert = x509.load_pem_x509_certificate(path.read_bytes())
        names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    except (OSError, ValueError):
        return f"the certificate {path}"
    return f"certificate {names[0].value!s}" if names else f"the certificate {path}"


def keep_freed_memory() -> bool:
    """Make glibc reuse freed heap instead of handing it back to the kernel at once.

    Blocks up to 32 MB (512 KB on 32-bit builds) then come from the heap rather than
    from a fresh mmap each, and each arena keeps up to 64 MB free at the top of its heap
    before trimming it (glibc's defaults: 128 KB, then adjusted as it goes). See
    "Memory" in this module's docstring for why. The first :meth:`ZenohTransport.open`
    of a process calls it; later calls return the first one's answer. Returns whether
    the settings are in effect; it changes nothing and returns False on a C library
    other than glibc, or when the user chose allocator settings of their own
    (``MALLOC_*_THRESHOLD_``, ``MALLOC_TOP_PAD_`` or ``glibc.malloc`` tunables).
    """
    global _allocator_tuned
    if _allocator_tuned is None:
        _allocator_tuned = _set_malloc_thresholds()
    return _allocator_tuned


def _set_malloc_thresholds() -> bool:
    user_choice = any(name in os.environ for name in _MALLOC_ENV)
    if user_choice or "glibc.malloc" in os.environ.get("GLIBC_TUNABLES", ""):
        return False
    if platform.libc_ver()[0] != "glibc":
        return False
    mallopt = ctypes.CDLL(None).mallopt
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    # The mmap threshold first: setting the trim threshold also stops glibc adjusting
    # the mmap threshold, and it must not then stay at 128 KB.
    if mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD) and mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD):
        return True
    logger.warning("glibc refused the malloc settings; large samples may be slow")
    return False


def name_os_thread(name: str) -> None:
    """Give the calling thread ``name`` in the OS too (``/proc/PID/task/TID/comm``, at most
    15 bytes; Linux only, elsewhere nothing)."""
    with contextlib.suppress(Exception):
        ctypes.CDLL(None).prctl(_PR_SET_NAME, name.encode("ascii")[:15], 0, 0, 0)


_PR_SET_NAME = 15


def _call_soon(loop: asyncio.AbstractEventLoop, fn: Callable[..., object], *args: Any) -> bool:
    """Schedule ``fn`` on ``loop`` from any thread; False if the loop is already closed."""
    try:
        loop.call_soon_threadsafe(fn, *args)
    except RuntimeError:
        # The loop was closed under a late zenoh callback: nobody is left to deliver to.
        return False
    return True


async def _run_in_daemon_thread(fn: Callable[[], _T], name: str) -> _T:
    """Run blocking ``fn`` on a fresh daemon thread and await its result.

    Unlike ``asyncio.to_thread``, a call that never returns cannot hold up the exit of
    ``asyncio.run`` (which joins the default executor) or of the interpreter.
    """
    loop = asyncio.get_running_loop()
    future: asyncio.Future[_T] = loop.create_future()

    def set_result(result: _T) -> None:
        if not future.done():  # else the awaiting side timed out or was cancelled
            future.set_result(result)

    def set_exception(error: BaseException) -> None:
        if not future.done():
            future.set_exception(error)

    def target() -> None:
        try:
            result = fn()
        except BaseException as exc:
            _call_soon(loop, set_exception, exc)
        else:
            _call_soon(loop, set_result, result)

    threading.Thread(target=target, name=name, daemon=True).start()
    return await future


class _Undeclarable(Protocol):
    # zenoh's stubs leave undeclare() unannotated; this gives our calls a type.
    def undeclare(self) -> object: ...


class _Closable(Protocol):
    def close(self) -> object: ...


def _undeclare(raw: _Undeclarable | None, what: str) -> None:
    """Undeclare ``raw``; an entity already gone with its session needs nothing more."""
    if raw is None:
        return
    try:
        raw.undeclare()
    except zenoh.ZError as exc:
        logger.debug("undeclaring %s: %s", what, _reason(exc))


def _close_session(session: _Closable) -> None:
    session.close()


class _Entity:
    """Something declared on the session that the transport must undeclare on close."""

    _closed: bool
    _transport: ZenohTransport

    def close(self) -> None:
        """Stop at once, forget it in the transport and undeclare it; idempotent."""
        if self._closed:
            return
        self._mark_closed()
        self._transport._forget(self)
        self._undeclare()

    def _mark_closed(self) -> None:
        """Stop delivering at once (on the loop), without calling into zenoh."""
        self._closed = True

    def _undeclare(self) -> None:
        """Undeclare in zenoh; may be called from a worker thread."""


class ZenohPublisher(_Entity, Publisher):
    """Publishes on one key with the QoS of one lane (see :data:`LANE_QOS`)."""

    def __init__(
        self, transport: ZenohTransport, raw: zenoh.Publisher, key: str, lane: Lane
    ) -> None:
        self._transport = transport
        self._raw = raw
        self.key = key
        self.lane = lane
        self._closed = False

    @property
    def raw(self) -> zenoh.Publisher:
        """The underlying zenoh publisher (to inspect its QoS)."""
        return self._raw

    def put(self, payload: bytes) -> None:
        """Send ``payload``; never blocks (congestion control DROP)."""
        if self._closed:
            raise TransportError(f"zenoh publisher on {self.key!r} is closed")
        try:
            self._raw.put(payload)
        except zenoh.ZError as exc:
            raise TransportError(f"zenoh put on {self.key!r} failed: {_reason(exc)}") from exc
        self._transport.stats.published += 1

    def _undeclare(self) -> None:
        _undeclare(self._raw, f"publisher {self.key}")


class ZenohSubscription(_Entity, Subscription):
    """Delivers matching samples to a callback on the loop, in batches.

    The reader thread pushes into the subscription's :attr:`inbox` (bounded in samples
    and bytes, dropping the oldest) and schedules one drain per batch; the drain, on the loop, hands at most ``limits.batch`` samples to
    the callback and schedules itself again for the rest, so other subscriptions'
    drains run in between.
    """

    def __init__(
        self,
        transport: ZenohTransport,
        loop: asyncio.AbstractEventLoop,
        pattern: str,
        callback: SampleBatchCallback,
        limits: ReceiveLimits,
    ) -> None:
        self._transport = transport
        self._loop = loop
        self.pattern = pattern
        self._callback = callback
        self.limits = limits
        # A pattern without wildcards is the key of every sample it gets.
        self._exact = "*" not in pattern
        #: Payloads (exact pattern) or (key, payload) pairs, between the reader and the loop.
        self.inbox: Inbox[Any] = Inbox(
            limits,
            default_samples=transport.settings.queue_size,
            default_bytes=transport.settings.queue_bytes,
        )
        self._drain_scheduled = False
        self.stats = SubscriptionStats()
        self._closed = False
        self._raw: zenoh.Subscriber[zenoh.handlers.Handler[zenoh.Sample]] | None = None
        self._reader: threading.Thread | None = None

    def _read(self, handler: Any) -> None:
        """Reader thread: move samples from zenoh's channel to the queue, in batches.

        ``recv()`` waits with the GIL released; once a sample is there, every sample
        already waiting is taken with ``try_recv()`` under one hold of the GIL, and the
        loop is woken once for all of them. A payload over ``max_payload`` is dropped
        before it is copied: a 1 MB sample sent by a stranger costs a length check, not
        a megabyte. No lock: deque appends and pops are atomic, and the flag is set here
        and cleared by the drain *before* it takes from the queue, so a sample appended
        at any moment is either taken by a drain already running or schedules the next
        one. Ends when the subscriber is undeclared, which closes zenoh's channel under
        ``recv()`` or ``try_recv()`` alike.
        """
        if self._transport.reader_name is not None:
            name_os_thread(self._transport.reader_name)
        recv, try_recv = handler.recv, handler.try_recv
        inbox, exact = self.inbox, self._exact
        admits, push = inbox.admits, inbox.push
        while True:
            try:
                sample = recv()
            except zenoh.ZError:  # "channel is empty and closed": undeclared
                return
            taken = 0
            while sample is not None:
                if sample.kind == _PUT and not self._closed:
                    raw = sample.payload
                    size = len(raw)
                    payload = None
                    if not admits(size):
                        self._wake()  # so that the count is reported, with nothing to deliver
                    else:
                        payload = raw.to_bytes()
                        gate = self.gate
                        # Before anything is dropped for it: what fails the gate takes
                        # no room from the frames queued before it.
                        if gate is not None and not gate_passes(gate, payload):
                            # Counted, not reported at once: waking the loop for each
                            # of a flood's frames would cost it what the gate saved.
                            inbox.gated += 1
                            payload = None
                    if payload is not None:
                        push(payload if exact else (str(sample.key_expr), payload), size)
                        taken += 1
                        if taken == _READ_BATCH:  # a long burst: let the loop start on it
                            taken = 0
                            self._wake()
                del sample
                try:
                    sample = try_recv()
                except zenoh.ZError:  # undeclared mid-batch: deliver what was taken, then end
                    sample = None
            if taken:
                self._wake()

    def _wake(self) -> None:
        """Reader thread: schedule one drain on the loop unless one is pending."""
        if not self._drain_scheduled:
            self._drain_scheduled = True
            _call_soon(self._loop, self._drain)

    def _drain(self) -> None:
        """Loop: deliver up to ``limits.batch`` queued samples; schedule the rest."""
        self._drain_scheduled = False
        items = self.inbox.take()
        if self._exact:
            key = self.pattern
            batch = [Sample(key, payload) for payload in items]
        else:
            batch = [Sample(*item) for item in items]
        if len(self.inbox) and not self._closed:  # the rest after other callbacks had their turn
            self._drain_scheduled = True
            self._loop.call_soon(self._drain)
        self.inbox.report(self.stats, self._transport.stats)
        if self._closed or not batch:
            return
        try:
            self._callback(batch)
        except Exception:
            # One bad batch must not end the subscription: later batches still come.
            logger.exception("subscriber callback for %r raised", self.pattern)

    def _mark_closed(self) -> None:
        self._closed = True
        self.inbox.clear()

    def _undeclare(self) -> None:
        _undeclare(self._raw, f"subscriber {self.pattern}")
        # Undeclaring wakes the reader, which then ends. Wait for that: a reader still
        # inside zenoh when the interpreter exits is killed there, which aborts the
        # process ("FATAL: exception not rethrown").
        reader = self._reader
        if reader is not None and reader is not threading.current_thread():
            reader.join(READER_EXIT_TIMEOUT)


class ZenohPresence(_Entity, Presence):
    """A liveliness token: alive for watchers until closed or the session ends."""

    def __init__(self, transport: ZenohTransport, raw: zenoh.LivelinessToken, key: str) -> None:
        self._transport = transport
        self._raw = raw  # zenoh undeclares a token when this object is collected
        self.key = key
        self._closed = False

    def _undeclare(self) -> None:
        _undeclare(self._raw, f"token {self.key}")


class ZenohPresenceWatch(_Entity, Subscription):
    """Reports liveliness tokens appearing (PUT) and vanishing (DELETE), on the loop."""

    def __init__(
        self,
        transport: ZenohTransport,
        loop: asyncio.AbstractEventLoop,
        pattern: str,
        callback: PresenceCallback,
    ) -> None:
        self._transport = transport
        self._loop = loop
        self.pattern = pattern
        self._callback = callback
        self.stats = SubscriptionStats()  # presence changes are not samples: stays zero
        self._closed = False
        self._raw: zenoh.Subscriber[None] | None = None

    def _on_sample(self, sample: zenoh.Sample) -> None:
        """zenoh thread: forward (key, alive) to the loop; presence changes are rare."""
        if self._closed:
            return
        alive = sample.kind == zenoh.SampleKind.PUT
        _call_soon(self._loop, self._deliver, str(sample.key_expr), alive)

    def _deliver(self, key: str, alive: bool) -> None:
        if self._closed:
            return
        try:
            self._callback(key, alive)
        except Exception:
            logger.exception("presence callback for %r raised", self.pattern)

    def _undeclare(self) -> None:
        _undeclare(self._raw, f"presence watch {self.pattern}")


class ZenohTransport(Transport):
    """Frames and presence over an Eclipse Zenoh session.

    Single use: :meth:`open` once, :meth:`close` once (further closes do nothing).
    """

    name = "zenoh"
    section = "zenoh"
    cli_options = (
        CliOption(
            "--listen",
            "listen",
            "zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)",
            metavar="ENDPOINT",
            repeatable=True,
        ),
        CliOption(
            "--connect",
            "connect",
            "zenoh endpoint (peer or router) to connect to, e.g. tcp/10.0.0.5:7447 (repeatable)",
            metavar="ENDPOINT",
            repeatable=True,
        ),
    )

    def __init__(
        self, settings: ZenohSettings | None = None, *, reader_name: str | None = None
    ) -> None:
        super().__init__()
        self.settings = settings if settings is not None else ZenohSettings()
        #: The OS name of this transport's reader threads (:func:`name_os_thread`), to tell
        #: their CPU apart (the robot's gateway); None: left as they are.
        self.reader_name = reader_name
        self._session: zenoh.Session | None = None
        # The second session of ``settings.data_session`` (calls' data keys), if any.
        self._data_session: zenoh.Session | None = None
        self._session_id: str | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._opening = False
        self._closed = False
        # Strong references to everything declared: tokens and publishers die with
        # their Python object, and close() must reach every subscriber.
        self._entities: dict[int, _Entity] = {}
        self._owns_session = True
        if self.settings.mode == "client" and self.settings.tls.cert is not None:
            # A router's ACL drops what it does not allow without a word to the sender.
            self.unanswered_hint = (
                f"or the router's access control does not let {_cert_name(self.settings.tls.cert)} "
                "reach it (revoked, or not issued by telebot-router cert)"
            )

    @classmethod
    def from_settings(cls, settings: TransportSettings) -> Self:
        """Build an unopened transport from ``settings.zenoh``."""
        return cls(settings.zenoh)

    @property
    def session_id(self) -> str:
        """The zenoh id of the session (hex string); available once opened."""
        if self._session_id is None:
            raise TransportError("zenoh transport is not open")
        return self._session_id

    @property
    def session(self) -> zenoh.Session:
        """The underlying ``zenoh.Session``, for what this interface does not cover."""
        return self._require_open()

    @property
    def data_session(self) -> zenoh.Session | None:
        """The second session that carries calls' data keys (``[transport.zenoh]
        data_session``), or None: all on :attr:`session`."""
        self._require_open()
        return self._data_session

    async def open(self) -> None:
        """Open the zenoh session on a worker thread (zenoh.open may block)."""
        if self._closed:
            raise TransportError("zenoh transport is closed; create a new one")
        if self._session is not None or self._opening:
            raise TransportError("zenoh transport is already open")
        if self.settings.data_session and not self.settings.connect:
            raise TransportError(
                "transport.zenoh.data_session = true needs connect endpoints: "
                "the second session only dials"
            )
        configs = [build_zenoh_config(self.settings)]
        if self.settings.splits_data:
            configs.append(data_session_config(self.settings))
        keep_freed_memory()
        self._loop = asyncio.get_running_loop()
        self._opening = True
        task = asyncio.ensure_future(_open_sessions(configs))
        try:
            session, *data = await asyncio.shield(task)
        except asyncio.CancelledError:
            # The thread cannot be stopped; close the session it may still produce.
            task.add_done_callback(_close_late_session)
            raise
        except _OpenFailed as failed:
            exc = failed.error
            which = " (its data session: transport.zenoh.data_session)" if failed.index else ""
            hint = ""
            if any(e.startswith(("tls/", "quic/")) for e in self.settings.connect):
                # zenoh says only "Unable to connect"; through a telebot router the usual
                # cause is the certificate, which the router refuses without a word.
                hint = (
                    " (is the router up? a TLS or QUIC router refuses a client without a "
                    "certificate from its CA: check transport.zenoh.tls)"
                )
            raise TransportError(
                f"cannot open zenoh session{which} (mode={self.settings.mode}, "
                f"listen={self.settings.listen}, connect={self.settings.connect}): "
                f"{_reason(exc)}{hint}"
            ) from exc
        finally:
            self._opening = False
        if self._closed:  # close() ran while zenoh.open was still working
            _close_in_background([session, *data])
            raise TransportError("zenoh transport was closed while opening")
        self._session = session
        self._data_session = data[0] if data else None
        self._session_id = str(session.zid())
        logger.debug("zenoh session %s open (%s)", self._session_id, self.settings.mode)

    async def adopt(
        self, session: zenoh.Session, data_session: zenoh.Session | None = None
    ) -> None:
        """Use open sessions of someone else's (the router's or the robot's, for its browser
        gateway) instead of opening them: ``session``, and ``data_session`` for calls' data
        keys if the owner has one (:attr:`data_session`); :meth:`close` undeclares what this
        transport declared and leaves the sessions open."""
        if self._closed or self._session is not None or self._opening:
            raise TransportError("zenoh transport is already open or closed")
        self._loop = asyncio.get_running_loop()
        self._session = session
        self._data_session = data_session
        self._session_id = str(session.zid())
        self._owns_session = False

    async def close(self) -> None:
        """Undeclare everything and close the session within ``settings.close_timeout``.

        Callbacks stop at once; the zenoh calls run on a daemon thread, and if they do
        not finish in time a warning is logged and close returns anyway.
        """
        if self._closed:
            return
        self._closed = True
        session, self._session = self._session, None
        data_session, self._data_session = self._data_session, None
        entities = list(self._entities.values())
        self._entities.clear()
        for entity in entities:
            entity._mark_closed()
        if session is None:
            return
        # Subscribers first: their callback threads keep the interpreter alive.
        entities.sort(key=lambda e: not isinstance(e, ZenohSubscription | ZenohPresenceWatch))

        def shutdown() -> None:
            for entity in entities:
                entity._undeclare()
            if self._owns_session:
                _close_session(session)
                if data_session is not None:
                    _close_session(data_session)

        timeout = self.settings.close_timeout
        try:
            await asyncio.wait_for(_run_in_daemon_thread(shutdown, "zenoh-close"), timeout)
        except TimeoutError:
            logger.warning(
                "zenoh session %s did not close within %.1f s; abandoning it",
                self._session_id,
                timeout,
            )
        except Exception as exc:  # close must not raise: the session is abandoned either way
            logger.warning("closing zenoh session %s: %s", self._session_id, _reason(exc))

    def publisher(self, key: str, lane: Lane = Lane.DATA) -> ZenohPublisher:
        """Declare a publisher on ``key`` with the QoS of ``lane``."""
        session = self._session_for(key)
        try:
            raw = session.declare_publisher(key, **LANE_QOS[lane])
        except zenoh.ZError as exc:
            raise TransportError(f"cannot publish on {key!r}: {_reason(exc)}") from exc
        return self._remember(ZenohPublisher(self, raw, key, lane))

    def subscribe(
        self,
        pattern: str,
        callback: SampleBatchCallback,
        *,
        limits: ReceiveLimits | None = None,
    ) -> ZenohSubscription:
        """Deliver samples matching ``pattern`` to ``callback(batch)`` on the loop."""
        session = self._session_for(pattern)
        assert self._loop is not None
        limits = limits if limits is not None else ReceiveLimits()
        sub = ZenohSubscription(self, self._loop, pattern, callback, limits)
        try:
            raw = session.declare_subscriber(
                pattern, zenoh.handlers.RingChannel(_ZENOH_CHANNEL_SIZE)
            )
        except zenoh.ZError as exc:
            raise TransportError(f"cannot subscribe to {pattern!r}: {_reason(exc)}") from exc
        sub._raw = raw
        # The reader waits on the subscriber's handler, not on the subscriber: undeclaring
        # the subscriber while another thread waits in its recv() fails in zenoh-python.
        sub._reader = threading.Thread(
            target=sub._read, args=(raw.handler,), name=f"zenoh-sub {pattern}", daemon=True
        )
        sub._reader.start()
        return self._remember(sub)

    def declare_presence(self, key: str) -> ZenohPresence:
        """Declare a liveliness token on ``key``."""
        session = self._require_open()
        try:
            raw = session.liveliness().declare_token(key)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot declare presence {key!r}: {_reason(exc)}") from exc
        return self._remember(ZenohPresence(self, raw, key))

    def watch_presence(self, pattern: str, callback: PresenceCallback) -> ZenohPresenceWatch:
        """Call ``callback(key, alive)`` on the loop for tokens matching ``pattern``."""
        session = self._require_open()
        assert self._loop is not None
        watch = ZenohPresenceWatch(self, self._loop, pattern, callback)
        try:
            watch._raw = session.liveliness().declare_subscriber(
                pattern, watch._on_sample, history=True
            )
        except zenoh.ZError as exc:
            raise TransportError(f"cannot watch presence {pattern!r}: {_reason(exc)}") from exc
        return self._remember(watch)

    def _require_open(self) -> zenoh.Session:
        if self._closed:
            raise TransportError("zenoh transport is closed")
        if self._session is None:
            raise TransportError("zenoh transport is not open; call open() first")
        return self._session

    def _session_for(self, key: str) -> zenoh.Session:
        """The session for ``key``: the data session (if open) for a call's data key."""
        session = self._require_open()
        if self._data_session is not None and is_call_data_key(key):
            return self._data_session
        return session

    def _remember(self, entity: _E) -> _E:
        self._entities[id(entity)] = entity
        return entity

    def _forget(self, entity: _Entity) -> None:
        self._entities.pop(id(entity), None)


class _OpenFailed(Exception):
    """zenoh.open's error for the ``index``-th config of :func:`_open_sessions`."""

    def __init__(self, index: int, error: zenoh.ZError) -> None:
        super().__init__(str(error))
        self.index, self.error = index, error


async def _open_sessions(configs: list[zenoh.Config]) -> list[zenoh.Session]:
    """One zenoh session per config, opened at once on worker threads; if one fails, those
    that opened are closed and its error raised (a ZError as :class:`_OpenFailed`)."""
    results = await asyncio.gather(
        *(asyncio.to_thread(zenoh.open, config) for config in configs), return_exceptions=True
    )
    sessions = [r for r in results if isinstance(r, zenoh.Session)]
    for index, result in enumerate(results):
        if isinstance(result, BaseException):
            _close_in_background(sessions)
            if isinstance(result, zenoh.ZError):
                raise _OpenFailed(index, result) from result
            raise result
    return sessions


def _close_late_session(task: asyncio.Future[list[zenoh.Session]]) -> None:
    """Close the sessions whose open() was cancelled while zenoh.open was still running."""
    if task.cancelled() or task.exception() is not None:
        return
    _close_in_background(task.result())


def _close_in_background(sessions: list[zenoh.Session]) -> None:
    """Close sessions nobody will use (an open that failed or was given up) on daemon
    threads: zenoh's close may block, and no one waits for it."""
    for session in sessions:
        threading.Thread(target=session.close, name="zenoh-close-late", daemon=True).start()
