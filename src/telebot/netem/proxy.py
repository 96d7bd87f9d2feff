"""A loopback proxy that plays a netem profile between two zenoh endpoints.

The machines we test on have no ``tc netem``: instead, a zenoh session connects to the
proxy, and the proxy forwards to the real endpoint (a router or a peer that listens)
through :class:`~telebot.netem.model.LinkModel`::

    with NetemProxy("wifi", listen="tcp/127.0.0.1:0", target="tcp/127.0.0.1:7447") as proxy:
        config.transport.zenoh.connect = [proxy.endpoint]
        ...
        proxy.outage(0.3)  # a roaming gap, now

"up" is the direction from the side that connects to the proxy to the target, "down" the
way back (the connecting side is the one on the profiled network).

Two modes, chosen by the endpoints' scheme:

* **UDP** (``udp/``, and ``quic/``, which is UDP underneath): each datagram goes through
  the model on its own; a lost one is gone, jitter may reorder them, a full bandwidth queue
  drops at its tail. Every client address gets its own upstream socket; all clients share
  one link (one pair of models: one queue, one burst chain).
* **TCP** (``tcp/``, and ``tls/``, whose bytes it relays unread): each connection's byte
  stream is cut into segments of :data:`MSS` bytes (on a lossless profile, whole reads)
  that go through an ``ordered`` model:
  nothing is lost, but a segment the model loses arrives one retransmission timeout later
  (doubling while it keeps being lost) and holds up every byte behind it in its own
  connection — how TCP turns loss into stalls of every lane. All connections share one
  link too (one pair of ordered models: one bandwidth queue, one burst chain), each in
  order on its own (:class:`~telebot.netem.model.InOrder`), as connections through one
  4G dongle do. The bandwidth queue never drops: when it holds more than
  the profile's ``queue`` seconds, or :data:`WINDOW` bytes wait undelivered, the proxy
  stops reading from the sender (TCP's flow control).

Outages (the profile's schedule, or :meth:`NetemProxy.outage`) cut both directions at
once. UDP datagrams sent during one are lost. A TCP connection survives them, its data
held up until TCP's backed-off retransmission after the gap (as a real connection
survives a Wi-Fi roam), unless the outage lasts longer than ``cut_after`` seconds
(default :data:`CUT_AFTER`, zenoh's default lease: beyond it zenoh gives the session up
anyway): then the proxy resets every connection and refuses new ones until the gap
ends, so zenoh has to reconnect, as after a real network change.

The proxy runs on its own thread with its own event loop, so it works the same under
synchronous and asynchronous callers (``with`` or ``async with``, or :meth:`start` and
:meth:`close`); :meth:`close` leaves no thread nor socket behind.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import heapq
import ipaddress
import itertools
import logging
import math
import os
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from types import TracebackType
from typing import Any, Literal, Self

from telebot.errors import ConfigError, TransportError
from telebot.netem.model import (
    Direction,
    InOrder,
    LinkModel,
    ModelStats,
    OutageSchedule,
    Profile,
    profile,
)

__all__ = ["CUT_AFTER", "MSS", "WINDOW", "Endpoint", "NetemProxy", "ProxyStats", "parse_endpoint"]

_log = logging.getLogger(__name__)

#: A TCP connection is reset by an outage longer than this, seconds (zenoh's default lease).
CUT_AFTER = 10.0
#: The TCP segment size the stream is cut into for the model (Ethernet's MSS), bytes.
MSS = 1448
#: Bytes of one TCP direction the proxy holds undelivered before it stops reading.
WINDOW = 1 << 20
#: How often the proxy checks whether an outage has lasted long enough to cut, seconds.
_HOUSEKEEPING = 0.02
_START_TIMEOUT = 10.0
_STOP_TIMEOUT = 10.0
_SCHEMES = {"udp": "udp", "quic": "udp", "tcp": "tcp", "tls": "tcp"}


@dataclass(frozen=True)
class Endpoint:
    """A zenoh endpoint the proxy can listen on or forward to: ``scheme/host:port``."""

    scheme: str
    host: str
    port: int

    @property
    def mode(self) -> Literal["udp", "tcp"]:
        """``udp`` for udp/ and quic/ endpoints, ``tcp`` for tcp/ and tls/."""
        return "udp" if _SCHEMES[self.scheme] == "udp" else "tcp"

    def __str__(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.scheme}/{host}:{self.port}"


def parse_endpoint(text: str, *, listen: bool = False) -> Endpoint:
    """``udp/127.0.0.1:7447`` as an :class:`Endpoint`; ConfigError naming what is wrong.

    Zenoh's ``?``/``#`` options are not kept. Port 0 (any free port) only for ``listen``.
    """
    shown = text if len(text) <= 60 else text[:57] + "..."
    scheme, sep, address = text.partition("/")
    address = address.split("?", 1)[0].split("#", 1)[0]
    if not sep or scheme not in _SCHEMES:
        known = ", ".join(f"{s}/" for s in _SCHEMES)
        raise ConfigError(f"endpoint {shown!r}: expected one of {known} then HOST:PORT")
    host, colon, port_text = address.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    low = 0 if listen else 1
    if not colon or not host or not port_text.isdigit() or not low <= int(port_text) <= 65535:
        raise ConfigError(f"endpoint {shown!r}: expected {scheme}/HOST:PORT, port {low}..65535")
    if ":" in host:
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise ConfigError(f"endpoint {shown!r}: {host[:40]!r} is not an address") from None
    return Endpoint(scheme, host, int(port_text))


@dataclass
class ProxyStats:
    """The proxy's counters (a snapshot: :attr:`NetemProxy.stats`).

    ``up``/``down`` count the link's two directions: for TCP, ``sent`` counts segments
    and ``retransmitted`` the late ones; for UDP, ``sent`` counts datagrams and ``lost``
    those that did not arrive.
    """

    up: ModelStats = field(default_factory=ModelStats)
    down: ModelStats = field(default_factory=ModelStats)
    #: Packets (datagrams, or TCP segments) handed on to the other side, per direction.
    delivered_up: int = 0
    delivered_down: int = 0
    #: Bytes handed on to the other side, per direction.
    bytes_up: int = 0
    bytes_down: int = 0
    #: TCP connections accepted, or UDP client addresses seen.
    connections: int = 0
    #: TCP connections reset because an outage outlasted ``cut_after``; connections
    #: refused during such an outage or because the target did not answer.
    cut: int = 0
    refused: int = 0
    #: Outages forced by :meth:`NetemProxy.outage`.
    outages: int = 0

    def as_dict(self) -> dict[str, Any]:
        """The counters as a JSON-ready dict."""
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            out[f.name] = value.as_dict() if isinstance(value, ModelStats) else value
        return out


class _Timeline:
    """Calls due at given loop times, in order of time then of scheduling (the loop's own
    timers do not keep equal times first-in first-out, which a byte stream needs)."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._heap: list[tuple[float, int, Callable[[], None]]] = []
        self._seq = itertools.count()
        self._handle: asyncio.TimerHandle | None = None
        self._armed_at = math.inf

    def at(self, due: float, fn: Callable[[], None]) -> None:
        heapq.heappush(self._heap, (due, next(self._seq), fn))
        self._arm()

    def _arm(self) -> None:
        """Have the timer fire at the earliest due time (one timer at most)."""
        if not self._heap or self._heap[0][0] >= self._armed_at:
            return
        if self._handle is not None:
            self._handle.cancel()
        self._armed_at = self._heap[0][0]
        self._handle = self._loop.call_at(self._armed_at, self._run)

    def _run(self) -> None:
        # The loop may fire a timer a hair early: what it was armed for is due.
        limit = max(self._loop.time(), self._armed_at)
        self._handle, self._armed_at = None, math.inf
        while self._heap and self._heap[0][0] <= limit:
            _, _, fn = heapq.heappop(self._heap)
            try:
                fn()  # may schedule more (through at(), which arms the timer)
            except Exception:  # one broken delivery must not stop the others
                _log.exception("netem delivery failed")
        self._arm()

    def close(self) -> None:
        if self._handle is not None:
            self._handle.cancel()
        self._heap.clear()


class _Relay:
    """What both modes share: models, counters, the clock."""

    def __init__(self, proxy: NetemProxy, loop: asyncio.AbstractEventLoop) -> None:
        self.proxy = proxy
        self.loop = loop
        self.timeline = _Timeline(loop)
        self.models: list[LinkModel] = []

    def new_models(self, seed: int, *, ordered: bool) -> dict[Direction, LinkModel]:
        up, down = (
            LinkModel(self.proxy.profile, seed, d, ordered=ordered, schedule=self.proxy.schedule)
            for d in ("up", "down")
        )
        self.models += [up, down]
        return {"up": up, "down": down}

    def delivered(self, direction: Direction, size: int) -> None:
        stats = self.proxy._counters
        if direction == "up":
            stats.delivered_up += 1
            stats.bytes_up += size
        else:
            stats.delivered_down += 1
            stats.bytes_down += size


# --------------------------------------------------------------------------- UDP


class _UdpListener(asyncio.DatagramProtocol):
    def __init__(self, relay: _UdpRelay) -> None:
        self.relay = relay

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.relay.from_client(data, addr)

    def error_received(self, exc: Exception) -> None:  # ICMP unreachable: a peer went away
        _log.debug("netem udp listener: %s", exc)


class _UdpRelay(_Relay):
    """Datagrams: one link (a pair of models) for every client; a socket per client."""

    def __init__(self, proxy: NetemProxy, loop: asyncio.AbstractEventLoop) -> None:
        super().__init__(proxy, loop)
        self.listener: asyncio.DatagramTransport | None = None
        # Per client address, a plain non-blocking socket connected to the target: made
        # at once (no await), so the client's first datagram already has its way out.
        self.upstreams: dict[tuple[str, int], socket.socket] = {}
        self.target: tuple[socket.AddressFamily, Any] | None = None
        self.link = self.new_models(proxy.seed, ordered=False)

    async def open(self, listen: Endpoint) -> int:
        target = self.proxy.target
        infos = await self.loop.getaddrinfo(target.host, target.port, type=socket.SOCK_DGRAM)
        self.target = (infos[0][0], infos[0][4])
        transport, _ = await self.loop.create_datagram_endpoint(
            lambda: _UdpListener(self), local_addr=(listen.host, listen.port)
        )
        self.listener = transport
        return int(transport.get_extra_info("sockname")[1])

    def from_client(self, data: bytes, client: tuple[str, int]) -> None:
        upstream = self.upstreams.get(client) or self._upstream(client)
        if upstream is not None:
            self._send("up", data, functools.partial(self._to_target, upstream, data))

    def _upstream(self, client: tuple[str, int]) -> socket.socket | None:
        assert self.target is not None
        family, address = self.target
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.setblocking(False)
            sock.connect(address)
        except OSError as exc:
            sock.close()
            _log.warning("netem: cannot reach %s: %s", self.proxy.target, exc)
            self.proxy._counters.refused += 1
            return None
        self.upstreams[client] = sock
        self.proxy._counters.connections += 1
        self.loop.add_reader(sock.fileno(), self._from_target, sock, client)
        return sock

    def _from_target(self, sock: socket.socket, client: tuple[str, int]) -> None:
        while True:
            try:
                data = sock.recv(1 << 16)
            except BlockingIOError:
                return
            except OSError as exc:  # ICMP unreachable: the target is not there (yet)
                _log.debug("netem udp upstream: %s", exc)
                return
            self._send("down", data, functools.partial(self._to_client, client, data))

    def _send(self, direction: Direction, data: bytes, deliver: Callable[[], None]) -> None:
        arrival = self.link[direction].transmit(len(data), self.loop.time())
        if arrival is not None:
            self.timeline.at(arrival, deliver)

    def _to_target(self, upstream: socket.socket, data: bytes) -> None:
        if upstream.fileno() < 0:
            return
        try:
            upstream.send(data)
        except OSError as exc:  # a full buffer or no target: the datagram is lost
            _log.debug("netem udp upstream send: %s", exc)
            return
        self.delivered("up", len(data))

    def _to_client(self, client: tuple[str, int], data: bytes) -> None:
        if self.listener is not None and not self.listener.is_closing():
            self.listener.sendto(data, client)
            self.delivered("down", len(data))

    def tick(self) -> None:
        pass  # an outage loses datagrams; there is no connection to cut

    async def close(self) -> None:
        self.timeline.close()
        for sock in self.upstreams.values():
            self.loop.remove_reader(sock.fileno())
            sock.close()
        self.upstreams.clear()
        if self.listener is not None:
            self.listener.close()
        await asyncio.sleep(0)  # let the transports finish closing their sockets


# --------------------------------------------------------------------------- TCP


class _Stream:
    """One direction of one TCP connection through an ordered model."""

    def __init__(
        self,
        relay: _TcpRelay,
        direction: Direction,
        model: LinkModel,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
    ) -> None:
        self.relay = relay
        self.direction = direction
        self.model = model
        self.reader = reader
        self.writer = writer
        self.order = InOrder()  # this connection's own order on the shared link
        self.pending = 0  # bytes scheduled, not yet written
        self.drained = asyncio.Event()

    async def pump(self) -> None:
        loop = self.relay.loop
        queue = self.relay.proxy.profile.queue
        try:
            while True:
                # Flow control: a full bandwidth queue or a stalled stream holds the sender
                # (checked again after the wait: other connections share the queue).
                if (backlog := self.model.backlog(loop.time())) > queue:
                    await asyncio.sleep(backlog - queue)
                    continue
                while self.pending > WINDOW:
                    self.drained.clear()
                    await self.drained.wait()
                await self.writer.drain()  # and a receiver that does not read holds it too
                data = await self.reader.read(1 << 16)
                if not data:
                    break
                self._send(data, loop.time())
        except OSError:  # a reset: reset the other side too, once what was sent arrived
            self.relay.timeline.at(self.done_at(), self.relay_reset)
            return
        # EOF: pass the half-close on once everything sent has arrived.
        self.relay.timeline.at(self.done_at(), self.write_eof)

    def done_at(self) -> float:
        """When everything this direction was given will have arrived."""
        return max(self.relay.loop.time(), self.order.last_arrival)

    def write_eof(self) -> None:
        if not self.writer.is_closing() and self.writer.can_write_eof():
            with contextlib.suppress(OSError):
                self.writer.write_eof()

    def relay_reset(self) -> None:
        self.relay.end(self.writer, abort=True)

    def _send(self, data: bytes, now: float) -> None:
        view = memoryview(data)
        batch_at, batch = -math.inf, bytearray()
        # Segments matter only where the profile loses some (each its own fate); on a
        # lossless link one read goes whole, which spares the CPU on fast links.
        size = MSS if self.model.profile.mean_loss > 0 else len(data)
        for offset in range(0, len(data), size):
            segment = view[offset : offset + size]
            arrival = self.model.transmit(len(segment), now, self.order)
            assert arrival is not None  # an ordered model delays, it does not lose
            if arrival != batch_at and batch:  # segments arriving together go together
                self._deliver_at(batch_at, bytes(batch))
                batch = bytearray()
            batch_at = arrival
            batch += segment
        if batch:
            self._deliver_at(batch_at, bytes(batch))

    def _deliver_at(self, due: float, data: bytes) -> None:
        self.pending += len(data)
        self.relay.timeline.at(due, lambda: self._deliver(data))

    def _deliver(self, data: bytes) -> None:
        self.pending -= len(data)
        if self.pending <= WINDOW:
            self.drained.set()
        if not self.writer.is_closing():
            self.writer.write(data)
            self.relay.delivered(self.direction, len(data))


class _TcpRelay(_Relay):
    """Byte streams: one link (a pair of ordered models) for every connection, each
    connection in order on its own."""

    def __init__(self, proxy: NetemProxy, loop: asyncio.AbstractEventLoop) -> None:
        super().__init__(proxy, loop)
        self.link = self.new_models(proxy.seed, ordered=True)
        self.server: asyncio.Server | None = None
        # Each connection's two sockets, each mapped to the other.
        self.connections: dict[asyncio.StreamWriter, asyncio.StreamWriter] = {}
        self.tasks: set[asyncio.Task[None]] = set()
        self.cut_gap: tuple[float, float] | None = None  # the outage that cut, until it ends

    async def open(self, listen: Endpoint) -> int:
        self.server = await asyncio.start_server(self._accept, listen.host, listen.port)
        return int(self.server.sockets[0].getsockname()[1])

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self.tasks.add(task)
        stats = self.proxy._counters
        try:
            if self.cut_gap is not None:  # the network is down for good: no connection
                stats.refused += 1
                writer.transport.abort()
                return
            target = self.proxy.target
            try:
                up_reader, up_writer = await asyncio.open_connection(target.host, target.port)
            except OSError as exc:
                _log.warning("netem: cannot reach %s: %s", target, exc)
                stats.refused += 1
                writer.transport.abort()
                return
            stats.connections += 1
            self.connections[writer] = up_writer
            self.connections[up_writer] = writer
            streams = (
                _Stream(self, "up", self.link["up"], reader, up_writer),
                _Stream(self, "down", self.link["down"], up_reader, writer),
            )
            await asyncio.gather(*(s.pump() for s in streams))
            # Both ways ended: close once the last bytes have arrived.
            last = max(s.done_at() for s in streams)
            self.timeline.at(last, functools.partial(self.end, writer))
        except asyncio.CancelledError:
            # close() cancels: end quietly (asyncio's server logs a cancelled handler).
            for w in (writer, self.connections.get(writer)):
                if w is not None:
                    w.transport.abort()
        finally:
            self.tasks.discard(task)

    def end(self, writer: asyncio.StreamWriter, *, abort: bool = False) -> None:
        """Close the connection of ``writer`` (both sockets); ``abort``: reset them."""
        other = self.connections.pop(writer, None)
        for w in (writer, other):
            if w is not None:
                self.connections.pop(w, None)
                if abort:
                    w.transport.abort()
                else:
                    w.close()

    def tick(self) -> None:
        now = self.loop.time()
        if self.cut_gap is not None and now >= self.cut_gap[1]:
            self.cut_gap = None  # the outage is over: connections may come back
        gap = self.proxy.schedule.gap_at(now)
        if gap is None or gap == self.cut_gap or now - gap[0] < self.proxy.cut_after:
            return
        self.cut_gap = gap
        self.proxy._counters.cut += len(self.connections) // 2  # both ends of each are in it
        for writer in list(self.connections):
            writer.transport.abort()  # a reset, as after a real network change
        self.connections.clear()

    async def close(self) -> None:
        self.timeline.close()
        if self.server is not None:
            self.server.close()
        for writer in list(self.connections):
            writer.transport.abort()
        self.connections.clear()
        for task in list(self.tasks):
            task.cancel()
        await asyncio.gather(*self.tasks, return_exceptions=True)
        if self.server is not None:
            await self.server.wait_closed()


# --------------------------------------------------------------------------- the proxy


class NetemProxy:
    """A loopback proxy playing ``profile`` between ``listen`` and ``target`` (module doc).

    ``listen`` and ``target`` are zenoh endpoints of the same kind (udp/ or quic/; tcp/
    or tls/); ``listen`` may have port 0 (any free port: see :attr:`endpoint`). ``seed``
    makes the losses repeatable; ``cut_after``: a TCP connection is reset by an outage
    longer than this (seconds).
    """

    def __init__(
        self,
        profile: Profile | str,
        listen: str,
        target: str,
        seed: int = 0,
        *,
        cut_after: float = CUT_AFTER,
    ) -> None:
        self.profile = _profile(profile)
        self.listen = parse_endpoint(listen, listen=True)
        self.target = parse_endpoint(target)
        if self.listen.mode != self.target.mode:
            raise ConfigError(
                f"cannot relay {self.listen.scheme}/ to {self.target.scheme}/: "
                "both endpoints must be udp/ or quic/, or both tcp/ or tls/"
            )
        if not cut_after > 0:
            raise ConfigError(f"cut_after must be > 0 seconds, got {cut_after!r}")
        self.seed = seed
        self.cut_after = float(cut_after)
        #: The outage schedule of the link (both directions, every connection).
        self.schedule = OutageSchedule(self.profile.outages, seed)
        self._counters = ProxyStats()
        self._port = self.listen.port
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._relay: _UdpRelay | _TcpRelay | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None

    @property
    def mode(self) -> Literal["udp", "tcp"]:
        """``udp`` (datagrams) or ``tcp`` (byte streams)."""
        return self.listen.mode

    @property
    def endpoint(self) -> str:
        """The zenoh endpoint to connect to (the listen endpoint with its actual port)."""
        return str(Endpoint(self.listen.scheme, self.listen.host, self._port))

    @property
    def stats(self) -> ProxyStats:
        """A snapshot of the counters."""
        snapshot = ProxyStats(
            **{f.name: getattr(self._counters, f.name) for f in fields(ProxyStats)}
        )
        snapshot.up, snapshot.down = ModelStats(), ModelStats()
        for model in list(self._relay.models if self._relay is not None else []):
            total = snapshot.up if model.direction == "up" else snapshot.down
            for f in fields(ModelStats):
                setattr(total, f.name, getattr(total, f.name) + getattr(model.stats, f.name))
        return snapshot

    def __repr__(self) -> str:
        return f"<NetemProxy {self.profile.name} {self.endpoint} -> {self.target}>"

    def start(self) -> Self:
        """Listen and relay on a thread of its own; TransportError if it cannot listen."""
        if self._thread is not None:
            raise TransportError("the netem proxy was started already; make a new one")
        self._thread = threading.Thread(
            target=self._main, name=f"netem-{self.profile.name}", daemon=True
        )
        self._thread.start()
        if not self._ready.wait(_START_TIMEOUT):
            raise TransportError(f"the netem proxy did not start within {_START_TIMEOUT} s")
        if self._error is not None:
            self._thread.join(_STOP_TIMEOUT)
            raise self._error
        return self

    def close(self) -> None:
        """Stop relaying, close every socket and end the thread. Idempotent."""
        thread, loop, stop = self._thread, self._loop, self._stop
        if thread is None or not thread.is_alive():
            return
        if loop is not None and stop is not None:
            with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
                loop.call_soon_threadsafe(stop.set)
        thread.join(_STOP_TIMEOUT)

    def outage(self, seconds: float) -> None:
        """An outage of ``seconds`` starting now, both directions (module doc)."""
        if not (isinstance(seconds, int | float) and math.isfinite(seconds) and seconds >= 0):
            raise ValueError(f"outage seconds must be a number >= 0, got {seconds!r}")
        loop = self._loop
        if loop is None or self._stop is None or self._stop.is_set():
            raise TransportError("the netem proxy is not running")

        async def force() -> None:
            self.schedule.force(loop.time(), seconds)
            self._counters.outages += 1

        asyncio.run_coroutine_threadsafe(force(), loop).result(_START_TIMEOUT)

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    async def __aenter__(self) -> Self:
        return await asyncio.to_thread(self.start)

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await asyncio.to_thread(self.close)

    # -- the proxy's thread

    def _main(self) -> None:
        loop = asyncio.new_event_loop()
        try:
            loop.run_until_complete(self._serve(loop))
        except BaseException as exc:  # reported to start() if it has not returned yet
            self._error = self._error or exc
            _log.exception("netem proxy failed")
        finally:
            self._ready.set()
            loop.close()

    async def _serve(self, loop: asyncio.AbstractEventLoop) -> None:
        relay: _UdpRelay | _TcpRelay = (
            _UdpRelay(self, loop) if self.mode == "udp" else _TcpRelay(self, loop)
        )
        self._relay = relay
        try:
            self._port = await relay.open(self.listen)
        except (OSError, socket.gaierror) as exc:
            await relay.close()
            reason = os.strerror(exc.errno) if exc.errno else str(exc)
            self._error = TransportError(f"cannot listen on {self.listen}: {reason.lower()}")
            return
        self._stop = asyncio.Event()
        self._loop = loop
        self._ready.set()
        try:
            while not self._stop.is_set():
                relay.tick()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._stop.wait(), _HOUSEKEEPING)
        finally:
            await relay.close()


def _profile(value: Profile | str) -> Profile:
    return value if isinstance(value, Profile) else profile(value)
