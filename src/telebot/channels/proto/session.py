"""Call set-up and the established call, sans-IO: bytes and ``now`` in, bytes and facts out.

:func:`start_call` / :func:`finish_call` are the caller's side of the handshake,
:func:`read_hello` / :func:`answer_hello` the robot's. Their payloads (inside Noise, so
encrypted and authenticated) are small JSON objects::

    HELLO payload    {"user": "alice", "ts": <caller's wall clock, ns>}
    WELCOME payload  {"accepted": true, "robot": "guiabot", "role": "driver"}
                     {"accepted": false, "robot": "guiabot", "reason": "not in the contact list of guiabot"}

Cipher suites (:class:`~.noise.Suite`) are negotiated in the HELLO: the caller offers
the suites it accepts, preferred first, and writes Noise message 1 with the first; the
robot picks one with :func:`choose_suite`. If it picks another, it answers with a RETRY
naming it and the caller sends the HELLO again written with that suite. The offers are in
the prologue and the suite names the Noise protocol, so an attacker who strips an offer,
or forges a RETRY, makes the handshake fail instead of changing the cipher.

:class:`CallSession` is one side of an established call: it seals and opens DATA
frames with the per-call keys, refuses replays, and keeps heartbeat bookkeeping
(when the next heartbeat is due, when the peer counts as gone, round-trip time, loss).
"""

from __future__ import annotations

import json
from collections import Counter, deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from cryptography.exceptions import InvalidTag

from telebot.channels.proto.frames import (
    DATA_HEADER_LEN,
    DataFrame,
    Heartbeat,
    Hello,
    Message,
    Welcome,
    decode_message,
    encode_heartbeat,
)
from telebot.channels.proto.noise import (
    InitiatorHandshake,
    ResponderHandshake,
    Suite,
    TransportKeys,
)
from telebot.channels.proto.replay import ReplayWindow
from telebot.errors import AuthenticationError, IncompatiblePeer, ProtocolError

__all__ = [
    "Answer",
    "CallSession",
    "CallStats",
    "Offer",
    "answer_hello",
    "choose_suite",
    "describe_suites",
    "finish_call",
    "read_hello",
    "start_call",
]

_MAX_COUNTER = 2**64 - 1
#: Version, type and call id: the first bytes of every DATA frame of a call.
DATA_PREFIX_LEN = 10
_MIN_DATA = DATA_HEADER_LEN + 16  # header and tag
_KNOWN_SUITES = frozenset(Suite)  # IntEnum members equal their numbers
_LOSS_WINDOW = 40  # heartbeats over which loss is estimated (2 s at 20 Hz)


@dataclass(frozen=True, slots=True)
class Offer:
    """What a caller's HELLO says, once authenticated."""

    caller_public_key: bytes
    user: str
    timestamp_ns: int


@dataclass(frozen=True, slots=True)
class Answer:
    """What a robot's WELCOME says, once authenticated."""

    accepted: bool
    robot: str
    role: str = ""
    reason: str = ""


def _json_payload(data: bytes, what: str) -> dict[str, Any]:
    try:
        value = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise ProtocolError(f"{what} payload is not JSON") from exc
    if not isinstance(value, dict):
        raise ProtocolError(f"{what} payload is not a JSON object")
    return value


def choose_suite(offers: Sequence[int], allowed: Sequence[Suite]) -> Suite | None:
    """The suite a robot that allows ``allowed`` (preferred first) picks from ``offers``.

    Both ends' first choice if it is the same (AESGCM when both have AES instructions);
    otherwise ChaChaPoly if both accept it (it is fast on any CPU); otherwise the
    caller's first offer that the robot allows; None when they have none in common.
    Unknown suite numbers in ``offers`` are ignored.
    """
    if not offers or not allowed:
        return None
    if offers[0] == allowed[0]:
        return allowed[0]
    if Suite.CHACHAPOLY in offers and Suite.CHACHAPOLY in allowed:
        return Suite.CHACHAPOLY
    for number in offers:
        if number in allowed:
            return Suite(number)
    return None


def describe_suites(numbers: Sequence[int]) -> str:
    """Suite numbers as people read them, e.g. ``"aesgcm, chachapoly"``."""
    names = [Suite(n).label if n in _KNOWN_SUITES else f"suite {n}" for n in numbers]
    return ", ".join(names) or "none"


def start_call(
    static_private: bytes,
    robot_public: bytes,
    *,
    caller: str,
    instance: bytes,
    call_id: bytes,
    wall_time_ns: int,
    offers: Sequence[Suite] = (Suite.CHACHAPOLY,),
    suite: Suite | None = None,
) -> tuple[Hello, InitiatorHandshake]:
    """The caller's HELLO (send it, and again if no answer comes) and its handshake state.

    ``offers`` are the suites the caller accepts, preferred first; the HELLO is written
    with ``suite`` (default: the first offer; after a RETRY, the one the robot named).
    """
    suite = offers[0] if suite is None else suite
    if suite not in offers:
        raise ValueError(f"cipher suite {suite.label} is not among the offers")
    offered = tuple(int(s) for s in offers)
    unsigned = Hello(call_id, caller, instance, b"", suite, offered)
    handshake = InitiatorHandshake(
        static_private, robot_public, unsigned.prologue, suite=Suite(suite)
    )
    payload = json.dumps({"user": caller, "ts": wall_time_ns}).encode()
    message = handshake.write_message(payload)
    return Hello(call_id, caller, instance, message, suite, offered), handshake


def finish_call(handshake: InitiatorHandshake, welcome: Welcome) -> tuple[Answer, TransportKeys]:
    """Authenticate the robot's WELCOME; raises AuthenticationError if it is not the robot."""
    payload, keys = handshake.read_message(welcome.noise_message)
    data = _json_payload(payload, "WELCOME")
    accepted, robot = data.get("accepted"), data.get("robot")
    role, reason = data.get("role", ""), data.get("reason", "")
    if not isinstance(accepted, bool) or not isinstance(robot, str):
        raise ProtocolError("WELCOME payload lacks 'accepted' or 'robot'")
    if not isinstance(role, str) or not isinstance(reason, str):
        raise ProtocolError("WELCOME payload has a non-text 'role' or 'reason'")
    return Answer(accepted, robot, role, reason), keys


def read_hello(static_private: bytes, hello: Hello) -> tuple[Offer, ResponderHandshake]:
    """Authenticate a HELLO: who is calling (their static key) and when they started.

    The handshake runs with the HELLO's suite; whether that suite is the one to use is
    the caller's business to check first (:func:`choose_suite`).
    """
    if hello.suite not in _KNOWN_SUITES:
        raise IncompatiblePeer(
            f"HELLO written with cipher suite {hello.suite}, unknown here (a newer telebot?)"
        )
    handshake = ResponderHandshake(static_private, hello.prologue, suite=Suite(hello.suite))
    payload = handshake.read_message(hello.noise_message)
    assert handshake.remote_static is not None
    data = _json_payload(payload, "HELLO")
    user, ts = data.get("user"), data.get("ts")
    if not isinstance(user, str) or not isinstance(ts, int) or isinstance(ts, bool):
        raise ProtocolError("HELLO payload lacks 'user' or 'ts'")
    return Offer(handshake.remote_static, user, ts), handshake


def answer_hello(
    handshake: ResponderHandshake, call_id: bytes, answer: Answer
) -> tuple[Welcome, TransportKeys]:
    """The robot's WELCOME for a HELLO read with :func:`read_hello`, and its call keys."""
    body: dict[str, Any] = {"accepted": answer.accepted, "robot": answer.robot}
    if answer.role:
        body["role"] = answer.role
    if answer.reason:
        body["reason"] = answer.reason
    message, keys = handshake.write_message(json.dumps(body).encode())
    return Welcome(call_id, message), keys


@dataclass(slots=True)
class CallStats:
    """Counters and link quality of one established call."""

    frames_sent: int = 0
    frames_received: int = 0
    #: Sealed frames the transport refused to publish (their datagrams are lost).
    send_failures: int = 0
    #: Frames refused, by reason: "forged" (fails AEAD), "replayed", "malformed".
    rejected: Counter[str] = field(default_factory=Counter)
    #: Latest round-trip time in seconds, from heartbeats (None until measured).
    rtt: float | None = None
    #: Share of the peer's recent heartbeats that did not arrive (0..1).
    loss: float = 0.0


class CallSession:
    """One side of an established call: sealing, opening and heartbeat timing."""

    def __init__(
        self,
        call_id: bytes,
        keys: TransportKeys,
        *,
        heartbeat_interval: float,
        timeout: float,
        now: float,
    ) -> None:
        self.call_id = call_id
        #: The cipher suite of this call.
        self.suite = keys.suite
        self._sealer = keys.suite.aead(keys.send_key)
        self._opener = keys.suite.aead(keys.receive_key)
        # authentic()'s own: it may run on another thread than open().
        self._checker = keys.suite.aead(keys.receive_key)
        self._gate_window = ReplayWindow()
        self._prefix = DataFrame.make_header(call_id, 0)[:DATA_PREFIX_LEN]
        self._nonce = keys.suite.nonce
        self._send_counter = 0
        self._replay = ReplayWindow()
        self.heartbeat_interval = heartbeat_interval
        self.timeout = timeout
        self.last_heard = now
        self._next_heartbeat = now
        self._heartbeat_seq = 0
        self._peer_beat: tuple[int, float] | None = None  # (peer's sent_us, our receive time)
        self._peer_seqs: deque[int] = deque(maxlen=_LOSS_WINDOW)
        self.stats = CallStats()

    # -- sending ---------------------------------------------------------------------

    def seal(self, plaintext: bytes) -> bytes:
        """A DATA frame carrying ``plaintext`` under the next counter."""
        counter = self._send_counter
        if counter >= _MAX_COUNTER:  # never reuse a nonce; 2**64 frames will not happen
            raise ProtocolError("call counter exhausted")
        self._send_counter = counter + 1
        header = DataFrame.make_header(self.call_id, counter)
        self.stats.frames_sent += 1
        return header + self._sealer.encrypt(self._nonce(counter), plaintext, header)

    def heartbeat_due(self, now: float) -> bool:
        """Whether a heartbeat should be sent now."""
        return now >= self._next_heartbeat

    def seal_heartbeat(self, now: float) -> bytes:
        """The next heartbeat frame; schedules the one after."""
        # Keep the cadence; after a stall, start a fresh one rather than sending a burst.
        self._next_heartbeat += self.heartbeat_interval
        if self._next_heartbeat <= now:
            self._next_heartbeat = now + self.heartbeat_interval
        echo_us, echo_delay_us = 0, 0
        if self._peer_beat is not None:
            echo_us = self._peer_beat[0]
            echo_delay_us = int((now - self._peer_beat[1]) * 1e6)
        self._heartbeat_seq += 1
        beat = Heartbeat(self._heartbeat_seq, int(now * 1e6), echo_us, echo_delay_us)
        return self.seal(encode_heartbeat(beat))

    # -- receiving -------------------------------------------------------------------

    def authentic(self, data: bytes) -> bool:
        """Whether the raw frame ``data`` is this call's, new and genuine: this call's
        version, type and id, a counter not seen before, and the AEAD tag.

        The transport asks it on its receiving thread before it queues a frame, so a
        forged frame costs one failed AEAD there and never takes a genuine frame's place
        in the queue; nor does a copy of a genuine frame put back on the key, since the
        gate keeps a replay window of its own (each counter is let through once, even
        before :meth:`open` has seen it). Only that one thread may call it. A frame it
        lets through is opened again by :meth:`open`, which decides.
        """
        if len(data) < _MIN_DATA or data[:DATA_PREFIX_LEN] != self._prefix:
            return False
        counter = int.from_bytes(data[DATA_PREFIX_LEN:DATA_HEADER_LEN], "big")
        if not self._gate_window.check(counter):
            return False
        try:
            self._checker.decrypt(
                self._nonce(counter), data[DATA_HEADER_LEN:], data[:DATA_HEADER_LEN]
            )
        except InvalidTag:
            return False
        self._gate_window.accept(counter)
        return True

    def open(self, frame: DataFrame, now: float) -> Message:
        """Authenticate, de-duplicate and decode a DATA frame of this call.

        Raises AuthenticationError (counted as "forged" or "replayed") or ProtocolError
        ("malformed"); a frame that raises changes nothing else.
        """
        if not self._replay.check(frame.counter):
            self.stats.rejected["replayed"] += 1
            raise AuthenticationError(f"replayed or too old frame (counter {frame.counter})")
        try:
            plaintext = self._opener.decrypt(
                self._nonce(frame.counter), frame.ciphertext, frame.header
            )
        except InvalidTag as exc:
            self.stats.rejected["forged"] += 1
            raise AuthenticationError("frame failed authentication") from exc
        # Authentic: it counts as a sign of life even if its content is unusable.
        self._replay.accept(frame.counter)
        self.last_heard = max(self.last_heard, now)
        self.stats.frames_received += 1
        try:
            message = decode_message(plaintext)
        except ProtocolError:
            self.stats.rejected["malformed"] += 1
            raise
        if isinstance(message, Heartbeat):
            self._on_heartbeat(message, now)
        return message

    def _on_heartbeat(self, beat: Heartbeat, now: float) -> None:
        self._peer_beat = (beat.sent_us, now)
        self._peer_seqs.append(beat.seq)
        span = max(self._peer_seqs) - min(self._peer_seqs) + 1
        self.stats.loss = max(0.0, 1.0 - len(self._peer_seqs) / span)
        if beat.echo_us:
            rtt = now - (beat.echo_us + beat.echo_delay_us) / 1e6
            if 0 <= rtt < 60:  # a nonsense echo (garbled clock) is ignored, not trusted
                self.stats.rtt = rtt

    # -- timing ----------------------------------------------------------------------

    def timed_out(self, now: float) -> bool:
        """Whether nothing authentic arrived from the peer for longer than the timeout."""
        return now - self.last_heard > self.timeout

    def next_deadline(self) -> float:
        """When :meth:`heartbeat_due` or :meth:`timed_out` may next change."""
        return min(self._next_heartbeat, self.last_heard + self.timeout)
