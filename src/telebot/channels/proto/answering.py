"""How a robot answers a HELLO, sans-IO: handshake bytes and ``now`` in, decisions out.

:class:`Answering` is the robot's side of call set-up. It reads each frame that arrives on
the robot's handshake key and returns what to do about it, as a value:

- :class:`Ignore` — send nothing and count the frame under ``code`` (a HELLO under another
  sender's name, a replayed or reused one, one for a call that already ended);
- :class:`Reply` — send ``frame`` to the caller's handshake inbox: a RETRY naming the
  cipher suite to use, a refusal, or the cached answer to a HELLO heard before;
- :class:`Accept` — start the call: its :class:`~.session.CallSession` is ready, and its
  WELCOME goes to the caller once the robot listens on the call's keys.

Frames that do not decode or authenticate raise :class:`~telebot.errors.ProtocolError`
(as :meth:`~.session.CallSession.open` does); they change nothing here.

The rules it keeps:

- **The answer cache.** A caller repeats its HELLO until an answer comes (the link may eat
  either), so every answer (accepting or refusing) is kept by call id with the HELLO it
  answers, for the last :data:`ANSWER_CACHE` call ids; the same HELLO again gets the same
  bytes again, with no cryptography and no second call.
- **Call ids are never reused.** Another HELLO with a cached call id, or with the id of a
  call that is still up, is ignored; a repeated HELLO of an accepted call that has ended
  is ignored too (answering it would hand the caller a call that no longer exists here).
- **Replays.** The newest HELLO timestamp accepted from each contact is kept: an older or
  equal one is a replay and is ignored. A stranger's HELLO takes no such slot.
- **Signs of life.** While an accepted call has heard nothing else from the caller, a
  repeat of its HELLO keeps it up.
- **Closing.** Once :meth:`Answering.close` is called, a new call is refused.

The robot's driver (:mod:`telebot.channels.call`) tells it when a call it accepted ends
(:meth:`Answering.ended`), and moves the bytes.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

from telebot.channels.proto.frames import (
    LEGACY_VERSION,
    VERSION,
    DataFrame,
    Hello,
    Retry,
    Welcome,
    decode_frame,
)
from telebot.channels.proto.noise import ResponderHandshake, Suite
from telebot.channels.proto.session import (
    Answer,
    CallSession,
    answer_hello,
    choose_suite,
    describe_suites,
    read_hello,
)
from telebot.errors import ProtocolError

__all__ = [
    "ANSWER_CACHE",
    "Accept",
    "Answering",
    "Contact",
    "Contacts",
    "Decision",
    "Ignore",
    "Reply",
]

#: How many call ids' answers a robot keeps to repeat them (and to refuse their reuse).
ANSWER_CACHE = 256
#: How many older clients a robot warns about (once each); more are only counted.
_WARN_ONCE = 64


class Contact(Protocol):
    """A caller the robot answers (:class:`telebot.identity.Contact` is one)."""

    @property
    def name(self) -> str: ...

    @property
    def role(self) -> str: ...


class Contacts(Protocol):
    """The robot's contact list (:class:`telebot.identity.ContactBook` is one)."""

    def by_key(self, public_key: bytes, /) -> Contact | None: ...


@dataclass(frozen=True, slots=True)
class Ignore:
    """Send nothing; count the frame as rejected under ``code``."""

    code: str


@dataclass(frozen=True, slots=True)
class Reply:
    """Send ``frame`` to the handshake inbox of the caller of ``hello``.

    ``code`` is set when the reply refuses (count it as rejected under it); ``warning``,
    when the robot's operator should read why (log it).
    """

    hello: Hello
    frame: bytes
    code: str | None = None
    warning: str | None = None


@dataclass(frozen=True, slots=True)
class Accept:
    """A new call from ``contact``: listen on its keys, then send ``welcome`` to the
    caller of ``hello``."""

    hello: Hello
    contact: Contact
    session: CallSession
    welcome: bytes


Decision = Ignore | Reply | Accept


class Answering:
    """The robot's answering policy: :meth:`receive` decides on each handshake frame.

    ``suites`` are the cipher suites the robot accepts, preferred first;
    ``heartbeat_interval`` and ``timeout`` are those of the calls it accepts.
    """

    def __init__(
        self,
        name: str,
        private_key: bytes,
        contacts: Contacts,
        *,
        suites: Sequence[Suite],
        heartbeat_interval: float,
        timeout: float,
        cache_size: int = ANSWER_CACHE,
    ) -> None:
        self.name = name
        self._private_key = private_key
        self.contacts = contacts
        self.suites = tuple(suites)
        self.heartbeat_interval = heartbeat_interval
        self.timeout = timeout
        self._cache_size = cache_size
        # call id -> (the HELLO, the answer sent to it), oldest first.
        self._answered: OrderedDict[bytes, tuple[bytes, bytes]] = OrderedDict()
        # The call ids among the cached answers that accepted a call.
        self._accepted: set[bytes] = set()
        # The calls accepted here that are still up (until ended() is told).
        self._live: dict[bytes, CallSession] = {}
        # The newest HELLO timestamp accepted per caller key: an old HELLO is a replay.
        self._latest_hello: dict[bytes, int] = {}
        self._old_clients_warned: set[str] = set()
        self._closing = False

    @property
    def live(self) -> list[bytes]:
        """The ids of the calls accepted here that were not reported :meth:`ended`."""
        return list(self._live)

    def close(self) -> None:
        """The robot is shutting down: refuse new calls from now on."""
        self._closing = True

    def ended(self, call_id: bytes) -> None:
        """A call accepted here ended: a repeat of its HELLO gets silence from now on."""
        self._live.pop(call_id, None)

    def receive(self, data: bytes, sender: str | None, now: float) -> Decision:
        """Decide on ``data``, a frame from the robot's handshake key.

        ``sender`` is the name the key carries (None on the version-1 key, which names
        nobody); ``now`` is the robot's clock (that of the calls' sessions). Raises
        ProtocolError (IncompatiblePeer, AuthenticationError) for a frame that does not
        decode or authenticate.
        """
        frame = decode_frame(data)
        if isinstance(frame, DataFrame):
            return Ignore("data_on_handshake_key")
        if not isinstance(frame, Hello):
            raise ProtocolError(f"a robot does not take {type(frame).__name__} frames")
        return self.receive_hello(frame, sender, now)

    def receive_hello(self, frame: Hello, sender: str | None, now: float) -> Decision:
        """:meth:`receive` for a decoded HELLO."""
        if frame.version == VERSION and sender != frame.caller:
            # The key names the sender (a router lets only that user publish on it): a
            # HELLO that names someone else, or one on the version-1 key, is not read.
            return Ignore("sender_mismatch")
        raw = frame.encode()
        cached = self._answered.get(frame.call_id)
        if cached is not None:
            return self._repeat(frame, raw, cached, now)
        if frame.call_id in self._live:
            # A live call's id in a new HELLO (its answer left the cache): never a second
            # call, with its own keys, on top of the first.
            return Ignore("call_id_reused")
        if frame.version == LEGACY_VERSION:
            return self._refuse_old_version(frame, raw)
        suite = choose_suite(frame.offers, self.suites)
        if suite is not None and suite != frame.suite:
            # Before any cryptography: cheap, stateless, and it tells nothing that the
            # offers do not. The handshake with the HELLO written again proves our pick.
            return Reply(frame, Retry(frame.call_id, suite).encode(), code="cipher_retry")
        offer, handshake = read_hello(self._private_key, frame)  # raises if forged
        if offer.user != frame.caller:
            raise ProtocolError(
                f"HELLO header names {frame.caller!r} but its payload {offer.user!r}"
            )
        contact = self.contacts.by_key(offer.caller_public_key)
        if contact is None:
            return self._refuse(
                frame,
                raw,
                handshake,
                "not_a_contact",
                f"not in the contact list of {self.name}",
                warning=f"refused a call from {frame.caller!r}: key not in the contact list",
            )
        if suite is None:
            offered, accepted = describe_suites(frame.offers), describe_suites(self.suites)
            return self._refuse(
                frame,
                raw,
                handshake,
                "no_common_cipher",
                f"no common cipher suite: {frame.caller} offers {offered}, "
                f"{self.name} accepts {accepted}",
                warning=(
                    f"refused a call from {contact.name}: no common cipher suite (it "
                    f"offers {offered}, this robot accepts {accepted}: see [call] cipher)"
                ),
            )
        if offer.timestamp_ns <= self._latest_hello.get(offer.caller_public_key, -1):
            return Ignore("replayed_hello")
        self._latest_hello[offer.caller_public_key] = offer.timestamp_ns
        if self._closing:  # hanging up its calls: a new one would outlive the robot
            return self._refuse(frame, raw, handshake, "closing", f"{self.name} is shutting down")
        welcome, keys = answer_hello(
            handshake, frame.call_id, Answer(True, self.name, role=str(contact.role))
        )
        encoded = welcome.encode()
        self._remember(frame.call_id, raw, encoded)
        self._accepted.add(frame.call_id)
        session = CallSession(
            frame.call_id,
            keys,
            heartbeat_interval=self.heartbeat_interval,
            timeout=self.timeout,
            now=now,
        )
        self._live[frame.call_id] = session
        return Accept(frame, contact, session, encoded)

    def _repeat(
        self, frame: Hello, raw: bytes, cached: tuple[bytes, bytes], now: float
    ) -> Decision:
        """A HELLO whose call id has a cached answer: the same answer, or silence."""
        if cached[0] != raw:
            return Ignore("call_id_reused")
        # The caller did not get our answer: repeat it. While the call has heard nothing
        # else, the repeat is its only sign of life, so it keeps the call up; once the
        # call is gone, repeating the answer would hand the caller a call that no longer
        # exists here, so it gets silence and times out instead.
        session = self._live.get(frame.call_id)
        if session is None and frame.call_id in self._accepted:
            return Ignore("hello_for_ended_call")
        if session is not None and session.stats.frames_received == 0:
            session.last_heard = max(session.last_heard, now)
        return Reply(frame, cached[1])

    def _refuse_old_version(self, frame: Hello, raw: bytes) -> Reply:
        """An older client's HELLO: a refusal it can read, naming the version.

        The refusal is a version-1 WELCOME (authenticated, so the old client shows its
        reason rather than timing out), for its version-1 inbox; no call is made.
        """
        offer, handshake = read_hello(self._private_key, frame)  # raises if forged
        if offer.user != frame.caller:
            raise ProtocolError(
                f"HELLO header names {frame.caller!r} but its payload {offer.user!r}"
            )
        reason = (
            f"{self.name} speaks telebot protocol version {VERSION}, this client "
            f"version {LEGACY_VERSION}: upgrade telebot"
        )
        warning = None
        seen = self._old_clients_warned
        if frame.caller not in seen and len(seen) < _WARN_ONCE:
            seen.add(frame.caller)  # its HELLO repeats: say so once
            warning = (
                f"refused a call from {frame.caller!r}: it runs telebot protocol version "
                f"{LEGACY_VERSION}, this robot {VERSION} (the caller must upgrade telebot)"
            )
        welcome, _ = answer_hello(handshake, frame.call_id, Answer(False, self.name, reason=reason))
        encoded = Welcome(frame.call_id, welcome.noise_message, LEGACY_VERSION).encode()
        self._remember(frame.call_id, raw, encoded)
        return Reply(frame, encoded, code="old_protocol_version", warning=warning)

    def _refuse(
        self,
        frame: Hello,
        raw: bytes,
        handshake: ResponderHandshake,
        code: str,
        reason: str,
        *,
        warning: str | None = None,
    ) -> Reply:
        """A refusal naming ``reason``, kept to answer the HELLO's repeats alike."""
        welcome, _ = answer_hello(handshake, frame.call_id, Answer(False, self.name, reason=reason))
        encoded = welcome.encode()
        self._remember(frame.call_id, raw, encoded)
        return Reply(frame, encoded, code=code, warning=warning)

    def _remember(self, call_id: bytes, hello: bytes, answer: bytes) -> None:
        self._answered[call_id] = (hello, answer)
        while len(self._answered) > self._cache_size:
            forgotten, _ = self._answered.popitem(last=False)
            self._accepted.discard(forgotten)
