"""The browser client's protocol core (web/src, JavaScript) calls a real Python robot.

``node web/test/interop/client.mjs`` runs the JS user side; its link speaks newline-delimited
JSON over stdin/stdout (payloads in base64) to this process, which relays it to an in-memory
hub where :func:`rig.robot_on_hub` runs the robot (simulator, supervisor, RobotServer). No
gateway is involved: this checks the two implementations of docs/protocol.md §2–§8 against
each other, in both cipher suites and through a RETRY.

The ``session`` scenario runs the JS services (web/src/session.js RobotSession, connecting
with ``Endpoint.call``) against the same robot, as a page would use them: §19 page messages
in, the messages it emits out. The relay between node and the hub can lose a seeded share of
the frames each way (CONTROL included or not) or cut them all (:class:`Relay`).

Node is required wherever ``make test`` runs: without it these tests fail, saying so.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import functools
import io
import json
import math
import random
import shutil
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from PIL import Image

import telebot.services.robot as robot_module
from conftest import wait_until
from rig import GENEROUS_TIMEOUT, ROBOT, SLACK, USER, robot_on_hub
from telebot.channels.call import Call, RobotEndpoint
from telebot.channels.transports.base import Lane, Presence, Sample, Subscription
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import CipherChoice
from telebot.identity import Identity, encode_key
from telebot.robot.nav import Velocity
from telebot.robot.sim.stack import SimNavStack
from telebot.services.mapxfer.robot import MapService
from telebot.services.robot import RobotServer
from telebot.services.safety.robot import SafetyDriver
from telebot.services.video.wire import VideoSettings

ROOT = Path(__file__).resolve().parent.parent
CLIENT = ROOT / "web" / "test" / "interop" / "client.mjs"
#: Seconds the whole JS run may take on a loaded machine (it normally takes about one).
RUN_DEADLINE = 60.0


def node_binary() -> str:
    """The node executable; the test fails (never skips) without it or its packages."""
    node = shutil.which("node")
    if node is None:
        pytest.fail("node is not installed: the JS tests need Node.js 20+ (apt install nodejs npm)")
    if not (ROOT / "node_modules" / "@noble" / "curves").is_dir():
        pytest.fail("node_modules is missing: run 'npm ci' at the repository root")
    return node


@dataclass
class Relay:
    """What this process does to the frames it relays between the JS link and the hub.

    ``loss``: the share of frames dropped, each way, drawn from a seeded random stream;
    ``control``: whether CONTROL frames (HELLO/WELCOME, heartbeats, HANGUP: ``pub`` on the
    control lane, samples on any key but a call's ``/data``) are dropped too; ``cut``: drop
    every frame both ways (presence, subscriptions and tokens are untouched: the call must
    be dropped by its timeout, as on a link that went silent).
    """

    loss: float = 0.0
    control: bool = True
    cut: bool = False
    seed: int = 24
    dropped: int = 0
    passed: int = 0
    rng: random.Random = field(init=False)

    def __post_init__(self) -> None:
        self.rng = random.Random(self.seed)

    def passes(self, control: bool) -> bool:
        """Whether one frame goes through (counted either way)."""
        lose = self.rng.random() < self.loss and (self.control or not control)
        if self.cut or lose:
            self.dropped += 1
            return False
        self.passed += 1
        return True


class JsClient:
    """The JS client in a node process, its link relayed to ``hub`` through a :class:`Relay`.

    ``results`` are its ``result`` lines, ``emitted`` the page messages of a session
    scenario (in order); :meth:`page` sends it a §19 page message.
    """

    def __init__(self, hub: MemoryHub, options: dict[str, Any], relay: Relay | None = None):
        self.hub = hub
        self.options = options
        self.relay = relay if relay is not None else Relay()
        self.results: list[dict[str, Any]] = []
        self.emitted: list[dict[str, Any]] = []
        self.code: int | None = None
        self.stderr = ""
        self._process: asyncio.subprocess.Process | None = None
        self._handles: dict[int, Subscription | Presence] = {}

    def _write(self, message: dict[str, Any]) -> None:
        assert self._process is not None and self._process.stdin is not None
        if not self._process.stdin.is_closing():
            self._process.stdin.write((json.dumps(message) + "\n").encode())

    def page(self, msg: dict[str, Any]) -> None:
        """Hand the session one page → client message (§19)."""
        self._write({"op": "page", "msg": msg})

    def close_session(self) -> None:
        """Ask the session scenario to hang up and exit."""
        self._write({"op": "close"})

    def of_type(self, kind: str) -> list[dict[str, Any]]:
        """The page messages of ``type`` emitted so far."""
        return [m for m in self.emitted if m.get("type") == kind]

    def _on_samples(self, sub_id: int) -> Any:
        def deliver(samples: Any) -> None:
            for sample in samples:
                assert isinstance(sample, Sample)
                if not self.relay.passes(control=not sample.key.endswith("/data")):
                    continue
                data = base64.b64encode(sample.payload).decode()
                self._write({"op": "sample", "id": sub_id, "key": sample.key, "data": data})

        return deliver

    def _on_presence(self, watch_id: int) -> Any:
        return lambda key, alive: self._write(
            {"op": "alive", "id": watch_id, "key": key, "alive": alive}
        )

    async def run(self) -> list[dict[str, Any]]:
        """Run the client to its end; its result lines (it must exit 0)."""
        self._process = process = await asyncio.create_subprocess_exec(
            node_binary(),
            str(CLIENT),
            json.dumps(self.options),
            cwd=ROOT,
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
            limit=16 * 1024 * 1024,  # a line carries a map PNG
        )
        assert process.stdout is not None and process.stderr is not None
        async with MemoryTransport(self.hub, "browser") as transport:
            try:
                while line := await process.stdout.readline():
                    self._handle(transport, json.loads(line))
                self.code = await process.wait()
            finally:
                if process.returncode is None:
                    process.kill()
                    await process.wait()
                for handle in self._handles.values():
                    handle.close()
        self.stderr = (await process.stderr.read()).decode(errors="replace")
        assert self.code == 0, (
            f"the JS client failed ({self.code}): {self.results} {self.stderr[-2000:]}"
        )
        return self.results

    def _handle(self, transport: MemoryTransport, message: dict[str, Any]) -> None:
        op = message["op"]
        if op == "sub":
            self._handles[message["id"]] = transport.subscribe(
                message["key"], self._on_samples(message["id"])
            )
        elif op == "watch":
            self._handles[message["id"]] = transport.watch_presence(
                message["key"], self._on_presence(message["id"])
            )
        elif op == "token":
            self._handles[message["id"]] = transport.declare_presence(message["key"])
        elif op in ("unsub", "unwatch", "untoken"):
            self._handles.pop(message["id"]).close()
        elif op == "pub":
            if self.relay.passes(control=message["lane"] == "control"):
                publisher = transport.publisher(message["key"], Lane(message["lane"]))
                publisher.put(base64.b64decode(message["data"]))
                publisher.close()
        elif op == "result":
            self.results.append(message)
        elif op == "emit":
            self.emitted.append(message["msg"])


async def run_client(hub: MemoryHub, options: dict[str, Any]) -> list[dict[str, Any]]:
    """Run the JS client with ``options``, relaying its link to ``hub``; its result lines."""
    async with asyncio.timeout(RUN_DEADLINE):
        return await JsClient(hub, options).run()


@pytest.mark.parametrize(
    ("suites", "cipher", "expected"),
    [
        (["aesgcm"], "aesgcm", "aesgcm"),
        (["chachapoly"], "chachapoly", "chachapoly"),
        # The JS client prefers AESGCM, the robot takes only ChaChaPoly: RETRY, then ChaChaPoly.
        (["aesgcm", "chachapoly"], "chachapoly", "chachapoly"),
    ],
)
async def test_js_client_calls_python_robot(
    tmp_path: Path, suites: list[str], cipher: CipherChoice, expected: str
) -> None:
    hub = MemoryHub(seed=24)
    async with robot_on_hub(tmp_path, hub, timeout=GENEROUS_TIMEOUT, cipher=cipher) as (
        _nav,
        _safety,
        _server,
        endpoint,
    ):
        user = Identity.load(tmp_path / "user")
        robot = Identity.load(tmp_path / "robot")
        seen: list[Call] = []
        watcher = asyncio.create_task(_track_calls(endpoint, seen))
        try:
            results = await run_client(
                hub,
                {
                    "scenario": "chat",
                    "name": USER,
                    "privateKey": encode_key(user.private_key),
                    "robot": ROBOT,
                    "robotKey": encode_key(robot.public_key),
                    "suites": suites,
                    "timeout": GENEROUS_TIMEOUT,
                },
            )
        finally:
            watcher.cancel()
        called, done = results
        assert called["event"] == "called", results
        assert called["suite"] == expected
        assert called["role"] == "driver"
        assert done["event"] == "done", results
        reply = done["reply"]
        assert reply["id"] == 1 and reply["final"] and reply["ok"], reply
        assert reply["text"].startswith("x ") and "heading" in reply["text"], reply
        assert done["stats"]["rtt"] is not None and 0 <= done["stats"]["rtt"] < 60
        assert done["stats"]["received"] > 0
        assert done["end"] == {"kind": "hung_up", "detail": "bye", "byPeer": False}
        # The robot's side: the same call, in the same suite, hung up by the user.
        assert [c.id for c in seen] == [called["id"]]
        robot_call = seen[0]
        assert robot_call.suite.label == expected
        await wait_until(lambda: robot_call.end is not None)
        assert robot_call.end is not None
        assert (robot_call.end.kind, robot_call.end.by_peer, robot_call.end.detail) == (
            "hung_up",
            True,
            "bye",
        )


async def test_js_client_wrong_robot_key_is_key_mismatch(tmp_path: Path) -> None:
    hub = MemoryHub(seed=24)
    async with robot_on_hub(tmp_path, hub, timeout=GENEROUS_TIMEOUT) as (_n, _s, _r, endpoint):
        user = Identity.load(tmp_path / "user")
        robot = Identity.load(tmp_path / "robot")
        results = await run_client(
            hub,
            {
                "scenario": "wrongkey",
                "name": USER,
                "privateKey": encode_key(user.private_key),
                "robot": ROBOT,
                "suites": ["aesgcm", "chachapoly"],
            },
        )
        (result,) = results
        assert result["event"] == "error", result
        assert result["name"] == "KeyMismatch"
        assert result["message"].startswith(
            f"KEY MISMATCH: robot {ROBOT} is online with key {encode_key(robot.public_key)} "
            "but known_robots has "
        )
        assert endpoint.calls == []


async def _track_calls(endpoint: RobotEndpoint, seen: list[Call]) -> None:
    """Note every call the robot endpoint has, as it comes (the test checks its end)."""
    while True:
        for call in endpoint.calls:
            if call not in seen:
                seen.append(call)
        await asyncio.sleep(0.005)


# -- the JS services (web/src/session.js RobotSession) against the Python robot -------------

#: The JS session's page sees its first picture of this size (the rig's synthetic camera).
VIDEO = VideoSettings(width=160, height=120, max_fps=10, quality=60, min_quality=30)
#: Seconds for what has to happen over a lossy link on a loaded machine.
LONG = 45.0 + SLACK


@contextlib.asynccontextmanager
async def js_session(
    tmp_path: Path, relay: Relay
) -> AsyncIterator[tuple[JsClient, SimNavStack, SafetyDriver, RobotServer, RobotEndpoint]]:
    """A robot (simulator, synthetic camera) on a memory hub, and the JS RobotSession of its
    driver started on it through ``relay``; closed (hung up) at the end."""
    hub = MemoryHub(seed=24)
    async with robot_on_hub(tmp_path, hub, timeout=GENEROUS_TIMEOUT, video=VIDEO) as (
        nav,
        safety,
        server,
        endpoint,
    ):
        user = Identity.load(tmp_path / "user")
        robot = Identity.load(tmp_path / "robot")
        options = {
            "scenario": "session",
            "name": USER,
            "privateKey": encode_key(user.private_key),
            "robot": ROBOT,
            "robotKey": encode_key(robot.public_key),
            "suites": ["aesgcm", "chachapoly"],
            "timeout": GENEROUS_TIMEOUT,
        }
        client = JsClient(hub, options, relay)
        runner = asyncio.create_task(client.run())
        try:
            await wait_until(lambda: bool(client.results) or runner.done(), LONG)
            assert client.results[:1] == [{"op": "result", "event": "started", "role": "driver"}]
            yield client, nav, safety, server, endpoint
            relay.cut = False
            client.close_session()
            async with asyncio.timeout(LONG):
                await runner
            assert client.results[-1]["event"] == "closed", client.results
        finally:
            if not runner.done():
                runner.cancel()
            await asyncio.gather(runner, return_exceptions=True)


def _acks(client: JsClient, what: str) -> list[dict[str, Any]]:
    return [m for m in client.of_type("ack") if m["what"] == what]


async def test_js_session_drives_python_robot_at_10_percent_loss(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # 10 % of the frames lost each way, CONTROL frames (handshake, heartbeats) included.
    relay = Relay(loss=0.10, control=True)
    # The small map's PNG (~350 bytes) fits one chunk: the robot sends it in chunks of 8
    # bytes here (a sender's choice, §15.1), so lost chunks are asked for again (§15.3).
    monkeypatch.setattr(robot_module, "MapService", functools.partial(MapService, chunk_size=8))
    async with js_session(tmp_path, relay) as (client, nav, safety, server, _endpoint):
        # The page's greeting: who it is, with the role the robot gave.
        hello = client.of_type("hello")[0]
        assert hello == {**hello, "robot": ROBOT, "user": USER, "role": "driver", "may_drive": True}

        # The map, complete and intact: the robot's PNG byte for byte, decoded to its size.
        await wait_until(lambda: bool(client.of_type("map_decoded")), LONG)
        (map_msg,) = client.of_type("map")
        encoded = server.encoded_map()
        assert base64.b64decode(map_msg["png"]) == encoded.png
        assert (map_msg["width"], map_msg["height"], map_msg["version"]) == (
            encoded.width,
            encoded.height,
            encoded.version,
        )
        assert map_msg["resolution"] == encoded.resolution
        assert encoded.size > 30 * 8  # many chunks
        (decoded,) = client.of_type("map_decoded")
        assert (decoded["width"], decoded["height"]) == (encoded.width, encoded.height)
        with Image.open(io.BytesIO(encoded.png)) as image:
            assert image.size == (encoded.width, encoded.height)

        # Poses: where the simulator has the robot.
        await wait_until(lambda: len(client.of_type("pose")) >= 5, LONG)
        pose = client.of_type("pose")[-1]
        here = nav.pose().pose
        assert abs(pose["x"] - here.x) < 0.5 and abs(pose["y"] - here.y) < 0.5, (pose, here)

        # A picture of the synthetic camera, a JPEG of the rig's size.
        await wait_until(lambda: bool(client.of_type("video")), LONG)
        picture = client.of_type("video")[0]
        assert picture["header"]["kind"] == "video" and picture["header"]["codec"] == "jpeg"
        with Image.open(io.BytesIO(base64.b64decode(picture["data"]))) as image:
            assert (image.format, image.size) == ("JPEG", (VIDEO.width, VIDEO.height))

        # Arm, then a goal across the room: accepted, and the robot drives toward it.
        client.page({"type": "arm"})
        await wait_until(lambda: bool(_acks(client, "arm")), LONG)
        assert _acks(client, "arm")[0]["ok"], client.of_type("ack")
        goal = (3.0, 5.2)  # room-a; the robot starts at (1.0, 1.2)
        start = math.dist((here.x, here.y), goal)
        client.page({"type": "goal", "x": goal[0], "y": goal[1]})
        await wait_until(
            lambda: any(g["status"] in ("active", "succeeded") for g in client.of_type("goal")),
            LONG,
        )
        refused = [g for g in client.of_type("goal") if g["status"] in ("refused", "failed")]
        assert not refused, refused
        await wait_until(
            lambda: nav.current_goal() is not None or nav.velocity() != Velocity(), LONG
        )

        def nearer() -> bool:
            now = nav.pose().pose
            return math.dist((now.x, now.y), goal) < start - 1.0

        await wait_until(nearer, LONG)
        seen = client.of_type("pose")[-1]
        assert math.dist((seen["x"], seen["y"]), goal) < start - 0.5  # the page saw it too

        # Driving by hand (§27): the page's drive at 20 Hz takes over from the goal (the
        # robot says so in drive_state, which the JS session decodes), and a release stops
        # the robot, still armed.
        def driving() -> bool:
            return any(d["active"] and d["code"] == "ok" for d in client.of_type("drive_state"))

        async with asyncio.timeout(LONG):
            while not (driving() and nav.velocity().angular > 0.1):
                client.page({"type": "drive", "linear": 0.0, "angular": 0.8})
                await asyncio.sleep(0.05)
        client.page({"type": "drive", "linear": 0, "angular": 0})
        await wait_until(lambda: client.of_type("drive_state")[-1]["code"] == "released", LONG)
        await wait_until(lambda: nav.velocity() == Velocity(), LONG)
        assert safety.state().armed and nav.current_goal() is None
        await wait_until(lambda: client.of_type("goal")[-1]["code"] == "replaced", LONG)

        # A stop: acknowledged, and the robot stays latched (disarmed) afterwards.
        client.page({"type": "stop", "how": "button"})
        await wait_until(lambda: bool(_acks(client, "stop")), LONG)
        assert _acks(client, "stop")[0]["ok"], client.of_type("ack")
        assert not safety.state().armed
        await wait_until(lambda: nav.velocity() == Velocity(), LONG)
        await wait_until(lambda: client.of_type("safety")[-1]["armed"] is False, LONG)
        assert not safety.state().armed and nav.current_goal() is None
    assert relay.dropped > 0 and relay.passed > 0
    closed = client.results[-1]
    assert closed["reconnects"] == 0, closed  # 10 % loss never dropped the call
    # The JS decoders read everything the Python robot sent.
    assert set(closed["drops"].values()) == {0}, closed


async def test_js_session_reconnects_after_a_cut_and_the_robot_stays_latched(
    tmp_path: Path,
) -> None:
    relay = Relay()
    async with js_session(tmp_path, relay) as (client, nav, safety, _server, endpoint):
        client.page({"type": "arm"})
        await wait_until(lambda: bool(_acks(client, "arm")), LONG)
        assert _acks(client, "arm")[0]["ok"], client.of_type("ack")
        assert safety.state().armed
        (first,) = endpoint.calls
        # Silence both ways (presence stays): each side drops the call by its timeout.
        relay.cut = True
        await wait_until(
            lambda: any(c["state"] == "reconnecting" for c in client.of_type("connection")), LONG
        )
        await wait_until(lambda: first.end is not None, LONG)
        assert first.end is not None and first.end.kind == "dropped"
        # The robot latches when its driver's call drops (the supervisor hears of the drop
        # on its own task, a moment after the endpoint).
        await wait_until(lambda: not safety.state().armed, LONG)
        relay.cut = False
        await wait_until(
            lambda: any(c["state"] == "reconnected" for c in client.of_type("connection")), LONG
        )
        states = [c["state"] for c in client.of_type("connection")]
        assert states.index("reconnecting") < states.index("reconnected"), states
        assert "ended" not in states, states
        await wait_until(lambda: any(c.end is None for c in endpoint.calls), LONG)
        (second,) = [c for c in endpoint.calls if c.end is None]
        assert second.id != first.id
        # Still latched on the new call: nothing re-armed it, the page is told so.
        assert not safety.state().armed and nav.velocity() == Velocity()
        back = next(
            i
            for i, m in enumerate(client.emitted)
            if m["type"] == "connection" and m["state"] == "reconnected"
        )

        def safety_since() -> list[dict[str, Any]]:
            return [m for m in client.emitted[back:] if m["type"] == "safety"]

        await wait_until(lambda: bool(safety_since()), LONG)
        assert safety_since()[0]["armed"] is False, safety_since()
        # The session works on the new call: the driver re-arms deliberately.
        client.page({"type": "arm"})
        await wait_until(lambda: len(_acks(client, "arm")) == 2, LONG)
        assert _acks(client, "arm")[1]["ok"], client.of_type("ack")
        await wait_until(lambda: safety.state().armed, LONG)
    closed = client.results[-1]
    assert closed["reconnects"] == 1, closed
    assert set(closed["drops"].values()) == {0}, closed
