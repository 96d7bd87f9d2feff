"""The gateway over WebTransport (docs/protocol.md §26.5), with a Python client (aioquic).

The same gateway as tests/test_gateway.py's (a real zenoh session behind it, one more on
the "network" side), reached over HTTP/3 on UDP: the offer at ``/webtransport`` names the
certificate the listener presents; a session is admitted with the same proof; PUTs go by
datagram or by a stream of their own, SAMPLEs come back the same way by size; what breaks
the framing is refused or cut in one line with the WebSocket's codes; sessions count
against the gateway's caps. The browser's own client over it: tests/test_browser_e2e.py.
"""

from __future__ import annotations

import base64
import hashlib
import itertools
import json
import os
from typing import Any

import pytest
from aioquic.buffer import encode_uint_var

from conftest import wait_until
from gateway_client import b64, parse_sample, proof, put_frame
from rig import ROBOT, USER
from telebot.gateway.core import Limits
from telebot.identity import Identity
from test_gateway import NS, Live, _another_gateway, _received_until, live
from webtransport_client import Session, peer_certificate_der, session

__all__ = ["live"]  # the fixture, shared with tests/test_gateway.py

HOST = "127.0.0.1"


async def _admit(wt: Session, who: Identity) -> dict[str, Any]:
    wt.open_stream()
    challenge = json.loads(await wt.receive())
    assert challenge["op"] == "challenge", challenge
    public, mac = proof(who.private_key, who.name, challenge)
    wt.send_text(
        json.dumps({"op": "admit", "name": who.name, "key": b64(public), "proof": b64(mac)})
    )
    answer: dict[str, Any] = json.loads(await wt.receive())
    return answer


def _port(live: Live) -> int:
    assert live.gateway.listener is not None
    return live.gateway.listener.port


async def test_the_offer_names_the_certificate_the_listener_presents(live: Live) -> None:
    async with live.http.get(live.gateway.url + "webtransport") as response:
        assert response.status == 200
        offer = await response.json()
    assert offer["port"] == _port(live) and offer["path"] == "/gateway"
    async with session(HOST, offer["port"]) as wt:
        assert wt.status == 200
        digest = hashlib.sha256(peer_certificate_der(wt)).digest()
    assert offer["hashes"] == [base64.b64encode(digest).decode()]
    # Another path is no session.
    async with session(HOST, offer["port"], "/elsewhere") as wt:
        assert wt.status == 404


async def test_a_gateway_without_webtransport_says_so(live: Live) -> None:
    async with _another_gateway(live, Limits(), webtransport=False) as gw:
        assert gw.listener is None
        async with live.http.get(gw.url + "webtransport") as response:
            assert response.status == 404
            assert "no WebTransport" in (await response.json())["error"]


async def test_a_session_is_admitted_and_relays_by_datagram_and_by_stream(live: Live) -> None:
    async with session(HOST, _port(live)) as wt:
        assert await _admit(wt, live.alice) == {"op": "admitted", "name": USER}
        hello_key = f"{NS}/robot/{ROBOT}/in/{USER}"
        call_key = f"{NS}/robot/{ROBOT}/call/{USER}/0123456789abcdef/data"
        big = os.urandom(20_000)

        async def datagram() -> None:
            wt.send_datagram(put_frame(hello_key, b"HELLO", lane=0))

        async def stream() -> None:
            wt.send_stream(put_frame(call_key, big))

        pattern = f"{NS}/robot/{ROBOT}/**"
        await _received_until(live.network, pattern, datagram, lambda s: s.payload == b"HELLO")
        await _received_until(live.network, pattern, stream, lambda s: s.payload == big)
        # The other way: a small SAMPLE as a datagram, a large one on a stream of its own.
        wt.send_text(json.dumps({"op": "sub", "id": 7, "key": f"{NS}/user/{USER}/**"}))
        inbox = f"{NS}/user/{USER}/0123456789abcdef/in/{ROBOT}"
        publisher = live.network.publisher(inbox)
        got: dict[int, bytes] = {}
        for payload in (b"WELCOME", os.urandom(5_000)):
            for _ in range(300):
                publisher.put(payload)
                try:
                    message = await wt.receive(timeout=0.2)
                except TimeoutError:
                    continue
                assert isinstance(message, bytes)
                assert parse_sample(message) == (7, inbox, payload)
                got[len(payload)] = message
                break
        assert set(got) == {7, 5_000}, "a SAMPLE did not reach the browser"
        assert live.gateway.stats.cut == {} and live.gateway.stats.published >= 2


@pytest.mark.parametrize(
    ("case", "code"),
    [("preamble", "garbage"), ("binary", "garbage"), ("oversize", "too_large")],
)
async def test_bad_framing_before_admission_is_refused_with_4001(
    live: Live, case: str, code: str
) -> None:
    async with session(HOST, _port(live)) as wt:
        if case == "preamble":
            wt.send_raw(b"GET / HTTP/1.1\r\n")
        else:
            wt.open_stream()
            assert json.loads(await wt.receive())["op"] == "challenge"
            if case == "binary":
                wt.send_datagram(os.urandom(100))
            else:
                wt.send_raw((1 << 30).to_bytes(4, "big"))
        messages, (close_code, reason) = await wt.until_closed()
    assert close_code == 4001 and reason == code
    if case != "preamble":  # with no stream, nothing can be said before the close
        answer = json.loads(messages[-1])
        assert answer["op"] == "refused" and answer["code"] == code and len(answer["text"]) < 300
    assert live.gateway.stats.refused == {code: 1}
    assert live.gateway.stats.admitted == 0


@pytest.mark.parametrize(
    ("case", "code"),
    [("garbage", "garbage"), ("oversize", "too_large"), ("key", "key"), ("partial", "flood")],
)
async def test_bad_input_after_admission_cuts_off_with_4008(
    live: Live, case: str, code: str
) -> None:
    async with session(HOST, _port(live)) as wt:
        assert (await _admit(wt, live.alice))["op"] == "admitted"
        if case == "garbage":
            wt.send_datagram(b"\x09\x00")
        elif case == "oversize":
            wt.send_stream(b"\x01" * 40_000)
        elif case == "partial":  # streams begun and never ended hold memory: 16 at most
            for _ in range(17):
                wt.send_partial(b"\x01\x00")
        else:
            wt.send_datagram(put_frame(f"{NS}/robot/{ROBOT}/call/bob/0123456789abcdef/ctl", b"x"))
        messages, (close_code, reason) = await wt.until_closed()
    assert close_code == 4008 and reason == code
    cut = json.loads(messages[-1])
    assert cut["op"] == "cut" and cut["code"] == code and len(cut["text"]) < 400
    assert live.gateway.stats.cut == {code: 1}


async def test_sessions_count_against_the_gateway_s_caps(live: Live) -> None:
    async with _another_gateway(live, Limits(max_connections=1)) as gw:
        assert gw.listener is not None
        async with session(HOST, gw.listener.port) as first:
            assert first.status == 200
            first.open_stream()
            assert json.loads(await first.receive())["op"] == "challenge"
            assert gw._pending == {HOST: 1}  # counted by its own address
            async with session(HOST, gw.listener.port) as second:
                assert second.status == 503
            assert gw.stats.refused == {"full": 1}
        # The first one gone, its place is free again.
        await wait_until(lambda: not gw._sockets, timeout=30)
        async with session(HOST, gw.listener.port) as third:
            assert third.status == 200


def sent_packet(number: int, sent_time: float) -> Any:
    """An application-data packet of 1,200 bytes, ack-eliciting, as aioquic records one."""
    from aioquic.quic.packet_builder import QuicSentPacket

    return QuicSentPacket(
        epoch=3,
        in_flight=True,
        is_ack_eliciting=True,
        is_crypto_packet=False,
        packet_number=number,
        packet_type=0,
        sent_time=sent_time,
        sent_bytes=1200,
    )


def test_probes_keep_coming_every_quarter_second_through_an_outage() -> None:
    from aioquic.quic.recovery import QuicPacketRecovery, QuicPacketSpace

    from telebot.gateway.webtransport import MAX_PROBE_INTERVAL, cap_probe_backoff

    def probe_times(capped: bool, rtt: float, outage: float) -> list[float]:
        """When the probes go out while nothing comes back for ``outage`` s, and the first
        one after it."""
        recovery = QuicPacketRecovery(
            congestion_control_algorithm="reno",
            initial_rtt=0.1,
            max_datagram_size=1200,
            peer_completed_address_validation=True,
            send_probe=lambda: None,
        )
        if capped:
            cap_probe_backoff(recovery)
        space = QuicPacketSpace()
        space.is_application_data = True  # type: ignore[attr-defined]
        recovery.spaces = [space]
        recovery.handshake_confirmed = True
        recovery._rtt_initialized, recovery._rtt_smoothed = True, rtt
        recovery._rtt_variance = rtt / 4

        def send(number: int, now: float) -> None:
            recovery.on_packet_sent(packet=sent_packet(number, now), space=space)

        send(0, 0.0)
        times: list[float] = []
        while True:
            due = recovery.get_loss_detection_time(amplification_limited=False)
            assert due is not None
            times.append(due)
            if due > outage:
                return times
            recovery.on_loss_detection_timeout(now=due)
            send(len(times), due)  # the probe (lost: the network is gone)

    # 4G's round trip, a 3 s outage: with RFC 9002's doubling the first probe after the heal
    # comes 2.7 s after it; capped, one goes every 0.25 s, the first within 0.25 s.
    plain, capped = probe_times(False, 0.08, 3.0), probe_times(True, 0.08, 3.0)
    assert plain[-1] - 3.0 > 1.0, plain
    assert max(b - a for a, b in itertools.pairwise(capped)) <= MAX_PROBE_INTERVAL
    assert capped[-1] - 3.0 <= MAX_PROBE_INTERVAL
    # Across an ocean the undoubled probe timeout is longer than the cap: it is kept.
    ocean = probe_times(True, 0.32, 3.0)
    assert min(b - a for a, b in itertools.pairwise(ocean)) > MAX_PROBE_INTERVAL


def test_random_loss_does_not_shrink_the_window_below_the_floor_rate() -> None:
    from aioquic.quic.congestion.reno import RenoCongestionControl

    from telebot.gateway.webtransport import MIN_RATE, FloorReno

    def lossy(control: RenoCongestionControl) -> int:
        """An ocean's round trip, then a loss every round trip for 20 of them."""
        control.on_rtt_measurement(now=0.0, rtt=0.32)
        for n in range(20):
            packet = sent_packet(n, 0.32 * n + 0.01)
            control.on_packet_sent(packet=packet)
            control.on_packets_lost(now=0.32 * n + 0.02, packets=[packet])
        return control.congestion_window

    floor = int(MIN_RATE / 8 * 0.32)
    assert lossy(RenoCongestionControl(max_datagram_size=1200)) < floor // 4  # plain Reno
    assert lossy(FloorReno(max_datagram_size=1200)) == floor
    # The floor follows the last round trip measured, down as well as up.
    near = FloorReno(max_datagram_size=1200)
    near.on_rtt_measurement(now=0.0, rtt=0.32)
    near.on_rtt_measurement(now=1.0, rtt=0.05)
    assert near.floor == int(MIN_RATE / 8 * 0.05)
    persistent = FloorReno(max_datagram_size=1200)
    persistent.on_rtt_measurement(now=0.0, rtt=0.32)
    persistent.on_persistent_congestion()  # an outage
    assert persistent.congestion_window == floor


async def test_through_a_lossy_link_streams_arrive_whole_and_most_datagrams_arrive(
    live: Live,
) -> None:
    # The `bad` profile (80 ± 40 ms, 5 % loss in bursts, 1 Mbit/s) between the browser and
    # the gateway's UDP port: admission and text ride the reliable stream, each large SAMPLE
    # its own stream (resent until whole), datagrams are lost now and then, never late.
    from telebot.netem import NetemProxy

    target = f"udp/{HOST}:{_port(live)}"
    with NetemProxy("bad", f"udp/{HOST}:0", target, seed=7) as proxy:
        port = int(proxy.endpoint.rpartition(":")[2])
        async with session(HOST, port) as wt:
            assert await _admit(wt, live.alice) == {"op": "admitted", "name": USER}
            wt.send_text(json.dumps({"op": "sub", "id": 1, "key": f"{NS}/user/{USER}/**"}))
            inbox = f"{NS}/user/{USER}/0123456789abcdef/in/{ROBOT}"
            publisher = live.network.publisher(inbox)
            pictures = [bytes([n]) * 5_000 for n in range(20)]
            first = pictures[0]
            for _ in range(300):  # until the subscription is declared
                publisher.put(first)
                try:
                    message = await wt.receive(timeout=0.2)
                except TimeoutError:
                    continue
                if isinstance(message, bytes) and parse_sample(message)[2] == first:
                    break
            for picture in pictures[1:]:
                publisher.put(picture)
            got: set[bytes] = set()
            while not set(pictures[1:]) <= got:  # every one, whole (else a timeout here)
                message = await wt.receive(timeout=30)
                assert isinstance(message, bytes)
                got.add(parse_sample(message)[2])
            # 100 small PUTs as datagrams, 20 ms apart: most go through, some may not.
            call_key = f"{NS}/robot/{ROBOT}/call/{USER}/0123456789abcdef/ctl"
            seen: list[bytes] = []
            sub = live.network.subscribe(
                call_key, lambda batch: seen.extend(s.payload for s in batch)
            )
            try:
                for n in range(100):
                    wt.send_datagram(put_frame(call_key, n.to_bytes(2, "big"), lane=0))
                    await wt.pump(0.02)
                await wait_until(lambda: len(seen) >= 50, timeout=30)
            finally:
                sub.close()
            sent = {n.to_bytes(2, "big") for n in range(100)}
            assert len(set(seen)) == len(seen) and set(seen) <= sent  # none twice, none made up
    assert live.gateway.stats.cut == {}


def test_the_certificate_is_short_lived_and_made_anew_half_way() -> None:
    import datetime

    from cryptography import x509

    from telebot.gateway.webtransport import CERT_DAYS, WebTransportListener

    now = [datetime.datetime(2026, 11, 27, tzinfo=datetime.UTC)]

    async def never(session: Any) -> None:
        raise AssertionError("no session here")

    listener = WebTransportListener(
        HOST, 0, admits=lambda s: None, serve_session=never, max_message=1, clock=lambda: now[0]
    )
    cert = listener._configuration.certificate
    assert isinstance(cert, x509.Certificate)
    life = cert.not_valid_after_utc - cert.not_valid_before_utc
    assert (
        datetime.timedelta(days=CERT_DAYS) <= life < datetime.timedelta(days=14)
    )  # a browser's bound
    first = listener.offer()["hashes"]
    now[0] += datetime.timedelta(days=CERT_DAYS / 2 - 1)
    assert listener.offer()["hashes"] == first
    now[0] += datetime.timedelta(days=2)
    assert listener.offer()["hashes"] != first


async def test_a_session_the_browser_closes_frees_its_place_at_once(live: Live) -> None:
    async with session(HOST, _port(live)) as wt:
        assert (await _admit(wt, live.alice))["op"] == "admitted"
        assert live.gateway.stats.active == 1 and live.gateway._names == {USER: 1}
        # A capsule of a browser's own (WT_MAX_STREAMS, say) ends nothing.
        wt.send_capsule(0x190B4D3F, encode_uint_var(100))
        wt.send_text(json.dumps({"op": "unsub", "id": 3}))
        assert json.loads(await wt.receive())["code"] == "unknown_id"  # still served
        wt.close_session()  # the QUIC connection stays: only the session ends
        await wait_until(lambda: live.gateway.stats.active == 0, timeout=5)
        assert not live.gateway._sockets and live.gateway._names == {}
