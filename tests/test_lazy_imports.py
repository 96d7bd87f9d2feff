"""``import telebot; telebot.connect`` stays light: PyAV and OpenCV load only when used."""

from __future__ import annotations

import subprocess
import sys

_PROBE = """
import sys, telebot
telebot.connect
heavy = sorted(name for name in ("av", "cv2") if name in sys.modules)
print(",".join(heavy) or "none")
"""


def test_connect_imports_neither_pyav_nor_opencv() -> None:
    # A fresh interpreter: this test process has long imported both.
    done = subprocess.run(
        [sys.executable, "-c", _PROBE],
        capture_output=True,
        text=True,
        timeout=120,  # a hang guard only: a loaded machine imports slowly
        check=True,
    )
    assert done.stdout.strip() == "none", done.stdout + done.stderr
