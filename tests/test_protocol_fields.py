"""docs/protocol.md §13 and §16 say what the robot does: the channels a call gets, and the
fields of the pose, goals, telemetry and plan messages.

§13: the channel table lists exactly the channels (and lanes) the robot's services open on a
call, as ``telebot-robot run`` sets them up (every registered service, media included).

§16: the field tables are what the robot sends.

Real ``pose``, ``telemetry``, ``goals`` and ``plan`` messages, taken off a call to the
in-process robot of ``rig.robot_on_hub`` (idle, then driving a goal sent as raw JSON), and the
client library's ``goals`` requests, are checked against the tables parsed from the document:
every field a message has is in its table with a matching type, and every field the table
does not call optional is there. The two ``goal`` fields mean what §16 says they mean.
"""

from __future__ import annotations

import asyncio
import json
import re
from collections import defaultdict
from pathlib import Path
from typing import Any

from conftest import ROBOT, wait_until
from rig import FAST_SIM, GENEROUS_TIMEOUT, robot_on_hub, user_on_hub
from telebot.channels.channel import ReceivedDatagram
from telebot.channels.transports import Lane
from telebot.channels.transports.memory import MemoryHub
from telebot.reasons import Reason
from telebot.services.client import RobotClient
from telebot.services.messages import is_finite_number
from telebot.services.plan.wire import PLAN
from telebot.services.registry import robot_services
from telebot.services.status.wire import GOALS, POSE, TELEMETRY, GoalCommand

PROTOCOL = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"
_HEADER = re.compile(r"^\| `?([\w ]+?)`? field \| type \| meaning \|$")
_ROW = re.compile(r"^\| `(\w+)` \| ([^|]+?) \| .+ \|$")


def parse_tables(text: str) -> dict[str, dict[str, str]]:
    """Each field table in ``text`` (header ``| `NAME` field | type | meaning |``) by NAME:
    field → type as written (``integer or null``, ``text, optional``)."""
    tables: dict[str, dict[str, str]] = {}
    current: dict[str, str] | None = None
    for line in text.splitlines():
        if header := _HEADER.match(line):
            current = tables.setdefault(header.group(1), {})
        elif current is not None and (row := _ROW.match(line)):
            current[row.group(1)] = row.group(2)
        elif not line.startswith("|"):
            current = None
    return tables


def field_tables() -> dict[str, dict[str, str]]:
    """Each table of §16 by message name (``pose``, ``status``, ``place``, …): field → type."""
    text = PROTOCOL.read_text(encoding="utf-8")
    return parse_tables(text[text.index("## 16. Pose, goals and telemetry") : text.index("## 17.")])


TABLES = field_tables()


def _is_number(value: Any) -> bool:
    return is_finite_number(value)


def _is_integer(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _one(value: Any, kind: str) -> bool:
    """Whether ``value`` is of the document's type ``kind`` (one alternative)."""
    simple = {
        "number": _is_number,
        "integer": _is_integer,
        "text": lambda v: isinstance(v, str),
        "boolean": lambda v: isinstance(v, bool),
        "null": lambda v: v is None,
        "array of 3 numbers": lambda v: (
            isinstance(v, list) and len(v) == 3 and all(map(_is_number, v))
        ),
        "array of [number, number]": lambda v: (
            isinstance(v, list)
            and all(isinstance(p, list) and len(p) == 2 and all(map(_is_number, p)) for p in v)
        ),
        "object of text": lambda v: (
            isinstance(v, dict) and all(isinstance(x, str) for x in v.values())
        ),
        "array of text": lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v),
        "array of places": lambda v: isinstance(v, list) and all(conforms(p, "place") for p in v),
    }
    assert kind in simple, f"the docs use a type this test does not know: {kind!r}"
    return bool(simple[kind](value))


def mismatches(
    message: dict[str, Any], name: str, tables: dict[str, dict[str, str]] = TABLES
) -> list[str]:
    """What in ``message`` disagrees with the table of ``name`` (empty: it conforms)."""
    table = tables[name]
    found = []
    for key, value in message.items():
        if key not in table:
            found.append(f"{name}: field {key!r} is not in the table")
            continue
        kind = table[key].removesuffix(", optional")
        if not any(_one(value, alternative) for alternative in kind.split(" or ")):
            found.append(f"{name}: {key} = {value!r} is not {kind}")
    for key, kind in table.items():
        if not kind.endswith(", optional") and key not in message:
            found.append(f"{name}: field {key!r} is missing")
    return found


def conforms(message: dict[str, Any], name: str) -> bool:
    return not mismatches(message, name)


_CHANNEL_ROW = re.compile(r"^\| `([\w/]+)` \| ([A-Z]+(?:, latest only)?) \| ")


def documented_channels() -> dict[str, set[str]]:
    """The channel table of §13: each channel's lanes as written (``DATA, latest only``)."""
    text = PROTOCOL.read_text(encoding="utf-8")
    section = text[text.index("## 13. Robot services") : text.index("### 13.1")]
    found: dict[str, set[str]] = defaultdict(set)
    for line in section.splitlines():
        if row := _CHANNEL_ROW.match(line):
            found[row.group(1)].add(row.group(2))
    return found


async def test_section_13_lists_every_channel_a_call_gets(tmp_path: Path) -> None:
    hub = MemoryHub(seed=13)
    # The daemon's services: the default registry (media is one of them).
    services = robot_services()
    async with robot_on_hub(
        tmp_path, hub, timeout=GENEROUS_TIMEOUT, sim=FAST_SIM, robot_services=services
    ) as (
        _,
        _,
        server,
        endpoint,
    ):
        assert "media" in server.hosted.names()
        async with (
            user_on_hub(tmp_path, hub) as user,
        ):
            user_call = await user.call(ROBOT)
            await wait_until(lambda: user_call.id in server.open)
            (robot_call,) = [c for c in endpoint.calls if c.id == user_call.id]
            opened: dict[str, set[str]] = {
                name: {str(channel.lane.name) + (", latest only" if channel.latest_only else "")}
                for name, channel in robot_call.channels.items()
            }
            await user_call.hangup()
    documented = documented_channels()
    assert "people" in opened  # §23's channel, once missing from the table
    assert documented == opened


def test_the_tables_are_found() -> None:
    # Guards the parser: a table it cannot read would let every message pass.
    assert set(TABLES) == {
        "pose",
        "goal",
        "cancel",
        "query",
        "status",
        "telemetry",
        "plan",
        "places",
        "place",
    }
    assert TABLES["pose"]["goal"] == "integer or null"
    assert TABLES["telemetry"]["goal"] == "text or null"
    assert mismatches({"type": "query", "id": "7"}, "query") == ["query: id = '7' is not integer"]


def test_the_clients_goal_requests_match_the_tables() -> None:
    for command, name in [
        (GoalCommand("goal", 7, 3.0, 5.2, 0.5), "goal"),
        (GoalCommand("goal", 2**32 - 1, 3.0, 5.2), "goal"),
        (GoalCommand("cancel", 7), "cancel"),
        (GoalCommand("query", 7), "query"),
    ]:
        assert mismatches(json.loads(command.encode()), name) == []


async def test_the_robots_pose_telemetry_goals_and_plan_match_the_tables(tmp_path: Path) -> None:
    hub = MemoryHub(seed=9)
    async with (
        robot_on_hub(tmp_path, hub, timeout=GENEROUS_TIMEOUT, sim=FAST_SIM) as (nav, _, _, _),
        user_on_hub(tmp_path, hub) as user,
    ):
        call = await user.call(ROBOT)
        client = RobotClient(call)
        assert (await client.arm()).ok
        # From here on the test reads the channels itself: the messages as they travel.
        seen: dict[str, list[dict[str, Any]]] = defaultdict(list)

        def keep(name: str) -> Any:
            def on_datagram(datagram: ReceivedDatagram) -> None:
                message = json.loads(datagram.payload)
                seen[message.get("type", name) if name in (GOALS, PLAN) else name].append(message)

            return on_datagram

        for name in (POSE, TELEMETRY, GOALS):
            call.channels[name].set_callback(keep(name))
        plan = call.channels.get(PLAN) or call.channel(PLAN, lane=Lane.DATA)
        plan.set_callback(keep(PLAN))
        goals = call.channels[GOALS]
        await wait_until(lambda: bool(seen["pose"]) and bool(seen["telemetry"]))
        await wait_until(lambda: bool(seen["places"]))
        idle_pose, idle_telemetry = seen["pose"][-1], seen["telemetry"][-1]
        assert idle_pose["goal"] is None and idle_telemetry["goal"] is None

        # A goal as a client written from §16.2 sends it; a goal refused because the round
        # trip is not measured yet (``rtt_unmeasured``) stays refused, so a retry takes a new id.
        def last_status(goal_id: int) -> dict[str, Any] | None:
            mine = [m for m in seen["status"] if m["id"] == goal_id]
            return mine[-1] if mine else None

        def status_of(goal_id: int) -> str | None:
            last = last_status(goal_id)
            return last["status"] if last is not None else None

        async def start_goal() -> int:
            for goal_id in range(4242, 4342):
                goals.send(GoalCommand("goal", goal_id, 9.5, 4.0).encode())
                await wait_until(lambda goal_id=goal_id: last_status(goal_id) is not None)
                answer = last_status(goal_id)
                assert answer is not None
                if answer["status"] == "active":
                    return goal_id
                assert answer["code"] == Reason.RTT_UNMEASURED, answer
                await asyncio.sleep(0.1)
            raise AssertionError("the robot never accepted the goal")

        client_id = await start_goal()
        running = nav.current_goal()
        assert running is not None

        def driving(message: dict[str, Any]) -> bool:
            return message["goal"] is not None

        await wait_until(lambda: any(map(driving, seen["pose"])))
        await wait_until(lambda: any(map(driving, seen["telemetry"])))
        await wait_until(lambda: any(m["points"] for m in seen["plan"]))
        goals.send(GoalCommand("query", client_id).encode())
        goals.send(GoalCommand("query", 99).encode())  # unknown to the robot
        await wait_until(lambda: status_of(99) == "unknown")
        goals.send(GoalCommand("cancel", client_id).encode())
        await wait_until(lambda: status_of(client_id) == "cancelled")

        # Every message the robot sent matches its table.
        problems = [
            problem
            for name, messages in seen.items()
            for m in messages
            for problem in mismatches(m, name)
        ]
        assert problems == []
        assert {"pose", "telemetry", "status", "plan", "places"} <= set(seen)

        # The two ``goal`` fields (§16): pose's (and plan's) is the robot's number of the
        # motion, not the client's id; telemetry's is the motion in words.
        pose_goal = next(m["goal"] for m in seen["pose"] if driving(m))
        telemetry_goal = next(m["goal"] for m in seen["telemetry"] if driving(m))
        plan_goal = next(m["goal"] for m in seen["plan"] if m["points"])
        assert pose_goal == plan_goal == running.goal_id != client_id
        assert telemetry_goal == running.description == "goto (9.50, 4.00)"
