"""Every benchmark still runs: each ``bench/*.py`` in its ``--quick`` mode, end to end in a
subprocess, exits 0 and ends with a well-formed ``RESULT key=value ...`` line.

The figures are not checked (a quick run's are noise, and bench/ measures speed): this only
keeps a refactor from breaking a benchmark unseen (one did: ``bench/ui.py`` called a method
the web UI no longer had). Each benchmark is its own test; ``make test`` runs this module
after the rest of the suite, two benchmarks at a time (each starts several processes, and
beside the browser tests they starved Chromium's video). ``bench/_*.py`` are the
benchmarks' helpers, run by them. ``make bench-quick`` runs the same list by hand.
"""

from __future__ import annotations

import asyncio
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BENCH = ROOT / "bench"
#: Benchmarks whose quick run a test of their own makes already, checking their figures
#: too (running them twice would cost the suite the time of a browser session).
ELSEWHERE = {"browser.py": "test_bench_browser.py"}
BENCHES = sorted(
    path.name
    for path in BENCH.glob("*.py")
    if not path.name.startswith("_") and path.name not in ELSEWHERE
)
#: What a quick run may cost on a loaded 2-core machine (a few seconds when idle; the
#: heaviest start a browser, routers or several processes).
QUICK_TIMEOUT = 300.0
RESULT = re.compile(r"RESULT( [A-Za-z0-9_]+=\S+)+")


def result_fields(stdout: str) -> dict[str, str]:
    """The ``RESULT`` line's fields, which must be the last line of ``stdout``."""
    lines = stdout.strip().splitlines()
    assert lines, "the benchmark printed nothing"
    last = lines[-1]
    assert RESULT.fullmatch(last), f"the last line is not a RESULT line: {last!r}"
    return dict(item.split("=", 1) for item in last.split()[1:])


def is_figure(value: str) -> bool:
    """A number (nan where a part could not be measured), or ``n/a``/``na`` for a part a
    quick run leaves out."""
    if value in {"n/a", "na"}:
        return True
    try:
        float(value)
    except ValueError:
        return False
    return True


@pytest.mark.timeout(QUICK_TIMEOUT + 30)
@pytest.mark.parametrize("name", BENCHES)
def test_the_benchmark_runs_in_quick_mode(name: str) -> None:
    result = subprocess.run(
        [sys.executable, str(BENCH / name), "--quick"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=QUICK_TIMEOUT,
        check=False,
    )
    assert result.returncode == 0, f"bench/{name} --quick failed:\n{result.stderr[-3000:]}"
    fields = result_fields(result.stdout)
    bad = {key: value for key, value in fields.items() if not is_figure(value)}
    assert bad == {}, f"bench/{name}: RESULT fields that are not figures: {bad}"


def test_every_benchmark_is_run_by_make_and_by_a_test() -> None:
    # A new benchmark joins `make bench`, `make bench-quick` and this module by being a
    # file of bench/; one run elsewhere says where, and that test runs it quick.
    makefile = (ROOT / "Makefile").read_text()
    listed = re.search(r"^BENCHES := (.*?)(?<!\\)$", makefile, re.M | re.S)
    assert listed is not None, "the Makefile lists no BENCHES"
    names = set(listed.group(1).replace("\\\n", " ").split())
    every = {path.stem for path in BENCH.glob("*.py") if not path.name.startswith("_")}
    assert names == every, f"Makefile BENCHES differs from bench/*.py: {names ^ every}"
    for name, test in ELSEWHERE.items():
        text = (ROOT / "tests" / test).read_text()
        assert f'"{name}"' in text and "--quick" in text, f"{test} does not run {name} quick"


def test_the_result_check_refuses_what_is_not_a_result() -> None:
    assert result_fields("x\nRESULT a=1.5 b=nan c=n/a\n") == {"a": "1.5", "b": "nan", "c": "n/a"}
    assert all(is_figure(v) for v in ("1.5", "nan", "-3", "n/a"))
    for bad in ("RESULT\n", "RESULT a=1\ntook 3 s\n", "RESULT a 1\n", ""):
        with pytest.raises(AssertionError):
            result_fields(bad)
    assert not is_figure("5.0x") and not is_figure("")


async def test_the_video_benchmarks_robot_keeps_the_loops_clock() -> None:
    # bench/video.py steps its simulated robot to loop.time() (CLOCK_MONOTONIC: the
    # machine's uptime). A robot whose clock started at 0 integrated the whole uptime in its
    # first step: a minute of blocked loop on a machine up for a day, and the call timed out.
    sys.path.insert(0, str(BENCH))  # video.py imports bench/_child.py
    try:
        import video
    finally:
        sys.path.remove(str(BENCH))
    loop = asyncio.get_running_loop()
    nav = video.sim_robot()
    assert nav.now == pytest.approx(loop.time(), abs=5.0)
