"""The test suite's own layout: no test module imports another test module.

Shared helpers and fixtures live in ``tests/support/`` (fixtures registered by the root
``conftest.py``); a test module that imports another one runs that module's fixtures and
module-level code where nobody looks for them, and ties the two files together. A
``conftest.py`` is not imported either: pytest finds its fixtures by name. Checked on the
source (no import is executed), imports inside functions included.
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
