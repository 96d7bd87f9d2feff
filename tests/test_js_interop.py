"""The browser client's protocol core (web/src, JavaScript) calls a real Python robot.

``node web/test/interop/client.mjs`` runs the JS user side; its link speaks newline-delimited
JSON over stdin/stdout (payloads in base64) to this process, which relays it to an in-memory
hub where :func:`rig.robot_on_hub` runs the robot (simulator, supervisor, RobotServer). No
gateway is involved: this checks the two implementations of docs/protocol.md §2–§8 against
each other, in both cipher suites and through a RETRY.

Node is required wherever ``make test`` runs: without it these tests fail, saying so.
"""

from __future__ import annotations

import asyncio
import base64
import json
import shutil
from pathlib import Path
from typing import Any

import pytest

from conftest import wait_until
from rig import GENEROUS_TIMEOUT, ROBOT, USER, robot_on_hub
from telebot.channels.call import Call, RobotEndpoint
from telebot.channels.transports.base import Lane, Presence, Sample, Subscription
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import CipherChoice
from telebot.identity import Identity, encode_key

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


async def run_client(hub: MemoryHub, options: dict[str, Any]) -> list[dict[str, Any]]:
    """Run the JS client with ``options``, relaying its link to ``hub``; its result lines."""
    process = await asyncio.create_subprocess_exec(
        node_binary(),
        str(CLIENT),
        json.dumps(options),
        cwd=ROOT,
        stdin=asyncio.subprocess.PIPE,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    assert process.stdin is not None and process.stdout is not None and process.stderr is not None
    stdin = process.stdin
    results: list[dict[str, Any]] = []
    handles: dict[int, Subscription | Presence] = {}

    def write(message: dict[str, Any]) -> None:
        if not stdin.is_closing():
            stdin.write((json.dumps(message) + "\n").encode())

    def on_samples(sub_id: int) -> Any:
        def deliver(samples: Any) -> None:
            for sample in samples:
                assert isinstance(sample, Sample)
                data = base64.b64encode(sample.payload).decode()
                write({"op": "sample", "id": sub_id, "key": sample.key, "data": data})

        return deliver

    def on_presence(watch_id: int) -> Any:
        return lambda key, alive: write({"op": "alive", "id": watch_id, "key": key, "alive": alive})

    async with MemoryTransport(hub, "browser") as transport:
        try:
            async with asyncio.timeout(RUN_DEADLINE):
                while line := await process.stdout.readline():
                    message = json.loads(line)
                    op = message["op"]
                    if op == "sub":
                        handles[message["id"]] = transport.subscribe(
                            message["key"], on_samples(message["id"])
                        )
                    elif op == "watch":
                        handles[message["id"]] = transport.watch_presence(
                            message["key"], on_presence(message["id"])
                        )
                    elif op == "token":
                        handles[message["id"]] = transport.declare_presence(message["key"])
                    elif op in ("unsub", "unwatch", "untoken"):
                        handles.pop(message["id"]).close()
                    elif op == "pub":
                        publisher = transport.publisher(message["key"], Lane(message["lane"]))
                        publisher.put(base64.b64decode(message["data"]))
                        publisher.close()
                    elif op == "result":
                        results.append(message)
                code = await process.wait()
        finally:
            if process.returncode is None:
                process.kill()
                await process.wait()
            for handle in handles.values():
                handle.close()
    stderr = (await process.stderr.read()).decode(errors="replace")
    assert code == 0, f"the JS client failed ({code}): {results} {stderr[-2000:]}"
    return results


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
