"""Docstrings and comments in ``server/servotune`` state the contract, not the history.

Two rules a scan can hold, checked on the source (nothing is imported): no issue numbers
(the rule an issue asked for is written out instead; the issue is in git and docs/),
and no hand-kept import maps (``Imports:``, ``Imported by``, ``May import``): the
layer test (``tests/unit/test_layers.py``) is the import map, and a copy in prose goes
stale. Docstrings are every triple-quoted string, comments every ``#`` token.
"""

from __future__ import annotations

import io
import re
import tokenize
from pathlib import Path

import pytest

from tests.support.paths import PACKAGE

ISSUE_REF = re.compile(r"\b[Ii]ssue \d+|\bissue #\d")
IMPORT_MAP = re.compile(r"\bImports\s*:|\bImported by\b|\bMay import\b")


def prose_lines(source: str) -> list[tuple[int, str]]:
    """(line number, text) of every docstring or comment line of ``source``."""
    lines: list[tuple[int, str]] = []
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            lines.append((tok.start[0], tok.string))
        elif tok.type == tokenize.STRING and tok.string.lstrip("rbfuRBFU").startswith(
            ('"""', "'''")
        ):
            for offset, text in enumerate(tok.string.splitlines()):
                lines.append((tok.start[0] + offset, text))
    return lines


def violations(source: str) -> list[str]:
    found = []
    for number, text in prose_lines(source):
        if ISSUE_REF.search(text):
            found.append(f"{number}: issue number: {text.strip()}")
        if IMPORT_MAP.search(text):
            found.append(f"{number}: import map: {text.strip()}")
    return found


MODULES = sorted(PACKAGE.rglob("*.py"))


def test_scan_finds_modules() -> None:
    assert len(MODULES) > 100, MODULES


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_docstrings_state_the_contract(path: Path) -> None:
    found = violations(path.read_text(encoding="utf-8"))
    assert not found, f"{path.relative_to(PACKAGE.parent)}:\n" + "\n".join(found)


def test_scanner_reads_docstrings_and_comments_only() -> None:
    source = (
        '"""Module.\n\nImports: os only.\n"""\n'
        "x = 'issue 4'  # fine: a string, not a docstring\n"
        "# see issue 12\n"
        "def f() -> None:\n"
        "    '''Used here. Imported by: g.'''\n"
    )
    found = violations(source)
    assert [line.split(":")[0] for line in found] == ["3", "6", "8"], found
