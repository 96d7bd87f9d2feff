"""The layers stay visible: sans-IO protocol code does no I/O, nothing imports upwards.

Layers, lowest first (a module may import from its own layer and those below)::

    errors < registry < config < channels.proto < identity < reasons, rights
           < router (certificates, router configs) < netem (network emulator)
           < channels.transports
           < channels (call, channel) < robot < safety < services < gateway < apps
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parent.parent / "src" / "telebot"

LAYERS = [
    "telebot.errors",
    "telebot.registry",
    "telebot.config",
    "telebot.channels.proto",
    "telebot.identity",
    "telebot.reasons",
    "telebot.rights",
    "telebot.router",
    "telebot.netem",
    "telebot.channels.transports",
    "telebot.channels",
    "telebot.robot",
    "telebot.safety",
    "telebot.services",
    "telebot.gateway",
    "telebot.apps",
]

SANS_IO_FORBIDDEN = {
    "asyncio",
    "zenoh",
    "time",
    "threading",
    "socket",
    "selectors",
    "trio",
    "anyio",
}


def module_name(path: Path) -> str:
    parts = path.relative_to(SRC.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer_of(module: str) -> int | None:
    """Index of the most specific layer ``module`` belongs to (None for telebot itself)."""
    best: int | None = None
    best_len = -1
    for index, prefix in enumerate(LAYERS):
        if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best_len:
            best, best_len = index, len(prefix)
    return best


def imports_of(path: Path) -> list[str]:
    """Every module imported anywhere in the file (inside functions and TYPE_CHECKING too)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found: list[str] = []
    package = (
        module_name(path).rsplit(".", 1)[0] if path.name != "__init__.py" else module_name(path)
    )
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                found.append(".".join([*base, node.module] if node.module else base))
            elif node.module:
                found.append(node.module)
    return found


SOURCES = sorted(SRC.rglob("*.py"))


def test_the_layer_map_covers_every_module() -> None:
    unmapped = [
        module_name(p)
        for p in SOURCES
        if module_name(p) != "telebot" and layer_of(module_name(p)) is None
    ]
    assert unmapped == []


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: module_name(p))
def test_nothing_imports_from_a_layer_above_it(path: Path) -> None:
    own = layer_of(module_name(path))
    if own is None:
        return  # telebot/__init__.py: the public face may re-export from any layer
    upward = []
    for imported in imports_of(path):
        if not imported.startswith("telebot"):
            continue
        target = layer_of(imported)
        if target is not None and target > own:
            upward.append(imported)
    assert upward == [], f"{module_name(path)} imports from layers above it: {upward}"


# Protocol logic, service protocols and the simulated robot (stepped by the caller's clock)
# are sans-IO.
SANS_IO_SOURCES = sorted(
    [
        *(SRC / "channels" / "proto").rglob("*.py"),
        *(SRC / "robot" / "sim").rglob("*.py"),
        *(SRC / "services").glob("*/wire.py"),
        SRC / "services" / "messages.py",
        SRC / "safety.py",
        SRC / "reasons.py",
        SRC / "rights.py",
        SRC / "router" / "acl.py",
        SRC / "netem" / "model.py",
        SRC / "gateway" / "core.py",
    ]
)


@pytest.mark.parametrize("path", SANS_IO_SOURCES, ids=lambda p: module_name(p))
def test_sans_io_modules_import_no_io_and_no_clock(path: Path) -> None:
    bad = [name for name in imports_of(path) if name.split(".")[0] in SANS_IO_FORBIDDEN]
    assert bad == [], f"{module_name(path)} is sans-IO but imports {bad}"


def test_the_checker_sees_imports_it_must_refuse(tmp_path: Path) -> None:
    # Guard against a checker that silently finds nothing.
    proto = SRC / "channels" / "proto" / "session.py"
    assert "telebot.channels.proto.frames" in imports_of(proto)
    assert layer_of("telebot.apps.demo") > layer_of("telebot.channels.call")  # type: ignore[operator]
    assert layer_of("telebot.channels.transports.zenoh") == LAYERS.index(
        "telebot.channels.transports"
    )


def test_import_telebot_does_not_import_zenoh() -> None:
    code = (
        "import sys, telebot, telebot.channels.call, telebot.channels.transports, telebot.apps.user_cli; "
        "from telebot.channels.transports import get_transport_class; get_transport_class('memory'); "
        "from telebot.robot import get_robot_class; get_robot_class('sim'); "
        "assert 'zenoh' not in sys.modules, 'zenoh imported'; "
        "get_transport_class('zenoh'); assert 'zenoh' in sys.modules"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr


# A ROS 2 robot is a zenoh network (rmw_zenoh): its adapter, and only it, speaks zenoh.
ZENOH_ROBOT_ADAPTERS = ("telebot.robot.ros2",)


def forbidden_in_robot(module: str) -> tuple[str, ...]:
    """Import prefixes ``module`` (inside ``telebot.robot``) must not use."""
    comms: tuple[str, ...] = ("telebot.channels", "telebot.identity")
    if module == ZENOH_ROBOT_ADAPTERS[0] or module.startswith(
        tuple(f"{name}." for name in ZENOH_ROBOT_ADAPTERS)
    ):
        return comms
    return (*comms, "zenoh")


def test_only_the_ros2_adapter_may_import_zenoh() -> None:
    # Guard the exemption: ros2 (and only ros2, not a look-alike) may use zenoh; no
    # robot module may use telebot's calls.
    assert "zenoh" not in forbidden_in_robot("telebot.robot.ros2.graph")
    assert "zenoh" not in forbidden_in_robot("telebot.robot.ros2")
    for module in ("telebot.robot.sim.stack", "telebot.robot.nav", "telebot.robot.ros2x"):
        assert "zenoh" in forbidden_in_robot(module)
    assert "telebot.channels" in forbidden_in_robot("telebot.robot.ros2.graph")


@pytest.mark.parametrize(
    "path", sorted((SRC / "robot").rglob("*.py")), ids=lambda p: module_name(p)
)
def test_the_robot_adapter_knows_nothing_of_calls_or_transports(path: Path) -> None:
    # The navigation stack is usable on its own (and by a ROS 2 adapter): no telebot comms
    # inside, and no zenoh outside robot/ros2/.
    module = module_name(path)
    bad = [name for name in imports_of(path) if name.startswith(forbidden_in_robot(module))]
    assert bad == [], f"{module} imports {bad}"


def test_no_project_file_reads_beside_the_checkout() -> None:
    """Tests, benchmarks, sources and scripts carry their own data: a user's clone has no
    shared folder beside it, so nothing of the project may look there."""
    root = SRC.parent.parent
    # Spelled in pieces so that this file does not name what it looks for.
    needles = ("../" + "shared", "shared" + "/data")
    offenders = []
    for folder in ("src", "tests", "bench", ".ci"):
        for path in (root / folder).rglob("*"):
            if not path.is_file() or path.suffix in {".pgm", ".mcap", ".zstd", ".pyc"}:
                continue
            text = path.read_text(errors="replace")
            if any(needle in text for needle in needles):
                offenders.append(str(path.relative_to(root)))
    makefile = (root / "Makefile").read_text()
    if any(needle in makefile for needle in needles):
        offenders.append("Makefile")
    assert offenders == [], (
        f"these files read beside the checkout, which users do not have: {offenders}"
    )


# What a client that only chats and reads poses must not load (issue 25): PyAV and OpenCV
# (video, audio, people), numpy (maps, plans, pictures) and YAML (map files).
HEAVY_FOR_A_CLIENT = ("av", "cv2", "numpy", "yaml")

_LIGHT_CLIENT = """
import asyncio, sys, tempfile
from pathlib import Path

import telebot
telebot.connect, telebot.RobotClient
import telebot.apps.user_cli, telebot.apps.user_client
from telebot.channels.call import RobotEndpoint, UserEndpoint
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.identity import ContactBook, KnownRobots, create_paired_homes
from telebot.services.client import RobotClient

HEAVY = {heavy!r}


async def main(base: Path) -> None:
    robot_id, user_id = create_paired_homes(base, "robot", "alice")
    hub = MemoryHub()
    async with (
        MemoryTransport(hub, "robot") as robot_transport,
        MemoryTransport(hub, "user") as user_transport,
        RobotEndpoint(robot_transport, robot_id, ContactBook.load(base / "robot")),
        UserEndpoint(user_transport, user_id, KnownRobots.load(base / "user")) as user,
    ):
        call = await user.call("robot")
        client = RobotClient(call)  # every default service opened on the call
        assert set(client.services.names()) >= {{"core", "video", "media", "people"}}
        client.services.tick(0.0)
        loaded = sorted(name for name in HEAVY if name in sys.modules)
        assert loaded == [], f"a client loaded {{loaded}}"
        # The guard sees a heavy import when one happens: video decoding loads PyAV.
        from telebot.errors import ProtocolError
        from telebot.services.codecs import VideoDecoder
        from telebot.services.media.wire import CODEC_H264
        try:
            VideoDecoder().decode(b"not h264", CODEC_H264)
        except ProtocolError:
            pass
        assert "av" in sys.modules, "decoding H.264 did not load PyAV"
        await client.aclose()
        await call.hangup()


with tempfile.TemporaryDirectory() as tmp:
    asyncio.run(main(Path(tmp)))
"""


def test_a_chatting_client_loads_no_video_audio_or_map_libraries() -> None:
    # `import telebot`, `telebot.connect`, the user CLI and a client on a call (its services
    # open) stay light: PyAV, OpenCV, numpy and YAML load when video, audio, people, a plan
    # or a map is used (`telebot-user send` would otherwise spend ~0.6 s importing them).
    code = _LIGHT_CLIENT.format(heavy=HEAVY_FOR_A_CLIENT)
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
