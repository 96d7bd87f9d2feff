"""The demo behind ``make demo``: the robot daemon and the web UI in a real call.

It creates a demo home (``.telebot-demo/`` in the current folder, kept between runs) with a
robot key ``guiabot``, a user key ``alice`` and alice in the robot's contacts as a driver;
starts ``telebot-robot run`` on the default 4000 × 4000 building map in its own process on
the embedded zenoh peer default (a loopback endpoint, no router); and starts the user
client, ``telebot-user ui guiabot``, printing the URL to open (map, click-to-goal, any key
stops, video, chat) until Ctrl-C. With no terminal (CI, a pipe) it checks that the page is
served, closes the UI and plays a short tour of the paper's Table I commands in the chat
client instead. At the end it stops the robot with SIGTERM and reports how fast it exited.
"""

from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

from telebot.identity import Role, create_paired_homes
from telebot.testing.net import free_port

__all__ = ["TOUR", "main"]

DEMO_HOME = Path(".telebot-demo")

#: What the demo types when nobody is at the keyboard.
TOUR = [
    "arm",
    "where?",
    "places",
    "battery",
    "fwd 1",
    "turn 90",
    "left",
    "usercam",
    "navcam",
    "goto reception",
    "where?",
    "getmap",
    "status",
]


def _homes() -> tuple[Path, Path]:
    robot_home, user_home = DEMO_HOME / "robot", DEMO_HOME / "user"
    if not (robot_home / "id_telebot").exists() or not (user_home / "id_telebot").exists():
        create_paired_homes(DEMO_HOME, "guiabot", "alice", role=Role.DRIVER)
    return robot_home, user_home


def _start_ui(user_home: Path, endpoint: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "telebot.apps.user_cli",
            "ui",
            "guiabot",
            "--home",
            str(user_home),
            "--connect",
            endpoint,
            "--port",
            str(free_port()),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )


def _ui_url(ui: subprocess.Popen[str]) -> str | None:
    """The URL the UI prints on its first line ("open URL in a browser ...")."""
    assert ui.stdout is not None
    words = ui.stdout.readline().split()
    return words[1] if len(words) > 1 and words[0] == "open" else None


def main() -> int:
    """Run the demo; exit 0 when every step worked."""
    robot_home, user_home = _homes()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    print(f"demo home {DEMO_HOME.resolve()}: robot guiabot, user alice (driver)")
    print(f"starting telebot-robot run (zenoh peer, listening on {endpoint}) on the building map")
    robot = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "telebot.apps.robot_cli",
            "run",
            "--home",
            str(robot_home),
            "--listen",
            endpoint,
            "--events",
            "--log-level",
            "error",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert robot.stdout is not None
        ready = json.loads(robot.stdout.readline() or "{}")
        if ready.get("event") != "ready":
            print("demo: error: the robot daemon did not start", file=sys.stderr)
            return 1
        print(f"robot ready on map {ready['map']}; places: {', '.join(ready['places'])}")
        user = [
            sys.executable,
            "-m",
            "telebot.apps.user_cli",
            "chat",
            "guiabot",
            "--home",
            str(user_home),
            "--connect",
            endpoint,
            "--map-dir",
            str(DEMO_HOME),
        ]
        chat: subprocess.CompletedProcess[str] = subprocess.CompletedProcess(user, 0)
        ui = _start_ui(user_home, endpoint)
        try:
            url = _ui_url(ui)
            if url is None:
                print("demo: error: the web UI did not start", file=sys.stderr)
                return 1
            if sys.stdin.isatty():
                print(f"web UI: open {url} in a browser ('re-arm', then click on the map)")
                print("Ctrl-C ends the demo")
                with contextlib.suppress(KeyboardInterrupt):
                    ui.wait()
            else:
                with urllib.request.urlopen(url, timeout=5) as page:
                    size = len(page.read())
                print(f"web UI served at {url} ({size} bytes); no terminal, so closing it")
        finally:
            if ui.poll() is None:
                ui.send_signal(signal.SIGTERM)
                ui.wait(timeout=5)
        if not sys.stdin.isatty():
            print("playing a tour of the chat commands")
            chat = subprocess.run(user, input="\n".join(TOUR) + "\n", text=True, check=False)
        started = time.perf_counter()
        robot.send_signal(signal.SIGTERM)
        robot.wait(timeout=5)
        print(
            f"robot process exited with {robot.returncode} "
            f"{time.perf_counter() - started:.2f} s after SIGTERM"
        )
        return 0 if chat.returncode == 0 and robot.returncode == 0 else 1
    finally:
        if robot.poll() is None:
            robot.kill()
            robot.wait()


if __name__ == "__main__":
    sys.exit(main())
