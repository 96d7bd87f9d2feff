"""The network emulator's proxy on real sockets (127.0.0.1), and its command line.

Assertions are about behaviour (what arrives, in what order, what is lost, what survives
an outage); times only as lower bounds (an emulated delay cannot make things faster).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import os
import socket
import struct
import threading
from collections.abc import AsyncIterator, Iterator
from typing import cast

import pytest

from conftest import wait_until
from rig import SLACK, Process
from telebot.apps import netem_cli
from telebot.errors import ConfigError, TransportError
from telebot.netem import LinkModel, NetemProxy, Profile
from telebot.testing.net import free_port

LOSSY = Profile("lossy", delay=0.01, jitter=0.005, loss=0.1)


def open_fds() -> set[str]:
    return set(os.listdir("/proc/self/fd"))


def netem_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("netem-")]


# --------------------------------------------------------------------------- UDP


class _Recorder(asyncio.DatagramProtocol):
    """A UDP server that records what it receives and echoes it back."""

    def __init__(self) -> None:
        self.got: list[bytes] = []
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.DatagramTransport, transport)

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.got.append(data)
        assert self.transport is not None
        self.transport.sendto(b"echo:" + data, addr)


class _Client(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.got: list[bytes] = []

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.got.append(data)


@contextlib.asynccontextmanager
async def udp_echo() -> AsyncIterator[tuple[_Recorder, int]]:
    loop = asyncio.get_running_loop()
    transport, server = await loop.create_datagram_endpoint(_Recorder, local_addr=("127.0.0.1", 0))
    try:
        yield server, transport.get_extra_info("sockname")[1]
    finally:
        transport.close()


@contextlib.asynccontextmanager
async def udp_client(port: int) -> AsyncIterator[tuple[asyncio.DatagramTransport, _Client]]:
    loop = asyncio.get_running_loop()
    transport, client = await loop.create_datagram_endpoint(
        _Client, remote_addr=("127.0.0.1", port)
    )
    try:
        yield transport, client
    finally:
        transport.close()


def settled(proxy: NetemProxy, at_server: int, at_client: int) -> bool:
    """Whether nothing is in flight any more: all sent has arrived or been lost."""
    s = proxy.stats
    return (
        s.delivered_up == at_server == s.up.sent - s.up.lost == s.down.sent
        and s.delivered_down == at_client == s.down.sent - s.down.lost
    )


async def test_udp_datagrams_meet_the_seeded_losses_of_the_model_both_ways() -> None:
    async with udp_echo() as (server, port):
        with NetemProxy(LOSSY, "udp/127.0.0.1:0", f"udp/127.0.0.1:{port}", seed=7) as proxy:
            assert proxy.mode == "udp" and proxy.endpoint.startswith("udp/127.0.0.1:")
            async with udp_client(int(proxy.endpoint.rsplit(":", 1)[1])) as (sock, client):
                sent = 0
                for _batch in range(20):  # in batches, so no socket buffer overflows
                    for _ in range(25):
                        sock.sendto(struct.pack(">I", sent))
                        sent += 1
                    await wait_until(lambda n=sent: proxy.stats.up.sent == n)  # type: ignore[misc]
                await wait_until(lambda: settled(proxy, len(server.got), len(client.got)))
        stats = proxy.stats
    # Exactly the datagrams the model loses with this seed never reach the server...
    replay = LinkModel(LOSSY, 7, "up")
    expected = [replay.transmit(4, 0.0) is not None for _ in range(sent)]
    arrived = {struct.unpack(">I", data)[0] for data in server.got}
    assert arrived == {i for i, ok in enumerate(expected) if ok}
    assert stats.up.lost == expected.count(False) and 20 < stats.up.lost < 80  # ~10 %
    # ...and of the echoes, the model's "down" direction loses its own share.
    assert len(client.got) == stats.delivered_down == len(arrived) - stats.down.lost
    assert 20 < stats.down.lost < 80
    assert stats.connections == 1


async def test_udp_delays_each_way_and_keeps_clients_apart() -> None:
    slow = Profile("slow", delay=0.1)
    async with udp_echo() as (_server, port):
        with NetemProxy(slow, "udp/127.0.0.1:0", f"udp/127.0.0.1:{port}") as proxy:
            listen = int(proxy.endpoint.rsplit(":", 1)[1])
            async with udp_client(listen) as (a, got_a), udp_client(listen) as (b, got_b):
                loop = asyncio.get_running_loop()
                start = loop.time()
                a.sendto(b"from a")
                b.sendto(b"from b")
                await wait_until(lambda: got_a.got and got_b.got)
                assert loop.time() - start >= 0.2  # 100 ms each way
                assert (got_a.got, got_b.got) == ([b"echo:from a"], [b"echo:from b"])
            assert proxy.stats.connections == 2


async def test_a_udp_outage_loses_what_is_sent_during_it() -> None:
    async with udp_echo() as (server, port):
        with NetemProxy("lan", "udp/127.0.0.1:0", f"udp/127.0.0.1:{port}") as proxy:
            async with udp_client(int(proxy.endpoint.rsplit(":", 1)[1])) as (sock, client):
                sock.sendto(b"before")
                await wait_until(lambda: client.got == [b"echo:before"])
                proxy.outage(1.0 + SLACK)
                sock.sendto(b"during")
                await wait_until(lambda: proxy.stats.up.sent == 2)
                assert proxy.stats.up.outage_lost == 1
                while not server.got[1:]:  # after the gap, datagrams pass again
                    sock.sendto(b"after")
                    await asyncio.sleep(0.1)
            assert b"during" not in server.got and server.got[1] == b"after"
            assert proxy.stats.outages == 1


# --------------------------------------------------------------------------- TCP


@contextlib.asynccontextmanager
async def tcp_echo() -> AsyncIterator[int]:
    async def echo(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        with contextlib.suppress(OSError):
            while data := await reader.read(65536):
                writer.write(data)
                await writer.drain()
        writer.close()

    server = await asyncio.start_server(echo, "127.0.0.1", 0)
    try:
        yield server.sockets[0].getsockname()[1]
    finally:
        server.close()


def port_of(proxy: NetemProxy) -> int:
    return int(proxy.endpoint.rsplit(":", 1)[1])


async def test_a_tcp_stream_loses_nothing_but_lost_segments_stall_it() -> None:
    lossy = dataclasses.replace(LOSSY, loss=0.05)
    payload = os.urandom(300_000)  # ~200 segments each way: a handful lost
    async with tcp_echo() as port:
        with NetemProxy(lossy, "tcp/127.0.0.1:0", f"tcp/127.0.0.1:{port}", seed=3) as proxy:
            reader, writer = await asyncio.open_connection("127.0.0.1", port_of(proxy))
            loop = asyncio.get_running_loop()
            start = loop.time()
            writer.write(payload)
            echoed = await asyncio.wait_for(reader.readexactly(len(payload)), 30 + SLACK)
            elapsed = loop.time() - start
            writer.close()
            await wait_until(lambda: not proxy._relay.connections)  # type: ignore[union-attr]
            stats = proxy.stats
    assert echoed == payload  # whole and in order
    assert stats.up.retransmitted > 0 and stats.down.retransmitted > 0
    assert stats.up.lost == stats.down.lost == 0
    assert stats.bytes_up == stats.bytes_down == len(payload)
    # A lost segment waits an RTO (200 ms at least) and holds up what follows it.
    assert elapsed >= 0.2 + 2 * lossy.delay - 2 * lossy.jitter


async def test_a_tcp_half_close_passes_on_after_the_data() -> None:
    async def count(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        received = len(await reader.read())  # until the client's EOF
        writer.write(str(received).encode())
        writer.close()

    server = await asyncio.start_server(count, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        with NetemProxy(LOSSY, "tcp/127.0.0.1:0", f"tcp/127.0.0.1:{port}") as proxy:
            reader, writer = await asyncio.open_connection("127.0.0.1", port_of(proxy))
            writer.write(bytes(100_000))
            writer.write_eof()
            # The EOF reached the server after all the data; its answer came back.
            assert await asyncio.wait_for(reader.read(), 30 + SLACK) == b"100000"
            writer.close()
    finally:
        server.close()


async def test_a_tcp_bandwidth_cap_paces_the_stream() -> None:
    capped = Profile("capped", rate_up=4e6, queue=0.05)
    async with tcp_echo() as port:
        with NetemProxy(capped, "tcp/127.0.0.1:0", f"tcp/127.0.0.1:{port}") as proxy:
            reader, writer = await asyncio.open_connection("127.0.0.1", port_of(proxy))
            loop = asyncio.get_running_loop()
            start = loop.time()
            writer.write(bytes(200_000))  # 1.6 Mbit at 4 Mbit/s: 0.4 s at least
            await asyncio.wait_for(reader.readexactly(200_000), 30 + SLACK)
            assert loop.time() - start >= 0.39
            writer.close()


async def test_tcp_connections_share_the_link_s_bandwidth() -> None:
    # Two connections through one 4 Mbit/s uplink: 2 x 1.6 Mbit take 0.8 s at least (each
    # with a cap of its own, both would be through in 0.4 s).
    capped = Profile("capped", rate_up=4e6, queue=0.05)
    async with tcp_echo() as port:
        with NetemProxy(capped, "tcp/127.0.0.1:0", f"tcp/127.0.0.1:{port}") as proxy:
            pairs = [await asyncio.open_connection("127.0.0.1", port_of(proxy)) for _ in "ab"]
            loop = asyncio.get_running_loop()
            start = loop.time()
            for _, writer in pairs:
                writer.write(bytes(200_000))
            reads = (reader.readexactly(200_000) for reader, _ in pairs)
            echoed = await asyncio.wait_for(asyncio.gather(*reads), 30 + SLACK)
            elapsed = loop.time() - start
            for _, writer in pairs:
                writer.close()
    assert [len(e) for e in echoed] == [200_000, 200_000]
    assert elapsed >= 0.79


async def test_a_short_tcp_outage_delays_the_stream_and_a_long_one_cuts_it() -> None:
    async with tcp_echo() as port:
        with NetemProxy("lan", "tcp/127.0.0.1:0", f"tcp/127.0.0.1:{port}", cut_after=0.8) as proxy:
            reader, writer = await asyncio.open_connection("127.0.0.1", port_of(proxy))
            loop = asyncio.get_running_loop()
            # Shorter than cut_after: held up, not lost, the connection stays.
            proxy.outage(0.5)
            start = loop.time()
            writer.write(b"during a roam")
            assert await asyncio.wait_for(reader.readexactly(13), 10 + SLACK) == b"during a roam"
            assert loop.time() - start >= 0.5 - 0.05  # not before the gap ended
            assert proxy.stats.cut == 0 and proxy.stats.up.retransmitted == 1
            # Longer than cut_after: the connection is reset, new ones are refused...
            proxy.outage(2.0)
            with pytest.raises((ConnectionError, asyncio.IncompleteReadError)):
                await asyncio.wait_for(reader.readexactly(1), 10 + SLACK)
            writer.close()
            assert proxy.stats.cut == 1
            again, again_writer = await asyncio.open_connection("127.0.0.1", port_of(proxy))
            with pytest.raises((ConnectionError, asyncio.IncompleteReadError)):
                await asyncio.wait_for(again.readexactly(1), 10 + SLACK)
            again_writer.close()
            assert proxy.stats.refused >= 1
            # ...until it ends.
            await wait_until(lambda: proxy.schedule.gap_at(loop.time()) is None, 10 + SLACK)
            await asyncio.sleep(0.1)  # the proxy notices within its 20 ms housekeeping
            fresh, fresh_writer = await asyncio.open_connection("127.0.0.1", port_of(proxy))
            fresh_writer.write(b"back")
            assert await asyncio.wait_for(fresh.readexactly(4), 10 + SLACK) == b"back"
            fresh_writer.close()


# --------------------------------------------------------------------------- lifecycle


@pytest.fixture
def no_leaks() -> Iterator[None]:
    fds, threads = open_fds(), netem_threads()
    yield
    assert netem_threads() == threads
    assert open_fds() <= fds


def test_close_leaves_no_thread_nor_socket(no_leaks: None) -> None:
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
        for listen in ("tcp/127.0.0.1:0", "udp/127.0.0.1:0"):
            target = f"{listen[:3]}/127.0.0.1:{port}"
            with NetemProxy("wifi", listen, target) as proxy:
                kind = socket.SOCK_STREAM if proxy.mode == "tcp" else socket.SOCK_DGRAM
                with socket.socket(socket.AF_INET, kind) as client:
                    client.connect(("127.0.0.1", port_of(proxy)))
                    client.send(b"hello")
                    if proxy.mode == "tcp":
                        conn, _ = server.accept()
                        assert conn.recv(5) == b"hello"
                        conn.close()
                    else:
                        for _ in range(500):  # the UDP upstream socket is opened
                            if proxy.stats.delivered_up:
                                break
                            threading.Event().wait(0.01)
                        assert proxy.stats.delivered_up == 1
            proxy.close()  # idempotent


def test_bad_endpoints_and_a_port_in_use_are_one_error_each() -> None:
    with pytest.raises(ConfigError, match=r"endpoint 'ws/1.2.3.4:5': expected one of udp/"):
        NetemProxy("lan", "ws/1.2.3.4:5", "tcp/127.0.0.1:7447")
    with pytest.raises(ConfigError, match=r"expected tcp/HOST:PORT, port 1..65535"):
        NetemProxy("lan", "tcp/127.0.0.1:0", "tcp/127.0.0.1:0")
    with pytest.raises(ConfigError, match="cannot relay udp/ to tcp/"):
        NetemProxy("lan", "udp/127.0.0.1:0", "tcp/127.0.0.1:7447")
    with pytest.raises(ConfigError, match="unknown network profile 'fiber'"):
        NetemProxy("fiber", "udp/127.0.0.1:0", "udp/127.0.0.1:7447")
    with socket.create_server(("127.0.0.1", 0)) as busy:
        port = busy.getsockname()[1]
        proxy = NetemProxy("lan", f"tcp/127.0.0.1:{port}", "tcp/127.0.0.1:7447")
        with pytest.raises(TransportError, match=f"cannot listen on tcp/127.0.0.1:{port}: address"):
            proxy.start()
    assert not netem_threads()
    with pytest.raises(TransportError, match="not running"):
        proxy.outage(1.0)


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (
            ["dialup", "--listen", "tcp/127.0.0.1:0", "--to", "tcp/127.0.0.1:1"],
            "argument PROFILE: unknown network profile 'dialup'; known: lan, wifi",
        ),
        (
            ["wifi", "--listen", "tcp/127.0.0.1", "--to", "tcp/127.0.0.1:1"],
            "argument --listen: endpoint 'tcp/127.0.0.1': expected tcp/HOST:PORT",
        ),
        (
            ["wifi", "--listen", "udp/127.0.0.1:0", "--to", "tcp/127.0.0.1:1"],
            "cannot relay udp/ to tcp/",
        ),
        (["wifi", "--listen", "tcp/127.0.0.1:0"], "the following arguments are required: --to"),
        (
            ["wifi", "--listen", "tcp/127.0.0.1:0", "--to", "tcp/1.2.3.4:1", "--cut-after", "-1"],
            "argument --cut-after: expected seconds > 0",
        ),
    ],
)
def test_the_cli_refuses_bad_flags_in_one_line(
    args: list[str], needle: str, capsys: pytest.CaptureFixture[str]
) -> None:
    try:
        code = netem_cli.main(args)
    except SystemExit as exc:  # argparse's own errors
        code = int(exc.code or 0)
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and needle in err and err.startswith("telebot-netem: error: ")


def test_the_cli_refuses_a_port_in_use_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    with socket.create_server(("127.0.0.1", 0)) as busy:
        port = busy.getsockname()[1]
        code = netem_cli.main(["lan", "--listen", f"tcp/127.0.0.1:{port}", "--to", "tcp/1.2.3.4:1"])
    assert code == 2
    assert capsys.readouterr().err == (
        f"telebot-netem: error: cannot listen on tcp/127.0.0.1:{port}: address already in use\n"
    )


async def test_the_cli_relays_until_sigterm() -> None:
    async with tcp_echo() as port:
        listen = free_port()
        proc = Process(
            [
                "telebot.apps.netem_cli",
                "4g",
                "--listen",
                f"tcp/127.0.0.1:{listen}",
                "--to",
                f"tcp/127.0.0.1:{port}",
                "--seed",
                "5",
                "--events",
            ]
        )
        try:
            ready = await proc.next_event(timeout=30)
            assert ready == {
                "event": "ready",
                "profile": "4g",
                "listen": f"tcp/127.0.0.1:{listen}",
                "to": f"tcp/127.0.0.1:{port}",
                "seed": 5,
            }
            reader, writer = await asyncio.open_connection("127.0.0.1", listen)
            writer.write(b"over 4g")
            assert await asyncio.wait_for(reader.readexactly(7), 10 + SLACK) == b"over 4g"
            writer.close()
            proc.popen.terminate()
            assert await asyncio.to_thread(proc.popen.wait, 30) == 0
        finally:
            proc.stop()


def test_the_profile_names_in_help_are_the_profiles(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        netem_cli.main(["--help"])
    assert "lan, wifi, 4g, intercontinental, bad" in " ".join(capsys.readouterr().out.split())
