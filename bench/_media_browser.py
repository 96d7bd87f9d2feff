"""The browser half of ``bench/media.py``: glass-to-glass, mouth-to-ear and recovery in Chromium.

Called by ``bench/media.py`` (``browser_results``); runnable alone:
``.venv/bin/python bench/_media_browser.py [--quick]``. One process, loopback: the robot
(simulator, H.264 640 × 480 at up to 30 fps, its frame numbers stamped, a 440 Hz
microphone) in a call over the memory transport with a user whose web UI relays to Debian's
chromium (fake camera and microphone), as ``tests/test_media_web.py`` sets it up. Both
clocks are this machine's wall clock, so the times below need no clock sync.

- ``glass_p50_ms`` / ``glass_p99_ms``: the robot's capture time of a picture (when the
  camera gave it) to the moment Chromium decoded it and drew it on the canvas: encoding
  (x264 in a worker thread), fragments, the call, reassembly, the websocket, WebCodecs.
  Targets 30 / 60 ms.
- ``audio_ms``: mouth to ear p50, the robot microphone's sample (a packet's first sample)
  to the moment the page's AudioWorklet played it, through the jitter buffer (40–80 ms
  target depth) and the context's output timestamp. Target 80 ms.
- ``recover_ms``: recovery after a lost keyframe at 10 % loss: with 10 % random loss on
  the robot's link, one frame is dropped each second and so is the first keyframe sent
  to repair it; the page's picture then stands still until the repeated request's
  keyframe arrives. Measured from the moment the keyframe was lost to the first picture
  the page shows after it (p50; the whole freeze, from the last picture before the first
  loss, is printed too). Target 300 ms + RTT (requests are repeated, and keyframes
  forced, at most once per max(RTT, 300 ms)). Periodic keyframes are off (30 s), so only
  requests repair.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from telebot.channels.channel import Channel
from telebot.services.video.wire import CODEC_KEYFRAME, FRAGMENT_HEADER, KIND_FRAGMENT
from test_media_web import MediaRig, media_rig, stats, wait_stats

__all__ = ["browser_results"]


def pct(values: list[float], q: float) -> float:
    """The ``q`` quantile (nearest rank) of ``values``."""
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


class KeyframeLoser:
    """Wraps the robot's video channel: every ``every`` s drops one frame, then the first
    keyframe sent after it (all their fragments), and notes when each episode began."""

    def __init__(self, channel: Channel, every: float = 1.0) -> None:
        self.channel = channel
        self.every = every
        self.episodes: list[float] = []  # wall ms at which a frame was dropped
        self.keys_lost: list[float] = []  # wall ms at which its repairing keyframe was dropped
        self._original = channel.send
        self._next = time.time() + every
        self._phase = "idle"
        self._dropping: int | None = None
        channel.send = self._send  # type: ignore[method-assign]

    def close(self) -> None:
        del self.channel.send

    def last_episode(self) -> None:
        """Begin no episode after the one under way, if any (its keyframe is still lost)."""
        self.every = math.inf
        if self._phase == "idle":
            self._next = math.inf

    def _send(self, payload: str | bytes) -> None:
        if isinstance(payload, bytes) and payload[:1] == bytes((KIND_FRAGMENT,)):
            codec, frame_id = payload[1], FRAGMENT_HEADER.unpack_from(payload)[3]
            key = bool(codec & CODEC_KEYFRAME)
            if frame_id == self._dropping:
                return  # the rest of a frame being dropped
            if self._phase == "idle" and not key and time.time() >= self._next:
                self._dropping, self._phase = frame_id, "key"
                self.episodes.append(time.time() * 1000)
                return
            if self._phase == "key" and key:
                self._dropping, self._phase = frame_id, "idle"
                self.keys_lost.append(time.time() * 1000)
                self._next = time.time() + self.every
                return
        self._original(payload)


async def measure(rig: MediaRig, seconds: float, loss_seconds: float) -> dict[str, float]:
    """Glass and audio for ``seconds`` on a clean link, then recovery under loss for
    ``loss_seconds`` and until a lost keyframe's picture has come at least once."""
    page = rig.page
    await wait_stats(page, "s.videoDecoded >= 10 && s.audioMs.length >= 10", timeout=30)
    await page.evaluate(
        "() => { const s = window.telebotMedia.stats; s.glassMs.length = 0;"
        " s.audioMs.length = 0; s.audioTransitMs.length = 0; }"
    )
    await asyncio.sleep(seconds)
    s = await stats(page)
    glass, audio = s["glassMs"], s["audioMs"]
    print(
        f"  glass: {len(glass)} pictures {s['width']} x {s['height']} {s['codec']}, "
        f"p50 {pct(glass, 0.5):.1f} ms, p99 {pct(glass, 0.99):.1f} ms"
    )
    transit = s["audioTransitMs"]
    print(
        f"  audio: {len(audio)} packets played, mouth to ear p50 {pct(audio, 0.5):.1f} ms, "
        f"p99 {pct(audio, 0.99):.1f} ms (arrival p50 {pct(transit, 0.5):.1f} ms; jitter "
        f"buffer target {s['audioTarget']:.0f} ms, level {s['audioLevel']:.0f} ms; output "
        f"latency {s['audioOutputMs']:.0f} ms; {s['audioUnderruns']} underruns)"
    )
    sender = rig.server.video_of(rig.client.call.id)
    assert sender is not None
    before = len(s["recoveredAt"])
    loser = KeyframeLoser(sender.channel)
    rig.hub.link("robot", "user").loss = 0.1
    try:
        await asyncio.sleep(loss_seconds)
        async with asyncio.timeout(30):
            while not loser.keys_lost:  # noqa: ASYNC110  (a lost keyframe wakes nobody)
                await asyncio.sleep(0.05)
        # A loaded machine can take longer than an episode to repair one: episodes in a row
        # would keep the picture still. The first lost keyframe's repair ends the phase.
        loser.last_episode()
        await wait_stats(page, f"s.recoveredAt.some((t) => t > {loser.keys_lost[0]})")
    finally:
        rig.hub.link("robot", "user").loss = 0.0
        loser.close()
    s = await stats(page)
    ends, times = s["recoveredAt"][before:], s["recoveries"][before:]
    # Each episode: the freeze that ended first after it began (last picture before the
    # loss to the first after it), and the time from its lost keyframe to that picture.
    freezes, after_key = [], []
    for lost in loser.keys_lost:
        for end, took in zip(ends, times, strict=True):
            if end > lost:
                freezes.append(took)
                after_key.append(end - lost)
                break
    rtt = (rig.client.call.stats.rtt or 0.0) * 1000
    print(
        f"  10 % loss: {len(times)} freezes, p50 {statistics.median(times):.0f} ms; with a lost "
        f"keyframe ({len(after_key)} episodes): picture still for p50 "
        f"{statistics.median(freezes):.0f} ms, from the lost keyframe to the next picture p50 "
        f"{statistics.median(after_key):.0f} ms, max {max(after_key):.0f} ms (RTT {rtt:.1f} ms)"
    )
    return {
        "glass_p50_ms": pct(glass, 0.5),
        "glass_p99_ms": pct(glass, 0.99),
        "audio_ms": pct(audio, 0.5),
        "recover_ms": statistics.median(after_key),
    }


async def browser_results(quick: bool) -> dict[str, float]:
    """Glass p50/p99, audio mouth-to-ear p50 and recovery after a lost keyframe (ms)."""
    with tempfile.TemporaryDirectory() as tmp:
        width, height = (320, 240) if quick else (640, 480)
        async with media_rig(Path(tmp), width=width, height=height, fps=30) as rig:
            return await measure(rig, 1.0, 0.0) if quick else await measure(rig, 10.0, 10.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick",
        action="store_true",
        help="320 x 240, 1 s of glass and audio, loss until one keyframe was lost and repaired",
    )
    results: dict[str, Any] = asyncio.run(browser_results(parser.parse_args().quick))
    print(" ".join(f"{k}={v:.2f}" for k, v in results.items()))


if __name__ == "__main__":
    main()
