"""Map transfer over a call's "map" channel: the robot's :class:`MapService`, the user's
:func:`fetch_map`.

The protocol itself (PNG encoding, offer, chunks, resends, hash) is sans-IO in
:mod:`telebot.services.proto.mapxfer`; this module only moves its datagrams and keeps time
with the event loop. Neither side starts a task: the robot is driven by the channel's
callback and loop timers, the user by the awaiting coroutine, so nothing is left running
behind a call.

Robot::

    service = MapService.attach(call, lambda: encoded)   # cache-friendly provider

User::

    download = await fetch_map(map_channel(call), progress=bar.update)
    download.save(Path("map.png"))                        # map.png + map.yaml

A map that changes (SLAM) is followed: every transfer sends the map as it is at the
request, ``download.version`` says which version that was, and the robot's telemetry
carries the current ``map_version``; when the two differ, fetch again.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from telebot.channels.channel import Channel, ReceivedDatagram
from telebot.channels.transports.base import Lane
from telebot.errors import CallEnded, ProtocolError, TelebotError
from telebot.robot.grid import OccupancyGrid
from telebot.robot.mapfile import map_yaml
from telebot.services.proto import MAP
from telebot.services.proto.mapxfer import (
    IDLE_TIMEOUT,
    MAX_CHUNK_DATA,
    RESEND_AFTER,
    EncodedMap,
    MapReceiver,
    MapSender,
    decode_map,
    png_size,
)

if TYPE_CHECKING:
    from telebot.channels.call import Call

__all__ = ["DEFAULT_BURST", "MapDownload", "MapService", "fetch_map", "map_channel"]

log = logging.getLogger("telebot.services.map")

#: Chunks the robot sends per turn of the event loop (8 × 32 KB = 256 KB): enough to fill
#: a loopback link, few enough that heartbeats and a stop are never held up behind a map.
DEFAULT_BURST = 8


def map_channel(call: Call) -> Channel:
    """The call's "map" channel, opened as both ends of the map transfer use it (BULK lane)."""
    return call.channel(MAP, lane=Lane.BULK)


# --------------------------------------------------------------------------- robot side


class MapService:
    """Serves the map on one call's "map" channel (the robot's side).

    ``provider`` returns the encoded map (:func:`~telebot.services.proto.mapxfer.encode_map`);
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


@dataclass(frozen=True, slots=True)
class MapDownload:
    """A map fetched from a robot: the PNG as sent, its georeference and the decoded grid."""

    #: The PNG bytes, SHA-256 (checked), size and georeference exactly as the robot sent them.
    encoded: EncodedMap
    #: The decoded occupancy grid (the robot's map cropped to its known cells).
    grid: OccupancyGrid
    #: Seconds from the first request to the verified hash.
    elapsed: float
    #: Chunk indices this side had to ask for again (0 on a loss-free link).
    resent: int
    #: Datagrams dropped as invalid during the transfer.
    rejected: int

    @property
    def png(self) -> bytes:
        """The map image (8-bit grey PNG: free 254, occupied 0, unknown 205)."""
        return self.encoded.png

    @property
    def resolution(self) -> float:
        """Metres per pixel."""
        return self.encoded.resolution

    @property
    def origin(self) -> tuple[float, float]:
        """World ``(x, y)`` of the lower-left corner of the image's bottom-left pixel."""
        return self.encoded.origin_x, self.encoded.origin_y

    @property
    def origin_x(self) -> float:
        """World x of the image's left edge (metres)."""
        return self.encoded.origin_x

    @property
    def origin_y(self) -> float:
        """World y of the image's bottom edge (metres)."""
        return self.encoded.origin_y

    @property
    def width(self) -> int:
        """Image width in pixels (cells along x)."""
        return self.encoded.width

    @property
    def height(self) -> int:
        """Image height in pixels (cells along y)."""
        return self.encoded.height

    @property
    def sha256(self) -> str:
        """SHA-256 of the PNG, hex (checked against the robot's offer)."""
        return self.encoded.sha256

    @property
    def name(self) -> str:
        """The map's name as the robot offered it."""
        return self.encoded.name

    @property
    def version(self) -> int:
        """The robot's map version this download shows (compare ``Telemetry.map_version``)."""
        return self.encoded.version

    def yaml(self, image_name: str) -> str:
        """The ROS map_server YAML for this map, its image saved as ``image_name``."""
        return map_yaml(image_name, *self._georeference())

    def save(self, png_path: Path) -> Path:
        """Write the PNG to ``png_path`` and its map_server YAML beside it; returns the YAML path.

        The YAML is ``png_path`` with the suffix ``.yaml`` and names the image relatively,
        so the pair can be moved together and loaded by any ROS tool.
        """
        png_path = Path(png_path)
        yaml_path = png_path.with_suffix(".yaml")
        if yaml_path == png_path:
            raise ValueError(f"{png_path}: the image needs a suffix other than .yaml")
        png_path.write_bytes(self.png)
        yaml_path.write_text(self.yaml(png_path.name), encoding="utf-8")
        return yaml_path

    def _georeference(self) -> tuple[float, float, float]:
        return self.encoded.resolution, self.encoded.origin_x, self.encoded.origin_y


async def fetch_map(
    channel: Channel,
    *,
    timeout: float = 30.0,
    progress: Callable[[int, int], None] | None = None,
    resend_after: float = RESEND_AFTER,
) -> MapDownload:
    """Fetch the robot's map over ``channel`` (see :func:`map_channel`).

    ``progress(received_bytes, total_bytes)`` is called from this coroutine whenever more
    of the map arrived (first once the robot's offer says how big it is), last with
    ``(total, total)``. The channel's callback is taken for the duration and cleared after.

    Raises ``TimeoutError`` when the map is not complete within ``timeout`` seconds (the
    robot is told to forget the transfer), ProtocolError when the robot refuses (its
    reason, e.g. "a map transfer is already running") or the map fails its checks, and
    CallEnded when the call ends meanwhile.
    """
    loop = asyncio.get_running_loop()
    receiver = MapReceiver(secrets.randbits(32), resend_after=resend_after)
    wake = asyncio.Event()
    outbox: list[str] = []

    def on_datagram(datagram: ReceivedDatagram) -> None:
        # Replies are sent by the coroutine: a send error then surfaces to the caller
        # instead of being logged and swallowed by the channel.
        outbox.extend(receiver.on_message(datagram.payload, loop.time()))
        wake.set()

    def flush() -> None:
        while outbox:
            channel.send(outbox.pop(0))

    started = loop.time()
    reported: tuple[int, int] | None = None
    channel.set_callback(on_datagram)
    try:
        async with asyncio.timeout(timeout):
            channel.send(receiver.request(loop.time()))
            while True:
                flush()
                current = receiver.progress
                if progress is not None and receiver.offer is not None and current != reported:
                    reported = current
                    progress(*current)
                if receiver.done or receiver.failed:
                    break
                wake.clear()
                deadline = receiver.next_deadline()
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout_at(deadline):
                        await wake.wait()
                outbox.extend(receiver.poll(loop.time()))
    except TimeoutError:
        _give_up(channel, receiver)
        received, total = receiver.progress
        if receiver.offer is None:
            detail = f"the robot did not answer {receiver.requests} map requests"
        else:
            detail = f"{received} of {total} bytes arrived, {receiver.resent} chunks asked again"
        raise TimeoutError(f"map transfer not complete within {timeout:g} s: {detail}") from None
    except BaseException:
        _give_up(channel, receiver)
        raise
    finally:
        channel.set_callback(None)
    elapsed = loop.time() - started  # the hash is verified: decoding is not transfer time
    if receiver.failed or receiver.result is None:
        raise ProtocolError(f"map transfer failed: {receiver.error}")
    encoded = receiver.result
    if png_size(encoded.png) != (encoded.width, encoded.height):
        width, height = png_size(encoded.png)
        raise ProtocolError(
            f"map transfer failed: the image is {width} × {height}, "
            f"the offer said {encoded.width} × {encoded.height}"
        )
    grid = decode_map(encoded.png, encoded.resolution, encoded.origin_x, encoded.origin_y)
    return MapDownload(
        encoded=encoded,
        grid=grid,
        elapsed=elapsed,
        resent=receiver.resent,
        rejected=receiver.rejected,
    )


def _give_up(channel: Channel, receiver: MapReceiver) -> None:
    """Tell the robot to forget the transfer now rather than after its idle timeout."""
    for message in receiver.cancel():
        try:
            channel.send(message)
        except TelebotError:
            return  # the call is gone: so is the robot's transfer
