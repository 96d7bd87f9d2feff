"""Map transfer, sans-IO: PNG encoding and the chunked transfer driven with a fake clock."""

from __future__ import annotations

import hashlib
import heapq
import itertools
import json
import math
import os
import random
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from telebot.channels.proto.frames import MAX_DATAGRAM
from telebot.errors import MapError, ProtocolError
from telebot.robot.grid import OccupancyGrid
from telebot.robot.mapfile import CELL_FREE_MAX, CELL_OCCUPIED_MIN, load_map, map_yaml
from telebot.services.mapxfer.wire import (
    ALREADY_RUNNING,
    CHUNK_HEADER,
    IDLE_TIMEOUT,
    MAX_CHUNK_DATA,
    MAX_MAP_BYTES,
    MAX_RESEND_INDICES,
    REPEATS,
    REQUEST_INTERVAL,
    RESEND_AFTER,
    STALE_AFTER,
    EncodedMap,
    MapReceiver,
    MapSender,
    decode_map,
    encode_map,
    png_size,
)

# --------------------------------------------------------------------------- helpers


def grid_of(
    data: list[list[int]] | np.ndarray, res: float = 0.05, ox: float = -1.0, oy: float = 2.0
) -> OccupancyGrid:
    return OccupancyGrid(np.asarray(data, dtype=np.int8), res, ox, oy)


def fake_map(size: int, seed: int = 0, version: int = 0) -> EncodedMap:
    """An EncodedMap of ``size`` random bytes: the transfer does not look inside the PNG."""
    png = random.Random(seed).randbytes(size)
    digest = hashlib.sha256(png).hexdigest()
    return EncodedMap(png, digest, 7, 5, 0.05, -3.5, 1.25, "office", version=version)


def messages(replies: list[str] | list[str | bytes]) -> list[dict[str, Any]]:
    out = []
    for reply in replies:
        assert isinstance(reply, str)
        out.append(json.loads(reply))
    return out


def get(xfer: int) -> str:
    return json.dumps({"type": "get", "xfer": xfer})


def offer_for(sender: MapSender, receiver: MapReceiver, now: float = 0.0) -> dict[str, Any]:
    """Start a transfer: the receiver's get, the sender's offer (not yet delivered)."""
    (offer,) = sender.on_message(receiver.request(now), now)
    assert isinstance(offer, str)
    decoded: dict[str, Any] = json.loads(offer)
    return decoded


def deliver_all(sender: MapSender, receiver: MapReceiver, now: float) -> list[str]:
    """Hand every pending chunk to the receiver; returns its replies."""
    replies: list[str] = []
    while sender.has_pending:
        for chunk in sender.next_chunks(16):
            replies += receiver.on_message(chunk, now)
    return replies


def receiving(encoded: EncodedMap, chunk_size: int = 1024) -> tuple[MapSender, MapReceiver]:
    """A sender and a receiver with the offer delivered and no chunk yet."""
    sender = MapSender(lambda: encoded, chunk_size=chunk_size)
    receiver = MapReceiver(42)
    offer = offer_for(sender, receiver)
    assert receiver.on_message(json.dumps(offer), 0.01) == []
    assert receiver.state == "receiving"
    return sender, receiver


# --------------------------------------------------------------------------- encoding


@st.composite
def bordered_grids(draw: st.DrawFn) -> tuple[OccupancyGrid, tuple[int, int, int, int]]:
    """A small trinary grid inside an unknown border; also the bounds of its known cells."""
    h, w = draw(st.integers(1, 10)), draw(st.integers(1, 10))
    core = draw(arrays(np.int8, (h, w), elements=st.sampled_from([-1, 0, 100])))
    if not (core != -1).any():
        core[draw(st.integers(0, h - 1)), draw(st.integers(0, w - 1))] = draw(
            st.sampled_from([0, 100])
        )
    top, bottom, left, right = (draw(st.integers(0, 4)) for _ in range(4))
    data = np.pad(core, ((bottom, top), (left, right)), constant_values=-1)
    res = draw(st.sampled_from([0.05, 0.1, 0.025, 1.0]))
    ox = draw(st.floats(-1000, 1000, allow_nan=False))
    oy = draw(st.floats(-1000, 1000, allow_nan=False))
    known = np.argwhere(data != -1)
    (r0, c0), (r1, c1) = known.min(axis=0), known.max(axis=0) + 1
    return OccupancyGrid(data, res, ox, oy), (int(r0), int(r1), int(c0), int(c1))


@settings(max_examples=150, deadline=None)
@given(bordered_grids())
def test_encode_decode_is_the_exact_crop(
    case: tuple[OccupancyGrid, tuple[int, int, int, int]],
) -> None:
    grid, (r0, r1, c0, c1) = case
    encoded = encode_map(grid)
    assert (encoded.width, encoded.height) == (c1 - c0, r1 - r0)
    assert png_size(encoded.png) == (encoded.width, encoded.height)
    assert encoded.sha256 == hashlib.sha256(encoded.png).hexdigest()
    assert encoded.origin_x == grid.origin_x + c0 * grid.resolution
    assert encoded.origin_y == grid.origin_y + r0 * grid.resolution
    decoded = decode_map(encoded.png, encoded.resolution, encoded.origin_x, encoded.origin_y)
    assert np.array_equal(decoded.data, grid.data[r0:r1, c0:c1])
    # The same world point has the same value in both grids.
    x, y = decoded.center_of(0, 0)
    assert grid.value_at(x, y) == decoded.value_at(x, y)


def test_rows_are_flipped_top_row_farthest_from_origin() -> None:
    grid = grid_of([[100, 0, 0], [0, -1, 0]])  # row 0 (bottom) has the wall at its left
    encoded = encode_map(grid)
    image = cv2.imdecode(np.frombuffer(encoded.png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image is not None
    assert image.dtype == np.uint8 and image.ndim == 2
    assert image.tolist() == [[254, 205, 254], [0, 254, 254]]


def test_pixel_values_follow_map_saver_thresholds() -> None:
    free, occupied = CELL_FREE_MAX, CELL_OCCUPIED_MIN
    values = [0, free, free + 1, occupied - 1, occupied, 100, -1, 101, 127, -128, -2]
    encoded = encode_map(grid_of([values]))
    image = cv2.imdecode(np.frombuffer(encoded.png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image is not None
    assert image[0].tolist() == [254, 254, 205, 205, 0, 0, 205, 205, 205, 205, 205]


def test_decode_reads_other_shades_like_map_server() -> None:
    image = np.array([[0, 89, 90, 204, 205, 206, 254, 255]], dtype=np.uint8)
    ok, png = cv2.imencode(".png", image)
    assert ok
    grid = decode_map(png.tobytes(), 0.1, 0.0, 0.0)
    # occupancy 1 - v/255: > 0.65 occupied, < 0.196 free, else unknown
    assert grid.data[0].tolist() == [100, 100, -1, -1, -1, 0, 0, 0]


def test_an_all_unknown_map_cannot_be_encoded() -> None:
    with pytest.raises(MapError, match="no known cells"):
        encode_map(grid_of(np.full((5, 5), -1)), name="empty")


@pytest.mark.parametrize(
    "png",
    [b"", b"not a png at all, just text....", b"\x89PNG\r\n\x1a\n" + b"\0" * 30],
)
def test_decode_refuses_what_is_not_a_png(png: bytes) -> None:
    with pytest.raises(ProtocolError):
        decode_map(png, 0.05, 0.0, 0.0)


def test_decode_refuses_colour_images_and_bad_georeference() -> None:
    ok, colour = cv2.imencode(".png", np.zeros((2, 2, 3), np.uint8))
    assert ok
    with pytest.raises(ProtocolError, match="8-bit grey"):
        decode_map(colour.tobytes(), 0.05, 0.0, 0.0)
    grey = encode_map(grid_of([[0]])).png
    with pytest.raises(ProtocolError, match="georeference"):
        decode_map(grey, -1.0, 0.0, 0.0)


def test_png_and_yaml_load_back_in_ros_map_server_loader(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    data = rng.choice(np.array([-1, 0, 100], dtype=np.int8), size=(40, 60))
    data[:5] = -1
    data[:, -7:] = -1
    grid = grid_of(data, res=0.05, ox=-12.3, oy=4.56)
    encoded = encode_map(grid)
    (tmp_path / "m.png").write_bytes(encoded.png)
    text = map_yaml("m.png", encoded.resolution, encoded.origin_x, encoded.origin_y)
    (tmp_path / "m.yaml").write_text(text)
    meta = yaml.safe_load(text)
    assert meta["mode"] == "trinary" and meta["negate"] == 0
    assert meta["occupied_thresh"] == 0.65
    # 205 (occupancy 50/255 = 0.19608) must stay unknown: map_saver's 0.25 would make it free
    assert meta["free_thresh"] < 50 / 255
    loaded = load_map(tmp_path / "m.yaml")
    r0, r1, c0, c1 = grid.known_bounds()  # type: ignore[misc]
    assert np.array_equal(loaded.data, grid.data[r0:r1, c0:c1])
    assert (loaded.origin_x, loaded.origin_y) == (encoded.origin_x, encoded.origin_y)
    assert loaded.resolution == encoded.resolution


def test_a_click_on_the_image_maps_to_world_coordinates() -> None:
    data = np.full((20, 30), -1, dtype=np.int8)
    data[4:9, 10:25] = 0
    grid = grid_of(data, res=0.1, ox=-5.0, oy=-2.0)
    encoded = encode_map(grid)
    # The centre of the image's bottom-left pixel is the centre of cell (4, 10).
    x, y = encoded.world_of_pixel(0.5, encoded.height - 0.5)
    assert (x, y) == pytest.approx(grid.center_of(4, 10))
    x, y = encoded.world_of_pixel(encoded.width - 0.5, 0.5)  # top-right pixel
    assert (x, y) == pytest.approx(grid.center_of(8, 24))


# --------------------------------------------------------------------------- chunking


@pytest.mark.parametrize(("size", "chunks"), [(MAX_CHUNK_DATA, 1), (MAX_CHUNK_DATA + 1, 2)])
def test_chunking_at_exactly_one_chunk_and_one_byte_more(size: int, chunks: int) -> None:
    encoded = fake_map(size)
    sender = MapSender(lambda: encoded)
    receiver = MapReceiver(7)
    offer = offer_for(sender, receiver)
    assert offer["chunks"] == chunks and offer["chunk_size"] == MAX_CHUNK_DATA
    assert offer["size"] == size
    receiver.on_message(json.dumps(offer), 0.0)
    datagrams = sender.next_chunks(100)
    assert len(datagrams) == chunks and not sender.has_pending
    assert len(datagrams[0]) == MAX_DATAGRAM  # a full chunk fills a datagram exactly
    if chunks == 2:
        assert len(datagrams[1]) == CHUNK_HEADER.size + 1
        assert datagrams[1][: CHUNK_HEADER.size] == CHUNK_HEADER.pack(1, 7, 1)
    replies: list[str] = []
    for datagram in datagrams:
        replies += receiver.on_message(datagram, 0.0)
    assert messages(replies) == [{"type": "done", "xfer": 7}] * REPEATS
    assert receiver.done and receiver.result is not None
    assert receiver.result.png == encoded.png
    assert receiver.progress == (size, size)
    assert receiver.resent == 0 and receiver.rejected == 0


def test_offer_carries_the_georeference() -> None:
    encoded = fake_map(100, version=12)
    offer = offer_for(MapSender(lambda: encoded), MapReceiver(1))
    assert offer == {
        "type": "offer",
        "xfer": 1,
        "name": "office",
        "size": 100,
        "chunks": 1,
        "chunk_size": MAX_CHUNK_DATA,
        "sha256": encoded.sha256,
        "width": 7,
        "height": 5,
        "resolution": 0.05,
        "origin": [-3.5, 1.25],
        "version": 12,
    }


def test_an_offer_without_a_version_is_version_0() -> None:
    # Robots from before map versions do not send one.
    sender, receiver = MapSender(lambda: fake_map(10, version=5)), MapReceiver(1)
    offer = offer_for(sender, receiver)
    del offer["version"]
    receiver.on_message(json.dumps(offer), 0.0)
    deliver_all(sender, receiver, 0.0)
    assert receiver.done and receiver.result is not None and receiver.result.version == 0


@pytest.mark.parametrize("version", [-1, 2**53, 1.5, True, "3"])
def test_an_offer_with_a_bad_version_is_rejected(version: Any) -> None:
    sender, receiver = MapSender(lambda: fake_map(10)), MapReceiver(1)
    offer = offer_for(sender, receiver)
    offer["version"] = version
    receiver.on_message(json.dumps(offer), 0.0)
    assert receiver.offer is None and receiver.rejections["bad_offer"] == 1


def test_a_map_that_changes_mid_transfer_finishes_as_offered_and_the_next_is_new() -> None:
    current = fake_map(3 * MAX_CHUNK_DATA, seed=1, version=1)
    sender = MapSender(lambda: current)
    first = MapReceiver(1)
    first.on_message(json.dumps(offer_for(sender, first)), 0.0)
    half = sender.next_chunks(2)
    current = fake_map(2 * MAX_CHUNK_DATA, seed=2, version=2)  # SLAM: the map changed
    replies = [r for chunk in half for r in first.on_message(chunk, 0.1)]
    replies += deliver_all(sender, first, 0.1)
    assert first.done and first.result is not None
    assert first.result.version == 1 and first.result.png == fake_map(3 * MAX_CHUNK_DATA, 1).png
    for reply in replies:
        sender.on_message(reply, 0.2)
    second = MapReceiver(2)
    offer = offer_for(sender, second, 0.3)
    assert offer["version"] == 2 and offer["sha256"] == current.sha256
    second.on_message(json.dumps(offer), 0.3)
    deliver_all(sender, second, 0.3)
    assert second.result is not None and second.result.png == current.png


# --------------------------------------------------------------------------- loss and reordering


def simulate(
    encoded: EncodedMap,
    *,
    seed: int,
    loss: float,
    jitter: float,
    chunk_size: int,
    latency: float = 0.002,
    burst: int = 4,
    pump_interval: float = 0.0005,
    max_time: float = 60.0,
) -> tuple[MapSender, MapReceiver, float]:
    """Run one transfer over a simulated link: each datagram is lost with ``loss`` (both
    ways), delayed by ``latency`` + uniform(0, ``jitter``) (so reordered), with a fake clock."""
    rng = random.Random(seed)
    sender = MapSender(lambda: encoded, chunk_size=chunk_size)
    receiver = MapReceiver(rng.getrandbits(32))
    in_flight: list[tuple[float, int, str, str | bytes]] = []
    order = itertools.count()
    now = 0.0

    def send(to: str, payload: str | bytes) -> None:
        if rng.random() >= loss:
            arrival = now + latency + rng.random() * jitter
            heapq.heappush(in_flight, (arrival, next(order), to, payload))

    send("robot", receiver.request(now))
    next_pump = math.inf
    while now < max_time and not receiver.failed:
        if receiver.done and not in_flight:
            break
        times = [
            next_pump,
            receiver.next_deadline() or math.inf,
            sender.next_deadline() or math.inf,
        ]
        if in_flight:
            times.append(in_flight[0][0])
        if min(times) == math.inf:
            break
        now = max(now, min(times))
        while in_flight and in_flight[0][0] <= now:
            _, _, to, payload = heapq.heappop(in_flight)
            if to == "robot":
                for reply in sender.on_message(payload, now):
                    send("user", reply)
            else:
                for reply in receiver.on_message(payload, now):
                    send("robot", reply)
        if sender.has_pending and next_pump == math.inf:
            next_pump = now
        if now >= next_pump:
            for chunk in sender.next_chunks(burst):
                send("user", chunk)
            next_pump = now + pump_interval if sender.has_pending else math.inf
        for message in receiver.poll(now):
            send("robot", message)
        sender.poll(now)
    return sender, receiver, now


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    loss=st.floats(0.0, 0.5),
    jitter=st.floats(0.0, 0.05),
    size=st.integers(1, 40_000),
    chunk_size=st.integers(200, 4096),
)
def test_transfer_completes_under_loss_and_reordering(
    seed: int, loss: float, jitter: float, size: int, chunk_size: int
) -> None:
    encoded = fake_map(size, seed)
    sender, receiver, now = simulate(
        encoded, seed=seed, loss=loss, jitter=jitter, chunk_size=chunk_size
    )
    assert receiver.done, (receiver.state, receiver.error, receiver.progress)
    assert receiver.result is not None and receiver.result.png == encoded.png
    assert receiver.progress == (size, size)
    assert receiver.rejected == 0 and sender.rejected == 0
    if loss == 0.0:
        assert receiver.resent == 0 and sender.chunks_resent == 0
    # The robot forgot the transfer: on "done", or (all three lost) once idle.
    sender.poll(now + IDLE_TIMEOUT)
    assert not sender.active


def test_thirty_percent_loss_with_reordering_resends_only_what_is_missing() -> None:
    encoded = fake_map(300_000, seed=5)
    sender, receiver, now = simulate(
        encoded, seed=99, loss=0.3, jitter=0.02, chunk_size=MAX_CHUNK_DATA
    )
    assert receiver.done and receiver.result is not None
    assert receiver.result.png == encoded.png
    chunks = -(-300_000 // MAX_CHUNK_DATA)
    assert receiver.resent > 0
    # Each round asks only for what is missing: far fewer than "everything again" rounds.
    assert sender.chunks_sent < 3 * chunks
    assert now < 5.0


def test_chunks_before_the_offer_are_kept() -> None:
    encoded = fake_map(5000)
    sender = MapSender(lambda: encoded, chunk_size=1000)
    receiver = MapReceiver(3)
    (offer,) = sender.on_message(receiver.request(0.0), 0.0)
    for chunk in sender.next_chunks(10):
        assert receiver.on_message(chunk, 0.001) == []
    assert receiver.progress == (0, 0)  # size unknown until the offer
    assert isinstance(offer, str)
    replies = receiver.on_message(offer, 0.002)
    assert messages(replies) == [{"type": "done", "xfer": 3}] * REPEATS
    assert receiver.result is not None and receiver.result.png == encoded.png
    assert receiver.resent == 0


def test_chunks_without_their_offer_make_the_get_come_again_sooner() -> None:
    encoded = fake_map(5000)
    sender = MapSender(lambda: encoded, chunk_size=1000)
    receiver = MapReceiver(4)
    sender.on_message(receiver.request(0.0), 0.0)  # the offer is lost
    for chunk in sender.next_chunks(10):
        receiver.on_message(chunk, 0.01)
    assert receiver.next_deadline() == pytest.approx(0.01 + RESEND_AFTER)
    assert receiver.poll(0.01 + RESEND_AFTER - 0.001) == []
    (again,) = receiver.poll(0.01 + RESEND_AFTER)
    (offer,) = sender.on_message(again, 0.1)
    assert isinstance(offer, str) and not sender.has_pending  # no chunk is sent twice
    assert receiver.poll(0.1 + RESEND_AFTER / 2) == []  # not again straight away
    receiver.on_message(offer, 0.11)
    assert receiver.done and receiver.result is not None and receiver.result.png == encoded.png


def test_the_get_is_repeated_until_an_offer_comes_and_the_robot_repeats_its_offer() -> None:
    encoded = fake_map(5000)
    sender = MapSender(lambda: encoded, chunk_size=1000)
    receiver = MapReceiver(9)
    first = receiver.request(0.0)
    assert receiver.poll(REQUEST_INTERVAL - 0.01) == []
    assert receiver.next_deadline() == REQUEST_INTERVAL
    (again,) = receiver.poll(REQUEST_INTERVAL)
    assert again == first and receiver.requests == 2
    offer1 = sender.on_message(first, 0.0)
    pending = sender.next_chunks(100)
    offer2 = sender.on_message(again, 0.3)  # the repeat gets the offer again, no chunks
    assert offer1 == offer2 and not sender.has_pending and len(pending) == 5
    assert receiver.on_message(offer2[0], 0.31) == []
    assert receiver.on_message(offer1[0], 0.32) == []  # the same offer twice: harmless
    assert receiver.rejected == 0 and receiver.state == "receiving"


def test_resend_waits_for_silence_and_asks_only_for_missing_chunks() -> None:
    encoded = fake_map(10_000)
    sender, receiver = receiving(encoded, chunk_size=1000)
    chunks = sender.next_chunks(10)
    for index in (0, 1, 2, 4, 5, 6, 8):
        receiver.on_message(chunks[index], 0.02 + index * 0.001)
    last = 0.028
    assert receiver.poll(last + RESEND_AFTER - 0.001) == []
    (resend,) = messages(receiver.poll(last + RESEND_AFTER + 0.001))
    assert resend == {"type": "resend", "xfer": 42, "missing": [3, 7, 9]}
    assert receiver.resent == 3
    assert sender.on_message(json.dumps(resend), 0.2) == []
    resent = sender.next_chunks(10)
    assert [CHUNK_HEADER.unpack_from(c)[2] for c in resent] == [3, 7, 9]
    assert sender.chunks_resent == 3
    replies: list[str] = []
    for chunk in resent:
        replies += receiver.on_message(chunk, 0.21)
    assert receiver.done and messages(replies)[0]["type"] == "done"


def test_resend_wait_grows_with_the_round_trip_time() -> None:
    encoded = fake_map(10_000)
    sender = MapSender(lambda: encoded, chunk_size=1000)
    receiver = MapReceiver(5)
    (offer,) = sender.on_message(receiver.request(0.0), 0.0)
    assert isinstance(offer, str)
    receiver.on_message(offer, 0.4)  # a 0.4 s round trip
    assert receiver.rtt == pytest.approx(0.4)
    assert receiver.resend_wait == pytest.approx(0.8)
    assert receiver.poll(0.4 + RESEND_AFTER + 0.01) == []  # too early on this link
    assert len(receiver.poll(1.21)) == 1


def test_more_than_1000_missing_chunks_take_several_resend_messages() -> None:
    encoded = fake_map(2500)
    sender, receiver = receiving(encoded, chunk_size=1)
    sender.next_chunks(10_000)  # all lost
    replies = receiver.poll(5.0)
    assert [len(m["missing"]) for m in messages(replies)] == [1000, 1000, 500]
    assert all(len(r.encode()) <= MAX_DATAGRAM for r in replies)
    for reply in replies:
        assert sender.on_message(reply, 5.1) == []
    assert sender.rejected == 0 and len(sender.next_chunks(10_000)) == 2500


# --------------------------------------------------------------------------- one at a time


def test_one_transfer_at_a_time_per_call() -> None:
    encoded = fake_map(3000)
    sender = MapSender(lambda: encoded, chunk_size=1000)
    first = MapReceiver(1)
    second = MapReceiver(2)
    offer_for(sender, first)
    (refusal,) = messages(sender.on_message(second.request(0.1), 0.1))
    assert refusal == {"type": "error", "xfer": 2, "reason": ALREADY_RUNNING}
    assert sender.refused == 1 and sender.xfer == 1
    second.on_message(json.dumps(refusal), 0.2)
    assert second.failed and second.error == ALREADY_RUNNING
    assert second.poll(10.0) == [] and second.next_deadline() is None
    # the first one finishes, then a new one may start
    first.on_message(sender.on_message(get(1), 0.3)[0], 0.3)
    for reply in deliver_all(sender, first, 0.4):
        sender.on_message(reply, 0.4)
    assert first.done and not sender.active and sender.completed == 1
    third = MapReceiver(3)
    assert messages(sender.on_message(third.request(0.5), 0.5))[0]["type"] == "offer"


def test_a_stale_transfer_whose_done_was_lost_is_replaced_by_a_new_get() -> None:
    encoded = fake_map(3000)
    sender, receiver = receiving(encoded, chunk_size=1000)  # the get came at 0.0
    assert messages(sender.on_message(get(7), STALE_AFTER))[0]["type"] == "error"  # chunks due
    deliver_all(sender, receiver, 0.1)  # the receiver's three "done" are all lost
    assert receiver.done and sender.active
    assert messages(sender.on_message(get(7), STALE_AFTER - 0.01))[0]["type"] == "error"
    (offer,) = messages(sender.on_message(get(7), STALE_AFTER))
    assert offer["type"] == "offer" and sender.xfer == 7 and sender.expired == 1
    assert sender.refused == 2


def test_a_late_repeated_get_does_not_restart_a_finished_transfer() -> None:
    encoded = fake_map(3000)
    sender = MapSender(lambda: encoded, chunk_size=1000)
    receiver = MapReceiver(11)
    receiver.on_message(json.dumps(offer_for(sender, receiver)), 0.0)
    for reply in deliver_all(sender, receiver, 0.1):
        sender.on_message(reply, 0.1)
    assert receiver.done and not sender.active
    assert sender.on_message(get(11), 0.5) == []
    assert not sender.active and sender.ignored >= 1


def test_the_robot_forgets_an_idle_transfer_and_says_so_when_asked_to_resend() -> None:
    encoded = fake_map(3000)
    sender, receiver = receiving(encoded, chunk_size=1000)
    assert sender.next_deadline() == IDLE_TIMEOUT
    sender.poll(IDLE_TIMEOUT - 0.01)
    assert sender.active
    sender.poll(IDLE_TIMEOUT)
    assert not sender.active and sender.expired == 1 and not sender.has_pending
    # The user comes back after all: it is told, rather than left to time out.
    resend = json.dumps({"type": "resend", "xfer": 42, "missing": [0]})
    (error,) = messages(sender.on_message(resend, 31.0))
    assert error["type"] == "error" and "expired" in error["reason"]
    receiver.on_message(json.dumps(error), 31.1)
    assert receiver.failed and receiver.error is not None and "expired" in receiver.error


def test_cancel_frees_the_robot_at_once() -> None:
    encoded = fake_map(3000)
    sender, receiver = receiving(encoded, chunk_size=1000)
    cancels = receiver.cancel()
    assert messages(cancels) == [{"type": "cancel", "xfer": 42}] * REPEATS
    assert receiver.failed and receiver.error == "cancelled"
    for message in cancels:
        sender.on_message(message, 1.0)
    assert not sender.active and sender.ignored == REPEATS - 1 and sender.rejected == 0
    assert receiver.cancel() == []


def test_hash_mismatch_fails_with_a_clear_error_and_cancels() -> None:
    good = fake_map(3000)
    bad = EncodedMap(good.png, "0" * 64, 7, 5, 0.05, 0.0, 0.0)
    sender, receiver = receiving(bad, chunk_size=1000)
    replies = deliver_all(sender, receiver, 0.1)
    assert receiver.failed and receiver.result is None
    assert receiver.error is not None and "hash mismatch" in receiver.error
    assert messages(replies) == [{"type": "cancel", "xfer": 42}] * REPEATS
    sender.on_message(replies[0], 0.2)
    assert not sender.active


def test_a_failing_provider_is_a_refusal_with_its_reason_and_is_asked_again() -> None:
    calls = 0
    encoded = fake_map(10)

    def provider() -> EncodedMap:
        nonlocal calls
        calls += 1
        if calls == 1:
            raise MapError("map 'x' has no known cells")
        return encoded

    sender = MapSender(provider)
    (error,) = messages(sender.on_message(get(1), 0.0))
    assert error["type"] == "error" and "no known cells" in error["reason"]
    assert isinstance(sender.provider_error, MapError) and not sender.active
    assert messages(sender.on_message(get(2), 0.1))[0]["type"] == "offer"
    sender.on_message(json.dumps({"type": "done", "xfer": 2}), 0.2)
    sender.on_message(get(3), 0.3)
    assert calls == 3  # asked at every new transfer: a map that changed is sent as it is now


def test_the_robot_refusal_reaches_the_receiver() -> None:
    receiver = MapReceiver(8)
    receiver.request(0.0)
    receiver.on_message(json.dumps({"type": "error", "xfer": 8, "reason": "busy"}), 0.1)
    assert receiver.failed and receiver.error == "busy"


# --------------------------------------------------------------------------- garbage

SENDER_GARBAGE: list[str | bytes] = [
    b"\x01\x00\x00\x00\x01",
    b"",
    "",
    "not json",
    "[1, 2]",
    '{"type": "get"}',
    '{"type": "get", "xfer": -1}',
    '{"type": "get", "xfer": 4294967296}',
    '{"type": "get", "xfer": true}',
    '{"type": "get", "xfer": 1.5}',
    '{"type": "get", "xfer": NaN}',
    '{"type": "fetch", "xfer": 1}',
    '{"xfer": 1}',
    "x" * 40_000,
    '{"type": "resend", "xfer": 42, "missing": "all"}',
    '{"type": "resend", "xfer": 42, "missing": []}',
    '{"type": "resend", "xfer": 42, "missing": [3]}',  # out of range (3 chunks)
    '{"type": "resend", "xfer": 42, "missing": [-1]}',
    '{"type": "resend", "xfer": 42, "missing": [true]}',
    '{"type": "resend", "xfer": 42, "missing": [1.0]}',
    json.dumps({"type": "resend", "xfer": 42, "missing": [0] * (MAX_RESEND_INDICES + 1)}),
    '{"type": "done", "xfer": 43}',
]


def test_garbage_to_the_robot_is_counted_and_changes_nothing() -> None:
    encoded = fake_map(3000)
    sender, _ = receiving(encoded, chunk_size=1000)
    for payload in SENDER_GARBAGE:
        assert sender.on_message(payload, 1.0) == []
    assert sender.rejected == len(SENDER_GARBAGE)
    assert sender.xfer == 42 and sender.chunks_sent == 0
    assert len(sender.next_chunks(100)) == 3  # the first pass only, nothing queued twice
    assert sender.next_deadline() == IDLE_TIMEOUT  # garbage does not keep a transfer alive


def test_garbage_to_an_idle_robot_starts_nothing() -> None:
    sender = MapSender(lambda: fake_map(10))
    for payload in SENDER_GARBAGE:
        sender.on_message(payload, 0.0)
    assert not sender.active and not sender.has_pending and sender.rejected > 0


def chunk(xfer: int, index: int, data: bytes, kind: int = 1) -> bytes:
    return CHUNK_HEADER.pack(kind, xfer, index) + data


RECEIVER_GARBAGE: list[str | bytes] = [
    b"",
    b"\x01\x00\x00",
    chunk(42, 0, b"x" * 1000, kind=2),
    chunk(41, 0, b"x" * 1000),  # another transfer
    chunk(42, 3, b"x" * 1000),  # out of range
    chunk(42, 2**32 - 1, b"x"),
    chunk(42, 0, b"x" * 999),  # wrong length
    chunk(42, 2, b"x" * 1000),  # the last chunk is 500 bytes
    "nonsense",
    "{}",
    '{"type": "offer", "xfer": 41}',
    '{"type": "surprise", "xfer": 42}',
    '{"type": "offer", "xfer": 42, "size": 1}',  # a broken offer
]


def test_garbage_to_the_user_is_counted_and_changes_nothing() -> None:
    encoded = fake_map(2500)
    sender, receiver = receiving(encoded, chunk_size=1000)
    for payload in RECEIVER_GARBAGE:
        assert receiver.on_message(payload, 0.05) == []
    assert receiver.rejected == len(RECEIVER_GARBAGE)
    assert receiver.progress == (0, 2500) and receiver.state == "receiving"
    deliver_all(sender, receiver, 0.1)
    assert receiver.done and receiver.result is not None and receiver.result.png == encoded.png


def valid_offer(**changes: Any) -> dict[str, Any]:
    offer: dict[str, Any] = {
        "type": "offer",
        "xfer": 5,
        "name": "map",
        "size": 5000,
        "chunks": 5,
        "chunk_size": 1000,
        "sha256": "ab" * 32,
        "width": 10,
        "height": 10,
        "resolution": 0.05,
        "origin": [0.0, 0.0],
    }
    offer.update(changes)
    return offer


@pytest.mark.parametrize(
    "changes",
    [
        {
            "size": MAX_MAP_BYTES + 1,
            "chunks": -(-(MAX_MAP_BYTES + 1) // MAX_CHUNK_DATA),
            "chunk_size": MAX_CHUNK_DATA,
        },
        {"size": 0, "chunks": 0},
        {"chunks": 4},
        {"chunks": 6},
        {"chunk_size": 0},
        {"chunk_size": MAX_CHUNK_DATA + 1, "chunks": 1},
        {"size": 10**6, "chunk_size": 1, "chunks": 10**6},  # far too many chunks
        {"sha256": "AB" * 32},
        {"sha256": "ab" * 31},
        {"width": 0},
        {"width": 100_000, "height": 100_000},
        {"resolution": 0},
        {"resolution": -0.05},
        {"resolution": "0.05"},
        {"origin": [0.0, 0.0, 0.0]},
        {"origin": [0.0, "x"]},
        {"origin": None},
        {"name": ""},
        {"name": "n" * 1000},
        {"name": 5},
        {"size": True},
    ],
)
def test_absurd_offers_are_dropped_and_counted(changes: dict[str, Any]) -> None:
    receiver = MapReceiver(5)
    receiver.request(0.0)
    assert receiver.on_message(json.dumps(valid_offer(**changes)), 0.1) == []
    assert receiver.rejections["bad_offer"] == 1
    assert receiver.state == "requesting" and receiver.offer is None
    # and the genuine offer is still taken afterwards
    receiver.on_message(json.dumps(valid_offer()), 0.2)
    assert receiver.offer is not None and receiver.progress == (0, 5000)


def test_a_different_second_offer_and_an_unrequested_offer_are_refused() -> None:
    receiver = MapReceiver(5)
    assert receiver.on_message(json.dumps(valid_offer()), 0.0) == []
    assert receiver.rejections["unrequested"] == 1 and receiver.offer is None
    receiver.request(0.0)
    receiver.on_message(json.dumps(valid_offer()), 0.1)
    receiver.on_message(json.dumps(valid_offer(sha256="cd" * 32)), 0.2)
    assert receiver.rejections["conflicting_offer"] == 1
    assert receiver.offer is not None and receiver.offer.sha256 == "ab" * 32


def test_early_chunks_are_bounded_in_memory() -> None:
    receiver = MapReceiver(5)
    receiver.request(0.0)
    junk = os.urandom(MAX_CHUNK_DATA)
    for index in range(300):  # 300 × 32 KB > the 8 MiB early buffer
        receiver.on_message(chunk(5, index, junk), 0.0)
    assert receiver.rejections["early_overflow"] > 0
    assert receiver.rejections["early_overflow"] + 256 >= 300
    # the offer then rejects whatever does not fit it
    receiver.on_message(json.dumps(valid_offer()), 0.1)
    assert receiver.progress == (0, 5000)
    assert receiver.rejections["bad_length"] + receiver.rejections["index_out_of_range"] > 0
