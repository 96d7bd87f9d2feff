"""The demo behind ``make demo``: a robot process and a user client in a real call.

Until the robot daemon exists (next issues), the robot is ``telebot-robot echo``. The
demo creates throw-away keys for robot ``guiabot`` and user ``alice``, makes them
known to each other, starts the robot in its own process on the embedded zenoh peer
default (loopback endpoint, no router), calls it, exchanges datagrams, and prints what
it measured: call set-up time, round-trip times, echoed datagrams per second, loss,
and how fast the robot process exits on SIGTERM.
"""

from __future__ import annotations

import asyncio
import json
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from telebot.apps.ping import ping, throughput
from telebot.channels.call import UserEndpoint
from telebot.channels.transports import create_transport
from telebot.config import AppConfig
from telebot.identity import Identity, KnownRobots, create_paired_homes


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


async def _user_side(user_home: Path, endpoint: str) -> None:
    config = AppConfig()
    config.transport.zenoh.connect = [endpoint]
    identity, known = Identity.load(user_home), KnownRobots.load(user_home)
    async with (
        create_transport(config.transport) as transport,
        UserEndpoint(transport, identity, known, settings=config.call) as user,
    ):
        online = await user.robots_online(wait=0.5)
        print(
            f"robots online: {', '.join(f'{r.name} (trusted)' if r.trusted else r.name for r in online) or 'none'}"
        )
        started = time.perf_counter()
        call = await user.call("guiabot")
        print(
            f"call {call.id}: alice -> guiabot answered in {(time.perf_counter() - started) * 1e3:.1f} ms, role {call.role}"
        )
        chat = call.channel("chat")
        chat.send("hello robot")
        reply = await asyncio.wait_for(chat.receive(), 2.0)
        print(f"chat: sent 'hello robot', echoed back from {reply.sender}: {reply.payload!r}")
        print("round trips (one datagram in flight):")
        for size in (64, 1024, 32768):
            result = await ping(call, count=100 if size < 32768 else 40, size=size, interval=0.005)
            print(f"  {result.summary()}")
        print("echo throughput (64 datagrams in flight, 1 s each):")
        for size in (64, 1024, 32768):
            rate, loss = await throughput(call, size=size, duration=1.0)
            print(
                f"  {size:>6} B: {rate:8.0f} datagrams/s echoed, {rate * size * 8 / 1e6:7.1f} Mbit/s each way, loss {loss:.1%}"
            )
        print(
            f"heartbeats: rtt {call.stats.rtt * 1e3 if call.stats.rtt else float('nan'):.2f} ms, loss {call.stats.loss:.1%}"
        )
        await call.hangup("demo done")
        print(f"call ended: {call.end}")


def main() -> int:
    """Run the demo; exit 0 when every step worked."""
    with tempfile.TemporaryDirectory(prefix="telebot-demo-") as tmp:
        create_paired_homes(Path(tmp), "guiabot", "alice")
        robot_home, user_home = Path(tmp) / "robot", Path(tmp) / "user"
        port = _free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        print(
            f"robot guiabot and user alice: keys in {tmp}; zenoh peer mode, robot listens on {endpoint}"
        )
        robot = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "telebot.apps.robot_cli",
                "echo",
                "--home",
                str(robot_home),
                "--listen",
                endpoint,
                "--events",
            ],
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert robot.stdout is not None
            ready = json.loads(robot.stdout.readline() or "{}")
            if ready.get("event") != "ready":
                print("demo: error: the robot process did not start", file=sys.stderr)
                return 1
            print(f"robot process {robot.pid} ready (telebot-robot echo)")
            asyncio.run(_user_side(user_home, endpoint))
            started = time.perf_counter()
            robot.send_signal(signal.SIGTERM)
            robot.wait(timeout=5)
            print(
                f"robot process exited with {robot.returncode} {time.perf_counter() - started:.2f} s after SIGTERM"
            )
            return 0 if robot.returncode == 0 else 1
        finally:
            if robot.poll() is None:
                robot.kill()
                robot.wait()


if __name__ == "__main__":
    sys.exit(main())
