"""Fake camera and microphone files for Chromium, made at test time, and their read-back.

Chromium's ``--use-file-for-fake-video-capture=X.y4m`` plays a Y4M file as the camera (in a
loop) and ``--use-file-for-fake-audio-capture=X.wav`` a WAV file as the microphone. The
pictures carry their frame number in the stamp ``static/media.js`` reads: 16 cells across
the top eighth of the picture, most significant bit first, a bright cell is a 1.
"""

from __future__ import annotations

import wave
from pathlib import Path

import numpy as np
import numpy.typing as npt

#: Luma of a 1 cell and a 0 cell (video range, far from the 128 threshold).
BRIGHT, DARK = 235, 16


def stamp_luma(number: int, width: int, height: int) -> npt.NDArray[np.uint8]:
    """A luma plane with ``number`` stamped on top and a moving gradient below."""
    y = np.empty((height, width), np.uint8)
    ramp = (np.arange(width) * 160 // width + number * 4) % 160 + 48
    y[:] = ramp[None, :].astype(np.uint8)
    band = height // 8
    for i in range(16):
        bit = (number >> (15 - i)) & 1
        y[:band, i * width // 16 : (i + 1) * width // 16] = BRIGHT if bit else DARK
    return y


def read_stamp(luma: npt.NDArray[np.uint8]) -> int:
    """The number :func:`stamp_luma` put in a (decoded) luma plane."""
    height, width = luma.shape[:2]
    row = luma[height // 16]
    n = 0
    for i in range(16):
        n = (n << 1) | int(row[int((i + 0.5) * width / 16)] > 128)
    return n


def write_y4m(
    path: Path, *, frames: int, width: int = 320, height: int = 240, fps: int = 30
) -> Path:
    """A 4:2:0 Y4M file of ``frames`` pictures numbered 0, 1, … (Chromium loops it)."""
    chroma = np.full((height // 2) * (width // 2), 128, np.uint8).tobytes()
    with path.open("wb") as out:
        out.write(f"YUV4MPEG2 W{width} H{height} F{fps}:1 Ip A1:1 C420jpeg\n".encode())
        for n in range(frames):
            out.write(b"FRAME\n")
            out.write(stamp_luma(n, width, height).tobytes())
            out.write(chroma)
            out.write(chroma)
    return path


def write_wav(path: Path, *, freq: float, seconds: float = 4.0, rate: int = 48000) -> Path:
    """A mono 16-bit WAV of a ``freq`` Hz tone (a whole number of periods: it loops clean)."""
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


def dominant_frequency(pcm: npt.NDArray[np.float64] | npt.NDArray[np.int16], rate: int) -> float:
    """The strongest frequency (Hz) of a mono signal (FFT peak, Hann window)."""
    x = np.asarray(pcm, np.float64)
    x = x - x.mean()
    if len(x) < 64 or not np.any(x):
        return 0.0
    spectrum = np.abs(np.fft.rfft(x * np.hanning(len(x))))
    return float(np.argmax(spectrum[1:]) + 1) * rate / len(x)
