"""bench/browser.py runs: its quick mode end to end (a robot daemon with its gateway, the
local web UI, headless Chromium), and its last line is a RESULT with every figure.

The figures are not checked against targets here (bench/ measures speed); only that each is
a number in a sane range (the gateway's half may be nan while its path is broken: then the
benchmark says where it failed, checked below).
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parent.parent / "bench" / "browser.py"
KEYS = [
    "first_frame_ms",
    "handshake_ms_p50",
    "stop_p99_ms",
    "glass_p50_ms",
    "glass_p99_ms",
    "gateway_cpu_pct",
    "bundle_kb",
]


def test_the_browser_benchmark_quick_mode_ends_with_a_sane_result_line() -> None:
    run = subprocess.run(
        [sys.executable, str(BENCH), "--quick"], capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, run.stderr[-2000:]
    lines = run.stdout.strip().splitlines()
    assert lines and lines[-1].startswith("RESULT "), run.stdout[-2000:]
    fields = dict(part.split("=", 1) for part in lines[-1].split()[1:])
    assert list(fields) == KEYS
    values = {key: float(text) for key, text in fields.items()}
    # The bundle is there and gzipped it is between 10 kB and 1 MB.
    assert 10 < values["bundle_kb"] < 1000
    failed = "GATEWAY WAY FAILED" in run.stdout
    for key, value in values.items():
        if math.isnan(value):
            # Only when the gateway way failed, and the benchmark said where.
            assert failed, (key, run.stdout[-2000:])
            continue
        assert 0 <= value < 60_000, (key, value)
    # The local baseline always measures (the table's local column): the page drew pictures.
    assert "glass n=0;" not in next(line for line in lines if line.startswith("  local:"))
