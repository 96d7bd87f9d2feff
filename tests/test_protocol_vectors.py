"""The test vectors of docs/protocol.md section 11, for both cipher suites, checked
against the code: every value the code computes is in the document, and every hex
string in those sections is one the code computes (no stale vector is left behind)."""

from __future__ import annotations

import contextlib
import hashlib
import io
import re
from pathlib import Path

import pytest

from telebot.channels.proto.frames import (
    Hello,
    Retry,
    decode_frame,
    encode_datagram,
    encode_hangup,
)
from telebot.channels.proto.noise import (
    InitiatorHandshake,
    ResponderHandshake,
    Suite,
    public_key_of,
)
from telebot.channels.proto.session import (
    Answer,
    CallSession,
    answer_hello,
    finish_call,
    read_hello,
)

PROTOCOL_MD = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"

USER_S = bytes(range(0, 32))
USER_E = bytes(range(32, 64))
ROBOT_S = bytes(range(64, 96))
ROBOT_E = bytes(range(96, 128))
CALL_ID = bytes.fromhex("0123456789abcdef")
INSTANCE = bytes.fromhex("a1a2a3a4a5a6a7a8")
P1 = b'{"user": "alice", "ts": 1700000000000000000}'
#: What a user without AES instructions offers, and one with them (``cipher = "auto"``).
OFFERS = {
    Suite.CHACHAPOLY: (Suite.CHACHAPOLY, Suite.AESGCM),
    Suite.AESGCM: (Suite.AESGCM, Suite.CHACHAPOLY),
}


def vectors(suite: Suite) -> dict[str, str]:
    """Every value section 11 shows for ``suite``, by name, in lowercase hex."""
    offers = tuple(int(s) for s in OFFERS[suite])
    unsigned = Hello(CALL_ID, "alice", INSTANCE, b"", suite, offers)
    initiator = InitiatorHandshake(
        USER_S, public_key_of(ROBOT_S), unsigned.prologue, suite=suite, ephemeral_private=USER_E
    )
    msg1 = initiator.write_message(P1)
    hello = decode_frame(Hello(CALL_ID, "alice", INSTANCE, msg1, suite, offers).encode())
    assert isinstance(hello, Hello)

    def welcome(answer: Answer) -> tuple[bytes, CallSession, CallSession]:
        responder = ResponderHandshake(
            ROBOT_S, hello.prologue, suite=suite, ephemeral_private=ROBOT_E
        )
        assert responder.read_message(hello.noise_message) == P1
        frame, robot_keys = answer_hello(responder, CALL_ID, answer)
        caller = InitiatorHandshake(
            USER_S, public_key_of(ROBOT_S), hello.prologue, suite=suite, ephemeral_private=USER_E
        )
        assert caller.write_message(P1) == msg1
        _, user_keys = finish_call(caller, frame)
        sessions = [
            CallSession(CALL_ID, keys, heartbeat_interval=0.05, timeout=0.5, now=0.0)
            for keys in (user_keys, robot_keys)
        ]
        return frame.encode(), sessions[0], sessions[1]

    # read_hello (the robot's real entry point) authenticates the vector HELLO.
    assert read_hello(ROBOT_S, hello)[0].user == "alice"
    accepted, user, robot = welcome(Answer(True, "guiabot", role="driver"))
    refused, _, _ = welcome(Answer(False, "guiabot", reason="not in the contact list of guiabot"))
    datagram = encode_datagram(b"chat", "hello")
    data_user = user.seal(datagram)
    data_robot = robot.seal(datagram)
    hangup = user.seal(encode_hangup("bye"))
    caller = InitiatorHandshake(
        USER_S, public_key_of(ROBOT_S), hello.prologue, suite=suite, ephemeral_private=USER_E
    )
    caller.write_message(P1)
    _, split = caller.read_message(accepted[10:])
    name = suite.protocol_name
    h0 = name.ljust(32, b"\x00") if len(name) <= 32 else hashlib.blake2s(name).digest()
    return {
        "h0": h0.hex(),
        "nonce1": suite.nonce(1).hex(),
        "hello": hello.encode().hex(),
        "prologue": hello.prologue.hex(),
        "e": msg1[:32].hex(),
        "enc_s": msg1[32:80].hex(),
        "enc_payload": msg1[80:].hex(),
        "welcome": accepted.hex(),
        "welcome_e": accepted[10:42].hex(),
        "welcome_payload": accepted[42:].hex(),
        "refused": refused.hex(),
        "k1": split.send_key.hex(),
        "k2": split.receive_key.hex(),
        "h": split.handshake_hash.hex(),
        "datagram": datagram.hex(),
        "data_user": data_user.hex(),
        "data_robot": data_robot.hex(),
        "hangup": hangup.hex(),
    }


def section(suite: Suite) -> str:
    """The text of the subsections of section 11 whose titles name ``suite``."""
    text = PROTOCOL_MD.read_text(encoding="utf-8")
    start, end = text.index("\n## 11. "), text.index("\n## 12. ")
    parts = re.split(r"\n(?=### )", text[start:end])
    title = {Suite.CHACHAPOLY: "(ChaChaPoly)", Suite.AESGCM: "(AESGCM)"}[suite]
    chosen = [part for part in parts if part.startswith("### ") and title in part.splitlines()[0]]
    assert chosen, f"no subsection of section 11 is titled with {title}"
    return "\n".join(chosen)


def hex_in(text: str) -> set[str]:
    """Hex strings of 16+ digits in ``text``; a value may be split over lines or with spaces."""
    joined = re.sub(r"(?<=[0-9a-f])`?[ \n]`?(?=[0-9a-f]{16})", "", text)
    return set(re.findall(r"(?<![0-9A-Za-z])[0-9a-f]{16,}(?![0-9A-Za-z])", joined))


@pytest.mark.parametrize("suite", list(Suite), ids=lambda s: s.label)
def test_documented_vectors_match_the_code(suite: Suite) -> None:
    computed = vectors(suite)
    assert vectors(suite) == computed  # deterministic
    text = section(suite)
    shown = hex_in(text)
    flat = re.sub(r"[\s`]", "", text)
    for name, value in computed.items():
        assert value in flat, f"{suite.label}: {name} = {value} is not in docs/protocol.md"
    # Every hex string shown is (part of) a computed value, and so not stale.
    wholes = "|".join(computed.values())
    for value in shown:
        assert value in wholes, f"{suite.label}: {value} in docs/protocol.md is not computed"


#: The HELLO a user sends after the RETRY of section 11.8: a fresh ephemeral and ``ts``.
RETRY_E = bytes(range(128, 160))
RETRY_P1 = b'{"user": "alice", "ts": 1700000000000000001}'


def hello_after_retry() -> Hello:
    """The user of 11.5 (offers aesgcm, chachapoly) writes its HELLO again with ChaChaPoly."""
    offers = (int(Suite.AESGCM), int(Suite.CHACHAPOLY))
    unsigned = Hello(CALL_ID, "alice", INSTANCE, b"", Suite.CHACHAPOLY, offers)
    initiator = InitiatorHandshake(
        USER_S,
        public_key_of(ROBOT_S),
        unsigned.prologue,
        suite=Suite.CHACHAPOLY,
        ephemeral_private=RETRY_E,
    )
    message = initiator.write_message(RETRY_P1)
    return Hello(CALL_ID, "alice", INSTANCE, message, Suite.CHACHAPOLY, offers)


def test_documented_retry_and_the_hello_after_it_match_the_code() -> None:
    text = PROTOCOL_MD.read_text(encoding="utf-8")
    retry_section = text[text.index("### 11.8 RETRY") : text.index("\n## 12. ")]
    assert Retry(CALL_ID, Suite.CHACHAPOLY).encode().hex() in retry_section
    hello = hello_after_retry()
    flat = re.sub(r"[\s`]", "", retry_section)
    for part in (hello.prologue, hello.noise_message[:32], hello.encode()):
        assert part.hex() in flat, part.hex()
    assert public_key_of(RETRY_E).hex() in flat
    # A robot that prefers ChaChaPoly reads it (the same offers it answered RETRY to).
    offer, handshake = read_hello(ROBOT_S, hello)
    assert (offer.user, offer.timestamp_ns, handshake.suite) == ("alice", 1700000000000000001, 1)
    # Every hex string shown in 11.8 is one of these values (none is stale).
    wholes = "|".join(
        [
            Retry(CALL_ID, Suite.CHACHAPOLY).encode().hex(),
            hello.encode().hex(),
            RETRY_E.hex(),
            public_key_of(RETRY_E).hex(),
            RETRY_P1.decode(),
        ]
    )
    for value in hex_in(retry_section):
        assert value in wholes, value


def test_appendix_a_derives_the_same_vectors_from_the_bare_primitives() -> None:
    text = PROTOCOL_MD.read_text(encoding="utf-8")
    appendix = text[text.index("## Appendix A.") :]
    script = appendix[appendix.index("```python\n") + 10 :]
    script = script[: script.index("```")]
    output = io.StringIO()
    with contextlib.redirect_stdout(output):
        exec(compile(script, "protocol.md appendix A", "exec"), {})  # our own document
    lines = output.getvalue().splitlines()
    for index, suite in enumerate([Suite.CHACHAPOLY, Suite.AESGCM]):
        v = vectors(suite)
        assert lines[index * 6 : index * 6 + 6] == [
            suite.protocol_name.decode(),
            v["hello"],
            v["welcome"],
            f"{v['k1']} {v['k2']} {v['h']}",
            v["data_user"],
            v["data_robot"],
        ]


def test_the_two_suites_give_other_handshakes() -> None:
    chacha, aes = vectors(Suite.CHACHAPOLY), vectors(Suite.AESGCM)
    assert chacha["e"] == aes["e"]  # the same ephemeral key ...
    for name in ("enc_s", "enc_payload", "welcome_payload", "k1", "k2", "h"):
        assert chacha[name] != aes[name]  # ... but another protocol name, so all else differs


if __name__ == "__main__":  # prints the values for the document
    print("hello after retry", hello_after_retry().encode().hex())
    for each in Suite:
        print(each.label)
        for key, val in vectors(each).items():
            print(f"  {key}: {val}")
