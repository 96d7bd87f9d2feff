"""What both sides of a media call share: audio blocks, the audio channel's two directions, pacing."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from telebot.channels.channel import Channel, ReceivedDatagram
from telebot.errors import CallEnded, ProtocolError, TelebotError
from telebot.services.media.wire import (
    FRAME_MS,
    AudioPacket,
    AudioSequencer,
    encode_audio,
    parse_media_report,
)
from telebot.services.video.stream import REPORT_INTERVAL

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt


__all__ = ["BLOCK", "IDLE_AFTER", "AudioBlock", "Unsubscribe"]

log = logging.getLogger(__name__)


#: Seconds of one audio block / packet.
BLOCK = FRAME_MS / 1000


@dataclass(frozen=True, slots=True)
class AudioBlock:
    """Decoded audio: 48 kHz mono int16 samples (20 ms per packet; silence for a lost one)."""

    samples: npt.NDArray[np.int16]
    seq: int
    #: Sender's wall clock at the first sample (0 for a concealed block).
    capture_time: float
    #: This side's wall clock when decoded.
    received_time: float


class _AudioOut:
    """Sends AUDIO packets on one channel while its receiver's reports come; with ``probe``
    (the user's microphone) also for that long from the first wish to send, before any."""

    def __init__(
        self, channel: Channel, loop: asyncio.AbstractEventLoop, *, probe: float = 0.0
    ) -> None:
        self.channel = channel
        self._loop = loop
        self.probe = probe
        self._probe_from: float | None = None
        self._last_report: float | None = None
        self._bye = False
        self._seq = 0
        self.sent = 0
        self.rejected = 0
        channel.set_callback(self._on_datagram)

    def watching(self, now: float) -> bool:
        """Whether to send now (a sender asks just before it sends)."""
        at = self._last_report
        if at is None:
            if self.probe <= 0:
                return False
            if self._probe_from is None:
                self._probe_from = now
            return now - self._probe_from <= self.probe
        return not self._bye and now - at <= IDLE_AFTER

    def _on_datagram(self, datagram: ReceivedDatagram) -> None:
        try:
            report = parse_media_report(datagram.payload)
        except ProtocolError:
            self.rejected += 1
            return
        self._last_report = self._loop.time()
        self._bye = report.bye

    def send(self, packet: bytes, capture_time: float) -> None:
        self.channel.send(encode_audio(self._seq, capture_time, packet))
        self._seq += 1
        self.sent += 1

    def close(self) -> None:
        self.channel.set_callback(None)


class _AudioIn:
    """Takes AUDIO packets on one channel and reports back every 200 ms while running.

    With ``wait_for_media`` (the robot, on ``audio/user``) the reports begin only with the
    first packet taken: a call that sends no voice gets no reports (§25).
    """

    def __init__(
        self,
        channel: Channel,
        on_packets: Callable[[list[AudioPacket | None]], None],
        loop: asyncio.AbstractEventLoop,
        report_interval: float = REPORT_INTERVAL,
        *,
        wait_for_media: bool = False,
    ) -> None:
        self.channel = channel
        self.sequencer = AudioSequencer()
        self._on_packets = on_packets
        self._loop = loop
        self.report_interval = report_interval
        self.wait_for_media = wait_for_media
        self._timer: asyncio.TimerHandle | None = None
        self.running = False
        #: Whether reports are going (from start, or from the first packet).
        self.reporting = False

    def start(self) -> None:
        if self.running:
            return
        self.running = True
        self.channel.set_callback(self._on_datagram)
        if not self.wait_for_media or self.sequencer.stats.packets:
            self._start_reports()

    def _start_reports(self) -> None:
        self.reporting = True
        self._on_timer()

    def stop(self, *, bye: bool) -> None:
        if not self.running:
            return
        self.running = False
        reporting, self.reporting = self.reporting, False
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self.channel.set_callback(None)
        if bye and reporting:
            report = self.sequencer.report(int(self._loop.time() * 1000), bye=True)
            with contextlib.suppress(TelebotError):
                self.channel.send(report.encode())

    def _on_datagram(self, datagram: ReceivedDatagram) -> None:
        out = self.sequencer.on_datagram(datagram.payload, self._loop.time())
        if not self.reporting and self.running and self.sequencer.stats.packets:
            self._start_reports()  # the first voice of the call: ask for more from now on
        if out:
            self._on_packets(out)

    def _on_timer(self) -> None:
        self._timer = None
        if not self.running or not self.reporting:
            return
        report = self.sequencer.report(int(self._loop.time() * 1000))
        try:
            self.channel.send(report.encode())
        except CallEnded:
            self.running = self.reporting = False
            return
        except TelebotError as exc:
            log.debug("audio report not sent: %s", exc)
        self._timer = self._loop.call_later(self.report_interval, self._on_timer)


async def _pace(loop: asyncio.AbstractEventLoop, on_block: Callable[[float], None]) -> None:
    """Call ``on_block(now)`` every 20 ms of the loop's clock (never in a burst after a stall:
    a late loop skips blocks rather than sending them all at once)."""
    due = loop.time()
    while True:
        now = loop.time()
        if now < due:
            await asyncio.sleep(due - now)
            continue
        try:
            on_block(now)
        except Exception:
            log.exception("audio block failed")
        due += BLOCK
        if due < loop.time() - 5 * BLOCK:
            due = loop.time()


Unsubscribe = Callable[[], None]


#: A stream's sender stops this long after the receiver's last report.
IDLE_AFTER = 2.0
