"""The battery channel's one message, robot → user: ``{"percent": 87.5}``."""

from __future__ import annotations

from telebot.errors import ProtocolError
from telebot.services.messages import decode_object, encode_object, is_finite_number

#: The channel's name.
BATTERY = "battery"


def encode_level(percent: float) -> str:
    """The level as it travels."""
    return encode_object({"percent": round(percent, 1)})


def decode_level(payload: str | bytes) -> float:
    """The level in a datagram (ProtocolError if it is not one)."""
    message = decode_object(payload, what="battery level")
    percent = message.get("percent")
    if not is_finite_number(percent) or not 0 <= percent <= 100:
        raise ProtocolError("a battery level is a number from 0 to 100")
    return float(percent)
