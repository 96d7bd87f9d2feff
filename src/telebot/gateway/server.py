"""The gateway's I/O: HTTPS + WebSocket (aiohttp) on one side, one transport on the other.

One :class:`Gateway` holds one transport (the robot daemon's own zenoh session, or the
router's) and relays for many websockets at ``/gateway``; it also serves the web app's
static files (``/`` is ``static/gateway.html``, ``/call`` ``static/index.html``) and its counters at ``/stats`` (JSON).
Every decision is :mod:`telebot.gateway.core`'s; this module only moves bytes:

- admission: send the challenge, wait (bounded) for the answer, ask the core and the
  :class:`~telebot.gateway.admission.Admitter`, answer ``admitted`` or ``refused`` + 4001;
- every :data:`RECHECK` seconds, when the admitter's files changed, each open connection
  whose name no longer holds its key (removed, revoked, another key) is cut (``revoked``);
- then each message is counted against the connection's budget and parsed; a key the
  user may not use, garbage, or a flood ends the connection (``cut`` + 4008), counted and
  logged in one line, before anything of that message is forwarded;
- towards the browser, samples and presence changes go through two bounded queues per
  connection (:class:`~telebot.gateway.core.OutQueue`: control frames first, the oldest of
  a kind dropped and counted), so a slow browser only loses its own, and data first;
- connections are bounded in all, per source address before admission (HTTP 503 before
  the websocket is accepted) and per admitted name (refused ``too_many``), and the TLS
  handshake by :attr:`Limits.tls_handshake_timeout`.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import json
import logging
import os
import ssl
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Protocol, Self

from aiohttp import WSMsgType, web

from telebot.channels.transports.base import (
    Lane,
    Presence,
    Publisher,
    ReceiveLimits,
    Sample,
    Subscription,
    Transport,
)
from telebot.errors import ConfigError, TransportError, excerpt
from telebot.gateway.admission import Admitter
from telebot.gateway.core import (
    CLOSE_CUT,
    CLOSE_REFUSED,
    MAX_KEY_BYTES,
    MAX_PAYLOAD,
    Budget,
    CopyFilter,
    KeyRules,
    Limits,
    Op,
    OutQueue,
    Refusal,
    make_challenge,
    parse_admission,
    parse_op,
    parse_put,
    sample_header,
)
from telebot.gateway.webtransport import Session, WebTransportListener

__all__ = ["STATIC", "Gateway", "GatewayStats"]

log = logging.getLogger(__name__)

#: The web app's files (``telebot.apps.web``'s, found by path: the gateway sits below the apps).
STATIC = Path(__file__).resolve().parent.parent / "apps" / "web" / "static"
#: Larger websocket messages are refused by aiohttp itself (close 1009), and counted.
MAX_MESSAGE = 3 + MAX_KEY_BYTES + MAX_PAYLOAD + 1024
#: Publishers kept per connection (by key and lane), the least recently used closed first.
MAX_PUBLISHERS = 32
#: SAMPLE headers kept per connection (by sub id and key); all are dropped beyond it.
MAX_HEADERS = 256
_LANES = {"control": Lane.CONTROL, "data": Lane.DATA, "bulk": Lane.BULK}
_RECEIVE = ReceiveLimits(max_samples=512, max_bytes=4_000_000, max_payload=MAX_PAYLOAD)
#: How often (seconds) the writer looks again whether a connection has room for data.
ROOM_POLL = 0.01
#: How often (seconds) open connections are checked against the admitter's files, if changed.
RECHECK = 5.0


@dataclass(slots=True)
class GatewayStats:
    """What the gateway counted (``/stats``)."""

    connections: int = 0
    admitted: int = 0
    active: int = 0
    refused: dict[str, int] = field(default_factory=dict)
    cut: dict[str, int] = field(default_factory=dict)
    frames_in: int = 0
    bytes_in: int = 0
    published: int = 0
    frames_out: int = 0
    bytes_out: int = 0
    dropped_out: int = 0
    dropped_control: int = 0
    #: PUTs not published: a copy of one that came first on another WebSocket (§26.2).
    duplicates: int = 0

    def count(self, table: dict[str, int], code: str) -> None:
        """One more ``code`` in ``refused`` or ``cut``."""
        table[code] = table.get(code, 0) + 1


class Gateway:
    """``async with Gateway(transport, admitter, ...) as gw:`` serves until closed.

    ``ssl_context`` None serves plain HTTP, allowed on a loopback host only (tests).
    ``port`` 0 picks a free port (see :attr:`url`). ``webtransport`` also serves the
    gateway over HTTP/3 WebTransport on UDP (docs/protocol.md §26.5; ``GET /webtransport``
    tells a page where).
    """

    def __init__(
        self,
        transport: Transport,
        admitter: Admitter,
        *,
        namespace: str = "telebot",
        host: str = "127.0.0.1",
        port: int = 8443,
        ssl_context: ssl.SSLContext | None = None,
        limits: Limits | None = None,
        static: Path = STATIC,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
        recheck: float = RECHECK,
        webtransport: bool = True,
    ) -> None:
        if ssl_context is None and host not in ("127.0.0.1", "::1", "localhost"):
            raise ValueError(f"the gateway serves plain HTTP on loopback only, not on {host}")
        self.transport = transport
        self.admitter = admitter
        self.namespace = namespace
        self.host = host
        self.port = port
        self.ssl_context = ssl_context
        self.limits = limits or Limits()
        self.static = static
        self.clock = clock
        self.wall_clock = wall_clock
        self.recheck = recheck
        self.webtransport = webtransport
        #: The WebTransport listener once started (UDP, the same port number as HTTPS,
        #: or any free one when ``port`` is 0), None when off or its port was taken.
        self.listener: WebTransportListener | None = None
        self.stats = GatewayStats()
        self._browsers: set[_Browser] = set()
        self._runner: web.AppRunner | None = None
        #: Websockets being served (admitted or not), not yet admitted ones by source
        #: address, admitted ones (and admissions being answered) by name.
        self._sockets: set[_Socket] = set()
        self._pending: dict[str, int] = {}
        self._names: dict[str, int] = {}
        #: Per admitted name, the copy ids of its recent copied PUTs (§26.2).
        self._copies: dict[str, CopyFilter] = {}
        self._rechecking: asyncio.Task[None] | None = None
        self._cutting: set[asyncio.Task[None]] = set()

    @property
    def url(self) -> str:
        """The page's address (``https://HOST:PORT/``)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        scheme = "https" if self.ssl_context is not None else "http"
        return f"{scheme}://{host}:{self.port}/"

    async def start(self) -> None:
        """Listen (OSError if the address is taken)."""
        requested = self.port
        app = web.Application()
        app.router.add_get("/", self._page("gateway.html"))
        app.router.add_get("/call", self._page("index.html"))
        app.router.add_get("/gateway", self._websocket)
        app.router.add_get("/stats", self._stats)
        app.router.add_get("/webtransport", self._offer)
        if self.static.is_dir():
            app.router.add_static("/static/", self.static, show_index=False)
        self._runner = web.AppRunner(app, handle_signals=False, access_log=None)
        await self._runner.setup()
        site = _Site(
            self._runner,
            self.host,
            self.port,
            ssl_context=self.ssl_context,
            handshake_timeout=self.limits.tls_handshake_timeout,
        )
        try:
            await site.start()
        except OSError:
            await self._runner.cleanup()
            self._runner = None
            raise
        if self.port == 0:
            sockets = getattr(site._server, "sockets", None) or []
            self.port = int(sockets[0].getsockname()[1])
        if self.webtransport:
            await self._listen_webtransport(0 if requested == 0 else self.port)
        self._rechecking = asyncio.create_task(self._recheck(), name="gateway recheck")
        log.info("browser gateway at %s", self.url)

    async def _listen_webtransport(self, port: int) -> None:
        listener = WebTransportListener(
            self.host,
            port,
            admits=lambda session: self._enter(session, session.peer),
            serve_session=self._webtransport,
            max_message=MAX_MESSAGE,
        )
        try:
            await listener.start()
        except OSError as exc:  # pages fall back to WebSockets: worse on a lossy link, not broken
            log.warning("gateway: no WebTransport (UDP port %d: %s)", port, exc.strerror or exc)
            return
        self.listener = listener
        log.info("browser gateway: WebTransport on UDP port %d", listener.port)

    async def close(self) -> None:
        """Close every websocket and the server; idempotent."""
        if self._rechecking is not None:
            self._rechecking.cancel()
            self._rechecking = None
        for task in list(self._cutting):
            task.cancel()
        for sock in list(self._sockets):  # admitted or still being challenged
            with contextlib.suppress(Exception):
                await sock.close(1001, "gateway shutting down")
        if self.listener is not None:
            listener, self.listener = self.listener, None
            await listener.close()
        if self._runner is not None:
            runner, self._runner = self._runner, None
            await runner.cleanup()

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

    def stats_json(self) -> dict[str, Any]:
        """The counters as JSON-ready data."""
        return asdict(self.stats)

    # --- HTTP ---------------------------------------------------------------------------

    def _page(self, name: str) -> Callable[[web.Request], Awaitable[web.StreamResponse]]:
        """A handler serving ``static/NAME`` (``/``: the start page, ``/call?robot=R``: the
        robot page, which calls R through this gateway)."""

        async def serve(request: web.Request) -> web.StreamResponse:
            page = self.static / name
            if page.is_file():
                return web.FileResponse(page, headers={"Cache-Control": "no-cache"})
            return web.Response(status=404, text=f"telebot gateway: {name} is not installed\n")

        return serve

    async def _stats(self, request: web.Request) -> web.StreamResponse:
        return web.json_response(self.stats_json())

    async def _offer(self, request: web.Request) -> web.StreamResponse:
        """Where and with which certificate a page opens a WebTransport session (§26.5)."""
        if self.listener is None:
            return web.json_response({"error": "this gateway serves no WebTransport"}, status=404)
        return web.json_response(self.listener.offer(), headers={"Cache-Control": "no-store"})

    async def _websocket(self, request: web.Request) -> web.StreamResponse:
        peer = str(request.remote)
        # No permessage-deflate: the frames are sealed (ciphertext does not compress), so
        # deflating them only burns CPU on both ends, 30 pictures a second.
        ws = web.WebSocketResponse(max_msg_size=MAX_MESSAGE, heartbeat=30.0, compress=False)
        sock = _WebSocket(ws)
        # Checked and counted before the websocket is accepted, before any await.
        busy = self._enter(sock, peer)
        if busy is not None:
            return web.Response(status=503, text=f"telebot gateway: {busy}\n")
        try:
            await ws.prepare(request)
        except BaseException:
            self._leave(sock, peer, pending=True)
            raise
        await self._serve(sock, peer)
        return ws

    async def _webtransport(self, session: Session) -> None:
        await self._serve(session, session.peer)

    def _enter(self, sock: _Socket, peer: str) -> str | None:
        """Count a new connection from ``peer``, or say (one line, counted) why not."""
        limits = self.limits
        if len(self._sockets) >= limits.max_connections:
            return self._busy("full", f"the gateway serves {limits.max_connections} connections")
        if self._pending.get(peer, 0) >= limits.max_pending_per_address:
            return self._busy(
                "busy",
                f"{peer} has {limits.max_pending_per_address} connections not yet admitted",
            )
        self._sockets.add(sock)
        self._pending[peer] = self._pending.get(peer, 0) + 1
        return None

    def _leave(self, sock: _Socket, peer: str, *, pending: bool) -> None:
        self._sockets.discard(sock)
        if pending:
            self._release_pending(peer)

    async def _serve(self, sock: _Socket, peer: str) -> None:
        """Admit a connection counted by :meth:`_enter`, then relay for it until it ends."""
        pending, name = True, None
        try:
            self.stats.connections += 1
            admitted = await self._admit(sock, peer)  # its name counted in _names if admitted
            pending = False
            self._release_pending(peer)
            if admitted is None:
                return
            name, key = admitted
            browser = _Browser(self, sock, name, peer, key)
            self._browsers.add(browser)
            self.stats.admitted += 1
            self.stats.active += 1
            try:
                await browser.serve()
            finally:
                self._browsers.discard(browser)
                self.stats.active -= 1
                browser.release()
        finally:
            self._leave(sock, peer, pending=pending)
            if name is not None:
                self._release_name(name)

    def _busy(self, code: str, text: str) -> str:
        self.stats.count(self.stats.refused, code)
        log.info("gateway: refused a connection: %s", text)
        return text

    def _release_pending(self, peer: str) -> None:
        left = self._pending.get(peer, 0) - 1
        if left > 0:
            self._pending[peer] = left
        else:
            self._pending.pop(peer, None)

    def _release_name(self, name: str) -> None:
        left = self._names.get(name, 0) - 1
        if left > 0:
            self._names[name] = left
        else:
            self._names.pop(name, None)
            self._copies.pop(name, None)

    def copies(self, name: str) -> CopyFilter:
        """The copy ids of ``name``'s recent copied PUTs (§26.2), across its WebSockets."""
        copies = self._copies.get(name)
        if copies is None:
            copies = self._copies[name] = CopyFilter()
        return copies

    # --- admission ----------------------------------------------------------------------

    async def _admit(self, sock: _Socket, peer: str) -> tuple[str, bytes] | None:
        challenge = make_challenge(os.urandom(32), os.urandom(32))
        try:
            await sock.send_text(json.dumps(challenge.message(self.namespace)))
            try:
                answer = await asyncio.wait_for(sock.receive(), self.limits.admission_timeout)
            except TimeoutError:
                raise Refusal("timeout", "no answer to the challenge in time") from None
            if answer is None:
                return None
            admit = parse_admission(answer)
            if not challenge.verify(admit.name, admit.key, admit.proof):
                raise Refusal("bad_proof", f"the proof for {admit.name} does not verify")
            # After the proof: only the key's holder can use up its name's connections.
            if self._names.get(admit.name, 0) >= self.limits.max_per_name:
                raise Refusal(
                    "too_many",
                    f"{admit.name} has {self.limits.max_per_name} connections here already",
                )
            try:
                if admit.invite is not None:
                    self.admitter.redeem(admit.invite, admit.name, admit.key, self.wall_clock())
                    log.info("gateway: invite redeemed by %s from %s", admit.name, peer)
                else:
                    known = self.admitter.key_of(admit.name)
                    if known is None:
                        raise Refusal("unknown_name", f"{admit.name} is not admitted here")
                    if known != admit.key:
                        raise Refusal("wrong_key", f"{admit.name} is admitted with another key")
            except (ConfigError, OSError) as exc:  # the gateway's files: its trouble, said once
                text = "the gateway cannot read or write its lists (its log says why)"
                raise Refusal("gateway_error", text) from exc
            self._names[admit.name] = self._names.get(admit.name, 0) + 1
            sock.admitted = True  # from now on its PUTs are taken, whatever way they come
            try:
                await sock.send_text(json.dumps({"op": "admitted", "name": admit.name}))
            except BaseException:
                self._release_name(admit.name)
                raise
            return admit.name, admit.key
        except Refusal as refusal:
            self.stats.count(self.stats.refused, refusal.code)
            if isinstance(refusal.__cause__, (ConfigError, OSError)):
                log.warning(
                    "gateway: refused %s: %s: %s",
                    peer,
                    refusal.code,
                    excerpt(str(refusal.__cause__)),
                )
            else:
                log.info("gateway: refused %s: %s", peer, excerpt(str(refusal)))
            with contextlib.suppress(Exception):
                await sock.send_text(
                    json.dumps({"op": "refused", "code": refusal.code, "text": refusal.text})
                )
            with contextlib.suppress(Exception):
                await sock.close(CLOSE_REFUSED, refusal.code)
            return None
        except (ConnectionError, RuntimeError):  # the browser went away mid-admission
            return None

    # --- re-checking open connections ---------------------------------------------------

    async def _recheck(self) -> None:
        """Cut each open connection whose name no longer holds its key: checked when the
        admitter's files changed since that connection was last checked (or never was)."""
        while True:
            await asyncio.sleep(self.recheck)
            stamp = self.admitter.stamp()  # before reading: a later change is seen next time
            keys: dict[str, bytes | None] = {}
            for browser in list(self._browsers):
                if browser.stamp == stamp or browser._cut:
                    continue
                browser.stamp = stamp
                if browser.name not in keys:
                    try:
                        keys[browser.name] = self.admitter.key_of(browser.name)
                    except (Refusal, ConfigError, OSError, ValueError):  # fails closed
                        keys[browser.name] = None
                if keys[browser.name] != browser.key:
                    # Cut from this task while the browser's own waits on its websocket:
                    # aiohttp then closes the TCP connection right after the close frame.
                    refusal = Refusal("revoked", f"{browser.name} is no longer admitted here")
                    task = asyncio.create_task(browser._cut_off(refusal))
                    self._cutting.add(task)
                    task.add_done_callback(self._cutting.discard)


class _Socket(Protocol):
    """A connection as the gateway serves it: a WebSocket or a WebTransport session.

    ``receive`` gives a text message (``str``), a binary one (``bytes``) or None once
    closed, and raises :class:`Refusal` for what the connection's own layer refused.
    ``has_room`` says whether a data item would go now rather than wait behind others, so
    control items are not held up behind it in the sender (§26.5). ``admitted`` is set
    once the gateway admits it (before, a WebTransport session takes text only).
    """

    admitted: bool

    async def receive(self) -> str | bytes | None: ...
    def has_room(self, item: str | bytes) -> bool: ...
    async def send_text(self, text: str) -> None: ...
    async def send_bytes(self, data: bytes) -> None: ...
    async def close(self, code: int, reason: str) -> None: ...


class _WebSocket:
    """aiohttp's websocket as a :class:`_Socket`."""

    def __init__(self, ws: web.WebSocketResponse) -> None:
        self.ws = ws
        self.admitted = False

    async def receive(self) -> str | bytes | None:
        while True:
            msg = await self.ws.receive()
            kind = msg.type
            if kind is WSMsgType.BINARY or kind is WSMsgType.TEXT:
                data: str | bytes = msg.data
                return data
            if kind is WSMsgType.ERROR:
                raise Refusal("too_large", f"a message the websocket refused: {msg.data}")
            if kind in (WSMsgType.CLOSE, WSMsgType.CLOSING, WSMsgType.CLOSED):
                return None

    def has_room(self, item: str | bytes) -> bool:
        return True  # one TCP stream: aiohttp's send waits for its drain itself

    async def send_text(self, text: str) -> None:
        await self.ws.send_str(text)

    async def send_bytes(self, data: bytes) -> None:
        await self.ws.send_bytes(data)

    async def close(self, code: int, reason: str) -> None:
        await self.ws.close(code=code, message=reason.encode())


class _Browser:
    """One admitted connection: its budget, subscriptions, tokens, watches, out queue."""

    def __init__(self, gateway: Gateway, sock: _Socket, name: str, peer: str, key: bytes) -> None:
        self.gateway = gateway
        self.sock = sock
        self.name = name
        self.peer = peer
        self.key = key
        #: The admitter's stamp when last re-checked (never yet: matches no stamp).
        self.stamp: object = object()
        self.rules = KeyRules(gateway.namespace, name)
        self.budget = Budget.of(gateway.limits)
        self.subs: dict[int, Subscription] = {}
        self.sub_keys: dict[int, str] = {}
        self.tokens: dict[int, Presence] = {}
        self.watches: dict[int, Subscription] = {}
        self.publishers: collections.OrderedDict[tuple[str, str], Publisher] = (
            collections.OrderedDict()
        )
        # SAMPLE header and whether the key is a call's control key, by (sub id, key).
        self._headers: dict[tuple[int, str], tuple[bytes, bool]] = {}
        self._out = OutQueue(gateway.limits)
        # The writer's wake-up while it waits for something to send (one future per wait,
        # cheaper than an Event's set/clear/wait for every frame).
        self._waiting: asyncio.Future[None] | None = None
        self._cut = False

    async def serve(self) -> None:
        """Relay until the browser closes or is cut off."""
        writer = asyncio.create_task(self._write(), name=f"gateway writer {self.name}")
        stats, spend, clock = self.gateway.stats, self.budget.spend, self.gateway.clock
        receive = self.sock.receive
        try:
            while (data := await receive()) is not None:
                if self._cut:  # cut off from outside (revoked): nothing more goes anywhere
                    break
                size = len(data)
                stats.frames_in += 1
                stats.bytes_in += size
                spend(size, clock())
                if isinstance(data, bytes):
                    self._put(data)
                else:
                    self._handle(parse_op(data))
        except Refusal as refusal:
            await self._cut_off(refusal)
        finally:
            writer.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await writer

    # --- browser -> zenoh ----------------------------------------------------------------

    def _put(self, data: bytes) -> None:
        put = parse_put(data)
        slot = (put.key, put.lane)
        publisher = self.publishers.get(slot)
        if publisher is None:
            # The rules are checked here only: a publisher is kept for a key they allowed,
            # and they do not change during a connection, so a kept one needs no second look.
            if not self.rules.may_put(put.key):
                raise Refusal("key", f"{self.name} may not publish on {excerpt(put.key, 120)}")
            try:
                publisher = self.gateway.transport.publisher(put.key, _LANES[put.lane])
            except TransportError as exc:  # the gateway's session, not the browser's fault
                self._send_text({"op": "error", "code": "zenoh", "text": excerpt(str(exc))})
                return
            self.publishers[slot] = publisher
            if len(self.publishers) > MAX_PUBLISHERS:
                _, oldest = self.publishers.popitem(last=False)
                oldest.close()
        else:
            self.publishers.move_to_end(slot)
        copy, copies = put.copy, None
        if copy is not None:
            copies = self.gateway.copies(self.name)
            if not copies.first(copy):
                self.gateway.stats.duplicates += 1  # its twin came first on the other WebSocket
                return
        try:
            publisher.put(put.payload)
        except TransportError as exc:
            log.debug("gateway: put on %s failed: %s", put.key, exc)
            if copies is not None and copy is not None:
                copies.forget(copy)  # not published: its twin may still be
            return
        self.gateway.stats.published += 1

    def _handle(self, op: Op) -> None:
        limits = self.gateway.limits
        key = op.key or ""
        transport = self.gateway.transport
        if op.key is not None:  # sub, token, watch: a zenoh declaration each
            self.budget.declare(self.gateway.clock())
        match op.op:
            case "sub":
                self._check(key, self.rules.may_subscribe, "subscribe to")
                if self._taken(op, self.subs, limits.max_subscriptions, "subscriptions"):
                    return
                sub_id = op.id
                held = next((i for i, k in self.sub_keys.items() if k == key), None)
                if held is not None:  # the same samples twice would only double the traffic
                    self._send_text(
                        {
                            "op": "error",
                            "code": "duplicate",
                            "text": f"sub {sub_id}: {excerpt(key, 120)} is subscribed as {held}",
                        }
                    )
                    return
                self._declare(
                    self.subs,
                    op,
                    lambda: transport.subscribe(
                        key, lambda batch: self._samples(sub_id, batch), limits=_RECEIVE
                    ),
                )
                if sub_id in self.subs:
                    self.sub_keys[sub_id] = key
            case "token":
                self._check(key, self.rules.may_declare_token, "declare the token")
                if self._taken(op, self.tokens, limits.max_tokens, "tokens"):
                    return
                self._declare(self.tokens, op, lambda: transport.declare_presence(key))
            case "watch":
                self._check(key, self.rules.may_watch, "watch")
                if self._taken(op, self.watches, limits.max_watches, "watches"):
                    return
                watch_id = op.id
                self._declare(
                    self.watches,
                    op,
                    lambda: transport.watch_presence(
                        key, lambda k, alive: self._alive(watch_id, k, alive)
                    ),
                )
            case "unsub" | "untoken" | "unwatch":
                tables: dict[str, dict[int, Any]] = {
                    "unsub": self.subs,
                    "untoken": self.tokens,
                    "unwatch": self.watches,
                }
                table = tables[op.op]
                entity = table.pop(op.id, None)
                if op.op == "unsub":
                    self.sub_keys.pop(op.id, None)
                if entity is None:
                    self._send_text(
                        {"op": "error", "code": "unknown_id", "text": f"{op.op} {op.id}"}
                    )
                else:
                    entity.close()

    def _check(self, key: str, rule: Callable[[str], bool], what: str) -> None:
        if not rule(key):
            raise Refusal("key", f"{self.name} may not {what} {excerpt(key, 120)}")

    def _taken(self, op: Op, table: dict[int, Any], most: int, what: str) -> bool:
        if op.id in table:
            self._send_text({"op": "error", "code": "id_in_use", "text": f"{op.op} {op.id}"})
            return True
        if len(table) >= most:
            raise Refusal("too_many", f"more than {most} {what}")
        return False

    def _declare(self, table: dict[int, Any], op: Op, declare: Callable[[], Any]) -> None:
        try:
            table[op.id] = declare()
        except TransportError as exc:
            # The rules let only plain keys through, so zenoh refusing one is the gateway's
            # trouble (its session closing), not the browser's: an error, not a cut.
            self._send_text({"op": "error", "code": "zenoh", "text": excerpt(str(exc))})

    # --- zenoh -> browser ----------------------------------------------------------------

    def _samples(self, sub_id: int, batch: Sequence[Sample]) -> None:
        if sub_id not in self.subs:
            return
        headers = self._headers
        for sample in batch:
            slot = (sub_id, sample.key)
            known = headers.get(slot)
            if known is None:
                if len(headers) >= MAX_HEADERS:
                    headers.clear()
                known = headers[slot] = (
                    sample_header(sub_id, sample.key),
                    sample.key.endswith("/ctl"),
                )
            self._enqueue(known[0] + sample.payload, known[1])

    def _alive(self, watch_id: int, key: str, alive: bool) -> None:
        if watch_id in self.watches:
            self._send_text({"op": "alive", "id": watch_id, "key": key, "alive": alive})

    def _send_text(self, message: dict[str, Any]) -> None:
        self._enqueue(json.dumps(message), True)  # presence changes, errors: control

    def _enqueue(self, item: str | bytes, control: bool) -> None:
        if self._cut:
            return
        dropped = self._out.push(item, control)
        if dropped:
            stats = self.gateway.stats
            if control:
                stats.dropped_control += dropped
            else:
                stats.dropped_out += dropped
        waiting = self._waiting
        if waiting is not None:
            self._waiting = None
            if not waiting.done():
                waiting.set_result(None)

    async def _write(self) -> None:
        stats, out, sock = self.gateway.stats, self._out, self.sock
        loop = asyncio.get_running_loop()
        try:
            while True:
                item = out.pop(sock.has_room)
                if item is None:
                    self._waiting = waiting = loop.create_future()
                    if len(out):  # data waits for room: look again soon, or at a new item
                        with contextlib.suppress(TimeoutError):
                            await asyncio.wait_for(waiting, ROOM_POLL)
                    else:
                        await waiting
                    continue
                size = len(item)
                if isinstance(item, bytes):
                    await sock.send_bytes(item)
                else:
                    await sock.send_text(item)
                stats.frames_out += 1
                stats.bytes_out += size
        except (ConnectionError, RuntimeError):
            return  # the browser is gone; serve() sees the close

    # --- the end -------------------------------------------------------------------------

    async def _cut_off(self, refusal: Refusal) -> None:
        self._cut = True
        self._out.clear()
        self.release()  # nothing more in or out for it, before any await
        stats = self.gateway.stats
        stats.count(stats.cut, refusal.code)
        log.warning("gateway: cut off %s from %s: %s", self.name, self.peer, excerpt(str(refusal)))
        with contextlib.suppress(Exception):
            await self.sock.send_text(
                json.dumps({"op": "cut", "code": refusal.code, "text": refusal.text})
            )
        with contextlib.suppress(Exception):
            await self.sock.close(CLOSE_CUT, refusal.code)

    def release(self) -> None:
        """Undeclare everything this browser declared; idempotent."""
        self.sub_keys.clear()
        tables: tuple[dict[int, Any], ...] = (self.subs, self.tokens, self.watches)
        for table in tables:
            entities = list(table.values())
            table.clear()
            for entity in entities:
                with contextlib.suppress(Exception):
                    entity.close()
        publishers = list(self.publishers.values())
        self.publishers.clear()
        for publisher in publishers:
            with contextlib.suppress(Exception):
                publisher.close()


class _Site(web.TCPSite):
    """aiohttp's TCP site with a bound on the TLS handshake (``ssl_handshake_timeout``,
    which ``web.TCPSite`` does not pass to ``loop.create_server``)."""

    def __init__(
        self,
        runner: web.BaseRunner,
        host: str,
        port: int,
        *,
        ssl_context: ssl.SSLContext | None,
        handshake_timeout: float,
    ) -> None:
        super().__init__(runner, host, port, ssl_context=ssl_context)
        self._handshake_timeout = handshake_timeout

    async def start(self) -> None:
        if self._ssl_context is None:  # plain HTTP (loopback, tests): no handshake to bound
            await super().start()
            return
        await web.BaseSite.start(self)  # registers the site with its runner
        server = self._runner.server
        assert server is not None
        self._server = await asyncio.get_running_loop().create_server(
            server,
            self._host,
            self._port,
            ssl=self._ssl_context,
            backlog=self._backlog,
            ssl_handshake_timeout=self._handshake_timeout,
        )
