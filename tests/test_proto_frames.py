"""Wire format: outer frames and the messages sealed inside DATA frames."""

from __future__ import annotations

import struct

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from telebot.channels.proto.frames import (
    CALL_ID_LEN,
    INSTANCE_LEN,
    LEGACY_VERSION,
    MAX_BUNDLE,
    MAX_CHANNEL_NAME,
    MAX_DATAGRAM,
    MAX_FRAME,
    NAME_PATTERN,
    VERSION,
    Bundle,
    Coalescer,
    DataFrame,
    Datagram,
    Hangup,
    Heartbeat,
    Hello,
    Retry,
    Welcome,
    decode_frame,
    decode_message,
    encode_bundle,
    encode_datagram,
    encode_hangup,
    encode_heartbeat,
    validate_channel_name,
    validate_name,
)
from telebot.errors import DatagramTooLarge, ProtocolError

SETTINGS = settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
FUZZ = settings(max_examples=300, deadline=None)

# --------------------------------------------------------------------------- strategies

call_ids = st.binary(min_size=CALL_ID_LEN, max_size=CALL_ID_LEN)
instances = st.binary(min_size=INSTANCE_LEN, max_size=INSTANCE_LEN)
names = st.from_regex(NAME_PATTERN, fullmatch=True)
noise_messages = st.binary(min_size=1, max_size=2048)
counters = st.integers(0, 2**64 - 1)
u32 = st.integers(0, 2**32 - 1)
u64 = st.integers(0, 2**64 - 1)


def _fit_utf8(text: str, limit: int) -> str:
    while len(text.encode("utf-8")) > limit:
        text = text[:-1]
    return text


channel_names = st.text(min_size=1, max_size=MAX_CHANNEL_NAME).map(
    lambda t: _fit_utf8(t, MAX_CHANNEL_NAME)
).filter(bool) | st.sampled_from(["a", "x" * 255, "é" * 127 + "a", "📷" * 63 + "abc", "/video"])
# Up to 32,768 UTF-8 bytes: 8,192 characters of at most 4 bytes each.
text_payloads = st.text(max_size=MAX_DATAGRAM // 4) | st.sampled_from(
    ["", "x" * MAX_DATAGRAM, "é" * (MAX_DATAGRAM // 2), "€" * 10_922 + "ab"]
)
byte_payloads = st.binary(max_size=MAX_DATAGRAM) | st.sampled_from(
    [b"", bytes(MAX_DATAGRAM), b"\xff" * MAX_DATAGRAM]
)
payloads = text_payloads | byte_payloads
heartbeats = st.builds(Heartbeat, u32, u64, u64, u32)

# Offers: 1-8 distinct non-zero suite numbers (unknown ones too); the suite is one of them.
offer_lists = st.lists(st.integers(1, 255), min_size=1, max_size=8, unique=True).map(tuple)
hellos = st.builds(
    lambda call_id, name, instance, noise, offers, pick: Hello(
        call_id, name, instance, noise, offers[pick % len(offers)], offers
    ),
    call_ids,
    names,
    instances,
    noise_messages,
    offer_lists,
    st.integers(0, 7),
)
retries = st.builds(Retry, call_ids, st.integers(0, 255))
welcomes = st.builds(Welcome, call_ids, noise_messages)
data_frames = st.builds(
    lambda call_id, counter, ct: DataFrame(
        call_id, counter, DataFrame.make_header(call_id, counter), ct
    ),
    call_ids,
    counters,
    st.binary(min_size=16, max_size=2048),
)


def frame_bytes(frame: Hello | Welcome | DataFrame | Retry) -> bytes:
    if isinstance(frame, DataFrame):
        return frame.header + frame.ciphertext
    return frame.encode()


def assert_valid_frame(data: bytes, frame: object) -> None:
    """A decoded frame re-encodes to exactly the bytes it came from."""
    # Only a HELLO may be of version 1 (read, to be refused with a reason).
    assert data[0] == VERSION or (isinstance(frame, Hello) and data[0] == LEGACY_VERSION)
    if isinstance(frame, Hello):
        assert data[1] == 4
        assert NAME_PATTERN.fullmatch(frame.caller)
        assert len(frame.instance) == INSTANCE_LEN
        assert 1 <= len(frame.offers) <= 8 and frame.suite in frame.offers
        assert 1 <= len(frame.noise_message) <= 2048
        assert frame.encode() == data
        assert frame.prologue == data[: len(data) - len(frame.noise_message)]
    elif isinstance(frame, Welcome):
        assert data[1] == 2
        assert 1 <= len(frame.noise_message) <= 2048
        assert frame.encode() == data
    elif isinstance(frame, Retry):
        assert data[1] == 5 and len(data) == 11
        assert frame.encode() == data
    elif isinstance(frame, DataFrame):
        assert data[1] == 3
        assert frame.header == DataFrame.make_header(frame.call_id, frame.counter)
        assert frame.header + frame.ciphertext == data
        assert len(frame.ciphertext) >= 16
    else:
        pytest.fail(f"decode_frame returned {frame!r}")
    assert frame.call_id == data[2:10]
    assert len(data) <= MAX_FRAME


def assert_valid_message(data: bytes, message: object) -> None:
    """A decoded message re-encodes to exactly the bytes it came from."""
    if isinstance(message, Datagram):
        assert 1 <= len(message.channel.encode()) <= MAX_CHANNEL_NAME
        assert isinstance(message.payload, str) == bool(data[1] & 1)
        assert encode_datagram(message.channel.encode(), message.payload) == data
    elif isinstance(message, Heartbeat):
        assert encode_heartbeat(message) == data
    elif isinstance(message, Hangup):
        assert data[0] == 3
        assert message.reason.encode() == data[1:]
        if len(data) <= 201:
            assert encode_hangup(message.reason) == data
    elif isinstance(message, Bundle):
        assert len(message.datagrams) >= 2 and len(data) <= MAX_BUNDLE
        entries = [encode_datagram(d.channel.encode(), d.payload) for d in message.datagrams]
        assert encode_bundle(entries) == data
    else:
        pytest.fail(f"decode_message returned {message!r}")


# --------------------------------------------------------------------------- round trips


@SETTINGS
@given(hello=hellos)
def test_hello_round_trip(hello: Hello) -> None:
    data = hello.encode()
    assert data[:2] == bytes([VERSION, 4])
    assert decode_frame(data) == hello
    assert_valid_frame(data, hello)


@SETTINGS
@given(welcome=welcomes)
def test_welcome_round_trip(welcome: Welcome) -> None:
    data = welcome.encode()
    assert data[:2] == bytes([VERSION, 2])
    assert decode_frame(data) == welcome


@SETTINGS
@given(retry=retries)
def test_retry_round_trip(retry: Retry) -> None:
    data = retry.encode()
    assert data == bytes([VERSION, 5]) + retry.call_id + bytes([retry.suite])
    assert decode_frame(data) == retry


@SETTINGS
@given(frame=data_frames)
def test_data_frame_round_trip(frame: DataFrame) -> None:
    data = frame_bytes(frame)
    assert len(frame.header) == 18
    assert decode_frame(data) == frame
    assert decode_frame(bytearray(data)) == frame
    assert decode_frame(memoryview(data)) == frame


def test_data_header_layout() -> None:
    header = DataFrame.make_header(b"ABCDEFGH", 0x0102030405060708)
    assert header == b"\x02\x03ABCDEFGH\x01\x02\x03\x04\x05\x06\x07\x08"


def test_hello_layout_and_prologue() -> None:
    hello = Hello(b"\x00" * 7 + b"\x01", "alice", b"instance", b"noise", 2, (2, 1))
    assert hello.prologue == (
        b"\x02\x04" + b"\x00" * 7 + b"\x01" + b"\x05alice" + b"instance" + b"\x02\x02\x02\x01"
    )
    assert hello.encode() == hello.prologue + b"noise"
    # The defaults: ChaChaPoly alone.
    assert Hello(bytes(8), "a", bytes(8), b"n").prologue.endswith(b"\x01\x01\x01")


def test_a_version_1_hello_is_read_as_one_and_other_version_1_frames_are_refused() -> None:
    hello = Hello(bytes(8), "alice", bytes(8), bytes(96), 1, (1,), LEGACY_VERSION)
    assert hello.encode()[0] == 1 and hello.prologue[0] == 1
    assert decode_frame(hello.encode()) == hello  # read, so that it can be refused
    welcome = Welcome(bytes(8), bytes(48), LEGACY_VERSION)
    assert welcome.encode()[:2] == b"\x01\x02"
    for frame in (welcome.encode(), bytes([1, 3]) + bytes(8 + 8 + 16)):
        with pytest.raises(ProtocolError, match="unsupported protocol version 1"):
            decode_frame(frame)


def test_hello_of_the_protocol_before_suites_is_refused_with_a_clear_error() -> None:
    old = b"\x01\x01" + bytes(8) + b"\x05alice" + bytes(8) + bytes(96)
    with pytest.raises(ProtocolError, match="older telebot"):
        decode_frame(old)


@pytest.mark.parametrize(
    ("suite", "offers", "match"),
    [
        (1, (), "list of cipher suites"),
        (1, (1, 1), "list of cipher suites"),
        (1, (0, 1), "list of cipher suites"),
        (1, tuple(range(1, 10)), "list of cipher suites"),
        (2, (1,), "does not offer"),
        (0, (1, 2), "does not offer"),
    ],
)
def test_hello_with_bad_suites_is_refused(suite: int, offers: tuple[int, ...], match: str) -> None:
    data = Hello(bytes(8), "alice", bytes(8), bytes(96), suite, offers).encode()
    with pytest.raises(ProtocolError, match=match):
        decode_frame(data)


@SETTINGS
@given(channel=channel_names, payload=payloads)
def test_datagram_round_trip(channel: str, payload: str | bytes) -> None:
    name = validate_channel_name(channel)
    assert name == channel.encode("utf-8")
    data = encode_datagram(name, payload)
    assert data[0] == 1
    assert data[1] == (1 if isinstance(payload, str) else 0)
    assert data[2] == len(name)
    message = decode_message(data)
    assert message == Datagram(channel, payload)
    assert type(message.payload) is type(payload)  # type: ignore[union-attr]


@SETTINGS
@given(payload=st.binary(max_size=256))
def test_datagram_accepts_bytes_like(payload: bytes) -> None:
    for wrapped in (bytearray(payload), memoryview(payload)):
        message = decode_message(encode_datagram(b"ch", wrapped))
        assert message == Datagram("ch", payload)
        assert type(message.payload) is bytes  # type: ignore[union-attr]


@pytest.mark.parametrize("payload", [1, None, 1.5, ["x"]])
def test_datagram_rejects_other_payload_types(payload: object) -> None:
    with pytest.raises(TypeError):
        encode_datagram(b"ch", payload)  # type: ignore[arg-type]


@SETTINGS
@given(beat=heartbeats)
def test_heartbeat_round_trip(beat: Heartbeat) -> None:
    data = encode_heartbeat(beat)
    assert len(data) == 25
    assert data[0] == 2
    assert decode_message(data) == beat


def test_heartbeat_layout_and_saturation() -> None:
    data = encode_heartbeat(Heartbeat(2**32 + 5, 1, 2, 2**40))
    assert data == struct.pack(">BIQQI", 2, 5, 1, 2, 0xFFFFFFFF)
    assert decode_message(data) == Heartbeat(5, 1, 2, 0xFFFFFFFF)


@SETTINGS
@given(reason=st.text(max_size=50))
def test_hangup_round_trip(reason: str) -> None:
    if len(reason.encode()) > 200:
        reason = _fit_utf8(reason, 200)
    data = encode_hangup(reason)
    assert data[0] == 3
    assert decode_message(data) == Hangup(reason)


def test_hangup_reason_is_cut_to_200_bytes() -> None:
    message = decode_message(encode_hangup("x" * 500))
    assert message == Hangup("x" * 200)


def test_hangup_with_long_non_ascii_reason_stays_decodable() -> None:
    reason = "€" * 100  # 300 bytes; byte 200 falls inside the 67th character
    message = decode_message(encode_hangup(reason))
    assert isinstance(message, Hangup)
    assert reason.startswith(message.reason)
    assert len(message.reason.encode()) <= 200


# --------------------------------------------------------------------------- limits


@pytest.mark.parametrize(
    "payload",
    [
        b"\x00" * MAX_DATAGRAM,
        "x" * MAX_DATAGRAM,
        "é" * (MAX_DATAGRAM // 2),
        "€" * (MAX_DATAGRAM // 3) + "ab",
        "📷" * (MAX_DATAGRAM // 4),
    ],
    ids=["bytes", "ascii", "2-byte", "3-byte", "4-byte"],
)
def test_largest_datagram_encodes(payload: str | bytes) -> None:
    body = payload.encode() if isinstance(payload, str) else payload
    assert len(body) == MAX_DATAGRAM == 32_768
    data = encode_datagram(b"ch", payload)
    assert decode_message(data) == Datagram("ch", payload)


@pytest.mark.parametrize(
    "payload",
    [
        b"\x00" * (MAX_DATAGRAM + 1),
        bytearray(MAX_DATAGRAM + 1),
        "x" * (MAX_DATAGRAM + 1),
        "é" * (MAX_DATAGRAM // 2) + "x",  # 16,385 characters, 32,769 bytes
        "x" * (MAX_DATAGRAM - 1) + "é",  # 32,768 characters, 32,769 bytes
        "📷" * (MAX_DATAGRAM // 4 + 1),
    ],
    ids=["bytes", "bytearray", "ascii", "2-byte", "chars-under-limit", "4-byte"],
)
def test_datagram_over_limit_is_refused(payload: str | bytes) -> None:
    with pytest.raises(DatagramTooLarge, match="32768"):
        encode_datagram(b"ch", payload)
    assert issubclass(DatagramTooLarge, ValueError)


def test_largest_data_frame_fits() -> None:
    """A full datagram with the longest channel name still fits a DATA frame."""
    plaintext = encode_datagram(b"c" * MAX_CHANNEL_NAME, bytes(MAX_DATAGRAM))
    data = DataFrame.make_header(bytes(8), 7) + plaintext + bytes(16)
    assert len(data) == MAX_FRAME
    frame = decode_frame(data)
    assert isinstance(frame, DataFrame)
    assert frame.counter == 7
    with pytest.raises(ProtocolError, match="too long"):
        decode_frame(data + b"\x00")


def test_received_datagram_over_limit_is_refused() -> None:
    ok = bytes([1, 0, 1]) + b"c" + bytes(MAX_DATAGRAM)
    assert decode_message(ok) == Datagram("c", bytes(MAX_DATAGRAM))
    with pytest.raises(ProtocolError):
        decode_message(ok + b"\x00")


@pytest.mark.parametrize(
    "name",
    ["a", "x" * 255, "é" * 127 + "a", "€" * 85, "📷" * 63 + "abc", "with space/and*wildcards"],
)
def test_channel_names_up_to_255_bytes(name: str) -> None:
    encoded = validate_channel_name(name)
    assert encoded == name.encode()
    assert len(encoded) <= 255
    assert decode_message(encode_datagram(encoded, b"p")) == Datagram(name, b"p")


@pytest.mark.parametrize(
    "name",
    ["", "x" * 256, "é" * 128, "€" * 85 + "a", "📷" * 64, "\ud800", None, b"bytes"],
    ids=["empty", "256-ascii", "256-2byte", "256-3byte", "256-4byte", "surrogate", "none", "bytes"],
)
def test_bad_channel_names_are_refused(name: object) -> None:
    with pytest.raises(ValueError, match=r"channel name|surrogates not allowed"):
        validate_channel_name(name)  # type: ignore[arg-type]


@pytest.mark.parametrize("name", ["a", "A", "0", "alice", "gui.a-bot_2", "x" * 64, "9lives", "a-"])
def test_valid_names(name: str) -> None:
    assert validate_name(name) == name
    assert NAME_PATTERN.fullmatch(name)


@pytest.mark.parametrize(
    "name",
    ["", "x" * 65, "-a", ".a", "_a", "a b", "a/b", "a*", "a$", "a?", "a#", "é", "a\n"],
)
def test_invalid_names(name: str) -> None:
    with pytest.raises(ValueError, match="invalid robot name"):
        validate_name(name, "robot name")


# --------------------------------------------------------------------------- rejection


# A version-1 HELLO is read (test_a_version_1_hello_is_read_as_one_...): not among these.
@pytest.mark.parametrize(
    ("version", "kind"),
    [(v, k) for v in (0, 1, 3, 255) for k in (2, 3, 4, 5) if (v, k) != (LEGACY_VERSION, 4)],
)
def test_unknown_version_is_refused(version: int, kind: int) -> None:
    valid = {
        4: Hello(bytes(8), "alice", bytes(8), b"n").encode(),
        2: Welcome(bytes(8), b"n").encode(),
        3: DataFrame.make_header(bytes(8), 0) + bytes(16),
        5: Retry(bytes(8), 1).encode(),
    }[kind]
    decode_frame(valid)  # fine as it is
    with pytest.raises(ProtocolError, match="version"):
        decode_frame(bytes([version]) + valid[1:])


@pytest.mark.parametrize("kind", [0, 6, 127, 255])
def test_unknown_frame_type_is_refused(kind: int) -> None:
    with pytest.raises(ProtocolError, match="type"):
        decode_frame(bytes([VERSION, kind]) + bytes(40))


@pytest.mark.parametrize("kind", [0, 5, 127, 255])
def test_unknown_message_kind_is_refused(kind: int) -> None:
    with pytest.raises(ProtocolError, match="kind"):
        decode_message(bytes([kind]) + bytes(24))


@pytest.mark.parametrize("flags", [0x02, 0x03, 0x80, 0xFF])
def test_unknown_datagram_flags_are_refused(flags: int) -> None:
    with pytest.raises(ProtocolError, match="flags"):
        decode_message(bytes([1, flags, 1]) + b"cpayload")


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (b"", "empty"),
        (b"\x01", "truncated"),
        (b"\x01\x00", "truncated"),
        (b"\x01\x00\x00payload", "channel name"),  # empty channel name
        (b"\x01\x00\x05abc", "channel name"),  # truncated channel name
        (b"\x01\x00\x02\xff\xfe", "UTF-8"),  # channel name not UTF-8
        (b"\x01\x01\x01c\xff", "UTF-8"),  # text payload not UTF-8
        (b"\x01\x01\x01c\xed\xa0\x80", "UTF-8"),  # an encoded surrogate
        (b"\x02" + bytes(23), "size"),
        (b"\x02" + bytes(25), "size"),
        (b"\x03\xc3", "UTF-8"),
    ],
)
def test_malformed_messages_are_refused(data: bytes, match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        decode_message(data)


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (b"", "too short"),
        (bytes([2, 3]) + bytes(7), "too short"),
        (bytes([2, 3]) + bytes(8 + 8 + 15), "DATA frame too short"),
        (bytes([2, 4]) + bytes(8), "HELLO frame too short"),
        (bytes([2, 4]) + bytes(8) + b"\x05alice" + bytes(8), "truncated"),  # no suites
        (bytes([2, 4]) + bytes(8) + b"\x05alice" + bytes(8) + b"\x01", "truncated"),
        (bytes([2, 4]) + bytes(8) + b"\x05alice" + bytes(8) + b"\x01\x01\x01", "truncated"),
        (bytes([2, 4]) + bytes(8) + b"\x05alice" + bytes(8) + b"\x01\x02\x01", "truncated"),
        (bytes([2, 4]) + bytes(8) + b"\x05ali", "truncated"),
        (bytes([2, 4]) + bytes(8) + b"\x00" + bytes(11), "caller name"),  # empty name
        (bytes([2, 4]) + bytes(8) + b"\x03a b" + bytes(11), "caller name"),
        (bytes([2, 4]) + bytes(8) + b"\x02\xc3\xa9" + bytes(11), "caller name"),  # é
        (bytes([2, 4]) + bytes(8) + b"\x41" + b"a" * 65 + bytes(11), "caller name"),  # 65 chars
        (
            bytes([2, 4]) + bytes(8) + b"\x01a" + bytes(8) + b"\x01\x01\x01" + bytes(2049),
            "too long",
        ),
        (bytes([2, 5]) + bytes(8), "RETRY frame of the wrong size"),
        (bytes([2, 5]) + bytes(10), "RETRY frame of the wrong size"),
        (bytes([2, 2]) + bytes(8), "missing"),
        (bytes([2, 2]) + bytes(8) + bytes(2049), "too long"),
    ],
)
def test_malformed_frames_are_refused(data: bytes, match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        decode_frame(data)


def test_longest_handshake_messages_are_accepted() -> None:
    hello = Hello(bytes(8), "a" * 64, bytes(8), bytes(2048))
    assert decode_frame(hello.encode()) == hello
    welcome = Welcome(bytes(8), bytes(2048))
    assert decode_frame(welcome.encode()) == welcome


# --------------------------------------------------------------------------- fuzzing

# Random bytes rarely start with a valid version and type, so half start with one.
frame_like = st.binary(max_size=300) | st.builds(
    lambda kind, rest: bytes([VERSION, kind]) + rest,
    st.sampled_from([1, 2, 3, 4, 5]) | st.integers(0, 255),
    st.binary(max_size=300),
)


@FUZZ
@given(data=frame_like)
@example(data=b"\x01\x04" + bytes(8) + b"\x05alice" + bytes(8) + b"\x01\x01\x01\x00")
def test_decode_frame_fuzz(data: bytes) -> None:
    try:
        frame = decode_frame(data)
    except ProtocolError:
        return
    assert_valid_frame(data, frame)


message_like = st.binary(max_size=300) | st.builds(
    lambda kind, rest: bytes([kind]) + rest,
    st.sampled_from([1, 2, 3, 4]),
    st.binary(max_size=300) | st.binary(min_size=24, max_size=24),
)


@FUZZ
@given(data=message_like)
@example(data=b"\x01\x01\x01c\xf0\x9f\x93\xb7")
@example(data=b"\x02" + bytes(24))
@example(data=b"\x04\x00\x04\x01\x00\x01a\x00\x04\x01\x01\x01b")
def test_decode_message_fuzz(data: bytes) -> None:
    try:
        message = decode_message(data)
    except ProtocolError:
        return
    assert_valid_message(data, message)


@SETTINGS
@given(frame=hellos | welcomes | data_frames | retries, data=st.data())
def test_truncated_frames_are_refused_or_decoded_consistently(
    frame: Hello | Welcome | DataFrame | Retry, data: st.DataObject
) -> None:
    full = frame_bytes(frame)
    cuts = {0, 1, 9, 10, 11, 17, 18, len(full) - 1}
    cuts.add(data.draw(st.integers(0, len(full) - 1)))
    for size in sorted(c for c in cuts if 0 <= c < len(full)):
        cut = full[:size]
        try:
            decoded = decode_frame(cut)
        except ProtocolError:
            continue
        # A prefix that still decodes is the same frame with a shorter tail.
        assert type(decoded) is type(frame)
        assert decoded.call_id == frame.call_id
        assert_valid_frame(cut, decoded)
        if isinstance(frame, Hello):
            assert isinstance(decoded, Hello)
            assert (decoded.caller, decoded.instance) == (frame.caller, frame.instance)
            assert (decoded.suite, decoded.offers) == (frame.suite, frame.offers)
            assert frame.noise_message.startswith(decoded.noise_message)
        elif isinstance(frame, DataFrame):
            assert isinstance(decoded, DataFrame)
            assert decoded.counter == frame.counter
            assert frame.ciphertext.startswith(decoded.ciphertext)


@SETTINGS
@given(
    message=st.builds(encode_datagram, channel_names.map(str.encode), st.binary(max_size=64))
    | heartbeats.map(encode_heartbeat)
    | st.text(max_size=40).map(encode_hangup)
    | st.lists(
        st.builds(encode_datagram, channel_names.map(str.encode), st.binary(max_size=64)),
        min_size=2,
        max_size=5,
    ).map(encode_bundle),
)
def test_truncated_messages_are_refused_or_decoded_consistently(message: bytes) -> None:
    for size in range(len(message)):
        cut = message[:size]
        try:
            decoded = decode_message(cut)
        except ProtocolError:
            continue
        assert cut  # the empty message never decodes
        assert cut[0] in (1, 3, 4)  # heartbeats have a fixed size
        assert_valid_message(cut, decoded)
        if isinstance(decoded, Bundle):  # only whole entries survive a cut
            full = decode_message(message)
            assert isinstance(full, Bundle)
            assert decoded.datagrams == full.datagrams[: len(decoded.datagrams)]


# --------------------------------------------------------------------------- bundles

small_datagrams = st.lists(
    st.tuples(
        channel_names, text_payloads.filter(lambda t: len(t) < 2000) | st.binary(max_size=2000)
    ),
    min_size=2,
    max_size=12,
)


@SETTINGS
@given(datagrams=small_datagrams)
def test_bundle_round_trip(datagrams: list[tuple[str, str | bytes]]) -> None:
    entries = [encode_datagram(name.encode(), payload) for name, payload in datagrams]
    message = decode_message(encode_bundle(entries))
    assert isinstance(message, Bundle)
    assert [(d.channel, d.payload) for d in message.datagrams] == datagrams


def test_bundle_layout() -> None:
    first, second = encode_datagram(b"a", "x"), encode_datagram(b"bc", b"\x00")
    assert encode_bundle([first, second]) == (
        b"\x04" + len(first).to_bytes(2, "big") + first + len(second).to_bytes(2, "big") + second
    )


def test_encode_bundle_refuses_one_datagram_and_oversize() -> None:
    one = encode_datagram(b"a", "x")
    with pytest.raises(ValueError, match="at least two"):
        encode_bundle([one])
    big = encode_datagram(b"a", bytes(MAX_DATAGRAM // 2 + 200))
    with pytest.raises(ValueError, match="over"):
        encode_bundle([big, big, one])


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (b"\x04", "fewer than two"),
        (b"\x04\x00\x05" + encode_datagram(b"a", "x"), "fewer than two"),
        (b"\x04\x00", "length truncated"),
        (b"\x04\x00\x09\x01\x01\x01a", "entry truncated"),
        (b"\x04\x00\x00\x00\x05" + encode_datagram(b"a", "x"), "not a DATAGRAM"),
        (b"\x04\x00\x04\x03bye\x00\x05" + encode_datagram(b"a", "x"), "not a DATAGRAM"),
        (
            b"\x04\x00\x0f"
            + encode_bundle([encode_datagram(b"a", "x")] * 2)
            + b"\x00\x05"
            + encode_datagram(b"a", "x"),
            "not a DATAGRAM",
        ),  # a BUNDLE does not nest
        (b"\x04\x00\x03\x01\x00\x00\x00\x05" + encode_datagram(b"a", "x"), "channel name"),
        (b"\x04" + bytes(MAX_BUNDLE), "over the limit"),
    ],
)
def test_malformed_bundles_are_refused(data: bytes, match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        decode_message(data)


def test_coalescer_sends_a_lone_datagram_as_itself() -> None:
    coalescer = Coalescer()
    assert not coalescer and coalescer.take() is None
    datagram = encode_datagram(b"pose", b"xyz")
    assert coalescer.add(datagram) is None and coalescer
    assert coalescer.take() == datagram
    assert not coalescer and coalescer.take() is None


def test_coalescer_bundles_in_order() -> None:
    coalescer = Coalescer()
    sent = [encode_datagram(f"ch{i % 3}".encode(), f"#{i}") for i in range(50)]
    assert all(coalescer.add(d) is None for d in sent)
    message = decode_message(coalescer.take() or b"")
    assert isinstance(message, Bundle)
    assert [(d.channel, d.payload) for d in message.datagrams] == [
        (f"ch{i % 3}", f"#{i}") for i in range(50)
    ]


@SETTINGS
@given(sizes=st.lists(st.integers(0, MAX_DATAGRAM), min_size=1, max_size=12))
def test_coalescer_never_builds_a_message_over_the_limit(sizes: list[int]) -> None:
    coalescer = Coalescer()
    sent = [encode_datagram(b"x" * (i % 255 + 1), bytes(size)) for i, size in enumerate(sizes)]
    messages = [m for m in (coalescer.add(d) for d in sent) if m is not None]
    last = coalescer.take()
    assert last is not None
    messages.append(last)
    received: list[Datagram] = []
    for message in messages:
        assert len(message) <= MAX_BUNDLE
        decoded = decode_message(message)
        received.extend(decoded.datagrams if isinstance(decoded, Bundle) else [decoded])  # type: ignore[list-item]
    assert [encode_datagram(d.channel.encode(), d.payload) for d in received] == sent
