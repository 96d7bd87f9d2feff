"""A telebot router on loopback with certificates, and robots and users that reach it.

Shared by tests/test_router.py and bench/fleet.py (with ``tests/`` on ``sys.path``).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from rig import FAST_SIM, GENEROUS_TIMEOUT, Process
from telebot.config import AppConfig, CallSettings, ReconnectSettings, ZenohSettings
from telebot.router import certs
from telebot.testing.net import free_port

__all__ = ["RouterRig"]


class RouterRig:
    """A router directory under ``base`` (CA, router certificate) and its process."""

    def __init__(self, base: Path, *, create: bool = True, ca: RouterRig | None = None) -> None:
        """``ca``: share that router's CA (a second router to link to it, §22.5)."""
        self.dir = base / "router"
        if create:
            if ca is None:
                certs.init_ca(self.dir)
            else:
                certs.init_ca(self.dir, ca=ca.dir / "ca.pem", ca_key=ca.dir / "ca.key")
        self.port = 0
        self.process: Process | None = None

    @classmethod
    def existing(cls, base: Path, endpoint: str) -> RouterRig:
        """The rig of a router directory made by another process, reached at ``endpoint``."""
        rig = cls(base, create=False)
        rig.port = int(endpoint.rsplit(":", 1)[1])
        return rig

    def client(self, kind: certs.Kind, name: str) -> certs.ClientCert:
        """The certificate already issued to ``name``."""
        return certs.ClientCert(kind, name, certs.client_dir(self.dir, kind, name))

    @property
    def endpoint(self) -> str:
        return f"tls/127.0.0.1:{self.port}"

    def issue(self, kind: certs.Kind, name: str) -> certs.ClientCert:
        """A client certificate for ``name`` (before :meth:`start`: the ACL is made then)."""
        return certs.issue_client(self.dir, kind, name)

    def start(self, *, port: int | None = None, extra: tuple[str, ...] = ()) -> dict[str, Any]:
        """Run ``telebot-router run`` (again on the same port if given); its ready event."""
        self.port = port if port is not None else free_port()
        self.process = Process(
            [
                "telebot.apps.router_cli",
                "run",
                str(self.dir),
                "--listen",
                self.endpoint,
                "--events",
                *extra,
            ]
        )
        line = self.process.next_line(timeout=30)
        event: dict[str, Any] = json.loads(line)
        assert event["event"] == "ready", line
        return event

    def stop(self) -> None:
        if self.process is not None:
            self.process.stop()

    def zenoh(self, client: certs.ClientCert | None) -> ZenohSettings:
        """Client-mode settings that reach the router with ``client``'s certificate."""
        tls = {}
        if client is not None:
            tls = {"ca": client.ca, "cert": client.cert, "key": client.key}
        return ZenohSettings.model_validate(
            {
                "mode": "client",
                "connect": [self.endpoint],
                "multicast_scouting": False,
                "tls": tls,
            }
        )

    def app_config(
        self, client: certs.ClientCert, *, timeout: float = GENEROUS_TIMEOUT
    ) -> AppConfig:
        """A user's config in this process: through the router, quick reconnection."""
        return AppConfig.model_validate(
            {
                "transport": {"zenoh": self.zenoh(client)},
                "call": CallSettings(timeout=timeout),
                "reconnect": ReconnectSettings(base=0.05, cap=0.5),
            }
        )

    def write_robot_config(
        self,
        path: Path,
        client: certs.ClientCert,
        *,
        timeout: float = GENEROUS_TIMEOUT,
        sim: Mapping[str, Any] | None = None,
        extra: str = "",
        endpoint: str | None = None,
    ) -> Path:
        """A robot daemon's TOML config: a client of the router (its TLS endpoint, or
        ``endpoint``), the small fast map."""
        sim = FAST_SIM if sim is None else sim
        lines = [
            "[transport.zenoh]",
            'mode = "client"',
            f"connect = [{json.dumps(endpoint or self.endpoint)}]",
            "multicast_scouting = false",
            "[transport.zenoh.tls]",
            f"ca = {json.dumps(str(client.ca))}",
            f"cert = {json.dumps(str(client.cert))}",
            f"key = {json.dumps(str(client.key))}",
            "[call]",
            f"timeout = {timeout}",
            "[sim]",
            *(f"{k} = {json.dumps(v)}" for k, v in sim.items()),
            extra,
        ]
        path.write_text("\n".join(lines) + "\n")
        return path
