"""The user's side of map transfer: :func:`fetch_map` and :class:`MapDownload` (see the
service's overview in :mod:`telebot.services.mapxfer`).
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
from telebot.errors import ProtocolError, TelebotError
from telebot.robot.grid import OccupancyGrid
from telebot.robot.mapfile import map_yaml
from telebot.services.mapxfer.wire import (
    RESEND_AFTER,
    EncodedMap,
    MapReceiver,
    decode_map,
    png_size,
)

if TYPE_CHECKING:
    pass

__all__ = ["MapDownload", "fetch_map"]

log = logging.getLogger(__name__)


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
