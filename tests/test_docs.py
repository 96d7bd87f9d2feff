"""What README.md and docs/*.md name must exist in the code, so the docs cannot rot.

Every Python name the docs mention (``from telebot... import ...`` lines in code blocks, and
dotted ``telebot.x.y.Name`` references anywhere) is imported and looked up. A dotted name that
is not a Python object must be a name the code spells out whole as a string: a JSON schema's
title (``telebot.Telemetry`` on a Foxglove channel) or an entry-point group.
"""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "telebot"
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

#: ``from telebot.x import A, B`` / ``import telebot.x`` at the start of a line (code blocks).
_IMPORT_LINE = re.compile(
    r"^\s*(from\s+telebot(?:\.\w+)*\s+import\s+[\w\s,()]+|import\s+telebot(?:\.\w+)*)\s*$"
)
#: A dotted reference ``telebot.x.y.Name`` that is not part of a longer word (``id_telebot.pub``).
_DOTTED = re.compile(r"(?<![\w.-])telebot(?:\.[A-Za-z_]\w*)+")
#: Names that are not Python objects: entry-point groups, checked against the code's constants.
_ENTRY_POINT_GROUP = re.compile(r"entry-point group `(telebot(?:\.\w+)+)`")


def _doc_texts() -> list[tuple[str, str]]:
    return [(path.relative_to(ROOT).as_posix(), path.read_text(encoding="utf-8")) for path in DOCS]


def _import_lines() -> list[tuple[str, str]]:
    found = []
    for name, text in _doc_texts():
        for number, line in enumerate(text.splitlines(), 1):
            if _IMPORT_LINE.match(line):
                found.append((f"{name}:{number}", line.strip()))
    return found


def _entry_point_groups() -> set[str]:
    return {group for _, text in _doc_texts() for group in _ENTRY_POINT_GROUP.findall(text)}


def _dotted_references() -> list[tuple[str, str]]:
    groups = _entry_point_groups()
    found = []
    for name, text in _doc_texts():
        for number, line in enumerate(text.splitlines(), 1):
            for ref in _DOTTED.findall(line):
                if ref not in groups:
                    found.append((f"{name}:{number}", ref))
    return found


#: A string literal that is a whole dotted ``telebot.`` name (a schema title, a group name).
_NAME_LITERAL = re.compile(r"""["'](telebot(?:\.\w+)+)["']""")


def code_names() -> set[str]:
    """Every ``"telebot.X"`` string literal of the source (not names inside longer text)."""
    return {
        name
        for path in SRC.rglob("*.py")
        for name in _NAME_LITERAL.findall(path.read_text(encoding="utf-8"))
    }


def resolve(ref: str) -> object:
    """The object ``ref`` (``package.module.Name.attr``) names: the longest importable module
    prefix, then attributes. Raises ImportError / AttributeError naming what is missing."""
    parts = ref.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj: object = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError as exc:
            if exc.name is None or not ".".join(parts[:cut]).startswith(exc.name):
                raise  # the module exists but imports something missing: a real failure
            continue
        for attr in parts[cut:]:
            obj = getattr(obj, attr)
        return obj
    raise ImportError(f"no module of {ref!r} can be imported")


def test_the_docs_are_scanned() -> None:
    # Guards the scanners themselves: a regex that matches nothing would pass every test below.
    lines = [line for _, line in _import_lines()]
    refs = {ref for _, ref in _dotted_references()}
    assert "from telebot.config import AppConfig" in lines
    assert {
        "telebot.connect",
        "telebot.robot.sim.SimNavStack",
        "telebot.robot.nav.NavStack",
    } <= refs
    assert "telebot.pub" not in refs  # ``id_telebot.pub`` is a file name
    assert {"telebot.robots", "telebot.transports"} <= code_names()
    assert "telebot.robot.sim.SimNavStack" not in code_names()  # only whole string literals
    assert _entry_point_groups() == {"telebot.robots", "telebot.transports"}


@pytest.mark.parametrize(("where", "line"), _import_lines())
def test_every_import_line_of_the_docs_works(where: str, line: str) -> None:
    exec(compile(line, where, "exec"), {})  # our own documents' import statements


@pytest.mark.parametrize(("where", "ref"), _dotted_references())
def test_every_dotted_name_of_the_docs_exists(where: str, ref: str) -> None:
    try:
        resolve(ref)
        problem = ""
    except (ImportError, AttributeError) as exc:
        problem = str(exc)
    if problem:
        assert ref in code_names(), (
            f"{where}: {ref}: not importable ({problem}), nor a name the code uses"
        )


def test_every_entry_point_group_of_the_docs_is_the_codes() -> None:
    from telebot import robot
    from telebot.channels import transports

    assert _entry_point_groups() == {robot.ENTRY_POINT_GROUP, transports.ENTRY_POINT_GROUP}
