"""The background tasks of a long-lived app object (a page server, a bridge).

Servers that answer callbacks (a websocket message, a robot's stream) start small tasks
they do not await: a send to a page, a chat command, a goal. :class:`BackgroundTasks`
keeps a strong reference to each (asyncio holds tasks only weakly), logs one that fails
with an unexpected error, and cancels and awaits whatever is left when its owner closes::

    self._tasks = BackgroundTasks("web UI")
    self._tasks.spawn(page.ws.send_str(text))
    ...
    await self._tasks.cancel_all()
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Coroutine
from typing import Any

from telebot.errors import CallEnded

__all__ = ["EXPECTED_ENDINGS", "BackgroundTasks"]

log = logging.getLogger(__name__)

#: How a background task may end without it being an error: its call ended, it timed
#: out, or the page it was sending to went away (its close is handled elsewhere).
EXPECTED_ENDINGS: tuple[type[BaseException], ...] = (CallEnded, TimeoutError, ConnectionError)


class BackgroundTasks:
    """Tasks started and not awaited by ``owner`` (a name for the log)."""

    def __init__(
        self, owner: str, *, expected: tuple[type[BaseException], ...] = EXPECTED_ENDINGS
    ) -> None:
        self.owner = owner
        self.expected = expected
        self._tasks: set[asyncio.Task[Any]] = set()

    def __len__(self) -> int:
        return len(self._tasks)

    def spawn(self, coro: Coroutine[Any, Any, Any]) -> asyncio.Task[Any]:
        """Run ``coro`` as a task of the running loop, kept until it ends."""
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._done)
        return task

    async def cancel_all(self) -> None:
        """Cancel every task still running and wait for them all to end."""
        tasks = list(self._tasks)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    def _done(self, task: asyncio.Task[Any]) -> None:
        self._tasks.discard(task)
        if task.cancelled():
            return
        exc = task.exception()
        if exc is not None and not isinstance(exc, self.expected):
            log.error("%s task failed", self.owner, exc_info=exc)
