"""One contract suite for calls and channels, run on every transport.

``memory``: robot and user endpoints on one in-process hub. ``zenoh``: the robot is a real
``telebot-robot echo`` process on 127.0.0.1 (its own free port), the user is this process.
Both robots echo every datagram back and answer ``_stats`` with their counters.
"""

from __future__ import annotations

import asyncio
import json
import os
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from conftest import ROBOT, USER, Homes, Process, memory_endpoints, write_config
from rig import GENEROUS_TIMEOUT, SLACK
from telebot.apps.echo import STATS_CHANNEL, echo_call
from telebot.channels.call import Call, RobotEndpoint, UserEndpoint
from telebot.channels.channel import Channel
from telebot.channels.proto.frames import MAX_DATAGRAM
from telebot.channels.transports import Lane, Sample, Transport
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import CallSettings, ZenohSettings
from telebot.errors import CallEnded, CallError, CallRejected, CallTimeout, DatagramTooLarge
from telebot.identity import Identity, KnownRobots, encode_key
from telebot.testing.net import free_port

#: Call settings of robots and users here unless a test says otherwise: no test in this suite
#: is about drop timing, and a preempted process must not drop a call (tests/rig.py).
GENEROUS = CallSettings(timeout=GENEROUS_TIMEOUT)


class Peer:
    """A robot that echoes, reachable from user endpoints this test opens."""

    kind: str
    homes: Homes
    events: asyncio.Queue[dict[str, Any]]

    async def user_transport(self) -> Transport:
        raise NotImplementedError

    async def wait_event(self, name: str, timeout: float = 10.0) -> dict[str, Any]:
        raise NotImplementedError

    async def kill(self) -> None:
        """End the robot without a hang-up."""
        raise NotImplementedError


class MemoryPeer(Peer):
    kind = "memory"

    def __init__(self, homes: Homes) -> None:
        self.homes = homes
        self.hub = MemoryHub(seed=11)
        self.events = asyncio.Queue()
        self._users = 0

    async def start(self) -> None:
        self.robot_transport = MemoryTransport(self.hub, "robot")
        await self.robot_transport.open()
        self.robot = RobotEndpoint(
            self.robot_transport, self.homes.robot, self.homes.contacts, settings=GENEROUS
        )
        await self.robot.start()
        self.robot.on_call = lambda call: echo_call(call, self.robot, self.events.put_nowait)

    async def user_transport(self) -> Transport:
        self._users += 1
        transport = MemoryTransport(self.hub, f"user{self._users}")
        await transport.open()
        return transport

    async def wait_event(self, name: str, timeout: float = 10.0) -> dict[str, Any]:
        async with asyncio.timeout(timeout):
            while True:
                event = await self.events.get()
                if event["event"] == name:
                    return event

    async def kill(self) -> None:
        await self.robot_transport.close()  # presence disappears, nothing is hung up

    async def stop(self) -> None:
        await self.robot.close()
        await self.robot_transport.close()


class ZenohPeer(Peer):
    kind = "zenoh"

    def __init__(self, homes: Homes, tmp_path: Path) -> None:
        self.homes = homes
        self.port = free_port()
        config = write_config(tmp_path / "robot.toml", timeout=GENEROUS.timeout)
        self.process = Process(
            [
                "telebot.apps.robot_cli",
                "echo",
                "--home",
                str(homes.robot_home),
                "--config",
                str(config),
                "--listen",
                f"tcp/127.0.0.1:{self.port}",
                "--events",
            ]
        )

    async def start(self) -> None:
        await self.process.wait_event("ready")

    async def user_transport(self) -> Transport:
        from telebot.channels.transports.zenoh import ZenohTransport

        settings = ZenohSettings(connect=[f"tcp/127.0.0.1:{self.port}"], multicast_scouting=False)
        transport = ZenohTransport(settings)
        await transport.open()
        return transport

    async def wait_event(self, name: str, timeout: float = 10.0) -> dict[str, Any]:
        return await self.process.wait_event(name, timeout)

    async def kill(self) -> None:
        self.process.popen.kill()
        await asyncio.to_thread(self.process.popen.wait)

    async def stop(self) -> None:
        self.process.stop()


@pytest.fixture(params=["memory", pytest.param("zenoh", marks=pytest.mark.zenoh)])
async def peer(request: pytest.FixtureRequest, homes: Homes, tmp_path: Path) -> AsyncIterator[Peer]:
    robot: MemoryPeer | ZenohPeer = (
        MemoryPeer(homes) if request.param == "memory" else ZenohPeer(homes, tmp_path)
    )
    try:
        await robot.start()
        yield robot
    finally:
        await robot.stop()


class User:
    """A user endpoint on its own transport, closed at the end."""

    def __init__(
        self,
        peer: Peer,
        identity: Identity | None = None,
        known: KnownRobots | None = None,
        settings: CallSettings | None = None,
    ) -> None:
        self.peer = peer
        self.identity = identity or peer.homes.user
        self.known = known or peer.homes.known
        self.settings = settings or GENEROUS

    async def __aenter__(self) -> UserEndpoint:
        self.transport = await self.peer.user_transport()
        self.endpoint = UserEndpoint(
            self.transport, self.identity, self.known, settings=self.settings
        )
        await self.endpoint.start()
        return self.endpoint

    async def __aexit__(self, *exc: object) -> None:
        await self.endpoint.close()
        await self.transport.close()


async def robot_stats(call: Call) -> dict[str, Any]:
    """Ask the echo robot for its counters of this call."""
    stats = call.channel(STATS_CHANNEL)
    for _ in range(20):  # the request or its answer may be lost on a lossy link
        stats.send("?")
        try:
            reply = await asyncio.wait_for(stats.receive(), 0.5)
        except TimeoutError:
            continue
        assert isinstance(reply.payload, str)
        result: dict[str, Any] = json.loads(reply.payload)
        return result
    raise AssertionError("the robot never answered _stats")


async def echo(channel: Channel, payload: str | bytes, timeout: float = 5.0) -> str | bytes:
    channel.send(payload)
    reply = await asyncio.wait_for(channel.receive(), timeout)
    return reply.payload


async def test_call_and_echo_on_runtime_channels(peer: Peer) -> None:
    async with User(peer) as user:
        call = await user.call(ROBOT)
        assert call.peer == ROBOT and call.role is not None and call.role.value == "driver"
        event = await peer.wait_event("call")
        assert event["peer"] == USER and event["id"] == call.id
        for name in ("chat", "pose", "vidéo/nav", "x" * 255):
            channel = call.channel(name)
            assert await echo(channel, f"hello {name}") == f"hello {name}"
            assert await echo(channel, b"\x00\xffbinary") == b"\x00\xffbinary"
        chat = call.channel("chat")
        reply_from = None
        chat.send("who?")
        async for datagram in chat:
            reply_from = datagram.sender
            assert datagram.channel == "chat"
            break
        assert reply_from == ROBOT
        assert chat.stats.sent == 3 and chat.stats.received == 3


async def test_datagram_size_limit(peer: Peer) -> None:
    async with User(peer) as user:
        call = await user.call(ROBOT)
        channel = call.channel("big", lane=Lane.BULK)
        largest = os.urandom(MAX_DATAGRAM)
        assert await echo(channel, largest) == largest
        assert await echo(channel, "é" * (MAX_DATAGRAM // 2)) == "é" * (MAX_DATAGRAM // 2)
        frames_before = call.stats.frames_sent
        with pytest.raises(DatagramTooLarge):
            channel.send(os.urandom(MAX_DATAGRAM + 1))
        with pytest.raises(DatagramTooLarge):
            channel.send("é" * (MAX_DATAGRAM // 2) + "x")
        assert call.stats.frames_sent == frames_before  # refused before any I/O
        assert channel.stats.rejected == 2 and channel.stats.sent == 2


async def test_unauthorised_caller_is_rejected_with_reason(peer: Peer, tmp_path: Path) -> None:
    mallory = Identity.generate("mallory")
    async with User(peer, identity=mallory) as user:
        with pytest.raises(CallRejected, match=f"not in the contact list of {ROBOT}"):
            await user.call(ROBOT)


async def test_a_robot_online_with_another_key_fails_at_once_with_key_mismatch(
    peer: Peer, tmp_path: Path
) -> None:
    known = KnownRobots(tmp_path / "k.toml")
    wrong = Identity.generate(ROBOT).public_key  # not the key the robot runs with
    known.add(ROBOT, wrong)
    async with User(peer, known=known) as user:
        started = time.monotonic()
        with pytest.raises(CallError, match="KEY MISMATCH") as caught:
            await user.call(ROBOT, timeout=10.0)
        # At once (its presence token shows its key), not after the call's timeout.
        assert not isinstance(caught.value, CallTimeout)
        assert time.monotonic() - started < 5.0 + SLACK
        message = str(caught.value)
        assert encode_key(peer.homes.robot.public_key) in message and encode_key(wrong) in message


async def test_a_known_robot_that_is_not_online_times_out(peer: Peer, tmp_path: Path) -> None:
    known = KnownRobots(tmp_path / "k.toml")
    known.add("ghost", Identity.generate("ghost").public_key)
    async with User(peer, known=known) as user:
        with pytest.raises(CallTimeout, match=r"robot ghost did not answer .*is it online"):
            await user.call("ghost", timeout=1.0)


async def test_hangup_reaches_the_robot_with_reason(peer: Peer) -> None:
    async with User(peer) as user:
        call = await user.call(ROBOT)
        await peer.wait_event("call")
        await call.hangup("bye for now")
        event = await peer.wait_event("ended")
        assert event["kind"] == "hung_up" and event["by_peer"] is True
        assert event["detail"] == "bye for now"
        assert call.end is not None and call.end.kind == "hung_up" and not call.end.by_peer
        with pytest.raises(CallEnded):
            call.channel("chat").send("too late")


async def test_forged_tampered_replayed_and_garbage_frames_are_dropped_and_counted(
    peer: Peer,
) -> None:
    async with User(peer) as user:
        call = await user.call(ROBOT)
        chat = call.channel("chat")
        # The call's DATA key on the robot (chat is a DATA-lane channel here).
        inbox = f"telebot/robot/{ROBOT}/call/{USER}/{call.id}/data"
        captured: list[bytes] = []

        def tap(samples: Any) -> None:
            captured.extend(
                s.payload for s in samples if isinstance(s, Sample) and s.payload[1] == 3
            )

        subscription = user.transport.subscribe(inbox, tap)
        # Until the tap's declaration has reached the router (a loaded machine takes its
        # time), echoes pass unseen: echo until one is captured.
        deadline = time.monotonic() + 10 + SLACK
        echoed = 0
        while not captured and time.monotonic() < deadline:
            echoed += 1
            assert await echo(chat, "original") == "original"
            await asyncio.sleep(0.1)
        subscription.close()
        # Heartbeats travel on the call's CONTROL key: what is captured is datagrams only.
        assert 1 <= len(captured) <= echoed
        frame = captured[-1]
        raw = user.transport.publisher(inbox, Lane.DATA)
        handshake = user.transport.publisher(f"telebot/robot/{ROBOT}/in/{USER}", Lane.CONTROL)
        header_tampered = bytearray(frame)
        header_tampered[12] ^= 0x40  # counter changed: the associated data no longer matches
        # A fresh, valid frame that has not been sent: tampered first, then the original.
        from telebot.channels.proto.frames import encode_datagram

        fresh = call._session.seal(encode_datagram(b"chat", "sealed by hand"))
        tampered = bytearray(fresh)
        tampered[-1] ^= 0x01
        other_call = bytearray(fresh)
        other_call[2] ^= 0xFF  # another call's id on this call's key

        def send_garbage() -> None:
            raw.put(frame)  # replayed
            raw.put(bytes(header_tampered))
            raw.put(bytes(tampered))  # tampered ciphertext
            raw.put(b"\x01\x03garbage!")  # truncated DATA
            raw.put(os.urandom(200))  # noise
            raw.put(b"")  # empty
            raw.put(bytes(other_call))  # another call's id
            # The same garbage on the handshake key is the endpoint's to count.
            for junk in (fresh, os.urandom(200), b""):
                handshake.put(junk)

        def all_counted(stats: dict[str, Any]) -> bool:
            rejected, endpoint = stats["rejected"], stats["endpoint_rejected"]
            return (
                rejected.get("replayed", 0) >= 1
                and rejected.get("forged", 0) >= 2
                and rejected.get("malformed", 0) >= 3
                and rejected.get("not_this_call", 0) >= 1
                and endpoint.get("data_on_handshake_key", 0) >= 1
                and sum(endpoint.values()) >= 3
            )

        # Counted as the robot gets to them (a loaded machine takes its time). Datagrams may be
        # lost on the way (zenoh drops under congestion, by design), so what is not counted
        # after a second is sent again: every copy is as bad as the first.
        deadline = time.monotonic() + 10 + SLACK
        send_garbage()
        resent_at = time.monotonic()
        stats = await robot_stats(call)
        while not all_counted(stats) and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
            if time.monotonic() - resent_at > 1.0:
                send_garbage()
                resent_at = time.monotonic()
            stats = await robot_stats(call)
        handshake.close()
        assert stats["rejected"].get("replayed", 0) >= 1
        assert stats["rejected"].get("forged", 0) >= 2
        assert stats["rejected"].get("malformed", 0) >= 3
        assert stats["rejected"].get("not_this_call", 0) >= 1
        assert stats["endpoint_rejected"].get("data_on_handshake_key", 0) >= 1
        assert sum(stats["endpoint_rejected"].values()) >= 3
        # neither the replay nor the forgeries reached the channel
        assert stats["channels"]["chat"]["received"] == echoed
        # tampering did not burn the counter: the genuine frame is still accepted
        raw.put(fresh)
        raw.close()
        assert (await asyncio.wait_for(chat.receive(), 5.0)).payload == "sealed by hand"
        # and the call is still fine
        assert await echo(chat, "still here") == "still here"


async def test_call_drops_when_robot_dies_and_can_call_again_with_nothing_left(peer: Peer) -> None:
    async with User(peer) as user:
        call = await user.call(ROBOT)
        old_channel = call.channel("chat")
        assert await echo(old_channel, "ping") == "ping"
        await peer.kill()
        end = await asyncio.wait_for(call.wait_ended(), 5.0)
        assert end.kind == "dropped"
        with pytest.raises(CallEnded):
            old_channel.send("anyone?")
        with pytest.raises(CallEnded):
            await old_channel.receive()
        assert user.calls == []


async def test_call_again_after_a_drop(peer: Peer) -> None:
    settings = CallSettings(timeout=0.5)
    async with User(peer, settings=settings) as user:
        first = await user.call(ROBOT)
        assert await echo(first.channel("chat"), "one") == "one"
        # a frozen user: stop its heartbeats by cancelling the timer, as a stuck loop would
        first._timer.cancel()  # type: ignore[union-attr]
        event = await peer.wait_event("ended", timeout=5.0 + SLACK)
        assert event["kind"] == "dropped"
        first._schedule()  # the frozen user thaws: it finds the robot silent too
        end = await asyncio.wait_for(first.wait_ended(), 5.0)
        assert end.kind == "dropped"
        second = await user.call(ROBOT)
        assert second.id != first.id
        assert second.channels == {}  # no ghost channels
        assert await echo(second.channel("chat"), "two") == "two"
        assert [c.id for c in user.calls] == [second.id]


async def test_a_burst_travels_in_one_frame_and_arrives_in_order(peer: Peer) -> None:
    async with User(peer) as user:
        call = await user.call(ROBOT)
        left, right = call.channel("left"), call.channel("right")
        assert await echo(left, "open") == "open" and await echo(right, "open") == "open"
        frames_before = call.stats.frames_sent
        for i in range(100):
            (left if i % 2 else right).send(f"#{i}")
        # The first datagram of the turn went out at once, the others wait for its end ...
        assert call.stats.frames_sent == frames_before + 1
        await asyncio.sleep(0)
        # ... and then go out as one BUNDLE (plus a heartbeat, perhaps).
        assert 2 <= call.stats.frames_sent - frames_before <= 3
        for channel, first in ((left, 1), (right, 0)):
            echoed = [(await asyncio.wait_for(channel.receive(), 5.0)).payload for _ in range(50)]
            assert echoed == [f"#{i}" for i in range(first, 100, 2)]


async def test_control_datagrams_are_not_held_back(peer: Peer) -> None:
    async with User(peer) as user:
        call = await user.call(ROBOT)
        stop = call.channel("stop", lane=Lane.CONTROL)
        frames_before = call.stats.frames_sent
        stop.send("stop")
        stop.send("stop")
        assert call.stats.frames_sent == frames_before + 2  # published at once, one frame each
        assert (await asyncio.wait_for(stop.receive(), 5.0)).payload == "stop"


async def test_datagrams_sent_before_a_hangup_go_out_before_it(peer: Peer) -> None:
    async with User(peer) as user:
        call = await user.call(ROBOT)
        chat = call.channel("chat")
        frames_before = call.stats.frames_sent
        chat.send("my")
        assert call.stats.frames_sent - frames_before == 1  # the turn's first: at once
        chat.send("last")
        chat.send("words")
        call.hangup_now("bye")
        # then one BUNDLE for the other two, sealed before the HANGUP (sent 3 times)
        assert call.stats.frames_sent - frames_before == 3
        await asyncio.sleep(0.05)
        assert call.stats.frames_sent - frames_before == 3  # nothing left to flush


# --- closing (memory only: the test needs the robot endpoint in this process) ---------


async def test_a_closing_robot_hangs_up_and_refuses_new_calls_with_a_reason(homes: Homes) -> None:
    async with memory_endpoints(homes, MemoryHub(seed=2)) as (robot, user):
        robot.on_call = lambda call: echo_call(call, robot, lambda event: None)
        first = await user.call(ROBOT)
        closing = asyncio.create_task(robot.close())
        await asyncio.sleep(0)  # close has hung up and waits before going offline
        assert not closing.done()
        end = await asyncio.wait_for(first.wait_ended(), 5)
        assert (end.kind, end.by_peer, end.detail) == ("hung_up", True, "shutting down")
        # A call made now would outlive the robot's endpoint: it is refused, with a reason.
        with pytest.raises(CallRejected, match=f"{ROBOT} is shutting down"):
            await user.call(ROBOT, timeout=5)
        await closing
        assert robot.calls == [] and robot.stats.rejected["closing"] == 1


async def test_a_cancelled_close_still_takes_the_robot_offline(homes: Homes) -> None:
    async with memory_endpoints(homes, MemoryHub(seed=2)) as (robot, user):
        robot.on_call = lambda call: echo_call(call, robot, lambda event: None)
        assert [p.name for p in await user.robots_online(wait=0.1)] == [ROBOT]
        call = await user.call(ROBOT)
        closing = asyncio.create_task(robot.close())
        await asyncio.sleep(0)
        closing.cancel()  # e.g. the task running close is cancelled during the pause
        with pytest.raises(asyncio.CancelledError):
            await closing
        end = await asyncio.wait_for(call.wait_ended(), 5)
        assert end.kind == "hung_up"
        assert await user.robots_online(wait=0.1) == []


async def test_closing_a_user_endpoint_fails_a_call_being_set_up_and_later_calls(
    homes: Homes,
) -> None:
    hub = MemoryHub(seed=2)
    async with memory_endpoints(homes, hub) as (robot, user):
        robot.on_call = lambda call: echo_call(call, robot, lambda event: None)
        hub.link("robot", "user").loss = 1.0  # the robot's answers never arrive
        calling = asyncio.create_task(user.call(ROBOT, timeout=30))
        await asyncio.sleep(0.1)
        await user.close()
        with pytest.raises(CallError, match="closed while calling"):
            await asyncio.wait_for(calling, 1 + SLACK)  # at once, not after the 30 s timeout
        with pytest.raises(CallError, match="closed"):
            await user.call(ROBOT)
