"""Video frames for other programs on this computer: a named shared-memory ring.

The user client publishes each decoded frame with :class:`FrameRingWriter`; any number of
local processes (a video logger, an analysis script) read the newest one with
:class:`FrameRingReader`, without another network hop::

    with FrameRingWriter("guiabot-video", 640, 480) as ring:      # the user client
        ring.write(frame.image, frame_id=frame.frame_id, capture_time=..., camera="navcam")

    with FrameRingReader("guiabot-video") as ring:                 # another process
        for frame in ring.frames(timeout=5.0):
            cv2.imshow("robot", frame.image)

Design: one writer, lock-free readers (seqlock). The segment holds a header and ``slots``
slots; frame ``n`` goes to slot ``n % slots``. Each slot starts with a sequence counter
that the writer makes odd before it touches the slot and even again after; a reader copies
the slot and accepts the copy only if the counter was even and unchanged across the copy,
otherwise the copy was torn by the writer and it retries with the newest frame. The
writer never waits for anyone: a slow reader only retries, a reader that crashes (even in
the middle of a copy) leaves nothing to clean up, and readers attach and detach at any
time. The writer unlinks the segment on :meth:`~FrameRingWriter.close` (also at
interpreter exit and on ``with``); readers then see :attr:`FrameRingReader.writer_closed`.
A writer sets a ring up in steps (name, size, header, magic last); a reader that looks in
between gets :class:`RingNotReady`, a FileNotFoundError, exactly as if there were no ring
yet, so a loop that waits for the ring waits through it.

Layout (little-endian, every field naturally aligned)::

    header, 64 bytes:
      0  8s  magic b"TBVRING1"      24 u64 slot_bytes (capacity of one slot's picture)
      8  u32 version = 1            32 u64 frames written (the newest is frames − 1)
      12 u32 slots                  40 u32 writer pid
      16 u32 max_width              44 u32 closed (1 once the writer closed)
      20 u32 max_height
    slot headers, 64 bytes each, at 64 + 64·i:
      0  u64 seq (odd while written)   32 u32 height   36 u32 width
      8  u64 frame number (n)          40 u32 camera length, then 20 bytes of camera name
      16 u64 frame_id   24 f64 capture_time (Unix seconds; 0 when unknown)
    slot pictures: slot_bytes each (BGR uint8, height × width × 3), 64-byte aligned

The copy is checked on x86-64 and arm64 alike by re-reading the counter after the copy;
the writer's stores of the counter are single aligned 8-byte stores through numpy.

Python 3.11's ``resource_tracker`` treats every process that opens a segment as its
owner and unlinks it when that process exits (and warns of a "leak"): readers therefore
open the segment untracked (``track=False`` from Python 3.13, an untracked open before).
"""

from __future__ import annotations

import contextlib
import os
import re
import struct
import sys
import threading
import time
import weakref
from collections.abc import Iterator
from dataclasses import dataclass
from multiprocessing import resource_tracker, shared_memory
from types import TracebackType
from typing import Final, Self

import cv2
import numpy as np
import numpy.typing as npt

__all__ = [
    "FrameRingReader",
    "FrameRingWriter",
    "RingFrame",
    "RingNotReady",
    "validate_ring_name",
]

MAGIC: Final = b"TBVRING1"
VERSION: Final = 1
HEADER: Final = struct.Struct("<8sIIIIQQII")
SLOT_HEADER: Final = struct.Struct("<QQQdIII20s")
#: The slot header after its sequence counter (the counter is written on its own).
_SLOT_META: Final = struct.Struct("<QQdIII20s")
_HEADER_SIZE: Final = 64
_SLOT_HEADER_SIZE: Final = 64
_ALIGN: Final = 64
_FRAMES_AT: Final = 32  # offset of the "frames written" counter in the header
_CLOSED_AT: Final = 44
_CAMERA_BYTES: Final = 20
#: Default number of slots: a reader may lag up to ``slots − 1`` frames without retrying.
DEFAULT_SLOTS: Final = 4
#: How often a waiting reader looks for a new frame (seconds).
POLL_INTERVAL: Final = 0.002
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,29}")

assert HEADER.size <= _HEADER_SIZE and SLOT_HEADER.size <= _SLOT_HEADER_SIZE


def validate_ring_name(name: str) -> str:
    """``name`` if it is a portable shared-memory name (1–30 of ``A-Za-z0-9._-``)."""
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise ValueError(
            f"shared-memory name {name!r}: use 1 to 30 letters, digits, '.', '_' or '-'"
        )
    return name


def _align(n: int) -> int:
    return -(-n // _ALIGN) * _ALIGN


def _layout(slots: int, slot_bytes: int) -> tuple[int, int]:
    """(offset of the first picture, total segment size)."""
    data_at = _align(_HEADER_SIZE + slots * _SLOT_HEADER_SIZE)
    return data_at, data_at + slots * _align(slot_bytes)


_untracked_lock = threading.Lock()


class RingNotReady(FileNotFoundError):
    """The segment exists but its writer has not finished setting it up: try again soon.

    A FileNotFoundError, so code that waits for a ring to appear waits through this too.
    """


def _open_untracked(name: str) -> shared_memory.SharedMemory:
    """Attach to an existing segment without making this process its owner.

    Raises :class:`RingNotReady` for a segment that is still empty: its creator has
    named it but not yet sized it (``shm_open`` and ``ftruncate`` are two steps).
    """
    try:
        return _attach_untracked(name)
    except ValueError:  # mmap refuses an empty file; SharedMemory raises nothing else here
        pass
    # Raised out here: an error raised in the handler would keep the half-made
    # SharedMemory (and its open descriptor) alive through its context's traceback.
    raise RingNotReady(f"shared memory {name!r} is still being created")


def _attach_untracked(name: str) -> shared_memory.SharedMemory:
    if sys.version_info >= (3, 13):
        return shared_memory.SharedMemory(name, track=False)  # type: ignore[call-arg,unused-ignore]
    # Before 3.13 SharedMemory always registers the segment with the resource tracker,
    # which unlinks it when this process exits. Unregistering afterwards is no cure: a
    # tracker shared with the writer (multiprocessing children share one) would then
    # forget the writer's own registration. So the registration is skipped instead.
    with _untracked_lock:
        original = resource_tracker.register

        def register(rname: str, rtype: str) -> None:
            if rtype != "shared_memory":
                original(rname, rtype)

        resource_tracker.register = register  # type: ignore[assignment]
        try:
            return shared_memory.SharedMemory(name)
        finally:
            resource_tracker.register = original


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # someone else's live process
    return True


@dataclass(frozen=True, slots=True, eq=False)
class RingFrame:
    """A frame read from the ring (the image is the reader's own copy)."""

    #: BGR uint8, shape (height, width, 3).
    image: npt.NDArray[np.uint8]
    frame_id: int
    #: Capture time (Unix seconds) as the writer gave it; 0.0 when unknown.
    capture_time: float
    camera: str
    #: The ring's own frame number (0, 1, 2, … in the order written: gaps are frames
    #: this reader skipped).
    number: int


class _Ring:
    """What writer and reader share: the mapping and numpy views of its counters."""

    def __init__(self, shm: shared_memory.SharedMemory) -> None:
        self.shm = shm
        buf = shm.buf
        assert buf is not None
        (magic, version, slots, width, height, slot_bytes, _, _, _) = HEADER.unpack_from(buf)
        # The writer stores the magic last. (A zero slot count with the magic: a CPU that
        # reorders stores, such as arm64, showed the magic first. Also not ready.)
        if magic == bytes(len(MAGIC)) or (magic == MAGIC and slots == 0):
            raise RingNotReady(f"shared memory {shm.name!r} is not a frame ring yet")
        if magic != MAGIC or version != VERSION:
            raise ValueError(f"shared memory {shm.name!r} is not a telebot frame ring")
        data_at, size = _layout(slots, slot_bytes)
        # len(buf), not shm.size: SharedMemory reads the size before mmap does, and a
        # segment sized in between is mapped whole but reported as 0 bytes.
        if not 0 < slots <= 1024 or len(buf) < size or slot_bytes < width * height * 3:
            raise ValueError(f"shared memory {shm.name!r}: inconsistent frame ring header")
        self.slots = int(slots)
        self.max_width = int(width)
        self.max_height = int(height)
        self.slot_bytes = int(slot_bytes)
        self.data_at = data_at
        self.counters: npt.NDArray[np.uint64] = np.ndarray(
            (1,), dtype=np.uint64, buffer=buf, offset=_FRAMES_AT
        )
        self.seqs: list[npt.NDArray[np.uint64]] = [
            np.ndarray((1,), dtype=np.uint64, buffer=buf, offset=self._slot_at(i))
            for i in range(slots)
        ]
        self.pictures: list[npt.NDArray[np.uint8]] = [
            np.ndarray((slot_bytes,), dtype=np.uint8, buffer=buf, offset=self._picture_at(i))
            for i in range(slots)
        ]

    def _slot_at(self, index: int) -> int:
        return _HEADER_SIZE + index * _SLOT_HEADER_SIZE

    def _picture_at(self, index: int) -> int:
        return self.data_at + index * _align(self.slot_bytes)

    @property
    def frames_written(self) -> int:
        return int(self.counters[0])

    def release(self, *, unmap: bool = True) -> None:
        # numpy views pin the mapping: drop them before closing it.
        self.counters = np.zeros(1, dtype=np.uint64)
        self.seqs = []
        self.pictures = []
        if unmap:
            with contextlib.suppress(BufferError):
                self.shm.close()


class FrameRingWriter:
    """Publishes frames into the named ring (one writer per name).

    ``width`` × ``height`` is the largest picture a slot holds; a larger frame is shrunk
    to fit (keeping its aspect ratio), a smaller one is stored as it is. If a segment of
    that name exists from a writer that died, it is replaced; if its writer lives or is
    still setting it up, FileExistsError.
    """

    def __init__(self, name: str, width: int, height: int, *, slots: int = DEFAULT_SLOTS) -> None:
        validate_ring_name(name)
        if not (1 <= width <= 8192 and 1 <= height <= 8192):
            raise ValueError("ring width and height must be 1..8192")
        if not 2 <= slots <= 1024:
            raise ValueError("a ring needs 2..1024 slots")
        slot_bytes = width * height * 3
        _, size = _layout(slots, slot_bytes)
        self.name = name
        self._shm = self._create(name, size)  # a new segment is all zeros
        buf = self._shm.buf
        assert buf is not None
        HEADER.pack_into(
            buf, 0, bytes(len(MAGIC)), VERSION, slots, width, height, slot_bytes, 0, os.getpid(), 0
        )
        buf[: len(MAGIC)] = MAGIC  # last: a reader that sees the magic sees the whole header
        self._ring = _Ring(self._shm)
        self._closed = False
        # Unlinked at the latest when the writer is collected or the interpreter exits.
        self._finalizer = weakref.finalize(self, _retire, self._shm)

    @staticmethod
    def _create(name: str, size: int) -> shared_memory.SharedMemory:
        try:
            return shared_memory.SharedMemory(name, create=True, size=size)
        except FileExistsError:
            pass
        # A segment of that name exists: reclaim it only if its writer is gone.
        busy = False
        try:
            old = _open_untracked(name)
        except RingNotReady:
            old, busy = None, True
        except FileNotFoundError:
            old = None  # its writer closed it meanwhile: the name is free again
        if old is not None:
            try:
                buf = old.buf
                assert buf is not None
                if len(buf) < HEADER.size:
                    raise FileExistsError(f"shared memory {name!r} exists and is not a frame ring")
                magic, *_, pid, closed = HEADER.unpack_from(buf)
                unfinished = magic == bytes(len(MAGIC))  # a writer has not stored it yet
                if magic != MAGIC and not unfinished:
                    raise FileExistsError(f"shared memory {name!r} exists and is not a frame ring")
                busy = unfinished and not pid  # not even its writer's pid: just created
                if not busy and not closed and _pid_alive(pid):
                    raise FileExistsError(f"shared memory {name!r} is in use by process {pid}")
            finally:
                old.close()
        if busy:
            # Only a writer that died in its first microseconds leaves this for good.
            raise FileExistsError(
                f"shared memory {name!r} is being set up by another process "
                f"(if none is, remove /dev/shm/{name})"
            )
        if old is not None:
            _unlink_untracked(name)
        return shared_memory.SharedMemory(name, create=True, size=size)

    @property
    def slots(self) -> int:
        """Number of slots."""
        return self._ring.slots

    @property
    def frames_written(self) -> int:
        """Frames published so far."""
        return self._ring.frames_written

    def write(
        self,
        image: npt.NDArray[np.uint8],
        *,
        frame_id: int = 0,
        capture_time: float = 0.0,
        camera: str = "",
    ) -> int:
        """Publish ``image`` (BGR uint8, H × W × 3) as the newest frame; returns its number.

        Never blocks and never waits for readers.
        """
        if self._closed:
            raise ValueError(f"frame ring {self.name!r} is closed")
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"expected a BGR uint8 image, got {image.dtype} {image.shape}")
        ring = self._ring
        height, width = image.shape[:2]
        if width > ring.max_width or height > ring.max_height:
            factor = min(ring.max_width / width, ring.max_height / height)
            width = max(1, int(width * factor))
            height = max(1, int(height * factor))
            image = np.asarray(
                cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA), dtype=np.uint8
            )
        number = ring.frames_written
        index = number % ring.slots
        seq = ring.seqs[index]
        buf = self._shm.buf
        assert buf is not None
        name = camera.encode("utf-8")[:_CAMERA_BYTES]
        seq[0] += np.uint64(1)  # odd: readers of this slot will retry
        _SLOT_META.pack_into(
            buf,
            _HEADER_SIZE + index * _SLOT_HEADER_SIZE + 8,
            number,
            frame_id % (1 << 64),
            float(capture_time),
            height,
            width,
            len(name),
            name,
        )
        n = height * width * 3
        ring.pictures[index][:n] = np.ascontiguousarray(image).reshape(-1)
        seq[0] += np.uint64(1)  # even again: the slot is whole
        ring.counters[0] = np.uint64(number + 1)
        return number

    def close(self) -> None:
        """Mark the ring closed and unlink it; idempotent. Attached readers keep their copy."""
        if self._closed:
            return
        self._closed = True
        self._ring.release(unmap=False)  # _retire still writes the closed flag
        self._finalizer()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def _retire(shm: shared_memory.SharedMemory) -> None:
    """Tell readers the ring is closed, unlink it and unmap it (the writer's finaliser)."""
    buf = shm.buf
    if buf is not None:
        struct.pack_into("<I", buf, _CLOSED_AT, 1)
    with contextlib.suppress(FileNotFoundError):
        shm.unlink()  # also unregisters it from the resource tracker
    with contextlib.suppress(BufferError):  # numpy views still alive at exit: the OS unmaps
        shm.close()


def _unlink_untracked(name: str) -> None:
    """Remove the name of a segment this process did not create, bypassing the tracker.

    (``SharedMemory.unlink`` would also unregister it from this process's resource
    tracker, which never registered it.) Windows has no names to remove.
    """
    if os.name != "posix":
        return
    import _posixshmem  # type: ignore[import-not-found,unused-ignore]

    with contextlib.suppress(FileNotFoundError):
        _posixshmem.shm_unlink("/" + name)


class FrameRingReader:
    """Reads the newest frames of the named ring; attach and detach at any time.

    Raises FileNotFoundError when no ring of that name exists yet (:class:`RingNotReady`
    while its writer is still setting it up), ValueError when the segment is not a frame
    ring. Lock-free: reading never blocks the writer.
    """

    def __init__(self, name: str) -> None:
        validate_ring_name(name)
        self.name = name
        shm = _open_untracked(name)
        try:
            self._ring = _Ring(shm)
        except BaseException:
            shm.close()
            raise
        self._last: int | None = None
        #: Copies discarded because the writer overwrote the slot meanwhile.
        self.torn = 0
        #: Frames written that this reader never returned (it was slower than the writer).
        self.skipped = 0

    @property
    def max_size(self) -> tuple[int, int]:
        """(width, height) of the largest picture the ring holds."""
        return self._ring.max_width, self._ring.max_height

    @property
    def frames_written(self) -> int:
        """Frames the writer published so far."""
        return self._ring.frames_written

    @property
    def writer_closed(self) -> bool:
        """True once the writer closed the ring, or its process is gone."""
        buf = self._ring.shm.buf
        if buf is None:
            return True
        _, _, _, _, _, _, _, pid, closed = HEADER.unpack_from(buf)
        return bool(closed) or not _pid_alive(pid)

    def latest(self) -> RingFrame | None:
        """A copy of the newest frame (None before the first one)."""
        for _ in range(100):
            written = self._ring.frames_written
            if written == 0:
                return None
            frame = self._read_slot(written - 1)
            if frame is not None:
                return frame
            self.torn += 1
        return None  # the writer laps us continuously: give up for now

    def read_next(self, timeout: float | None = None) -> RingFrame | None:
        """The newest frame newer than the last one returned, waiting up to ``timeout`` s.

        Returns None on timeout or when the writer closed the ring and nothing new is left.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            written = self._ring.frames_written
            if written and (self._last is None or written - 1 > self._last):
                frame = self.latest()
                if frame is not None and (self._last is None or frame.number > self._last):
                    if self._last is not None:
                        self.skipped += frame.number - self._last - 1
                    self._last = frame.number
                    return frame
            if self.writer_closed:
                return None
            if deadline is not None and time.monotonic() >= deadline:
                return None
            time.sleep(POLL_INTERVAL)

    def frames(self, timeout: float | None = None) -> Iterator[RingFrame]:
        """Newer and newer frames until the writer closes, or none came for ``timeout`` s."""
        while True:
            frame = self.read_next(timeout)
            if frame is None:
                return
            yield frame

    def _read_slot(self, number: int) -> RingFrame | None:
        ring = self._ring
        index = number % ring.slots
        seq = ring.seqs[index]
        buf = ring.shm.buf
        assert buf is not None
        before = int(seq[0])
        if before & 1:
            return None
        (_, slot_number, frame_id, capture_time, height, width, name_len, name) = (
            SLOT_HEADER.unpack_from(buf, _HEADER_SIZE + index * _SLOT_HEADER_SIZE)
        )
        n = height * width * 3
        if slot_number != number or not 0 < n <= ring.slot_bytes or name_len > _CAMERA_BYTES:
            return None  # overwritten meanwhile (or being written): retry
        image = ring.pictures[index][:n].copy().reshape(height, width, 3)
        if int(seq[0]) != before:
            return None  # torn: the writer was here during the copy
        camera = name[:name_len].decode("utf-8", errors="replace")
        return RingFrame(image, frame_id, capture_time, camera, slot_number)

    def close(self) -> None:
        """Detach; idempotent. (The writer keeps writing; nothing else to clean up.)"""
        ring = getattr(self, "_ring", None)
        if ring is not None:
            ring.release()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __iter__(self) -> Iterator[RingFrame]:
        return self.frames()
