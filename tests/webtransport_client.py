"""A browser's WebTransport session to the gateway in Python (aioquic), for tests.

Written from docs/protocol.md §26.5 (the preamble, the text frames, datagrams and a stream
per larger message, the close capsule), not from ``telebot.gateway.webtransport``, so the
tests check the gateway against the document.
"""

from __future__ import annotations

import asyncio
import contextlib
import ssl
import struct
from collections.abc import AsyncIterator
from typing import Any

from aioquic.asyncio.client import connect
from aioquic.asyncio.protocol import QuicConnectionProtocol
from aioquic.buffer import Buffer, encode_uint_var
from aioquic.h3.connection import H3_ALPN, FrameType, H3Connection
from aioquic.h3.events import (
    DatagramReceived,
    DataReceived,
    HeadersReceived,
    WebTransportStreamDataReceived,
)
from aioquic.quic.configuration import QuicConfiguration
from aioquic.quic.events import ConnectionTerminated, QuicEvent

PREAMBLE = b"TBG1"


class _Client(QuicConnectionProtocol):
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.h3 = H3Connection(self._quic, enable_webtransport=True)
        self.events: asyncio.Queue[Any] = asyncio.Queue()

    def quic_event_received(self, event: QuicEvent) -> None:
        if isinstance(event, ConnectionTerminated):
            self.events.put_nowait(event)
            return
        for h3_event in self.h3.handle_event(event):
            self.events.put_nowait(h3_event)


class Session:
    """One session: ``status`` (the CONNECT's answer), ``send_*``, :meth:`receive`, and
    ``closed`` ((code, reason) from the gateway's close capsule, once received)."""

    def __init__(self, client: _Client, session_id: int) -> None:
        self.client = client
        self.session_id = session_id
        self.status = 0
        self.bidi: int | None = None
        self.closed: tuple[int, str] | None = None
        self.ended = False
        self._text = bytearray()
        self._streams: dict[int, bytearray] = {}
        self._inbox: asyncio.Queue[str | bytes] = asyncio.Queue()

    def _flush(self) -> None:
        self.client.transmit()

    def send_raw(self, data: bytes) -> None:
        """Bytes on the bidirectional stream (opened at the first call)."""
        if self.bidi is None:
            h3 = self.client.h3
            self.bidi = h3.create_webtransport_stream(self.session_id)
            # aioquic parses what comes back on a stream it opened as HTTP frames: mark it
            # as the WebTransport stream it is (a browser needs no such thing).
            with h3._get_or_create_stream(self.bidi) as stream:
                stream.frame_type = FrameType.WEBTRANSPORT_STREAM
                stream.session_id = self.session_id
        self.client._quic.send_stream_data(self.bidi, data)
        self._flush()

    def open_stream(self) -> None:
        """The bidirectional stream, with its preamble."""
        self.send_raw(PREAMBLE)

    def send_text(self, text: str) -> None:
        data = text.encode()
        self.send_raw(struct.pack(">I", len(data)) + data)

    def send_datagram(self, data: bytes) -> None:
        self.client.h3.send_datagram(self.session_id, data)
        self._flush()

    def send_stream(self, data: bytes) -> None:
        """One message on a unidirectional stream of its own."""
        stream_id = self.client.h3.create_webtransport_stream(
            self.session_id, is_unidirectional=True
        )
        self.client._quic.send_stream_data(stream_id, data, end_stream=True)
        self._flush()

    def send_partial(self, data: bytes) -> None:
        """Bytes on a new unidirectional stream, never ended."""
        stream_id = self.client.h3.create_webtransport_stream(
            self.session_id, is_unidirectional=True
        )
        self.client._quic.send_stream_data(stream_id, data)
        self._flush()

    def send_capsule(self, kind: int, body: bytes, end: bool = False) -> None:
        """A capsule on the CONNECT stream (``end``: and the stream's end)."""
        capsule = encode_uint_var(kind) + encode_uint_var(len(body)) + body
        self.client.h3.send_data(self.session_id, capsule, end_stream=end)
        self._flush()

    def close_session(self, code: int = 0) -> None:
        """Close the session (its capsule and the end of the CONNECT stream), keeping the
        QUIC connection."""
        self.send_capsule(0x2843, struct.pack(">I", code), end=True)

    def _event(self, event: Any) -> None:
        if isinstance(event, ConnectionTerminated):
            self.ended = True
        elif isinstance(event, HeadersReceived) and event.stream_id == self.session_id:
            self.status = int(dict(event.headers)[b":status"])
        elif isinstance(event, DataReceived) and event.stream_id == self.session_id:
            buf = Buffer(data=event.data)
            if event.data and buf.pull_uint_var() == 0x2843:
                length = buf.pull_uint_var()
                body = buf.pull_bytes(length)
                self.closed = (struct.unpack(">I", body[:4])[0], body[4:].decode())
        elif isinstance(event, DatagramReceived):
            self._inbox.put_nowait(event.data)
        elif isinstance(event, WebTransportStreamDataReceived):
            if event.stream_id == self.bidi:
                self._text += event.data
                while len(self._text) >= 4:
                    (length,) = struct.unpack_from(">I", self._text)
                    if len(self._text) < 4 + length:
                        break
                    self._inbox.put_nowait(self._text[4 : 4 + length].decode())
                    del self._text[: 4 + length]
            else:
                buffer = self._streams.setdefault(event.stream_id, bytearray())
                buffer += event.data
                if event.stream_ended:
                    self._inbox.put_nowait(bytes(self._streams.pop(event.stream_id)))

    async def pump(self, timeout: float) -> None:
        """Handle what arrived, waiting up to ``timeout`` for something."""
        with contextlib.suppress(TimeoutError):
            self._event(await asyncio.wait_for(self.client.events.get(), timeout))
        while not self.client.events.empty():
            self._event(self.client.events.get_nowait())

    async def receive(self, timeout: float = 30.0) -> str | bytes:
        """The next message: a text (``str``), a datagram or a stream's content (``bytes``)."""
        deadline = asyncio.get_running_loop().time() + timeout
        while self._inbox.empty():
            left = deadline - asyncio.get_running_loop().time()
            if left <= 0 or self.ended:
                raise TimeoutError("nothing from the gateway")
            await self.pump(min(left, 0.1))
        return self._inbox.get_nowait()

    async def until_closed(
        self, timeout: float = 30.0
    ) -> tuple[list[str | bytes], tuple[int, str]]:
        """Every message until the gateway's close capsule, and its (code, reason)."""
        messages: list[str | bytes] = []
        deadline = asyncio.get_running_loop().time() + timeout
        while self.closed is None:
            if asyncio.get_running_loop().time() > deadline or self.ended:
                raise AssertionError(f"no close capsule; got {messages!r:.300}")
            await self.pump(0.1)
            while not self._inbox.empty():
                messages.append(self._inbox.get_nowait())
        while not self._inbox.empty():
            messages.append(self._inbox.get_nowait())
        return messages, self.closed


@contextlib.asynccontextmanager
async def session(host: str, port: int, path: str = "/gateway") -> AsyncIterator[Session]:
    """A WebTransport session (the certificate not checked: tests pin nothing here)."""
    configuration = QuicConfiguration(
        is_client=True, alpn_protocols=H3_ALPN, max_datagram_frame_size=65536
    )
    configuration.verify_mode = ssl.CERT_NONE
    async with connect(host, port, configuration=configuration, create_protocol=_Client) as client:
        assert isinstance(client, _Client)
        session_id = client._quic.get_next_available_stream_id()
        client.h3.send_headers(
            session_id,
            [
                (b":method", b"CONNECT"),
                (b":scheme", b"https"),
                (b":authority", f"{host}:{port}".encode()),
                (b":path", path.encode()),
                (b":protocol", b"webtransport"),
                (b"sec-webtransport-http3-draft02", b"1"),
                (b"origin", f"https://{host}:{port}".encode()),
            ],
        )
        client.transmit()
        result = Session(client, session_id)
        while result.status == 0 and not result.ended:
            await result.pump(0.1)
        yield result


def peer_certificate_der(result: Session) -> bytes:
    """The DER of the certificate the gateway presented."""
    from cryptography.hazmat.primitives.serialization import Encoding

    cert = result.client._quic.tls._peer_certificate
    assert cert is not None
    return cert.public_bytes(Encoding.DER)
