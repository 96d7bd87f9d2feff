"""Sans-IO service protocols: message formats, chat command parsing, map transfer.

No asyncio, no clock, no I/O: functions take payloads (and ``now``) and return messages.
"""

from __future__ import annotations

__all__ = ["CHAT", "GOALS", "MAP", "POSE", "TELEMETRY"]

#: Channel names of the robot's services (both ends open them by these names).
CHAT = "chat"
MAP = "map"
POSE = "pose"
GOALS = "goals"
TELEMETRY = "telemetry"
