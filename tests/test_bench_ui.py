"""bench/ui.py runs: a few key presses of its section A in headless Chromium.

The benchmark's figures are not checked here (bench/ measures speed); only that it runs
through against the current web UI and measures every press (a refactor once broke it).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parent.parent / "bench" / "ui.py"


async def test_the_ui_benchmark_runs_and_measures_each_press() -> None:
    spec = importlib.util.spec_from_file_location("bench_ui", BENCH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("bench_ui", module)
    spec.loader.exec_module(module)
    key_stop, pose_draw = await module.bench(2)
    assert len(key_stop) == 2 and pose_draw
