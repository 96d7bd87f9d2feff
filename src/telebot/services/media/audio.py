"""Audio in and out: sources and sinks of 48 kHz mono int16 samples in 20 ms blocks.

A :class:`AudioSource` gives the next 20 ms block (:data:`FRAME_SAMPLES` samples) each
time it is asked; the media service asks once per 20 ms of the event loop's clock, so the
synthetic sources run at the simulator's pace. A :class:`AudioSink` takes decoded
samples. Chosen by a spec string (config ``[media] mic`` / ``speaker``, ``--mic``):

* ``tone:440`` — a sine tone (source); ``none`` — silence / discard;
* ``wav:PATH`` — a WAV file: read (looped, any rate, mixed to mono) or written;
* ``memory`` — a sink that keeps what it heard (tests read it back);
* ``default`` — the sound card through sounddevice/PortAudio, the optional extra
  ``telebot[audio]`` (imported only then; a clear error when it is missing).

:class:`MixSource` adds one-off sounds (the robot's spoken replies) to a source.
"""

from __future__ import annotations

import math
import threading
import wave
from collections import deque
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from telebot.services.media.wire import FRAME_SAMPLES, SAMPLE_RATE

__all__ = [
    "AudioSink",
    "AudioSource",
    "MemorySink",
    "MixSource",
    "NullSink",
    "SilenceSource",
    "ToneSource",
    "WavSink",
    "WavSource",
    "dominant_frequency",
    "open_sink",
    "open_source",
    "read_wav",
    "resample",
]

Samples = npt.NDArray[np.int16]


class AudioSource(Protocol):
    """Gives 20 ms blocks of 48 kHz mono int16 samples."""

    def read(self) -> Samples:
        """The next block (:data:`FRAME_SAMPLES` samples)."""
        ...

    def close(self) -> None:
        """Release the device or file."""
        ...


class AudioSink(Protocol):
    """Takes 48 kHz mono int16 samples."""

    def write(self, samples: Samples) -> None:
        """Play or keep ``samples``."""
        ...

    def close(self) -> None:
        """Flush and release the device or file."""
        ...


class SilenceSource:
    """Zeros."""

    def read(self) -> Samples:
        """20 ms of silence."""
        return np.zeros(FRAME_SAMPLES, dtype=np.int16)

    def close(self) -> None:
        """Nothing to release."""


class ToneSource:
    """A sine tone of ``frequency`` Hz at ``amplitude`` (of full scale), phase-continuous."""

    def __init__(self, frequency: float = 440.0, amplitude: float = 0.3) -> None:
        if not 0 < frequency < SAMPLE_RATE / 2:
            raise ValueError(f"a tone needs 0 < frequency < {SAMPLE_RATE // 2} Hz")
        self.frequency = frequency
        self.amplitude = amplitude
        self._n = 0

    def read(self) -> Samples:
        """The next 20 ms of the tone."""
        t = (self._n + np.arange(FRAME_SAMPLES)) / SAMPLE_RATE
        self._n += FRAME_SAMPLES
        wave_ = np.sin(2 * math.pi * self.frequency * t) * self.amplitude * 32767
        return wave_.astype(np.int16)

    def close(self) -> None:
        """Nothing to release."""


def resample(samples: npt.NDArray[Any], rate: int) -> Samples:
    """Mono samples at ``rate`` Hz → 48 kHz int16 (linear interpolation: fine for speech)."""
    if rate == SAMPLE_RATE or len(samples) == 0:
        return np.asarray(samples, dtype=np.int16)
    n = round(len(samples) * SAMPLE_RATE / rate)
    x = np.linspace(0, len(samples) - 1, n)
    return np.interp(x, np.arange(len(samples)), samples.astype(np.float64)).astype(np.int16)


def read_wav(path: str | Path) -> Samples:
    """A 16-bit PCM WAV file as 48 kHz mono int16 (channels mixed); ValueError if not one."""
    try:
        with wave.open(str(path), "rb") as wav:
            width, channels, rate = wav.getsampwidth(), wav.getnchannels(), wav.getframerate()
            raw = wav.readframes(wav.getnframes())
    except (OSError, EOFError, wave.Error) as exc:
        raise ValueError(f"cannot read WAV file {path}: {exc}") from exc
    if width != 2:
        raise ValueError(f"WAV file {path}: {8 * width}-bit samples, need 16-bit PCM")
    data = np.frombuffer(raw, dtype="<i2").reshape(-1, channels).mean(axis=1)
    return resample(data, rate)


class WavSource:
    """A WAV file, looped (or silence after its end with ``loop=False``)."""

    def __init__(self, path: str | Path, *, loop: bool = True) -> None:
        self.samples = read_wav(path)
        if len(self.samples) == 0:
            raise ValueError(f"WAV file {path} has no samples")
        self.loop = loop
        self._at = 0

    def read(self) -> Samples:
        """The next 20 ms of the file."""
        out = np.zeros(FRAME_SAMPLES, dtype=np.int16)
        filled = 0
        while filled < FRAME_SAMPLES:
            if self._at >= len(self.samples):
                if not self.loop:
                    break
                self._at = 0
            take = min(FRAME_SAMPLES - filled, len(self.samples) - self._at)
            out[filled : filled + take] = self.samples[self._at : self._at + take]
            filled += take
            self._at += take
        return out

    def close(self) -> None:
        """Nothing to release."""


class MixSource:
    """``base`` plus sounds queued with :meth:`play` (e.g. the robot's spoken replies)."""

    def __init__(self, base: AudioSource) -> None:
        self.base = base
        self._queue: deque[Samples] = deque()
        self._lock = threading.Lock()  # play() may come from a speech thread

    def play(self, samples: Samples) -> None:
        """Mix ``samples`` (48 kHz mono) into the next blocks."""
        with self._lock:
            for start in range(0, len(samples), FRAME_SAMPLES):
                block = np.zeros(FRAME_SAMPLES, dtype=np.int16)
                part = samples[start : start + FRAME_SAMPLES]
                block[: len(part)] = part
                self._queue.append(block)

    @property
    def playing(self) -> bool:
        """Whether queued sound is still to come."""
        return bool(self._queue)

    def read(self) -> Samples:
        """The base's next block with the queued sound added (clipped)."""
        block = self.base.read()
        with self._lock:
            extra = self._queue.popleft() if self._queue else None
        if extra is None:
            return block
        mixed = block.astype(np.int32) + extra
        out: Samples = np.clip(mixed, -32768, 32767).astype(np.int16)
        return out

    def close(self) -> None:
        """Close the base."""
        self.base.close()


class NullSink:
    """Discards everything."""

    def write(self, samples: Samples) -> None:
        """Discard."""

    def close(self) -> None:
        """Nothing to release."""


class MemorySink:
    """Keeps the last ``max_seconds`` of what it heard (tests and the bench read it)."""

    def __init__(self, max_seconds: float = 30.0) -> None:
        self.max_samples = int(max_seconds * SAMPLE_RATE)
        self._blocks: deque[Samples] = deque()
        self._count = 0
        #: Samples written in all.
        self.total = 0

    def write(self, samples: Samples) -> None:
        """Keep ``samples``."""
        self._blocks.append(np.asarray(samples, dtype=np.int16).copy())
        self._count += len(samples)
        self.total += len(samples)
        while self._blocks and self._count - len(self._blocks[0]) >= self.max_samples:
            self._count -= len(self._blocks.popleft())

    def samples(self, last_seconds: float | None = None) -> Samples:
        """What it heard (the last ``last_seconds`` of it)."""
        if not self._blocks:
            return np.zeros(0, dtype=np.int16)
        out = np.concatenate(list(self._blocks))
        if last_seconds is not None:
            out = out[-int(last_seconds * SAMPLE_RATE) :]
        return out

    def close(self) -> None:
        """Nothing to release."""


class WavSink:
    """Writes a 48 kHz mono 16-bit WAV file."""

    def __init__(self, path: str | Path) -> None:
        try:
            self._wav = wave.open(str(path), "wb")  # noqa: SIM115 - closed by close()
        except OSError as exc:
            raise ValueError(f"cannot write WAV file {path}: {exc}") from exc
        self._wav.setnchannels(1)
        self._wav.setsampwidth(2)
        self._wav.setframerate(SAMPLE_RATE)

    def write(self, samples: Samples) -> None:
        """Append ``samples``."""
        self._wav.writeframes(np.asarray(samples, dtype="<i2").tobytes())

    def close(self) -> None:
        """Finish the file."""
        self._wav.close()


def _sounddevice() -> Any:
    try:
        import sounddevice  # type: ignore[import-not-found,unused-ignore]
    except (ImportError, OSError) as exc:
        raise RuntimeError(
            "audio device 'default' needs sounddevice/PortAudio: pip install 'telebot[audio]' "
            f"(and the PortAudio library, Debian: libportaudio2) ({exc})"
        ) from exc
    return sounddevice


class DeviceSource:
    """The default microphone (sounddevice): blocks are taken from a bounded queue."""

    def __init__(self) -> None:
        sd = _sounddevice()
        self._blocks: deque[Samples] = deque(maxlen=10)

        def callback(indata: Any, frames: int, time_info: Any, status: Any) -> None:
            self._blocks.append(np.asarray(indata[:, 0], dtype=np.int16).copy())

        self._stream = sd.InputStream(
            samplerate=SAMPLE_RATE,
            channels=1,
            dtype="int16",
            blocksize=FRAME_SAMPLES,
            callback=callback,
        )
        self._stream.start()

    def read(self) -> Samples:
        """The oldest captured block, or silence when the device is behind."""
        if self._blocks:
            return self._blocks.popleft()
        return np.zeros(FRAME_SAMPLES, dtype=np.int16)

    def close(self) -> None:
        """Stop the device."""
        self._stream.close()


class DeviceSink:
    """The default speaker (sounddevice), fed through a blocking output stream."""

    def __init__(self) -> None:
        sd = _sounddevice()
        self._stream = sd.OutputStream(samplerate=SAMPLE_RATE, channels=1, dtype="int16")
        self._stream.start()

    def write(self, samples: Samples) -> None:
        """Play ``samples``."""
        self._stream.write(np.asarray(samples, dtype=np.int16).reshape(-1, 1))

    def close(self) -> None:
        """Stop the device."""
        self._stream.close()


def open_source(spec: str) -> AudioSource:
    """The source a spec names (``tone:440``, ``wav:PATH``, ``default``, ``none``)."""
    kind, _, arg = spec.partition(":")
    if kind == "none":
        return SilenceSource()
    if kind == "tone":
        try:
            return ToneSource(float(arg or 440))
        except ValueError as exc:
            raise ValueError(f"audio source {spec!r}: {exc}") from None
    if kind == "wav" and arg:
        return WavSource(arg)
    if kind == "default":
        return DeviceSource()
    raise ValueError(f"audio source {spec!r}: use tone:HZ, wav:PATH, default or none")


def open_sink(spec: str) -> AudioSink:
    """The sink a spec names (``wav:PATH``, ``memory``, ``default``, ``none``)."""
    kind, _, arg = spec.partition(":")
    if kind == "none":
        return NullSink()
    if kind == "memory":
        return MemorySink()
    if kind == "wav" and arg:
        return WavSink(arg)
    if kind == "default":
        return DeviceSink()
    raise ValueError(f"audio sink {spec!r}: use wav:PATH, memory, default or none")


def dominant_frequency(samples: npt.NDArray[Any]) -> float:
    """The strongest frequency (Hz) in 48 kHz ``samples`` (0 for silence or nothing)."""
    if len(samples) < 2 or not np.any(samples):
        return 0.0
    window = np.hanning(len(samples))
    spectrum = np.abs(np.fft.rfft(samples.astype(np.float64) * window))
    spectrum[0] = 0
    return float(np.argmax(spectrum) * SAMPLE_RATE / len(samples))
