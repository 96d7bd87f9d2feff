"""The media wire format, sans-IO: codec ids and the keyframe bit in FRAGMENTs, REPORTs with
the keyframe flag and codec list (old 28-byte reports still parse), AUDIO datagrams, the
keyframe gate, request and pacing logic, codec choice. ``now`` is a number the tests move."""

from __future__ import annotations

import contextlib
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telebot.errors import ProtocolError
from telebot.services.media.wire import (
    AUDIO_HEADER,
    CODEC_H264,
    CODEC_JPEG,
    CODEC_OPUS,
    CODEC_VP8,
    MAX_OPUS_PACKET,
    VIDEO_CODECS,
    AudioSequencer,
    KeyframeGate,
    KeyframePacer,
    KeyframeRequests,
    choose_codec,
    codec_id,
    encode_audio,
    parse_audio,
    parse_media_report,
)
from telebot.services.video.wire import (
    REPORT,
    Reassembler,
    Report,
    encode_report,
    fragment,
    parse_fragment,
    parse_report,
)

# --------------------------------------------------------------------------- fragments


def test_the_keyframe_bit_rides_in_bit_7_of_the_codec_byte() -> None:
    [key] = fragment(1, "navcam", 10.0, b"\x00\x00\x00\x01\x67", codec=CODEC_H264, keyframe=True)
    [delta] = fragment(2, "navcam", 10.0, b"\x00\x00\x00\x01\x41", codec=CODEC_H264)
    assert key[1] == 0x83 and delta[1] == 0x03
    parsed = parse_fragment(key, codec=VIDEO_CODECS)
    assert (parsed.codec, parsed.keyframe) == (CODEC_H264, True)
    assert parse_fragment(delta, codec=VIDEO_CODECS).keyframe is False


def test_old_jpeg_fragments_are_keyframes_and_the_old_parser_default_still_takes_them() -> None:
    [jpeg] = fragment(1, "navcam", 10.0, b"\xff\xd8\xff\xd9")  # what old robots send: 0x01
    assert jpeg[1] == CODEC_JPEG
    assert parse_fragment(jpeg).keyframe is True
    [h264] = fragment(1, "navcam", 10.0, b"abc", codec=CODEC_H264)
    with pytest.raises(ProtocolError, match="unknown codec 3"):
        parse_fragment(h264)  # a JPEG-only receiver refuses H.264


def test_a_reassembler_of_several_codecs_keeps_codec_and_keyframe_and_refuses_mixed_frames() -> (
    None
):
    reasm = Reassembler(codec=VIDEO_CODECS)
    data = random.Random(1).randbytes(500)
    parts = fragment(5, "navcam", 10.0, data, 200, codec=CODEC_VP8, keyframe=True)
    assert reasm.on_datagram(parts[0], 0.0) is None
    # A fragment of the same frame claiming another codec contradicts the first one.
    forged = fragment(5, "navcam", 10.0, data, 200, codec=CODEC_H264, keyframe=True)[1]
    assert reasm.on_datagram(forged, 0.0) is None
    assert reasm.stats.inconsistent == 1
    for part in parts[1:-1]:
        assert reasm.on_datagram(part, 0.0) is None
    done = reasm.on_datagram(parts[-1], 0.0)
    assert done is not None and done.data == data
    assert (done.codec, done.keyframe) == (CODEC_VP8, True)


def test_a_frame_with_a_missing_piece_is_dropped_whole() -> None:
    reasm = Reassembler(codec=VIDEO_CODECS)
    parts = fragment(1, "navcam", 10.0, bytes(450), 200, codec=CODEC_H264, interval=0.03)
    assert len(parts) == 3
    reasm.on_datagram(parts[0], 0.0)
    reasm.on_datagram(parts[2], 0.0)
    reasm.poll(0.1)
    assert reasm.stats.incomplete == 1 and reasm.stats.frames == 0


# --------------------------------------------------------------------------- reports


def test_a_report_without_codecs_is_the_old_28_bytes_and_parses_as_jpeg_only() -> None:
    old = Report(1, 2, 3, 4, 5, 6, 7)
    raw = encode_report(old)
    assert len(raw) == REPORT.size == 28
    parsed = parse_report(raw)
    assert parsed.codecs == () and not parsed.keyframe
    assert choose_codec(parsed.codecs, (CODEC_H264, CODEC_VP8, CODEC_JPEG)) == CODEC_JPEG


def test_a_report_with_keyframe_flag_and_codec_list_round_trips() -> None:
    report = Report(123456, 44, 40, 160000, 9, 1, 12, keyframe=True, codecs=(CODEC_VP8, CODEC_H264))
    raw = encode_report(report)
    assert raw[1] == 0x02 and raw[28:] == bytes((2, CODEC_VP8, CODEC_H264))
    assert parse_media_report(raw) == report
    assert raw.hex() == "02020001e2400000002c000000280002710000000009000000010" + "00c020403"


@pytest.mark.parametrize(
    "raw",
    [
        encode_report(Report(1, 2, 3, 4, 5, 6, 7)) + b"\x00",  # a list of 0 codecs
        encode_report(Report(1, 2, 3, 4, 5, 6, 7)) + b"\x02\x03",  # shorter than it says
        encode_report(Report(1, 2, 3, 4, 5, 6, 7)) + b"\x02\x03\x03",  # repeated
        encode_report(Report(1, 2, 3, 4, 5, 6, 7)) + b"\x01\x83",  # not a 7-bit id
        encode_report(Report(1, 2, 3, 4, 5, 6, 7)) + b"\x09" + bytes(range(1, 10)),  # too many
        encode_report(Report(1, 2, 3, 4, 5, 6, 7))[:27],
        b"\x03" + bytes(27),
    ],
)
def test_bad_reports_are_refused_with_a_one_line_reason(raw: bytes) -> None:
    with pytest.raises(ProtocolError) as info:
        parse_media_report(raw)
    assert "\n" not in str(info.value)


def test_codec_choice_prefers_the_senders_configured_codec_among_the_receivers() -> None:
    robot = (CODEC_VP8, CODEC_H264, CODEC_JPEG)
    assert choose_codec((CODEC_H264, CODEC_VP8), robot) == CODEC_VP8
    assert choose_codec((CODEC_H264, CODEC_JPEG), robot) == CODEC_H264
    assert choose_codec((CODEC_JPEG,), robot) == CODEC_JPEG
    assert choose_codec((CODEC_H264,), (CODEC_VP8,)) is None
    assert codec_id("H264") == CODEC_H264
    with pytest.raises(ValueError, match="unknown codec 'av1'"):
        codec_id("av1")


# --------------------------------------------------------------------------- keyframes


def test_the_gate_skips_deltas_after_a_gap_until_a_keyframe() -> None:
    gate = KeyframeGate()
    assert gate.need_keyframe  # nothing decoded yet
    assert not gate.admit(1, CODEC_H264, keyframe=False)
    assert gate.admit(2, CODEC_H264, keyframe=True) and not gate.need_keyframe
    assert gate.admit(3, CODEC_H264, keyframe=False)
    assert not gate.admit(5, CODEC_H264, keyframe=False)  # frame 4 was lost
    assert gate.need_keyframe and gate.waits == 1
    assert not gate.admit(6, CODEC_H264, keyframe=False)
    assert gate.admit(7, CODEC_H264, keyframe=True)
    assert gate.admit(8, CODEC_H264, keyframe=False)
    gate.corrupt()  # frame 8 did not decode
    assert not gate.admit(9, CODEC_H264, keyframe=False)
    assert gate.skipped == 4 and gate.waits == 2
    assert gate.admit(11, CODEC_JPEG, keyframe=False)  # JPEG always decodes alone


def test_gate_across_a_codec_change_waits_for_a_keyframe() -> None:
    gate = KeyframeGate()
    assert gate.admit(1, CODEC_H264, keyframe=True)
    assert not gate.admit(2, CODEC_VP8, keyframe=False)
    assert gate.admit(3, CODEC_VP8, keyframe=True)


def test_requests_go_at_once_then_once_per_max_rtt_300ms() -> None:
    req = KeyframeRequests()
    assert not req.due(False, 0.0)
    assert req.due(True, 1.0)
    assert not req.due(True, 1.2)
    assert req.due(True, 1.31)  # a lost request is repeated
    assert not req.due(True, 1.9, rtt=0.8)
    assert req.due(True, 2.2, rtt=0.8)
    assert not req.due(False, 2.3)
    assert req.due(True, 2.31)  # a new need asks at once
    assert req.sent == 4


def test_the_sender_forces_keyframes_periodically_and_on_request_at_most_once_per_gap() -> None:
    pacer = KeyframePacer(interval=3.0)
    assert pacer.next_is_key(0.0)  # the first frame
    pacer.sent(True, 0.0)
    assert not pacer.next_is_key(0.1)
    assert not pacer.request(0.1)  # a keyframe went 100 ms ago
    assert pacer.request(0.5)
    assert pacer.request(0.55)  # still pending: the same keyframe answers it
    assert pacer.next_is_key(0.6)
    pacer.sent(True, 0.6)
    assert not pacer.request(0.7, rtt=0.5)
    assert not pacer.request(1.0, rtt=0.5)
    assert pacer.request(1.2, rtt=0.5)
    pacer.sent(True, 1.2)
    assert not pacer.next_is_key(4.1) and pacer.next_is_key(4.2)  # periodic
    assert (pacer.forced, pacer.ignored) == (2, 3)


def test_a_request_too_soon_after_a_keyframe_is_honoured_when_the_gap_ends() -> None:
    # The keyframe a request forced was lost: the receiver asks again before the gap is
    # over. The sender must not drop that request (the receiver would wait a whole repeat
    # interval more) but send a keyframe as soon as the gap allows.
    pacer = KeyframePacer(interval=3.0)
    pacer.sent(True, 0.0)
    assert pacer.request(1.0)
    assert pacer.next_is_key(1.0)
    pacer.sent(True, 1.0)  # lost on the way
    assert not pacer.request(1.1, rtt=0.05)  # 100 ms after it: too soon
    assert not pacer.next_is_key(1.2)
    assert pacer.next_is_key(1.3)  # min_gap (0.3 s) after the last keyframe
    pacer.sent(True, 1.3)
    assert not pacer.next_is_key(1.4)  # answered once, not again
    assert (pacer.forced, pacer.ignored) == (2, 1)


# --------------------------------------------------------------------------- audio


def test_an_audio_datagram_has_the_documented_layout() -> None:
    raw = encode_audio(7, 1_700_000_000.25, b"\xfc\x01\x02")
    assert raw.hex() == "031000000007" + "00060a2418221090" + "fc0102"
    packet = parse_audio(raw)
    assert (packet.seq, packet.capture_us, packet.data, packet.codec) == (
        7,
        1_700_000_000_250_000,
        b"\xfc\x01\x02",
        CODEC_OPUS,
    )
    with pytest.raises(ValueError, match=r"1\.\.3825"):
        encode_audio(1, 0.0, b"")


@pytest.mark.parametrize(
    "raw",
    [
        "text",
        b"",
        AUDIO_HEADER.pack(3, 0x10, 1, 2),  # header only
        AUDIO_HEADER.pack(1, 0x10, 1, 2) + b"x",  # a fragment's kind
        AUDIO_HEADER.pack(3, 0x11, 1, 2) + b"x",  # unknown codec
        AUDIO_HEADER.pack(3, 0x10, 1, 2) + bytes(MAX_OPUS_PACKET + 1),
    ],
)
def test_bad_audio_datagrams_are_refused(raw: str | bytes) -> None:
    with pytest.raises(ProtocolError):
        parse_audio(raw)


def test_the_sequencer_conceals_short_gaps_drops_late_packets_and_counts_garbage() -> None:
    seq = AudioSequencer()
    assert seq.on_datagram(encode_audio(10, 1.0, b"a"), 1.05) == [
        parse_audio(encode_audio(10, 1.0, b"a"))
    ]
    out = seq.on_datagram(encode_audio(13, 1.06, b"d"), 1.11)
    assert out[:2] == [None, None] and out[2] is not None and out[2].data == b"d"
    assert seq.on_datagram(encode_audio(12, 1.04, b"c"), 1.12) == []  # late
    assert seq.on_datagram(b"\x03garbage", 1.13) == []
    assert seq.on_datagram(encode_audio(100, 2.0, b"z"), 2.05)[:-1] == [None] * 5  # bounded
    stats = seq.stats
    assert (stats.packets, stats.lost, stats.late, stats.malformed) == (3, 88, 1, 1)
    report = seq.report(500)
    assert report.highest_seq == 100 and report.codecs == (CODEC_OPUS,)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=64))
def test_garbage_never_raises_out_of_the_receivers(raw: bytes) -> None:
    AudioSequencer().on_datagram(raw, 0.0)
    Reassembler(codec=VIDEO_CODECS).on_datagram(raw, 0.0)
    with contextlib.suppress(ProtocolError):
        parse_media_report(raw)
