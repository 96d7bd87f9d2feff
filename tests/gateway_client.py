"""A browser's side of the gateway in Python, for tests: admission and a Transport.

Written from docs/protocol.md §26 (the proof is computed here with ``cryptography`` and
``hmac`` directly, not with ``telebot.gateway.core``), so the tests check the gateway
against the document. :class:`GatewayTransport` lets the ordinary ``UserEndpoint`` call a
robot through a gateway, as the page's JavaScript client does.
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import hmac
import json
import ssl
import struct
from collections.abc import Sequence
from typing import Any, Self

import aiohttp
from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey, X25519PublicKey
from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

from telebot.channels.transports.base import (
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
)
from telebot.config import TransportSettings
from telebot.identity import Identity

LANE_BYTE = {Lane.CONTROL: 0, Lane.DATA: 1, Lane.BULK: 2}


def b64(raw: bytes) -> str:
    return base64.urlsafe_b64encode(raw).rstrip(b"=").decode()


def unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=")


def proof(private_key: bytes, name: str, challenge: dict[str, Any]) -> tuple[bytes, bytes]:
    """(user public key, proof) answering ``challenge`` as §26.1 says."""
    me = X25519PrivateKey.from_private_bytes(private_key)
    public = me.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)
    gateway, nonce = unb64(challenge["gateway"]), unb64(challenge["nonce"])
    shared = me.exchange(X25519PublicKey.from_public_bytes(gateway))
    message = b"telebot-gateway-v1" + nonce + gateway + public + name.encode()
    return public, hmac.new(shared, message, hashlib.sha256).digest()


def put_frame(key: str, payload: bytes, lane: int = 1, copy: int | None = None) -> bytes:
    """A PUT (docs/protocol.md §26.2); with ``copy``, flagged with that copy id."""
    encoded = key.encode()
    head = bytes([lane]) if copy is None else bytes([lane | 0x80]) + copy.to_bytes(8, "big")
    return head + struct.pack(">H", len(encoded)) + encoded + payload


def parse_sample(frame: bytes) -> tuple[int, str, bytes]:
    sub_id, length = struct.unpack_from(">HH", frame)
    return sub_id, frame[4 : 4 + length].decode(), frame[4 + length :]


async def admit(
    ws: aiohttp.ClientWebSocketResponse,
    identity: Identity,
    *,
    name: str | None = None,
    invite: str | None = None,
) -> dict[str, Any]:
    """Answer the challenge as ``identity`` (claiming ``name``); the gateway's answer."""
    challenge = json.loads((await ws.receive(timeout=30)).data)
    assert challenge["op"] == "challenge" and challenge["v"] == 1, challenge
    name = name or identity.name
    public, mac = proof(identity.private_key, name, challenge)
    message: dict[str, Any] = {"op": "admit", "name": name, "key": b64(public), "proof": b64(mac)}
    if invite is not None:
        message = {
            "op": "redeem",
            "invite": invite,
            **{k: v for k, v in message.items() if k != "op"},
        }
    await ws.send_str(json.dumps(message))
    answer: dict[str, Any] = json.loads((await ws.receive(timeout=30)).data)
    return answer


class _Sub(Subscription):
    def __init__(self, transport: GatewayTransport, kind: str, ident: int) -> None:
        self.stats = SubscriptionStats()
        self._transport, self._kind, self._id = transport, kind, ident

    def close(self) -> None:
        self._transport._close_entity(self._kind, self._id)


class _Token(Presence):
    def __init__(self, transport: GatewayTransport, ident: int) -> None:
        self._transport, self._id = transport, ident

    def close(self) -> None:
        self._transport._close_entity("token", self._id)


class _Pub(Publisher):
    def __init__(self, transport: GatewayTransport, key: str, lane: Lane) -> None:
        self._transport, self.key, self.lane = transport, key, lane

    def put(self, payload: bytes) -> None:
        self._transport._send(put_frame(self.key, payload, LANE_BYTE[self.lane]))

    def close(self) -> None:
        pass


class GatewayTransport(Transport):
    """A Transport over a gateway websocket (what gateway-link.js is to the page)."""

    name = "gateway"

    def __init__(
        self,
        url: str,
        identity: Identity,
        *,
        ssl_context: ssl.SSLContext | None = None,
        invite: str | None = None,
    ) -> None:
        super().__init__()
        self.url, self.identity, self.ssl_context, self.invite = url, identity, ssl_context, invite
        self._http: aiohttp.ClientSession | None = None
        self.ws: aiohttp.ClientWebSocketResponse | None = None
        self._reader: asyncio.Task[None] | None = None
        self._subs: dict[int, SampleBatchCallback] = {}
        self._watches: dict[int, PresenceCallback] = {}
        self._next = {"sub": 0, "token": 0, "watch": 0}
        self._pending: set[asyncio.Task[None]] = set()
        self.cut: dict[str, Any] | None = None

    @classmethod
    def from_settings(cls, settings: TransportSettings) -> Self:
        raise NotImplementedError

    async def open(self) -> None:
        self._http = aiohttp.ClientSession()
        self.ws = await self._http.ws_connect(self.url + "gateway", ssl=self.ssl_context or False)
        answer = await admit(self.ws, self.identity, invite=self.invite)
        if answer["op"] != "admitted":
            raise ConnectionError(f"gateway refused: {answer}")
        self._reader = asyncio.create_task(self._read())

    async def close(self) -> None:
        if self._reader is not None:
            self._reader.cancel()
            await asyncio.gather(self._reader, return_exceptions=True)
        await asyncio.gather(*self._pending, return_exceptions=True)
        if self.ws is not None:
            await self.ws.close()
        if self._http is not None:
            await self._http.close()

    async def _read(self) -> None:
        assert self.ws is not None
        async for msg in self.ws:
            if msg.type == aiohttp.WSMsgType.BINARY:
                sub_id, key, payload = parse_sample(msg.data)
                callback = self._subs.get(sub_id)
                if callback is not None:
                    callback([Sample(key, payload)])
            elif msg.type == aiohttp.WSMsgType.TEXT:
                data = json.loads(msg.data)
                if data["op"] == "alive" and data["id"] in self._watches:
                    self._watches[data["id"]](data["key"], data["alive"])
                elif data["op"] == "cut":
                    self.cut = data

    def _send(self, message: str | bytes) -> None:
        assert self.ws is not None
        if self.ws.closed:
            return
        send = (
            self.ws.send_bytes(message) if isinstance(message, bytes) else self.ws.send_str(message)
        )
        task = asyncio.ensure_future(send)
        self._pending.add(task)
        task.add_done_callback(self._pending.discard)

    def _new_id(self, kind: str) -> int:
        self._next[kind] += 1
        return self._next[kind]

    def _close_entity(self, kind: str, ident: int) -> None:
        table: dict[int, Any] = {"sub": self._subs, "watch": self._watches}.get(kind, {})
        table.pop(ident, None)
        self._send(json.dumps({"op": "un" + kind, "id": ident}))

    def publisher(self, key: str, lane: Lane = Lane.DATA) -> Publisher:
        return _Pub(self, key, lane)

    def subscribe(
        self, pattern: str, callback: SampleBatchCallback, *, limits: ReceiveLimits | None = None
    ) -> Subscription:
        ident = self._new_id("sub")
        self._subs[ident] = callback
        self._send(json.dumps({"op": "sub", "id": ident, "key": pattern}))
        return _Sub(self, "sub", ident)

    def declare_presence(self, key: str) -> Presence:
        ident = self._new_id("token")
        self._send(json.dumps({"op": "token", "id": ident, "key": key}))
        return _Token(self, ident)

    def watch_presence(self, pattern: str, callback: PresenceCallback) -> Subscription:
        ident = self._new_id("watch")
        self._watches[ident] = callback
        self._send(json.dumps({"op": "watch", "id": ident, "key": pattern}))
        return _Sub(self, "watch", ident)


def unused(_: Sequence[object]) -> None:
    """A sample callback that keeps nothing."""
