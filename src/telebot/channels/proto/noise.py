"""The Noise IK handshake (Noise_IK_25519_{ChaChaPoly,AESGCM}_BLAKE2s), sans-IO.

This is the pattern WireGuard uses: the caller (initiator) already knows the robot's
static public key, as ssh knows a host key from ``known_hosts``; its first message
carries its own static key, encrypted, so the robot learns who calls and both sides
prove their keys in one round trip::

    <- s
    ...
    -> e, es, s, ss      (HELLO: the caller's ephemeral and static keys, and a payload)
    <- e, ee, se         (WELCOME: the robot's ephemeral key and its answer)

It follows the Noise Protocol Framework, revision 34 (https://noiseprotocol.org/noise.html),
section 5 (CipherState, SymmetricState, HandshakeState) with the primitives of the
``cryptography`` package: X25519, ChaCha20-Poly1305 or AES-256-GCM, and BLAKE2s
(HMAC-BLAKE2s for HKDF). The cipher is a :class:`Suite`, agreed per call (see
``session.py``); it is part of the Noise protocol name, so the two suites' handshakes
have different hashes and keys. Nothing here is new cryptography; the interoperability
test checks both suites byte for byte against the independent ``noiseprotocol``
implementation.

After the handshake, :meth:`split` gives two 32-byte keys, one per direction. telebot's
datagrams use them with explicit 64-bit counters as nonces (see ``frames.py``), as
WireGuard's transport messages do, because datagrams may be lost or reordered.
"""

from __future__ import annotations

import enum
import hashlib
import hmac
from collections.abc import Callable

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey, X25519PublicKey
from cryptography.hazmat.primitives.ciphers.aead import AESGCM, ChaCha20Poly1305
from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

from telebot.errors import AuthenticationError, ProtocolError

__all__ = [
    "DH_LEN",
    "TAG_LEN",
    "Aead",
    "InitiatorHandshake",
    "ResponderHandshake",
    "Suite",
    "TransportKeys",
    "aead_nonce",
    "public_key_of",
]

HASH_LEN = 32
DH_LEN = 32
TAG_LEN = 16

#: What ChaCha20Poly1305 and AESGCM of ``cryptography`` have in common.
Aead = ChaCha20Poly1305 | AESGCM


class Suite(enum.IntEnum):
    """A Noise cipher suite, by its number on the wire (HELLO's ``suite`` and offers).

    Both use X25519 and BLAKE2s; they differ in the AEAD. AES-256-GCM is the faster
    where the CPU has AES instructions, ChaCha20-Poly1305 everywhere else (and it has
    no table lookups to leak timing without them).
    """

    CHACHAPOLY = 1
    AESGCM = 2

    @property
    def protocol_name(self) -> bytes:
        """The Noise protocol name, which starts the handshake hash."""
        return _PROTOCOL_NAMES[self]

    @property
    def label(self) -> str:
        """The name people and config files use: ``"chachapoly"`` or ``"aesgcm"``."""
        return self.name.lower()

    def aead(self, key: bytes) -> Aead:
        """The AEAD of this suite under ``key`` (32 bytes)."""
        return ChaCha20Poly1305(key) if self is Suite.CHACHAPOLY else AESGCM(key)

    @property
    def nonce(self) -> Callable[[int], bytes]:
        """The suite's 12-byte nonce for a 64-bit counter (see :func:`aead_nonce`)."""
        return aead_nonce if self is Suite.CHACHAPOLY else _aesgcm_nonce


_PROTOCOL_NAMES = {
    Suite.CHACHAPOLY: b"Noise_IK_25519_ChaChaPoly_BLAKE2s",
    Suite.AESGCM: b"Noise_IK_25519_AESGCM_BLAKE2s",
}


def public_key_of(private_key: bytes) -> bytes:
    """The raw 32-byte X25519 public key of a raw 32-byte private key."""
    return (
        X25519PrivateKey.from_private_bytes(private_key)
        .public_key()
        .public_bytes(Encoding.Raw, PublicFormat.Raw)
    )


def aead_nonce(counter: int) -> bytes:
    """Noise's ChaChaPoly nonce: 32 zero bits then the counter as 64-bit little-endian."""
    return b"\x00\x00\x00\x00" + counter.to_bytes(8, "little")


def _aesgcm_nonce(counter: int) -> bytes:
    """Noise's AESGCM nonce: 32 zero bits then the counter as 64-bit big-endian."""
    return b"\x00\x00\x00\x00" + counter.to_bytes(8, "big")


def _hash(data: bytes) -> bytes:
    return hashlib.blake2s(data).digest()


def _hmac(key: bytes, data: bytes) -> bytes:
    return hmac.new(key, data, hashlib.blake2s).digest()


def _hkdf2(chaining_key: bytes, key_material: bytes) -> tuple[bytes, bytes]:
    temp_key = _hmac(chaining_key, key_material)
    out1 = _hmac(temp_key, b"\x01")
    out2 = _hmac(temp_key, out1 + b"\x02")
    return out1, out2


def _dh(private_key: X25519PrivateKey, public_key: bytes) -> bytes:
    try:
        return private_key.exchange(X25519PublicKey.from_public_bytes(public_key))
    except ValueError as exc:  # a low-order point gives an all-zero secret
        raise AuthenticationError("invalid X25519 public key in handshake") from exc


class _SymmetricState:
    """Noise's SymmetricState with its embedded CipherState (section 5.2)."""

    def __init__(self, prologue: bytes, suite: Suite) -> None:
        # Names longer than HASHLEN are hashed (ChaChaPoly's, 33 bytes), shorter ones
        # padded with zeros (AESGCM's, 29 bytes).
        name = suite.protocol_name
        self.h = name.ljust(HASH_LEN, b"\x00") if len(name) <= HASH_LEN else _hash(name)
        self.ck = self.h
        self.suite = suite
        self._key: bytes | None = None
        self._nonce = 0
        self.mix_hash(prologue)

    def mix_hash(self, data: bytes) -> None:
        self.h = _hash(self.h + data)

    def mix_key(self, key_material: bytes) -> None:
        self.ck, self._key = _hkdf2(self.ck, key_material)
        self._nonce = 0

    def encrypt_and_hash(self, plaintext: bytes) -> bytes:
        assert self._key is not None, "IK always has a key before the first encryption"
        ciphertext = self.suite.aead(self._key).encrypt(
            self.suite.nonce(self._nonce), plaintext, self.h
        )
        self._nonce += 1
        self.mix_hash(ciphertext)
        return ciphertext

    def decrypt_and_hash(self, ciphertext: bytes) -> bytes:
        assert self._key is not None, "IK always has a key before the first decryption"
        try:
            plaintext = self.suite.aead(self._key).decrypt(
                self.suite.nonce(self._nonce), ciphertext, self.h
            )
        except InvalidTag as exc:
            raise AuthenticationError("handshake message failed authentication") from exc
        self._nonce += 1
        self.mix_hash(ciphertext)
        return plaintext

    def split(self) -> tuple[bytes, bytes]:
        return _hkdf2(self.ck, b"")

    def copy(self) -> _SymmetricState:
        clone = object.__new__(_SymmetricState)
        clone.h, clone.ck, clone._key, clone._nonce = self.h, self.ck, self._key, self._nonce
        clone.suite = self.suite
        return clone


class TransportKeys:
    """The two per-call keys a finished handshake yields, seen from one side."""

    __slots__ = ("handshake_hash", "receive_key", "send_key", "suite")

    def __init__(
        self,
        send_key: bytes,
        receive_key: bytes,
        handshake_hash: bytes,
        suite: Suite = Suite.CHACHAPOLY,
    ) -> None:
        self.send_key = send_key
        self.receive_key = receive_key
        #: Noise's h after the handshake: a unique, secret-dependent id of this call.
        self.handshake_hash = handshake_hash
        #: The cipher suite of the handshake; the call's frames use its AEAD.
        self.suite = suite


def _ephemeral(ephemeral_private: bytes | None) -> X25519PrivateKey:
    # Tests pass a fixed ephemeral key to compare with another implementation.
    if ephemeral_private is None:
        return X25519PrivateKey.generate()
    return X25519PrivateKey.from_private_bytes(ephemeral_private)


def _public(key: X25519PrivateKey) -> bytes:
    return key.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)


class InitiatorHandshake:
    """The caller's side: writes HELLO's Noise message, reads WELCOME's."""

    def __init__(
        self,
        static_private: bytes,
        responder_static_public: bytes,
        prologue: bytes,
        *,
        suite: Suite = Suite.CHACHAPOLY,
        ephemeral_private: bytes | None = None,
    ) -> None:
        self.suite = suite
        self._s = X25519PrivateKey.from_private_bytes(static_private)
        self._rs = responder_static_public
        self._e = _ephemeral(ephemeral_private)
        self._state = _SymmetricState(prologue, suite)
        self._state.mix_hash(responder_static_public)  # pre-message "<- s"
        self._written = False

    def write_message(self, payload: bytes) -> bytes:
        """``-> e, es, s, ss`` with ``payload`` encrypted; call once."""
        if self._written:
            raise RuntimeError("the first handshake message is written once")
        self._written = True
        st = self._state
        e_pub = _public(self._e)
        st.mix_hash(e_pub)
        st.mix_key(_dh(self._e, self._rs))
        encrypted_static = st.encrypt_and_hash(_public(self._s))
        st.mix_key(_dh(self._s, self._rs))
        return e_pub + encrypted_static + st.encrypt_and_hash(payload)

    def read_message(self, message: bytes) -> tuple[bytes, TransportKeys]:
        """``<- e, ee, se``: returns the responder's payload and this side's transport keys."""
        if not self._written:
            raise RuntimeError("write the first message before reading the answer")
        if len(message) < DH_LEN + TAG_LEN:
            raise ProtocolError("handshake answer too short")
        # Work on a copy: a forged answer must not spoil the state for the genuine one.
        st = self._state.copy()
        re = message[:DH_LEN]
        st.mix_hash(re)
        st.mix_key(_dh(self._e, re))
        st.mix_key(_dh(self._s, re))
        payload = st.decrypt_and_hash(message[DH_LEN:])
        initiator_to_responder, responder_to_initiator = st.split()
        return payload, TransportKeys(
            initiator_to_responder, responder_to_initiator, st.h, self.suite
        )


class ResponderHandshake:
    """The robot's side: reads HELLO's Noise message, writes WELCOME's."""

    def __init__(
        self,
        static_private: bytes,
        prologue: bytes,
        *,
        suite: Suite = Suite.CHACHAPOLY,
        ephemeral_private: bytes | None = None,
    ) -> None:
        self.suite = suite
        self._s = X25519PrivateKey.from_private_bytes(static_private)
        self._e = _ephemeral(ephemeral_private)
        self._state = _SymmetricState(prologue, suite)
        self._state.mix_hash(_public(self._s))  # pre-message "<- s"
        self._re: bytes | None = None
        #: The caller's static public key, known once the first message is read.
        self.remote_static: bytes | None = None

    def read_message(self, message: bytes) -> bytes:
        """``-> e, es, s, ss``: returns the caller's payload; sets :attr:`remote_static`."""
        if self._re is not None:
            raise RuntimeError("the first handshake message is read once")
        if len(message) < DH_LEN + DH_LEN + TAG_LEN + TAG_LEN:
            raise ProtocolError("handshake message too short")
        st = self._state
        re = message[:DH_LEN]
        st.mix_hash(re)
        st.mix_key(_dh(self._s, re))
        rs = st.decrypt_and_hash(message[DH_LEN : DH_LEN + DH_LEN + TAG_LEN])
        st.mix_key(_dh(self._s, rs))
        payload = st.decrypt_and_hash(message[DH_LEN + DH_LEN + TAG_LEN :])
        self._re = re
        self.remote_static = rs
        return payload

    def write_message(self, payload: bytes) -> tuple[bytes, TransportKeys]:
        """``<- e, ee, se`` with ``payload`` encrypted; returns it and this side's keys."""
        if self._re is None or self.remote_static is None:
            raise RuntimeError("read the first message before answering")
        st = self._state
        e_pub = _public(self._e)
        st.mix_hash(e_pub)
        st.mix_key(_dh(self._e, self._re))
        st.mix_key(_dh(self._e, self.remote_static))
        message = e_pub + st.encrypt_and_hash(payload)
        initiator_to_responder, responder_to_initiator = st.split()
        return message, TransportKeys(
            responder_to_initiator, initiator_to_responder, st.h, self.suite
        )
