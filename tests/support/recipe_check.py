"""Checks a printed command (tests/support/doc_commands.py) as the user would run it.

``servotune ...`` goes through the CLI's own argparse parser (``servotune.cli.
build_parser``): strictly for a code block or a comment, and for an inline span in prose
with the required arguments relaxed (a span may name a command without every argument).
``docker compose ...`` / ``docker-compose ...`` is checked against docker-compose.yml:
its profiles and services exist, a ``run``'s command parses, an account command run in a
service works on the data directory that service's server uses, and the services an
``up`` or ``run`` starts find every file they mount, in the checkout or written by an
earlier command of the same recipe (``servotune bus-accounts --out``). ``docker run``
of the servotune image: its command parses and the image's bind rule lets it start.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import io
import json
import os
import re
import shlex
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from servotune.auth.cli import account_data_dir
from servotune.cli import build_parser, local_bind_refusal, loopback_published, server_data_dir
from tests.support.doc_commands import ROOT, Printed, Recipe

IMAGE = "servotune:demo"
SERVER_COMMANDS = frozenset({"demo", "serve", "hub"})


class RecipeError(Exception):
    """A printed command that would fail for its user; the message says where and why."""


# --- the servotune CLI -----------------------------------------------------------------


def _relaxed(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """``parser`` with nothing required, for inline mentions such as `servotune hub`."""
    for action in parser._actions:
        action.required = False
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                _relaxed(child)
        elif not action.option_strings and action.nargs is None:
            action.nargs = "?"
    return parser


def parse_servotune(argv: list[str], where: str, *, relaxed: bool = False) -> argparse.Namespace:
    """``servotune`` arguments through the CLI's parser; RecipeError with its message."""
    parser = _relaxed(build_parser()) if relaxed else build_parser()
    errors = io.StringIO()
    try:
        with contextlib.redirect_stderr(errors):
            return parser.parse_args(argv)
    except SystemExit:
        message = errors.getvalue().strip().splitlines()[-1:] or ["(no message)"]
        raise RecipeError(f"{where}: servotune {shlex.join(argv)}: {message[0]}") from None


# --- the image and the compose file ------------------------------------------------------


def dockerfile() -> tuple[dict[str, str], list[str]]:
    """The final stage's ENV and its CMD."""
    env: dict[str, str] = {}
    cmd: list[str] = []
    for line in (ROOT / "Dockerfile").read_text().splitlines():
        if line.startswith("FROM "):
            env, cmd = {}, []
        elif line.startswith("ENV "):
            for word in shlex.split(line[4:]):
                key, _, value = word.partition("=")
                env[key] = value
        elif line.startswith("CMD "):
            cmd = json.loads(line[4:])
    return env, cmd


_VARIABLE = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?::?-([^}]*))?\}")


def interpolate(value: Any, env: dict[str, str]) -> Any:
    """Compose's ``${NAME:-default}``, in every string of ``value``."""
    if isinstance(value, str):
        return _VARIABLE.sub(lambda m: env.get(m.group(1)) or m.group(2) or "", value)
    if isinstance(value, list):
        return [interpolate(v, env) for v in value]
    if isinstance(value, dict):
        return {k: interpolate(v, env) for k, v in value.items()}
    return value


def compose_file(env: dict[str, str] | None = None) -> dict[str, Any]:
    data: dict[str, Any] = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    return interpolate(data, env or {})  # type: ignore[no-any-return]


@dataclass
class Service:
    name: str
    spec: dict[str, Any]

    @property
    def profiles(self) -> list[str]:
        return list(self.spec.get("profiles", []))

    @property
    def servotune_image(self) -> bool:
        return self.spec.get("image") == IMAGE

    def command(self) -> list[str]:
        """The command it runs (the image's CMD when it names none)."""
        command = self.spec.get("command")
        if command is None:
            return dockerfile()[1] if self.servotune_image else []
        return shlex.split(command) if isinstance(command, str) else [str(c) for c in command]

    def environment(self) -> dict[str, str]:
        value = self.spec.get("environment", {})
        if isinstance(value, list):
            return dict(item.split("=", 1) for item in value)
        return {str(k): str(v) for k, v in value.items()}

    def dependencies(self) -> list[str]:
        names = list(self.spec.get("depends_on", []))
        mode = self.spec.get("network_mode", "")
        if mode.startswith("service:"):
            names.append(mode.removeprefix("service:"))
        return names

    def host_files(self, compose: dict[str, Any]) -> list[str]:
        """The checkout's files it mounts: bind-mount sources and secret files."""
        files = [
            v.split(":", 1)[0] for v in self.spec.get("volumes", []) if v.startswith(("./", "/"))
        ]
        for secret in self.spec.get("secrets", []):
            name = secret if isinstance(secret, str) else secret["source"]
            files.append(compose["secrets"][name]["file"])
        return files


def services(compose: dict[str, Any]) -> dict[str, Service]:
    return {name: Service(name, spec) for name, spec in compose["services"].items()}


def all_profiles(compose: dict[str, Any]) -> set[str]:
    return {p for s in services(compose).values() for p in s.profiles}


def with_dependencies(names: list[str], known: dict[str, Service]) -> list[str]:
    order: list[str] = []

    def visit(name: str) -> None:
        if name not in order:
            order.append(name)
            for dependency in known[name].dependencies():
                visit(dependency)

    for name in names:
        visit(name)
    return order


def service_server_args(service: Service, where: str) -> argparse.Namespace:
    return parse_servotune(service.command()[1:], f"{where} (service {service.name})")


@contextlib.contextmanager
def image_environment(extra: dict[str, str] | None = None) -> Iterator[None]:
    """os.environ as inside the image (its ENV, e.g. SERVOTUNE_DATA=/data)."""
    values = {**dockerfile()[0], **(extra or {})}
    saved = {key: os.environ.get(key) for key in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def check_bind_rule(
    args: argparse.Namespace, env: dict[str, str], ports: list[str], where: str
) -> None:
    """A server command in the image must pass the bind rule, and a stated loopback
    publish must be true of every port it publishes."""
    if args.command not in SERVER_COMMANDS:
        return
    from servotune.auth.cli import security_config_from_args

    security = security_config_from_args(args, args.host)
    stated = loopback_published(args, env)
    refusal = local_bind_refusal(
        exposed=security.exposed, host=args.host, published_on_loopback=stated
    )
    if refusal is not None:
        raise RecipeError(f"{where}: servotune would refuse to start: {refusal}")
    if stated:
        for port in ports:
            if not str(port).startswith(("127.0.0.1:", "[::1]:")):
                raise RecipeError(
                    f"{where}: says the port is published on loopback only, but publishes {port}"
                )


# --- running a recipe -------------------------------------------------------------------


@dataclass
class RecipeState:
    """What the recipe's earlier commands left on the host (paths relative to ROOT)."""

    made: set[str] = field(default_factory=set)


def bus_accounts_files(args: argparse.Namespace) -> list[str]:
    """The names ``servotune bus-accounts`` writes for these arguments (run for real into
    a scratch directory)."""
    import tempfile

    with tempfile.TemporaryDirectory() as scratch:
        argv = ["bus-accounts", "--hub", args.hub, "--out", scratch]
        for rig in args.rig:
            argv += ["--rig", rig]
        for viewer in args.viewer:
            argv += ["--viewer", viewer]
        if args.leaf:
            argv += ["--leaf"]
        result = subprocess.run(
            [sys.executable, "-m", "servotune", *argv],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        if result.returncode != 0:
            raise RecipeError(f"bus-accounts {argv}: {result.stderr.strip()}")
        return sorted(p.name for p in Path(scratch).iterdir())


def _host_path(path: str, mounts: dict[str, str] | None = None) -> str | None:
    """A path as the checkout's relative path (None when outside it); ``mounts`` maps
    a container path to the host path bound there."""
    for inside, outside in (mounts or {}).items():
        if path == inside or path.startswith(inside.rstrip("/") + "/"):
            path = outside + path[len(inside.rstrip("/")) :]
            break
    path = path.replace("$PWD", str(ROOT)).replace("${PWD}", str(ROOT))
    full = (ROOT / path).resolve() if not path.startswith("/") else Path(path)
    return full.relative_to(ROOT).as_posix() if full.is_relative_to(ROOT) else None


def run_servotune(
    argv: list[str], where: str, state: RecipeState, mounts: dict[str, str] | None = None
) -> argparse.Namespace:
    args = parse_servotune(argv, where)
    if args.command == "bus-accounts":
        out = _host_path(str(args.out), mounts)
        if out is not None:
            state.made |= {f"{out}/{name}" for name in bus_accounts_files(args)}
    return args


def _split_options(
    words: list[str], flags: set[str], valued: set[str], where: str
) -> tuple[dict[str, list[str]], list[str]]:
    """Leading options of a docker (compose) subcommand, and the words after them."""
    options: dict[str, list[str]] = {}
    index = 0
    while index < len(words) and words[index].startswith("-"):
        word = words[index]
        name, _, inline_value = word.partition("=")
        if name in flags:
            options.setdefault(name, [])
        elif name in valued:
            value = inline_value or words[index + 1]
            index += 0 if inline_value else 1
            options.setdefault(name, []).append(value)
        else:
            raise RecipeError(f"{where}: option {word} is not known to this check: add it")
        index += 1
    return options, words[index:]


_COMPOSE_GLOBAL = {"--profile", "-f", "--file", "-p", "--project-name", "--env-file"}
_COMPOSE_FLAGS = {
    "run": {"--rm", "--no-deps", "-d", "--detach", "-T", "--service-ports", "-it"},
    "up": {"-d", "--detach", "--build", "--force-recreate", "--no-deps", "--wait"},
    "build": {"--pull", "--no-cache"},
    "config": {"-q", "--quiet", "--services"},
    "down": {"-v", "--volumes"},
    "logs": {"-f", "--follow"},
    "ps": set(),
    "restart": set(),
    "stop": set(),
    "exec": {"-T"},
}
_COMPOSE_VALUED = {
    "run": {"-e", "-v", "--volume", "--user", "-u", "--entrypoint", "--name"},
    "exec": {"-u", "--user", "-e"},
    "logs": {"--tail"},
}


@functools.cache
def _checkout() -> frozenset[str] | None:
    """The checkout's files and folders as a fresh clone has them (None without git): a
    generated, ignored file in this working tree (lab/nats/secrets) must not make a
    recipe that skips the step generating it pass."""
    listing = subprocess.run(
        ["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=False
    )
    if listing.returncode != 0:
        return None
    paths = set()
    for name in listing.stdout.splitlines():
        parts = name.split("/")
        paths |= {"/".join(parts[:i]) for i in range(1, len(parts) + 1)}
    return frozenset(paths)


def _in_checkout(relative: str) -> bool:
    tracked = _checkout()
    return (ROOT / relative).exists() if tracked is None else relative in tracked


def _check_files(
    names: list[str],
    known: dict[str, Service],
    compose: dict[str, Any],
    state: RecipeState,
    where: str,
) -> None:
    for name in names:
        for path in known[name].host_files(compose):
            relative = _host_path(path)
            if relative is None or _in_checkout(relative) or relative in state.made:
                continue
            raise RecipeError(
                f"{where}: service {name} mounts {path}, which does not exist and no "
                "earlier step of this recipe writes it"
            )


def run_compose(command: Printed, words: list[str], state: RecipeState, *, relaxed: bool) -> None:
    where = command.where
    options, rest = _split_options(words, set(), _COMPOSE_GLOBAL, where)
    if not rest:
        if relaxed:
            return  # prose naming the tool
        raise RecipeError(f"{where}: docker compose without a subcommand")
    compose = compose_file(command.env)
    known = services(compose)
    for profile in options.get("--profile", []):
        if profile not in all_profiles(compose):
            raise RecipeError(f"{where}: no profile {profile!r} in docker-compose.yml")
    sub, rest = rest[0], rest[1:]
    if sub not in _COMPOSE_FLAGS:
        raise RecipeError(f"{where}: compose subcommand {sub!r} is not known to this check")
    sub_options, rest = _split_options(
        rest, _COMPOSE_FLAGS[sub], _COMPOSE_VALUED.get(sub, set()), where
    )
    targets = rest[:1] if sub in ("run", "exec") else rest
    for name in targets:
        if name not in known:
            raise RecipeError(f"{where}: no service {name!r} in docker-compose.yml")
    if relaxed:
        return
    active = set(options.get("--profile", []))
    if sub in ("up", "run"):
        if sub == "run" or targets:
            chosen = targets
        else:
            chosen = [n for n, s in known.items() if not s.profiles or active & set(s.profiles)]
        started = chosen if "--no-deps" in sub_options else with_dependencies(chosen, known)
        _check_files(started, known, compose, state, where)
        for name in started:
            if sub == "run" and name in targets:
                continue  # it runs the recipe's command, checked below
            service = known[name]
            if service.servotune_image and service.command()[:1] == ["servotune"]:
                args = service_server_args(service, where)
                check_bind_rule(
                    args,
                    service.environment(),
                    service.spec.get("ports", []),
                    f"{where} (service {name})",
                )
    if sub in ("run", "exec") and rest[1:2] == ["servotune"]:
        service = known[targets[0]]
        mounts = dict((v.split(":")[1], v.split(":")[0]) for v in sub_options.get("-v", []))
        with image_environment():
            args = run_servotune(rest[2:], where, state, mounts)
            if args.command in ("users", "tokens"):
                server = service_server_args(service, where)
                if server.command in SERVER_COMMANDS:
                    wanted, used = server_data_dir(server), account_data_dir(args)
                    if wanted != used:
                        raise RecipeError(
                            f"{where}: the accounts go to {used}/auth.db, but service "
                            f"{service.name}'s server reads {wanted}/auth.db (--data-dir {wanted})"
                        )


_RUN_FLAGS = {"--rm", "-d", "--detach", "-it", "-i", "-t", "--init"}
_RUN_VALUED = {
    "-p",
    "--publish",
    "-e",
    "--env",
    "-v",
    "--volume",
    "--user",
    "-u",
    "--name",
    "--network",
    "--entrypoint",
}


def run_docker_run(
    command: Printed, words: list[str], state: RecipeState, *, relaxed: bool = False
) -> None:
    where = command.where
    options, rest = _split_options(words, _RUN_FLAGS, _RUN_VALUED, where)
    image, argv = rest[0], rest[1:]
    if image != IMAGE:
        return
    env = dict(e.split("=", 1) for e in options.get("-e", []) + options.get("--env", []))
    mounts = {}
    for volume in options.get("-v", []) + options.get("--volume", []):
        outside, inside = volume.split(":")[:2]
        mounts[inside] = outside
    argv = argv or dockerfile()[1]
    steps = [argv]
    if argv[:2] in (["sh", "-c"], ["bash", "-c"]):
        steps = [shlex.split(part) for part in re.split(r"&&|;", argv[2])]
    for step in steps:
        if step[:1] != ["servotune"]:
            continue
        if relaxed:  # named in prose, perhaps as what not to do
            parse_servotune(step[1:], where, relaxed=True)
            continue
        with image_environment():
            args = run_servotune(step[1:], where, state, mounts)
        ports = options.get("-p", []) + options.get("--publish", [])
        check_bind_rule(args, env, ports, where)


def run_recipe(recipe: Recipe) -> None:
    """Every command of ``recipe`` in order; RecipeError at the first that would fail."""
    state = RecipeState()
    for command in recipe.commands:
        run_command(command, state)


def run_command(command: Printed, state: RecipeState | None = None) -> None:
    state = state or RecipeState()
    argv = command.argv
    if argv[0] == "servotune":
        if command.inline:
            parse_servotune(argv[1:], command.where, relaxed=True)
        else:
            run_servotune(argv[1:], command.where, state)
    elif argv[0] == "docker-compose":
        run_compose(command, argv[1:], state, relaxed=command.inline)
    elif argv[1:2] == ["compose"]:
        run_compose(command, argv[2:], state, relaxed=command.inline)
    elif argv[1:2] == ["run"]:
        run_docker_run(command, argv[2:], state, relaxed=command.inline)
    elif argv[1:2] in (["build"], ["images"], ["logs"], ["ps"], ["rm"], ["stop"], ["restart"]):
        pass  # plain docker housekeeping: nothing of ours to check
    else:
        raise RecipeError(f"{command.where}: docker {argv[1:2]} is not known to this check")
