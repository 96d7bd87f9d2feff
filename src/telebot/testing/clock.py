"""A virtual clock for in-process tests: an event loop whose time jumps when it is idle.

Everything telebot schedules in-process runs on the event loop's clock: the memory
transport's link delays and bandwidth queues (``loop.time()``, ``loop.call_at``), a
call's heartbeats, timeouts and retries. On a :class:`VirtualClockLoop` that clock starts
at 0 and stands still while callbacks run; when nothing is ready, instead of sleeping
until the next timer the loop jumps its clock to it (trio's ``MockClock(autojump)``). So a
test of "the frame arrives 50 ms later" or "the call survives 1 s of loss" takes no wall
time and sees exact times, however loaded the machine::

    from telebot.testing.clock import run_virtual

    def test_latency() -> None:
        async def main() -> None:
            ...  # MemoryHub, MemoryTransport, calls, asyncio.sleep: all virtual
        run_virtual(main())

Only for code whose waiting is on the loop: a wait for another thread (``to_thread``,
a real socket, zenoh) with no timer due blocks for real, but one with a timer pending lets
the clock jump past it, as if the thread were infinitely slow.
"""

from __future__ import annotations

import asyncio
import selectors
from collections.abc import Coroutine, Mapping
from typing import TYPE_CHECKING, Any, TypeVar

if TYPE_CHECKING:
    from _typeshed import FileDescriptorLike

__all__ = ["VirtualClockLoop", "run_virtual"]

_T = TypeVar("_T")


class _JumpingSelector(selectors.BaseSelector):
    """A selector that, when nothing is ready and a timer is due, advances the loop's
    clock to it instead of waiting (the real selector still serves the loop's own
    self-pipe, so ``call_soon_threadsafe`` keeps working)."""

    def __init__(self, loop: VirtualClockLoop) -> None:
        self._real = selectors.DefaultSelector()
        self._loop = loop

    def register(
        self, fileobj: FileDescriptorLike, events: int, data: Any = None
    ) -> selectors.SelectorKey:
        return self._real.register(fileobj, events, data)

    def unregister(self, fileobj: FileDescriptorLike) -> selectors.SelectorKey:
        return self._real.unregister(fileobj)

    def modify(
        self, fileobj: FileDescriptorLike, events: int, data: Any = None
    ) -> selectors.SelectorKey:
        return self._real.modify(fileobj, events, data)

    def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
        events = self._real.select(0)
        if events or (timeout is not None and timeout <= 0):
            return events
        if timeout is None:  # no timer at all: only another thread can wake the loop
            return self._real.select(None)
        self._loop.advance(timeout)
        return []

    def close(self) -> None:
        self._real.close()

    def get_map(self) -> Mapping[FileDescriptorLike, selectors.SelectorKey]:
        return self._real.get_map()


class VirtualClockLoop(asyncio.SelectorEventLoop):
    """An event loop on a virtual clock that jumps to the next timer whenever it is idle."""

    def __init__(self) -> None:
        self._now = 0.0
        super().__init__(_JumpingSelector(self))

    def time(self) -> float:
        """The virtual time: seconds since the loop was made, counting only jumps."""
        return self._now

    def advance(self, seconds: float) -> None:
        """Move the clock forward (the loop does it when idle; a test may too)."""
        if seconds < 0:
            raise ValueError(f"the clock cannot go back ({seconds} s)")
        self._now += seconds


def run_virtual(main: Coroutine[Any, Any, _T]) -> _T:
    """Run ``main`` to completion on a fresh :class:`VirtualClockLoop` (as ``asyncio.run``)."""
    with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
        return runner.run(main)
