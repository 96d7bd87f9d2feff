"""docs/events.md describes every ``--events`` line the programs print.

Statically, every ``{"event": KIND, ...}`` the code emits (``emit(...)`` in any module, the
router's and the network emulator's ``ready`` lines) has a table for its program in docs/events.md with exactly its
fields. Live, a real ``telebot-robot run --events`` process is driven through every kind
(call, chat, goal, safety, say, hang-up, shutdown) and each line it prints matches its table.
"""

from __future__ import annotations

import ast
import json
import queue
import re
from collections import defaultdict
from pathlib import Path

import pytest

from rig import SLACK, Daemon
from telebot.apps import robot_cli
from test_protocol_fields import mismatches, parse_tables

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "telebot"
EVENTS_MD = ROOT / "docs" / "events.md"

RUN = "telebot-robot run --events"
ECHO = "telebot-robot echo --events"
ROUTER = "telebot-router run --events"
NETEM = "telebot-netem --events"


def documented() -> dict[str, dict[str, dict[str, str]]]:
    """docs/events.md's tables by program (its ``## `PROGRAM``` heading) and kind."""
    text = EVENTS_MD.read_text(encoding="utf-8")
    programs: dict[str, dict[str, dict[str, str]]] = {}
    for part in text.split("\n## ")[1:]:
        heading, _, body = part.partition("\n")
        programs[heading.strip("`")] = parse_tables(body)
    return programs


def _event_dicts(tree: ast.AST, *, emitted_only: bool) -> list[ast.Dict]:
    """Dict literals with an ``"event"`` key: the argument of an ``emit(...)`` call, or any."""
    found = []
    for node in ast.walk(tree):
        if emitted_only:
            if not isinstance(node, ast.Call) or not node.args:
                continue
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            if name != "emit" or not isinstance(node.args[0], ast.Dict):
                continue
            candidate = node.args[0]
        elif isinstance(node, ast.Dict):
            candidate = node
        else:
            continue
        keys = [k.value if isinstance(k, ast.Constant) else None for k in candidate.keys]
        if "event" in keys:
            found.append(candidate)
    return found


def emitted() -> dict[str, dict[str, set[str]]]:
    """What the code prints, by program and kind: the set of field names."""
    programs: dict[str, dict[str, set[str]]] = defaultdict(dict)
    for path in sorted(SRC.rglob("*.py")):
        relative = path.relative_to(SRC).as_posix()
        text = path.read_text(encoding="utf-8")
        if '"event"' not in text:  # most modules: no need to parse them
            continue
        tree = ast.parse(text)
        # The router and the network emulator print their one line without emit().
        router = relative == "apps/router_cli.py"
        netem = relative == "apps/netem_cli.py"
        program = (
            ROUTER if router else NETEM if netem else ECHO if relative == "apps/echo.py" else RUN
        )
        for node in _event_dicts(tree, emitted_only=not (router or netem)):
            keys = [k.value if isinstance(k, ast.Constant) else None for k in node.keys]
            assert None not in keys, f"{relative}:{node.lineno}: an event with computed fields"
            kind = node.values[keys.index("event")]
            assert isinstance(kind, ast.Constant), f"{relative}:{node.lineno}: a computed kind"
            fields = {str(key) for key in keys}
            known = programs[program].setdefault(str(kind.value), fields)
            assert known == fields, f"{relative}:{node.lineno}: {kind.value} with other fields"
    return programs


def test_every_event_the_code_emits_is_documented_with_its_fields() -> None:
    code = emitted()
    docs = {
        program: {kind: set(table) for kind, table in kinds.items()}
        for program, kinds in documented().items()
    }
    # The scan itself works: the kinds everyone knows are found.
    assert {"ready", "call", "ended", "stopping", "chat", "goal", "safety", "say"} <= set(code[RUN])
    assert docs == code


async def test_a_running_daemons_events_match_the_document(tmp_path: Path) -> None:
    tables = documented()[RUN]
    daemon = Daemon(tmp_path, observer=None)
    daemon.start()
    events = [daemon.ready]
    try:
        async with daemon.connect() as robot:
            assert (await robot.arm()).ok
            assert (await robot.chat("where?")).ok
            assert (await robot.goto(1.5, 1.2)).status == "succeeded"
            await robot.say("hello from the test")
            call_id = robot.call.id
        while not (events[-1]["event"] == "ended" and events[-1]["id"] == call_id):
            events.append(await daemon.events.next_event(timeout=10.0 + SLACK))
    finally:
        daemon.stop(graceful=True)
    while True:
        try:
            events.append(json.loads(daemon.events.lines.get_nowait()))
        except queue.Empty:
            break
    problems = [p for event in events for p in mismatches(event, event["event"], tables)]
    assert problems == []
    assert {event["event"] for event in events} == set(tables), events  # every kind printed
    assert {"event": "safety", "peer": "alice", "type": "arm", "ok": True} in events
    assert {"event": "chat", "peer": "alice", "text": "where?"} in events
    assert {"event": "say", "peer": "alice", "text": "hello from the test"} in events
    ended = next(event for event in events if event["event"] == "ended")
    assert (ended["id"], ended["peer"], ended["kind"]) == (call_id, "alice", "hung_up")
    assert events[-1] == {"event": "stopping", "calls": 0}


def test_run_help_names_every_kind_and_the_document(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        robot_cli.main(["run", "--help"])
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    assert "docs/events.md" in text
    kinds = re.search(r"JSON lines on stdout: ([a-z, ]+) \(", text)
    assert kinds is not None, text
    assert set(kinds.group(1).split(", ")) == set(documented()[RUN])
