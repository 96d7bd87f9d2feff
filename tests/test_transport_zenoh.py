"""The zenoh transport on loopback: in one process, and across two real processes.

Every session uses TCP on 127.0.0.1 with multicast scouting off, so tests never see
peers from other tests or other machines: one side listens on a free port, the other
connects to it.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import platform
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import AsyncIterator, Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, cast

import pytest
import zenoh

from conftest import SLACK, wait_until
from telebot.channels.transports import create_transport
from telebot.channels.transports.base import Lane, ReceiveLimits, Sample, is_call_data_key
from telebot.channels.transports.zenoh import (
    LINK_LEASE_MS,
    ZenohTransport,
    build_zenoh_config,
    data_session_config,
)
from telebot.config import AppConfig, TransportSettings, ZenohSettings
from telebot.errors import TransportError
from telebot.testing.net import free_port

pytestmark = pytest.mark.zenoh

PEER_SCRIPT = Path(__file__).with_name("zenoh_peer_proc.py")


def listen_settings(endpoint: str, **kwargs: Any) -> ZenohSettings:
    return ZenohSettings(listen=[endpoint], multicast_scouting=False, **kwargs)


def connect_settings(endpoint: str, **kwargs: Any) -> ZenohSettings:
    return ZenohSettings(connect=[endpoint], multicast_scouting=False, **kwargs)


WARM_UP = b"warm-up"
WARMED_UP = b"warm-up done"


class Inbox:
    """Collects batches delivered by a subscription (all but :func:`warm_up`'s samples)."""

    def __init__(self) -> None:
        self.batches: list[list[Sample]] = []
        self.event = asyncio.Event()
        #: The warm-up payloads seen, in order.
        self.warm_ups: list[bytes] = []

    def __call__(self, batch: Sequence[Sample]) -> None:
        kept = []
        for sample in batch:
            if sample.payload in (WARM_UP, WARMED_UP):
                self.warm_ups.append(sample.payload)
            else:
                kept.append(sample)
        if kept:
            self.batches.append(kept)
        self.event.set()

    @property
    def samples(self) -> list[Sample]:
        return [sample for batch in self.batches for sample in batch]

    async def next_sample(self, timeout: float = 5.0) -> Sample:
        """Wait for and remove the oldest sample not yet taken."""
        async with asyncio.timeout(timeout):
            while not self.batches:
                self.event.clear()
                await self.event.wait()
        sample = self.batches[0].pop(0)
        if not self.batches[0]:
            self.batches.pop(0)
        return sample


async def warm_up(put: Callable[[bytes], None], inbox: Inbox, timeout: float = 5.0) -> None:
    """Publish until a sample gets through (declarations propagate asynchronously), then
    wait for an end marker: one publisher's samples arrive in order, so no stray warm-up
    can come after it and into the test proper."""
    deadline = time.monotonic() + timeout
    # The end marker is sent once (after the first warm-up got through, nothing is lost
    # on loopback): a second copy could arrive in the test proper and count in the stats.
    for marker, every in ((WARM_UP, 0.05), (WARMED_UP, timeout)):
        while marker not in inbox.warm_ups:
            if time.monotonic() > deadline:
                raise AssertionError(f"{marker!r} did not get through")
            put(marker)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(every):
                    while marker not in inbox.warm_ups:
                        inbox.event.clear()
                        await inbox.event.wait()


@pytest.fixture
async def pair() -> AsyncIterator[tuple[ZenohTransport, ZenohTransport]]:
    """Two open transports in this process: the first listens, the second connects."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    listener = ZenohTransport(listen_settings(endpoint))
    connector = ZenohTransport(connect_settings(endpoint))
    await listener.open()
    try:
        await connector.open()
        try:
            yield listener, connector
        finally:
            await connector.close()
    finally:
        await listener.close()


class Peer:
    """A zenoh peer in a child process (tests/zenoh_peer_proc.py)."""

    def __init__(self, test_id: str, token: str | None = None) -> None:
        self.test_id = test_id
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        args = [sys.executable, str(PEER_SCRIPT), "--listen", self.endpoint, "--id", test_id]
        if token is not None:
            args += ["--token", token]
        env = dict(os.environ)
        src = str(Path(__file__).resolve().parents[1] / "src")
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [src, env.get("PYTHONPATH")]))
        self.proc = subprocess.Popen(
            args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env
        )

    async def ready(self, timeout: float = 10.0) -> None:
        assert self.proc.stdout is not None
        async with asyncio.timeout(timeout):
            line = await asyncio.to_thread(self.proc.stdout.readline)
        if line.strip() != b"ready":
            self.stop()
            assert self.proc.stderr is not None
            raise AssertionError(f"peer failed: {line!r} {self.proc.stderr.read()!r}")

    def stop(self) -> None:
        """Ask the child to exit (stdin EOF), kill it if it does not, reap it."""
        if self.proc.poll() is None:
            assert self.proc.stdin is not None
            try:
                self.proc.stdin.close()
                self.proc.wait(timeout=3)
            except (subprocess.TimeoutExpired, OSError):
                self.proc.kill()
        self.proc.wait()
        for stream in (self.proc.stdin, self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()


@pytest.fixture
def peer_factory() -> Iterator[Callable[..., Peer]]:
    """Start child peers; every one is stopped and reaped at teardown, whatever happened."""
    peers: list[Peer] = []

    def start(test_id: str, token: str | None = None) -> Peer:
        peer = Peer(test_id, token)
        peers.append(peer)
        return peer

    yield start
    for peer in peers:
        peer.stop()


# --- configuration -------------------------------------------------------------------


def test_build_config_inserts_settings() -> None:
    settings = ZenohSettings(
        mode="client",
        listen=["tcp/127.0.0.1:7001"],
        connect=["tcp/10.0.0.5:7447", "tcp/10.0.0.6:7447"],
        multicast_scouting=False,
        options={"scouting/delay": 123, "transport/unicast/max_sessions": 7},
    )
    config = build_zenoh_config(settings)
    assert config.get_json("mode") == '"client"'
    assert config.get_json("listen/endpoints") == '["tcp/127.0.0.1:7001"]'
    assert config.get_json("connect/endpoints") == '["tcp/10.0.0.5:7447","tcp/10.0.0.6:7447"]'
    assert config.get_json("scouting/multicast/enabled") == "false"
    assert config.get_json("scouting/delay") == "123"
    assert config.get_json("transport/unicast/max_sessions") == "7"


def test_build_config_keeps_defaults_for_empty_endpoints() -> None:
    default = zenoh.Config()
    config = build_zenoh_config(ZenohSettings())
    assert config.get_json("listen/endpoints") == default.get_json("listen/endpoints")
    assert config.get_json("connect/endpoints") == default.get_json("connect/endpoints")
    assert config.get_json("mode") == '"peer"'
    assert config.get_json("scouting/multicast/enabled") == "true"


def test_build_config_file_is_loaded_then_overridden(tmp_path: Path) -> None:
    path = tmp_path / "zenoh.json5"
    path.write_text('{ mode: "client", scouting: { delay: 321 } }', encoding="utf-8")
    config = build_zenoh_config(ZenohSettings(config_file=path))
    assert config.get_json("scouting/delay") == "321"  # from the file
    assert config.get_json("mode") == '"peer"'  # the settings win


@pytest.mark.parametrize(
    ("settings", "expected"),
    [
        (ZenohSettings(options={"bogus/key": 1}), "'bogus/key'"),
        (ZenohSettings(options={"scouting/multicast/enabled": "yes"}), "expected a boolean"),
        (ZenohSettings(listen=["tcp/127.0.0.1:7447", "localhost:7447"]), "'localhost:7447'"),
        (ZenohSettings(connect=["127.0.0.1"]), "connect endpoint '127.0.0.1'"),
        (ZenohSettings(config_file=Path("/nonexistent/zenoh.json5")), "/nonexistent/zenoh.json5"),
    ],
)
def test_build_config_errors_name_the_culprit(settings: ZenohSettings, expected: str) -> None:
    with pytest.raises(TransportError) as info:
        build_zenoh_config(settings)
    message = str(info.value)
    assert expected in message
    assert "\n" not in message
    assert ".rs:" not in message  # no Rust source locations in user-facing errors
    assert isinstance(info.value.__cause__, zenoh.ZError)


async def test_open_error_is_transport_error() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    async with ZenohTransport(listen_settings(endpoint)):
        clash = ZenohTransport(listen_settings(endpoint))
        with pytest.raises(TransportError, match=r"127\.0\.0\.1"):
            await clash.open()


def test_registry_builds_zenoh_transport() -> None:
    settings = TransportSettings(kind="zenoh", zenoh=ZenohSettings(queue_size=99))
    transport = create_transport(settings)
    assert isinstance(transport, ZenohTransport)
    assert transport.name == "zenoh"
    assert transport.settings.queue_size == 99


# --- lifecycle -----------------------------------------------------------------------


async def test_use_before_open_and_after_close_raises() -> None:
    transport = ZenohTransport(listen_settings(f"tcp/127.0.0.1:{free_port()}"))
    with pytest.raises(TransportError, match="not open"):
        transport.publisher("test/x")
    with pytest.raises(TransportError, match="not open"):
        _ = transport.session_id
    await transport.open()
    assert len(transport.session_id) >= 16
    int(transport.session_id, 16)  # a hex zenoh id
    publisher = transport.publisher("test/x")
    await transport.close()
    await transport.close()  # idempotent
    for use in (
        lambda: transport.publisher("test/x"),
        lambda: transport.subscribe("test/x", lambda batch: None),
        lambda: transport.declare_presence("test/x"),
        lambda: transport.watch_presence("test/x", lambda key, alive: None),
    ):
        with pytest.raises(TransportError, match="closed"):
            use()
    with pytest.raises(TransportError, match="closed"):
        publisher.put(b"late")
    with pytest.raises(TransportError, match="closed"):
        await transport.open()


async def test_default_peer_mode_works_without_router() -> None:
    """The defaults (peer, multicast scouting on, no endpoints) open and deliver locally."""
    async with ZenohTransport() as transport:
        inbox = Inbox()
        key = f"test/{uuid.uuid4().hex}/local"
        transport.subscribe(key, inbox)
        transport.publisher(key).put(b"hello")
        sample = await inbox.next_sample()
        assert sample == Sample(key, b"hello")


# Run in a fresh interpreter: the allocator settings are per process and stay set.
_HEAP_SCRIPT = """
import asyncio, ctypes, sys
from telebot.channels.transports.zenoh import ZenohTransport
from telebot.config import ZenohSettings

class MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks",
        "uordblks", "fordblks", "keepcost")]

libc = ctypes.CDLL(None)
libc.mallinfo2.restype = MallInfo2

def free_heap_after_burst():
    burst = [bytes(32768) for _ in range(600)]  # about 19 MB of 32 KB payloads
    del burst
    return libc.mallinfo2().fordblks

async def open_transport():
    settings = ZenohSettings(listen=[sys.argv[1]], multicast_scouting=False)
    async with ZenohTransport(settings):
        pass

before = free_heap_after_burst()
asyncio.run(open_transport())
print(before, free_heap_after_burst())
"""


def _glibc_with_mallinfo2() -> bool:
    name, version = platform.libc_ver()
    return name == "glibc" and tuple(map(int, version.split(".")[:2])) >= (2, 33)


@pytest.mark.skipif(not _glibc_with_mallinfo2(), reason="a glibc allocator setting")
@pytest.mark.parametrize(
    ("user_setting", "kept"), [(None, True), (("MALLOC_TOP_PAD_", "131072"), False)]
)
def test_opening_keeps_freed_payload_memory_for_reuse(
    user_setting: tuple[str, str] | None, kept: bool
) -> None:
    """After a transport opened, a freed burst of 32 KB buffers stays in the heap.

    Before, glibc hands it back to the kernel at once, and the next burst pays page
    faults for every buffer (see "Memory" in the zenoh transport's docstring). A user's
    own allocator settings are left alone.
    """
    env = {key: value for key, value in os.environ.items() if not key.startswith("MALLOC_")}
    env.pop("GLIBC_TUNABLES", None)
    if user_setting is not None:
        env[user_setting[0]] = user_setting[1]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    result = subprocess.run(
        [sys.executable, "-c", _HEAP_SCRIPT, endpoint],
        capture_output=True,
        text=True,
        timeout=30,
        env=env,
    )
    assert result.returncode == 0, result.stderr
    before, after = map(int, result.stdout.split())
    assert before < 4 << 20, "glibc kept the burst even before: the test shows nothing"
    assert (after > 16 << 20) is kept, f"{after} bytes free in the heap after the burst"


async def test_close_is_bounded_even_if_zenoh_hangs(caplog: pytest.LogCaptureFixture) -> None:
    transport = ZenohTransport(listen_settings(f"tcp/127.0.0.1:{free_port()}", close_timeout=0.3))
    await transport.open()
    transport.subscribe("test/**", lambda batch: None)
    real_session: Any = transport.session
    release = threading.Event()

    class HangingSession:
        """Stands in for a zenoh session whose close() does not return."""

        def close(self) -> None:
            release.wait(10)
            real_session.close()

    transport._session = cast(Any, HangingSession())
    started = time.monotonic()
    try:
        with caplog.at_level(logging.WARNING, logger="telebot.channels.transports.zenoh"):
            await transport.close()
        elapsed = time.monotonic() - started
    finally:
        release.set()
    assert elapsed < 0.3 + 0.5 + SLACK  # the close timeout, not the hung close's 10 s
    assert "did not close within" in caplog.text


async def test_close_with_live_entities_is_quick(
    pair: tuple[ZenohTransport, ZenohTransport],
) -> None:
    listener, connector = pair
    test_id = uuid.uuid4().hex
    events: list[tuple[str, bool]] = []
    listener.watch_presence(f"test/{test_id}/**", lambda key, alive: events.append((key, alive)))
    for i in range(5):
        connector.subscribe(f"test/{test_id}/sub/{i}", lambda batch: None)
        connector.publisher(f"test/{test_id}/pub/{i}", Lane.BULK)
        connector.watch_presence(f"test/{test_id}/token/{i}", lambda key, alive: None)
        connector.declare_presence(f"test/{test_id}/token/{i}")
    await wait_until(lambda: len(events) == 5)
    started = time.monotonic()
    await connector.close()
    assert time.monotonic() - started < connector.settings.close_timeout + 0.5 + SLACK
    # Every token went with the session, and the other side saw it.
    await wait_until(lambda: len(events) == 10)
    assert sorted(key for key, alive in events if not alive) == [
        f"test/{test_id}/token/{i}" for i in range(5)
    ]


def test_connect_retries_default_to_a_quick_comeback_and_an_option_wins() -> None:
    default = json.loads(build_zenoh_config(ZenohSettings()).get_json("connect/retry"))
    assert default["period_init_ms"] == 100 and default["period_max_ms"] == 500
    mine = {"period_init_ms": 500, "period_max_ms": 5000, "period_increase_factor": 3}
    chosen = build_zenoh_config(ZenohSettings(options={"connect/retry": mine}))
    assert json.loads(chosen.get_json("connect/retry"))["period_init_ms"] == 500


def test_a_dialling_session_announces_a_one_second_lease_and_an_option_or_a_file_wins(
    tmp_path: Path,
) -> None:
    def lease(settings: ZenohSettings) -> int:
        return int(json.loads(build_zenoh_config(settings).get_json("transport/link/tx/lease")))

    # The dialling end: a client, or a peer that connects and does not listen.
    assert lease(ZenohSettings(mode="client")) == LINK_LEASE_MS == 1000
    assert lease(ZenohSettings(connect=["quic/127.0.0.1:7447"])) == 1000
    # The listening end keeps zenoh's 10 s, so after an outage it has dropped the link and
    # the dialler's first packet is answered with a reset (a new link at once).
    assert lease(ZenohSettings()) == 10_000
    assert lease(ZenohSettings(listen=["quic/0.0.0.0:7447"])) == 10_000
    assert lease(ZenohSettings(listen=["tcp/0.0.0.0:1"], connect=["tcp/127.0.0.1:2"])) == 10_000
    assert lease(ZenohSettings(mode="client", options={"transport/link/tx/lease": 7000})) == 7000
    file = tmp_path / "zenoh.json5"
    file.write_text('{"transport": {"link": {"tx": {"lease": 5000}}}}')
    assert lease(ZenohSettings(mode="client", config_file=file)) == 5000
    # The key sets it for any session; a dialler's default outlives a long call timeout.
    assert lease(ZenohSettings(listen=["quic/0.0.0.0:7447"], lease=2.5)) == 2500
    assert lease(AppConfig().transport.zenoh) == 10_000  # a peer listening on zenoh's default
    dialler = {"transport": {"zenoh": {"mode": "client"}}}
    assert lease(AppConfig.model_validate(dialler).transport.zenoh) == 1000
    slow = AppConfig.model_validate({**dialler, "call": {"timeout": 3.0}})
    assert lease(slow.transport.zenoh) == 6000
    # Endpoints changed after validation (--connect, --listen) count, not those at load time.
    later = AppConfig.model_validate({"call": {"timeout": 1.0}})
    later.transport.zenoh.connect = ["quic/127.0.0.1:7447"]
    assert lease(later.transport.zenoh) == 2000
    later.transport.zenoh.listen = ["quic/0.0.0.0:7448"]
    assert lease(later.transport.zenoh) == 10_000


def test_a_session_dialling_quic_splits_calls_data_onto_a_second_session() -> None:
    # On by default only where it pays: a dialler on QUIC (one congestion window per
    # connection); a listener, TCP, or the key set either way decides as it says.
    assert ZenohSettings(mode="client", connect=["quic/127.0.0.1:7447"]).splits_data
    assert ZenohSettings(connect=["quic/127.0.0.1:7447"]).splits_data
    assert not ZenohSettings(mode="client", connect=["tcp/127.0.0.1:7447"]).splits_data
    assert not ZenohSettings(listen=["quic/0.0.0.0:7447"]).splits_data
    assert not ZenohSettings(
        listen=["quic/0.0.0.0:7447"], connect=["quic/127.0.0.1:7448"]
    ).splits_data
    assert not ZenohSettings(
        mode="client", connect=["quic/127.0.0.1:7447"], data_session=False
    ).splits_data
    assert ZenohSettings(connect=["tcp/127.0.0.1:7447"], data_session=True).splits_data


def test_only_a_calls_data_keys_go_on_the_data_session() -> None:
    call = "telebot/user/alice/00112233aabbccdd/call/guiabot/0123456789abcdef"
    assert is_call_data_key(f"{call}/data")
    assert is_call_data_key("telebot/user/alice/00112233aabbccdd/call/guiabot/*/data")
    assert not is_call_data_key(f"{call}/ctl")
    # A user named "data" sends its HELLO here, and a robot named "call" listens here.
    assert not is_call_data_key("telebot/robot/guiabot/in/data")
    assert not is_call_data_key("telebot/robot/call/in/data")
    assert not is_call_data_key("telebot/user/alice/**")
    assert not is_call_data_key("data")


def test_the_data_session_only_dials() -> None:
    # Even where the first session listens (zenoh's default for a peer, or an endpoint),
    # the second takes no port and scouts nobody: it dials what the first dials, in the
    # first's mode (a peer keeps retrying an endpoint that is not up yet).
    settings = ZenohSettings(
        connect=["quic/127.0.0.1:7447", "quic/127.0.0.1:7449"], listen=["tcp/0.0.0.0:7448"]
    )
    config = data_session_config(settings)
    assert json.loads(config.get_json("mode")) == "peer"
    assert json.loads(config.get_json("listen/endpoints")) == []
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    assert json.loads(config.get_json("scouting/gossip/enabled")) is False
    assert json.loads(config.get_json("connect/endpoints")) == [
        "quic/127.0.0.1:7447?mixed_rel=auto",
        "quic/127.0.0.1:7449?mixed_rel=auto",
    ]
    client = data_session_config(settings.model_copy(update={"mode": "client", "listen": []}))
    assert json.loads(client.get_json("mode")) == "client"
    assert int(json.loads(client.get_json("transport/link/tx/lease"))) == LINK_LEASE_MS


async def test_a_peer_whose_robot_is_not_up_yet_opens_both_sessions_and_finds_it_later() -> None:
    # A user in peer mode (the default) started before its robot: both sessions open and
    # keep dialling; once the robot listens, a call's data reaches the data session.
    listen = f"tcp/127.0.0.1:{free_port()}"
    user = ZenohSettings(connect=[listen], multicast_scouting=False, data_session=True)
    call = f"t/{uuid.uuid4().hex}/call/guiabot/0123456789abcdef"
    async with ZenohTransport(user) as transport:
        assert transport.data_session is not None
        data = Inbox()
        transport.subscribe(f"{call}/data", data)
        robot = ZenohSettings(listen=[listen], multicast_scouting=False)
        async with ZenohTransport(robot) as robot_transport:
            await warm_up(robot_transport.publisher(f"{call}/data").put, data, timeout=15)


async def test_a_data_session_without_connect_endpoints_is_a_one_line_error() -> None:
    transport = ZenohTransport(ZenohSettings(data_session=True, multicast_scouting=False))
    with pytest.raises(TransportError, match=r"data_session = true needs connect endpoints"):
        await transport.open()


# --- publish / subscribe in one process ------------------------------------------------


async def test_an_adopting_transport_keeps_its_owners_data_session_and_leaves_both_open() -> None:
    # A robot that is a router's client on QUIC has a data session; its gateway adopts
    # both of its sessions, so a page's call data meets the robot's own on one session.
    listen = f"tcp/127.0.0.1:{free_port()}"
    call = f"t/{uuid.uuid4().hex}/call/guiabot/0123456789abcdef"
    peer = ZenohSettings(listen=[listen], multicast_scouting=False)
    dialler = ZenohSettings(
        mode="client", connect=[listen], multicast_scouting=False, data_session=True
    )
    async with ZenohTransport(peer) as robot, ZenohTransport(dialler) as owner:
        assert owner.data_session is not None
        gateway = ZenohTransport()
        await gateway.adopt(owner.session, owner.data_session)
        assert gateway.data_session is owner.data_session
        data, ctl = Inbox(), Inbox()
        gateway.subscribe(f"{call}/data", data)
        gateway.subscribe(f"{call}/ctl", ctl)
        to_data, to_ctl = robot.publisher(f"{call}/data"), robot.publisher(f"{call}/ctl")
        await warm_up(to_data.put, data)
        await warm_up(to_ctl.put, ctl)
        await gateway.close()
        # Both sessions stay open for their owner, which still hears the robot.
        mine = Inbox()
        owner.subscribe(f"{call}/data", mine)
        await warm_up(to_data.put, mine)
        # ...and the data key was on the data session: without it, nothing more comes.
        owner.data_session.close()
        await asyncio.sleep(0.2)
        to_data.put(b"after")
        await asyncio.sleep(0.5)
        assert mine.samples == []


async def test_roundtrip_between_two_transports(
    pair: tuple[ZenohTransport, ZenohTransport],
) -> None:
    listener, connector = pair
    test_id = uuid.uuid4().hex
    inbox = Inbox()
    listener.subscribe(f"test/{test_id}/in", inbox)
    publisher = connector.publisher(f"test/{test_id}/in")
    await warm_up(publisher.put, inbox)
    published = connector.stats.published
    payload = bytes(range(256)) * 4
    publisher.put(payload)
    sample = await inbox.next_sample()
    assert sample.key == f"test/{test_id}/in"
    assert sample.payload == payload
    assert connector.stats.published == published + 1
    assert listener.stats.received >= 1
    assert listener.session_id != connector.session_id


async def test_wildcard_pattern(pair: tuple[ZenohTransport, ZenohTransport]) -> None:
    listener, connector = pair
    test_id = uuid.uuid4().hex
    inbox = Inbox()
    listener.subscribe(f"test/{test_id}/**", inbox)
    await warm_up(connector.publisher(f"test/{test_id}/warm").put, inbox)
    connector.publisher(f"test/{test_id}/a/b/c").put(b"deep")
    connector.publisher(f"test/{test_id}-other/a").put(b"outside")
    connector.publisher(f"test/{test_id}/d").put(b"shallow")
    await wait_until(lambda: len(inbox.samples) >= 2)
    await asyncio.sleep(0.1)  # room for a wrong extra sample to show up
    assert sorted((s.key, s.payload) for s in inbox.samples) == [
        (f"test/{test_id}/a/b/c", b"deep"),
        (f"test/{test_id}/d", b"shallow"),
    ]


async def test_closed_subscription_gets_nothing(
    pair: tuple[ZenohTransport, ZenohTransport],
) -> None:
    listener, connector = pair
    key = f"test/{uuid.uuid4().hex}/in"
    inbox = Inbox()
    subscription = listener.subscribe(key, inbox)
    publisher = connector.publisher(key)
    await warm_up(publisher.put, inbox)
    subscription.close()
    subscription.close()  # idempotent
    publisher.put(b"after close")
    await asyncio.sleep(0.3)
    assert inbox.batches == []


def reader_threads(key: str) -> list[threading.Thread]:
    """The transport's reader threads for subscriptions on ``key``."""
    return [t for t in threading.enumerate() if t.name == f"zenoh-sub {key}"]


async def test_each_subscription_has_one_reader_thread_that_ends_with_it(
    pair: tuple[ZenohTransport, ZenohTransport],
) -> None:
    listener, connector = pair
    key, other = f"test/{uuid.uuid4().hex}/in", f"test/{uuid.uuid4().hex}/in"
    inbox = Inbox()
    subscription = listener.subscribe(key, inbox)
    listener.subscribe(other, Inbox())
    await warm_up(connector.publisher(key).put, inbox)
    (reader,) = reader_threads(key)
    assert reader.daemon and reader.is_alive() and len(reader_threads(other)) == 1
    subscription.close()
    # Ended by the time close returns: a reader still inside zenoh when the interpreter
    # exits aborts the process.
    assert not reader.is_alive()
    (remaining,) = reader_threads(other)
    await listener.close()  # closing the transport ends the others
    assert not remaining.is_alive()


def flood(put: Callable[[bytes], None], until: threading.Event) -> None:
    """Publish small samples as fast as possible until ``until`` is set."""
    while not until.is_set():
        put(b"x" * 64)


async def test_closing_a_subscription_mid_burst_ends_its_reader_quietly(
    pair: tuple[ZenohTransport, ZenohTransport],
) -> None:
    # Undeclaring closes zenoh's channel; the reader may be anywhere in a batch then,
    # and must end without an exception escaping its thread (warnings are errors here).
    listener, connector = pair
    for _ in range(20):
        key = f"test/{uuid.uuid4().hex}/in"
        inbox = Inbox()
        subscription = listener.subscribe(key, inbox)
        publisher = connector.publisher(key)
        await warm_up(publisher.put, inbox)
        (reader,) = reader_threads(key)
        flooding = threading.Event()

        flooder = threading.Thread(target=flood, args=(publisher.put, flooding))
        flooder.start()
        try:
            await wait_until(lambda inbox=inbox: len(inbox.batches) > 2)
            subscription.close()
            await asyncio.to_thread(reader.join, 2.0)
        finally:
            flooding.set()
            flooder.join()
        assert not reader.is_alive()


async def test_callback_error_is_logged_and_delivery_goes_on(
    pair: tuple[ZenohTransport, ZenohTransport], caplog: pytest.LogCaptureFixture
) -> None:
    listener, connector = pair
    key = f"test/{uuid.uuid4().hex}/in"
    inbox = Inbox()

    def explosive(batch: Sequence[Sample]) -> None:
        inbox(batch)
        if any(sample.payload == b"boom" for sample in batch):
            raise RuntimeError("consumer bug")

    listener.subscribe(key, explosive)
    publisher = connector.publisher(key)
    await warm_up(publisher.put, inbox)
    with caplog.at_level(logging.ERROR, logger="telebot.channels.transports.zenoh"):
        publisher.put(b"boom")
        assert (await inbox.next_sample()).payload == b"boom"
        publisher.put(b"after")
        assert (await inbox.next_sample()).payload == b"after"
    assert "consumer bug" in caplog.text


# --- batching and back-pressure -----------------------------------------------------


async def test_burst_arrives_in_few_batches(pair: tuple[ZenohTransport, ZenohTransport]) -> None:
    listener, connector = pair
    key = f"test/{uuid.uuid4().hex}/burst"
    inbox = Inbox()
    listener.subscribe(key, inbox)
    publisher = connector.publisher(key)
    await warm_up(publisher.put, inbox)
    # Within zenoh's ring (256 samples): the reader thread may not run before the burst is
    # in (this loop holds the GIL while it publishes), and a ring that overflows drops.
    count = 250
    for i in range(count):
        publisher.put(b"%d" % i)
    # Keep the loop busy while zenoh's threads receive the burst (as a loaded robot's
    # would be): everything that arrived meanwhile must come in a handful of wake-ups.
    time.sleep(0.3)  # noqa: ASYNC251  (blocking the loop is the point here)
    await wait_until(lambda: len(inbox.samples) >= count)
    await asyncio.sleep(0.05)
    assert [s.payload for s in inbox.samples] == [b"%d" % i for i in range(count)]
    assert len(inbox.batches) < count // 10, f"{len(inbox.batches)} loop wake-ups"
    assert listener.stats.dropped == 0


async def test_slow_consumer_drops_oldest() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    async with (
        ZenohTransport(listen_settings(endpoint, queue_size=16)) as listener,
        ZenohTransport(connect_settings(endpoint)) as connector,
    ):
        key = f"test/{uuid.uuid4().hex}/flood"
        inbox = Inbox()
        count = 200
        blocking = threading.Event()
        sent = threading.Event()

        def consumer(batch: Sequence[Sample]) -> None:
            inbox(batch)
            if any(sample.payload == b"block" for sample in batch):
                # Hog the event loop while the flood arrives, as a slow consumer would.
                blocking.set()
                sent.wait(5)
                # The reader thread's own count: the transport's stats are updated on
                # the loop, which this consumer is holding.
                deadline = time.monotonic() + 5
                while subscription.inbox.received < received_before + count + 1:
                    assert time.monotonic() < deadline, "flood did not arrive"
                    time.sleep(0.01)

        subscription = listener.subscribe(key, consumer)
        publisher = connector.publisher(key)
        await warm_up(publisher.put, inbox)
        received_before = subscription.inbox.received

        def flood() -> None:
            blocking.wait(5)
            for i in range(count):
                publisher.put(b"%d" % i)
            sent.set()

        sender = threading.Thread(target=flood)
        sender.start()
        try:
            publisher.put(b"block")
            await wait_until(lambda: any(s.payload == b"199" for s in inbox.samples))
        finally:
            sent.set()
            sender.join()
        after_block = [s.payload for s in inbox.samples if s.payload != b"block"]
        # Only the newest queue_size samples survived, in order, in one batch.
        assert after_block == [b"%d" % i for i in range(count - 16, count)]
        assert listener.stats.dropped == count - 16
        assert len(inbox.batches[-1]) == 16


async def test_receive_limits_bound_bytes_drop_oversized_uncopied_and_cap_batches() -> None:
    """A subscription's own limits: the queue holds at most ``max_bytes`` (oldest dropped),
    a payload over ``max_payload`` is dropped and counted, and the callback gets at most
    ``batch`` samples per loop turn."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    limits = ReceiveLimits(max_bytes=10_000, max_payload=5_000, batch=4)
    async with (
        ZenohTransport(listen_settings(endpoint)) as listener,
        ZenohTransport(connect_settings(endpoint)) as connector,
    ):
        key = f"test/{uuid.uuid4().hex}/flood"
        inbox = Inbox()
        count = 20
        blocking = threading.Event()
        sent = threading.Event()

        def consumer(batch: Sequence[Sample]) -> None:
            inbox(batch)
            if any(sample.payload == b"block" for sample in batch):
                blocking.set()  # hog the loop while the flood arrives
                sent.wait(5)
                deadline = time.monotonic() + 5
                # The block itself, the flood and the oversized one.
                while (
                    subscription.inbox.received + subscription.inbox.oversized
                    < before + 1 + count + 1
                ):
                    assert time.monotonic() < deadline, "flood did not arrive"
                    time.sleep(0.01)

        subscription = listener.subscribe(key, consumer, limits=limits)
        publisher = connector.publisher(key)
        await warm_up(publisher.put, inbox)
        before = subscription.inbox.received + subscription.inbox.oversized

        def flood() -> None:
            blocking.wait(5)
            for i in range(count):
                publisher.put(b"%02d" % i + bytes(998))
            publisher.put(bytes(6_000))  # over max_payload
            sent.set()

        sender = threading.Thread(target=flood)
        sender.start()
        try:
            publisher.put(b"block")
            await wait_until(lambda: any(s.payload[:2] == b"19" for s in inbox.samples))
        finally:
            sent.set()
            sender.join()
        after_block = [s.payload[:2] for s in inbox.samples if s.payload != b"block"]
        # 10 payloads of 1,000 bytes fill 10,000 bytes: the newest 10 survived, in order.
        assert after_block == [b"%02d" % i for i in range(count - 10, count)]
        assert subscription.stats.dropped == count - 10
        assert subscription.stats.oversized == 1
        assert listener.stats.oversized == 1
        flood_batches = inbox.batches[-3:]
        assert [len(batch) for batch in flood_batches] == [4, 4, 2]


# --- lanes ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("lane", "priority", "express"),
    [
        (Lane.CONTROL, zenoh.Priority.REAL_TIME, True),
        (Lane.DATA, zenoh.Priority.DATA, False),
        (Lane.BULK, zenoh.Priority.DATA_LOW, False),
    ],
)
async def test_lane_qos(
    pair: tuple[ZenohTransport, ZenohTransport], lane: Lane, priority: Any, express: bool
) -> None:
    listener, connector = pair
    key = f"test/{uuid.uuid4().hex}/{lane.value}"
    publisher = connector.publisher(key, lane)
    assert publisher.raw.priority == priority
    assert publisher.raw.congestion_control == zenoh.CongestionControl.DROP
    # The QoS must also travel with the data: look at the sample the other side gets.
    received: list[Any] = []
    raw_sub: Any = listener.session.declare_subscriber(key, received.append)
    try:
        deadline = time.monotonic() + 5
        while not received:
            assert time.monotonic() < deadline, "nothing received"
            publisher.put(b"x")
            await asyncio.sleep(0.05)
        sample = received[0]
        assert sample.priority == priority
        assert sample.express is express
        assert sample.congestion_control == zenoh.CongestionControl.DROP
    finally:
        raw_sub.undeclare()


# --- across two processes ------------------------------------------------------------


async def test_roundtrip_across_processes(peer_factory: Callable[..., Peer]) -> None:
    test_id = uuid.uuid4().hex
    peer = peer_factory(test_id)
    await peer.ready()
    async with ZenohTransport(connect_settings(peer.endpoint)) as transport:
        inbox = Inbox()
        transport.subscribe(f"test/{test_id}/pong", inbox)
        ping = transport.publisher(f"test/{test_id}/ping")
        await warm_up(ping.put, inbox)
        for size in (0, 1, 100, 1400, 8192, 32768, 32768 + 100):
            payload = os.urandom(size)
            ping.put(payload)
            sample = await inbox.next_sample()
            assert sample.key == f"test/{test_id}/pong"
            assert sample.payload == payload, f"size {size}"


async def test_presence_across_processes(peer_factory: Callable[..., Peer]) -> None:
    test_id = uuid.uuid4().hex
    token = f"test/{test_id}/presence/child"
    peer = peer_factory(test_id, token=token)
    await peer.ready()
    async with ZenohTransport(connect_settings(peer.endpoint)) as transport:
        events: list[tuple[str, bool]] = []
        transport.watch_presence(f"test/{test_id}/presence/**", lambda k, a: events.append((k, a)))
        await wait_until(lambda: (token, True) in events)
        peer.proc.kill()  # SIGKILL: no goodbye, only the TCP link closing
        started = time.monotonic()
        await wait_until(lambda: (token, False) in events, timeout=5.0 + SLACK)
        assert time.monotonic() - started < 5.0 + SLACK  # the TCP link, not the 10 s lease
        assert events == [(token, True), (token, False)]


async def test_local_presence_token_and_watch(
    pair: tuple[ZenohTransport, ZenohTransport],
) -> None:
    listener, connector = pair
    test_id = uuid.uuid4().hex
    events: list[tuple[str, bool]] = []
    on_loop: list[bool] = []
    loop_thread = threading.get_ident()

    def watcher(key: str, alive: bool) -> None:
        on_loop.append(threading.get_ident() == loop_thread)
        events.append((key, alive))

    early = connector.declare_presence(f"test/{test_id}/early")
    listener.watch_presence(f"test/{test_id}/*", watcher)
    await wait_until(lambda: (f"test/{test_id}/early", True) in events)  # history
    late = connector.declare_presence(f"test/{test_id}/late")
    await wait_until(lambda: (f"test/{test_id}/late", True) in events)
    late.close()
    await wait_until(lambda: (f"test/{test_id}/late", False) in events)
    assert (f"test/{test_id}/early", False) not in events
    early.close()
    await wait_until(lambda: (f"test/{test_id}/early", False) in events)
    assert all(on_loop)
