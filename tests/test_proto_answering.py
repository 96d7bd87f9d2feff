"""How a robot answers HELLOs (sans-IO): both ends exchange bytes in a loop on a fake
clock, as aioquic's tests drive a client and a server, with no transport and no event loop.

The user's end here is :class:`Caller`, a few lines over :func:`start_call` and
:func:`finish_call` (the caller's sans-IO half of the handshake); the robot's is
:class:`Answering`, the policy :mod:`telebot.channels.call` drives.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from telebot.channels.proto.answering import Accept, Answering, Decision, Ignore, Reply
from telebot.channels.proto.frames import (
    INSTANCE_LEN,
    LEGACY_VERSION,
    DataFrame,
    Datagram,
    Hello,
    Retry,
    Welcome,
    decode_frame,
    encode_datagram,
)
from telebot.channels.proto.noise import InitiatorHandshake, Suite, TransportKeys
from telebot.channels.proto.session import Answer, CallSession, finish_call, start_call
from telebot.errors import AuthenticationError, ProtocolError
from telebot.identity import Contact, ContactBook, Identity, Role

ALICE = Identity.generate("alice")
BOB = Identity.generate("bob")
MALLORY = Identity.generate("mallory")  # not a contact
ROBOT = Identity.generate("guiabot")
C, A = Suite.CHACHAPOLY, Suite.AESGCM
INTERVAL, TIMEOUT = 0.05, 1.0
HELLO_RETRY = 0.25  # how often a caller repeats its HELLO (as UserEndpoint does)


def contacts() -> ContactBook:
    return ContactBook(
        Path("contacts.toml"),  # never read nor written here
        {
            "alice": Contact("alice", ALICE.public_key, Role.DRIVER),
            "bob": Contact("bob", BOB.public_key, Role.OBSERVER),
        },
    )


def robot(*, suites: tuple[Suite, ...] = (C,), cache_size: int = 256) -> Answering:
    return Answering(
        ROBOT.name,
        ROBOT.private_key,
        contacts(),
        suites=suites,
        heartbeat_interval=INTERVAL,
        timeout=TIMEOUT,
        cache_size=cache_size,
    )


@dataclass
class Caller:
    """The user's end: sends its HELLO, repeats it every :data:`HELLO_RETRY` until an
    answer comes, writes it again after a RETRY, and reads the WELCOME."""

    identity: Identity
    ts: int
    offers: tuple[Suite, ...] = (C,)
    call_id: bytes = field(default_factory=lambda: os.urandom(8))
    instance: bytes = field(default_factory=lambda: os.urandom(INSTANCE_LEN))
    answer: Answer | None = None
    keys: TransportKeys | None = None
    sent: int = 0
    _last_sent: float | None = None

    def __post_init__(self) -> None:
        self.write(self.offers[0])

    def write(self, suite: Suite) -> None:
        self.hello, self.handshake = start_call(
            self.identity.private_key,
            ROBOT.public_key,
            caller=self.identity.name,
            instance=self.instance,
            call_id=self.call_id,
            wall_time_ns=self.ts,
            offers=self.offers,
            suite=suite,
        )
        self._last_sent = None  # the new HELLO goes out at once

    def due(self, now: float) -> bytes | None:
        """The HELLO if it is time to (re)send it."""
        if self.answer is not None:
            return None
        if self._last_sent is not None and now - self._last_sent < HELLO_RETRY:
            return None
        self._last_sent = now
        self.sent += 1
        return self.hello.encode()

    def receive(self, data: bytes) -> None:
        frame = decode_frame(data)
        if isinstance(frame, Retry):
            if frame.suite != self.handshake.suite:
                self.write(Suite(frame.suite))
            return
        assert isinstance(frame, Welcome)
        if self.answer is None:
            self.answer, self.keys = finish_call(self.handshake, frame)


def sent(decision: Decision) -> bytes | None:
    """What the robot sends back for ``decision`` (None: nothing)."""
    if isinstance(decision, Reply):
        return decision.frame
    if isinstance(decision, Accept):
        return decision.welcome
    return None


def run(
    caller: Caller, answering: Answering, *, lose: int = 0, until: float = 5.0, step: float = 0.05
) -> list[Decision]:
    """Exchange bytes on a fake clock until the caller has an answer (or ``until``);
    the link loses the robot's first ``lose`` answers. Returns the robot's decisions."""
    decisions: list[Decision] = []
    now = 0.0
    while caller.answer is None and now < until:
        data = caller.due(now)
        if data is not None:
            decision = answering.receive(data, caller.identity.name, now)
            decisions.append(decision)
            answer = sent(decision)
            if answer is not None:
                if lose > 0:
                    lose -= 1
                else:
                    caller.receive(answer)
        now += step
    return decisions


def accept(decision: Decision) -> Accept:
    assert isinstance(decision, Accept), decision
    return decision


def caller_session(caller: Caller, now: float = 0.0) -> CallSession:
    assert caller.keys is not None
    return CallSession(
        caller.call_id, caller.keys, heartbeat_interval=INTERVAL, timeout=TIMEOUT, now=now
    )


# --------------------------------------------------------------------------- calls


def test_a_call_comes_up_over_a_perfect_link() -> None:
    answering = robot()
    caller = Caller(ALICE, ts=1)
    decisions = run(caller, answering)
    assert len(decisions) == 1
    call = accept(decisions[0])
    assert caller.answer == Answer(True, ROBOT.name, role="driver")
    assert call.contact.name == "alice" and call.contact.role == Role.DRIVER
    assert answering.live == [caller.call_id]
    # The two ends hold each other's keys: what the user seals, the robot opens.
    frame = caller_session(caller).seal(encode_datagram(b"chat", "hi"))
    decoded = decode_frame(frame)
    assert isinstance(decoded, DataFrame)
    assert call.session.open(decoded, 0.1) == Datagram("chat", "hi")


def test_retransmitted_hellos_get_the_cached_answer_and_one_call() -> None:
    """The link eats the robot's first two WELCOMEs: the caller's repeats of its HELLO
    are answered with the very same bytes, and no second call is made."""
    answering = robot()
    caller = Caller(ALICE, ts=1)
    decisions = run(caller, answering, lose=2)
    assert caller.sent == 3 and caller.answer is not None and caller.answer.accepted
    first = accept(decisions[0])
    assert decisions[1:] == [Reply(first.hello, first.welcome)] * 2
    assert answering.live == [caller.call_id]
    frame = caller_session(caller).seal(encode_datagram(b"chat", "hi"))
    decoded = decode_frame(frame)
    assert isinstance(decoded, DataFrame)
    assert first.session.open(decoded, 1.0) == Datagram("chat", "hi")


def test_a_repeated_hello_keeps_a_silent_call_up_until_the_caller_is_heard() -> None:
    """While an accepted call has heard nothing else, the repeats of its HELLO are its
    only sign of life; once the caller's frames come, they are what counts."""
    answering = robot()
    caller = Caller(ALICE, ts=1)
    call = accept(answering.receive(caller.hello.encode(), "alice", 0.0))
    assert call.session.last_heard == 0.0
    answering.receive(caller.hello.encode(), "alice", 0.9)
    assert call.session.last_heard == 0.9 and not call.session.timed_out(1.5)
    caller.receive(call.welcome)
    beat = decode_frame(caller_session(caller, 1.0).seal_heartbeat(1.0))
    assert isinstance(beat, DataFrame)
    call.session.open(beat, 1.0)
    answering.receive(caller.hello.encode(), "alice", 1.8)  # an old copy, late
    assert call.session.last_heard == 1.0


def test_a_cipher_retry_then_the_call_with_the_robots_pick() -> None:
    """The caller prefers AES-GCM, the robot only takes ChaCha20-Poly1305: a RETRY (no
    cryptography, not cached), then the HELLO written again, accepted with that suite."""
    answering = robot(suites=(C,))
    caller = Caller(ALICE, ts=1, offers=(A, C))
    decisions = run(caller, answering)
    assert [type(d) for d in decisions] == [Reply, Accept]
    assert isinstance(decisions[0], Reply) and decisions[0].code == "cipher_retry"
    assert decode_frame(decisions[0].frame) == Retry(caller.call_id, C)
    assert accept(decisions[1]).session.suite == C
    assert caller.answer is not None and caller.answer.accepted


# --------------------------------------------------------------------------- refusals


def test_a_stranger_is_refused_with_a_warning_and_its_repeats_get_the_same_refusal() -> None:
    answering = robot()
    caller = Caller(MALLORY, ts=1)
    decisions = run(caller, answering, lose=1)
    assert caller.answer == Answer(False, ROBOT.name, reason="not in the contact list of guiabot")
    first, repeat = decisions
    assert isinstance(first, Reply) and first.code == "not_a_contact"
    assert first.warning == "refused a call from 'mallory': key not in the contact list"
    assert repeat == Reply(first.hello, first.frame)  # from the cache: no code, no warning
    assert answering.live == []


def test_no_common_cipher_suite_is_refused_naming_both_sides() -> None:
    answering = robot(suites=(A,))
    caller = Caller(ALICE, ts=1, offers=(C,))
    (decision,) = run(caller, answering)
    assert isinstance(decision, Reply) and decision.code == "no_common_cipher"
    assert decision.warning is not None and "see [call] cipher" in decision.warning
    assert caller.answer is not None and caller.answer.reason == (
        "no common cipher suite: alice offers chachapoly, guiabot accepts aesgcm"
    )


def test_a_closing_robot_refuses_new_calls() -> None:
    answering = robot()
    answering.close()
    caller = Caller(ALICE, ts=1)
    (decision,) = run(caller, answering)
    assert isinstance(decision, Reply) and decision.code == "closing"
    assert caller.answer == Answer(False, ROBOT.name, reason="guiabot is shutting down")
    assert answering.live == []


def _old_hello(
    identity: Identity, ts: int, *, header_name: str | None = None
) -> tuple[Hello, InitiatorHandshake]:
    """A HELLO as a client of protocol version 1 writes it (its header naming
    ``header_name``, the identity's name unless told)."""
    name = identity.name if header_name is None else header_name
    unsigned = Hello(os.urandom(8), name, os.urandom(8), b"", 1, (1,), LEGACY_VERSION)
    handshake = InitiatorHandshake(identity.private_key, ROBOT.public_key, unsigned.prologue)
    message = handshake.write_message(f'{{"user": "{identity.name}", "ts": {ts}}}'.encode())
    return Hello(unsigned.call_id, name, unsigned.instance, message, 1, (1,), 1), handshake


def test_an_old_client_is_refused_in_its_version_and_warned_about_once() -> None:
    answering = robot()
    hello, handshake = _old_hello(ALICE, 1)
    first = answering.receive(hello.encode(), None, 0.0)  # on the version-1 key
    again = answering.receive(hello.encode(), None, 0.25)
    assert isinstance(first, Reply) and first.code == "old_protocol_version"
    assert first.warning is not None and "protocol version 1" in first.warning
    assert again == Reply(hello, first.frame)
    assert first.frame[:2] == bytes([LEGACY_VERSION, 2])  # a WELCOME it can read
    answer, _ = finish_call(handshake, Welcome(hello.call_id, first.frame[10:]))
    assert not answer.accepted and "upgrade telebot" in answer.reason
    # Another call from the same old client is refused again, without a second warning.
    other, _ = _old_hello(ALICE, 2)
    decision = answering.receive(other.encode(), None, 1.0)
    assert isinstance(decision, Reply) and decision.code == "old_protocol_version"
    assert decision.warning is None


# --------------------------------------------------------------------------- replays


def test_a_replayed_hello_is_refused_once_its_answer_left_the_cache() -> None:
    """A HELLO recorded off the wire and played back later, after its call ended and its
    answer was forgotten, is older than the newest HELLO the robot accepted from that
    caller: a replay, ignored (no refusal to sign, no call)."""
    answering = robot(cache_size=1)
    recorded = Caller(ALICE, ts=100)
    call = accept(run(recorded, answering)[0])
    answering.ended(call.hello.call_id)
    newer = Caller(ALICE, ts=200)  # pushes the recorded call's answer out of the cache
    accept(run(newer, answering)[0])
    assert answering.receive(recorded.hello.encode(), "alice", 9.0) == Ignore("replayed_hello")
    # Same timestamp on another call id (the caller's clock stepped back): a replay too.
    same_ts = Caller(ALICE, ts=200)
    assert run(same_ts, answering, until=0.1) == [Ignore("replayed_hello")]
    assert answering.live == [newer.call_id]


def test_the_replay_guard_is_per_caller() -> None:
    """Bob's clock running behind alice's does not make his HELLO a replay."""
    answering = robot()
    accept(run(Caller(ALICE, ts=1_000), answering)[0])
    bob = Caller(BOB, ts=5)
    accept(run(bob, answering)[0])
    assert bob.answer is not None and bob.answer.role == "observer"


def test_strangers_leave_no_per_caller_state() -> None:
    """Only contacts' keys get a replay slot (the contact list bounds that memory): a
    stranger calling with ever new keys, or a contact's newest timestamp, change nothing
    for anyone else."""
    answering = robot()
    for n in range(5):
        run(Caller(Identity.generate(f"stranger{n}"), ts=10**18), answering)
    accept(run(Caller(ALICE, ts=1), answering)[0])
    assert list(answering._latest_hello) == [ALICE.public_key]


# --------------------------------------------------------------------------- call ids


def test_another_hello_with_a_cached_call_id_is_ignored() -> None:
    """A HELLO that differs from the one a cached answer went to, with the same call
    id (a newer timestamp: not a replay) makes no second call and gets no answer."""
    answering = robot()
    first = Caller(ALICE, ts=1)
    accept(run(first, answering)[0])
    reuse = Caller(ALICE, ts=2, call_id=first.call_id)
    assert run(reuse, answering, until=0.1) == [Ignore("call_id_reused")]
    assert answering.live == [first.call_id]


def test_a_live_calls_id_in_a_new_hello_is_ignored_after_its_answer_left_the_cache() -> None:
    answering = robot(cache_size=1)
    first = Caller(ALICE, ts=1)
    accept(run(first, answering)[0])
    run(Caller(MALLORY, ts=1), answering)  # its refusal pushes the first answer out
    reuse = Caller(ALICE, ts=2, call_id=first.call_id)
    assert run(reuse, answering, until=0.1) == [Ignore("call_id_reused")]
    assert answering.live == [first.call_id]
    # Once that call has ended, its id is free again (its answer is no longer cached).
    answering.ended(first.call_id)
    later = Caller(ALICE, ts=3, call_id=first.call_id)
    accept(run(later, answering)[0])


def test_a_repeat_for_an_ended_call_gets_silence_and_a_refusals_repeat_does_not() -> None:
    """Answering the repeated HELLO of a call that ended would hand the caller a call
    that no longer exists here; a refused call has nothing to hand, so its answer repeats."""
    answering = robot()
    caller = Caller(ALICE, ts=1)
    call = accept(run(caller, answering)[0])
    answering.ended(call.hello.call_id)
    assert answering.receive(caller.hello.encode(), "alice", 2.0) == Ignore("hello_for_ended_call")
    stranger = Caller(MALLORY, ts=1)
    (refusal,) = run(stranger, answering)
    assert answering.receive(stranger.hello.encode(), "mallory", 2.0) == sent_again(refusal)


def sent_again(decision: Decision) -> Reply:
    assert isinstance(decision, Reply)
    return Reply(decision.hello, decision.frame)


# --------------------------------------------------------------------------- limits


def test_the_answer_cache_is_bounded_and_forgets_the_oldest_first() -> None:
    """Strangers calling from many call ids cannot grow the robot's memory: past
    ``cache_size`` answers the oldest is forgotten (its repeat is read and answered
    afresh, with a new ephemeral key), the newest are still repeated byte for byte."""
    answering = robot(cache_size=3)
    callers = [Caller(MALLORY, ts=n) for n in range(4)]
    answers = [sent(run(c, answering)[0]) for c in callers]
    for caller, answer in zip(callers[1:], answers[1:], strict=True):
        assert sent(answering.receive(caller.hello.encode(), "mallory", 1.0)) == answer
    again = answering.receive(callers[0].hello.encode(), "mallory", 1.0)
    assert isinstance(again, Reply) and again.code == "not_a_contact"  # read again
    assert again.frame != answers[0]


def test_a_forgotten_accepted_call_is_no_longer_held_as_ended() -> None:
    """The record that a cached answer accepted a call leaves with that answer: once an
    ended call's answer was forgotten, a refusal later cached under the same call id is
    repeated like any refusal (not taken for the ended call's repeat)."""
    answering = robot(cache_size=1)
    caller = Caller(ALICE, ts=1)
    call = accept(run(caller, answering)[0])
    answering.ended(call.hello.call_id)
    run(Caller(MALLORY, ts=1), answering)  # pushes it out
    stranger = Caller(MALLORY, ts=2, call_id=caller.call_id)
    (refusal,) = run(stranger, answering)
    assert isinstance(refusal, Reply) and refusal.code == "not_a_contact"
    assert answering.receive(stranger.hello.encode(), "mallory", 2.0) == sent_again(refusal)


def test_old_clients_are_warned_about_at_most_64_times() -> None:
    answering = robot()
    names = [f"old{n}" for n in range(66)]
    warnings = []
    for name in names:
        identity = Identity.generate(name)
        hello, _ = _old_hello(identity, 1)
        decision = answering.receive(hello.encode(), None, 0.0)
        assert isinstance(decision, Reply) and decision.code == "old_protocol_version"
        warnings.append(decision.warning)
    assert sum(w is not None for w in warnings) == 64
    assert warnings[-2:] == [None, None]


# --------------------------------------------------------------------------- garbage


def test_a_hello_under_another_senders_name_is_not_read() -> None:
    """The key names the sender: a HELLO naming someone else, or on the version-1 key
    (no sender), is ignored before any cryptography."""
    answering = robot()
    caller = Caller(ALICE, ts=1)
    assert answering.receive(caller.hello.encode(), "mallory", 0.0) == Ignore("sender_mismatch")
    assert answering.receive(caller.hello.encode(), None, 0.0) == Ignore("sender_mismatch")
    accept(answering.receive(caller.hello.encode(), "alice", 0.0))  # not spent by those


def test_frames_that_are_not_hellos() -> None:
    answering = robot()
    data = DataFrame.make_header(os.urandom(8), 0) + os.urandom(40)
    assert answering.receive(data, "alice", 0.0) == Ignore("data_on_handshake_key")
    with pytest.raises(ProtocolError, match="does not take Welcome"):
        answering.receive(Welcome(os.urandom(8), os.urandom(48)).encode(), "alice", 0.0)
    with pytest.raises(ProtocolError, match="does not take Retry"):
        answering.receive(Retry(os.urandom(8), C).encode(), "alice", 0.0)


def test_forged_and_mislabelled_hellos_raise_and_change_nothing() -> None:
    answering = robot()
    caller = Caller(ALICE, ts=1)
    hello = caller.hello
    tampered = Hello(
        hello.call_id,
        hello.caller,
        hello.instance,
        hello.noise_message[:-1] + bytes([hello.noise_message[-1] ^ 1]),
        hello.suite,
        hello.offers,
    )
    with pytest.raises(AuthenticationError):
        answering.receive(tampered.encode(), "alice", 0.0)
    # Mallory writes a HELLO whose payload names her but whose header names bob.
    unsigned = Hello(os.urandom(8), "bob", os.urandom(8), b"", C, (C,))
    handshake = InitiatorHandshake(MALLORY.private_key, ROBOT.public_key, unsigned.prologue)
    message = handshake.write_message(b'{"user": "mallory", "ts": 1}')
    mislabelled = Hello(unsigned.call_id, "bob", unsigned.instance, message, C, (C,))
    with pytest.raises(ProtocolError, match="header names 'bob' but its payload 'mallory'"):
        answering.receive(mislabelled.encode(), "bob", 0.0)
    old, _ = _old_hello(MALLORY, 1, header_name="bob")  # an older client's, alike
    with pytest.raises(ProtocolError, match="header names 'bob' but its payload 'mallory'"):
        answering.receive(old.encode(), None, 0.0)
    # Neither left a trace: the genuine HELLO (same call id as the tampered one) is answered.
    accept(answering.receive(hello.encode(), "alice", 0.0))


@given(st.binary(max_size=600))
def test_garbage_raises_protocol_error_or_is_ignored_never_anything_else(data: bytes) -> None:
    answering = robot()
    try:
        decision = answering.receive(data, "alice", 0.0)
    except ProtocolError:
        return
    assert isinstance(decision, Ignore)
