"""JSON messages on service channels: one compact JSON object per text datagram."""

from __future__ import annotations

import json
import math
from typing import Any, TypeGuard

from telebot.errors import ProtocolError

__all__ = ["decode_object", "encode_object", "finite_number", "is_finite_number", "require_int"]

#: Longest JSON message a service accepts (a datagram's limit is 32 KB anyway).
MAX_MESSAGE = 32768


def encode_object(message: dict[str, Any]) -> str:
    """``message`` as compact JSON text (no NaN: such a value is a bug, so it raises)."""
    return json.dumps(message, separators=(",", ":"), ensure_ascii=False, allow_nan=False)


def decode_object(payload: str | bytes, *, what: str) -> dict[str, Any]:
    """Parse a text datagram holding one JSON object; ProtocolError names ``what`` failed."""
    if isinstance(payload, bytes):
        raise ProtocolError(f"{what}: expected a JSON text datagram, got {len(payload)} bytes")
    if len(payload) > MAX_MESSAGE:
        raise ProtocolError(f"{what}: message of {len(payload)} characters is too long")
    try:
        value = json.loads(payload, parse_constant=_refuse_constant)
    except (ValueError, RecursionError) as exc:
        raise ProtocolError(f"{what}: not JSON ({exc})") from exc
    if not isinstance(value, dict):
        raise ProtocolError(f"{what}: expected a JSON object, got {type(value).__name__}")
    return value


def _refuse_constant(name: str) -> float:
    raise ValueError(f"{name} is not allowed")


def is_finite_number(value: object) -> TypeGuard[int | float]:
    """True for an int or a float (not a bool) that is finite as a float: a JSON integer
    too large for a float (``1e400`` written out) is not, and raises nothing."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def finite_number(message: dict[str, Any], key: str, *, what: str) -> float:
    """``message[key]`` as a finite float; ProtocolError if missing or not a finite number."""
    value = message.get(key)
    if not is_finite_number(value):
        raise ProtocolError(f"{what}: {key!r} must be a finite number")
    return float(value)


def require_int(
    message: dict[str, Any], key: str, *, what: str, low: int = 0, high: int = 2**32 - 1
) -> int:
    """``message[key]`` as an int in ``[low, high]``; ProtocolError otherwise."""
    value = message.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ProtocolError(f"{what}: {key!r} must be an integer in {low}..{high}")
    return value
