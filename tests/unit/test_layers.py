"""The one-way layers by role, checked on the source (no import is executed).

Every module has a role (``role``); ``ALLOWED`` says which roles a role may import.
Besides the roles: a device imports no other device, a device's non-``sim`` code does
not import its own simulator (only its ``entry`` does, to wire the demo and ``servotune
sim``), and only the registry (``servotune.devices``) imports device folders, and only
their ``entry``. Code outside the device folders does not name a device either (no
string that is a device's name: a ``device == "..."`` branch or a list of devices
belongs in the device's registry entry). Imports inside functions count too: they break
a cycle at run time but not the layering. Module-level imports form no cycle, and a
package's ``__init__`` imports nothing (a re-export runs the package on every import of
one of its modules), except a facade's (``FACADES``): its ``__init__`` re-exports the
names of its own modules only, so every importer names the one place, and none of its
modules imports the facade (that would be a cycle).

``KNOWN`` lists violations a later change removes (empty now); a listed violation that
no longer exists fails too, so the list only shrinks.
"""

from __future__ import annotations

import ast
from collections.abc import Mapping
from pathlib import Path

import pytest

from tests.support.paths import PACKAGE

CODEC_FILES = {"codec", "frame", "modulo"}
TOP_ROLES = {
    "": "package",
    "schema": "schema",
    "descriptor": "schema",
    "schema_ts": "tool",
    "storage": "storage",
    "private_files": "storage",
    "compute": "compute",
    "config": "config",
    "registry": "registry",
    "transports": "transport",
    "link": "link",
    "sim": "sim",
    "tuning": "tuning",
    "hub": "hub",
    "bench": "bench",
    "autotune": "autotune",
    "auth": "auth",
    "twin": "twin",
    "bus": "bus",
    "api": "api",
    "cli": "root",
    "demo": "root",
    "perf": "root",
    "__main__": "root",
}
GENERIC_BELOW_DEVICES = {
    "schema",
    "storage",
    "compute",
    "config",
    "transport",
    "link",
    "sim",
    "tuning",
    "hub",
    "bench",
    "autotune",
    "identity",
}
ALLOWED: dict[str, set[str]] = {
    "package": set(),
    "schema": {"schema"},
    "tool": {"schema", "package"},
    "storage": {"storage"},
    "compute": set(),
    "config": set(),
    "identity": set(),
    "transport": {"transport"},
    "device-codec": {"device-codec"},
    "link": {"link", "transport", "schema"},
    "sim": {"sim", "transport"},
    "device-sim": {"device-sim", "device-codec", "sim", "transport"},
    "tuning": {"tuning", "schema"},
    "hub": {"hub", "link", "schema", "storage", "identity", "package"},
    # compute: the import processes are forks of the compute workers' fork server
    "bench": {
        "bench",
        "hub",
        "link",
        "tuning",
        "schema",
        "storage",
        "compute",
        "identity",
        "package",
    },
    "autotune": {
        "autotune",
        "bench",
        "hub",
        "link",
        "tuning",
        "schema",
        "storage",
        "compute",
        "identity",
    },
    "device": {"device", "device-codec"} | GENERIC_BELOW_DEVICES | {"package"},
    "device-entry": {"device", "device-codec", "device-sim", "device-entry", "registry"}
    | GENERIC_BELOW_DEVICES,
    "registry": {"device-entry", "registry"} | GENERIC_BELOW_DEVICES,
    # compute: password hashing runs in the compute worker, off the event loop
    "auth": {"auth", "identity", "hub", "link", "schema", "storage", "compute", "package"},
    "twin": {"twin", "hub", "link", "schema"},
    "bus": {
        "bus",
        "hub",
        "bench",
        "autotune",
        "link",
        "tuning",
        "schema",
        "storage",
        "compute",
        "config",
        "identity",
        "auth",
        "package",
    },
    "api": {"api", "auth", "bus", "twin", "registry"} | GENERIC_BELOW_DEVICES | {"package"},
    "root": {"api", "auth", "bus", "twin", "registry", "root", "tool"}
    | GENERIC_BELOW_DEVICES
    | {"package"},
}

# Violations a later step removes; a listed violation that no longer exists fails too.
KNOWN: set[str] = set()

# Packages whose ``__init__`` re-exports its own modules' names: the wire schema is one
# place to import from (``from servotune.schema import X``) split into modules by seam.
# Importing any of its modules runs them all, as importing the one file did.
FACADES = {"servotune.schema"}


def role(module: str) -> str:
    parts = module.split(".")
    if parts[1:2] == ["devices"]:
        if len(parts) == 2:
            return "registry"
        if len(parts) >= 4 and parts[3] == "sim":
            return "device-sim"
        if len(parts) == 4 and parts[3] in CODEC_FILES:
            return "device-codec"
        if len(parts) == 4 and parts[3] == "entry":
            return "device-entry"
        return "device"
    if module == "servotune.auth.principal":
        return "identity"
    return TOP_ROLES[parts[1] if len(parts) > 1 else ""]


def device_of(module: str) -> str | None:
    parts = module.split(".")
    return parts[2] if parts[1:2] == ["devices"] and len(parts) > 2 else None


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(tree: ast.AST, *, top_level_only: bool) -> set[str]:
    """The servotune modules ``tree`` imports (``from a import b`` gives ``a`` and,
    when ``a.b`` is a module, ``a.b`` instead)."""
    nodes = tree.body if top_level_only and isinstance(tree, ast.Module) else ast.walk(tree)
    found: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                candidate = f"{node.module}.{alias.name}"
                base = PACKAGE.parent / Path(*candidate.split("."))
                if base.with_suffix(".py").exists() or (base / "__init__.py").exists():
                    found.add(candidate)
                else:
                    found.add(node.module)
    return {name for name in found if name == "servotune" or name.startswith("servotune.")}


SOURCES = {
    _module_name(path): ast.parse(path.read_text(encoding="utf-8"))
    for path in sorted(PACKAGE.rglob("*.py"))
}


def violations(sources: Mapping[str, ast.AST]) -> set[str]:
    """Every import that breaks a rule of the module docstring, as 'a imports b'."""
    wrong: set[str] = set()
    for module, tree in sources.items():
        mine, my_device = role(module), device_of(module)
        for target in _imports(tree, top_level_only=False):
            theirs, their_device = role(target), device_of(target)
            bad = theirs not in ALLOWED[mine] and not (
                mine == "registry" and target == "servotune.devices"
            )
            if their_device and my_device and their_device != my_device:
                bad = True  # a device imports another device
            if their_device and not my_device and theirs != "device-entry":
                bad = bad or mine != "registry" or theirs != "device-entry"
            if theirs == "device-sim" and mine not in ("device-sim", "device-entry"):
                bad = True
            if bad:
                wrong.add(f"{module} imports {target}")
    return wrong


def test_the_source_tree_was_found() -> None:
    # A wrong path would make every check below pass vacuously; every role is used.
    assert "servotune.devices.slap2.link" in SOURCES and "servotune.hub.hub" in SOURCES
    used = {role(m) for m in SOURCES}
    assert used >= set(ALLOWED) - {"device-entry", "registry", "identity", "tool"}, used


def test_every_module_imports_only_what_its_role_may() -> None:
    wrong = violations(SOURCES)
    assert not wrong - KNOWN, "\n".join(sorted(wrong - KNOWN))
    assert not KNOWN - wrong, f"fixed, remove from KNOWN: {sorted(KNOWN - wrong)}"


@pytest.mark.parametrize(
    ("module", "source", "expected"),
    [
        ("servotune.hub.fake", "from servotune.devices.slap2.link import Slap2Link", True),
        ("servotune.bench.fake", "import servotune.devices.z1100.codec", True),
        ("servotune.devices.slap2.fake", "from servotune.devices.z1100 import codec", True),
        ("servotune.devices.slap2.sim.fake", "from servotune.link.base import Sample", True),
        ("servotune.devices.slap2.fake", "from servotune.devices.slap2.sim import line", True),
        ("servotune.tuning.fake", "from servotune.bench.metrics import Metrics", True),
        ("servotune.perf.fake", "from servotune.devices.z1100.sim.demo import stop_plant", True),
        ("servotune.perf.fake", "from servotune.registry import StopRig", False),
        ("servotune.devices.slap2.sim.fake", "from servotune.devices.slap2 import codec", False),
        ("servotune.devices.slap2.fake", "from servotune.bench.metrics import Metrics", False),
    ],
)
def test_the_checker_finds_an_injected_violation(module: str, source: str, expected: bool) -> None:
    # The checker's self-check: a rule that never fires proves nothing.
    assert bool(violations({module: ast.parse(source)})) is expected


# A device's name is its folder's (``servotune.devices.<name>.NAME``).
DEVICE_NAMES = frozenset(path.parent.name for path in (PACKAGE / "devices").glob("*/entry.py"))


def _docstrings(tree: ast.AST) -> set[int]:
    kinds = (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)
    return {
        id(node.body[0].value)
        for node in ast.walk(tree)
        if isinstance(node, kinds)
        and node.body
        and isinstance(node.body[0], ast.Expr)
        and isinstance(node.body[0].value, ast.Constant)
    }


def devices_named(sources: Mapping[str, ast.AST]) -> set[str]:
    """Every string in the code (docstrings aside) of a module outside the device
    folders that is a device's name, as 'module names device'."""
    named: set[str] = set()
    for module, tree in sources.items():
        if module.startswith("servotune.devices"):
            continue
        docstrings = _docstrings(tree)
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Constant)
                and isinstance(node.value, str)
                and id(node) not in docstrings
                and node.value.lower() in DEVICE_NAMES
            ):
                named.add(f"{module} names {node.value}")
    return named


def test_no_generic_module_names_a_device() -> None:
    assert {"slap2", "z1100", "ep7047"} <= DEVICE_NAMES, DEVICE_NAMES
    wrong = devices_named(SOURCES)
    assert not wrong, "\n".join(sorted(wrong))


@pytest.mark.parametrize(
    ("module", "source", "expected"),
    [
        ("servotune.perf.fake", 'if case.device == "slap2":\n    pass', True),
        ("servotune.hub.fake", 'CASES = (Case("Z1100", "bench-x"),)', True),
        ("servotune.perf.fake", '"""Stops on the slap2."""\nNAME = "bench"', False),
        ("servotune.devices.slap2.entry", 'NAME = "slap2"', False),
    ],
)
def test_the_device_name_check_finds_an_injected_name(
    module: str, source: str, expected: bool
) -> None:
    assert bool(devices_named({module: ast.parse(source)})) is expected


def init_violations(sources: Mapping[str, ast.AST], packages: set[str]) -> list[str]:
    """The ``packages`` of ``sources`` whose ``__init__`` imports what it may not: anything,
    or for a facade anything but its own modules."""
    wrong = []
    for m, tree in sources.items():
        if m == "servotune" or m not in packages:
            continue
        # servotune.devices is the registry's list: its imports are inside
        # default_registry(), so importing a device module does not run them.
        imported = _imports(tree, top_level_only=m == "servotune.devices")
        if m in FACADES:
            imported = {t for t in imported if not t.startswith(f"{m}.")}
        if imported:
            wrong.append(m)
    return sorted(wrong)


PACKAGES = {m for m in SOURCES if (PACKAGE.parent / Path(*m.split(".")) / "__init__.py").exists()}


def test_package_inits_import_nothing() -> None:
    assert FACADES <= PACKAGES, FACADES - PACKAGES
    wrong = init_violations(SOURCES, PACKAGES)
    assert not wrong, wrong


@pytest.mark.parametrize(
    ("module", "source", "expected"),
    [
        ("servotune.hub", "from servotune.hub.hub import Hub", True),
        ("servotune.schema", "from servotune.schema.runs import RunMetrics", False),
        ("servotune.schema", "from servotune.descriptor import Conversion", True),
        ("servotune.schema", "import servotune.hub.hub", True),
    ],
)
def test_the_init_check_finds_an_injected_import(module: str, source: str, expected: bool) -> None:
    assert bool(init_violations({module: ast.parse(source)}, {module})) is expected


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


def import_graph(sources: Mapping[str, ast.AST]) -> dict[str, set[str]]:
    """Each module's module-level imports among ``sources``. A module imports its
    package's ``__init__`` too (Python runs it first), except a facade's: the facade runs
    its modules itself, and a module of it importing the facade is the cycle to find."""
    return {
        module: {t for t in _imports(tree, top_level_only=True) if t in sources and t != module}
        | {
            p
            for p in (module.rsplit(".", 1)[0],)
            if p in sources and p != module and p not in FACADES
        }
        for module, tree in sources.items()
    }


def test_a_facade_module_importing_its_facade_is_a_cycle() -> None:
    facade = {
        "servotune.schema": ast.parse("from servotune.schema.runs import RunMetrics"),
        "servotune.schema.base": ast.parse("X = 1"),
    }
    runs = "from servotune.schema.base import X"
    assert not _on_or_behind_a_cycle(
        import_graph({**facade, "servotune.schema.runs": ast.parse(runs)})
    )
    runs = "from servotune.schema import X"
    graph = import_graph({**facade, "servotune.schema.runs": ast.parse(runs)})
    assert _on_or_behind_a_cycle(graph) == ["servotune.schema", "servotune.schema.runs"]


def test_module_level_imports_form_no_cycle() -> None:
    stuck = _on_or_behind_a_cycle(import_graph(SOURCES))
    assert not stuck, f"import cycle among: {stuck}"
