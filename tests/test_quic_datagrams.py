"""QUIC links carry telebot's CONTROL and DATA lanes as QUIC datagrams (zenoh's mixed
reliability).

The endpoint rewriting is checked as text; the behaviour over two real zenoh sessions, a
QUIC link and a :class:`~telebot.netem.NetemProxy` that cuts the link for a moment: what is
published into the cut is lost, as a datagram is, instead of arriving late behind a
retransmission (a QUIC stream's behaviour, and so every lane's before).
"""

from __future__ import annotations

import asyncio
import json
import time
import uuid
from collections.abc import Sequence
from pathlib import Path

import pytest

from telebot.channels.transports.base import Lane, Sample
from telebot.channels.transports.zenoh import LANE_QOS, ZenohTransport, build_zenoh_config
from telebot.config import ZenohSettings
from telebot.netem import NetemProxy
from telebot.router import acl, certs
from telebot.testing.net import free_port


@pytest.mark.parametrize(
    ("endpoint", "expected"),
    [
        ("quic/10.0.0.5:7447", "quic/10.0.0.5:7447?mixed_rel=auto"),
        ("quic/[::1]:7447", "quic/[::1]:7447?mixed_rel=auto"),
        ("quic/host:7447?prio=1-7", "quic/host:7447?prio=1-7;mixed_rel=auto"),
        ("quic/host:7447#bind=0.0.0.0:0", "quic/host:7447?mixed_rel=auto#bind=0.0.0.0:0"),
        ("quic/host:7447?mixed_rel=0", "quic/host:7447?mixed_rel=0"),  # the user's choice
        ("quic/host:7447?a=1;mixed_rel=1", "quic/host:7447?a=1;mixed_rel=1"),
        ("tcp/host:7447", "tcp/host:7447"),
        ("tls/host:7447", "tls/host:7447"),
        ("udp/host:7447", "udp/host:7447"),
    ],
)
def test_quic_endpoints_get_mixed_reliability_unless_they_choose(
    endpoint: str, expected: str
) -> None:
    assert acl.with_quic_datagrams(endpoint) == expected


def test_sessions_and_the_router_listen_and_connect_with_quic_datagrams(tmp_path: Path) -> None:
    settings = ZenohSettings(listen=["quic/0.0.0.0:7447", "tcp/0.0.0.0:7448"], connect=["quic/r:1"])
    config = build_zenoh_config(settings)
    assert json.loads(config.get_json("listen/endpoints")) == [
        "quic/0.0.0.0:7447?mixed_rel=auto",
        "tcp/0.0.0.0:7448",
    ]
    assert json.loads(config.get_json("connect/endpoints")) == ["quic/r:1?mixed_rel=auto"]
    plan = acl.RouterPlan(
        listen_tls=("tls/0.0.0.0:7447",),
        listen_quic=("quic/0.0.0.0:7447",),
        ca=str(tmp_path / "ca.pem"),
        cert=str(tmp_path / "router.pem"),
        key=str(tmp_path / "router.key"),
    )
    router = acl.router_config(plan)
    assert router["listen"]["endpoints"] == ["tls/0.0.0.0:7447", "quic/0.0.0.0:7447?mixed_rel=auto"]


def test_control_and_data_are_best_effort_bulk_is_reliable() -> None:
    import zenoh

    reliability = {lane: qos["reliability"] for lane, qos in LANE_QOS.items()}
    assert reliability == {
        Lane.CONTROL: zenoh.Reliability.BEST_EFFORT,
        Lane.DATA: zenoh.Reliability.BEST_EFFORT,
        Lane.BULK: zenoh.Reliability.RELIABLE,
    }


#: Frames published into the cut (one every :data:`EVERY` s), and after it.
IN_CUT, EVERY = 15, 0.02
CUT = 1.0


class Arrivals:
    """Payloads delivered by a subscription."""

    def __init__(self) -> None:
        self.payloads: list[bytes] = []

    def __call__(self, batch: Sequence[Sample]) -> None:
        self.payloads += [sample.payload for sample in batch]


async def published_until_seen(put: object, arrivals: Arrivals, tag: bytes) -> None:
    """Publish ``tag`` + a number every :data:`EVERY` s until one of them arrives."""
    assert callable(put)
    async with asyncio.timeout(20):
        n = 0
        while not any(p.startswith(tag) for p in arrivals.payloads):
            put(tag + str(n).encode())
            n += 1
            await asyncio.sleep(EVERY)


@pytest.mark.zenoh
async def test_frames_published_into_a_cut_quic_link_are_lost_not_late(tmp_path: Path) -> None:
    tls = tmp_path / "tls"
    certs.init_ca(tls, [])
    listen = f"quic/127.0.0.1:{free_port('udp')}"
    robot = ZenohTransport(
        ZenohSettings(
            listen=[listen],
            multicast_scouting=False,
            options={
                "transport/link/tls/listen_certificate": str(tls / "router.pem"),
                "transport/link/tls/listen_private_key": str(tls / "router.key"),
            },
        )
    )
    key = f"test/{uuid.uuid4().hex}/ctl"
    arrivals = Arrivals()
    async with robot, NetemProxy("lan", "quic/127.0.0.1:0", listen, seed=1) as proxy:
        user = ZenohTransport(
            ZenohSettings(
                mode="client",
                connect=[proxy.endpoint],
                multicast_scouting=False,
                options={"transport/link/tls/root_ca_certificate": str(tls / "ca.pem")},
            )
        )
        async with user:
            robot.subscribe(key, arrivals)
            publisher = user.publisher(key, Lane.CONTROL)
            await published_until_seen(publisher.put, arrivals, b"before-")
            proxy.outage(CUT)  # returns once the cut is on
            cut_at = time.monotonic()
            await asyncio.sleep(CUT / 5)
            published = 0
            # Only well inside the cut (a loaded machine may oversleep).
            while published < IN_CUT and time.monotonic() - cut_at < CUT * 0.7:
                publisher.put(b"cut-" + str(published).encode())
                published += 1
                await asyncio.sleep(EVERY)
            await asyncio.sleep(CUT)  # healed
            await published_until_seen(publisher.put, arrivals, b"after-")
            await asyncio.sleep(0.5)  # a retransmission would have come by now
    in_cut = [p for p in arrivals.payloads if p.startswith(b"cut-")]
    # On a stream every one of them arrives once the link heals; as datagrams, none does.
    assert published >= 3
    assert len(in_cut) < (published + 1) // 2, (published, in_cut)
