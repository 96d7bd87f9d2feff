"""Which cipher suites this machine offers and accepts, preferred first.

``CallSettings.cipher`` is ``"auto"``, ``"aesgcm"`` or ``"chachapoly"``. A forced suite
is the only one this end accepts. ``"auto"`` accepts both and prefers AES-256-GCM when
the CPU has AES instructions, ChaCha20-Poly1305 otherwise: AES in software is slower
than ChaCha20 and, table-driven, can leak timing. The robot picks between the two ends'
lists (:func:`telebot.channels.proto.session.choose_suite`).
"""

from __future__ import annotations

import functools
import platform
import sys
from pathlib import Path

from telebot.channels.proto.noise import Suite
from telebot.config import CipherChoice

__all__ = ["cpu_has_aes", "has_aes_instructions", "suite_preference"]


def cpu_has_aes(cpuinfo: str) -> bool:
    """Whether ``/proc/cpuinfo`` text lists ``aes`` among the CPU's flags.

    x86 calls the list ``flags``, arm64 ``Features``; both name AES instructions ``aes``.
    """
    for line in cpuinfo.splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip().lower() in ("flags", "features") and "aes" in value.split():
            return True
    return False


@functools.cache
def has_aes_instructions() -> bool:
    """Whether this CPU has AES instructions; False when it cannot tell (cached)."""
    if sys.platform == "darwin":
        return platform.machine() == "arm64"  # every Apple silicon CPU has them
    try:
        return cpu_has_aes(Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace"))
    except OSError:
        return False


def suite_preference(cipher: CipherChoice, *, aes: bool | None = None) -> tuple[Suite, ...]:
    """The suites an end with setting ``cipher`` accepts, preferred first.

    ``aes`` overrides the CPU detection (for tests).
    """
    if cipher == "aesgcm":
        return (Suite.AESGCM,)
    if cipher == "chachapoly":
        return (Suite.CHACHAPOLY,)
    if cipher != "auto":
        raise ValueError(f"unknown cipher {cipher!r}: use 'auto', 'aesgcm' or 'chachapoly'")
    if has_aes_instructions() if aes is None else aes:
        return (Suite.AESGCM, Suite.CHACHAPOLY)
    return (Suite.CHACHAPOLY, Suite.AESGCM)
