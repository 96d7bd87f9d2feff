"""The video protocol, sans-IO: fragments, reassembly (loss, reordering, latest frame wins,
bad input), receiver reports, JPEG checks and the rate controller. No clock: ``now`` is a
number the tests move."""

from __future__ import annotations

import itertools
import math
import random
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telebot.channels.proto.frames import MAX_DATAGRAM
from telebot.errors import ProtocolError
from telebot.services.video.wire import (
    FRAGMENT_HEADER,
    JUMP_SLACK,
    MAX_FRAGMENTS,
    MAX_FRAME_BYTES,
    MAX_IN_FLIGHT,
    REPORT,
    CompleteFrame,
    Reassembler,
    Report,
    VideoRateController,
    VideoSettings,
    decode_jpeg,
    encode_jpeg,
    encode_report,
    fragment,
    fragment_span,
    jpeg_size,
    parse_fragment,
    parse_report,
    serial_diff,
)

CAMERA = "navcam"


def frame_bytes(frame_id: int, size: int) -> bytes:
    """Deterministic pseudo-random bytes of a frame (not a JPEG: reassembly does not decode)."""
    return random.Random(frame_id).randbytes(size)


def frags(frame_id: int, data: bytes, max_payload: int = 200, **kw: float) -> list[bytes]:
    return fragment(frame_id, CAMERA, 1000.0 + frame_id / 30, data, max_payload, **kw)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- fragments


def test_a_small_frame_is_one_datagram_with_the_documented_header() -> None:
    data = b"\xff\xd8hello"
    [datagram] = fragment(7, CAMERA, 1234.5, data, seq=41, interval=0.05)
    assert len(datagram) == FRAGMENT_HEADER.size + len(CAMERA) + len(data)
    # kind, codec, seq, frame_id, index, count, size, capture_us, interval_ms, name length
    assert FRAGMENT_HEADER.unpack_from(datagram) == (1, 1, 41, 7, 0, 1, 7, 1234500000, 50, 6)
    assert datagram[29:35] == b"navcam" and datagram[35:] == data
    parsed = parse_fragment(datagram)
    assert (parsed.frame_id, parsed.camera, parsed.data, parsed.seq) == (7, CAMERA, data, 41)


def test_a_frame_larger_than_a_datagram_is_split_into_full_sized_fragments() -> None:
    data = frame_bytes(1, 100_000)
    datagrams = fragment(1, CAMERA, 0.0, data, seq=2**32 - 1)
    assert len(datagrams) == 4  # 100,000 bytes at ~32.7 KB a datagram
    assert all(len(d) <= MAX_DATAGRAM for d in datagrams)
    parsed = [parse_fragment(d) for d in datagrams]
    assert [p.index for p in parsed] == [0, 1, 2, 3]
    assert [p.seq for p in parsed] == [2**32 - 1, 0, 1, 2]  # wraps
    assert b"".join(p.data for p in parsed) == data
    # Balanced split: lengths differ by at most one byte.
    lengths = {len(p.data) for p in parsed}
    assert max(lengths) - min(lengths) <= 1


@given(size=st.integers(1, 5000), count=st.integers(1, 64))
def test_fragment_spans_tile_the_frame(size: int, count: int) -> None:
    count = min(count, size)
    spans = [fragment_span(size, count, i) for i in range(count)]
    assert spans[0][0] == 0 and spans[-1][1] == size
    assert all(a[1] == b[0] for a, b in itertools.pairwise(spans))
    assert all(end > start for start, end in spans)


def test_fragment_refuses_what_cannot_be_sent() -> None:
    with pytest.raises(ValueError, match=r"1\.\."):
        fragment(1, CAMERA, 0.0, b"")
    with pytest.raises(ValueError, match="fragments"):
        fragment(1, CAMERA, 0.0, bytes(MAX_FRAGMENTS * 100 + 1), 100 + 35)
    with pytest.raises(ValueError, match="no room"):
        fragment(1, CAMERA, 0.0, b"abc", 30)
    with pytest.raises(ValueError, match="camera"):
        fragment(1, "x" * 33, 0.0, b"abc")
    with pytest.raises(ValueError, match=r"1\.\."):
        fragment(1, CAMERA, 0.0, bytes(MAX_FRAME_BYTES + 1))


# --------------------------------------------------------------------------- reassembly


@settings(max_examples=200, deadline=None)
@given(
    size=st.integers(1, 3000),
    max_payload=st.integers(60, 700),
    seed=st.integers(0, 2**32),
    loss=st.sampled_from([0.0, 0.1, 0.3]),
)
def test_one_frame_survives_reordering_and_completes_iff_nothing_is_lost(
    size: int, max_payload: int, seed: int, loss: float
) -> None:
    rng = random.Random(seed)
    data = frame_bytes(seed, size)
    room = max_payload - FRAGMENT_HEADER.size - len(CAMERA)
    if -(-size // room) > MAX_FRAGMENTS:
        with pytest.raises(ValueError, match="fragments"):
            frags(5, data, max_payload)
        return
    datagrams = frags(5, data, max_payload)
    kept = [d for d in datagrams if rng.random() >= loss]
    rng.shuffle(kept)
    if kept and rng.random() < 0.3:
        kept.insert(rng.randrange(len(kept) + 1), rng.choice(kept))  # a duplicate
    reassembler = Reassembler()
    results = [r for d in kept if (r := reassembler.on_datagram(d, 0.0)) is not None]
    if len(set(kept)) == len(datagrams):
        assert len(results) == 1 and results[0].data == data
        assert results[0].fragments == len(datagrams) and results[0].camera == CAMERA
        assert reassembler.in_flight == 0
    else:
        assert results == []
        reassembler.poll(1.0)  # one frame interval later the partial frame is gone
        assert reassembler.in_flight == 0
        assert reassembler.stats.incomplete == (1 if kept else 0)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32), loss=st.sampled_from([0.0, 0.05, 0.2]))
def test_a_lossy_reordered_stream_yields_intact_frames_in_increasing_order(
    seed: int, loss: float
) -> None:
    rng = random.Random(seed)
    originals: dict[int, bytes] = {}
    wire: list[tuple[float, bytes]] = []  # (arrival time, datagram)
    seq = 0
    intact: list[int] = []  # the frames none of whose datagrams was lost
    for frame_id in range(1, 61):
        data = frame_bytes(frame_id * 7919 + seed, rng.randrange(50, 2000))
        originals[frame_id] = data
        sent_at = frame_id / 30
        datagrams = frags(frame_id, data, 400, seq=seq, interval=1 / 30)
        seq += len(datagrams)
        kept = [d for d in datagrams if rng.random() >= loss]
        if len(kept) == len(datagrams):
            intact.append(frame_id)
        # Jitter reorders a frame's datagrams but, at 20 ms, never mixes two frames.
        wire.extend((sent_at + rng.uniform(0, 0.02), d) for d in kept)
    wire.sort(key=lambda item: item[0])
    reassembler = Reassembler()
    returned: list[CompleteFrame] = []
    for at, datagram in wire:
        result = reassembler.on_datagram(datagram, at)
        if result is not None:
            returned.append(result)
        assert reassembler.in_flight <= MAX_IN_FLIGHT
    ids = [f.frame_id for f in returned]
    assert ids == sorted(set(ids)), "latest frame wins: ids strictly increase"
    assert all(f.data == originals[f.frame_id] for f in returned)
    # Every frame that arrived whole is returned (jitter is less than a frame interval, so
    # no later frame overtakes it), and no other: with no loss, all 60.
    assert ids == intact
    if loss == 0.0:
        assert len(returned) == 60
    stats = reassembler.stats
    assert stats.frames == len(returned)
    assert stats.malformed == stats.inconsistent == stats.absurd == 0


def test_latest_frame_wins_a_late_frame_is_never_returned_after_a_newer_one() -> None:
    old = frags(1, frame_bytes(1, 500))
    new = frags(2, frame_bytes(2, 500))
    reassembler = Reassembler()
    assert reassembler.on_datagram(old[0], 0.0) is None  # frame 1 starts ...
    results = [reassembler.on_datagram(d, 0.001) for d in new]  # ... frame 2 overtakes it
    assert results[-1] is not None and results[-1].frame_id == 2
    assert reassembler.in_flight == 0  # frame 1 can never be shown now: dropped
    for d in old[1:]:  # the rest of frame 1 arrives late
        assert reassembler.on_datagram(d, 0.002) is None
    assert reassembler.stats.late == len(old) - 1
    assert reassembler.stats.incomplete == 1
    assert reassembler.newest_returned == 2


def test_an_incomplete_frame_is_dropped_one_frame_interval_after_its_first_fragment() -> None:
    datagrams = frags(1, frame_bytes(1, 1000), interval=0.1)
    reassembler = Reassembler()
    reassembler.on_datagram(datagrams[0], 10.0)
    assert reassembler.next_deadline() == pytest.approx(10.1)
    reassembler.poll(10.09)
    assert reassembler.in_flight == 1
    reassembler.poll(10.1)
    assert reassembler.in_flight == 0 and reassembler.stats.incomplete == 1
    assert reassembler.next_deadline() is None


def test_frames_in_reassembly_are_capped() -> None:
    reassembler = Reassembler()
    for frame_id in range(1, 50):
        reassembler.on_datagram(frags(frame_id, frame_bytes(frame_id, 1000))[0], 0.0)
        assert reassembler.in_flight <= MAX_IN_FLIGHT
    assert reassembler.stats.incomplete == 49 - MAX_IN_FLIGHT


def header(**fields: int) -> bytes:
    values = {
        "kind": 1,
        "codec": 1,
        "seq": 0,
        "frame_id": 1,
        "index": 0,
        "count": 1,
        "size": 4,
        "capture_us": 0,
        "interval_ms": 33,
        "name_len": 1,
    }
    values.update(fields)
    return FRAGMENT_HEADER.pack(*values.values()) + b"c"


@pytest.mark.parametrize(
    ("datagram", "why"),
    [
        (b"\x01\x01", "shorter than its header"),
        (header(kind=9) + b"abcd", "not a fragment"),
        (header(codec=7) + b"abcd", "codec"),
        (header(count=0) + b"abcd", "index 0 of 0"),
        (header(index=3, count=3, size=9) + b"abc", "index 3 of 3"),
        (header(count=65, size=65_000) + b"x" * 1000, "index 0 of 65"),
        (header(size=MAX_FRAME_BYTES + 1) + b"abcd", "frame size"),
        (header(count=5, size=4) + b"a", "frame size"),
        (header() + b"abcdefgh", "data bytes"),
        (header(name_len=0) + b"abcd", "camera name"),
        (header(name_len=40) + b"abcd", "camera name"),
        (FRAGMENT_HEADER.pack(1, 1, 0, 1, 0, 1, 4, 0, 33, 1) + b"\xff" + b"abcd", "UTF-8"),
    ],
)
def test_malformed_fragments_are_refused_and_counted(datagram: bytes, why: str) -> None:
    with pytest.raises(ProtocolError, match=why):
        parse_fragment(datagram)
    reassembler = Reassembler()
    assert reassembler.on_datagram(datagram, 0.0) is None
    assert reassembler.stats.malformed == 1 and reassembler.in_flight == 0


def test_text_datagrams_are_malformed() -> None:
    reassembler = Reassembler()
    assert reassembler.on_datagram("hello", 0.0) is None
    assert reassembler.stats.malformed == 1


def test_fragments_that_contradict_their_frame_are_dropped_and_counted() -> None:
    a = frags(1, frame_bytes(1, 1000))
    b = frags(1, frame_bytes(2, 1500))  # same frame id, another size and count
    reassembler = Reassembler()
    reassembler.on_datagram(a[0], 0.0)
    assert reassembler.on_datagram(b[1], 0.0) is None
    assert reassembler.stats.inconsistent == 1
    assert reassembler.on_datagram(a[0], 0.0) is None
    assert reassembler.stats.duplicates == 1
    results = [reassembler.on_datagram(d, 0.0) for d in a[1:]]
    assert results[-1] is not None and results[-1].data == frame_bytes(1, 1000)


def test_absurd_frame_ids_are_refused_but_a_stream_that_kept_counting_is_followed() -> None:
    reassembler = Reassembler()
    assert reassembler.on_datagram(frags(10, b"a")[0], 0.0) is not None
    # A wild jump would make every later real frame look old: refused.
    assert reassembler.on_datagram(frags(2_000_000_000, b"b")[0], 0.1) is None
    assert reassembler.stats.absurd == 1
    assert reassembler.on_datagram(frags(11, b"c")[0], 0.2) is not None
    # After a 10 s outage at 30 fps the sender is 300 frames on: followed.
    assert reassembler.on_datagram(frags(11 + 300, b"d")[0], 10.2) is not None
    assert reassembler.stats.absurd == 1
    assert reassembler.on_datagram(frags(311 + JUMP_SLACK, b"e")[0], 10.2) is not None


def test_frame_ids_wrap_around() -> None:
    reassembler = Reassembler()
    last = 2**32 - 1
    assert reassembler.on_datagram(frags(last, b"a")[0], 0.0) is not None
    wrapped = reassembler.on_datagram(frags(0, b"b")[0], 0.03)
    assert wrapped is not None and wrapped.frame_id == 0
    assert reassembler.on_datagram(frags(last, b"a")[0], 0.06) is None  # late now
    assert serial_diff(0, last) == 1 and serial_diff(last, 0) == -1


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(min_size=0, max_size=120), max_size=40))
def test_garbage_never_raises_and_never_grows_without_bound(datagrams: list[bytes]) -> None:
    reassembler = Reassembler()
    for i, junk in enumerate(datagrams):
        # Half of them with a valid-looking start, to get past the first checks.
        payload = (b"\x01\x01" + junk) if i % 2 else junk
        reassembler.on_datagram(payload, i * 0.01)
        assert reassembler.in_flight <= MAX_IN_FLIGHT


@settings(max_examples=100, deadline=None)
@given(
    frame_id=st.integers(0, 2**32 - 1),
    count=st.integers(1, MAX_FRAGMENTS),
    size=st.integers(1, MAX_FRAME_BYTES),
    index=st.integers(0, MAX_FRAGMENTS),
)
def test_forged_headers_with_absurd_sizes_allocate_at_most_the_cap(
    frame_id: int, count: int, size: int, index: int
) -> None:
    # A header may announce up to MAX_FRAME_BYTES; the reassembler holds at most
    # MAX_IN_FLIGHT such frames, whatever comes.
    reassembler = Reassembler()
    for k in range(10):
        head = FRAGMENT_HEADER.pack(1, 1, k, (frame_id + k) % 2**32, index, count, size, 0, 33, 1)
        start, end = fragment_span(size, count, min(index, count - 1)) if size >= count else (0, 1)
        reassembler.on_datagram(head + b"c" + bytes(min(end - start, 40_000)), 0.0)
    assert reassembler.in_flight <= MAX_IN_FLIGHT


# --------------------------------------------------------------------------- reports


def test_reports_round_trip_and_wrap() -> None:
    report = Report(
        receiver_ms=2**32 + 5,
        highest_seq=17,
        fragments=2**32 + 3,
        data_bytes=123_456,
        frames=9,
        dropped=1,
        queue_delay_ms=70_000,
    )
    datagram = encode_report(report)
    assert len(datagram) == REPORT.size == 28 and datagram[0] == 0x02
    parsed = parse_report(datagram)
    assert parsed == Report(5, 17, 3, 123_456, 9, 1, 0xFFFF)
    bye = parse_report(encode_report(Report(1, 0, 0, 0, 0, 0, 0, bye=True)))
    assert bye.bye and encode_report(bye)[1] == 0x01
    for bad in (datagram[:-1], b"\x01" + datagram[1:], "text"):
        with pytest.raises(ProtocolError):
            parse_report(bad)


def test_the_reassembler_reports_what_it_received() -> None:
    reassembler = Reassembler()
    datagrams = frags(1, frame_bytes(1, 1000), seq=100)
    for d in datagrams[1:]:  # the first one is lost
        reassembler.on_datagram(d, 0.0)
    reassembler.poll(1.0)
    report = reassembler.report(1234)
    assert report.highest_seq == 100 + len(datagrams) - 1
    assert report.fragments == len(datagrams) - 1
    assert report.frames == 0 and report.dropped == 1 and report.receiver_ms == 1234


def test_queue_delay_is_the_transit_above_its_minimum() -> None:
    reassembler = Reassembler()
    # Capture times are on another clock (offset 1000 s): only differences count.
    for i, extra in enumerate([0.0, 0.0, 0.08]):
        [d] = fragment(i + 1, CAMERA, 1000.0 + i, b"x")
        reassembler.on_datagram(d, i + 0.01 + extra)
    assert reassembler.queue_delay == pytest.approx(0.08)


# --------------------------------------------------------------------------- JPEG


def test_jpeg_size_reads_the_header_and_decode_round_trips() -> None:
    image = np.zeros((48, 64, 3), dtype=np.uint8)
    image[:, :32] = (0, 0, 255)
    data = encode_jpeg(image, 90)
    assert jpeg_size(data) == (64, 48)
    decoded = decode_jpeg(data)
    assert decoded.shape == (48, 64, 3) and decoded.dtype == np.uint8
    assert abs(int(decoded[10, 10, 2]) - 255) < 10 and int(decoded[10, 50, 2]) < 10


def test_corrupt_and_oversized_jpegs_are_refused() -> None:
    good = encode_jpeg(np.full((32, 32, 3), 128, dtype=np.uint8), 80)
    for bad in (b"", b"not a jpeg", good[:20], b"\xff\xd8\xff\xd9"):
        with pytest.raises(ProtocolError):
            decode_jpeg(bad)
    # A forged frame header announcing 60000 × 60000 pixels is refused before decoding.
    at = good.index(b"\xff\xc0")
    forged = bytearray(good)
    struct.pack_into(">HH", forged, at + 5, 60000, 60000)
    with pytest.raises(ProtocolError, match="out of bounds"):
        decode_jpeg(bytes(forged))
    # Garbage after a valid header: OpenCV may decode garbage, but never crashes us.
    mangled = good[:200] + bytes(len(good) - 200)
    try:
        image = decode_jpeg(mangled)
    except ProtocolError:
        pass
    else:
        assert image.shape == (32, 32, 3)  # whatever it shows, it has the header's size


# --------------------------------------------------------------------------- controller


class LinkModel:
    """Feeds a controller reports of a link with ``loss``, optional ``capacity`` (bytes/s)."""

    def __init__(self, controller: VideoRateController) -> None:
        self.controller = controller
        self.now = 0.0
        self.seq = self.fragments = self.bytes = 0
        self.rng = random.Random(3)
        self.queue = 0.0  # seconds of backlog

    def size_of(self, quality: int, scale: float, base: int) -> int:
        # JPEG size roughly doubles from quality 50 to 90 and goes with the picture area.
        return int(base * scale * scale * 2 ** ((quality - 80) / 40))

    def run(self, seconds: float, *, loss: float, base: int, capacity: float | None = None) -> None:
        c = self.controller
        end = self.now + seconds
        next_report = self.now
        while self.now < end:
            size = self.size_of(c.quality, c.scale, base)
            if c.on_encoded(size, self.now):
                size = self.size_of(c.quality, c.scale, base)
            count = -(-size // c.data_per_fragment)
            self.seq += count
            if capacity is not None:
                self.queue = max(0.0, self.queue + size / capacity - c.frame_interval)
            tail_drop = capacity is not None and self.queue > 0.3
            if tail_drop:
                self.queue -= size / capacity  # type: ignore[operator]
            for _ in range(count):
                if not tail_drop and self.rng.random() >= loss:
                    self.fragments += 1
                    self.bytes += size // count
            self.now += c.frame_interval
            if self.now >= next_report:
                report = Report(
                    round(self.now * 1000),
                    self.seq,
                    self.fragments,
                    self.bytes,
                    0,
                    0,
                    round(self.queue * 1000),
                )
                c.on_report(report, self.now)
                next_report = self.now + 0.2


def controller(**kw: object) -> VideoRateController:
    return VideoRateController(VideoSettings(**kw), data_per_fragment=32_000)  # type: ignore[arg-type]


def test_random_loss_shrinks_frames_to_fewer_fragments_but_keeps_the_frame_rate() -> None:
    c = controller()
    link = LinkModel(c)
    link.run(3.0, loss=0.0, base=50_000)  # 2 fragments at quality 80: fine on a clean link
    assert c.quality == 80 and c.max_fragments == 8 and c.fps == 30
    link.run(5.0, loss=0.10, base=50_000)
    assert c.loss == pytest.approx(0.10, abs=0.05)
    assert c.max_fragments == 1
    assert link.size_of(c.quality, c.scale, 50_000) <= 32_000  # one fragment a frame
    assert c.fps == 30 and c.rate is None  # random loss is not congestion
    link.run(6.0, loss=0.0, base=50_000)  # the link heals: quality comes back
    assert c.quality == 80 and c.scale == 1.0 and c.max_fragments > 1


def test_very_large_frames_step_the_scale_down_and_back_up() -> None:
    c = controller()
    link = LinkModel(c)
    link.run(5.0, loss=0.2, base=150_000)  # 5 fragments at quality 80, at 20 % loss
    assert c.max_fragments == 1
    assert c.scale < 1.0 and c.quality >= 30
    assert link.size_of(c.quality, c.scale, 150_000) <= 32_000
    link.run(10.0, loss=0.0, base=150_000)
    assert (c.quality, c.scale) == (80, 1.0)


def test_congestion_lowers_rate_quality_and_fps_and_they_recover() -> None:
    c = controller()
    link = LinkModel(c)
    link.run(2.0, loss=0.0, base=25_000)  # 750 KB/s wanted
    assert c.rate is None
    link.run(8.0, loss=0.0, base=25_000, capacity=60_000)  # the link carries 60 KB/s
    assert c.rate is not None and c.rate < 150_000
    sent = link.size_of(c.quality, c.scale, 25_000) * c.fps
    assert sent < 120_000  # the stream fits the link, about
    assert c.decreases >= 1
    assert (c.quality, c.scale, c.fps) != (80, 1.0, 30.0)
    link.run(25.0, loss=0.0, base=25_000)  # capacity is back
    assert (c.quality, c.scale, c.fps) == (80, 1.0, 30.0)
    assert c.rate is None


def test_a_fixed_stream_ignores_the_link() -> None:
    c = controller(adaptive=False)
    link = LinkModel(c)
    link.run(3.0, loss=0.5, base=200_000, capacity=10_000)
    assert (c.quality, c.scale, c.fps) == (80, 1.0, 30.0)


def test_reports_are_the_subscription() -> None:
    c = controller(idle_after=2.0)
    assert not c.watching(0.0)
    c.on_report(Report(0, 0, 0, 0, 0, 0, 0), 1.0)
    assert c.watching(2.9) and not c.watching(3.1)
    c.on_report(Report(10, 0, 0, 0, 0, 0, 0, bye=True), 3.2)
    assert not c.watching(3.2)  # the receiver said goodbye: stop at once
    c.on_report(Report(5, 0, 0, 0, 0, 0, 0), 3.3)  # an older report, reordered: ignored
    assert not c.watching(3.3)
    c.on_report(Report(20, 0, 0, 0, 0, 0, 0), 3.4)  # watching again
    assert c.watching(3.4)
    assert controller(on_demand=False).watching(0.0)


def test_stale_or_reordered_reports_fall_back_to_heartbeats() -> None:
    c = controller()
    c.on_report(Report(1000, 10, 10, 0, 0, 0, 0), 0.0)
    c.on_report(Report(1200, 20, 15, 0, 0, 0, 0), 0.2)  # half of ten fragments lost
    assert c.loss == pytest.approx(0.5)
    c.on_report(Report(1100, 99, 0, 0, 0, 0, 0), 0.3)  # older: ignored
    assert c.loss == pytest.approx(0.5)
    c.on_link(loss=0.02, rtt=0.05, now=0.5)
    assert c.loss == pytest.approx(0.5)  # reports are fresh: they win
    c.on_link(loss=0.02, rtt=0.05, now=5.0)
    assert c.loss == pytest.approx(0.02) and c.link.rtt == 0.05
    assert c.max_fragments == 6  # 0.98^6 ≈ 0.886


def test_fragment_budget_follows_loss() -> None:
    c = controller()
    budgets = {}
    for loss in (0.0, 0.01, 0.05, 0.1, 0.5, 1.0):
        c.link.heartbeat_loss = loss
        budgets[loss] = c.max_fragments
    assert budgets == {0.0: 8, 0.01: 8, 0.05: 2, 0.1: 1, 0.5: 1, 1.0: 1}
    assert all(
        (1 - loss) ** k >= 0.88
        for loss, k in budgets.items()
        if k > 1 and not math.isclose(loss, 0)
    )


def test_settings_are_validated() -> None:
    for bad in (
        {"max_fps": 0},
        {"min_fps": 40},
        {"quality": 101},
        {"min_quality": 90},
        {"min_scale": 0},
        {"max_payload": 40},
        {"max_payload": MAX_DATAGRAM + 1},
        {"width": 8},
    ):
        with pytest.raises(ValueError, match="video settings"):
            VideoSettings(**bad)  # type: ignore[arg-type]
    assert VideoSettings(min_scale=0.5).scales == (1.0, 0.75, 0.5)


def test_the_probe_runs_from_the_first_frame_sent_not_from_creation() -> None:
    # A user's camera slow to start (an encoder, a webcam) must not use the probe up: the
    # sender keeps trying until its first picture goes out, then probes for ``probe`` s.
    rc = VideoRateController(
        VideoSettings(on_demand=True, probe=2.0), data_per_fragment=32_000, now=0.0
    )
    assert rc.watching(5.0)  # nothing sent yet, 5 s after creation
    rc.frame_sent(5.0)
    rc.frame_sent(6.0)  # later frames do not move the start
    assert rc.watching(6.9)
    assert not rc.watching(7.1)  # no report within the probe: the robot does not want it


def test_a_backlog_of_unreported_frames_holds_new_frames_but_lets_a_probe_through() -> None:
    c = controller()
    c.on_link(loss=0.0, rtt=0.1, now=0.0)
    c.frame_sent(0.0, 2)
    assert not c.held_up(5.0)  # before any report: nothing to judge by
    c.on_report(Report(0, 2, 0, 0, 0, 0, 0), 0.0)
    c.on_report(Report(200, 2, 0, 0, 0, 0, 0), 0.2)  # reports every 0.2 s
    # limit = least round trip 0.1 + gap between reports 0.2 + BACKLOG_SLACK 0.1 = 0.4 s.
    sent = [(0.2 + 0.05 * i, 3 * i + 5) for i in range(10)]  # 20 fps, 3 fragments each
    for at, last_seq in sent:
        c.frame_sent(at, last_seq)
    c.on_report(Report(400, sent[0][1], 0, 0, 0, 0, 0), 0.4)  # the first one arrived
    oldest = sent[1][0]  # 0.25: not reported yet
    assert not c.held_up(oldest + 0.39) and c.held_up(oldest + 0.41)
    # While held, one frame per limit, at most BACKLOG_PROBE (0.25 s), still goes (a
    # probe), so frames lost for good or a receiver that took none cannot stop the video
    # for ever, nor freeze it for the stale-video rule.
    newest = sent[-1][0]  # 0.65
    assert c.held_up(newest + 0.24) and not c.held_up(newest + 0.26)
    c.frame_sent(newest + 0.26, 40)
    assert c.held_up(newest + 0.3)
    # The receiver catches up: everything covered, frames flow again.
    c.on_report(Report(600, 40, 0, 0, 0, 0, 0), 1.2)
    assert not c.held_up(1.2)
    # The round trip that counts is the least seen, not one a queue inflated.
    c.on_link(loss=0.0, rtt=2.0, now=1.3)
    c.frame_sent(1.3, 43)
    c.frame_sent(1.5, 46)
    assert c.held_up(1.3 + 0.4 + 0.2 + 0.01) is False  # gap between reports is now 0.8
    c.on_report(Report(800, 40, 0, 0, 0, 0, 0), 1.4)  # reports every 0.2 s again
    assert c.held_up(1.3 + 0.41) and not c.held_up(1.5 + 0.26)
