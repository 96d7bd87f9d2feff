"""The Noise IK handshake: interoperability with ``noiseprotocol`` (both cipher suites),
failures, fuzzing."""

from __future__ import annotations

import os
import warnings

import pytest
from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives.ciphers.aead import AESGCM, ChaCha20Poly1305
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from noise.connection import Keypair, NoiseConnection

from telebot.channels.proto.noise import (
    DH_LEN,
    TAG_LEN,
    InitiatorHandshake,
    ResponderHandshake,
    Suite,
    TransportKeys,
    aead_nonce,
    public_key_of,
)
from telebot.errors import AuthenticationError, ProtocolError

MSG1_OVERHEAD = DH_LEN + DH_LEN + TAG_LEN + TAG_LEN  # e, encrypted s, payload tag
MSG2_OVERHEAD = DH_LEN + TAG_LEN  # e, payload tag

# X25519 points of small order (RFC 7748 section 6; libsodium's blocklist): DH gives zero.
LOW_ORDER_POINTS = [
    bytes(32),
    b"\x01" + bytes(31),
    bytes.fromhex("e0eb7a7c3b41b8ae1656e3faf19fc46ada098deb9c32b1fd866205165f49b800"),
    bytes.fromhex("5f9c95bca3508c24b1d0b1559c83ef5b04445cc4581c8e86d8224eddd09f1157"),
    bytes.fromhex("ec" + "ff" * 30 + "7f"),
    bytes.fromhex("ed" + "ff" * 30 + "7f"),
    bytes.fromhex("ee" + "ff" * 30 + "7f"),
]

keys = st.binary(min_size=32, max_size=32)
prologues = st.binary(max_size=128)
payloads = st.binary(max_size=512)
FAST = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
SUITES = pytest.mark.parametrize("suite", list(Suite), ids=lambda s: s.label)


# --------------------------------------------------------------------------- helpers


def their_side(
    *,
    initiator: bool,
    static_private: bytes,
    prologue: bytes,
    remote_static: bytes | None = None,
    ephemeral_private: bytes | None = None,
    suite: Suite = Suite.CHACHAPOLY,
) -> NoiseConnection:
    """A started ``noiseprotocol`` handshake of the protocol name of ``suite``."""
    conn = NoiseConnection.from_name(suite.protocol_name)
    if initiator:
        conn.set_as_initiator()
    else:
        conn.set_as_responder()
    conn.set_keypair_from_private_bytes(Keypair.STATIC, static_private)
    if remote_static is not None:
        conn.set_keypair_from_public_bytes(Keypair.REMOTE_STATIC, remote_static)
    conn.set_prologue(prologue)
    if ephemeral_private is None:
        conn.start_handshake()
    else:
        conn.set_keypair_from_private_bytes(Keypair.EPHEMERAL, ephemeral_private)
        # noiseprotocol warns (rightly) that a fixed ephemeral key is for tests only.
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", "One of ephemeral keypairs", UserWarning)
            conn.start_handshake()
    return conn


def assert_keys_match_theirs(ours: TransportKeys, theirs: NoiseConnection) -> None:
    """``theirs`` is our peer: both directions agree, with Noise's nonces 0 and 1."""
    assert ours.handshake_hash == bytes(theirs.get_handshake_hash())
    suite = ours.suite
    # Theirs -> ours: their cipher state, our receive key (nonce 1 tells LE from BE).
    for n, text in enumerate([b"first from noiseprotocol", b"second"]):
        sealed = bytes(theirs.encrypt(text))
        assert suite.aead(ours.receive_key).decrypt(suite.nonce(n), sealed, None) == text
    # Ours -> theirs: our send key, their cipher state.
    for n, text in enumerate([b"first from telebot", b"second"]):
        sealed = suite.aead(ours.send_key).encrypt(suite.nonce(n), text, None)
        assert bytes(theirs.decrypt(sealed)) == text
    # The two directions use different keys.
    assert ours.send_key != ours.receive_key


def handshake(
    prologue: bytes = b"prologue",
    payload1: bytes = b"hello",
    payload2: bytes = b"welcome",
) -> tuple[bytes, bytes, bytes, bytes, bytes, bytes]:
    """Fixed keys (static and ephemeral) and the two messages they give."""
    i_s, r_s, i_e, r_e = (bytes([n]) * 32 for n in (1, 2, 3, 4))
    initiator = InitiatorHandshake(i_s, public_key_of(r_s), prologue, ephemeral_private=i_e)
    msg1 = initiator.write_message(payload1)
    responder = ResponderHandshake(r_s, prologue, ephemeral_private=r_e)
    responder.read_message(msg1)
    msg2, _ = responder.write_message(payload2)
    return i_s, r_s, i_e, r_e, msg1, msg2


def flip(data: bytes, bit: int) -> bytes:
    out = bytearray(data)
    out[bit // 8] ^= 1 << (bit % 8)
    return bytes(out)


# --------------------------------------------------------------------------- interoperability


@SUITES
@FAST
@given(i_s=keys, r_s=keys, prologue=prologues, p1=payloads, p2=payloads)
def test_our_initiator_with_their_responder(
    suite: Suite, i_s: bytes, r_s: bytes, prologue: bytes, p1: bytes, p2: bytes
) -> None:
    theirs = their_side(initiator=False, static_private=r_s, prologue=prologue, suite=suite)
    ours = InitiatorHandshake(i_s, public_key_of(r_s), prologue, suite=suite)

    msg1 = ours.write_message(p1)
    assert len(msg1) == MSG1_OVERHEAD + len(p1)
    assert bytes(theirs.read_message(msg1)) == p1
    # Their responder learned our static key from message 1.
    assert theirs.noise_protocol.handshake_state.rs.public_bytes == public_key_of(i_s)

    msg2 = bytes(theirs.write_message(p2))
    assert len(msg2) == MSG2_OVERHEAD + len(p2)
    payload, transport = ours.read_message(msg2)
    assert payload == p2
    assert theirs.handshake_finished
    assert transport.suite is suite
    assert_keys_match_theirs(transport, theirs)


@SUITES
@FAST
@given(i_s=keys, r_s=keys, prologue=prologues, p1=payloads, p2=payloads)
def test_their_initiator_with_our_responder(
    suite: Suite, i_s: bytes, r_s: bytes, prologue: bytes, p1: bytes, p2: bytes
) -> None:
    theirs = their_side(
        initiator=True,
        static_private=i_s,
        prologue=prologue,
        remote_static=public_key_of(r_s),
        suite=suite,
    )
    ours = ResponderHandshake(r_s, prologue, suite=suite)
    assert ours.remote_static is None

    assert ours.read_message(bytes(theirs.write_message(p1))) == p1
    assert ours.remote_static == public_key_of(i_s)

    msg2, transport = ours.write_message(p2)
    assert bytes(theirs.read_message(msg2)) == p2
    assert theirs.handshake_finished
    assert_keys_match_theirs(transport, theirs)


@SUITES
@settings(max_examples=10, deadline=None)
@given(i_s=keys, r_s=keys, i_e=keys, r_e=keys, prologue=prologues, p1=payloads, p2=payloads)
def test_fixed_ephemerals_give_byte_identical_messages(
    suite: Suite,
    i_s: bytes,
    r_s: bytes,
    i_e: bytes,
    r_e: bytes,
    prologue: bytes,
    p1: bytes,
    p2: bytes,
) -> None:
    r_pub = public_key_of(r_s)
    our_init = InitiatorHandshake(i_s, r_pub, prologue, suite=suite, ephemeral_private=i_e)
    their_init = their_side(
        initiator=True,
        static_private=i_s,
        prologue=prologue,
        remote_static=r_pub,
        ephemeral_private=i_e,
        suite=suite,
    )
    msg1 = our_init.write_message(p1)
    assert msg1 == bytes(their_init.write_message(p1))
    assert msg1[:DH_LEN] == public_key_of(i_e)

    our_resp = ResponderHandshake(r_s, prologue, suite=suite, ephemeral_private=r_e)
    their_resp = their_side(
        initiator=False, static_private=r_s, prologue=prologue, ephemeral_private=r_e, suite=suite
    )
    assert our_resp.read_message(msg1) == p1
    assert bytes(their_resp.read_message(msg1)) == p1
    msg2, resp_keys = our_resp.write_message(p2)
    assert msg2 == bytes(their_resp.write_message(p2))
    assert msg2[:DH_LEN] == public_key_of(r_e)

    payload, init_keys = our_init.read_message(msg2)
    assert payload == p2
    assert bytes(their_init.read_message(msg2)) == p2
    # Our two sides agree with each other...
    assert init_keys.send_key == resp_keys.receive_key
    assert init_keys.receive_key == resp_keys.send_key
    assert init_keys.handshake_hash == resp_keys.handshake_hash
    # ...and with theirs: our initiator talks to their responder and vice versa.
    assert_keys_match_theirs(init_keys, their_resp)
    assert_keys_match_theirs(resp_keys, their_init)


def test_fixed_handshake_is_deterministic_and_ephemerals_differ_otherwise() -> None:
    assert handshake() == handshake()
    i_s, r_s = os.urandom(32), os.urandom(32)
    a = InitiatorHandshake(i_s, public_key_of(r_s), b"").write_message(b"")
    b = InitiatorHandshake(i_s, public_key_of(r_s), b"").write_message(b"")
    assert a[:DH_LEN] != b[:DH_LEN]  # fresh ephemeral keys
    assert a != b


def test_protocol_names_nonce_layouts_and_aeads() -> None:
    assert Suite.CHACHAPOLY.protocol_name == b"Noise_IK_25519_ChaChaPoly_BLAKE2s"
    assert Suite.AESGCM.protocol_name == b"Noise_IK_25519_AESGCM_BLAKE2s"
    assert [int(s) for s in Suite] == [1, 2]  # their numbers on the wire
    assert [s.label for s in Suite] == ["chachapoly", "aesgcm"]
    assert aead_nonce is Suite.CHACHAPOLY.nonce
    for nonce in (Suite.CHACHAPOLY.nonce, Suite.AESGCM.nonce):
        assert nonce(0) == bytes(12)
        assert nonce(2**64 - 1) == bytes(4) + b"\xff" * 8
    # ChaChaPoly writes the counter little-endian, AESGCM big-endian (Noise section 12).
    assert Suite.CHACHAPOLY.nonce(1) == bytes(4) + b"\x01" + bytes(7)
    assert Suite.AESGCM.nonce(1) == bytes(11) + b"\x01"
    assert isinstance(Suite.CHACHAPOLY.aead(bytes(32)), ChaCha20Poly1305)
    assert isinstance(Suite.AESGCM.aead(bytes(32)), AESGCM)


@pytest.mark.parametrize(("ours", "theirs"), [(a, b) for a in Suite for b in Suite if a != b])
def test_the_suite_is_bound_into_the_handshake(ours: Suite, theirs: Suite) -> None:
    """Same keys, ephemerals and prologue: another suite fails, in both directions."""
    i_s, r_s, i_e, r_e = (bytes([n]) * 32 for n in (1, 2, 3, 4))
    msg1 = InitiatorHandshake(
        i_s, public_key_of(r_s), b"p", suite=ours, ephemeral_private=i_e
    ).write_message(b"x")
    with pytest.raises(AuthenticationError):
        ResponderHandshake(r_s, b"p", suite=theirs).read_message(msg1)
    # An initiator of the other suite refuses the genuine answer.
    initiator = InitiatorHandshake(i_s, public_key_of(r_s), b"p", suite=ours, ephemeral_private=i_e)
    initiator.write_message(b"x")
    responder = ResponderHandshake(r_s, b"p", suite=ours, ephemeral_private=r_e)
    responder.read_message(msg1)
    msg2, keys = responder.write_message(b"y")
    other = InitiatorHandshake(i_s, public_key_of(r_s), b"p", suite=theirs, ephemeral_private=i_e)
    other.write_message(b"x")
    with pytest.raises(AuthenticationError):
        other.read_message(msg2)
    # The genuine pair agrees, and its keys are not those of the other suite.
    payload, initiator_keys = initiator.read_message(msg2)
    assert payload == b"y" and initiator_keys.suite is keys.suite is ours
    assert initiator_keys.send_key == keys.receive_key


# --------------------------------------------------------------------------- failures


def test_responder_learns_initiator_static_key() -> None:
    i_s, r_s = os.urandom(32), os.urandom(32)
    msg1 = InitiatorHandshake(i_s, public_key_of(r_s), b"p").write_message(b"x")
    responder = ResponderHandshake(r_s, b"p")
    assert responder.read_message(msg1) == b"x"
    assert responder.remote_static == public_key_of(i_s)


def test_different_prologue_fails_on_both_sides() -> None:
    i_s, r_s = os.urandom(32), os.urandom(32)
    msg1 = InitiatorHandshake(i_s, public_key_of(r_s), b"prologue A").write_message(b"x")
    responder = ResponderHandshake(r_s, b"prologue B")
    with pytest.raises(AuthenticationError):
        responder.read_message(msg1)
    assert responder.remote_static is None

    # The same against noiseprotocol, in both roles.
    theirs = their_side(initiator=False, static_private=r_s, prologue=b"prologue B")
    with pytest.raises(InvalidTag):
        theirs.read_message(msg1)

    their_init = their_side(
        initiator=True, static_private=i_s, prologue=b"prologue A", remote_static=public_key_of(r_s)
    )
    with pytest.raises(AuthenticationError):
        ResponderHandshake(r_s, b"prologue B").read_message(bytes(their_init.write_message(b"")))


def test_initiator_detects_responder_with_other_prologue() -> None:
    """The initiator's prologue is bound in too: msg2 from a mismatching h fails."""
    i_s, r_s = os.urandom(32), os.urandom(32)
    initiator = InitiatorHandshake(i_s, public_key_of(r_s), b"same")
    msg1 = initiator.write_message(b"")
    responder = ResponderHandshake(r_s, b"same")
    responder.read_message(msg1)
    msg2, _ = responder.write_message(b"")
    other = InitiatorHandshake(i_s, public_key_of(r_s), b"other")
    other.write_message(b"")
    with pytest.raises(AuthenticationError):
        other.read_message(msg2)
    assert initiator.read_message(msg2)[0] == b""


def test_wrong_responder_key_fails() -> None:
    i_s, r_s, impostor = os.urandom(32), os.urandom(32), os.urandom(32)
    msg1 = InitiatorHandshake(i_s, public_key_of(r_s), b"").write_message(b"secret")
    # Someone who is not the robot cannot read the caller's message...
    with pytest.raises(AuthenticationError):
        ResponderHandshake(impostor, b"").read_message(msg1)

    # ...and a caller who expects another robot rejects the real one's answer.
    initiator = InitiatorHandshake(i_s, public_key_of(impostor), b"")
    msg1 = initiator.write_message(b"")
    with pytest.raises(AuthenticationError):
        ResponderHandshake(r_s, b"").read_message(msg1)


def test_answer_from_other_responder_fails() -> None:
    """A WELCOME made by another responder (for another caller) does not authenticate."""
    i_s, r_s, other_r = os.urandom(32), os.urandom(32), os.urandom(32)
    initiator = InitiatorHandshake(i_s, public_key_of(r_s), b"")
    initiator.write_message(b"")
    stranger = InitiatorHandshake(os.urandom(32), public_key_of(other_r), b"")
    responder = ResponderHandshake(other_r, b"")
    responder.read_message(stranger.write_message(b""))
    msg2, _ = responder.write_message(b"")
    with pytest.raises(AuthenticationError):
        initiator.read_message(msg2)


def test_every_bit_flip_in_message_1_fails() -> None:
    _, r_s, _, r_e, msg1, _ = handshake()
    assert ResponderHandshake(r_s, b"prologue", ephemeral_private=r_e).read_message(msg1)
    for bit in range(len(msg1) * 8):
        responder = ResponderHandshake(r_s, b"prologue", ephemeral_private=r_e)
        with pytest.raises(AuthenticationError):
            responder.read_message(flip(msg1, bit))
        assert responder.remote_static is None


def test_every_bit_flip_in_message_2_fails() -> None:
    i_s, r_s, i_e, _, msg1, msg2 = handshake()
    for bit in [None, *range(len(msg2) * 8)]:
        initiator = InitiatorHandshake(i_s, public_key_of(r_s), b"prologue", ephemeral_private=i_e)
        assert initiator.write_message(b"hello") == msg1
        if bit is None:
            assert initiator.read_message(msg2)[0] == b"welcome"
            continue
        with pytest.raises(AuthenticationError):
            initiator.read_message(flip(msg2, bit))


def test_truncated_or_extended_messages_fail() -> None:
    i_s, r_s, i_e, r_e, msg1, msg2 = handshake()
    for size in range(len(msg1)):
        with pytest.raises(ProtocolError) as info:
            ResponderHandshake(r_s, b"prologue", ephemeral_private=r_e).read_message(msg1[:size])
        if size < MSG1_OVERHEAD:
            assert type(info.value) is ProtocolError  # too short to try
        else:
            assert isinstance(info.value, AuthenticationError)
    with pytest.raises(AuthenticationError):
        ResponderHandshake(r_s, b"prologue").read_message(msg1 + b"\x00")

    for size in [*range(len(msg2)), len(msg2) + 1]:
        initiator = InitiatorHandshake(i_s, public_key_of(r_s), b"prologue", ephemeral_private=i_e)
        initiator.write_message(b"hello")
        message = msg2[:size] if size < len(msg2) else msg2 + b"\x00"
        with pytest.raises(ProtocolError) as info:
            initiator.read_message(message)
        if size < MSG2_OVERHEAD:
            assert type(info.value) is ProtocolError
        else:
            assert isinstance(info.value, AuthenticationError)


@pytest.mark.parametrize("point", LOW_ORDER_POINTS, ids=lambda p: p[:4].hex())
def test_low_order_ephemeral_keys_are_refused(point: bytes) -> None:
    _, r_s, _, _, msg1, msg2 = handshake()
    with pytest.raises(AuthenticationError):
        ResponderHandshake(r_s, b"prologue").read_message(point + msg1[DH_LEN:])
    initiator = InitiatorHandshake(os.urandom(32), public_key_of(r_s), b"prologue")
    initiator.write_message(b"")
    with pytest.raises(AuthenticationError):
        initiator.read_message(point + msg2[DH_LEN:])


def test_misuse_of_the_state_machines_is_refused() -> None:
    i_s, r_s, i_e, r_e, msg1, _ = handshake()
    initiator = InitiatorHandshake(i_s, public_key_of(r_s), b"prologue", ephemeral_private=i_e)
    with pytest.raises(RuntimeError):
        initiator.read_message(bytes(64))
    initiator.write_message(b"hello")
    with pytest.raises(RuntimeError):
        initiator.write_message(b"again")

    responder = ResponderHandshake(r_s, b"prologue", ephemeral_private=r_e)
    with pytest.raises(RuntimeError):
        responder.write_message(b"")
    responder.read_message(msg1)
    with pytest.raises(RuntimeError):
        responder.read_message(msg1)


def test_transport_keys_are_not_interchangeable_between_calls() -> None:
    i_s, r_s = os.urandom(32), os.urandom(32)

    def one_call() -> TransportKeys:
        initiator = InitiatorHandshake(i_s, public_key_of(r_s), b"")
        responder = ResponderHandshake(r_s, b"")
        responder.read_message(initiator.write_message(b""))
        msg2, _ = responder.write_message(b"")
        return initiator.read_message(msg2)[1]

    first, second = one_call(), one_call()
    assert first.send_key != second.send_key
    assert first.handshake_hash != second.handshake_hash
    sealed = ChaCha20Poly1305(first.send_key).encrypt(aead_nonce(0), b"x", None)
    with pytest.raises(InvalidTag):
        ChaCha20Poly1305(second.send_key).decrypt(aead_nonce(0), sealed, None)


# --------------------------------------------------------------------------- fuzzing

_, _R_S, _, _, _MSG1, _MSG2 = handshake()


def mutated(valid: bytes) -> st.SearchStrategy[bytes]:
    """Valid messages with a few bytes changed, cut short or extended."""
    positions = st.integers(0, len(valid) - 1)
    return st.one_of(
        st.tuples(positions, st.integers(0, 255)).map(
            lambda pv: valid[: pv[0]] + bytes([pv[1]]) + valid[pv[0] + 1 :]
        ),
        st.integers(0, len(valid)).map(lambda n: valid[:n]),
        st.binary(max_size=64).map(lambda extra: valid + extra),
        st.sampled_from(LOW_ORDER_POINTS).map(lambda p: p + valid[DH_LEN:]),
    )


@settings(max_examples=150, deadline=None)
@given(data=st.one_of(st.binary(max_size=400), mutated(_MSG1)))
@example(data=b"")
@example(data=bytes(MSG1_OVERHEAD))
@example(data=bytes(MSG1_OVERHEAD - 1))
def test_responder_read_raises_only_protocol_errors(data: bytes) -> None:
    responder = ResponderHandshake(_R_S, b"prologue")
    try:
        payload = responder.read_message(data)
    except ProtocolError:
        assert responder.remote_static is None
    else:  # only the untouched message authenticates
        assert data == _MSG1
        assert payload == b"hello"


@settings(max_examples=150, deadline=None)
@given(data=st.one_of(st.binary(max_size=200), mutated(_MSG2)))
@example(data=b"")
@example(data=bytes(MSG2_OVERHEAD))
@example(data=bytes(MSG2_OVERHEAD - 1))
def test_initiator_read_raises_only_protocol_errors(data: bytes) -> None:
    i_s, r_s, i_e = bytes([1]) * 32, bytes([2]) * 32, bytes([3]) * 32
    initiator = InitiatorHandshake(i_s, public_key_of(r_s), b"prologue", ephemeral_private=i_e)
    initiator.write_message(b"hello")
    try:
        payload, _ = initiator.read_message(data)
    except ProtocolError:
        pass
    else:
        assert data == _MSG2
        assert payload == b"welcome"


def test_a_forged_answer_does_not_spoil_the_handshake_for_the_genuine_one() -> None:
    initiator_static, responder_static = os.urandom(32), os.urandom(32)
    initiator = InitiatorHandshake(initiator_static, public_key_of(responder_static), b"p")
    responder = ResponderHandshake(responder_static, b"p")
    responder.read_message(initiator.write_message(b"hi"))
    genuine, _ = responder.write_message(b"welcome")
    forged = os.urandom(len(genuine))
    with pytest.raises(AuthenticationError):
        initiator.read_message(forged)
    payload, _ = initiator.read_message(genuine)
    assert payload == b"welcome"
