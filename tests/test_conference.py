"""Many users, one robot: the roster and the messages of the ``conference`` channel."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from conftest import wait_until
from fleet_rig import CALLS, make_homes, running_robot, user_endpoint, user_home
from telebot.channels.call import UserEndpoint
from telebot.channels.transports.memory import MemoryHub, MemoryTransport
from telebot.errors import ProtocolError
from telebot.identity import Identity, KnownRobots, Role
from telebot.reasons import Reason
from telebot.services.client import RobotClient
from telebot.services.conference.wire import (
    MAX_TEXT,
    RATE_LIMIT,
    Conference,
    Message,
    Roster,
    Say,
    Since,
    decode_conference_reply,
    decode_conference_request,
    say_text,
)

# -- sans-IO -----------------------------------------------------------------------------


def test_a_say_is_numbered_for_everyone_and_a_repeat_is_answered_without_a_second() -> None:
    room = Conference("bot")
    joined = room.join("c1", "alice", "driver")
    assert joined == Message(1, "bot", "robot", "alice joined (driver)")
    said, message = room.say("c1", Say(5, " hi all "), now=0.0)
    assert said.ok and said.code == Reason.OK
    assert message == Message(2, "alice", "user", "hi all")
    again, none = room.say("c1", Say(5, " hi all "), now=0.1)
    assert again == said and none is None and room.seq == 2
    assert room.since(0) == [joined, message] and room.since(1) == [message]


@pytest.mark.parametrize(
    ("text", "code"), [("   ", Reason.EMPTY), ("x" * (MAX_TEXT + 1), Reason.TOO_LONG)]
)
def test_a_bad_say_is_refused_with_a_code(text: str, code: Reason) -> None:
    room = Conference("bot")
    room.join("c1", "alice", "observer")
    said, message = room.say("c1", Say(1, text), now=0.0)
    assert not said.ok and said.code == code and said.text and message is None


def test_too_many_says_are_refused_until_the_window_passes() -> None:
    room = Conference("bot")
    room.join("c1", "alice", "observer")
    for i in range(RATE_LIMIT):
        assert room.say("c1", Say(i, "hi"), now=0.0)[0].ok
    said, message = room.say("c1", Say(99, "hi"), now=1.0)
    assert said.code == Reason.TOO_FAST and message is None
    assert room.say("c1", Say(100, "hi"), now=10.5)[0].ok
    # A call that is not in the room (its join was lost in a race) is told so.
    assert room.say("nope", Say(1, "hi"), now=0.0)[0].code == Reason.UNKNOWN_CALL


def test_the_roster_marks_the_reader_and_the_driver() -> None:
    room = Conference("bot")
    room.join("c1", "alice", "driver")
    room.join("c2", "bob", "observer")
    roster = room.roster("c2", driving="c1")
    assert [(m.name, m.role, m.driving, m.you) for m in roster.users] == [
        ("alice", "driver", True, False),
        ("bob", "observer", False, True),
    ]
    assert decode_conference_reply(roster.encode()) == roster
    assert room.leave("c2") == Message(3, "bot", "robot", "bob left")
    assert room.leave("c2") is None


def test_a_user_s_second_call_is_listed_but_only_the_call_holding_the_drive_drives() -> None:
    room = Conference("bot")
    room.join("c1", "alice", "driver")
    room.join("c2", "alice", "driver")  # alice's page beside her terminal
    roster = room.roster("c2", driving="c1")
    assert [(m.name, m.driving, m.you) for m in roster.users] == [
        ("alice", True, False),
        ("alice", False, True),
    ]


def test_a_call_replacing_its_client_s_old_one_reads_as_one_reconnection() -> None:
    room = Conference("bot")
    room.join("c1", "alice", "driver")
    room.join("c2", "bob", "observer")
    for i in range(RATE_LIMIT):
        assert room.say("c1", Say(i, "hi"), now=0.0)[0].ok
    back = room.join("c3", "alice", "driver", replaces="c1")
    assert back.text == "alice reconnected (driver)"
    assert room.calls == ["c2", "c3"]
    # The old call's end, when it comes, says nothing: no "alice left" after the rejoin.
    assert room.leave("c1") is None
    assert [m.text for m in room.since(0)] == [
        "alice joined (driver)",
        "bob joined (observer)",
        *["hi"] * RATE_LIMIT,
        "alice reconnected (driver)",
    ]
    # Calling again is no way round the rate limit.
    assert room.say("c3", Say(1, "again"), now=1.0)[0].code == Reason.TOO_FAST
    # A client whose call dropped (its leave heard) comes back: a reconnection too.
    assert room.join("c5", "carol", "observer", again=True).text == "carol reconnected (observer)"
    # Only the same user's call is replaced.
    assert room.join("c4", "bob", "observer", replaces="c3").text == "bob joined (observer)"
    assert room.calls == ["c2", "c3", "c5", "c4"]


def test_messages_round_trip_and_garbage_is_refused() -> None:
    for request in (Say(3, "hello"), Since(41)):
        assert decode_conference_request(request.encode()) == request
    message = Message(7, "alice", "user", "hi")
    assert decode_conference_reply(message.encode()) == message
    for bad in ('{"type":"say","id":1}', '{"type":"shout"}', "[]", b"\x00", '{"type":"since"}'):
        with pytest.raises(ProtocolError):
            decode_conference_request(bad)
    for bad in ('{"type":"roster","seq":1,"users":[1]}', '{"type":"msg","seq":1,"from":""}'):
        with pytest.raises(ProtocolError):
            decode_conference_reply(bad)
    assert say_text("say  hello there ") == "hello there"
    assert say_text("Say") == "" and say_text("sayso") is None and say_text("fwd 1") is None


# -- two users, one robot -------------------------------------------------------------------


@contextlib.asynccontextmanager
async def two_users(tmp_path: Path, hub: MemoryHub) -> AsyncIterator[tuple[RobotClient, ...]]:
    make_homes(tmp_path, ["bot1"], {"alice": Role.DRIVER, "bob": Role.OBSERVER})
    async with (
        running_robot(tmp_path, "bot1", hub),
        user_endpoint(tmp_path, "alice", hub) as alice_end,
        user_endpoint(tmp_path, "bob", hub) as bob_end,
    ):
        alice = RobotClient(await alice_end.call("bot1", timeout=10))
        alice.start()
        bob = RobotClient(await bob_end.call("bot1", timeout=10))
        bob.start()
        try:
            yield alice, bob
        finally:
            for client in (alice, bob):
                with contextlib.suppress(Exception):
                    await client.hangup()
                await client.aclose()


def _names(roster: Roster | None) -> list[tuple[str, str, bool, bool]]:
    if roster is None:
        return []
    return [(m.name, m.role, m.driving, m.you) for m in roster.users]


def _texts(client: RobotClient) -> list[tuple[str, str, str]]:
    return [(m.sender, m.kind, m.text) for m in client.conference.messages]


async def test_two_users_see_each_other_and_each_other_s_messages(tmp_path: Path) -> None:
    async with two_users(tmp_path, MemoryHub(seed=3)) as (alice, bob):
        await wait_until(lambda: len(_names(alice.conference.roster)) == 2)
        await wait_until(lambda: len(_names(bob.conference.roster)) == 2)
        # alice joined first, so she holds the drive; each sees itself marked.
        assert _names(alice.conference.roster) == [
            ("alice", "driver", True, True),
            ("bob", "observer", False, False),
        ]
        assert _names(bob.conference.roster)[1] == ("bob", "observer", False, True)
        await wait_until(lambda: ("bot1", "robot", "bob joined (observer)") in _texts(alice))

        said = await bob.say("hello from bob")
        assert said.ok and said.code == Reason.OK
        said = await alice.say("hello bob")
        assert said.ok
        for client in (alice, bob):
            await wait_until(lambda c=client: ("bob", "user", "hello from bob") in _texts(c))
            await wait_until(lambda c=client: ("alice", "user", "hello bob") in _texts(c))
        refused = await bob.say("   ")
        assert not refused.ok and refused.code == Reason.EMPTY

        # A chat command's replies still go to its sender only.
        result = await alice.chat("where")
        assert result.ok and not any("heading" in text for _, _, text in _texts(bob))

        # alice gives up the drive: everyone hears it and the roster shows nobody driving.
        assert (await alice.release_drive()).ok
        await wait_until(lambda: ("bot1", "robot", "the drive is free") in _texts(bob))
        await wait_until(lambda: not any(m[2] for m in _names(bob.conference.roster)))

        await bob.hangup()
        await wait_until(lambda: ("bot1", "robot", "bob left") in _texts(alice))
        await wait_until(lambda: [m[0] for m in _names(alice.conference.roster)] == ["alice"])


async def test_a_user_s_second_client_observes_and_only_the_call_holding_the_drive_drives(
    tmp_path: Path,
) -> None:
    hub = MemoryHub(seed=5)
    async with (
        two_users(tmp_path, hub) as (alice, bob),
        MemoryTransport(hub, "alice-page") as transport,
        UserEndpoint(
            transport,
            Identity.load(user_home(tmp_path, "alice")),
            KnownRobots.load(user_home(tmp_path, "alice")),
            settings=CALLS,
        ) as page_end,
    ):
        # alice's second client (another process: the page beside her terminal).
        page = RobotClient(await page_end.call("bot1", timeout=10))
        page.start()
        try:
            expected = [
                ("alice", "driver", True, False),
                ("bob", "observer", False, True),
                ("alice", "driver", False, False),
            ]
            await wait_until(lambda: _names(bob.conference.roster) == expected)
            await wait_until(lambda: ("bot1", "robot", "alice joined (driver)") in _texts(bob))
            # The second call observes: one driver, the first call.
            refused = await page.arm()
            assert not refused.ok and refused.code == Reason.NOT_HOLDER
            assert refused.text.startswith("your other call holds the drive")
            # alice moves the drive to her page: the roster follows, the first call observes.
            assert (await page.take_drive()).ok
            await wait_until(
                lambda: [m[2] for m in _names(bob.conference.roster)] == [False, False, True]
            )
            assert [m[2] for m in _names(page.conference.roster)] == [False, False, True]
            assert _names(page.conference.roster)[2][3]  # "you" on the page's own entry
            assert (await page.arm()).ok
            assert not (await alice.arm()).ok
        finally:
            with contextlib.suppress(Exception):
                await page.hangup()
            await page.aclose()


async def test_messages_lost_on_the_way_are_asked_for_again(tmp_path: Path) -> None:
    hub = MemoryHub(seed=11)
    async with two_users(tmp_path, hub) as (alice, bob):
        await wait_until(lambda: len(_names(bob.conference.roster)) == 2)
        hub.link("bot1", "bob").loss = 0.5  # half of what the robot sends bob is lost
        for i in range(8):
            assert (await alice.say(f"note {i}")).ok
        notes = [("alice", "user", f"note {i}") for i in range(8)]
        await wait_until(lambda: all(n in _texts(bob) for n in notes), timeout=15.0)
        # Each once, in the order the robot numbered them.
        heard = [t for t in _texts(bob) if t in notes]
        assert heard == notes
        seqs = [m.seq for m in bob.conference.messages]
        assert seqs == sorted(set(seqs))


async def test_the_chat_cli_shows_the_roster_and_the_others_messages_and_says(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from telebot.apps.user_client import _run_command, _show_conference

    async with two_users(tmp_path, MemoryHub(seed=4)) as (alice, bob):
        await wait_until(lambda: len(_names(alice.conference.roster)) == 2)
        _show_conference(alice)
        assert (await bob.say("anyone there?")).ok
        seen: list[str] = []

        def heard(text: str) -> bool:
            seen.append(capsys.readouterr().err)
            return text in "".join(seen)

        await wait_until(lambda: heard("[bob] anyone there?"))
        assert "[in the call: alice (you) (driver, driving), bob (observer)]" in "".join(seen)
        # "say" in the chat is a message to everyone, not a robot command.
        assert await _run_command(alice, "say yes, alice here", None, tmp_path)
        await wait_until(lambda: ("alice", "user", "yes, alice here") in _texts(bob))
        assert not await _run_command(alice, "say", None, tmp_path)
        out, err = capsys.readouterr()
        assert "! say refused: nothing to say" in out
        assert "[alice] yes, alice here" not in err  # what alice typed is not echoed back


def test_the_roster_line_of_the_chat() -> None:
    from telebot.apps.user_client import format_message, format_roster

    room = Conference("bot1")
    room.join("c1", "alice", "driver")
    room.join("c2", "bob", "observer")
    assert format_roster(room.roster("c1", "c1")) == (
        "alice (you) (driver, driving), bob (observer)"
    )
    room.join("c3", "alice", "driver")
    assert format_roster(room.roster("c3", "c1")) == (
        "alice (driver, driving), bob (observer), alice (you) (driver, another call)"
    )
    assert format_message(Message(3, "bot1", "robot", "bob left")) == "[bot1: bob left]"
    assert format_message(Message(4, "bob", "user", "hi")) == "[bob] hi"
