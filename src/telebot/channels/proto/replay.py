"""A sliding replay window over 64-bit datagram counters (RFC 6479's idea, as in WireGuard).

Datagrams may arrive late or out of order, so the receiver cannot demand strictly
increasing counters; it accepts each counter at most once, within the last
:data:`WINDOW` counters of the highest it has seen, and refuses older ones.
"""

from __future__ import annotations

__all__ = ["WINDOW", "ReplayWindow"]

WINDOW = 2048


class ReplayWindow:
    """Remembers which of the last :data:`WINDOW` counters were accepted."""

    __slots__ = ("_bits", "_highest")

    def __init__(self) -> None:
        self._highest = -1
        self._bits = 0  # bit i set = counter (highest - i) was accepted

    def check(self, counter: int) -> bool:
        """Whether ``counter`` would be accepted (fresh and inside the window); no change."""
        if counter > self._highest:
            return True
        offset = self._highest - counter
        return offset < WINDOW and not (self._bits >> offset) & 1

    def accept(self, counter: int) -> None:
        """Mark ``counter`` as seen; call only after :meth:`check` and authentication pass."""
        if counter > self._highest:
            shift = counter - self._highest
            # A jump past the whole window forgets everything; shifting by a huge gap
            # first would allocate gigabytes (a peer chooses the counter).
            if shift >= WINDOW:
                self._bits = 1
            else:
                self._bits = ((self._bits << shift) | 1) & ((1 << WINDOW) - 1)
            self._highest = counter
        else:
            self._bits |= 1 << (self._highest - counter)
