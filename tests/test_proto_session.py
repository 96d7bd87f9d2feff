"""Call set-up and established calls (sans-IO): sealing, replay, heartbeats, the window."""

from __future__ import annotations

import json
import os
import random
from dataclasses import dataclass

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telebot.channels.proto.frames import (
    DataFrame,
    Datagram,
    Hangup,
    Heartbeat,
    Hello,
    Welcome,
    decode_frame,
    encode_datagram,
    encode_hangup,
    encode_heartbeat,
)
from telebot.channels.proto.noise import InitiatorHandshake, ResponderHandshake, Suite
from telebot.channels.proto.replay import WINDOW, ReplayWindow
from telebot.channels.proto.session import (
    Answer,
    CallSession,
    Offer,
    answer_hello,
    finish_call,
    read_hello,
    start_call,
)
from telebot.errors import AuthenticationError, IncompatiblePeer, ProtocolError
from telebot.identity import Identity

ALICE = Identity.generate("alice")
ROBOT = Identity.generate("guiabot")
INTERVAL = 0.05
TIMEOUT = 1.0


# --------------------------------------------------------------------------- helpers


@dataclass
class Pair:
    caller: CallSession
    robot: CallSession
    offer: Offer
    answer: Answer


def make_pair(
    *,
    call_id: bytes | None = None,
    now: float = 0.0,
    interval: float = INTERVAL,
    timeout: float = TIMEOUT,
    answer: Answer | None = None,
    suite: Suite = Suite.CHACHAPOLY,
) -> Pair:
    """Two sides of a call set up through the real handshake, frames serialized in between."""
    call_id = os.urandom(8) if call_id is None else call_id
    hello, handshake = start_call(
        ALICE.private_key,
        ROBOT.public_key,
        caller="alice",
        instance=os.urandom(8),
        call_id=call_id,
        wall_time_ns=1_700_000_000_000_000_000,
        offers=(suite,),
    )
    received_hello = decode_frame(hello.encode())
    assert isinstance(received_hello, Hello)
    offer, robot_handshake = read_hello(ROBOT.private_key, received_hello)
    sent = answer or Answer(True, "guiabot", role="driver")
    welcome, robot_keys = answer_hello(robot_handshake, call_id, sent)
    received_welcome = decode_frame(welcome.encode())
    assert isinstance(received_welcome, Welcome)
    got, caller_keys = finish_call(handshake, received_welcome)
    kwargs = {"heartbeat_interval": interval, "timeout": timeout, "now": now}
    return Pair(
        CallSession(call_id, caller_keys, **kwargs),
        CallSession(call_id, robot_keys, **kwargs),
        offer,
        got,
    )


def frame(data: bytes) -> DataFrame:
    decoded = decode_frame(data)
    assert isinstance(decoded, DataFrame)
    return decoded


def raw_frame(data: bytes) -> DataFrame:
    """Split DATA bytes without decode_frame's checks (to tamper with any header byte)."""
    return DataFrame(data[2:10], int.from_bytes(data[10:18], "big"), data[:18], data[18:])


def datagram(text: str) -> bytes:
    return encode_datagram(b"chat", text)


def flip(data: bytes, bit: int) -> bytes:
    out = bytearray(data)
    out[bit // 8] ^= 1 << (bit % 8)
    return bytes(out)


# --------------------------------------------------------------------------- call set-up


def test_accepted_call_round_trips_offer_and_answer() -> None:
    pair = make_pair(answer=Answer(True, "guiabot", role="driver"))
    assert pair.offer == Offer(ALICE.public_key, "alice", 1_700_000_000_000_000_000)
    assert pair.answer == Answer(True, "guiabot", role="driver", reason="")


def test_rejected_call_round_trips_reason() -> None:
    refusal = Answer(False, "guiabot", reason="not in the contact list of guiabot")
    pair = make_pair(answer=refusal)
    assert pair.answer == refusal
    assert pair.answer.role == ""


def test_both_sides_derive_matching_keys() -> None:
    call_id = os.urandom(8)
    hello, handshake = start_call(
        ALICE.private_key,
        ROBOT.public_key,
        caller="alice",
        instance=b"instance",
        call_id=call_id,
        wall_time_ns=5,
    )
    assert hello.call_id == call_id
    assert hello.caller == "alice"
    assert hello.instance == b"instance"
    offer, responder = read_hello(ROBOT.private_key, hello)
    assert offer.caller_public_key == ALICE.public_key
    assert offer.timestamp_ns == 5
    welcome, robot_keys = answer_hello(responder, call_id, Answer(True, "guiabot", "observer"))
    assert welcome.call_id == call_id
    answer, caller_keys = finish_call(handshake, welcome)
    assert answer.role == "observer"
    assert caller_keys.send_key == robot_keys.receive_key
    assert caller_keys.receive_key == robot_keys.send_key
    assert caller_keys.handshake_hash == robot_keys.handshake_hash
    assert caller_keys.send_key != caller_keys.receive_key


def _hello_bytes() -> tuple[bytes, Hello]:
    hello, _ = start_call(
        ALICE.private_key,
        ROBOT.public_key,
        caller="alice",
        instance=b"INSTANCE",
        call_id=b"CALL-ID!",
        wall_time_ns=1,
    )
    return hello.encode(), hello


@pytest.mark.parametrize(
    ("old", "new"),
    [
        (b"alice", b"alicf"),  # the caller's name
        (b"INSTANCE", b"INSTANCF"),  # the client instance
        (b"CALL-ID!", b"CALL-ID?"),  # the call id
    ],
    ids=["caller", "instance", "call_id"],
)
def test_changed_hello_header_fails_authentication(old: bytes, new: bytes) -> None:
    data, hello = _hello_bytes()
    read_hello(ROBOT.private_key, hello)  # untouched, it authenticates
    assert data.count(old) == 1
    changed = decode_frame(data.replace(old, new))
    assert isinstance(changed, Hello)
    assert changed.noise_message == hello.noise_message
    with pytest.raises(AuthenticationError):
        read_hello(ROBOT.private_key, changed)


@pytest.mark.parametrize(
    ("offers", "suite", "tampered"),
    [
        ((Suite.AESGCM, Suite.CHACHAPOLY), Suite.CHACHAPOLY, (Suite.CHACHAPOLY,)),  # strip
        ((Suite.CHACHAPOLY, Suite.AESGCM), Suite.CHACHAPOLY, (Suite.CHACHAPOLY,)),
        ((Suite.CHACHAPOLY, Suite.AESGCM), Suite.AESGCM, (Suite.AESGCM, Suite.CHACHAPOLY)),
    ],
)
def test_changed_offers_fail_authentication(
    offers: tuple[Suite, ...], suite: Suite, tampered: tuple[Suite, ...]
) -> None:
    """A downgrade: whoever strips or reorders the offers breaks the handshake."""
    hello, _ = start_call(
        ALICE.private_key,
        ROBOT.public_key,
        caller="alice",
        instance=bytes(8),
        call_id=bytes(8),
        wall_time_ns=1,
        offers=offers,
        suite=suite,
    )
    read_hello(ROBOT.private_key, hello)  # untouched, it authenticates
    changed = decode_frame(
        Hello(hello.call_id, "alice", hello.instance, hello.noise_message, suite, tampered).encode()
    )
    assert isinstance(changed, Hello)
    with pytest.raises(AuthenticationError):
        read_hello(ROBOT.private_key, changed)


def test_changed_suite_fails_authentication() -> None:
    """Claiming the HELLO was written with the other (offered) suite breaks it too."""
    offers = (Suite.AESGCM, Suite.CHACHAPOLY)
    hello, _ = start_call(
        ALICE.private_key,
        ROBOT.public_key,
        caller="alice",
        instance=bytes(8),
        call_id=bytes(8),
        wall_time_ns=1,
        offers=offers,
    )
    assert hello.suite == Suite.AESGCM
    changed = Hello(
        hello.call_id, "alice", hello.instance, hello.noise_message, Suite.CHACHAPOLY, offers
    )
    with pytest.raises(AuthenticationError):
        read_hello(ROBOT.private_key, changed)


def test_start_call_writes_with_an_offered_suite_only() -> None:
    with pytest.raises(ValueError, match="not among the offers"):
        start_call(
            ALICE.private_key,
            ROBOT.public_key,
            caller="alice",
            instance=bytes(8),
            call_id=bytes(8),
            wall_time_ns=1,
            offers=(Suite.CHACHAPOLY,),
            suite=Suite.AESGCM,
        )


def test_hello_written_with_an_unknown_suite_is_an_incompatible_peer() -> None:
    _, hello = _hello_bytes()
    newer = Hello(hello.call_id, "alice", hello.instance, hello.noise_message, 9, (9, 1))
    with pytest.raises(IncompatiblePeer, match="cipher suite 9, unknown here"):
        read_hello(ROBOT.private_key, newer)


def test_hello_with_renamed_caller_of_other_length_fails() -> None:
    _, hello = _hello_bytes()
    renamed = Hello(hello.call_id, "mallory", hello.instance, hello.noise_message)
    with pytest.raises(AuthenticationError):
        read_hello(ROBOT.private_key, decode_frame(renamed.encode()))  # type: ignore[arg-type]


def test_hello_for_another_robot_fails() -> None:
    _, hello = _hello_bytes()
    with pytest.raises(AuthenticationError):
        read_hello(Identity.generate("other").private_key, hello)


def test_welcome_from_a_different_robot_key_fails() -> None:
    """An impostor robot answering under the same call id cannot authenticate."""
    call_id = os.urandom(8)
    _, handshake = start_call(
        ALICE.private_key,
        ROBOT.public_key,
        caller="alice",
        instance=bytes(8),
        call_id=call_id,
        wall_time_ns=1,
    )
    impostor = Identity.generate("guiabot")
    # The impostor can only answer a HELLO made out to its own key.
    hello_to_impostor, _ = start_call(
        ALICE.private_key,
        impostor.public_key,
        caller="alice",
        instance=bytes(8),
        call_id=call_id,
        wall_time_ns=1,
    )
    _, impostor_handshake = read_hello(impostor.private_key, hello_to_impostor)
    welcome, _ = answer_hello(impostor_handshake, call_id, Answer(True, "guiabot", "admin"))
    with pytest.raises(AuthenticationError):
        finish_call(handshake, welcome)


def test_welcome_of_another_call_fails() -> None:
    """The real robot's answer to one HELLO does not finish another (no WELCOME replay)."""
    first, first_hs = start_call(
        ALICE.private_key,
        ROBOT.public_key,
        caller="alice",
        instance=bytes(8),
        call_id=bytes(8),
        wall_time_ns=1,
    )
    _, second_hs = start_call(
        ALICE.private_key,
        ROBOT.public_key,
        caller="alice",
        instance=bytes(8),
        call_id=bytes(8),
        wall_time_ns=1,
    )
    _, robot_hs = read_hello(ROBOT.private_key, first)
    welcome, _ = answer_hello(robot_hs, bytes(8), Answer(True, "guiabot", "driver"))
    with pytest.raises(AuthenticationError):
        finish_call(second_hs, welcome)
    assert finish_call(first_hs, welcome)[0].accepted


def _raw_hello(payload: bytes) -> Hello:
    unsigned = Hello(bytes(8), "alice", bytes(8), b"")
    initiator = InitiatorHandshake(ALICE.private_key, ROBOT.public_key, unsigned.prologue)
    return Hello(bytes(8), "alice", bytes(8), initiator.write_message(payload))


@pytest.mark.parametrize(
    "payload",
    [
        b"not json",
        b"\xff\xfe",
        b"[1, 2]",
        b"{}",
        json.dumps({"user": "alice"}).encode(),
        json.dumps({"user": "alice", "ts": "1"}).encode(),
        json.dumps({"user": "alice", "ts": True}).encode(),
        json.dumps({"user": 5, "ts": 1}).encode(),
    ],
)
def test_authentic_hello_with_bad_payload_is_a_protocol_error(payload: bytes) -> None:
    with pytest.raises(ProtocolError) as info:
        read_hello(ROBOT.private_key, _raw_hello(payload))
    assert not isinstance(info.value, AuthenticationError)


@pytest.mark.parametrize(
    "body",
    [
        b"not json",
        b"null",
        b"{}",
        json.dumps({"accepted": 1, "robot": "guiabot"}).encode(),
        json.dumps({"accepted": True}).encode(),
        json.dumps({"accepted": True, "robot": "guiabot", "role": 3}).encode(),
        json.dumps({"accepted": False, "robot": "guiabot", "reason": None}).encode(),
    ],
)
def test_authentic_welcome_with_bad_payload_is_a_protocol_error(body: bytes) -> None:
    hello, handshake = start_call(
        ALICE.private_key,
        ROBOT.public_key,
        caller="alice",
        instance=bytes(8),
        call_id=bytes(8),
        wall_time_ns=1,
    )
    responder = ResponderHandshake(ROBOT.private_key, hello.prologue)
    responder.read_message(hello.noise_message)
    message, _ = responder.write_message(body)
    with pytest.raises(ProtocolError) as info:
        finish_call(handshake, Welcome(bytes(8), message))
    assert not isinstance(info.value, AuthenticationError)


# --------------------------------------------------------------------------- sealing and opening


@pytest.mark.parametrize("suite", list(Suite), ids=lambda s: s.label)
def test_seal_and_open_both_ways(suite: Suite) -> None:
    pair = make_pair(suite=suite)
    assert pair.caller.suite is pair.robot.suite is suite
    sealed = pair.caller.seal(datagram("hi robot"))
    assert sealed[:2] == b"\x02\x03"
    assert sealed[2:10] == pair.caller.call_id
    assert b"hi robot" not in sealed
    assert pair.robot.open(frame(sealed), now=0.1) == Datagram("chat", "hi robot")
    back = pair.robot.seal(encode_hangup("bye"))
    assert pair.caller.open(frame(back), now=0.2) == Hangup("bye")
    assert pair.caller.stats.frames_sent == 1
    assert pair.caller.stats.frames_received == 1
    assert pair.robot.stats.frames_received == 1
    assert not pair.robot.stats.rejected


def test_the_gate_lets_each_genuine_frame_through_once_before_it_is_opened() -> None:
    """A copy of a genuine frame put back on the key is refused by the gate even before
    the first copy was opened (a replayer cannot fill the queue with it), forgeries and
    other calls' frames are refused, and the frame then opens as usual."""
    pair = make_pair()
    first, second = (pair.caller.seal(datagram(text)) for text in ("one", "two"))
    assert pair.robot.authentic(first)
    assert not pair.robot.authentic(first)  # the replayed copy, still unopened
    assert not pair.robot.authentic(flip(second, 8 * 30))  # a changed byte: forged
    assert not pair.robot.authentic(make_pair().caller.seal(datagram("other call")))
    assert pair.robot.authentic(second)  # out of order is fine, once
    assert pair.robot.open(frame(second), now=0.1) == Datagram("chat", "two")
    assert pair.robot.open(frame(first), now=0.1) == Datagram("chat", "one")


def test_the_suites_seal_differently_and_do_not_open_each_other() -> None:
    """Same inputs, other suite: other keys, so a frame of one never opens in the other."""
    chacha = make_pair(call_id=bytes(8), suite=Suite.CHACHAPOLY)
    aes = make_pair(call_id=bytes(8), suite=Suite.AESGCM)
    sealed = aes.caller.seal(datagram("x"))
    assert aes.robot.open(frame(sealed), now=0.0) == Datagram("chat", "x")
    with pytest.raises(AuthenticationError):
        chacha.robot.open(frame(sealed), now=0.0)


def test_counters_increase_from_zero() -> None:
    pair = make_pair()
    counters = [frame(pair.caller.seal(datagram(str(n)))).counter for n in range(5)]
    assert counters == [0, 1, 2, 3, 4]


def test_a_side_cannot_open_its_own_frames() -> None:
    pair = make_pair()
    with pytest.raises(AuthenticationError):
        pair.caller.open(frame(pair.caller.seal(datagram("echo"))), now=0.0)
    assert pair.caller.stats.rejected["forged"] == 1


def test_replayed_frame_is_refused_and_counted() -> None:
    pair = make_pair()
    sealed = pair.caller.seal(datagram("once"))
    assert pair.robot.open(frame(sealed), now=0.1) == Datagram("chat", "once")
    for n in range(1, 4):
        with pytest.raises(AuthenticationError, match="replayed"):
            pair.robot.open(frame(sealed), now=0.2)
        assert pair.robot.stats.rejected["replayed"] == n
    assert pair.robot.stats.frames_received == 1
    assert pair.robot.stats.rejected["forged"] == 0


def test_every_tampered_byte_is_forged() -> None:
    pair = make_pair()
    sealed = pair.caller.seal(datagram("steer left"))
    flips = 0
    for byte in range(len(sealed)):
        for bit in (0, 7):
            with pytest.raises(AuthenticationError):
                pair.robot.open(raw_frame(flip(sealed, byte * 8 + bit)), now=0.5)
            flips += 1
    assert pair.robot.stats.rejected["forged"] == flips
    assert pair.robot.stats.rejected["replayed"] == 0
    assert pair.robot.stats.frames_received == 0
    assert pair.robot.last_heard == 0.0  # forgeries are no sign of life
    # The original still opens: the forgeries changed nothing.
    assert pair.robot.open(frame(sealed), now=0.6) == Datagram("chat", "steer left")


def test_frame_of_another_call_is_forged() -> None:
    call_id = os.urandom(8)
    first, second = make_pair(call_id=call_id), make_pair(call_id=call_id)
    sealed = second.caller.seal(datagram("wrong call"))
    with pytest.raises(AuthenticationError):
        first.robot.open(frame(sealed), now=0.1)
    assert first.robot.stats.rejected["forged"] == 1
    assert second.robot.open(frame(sealed), now=0.1) == Datagram("chat", "wrong call")


def test_reordered_frames_are_accepted_once_each() -> None:
    pair = make_pair()
    sealed = [pair.caller.seal(datagram(str(n))) for n in range(64)]
    order = list(range(64))
    random.Random(7).shuffle(order)
    for n in order:
        assert pair.robot.open(frame(sealed[n]), now=0.1) == Datagram("chat", str(n))
    for n in order:
        with pytest.raises(AuthenticationError):
            pair.robot.open(frame(sealed[n]), now=0.1)
    assert pair.robot.stats.frames_received == 64
    assert pair.robot.stats.rejected["replayed"] == 64


def test_frames_older_than_the_window_are_refused() -> None:
    pair = make_pair()
    sealed = [pair.caller.seal(datagram(str(n))) for n in range(WINDOW + 100)]
    newest = WINDOW + 99
    pair.robot.open(frame(sealed[newest]), now=0.1)
    oldest_kept = newest - (WINDOW - 1)
    for n in (0, 50, oldest_kept - 1):
        with pytest.raises(AuthenticationError, match="too old"):
            pair.robot.open(frame(sealed[n]), now=0.1)
    assert pair.robot.stats.rejected["replayed"] == 3
    assert pair.robot.open(frame(sealed[oldest_kept]), now=0.1) == Datagram(
        "chat", str(oldest_kept)
    )
    assert pair.robot.open(frame(sealed[newest - 1]), now=0.1) == Datagram("chat", str(newest - 1))


def test_authentic_but_malformed_frame() -> None:
    pair = make_pair()
    sealed = pair.caller.seal(b"\x09garbage")
    with pytest.raises(ProtocolError) as info:
        pair.robot.open(frame(sealed), now=0.4)
    assert not isinstance(info.value, AuthenticationError)
    assert pair.robot.stats.rejected["malformed"] == 1
    # It was authentic: a sign of life, and its counter is used up.
    assert pair.robot.last_heard == 0.4
    assert pair.robot.stats.frames_received == 1
    with pytest.raises(AuthenticationError):
        pair.robot.open(frame(sealed), now=0.5)
    assert pair.robot.stats.rejected["replayed"] == 1


# --------------------------------------------------------------------------- heartbeats and timing


def test_heartbeat_cadence() -> None:
    side = make_pair(now=10.0).caller
    assert side.heartbeat_due(10.0)
    assert side.next_deadline() == 10.0
    side.seal_heartbeat(10.0)
    assert not side.heartbeat_due(10.0)
    assert not side.heartbeat_due(10.0 + INTERVAL * 0.99)
    assert side.heartbeat_due(10.0 + INTERVAL)
    assert side.next_deadline() == pytest.approx(10.0 + INTERVAL)
    # Sent a little late, the schedule keeps its phase instead of drifting.
    side.seal_heartbeat(10.0 + INTERVAL * 1.2)
    assert side.next_deadline() == pytest.approx(10.0 + 2 * INTERVAL)
    assert side.stats.frames_sent == 2


def test_heartbeats_are_sealed_in_sequence() -> None:
    pair = make_pair()
    for n, t in enumerate([0.0, 0.05, 0.1], start=1):
        message = pair.robot.open(frame(pair.caller.seal_heartbeat(t)), now=t + 0.001)
        assert isinstance(message, Heartbeat)
        assert message.seq == n
        assert message.sent_us == round(t * 1e6)


def test_a_stall_sends_one_heartbeat_not_a_burst() -> None:
    side = make_pair().caller
    side.seal_heartbeat(0.0)
    sent = 0
    while side.heartbeat_due(5.0) and sent < 10:
        side.seal_heartbeat(5.0)
        sent += 1
    assert 1 <= sent <= 2  # no catching up on the 100 heartbeats missed
    assert not side.heartbeat_due(5.0)
    assert side.heartbeat_due(5.0 + INTERVAL)


def test_late_heartbeat_schedules_the_next_one_in_the_future() -> None:
    side = make_pair().caller
    side.seal_heartbeat(0.0)
    side.seal_heartbeat(5.0)
    assert not side.heartbeat_due(5.0)


def test_timeout_and_deadline() -> None:
    pair = make_pair(now=100.0)
    robot = pair.robot
    assert not robot.timed_out(100.0 + TIMEOUT)
    assert robot.timed_out(100.0 + TIMEOUT + 1e-6)
    robot.seal_heartbeat(100.0)
    assert robot.next_deadline() == pytest.approx(100.0 + INTERVAL)
    # Something authentic at 100.7 postpones the timeout to 101.7.
    robot.open(frame(pair.caller.seal(datagram("alive"))), now=100.7)
    assert robot.last_heard == 100.7
    assert not robot.timed_out(101.6)
    assert robot.timed_out(101.71)
    # Long without sending, the timeout is the next thing to happen.
    slow = make_pair(now=0.0, interval=5.0, timeout=1.0).robot
    slow.seal_heartbeat(0.0)
    assert slow.next_deadline() == pytest.approx(1.0)
    # A late-delivered frame with an older 'now' does not move last_heard back.
    robot.open(frame(pair.caller.seal(datagram("late"))), now=100.2)
    assert robot.last_heard == 100.7


def test_forged_and_replayed_frames_do_not_keep_a_call_alive() -> None:
    pair = make_pair(now=0.0)
    sealed = pair.caller.seal(datagram("x"))
    pair.robot.open(frame(sealed), now=0.5)
    with pytest.raises(AuthenticationError):
        pair.robot.open(frame(sealed), now=1.4)
    with pytest.raises(AuthenticationError):
        pair.robot.open(raw_frame(flip(sealed, 200)), now=1.4)
    assert pair.robot.last_heard == 0.5
    assert pair.robot.timed_out(1.6)


def test_rtt_from_echoed_heartbeats() -> None:
    pair = make_pair(now=1.0)
    a, b = pair.caller, pair.robot
    assert a.stats.rtt is None
    b.open(frame(a.seal_heartbeat(1.0)), now=1.01)
    assert b.stats.rtt is None  # A's first heartbeat echoes nothing
    echo = b.seal_heartbeat(1.02)
    message = a.open(frame(echo), now=1.03)
    assert isinstance(message, Heartbeat)
    assert message.echo_us == 1_000_000
    assert message.echo_delay_us == pytest.approx(10_000, abs=1)
    assert a.stats.rtt == pytest.approx(0.02, abs=2e-6)
    # And the other way round: A echoes B's heartbeat after holding it 0.02 s.
    b.open(frame(a.seal_heartbeat(1.05)), now=1.08)
    assert b.stats.rtt == pytest.approx(1.08 - 1.02 - 0.02, abs=2e-6)


def test_nonsense_echo_is_ignored() -> None:
    pair = make_pair()
    a, b = pair.caller, pair.robot
    b.open(frame(a.seal_heartbeat(1.0)), now=1.01)
    a.open(frame(b.seal_heartbeat(1.02)), now=1.03)
    assert a.stats.rtt == pytest.approx(0.02, abs=2e-6)
    # An echo from the future (negative RTT) or from long ago (over 60 s) is not trusted.
    for echo_us in (5_000_000, 1):
        beat = Heartbeat(seq=99, sent_us=1, echo_us=echo_us, echo_delay_us=0)
        a.open(frame(b.seal(encode_heartbeat(beat))), now=100.0)
        assert a.stats.rtt == pytest.approx(0.02, abs=2e-6)


def test_loss_estimate_when_every_other_heartbeat_is_dropped() -> None:
    pair = make_pair()
    a, b = pair.caller, pair.robot
    for n in range(80):
        t = n * INTERVAL
        sealed = a.seal_heartbeat(t)
        if n % 2 == 0:
            b.open(frame(sealed), now=t + 0.01)
    assert b.stats.loss == pytest.approx(0.5, abs=0.02)
    assert a.stats.loss == 0.0


def test_no_loss_and_reordering_is_not_loss() -> None:
    pair = make_pair()
    a, b = pair.caller, pair.robot
    beats = [a.seal_heartbeat(n * INTERVAL) for n in range(30)]
    for n in [*range(0, 30, 2), *range(1, 30, 2)]:
        b.open(frame(beats[n]), now=2.0)
    assert b.stats.loss == 0.0


def test_loss_recovers_when_heartbeats_come_back() -> None:
    pair = make_pair()
    a, b = pair.caller, pair.robot
    for n in range(200):
        sealed = a.seal_heartbeat(n * INTERVAL)
        if n < 50 and n % 4:
            continue  # three quarters lost at first
        b.open(frame(sealed), now=n * INTERVAL)
        if n == 49:
            assert b.stats.loss == pytest.approx(0.75, abs=0.05)
    assert b.stats.loss == 0.0


# --------------------------------------------------------------------------- the replay window


def test_window_fresh_counters() -> None:
    window = ReplayWindow()
    assert window.check(0)
    assert window.check(2**64 - 1)
    window.accept(0)
    assert not window.check(0)
    assert window.check(1)
    window.accept(5)  # 1..4 skipped, still acceptable later
    for n in (1, 2, 3, 4, 6, 1000):
        assert window.check(n)
    assert not window.check(5)


def test_window_check_changes_nothing() -> None:
    window = ReplayWindow()
    for _ in range(3):
        assert window.check(7)
    window.accept(7)
    assert not window.check(7)
    assert window.check(3)
    assert window.check(3)


def test_window_duplicates() -> None:
    window = ReplayWindow()
    for n in (10, 3, 7, 11, 4):
        assert window.check(n)
        window.accept(n)
        assert not window.check(n)
    for n in (10, 3, 7, 11, 4):
        assert not window.check(n)
    for n in (0, 1, 2, 5, 6, 8, 9, 12):
        assert window.check(n)


def test_window_edge() -> None:
    window = ReplayWindow()
    window.accept(WINDOW)
    assert window.check(1)  # offset WINDOW - 1: the oldest counter still inside
    assert not window.check(0)  # offset WINDOW: too old
    window.accept(1)
    assert not window.check(1)
    window.accept(WINDOW + 1)  # slides one: 1 leaves the window (and stays refused)
    assert not window.check(1)
    assert window.check(2)


@pytest.mark.parametrize("jump", [1, 2, WINDOW - 1, WINDOW, WINDOW + 1, 10 * WINDOW, 1_000_000])
def test_window_large_jumps(jump: int) -> None:
    window = ReplayWindow()
    for n in range(100):
        window.accept(n)
    top = 99 + jump
    window.accept(top)
    assert not window.check(top)
    assert window.check(top + 1)
    for n in range(100):  # each of the old ones is a duplicate or too old
        assert not window.check(n)
    for n in range(max(100, top - WINDOW + 1), top):  # the gap is fresh
        assert window.check(n)
    if top - WINDOW >= 0:
        assert not window.check(top - WINDOW)


def test_window_jump_to_a_huge_counter() -> None:
    window = ReplayWindow()
    window.accept(0)
    window.accept(2**63)
    assert not window.check(2**63)
    assert not window.check(0)
    assert window.check(2**63 - 1)


@settings(max_examples=100, deadline=None)
@given(counters=st.lists(st.integers(0, 3 * WINDOW), max_size=200))
def test_window_matches_a_model(counters: list[int]) -> None:
    """Accept-once within WINDOW of the highest, compared with a plain set."""
    window = ReplayWindow()
    seen: set[int] = set()
    highest = -1
    for n in counters:
        expected = n not in seen and (n > highest or highest - n < WINDOW)
        assert window.check(n) == expected
        if expected:
            window.accept(n)
            seen.add(n)
            highest = max(highest, n)
