"""The robot's call recorder: every call into MCAP files beside the audit log.

``[recording] enabled = true`` makes the daemon build a :class:`Recorder` and register its
:meth:`Recorder.service` as the ``recording`` service. Each call's :class:`RecordingService`
sets the call's :attr:`~telebot.channels.call.Call.tap`, so the recorder sees every
datagram the robot's services send and receive on the recorded channels (pose, telemetry,
plan, goal updates, chat replies and safety states going out; chat commands, goal
requests and safety requests coming in) without any service knowing about it. Safety
events come from the supervisor's audit records (:attr:`SafetyDriver.on_audit`: stops,
re-arms, latches, deadman stops, who asked and what came of it).

The calls go on one timeline, with a topic per user and stream: ``/NAME/pose`` (what the
robot sent), ``/NAME/chat/in`` (what NAME sent), plus ``/calls`` (call start and end) and
``/safety/audit``. One timeline because that is what someone replaying a session in
Foxglove wants: two users in a call at once, the stop one of them gave and what the other
saw, side by side on one time axis; topics named after the user, not the call id, so that
a Foxglove layout made once works on every recording. A topic is one MCAP channel in a
file, whatever the number of calls: its metadata names the user and the direction
(``peer``, ``stream``, ``direction``); which call a message belongs to, and the call's
role, the ``/calls`` events around it say (a user's calls rarely overlap: a reconnect).
Messages are the protocol's own JSON (``docs/protocol.md``), with ``json`` message
encoding and ``jsonschema`` schemas.

An MCAP file is readable once finished (its summary and footer written), so the writer
finishes the file at each call's end, at the latest ``max_seconds`` after it was begun, and
when it grows past ``max_bytes``; the next message begins the next one:
``calls-000001.mcap``, ``calls-000002.mcap`` … What was recorded is thus readable while the
robot runs, after the call or a few minutes. The oldest files are deleted as a new one
begins, keeping at most ``keep`` files and ``keep_bytes`` bytes.

The event loop only appends to a queue (:meth:`Recorder.tap`); a writer thread encodes,
writes, flushes idle chunks and finishes files. A disk that fails logs one line and turns
recording off; the robot and its calls go on. A queue that backs up past
:data:`MAX_PENDING` drops messages (counted) rather than grow.
"""

from __future__ import annotations

import contextlib
import json
import logging
import queue
import re
import threading
import time
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, Final

from mcap.writer import CompressionType, Writer

from telebot.safety import AuditRecord
from telebot.services.schemas import AUDIT_SCHEMA, CALLS_SCHEMA, SCHEMAS, schema_bytes
from telebot.services.schemas import json_schema as _schema

if TYPE_CHECKING:
    from telebot.channels.call import Call

__all__ = [
    "MAX_PENDING",
    "SCHEMAS",
    "Recorder",
    "RecordingService",
]

log = logging.getLogger(__name__)

#: Messages waiting for the writer thread beyond which new ones are dropped (and counted).
MAX_PENDING = 20000
#: The writer thread flushes its chunk to disk after this long without a message (s), so
#: that a robot that dies loses at most this much of a quiet call.
IDLE_FLUSH = 1.0
#: Largest chunk (bytes) the writer gathers before compressing and writing it.
MAX_CHUNK = 1024 * 1024

_FILE = re.compile(r"calls-(\d{6,})\.mcap")


@dataclass(frozen=True, slots=True)
class _Topic:
    """What an MCAP channel is (registered in each file on its first message there)."""

    topic: str
    schema: str
    metadata: dict[str, str] = field(default_factory=dict)
    #: Check the payload is a JSON object before writing it (what users send).
    untrusted: bool = False


#: A queue item's key: a call ended, finish the file (so that its call is readable).
_CALL_ENDED: Final = object()

# The queue's items: (topic key, payload, log time ns), or None to finish and stop.
_Item = tuple[object, "str | bytes", int] | None


class Recorder:
    """Writes calls into MCAP files in ``directory`` from a writer thread.

    A file is finished (a valid MCAP with its summary) at each call's end, ``max_seconds``
    after it was begun, past ``max_bytes``, and at :meth:`close`. As a file begins, the
    oldest are deleted down to ``keep`` files and ``keep_bytes`` bytes.

    Thread-safe: :meth:`tap`, :meth:`audit` and the call events may come from any thread.
    Call :meth:`start` before the first call and :meth:`close` at the end.
    """

    def __init__(
        self,
        directory: Path,
        *,
        max_bytes: int = 64 * 1024 * 1024,
        max_seconds: float = 300.0,
        keep: int = 1000,
        keep_bytes: int = 1024 * 1024 * 1024,
        streams: Iterable[str] = ("pose", "telemetry", "plan", "goals", "chat", "safety"),
    ) -> None:
        if max_bytes < 1 or keep < 1 or keep_bytes < 1 or not max_seconds > 0:
            raise ValueError("max_bytes, max_seconds, keep and keep_bytes must be positive")
        self.directory = directory
        self.max_bytes = max_bytes
        self.max_seconds = max_seconds
        self.keep = keep
        self.keep_bytes = keep_bytes
        self.streams = frozenset(streams)
        #: False once the disk failed (or after close): nothing more is queued.
        self.enabled = True
        #: Messages dropped because the writer fell behind.
        self.dropped = 0
        #: Messages written, and files finished.
        self.written = 0
        self.files_done = 0
        #: Calls being recorded now.
        self.calls = 0
        #: The file being written (None before the first message and after a failure).
        self.path: Path | None = None
        self._queue: queue.SimpleQueue[_Item] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        # Writer-thread state.
        self._topics: dict[object, _Topic] = {}
        self._file: IO[bytes] | None = None
        self._writer: Writer | None = None
        self._schema_ids: dict[str, int] = {}
        self._channel_ids: dict[object, int] = {}
        self._number = 0
        self._dirty = False
        self._opened_at = 0.0  # time.monotonic() of the file's first message

    # -- any thread -------------------------------------------------------------------

    def start(self) -> None:
        """Start the writer thread (the first file is opened with the first message)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="telebot-recorder", daemon=True)
            self._thread.start()

    def close(self, timeout: float = 10.0) -> None:
        """Write what is queued, finish the file and stop the thread (blocks; idempotent)."""
        if self._thread is None:
            return
        self._queue.put(None)
        self._thread.join(timeout)
        self._thread = None
        self.enabled = False

    def __enter__(self) -> Recorder:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _put(self, key: object, payload: str | bytes) -> None:
        if not self.enabled:
            return
        if self._queue.qsize() >= MAX_PENDING:
            self.dropped += 1
            return
        self._queue.put((key, payload, time.time_ns()))

    def audit(self, record: AuditRecord) -> None:
        """A safety audit record (:attr:`SafetyDriver.on_audit`) on ``/safety/audit``."""
        self._put("audit", json.dumps(asdict(record), ensure_ascii=False))

    def service(self, host: object, call: Call) -> RecordingService:
        """The ``recording`` :class:`~telebot.services.base.ServiceFactory`."""
        return RecordingService(self, call)

    # -- writer thread ----------------------------------------------------------------

    def _run(self) -> None:
        self._topics["audit"] = _Topic("/safety/audit", "audit")
        self._topics["calls"] = _Topic("/calls", "calls")
        while True:
            try:
                item = self._queue.get(timeout=self._wait())
            except queue.Empty:
                self._guard(self._finish if self._too_old() else self._flush)
                continue
            if item is None:
                self._guard(self._finish)
                return
            if self.enabled:
                self._guard(self._write, *item)

    def _wait(self) -> float | None:
        """How long the writer may wait for a message: until the next flush or finish."""
        waits = [IDLE_FLUSH] if self._dirty else []
        if self._writer is not None:
            waits.append(max(0.0, self._opened_at + self.max_seconds - time.monotonic()))
        return min(waits, default=None)

    def _too_old(self) -> bool:
        return self._writer is not None and time.monotonic() - self._opened_at >= self.max_seconds

    def _guard(self, action: Any, *args: Any) -> None:
        try:
            action(*args)
        except Exception as exc:  # a full or failing disk must not stop the robot
            if self.enabled:
                log.error("recording off: %s: %s", self.directory, exc)
            self.enabled = False
            self._abandon()

    def _write(self, key: object, payload: str | bytes, log_time: int) -> None:
        if key is _CALL_ENDED:
            self._finish()
            return
        topic = self._topics.get(key)
        if topic is None:
            return
        data = payload.encode() if isinstance(payload, str) else payload
        if topic.untrusted:
            try:
                message = json.loads(data)
            except ValueError:
                return
            if not isinstance(message, dict):
                return  # not a request: the services drop it too
        writer = self._writer if self._writer is not None else self._open()
        channel_id = self._channel_ids.get(key)
        if channel_id is None:
            schema_id = self._schema_ids.get(topic.schema)
            if schema_id is None:
                schema = _schema_of(topic.schema)
                schema_id = writer.register_schema(
                    name=schema["title"],
                    encoding="jsonschema",
                    data=schema_bytes(schema),
                )
                self._schema_ids[topic.schema] = schema_id
            channel_id = writer.register_channel(
                topic=topic.topic,
                message_encoding="json",
                schema_id=schema_id,
                metadata=topic.metadata,
            )
            self._channel_ids[key] = channel_id
        writer.add_message(channel_id, log_time=log_time, data=data, publish_time=log_time)
        self.written += 1
        self._dirty = True
        assert self._file is not None
        if self._file.tell() >= self.max_bytes or self._too_old():
            self._finish()

    def _open(self) -> Writer:
        self.directory.mkdir(parents=True, exist_ok=True)
        if self._number == 0:  # go on after the files already there
            self._number = max((n for n, _ in self._existing()), default=0)
        self._number += 1
        path = self.directory / f"calls-{self._number:06d}.mcap"
        self._file = path.open("wb")
        # Chunks well under a file's size, so that rotation happens near max_bytes.
        chunk = max(1024, min(MAX_CHUNK, self.max_bytes // 8))
        self._writer = Writer(self._file, chunk_size=chunk, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="telebot")
        self._schema_ids.clear()
        self._channel_ids.clear()
        self.path = path
        self._opened_at = time.monotonic()
        self._prune()
        return self._writer

    def _existing(self) -> list[tuple[int, Path]]:
        found = []
        for path in self.directory.iterdir():
            match = _FILE.fullmatch(path.name)
            if match is not None:
                found.append((int(match.group(1)), path))
        return sorted(found)

    def _prune(self) -> None:
        """Delete the oldest files (never the one just begun) down to ``keep`` and ``keep_bytes``."""
        existing, sizes = [], []
        for _, path in self._existing():
            try:
                sizes.append(path.stat().st_size)
            except FileNotFoundError:  # deleted meanwhile (by someone else): not ours to keep
                continue
            existing.append(path)
        count, total = len(existing), sum(sizes)
        for path, size in zip(existing, sizes, strict=True):
            if path == self.path or (count <= self.keep and total <= self.keep_bytes):
                break
            path.unlink(missing_ok=True)
            count, total = count - 1, total - size

    def _flush(self) -> None:
        if self._writer is not None and self._file is not None:
            self._writer.flush()  # type: ignore[no-untyped-call]  # writes the open chunk: a crash loses at most that much
            self._file.flush()
        self._dirty = False

    def _finish(self) -> None:
        writer, file = self._writer, self._file
        self._writer = self._file = None
        self._dirty = False
        if writer is not None and file is not None:
            try:
                writer.finish()  # type: ignore[no-untyped-call]
            finally:
                file.close()
            self.files_done += 1

    def _abandon(self) -> None:
        file = self._file
        self._writer = self._file = None
        self.path = None
        if file is not None:
            with contextlib.suppress(OSError):
                file.close()


def _schema_of(name: str) -> dict[str, Any]:
    if name == "audit":
        return AUDIT_SCHEMA
    if name == "calls":
        return CALLS_SCHEMA
    stream, _, direction = name.partition(":")
    return SCHEMAS.get((stream, direction), _schema(f"telebot.{stream}", {}))


class RecordingService:
    """The ``recording`` service of one call: taps its channels into the :class:`Recorder`."""

    def __init__(self, recorder: Recorder, call: Call) -> None:
        self.recorder = recorder
        self.call = call
        role = str(call.role) if call.role is not None else ""
        # A topic per user and stream, shared by all of the user's calls (one MCAP channel
        # each), so kept after the call: users are few. Registered here, on the loop,
        # before any message: the writer thread only reads.
        topics = recorder._topics
        self._keys: dict[tuple[str, bool], object] = {}
        for stream in sorted(recorder.streams):
            for sent in (True, False):
                key = (call.peer, stream, sent)
                direction = "out" if sent else "in"
                if key not in topics:
                    topics[key] = _Topic(
                        f"/{call.peer}/{stream}" + ("" if sent else "/in"),
                        f"{stream}:{direction}",
                        {"peer": call.peer, "stream": stream, "direction": direction},
                        untrusted=not sent,
                    )
                self._keys[stream, sent] = key
        recorder._put(
            "calls",
            json.dumps({"event": "start", "call": call.id, "peer": call.peer, "role": role}),
        )
        recorder.calls += 1
        call.tap = self._tap

    def _tap(self, channel: str, sent: bool, payload: str | bytes) -> None:
        key = self._keys.get((channel, sent))
        if key is not None:
            self.recorder._put(key, payload)

    def tick(self, now: float) -> None:
        """Nothing: the tap records as messages go."""

    def close(self) -> None:
        """The call ended: stop tapping it, record its end and finish the file."""
        self.call.tap = None
        end = self.call.end
        event = {
            "event": "end",
            "call": self.call.id,
            "peer": self.call.peer,
            "kind": end.kind if end is not None else "",
            "detail": end.detail if end is not None else "",
        }
        self.recorder._put("calls", json.dumps(event, ensure_ascii=False))
        # After its last message: what was recorded of the call is readable at once.
        self.recorder._put(_CALL_ENDED, b"")
        self.recorder.calls -= 1
