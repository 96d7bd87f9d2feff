"""Client-level followers: streams an app keeps up to date from a :class:`RobotClient`.

A follower sits above the client host and uses only its public API (requests, latest
values, connection events), so the web page and the Foxglove bridge follow the robot the
same way instead of each writing its own loop.

:class:`MapFollower` keeps the robot's map: it fetches it once, then again whenever the
robot's telemetry announces another ``map_version``, and carries on across reconnections
(a transfer cut by a drop is made again on the next call). Its guards, so that a robot
cannot make it fetch in a loop:

- one transfer at a time (telemetry arriving meanwhile is looked at afterwards);
- nothing is fetched for a version the map it holds already has;
- a version whose fetch failed (the robot refused it, the map was malformed or too large,
  the transfer timed out) or whose fetch delivered another version is not asked for again
  until telemetry announces a different version or the call reconnects;
- nothing is fetched once the client has finished.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Literal, TypeVar

from telebot.errors import CallEnded, TelebotError

if TYPE_CHECKING:
    from types import TracebackType

    from telebot.services.client import ConnectionEvent, RobotClient
    from telebot.services.mapxfer.user import MapDownload

__all__ = ["MapFollower"]

log = logging.getLogger(__name__)

T = TypeVar("T")

#: The version the first fetch was made for is not known (no telemetry had arrived).
_UNKNOWN: Literal["unknown"] = "unknown"


class MapFollower:
    """The robot's map, fetched again when the robot's ``map_version`` changes.

    ``async with MapFollower(client) as maps:`` (or :meth:`start` / :meth:`aclose`);
    :attr:`map` is the newest map that arrived (``None`` until one has), listeners in
    :attr:`on_map` hear each map that arrives and those in :attr:`on_error` each failed
    fetch (the map held stays). ``timeout`` bounds one transfer (s).
    """

    def __init__(self, client: RobotClient, *, timeout: float = 120.0) -> None:
        self.client = client
        self.timeout = timeout
        #: The newest map that arrived (``None`` until the first has).
        self.map: MapDownload | None = None
        #: The last fetch's error (``None`` after a fetch that succeeded).
        self.error: Exception | None = None
        #: Transfers started (the first, again after a drop, again for a changed map).
        self.fetches = 0
        #: Fetches started because the robot's telemetry announced another map version.
        self.refreshes = 0
        #: Called with each map that arrives (on the event loop).
        self.on_map: list[Callable[[MapDownload], None]] = []
        #: Called with the error of each fetch that failed while the client goes on.
        self.on_error: list[Callable[[Exception], None]] = []
        #: The announced version the last fetch was made for (``None``: any may be asked).
        self._asked: int | Literal["unknown"] | None = None
        self._task: asyncio.Task[None] | None = None

    async def __aenter__(self) -> MapFollower:
        self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()

    def start(self) -> None:
        """Fetch the map and follow the robot's changes to it (until :meth:`aclose`)."""
        if self._task is None:
            self.client.on_connection.append(self._on_connection)
            self._task = asyncio.get_running_loop().create_task(
                self._run(), name=f"map-follower-{self.client.robot}"
            )

    async def aclose(self) -> None:
        """Stop following (a transfer under way is abandoned)."""
        task, self._task = self._task, None
        if task is None:
            return
        with contextlib.suppress(ValueError):
            self.client.on_connection.remove(self._on_connection)
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task

    def _on_connection(self, event: ConnectionEvent) -> None:
        if event.state == "reconnected":
            self._asked = None  # a new call: a fetch that failed may succeed on it

    async def _run(self) -> None:
        try:
            latest = self.client.latest_telemetry.value
            await self._fetch(latest.map_version if latest is not None else _UNKNOWN)
            while True:
                version = (await self.client.telemetry(timeout=None)).map_version
                if self._wants(version):
                    log.info("the robot's map changed (version %s): fetching it again", version)
                    self.refreshes += 1
                    await self._fetch(version)
        except CallEnded:
            return  # the client finished: no map will come

    def _wants(self, version: int) -> bool:
        """Whether telemetry announcing ``version`` calls for a fetch (see the guards)."""
        if self.map is not None and self.map.version == version:
            self._asked = version
            return False
        if self._asked == _UNKNOWN and self.map is None:
            # The first fetch failed before any telemetry: it was for this version.
            self._asked = version
            return False
        return version != self._asked

    async def _fetch(self, announced: int | Literal["unknown"]) -> None:
        """Fetch the map (again after a drop) for the ``announced`` version."""
        self._asked = announced
        while True:
            self.fetches += 1
            try:
                download = await self.client.get_map(timeout=self.timeout)
                break
            except CallEnded:
                if self.client.finished:
                    raise
                # The call dropped mid-transfer: fetch it again on the next call.
            except (TelebotError, TimeoutError) as exc:
                log.error("the map did not arrive: %s", exc)
                self.error = exc
                self._tell(self.on_error, exc)
                return
        self.map = download
        self.error = None
        self._tell(self.on_map, download)

    @staticmethod
    def _tell(listeners: Sequence[Callable[[T], None]], value: T) -> None:
        for listener in list(listeners):
            try:
                listener(value)
            except Exception:
                log.exception("map listener failed")
