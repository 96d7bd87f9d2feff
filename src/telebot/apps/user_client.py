"""The user's commands that talk to a robot: ``chat``, ``send``, ``getmap``, ``where``."""

from __future__ import annotations

import asyncio
import contextlib
import math
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import TextIO

from telebot.apps.common import EXIT_FAILURE, EXIT_OK, EXIT_USAGE
from telebot.config import AppConfig
from telebot.services.client import RobotClient, connect
from telebot.services.proto.chat import ChatReply

__all__ = ["chat_session", "format_pose", "get_map", "send_command", "where"]


def format_pose(x: float, y: float, yaw: float) -> str:
    """A pose as people read it: metres and degrees (map frame, heading CCW from +x)."""
    return f"x {x:.2f} m, y {y:.2f} m, heading {math.degrees(yaw):.0f}°"


@contextlib.asynccontextmanager
async def _robot(
    robot: str, home: Path, config: AppConfig, timeout: float | None
) -> AsyncIterator[RobotClient]:
    async with connect(robot, home=home, config=config, timeout=timeout) as client:
        yield client


class _Progress:
    """A progress bar on a terminal; a single summary line otherwise."""

    def __init__(self, label: str, stream: TextIO = sys.stderr) -> None:
        self.label = label
        self.stream = stream
        self.tty = stream.isatty()

    def __call__(self, done: int, total: int) -> None:
        if not self.tty or total <= 0:
            return
        width = 30
        filled = int(width * done / total)
        self.stream.write(
            f"\r{self.label} [{'#' * filled}{' ' * (width - filled)}] {done}/{total} chunks"
        )
        self.stream.flush()

    def finish(self, text: str) -> None:
        if self.tty:
            self.stream.write("\r\033[K")
        print(text, file=self.stream)


async def _fetch_and_save(client: RobotClient, png_path: Path, timeout: float) -> Path:
    progress = _Progress(f"map from {client.robot}")
    download = await client.get_map(timeout=timeout, progress=progress)
    png_path.parent.mkdir(parents=True, exist_ok=True)
    yaml_path = download.save(png_path)
    progress.finish(
        f"map saved to {png_path} ({len(download.png) // 1024} KB, "
        f"{download.width} x {download.height} cells at {download.resolution:g} m, "
        f"{download.resent} chunks resent) and {yaml_path.name}"
    )
    return yaml_path


def _print_reply(reply: ChatReply) -> None:
    print(f"{'' if reply.ok or not reply.final else '! '}{reply.text}", flush=True)


async def _run_command(
    client: RobotClient, command: str, timeout: float | None, map_dir: Path
) -> bool:
    """One chat command: print its replies; fetch the map for getmap. True if it succeeded."""
    ok = False
    attachment = None
    async for reply in client.chat_replies(command, timeout=timeout):
        _print_reply(reply)
        if reply.final:
            ok, attachment = reply.ok, reply.attachment
    if ok and attachment == "map":
        await _fetch_and_save(client, map_dir / f"{client.robot}-map.png", timeout or 60.0)
    return ok


async def send_command(
    robot: str,
    command: str,
    *,
    home: Path,
    config: AppConfig,
    timeout: float,
    map_dir: Path,
) -> int:
    """``telebot-user send``: exit 0 on success, 1 when the robot reports failure."""
    async with _robot(robot, home, config, config.call.connect_timeout) as client:
        try:
            ok = await _run_command(client, command, timeout, map_dir)
        except TimeoutError:
            print(
                f"telebot-user: error: {robot} did not finish {command!r} within {timeout:g} s",
                file=sys.stderr,
            )
            return EXIT_USAGE
    return EXIT_OK if ok else EXIT_FAILURE


async def chat_session(
    robot: str,
    *,
    home: Path,
    config: AppConfig,
    timeout: float,
    map_dir: Path,
    stdin: TextIO = sys.stdin,
) -> int:
    """``telebot-user chat``: interactive on a terminal, one command per line otherwise.

    Piped input runs the commands one after the other, each to its end (a script of
    moves), and ends after the last one, all within ``timeout``. On a terminal commands
    run at once, so ``stop`` can be typed while the robot moves.
    """
    async with _robot(robot, home, config, config.call.connect_timeout) as client:
        print(
            f"connected to {robot} (role {client.call.role}); type help, Ctrl-D to leave",
            file=sys.stderr,
        )
        if not stdin.isatty():
            failures = 0
            try:
                async with asyncio.timeout(timeout):
                    for line in stdin:
                        command = line.strip()
                        if not command:
                            continue
                        print(f"> {command}", flush=True)
                        if not await _run_command(client, command, None, map_dir):
                            failures += 1
            except TimeoutError:
                print(
                    f"telebot-user: error: chat did not finish within {timeout:g} s",
                    file=sys.stderr,
                )
                return EXIT_USAGE
            return EXIT_OK if failures == 0 else EXIT_FAILURE
        return await _interactive(client, map_dir)


async def _interactive(client: RobotClient, map_dir: Path) -> int:
    with contextlib.suppress(ImportError):
        import readline  # noqa: F401  (line editing and history for input())
    async with asyncio.TaskGroup() as tasks:
        while True:
            try:
                line = await asyncio.to_thread(input, f"{client.robot}> ")
            except EOFError:
                break
            command = line.strip()
            if command in ("quit", "exit"):
                break
            if command:
                tasks.create_task(_run_command(client, command, None, map_dir))
    return EXIT_OK


async def get_map(
    robot: str, output: Path, *, home: Path, config: AppConfig, timeout: float
) -> int:
    """``telebot-user getmap``: write the PNG and its map_server YAML."""
    async with _robot(robot, home, config, config.call.connect_timeout) as client:
        await _fetch_and_save(client, output, timeout)
    return EXIT_OK


async def where(robot: str, *, home: Path, config: AppConfig, timeout: float) -> int:
    """``telebot-user where``: the robot's pose in the map frame and what it is doing."""
    async with _robot(robot, home, config, config.call.connect_timeout) as client:
        pose = await client.pose(timeout=timeout)
    state = pose.state + (f" ({pose.detail})" if pose.detail else "")
    print(f"{format_pose(pose.x, pose.y, pose.yaw)}; {state}")
    return EXIT_OK
