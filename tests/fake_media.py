"""Fake camera and microphone files for Chromium, made at test time.

Chromium's ``--use-file-for-fake-video-capture=X.y4m`` plays a Y4M file as the camera (in a
loop) and ``--use-file-for-fake-audio-capture=X.wav`` a WAV file as the microphone. The
pictures carry their frame number in the stamp of :func:`telebot.services.codecs.stamp_number`
(what the robot's test camera draws, and what ``static/media.js`` and
:func:`~telebot.services.codecs.read_number` read back).
"""

from __future__ import annotations

import wave
from pathlib import Path

import numpy as np

from telebot.services.codecs import stamp_number

__all__ = ["chromium_media_args", "write_wav", "write_y4m"]


def write_y4m(
    path: Path, *, frames: int, width: int = 320, height: int = 240, fps: int = 30
) -> Path:
    """A 4:2:0 Y4M file of ``frames`` pictures stamped 0, 1, … (Chromium loops it)."""
    chroma = np.full((height // 2) * (width // 2), 128, np.uint8).tobytes()
    ramp = (np.arange(width) * 160 // width).astype(np.uint8)
    with path.open("wb") as out:
        out.write(f"YUV4MPEG2 W{width} H{height} F{fps}:1 Ip A1:1 C420jpeg\n".encode())
        for n in range(frames):
            # A moving ramp below the stamp: the encoder has real motion to code.
            luma = np.broadcast_to(np.roll(ramp, n * 4) + 48, (height, width))
            out.write(b"FRAME\n")
            out.write(stamp_number(np.ascontiguousarray(luma), n).tobytes())
            out.write(chroma)
            out.write(chroma)
    return path


def write_wav(path: Path, *, freq: float, seconds: float = 4.0, rate: int = 48000) -> Path:
    """A mono 16-bit WAV of a ``freq`` Hz tone (whole periods: it loops without a click)."""
    periods = max(1, round(seconds * freq))
    n = round(periods * rate / freq)
    t = np.arange(n) / rate
    pcm = (np.sin(2 * np.pi * freq * t) * 0.5 * 32767).astype("<i2")
    with wave.open(str(path), "wb") as out:
        out.setnchannels(1)
        out.setsampwidth(2)
        out.setframerate(rate)
        out.writeframes(pcm.tobytes())
    return path


def chromium_media_args(folder: Path, *, tone: float = 1000.0) -> list[str]:
    """Chromium flags for a fake camera (numbered frames) and microphone (a ``tone`` Hz WAV)."""
    y4m = write_y4m(folder / "camera.y4m", frames=90)
    wav = write_wav(folder / "mic.wav", freq=tone)
    return [
        "--use-fake-device-for-media-stream",
        "--use-fake-ui-for-media-stream",
        f"--use-file-for-fake-video-capture={y4m}",
        f"--use-file-for-fake-audio-capture={wav}",
        "--autoplay-policy=no-user-gesture-required",
    ]
