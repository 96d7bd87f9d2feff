"""A simulated robot that drives for real: map, planner, controller, laser, cameras, battery.

Deterministic for a given seed and stepped by a clock the caller passes (sans-IO: no
asyncio, no clock, no threads), so tests run it faster than real time and the daemon runs it
in real time.

``from telebot.robot.sim import SimNavStack`` gives the simulated robot (the ``"sim"`` adapter,
:class:`~telebot.robot.sim.stack.SimNavStack`) and its goal record ``SimGoal``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__all__ = ["SimGoal", "SimNavStack"]

if TYPE_CHECKING:
    from telebot.robot.sim.stack import SimGoal, SimNavStack


def __getattr__(name: str) -> Any:
    # Imported on first use, so that a light submodule (e.g. ``building`` for ``make-map``)
    # does not pull in the whole simulator, and no import cycle through ``stack`` can form.
    if name in __all__:
        from telebot.robot.sim import stack

        return getattr(stack, name)
    raise AttributeError(f"module 'telebot.robot.sim' has no attribute {name!r}")
