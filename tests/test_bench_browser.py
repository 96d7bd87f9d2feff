"""bench/browser.py runs: its quick mode end to end (a robot daemon with its gateway, the
local web UI, headless Chromium; the router column is left out in quick mode), and its last
line is a RESULT with every figure; how it reports a failed step and picks the worse of the
two gateways.

The figures are not checked against targets here (bench/ measures speed); only that each is
a number in a sane range (a gateway's half may be nan while its path is broken: then the
benchmark says where it failed, checked below).
"""

from __future__ import annotations

import importlib.util
import math
import subprocess
import sys
from pathlib import Path
from types import ModuleType

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
NAN = float("nan")


def _bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_browser", BENCH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


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
    failed = "WAY FAILED at" in run.stdout
    for key, value in values.items():
        if math.isnan(value):
            # Only when a way failed, and the benchmark said where.
            assert failed, (key, run.stdout[-2000:])
            continue
        assert 0 <= value < 60_000, (key, value)
    # The local baseline always measures (the table's local column): the page drew pictures;
    # the robot's gateway ran; quick mode says that it left the router out, and where the
    # RESULT figures come from.
    assert "glass n=0;" not in next(line for line in lines if line.startswith("  local:"))
    assert any(line.startswith("  robot gateway: first frame") for line in lines), run.stdout
    assert "  router gateway: skipped in quick mode" in run.stdout
    assert "RESULT figures from the robot's gateway only" in lines[-3], lines[-3:]


async def test_a_failed_step_is_one_line_and_nan_and_the_worse_gateway_is_the_result() -> None:
    bench = _bench()
    way = bench.Way("robot gateway", stop=[5.0], glass=[10.0, 20.0], gateway_pct=2.0, fps=30.0)

    async def broken() -> None:
        raise RuntimeError("not armed after 4 tries: timed out\nsecond line")

    assert not await way.step("key presses", broken)
    assert way.failed == {"key presses": "not armed after 4 tries: timed out"}
    mine = bench.figures(way, True)
    assert math.isnan(mine["stop_p99_ms"])  # a failed step's figures are nan, not partial
    assert mine["glass_p99_ms"] == 20.0 and mine["gateway_cpu_pct"] == 2.0
    theirs = {**mine, "glass_p99_ms": 30.0, "gateway_cpu_pct": 1.0}
    result = bench.worse(mine, theirs)
    assert result["glass_p99_ms"] == (30.0, "router")
    assert result["gateway_cpu_pct"] == (2.0, "robot")
    assert math.isnan(result["stop_p99_ms"][0]) and math.isnan(result["first_frame_ms"][0])
    assert bench.worse(mine, None)["glass_p50_ms"] == (10.0, "robot")
    skipped = bench.figures(bench.Way("router gateway", skipped="skipped"), True)
    assert all(math.isnan(v) for v in skipped.values())
