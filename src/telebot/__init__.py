"""telebot: robot telepresence over authenticated App2App-style datagram channels.

``async with telebot.connect("guiabot") as robot:`` calls a robot and gives a
:class:`~telebot.services.client.RobotClient` (chat, goals, poses, map, stop); its
replies carry a :class:`~telebot.reasons.Reason` code to decide on.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"
__all__ = ["Reason", "RobotClient", "__version__", "connect"]

if TYPE_CHECKING:
    from telebot.reasons import Reason
    from telebot.services.client import RobotClient, connect


def __getattr__(name: str) -> Any:
    # Imported on first use, so that ``import telebot`` stays light (no zenoh, no OpenCV).
    if name in ("connect", "RobotClient"):
        from telebot.services import client

        return getattr(client, name)
    if name == "Reason":
        from telebot.reasons import Reason

        return Reason
    raise AttributeError(f"module 'telebot' has no attribute {name!r}")
