"""bench/wan.py's own arithmetic: the figures it prints and its RESULT line.

A quick run of the benchmark takes longer than a test may (a robot daemon, a call through
the emulator, an outage and a second call at 10 % loss: about half a minute on a loaded
machine), so what is tested here is what turns measurements into figures: percentiles,
late and never-shown frames, trips per hour, the worst row, the RESULT line, ``--row``.
"""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path
from types import ModuleType

import pytest

from telebot.netem import PROFILES

BENCH = Path(__file__).resolve().parent.parent / "bench"


@pytest.fixture(scope="module")
def wan() -> ModuleType:
    sys.path.insert(0, str(BENCH))  # wan.py imports bench/safety.py's helpers
    try:
        spec = importlib.util.spec_from_file_location("bench_wan", BENCH / "wan.py")
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules.setdefault("bench_wan", module)
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(BENCH))


def test_percentiles_late_frames_and_trips(wan: ModuleType) -> None:
    assert wan.pct([5.0, 1.0, 3.0, 2.0, 4.0], 50) == 3.0
    assert wan.pct(list(range(1, 101)), 99) == 99
    assert math.isnan(wan.pct([], 99))
    # 150 ms after capture plus the one-way delay (40 ms) is late: 190.5 is, 190 is not.
    assert wan.late_share([50.0, 190.0, 190.5, 400.0], 40.0) == 0.5
    assert math.isnan(wan.late_share([], 40.0))
    # Frames 10..19 sent, 15 never shown (a frame shown twice counts once).
    assert wan.never_shown([11, 12, 13, 14, 16, 17, 18, 18, 10, 19]) == (10, 1)
    assert wan.never_shown([]) == (0, 0)
    assert wan.per_hour(2, 60.0) == 120.0
    assert math.isnan(wan.per_hour(0, 0.0))


def test_the_longest_silence_spans_gaps_and_the_windows_edges(wan: ModuleType) -> None:
    # Heard at 1.0 (sampled three times), 1.2 and 2.0: the gap 1.2 -> 2.0 is the longest.
    assert wan.longest_silence([1.0, 1.0, 1.2, 1.0, 2.0, 2.1], 1.0, 2.1) == pytest.approx(0.8)
    # Nothing heard after 1.2 in a window to 3.0: the silence still running counts.
    assert wan.longest_silence([1.0, 1.2], 1.0, 3.0) == pytest.approx(1.8)
    # Moments outside the window do not count; a window with none is silent throughout.
    assert wan.longest_silence([0.5, 5.0], 1.0, 2.0) == pytest.approx(1.0)
    assert math.isnan(wan.longest_silence([1.0], 2.0, 2.0))
    row = wan.Row("bad", "quic")
    assert math.isnan(row.figures()["silence_max_ms"])
    row.silence = [0.3, 1.25]
    assert row.figures()["silence_max_ms"] == pytest.approx(1250.0)


def test_a_row_takes_the_one_way_delay_off_its_latencies(wan: ModuleType) -> None:
    row = wan.Row("4g", "tcp", delay_ms=40.0)
    row.stop = [45.0] * 99 + [90.0]
    row.glass = [60.0] * 100
    row.late = [60.0] * 98 + [300.0, 300.0]
    row.late_expected, row.late_lost = 200, 100
    row.trips, row.drive_seconds = 1, 1800.0
    figures = row.figures()
    assert figures["stop_p99_ms"] == 5.0 and figures["glass_p99_ms"] == 20.0
    assert figures["late_frames_pct"] == 2.0 and figures["never_shown_pct"] == 50.0
    assert figures["false_trips_h"] == 2.0
    assert math.isnan(figures["release_p99_ms"]) and math.isnan(figures["reconnect_p99_ms"])


def test_the_result_line_holds_the_worst_profile_on_the_default_link(wan: ModuleType) -> None:
    lan = wan.Row("lan", "quic", stop=[500.0], trips=9, drive_seconds=60.0)
    wifi = wan.Row("wifi", "quic", delay_ms=5.0, stop=[15.0], trips=0, drive_seconds=60.0)
    g_tcp = wan.Row("4g", "tcp", delay_ms=40.0, stop=[140.0], trips=9, drive_seconds=3600.0)
    g_quic = wan.Row("4g", "quic", delay_ms=40.0, stop=[50.0], trips=3, drive_seconds=3600.0)
    rows = [lan, wifi, g_quic, g_tcp]
    assert wan.DEFAULT_LINK == "quic" and wan.result_rows(rows) == [wifi, g_quic]
    fields = wan.result_fields(rows, drive=False)
    # 4g/quic's; neither the baseline's 500 nor 4g/tcp's 100 (a link compared, not chosen).
    assert fields["stop_p99_ms"] == 10.0
    assert fields["false_trips_wifi_h"] == 0.0 and fields["false_trips_4g_h"] == 3.0
    # Only other links measured (--row 4g/tcp): their worst.
    assert wan.result_fields([lan, g_tcp], drive=False)["stop_p99_ms"] == 100.0
    line = wan.result_line(fields, drive=False)
    assert line.startswith("RESULT stop_p99_ms=10.0 glass_p99_ms=nan late_frames_pct=nan ")
    assert line.endswith("false_trips_wifi_h=0.0 false_trips_4g_h=3.0 release_p99_ms=n/a")
    keys = [part.split("=")[0] for part in line.split()[1:]]
    assert keys == list(wan.TARGETS)
    assert wan.ratio(100.0, 20.0) == "5.0x" and wan.ratio(1.0, 0.0) == "-"


def test_a_missed_target_minus_the_delay_names_its_row_and_the_link_s_own_spread(
    wan: ModuleType,
) -> None:
    wifi = wan.Row("wifi", "quic", delay_ms=5.0, stop=[12.0], glass=[10.0], release=[9.0])
    bad = wan.Row("bad", "quic", delay_ms=80.0, stop=[130.0], glass=[90.0], release=[95.0])
    lines = wan.report([wifi, bad], drive=True, amounts=wan.FULL, seconds=1.0)
    stop = next(ln for ln in lines if ln.startswith("target stop p99"))
    # bad's +-40 ms: a p99 39 ms above the mean whatever the transport.
    assert stop.endswith(
        "50.0 MISS (bad/quic; the link alone: one-way delay p99 39 ms above its mean)"
    )
    assert next(ln for ln in lines if ln.startswith("target glass p99")).endswith("10.0 PASS")
    assert wan.spread_p99_ms("lan") == 0.0 and wan.spread_p99_ms("4g") == pytest.approx(14.7)


def test_rows_and_the_lossy_profile(wan: ModuleType) -> None:
    assert wan.parse_row("4g/quic") == ("4g", "quic") and wan.parse_row("wifi") == ("wifi", "quic")
    assert wan.parse_row("4g/browser") == ("4g", "browser")
    assert wan.parse_row("bad/browser-ws") == ("bad", "browser-ws")
    with pytest.raises(ValueError, match="unknown profile 'moon'"):
        wan.parse_row("moon/tcp")
    with pytest.raises(ValueError, match="unknown link 'sctp'"):
        wan.parse_row("4g/sctp")
    lossy = wan.with_loss(PROFILES["4g"], 0.10)
    assert lossy.mean_loss == pytest.approx(0.10) and lossy.delay == PROFILES["4g"].delay


def test_a_browser_row_shows_what_the_page_measured_and_dashes_elsewhere(wan: ModuleType) -> None:
    row = wan.Row("4g", "browser", 40.0, stop=[60.0, 250.0], glass=[70.0, 90.0], seconds=1.0)
    row.trips, row.drive_seconds, row.reconnect = 1, 36.0, [300.0, 500.0]
    lines = wan.report([row], drive=True, amounts=wan.FULL, seconds=1.0)
    cells = [
        c.strip() for c in next(ln for ln in lines if ln.lstrip().startswith("4g/b")).split("|")
    ]
    assert cells[:5] == ["4g/browser", "40", "210.0", "30.0", "50.0"]  # stop p99, glass p50/p99
    assert cells[7] == "500.0"  # reconnect p99: heal -> the page's first pose
    assert cells[8] == "100.00"  # trips/h: 1 in 36 s of the page driving
    assert set(cells[5:7] + cells[9:]) == {"-"}  # late, unshown, silence, release
    line = (
        "4g/browser (1 s): 2 key presses, 2 frames watched in the page, 1 trips in 36 s of "
        "driving, 0 calls dropped while driving, 2 outages of 3 s"
    )
    assert line in lines
    # A browser row compares ways to the robot: the RESULT stays the default link's.
    fallback = wan.Row("4g", "browser-ws", 40.0, stop=[60.0], glass=[70.0], seconds=1.0)
    assert [r.link for r in wan.result_rows([row, fallback, wan.Row("4g", "quic")])] == ["quic"]
    cells = wan.report([fallback], drive=True, amounts=wan.FULL, seconds=1.0)
    cells = [c.strip() for c in next(ln for ln in cells if "4g/browser-ws |" in ln).split("|")]
    assert cells[5:7] == ["-", "-"]  # the page's figures only, as on WebTransport
