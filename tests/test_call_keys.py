"""A call's own keys: what a robot does with a live call's id in a new HELLO, and how a
call being set up ends up when its first frames hang it up."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import os
import time

import pytest

from conftest import ROBOT, SLACK, USER, Homes, memory_endpoints, wait_until
from rig import GENEROUS_TIMEOUT
from telebot.channels import call as call_module
from telebot.channels.call import CONTROL_LIMITS, RobotEndpoint, UserEndpoint
from telebot.channels.proto.frames import (
    LEGACY_VERSION,
    DataFrame,
    Hello,
    Welcome,
    encode_datagram,
)
from telebot.channels.proto.noise import InitiatorHandshake
from telebot.channels.proto.session import finish_call, start_call
from telebot.channels.transports import Lane
from telebot.channels.transports.base import Publisher
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.channels.transports.zenoh import ZenohTransport
from telebot.config import CallSettings, ZenohSettings
from telebot.errors import CallTimeout
from telebot.identity import encode_key
from telebot.testing.net import free_port


async def test_a_live_call_id_in_a_new_hello_makes_no_second_call(homes: Homes) -> None:
    """Once a call's answer has left the robot's cache, a fresh HELLO (a new timestamp,
    so not a replay) that reuses the live call's id is refused, not a second call on the
    same keys."""
    async with memory_endpoints(homes, MemoryHub(seed=1)) as (robot, user):
        call = await user.call(ROBOT)
        await wait_until(lambda: len(robot.calls) == 1)
        robot._answering._answered.clear()  # as after 256 other HELLOs
        hello, _ = start_call(
            homes.user.private_key,
            homes.robot.public_key,
            caller=homes.user.name,
            instance=user.instance,
            call_id=bytes.fromhex(call.id),
            wall_time_ns=time.time_ns(),
        )
        publisher = user.transport.publisher(f"telebot/robot/{ROBOT}/in/{USER}", Lane.CONTROL)
        publisher.put(hello.encode())
        publisher.close()
        await wait_until(lambda: robot.stats.rejected["call_id_reused"] == 1)
        assert [c.id for c in robot.calls] == [call.id]
        assert call.active


async def test_a_repeated_hello_of_a_call_the_robot_hung_up_gets_silence(homes: Homes) -> None:
    """The robot tells its answering policy when a call ends: a late copy of that call's
    HELLO is then not answered with the cached WELCOME (which would hand the caller a call
    that no longer exists on the robot), it is dropped and counted."""
    async with memory_endpoints(homes, MemoryHub(seed=1)) as (robot, user):
        instance = os.urandom(8)
        answers: list[bytes] = []
        user.transport.subscribe(
            f"telebot/user/{USER}/{instance.hex()}/in/{ROBOT}",
            lambda batch: answers.extend(s.payload for s in batch),
        )
        hello, _ = start_call(
            homes.user.private_key,
            homes.robot.public_key,
            caller=homes.user.name,
            instance=instance,
            call_id=os.urandom(8),
            wall_time_ns=time.time_ns(),
        )
        publisher = user.transport.publisher(f"telebot/robot/{ROBOT}/in/{USER}", Lane.CONTROL)
        publisher.put(hello.encode())
        await wait_until(lambda: len(answers) == 1 and len(robot.calls) == 1)
        publisher.put(hello.encode())  # the caller did not get it: the same answer again
        await wait_until(lambda: len(answers) == 2)
        assert answers[0] == answers[1]
        robot.calls[0].hangup_now("test")
        publisher.put(hello.encode())
        await wait_until(lambda: robot.stats.rejected["hello_for_ended_call"] == 1)
        publisher.close()
        assert len(answers) == 2 and robot.calls == []


async def test_a_call_hung_up_by_its_first_frames_is_not_kept(homes: Homes) -> None:
    """The robot answers and hangs up at once ("robot busy"): the HANGUP may be read
    before the WELCOME is handled. The user's call then ends and is not left among the
    endpoint's calls."""
    async with memory_endpoints(homes, MemoryHub(seed=1)) as (robot, user):
        robot.on_call = lambda call: call.hangup_now("robot busy")
        call = await user.call(ROBOT)
        await wait_until(lambda: call.end is not None)
        assert call.end is not None and call.end.kind == "hung_up"
        assert "robot busy" in call.end.detail
        assert user.calls == []


def _old_hello(homes: Homes, instance: bytes) -> tuple[Hello, InitiatorHandshake]:
    """A HELLO as a client of protocol version 1 writes it (version byte 1)."""
    unsigned = Hello(os.urandom(8), homes.user.name, instance, b"", 1, (1,), LEGACY_VERSION)
    handshake = InitiatorHandshake(
        homes.user.private_key, homes.robot.public_key, unsigned.prologue
    )
    payload = json.dumps({"user": homes.user.name, "ts": time.time_ns()}).encode()
    message = handshake.write_message(payload)
    return Hello(unsigned.call_id, homes.user.name, instance, message, 1, (1,), 1), handshake


async def test_a_client_of_protocol_version_1_is_refused_with_the_reason(
    homes: Homes, caplog: pytest.LogCaptureFixture
) -> None:
    """An older client's HELLO on the old key gets an authenticated version-1 refusal on
    its old inbox (it shows the reason instead of timing out), and the robot logs it once."""
    async with memory_endpoints(homes, MemoryHub(seed=1)) as (robot, user):
        instance = os.urandom(8)
        old_inbox = f"telebot/user/{homes.user.name}/{instance.hex()}/in"
        answers: list[bytes] = []
        user.transport.subscribe(old_inbox, lambda b: answers.extend(s.payload for s in b))
        hello, handshake = _old_hello(homes, instance)
        publisher = user.transport.publisher(f"telebot/robot/{ROBOT}/in", Lane.CONTROL)
        with caplog.at_level(logging.WARNING, logger="telebot.channels.call"):
            for _ in range(3):  # an old client repeats its HELLO
                publisher.put(hello.encode())
            await wait_until(lambda: len(answers) == 3)
        assert answers[0] == answers[1] == answers[2]  # the cached answer, repeated
        assert answers[0][:2] == bytes([LEGACY_VERSION, 2])  # a WELCOME it can read
        answer, _ = finish_call(handshake, Welcome(hello.call_id, answers[0][10:]))
        assert not answer.accepted
        assert answer.reason == (
            f"{ROBOT} speaks telebot protocol version 2, this client version 1: upgrade telebot"
        )
        warnings = [
            r.getMessage() for r in caplog.records if "protocol version 1" in r.getMessage()
        ]
        assert len(warnings) == 1, warnings
        assert robot.stats.rejected["old_protocol_version"] == 1 and not robot.calls


async def test_a_hello_under_another_users_name_in_the_key_is_not_read(homes: Homes) -> None:
    """The key names the sender: a HELLO whose caller is not the key's last chunk (or on
    the version-1 key) is dropped before any cryptography; the real one gets its call."""
    async with memory_endpoints(homes, MemoryHub(seed=1)) as (robot, user):
        hello, _ = start_call(
            homes.user.private_key,
            homes.robot.public_key,
            caller=homes.user.name,
            instance=user.instance,
            call_id=os.urandom(8),
            wall_time_ns=time.time_ns(),
        )
        for key in (f"telebot/robot/{ROBOT}/in/mallory", f"telebot/robot/{ROBOT}/in"):
            publisher = user.transport.publisher(key, Lane.CONTROL)
            publisher.put(hello.encode())
            publisher.close()
        await wait_until(lambda: robot.stats.rejected["sender_mismatch"] == 2)
        assert not robot.calls
        call = await user.call(ROBOT)
        assert call.active


def _publish_while_the_loop_is_busy(
    publisher: Publisher, genuine: bytes, call_id: bytes, forged: int
) -> None:
    """Blocks the event loop (a plain function called from a coroutine) while ``genuine``
    and then ``forged`` forged frames of ``call_id`` are published and received."""
    publisher.put(genuine)
    for n in range(forged):
        publisher.put(DataFrame.make_header(call_id, 10_000 + n) + os.urandom(41))
        if n % 10 == 0:
            time.sleep(0.002)  # let the reader thread keep up with zenoh's own channel
    time.sleep(0.5 * SLACK)  # the reader has queued (or refused) all of it


@pytest.mark.zenoh
async def test_forged_frames_never_push_a_genuine_control_frame_out_of_the_queue(
    homes: Homes, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Over real zenoh: a genuine CONTROL frame, then more forged frames (the call's
    header, fresh counters, random tags) than the CONTROL queue holds, arrive while the
    event loop is busy. The forged ones fail the AEAD on the transport's thread and are
    never queued, so the genuine frame, the oldest, is still delivered (without that, the
    queue's bound would drop it to make room for forgeries). The queue is made small
    (32 frames) so that a few hundred forgeries overflow it: zenoh's own channel keeps
    that many even on a loaded machine, where thousands may be lost before the gate."""
    monkeypatch.setattr(
        call_module, "CONTROL_LIMITS", dataclasses.replace(CONTROL_LIMITS, max_samples=32)
    )
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    robot_settings = ZenohSettings(listen=[endpoint], multicast_scouting=False)
    user_settings = ZenohSettings(connect=[endpoint], multicast_scouting=False)
    settings = CallSettings(timeout=GENEROUS_TIMEOUT)
    async with (
        ZenohTransport(robot_settings) as robot_transport,
        ZenohTransport(user_settings) as user_transport,
        RobotEndpoint(robot_transport, homes.robot, homes.contacts, settings=settings) as robot,
        UserEndpoint(user_transport, homes.user, homes.known, settings=settings) as user,
    ):
        got: list[str] = []
        robot.on_call = lambda c: c.channel("chat", lane=Lane.CONTROL)
        call = await user.call(ROBOT)
        chat = call.channel("chat", lane=Lane.CONTROL)
        chat.set_callback(lambda d: got.append(str(d.payload)))
        await wait_until(lambda: len(robot.calls) == 1)
        robot_call = robot.calls[0]
        key = f"{user.base}/call/{ROBOT}/{call.id}/ctl"
        publisher = robot_transport.publisher(key, Lane.CONTROL)
        genuine = robot_call._session.seal(encode_datagram(b"chat", "genuine"))
        header = bytes.fromhex(call.id)
        forged_count = 32 + 150
        _publish_while_the_loop_is_busy(publisher, genuine, header, forged_count)
        await wait_until(lambda: "genuine" in got, timeout=10 + SLACK)
        # More forgeries than the queue holds came and were refused (a loaded machine's
        # zenoh may lose a few of its own; the bound is what would have evicted the genuine).
        await wait_until(lambda: call.stats.rejected["forged"] > 32, timeout=10 + SLACK)
        assert call.active and call.receive_dropped == 0


async def test_calling_a_robot_of_protocol_version_1_times_out_naming_the_version(
    homes: Homes,
) -> None:
    """A version-1 robot (online, listening on the old handshake key only) never sees a
    version-2 HELLO: the call times out, and says to check the robot's protocol version."""
    hub = MemoryHub(seed=1)
    async with (
        MemoryTransport(hub, "old-robot") as old_robot,
        MemoryTransport(hub, "user") as user_transport,
        UserEndpoint(user_transport, homes.user, homes.known) as user,
    ):
        heard: list[bytes] = []
        old_robot.subscribe(
            f"telebot/robot/{ROBOT}/in", lambda b: heard.extend(s.payload for s in b)
        )
        old_robot.declare_presence(
            f"telebot/presence/robot/{ROBOT}/{encode_key(homes.robot.public_key)}"
        )
        with pytest.raises(CallTimeout, match="does it run telebot protocol version 2"):
            await user.call(ROBOT, timeout=1.0)
        assert heard == []  # the HELLO went to .../in/alice, where version 1 never listens


async def test_the_next_call_is_listened_for_ahead_and_made_on_those_keys(homes: Homes) -> None:
    """Once a call is up, the client already subscribes to its next call's keys (a new
    call id); the next call to that robot is made on them, and closing ends them."""
    async with memory_endpoints(homes, MemoryHub(seed=1)) as (robot, user):
        transport = user.transport
        assert isinstance(transport, MemoryTransport)

        def call_ids() -> set[str]:
            return {
                sub.pattern.split("/")[-2]
                for sub in transport._subs
                if f"/call/{ROBOT}/" in sub.pattern
            }

        first = await user.call(ROBOT)
        ids = call_ids()
        assert first.id in ids and len(ids) == 2, ids
        (ahead,) = ids - {first.id}
        await first.hangup()
        await wait_until(lambda: not robot.calls)
        second = await user.call(ROBOT)
        assert second.id == ahead
        assert len(call_ids() - {ahead}) == 1  # the one after that, listened for already
        await user.close()
        assert call_ids() == set()


async def test_a_robot_that_comes_online_while_a_user_calls_gets_the_hello_at_once(
    homes: Homes, monkeypatch: pytest.MonkeyPatch
) -> None:
    """After its first HELLO a caller says HELLO again as soon as a presence token of the
    robot appears (the robot started, or the link to it is back after an outage), not only
    at its next repeat: with the repeats made a minute apart, a robot that starts while the
    user calls answers within the call's 10 s."""
    hub = MemoryHub(seed=1)
    settings = CallSettings(timeout=GENEROUS_TIMEOUT)
    hellos = 0

    def count(batch: list[object]) -> None:
        nonlocal hellos
        hellos += len(batch)

    async with (
        MemoryTransport(hub, "spy") as spy,
        MemoryTransport(hub, "user") as user_transport,
        UserEndpoint(user_transport, homes.user, homes.known, settings=settings) as user,
    ):
        spy.subscribe(f"telebot/robot/{ROBOT}/in/{USER}", count)
        calling = asyncio.create_task(user.call(ROBOT, timeout=10.0))
        await wait_until(lambda: hellos >= 2)  # repeated every 0.25 s: nobody answers
        monkeypatch.setattr(call_module, "HELLO_RETRY_INTERVAL", 60.0)
        await wait_until(lambda: hellos >= 3)  # the next repeat would be a minute away
        async with (
            MemoryTransport(hub, "robot") as robot_transport,
            RobotEndpoint(robot_transport, homes.robot, homes.contacts, settings=settings) as robot,
        ):
            call = await calling
            assert call.active
            assert [c.id for c in robot.calls] == [call.id]
            assert hellos == 4  # the one its presence token brought
            await call.hangup()
