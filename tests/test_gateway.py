"""The browser gateway (docs/protocol.md §26): admission, key rules, budgets, garbage,
invites, HTTPS on the router and the robot, and the JavaScript link against a live gateway.

A real gateway (aiohttp, in this process or in ``telebot-router run`` / ``telebot-robot
run``) over real zenoh sessions on loopback; browsers are aiohttp websocket clients that
compute the admission proof from the document (``tests/gateway_client.py``) and, once,
node running ``web/src/gateway-link.js``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import shutil
import ssl
import subprocess
import sys
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from conftest import Homes, wait_until
from gateway_client import GatewayTransport, admit, b64, parse_sample, proof, put_frame
from rig import ROBOT, USER, Process, write_config
from router_rig import RouterRig
from telebot.apps import robot_cli, router_cli
from telebot.channels.call import UserEndpoint
from telebot.channels.transports.base import Lane, Sample
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.channels.transports.zenoh import ZenohTransport
from telebot.config import CallSettings, RobotConfig, ZenohSettings, load_toml
from telebot.errors import ConfigError
from telebot.gateway.admission import (
    USERS_FILE,
    ContactsAdmitter,
    GatewayUsers,
    UsersAdmitter,
    contact_key,
    create_invite,
    read_invites,
)
from telebot.gateway.core import (
    MAX_PAYLOAD,
    Budget,
    CopyFilter,
    KeyRules,
    Limits,
    OutQueue,
    Refusal,
    TokenBucket,
    make_challenge,
    parse_op,
    parse_put,
)
from telebot.gateway.server import Gateway
from telebot.gateway.tls import self_signed, server_context
from telebot.identity import ContactBook, Identity, KnownRobots, Role
from telebot.services.client import RobotClient
from telebot.testing.net import free_port

ROOT = Path(__file__).resolve().parent.parent
NS = "telebot"

# --- the sans-IO core ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("method", "key", "allowed"),
    [
        ("may_put", "telebot/robot/guiabot/in/alice", True),
        ("may_put", "telebot/robot/guiabot/in", True),
        ("may_put", "telebot/robot/guiabot/call/alice/0123456789abcdef/ctl", True),
        ("may_put", "telebot/robot/guiabot/call/alice/0123456789abcdef/data", True),
        ("may_put", "telebot/robot/guiabot/in/bob", False),  # another user's name
        ("may_put", "telebot/robot/guiabot/call/bob/0123456789abcdef/data", False),
        ("may_put", "telebot/robot/guiabot/call/alice/0123456789abcdef/other", False),
        ("may_put", "telebot/user/bob/0123456789abcdef/in/guiabot", False),  # a robot's key
        ("may_put", "telebot/robot/*/in/alice", False),  # wildcards are not keys
        ("may_put", "other/robot/guiabot/in/alice", False),  # another namespace
        ("may_put", "telebot/robot/guiabot/in/alice/x", False),
        ("may_put", "telebot/robot/" + "g" * 300 + "/in/alice", False),  # too long
        ("may_subscribe", "telebot/user/alice/**", True),
        ("may_subscribe", "telebot/user/alice/0123456789abcdef/in/*", True),
        ("may_subscribe", "telebot/user/alice/0123456789abcdef/call/guiabot/0011/ctl", True),
        ("may_subscribe", "telebot/user/bob/**", False),
        ("may_subscribe", "telebot/user/*/**", False),
        ("may_subscribe", "telebot/**", False),
        ("may_subscribe", "telebot/user/alice/**/in", False),  # ** only last
        ("may_subscribe", "telebot/user/alice/$*x", False),
        ("may_subscribe", "telebot/robot/guiabot/**", False),
        ("may_declare_token", "telebot/presence/user/alice/0123456789abcdef", True),
        ("may_declare_token", "telebot/presence/user/bob/0123456789abcdef", False),
        ("may_declare_token", "telebot/presence/user/alice/*", False),
        ("may_declare_token", "telebot/presence/robot/guiabot/KEY", False),
        ("may_watch", "telebot/presence/robot/*/*", True),
        ("may_watch", "telebot/presence/robot/guiabot/*", True),
        ("may_watch", "telebot/presence/user/*/*", False),
        ("may_watch", "telebot/presence/robot/**", False),
    ],
)
def test_the_key_rules_are_the_routers_user_rules(method: str, key: str, allowed: bool) -> None:
    assert getattr(KeyRules(NS, USER), method)(key) is allowed


def test_the_admission_proof_matches_the_documents_vector() -> None:
    challenge = make_challenge(bytes(range(32, 64)), bytes(range(64, 96)))
    user = Identity("alice", bytes(range(32)))
    message = challenge.message(NS)
    assert message["gateway"] == "NYBy1jZYgNGu6jKa35EhODhR7SGijjt16WXQ0s0WYlQ"
    assert message["nonce"] == "QEFCQ0RFRkdISUpLTE1OT1BRUlNUVVZXWFlaW1xdXl8"
    assert b64(user.public_key) == "j0DFrbaPJWJK5bIU6nZ6bslNgp09e14a0bpvPiE4KF8"
    public, mac = proof(user.private_key, "alice", message)  # from the document's formula
    assert b64(mac) == "fgtcjEgNPRuPt8WQX63N6uobseO_X3nZGlf-GzdXTek"
    assert challenge.verify("alice", public, mac)
    assert not challenge.verify("alicf", public, mac)
    assert not challenge.verify("alice", bytes(32), mac)  # a low-order key proves nothing


def test_a_token_bucket_refills_at_its_rate_up_to_its_burst() -> None:
    bucket = TokenBucket(rate=10, burst=5)
    assert all(bucket.take(1, now=0.0) for _ in range(5))
    assert not bucket.take(1, now=0.0)
    assert bucket.take(1, now=0.1) and not bucket.take(1, now=0.1)
    assert all(bucket.take(1, now=100.0) for _ in range(5))  # capped at the burst
    assert not bucket.take(1, now=100.0)


def test_a_budget_refuses_a_flood_of_frames_or_bytes() -> None:
    budget = Budget.of(Limits(frames_per_s=10, frames_burst=3, bytes_per_s=1e6, bytes_burst=1e6))
    for _ in range(3):
        budget.spend(10, 0.0)
    with pytest.raises(Refusal) as caught:
        budget.spend(10, 0.0)
    assert caught.value.code == "flood"
    bytes_budget = Budget.of(Limits(bytes_per_s=100, bytes_burst=100))
    with pytest.raises(Refusal, match="bytes/s"):
        bytes_budget.spend(101, 0.0)


def test_parsing_refuses_garbage_in_one_short_line() -> None:
    huge = "x" * 100_000
    for bad in [
        '{"op": "sub", "id": 1}',
        '{"op": "nope", "id": 1}',
        "[1]",
        "{",
        '{"op":"sub","id":-1,"key":"a"}',
    ]:
        with pytest.raises(Refusal) as caught:
            parse_op(bad)
        assert caught.value.code == "garbage"
    with pytest.raises(Refusal) as caught:
        parse_op(huge)
    assert caught.value.code == "too_large" and len(str(caught.value)) < 300
    with pytest.raises(Refusal) as caught:
        parse_put(bytes([9, 0, 1]) + b"k" + os.urandom(5000))
    assert (
        caught.value.code == "garbage"
        and len(str(caught.value)) < 400
        and "\n" not in str(caught.value)
    )
    assert parse_put(put_frame("a/b", b"x" * MAX_PAYLOAD)).payload == b"x" * MAX_PAYLOAD


def test_a_copied_put_carries_its_copy_id_and_a_user_s_filter_passes_each_id_once() -> None:
    put = parse_put(put_frame("a/b", b"STOP", lane=0, copy=2**64 - 1))
    assert (put.lane, put.key, put.payload, put.copy) == ("control", "a/b", b"STOP", 2**64 - 1)
    assert parse_put(put_frame("a/b", b"x")).copy is None
    for bad, why in [
        (bytes([0x80, 0, 0, 0]), "shorter than a copied PUT's header"),
        (bytes([0x80]) + bytes(9), "shorter than a copied PUT's header"),  # 10 bytes
        (bytes([0x80]) + bytes(10), "a key length of 0"),  # 11: the header, no key
        (bytes([0x83]) + bytes(8) + b"\0\1k", "lane 3"),
        (bytes([0x80]) + bytes(8) + b"\0\x09k", "a key length of 9"),
    ]:
        with pytest.raises(Refusal, match=why) as caught:
            parse_put(bad)
        assert caught.value.code == "garbage"
    copies = CopyFilter(remembered=3)
    assert [copies.first(c) for c in (1, 2, 1, 3, 2)] == [True, True, False, True, False]
    assert copies.first(4) and copies.first(1)  # 1 was the oldest of four: forgotten
    assert not copies.first(4)
    copies.forget(4)  # its PUT could not be published: its twin may be
    assert copies.first(4)


def test_sub_token_and_watch_have_a_budget_of_their_own() -> None:
    budget = Budget.of(Limits(declarations_per_s=10, declarations_burst=64))
    for _ in range(64):
        budget.declare(0.0)
        budget.spend(100, 0.0)  # PUTs do not spend it, nor it theirs
    with pytest.raises(Refusal, match="sub/token/watch") as caught:
        budget.declare(0.0)
    assert caught.value.code == "flood"
    budget.declare(0.1)  # one more after a tenth of a second
    budget.spend(100, 0.0)


def test_the_out_queue_sends_control_first_and_drops_only_data_behind_data() -> None:
    queue = OutQueue(Limits(out_frames=1024, out_bytes=1000, out_control_frames=3))
    assert queue.push(b"d" * 400, control=False) == 0
    assert queue.push(b"CTL1", control=True) == 0
    assert queue.push("alive", control=True) == 0
    dropped = sum(queue.push(bytes([n]) * 400, control=False) for n in range(5))
    assert dropped == 4 and queue.dropped_data == 4 and queue.dropped_control == 0
    assert queue.data_bytes <= 1000
    # control first, in order; then the newest data that fit, oldest first
    assert [queue.pop(), queue.pop()] == [b"CTL1", "alive"]
    assert queue.pop() == bytes([3]) * 400 and queue.pop() == bytes([4]) * 400
    assert queue.pop() is None and len(queue) == 0
    # control frames are dropped only behind control frames, beyond their own bounds
    assert sum(queue.push(f"c{n}", control=True) for n in range(5)) == 2
    assert queue.dropped_control == 2 and queue.pop() == "c2"


def test_the_out_queue_holds_data_the_connection_has_no_room_for_never_control() -> None:
    queue = OutQueue(Limits())
    queue.push(b"P" * 5000, control=False)  # a picture's fragment: a stream of its own
    queue.push(b"pose", control=False)
    queue.push(b"CTL", control=True)
    no_room = lambda item: len(item) < 1000  # noqa: E731  (QUIC's streams full)
    assert queue.pop(no_room) == b"CTL"
    assert queue.pop(no_room) is None and len(queue) == 2  # data keeps its order
    assert queue.pop(lambda item: True) == b"P" * 5000 and queue.pop(no_room) == b"pose"


# --- a live gateway in this process --------------------------------------------------------


@dataclass
class Live:
    gateway: Gateway
    network: ZenohTransport  # another zenoh session: what the rest of the network sees
    home: Path
    contacts: ContactBook
    alice: Identity
    bob: Identity
    http: aiohttp.ClientSession

    @property
    def ws_url(self) -> str:
        return self.gateway.url + "gateway"

    async def connect(self) -> aiohttp.ClientWebSocketResponse:
        return await self.http.ws_connect(self.ws_url, max_msg_size=0)

    async def admitted(self, who: Identity) -> aiohttp.ClientWebSocketResponse:
        ws = await self.connect()
        answer = await admit(ws, who)
        assert answer == {"op": "admitted", "name": who.name}
        return ws


async def _received_until(
    network: ZenohTransport, pattern: str, send: Callable[[], Any], what: Callable[[Sample], bool]
) -> list[Sample]:
    """Subscribe on the network and ``send`` again until a sample ``what`` accepts arrives
    (the two sessions may still be connecting); every sample seen."""
    got: list[Sample] = []
    sub = network.subscribe(pattern, lambda batch: got.extend(batch))
    try:
        for _ in range(300):
            await send()
            try:
                await wait_until(lambda: any(what(s) for s in got), timeout=0.2)
                return got
            except AssertionError:
                continue
        raise AssertionError(f"nothing matching arrived on {pattern}")
    finally:
        sub.close()


@pytest.fixture
async def live(tmp_path: Path) -> AsyncIterator[Live]:
    port = free_port()
    home = tmp_path / "robot"
    alice, bob = Identity.generate(USER), Identity.generate("bob")
    contacts = ContactBook.load(home)
    contacts.add(USER, alice.public_key, Role.DRIVER)
    contacts.add("bob", bob.public_key, Role.OBSERVER)
    contacts.save()
    listen = ZenohSettings(multicast_scouting=False, listen=[f"tcp/127.0.0.1:{port}"])
    connect = ZenohSettings(multicast_scouting=False, connect=[f"tcp/127.0.0.1:{port}"])
    limits = Limits(frames_per_s=200, frames_burst=400)
    async with (
        ZenohTransport(listen) as session,
        ZenohTransport(connect) as network,
        Gateway(
            session, ContactsAdmitter(contacts, home), port=0, limits=limits, recheck=0.2
        ) as gateway,
        aiohttp.ClientSession() as http,
    ):
        yield Live(gateway, network, home, contacts, alice, bob, http)


async def _closed(ws: aiohttp.ClientWebSocketResponse) -> tuple[list[Any], int | None]:
    """Every message until the gateway closes the websocket, and its close code: the one
    in the gateway's close frame (a browser reports that one; aiohttp's client says 1006
    instead when the gateway has closed the connection before its reply got out, as when
    a connection is cut from outside its own task, on being revoked)."""
    messages = []
    while True:
        msg = await ws.receive(timeout=30)
        if msg.type is aiohttp.WSMsgType.CLOSE:
            return messages, int(msg.data)
        if msg.type in (aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.CLOSING):
            return messages, ws.close_code
        messages.append(json.loads(msg.data) if msg.type == aiohttp.WSMsgType.TEXT else msg.data)


async def test_a_contact_is_admitted_with_a_proof_of_its_key(live: Live) -> None:
    ws = await live.connect()
    answer = await admit(ws, live.alice)
    assert answer == {"op": "admitted", "name": USER}
    assert live.gateway.stats.admitted == 1
    async with live.http.get(live.gateway.url + "stats") as response:
        stats = await response.json()
    assert stats["admitted"] == 1 and stats["active"] == 1


@pytest.mark.parametrize(
    ("case", "code"),
    [
        ("wrong_key", "wrong_key"),
        ("unknown_name", "unknown_name"),
        ("bad_proof", "bad_proof"),
        ("garbage", "garbage"),
        ("binary", "garbage"),
        ("oversize", "too_large"),
    ],
)
async def test_admission_refuses_with_a_code_and_close_4001(
    live: Live, case: str, code: str
) -> None:
    ws = await live.connect()
    if case == "wrong_key":  # a key of its own, claiming alice's name
        answer = await admit(ws, Identity.generate("mallory"), name=USER)
    elif case == "unknown_name":
        answer = await admit(ws, Identity.generate("mallory"))
    else:
        challenge = json.loads((await ws.receive(timeout=30)).data)
        assert challenge["op"] == "challenge" and challenge["ns"] == NS
        if case == "bad_proof":
            key = b64(live.alice.public_key)
            await ws.send_str(
                json.dumps({"op": "admit", "name": USER, "key": key, "proof": b64(os.urandom(32))})
            )
        elif case == "garbage":
            await ws.send_str("hello, gateway")
        elif case == "binary":
            await ws.send_bytes(os.urandom(100))
        else:
            await ws.send_str('{"op": "admit", "name": "' + "a" * 20_000 + '"}')
        answer = json.loads((await ws.receive(timeout=30)).data)
    assert answer["op"] == "refused" and answer["code"] == code, answer
    assert len(answer["text"]) < 300
    _, close_code = await _closed(ws)
    assert close_code == 4001
    assert live.gateway.stats.refused == {code: 1}
    assert live.gateway.stats.admitted == 0


async def test_allowed_keys_reach_zenoh_and_samples_reach_the_browser(live: Live) -> None:
    ws = await live.admitted(live.alice)
    hello_key = f"{NS}/robot/{ROBOT}/in/{USER}"
    call_key = f"{NS}/robot/{ROBOT}/call/{USER}/0123456789abcdef/ctl"
    await _received_until(
        live.network,
        f"{NS}/robot/{ROBOT}/**",
        lambda: ws.send_bytes(put_frame(hello_key, b"HELLO", lane=0)),
        lambda s: s.key == hello_key and s.payload == b"HELLO",
    )
    await _received_until(
        live.network,
        f"{NS}/robot/{ROBOT}/**",
        lambda: ws.send_bytes(put_frame(call_key, b"DATA")),
        lambda s: s.key == call_key and s.payload == b"DATA",
    )
    # The other way: a subscription under the user's own keys gets SAMPLEs with its id.
    await ws.send_str(json.dumps({"op": "sub", "id": 7, "key": f"{NS}/user/{USER}/**"}))
    inbox = f"{NS}/user/{USER}/0123456789abcdef/in/{ROBOT}"
    publisher = live.network.publisher(inbox)
    for _ in range(300):
        publisher.put(b"WELCOME")
        try:
            msg = await ws.receive(timeout=0.2)
        except TimeoutError:
            continue
        assert parse_sample(msg.data) == (7, inbox, b"WELCOME")
        break
    else:
        raise AssertionError("no SAMPLE reached the browser")
    assert live.gateway.stats.cut == {}


async def test_a_put_sent_on_two_websockets_under_one_copy_id_is_published_once(
    live: Live,
) -> None:
    first, second, bob = [await live.admitted(who) for who in (live.alice, live.alice, live.bob)]
    key, bob_key = f"{NS}/robot/{ROBOT}/in/{USER}", f"{NS}/robot/{ROBOT}/in/bob"
    got: list[Sample] = []
    sub = live.network.subscribe(f"{NS}/robot/{ROBOT}/in/*", got.extend)
    try:
        # Until this subscription hears both names' keys (its declaration reached the
        # gateway's session: a busy machine takes its time).
        for _ in range(300):
            await first.send_bytes(put_frame(key, b"ready", lane=0))
            await bob.send_bytes(put_frame(bob_key, b"ready", lane=0))
            with contextlib.suppress(AssertionError):
                await wait_until(
                    lambda: {s.key for s in got if s.payload == b"ready"} == {key, bob_key},
                    timeout=0.2,
                )
                break
        stats = live.gateway.stats
        published = stats.published
        for copy in (1, 2):
            for ws in (first, second):  # a page's two WebSockets, the same PUT on each
                await ws.send_bytes(put_frame(key, b"STOP-%d" % copy, lane=0, copy=copy))
        await bob.send_bytes(put_frame(bob_key, b"BOB-1", lane=0, copy=1))  # bob's own id 1
        # Published: each of alice's two stops once, and bob's (his copy id 1 is his own).
        await wait_until(
            lambda: stats.duplicates == 2 and stats.published == published + 3, timeout=30
        )
        await first.send_bytes(put_frame(key, b"end", lane=0))
        await wait_until(lambda: any(s.payload == b"end" for s in got), timeout=30)
    finally:
        sub.close()
    # What the network heard (CONTROL is best effort: zenoh may drop one, never repeat one).
    sent = [s for s in got if s.payload != b"ready"]
    heard = [s.payload for s in sent if s.key == key]
    assert len(heard) == len(set(heard)) and set(heard) <= {b"STOP-1", b"STOP-2", b"end"}
    assert {s.payload for s in sent if s.key == bob_key} <= {b"BOB-1"}
    assert stats.duplicates == 2 and stats.published == published + 4 and stats.cut == {}
    # The name's copy ids are forgotten with its last WebSocket (bob's stay while he is on).
    assert set(live.gateway._copies) == {USER, "bob"}
    for ws in (first, second):
        await ws.close()
    await wait_until(lambda: set(live.gateway._copies) == {"bob"}, timeout=30)
    await bob.close()


async def test_presence_watch_and_token_go_both_ways(live: Live) -> None:
    ws = await live.admitted(live.alice)
    robot_token = f"{NS}/presence/robot/{ROBOT}/{b64(os.urandom(32))}"
    token = live.network.declare_presence(robot_token)
    await ws.send_str(json.dumps({"op": "watch", "id": 1, "key": f"{NS}/presence/robot/*/*"}))
    seen = json.loads((await ws.receive(timeout=30)).data)
    assert seen == {"op": "alive", "id": 1, "key": robot_token, "alive": True}
    token.close()
    gone = json.loads((await ws.receive(timeout=30)).data)
    assert gone == {"op": "alive", "id": 1, "key": robot_token, "alive": False}
    # The browser's own token is seen by the network.
    alive: list[tuple[str, bool]] = []
    mine = f"{NS}/presence/user/{USER}/0123456789abcdef"
    watch = live.network.watch_presence(
        f"{NS}/presence/user/*/*", lambda k, a: alive.append((k, a))
    )
    await ws.send_str(json.dumps({"op": "token", "id": 1, "key": mine}))
    await wait_until(lambda: (mine, True) in alive, timeout=30)
    await ws.send_str(json.dumps({"op": "untoken", "id": 1}))
    await wait_until(lambda: (mine, False) in alive, timeout=30)
    watch.close()


FORBIDDEN: list[tuple[str, Callable[[], str | bytes]]] = [
    ("a robot's key", lambda: put_frame(f"{NS}/user/bob/0123456789abcdef/in/{ROBOT}", b"forged")),
    ("another user's name", lambda: put_frame(f"{NS}/robot/{ROBOT}/in/bob", b"forged")),
    (
        "another user's call",
        lambda: put_frame(f"{NS}/robot/{ROBOT}/call/bob/0123456789abcdef/ctl", b"forged"),
    ),
    (
        "another user's inbox",
        lambda: json.dumps({"op": "sub", "id": 1, "key": f"{NS}/user/bob/**"}),
    ),
    ("everything", lambda: json.dumps({"op": "sub", "id": 1, "key": "**"})),
    (
        "another user's presence",
        lambda: json.dumps({"op": "token", "id": 1, "key": f"{NS}/presence/user/bob/0011"}),
    ),
    (
        "users' presence",
        lambda: json.dumps({"op": "watch", "id": 1, "key": f"{NS}/presence/user/*/*"}),
    ),
]


@pytest.mark.parametrize(("what", "message"), FORBIDDEN, ids=[f[0] for f in FORBIDDEN])
async def test_a_key_the_user_may_not_use_cuts_it_off_and_nothing_is_forwarded(
    live: Live, what: str, message: Callable[[], str | bytes]
) -> None:
    seen: list[Sample] = []
    spy = live.network.subscribe(f"{NS}/**", lambda batch: seen.extend(batch))
    bob = await live.admitted(live.bob)
    alice = await live.admitted(live.alice)
    frame = message()
    await (alice.send_bytes(frame) if isinstance(frame, bytes) else alice.send_str(frame))
    messages, code = await _closed(alice)
    assert code == 4008
    assert messages[-1]["op"] == "cut" and messages[-1]["code"] == "key"
    assert live.gateway.stats.cut == {"key": 1}
    # bob goes on: his frame arrives, alice's forbidden one never did (same session, sent
    # after it, so it would have come first).
    marker = f"{NS}/robot/{ROBOT}/in/bob"
    await _received_until(
        live.network,
        marker,
        lambda: bob.send_bytes(put_frame(marker, b"bob")),
        lambda s: s.payload == b"bob",
    )
    await wait_until(lambda: any(s.payload == b"bob" for s in seen), timeout=30)
    assert not any(s.payload == b"forged" for s in seen)
    spy.close()


async def test_a_flood_is_cut_off_and_another_browser_does_not_notice(live: Live) -> None:
    alice = await live.admitted(live.alice)
    bob = await live.admitted(live.bob)
    key = f"{NS}/robot/{ROBOT}/in/{USER}"
    sent = 0
    with contextlib.suppress(ConnectionError):
        for _ in range(2000):  # far above 400 at once and 200/s
            await alice.send_bytes(put_frame(key, b"flood"))
            sent += 1
    messages, code = await _closed(alice)
    assert code == 4008 and messages[-1]["code"] == "flood"
    assert live.gateway.stats.cut == {"flood": 1}
    assert live.gateway.stats.published < sent  # what came after the cut went nowhere
    marker = f"{NS}/robot/{ROBOT}/in/bob"
    await _received_until(
        live.network,
        marker,
        lambda: bob.send_bytes(put_frame(marker, b"bob")),
        lambda s: s.payload == b"bob",
    )
    assert not bob.closed


@pytest.mark.parametrize(
    ("frame", "code"),
    [
        (b"\x01\x00", "garbage"),  # shorter than a header
        (b"\x07\x00\x03abcpayload", "garbage"),  # no such lane
        (b"\x01\x00\xffab", "garbage"),  # key longer than the frame
        (b"\x01\x00\x02\xff\xfe", "garbage"),  # key not UTF-8
        (put_frame(f"{NS}/robot/{ROBOT}/in/{USER}", b"x" * (MAX_PAYLOAD + 1)), "too_large"),
        ("not json", "garbage"),
        (json.dumps({"op": "publish", "id": 1}), "garbage"),
        (json.dumps({"op": "sub", "id": 70_000, "key": f"{NS}/user/{USER}/**"}), "garbage"),
    ],
)
async def test_garbage_after_admission_cuts_off(live: Live, frame: str | bytes, code: str) -> None:
    ws = await live.admitted(live.alice)
    await (ws.send_bytes(frame) if isinstance(frame, bytes) else ws.send_str(frame))
    messages, close_code = await _closed(ws)
    assert close_code == 4008 and messages[-1]["code"] == code
    assert len(messages[-1]["text"]) < 400
    assert live.gateway.stats.cut == {code: 1} and live.gateway.stats.published == 0


async def test_more_than_16_subscriptions_cut_off(live: Live) -> None:
    ws = await live.admitted(live.alice)
    for ident in range(17):
        await ws.send_str(
            json.dumps({"op": "sub", "id": ident, "key": f"{NS}/user/{USER}/{ident}"})
        )
    messages, code = await _closed(ws)
    assert code == 4008 and messages[-1]["code"] == "too_many"


async def test_sub_token_watch_churn_is_cut_off_apart_from_puts(live: Live) -> None:
    ws = await live.admitted(live.alice)
    key = f"{NS}/user/{USER}/churn"
    with contextlib.suppress(ConnectionError):
        for ident in range(100):  # 200 messages: within 400 at once, far over 64 subs at once
            await ws.send_str(json.dumps({"op": "sub", "id": ident, "key": key}))
            await ws.send_str(json.dumps({"op": "unsub", "id": ident}))
    messages, code = await _closed(ws)
    assert code == 4008 and messages[-1]["code"] == "flood", messages[-1:]
    assert "sub/token/watch" in messages[-1]["text"]
    assert live.gateway.stats.cut == {"flood": 1}


async def test_a_second_sub_on_the_same_key_is_an_error_and_not_declared(live: Live) -> None:
    ws = await live.admitted(live.alice)
    key = f"{NS}/user/{USER}/0123456789abcdef/in/{ROBOT}"
    await ws.send_str(json.dumps({"op": "sub", "id": 1, "key": key}))
    await ws.send_str(json.dumps({"op": "sub", "id": 2, "key": key}))
    error = json.loads((await ws.receive(timeout=30)).data)
    assert error["op"] == "error" and error["code"] == "duplicate", error
    publisher = live.network.publisher(key)
    ids: list[int] = []
    for _ in range(300):
        publisher.put(b"WELCOME")
        with contextlib.suppress(TimeoutError):
            ids.append(parse_sample((await ws.receive(timeout=0.2)).data)[0])
            break
    publisher.put(b"again")  # a second sample: were sub 2 declared, it would come twice
    while len(ids) < 3:
        try:
            ids.append(parse_sample((await ws.receive(timeout=2)).data)[0])
        except TimeoutError:
            break
    assert ids and set(ids) == {1}, ids
    # Once unsubscribed, the key may be subscribed again.
    await ws.send_str(json.dumps({"op": "unsub", "id": 1}))
    await ws.send_str(json.dumps({"op": "sub", "id": 3, "key": key}))
    for _ in range(300):
        publisher.put(b"third")
        with contextlib.suppress(TimeoutError):
            msg = await ws.receive(timeout=0.2)
            assert msg.type == aiohttp.WSMsgType.BINARY, msg.data
            if parse_sample(msg.data)[0] == 3:
                break
    else:
        raise AssertionError("no SAMPLE for the new subscription")
    assert live.gateway.stats.cut == {}


@contextlib.asynccontextmanager
async def _another_gateway(live: Live, limits: Limits, **options: Any) -> AsyncIterator[Gateway]:
    admitter = ContactsAdmitter(live.contacts, live.home)
    async with Gateway(live.gateway.transport, admitter, port=0, limits=limits, **options) as gw:
        yield gw


async def test_connections_are_capped_in_all_and_per_address_before_the_websocket(
    live: Live,
) -> None:
    async with _another_gateway(live, Limits(max_connections=3, max_pending_per_address=2)) as gw:
        url = gw.url + "gateway"
        pending = [await live.http.ws_connect(url) for _ in range(2)]  # challenged, silent
        with pytest.raises(aiohttp.WSServerHandshakeError) as caught:
            await live.http.ws_connect(url)
        assert caught.value.status == 503
        assert gw.stats.refused == {"busy": 1}
        assert gw.stats.connections == 2  # the third never became a websocket
        # One answers: no longer pending, so the address may open another.
        assert (await admit(pending[0], live.alice))["op"] == "admitted"
        third = await live.http.ws_connect(url)
        async with live.http.get(url) as response:  # 3 websockets: full, for anyone
            body = await response.text()
            assert response.status == 503
        assert body.count("\n") == 1 and "3 connections" in body
        assert gw.stats.refused == {"busy": 1, "full": 1}
        # Closing one frees its place.
        await third.close()
        await wait_until(lambda: len(gw._sockets) < 3, timeout=30)
        fourth = await live.http.ws_connect(url)
        assert json.loads((await fourth.receive(timeout=30)).data)["op"] == "challenge"
        for ws in [*pending, fourth]:
            await ws.close()


async def test_an_admitted_name_has_at_most_its_connections(live: Live) -> None:
    async with _another_gateway(live, Limits(max_per_name=2)) as gw:
        url = gw.url + "gateway"
        first, second, third = [await live.http.ws_connect(url) for _ in range(3)]
        assert (await admit(first, live.alice))["op"] == "admitted"
        assert (await admit(second, live.alice))["op"] == "admitted"
        refused = await admit(third, live.alice)
        assert refused["op"] == "refused" and refused["code"] == "too_many", refused
        _, code = await _closed(third)
        assert code == 4001
        bob = await live.http.ws_connect(url)
        assert (await admit(bob, live.bob))["op"] == "admitted"  # other names go on
        await first.close()
        await wait_until(lambda: gw.stats.active == 2, timeout=30)
        again = await live.http.ws_connect(url)
        assert (await admit(again, live.alice))["op"] == "admitted"
        assert gw.stats.refused == {"too_many": 1}
        for ws in (second, bob, again):
            await ws.close()


async def test_a_tls_client_that_never_finishes_its_handshake_is_dropped(live: Live) -> None:
    cert, key, _ = self_signed(live.home / "tls", ["127.0.0.1"])
    limits = Limits(tls_handshake_timeout=1.0)  # asyncio's own default: 60 s
    async with _another_gateway(live, limits, ssl_context=server_context(cert, key)) as gw:
        reader, writer = await asyncio.open_connection("127.0.0.1", gw.port)
        try:
            # Connected, silent: the gateway ends it long before asyncio's 60 s.
            assert await asyncio.wait_for(reader.read(), timeout=30) == b""
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()


async def test_control_frames_and_presence_pass_a_stalled_browsers_data(live: Live) -> None:
    async with _another_gateway(live, Limits(out_bytes=100_000)) as gw:
        ws = await live.http.ws_connect(gw.url + "gateway", max_msg_size=0)
        assert (await admit(ws, live.alice))["op"] == "admitted"
        base = f"{NS}/user/{USER}/0123456789abcdef"
        await ws.send_str(json.dumps({"op": "sub", "id": 1, "key": f"{NS}/user/{USER}/**"}))
        await ws.send_str(json.dumps({"op": "watch", "id": 2, "key": f"{NS}/presence/robot/*/*"}))
        data = live.network.publisher(f"{base}/in/{ROBOT}")
        ctl_key = f"{base}/call/{ROBOT}/0011223344556677/ctl"
        ctl = live.network.publisher(ctl_key, Lane.CONTROL)
        for _ in range(300):  # until the two sessions are connected
            data.put(b"probe")
            with contextlib.suppress(TimeoutError):
                await ws.receive(timeout=0.2)
                break
        seq = 0

        async def flood_until(dropped: int) -> None:
            nonlocal seq
            deadline = asyncio.get_running_loop().time() + 120
            while gw.stats.dropped_out < dropped:
                assert asyncio.get_running_loop().time() < deadline, gw.stats
                for _ in range(20):
                    seq += 1
                    data.put(seq.to_bytes(4, "big") + bytes(30_000))
                await asyncio.sleep(0.01)  # the gateway runs on this loop

        # The browser reads nothing: its socket fills, then the data queue drops.
        await flood_until(1)
        before = seq
        ctl.put(b"HEARTBEAT")
        token_key = f"{NS}/presence/robot/{ROBOT}/{b64(os.urandom(32))}"
        token = live.network.declare_presence(token_key)
        await flood_until(gw.stats.dropped_out + 200)  # far more than the queue holds
        got: list[Any] = []
        deadline = asyncio.get_running_loop().time() + 120
        while not (any(g == "ctl" for g in got) and any(g == "alive" for g in got)):
            assert asyncio.get_running_loop().time() < deadline, got[-5:]
            msg = await ws.receive(timeout=60)
            if msg.type == aiohttp.WSMsgType.TEXT:
                text = json.loads(msg.data)
                if text.get("op") == "alive" and text["key"] == token_key:
                    got.append("alive")
            else:
                _, key, payload = parse_sample(msg.data)
                got.append("ctl" if key == ctl_key and payload == b"HEARTBEAT" else payload[:4])
        token.close()
        await ws.close()
        # The heartbeat went out before every data frame published after it (all queued
        # behind it, the writer stalled), and was never dropped for them.
        after = [g for g in got[: got.index("ctl")] if isinstance(g, bytes) and len(g) == 4]
        assert all(int.from_bytes(g, "big") <= before for g in after), (before, after[-3:])
        assert gw.stats.dropped_control == 0 and gw.stats.dropped_out > 200


async def test_the_page_is_served_at_the_root_when_installed(tmp_path: Path) -> None:
    static = tmp_path / "static"
    static.mkdir()
    async with (
        MemoryTransport(MemoryHub(), "gateway") as transport,
        Gateway(
            transport, ContactsAdmitter(ContactBook.load(tmp_path), tmp_path), port=0, static=static
        ) as gateway,
        aiohttp.ClientSession() as http,
    ):
        async with http.get(gateway.url) as response:
            assert response.status == 404  # no page installed: says so
        (static / "gateway.html").write_text("<title>telebot</title>")
        (static / "app.js").write_text("// app")
        (static / "index.html").write_text("<title>robot page</title>")
        async with http.get(gateway.url) as response:
            assert response.status == 200 and "telebot" in await response.text()
        async with http.get(gateway.url + "call?robot=guiabot") as response:
            assert response.status == 200 and "robot page" in await response.text()
        async with http.get(gateway.url + "static/app.js") as response:
            assert response.status == 200 and await response.text() == "// app"
    with pytest.raises(ValueError, match="loopback only"):
        Gateway(transport, ContactsAdmitter(ContactBook.load(tmp_path), tmp_path), host="0.0.0.0")


# --- invites ------------------------------------------------------------------------------


async def _redeem(live: Live, who: Identity, token: str) -> dict[str, Any]:
    ws = await live.connect()
    return await admit(ws, who, invite=token)


async def test_an_invite_adds_the_browser_as_a_contact_once(live: Live) -> None:
    nurse = Identity.generate("nurse1")
    token, _ = create_invite(live.home, "nurse1", Role.DRIVER, now=live.gateway.wall_clock())
    assert token not in (live.home / "invites.json").read_text()  # only its hash is kept
    assert await _redeem(live, nurse, token) == {"op": "admitted", "name": "nurse1"}
    # In the daemon's own book (calls are answered from it) and in contacts.toml.
    assert live.contacts.by_key(nurse.public_key) is not None
    stored = ContactBook.load(live.home).by_key(nurse.public_key)
    assert stored is not None and stored.name == "nurse1" and stored.role is Role.DRIVER
    # From now on an ordinary admission; the invite is spent.
    await live.admitted(nurse)
    again = await _redeem(live, Identity.generate("nurse1"), token)
    assert again["op"] == "refused" and again["code"] == "invite_used"


@pytest.mark.parametrize("case", ["unknown", "expired", "other_name"])
async def test_a_bad_invite_is_refused_with_a_clear_code(live: Live, case: str) -> None:
    now = live.gateway.wall_clock()
    token, _ = create_invite(
        live.home, "nurse1", Role.OBSERVER, now=now - (601 if case == "expired" else 0)
    )
    who = Identity.generate("nurse2" if case == "other_name" else "nurse1")
    answer = await _redeem(live, who, "A" * 43 if case == "unknown" else token)
    expected = {
        "unknown": "invite_unknown",
        "expired": "invite_expired",
        "other_name": "invite_name",
    }[case]
    assert answer["op"] == "refused" and answer["code"] == expected
    assert live.contacts.by_key(who.public_key) is None
    assert ContactBook.load(live.home).by_key(who.public_key) is None


def test_the_invite_command_prints_a_link_a_browser_can_redeem(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    home = tmp_path / "robot"
    robot = Identity.generate(ROBOT)
    robot.save(home)
    code = robot_cli.main(
        [
            "invite",
            "nurse1",
            "--role",
            "driver",
            "--url",
            "https://robot.local:8443",
            "--home",
            str(home),
        ]
    )
    out = capsys.readouterr().out
    assert code == 0
    link = next(line for line in out.splitlines() if line.startswith("https://"))
    base, fragment = link.split("#", 1)
    fields = dict(part.split("=", 1) for part in fragment.split("&"))
    assert base == "https://robot.local:8443/"
    assert fields["robot"] == ROBOT and fields["key"] == b64(robot.public_key)
    assert "█" in out or "▀" in out  # the QR code
    admitter = ContactsAdmitter(ContactBook.load(home), home)
    nurse = Identity.generate("nurse1")
    import time

    admitter.redeem(fields["invite"], "nurse1", nurse.public_key, time.time())
    contact = ContactBook.load(home).by_key(nurse.public_key)
    assert contact is not None and contact.role is Role.DRIVER
    bad = robot_cli.main(["invite", "x", "--url", "http://robot/", "--home", str(home)])
    assert bad == 2 and "https" in capsys.readouterr().err


async def test_an_invite_for_a_contact_is_refused_unless_it_may_replace_it(live: Live) -> None:
    bob_ws = await live.admitted(live.bob)
    token, _ = create_invite(live.home, "bob", Role.DRIVER, now=live.gateway.wall_clock())
    mallory = Identity.generate("bob")
    answer = await _redeem(live, mallory, token)
    assert answer["op"] == "refused" and answer["code"] == "name_in_use", answer
    # bob keeps his key and role, on disk and in the daemon's book.
    assert contact_key(ContactBook.load(live.home), "bob") == live.bob.public_key
    assert live.contacts.by_key(mallory.public_key) is None
    assert live.contacts.by_key(live.bob.public_key) is not None
    # An invite written with --replace may: the new key replaces bob's, with its role, and
    # the open connection of the old key, which no longer holds, is cut.
    token, _ = create_invite(
        live.home, "bob", Role.DRIVER, now=live.gateway.wall_clock(), replace=True
    )
    assert await _redeem(live, mallory, token) == {"op": "admitted", "name": "bob"}
    stored = ContactBook.load(live.home).by_key(mallory.public_key)
    assert stored is not None and stored.name == "bob" and stored.role is Role.DRIVER
    messages, code = await _closed(bob_ws)
    assert code == 4008 and messages[-1]["op"] == "cut" and messages[-1]["code"] == "revoked"
    assert live.gateway.stats.cut == {"revoked": 1}


async def test_a_removed_contact_is_cut_off_and_the_others_do_not_notice(live: Live) -> None:
    alice_ws, bob_ws = await live.admitted(live.alice), await live.admitted(live.bob)
    remove = [sys.executable, "-m", "telebot.apps.robot_cli", "contacts", "remove", "bob"]
    done = await asyncio.to_thread(
        subprocess.run, [*remove, "--home", str(live.home)], capture_output=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    messages, code = await _closed(bob_ws)
    assert code == 4008 and messages == [
        {"op": "cut", "code": "revoked", "text": "bob is no longer admitted here"}
    ]
    assert live.gateway.stats.cut == {"revoked": 1}
    # alice is still served (an unknown id is answered, not cut), and bob is refused now.
    await alice_ws.send_str(json.dumps({"op": "unsub", "id": 9}))
    reply = json.loads((await alice_ws.receive(timeout=30)).data)
    assert reply["op"] == "error" and reply["code"] == "unknown_id"
    refused = await admit(await live.connect(), live.bob)
    assert refused["op"] == "refused" and refused["code"] == "unknown_name"


@pytest.mark.parametrize("case", ["invites", "contacts", "write"])
async def test_a_gateway_file_that_fails_refuses_a_redemption_in_one_logged_line(
    live: Live, case: str, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO)
    token, _ = create_invite(live.home, "nurse1", Role.OBSERVER, now=live.gateway.wall_clock())
    if case == "invites":
        (live.home / "invites.json").write_text("{not json")
    elif case == "contacts":
        (live.home / "contacts.toml").write_text("[[[")
    else:  # writing contacts.toml fails (its temporary file cannot be made)
        (live.home / "contacts.toml.tmp").mkdir()
    ws = await live.connect()
    nurse = Identity.generate("nurse1")
    answer = await admit(ws, nurse, invite=token)
    assert answer["op"] == "refused" and answer["code"] == "gateway_error", answer
    assert str(live.home) not in answer["text"]  # the details are for the log, not the browser
    _, code = await _closed(ws)
    assert code == 4001
    assert live.gateway.stats.refused == {"gateway_error": 1}
    assert not any(r.exc_info for r in caplog.records), "a traceback was logged"
    said = [r for r in caplog.records if "gateway_error" in r.getMessage()]
    assert len(said) == 1 and said[0].levelno == logging.WARNING
    assert "\n" not in said[0].getMessage()
    assert live.contacts.by_key(nurse.public_key) is None
    if case == "write":
        # Undone: the invite is unused again, and once the trouble is gone it works, once.
        assert not any(i.used for i in read_invites(live.home).values())
        (live.home / "contacts.toml.tmp").rmdir()
        assert await _redeem(live, nurse, token) == {"op": "admitted", "name": "nurse1"}
        again = await _redeem(live, Identity.generate("nurse1"), token)
        assert again["code"] == "invite_used"


def test_a_redemption_marks_the_invite_used_before_it_saves_the_contact(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    token, _ = create_invite(tmp_path, "nurse1", Role.OBSERVER, now=1000.0)
    admitter = ContactsAdmitter(ContactBook.load(tmp_path), tmp_path)
    used_when_saved: list[bool] = []

    def save_fails(self: ContactBook) -> None:
        used_when_saved.extend(i.used for i in read_invites(tmp_path).values())
        raise OSError("disk full")

    with monkeypatch.context() as patch:
        patch.setattr(ContactBook, "save", save_fails)
        with pytest.raises(OSError, match="disk full"):
            admitter.redeem(token, "nurse1", Identity.generate("nurse1").public_key, 1001.0)
    assert used_when_saved == [True]  # a crash while saving can never leave it redeemable
    assert [i.used for i in read_invites(tmp_path).values()] == [False]  # the failure undone
    admitter.redeem(token, "nurse1", Identity.generate("nurse1").public_key, 1002.0)
    assert [i.used for i in read_invites(tmp_path).values()] == [True]


async def test_a_revoked_or_removed_gateway_user_is_refused_and_cut_off(tmp_path: Path) -> None:
    directory = tmp_path / "router"
    alice, bob = Identity.generate(USER), Identity.generate("bob")
    GatewayUsers(directory / USERS_FILE, {USER: alice.public_key, "bob": bob.public_key}).save()
    async with (
        MemoryTransport(MemoryHub(), "gateway") as transport,
        Gateway(transport, UsersAdmitter(directory), port=0, recheck=0.2) as gateway,
        aiohttp.ClientSession() as http,
    ):
        url = gateway.url + "gateway"
        alice_ws, bob_ws = await http.ws_connect(url), await http.ws_connect(url)
        assert await admit(alice_ws, alice) == {"op": "admitted", "name": USER}
        assert await admit(bob_ws, bob) == {"op": "admitted", "name": "bob"}
        revoke = ["revoke", str(directory), "--user", USER]
        assert await asyncio.to_thread(router_cli.main, revoke) == 0
        messages, code = await _closed(alice_ws)
        assert code == 4008 and messages[-1]["code"] == "revoked"
        refused = await admit(await http.ws_connect(url), alice)
        assert refused["op"] == "refused" and refused["code"] == "revoked"
        remove = ["gateway-user", "remove", str(directory), "bob"]
        assert await asyncio.to_thread(router_cli.main, remove) == 0
        messages, code = await _closed(bob_ws)
        assert code == 4008 and messages[-1]["code"] == "revoked"
        assert gateway.stats.cut == {"revoked": 2}
        assert gateway.stats.refused == {"revoked": 1}


# --- the router's gateway over HTTPS ---------------------------------------------------------


async def test_the_router_serves_the_gateway_over_https_with_its_certificate(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = RouterRig(tmp_path)
    robot_cert = rig.issue("robot", ROBOT)
    alice = Identity.generate(USER)
    assert router_cli.main(["gateway-user", "add", str(rig.dir), USER, alice.public_line()]) == 0
    assert router_cli.main(["gateway-user", "list", str(rig.dir)]) == 0
    assert f"{USER}\t{b64(alice.public_key)}" in capsys.readouterr().out
    assert router_cli.main(["gateway-user", "add", str(rig.dir), "x", "not-a-key"]) == 2
    port = free_port()
    await asyncio.to_thread(rig.start, extra=("--gateway", f"127.0.0.1:{port}"))
    try:
        trust = ssl.create_default_context(cafile=str(rig.dir / "ca.pem"))
        url = f"https://127.0.0.1:{port}/"
        async with (
            ZenohTransport(rig.zenoh(robot_cert)) as robot_side,
            aiohttp.ClientSession() as http,
        ):
            async with http.get(url + "stats", ssl=trust) as response:
                assert response.status == 200 and (await response.json())["admitted"] == 0
            ws = await http.ws_connect(url + "gateway", ssl=trust)
            assert await admit(ws, alice) == {"op": "admitted", "name": USER}
            # The browser's HELLO reaches a robot through the router's ACL.
            key = f"{NS}/robot/{ROBOT}/in/{USER}"
            await _received_until(
                robot_side,
                f"{NS}/robot/{ROBOT}/**",
                lambda: ws.send_bytes(put_frame(key, b"HELLO")),
                lambda s: s.payload == b"HELLO",
            )
            # A removed user is refused at the next admission, without a restart.
            assert router_cli.main(["gateway-user", "remove", str(rig.dir), USER]) == 0
            ws2 = await http.ws_connect(url + "gateway", ssl=trust)
            refused = await admit(ws2, alice)
            assert refused["op"] == "refused" and refused["code"] == "unknown_name"
            await ws.close()
            await ws2.close()
            # Plain HTTP is not served; a client that does not trust the CA gets nowhere.
            for plain, context in (
                (f"http://127.0.0.1:{port}/stats", None),
                (url + "stats", ssl.create_default_context()),
            ):
                with pytest.raises(aiohttp.ClientError):
                    async with http.get(plain, ssl=context if context else False):
                        pass
    finally:
        rig.stop()


def test_a_bad_gateway_option_is_a_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = RouterRig(tmp_path)
    assert router_cli.main(["run", str(rig.dir), "--gateway", "nonsense"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--gateway nonsense" in err
    assert router_cli.main(["run", str(rig.dir), "--gateway-cert", "x.pem"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--gateway-key" in err


def test_a_robot_gateway_needs_both_cert_and_key(tmp_path: Path) -> None:
    config = tmp_path / "robot.toml"
    config.write_text('[gateway]\ncert = "a.pem"\n')
    with pytest.raises(ConfigError, match=r"gateway: .*cert and key go together"):
        load_toml(config, RobotConfig)
    config.write_text("[gateway]\nport = 99999\n")
    with pytest.raises(ConfigError, match=r"gateway\.port"):
        load_toml(config, RobotConfig)
    config.write_text("[gateway]\n")
    gateway = load_toml(config, RobotConfig).gateway
    assert gateway is not None and gateway.port == 8443 and gateway.enabled


# --- the robot's own gateway: a call through it, and an invite redeemed on a live daemon ----


async def test_a_browser_calls_the_robot_through_its_gateway_after_an_invite(
    homes: Homes, tmp_path: Path, processes: list[Process]
) -> None:
    port = free_port()
    config = write_config(tmp_path / "robot.toml", timeout=5.0, sim={"map": "small"})
    config.write_text(config.read_text() + f'[gateway]\nlisten = "127.0.0.1"\nport = {port}\n')
    daemon = Process(
        [
            "telebot.apps.robot_cli",
            "run",
            "--home",
            str(homes.robot_home),
            "--config",
            str(config),
            "--events",
        ]
    )
    processes.append(daemon)
    ready = json.loads(await asyncio.to_thread(daemon.next_line, 60))
    assert ready["event"] == "ready"
    cert = homes.robot_home / "gateway" / "cert.pem"
    assert cert.is_file()  # self-signed, made once under the robot's home
    trust = ssl.create_default_context(cafile=str(cert))
    url = f"https://127.0.0.1:{port}/"
    # An invite written by the command line while the daemon runs...
    nurse = Identity.generate("nurse1")
    token, _ = create_invite(
        homes.robot_home, "nurse1", Role.OBSERVER, now=__import__("time").time()
    )
    known = KnownRobots.load(homes.user_home)
    nurse_home = tmp_path / "nurse"
    nurse_known = KnownRobots(nurse_home / "known_robots.toml")
    nurse_known.add(ROBOT, known.get(ROBOT) or b"")
    settings = CallSettings(timeout=5.0)
    # ...lets a new browser in, and the robot answers its call at once (no restart).
    async with (
        GatewayTransport(url, nurse, ssl_context=trust, invite=token) as link,
        UserEndpoint(link, nurse, nurse_known, settings=settings) as user,
    ):
        call = await user.call(ROBOT, timeout=30)
        where = await RobotClient(call).chat("where?", timeout=30)
        assert where.ok and "x" in where.final_text
        await call.hangup()
    # The contact is in contacts.toml with the invite's role; the known contact still calls.
    contact = ContactBook.load(homes.robot_home).by_key(nurse.public_key)
    assert contact is not None and contact.role is Role.OBSERVER
    async with (
        GatewayTransport(url, homes.user, ssl_context=trust) as link,
        UserEndpoint(link, homes.user, known, settings=settings) as user,
    ):
        call = await user.call(ROBOT, timeout=30)
        assert (await RobotClient(call).chat("where?", timeout=30)).ok
        await call.hangup()


# --- the JavaScript link against a live gateway -------------------------------------------

NODE_SCRIPT = """
import { connectGateway, encodeKey } from %(module)s;
const [url, name, priv, pub, robot] = process.argv.slice(2);
const hex = (s) => Uint8Array.from(Buffer.from(s, "hex"));
const link = await connectGateway(url, { name, privateKey: hex(priv), publicKey: hex(pub) });
const inbox = `telebot/user/${name}/0123456789abcdef/in/${robot}`;
link.subscribe(`telebot/user/${name}/**`, (key, payload) => {
  console.log(JSON.stringify({ sample: key, payload: new TextDecoder().decode(payload) }));
  link.close();
  link.publish("telebot/robot/x/in/y", new Uint8Array(1));  // dropped and counted, no throw
  console.log(JSON.stringify({ dropped: link.stats.dropped }));
});
link.watch("telebot/presence/robot/*/*", (key, alive) => console.log(JSON.stringify({ key, alive })));
console.log(JSON.stringify({ admitted: name }));
const timer = setInterval(() => link.publish(`telebot/robot/${robot}/in/${name}`, new TextEncoder().encode("from node"), "control"), 100);
link.onclose = () => clearInterval(timer);
try {
  await connectGateway(url, { name: "nobody", privateKey: hex(priv), publicKey: hex(pub) });
} catch (err) {
  console.log(JSON.stringify({ refused: err.message, code: err.code }));
}
"""


async def test_the_javascript_link_is_admitted_and_relays_both_ways(
    live: Live, tmp_path: Path
) -> None:
    node = shutil.which("node")
    assert node is not None, (
        "node is not installed: the JavaScript link's test needs it (apt-get install nodejs)"
    )
    assert (ROOT / "node_modules" / "@noble" / "curves").is_dir(), (
        "run 'npm ci' first (the JS test needs @noble)"
    )
    script = tmp_path / "link.mjs"
    module = json.dumps((ROOT / "web" / "src" / "gateway-link.js").as_uri())
    script.write_text(NODE_SCRIPT % {"module": module})
    token = live.network.declare_presence(f"{NS}/presence/robot/{ROBOT}/{b64(os.urandom(32))}")
    got: list[Sample] = []
    sub = live.network.subscribe(f"{NS}/robot/{ROBOT}/in/{USER}", lambda batch: got.extend(batch))
    # node 22 has WebSocket; node 20 behind a flag.
    probe = [node, "-e", "process.exit(typeof WebSocket === 'function' ? 0 : 1)"]
    has_websocket = (await asyncio.to_thread(subprocess.run, probe)).returncode == 0
    flags = [] if has_websocket else ["--experimental-websocket"]
    proc = await asyncio.create_subprocess_exec(
        node,
        *flags,
        str(script),
        live.ws_url,
        USER,
        live.alice.private_key.hex(),
        live.alice.public_key.hex(),
        ROBOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=ROOT,
    )
    try:
        assert proc.stdout is not None
        lines: list[dict[str, Any]] = []

        async def read() -> None:
            assert proc.stdout is not None
            async for line in proc.stdout:
                lines.append(json.loads(line))

        reader = asyncio.create_task(read())
        await wait_until(lambda: {"admitted": USER} in lines, timeout=60)
        await wait_until(lambda: any(s.payload == b"from node" for s in got), timeout=60)
        await wait_until(lambda: any(line.get("alive") is True for line in lines), timeout=60)
        await wait_until(lambda: any("refused" in line for line in lines), timeout=60)
        refused = next(line for line in lines if "refused" in line)
        assert refused["code"] == "unknown_name" and "\n" not in refused["refused"]
        publisher = live.network.publisher(f"{NS}/user/{USER}/0123456789abcdef/in/{ROBOT}")
        for _ in range(600):
            if any("sample" in line for line in lines):
                break
            publisher.put(b"to node")
            await asyncio.sleep(0.1)
        assert any(line.get("payload") == "to node" for line in lines), lines
        await wait_until(lambda: any("dropped" in line for line in lines), timeout=60)
        assert next(line for line in lines if "dropped" in line)["dropped"] >= 1
        await asyncio.wait_for(proc.wait(), 60)
        await reader
        assert proc.returncode == 0, (await proc.stderr.read()).decode() if proc.stderr else ""
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
        sub.close()
        token.close()
