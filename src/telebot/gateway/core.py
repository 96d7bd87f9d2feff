"""Sans-IO: the browser gateway's rules (docs/protocol.md §26).

Everything a gateway decides without touching a socket: the admission challenge and the
check of its proof, the keys an admitted user may use (the ``user:U`` rules of §22.2),
per-connection budgets (token buckets fed with the caller's ``now``), and the parsing of
what a browser sends, each refusal a :class:`Refusal` with a code and one short line that
quotes at most a few hundred characters of the input (:func:`telebot.errors.excerpt`).

The I/O adapter (``gateway/server.py``) owns the websockets and the zenoh session and asks
this module what to do.
"""

from __future__ import annotations

import collections
import hashlib
import hmac
import json
import re
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final, Literal

from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey, X25519PublicKey
from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

from telebot.errors import excerpt
from telebot.identity import decode_key, encode_key

__all__ = [
    "CLOSE_CUT",
    "CLOSE_REFUSED",
    "COPIES_REMEMBERED",
    "COPY_FLAG",
    "MAX_KEY_BYTES",
    "MAX_PAYLOAD",
    "PROOF_LABEL",
    "Admit",
    "Budget",
    "Challenge",
    "CopyFilter",
    "KeyRules",
    "Limits",
    "Op",
    "OutQueue",
    "Put",
    "Refusal",
    "TokenBucket",
    "make_challenge",
    "pack_sample",
    "parse_admission",
    "parse_op",
    "parse_put",
    "proof_of",
    "sample_header",
]

#: Close codes: refused at admission, cut off after it.
CLOSE_REFUSED: Final = 4001
CLOSE_CUT: Final = 4008
PROOF_LABEL: Final = b"telebot-gateway-v1"
#: The largest frame of the protocol (a DATA frame with a 32,768-byte datagram, §2.1).
MAX_PAYLOAD: Final = 33_060
#: Longest key (UTF-8 bytes) a browser may name: the longest telebot key is ~230 bytes.
MAX_KEY_BYTES: Final = 256
#: Longest JSON text message a browser may send.
MAX_TEXT: Final = 2048
#: ids of sub/token/watch are u16 (a SAMPLE carries the sub id in two bytes).
MAX_ID: Final = 0xFFFF
LANES: Final = ("control", "data", "bulk")

# A literal key chunk: names (§1), base64url keys (§3.1), hex ids; nothing zenoh treats
# specially (``*``, ``$``, ``?``, ``#``, ``@``).
_CHUNK = re.compile(r"[A-Za-z0-9._=-]{1,128}")


class Refusal(Exception):
    """Why a browser is refused or cut off: a short code and one line for people."""

    def __init__(self, code: str, text: str) -> None:
        super().__init__(code, text)
        self.code = code
        self.text = text

    def __str__(self) -> str:
        return f"{self.code}: {self.text}"


def _garbage(what: str, raw: str | bytes) -> Refusal:
    shown = raw if isinstance(raw, str) else raw[:300].decode("utf-8", "replace")
    size = f" ({len(raw)} bytes)" if isinstance(raw, bytes) and len(raw) > 300 else ""
    return Refusal("garbage", f"{what}: {excerpt(shown, 120)}{size}")


# --- admission --------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Challenge:
    """One connection's admission challenge: an ephemeral X25519 key and a nonce."""

    ephemeral_private: bytes = field(repr=False)
    nonce: bytes

    @property
    def ephemeral_public(self) -> bytes:
        """The public half, sent to the browser."""
        key = X25519PrivateKey.from_private_bytes(self.ephemeral_private)
        return key.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)

    def message(self, namespace: str) -> dict[str, object]:
        """The first message the gateway sends (JSON)."""
        return {
            "op": "challenge",
            "v": 1,
            "ns": namespace,
            "gateway": encode_key(self.ephemeral_public),
            "nonce": encode_key(self.nonce),
        }

    def verify(self, name: str, user_public: bytes, proof: bytes) -> bool:
        """Whether ``proof`` shows the holder of ``user_public``'s private key answered."""
        try:
            shared = X25519PrivateKey.from_private_bytes(self.ephemeral_private).exchange(
                X25519PublicKey.from_public_bytes(user_public)
            )
        except ValueError:  # a low-order point: no shared secret, no proof
            return False
        expected = proof_of(shared, self.nonce, self.ephemeral_public, user_public, name)
        return hmac.compare_digest(expected, proof)


def make_challenge(random32a: bytes, random32b: bytes) -> Challenge:
    """A challenge from 64 random bytes the caller drew (``os.urandom``)."""
    if len(random32a) != 32 or len(random32b) != 32:
        raise ValueError("a challenge needs two 32-byte random strings")
    return Challenge(random32a, random32b)


def proof_of(
    shared: bytes, nonce: bytes, gateway_public: bytes, user_public: bytes, name: str
) -> bytes:
    """HMAC-SHA256(DH, label ‖ nonce ‖ gateway ephemeral ‖ user key ‖ name): §26.1."""
    message = PROOF_LABEL + nonce + gateway_public + user_public + name.encode("utf-8")
    return hmac.new(shared, message, hashlib.sha256).digest()


@dataclass(frozen=True, slots=True)
class Admit:
    """A browser's ``admit`` (``invite`` is None) or ``redeem`` message, parsed."""

    name: str
    key: bytes
    proof: bytes
    invite: str | None = None


_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
_TOKEN = re.compile(r"[A-Za-z0-9_-]{16,64}")


def _json_object(raw: str, allowed: int = MAX_TEXT) -> dict[str, object]:
    if len(raw) > allowed:
        raise Refusal("too_large", f"a text message of {len(raw)} characters (at most {allowed})")
    try:
        data = json.loads(raw)
    except (ValueError, RecursionError):
        raise _garbage("not JSON", raw) from None
    if not isinstance(data, dict):
        raise _garbage("not a JSON object", raw)
    return data


def parse_admission(raw: str | bytes) -> Admit:
    """The browser's first message: ``admit`` or ``redeem``; Refusal if it is neither."""
    if isinstance(raw, bytes):
        raise Refusal("garbage", f"a binary message before admission ({len(raw)} bytes)")
    data = _json_object(raw)
    op = data.get("op")
    expected = {"op", "name", "key", "proof"} | ({"invite"} if op == "redeem" else set())
    if op not in ("admit", "redeem") or set(data) != expected:
        raise _garbage("expected an admit or redeem message", raw)
    name, key, proof = data["name"], data["key"], data["proof"]
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise _garbage("not a name", str(name))
    try:
        user_key = decode_key(str(key))
        user_proof = decode_key(str(proof))
    except ValueError as exc:
        raise Refusal("garbage", f"key or proof: {exc}") from None
    invite = data.get("invite")
    if op == "redeem" and (not isinstance(invite, str) or not _TOKEN.fullmatch(invite)):
        raise _garbage("not an invite token", str(invite))
    return Admit(name, user_key, user_proof, invite if isinstance(invite, str) else None)


# --- key rules (§22.2, subject user:U) --------------------------------------------------


def _chunks(key: str) -> list[str] | None:
    if not key or len(key.encode("utf-8")) > MAX_KEY_BYTES:
        return None
    return key.split("/")


def _literal(chunk: str) -> bool:
    return _CHUNK.fullmatch(chunk) is not None


@dataclass(frozen=True, slots=True)
class KeyRules:
    """What ``user`` may do under ``namespace``: the router ACL's ``user:U`` rules (§22.2).

    Pure and strict: a key chunk is a literal name, key or id (``[A-Za-z0-9._=-]``) or,
    where the rule has a wildcard, ``*``; ``**`` only as the last chunk of a subscription
    under the user's own keys. So every expression allowed is included in the rule's.
    """

    namespace: str
    user: str

    def may_subscribe(self, expr: str) -> bool:
        """``{ns}/user/U/**``."""
        chunks = _chunks(expr)
        if chunks is None or chunks[:3] != [self.namespace, "user", self.user]:
            return False
        rest = chunks[3:]
        for index, chunk in enumerate(rest):
            if chunk == "**" and index == len(rest) - 1:
                continue
            if chunk != "*" and not _literal(chunk):
                return False
        return True

    def may_put(self, key: str) -> bool:
        """``{ns}/robot/*/in/U``, ``{ns}/robot/*/call/U/*/ctl|data``, ``{ns}/robot/*/in``."""
        chunks = _chunks(key)
        if chunks is None or not all(_literal(c) for c in chunks):
            return False
        if chunks[:2] != [self.namespace, "robot"] or len(chunks) < 4:
            return False
        rest = chunks[3:]
        return (
            rest == ["in"]
            or rest == ["in", self.user]
            or (len(rest) == 4 and rest[:2] == ["call", self.user] and rest[3] in ("ctl", "data"))
        )

    def may_declare_token(self, key: str) -> bool:
        """``{ns}/presence/user/U/*`` (an exact key: a token has no wildcards)."""
        chunks = _chunks(key)
        return (
            chunks is not None
            and len(chunks) == 5
            and chunks[:4] == [self.namespace, "presence", "user", self.user]
            and _literal(chunks[4])
        )

    def may_watch(self, expr: str) -> bool:
        """``{ns}/presence/robot/*/*``."""
        chunks = _chunks(expr)
        return (
            chunks is not None
            and len(chunks) == 5
            and chunks[:3] == [self.namespace, "presence", "robot"]
            and all(c == "*" or _literal(c) for c in chunks[3:])
        )


# --- budgets ----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Limits:
    """The gateway's bounds (§26.3): per connection, per source address, per name, in all."""

    frames_per_s: float = 1000.0
    frames_burst: float = 2000.0
    bytes_per_s: float = 4_000_000.0
    bytes_burst: float = 8_000_000.0
    #: ``sub``/``token``/``watch`` messages (each a zenoh declaration), apart from PUTs.
    declarations_per_s: float = 10.0
    declarations_burst: float = 64.0
    max_subscriptions: int = 16
    max_tokens: int = 64
    max_watches: int = 64
    #: Data frames and bytes queued towards one browser; the oldest is dropped beyond either.
    out_frames: int = 1024
    out_bytes: int = 512_000
    #: Control frames (samples on ``…/ctl`` keys, text messages) queued towards one browser,
    #: sent before any data frame and dropped (the oldest) only beyond these.
    out_control_frames: int = 256
    out_control_bytes: int = 256_000
    #: Seconds a browser has to answer the challenge.
    admission_timeout: float = 10.0
    #: Websockets at once (admitted or not), and not yet admitted ones per source address;
    #: beyond either a websocket request is answered HTTP 503.
    max_connections: int = 32
    max_pending_per_address: int = 4
    #: Admitted websockets per name; beyond it the admission is refused (``too_many``).
    #: A page uses two (web/src/gateway-link.js ``SplitLink``): four pages.
    max_per_name: int = 8
    #: Seconds a client has to complete its TLS handshake (the listener's).
    tls_handshake_timeout: float = 5.0


@dataclass(slots=True)
class TokenBucket:
    """``rate`` per second, up to ``burst`` saved; :meth:`take` with the caller's clock."""

    rate: float
    burst: float
    level: float = -1.0
    last: float | None = None

    def take(self, amount: float, now: float) -> bool:
        """Spend ``amount`` if there is that much; False (nothing spent) if not."""
        # Once per browser message: comparisons, not min()/max() calls.
        last = self.last
        if last is None:
            level = self.burst
        else:
            level = self.level
            if now > last:
                level += (now - last) * self.rate
                if level > self.burst:
                    level = self.burst
        self.last = now
        if amount > level:
            self.level = level
            return False
        self.level = level - amount
        return True


@dataclass(slots=True)
class Budget:
    """One connection's frame and byte buckets, and its declarations' bucket."""

    frames: TokenBucket
    bytes: TokenBucket
    declarations: TokenBucket

    @classmethod
    def of(cls, limits: Limits) -> Budget:
        """Full buckets sized by ``limits``."""
        return cls(
            TokenBucket(limits.frames_per_s, limits.frames_burst),
            TokenBucket(limits.bytes_per_s, limits.bytes_burst),
            TokenBucket(limits.declarations_per_s, limits.declarations_burst),
        )

    def spend(self, size: int, now: float) -> None:
        """Count one message of ``size`` bytes; Refusal ``flood`` when over either budget."""
        if not self.frames.take(1, now):
            raise Refusal("flood", f"over {self.frames.rate:g} messages/s")
        if not self.bytes.take(size, now):
            raise Refusal("flood", f"over {self.bytes.rate:g} bytes/s")

    def declare(self, now: float) -> None:
        """Count one ``sub``/``token``/``watch``; Refusal ``flood`` when over its budget."""
        if not self.declarations.take(1, now):
            raise Refusal("flood", f"over {self.declarations.rate:g} sub/token/watch messages/s")


class OutQueue:
    """What waits to go to one browser: control frames first, then data frames.

    Two bounded queues: a control frame (a sample on a ``…/ctl`` key: heartbeats, safety
    acknowledgements; a text message: presence changes, errors) is sent before every data
    frame and is dropped only behind other control frames; each queue drops its oldest
    beyond its bounds, and :attr:`dropped_control` / :attr:`dropped_data` count them.
    """

    __slots__ = (
        "_control",
        "_control_bytes",
        "_data",
        "_data_bytes",
        "dropped_control",
        "dropped_data",
        "limits",
    )

    def __init__(self, limits: Limits) -> None:
        self.limits = limits
        self._control: collections.deque[str | bytes] = collections.deque()
        self._data: collections.deque[str | bytes] = collections.deque()
        self._control_bytes = 0
        self._data_bytes = 0
        self.dropped_control = 0
        self.dropped_data = 0

    def __len__(self) -> int:
        return len(self._control) + len(self._data)

    @property
    def data_bytes(self) -> int:
        """Bytes of data frames waiting."""
        return self._data_bytes

    def push(self, item: str | bytes, control: bool) -> int:
        """Queue ``item``; how many older items of its kind were dropped to make room."""
        dropped = 0
        if control:
            queue = self._control
            queue.append(item)
            self._control_bytes += len(item)
            most, most_bytes = self.limits.out_control_frames, self.limits.out_control_bytes
            while len(queue) > most or self._control_bytes > most_bytes:
                self._control_bytes -= len(queue.popleft())
                dropped += 1
            self.dropped_control += dropped
        else:
            queue = self._data
            queue.append(item)
            self._data_bytes += len(item)
            most, most_bytes = self.limits.out_frames, self.limits.out_bytes
            while len(queue) > most or self._data_bytes > most_bytes:
                self._data_bytes -= len(queue.popleft())
                dropped += 1
            self.dropped_data += dropped
        return dropped

    def pop(self, data_ok: Callable[[str | bytes], bool] | None = None) -> str | bytes | None:
        """The next item to send (a control one if any), or None if nothing waits; with
        ``data_ok``, a data item only if it accepts it (the connection has room for it)."""
        if self._control:
            item = self._control.popleft()
            self._control_bytes -= len(item)
            return item
        if self._data and (data_ok is None or data_ok(self._data[0])):
            item = self._data.popleft()
            self._data_bytes -= len(item)
            return item
        return None

    def clear(self) -> None:
        """Forget everything waiting (not counted as dropped)."""
        self._control.clear()
        self._data.clear()
        self._control_bytes = self._data_bytes = 0


# --- messages after admission ------------------------------------------------------------

OpName = Literal["sub", "unsub", "token", "untoken", "watch", "unwatch"]


@dataclass(frozen=True, slots=True)
class Op:
    """A text request: ``sub``/``token``/``watch`` carry a key, their ``un…`` none."""

    op: OpName
    id: int
    key: str | None = None


@dataclass(slots=True)
class Put:
    """A binary PUT: publish ``payload`` on ``key`` with the QoS of ``lane``; ``copy``: the
    copy id of a PUT the browser sent on more than one WebSocket (§26.2), or None.

    Not frozen: one is built for every PUT, and a frozen dataclass takes several times
    longer to build.
    """

    lane: str
    key: str
    payload: bytes
    copy: int | None = None


#: The lane byte's flag of a PUT with a copy id (§26.2).
COPY_FLAG: Final = 0x80
#: A user's copied PUTs are told apart by copy id among the last this many (§26.2).
COPIES_REMEMBERED: Final = 1024


class CopyFilter:
    """One user's recent copy ids: the first PUT of each is published, later ones dropped
    (a page sends a CONTROL PUT on both its WebSockets, §26.2, so that a stop does not
    wait for a retransmission on one of them)."""

    __slots__ = ("_order", "_remembered", "_seen")

    def __init__(self, remembered: int = COPIES_REMEMBERED) -> None:
        self._remembered = remembered
        self._seen: set[int] = set()
        self._order: collections.deque[int] = collections.deque()

    def first(self, copy: int) -> bool:
        """Whether ``copy`` is new (remembered from now on), False for a copy seen before."""
        if copy in self._seen:
            return False
        self._seen.add(copy)
        self._order.append(copy)
        if len(self._order) > self._remembered:
            self._seen.discard(self._order.popleft())
        return True

    def forget(self, copy: int) -> None:
        """Let ``copy`` pass again (its first PUT could not be published)."""
        self._seen.discard(copy)


_WITH_KEY: Final = ("sub", "token", "watch")
_WITHOUT_KEY: Final = ("unsub", "untoken", "unwatch")


def parse_op(raw: str) -> Op:
    """A text message after admission; Refusal ``garbage`` unless it is one of §26.2."""
    data = _json_object(raw)
    op = data.get("op")
    if op in _WITH_KEY:
        fields = {"op", "id", "key"}
    elif op in _WITHOUT_KEY:
        fields = {"op", "id"}
    else:
        raise _garbage("unknown op", raw)
    ident = data.get("id")
    if set(data) != fields or type(ident) is not int or not 0 <= ident <= MAX_ID:
        raise _garbage(f"a malformed {op} message", raw)
    key = data.get("key")
    if op in _WITH_KEY and not isinstance(key, str):
        raise _garbage(f"a {op} message without a key", raw)
    return Op(op, ident, key if isinstance(key, str) else None)


def parse_put(raw: bytes) -> Put:
    """A binary PUT ``[u8 lane][u16 key length][key][payload]``, or with the lane's
    :data:`COPY_FLAG` ``[u8 lane | 0x80][u64 copy id][u16 key length][key][payload]``
    (§26.2); Refusal if malformed."""
    copy, at = None, 1
    if raw[:1] and raw[0] & COPY_FLAG:
        if len(raw) < 11:
            raise _garbage("a binary message shorter than a copied PUT's header", raw)
        copy, at = int.from_bytes(raw[1:9], "big"), 9
    if len(raw) < at + 2:
        raise _garbage("a binary message shorter than a PUT header", raw)
    lane, length = raw[0] & ~COPY_FLAG, raw[at] << 8 | raw[at + 1]
    if lane >= len(LANES):
        raise _garbage(f"lane {lane} (0 control, 1 data, 2 bulk; +128 with a copy id)", raw)
    start = at + 2
    if not 1 <= length <= MAX_KEY_BYTES or len(raw) < start + length:
        raise _garbage(f"a key length of {length}", raw)
    payload = raw[start + length :]
    if len(payload) > MAX_PAYLOAD:
        raise Refusal("too_large", f"a payload of {len(payload)} bytes (at most {MAX_PAYLOAD})")
    try:
        key = raw[start : start + length].decode("utf-8")
    except UnicodeDecodeError:
        raise _garbage("a key that is not UTF-8", raw) from None
    return Put(LANES[lane], key, payload, copy)


def sample_header(sub_id: int, key: str) -> bytes:
    """What comes before the payload in a SAMPLE: ``[u16 sub id][u16 key length][key]``
    (the same for every sample of one key: the I/O adapter keeps it)."""
    encoded = key.encode("utf-8")
    return struct.pack(">HH", sub_id, len(encoded)) + encoded


def pack_sample(sub_id: int, key: str, payload: bytes) -> bytes:
    """A SAMPLE to the browser: ``[u16 sub id][u16 key length][key][payload]``."""
    return sample_header(sub_id, key) + payload
