"""Cipher suites: CPU detection, each end's preference, the robot's pick, and calls that
negotiate them (both suites, RETRY, no suite in common, forged RETRYs, old peers)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Sequence

import pytest

from conftest import ROBOT, USER, Homes, wait_until
from telebot.channels import suites
from telebot.channels.call import Call, RobotEndpoint, UserEndpoint
from telebot.channels.proto.frames import Hello, Retry, decode_frame
from telebot.channels.proto.noise import Suite
from telebot.channels.proto.session import choose_suite, read_hello
from telebot.channels.transports import Lane, Sample
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.config import CallSettings, CipherChoice
from telebot.errors import CallError, CallRejected

A, C = Suite.AESGCM, Suite.CHACHAPOLY

X86_CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
flags\t\t: fpu vme sse2 ssse3 pclmulqdq aes xsave avx
bugs\t\t: sysret_ss_attrs
"""
X86_NO_AES = X86_CPUINFO.replace(" aes ", " ")
ARM64_CPUINFO = """processor\t: 0
BogoMIPS\t: 108.00
Features\t: fp asimd evtstrm aes pmull sha1 sha2 crc32 cpuid
CPU implementer\t: 0x41
"""
# A Raspberry Pi 4 (Cortex-A72 without the crypto extension).
PI4_CPUINFO = ARM64_CPUINFO.replace("aes pmull sha1 sha2 ", "")


# --------------------------------------------------------------------------- detection


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (X86_CPUINFO, True),
        (X86_NO_AES, False),
        (ARM64_CPUINFO, True),
        (PI4_CPUINFO, False),
        ("", False),
        ("model name\t: Fake aes CPU\n", False),  # "aes" outside the flags does not count
        ("flags\t: vaes avx\n", False),  # only the word itself
    ],
)
def test_cpu_has_aes_reads_the_flags(text: str, expected: bool) -> None:
    assert suites.cpu_has_aes(text) is expected


def test_has_aes_instructions_is_deterministic() -> None:
    assert suites.has_aes_instructions() is suites.has_aes_instructions()


@pytest.mark.parametrize(
    ("cipher", "aes", "expected"),
    [
        ("auto", True, (A, C)),
        ("auto", False, (C, A)),
        ("aesgcm", False, (A,)),
        ("aesgcm", True, (A,)),
        ("chachapoly", True, (C,)),
    ],
)
def test_suite_preference(cipher: CipherChoice, aes: bool, expected: tuple[Suite, ...]) -> None:
    assert suites.suite_preference(cipher, aes=aes) == expected


def test_unknown_cipher_setting_is_a_clear_config_error() -> None:
    with pytest.raises(ValueError, match="cipher"):
        CallSettings(cipher="rot13")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unknown cipher 'rot13'"):
        suites.suite_preference("rot13")  # type: ignore[arg-type]


# --------------------------------------------------------------------------- the pick


@pytest.mark.parametrize(
    ("offers", "allowed", "expected"),
    [
        # Both ends auto: AESGCM only when both have AES instructions.
        ((A, C), (A, C), A),
        ((A, C), (C, A), C),
        ((C, A), (A, C), C),
        ((C, A), (C, A), C),
        # One end forced.
        ((A,), (C, A), A),
        ((A,), (A, C), A),
        ((C,), (A, C), C),
        ((A, C), (C,), C),
        ((C, A), (A,), A),
        # Nothing in common.
        ((A,), (C,), None),
        ((C,), (A,), None),
        # Suites this end does not know are skipped.
        ((77, A, C), (A, C), C),
        ((77, A), (C, A), A),
        ((77,), (A, C), None),
        ((), (A, C), None),
    ],
)
def test_choose_suite(
    offers: Sequence[int], allowed: Sequence[Suite], expected: Suite | None
) -> None:
    assert choose_suite(offers, allowed) == expected


# --------------------------------------------------------------------------- calls


def settings(cipher: CipherChoice) -> CallSettings:
    return CallSettings(cipher=cipher)


@contextlib.asynccontextmanager
async def endpoints(
    homes: Homes, hub: MemoryHub, robot_cipher: CipherChoice, user_cipher: CipherChoice
) -> AsyncIterator[tuple[RobotEndpoint, UserEndpoint]]:
    async with (
        MemoryTransport(hub, "robot") as robot_transport,
        MemoryTransport(hub, "user") as user_transport,
        RobotEndpoint(
            robot_transport, homes.robot, homes.contacts, settings=settings(robot_cipher)
        ) as robot,
        UserEndpoint(
            user_transport, homes.user, homes.known, settings=settings(user_cipher)
        ) as user,
    ):
        yield robot, user


async def echo_once(user_call: Call, robot: RobotEndpoint) -> None:
    """A datagram each way: the call's keys and AEAD work on both ends."""
    robot_call = await anext(robot.incoming())
    user_call.channel("x").send(b"ping")
    got = await asyncio.wait_for(robot_call.channel("x").receive(), 5)
    assert got.payload == b"ping"
    robot_call.channel("x").send("pong")
    assert (await asyncio.wait_for(user_call.channel("x").receive(), 5)).payload == "pong"
    assert robot_call.suite is user_call.suite


@pytest.mark.parametrize(
    ("robot_cipher", "user_cipher", "user_aes", "expected", "retries"),
    [
        ("aesgcm", "aesgcm", False, A, 0),
        ("chachapoly", "chachapoly", True, C, 0),
        ("auto", "aesgcm", False, A, 0),
        ("auto", "chachapoly", True, C, 0),
        # The user prefers AESGCM, the robot takes only ChaChaPoly: one RETRY.
        ("chachapoly", "auto", True, C, 1),
        # The user lacks AES instructions, the robot accepts only AESGCM: one RETRY.
        ("aesgcm", "auto", False, A, 1),
    ],
)
async def test_calls_agree_on_a_suite(
    homes: Homes,
    monkeypatch: pytest.MonkeyPatch,
    robot_cipher: CipherChoice,
    user_cipher: CipherChoice,
    user_aes: bool,
    expected: Suite,
    retries: int,
) -> None:
    monkeypatch.setattr(suites, "has_aes_instructions", lambda: user_aes)
    async with endpoints(homes, MemoryHub(), robot_cipher, user_cipher) as (robot, user):
        call = await user.call(ROBOT, timeout=10)
        assert call.suite is expected
        assert robot.stats.rejected["cipher_retry"] >= retries
        if not retries:
            assert robot.stats.rejected["cipher_retry"] == 0
        await echo_once(call, robot)
        await call.hangup()


@pytest.mark.parametrize(("robot_aes", "user_aes"), [(True, True), (True, False), (False, True)])
async def test_auto_on_both_ends_is_aesgcm_only_when_both_have_aes(
    homes: Homes, robot_aes: bool, user_aes: bool
) -> None:
    async with endpoints(homes, MemoryHub(), "auto", "auto") as (robot, user):
        robot.suites = suites.suite_preference("auto", aes=robot_aes)
        user.suites = suites.suite_preference("auto", aes=user_aes)
        call = await user.call(ROBOT, timeout=10)
        assert call.suite is (A if robot_aes and user_aes else C)
        await echo_once(call, robot)


@pytest.mark.parametrize(
    ("robot_cipher", "user_cipher"), [("aesgcm", "chachapoly"), ("chachapoly", "aesgcm")]
)
async def test_no_common_suite_is_refused_with_a_reason(
    homes: Homes, robot_cipher: CipherChoice, user_cipher: CipherChoice
) -> None:
    async with endpoints(homes, MemoryHub(), robot_cipher, user_cipher) as (robot, user):
        with pytest.raises(
            CallRejected,
            match=f"no common cipher suite: {USER} offers {user_cipher}, "
            f"{ROBOT} accepts {robot_cipher}",
        ):
            await user.call(ROBOT, timeout=10)
        assert robot.stats.rejected["no_common_cipher"] >= 1
        assert not robot.calls


class FakeRobot:
    """Sits on the robot's inbox and answers each HELLO with the next scripted RETRY."""

    def __init__(self, transport: MemoryTransport, answers: list[Suite]) -> None:
        self.hellos: list[Hello] = []
        self._answers = answers
        self._transport = transport
        transport.subscribe(f"telebot/robot/{ROBOT}/in/*", self._on_samples)

    def _on_samples(self, samples: Sequence[Sample]) -> None:
        for sample in samples:
            hello = decode_frame(sample.payload)
            assert isinstance(hello, Hello)
            if self.hellos and hello == self.hellos[-1]:
                continue  # a repeat
            self.hellos.append(hello)
            if self._answers:
                retry = Retry(hello.call_id, self._answers.pop(0)).encode()
                inbox = f"telebot/user/{hello.caller}/{hello.instance.hex()}/in/{ROBOT}"
                self._transport.publisher(inbox, Lane.CONTROL).put(retry)


async def test_a_retry_rewrites_the_hello_with_the_suite_and_the_same_offers(
    homes: Homes,
) -> None:
    hub = MemoryHub()
    async with (
        MemoryTransport(hub, "robot") as robot_transport,
        MemoryTransport(hub, "user") as user_transport,
        UserEndpoint(user_transport, homes.user, homes.known) as user,
    ):
        user.suites = (A, C)
        fake = FakeRobot(robot_transport, [C])
        calling = asyncio.ensure_future(user.call(ROBOT, timeout=10))
        await wait_until(lambda: len(fake.hellos) >= 2)
        first, second = fake.hellos[:2]
        assert (first.suite, first.offers) == (A, (A, C))
        assert (second.suite, second.offers) == (C, (A, C))
        assert second.call_id == first.call_id
        # The new HELLO is a genuine one, written with ChaChaPoly for the robot's key.
        offer, handshake = read_hello(homes.robot.private_key, second)
        assert offer.caller_public_key == homes.user.public_key
        assert handshake.suite is C
        calling.cancel()
        with pytest.raises(asyncio.CancelledError):
            await calling


async def test_a_second_retry_for_another_suite_fails_the_call_clearly(homes: Homes) -> None:
    """A robot's pick never changes: of RETRY(chachapoly) then RETRY(aesgcm), one is forged."""
    hub = MemoryHub()
    async with (
        MemoryTransport(hub, "robot") as robot_transport,
        MemoryTransport(hub, "user") as user_transport,
        UserEndpoint(user_transport, homes.user, homes.known) as user,
    ):
        user.suites = (A, C)
        FakeRobot(robot_transport, [C, A])
        with pytest.raises(CallError, match="negotiation with guiabot failed"):
            await user.call(ROBOT, timeout=10)


async def test_a_retry_for_a_suite_not_offered_is_ignored(homes: Homes) -> None:
    hub = MemoryHub()
    async with (
        MemoryTransport(hub, "robot") as robot_transport,
        MemoryTransport(hub, "user") as user_transport,
        UserEndpoint(user_transport, homes.user, homes.known) as user,
    ):
        user.suites = (C,)
        fake = FakeRobot(robot_transport, [A])
        calling = asyncio.ensure_future(user.call(ROBOT, timeout=10))
        await wait_until(lambda: user.stats.rejected["unexpected_retry"] >= 1)
        assert all(hello.suite == C for hello in fake.hellos)
        calling.cancel()
        with pytest.raises(asyncio.CancelledError):
            await calling


async def test_a_hello_from_an_older_telebot_is_dropped_with_a_warning(
    homes: Homes, caplog: pytest.LogCaptureFixture
) -> None:
    hub = MemoryHub()
    async with (
        MemoryTransport(hub, "robot") as robot_transport,
        MemoryTransport(hub, "old") as old_transport,
        RobotEndpoint(robot_transport, homes.robot, homes.contacts) as robot,
    ):
        # Protocol 1 before suites: type 1, no suite fields (a valid one would follow).
        old = b"\x01\x01" + bytes(8) + b"\x05alice" + bytes(8) + bytes(96)
        publisher = old_transport.publisher(f"telebot/robot/{ROBOT}/in", Lane.CONTROL)
        with caplog.at_level(logging.WARNING, logger="telebot.channels.call"):
            for _ in range(3):
                publisher.put(old)
            await wait_until(lambda: robot.stats.rejected["IncompatiblePeer"] == 3)
        warnings = [r for r in caplog.records if "older telebot" in r.getMessage()]
        assert len(warnings) == 1  # once, not once per repeat
        assert not robot.calls
