"""The house style's one-way layers, checked on the source (no import is executed).

codecs (``protocols``) -> transports -> drivers -> hub -> api; the simulators sit
beside the drivers and speak to them only through a codec or a transport seam
(``transports.ethercat`` for the EP7047). A module may import its own layer and the
layers below; the composition roots (``cli``, ``demo``, ``bench``) may import anything
but ``api`` is imported only by ``api`` itself and ``cli``. Imports inside functions
count too: they break a cycle at run time but not the layering. Module-level imports
must not form a cycle.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "server" / "servotune"

# What each low layer may import (its own layer included). An allowlist, so a new
# module above them (a split of the hub, say) is forbidden to them by default.
ALLOWED = {
    "protocols": {"protocols"},
    "transports": {"transports", "protocols"},
    # descriptor, profiles and wire are pure data and laws, importing nothing above.
    "drivers": {"drivers", "transports", "protocols", "descriptor", "profiles", "wire"},
    "sim": {"sim", "transports", "protocols", "profiles"},
    "descriptor": {"descriptor"},
    "profiles": {"profiles"},
    "wire": {"wire", "descriptor"},
}
MAY_IMPORT_API = {"api", "cli"}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(tree: ast.AST, *, top_level_only: bool) -> set[str]:
    """The servotune modules ``tree`` imports (``from a import b`` gives ``a`` and,
    when ``a.b`` is a module, ``a.b`` too)."""
    nodes = tree.body if top_level_only and isinstance(tree, ast.Module) else ast.walk(tree)
    found: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            for alias in node.names:
                candidate = f"{node.module}.{alias.name}"
                if (PACKAGE.parent / Path(*candidate.split("."))).with_suffix(".py").exists():
                    found.add(candidate)
    return {name for name in found if name == "servotune" or name.startswith("servotune.")}


def _layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


SOURCES = {
    _module_name(path): ast.parse(path.read_text(encoding="utf-8"))
    for path in sorted(PACKAGE.rglob("*.py"))
}


def test_the_source_tree_was_found() -> None:
    # A wrong path would make every check below pass vacuously.
    assert "servotune.drivers.slap2" in SOURCES and "servotune.hub" in SOURCES
    assert len(SOURCES) > 50


@pytest.mark.parametrize("layer", sorted(ALLOWED))
def test_a_low_layer_imports_nothing_above_it(layer: str) -> None:
    wrong = sorted(
        f"{module} imports {target}"
        for module, tree in SOURCES.items()
        if _layer(module) == layer
        for target in _imports(tree, top_level_only=False)
        if _layer(target) not in ALLOWED[layer] | {""}
    )
    assert not wrong, "\n".join(wrong)


def test_only_the_api_and_the_cli_import_the_api() -> None:
    wrong = sorted(
        f"{module} imports {target}"
        for module, tree in SOURCES.items()
        if _layer(module) not in MAY_IMPORT_API
        for target in _imports(tree, top_level_only=False)
        if _layer(target) == "api"
    )
    assert not wrong, "\n".join(wrong)


def _on_or_behind_a_cycle(graph: dict[str, set[str]]) -> list[str]:
    """Modules that cannot be ordered (Kahn's algorithm): on a cycle or importing one."""
    pending = {module: len(targets) for module, targets in graph.items()}
    users: dict[str, set[str]] = {module: set() for module in graph}
    for module, targets in graph.items():
        for target in targets:
            users[target].add(module)
    ready = [module for module, count in pending.items() if count == 0]
    while ready:
        done = ready.pop()
        for user in users[done]:
            pending[user] -= 1
            if pending[user] == 0:
                ready.append(user)
    return sorted(module for module, count in pending.items() if count > 0)


def test_the_cycle_check_finds_a_cycle() -> None:
    graph = {"a": {"b"}, "b": {"a"}, "c": {"a"}, "d": set(), "e": {"d"}}
    assert _on_or_behind_a_cycle(graph) == ["a", "b", "c"]


def test_module_level_imports_form_no_cycle() -> None:
    graph = {
        module: {t for t in _imports(tree, top_level_only=True) if t in SOURCES and t != module}
        for module, tree in SOURCES.items()
    }
    stuck = _on_or_behind_a_cycle(graph)
    assert not stuck, f"import cycle among: {stuck}"
