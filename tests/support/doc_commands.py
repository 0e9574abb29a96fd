"""The shell commands the project prints for its users, as argument lists.

Found in README.md and docs/*.md (fenced and indented code blocks; inline code spans),
and in the comments of docker-compose.yml, the Dockerfile and lab/'s configuration files
(a comment line indented by two or more spaces after ``#`` is a command, as the files
print them). Only ``servotune``, ``docker`` and ``docker-compose`` commands are kept;
environment assignments, ``sudo``, a trailing ``&`` and comments are dropped, and lines
ending in a backslash are joined. The commands of one code block (or one paragraph of a
comment) form one recipe: tests/support/recipe_check.py runs them in order.
"""

from __future__ import annotations

import re
import shlex
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from tests.support.paths import REPO as ROOT

COMMANDS = frozenset({"servotune", "docker", "docker-compose"})
# Block-drawing characters: a code block with them is a diagram, not commands.
_DIAGRAM = re.compile(r"[─│┌┐└┘├┤┬┴┼]")
_ASSIGNMENT = re.compile(r"[A-Za-z_][A-Za-z0-9_]*=.*")
# The program word of a line, past environment assignments and sudo: decided before the
# line is split as shell words (prose in comments has unbalanced apostrophes).
_PROGRAM = re.compile(
    r"""\s*(?:[A-Za-z_][A-Za-z0-9_]*=(?:"[^"]*"|'[^']*'|\S*)\s+)*(?:sudo\s+)?(\S+)"""
)
# Inline spans in usage notation ([optional], a|b, <placeholder>, {choices}) are
# synopses, not recipes.
_SYNOPSIS = re.compile(r"[\[\]|<>{}]")


@dataclass
class Printed:
    """One printed command: ``argv[0]`` is servotune, docker or docker-compose."""

    where: str  # "README.md:187"
    argv: list[str]
    env: dict[str, str] = field(default_factory=dict)
    inline: bool = False  # an inline code span in prose (may omit required arguments)


@dataclass
class Recipe:
    """The commands of one code block or comment paragraph, in order."""

    where: str
    commands: list[Printed]


def split_command(text: str, where: str, *, inline: bool = False) -> Printed | None:
    """``text`` as a Printed command, or None when it is not one of ours."""
    first = _PROGRAM.match(text)
    if first is None:
        return None
    word = first.group(1).rsplit("/", 1)[-1]
    if word not in COMMANDS and not word.startswith("python"):
        return None
    try:
        words = shlex.split(text, comments=True)
    except ValueError as exc:  # unbalanced quotes: a broken recipe
        raise ValueError(f"{where}: cannot split {text!r}: {exc}") from None
    env: dict[str, str] = {}
    while words and _ASSIGNMENT.fullmatch(words[0]):
        key, value = words.pop(0).split("=", 1)
        env[key] = value
    if words[:1] == ["sudo"]:
        words.pop(0)
    if words[-1:] == ["&"]:
        words.pop()
    if not words:
        return None
    program = words[0].rsplit("/", 1)[-1]
    if program.startswith("python") and words[1:3] == ["-m", "servotune"]:
        words = ["servotune", *words[3:]]
        program = "servotune"
    if program not in COMMANDS:
        return None
    return Printed(where, [program, *words[1:]], env, inline)


def _joined(lines: list[tuple[int, str]]) -> Iterator[tuple[int, str]]:
    """Lines with their backslash continuations joined, each with its first line number."""
    pending: tuple[int, str] | None = None
    for number, line in lines:
        if pending is not None:
            number, line = pending[0], pending[1] + " " + line.strip()
            pending = None
        if line.rstrip().endswith("\\"):
            pending = (number, line.rstrip()[:-1])
            continue
        yield number, line
    if pending is not None:
        yield pending


def _recipe(path: Path, lines: list[tuple[int, str]]) -> Recipe | None:
    name = path.relative_to(ROOT).as_posix()
    if any(_DIAGRAM.search(text) for _, text in lines):
        return None
    commands = [
        printed
        for number, text in _joined(lines)
        if (printed := split_command(text.strip(), f"{name}:{number}")) is not None
    ]
    return Recipe(f"{name}:{lines[0][0]}", commands) if commands else None


def markdown(path: Path) -> tuple[list[Recipe], list[Printed]]:
    """The code blocks of a markdown file as recipes, and its inline command spans."""
    name = path.relative_to(ROOT).as_posix()
    recipes: list[Recipe] = []
    prose: list[tuple[int, str]] = []
    block: list[tuple[int, str]] = []
    fence: str | None = None  # the info string of the open fence
    previous_blank = True
    indented = False

    def close() -> None:
        nonlocal block, indented
        if block and (recipe := _recipe(path, block)) is not None:
            recipes.append(recipe)
        block, indented = [], False

    for number, line in enumerate(path.read_text().splitlines(), 1):
        stripped = line.strip()
        if fence is not None:
            if stripped.startswith("```"):
                if fence in ("", "sh", "bash", "shell", "console"):
                    close()
                block, fence = [], None
            else:
                block.append((number, line))
            continue
        if stripped.startswith("```"):
            close()
            fence, block = stripped[3:].strip(), []
            continue
        leading = len(line) - len(line.lstrip(" "))
        if stripped and leading >= 4 and (previous_blank or indented):
            indented = True
            block.append((number, line))
        elif stripped:
            close()
            prose.append((number, line))
        previous_blank = not stripped
    close()
    return recipes, list(_inline(name, prose))


def _inline(name: str, prose: list[tuple[int, str]]) -> Iterator[Printed]:
    # Spans may break across lines: search the prose as one text, then map back.
    text = "\n".join(line for _, line in prose)
    starts = [0]
    for _, line in prose:
        starts.append(starts[-1] + len(line) + 1)
    for match in re.finditer(r"(?<!`)`([^`]+)`(?!`)", text):
        span = " ".join(match.group(1).split())
        if _SYNOPSIS.search(span) or " ... " in f" {span} ":
            continue
        index = max(i for i, start in enumerate(starts) if start <= match.start())
        printed = split_command(span, f"{name}:{prose[index][0]}", inline=True)
        if printed is not None:
            yield printed


def comments(path: Path) -> list[Recipe]:
    """Commands in ``#`` comments, one recipe per paragraph (a bare ``#`` ends one)."""
    recipes: list[Recipe] = []
    paragraph: list[tuple[int, str]] = []

    def close() -> None:
        nonlocal paragraph
        commands = [(n, t) for n, t in paragraph if t.startswith("  ") or t.startswith("\t")]
        # A command's continuation lines are indented like it; prose lines are not.
        if commands and (recipe := _recipe(path, commands)) is not None:
            recipes.append(recipe)
        paragraph = []

    for number, line in enumerate(path.read_text().splitlines(), 1):
        stripped = line.strip()
        if not stripped.startswith("#"):
            close()
            continue
        body = stripped[1:]
        if not body.strip():
            close()
            continue
        paragraph.append((number, body[1:] if body.startswith(" ") else body))
    close()
    return recipes


def documentation_files() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def commented_files() -> list[Path]:
    lab = ROOT / "lab"
    return [
        ROOT / "docker-compose.yml",
        ROOT / "Dockerfile",
        *sorted(p for p in lab.rglob("*") if p.is_file() and p.suffix != ".md"),
    ]


def all_printed() -> tuple[list[Recipe], list[Printed]]:
    """Every recipe (code blocks, comment paragraphs) and every inline command span."""
    recipes: list[Recipe] = []
    inline: list[Printed] = []
    for path in documentation_files():
        found, spans = markdown(path)
        recipes += found
        inline += spans
    for path in commented_files():
        if path.is_relative_to(ROOT / "lab" / "nats" / "secrets"):
            continue  # generated, not printed (and private)
        recipes += comments(path)
    return recipes, inline
