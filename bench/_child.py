"""A benchmark's child process: started with this script's own ``--child`` arguments, its
stdout read line by line by a thread, stopped by closing its stdin (it answers with one
JSON line of counters)."""

from __future__ import annotations

import contextlib
import json
import queue
import subprocess
import sys
import threading
from pathlib import Path


class Child:
    """``python SCRIPT --child ARGS...``; lines of its stdout are read by a thread."""

    def __init__(self, script: str, *args: str) -> None:
        command = [sys.executable, str(Path(script).resolve()), "--child", *args]
        self._proc = subprocess.Popen(
            command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )
        self._lines: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._read, name="child-stdout", daemon=True).start()

    def _read(self) -> None:
        assert self._proc.stdout is not None
        for line in self._proc.stdout:
            self._lines.put(line.strip())
        self._lines.put(None)

    def next_line(self, timeout: float) -> str:
        """The next stdout line; RuntimeError if none comes in time or the child exited."""
        try:
            line = self._lines.get(timeout=timeout)
        except queue.Empty:
            raise RuntimeError(f"the child said nothing for {timeout} s") from None
        if line is None:
            raise RuntimeError(f"the child exited with status {self._proc.wait()}")
        return line

    def close(self) -> dict[str, object]:
        """Close its stdin (it stops serving), return its counters; kill it if it hangs."""
        stats: dict[str, object] = {}
        with contextlib.suppress(OSError, ValueError):
            assert self._proc.stdin is not None
            self._proc.stdin.close()
        with contextlib.suppress(RuntimeError, ValueError):
            stats = json.loads(self.next_line(10.0))
        try:
            self._proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        return stats
