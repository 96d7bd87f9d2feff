"""``telebot-user talk``: a voice (and optionally video) call from the command line.

Sends a microphone (a WAV file, the sound card, or a test tone) and optionally a test
camera pattern to the robot, and plays or records what the robot's microphone hears.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
from pathlib import Path
from typing import TextIO

from telebot.apps.common import EXIT_FAILURE, EXIT_OK, EXIT_USAGE, stop_on_signals
from telebot.config import AppConfig
from telebot.errors import TelebotError
from telebot.services.client import connect
from telebot.services.media.audio import AudioSink, AudioSource, open_sink, open_source
from telebot.services.media.user import TestPattern

__all__ = ["mic_spec", "talk"]

PROG = "telebot-user"


def mic_spec(value: str) -> str:
    """``--mic``: a WAV file, ``default``, ``tone:HZ`` or ``none`` as a source spec."""
    if value in ("default", "none") or value.startswith(("tone:", "wav:")):
        return value
    return f"wav:{value}"


def speaker_spec(value: str) -> str:
    """``--speaker``: a WAV file to write, ``default`` or ``none`` as a sink spec."""
    if value in ("default", "none") or value.startswith("wav:"):
        return value
    return f"wav:{value}"


async def talk(
    robot: str,
    *,
    home: Path,
    config: AppConfig,
    mic: str = "default",
    speaker: str = "none",
    camera: bool = False,
    duration: float | None = None,
    stream: TextIO = sys.stderr,
) -> int:
    """Talk to ``robot`` until ``duration`` s passed, the call ends, or Ctrl-C.

    Exit 0 after a call in which the robot's audio came (or none was asked for), 1 when the
    call failed, 2 for a bad ``--mic`` / ``--speaker``.
    """
    source: AudioSource | None = None
    sink: AudioSink | None = None
    try:
        source = open_source(mic_spec(mic))
        sink = open_sink(speaker_spec(speaker))
    except (ValueError, RuntimeError) as exc:
        if source is not None:
            source.close()
        print(f"{PROG}: error: {exc}", file=stream)
        return EXIT_USAGE
    blocks = 0
    stop = asyncio.Event()
    try:
        with stop_on_signals(stop):
            async with connect(
                robot, home=home, config=config, timeout=config.call.connect_timeout
            ) as client:
                client.talk(mic=source, camera=TestPattern() if camera else None)
                print(f"talking to {robot} (Ctrl-C to hang up)", file=stream)

                async def listen() -> None:
                    nonlocal blocks
                    async with client.audio() as audio:
                        async for block in audio:
                            assert sink is not None
                            sink.write(block.samples)
                            blocks += 1

                listener = asyncio.create_task(listen())
                waiter = asyncio.create_task(stop.wait())
                finished = asyncio.create_task(client.wait_finished())
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(duration):
                        await asyncio.wait({waiter, finished}, return_when=asyncio.FIRST_COMPLETED)
                for task in (listener, waiter, finished):
                    task.cancel()
                await asyncio.gather(listener, waiter, finished, return_exceptions=True)
                client.talk()
    except (TelebotError, OSError) as exc:
        print(f"{PROG}: error: {exc}", file=stream)
        return EXIT_FAILURE
    finally:
        sink.close()
    print(f"heard {blocks * 0.02:.1f} s of the robot's audio", file=stream)
    return EXIT_OK
