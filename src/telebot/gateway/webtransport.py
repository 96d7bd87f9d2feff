"""The gateway's WebTransport (HTTP/3 over QUIC) listener: one more way in for a page.

A WebSocket is one TCP stream: on a lossy link one lost segment holds every byte behind it
(a stop included) for TCP's retransmission timeout. A WebTransport session carries the
same messages as the gateway's WebSocket (docs/protocol.md §26.5) without that: the
page's PUTs and the gateway's SAMPLEs each go as one QUIC datagram when they fit (lost,
never late) or on a unidirectional stream of their own (resent, but holding up nothing
else); text messages (admission, ``sub``, ``alive``, …) on the session's first
bidirectional stream, in order.

The listener (aioquic) has a certificate of its own: ECDSA P-256, valid
:data:`CERT_DAYS` days, made in memory at start and again when half its life is gone, as a
browser's ``serverCertificateHashes`` requires; the page learns its SHA-256 from the
gateway's HTTPS origin (``GET /webtransport``), so it trusts it exactly as far as the page
itself. Nothing here decides anything: a :class:`Session` is handed to the gateway, which
admits and serves it as it does a WebSocket.
"""

from __future__ import annotations

import asyncio
import base64
import collections
import contextlib
import datetime
import hashlib
import logging
import struct
import time
from collections.abc import Awaitable, Callable, Iterable
from typing import Any

from aioquic._buffer import Buffer, BufferReadError
from aioquic.asyncio.protocol import QuicConnectionProtocol
from aioquic.asyncio.server import QuicServer, serve
from aioquic.buffer import encode_uint_var
from aioquic.h3.connection import H3_ALPN, H3Connection
from aioquic.h3.events import (
    DatagramReceived,
    DataReceived,
    H3Event,
    HeadersReceived,
    WebTransportStreamDataReceived,
)
from aioquic.quic.configuration import QuicConfiguration
from aioquic.quic.congestion.base import K_MINIMUM_WINDOW, register_congestion_control
from aioquic.quic.congestion.reno import RenoCongestionControl
from aioquic.quic.events import ConnectionTerminated, ProtocolNegotiated, QuicEvent, StreamReset
from aioquic.quic.packet_builder import QuicSentPacket
from aioquic.quic.recovery import QuicPacketRecovery
from cryptography.hazmat.primitives import serialization

from telebot.errors import excerpt
from telebot.gateway.core import Refusal
from telebot.gateway.tls import server_certificate

__all__ = [
    "CERT_DAYS",
    "DATAGRAM_MAX",
    "MIN_RATE",
    "PATH",
    "PREAMBLE",
    "FloorReno",
    "Session",
    "WebTransportListener",
    "text_frame",
]

log = logging.getLogger(__name__)

#: What the browser's bidirectional stream starts with, before its first text message.
PREAMBLE = b"TBG1"
#: The session's path (the same as the WebSocket's).
PATH = b"/gateway"
#: Days a listener's certificate is valid (a browser takes a hash-pinned one of ≤ 14 days).
CERT_DAYS = 13
#: The largest message sent as one datagram; larger ones go on a stream of their own.
#: QUIC packets here are at most 1,200 bytes, less their header, tag and frame headers.
DATAGRAM_MAX = 1100
#: Messages and bytes received and not yet served, per session; beyond either the session
#: is cut (``flood``): the gateway's budget counts them as it serves them.
INBOX = 4096
INBOX_BYTES = 1_000_000
#: Unidirectional streams of a session half received at once; beyond it: ``flood``.
PARTIAL_STREAMS = 16
#: Unacknowledged bytes on the text stream beyond which the browser is too slow: closed.
TEXT_BACKLOG = 256 * 1024
#: Bytes of a session's streams handed to QUIC and not yet acknowledged, beyond which the
#: gateway's writer waits (its own bounded queues then drop the oldest data, as for a slow
#: WebSocket).
BACKLOG = 64 * 1024
#: Datagrams waiting in QUIC (its congestion window full) beyond which the oldest is dropped.
DATAGRAMS_WAITING = 64
#: Bits per second below which the gateway's QUIC does not shrink its window (:class:`FloorReno`):
#: above a page's video (about 0.6 Mbit/s), below the slowest link profile (1 Mbit/s).
MIN_RATE = 800_000
#: The close code of a browser too slow to take its text messages (as a WebSocket's 1008).
CLOSE_SLOW = 1008
#: Seconds the browser has to open its bidirectional stream after the session is accepted.
OPEN_TIMEOUT = 10.0
#: Seconds between PINGs on an idle connection (the idle timeout is three times it).
KEEPALIVE = 10.0
_CLOSE_CAPSULE = 0x2843  # CLOSE_WEBTRANSPORT_SESSION (draft-ietf-webtrans-http3)
#: The largest capsule a browser's CONNECT stream is expected to carry (its close: 1 KB).
MAX_CAPSULE = 4096


class FloorReno(RenoCongestionControl):
    """New Reno that never shrinks its window below what :data:`MIN_RATE` needs over the
    last round trip measured.

    Plain Reno halves its window at every loss: on a radio link's random loss (1–5 %) or
    across an ocean (a window regained at one packet per 0.32 s round trip), it ends far
    below the video's rate, whose pictures then arrive seconds late or not at all (the
    robot's stale-video lockout stops it). A real bottleneck below the floor shows as
    delay instead, which the robot's video follows (its receiver reports, §17.4), as a
    WebRTC sender's minimum bitrate does.
    """

    def __init__(self, *, max_datagram_size: int) -> None:
        super().__init__(max_datagram_size=max_datagram_size)
        self._minimum = self.floor = K_MINIMUM_WINDOW * max_datagram_size

    def _lift(self) -> None:
        self.congestion_window = max(self.congestion_window, self.floor)
        if self.ssthresh is not None:
            self.ssthresh = max(self.ssthresh, self.floor)

    def on_rtt_measurement(self, *, now: float, rtt: float) -> None:
        super().on_rtt_measurement(now=now, rtt=rtt)
        self.floor = max(self._minimum, int(MIN_RATE / 8 * min(rtt, 1.0)))
        self._lift()

    def on_packets_lost(self, *, now: float, packets: Iterable[QuicSentPacket]) -> None:
        super().on_packets_lost(now=now, packets=packets)
        self._lift()

    def on_persistent_congestion(self) -> None:
        super().on_persistent_congestion()
        self._lift()


register_congestion_control("telebot-floor-reno", FloorReno)

#: The longest wait (s) between two probes while nothing is acknowledged, once the probe
#: timeout has doubled up to it (RFC 9002 doubles it without bound).
MAX_PROBE_INTERVAL = 0.25


def cap_probe_backoff(recovery: QuicPacketRecovery) -> None:
    """Make ``recovery`` (a connection's loss recovery) probe at least every
    :data:`MAX_PROBE_INTERVAL` s (or its undoubled probe timeout, if longer).

    RFC 9002 doubles the probe timeout at every probe that goes unanswered. After a 3 s
    outage the next probe then comes up to as long again after the heal: the page's
    pictures (a session whose window the outage filled) came back 1.1–3.6 s after the
    network on 4G. Capped, a probe (a packet or two) goes out every 0.25 s while the
    network is gone, and the first after it returns unblocks the session. A dead browser
    still ends at the idle timeout.
    """
    probe = recovery.on_loss_detection_timeout

    def on_loss_detection_timeout(*, now: float) -> None:
        probe(now=now)
        while (
            recovery._pto_count > 0
            and recovery.get_probe_timeout() * 2**recovery._pto_count > MAX_PROBE_INTERVAL
        ):
            recovery._pto_count -= 1

    recovery.on_loss_detection_timeout = on_loss_detection_timeout  # type: ignore[method-assign]


def text_frame(text: str) -> bytes:
    """A text message on the session's bidirectional stream: ``u32 length ‖ UTF-8``."""
    data = text.encode()
    return struct.pack(">I", len(data)) + data


class Session:
    """One WebTransport session, as the gateway sees a connection.

    :meth:`receive` gives the browser's messages in arrival order: ``str`` (a text
    message of the bidirectional stream), ``bytes`` (a datagram, or a unidirectional
    stream's whole content), ``None`` once the session is closed; it raises
    :class:`Refusal` (``too_large``, ``garbage``, ``flood``) for what breaks the framing.
    """

    def __init__(self, protocol: _Protocol, session_id: int, peer: str, max_message: int) -> None:
        self._protocol = protocol
        self.session_id = session_id
        self.peer = peer
        self._max = max_message
        self._inbox: collections.deque[str | bytes | Refusal | None] = collections.deque()
        self._ready = asyncio.Event()
        self._control: int | None = None  # the browser's first bidirectional stream
        self._opened = asyncio.Event()  # set with its preamble: text can go back on it
        self._broken: Refusal | None = None  # a stream without the preamble
        self._text = bytearray()
        self._streams: dict[int, bytearray] = {}
        self._out_streams: set[int] = set()
        self._flooded = False
        self._capsule = bytearray()  # the CONNECT stream's capsules, received so far
        self._inbox_bytes = 0
        #: Datagrams and unidirectional streams are taken only once admitted (before, a
        #: browser may only answer the challenge, on the text stream).
        self.admitted = False
        self.closed = False

    # --- from the browser --------------------------------------------------------------

    def _push(self, item: str | bytes | Refusal | None) -> None:
        if (self.closed or self._flooded) and item is not None:
            return
        size = len(item) if isinstance(item, (str, bytes)) else 0
        if item is not None and (
            len(self._inbox) >= INBOX or self._inbox_bytes + size > INBOX_BYTES
        ):
            item, size = Refusal("flood", f"more than {INBOX} messages waiting"), 0
            self._flooded = True  # nothing more taken; the gateway cuts it off at this one
        self._inbox_bytes += size
        self._inbox.append(item)
        self._ready.set()

    def _ended(self) -> None:
        """The browser or its connection ended the session: :meth:`receive` says None."""
        self.closed = True
        self._opened.set()  # a sender waiting for the stream: it is over
        self._push(None)

    def _datagram(self, data: bytes) -> None:
        if self.admitted:
            self._push(data)
        else:  # only the answer to the challenge, on the text stream, before admission
            self._push(Refusal("garbage", "a datagram before admission"))

    def _stream_data(self, stream_id: int, data: bytes, ended: bool) -> None:
        if stream_id % 4 == 0:  # client-initiated bidirectional: the text stream
            if self._control is None:
                self._control = stream_id
            if stream_id != self._control:
                self._push(Refusal("garbage", "a second bidirectional stream"))
                return
            if self._broken is not None:
                return
            self._text += data
            if not self._opened.is_set():
                if len(self._text) < len(PREAMBLE):
                    return
                if self._text[: len(PREAMBLE)] != PREAMBLE:
                    self._broken = Refusal("garbage", "a stream that is not telebot's")
                    self._opened.set()  # a sender waiting for it: refused, not waiting on
                    return
                del self._text[: len(PREAMBLE)]
                self._opened.set()
            while len(self._text) >= 4:
                (length,) = struct.unpack_from(">I", self._text)
                if length > self._max:
                    self._push(Refusal("too_large", f"a text message of {length} bytes"))
                    return
                if len(self._text) < 4 + length:
                    break
                raw = bytes(self._text[4 : 4 + length])
                del self._text[: 4 + length]
                try:
                    self._push(raw.decode())
                except UnicodeDecodeError:
                    self._push(Refusal("garbage", "a text message that is not UTF-8"))
                    return
            if ended:
                self._push(None)
            return
        if not self.admitted:
            self._push(Refusal("garbage", "a stream before admission"))
            return
        buffer = self._streams.get(stream_id)
        if buffer is None:
            if len(self._streams) >= PARTIAL_STREAMS:
                self._push(Refusal("flood", f"more than {PARTIAL_STREAMS} streams at once"))
                return
            buffer = self._streams[stream_id] = bytearray()
        buffer += data
        if len(buffer) > self._max:
            self._streams.pop(stream_id, None)
            self._push(Refusal("too_large", f"a stream of more than {self._max} bytes"))
            return
        if ended:
            self._push(bytes(self._streams.pop(stream_id)))

    def _capsules(self, data: bytes) -> bool:
        """Take capsules the browser sent on the CONNECT stream; whether one closes it."""
        self._capsule += data
        while self._capsule:
            buf = Buffer(data=bytes(self._capsule))
            try:
                kind = buf.pull_uint_var()
                body = buf.pull_uint_var()
            except BufferReadError:
                return False
            if kind == _CLOSE_CAPSULE:
                return True
            if body > MAX_CAPSULE:  # nothing of ours is that large: not a browser's
                return True
            if buf.capacity - buf.tell() < body:
                return False
            del self._capsule[: buf.tell() + body]
        return False

    async def receive(self) -> str | bytes | None:
        """The next message (see the class), waiting for it."""
        while not self._inbox:
            self._ready.clear()
            await self._ready.wait()
        item = self._inbox.popleft()
        if isinstance(item, (str, bytes)):
            self._inbox_bytes -= len(item)
        if isinstance(item, Refusal):
            raise item
        if item is None:
            self._inbox.appendleft(None)  # closed for good: every later call says so
        return item

    # --- to the browser ----------------------------------------------------------------

    def backlog(self) -> int:
        """Bytes of this session's streams handed to QUIC and not yet acknowledged."""
        quic = self._protocol._quic
        pending = 0
        for stream_id in list(self._out_streams):
            stream = quic._streams.get(stream_id)
            if stream is None or stream.sender.is_finished:
                self._out_streams.discard(stream_id)
                continue
            sender = stream.sender
            pending += sender._buffer_stop - sender._buffer_start
        return pending

    def has_room(self, item: str | bytes) -> bool:
        """Whether data ``item`` goes now (the gateway asks for data only): a datagram while
        QUIC holds fewer than half :data:`DATAGRAMS_WAITING` (the rest is control's), a
        stream message while less than :data:`BACKLOG` of this session's streams is
        unacknowledged."""
        if isinstance(item, str):
            return True
        if len(item) <= DATAGRAM_MAX:  # data datagrams leave half the queue to control ones
            return len(self._protocol._quic._datagrams_pending) < DATAGRAMS_WAITING // 2
        return self.backlog() <= BACKLOG

    async def send_text(self, text: str) -> None:
        """A text message on the bidirectional stream (in order, reliable); raises
        :class:`Refusal` when the browser opened none in time, or one not telebot's."""
        if not self._opened.is_set():  # the browser opens the stream (and speaks) first
            try:
                await asyncio.wait_for(self._opened.wait(), OPEN_TIMEOUT)
            except TimeoutError:
                self._broken = Refusal("timeout", "no stream opened in time")
        if self._broken is not None:
            raise self._broken
        if self.closed or self._control is None:
            raise ConnectionError("the WebTransport session is closed")
        quic = self._protocol._quic
        stream = quic._streams.get(self._control)
        if stream is not None and (
            stream.sender._buffer_stop - stream.sender._buffer_start > TEXT_BACKLOG
        ):  # a browser that takes nothing: its queue stops here, and so does it
            await self.close(CLOSE_SLOW, "slow")
            raise ConnectionError("the browser takes no more text")
        try:
            quic.send_stream_data(self._control, text_frame(text))
        except ValueError as exc:  # the stream ended meanwhile
            raise ConnectionError(str(exc)) from None
        self._protocol.transmit()

    async def send_bytes(self, data: bytes) -> None:
        """One message: a datagram if it fits (QUIC sends datagrams ahead of streams, so a
        heartbeat passes the pictures; the oldest dropped beyond :data:`DATAGRAMS_WAITING`),
        else a unidirectional stream of its own (the gateway sends those only while
        :meth:`has_room`)."""
        if self.closed:
            raise ConnectionError("the WebTransport session is closed")
        protocol = self._protocol
        try:
            if len(data) <= DATAGRAM_MAX:
                waiting = protocol._quic._datagrams_pending
                while len(waiting) >= DATAGRAMS_WAITING:
                    waiting.popleft()  # stale by now: newer ones say more
                protocol._http.send_datagram(self.session_id, data)
            else:
                stream_id = protocol._http.create_webtransport_stream(
                    self.session_id, is_unidirectional=True
                )
                protocol._quic.send_stream_data(stream_id, data, end_stream=True)
                self._out_streams.add(stream_id)
        except ValueError as exc:  # the connection is closing
            raise ConnectionError(str(exc)) from None
        protocol.transmit()

    async def close(self, code: int = 0, reason: str = "") -> None:
        """End the session with ``code`` and ``reason`` (the browser's ``closed`` gets
        them), then the connection a moment later; idempotent."""
        if self.closed and self._protocol._ended:
            return
        self.closed = True
        self._push(None)
        protocol = self._protocol
        with contextlib.suppress(Exception):
            body = struct.pack(">I", code) + reason[:200].encode()
            capsule = encode_uint_var(_CLOSE_CAPSULE) + encode_uint_var(len(body)) + body
            protocol._http.send_data(self.session_id, capsule, end_stream=True)
            protocol.transmit()
        protocol.end_soon()


class _Protocol(QuicConnectionProtocol):
    """One QUIC connection: HTTP/3 with WebTransport, one session at most."""

    def __init__(self, *args: Any, listener: WebTransportListener, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        cap_probe_backoff(self._quic._loss)
        self._listener = listener
        self._http: H3Connection = None  # type: ignore[assignment]  # set when negotiated
        self._session: Session | None = None
        self._ended = False
        self._keepalive: asyncio.TimerHandle | None = None

    def quic_event_received(self, event: QuicEvent) -> None:
        if isinstance(event, ProtocolNegotiated):
            self._http = H3Connection(self._quic, enable_webtransport=True)
            # A connection that opens no session in time is closed (it holds state here).
            asyncio.get_running_loop().call_later(OPEN_TIMEOUT, self._no_session)
        elif isinstance(event, StreamReset) and self._session is not None:
            # HTTP/3 says nothing of a reset: what the stream brought so far is dropped here.
            self._session._streams.pop(event.stream_id, None)
        elif isinstance(event, ConnectionTerminated):
            self._ended = True
            if self._keepalive is not None:
                self._keepalive.cancel()
            if self._session is not None:
                self._session._ended()
            return
        if self._http is None:
            return
        try:
            events = self._http.handle_event(event)
        except Exception as exc:  # a peer breaking HTTP/3: its connection ends, not ours
            log.info("gateway: WebTransport: %s", exc)
            self._quic.close(error_code=0x101, reason_phrase="bad HTTP/3")
            self.transmit()
            return
        for h3_event in events:
            self._h3(h3_event)

    def _h3(self, event: H3Event) -> None:
        session = self._session
        if isinstance(event, HeadersReceived):
            headers = dict(event.headers)
            webtransport = (
                headers.get(b":method") == b"CONNECT"
                and headers.get(b":protocol") == b"webtransport"
            )
            if not webtransport or headers.get(b":path", b"").split(b"?")[0] != PATH:
                self._answer(event.stream_id, 404)
            elif session is not None:
                self._answer(event.stream_id, 429)  # one session a connection
            else:
                self._accept(event.stream_id)
        elif session is None:
            return
        elif isinstance(event, DatagramReceived):
            if event.stream_id == session.session_id:
                session._datagram(event.data)
        elif (
            isinstance(event, WebTransportStreamDataReceived)
            and event.session_id == session.session_id
        ):
            session._stream_data(event.stream_id, event.data, event.stream_ended)
        elif (
            isinstance(event, DataReceived)
            and event.stream_id == session.session_id
            and (session._capsules(event.data) or event.stream_ended)
        ):  # the browser's side of the CONNECT stream: capsules (its flow control, not
            # ours to follow), its close capsule, or its end
            session._ended()
            self.end_soon()

    def _no_session(self) -> None:
        if self._session is None and not self._ended:
            self._quic.close(error_code=0x10C, reason_phrase="no session")  # H3_REQUEST_CANCELLED
            self.transmit()

    def _answer(self, stream_id: int, status: int) -> None:
        self._http.send_headers(stream_id, [(b":status", str(status).encode())], end_stream=True)
        self.transmit()

    def _accept(self, stream_id: int) -> None:
        # The server's one UDP socket has no peer: the connection's current path has it.
        paths = self._quic._network_paths
        address = str(paths[0].addr[0]) if paths else "?"
        session = Session(self, stream_id, address, self._listener.max_message)
        if self._listener.admits(session) is not None:
            self._answer(stream_id, 503)
            self.end_soon()
            return
        self._session = session
        self._ping()
        self._http.send_headers(
            stream_id, [(b":status", b"200"), (b"sec-webtransport-http3-draft", b"draft02")]
        )
        self.transmit()
        self._listener.spawn(self._session)

    def _ping(self) -> None:
        if self._ended:
            return
        self._quic.send_ping(int(time.monotonic() * 1000))
        self.transmit()
        loop = asyncio.get_running_loop()
        self._keepalive = loop.call_later(KEEPALIVE, self._ping)

    def end_soon(self, delay: float = 1.0) -> None:
        """Close the connection after ``delay`` s (the close capsule on its way first)."""

        def end() -> None:
            if not self._ended:
                self._quic.close(error_code=0)
                self.transmit()

        asyncio.get_running_loop().call_later(delay, end)


class WebTransportListener:
    """HTTP/3 WebTransport at ``https://HOST:PORT/gateway`` over UDP.

    ``admits(session)`` decides before a session is accepted (None: yes; else a one-line
    reason, answered HTTP 503); ``serve_session(session)`` then runs for each accepted one.
    """

    def __init__(
        self,
        host: str,
        port: int,
        *,
        admits: Callable[[Session], str | None],
        serve_session: Callable[[Session], Awaitable[None]],
        max_message: int,
        clock: Callable[[], datetime.datetime] = lambda: datetime.datetime.now(datetime.UTC),
    ) -> None:
        self.host = host
        self.port = port
        self.admits = admits
        self._serve = serve_session
        self.max_message = max_message
        self._clock = clock
        self._server: QuicServer | None = None
        self._configuration = QuicConfiguration(
            alpn_protocols=H3_ALPN,
            is_client=False,
            max_datagram_frame_size=65536,
            idle_timeout=3 * KEEPALIVE,
            congestion_control_algorithm="telebot-floor-reno",
        )
        self._made = self._clock()
        self._rotate(force=True)
        self._tasks: set[asyncio.Task[None]] = set()

    def _rotate(self, force: bool = False) -> None:
        now = self._clock()
        if not force and now - self._made < datetime.timedelta(days=CERT_DAYS / 2):
            return
        # Chromium takes no certificate without a subject alternative name, even one pinned
        # by its hash (whose names it does not check against the address).
        cert, key = server_certificate(
            "telebot gateway", ["localhost"], datetime.timedelta(days=CERT_DAYS)
        )
        self._made = now
        self._configuration.certificate = cert
        self._configuration.private_key = key
        der = cert.public_bytes(serialization.Encoding.DER)
        self._hash = hashlib.sha256(der).digest()

    def offer(self) -> dict[str, Any]:
        """What a page needs to open a session: ``{"port": P, "path": "/gateway",
        "hashes": [<the certificate's SHA-256, base64>]}`` (a new certificate once the
        current one is half through its life)."""
        self._rotate()
        return {
            "port": self.port,
            "path": PATH.decode(),
            "hashes": [base64.b64encode(self._hash).decode()],
        }

    async def start(self) -> None:
        """Listen (OSError if the UDP port is taken)."""

        def protocol(*args: Any, **kwargs: Any) -> _Protocol:
            return _Protocol(*args, listener=self, **kwargs)

        self._server = await serve(
            self.host, self.port, configuration=self._configuration, create_protocol=protocol
        )
        if self.port == 0:
            transport = self._server._transport
            assert transport is not None
            self.port = int(transport.get_extra_info("sockname")[1])

    def spawn(self, session: Session) -> None:
        task = asyncio.create_task(self._run(session), name=f"webtransport {session.peer}")
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _run(self, session: Session) -> None:
        try:
            await self._serve(session)
        except Exception as exc:  # never the listener's end because one session failed
            log.warning("gateway: a WebTransport session failed: %s", excerpt(repr(exc)))
        finally:
            await session.close(1000, "")

    async def close(self) -> None:
        """Stop listening and end every session."""
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            with contextlib.suppress(BaseException):
                await task
        if self._server is not None:
            server, self._server = self._server, None
            server.close()
