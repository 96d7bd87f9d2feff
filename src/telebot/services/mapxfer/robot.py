"""The robot's side of map transfer: :class:`MapService` (see the service's overview in
:mod:`telebot.services.mapxfer`).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

from telebot.channels.channel import Channel, ReceivedDatagram
from telebot.channels.transports.base import Lane
from telebot.errors import CallEnded, TelebotError
from telebot.services.mapxfer import MAP
from telebot.services.mapxfer.wire import IDLE_TIMEOUT, MAX_CHUNK_DATA, EncodedMap, MapSender

if TYPE_CHECKING:
    from telebot.channels.call import Call

__all__ = ["DEFAULT_BURST", "MapService", "map_channel"]

log = logging.getLogger(__name__)

#: Chunks the robot sends per turn of the event loop (8 × 32 KB = 256 KB): enough to fill
#: a loopback link, few enough that heartbeats and a stop are never held up behind a map.
DEFAULT_BURST = 8


def map_channel(call: Call) -> Channel:
    """The call's "map" channel, opened as both ends of the map transfer use it (BULK lane)."""
    return call.channel(MAP, lane=Lane.BULK)


# --------------------------------------------------------------------------- robot side


class MapService:
    """Serves the map on one call's "map" channel (the robot's side).

    ``provider`` returns the encoded map (:func:`~telebot.services.mapxfer.wire.encode_map`);
    it is called at every new transfer, so a map that changed is served as it is now.
    Encoding the 4000 × 4000 default map takes ~15 ms on the loop; a robot should pass a
    provider that encodes each map version once, ahead of time when it can
    (:meth:`~telebot.services.robot.RobotServer.encoded_map`).

    The service runs from the channel's callback and two loop handles (the chunk pump and
    the idle timer): it never raises out of a callback, counts garbage in
    :attr:`rejected`, and stops by itself when the call ends. :meth:`close` detaches it.
    """

    def __init__(
        self,
        channel: Channel,
        provider: Callable[[], EncodedMap],
        *,
        chunk_size: int = MAX_CHUNK_DATA,
        burst: int = DEFAULT_BURST,
        idle_timeout: float = IDLE_TIMEOUT,
    ) -> None:
        if burst < 1:
            raise ValueError("burst must be at least 1")
        self.channel = channel
        self.sender = MapSender(provider, chunk_size=chunk_size, idle_timeout=idle_timeout)
        self.burst = burst
        self._loop = asyncio.get_running_loop()
        self._pump_handle: asyncio.Handle | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._closed = False
        #: Unexpected failures inside the service (logged; the service carries on).
        self.errors = 0
        channel.set_callback(self._on_datagram)

    @classmethod
    def attach(
        cls,
        call: Call,
        provider: Callable[[], EncodedMap],
        *,
        chunk_size: int = MAX_CHUNK_DATA,
        burst: int = DEFAULT_BURST,
        idle_timeout: float = IDLE_TIMEOUT,
    ) -> MapService:
        """Serve the map on ``call``'s "map" channel."""
        return cls(
            map_channel(call),
            provider,
            chunk_size=chunk_size,
            burst=burst,
            idle_timeout=idle_timeout,
        )

    @property
    def rejected(self) -> int:
        """Datagrams dropped as invalid (see ``sender.rejections`` for the reasons)."""
        return self.sender.rejected

    def poll(self, now: float) -> None:
        """Expire an idle transfer at loop time ``now``.

        Optional: the service keeps its own timer; a robot that ticks anyway may call this.
        """
        if self._closed:
            return
        self.sender.poll(now)
        self._reschedule()

    def close(self) -> None:
        """Stop serving: detach from the channel and cancel the pending handles; idempotent."""
        if self._closed:
            return
        self._closed = True
        self.channel.set_callback(None)
        for handle in (self._pump_handle, self._timer):
            if handle is not None:
                handle.cancel()
        self._pump_handle = self._timer = None

    def __enter__(self) -> MapService:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _on_datagram(self, datagram: ReceivedDatagram) -> None:
        if self._closed:
            return
        try:
            replies = self.sender.on_message(datagram.payload, self._loop.time())
            if self.sender.provider_error is not None:
                log.warning("map provider failed: %s", self.sender.provider_error)
                self.sender.provider_error = None
            for reply in replies:
                self.channel.send(reply)
        except CallEnded:
            self.close()
            return
        except Exception:  # a bug here must not take the call down with it
            self.errors += 1
            log.exception("map service failed on a datagram")
        self._reschedule()

    def _reschedule(self) -> None:
        if self._closed:
            return
        if self.sender.has_pending and self._pump_handle is None:
            self._pump_handle = self._loop.call_soon(self._pump)
        deadline = self.sender.next_deadline()
        if self._timer is not None and (deadline is None or self._timer.when() != deadline):
            self._timer.cancel()
            self._timer = None
        if deadline is not None and self._timer is None:
            self._timer = self._loop.call_at(deadline, self._on_timer)

    def _pump(self) -> None:
        """Send one burst of chunks, then yield to the loop before the next one."""
        self._pump_handle = None
        try:
            for chunk in self.sender.next_chunks(self.burst):
                self.channel.send(chunk)
        except CallEnded:
            self.close()
            return
        except TelebotError as exc:  # a transport hiccup: the user will ask again
            log.warning("map chunk not sent: %s", exc)
        except Exception:
            self.errors += 1
            log.exception("map service failed while sending chunks")
        self._reschedule()

    def _on_timer(self) -> None:
        self._timer = None
        try:
            self.sender.poll(self._loop.time())
        except Exception:
            self.errors += 1
            log.exception("map service failed on its timer")
        self._reschedule()


# --------------------------------------------------------------------------- user side
