"""The shared-memory frame ring: one writer, lock-free readers in other processes that come,
go and crash, torn copies detected, the segment removed when the writer goes."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
import uuid
from collections.abc import Iterator
from multiprocessing import resource_tracker, shared_memory
from pathlib import Path

import numpy as np
import pytest

from telebot.services.shm import (
    HEADER,
    MAGIC,
    VERSION,
    FrameRingReader,
    FrameRingWriter,
    RingNotReady,
    validate_ring_name,
)

SRC = str(Path(__file__).resolve().parents[1] / "src")


@pytest.fixture
def name() -> str:
    return f"tb-test-{uuid.uuid4().hex[:12]}"


def picture(value: int, height: int = 48, width: int = 64) -> np.ndarray:
    return np.full((height, width, 3), value % 251, dtype=np.uint8)


def exists(name: str) -> bool:
    """Whether a segment of that name is there at all, ring or not (Linux names them)."""
    return Path("/dev/shm", name).exists()


def test_frames_written_are_read_back_with_their_metadata(name: str) -> None:
    with FrameRingWriter(name, 64, 48, slots=3) as writer, FrameRingReader(name) as reader:
        assert reader.latest() is None and reader.read_next(timeout=0.01) is None
        assert reader.max_size == (64, 48) and writer.slots == 3
        writer.write(picture(7), frame_id=41, capture_time=1234.5, camera="navcam")
        frame = reader.read_next(timeout=1.0)
        assert frame is not None
        assert (frame.frame_id, frame.capture_time, frame.camera, frame.number) == (
            41,
            1234.5,
            "navcam",
            0,
        )
        assert frame.image.shape == (48, 64, 3) and int(frame.image.max()) == 7
        # The copy is the reader's own: later writes do not change it.
        for i in range(5):
            writer.write(picture(100 + i), frame_id=100 + i)
        assert int(frame.image.max()) == 7
        # A reader that fell behind gets the newest frame, never an older one after it.
        newest = reader.read_next(timeout=1.0)
        assert newest is not None and newest.frame_id == 104 and reader.skipped == 4
        assert reader.read_next(timeout=0.01) is None
        # Smaller pictures keep their size; larger ones are shrunk to fit, aspect kept.
        writer.write(picture(1, 20, 30), frame_id=1)
        small = reader.read_next(timeout=1.0)
        assert small is not None and small.image.shape == (20, 30, 3)
        writer.write(picture(2, 480, 1280), frame_id=2)
        big = reader.read_next(timeout=1.0)
        assert big is not None and big.image.shape == (24, 64, 3)
        assert not reader.writer_closed
    assert reader is not None
    assert not exists(name)  # the writer unlinked it


def test_readers_see_the_writer_close_and_the_name_goes_away(name: str) -> None:
    writer = FrameRingWriter(name, 32, 32)
    reader = FrameRingReader(name)
    writer.write(picture(3, 32, 32), frame_id=1)
    writer.close()
    writer.close()  # idempotent
    assert reader.writer_closed
    assert [f.frame_id for f in reader.frames(timeout=1.0)] == [1]  # what was left, then end
    reader.close()
    with pytest.raises(FileNotFoundError):
        FrameRingReader(name)
    with pytest.raises(ValueError, match="closed"):
        writer.write(picture(1, 32, 32))


def test_a_torn_copy_is_detected_and_not_returned(name: str) -> None:
    with FrameRingWriter(name, 16, 16, slots=2) as writer, FrameRingReader(name) as reader:
        writer.write(picture(5, 16, 16), frame_id=5)
        ring = writer._ring
        ring.seqs[0][0] += np.uint64(1)  # the writer is "in the middle" of slot 0
        assert reader.latest() is None and reader.torn > 0
        ring.seqs[0][0] += np.uint64(1)  # done
        frame = reader.latest()
        assert frame is not None and frame.frame_id == 5


def test_names_and_sizes_are_checked(name: str) -> None:
    for bad in ("", "a/b", "x" * 31, "-lead", "sp ace"):
        with pytest.raises(ValueError, match="shared-memory name"):
            validate_ring_name(bad)
    with pytest.raises(ValueError, match="slots"):
        FrameRingWriter(name, 8, 8, slots=1)
    with pytest.raises(ValueError, match="width"):
        FrameRingWriter(name, 0, 8)
    with FrameRingWriter(name, 8, 8) as writer:
        with pytest.raises(FileExistsError, match="in use"):
            FrameRingWriter(name, 8, 8)
        with pytest.raises(ValueError, match="BGR"):
            writer.write(np.zeros((8, 8), dtype=np.uint8))
    with pytest.raises(FileNotFoundError):
        FrameRingReader(name)


def dead_pid() -> int:
    """The pid of a process that has exited (a dead writer's, for these tests)."""
    child = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        check=True,
        capture_output=True,
        text=True,
    )
    return int(child.stdout)


def untracked_segment(name: str, size: int) -> shared_memory.SharedMemory:
    shm = shared_memory.SharedMemory(name, create=True, size=size)
    resource_tracker.unregister(shm._name, "shared_memory")  # type: ignore[attr-defined]
    return shm


def test_a_segment_left_by_a_dead_writer_is_reclaimed_and_a_foreign_one_is_not(
    name: str,
) -> None:
    dead = dead_pid()
    stale = untracked_segment(name, 4096)
    assert stale.buf is not None
    HEADER.pack_into(stale.buf, 0, MAGIC, VERSION, 2, 8, 8, 192, 9, dead, 0)
    stale.close()
    with FrameRingWriter(name, 8, 8) as writer:
        writer.write(picture(1, 8, 8), frame_id=1)
        with FrameRingReader(name) as reader:
            frame = reader.latest()
            assert frame is not None and frame.frame_id == 1 and frame.number == 0
    foreign = untracked_segment(name, 4096)
    assert foreign.buf is not None
    foreign.buf[:8] = b"NOTARING"  # (all zeros would read as a ring still being set up)
    try:
        with pytest.raises(FileExistsError, match="not a frame ring"):
            FrameRingWriter(name, 8, 8)
        with pytest.raises(ValueError, match="not a telebot frame ring"):
            FrameRingReader(name)
    finally:
        foreign.close()
        foreign.unlink()


def test_a_ring_still_being_set_up_is_not_there_yet_for_readers_and_busy_for_writers(
    name: str,
) -> None:
    import _posixshmem

    # A writer creates the name, then sizes it, then fills in the header: a reader or a
    # second writer can look in between each step.
    fd = _posixshmem.shm_open("/" + name, os.O_CREAT | os.O_EXCL | os.O_RDWR, mode=0o600)
    try:
        with pytest.raises(RingNotReady, match="still being created"):
            FrameRingReader(name)
        with pytest.raises(FileExistsError, match="being set up by another process"):
            FrameRingWriter(name, 8, 8)
        os.ftruncate(fd, 4096)  # sized: all zeros, no magic yet
        with pytest.raises(RingNotReady, match="not a frame ring yet"):
            FrameRingReader(name)
        with pytest.raises(FileExistsError, match="being set up by another process"):
            FrameRingWriter(name, 8, 8)
        assert issubclass(RingNotReady, FileNotFoundError)  # loops waiting for a ring wait on
        # The header without its magic, from a live writer: in use; from a dead one (it
        # died while setting up): reclaimed.
        with open(f"/proc/{os.getpid()}/fd/{fd}", "r+b", buffering=0) as segment:
            segment.write(HEADER.pack(bytes(8), VERSION, 2, 8, 8, 192, 0, os.getpid(), 0))
            with pytest.raises(FileExistsError, match=f"in use by process {os.getpid()}"):
                FrameRingWriter(name, 8, 8)
            dead = dead_pid()
            segment.seek(0)
            segment.write(HEADER.pack(bytes(8), VERSION, 2, 8, 8, 192, 0, dead, 0))
        with FrameRingWriter(name, 8, 8) as writer, FrameRingReader(name) as reader:
            writer.write(picture(7, 8, 8), frame_id=7)
            frame = reader.latest()
            assert frame is not None and frame.frame_id == 7
    finally:
        os.close(fd)
        with contextlib.suppress(FileNotFoundError):  # the writer above removed it
            _posixshmem.shm_unlink("/" + name)


RECREATE = textwrap.dedent(
    """
    import sys, time
    from telebot.services.shm import FrameRingWriter
    deadline = time.monotonic() + float(sys.argv[2])
    rounds = 0
    while time.monotonic() < deadline:
        FrameRingWriter(sys.argv[1], 8, 8, slots=2).close()
        rounds += 1
    print(rounds, flush=True)
    """
)


def test_readers_attaching_while_a_writer_comes_and_goes_see_a_whole_ring_or_none(
    name: str,
) -> None:
    writer = subprocess.Popen(
        [sys.executable, "-c", RECREATE, name, "1.0"],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": SRC},
    )
    attached = absent = 0
    try:
        while writer.poll() is None:
            try:
                with FrameRingReader(name) as reader:
                    assert reader.max_size == (8, 8)
                    attached += 1
            except FileNotFoundError:
                absent += 1  # none yet, or gone again: what a waiting reader retries on
    finally:
        out, _ = writer.communicate(timeout=10)
    assert writer.returncode == 0 and int(out) > 10
    assert attached > 0 and absent > 0  # both cases happened, neither raised anything else


READER = textwrap.dedent(
    """
    import json, sys
    from telebot.services.shm import FrameRingReader
    with FrameRingReader(sys.argv[1]) as ring:
        print("attached", flush=True)
        frames = bad = 0
        for frame in ring.frames(timeout=10.0):
            # Every pixel of frame n is n % 251: a torn copy mixes two frames.
            if not (frame.image == frame.frame_id % 251).all():
                bad += 1
            frames += 1
            if frames == 20:
                print("reading", flush=True)
        result = {"frames": frames, "bad": bad, "torn": ring.torn, "skipped": ring.skipped}
        print(json.dumps(result), flush=True)
    """
)


def start_reader(name: str) -> subprocess.Popen[str]:
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [SRC, os.environ.get("PYTHONPATH")])),
    }
    return subprocess.Popen(
        [sys.executable, "-c", READER, name],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


@pytest.fixture
def readers() -> Iterator[list[subprocess.Popen[str]]]:
    started: list[subprocess.Popen[str]] = []
    yield started
    for proc in started:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=10)
        for pipe in (proc.stdout, proc.stderr):
            if pipe is not None:
                pipe.close()


def test_a_writer_and_two_reader_processes_one_killed_mid_read(
    name: str, readers: list[subprocess.Popen[str]]
) -> None:
    # Big frames (640 × 480) and two slots: copies take long enough to be overtaken.
    writer = FrameRingWriter(name, 640, 480, slots=2)
    stop = threading.Event()
    frames = [np.full((480, 640, 3), v, dtype=np.uint8) for v in range(251)]

    def write() -> None:
        n = 0
        while not stop.is_set():
            n += 1
            writer.write(frames[n % 251], frame_id=n)  # flat out: readers get overtaken

    thread = threading.Thread(target=write)
    thread.start()
    try:
        survivor, victim = start_reader(name), start_reader(name)
        readers.extend([survivor, victim])
        for proc in (survivor, victim):
            assert proc.stdout is not None
            assert proc.stdout.readline().strip() == "attached", proc.stderr
        # Both are copying frames in a tight loop, so the kill lands mid-copy or near it.
        assert victim.stdout is not None and victim.stdout.readline().strip() == "reading"
        victim.send_signal(signal.SIGKILL)
        victim.wait(timeout=10)
        written = writer.frames_written
        time.sleep(0.3)
        assert writer.frames_written > written  # the writer never waited for the dead reader
        late = start_reader(name)  # readers come at any time
        readers.append(late)
        assert late.stdout is not None and late.stdout.readline().strip() == "attached"
        for proc in (survivor, late):  # both have whole frames to show for it
            assert proc.stdout is not None and proc.stdout.readline().strip() == "reading"
    finally:
        stop.set()
        thread.join()
        writer.close()  # the readers see the ring closed and finish
    results = []
    for proc in (survivor, late):
        assert proc.stdout is not None
        out, err = proc.communicate(timeout=20)
        assert proc.returncode == 0, err
        results.append(json.loads(out.strip().splitlines()[-1]))
    for result in results:
        assert result["frames"] >= 20
        assert result["bad"] == 0  # no torn or mixed frame ever returned
    assert victim.returncode == -signal.SIGKILL
    assert not exists(name)


def test_a_writer_that_exits_without_closing_still_removes_the_segment(name: str) -> None:
    code = textwrap.dedent(
        f"""
        import numpy as np
        from telebot.services.shm import FrameRingWriter
        ring = FrameRingWriter({name!r}, 8, 8)
        ring.write(np.zeros((8, 8, 3), dtype=np.uint8))
        print("written", flush=True)
        """
    )
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [SRC, os.environ.get("PYTHONPATH")])),
    }
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=30
    )
    assert result.returncode == 0 and "written" in result.stdout
    assert "leaked" not in result.stderr  # no resource_tracker complaint
    assert not exists(name)
