"""Interop in node: the browser's JavaScript client calls ``telebot-robot run`` through its
gateway, over a lossy link (issue 24, "Interop in node").

``telebot-robot run`` runs in its own process (:class:`rig.Daemon`) with its ``[gateway]``
on 127.0.0.1 (HTTPS/WSS with its self-signed certificate, which node trusts through
``NODE_EXTRA_CA_CERTS``: verified, not waved through). ``node
web/test/interop/gateway-client.mjs`` is the page's code without the page:
``connectGateway`` (admission with alice's key, a contact of the robot), ``Endpoint`` and
``RobotSession``. Between its GatewayLink and its Endpoint a link wrapper drops a seeded
10 % of the frames each way, CONTROL frames included (the handshake, RETRY, heartbeats,
HANGUP); subscriptions, tokens and presence are not frames and pass. It calls, asks
``where?``, downloads the map, sees poses, arms, stops and hangs up.

The robot's map is one of its own (a noisy floor written here, a map_server YAML the
``[sim] map`` setting names), whose PNG takes several chunks, so the download is a
multi-chunk transfer whose lost chunks are asked for again (§15.3). The suite is forced by
the robot's ``[call] cipher`` (``aesgcm``; ``chachapoly``, which the client, preferring
AES-GCM, reaches through a RETRY).

Node 20 has a WebSocket behind ``--experimental-websocket`` (node 22 without): no npm
package is needed.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from rig import FAST_SIM, ROBOT, SLACK, USER, Daemon
from telebot.config import SimSettings
from telebot.identity import Identity, encode_key
from telebot.robot.sim.stack import SimNavStack
from telebot.services.mapxfer.wire import MAX_CHUNK_DATA, encode_map
from telebot.testing.net import free_port

ROOT = Path(__file__).resolve().parent.parent
CLIENT = ROOT / "web" / "test" / "interop" / "gateway-client.mjs"
#: Seconds each step of the JS scenario may take over a lossy link on a loaded machine.
STEP = 60.0 + 10 * SLACK
#: The whole node run (a dozen steps, most of them quick).
RUN_DEADLINE = 4 * STEP
#: Where the robot starts on the noisy map (its only place), in a free corner.
START = (3.0, 3.0)

pytestmark = pytest.mark.timeout(int(RUN_DEADLINE + 120))


def node_binary() -> list[str]:
    """node, with the flag that gives node 20 its WebSocket; fails (never skips) without."""
    node = shutil.which("node")
    if node is None:
        pytest.fail("node is not installed: the JS tests need Node.js 20+ (apt install nodejs npm)")
    if not (ROOT / "node_modules" / "@noble" / "curves").is_dir():
        pytest.fail("node_modules is missing: run 'npm ci' at the repository root")
    probe = [node, "-e", "process.exit(typeof WebSocket === 'function' ? 0 : 1)"]
    has_websocket = subprocess.run(probe, check=False).returncode == 0
    return [node] if has_websocket else [node, "--experimental-websocket"]


def noisy_map(directory: Path) -> Path:
    """A 60 × 40 m floor (5 cm cells) of seeded noise with a free corner around
    :data:`START`: its PNG does not compress to one chunk. The YAML's path."""
    directory.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(24)
    height, width = 800, 1200
    image = rng.choice(np.array([0, 205, 254], dtype=np.uint8), size=(height, width))
    image[-160:, :240] = 254  # the bottom-left 12 × 8 m (the image's last rows are y = 0)
    image[[0, -1], :] = 0
    image[:, [0, -1]] = 0
    (directory / "noisy.pgm").write_bytes(b"P5\n%d %d\n255\n" % (width, height) + image.tobytes())
    yaml = directory / "noisy.yaml"
    yaml.write_text(
        "image: noisy.pgm\nmode: trinary\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\n"
        "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    (directory / "noisy.places.toml").write_text(
        f"[places.start]\nx = {START[0]}\ny = {START[1]}\nyaw_deg = 0.0\n"
    )
    return yaml


def daemon_with_gateway(base: Path, cipher: str) -> tuple[Daemon, int]:
    """A daemon on the noisy map, small JPEG video, no screen, no people; its ``[call]
    cipher`` set and its ``[gateway]`` on a free 127.0.0.1 port (not started)."""
    sim = {**FAST_SIM, "map": str(noisy_map(base / "map")), "camera_width": 160}
    sim["camera_height"] = 120
    daemon = Daemon(base, sim=sim)
    port = free_port()
    config = daemon.robot_config.read_text()
    assert config.count("[call]\n") == 1, config
    config = config.replace("[call]\n", f'[call]\ncipher = "{cipher}"\n')
    config += (
        '[video]\nwidth = 160\nheight = 120\nmax_fps = 5\n[media]\ncodec = "jpeg"\n'
        "[screen]\nenabled = false\n[people]\nenabled = false\n"
        f'[gateway]\nlisten = "127.0.0.1"\nport = {port}\n'
    )
    daemon.robot_config.write_text(config)
    return daemon, port


async def run_node(daemon: Daemon, port: int, suites: list[str]) -> list[dict[str, Any]]:
    """Run the JS client against the daemon's gateway to its end; its lines (exit 0)."""
    user = Identity.load(daemon.user_home)
    robot = Identity.load(daemon.robot_home)
    options = {
        "url": f"wss://127.0.0.1:{port}/gateway",
        "name": USER,
        "privateKey": encode_key(user.private_key),
        "robot": ROBOT,
        "robotKey": encode_key(robot.public_key),
        "suites": suites,
        "timeout": daemon.timeout,
        "loss": 0.10,
        "control": True,
        "seed": 24,
        "deadline": STEP,
    }
    # The robot's self-signed certificate, trusted as a phone told to would.
    env = {**os.environ, "NODE_EXTRA_CA_CERTS": str(daemon.robot_home / "gateway" / "cert.pem")}
    process = await asyncio.create_subprocess_exec(
        *await asyncio.to_thread(node_binary),
        str(CLIENT),
        json.dumps(options),
        cwd=ROOT,
        env=env,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    try:
        async with asyncio.timeout(RUN_DEADLINE):
            out, err = await process.communicate()
    finally:
        if process.returncode is None:
            process.kill()
            await process.wait()
    lines = [json.loads(line) for line in out.decode().splitlines() if line.strip()]
    assert process.returncode == 0, f"the JS client failed: {lines} {err.decode()[-2000:]}"
    return lines


@pytest.mark.parametrize(
    ("cipher", "suites", "expected"),
    [
        ("aesgcm", ["aesgcm"], "aesgcm"),
        # The client prefers AES-GCM, the robot takes only ChaCha20-Poly1305: a RETRY.
        ("chachapoly", ["aesgcm", "chachapoly"], "chachapoly"),
    ],
)
async def test_the_js_client_calls_the_robot_daemon_through_its_gateway_at_10_percent_loss(
    tmp_path: Path, cipher: str, suites: list[str], expected: str
) -> None:
    daemon, port = daemon_with_gateway(tmp_path, cipher)
    await asyncio.to_thread(daemon.start)
    try:
        lines = await run_node(daemon, port, suites)
        events = {line["event"]: line for line in lines}
        assert list(events) == ["admitted", "called", "where", "map", "poses", "stopped", "closed"]
        assert events["admitted"]["name"] == USER

        # The handshake, in the suite the robot's config forces; the robot has that call.
        called = events["called"]
        assert (called["suite"], called["role"]) == (expected, "driver"), called
        robot_call = await daemon.events.wait_event("call", timeout=STEP)
        assert (robot_call["id"], robot_call["peer"]) == (called["id"], USER), robot_call

        # where? — answered by the robot with where the simulator has it.
        reply = events["where"]["reply"]
        assert reply["ok"] and reply["final"], reply
        assert reply["text"].startswith("x ") and "heading" in reply["text"], reply

        # The map, complete: the robot's PNG byte for byte, in several chunks.
        grid = SimNavStack.from_settings(
            SimSettings.model_validate({"map": str(tmp_path / "map" / "noisy.yaml")}), now=0.0
        ).map()
        encoded = encode_map(grid, "noisy")
        got = events["map"]
        assert got["size"] == encoded.size and got["sha256"] == encoded.sha256, got
        assert encoded.size > 4 * MAX_CHUNK_DATA  # five chunks or more
        assert (got["width"], got["height"]) == (encoded.width, encoded.height)
        assert got["decoded"] == {"width": encoded.width, "height": encoded.height}
        assert got["resolution"] == encoded.resolution

        # Poses: where the robot is (at rest at its start; nothing drove it).
        poses = events["poses"]
        assert poses["count"] >= 5
        assert math.dist((poses["last"]["x"], poses["last"]["y"]), START) < 0.5, poses

        # Armed, then stopped: both acked, and the robot latched.
        stopped = events["stopped"]
        assert stopped["arm"]["ok"] and stopped["stop"]["ok"], stopped
        assert stopped["safety"]["armed"] is False, stopped
        # (A stop is repeated until acked: a lost ack can make the robot log two.)
        stops = [(r["who"], r["how"]) for r in daemon.audit() if r["what"] == "stop"]
        assert stops and set(stops) == {(USER, "api")}, stops

        # The loss was real, both ways, CONTROL frames included; the call never dropped,
        # and the JS decoders read everything the robot sent.
        closed = events["closed"]
        assert closed["link"]["dropped"] > 0 and closed["link"]["droppedControl"] > 0, closed
        assert closed["link"]["dropped"] < closed["link"]["passed"], closed
        assert closed["reconnects"] == 0 and "reconnecting" not in closed["connections"], closed
        assert set(closed["drops"].values()) == {0}, closed
        assert closed["gateway"]["malformed"] == 0, closed  # (samples after a close: late)
        assert closed["stats"]["rtt"] is not None and closed["stats"]["received"] > 0, closed
        ended = await daemon.call_ended(called["id"], timeout=STEP)
        assert (ended["kind"], ended["peer"]) == ("hung_up", USER), ended
    finally:
        await asyncio.to_thread(daemon.stop)
