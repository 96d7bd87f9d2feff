"""Network helpers for tests and benchmarks that run real processes on loopback."""

from __future__ import annotations

import socket
from typing import Literal

__all__ = ["free_port"]


def free_port(kind: Literal["tcp", "udp"] = "tcp") -> int:
    """A free loopback port: a TCP (or, with ``kind="udp"``, UDP) port on 127.0.0.1
    that was free a moment ago.

    The port is released before it is returned, so another process may take it before
    the caller binds it: races are the caller's concern.
    """
    if kind not in ("tcp", "udp"):
        raise ValueError(f"free_port: kind must be 'tcp' or 'udp', not {kind!r}")
    sock_type = socket.SOCK_STREAM if kind == "tcp" else socket.SOCK_DGRAM
    with socket.socket(socket.AF_INET, sock_type) as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
    return port
