"""Zenoh endpoint strings (``proto/address[?metadata][#config]``), without the zenoh library.

Used where telebot writes zenoh configs: its own sessions (:mod:`.zenoh`) and the router's
(:mod:`telebot.router.acl`).
"""

from __future__ import annotations

from typing import Final

__all__ = ["MIXED_RELIABILITY", "with_quic_datagrams"]

#: The QUIC endpoint metadata key of zenoh's mixed-reliability links.
MIXED_RELIABILITY: Final = "mixed_rel"


def with_quic_datagrams(endpoint: str) -> str:
    """``endpoint``, with ``mixed_rel=auto`` added if it is a ``quic/`` endpoint that does
    not choose for itself.

    On a mixed-reliability QUIC link zenoh sends best-effort frames (telebot's CONTROL
    and DATA lanes: see ``LANE_QOS``) as QUIC datagrams, so a lost packet costs only its
    own frame: no retransmission holds a stop or a heartbeat up. ``auto`` uses it
    when both ends offer it and falls back to QUIC streams with a zenoh that does not.
    Other endpoints are returned as they are.
    """
    if not endpoint.startswith("quic/"):
        return endpoint
    head, hash_, config = endpoint.partition("#")
    address, question, metadata = head.partition("?")
    params = [p for p in metadata.split(";") if p] if question else []
    if any(p.split("=", 1)[0] == MIXED_RELIABILITY for p in params):
        return endpoint
    params.append(f"{MIXED_RELIABILITY}=auto")
    return f"{address}?{';'.join(params)}{hash_}{config}"
