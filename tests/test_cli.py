"""The command lines as a user meets them: real processes, real files, one-line errors."""

from __future__ import annotations

import fcntl
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import ROBOT, Homes, write_config
from rig import GENEROUS_TIMEOUT
from telebot import __version__
from telebot.apps import robot_cli
from telebot.gateway.admission import ContactsAdmitter
from telebot.identity import ContactBook, Identity, KnownRobots, Role
from telebot.testing.net import free_port

ROOT = Path(__file__).resolve().parent.parent


def run(*args: str, timeout: float = 30) -> subprocess.CompletedProcess[str]:
    module = "telebot.apps.robot_cli" if args[0] == "robot" else "telebot.apps.user_cli"
    return subprocess.run(
        [sys.executable, "-m", module, *args[1:]], capture_output=True, text=True, timeout=timeout
    )


def one_line_error(result: subprocess.CompletedProcess[str], *needles: str) -> None:
    """Exit 2, exactly one line on stderr containing every needle, no traceback."""
    assert result.returncode == 2, (result.stdout, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


@pytest.mark.parametrize("side", ["robot", "user"])
def test_help_and_version(side: str) -> None:
    help_result = run(side, "--help")
    assert help_result.returncode == 0
    assert "keygen" in help_result.stdout
    version = run(side, "--version")
    assert version.returncode == 0
    assert version.stdout.strip() == f"telebot-{side} {__version__}"


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (("robot", "pubkey", "--bogus"), ["unrecognized arguments: --bogus"]),
        (("robot",), ["required: COMMAND"]),
        (
            ("robot", "contacts", "add", "bob", "not-a-key", "--home", "{home}"),
            ["bad public key for bob"],
        ),
        (
            ("robot", "contacts", "add", "bob", "x", "--role", "king", "--home", "{home}"),
            ["invalid choice: 'king'"],
        ),
        (
            ("robot", "contacts", "remove", "nobody", "--home", "{home}"),
            ["no contact named 'nobody'"],
        ),
        (("robot", "keygen", "bad/name", "--home", "{home}"), ["invalid name 'bad/name'"]),
        (
            ("robot", "run", "--robot", "tin-can", "--home", "{home}"),
            ["unknown robot 'tin-can'; known robots: ros2, sim"],
        ),
        (("user", "ping", "a*", "--home", "{home}"), ["invalid name 'a*'"]),
        (
            ("user", "ping", ROBOT, "--count", "0", "--home", "{home}"),
            ["--count", "must be at least 1"],
        ),
        (
            ("user", "ping", ROBOT, "--size", "40000", "--home", "{home}"),
            ["--size must be between 12 and 32768"],
        ),
        (("user", "ping", ROBOT, "--home", "{home}"), ["no key in", "keygen"]),
        (
            ("user", "known", "add", "guiabot", "AAAA", "--home", "{home}"),
            ["bad robot name or key"],
        ),
        (("user", "robots", "--wait", "-1", "--home", "{home}"), ["--wait", "must be positive"]),
    ],
)
def test_bad_input_gives_one_line_and_exit_2(
    tmp_path: Path, args: tuple[str, ...], needles: list[str]
) -> None:
    result = run(*(a.replace("{home}", str(tmp_path / "home")) for a in args))
    one_line_error(result, *needles)


def test_keygen_refuses_to_overwrite_a_key(tmp_path: Path) -> None:
    first = run("user", "keygen", "alice", "--home", str(tmp_path))
    assert first.returncode == 0
    assert first.stdout.strip().splitlines()[-1].startswith("telebot-x25519 ")
    one_line_error(run("user", "keygen", "alice", "--home", str(tmp_path)), "already exists")
    assert (
        run("user", "pubkey", "--home", str(tmp_path)).stdout
        == first.stdout.splitlines()[-1] + "\n"
    )


def test_contacts_and_known_robots_are_edited_on_disk(tmp_path: Path) -> None:
    robot_home, user_home = tmp_path / "robot", tmp_path / "user"
    robot_pub = run("robot", "keygen", "guiabot", "--home", str(robot_home)).stdout.splitlines()[-1]
    user_pub = run("user", "keygen", "alice", "--home", str(user_home)).stdout.splitlines()[-1]
    assert (
        run(
            "robot",
            "contacts",
            "add",
            "alice",
            user_pub,
            "--role",
            "driver",
            "--home",
            str(robot_home),
        ).returncode
        == 0
    )
    assert (
        run("user", "known", "add", "guiabot", robot_pub, "--home", str(user_home)).returncode == 0
    )
    contact = ContactBook.load(robot_home).by_key(
        __import__("telebot.identity").identity.parse_public_key(user_pub)
    )
    assert contact is not None and contact.name == "alice" and contact.role.value == "driver"
    assert KnownRobots.load(user_home).names() == ["guiabot"]
    listing = run("robot", "contacts", "list", "--home", str(robot_home))
    assert listing.stdout.startswith("alice\tdriver\t")
    assert run("robot", "contacts", "remove", "alice", "--home", str(robot_home)).returncode == 0
    assert len(ContactBook.load(robot_home)) == 0


def test_invite_refuses_a_name_that_is_a_contact_unless_replace(tmp_path: Path) -> None:
    home = str(tmp_path / "robot")
    run("robot", "keygen", "guiabot", "--home", home)
    alice = Identity.generate("alice")
    assert (
        run("robot", "contacts", "add", "alice", alice.public_line(), "--home", home).returncode
        == 0
    )
    invite = ("robot", "invite", "alice", "--url", "https://robot:8443/", "--no-qr", "--home", home)
    one_line_error(run(*invite), "alice is a contact already", "--replace")
    assert not (tmp_path / "robot" / "invites.json").exists()  # nothing written
    replacing = run(*invite, "--replace", "--role", "driver")
    assert replacing.returncode == 0, replacing.stderr
    token = replacing.stdout.split("#invite=", 1)[1].split("&", 1)[0]
    # The invite written with --replace may replace alice (her key and role) when redeemed.
    browser = Identity.generate("alice")
    robot_book = ContactBook.load(tmp_path / "robot")
    ContactsAdmitter(robot_book, tmp_path / "robot").redeem(
        token, "alice", browser.public_key, time.time()
    )
    contact = ContactBook.load(tmp_path / "robot").by_key(browser.public_key)
    assert contact is not None and contact.name == "alice" and contact.role is Role.DRIVER


@pytest.mark.parametrize("action", ["add", "remove"])
def test_contacts_add_and_remove_hold_the_lock_an_invite_redemption_holds(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, action: str
) -> None:
    home = tmp_path / "robot"
    bob = Identity.generate("bob")
    book = ContactBook.load(home)
    book.add("bob", bob.public_key, Role.OBSERVER)
    book.save()
    held: list[bool] = []

    def lock_is_held() -> None:  # another open file cannot take it while the command holds it
        fd = os.open(home / "invites.lock", os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            held.append(False)
        except BlockingIOError:
            held.append(True)
        finally:
            os.close(fd)

    load, save = ContactBook.load, ContactBook.save

    def probed_load(cls: type[ContactBook], where: Path) -> ContactBook:
        lock_is_held()
        return load(where)

    def probed_save(self: ContactBook) -> None:
        lock_is_held()
        save(self)

    monkeypatch.setattr(ContactBook, "load", classmethod(probed_load))
    monkeypatch.setattr(ContactBook, "save", probed_save)
    args = (
        ["add", "carol", Identity.generate("carol").public_line()]
        if action == "add"
        else [
            "remove",
            "bob",
        ]
    )
    assert robot_cli.main(["contacts", *args, "--home", str(home)]) == 0
    assert held == [True, True]  # read and written back under the lock: no lost update
    monkeypatch.undo()
    names = [c.name for c in ContactBook.load(home)]
    assert names == (["bob", "carol"] if action == "add" else [])


@pytest.mark.parametrize(
    ("config", "needles"),
    [
        ("[transport]\nkidn = 'zenoh'\n", ["transport.kidn: unknown key", "bad.toml"]),
        ("[call]\ntimeout = -1\n", ["call.timeout", "greater than 0"]),
        ("[transport.zenoh]\nmode = 'router'\n", ["transport.zenoh.mode"]),
        ("not toml at all [", ["invalid TOML"]),
        ("[transport]\nkind = 'smoke'\n", ["unknown transport 'smoke'", "memory", "zenoh"]),
        ("[transport.zenoh.options]\n'bogus/key' = 1\n", ["bogus/key"]),
        ("[robot]\nkidn = 'sim'\n", ["robot.kidn: unknown key"]),
        ("[ros2]\nlease = 0\n", ["ros2.lease", "greater than or equal to 0.1"]),
    ],
)
def test_bad_config_gives_one_line_and_exit_2(
    homes: Homes, tmp_path: Path, config: str, needles: list[str]
) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(config)
    result = run("robot", "echo", "--home", str(homes.robot_home), "--config", str(path))
    one_line_error(result, *needles)


def test_a_robot_kind_in_the_config_is_checked_before_anything_starts(
    homes: Homes, tmp_path: Path
) -> None:
    path = tmp_path / "robot.toml"
    path.write_text("[robot]\nkind = 'tin-can'\n")
    result = run("robot", "run", "--home", str(homes.robot_home), "--config", str(path))
    one_line_error(result, "unknown robot 'tin-can'", "known robots: ros2, sim")
    assert "--robot NAME" in run("robot", "run", "--help").stdout


def test_shipped_configs_are_valid_and_show_the_defaults() -> None:
    from telebot.config import AppConfig, RobotConfig, load_toml

    robot = load_toml(ROOT / "configs" / "robot.toml", RobotConfig)
    user = load_toml(ROOT / "configs" / "user.toml", AppConfig)
    # The files say "the values shown are the defaults": keep them true.
    assert robot == RobotConfig()
    assert user == AppConfig()
    assert robot.call.timeout <= 0.5 and robot.sim.max_linear_speed == 0.5
    assert robot.robot.kind == "sim"


@pytest.mark.zenoh
def test_robots_lists_and_ping_measures_through_a_real_robot(homes: Homes, tmp_path: Path) -> None:
    port = free_port()
    # Not about drop timing: a generous call timeout (tests/rig.py).
    config = str(write_config(tmp_path / "loopback.toml", timeout=GENEROUS_TIMEOUT))
    robot = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "telebot.apps.robot_cli",
            "echo",
            "--home",
            str(homes.robot_home),
            "--config",
            config,
            "--listen",
            f"tcp/127.0.0.1:{port}",
            "--events",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert robot.stdout is not None
        assert '"ready"' in robot.stdout.readline()
        connect = [
            "--home",
            str(homes.user_home),
            "--config",
            config,
            "--connect",
            f"tcp/127.0.0.1:{port}",
        ]
        robots = run("user", "robots", "--wait", "1", *connect)
        assert robots.returncode == 0
        assert robots.stdout.startswith(f"{ROBOT}\tknown\t")
        ping = run("user", "ping", ROBOT, "--count", "5", "--interval", "0.01", *connect)
        assert ping.returncode == 0, ping.stderr
        assert "5 sent, 5 received (0.0% loss)" in ping.stdout
        one_line_error(run("user", "ping", "nobot", *connect), "nobot is not a known robot")
    finally:
        robot.terminate()
        robot.wait(timeout=10)
        assert robot.stdout is not None
        robot.stdout.close()
    assert robot.returncode == 0


@pytest.mark.zenoh
def test_ping_to_an_offline_robot_says_so(homes: Homes, tmp_path: Path) -> None:
    config = str(write_config(tmp_path / "loopback.toml"))
    result = run(
        "user",
        "ping",
        ROBOT,
        "--timeout",
        "1",
        "--home",
        str(homes.user_home),
        "--config",
        config,
        "--listen",
        f"tcp/127.0.0.1:{free_port()}",
    )
    one_line_error(result, f"robot {ROBOT} did not answer within 1 s", "is it online?")


# A command whose transport left a thread inside zenoh (closing it took longer than its
# timeout, or the thread was still letting go of the session): exiting the interpreter
# under it aborted the process (SIGABRT) instead of exiting with the command's code.
_EXIT_SCRIPT = """
import sys, threading, time
from telebot.apps.common import run

done = []

def closing(seconds):
    time.sleep(seconds)
    done.append(seconds)

async def main():
    threading.Thread(target=closing, args=({seconds},), name="zenoh-close", daemon=True).start()
    print("ran", flush=True)
    return 2

code = run("prog", main, "warning")
print("finished" if done else "left behind", flush=True)
sys.exit(code)
"""


def test_a_command_waits_for_zenoh_threads_before_the_interpreter_exits() -> None:
    script = _EXIT_SCRIPT.format(seconds=0.5)
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert result.returncode == 2, result.stderr
    assert result.stdout.splitlines() == ["ran", "finished"]


def test_a_thread_stuck_in_zenoh_does_not_keep_the_command_or_abort_it() -> None:
    script = _EXIT_SCRIPT.format(seconds=3600)
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    # The code, what was printed, one warning; no finalization under the stuck thread.
    assert result.returncode == 2, result.stderr
    assert result.stdout.splitlines() == ["ran"]
    assert "zenoh did not finish closing" in result.stderr
