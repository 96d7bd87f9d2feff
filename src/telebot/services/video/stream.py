"""What both sides of the video stream share: its channel, report interval, rate meter."""

from __future__ import annotations

import logging
from collections import deque
from typing import TYPE_CHECKING

from telebot.channels.channel import Channel
from telebot.channels.transports.base import Lane
from telebot.errors import CallEnded
from telebot.services.media.wire import (
    CODEC_H264,
    CODEC_VP8,
)
from telebot.services.video.wire import (
    CODEC_JPEG,
    VIDEO,
)

if TYPE_CHECKING:
    from telebot.channels.call import Call

__all__ = ["DECODED_CODECS", "REPORT_INTERVAL", "video_channel"]

log = logging.getLogger(__name__)


#: Seconds between receiver reports (they are also the sender's sign that someone watches).
REPORT_INTERVAL = 0.2


#: What a Python receiver decodes (PyAV), best first.
DECODED_CODECS = (CODEC_H264, CODEC_VP8, CODEC_JPEG)


#: Window (s) over which frame rates are measured.
_RATE_WINDOW = 1.0


def video_channel(call: Call) -> Channel:
    """The call's "video" channel as both ends open it: BULK lane, every datagram kept.

    (Never *latest only*: that would drop all but the last fragment of a frame.)
    """
    return call.channel(VIDEO, lane=Lane.BULK)


class _RateMeter:
    """Events (or an amount of them, such as bytes) per second over the last
    :data:`_RATE_WINDOW` seconds."""

    def __init__(self) -> None:
        self._times: deque[tuple[float, int]] = deque()
        self._sum = 0

    def tick(self, now: float, amount: int = 1) -> None:
        self._times.append((now, amount))
        self._sum += amount
        self._trim(now)

    def rate(self, now: float) -> float:
        self._trim(now)
        return self._sum / _RATE_WINDOW

    def _trim(self, now: float) -> None:
        while self._times and self._times[0][0] <= now - _RATE_WINDOW:
            self._sum -= self._times.popleft()[1]


async def _until_call_ends(channel: Channel) -> None:
    """Return when the channel's call ends.

    The channel is in callback mode, so nothing is ever queued for ``receive()``: it
    returns (raises CallEnded) only when the call ends.
    """
    while True:
        try:
            await channel.receive()
        except CallEnded:
            return
