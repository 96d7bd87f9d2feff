"""Map transfer, sans-IO: the map as a cropped PNG, and the chunked transfer on channel "map".

Encoding. :func:`encode_map` crops the occupancy grid to its known cells (on a SLAM map most
of the grid is unknown: the default 4000 × 4000 map is 13 % known) and writes the crop as an
8-bit grey PNG with the pixel values of ROS ``map_saver``'s trinary maps (free 254, occupied
0, unknown 205), by the rules of :mod:`telebot.robot.mapfile`, the one home of the
map_server image and YAML conventions (:func:`~telebot.robot.mapfile.grid_to_image`).

The top image row is the grid row farthest from the origin (as in every map_server image);
the georeference travels beside the image: the resolution and the crop's origin (the world
position of the lower-left corner of the image's bottom-left pixel). :func:`decode_map` is
the exact inverse for trinary grids (-1/0/100), and :func:`telebot.robot.mapfile.map_yaml`
writes the YAML that makes any ROS tool load the PNG to the same grid.

Transfer (one JSON text datagram per control message, one binary datagram per chunk)::

    user  -> robot  {"type":"get","xfer":N}                       (re-sent until an offer comes)
    robot -> user   {"type":"offer","xfer":N,"name":…,"size":S,"chunks":K,"chunk_size":C,
                     "sha256":hex,"width":W,"height":H,"resolution":r,"origin":[x,y],
                     "version":V}
                 or {"type":"error","xfer":N,"reason":"a map transfer is already running"}
    robot -> user   chunk i: 0x01 | xfer u32 BE | i u32 BE | png[i·C : (i+1)·C]   (K of them)
    user  -> robot  {"type":"resend","xfer":N,"missing":[i,…]}      (≤ 1000 indices each)
    user  -> robot  {"type":"done","xfer":N}  or  {"type":"cancel","xfer":N}   (sent 3 times)

:class:`MapSender` is the robot's side (one per call, one transfer at a time) and
:class:`MapReceiver` the user's; both take payloads and ``now`` and return what to send.
Nothing here reads a clock or does I/O: ``services/mapxfer.py`` drives them over a channel.

A map may change (SLAM): each transfer sends the map as it is when the ``get`` arrives (its
``version`` is the robot's :meth:`~telebot.robot.nav.NavStack.map_version`, also in every
telemetry message), and a transfer that runs while the map changes finishes with the
snapshot it offered; the user fetches again to get the new one.
The wire format is specified in ``docs/protocol.md`` ("The map channel").
"""

from __future__ import annotations

import hashlib
import re
import struct
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final, Generic, Literal, TypeVar

import numpy as np

from telebot.channels.proto.frames import MAX_DATAGRAM
from telebot.errors import MapError, ProtocolError
from telebot.robot.grid import OccupancyGrid
from telebot.robot.mapfile import grid_to_image, image_to_grid
from telebot.services.messages import (
    decode_object,
    encode_object,
    finite_number,
    require_int,
)

__all__ = [
    "ALREADY_RUNNING",
    "CHUNK_HEADER",
    "CHUNK_KIND",
    "IDLE_TIMEOUT",
    "MAX_CHUNKS",
    "MAX_CHUNK_DATA",
    "MAX_MAP_BYTES",
    "MAX_MAP_CELLS",
    "MAX_MAP_VERSION",
    "MAX_RESEND_INDICES",
    "PNG_COMPRESSION",
    "REPEATS",
    "REQUEST_INTERVAL",
    "RESEND_AFTER",
    "STALE_AFTER",
    "EncodedMap",
    "MapReceiver",
    "MapSender",
    "Offer",
    "decode_map",
    "encode_map",
    "png_size",
]


# --------------------------------------------------------------------------- constants

#: First byte of a chunk datagram (other values are reserved and dropped).
CHUNK_KIND: Final = 0x01
#: Chunk header: kind u8, xfer u32, index u32, big-endian (9 bytes).
CHUNK_HEADER: Final = struct.Struct(">BII")
#: Most PNG bytes one chunk carries: a datagram's limit minus the header.
MAX_CHUNK_DATA: Final = MAX_DATAGRAM - CHUNK_HEADER.size
#: Largest map a receiver accepts (offer ``size``); bounds its memory.
MAX_MAP_BYTES: Final = 64 * 1024 * 1024
#: Most chunks in an offer (so a tiny ``chunk_size`` cannot blow up the receiver's tables).
MAX_CHUNKS: Final = 65536
#: Largest image (width × height cells) a receiver accepts: decoding it takes this many bytes.
MAX_MAP_CELLS: Final = 100_000_000
#: Most indices in one ``resend`` message (about 6 KB of JSON).
MAX_RESEND_INDICES: Final = 1000
#: Most ``resend`` messages one poll sends (the rest are asked for in the next round).
MAX_RESEND_MESSAGES: Final = 8
#: Seconds between ``get`` repeats while no offer has come.
REQUEST_INTERVAL: Final = 0.25
#: Least silence (seconds without a new chunk) before the receiver asks for missing chunks.
RESEND_AFTER: Final = 0.08
#: The silence the receiver waits for is never longer than this (seconds).
MAX_RESEND_WAIT: Final = 1.0
#: Seconds without a message about the running transfer after which the robot forgets it.
IDLE_TIMEOUT: Final = 30.0
#: A transfer with every chunk sent whose user has said nothing for this long is stale: a
#: ``get`` for another transfer replaces it instead of being refused. A live receiver that
#: misses a chunk asks within :data:`MAX_RESEND_WAIT`, so this silence means its ``done``
#: (or ``cancel``) was lost, and the user need not wait :data:`IDLE_TIMEOUT` to fetch again.
STALE_AFTER: Final = 3.0
#: ``done`` and ``cancel`` are not acknowledged, so they are sent this many times.
REPEATS: Final = 3
#: Chunks that arrive before their offer (reordering, or a lost offer) are kept up to this.
EARLY_BUFFER_BYTES: Final = 8 * 1024 * 1024
#: Finished transfer ids the robot remembers, so a late repeated ``get`` does not restart one.
RECENT_TRANSFERS: Final = 16
#: The robot's reason when a ``get`` comes while another transfer runs.
ALREADY_RUNNING: Final = "a map transfer is already running"
#: Largest map version on the wire: it travels in JSON, exact up to 2**53 − 1 in any language.
MAX_MAP_VERSION: Final = 2**53 - 1
#: Longest ``reason`` or ``name`` kept from a peer (characters).
MAX_TEXT: Final = 256

#: zlib level; with the RLE strategy below it changes nothing (RLE has one speed).
PNG_COMPRESSION: Final = 6


# Z_RLE: on the 4000² building map 10 ms and 5.6 KB against 18 ms and 4.8 KB for level 9
# of the default strategy, and, unlike that, its time does not grow with noise (a noisy
# SLAM map takes 10 ms, not 190 ms), so the ≤ 50 ms budget holds for any map.
def _png_params(cv2: Any) -> list[int]:
    return [
        cv2.IMWRITE_PNG_COMPRESSION,
        PNG_COMPRESSION,
        cv2.IMWRITE_PNG_STRATEGY,
        cv2.IMWRITE_PNG_STRATEGY_RLE,
    ]


_SHA256_HEX = re.compile(r"[0-9a-f]{64}")
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


# --------------------------------------------------------------------------- encoding


@dataclass(frozen=True, slots=True)
class EncodedMap:
    """A map as it travels: PNG bytes, their SHA-256 and the georeference of the image.

    ``origin_x``/``origin_y`` are the world coordinates (metres) of the lower-left corner of
    the image's bottom-left pixel; pixel ``(u, v)`` (column, row from the top) covers world
    ``x = origin_x + u·resolution`` … and ``y = origin_y + (height − 1 − v)·resolution`` ….
    """

    png: bytes
    sha256: str
    width: int
    height: int
    resolution: float
    origin_x: float
    origin_y: float
    name: str = "map"
    #: The robot's map version this image shows (``NavStack.map_version``; 0 if unknown).
    version: int = 0

    @property
    def size(self) -> int:
        """Length of the PNG in bytes."""
        return len(self.png)

    def world_of_pixel(self, u: float, v: float) -> tuple[float, float]:
        """World ``(x, y)`` of image point ``(u, v)`` (pixels, from the top-left corner).

        A click at the centre of pixel ``(col, row)`` is ``(col + 0.5, row + 0.5)``.
        """
        x = self.origin_x + u * self.resolution
        y = self.origin_y + (self.height - v) * self.resolution
        return x, y


def encode_map(grid: OccupancyGrid, name: str = "map", *, version: int = 0) -> EncodedMap:
    """``grid`` cropped to its known cells, as a trinary PNG with its georeference.

    ``version`` labels it with the robot's map version (see :class:`EncodedMap`).

    Raises :class:`~telebot.errors.MapError` when no cell is known (there is nothing to
    show), or when OpenCV cannot encode the image.
    """
    bounds = grid.known_bounds()
    if bounds is None:
        raise MapError(f"map {name!r} has no known cells")
    cropped = grid.crop(*bounds)
    import cv2  # here, not at the top: a user's client that never fetches a map never loads it

    ok, buffer = cv2.imencode(".png", grid_to_image(cropped), _png_params(cv2))
    if not ok:
        raise MapError(f"map {name!r}: OpenCV could not encode it as PNG")
    png = buffer.tobytes()
    return EncodedMap(
        png=png,
        sha256=hashlib.sha256(png).hexdigest(),
        width=cropped.width,
        height=cropped.height,
        resolution=cropped.resolution,
        origin_x=cropped.origin_x,
        origin_y=cropped.origin_y,
        name=name,
        version=version,
    )


def png_size(png: bytes) -> tuple[int, int]:
    """``(width, height)`` from a PNG's header, without decoding it; ProtocolError if not PNG."""
    # The signature, then the IHDR chunk: length (13), "IHDR", width u32, height u32.
    if len(png) < 24 or png[:8] != _PNG_SIGNATURE or png[12:16] != b"IHDR":
        raise ProtocolError("map image: not a PNG")
    width, height = struct.unpack_from(">II", png, 16)
    return int(width), int(height)


def decode_map(png: bytes, resolution: float, origin_x: float, origin_y: float) -> OccupancyGrid:
    """The occupancy grid of a map PNG: the inverse of :func:`encode_map`.

    Pixels are read as map_server reads them with the YAML of
    :func:`~telebot.robot.mapfile.map_yaml` (:func:`~telebot.robot.mapfile.image_to_grid`:
    254 → 0, 0 → 100, 205 → -1, others by their shade). Raises ProtocolError
    for anything but an 8-bit grey PNG of at most :data:`MAX_MAP_CELLS` pixels, or an
    invalid georeference.
    """
    width, height = png_size(png)
    if width * height > MAX_MAP_CELLS:
        raise ProtocolError(f"map image of {width} × {height} pixels is too large")
    import cv2  # here, not at the top: see encode_map

    try:
        image = cv2.imdecode(np.frombuffer(png, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        image = None
    if image is None:
        raise ProtocolError("map image: OpenCV cannot decode this PNG")
    if image.dtype != np.uint8 or image.ndim != 2:
        raise ProtocolError(f"map image: expected 8-bit grey, got {image.dtype} {image.shape}")
    try:
        return image_to_grid(image, resolution, origin_x, origin_y)
    except ValueError as exc:
        raise ProtocolError(f"map georeference: {exc}") from exc


# --------------------------------------------------------------------------- messages


@dataclass(frozen=True, slots=True)
class Offer:
    """A validated ``offer``: what the robot is about to send."""

    xfer: int
    name: str
    size: int
    chunks: int
    chunk_size: int
    sha256: str
    width: int
    height: int
    resolution: float
    origin_x: float
    origin_y: float
    #: The robot's map version (``NavStack.map_version``); 0 when the robot does not say.
    version: int = 0

    def chunk_length(self, index: int) -> int:
        """Length of chunk ``index``'s data: ``chunk_size``, or what is left for the last."""
        if index == self.chunks - 1:
            return self.size - (self.chunks - 1) * self.chunk_size
        return self.chunk_size

    def to_message(self) -> str:
        """The ``offer`` datagram."""
        return encode_object(
            {
                "type": "offer",
                "xfer": self.xfer,
                "name": self.name,
                "size": self.size,
                "chunks": self.chunks,
                "chunk_size": self.chunk_size,
                "sha256": self.sha256,
                "width": self.width,
                "height": self.height,
                "resolution": self.resolution,
                "origin": [self.origin_x, self.origin_y],
                "version": self.version,
            }
        )

    @classmethod
    def parse(cls, message: dict[str, Any], *, max_bytes: int = MAX_MAP_BYTES) -> Offer:
        """Validate an ``offer`` object; ProtocolError names the first bad field."""
        what = "map offer"
        xfer = require_int(message, "xfer", what=what)
        name = message.get("name")
        if not isinstance(name, str) or not 0 < len(name) <= MAX_TEXT:
            raise ProtocolError(f"{what}: 'name' must be a string of 1..{MAX_TEXT} characters")
        size = require_int(message, "size", what=what, low=1, high=max_bytes)
        chunk_size = require_int(message, "chunk_size", what=what, low=1, high=MAX_CHUNK_DATA)
        chunks = require_int(message, "chunks", what=what, low=1, high=MAX_CHUNKS)
        if chunks != -(-size // chunk_size):
            raise ProtocolError(
                f"{what}: {chunks} chunks cannot hold {size} bytes in chunks of {chunk_size}"
            )
        digest = message.get("sha256")
        if not isinstance(digest, str) or not _SHA256_HEX.fullmatch(digest):
            raise ProtocolError(f"{what}: 'sha256' must be 64 lowercase hex digits")
        width = require_int(message, "width", what=what, low=1)
        height = require_int(message, "height", what=what, low=1)
        if width * height > MAX_MAP_CELLS:
            raise ProtocolError(f"{what}: a {width} × {height} map is too large")
        resolution = finite_number(message, "resolution", what=what)
        if resolution <= 0:
            raise ProtocolError(f"{what}: 'resolution' must be positive")
        origin = message.get("origin")
        if not isinstance(origin, list) or len(origin) != 2:
            raise ProtocolError(f"{what}: 'origin' must be [x, y]")
        origin_x = finite_number({"x": origin[0]}, "x", what=f"{what} origin")
        origin_y = finite_number({"y": origin[1]}, "y", what=f"{what} origin")
        # Optional: robots before map versions did not send it.
        version = (
            require_int(message, "version", what=what, high=MAX_MAP_VERSION)
            if "version" in message
            else 0
        )
        return cls(
            xfer=xfer,
            name=name,
            size=size,
            chunks=chunks,
            chunk_size=chunk_size,
            sha256=digest,
            width=width,
            height=height,
            resolution=resolution,
            origin_x=origin_x,
            origin_y=origin_y,
            version=version,
        )


def _message(kind: str, xfer: int, **fields: Any) -> str:
    return encode_object({"type": kind, "xfer": xfer, **fields})


def _read_message(payload: str, what: str) -> tuple[dict[str, Any], Any, int]:
    """A control message of :func:`_message`: ``(message, type, xfer)``; ProtocolError if not."""
    message = decode_object(payload, what=what)
    return message, message.get("type"), require_int(message, "xfer", what=what)


def _chunk(xfer: int, index: int, data: bytes) -> bytes:
    return CHUNK_HEADER.pack(CHUNK_KIND, xfer, index) + data


# --------------------------------------------------------------------------- both sides

_Reply = TypeVar("_Reply")


class _Side(Generic[_Reply]):
    """What both ends of a transfer do alike: count the datagrams they drop, by reason."""

    def __init__(self) -> None:
        #: Datagrams dropped, by reason (garbage, unknown transfer, bad fields, …).
        self.rejections: Counter[str] = Counter()

    @property
    def rejected(self) -> int:
        """How many datagrams were dropped as invalid."""
        return sum(self.rejections.values())

    def _reject(self, reason: str) -> list[_Reply]:
        """Count a dropped datagram; returns the replies to it (none)."""
        self.rejections[reason] += 1
        return []


# --------------------------------------------------------------------------- robot side


class MapSender(_Side[str | bytes]):
    """The robot's side of map transfers on one call: one transfer at a time.

    Feed every datagram of the "map" channel to :meth:`on_message` and send what it returns
    (offers and errors) at once; then send chunks, a few at a time, from
    :meth:`next_chunks` while :attr:`has_pending` (so a big map yields to the event loop
    rather than flood the queues); call :meth:`poll` at :meth:`next_deadline`.

    ``provider`` is asked for the map at every new transfer (so a map that changed is sent
    as it is now; the provider should cache by map version, as
    :meth:`~telebot.services.robot.RobotServer.encoded_map` does) and the transfer sends
    that snapshot to its end; if it raises, the ``get`` is refused with the error as the
    reason and the next ``get`` asks again.
    """

    def __init__(
        self,
        provider: Callable[[], EncodedMap],
        *,
        chunk_size: int = MAX_CHUNK_DATA,
        idle_timeout: float = IDLE_TIMEOUT,
        stale_after: float = STALE_AFTER,
    ) -> None:
        if not 1 <= chunk_size <= MAX_CHUNK_DATA:
            raise ValueError(f"chunk_size must be in 1..{MAX_CHUNK_DATA}, not {chunk_size}")
        if not (idle_timeout > 0 and stale_after > 0):
            raise ValueError("idle_timeout and stale_after must be positive")
        super().__init__()
        self._provider = provider
        self.chunk_size = chunk_size
        self.idle_timeout = idle_timeout
        self.stale_after = stale_after
        self._map: EncodedMap | None = None
        self._offer: Offer | None = None
        self._offer_text = ""
        self._last_heard = 0.0
        # Chunks to send, in order, and the same as a set so a resend never queues twice.
        self._queue: deque[int] = deque()
        self._queued: set[int] = set()
        self._sent_before = bytearray()
        self._recent: OrderedDict[int, None] = OrderedDict()
        #: Late repeats of ``done``/``cancel``/``get`` for a finished transfer (not garbage).
        self.ignored = 0
        #: ``get`` requests refused because another transfer was running.
        self.refused = 0
        #: Transfers the user confirmed with ``done``.
        self.completed = 0
        #: Transfers forgotten after :attr:`idle_timeout` without a word from the user, or
        #: replaced by a new ``get`` once stale (see :data:`STALE_AFTER`).
        self.expired = 0
        #: Chunks handed out by :meth:`next_chunks`, and of those, sent before already.
        self.chunks_sent = 0
        self.chunks_resent = 0
        #: The last exception of the provider (the reason of the last refusal it caused).
        self.provider_error: Exception | None = None

    @property
    def active(self) -> bool:
        """Whether a transfer is running."""
        return self._offer is not None

    @property
    def xfer(self) -> int | None:
        """The id of the running transfer, if any."""
        return None if self._offer is None else self._offer.xfer

    @property
    def has_pending(self) -> bool:
        """Whether chunks are waiting to be sent."""
        return bool(self._queue)

    def on_message(self, payload: str | bytes, now: float) -> list[str | bytes]:
        """Handle one datagram from the user; returns the replies to send now."""
        if isinstance(payload, bytes):
            return self._reject("binary")
        try:
            message, kind, xfer = _read_message(payload, "map request")
        except ProtocolError:
            return self._reject("malformed")
        match kind:
            case "get":
                return self._on_get(xfer, now)
            case "resend":
                return self._on_resend(xfer, message.get("missing"), now)
            case "done" | "cancel":
                return self._on_finish(xfer, completed=kind == "done")
            case _:
                return self._reject("unknown_type")

    def next_chunks(self, limit: int) -> list[bytes]:
        """Up to ``limit`` chunk datagrams to send now (first pass, then requested resends)."""
        offer, encoded = self._offer, self._map
        out: list[bytes] = []
        if offer is None or encoded is None:
            return out
        size = self.chunk_size
        while self._queue and len(out) < limit:
            index = self._queue.popleft()
            self._queued.discard(index)
            out.append(_chunk(offer.xfer, index, encoded.png[index * size : (index + 1) * size]))
            if self._sent_before[index]:
                self.chunks_resent += 1
            self._sent_before[index] = 1
        self.chunks_sent += len(out)
        return out

    def poll(self, now: float) -> None:
        """Forget a transfer the user has been silent about for :attr:`idle_timeout`."""
        if self._offer is not None and now - self._last_heard >= self.idle_timeout:
            self.expired += 1
            # Not remembered as finished: a user that comes back after all is told that
            # the transfer expired, or gets a new one for a repeated get.
            self._forget(remember=False)

    def next_deadline(self) -> float | None:
        """When :meth:`poll` has something to do next (None while no transfer runs)."""
        if self._offer is None:
            return None
        return self._last_heard + self.idle_timeout

    # -- handlers

    def _on_get(self, xfer: int, now: float) -> list[str | bytes]:
        if self._offer is not None:
            if xfer == self._offer.xfer:  # the offer was lost: the user asks again
                self._last_heard = now
                return [self._offer_text]
            if self._queue or now - self._last_heard < self.stale_after:
                self.refused += 1
                return [_message("error", xfer, reason=ALREADY_RUNNING)]
            self.expired += 1
            self._forget(remember=False)
        if xfer in self._recent:  # a repeated get that arrived after its transfer ended
            self.ignored += 1
            return []
        try:
            encoded = self._provider()
        except Exception as exc:  # the provider is the robot's code: answer, do not crash
            self.provider_error = exc
            return [_message("error", xfer, reason=f"the map is not available: {exc}"[:MAX_TEXT])]
        count = -(-encoded.size // self.chunk_size)
        if not 0 < encoded.size <= MAX_MAP_BYTES or count > MAX_CHUNKS:
            return [_message("error", xfer, reason=f"the map is too large ({encoded.size} bytes)")]
        self._offer = Offer(
            xfer=xfer,
            name=encoded.name[:MAX_TEXT] or "map",
            size=encoded.size,
            chunks=count,
            chunk_size=self.chunk_size,
            sha256=encoded.sha256,
            width=encoded.width,
            height=encoded.height,
            resolution=encoded.resolution,
            origin_x=encoded.origin_x,
            origin_y=encoded.origin_y,
            version=encoded.version,
        )
        self._map = encoded  # the snapshot this transfer's chunks come from
        self._offer_text = self._offer.to_message()
        self._last_heard = now
        self._queue = deque(range(count))
        self._queued = set(range(count))
        self._sent_before = bytearray(count)
        return [self._offer_text]

    def _on_resend(self, xfer: int, missing: Any, now: float) -> list[str | bytes]:
        offer = self._offer
        if offer is None or xfer != offer.xfer:
            if xfer in self._recent:
                self.ignored += 1
                return []
            # The user is waiting for a transfer this side does not have (it expired):
            # say so, rather than let it wait for its timeout.
            self.rejections["unknown_xfer"] += 1
            return [_message("error", xfer, reason="no such map transfer (it ended or expired)")]
        if (
            not isinstance(missing, list)
            or not 0 < len(missing) <= MAX_RESEND_INDICES
            or not all(
                type(i) is int and 0 <= i < offer.chunks  # bool is not an index
                for i in missing
            )
        ):
            return self._reject("bad_resend")
        self._last_heard = now
        for index in missing:
            if index not in self._queued:
                self._queued.add(index)
                self._queue.append(index)
        return []

    def _on_finish(self, xfer: int, *, completed: bool) -> list[str | bytes]:
        if self._offer is not None and xfer == self._offer.xfer:
            self.completed += completed
            self._forget()
        elif xfer in self._recent:
            self.ignored += 1  # the 2nd and 3rd copies of done/cancel
        else:
            self.rejections["unknown_xfer"] += 1
        return []

    def _forget(self, *, remember: bool = True) -> None:
        assert self._offer is not None
        if remember:
            self._recent[self._offer.xfer] = None
            while len(self._recent) > RECENT_TRANSFERS:
                self._recent.popitem(last=False)
        self._offer = None
        self._offer_text = ""
        self._queue.clear()
        self._queued.clear()
        self._sent_before = bytearray()


# --------------------------------------------------------------------------- user side

ReceiverState = Literal["new", "requesting", "receiving", "done", "failed"]


class MapReceiver(_Side[str]):
    """The user's side of one map transfer, ``xfer`` (a u32 the requester picks).

    Send :meth:`request`; feed every datagram of the "map" channel to :meth:`on_message`
    and send what it returns; call :meth:`poll` at :meth:`next_deadline` and send what it
    returns (repeated ``get`` while no offer came, ``resend`` for missing chunks). The
    transfer ends :attr:`done` (then :attr:`result` holds the verified map) or
    :attr:`failed` (then :attr:`error` says why). Time-outs are the driver's business.

    The ``get`` is repeated every ``request_interval`` until the offer comes; chunks that
    arrive first are kept (up to :data:`EARLY_BUFFER_BYTES`) and, since they mean the
    offer was lost or is late, bring the next ``get`` forward to ``resend_after`` after
    the last of them.

    The resend rule: when no new chunk has arrived for :attr:`resend_wait` seconds, ask
    for every missing chunk (≤ 1000 indices per message), and again after each further
    silence of that length, until complete. ``resend_wait`` is the largest of
    ``resend_after``, 3 × the mean interval between new chunks and 2 × the round-trip time
    (measured from ``get`` to offer and from ``resend`` to its first chunk), capped at
    :data:`MAX_RESEND_WAIT`; so a slow link does not get every chunk asked twice.
    """

    def __init__(
        self,
        xfer: int,
        *,
        resend_after: float = RESEND_AFTER,
        request_interval: float = REQUEST_INTERVAL,
        max_bytes: int = MAX_MAP_BYTES,
    ) -> None:
        if not 0 <= xfer < 2**32:
            raise ValueError(f"xfer must be a u32, not {xfer}")
        if not (resend_after > 0 and request_interval > 0):
            raise ValueError("resend_after and request_interval must be positive")
        if not 1 <= max_bytes <= MAX_MAP_BYTES:
            raise ValueError(f"max_bytes must be in 1..{MAX_MAP_BYTES}")
        super().__init__()
        self.xfer = xfer
        self.resend_after = resend_after
        self.request_interval = request_interval
        self.max_bytes = max_bytes
        self.state: ReceiverState = "new"
        self.offer: Offer | None = None
        #: The verified map, once :attr:`done`.
        self.result: EncodedMap | None = None
        #: Why the transfer failed (the robot's reason, or a hash mismatch), once :attr:`failed`.
        self.error: str | None = None
        #: Chunk indices asked for again, in total (one chunk asked twice counts twice).
        self.resent = 0
        #: ``get`` messages sent, the first one included.
        self.requests = 0
        #: Chunks that arrived again (a resend crossed the first copy): harmless.
        self.duplicates = 0
        self._chunks: list[bytes | None] = []
        self._missing = 0
        self._received = 0
        self._early: dict[int, bytes] = {}
        self._early_bytes = 0
        self._early_at: float | None = None
        self._last_request = 0.0
        self._quiet_since = 0.0
        self._last_chunk_at: float | None = None
        self._resend_sent_at: float | None = None
        self._interval: float | None = None
        self._rtt: float | None = None

    # -- state

    @property
    def done(self) -> bool:
        """Whether the map arrived whole and its hash checked out."""
        return self.state == "done"

    @property
    def failed(self) -> bool:
        """Whether the transfer failed (see :attr:`error`)."""
        return self.state == "failed"

    @property
    def progress(self) -> tuple[int, int]:
        """``(bytes received, bytes in the map)``; ``(0, 0)`` until the offer arrives."""
        if self.offer is None:
            return 0, 0
        if self.state == "done":
            return self.offer.size, self.offer.size
        return self._received, self.offer.size

    @property
    def rtt(self) -> float | None:
        """The smoothed round-trip time seen by this transfer, if measured yet."""
        return self._rtt

    @property
    def resend_wait(self) -> float:
        """Seconds without a new chunk after which missing chunks are asked for."""
        wait = self.resend_after
        if self._interval is not None:
            wait = max(wait, 3.0 * self._interval)
        if self._rtt is not None:
            wait = max(wait, 2.0 * self._rtt)
        return min(max(self.resend_after, MAX_RESEND_WAIT), wait)

    # -- outgoing

    def request(self, now: float) -> str:
        """The ``get`` message that starts the transfer (send it now)."""
        if self.state == "new":
            self.state = "requesting"
        self._last_request = now
        self.requests += 1
        return _message("get", self.xfer)

    def cancel(self) -> list[str]:
        """Give up: the ``cancel`` messages that let the robot forget the transfer at once."""
        if self.state not in ("requesting", "receiving"):
            return []
        self._fail("cancelled")
        return [_message("cancel", self.xfer)] * REPEATS

    def poll(self, now: float) -> list[str]:
        """Messages due at ``now``: a repeated ``get``, or ``resend`` for missing chunks."""
        if self.state == "requesting" and now >= self._request_due():
            return [self.request(now)]
        if self.state == "receiving" and now >= self._quiet_since + self.resend_wait:
            missing = [i for i, chunk in enumerate(self._chunks) if chunk is None]
            missing = missing[: MAX_RESEND_INDICES * MAX_RESEND_MESSAGES]
            self.resent += len(missing)
            self._quiet_since = self._resend_sent_at = now
            return [
                _message("resend", self.xfer, missing=missing[i : i + MAX_RESEND_INDICES])
                for i in range(0, len(missing), MAX_RESEND_INDICES)
            ]
        return []

    def next_deadline(self) -> float | None:
        """When :meth:`poll` has something to do next (None once the transfer ended)."""
        if self.state == "requesting":
            return self._request_due()
        if self.state == "receiving":
            return self._quiet_since + self.resend_wait
        return None

    def _request_due(self) -> float:
        due = self._last_request + self.request_interval
        if self._early_at is not None:
            # Chunks but no offer: the robot answered and its offer was lost (or is late).
            # Ask again after a short silence instead of the full request interval.
            due = min(due, max(self._last_request, self._early_at) + self.resend_after)
        return due

    # -- incoming

    def on_message(self, payload: str | bytes, now: float) -> list[str]:
        """Handle one datagram from the robot; returns the replies to send now."""
        if self.state in ("done", "failed"):
            self.duplicates += isinstance(payload, bytes)  # late copies of resent chunks
            return []
        if isinstance(payload, bytes):
            return self._on_chunk(payload, now)
        try:
            message, kind, xfer = _read_message(payload, "map reply")
        except ProtocolError:
            return self._reject("malformed")
        if xfer != self.xfer:
            return self._reject("unknown_xfer")
        match kind:
            case "offer":
                return self._on_offer(message, now)
            case "error":
                return self._on_error(message)
            case _:
                return self._reject("unknown_type")

    def _on_error(self, message: dict[str, Any]) -> list[str]:
        if self.state == "new":
            return self._reject("unrequested")
        reason = message.get("reason")
        if not isinstance(reason, str) or not reason:
            reason = "the robot refused the map transfer without a reason"
        self._fail(reason[:MAX_TEXT])
        return []

    def _on_offer(self, message: dict[str, Any], now: float) -> list[str]:
        try:
            offer = Offer.parse(message, max_bytes=self.max_bytes)
        except ProtocolError:
            return self._reject("bad_offer")
        if self.offer is not None:
            if offer != self.offer:  # the robot changed its mind mid-transfer: not trusted
                return self._reject("conflicting_offer")
            return []  # the answer to a repeated get
        if self.state != "requesting":
            return self._reject("unrequested")
        self.offer = offer
        self.state = "receiving"
        self._chunks = [None] * offer.chunks
        self._missing = offer.chunks
        self._rtt = now - self._last_request
        self._quiet_since = now
        early, self._early, self._early_bytes = self._early, {}, 0
        for index, data in sorted(early.items()):
            self._store(index, data)
        return self._finish() if self._missing == 0 else []

    def _on_chunk(self, payload: bytes, now: float) -> list[str]:
        if len(payload) < CHUNK_HEADER.size:
            return self._reject("short_chunk")
        kind, xfer, index = CHUNK_HEADER.unpack_from(payload)
        if kind != CHUNK_KIND:
            return self._reject("unknown_kind")
        if xfer != self.xfer:
            return self._reject("unknown_xfer")
        data = payload[CHUNK_HEADER.size :]
        if self.offer is None:
            return self._keep_early(index, data, now)
        if not self._store(index, data):
            return []
        if self._resend_sent_at is not None:  # the first answer to a resend: a round trip
            sample = now - self._resend_sent_at
            self._rtt = sample if self._rtt is None else 0.75 * self._rtt + 0.25 * sample
            self._resend_sent_at = None
        elif self._last_chunk_at is not None:
            gap = now - self._last_chunk_at
            self._interval = gap if self._interval is None else 0.75 * self._interval + 0.25 * gap
        self._last_chunk_at = self._quiet_since = now
        return self._finish() if self._missing == 0 else []

    def _keep_early(self, index: int, data: bytes, now: float) -> list[str]:
        if self.state != "requesting":
            return self._reject("unrequested")
        if index in self._early:
            self.duplicates += 1
            return []
        if (
            index >= MAX_CHUNKS
            or len(data) > MAX_CHUNK_DATA
            or self._early_bytes + len(data) > EARLY_BUFFER_BYTES
        ):
            return self._reject("early_overflow")
        self._early[index] = data
        self._early_bytes += len(data)
        self._early_at = now
        return []

    def _store(self, index: int, data: bytes) -> bool:
        offer = self.offer
        assert offer is not None
        if index >= offer.chunks:
            self._reject("index_out_of_range")
            return False
        if len(data) != offer.chunk_length(index):
            self._reject("bad_length")
            return False
        if self._chunks[index] is not None:
            self.duplicates += 1
            return False
        self._chunks[index] = data
        self._missing -= 1
        self._received += len(data)
        return True

    def _finish(self) -> list[str]:
        offer = self.offer
        assert offer is not None
        png = b"".join(chunk for chunk in self._chunks if chunk is not None)
        self._chunks = []
        digest = hashlib.sha256(png).hexdigest()
        if digest != offer.sha256:
            # Datagrams are never corrupted, so this is the robot's bug: stop, say it clearly.
            self._fail(f"map hash mismatch: received {digest}, the offer said {offer.sha256}")
            return [_message("cancel", self.xfer)] * REPEATS
        self.result = EncodedMap(
            png=png,
            sha256=digest,
            width=offer.width,
            height=offer.height,
            resolution=offer.resolution,
            origin_x=offer.origin_x,
            origin_y=offer.origin_y,
            name=offer.name,
            version=offer.version,
        )
        self.state = "done"
        return [_message("done", self.xfer)] * REPEATS

    def _fail(self, error: str) -> None:
        self.state = "failed"
        self.error = error
        self._chunks = []
        self._early.clear()
        self._early_bytes = 0
