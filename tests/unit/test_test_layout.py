"""The test suite's own layout: no test module imports another test module, and a
shared fixture has one definition.

Shared helpers and fixtures live in ``tests/support/`` (fixtures registered by the root
``conftest.py``) and in a folder's ``conftest.py``; a test module that imports another one
runs that module's fixtures and module-level code where nobody looks for them, and ties the
two files together. A ``conftest.py`` is not imported either: pytest finds its fixtures by
name. A shared fixture redefined elsewhere silently shadows it there (one name, two
meanings). Checked on the source (no import is executed), imports inside functions included.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator, Mapping
from pathlib import Path

import pytest

from tests.support.paths import TESTS


def _is_test_module(dotted: str) -> bool:
    """``tests.a.test_b`` / ``test_b`` / ``.conftest``: a test module or a conftest."""
    last = dotted.rsplit(".", 1)[-1]
    return last.startswith("test_") or last == "conftest"


def imported_test_modules(source: str) -> Iterator[str]:
    """Every test module (or conftest) that ``source`` imports, as written."""
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if _is_test_module(alias.name):
                    yield alias.name
        elif isinstance(node, ast.ImportFrom):
            module = "." * node.level + (node.module or "")
            if node.module and _is_test_module(node.module):
                yield module
            elif not node.module or module.rstrip(".") in ("", "tests"):
                # ``from . import test_x`` / ``from tests import test_x``
                for alias in node.names:
                    if _is_test_module(alias.name):
                        yield f"{module}.{alias.name}".replace("..", ".")


def violations(sources: Mapping[str, str]) -> list[str]:
    """``file: imports module`` for every test-module import in ``sources`` (path -> text)."""
    return [
        f"{path}: imports {module}"
        for path, source in sorted(sources.items())
        for module in imported_test_modules(source)
    ]


def _is_fixture(node: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    return any(
        ast.unparse(d).startswith(("pytest.fixture", "fixture")) for d in node.decorator_list
    )


def _is_shared(path: str) -> bool:
    return path.startswith("support/") or Path(path).name == "conftest.py"


def shadowed_fixtures(sources: Mapping[str, str]) -> set[tuple[str, str]]:
    """(fixture, file) for every definition of a shared fixture name (one defined in a
    conftest or a support module) besides its first shared one."""
    defined: dict[str, list[str]] = {}
    for path, source in sorted(sources.items(), key=lambda item: not _is_shared(item[0])):
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and _is_fixture(node):
                defined.setdefault(node.name, []).append(path)
    return {
        (name, path)
        for name, paths in defined.items()
        if _is_shared(paths[0])
        for path in paths[1:]
    }


# Shadowing left on purpose, with the reason; an entry that no longer holds fails too.
KNOWN_SHADOWS = {
    # An echo peer on a bare pty, not the SLAP2 link of conftest's ``line``; the module's
    # echo/transact cases move to the SLAP2 exchange's tests.
    ("line", "unit/transports/test_serial_channel.py"),
}


def _sources() -> dict[str, str]:
    return {
        str(path.relative_to(TESTS)): path.read_text(encoding="utf-8")
        for path in TESTS.rglob("*.py")
    }


def test_the_test_tree_was_found() -> None:
    sources = _sources()
    assert "conftest.py" in sources
    assert sum(1 for path in sources if Path(path).name.startswith("test_")) > 50
    assert any(path.startswith("support/") for path in sources)


def test_no_test_module_imports_another_test_module_or_a_conftest() -> None:
    found = violations(_sources())
    assert not found, "move what is shared into tests/support/:\n" + "\n".join(found)


def test_a_shared_fixture_is_defined_once() -> None:
    found = shadowed_fixtures(_sources())
    assert found - KNOWN_SHADOWS == set(), "rename the local fixture or use the shared one"
    assert KNOWN_SHADOWS - found == set(), "no longer shadowed: remove from KNOWN_SHADOWS"


def test_the_fixture_check_finds_an_injected_shadow() -> None:
    fixture = "import pytest\n\n@pytest.fixture\nasync def api():\n    yield 1\n"
    sources = {"integration/conftest.py": fixture, "integration/api/test_a.py": fixture}
    assert shadowed_fixtures(sources) == {("api", "integration/api/test_a.py")}
    assert shadowed_fixtures({"integration/api/test_a.py": fixture}) == set()
    other = fixture.replace("pytest.fixture", "pytest.fixture(scope='module')")
    sources = {"support/x.py": fixture, "b/test_b.py": other}
    assert shadowed_fixtures(sources) == {("api", "b/test_b.py")}


@pytest.mark.parametrize(
    ("source", "expected"),
    [
        ("from .test_api import live_server\n", [".test_api"]),
        ("from tests.test_bench import start\n", ["tests.test_bench"]),
        (
            "from tests.integration.bench.test_bench import start\n",
            ["tests.integration.bench.test_bench"],
        ),
        ("from .conftest import wait_for\n", [".conftest"]),
        ("from . import test_frf\n", [".test_frf"]),
        ("from tests import test_frf\n", ["tests.test_frf"]),
        ("import tests.unit.test_compute\n", ["tests.unit.test_compute"]),
        ("def f():\n    from ..test_twin import demo_server\n", ["..test_twin"]),
        ("from tests.support.servers import live_server\n", []),
        ("from servotune.devices.slap2 import codec\n", []),
        ("import pytest\n", []),
    ],
)
def test_the_checker_finds_an_injected_violation(source: str, expected: list[str]) -> None:
    # The checker's self-check: a rule that never fires proves nothing.
    assert list(imported_test_modules(source)) == expected
    assert bool(violations({"test_x.py": source})) == bool(expected)
