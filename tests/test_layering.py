"""The layers stay visible: sans-IO protocol code does no I/O, nothing imports upwards, and
no module imports itself back through others (no import cycle, ``TYPE_CHECKING`` and
function-level imports included).

Layers, lowest first (a module may import from its own layer and those below)::

    errors < registry < config < channels.proto < identity < reasons, rights
           < router (certificates, router configs) < netem (network emulator)
           < channels.transports
           < channels (call, channel) < robot, rosmsg (ROS message encoding) < safety
           < services < followers < gateway < testing (contract suites) < apps

Sub-layers inside a layer (see :data:`SUBLAYERS`): in ``services/``, base.py < a service's
``wire.py`` < its stream machinery (``stream.py``, ``sender.py``, ``receiver.py``,
``audio.py``) < its ``robot.py`` and ``user.py`` < ``registry.py`` (names only) < the hosts
(``robot.py``, ``client.py``); ROS message encoding (``telebot.rosmsg``) < the robot adapters
(``telebot.robot.sim``, ``telebot.robot.ros2``), and the simulator never imports the ROS 2
adapter.
"""

from __future__ import annotations

import ast
import itertools
import re
import subprocess
import sys
from collections import deque
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parent.parent / "src" / "telebot"

# One entry per layer: a package prefix, or a tuple of prefixes that share a layer.
LAYERS: list[str | tuple[str, ...]] = [
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
    ("telebot.robot", "telebot.rosmsg"),
    "telebot.safety",
    "telebot.services",
    "telebot.followers",
    "telebot.gateway",
    "telebot.testing",
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


def module_name(path: Path, root: Path = SRC) -> str:
    """The dotted name of ``path``, a file of the package folder ``root``."""
    parts = path.relative_to(root.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer_of(module: str) -> int | None:
    """Index of the most specific layer ``module`` belongs to (None for telebot itself)."""
    best: int | None = None
    best_len = -1
    for index, entry in enumerate(LAYERS):
        for prefix in (entry,) if isinstance(entry, str) else entry:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best_len:
                best, best_len = index, len(prefix)
    return best


def _import_statements(path: Path, root: Path) -> list[tuple[int, str, list[str]]]:
    """(line, module, names) of every import anywhere in the file (inside functions and
    ``TYPE_CHECKING`` too), relative imports resolved; names are those of ``from m import
    names`` (empty for ``import m``)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found: list[tuple[int, str, list[str]]] = []
    package = module_name(path, root)
    if path.name != "__init__.py":
        package = package.rsplit(".", 1)[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name, []) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            names = [alias.name for alias in node.names]
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                found.append(
                    (node.lineno, ".".join([*base, node.module] if node.module else base), names)
                )
            elif node.module:
                found.append((node.lineno, node.module, names))
    return found


def imports_of(path: Path) -> list[str]:
    """Every module imported anywhere in the file (inside functions and TYPE_CHECKING too)."""
    return [module for _, module, _ in _import_statements(path, SRC)]


def import_graph(root: Path) -> dict[str, dict[str, int]]:
    """Module -> {module of the same package it imports: line of the first such import}.

    Every import counts (module level, ``if TYPE_CHECKING:``, inside functions): each of
    them is a dependency a reader must follow. ``import a.b`` is an import of ``a.b``, and
    ``from a import b`` one of ``a.b`` when that is a module, else of ``a``. A module's own
    name (a package's ``__init__`` importing a name it defines) is no edge.
    """
    files = {module_name(path, root): path for path in sorted(root.rglob("*.py"))}
    graph: dict[str, dict[str, int]] = {}
    for module, path in files.items():
        edges: dict[str, int] = {}
        for line, imported, names in _import_statements(path, root):
            targets = [f"{imported}.{name}" for name in names if f"{imported}.{name}" in files]
            if len(targets) < len(names) or not names:
                # Names that are not submodules, or a plain `import a.b`: the module itself,
                # or its closest enclosing module of the package.
                while imported and imported not in files:
                    imported = imported.rpartition(".")[0]
                if imported:
                    targets.append(imported)
            for target in targets:
                if target != module:
                    edges.setdefault(target, line)
        graph[module] = edges
    return graph


def _strongly_connected(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """Tarjan's strongly connected components of ``graph`` (each sorted)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for succ in graph.get(node, {}):
            if succ not in index:
                visit(succ)
                low[node] = min(low[node], low[succ])
            elif succ in on_stack:
                low[node] = min(low[node], index[succ])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            components.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return components


def import_cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """Cycles of ``graph`` as ``[a, b, ..., a]``: shortest ones, enough of them that every
    import taking part in a cycle is in one (listing every cycle could be exponential)."""
    cycles: list[list[str]] = []
    for component in _strongly_connected(graph):
        members = set(component)
        inner = sorted((a, b) for a in component for b in graph[a] if b in members)
        covered: set[tuple[str, str]] = set()
        for first, second in inner:
            if (first, second) in covered or len(members) < 2:
                continue
            # Shortest way back from `second` to `first` inside the component.
            came_from: dict[str, str] = {second: second}
            queue = deque([second])
            while first not in came_from:
                node = queue.popleft()
                for succ in sorted(graph[node]):
                    if succ in members and succ not in came_from:
                        came_from[succ] = node
                        queue.append(succ)
            path = [first]
            while path[-1] != second:
                path.append(came_from[path[-1]])
            cycle = [first, *reversed(path[1:])]
            covered.update(zip(cycle, [*cycle[1:], first], strict=True))
            start = cycle.index(min(cycle))
            cycle = cycle[start:] + cycle[:start]
            cycles.append([*cycle, cycle[0]])
    return cycles


def describe_cycles(graph: dict[str, dict[str, int]], cycles: list[list[str]]) -> str:
    """One line per cycle, ``a → b → … → a``, and where each of its imports is."""
    lines = []
    for cycle in cycles:
        lines.append("  " + " → ".join(cycle))
        where = ", ".join(f"{a} line {graph[a][b]}" for a, b in itertools.pairwise(cycle))
        lines.append(f"      (imports at {where})")
    return "\n".join(lines)


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


def test_no_import_cycles() -> None:
    # A cycle hides the order in which a reader (and Python) must take the modules, and a
    # typing-only import on the way back is still a cycle of ideas.
    graph = import_graph(SRC)
    cycles = import_cycles(graph)
    assert cycles == [], (
        f"{len(cycles)} import cycle(s) in src/ (a → b means a imports b; TYPE_CHECKING and "
        f"function-level imports count):\n{describe_cycles(graph, cycles)}"
    )


def test_the_cycle_finder_sees_typing_and_late_imports(tmp_path: Path) -> None:
    # Guard against a finder that silently finds nothing: a tiny package whose cycles close
    # through `if TYPE_CHECKING:`, a function body, `import a.b` and `from pkg import sub`.
    package = tmp_path / "pkg"
    (package / "sub").mkdir(parents=True)
    files = {
        "__init__.py": "",
        "a.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.b import B\n",
        "b.py": "from .c import C\n",
        "c.py": "def late():\n    from . import a\n",
        "d.py": "import pkg.sub.e\n",
        "sub/__init__.py": "",
        "sub/e.py": "from pkg import d\n",
        "f.py": "from pkg.sub import e\nimport os\n",
    }
    for name, text in files.items():
        (package / name).write_text(text)
    graph = import_graph(package)
    assert graph["pkg.a"] == {"pkg.b": 3} and graph["pkg.c"] == {"pkg.a": 2}
    assert import_cycles(graph) == [
        ["pkg.a", "pkg.b", "pkg.c", "pkg.a"],
        ["pkg.d", "pkg.sub.e", "pkg.d"],
    ]
    assert "pkg.a → pkg.b → pkg.c → pkg.a" in describe_cycles(graph, import_cycles(graph))
    # Acyclic once the typing import goes and e no longer imports d back.
    (package / "a.py").write_text("import os\n")
    (package / "sub" / "e.py").write_text("from pkg.sub import __name__ as n\n")
    assert import_cycles(import_graph(package)) == []


# Sub-layers, lowest first: a module matching a rank's pattern may not import one matching a
# higher rank's; ``False`` after a rank's patterns forbids imports between its own members
# too. Patterns name the target layout: a rule whose modules do not exist checks nothing.
SUBLAYERS: dict[str, list[tuple[tuple[str, ...], bool]]] = {
    "services": [
        ((r"telebot\.services\.base",), True),
        # A service's wire format may use another's (shared message types).
        ((r"telebot\.services\.\w+\.wire",), True),
        # A service's stream machinery (video's sender and receiver, media's audio codecs)
        # sits between the wire formats and the sides: another service may reuse it (the
        # user's camera is video's sender run the other way).
        ((r"telebot\.services\.\w+\.(stream|sender|receiver|audio)",), True),
        # A service side uses base.py, wire formats and lower layers: never another side.
        ((r"telebot\.services\.\w+\.(robot|user)",), False),
        # The registry names every side as a "module:attribute" string, loaded when a host
        # starts: it imports only base.py, and the hosts take their defaults from it.
        ((r"telebot\.services\.registry",), True),
        ((r"telebot\.services\.robot", r"telebot\.services\.client"), True),
    ],
    "robot adapters": [
        ((r"telebot\.rosmsg(\..+)?",), True),
        ((r"telebot\.robot\.sim(\..+)?",), True),
        # The ROS 2 adapter may reuse the simulator (telebot-sim serves it over ROS 2);
        # the simulator never needs the ROS 2 adapter.
        ((r"telebot\.robot\.ros2(\..+)?",), True),
    ],
}


def sublayer_of(rules: list[tuple[tuple[str, ...], bool]], module: str) -> int | None:
    """The rank of ``module`` in ``rules`` (None when no pattern matches)."""
    for rank, (patterns, _) in enumerate(rules):
        if any(re.fullmatch(pattern, module) for pattern in patterns):
            return rank
    return None


def sublayer_violations(
    graph: dict[str, dict[str, int]], rules: list[tuple[tuple[str, ...], bool]]
) -> list[str]:
    """``a line N imports b`` for every import from a rank to a higher one (or to its own
    rank where that is closed)."""
    found = []
    for module, edges in sorted(graph.items()):
        own = sublayer_of(rules, module)
        if own is None:
            continue
        for imported, line in sorted(edges.items()):
            target = sublayer_of(rules, imported)
            if target is not None and (target > own or (target == own and not rules[own][1])):
                found.append(f"{module} line {line} imports {imported}")
    return found


def test_the_sublayer_patterns_name_the_target_layout() -> None:
    services, robots = SUBLAYERS["services"], SUBLAYERS["robot adapters"]
    ranks = {
        name: sublayer_of(services, name)
        for name in (
            "telebot.services.base",
            "telebot.services.chat.wire",
            "telebot.services.video.sender",
            "telebot.services.chat.robot",
            "telebot.services.people.user",
            "telebot.services.robot",
            "telebot.services.client",
            "telebot.services.registry",
            "telebot.services.chat",
            "telebot.services.codecs",
        )
    }
    assert list(ranks.values()) == [0, 1, 2, 3, 3, 5, 5, 4, None, None]
    assert [sublayer_of(robots, name) for name in ("telebot.rosmsg", "telebot.rosmsg.cdr")] == [
        0,
        0,
    ]
    assert sublayer_of(robots, "telebot.robot.sim.stack") == 1
    assert sublayer_of(robots, "telebot.robot.ros2") == 2
    assert sublayer_of(robots, "telebot.robot.nav") is None
    graph = {
        "telebot.services.chat.wire": {"telebot.services.people.wire": 1},
        "telebot.services.chat.robot": {
            "telebot.services.chat.user": 2,
            "telebot.services.base": 3,
        },
        "telebot.services.base": {"telebot.services.client": 4},
        "telebot.robot.sim.stack": {"telebot.robot.ros2.types": 5, "telebot.rosmsg": 6},
    }
    assert sublayer_violations(graph, services) == [
        "telebot.services.base line 4 imports telebot.services.client",
        "telebot.services.chat.robot line 2 imports telebot.services.chat.user",
    ]
    assert sublayer_violations(graph, robots) == [
        "telebot.robot.sim.stack line 5 imports telebot.robot.ros2.types"
    ]


@pytest.mark.parametrize("name", sorted(SUBLAYERS))
def test_sublayers_import_only_downwards(name: str) -> None:
    bad = sublayer_violations(import_graph(SRC), SUBLAYERS[name])
    assert bad == [], f"{name}: imports from a sub-layer above (or beside) their own:\n  " + (
        "\n  ".join(bad)
    )


# Protocol logic, service protocols and the simulated robot (stepped by the caller's clock)
# are sans-IO.
SANS_IO_SOURCES = sorted(
    [
        *(SRC / "channels" / "proto").rglob("*.py"),
        *(SRC / "robot" / "sim").rglob("*.py"),
        *(SRC / "services").glob("*/wire.py"),
        SRC / "services" / "messages.py",
        # rosmsg.types guards its type cache with a lock (both adapters' threads use it) and
        # rosmsg.topics stamps messages with the wall clock: only the message encoding is pure.
        SRC / "rosmsg" / "messages.py",
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
