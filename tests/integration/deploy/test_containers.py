"""The container build and the compose lab as a user runs them.

Without Docker: the CLI behaviours the containers rely on (``--data-dir`` after a
``users``/``tokens`` action, the bind rule of local mode, a demo on a data directory it
cannot write, the credential files' uid), the Dockerfile's layers and pins, the
Caddyfile's issuer setting (with Debian's caddy where installed). With a compose client
(v2 plugin or v1): ``docker compose config`` of each profile. docs/containers.md records
the runs with a Docker daemon (build, up, restarts), which a unit test cannot do here.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import stat
import subprocess
import sys
import tempfile
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from packaging.requirements import Requirement

from servotune.auth.cli import account_data_dir
from servotune.cli import build_parser, local_bind_refusal, main
from servotune.perf.demo import free_port
from tests.support.paths import REPO as ROOT

ACCOUNT_ACTIONS = {
    "users": [
        ["list"],
        ["add", "ann", "--role", "admin"],
        ["passwd", "ann"],
        ["remove", "ann"],
        ["role", "ann", "viewer"],
    ],
    "tokens": [["list"], ["create", "ann", "ci"], ["revoke", "tok1"]],
}


# --- 1. --data-dir on every users/tokens action ------------------------------------------


@pytest.mark.parametrize(
    ("group", "action"),
    [(group, action) for group, actions in ACCOUNT_ACTIONS.items() for action in actions],
)
def test_data_dir_is_accepted_before_and_after_every_account_action(
    group: str, action: list[str]
) -> None:
    parser = build_parser()
    after = parser.parse_args([group, *action, "--data-dir", "/data/hub"])
    before = parser.parse_args([group, "--data-dir", "/data/hub", *action])
    assert account_data_dir(after) == account_data_dir(before) == Path("/data/hub")


def test_the_documented_first_admin_command_creates_the_account_where_the_hub_reads_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """docker-compose.yml's recipe, with the hub's data directory: the account is in
    <data>/hub/auth.db, and `users list` finds it with --data-dir in either place."""
    hub_dir = tmp_path / "hub"
    monkeypatch.setattr("sys.stdin", _Lines("correct horse battery staple\n"))
    argv = ["users", "add", "alice", "--role", "admin", "--data-dir", str(hub_dir)]
    assert main([*argv, "--password-stdin"]) == 0
    assert (hub_dir / "auth.db").is_file()
    capsys.readouterr()
    assert main(["users", "list", "--data-dir", str(hub_dir)]) == 0
    assert "alice" in capsys.readouterr().out
    assert main(["users", "--data-dir", str(hub_dir), "list"]) == 0
    assert "alice" in capsys.readouterr().out


def test_two_different_data_dirs_are_refused_without_a_traceback(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        main(
            ["users", "--data-dir", str(tmp_path / "a"), "list", "--data-dir", str(tmp_path / "b")]
        )
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--data-dir given twice" in err and "Traceback" not in err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


class _Lines:
    def __init__(self, text: str) -> None:
        self._lines = text.splitlines(keepends=True)

    def readline(self) -> str:
        return self._lines.pop(0) if self._lines else ""


# --- 7. the bind rule: local mode needs a loopback bind or the operator's word ------------


@pytest.mark.parametrize(
    ("host", "exposed", "stated", "refused"),
    [
        ("127.0.0.1", False, False, False),
        ("127.0.0.2", False, False, False),
        ("::1", False, False, False),
        ("localhost", False, False, False),
        ("0.0.0.0", False, False, True),
        ("::", False, False, True),
        ("192.0.2.7", False, False, True),
        ("0.0.0.0", False, True, False),  # the operator says: published on loopback only
        ("0.0.0.0", True, False, False),  # exposed mode: login, its own start-up rules
    ],
)
def test_local_mode_is_refused_on_a_non_loopback_bind_unless_stated(
    host: str, exposed: bool, stated: bool, refused: bool
) -> None:
    refusal = local_bind_refusal(exposed=exposed, host=host, published_on_loopback=stated)
    assert (refusal is not None) == refused
    if refused:
        assert host in refusal and "SERVOTUNE_LOOPBACK_PUBLISHED=1" in refusal


class _ServedError(Exception):
    """uvicorn.run was reached: the server would have started."""


@pytest.mark.parametrize("command", ["demo", "serve", "hub"])
def test_the_cli_refuses_the_images_default_command_without_the_statement(
    command: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """`docker run -p 8000:8000 servotune:demo` (the image's CMD: local mode on 0.0.0.0)
    stops with the reason, before any simulator or server starts; with
    SERVOTUNE_LOOPBACK_PUBLISHED=1 (docker-compose.yml's demo) it gets to serving."""
    import uvicorn

    def serve(*args: object, **kwargs: object) -> None:
        raise _ServedError

    monkeypatch.setattr(uvicorn, "run", serve)
    monkeypatch.delenv("SERVOTUNE_LOOPBACK_PUBLISHED", raising=False)
    argv = {
        "demo": ["demo"],
        "serve": ["serve", "--link", "slap2:/dev/null"],
        "hub": ["hub", "--bus", "nats://127.0.0.1:4222"],
    }[command]
    argv += ["--host", "0.0.0.0", "--mode", "local", "--data-dir", str(tmp_path)]
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "refusing local mode (no login) on 0.0.0.0" in err and "Traceback" not in err
    monkeypatch.setenv("SERVOTUNE_LOOPBACK_PUBLISHED", "0")
    with pytest.raises(SystemExit):
        main(argv)
    monkeypatch.setenv("SERVOTUNE_LOOPBACK_PUBLISHED", "1")
    with pytest.raises(_ServedError):
        main(argv)
    monkeypatch.delenv("SERVOTUNE_LOOPBACK_PUBLISHED")
    with pytest.raises(_ServedError):
        main([*argv, "--loopback-published"])


# --- 6. the demo on a data directory it cannot write ---------------------------------------


@contextlib.contextmanager
def _unwritable_dir() -> Iterator[tuple[Path, list[str]]]:
    """A data directory this process's uid cannot write, and the command prefix that
    makes it so: mode 0555 for an ordinary user; for root (whom modes do not stop, as
    in CI) a read-only bind mount in a mount namespace of the server's own, as a
    read-only volume would be."""
    directory = Path(tempfile.mkdtemp(prefix="servotune-ro-"))
    try:
        if os.geteuid() != 0:
            directory.chmod(0o555)
            yield directory, []
            return
        if shutil.which("unshare") is None:
            pytest.skip("root, and no unshare(1) to make a read-only mount")
        probe = subprocess.run(
            ["unshare", "--mount", "--", "sh", "-c",
             f'mount --bind -o ro "{directory}" "{directory}" && ! touch "{directory}/x"'],
            capture_output=True, timeout=30, check=False,
        )  # fmt: skip
        if probe.returncode != 0:
            pytest.skip(f"root, and no read-only bind mount here: {probe.stderr.decode()[-200:]}")
        yield directory, [
            "unshare", "--mount", "--", "sh", "-c",
            'mount --bind -o ro "$1" "$1" && shift && exec "$@"', "sh", str(directory),
        ]  # fmt: skip
    finally:
        directory.chmod(0o755)
        shutil.rmtree(directory, ignore_errors=True)


@pytest.mark.slow
def test_the_demo_starts_on_a_data_directory_it_cannot_write() -> None:
    """A root-owned or read-only /data: the simulators keep their state in a temporary
    directory, the log names the path and the uid, and all six axes are served
    (before: exit 3, 'simulator slap2 failed to start: PermissionError(13, ...)')."""
    port = free_port()
    with _unwritable_dir() as (data_dir, prefix):
        argv = [*prefix, sys.executable, "-m", "servotune", "demo", "--port", str(port),
                "--data-dir", str(data_dir), "--no-autopilot"]  # fmt: skip
        env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}
        with tempfile.TemporaryFile() as err_file:
            server = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=err_file, env=env)
            try:
                axes = _wait_for_axes(server, port)
            finally:
                server.terminate()
                server.wait(timeout=30)
            err_file.seek(0)
            err = err_file.read().decode(errors="replace")
        assert len(axes) == 6, err[-2000:]
        assert f"{data_dir}/demo/sim" in err or f"{data_dir}/sim" in err, err[-2000:]
        assert f"uid {os.getuid()}" in err and "for this run only" in err, err[-2000:]
        assert "Traceback" not in err, err[-3000:]
        assert list(data_dir.iterdir()) == []


def _wait_for_axes(server: subprocess.Popen[bytes], port: int) -> list[object]:
    # A start-up wait, not a timing assertion: generous for a loaded 2-core machine.
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        if server.poll() is not None:
            return []
        try:
            answer = httpx.get(f"http://127.0.0.1:{port}/api/axes", timeout=5)
            axes = answer.json()
            if isinstance(axes, list) and len(axes) == 6:
                return axes
        except (httpx.HTTPError, json.JSONDecodeError, ValueError):
            pass
        time.sleep(0.3)
    return []


def test_the_demo_state_dir_falls_back_with_the_reason(tmp_path: Path) -> None:
    from servotune.demo import demo_state_dir

    with demo_state_dir(tmp_path) as (state_dir, problem):
        assert state_dir == tmp_path / "sim" and problem is None
    blocked = tmp_path / "a-file"
    blocked.write_text("")  # a data directory that is a file: nothing can go under it
    with demo_state_dir(blocked) as (state_dir, problem):
        assert problem is not None and str(blocked / "sim") in problem
        assert f"uid {os.getuid()}" in problem
        assert state_dir.is_dir() and not state_dir.is_relative_to(blocked)
        scratch = state_dir
    assert not scratch.exists()


# --- 4. credential files the container's uid cannot read ----------------------------------


def _unreadable(path: Path) -> list[str]:
    """Make ``path`` unreadable to the process started with the returned prefix."""
    path.chmod(0o000)
    if os.geteuid() != 0:
        return []
    # Root reads any file: drop the capability that lets it (a container's root has it
    # too, but the image runs as uid 1000, which never had it).
    if shutil.which("setpriv") is None:
        pytest.skip("root, and no setpriv(1) to drop CAP_DAC_OVERRIDE")
    return ["setpriv", "--inh-caps=-all", "--bounding-set=-dac_override,-dac_read_search", "--"]


@pytest.mark.parametrize("which", ["hub", "hub-view"])
def test_an_unreadable_credential_file_names_the_uid_without_a_traceback(
    which: str, tmp_path: Path
) -> None:
    for name in ("hub", "hub-view", "hub-stop"):
        (tmp_path / f"{name}.cred").write_text(f"{name}\nsecret-{name}\n")
    prefix = _unreadable(tmp_path / f"{which}.cred")
    result = subprocess.run(
        [*prefix, sys.executable, "-m", "servotune", "hub", "--bus", "nats://127.0.0.1:9",
         "--bus-credentials", str(tmp_path / "hub.cred"), "--data-dir", str(tmp_path / "d")],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert result.returncode == 2, result.stderr
    assert f"cannot read {tmp_path / f'{which}.cred'} as uid {os.getuid()}" in result.stderr
    assert "chown -R 1000 lab/nats/secrets" in result.stderr
    assert "Traceback" not in result.stderr
    assert "secret-" not in result.stderr


def test_bus_accounts_says_which_uid_can_read_the_files(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out_dir = tmp_path / "secrets"
    assert main(["bus-accounts", "--rig", "rig-1", "--out", str(out_dir)]) == 0
    out = capsys.readouterr().out
    assert f"uid {os.getuid()}, mode 0600" in out
    assert f"chown -R 1000 {out_dir}" in out
    modes = {stat.S_IMODE(p.stat().st_mode) for p in out_dir.iterdir()}
    assert modes == {0o600}


# --- 7. the build: context, layers, pins ----------------------------------------------------


def _stages() -> dict[str, list[str]]:
    stages: dict[str, list[str]] = {}
    current = ""
    for line in (ROOT / "Dockerfile").read_text().splitlines():
        if line.startswith("FROM "):
            words = line.split()
            current = words[3] if len(words) > 3 and words[2].upper() == "AS" else "final"
            stages[current] = []
        elif line and not line.startswith("#"):
            stages[current].append(line)
    return stages


def test_the_web_stage_copies_only_the_client() -> None:
    """An edit under server/ must not invalidate the bundle's build layer."""
    copies = [line for line in _stages()["web"] if line.startswith(("COPY", "ADD"))]
    assert copies and all("server" not in line for line in copies), copies


def test_secrets_and_certificates_stay_out_of_the_build_context() -> None:
    patterns = {line.strip() for line in (ROOT / ".dockerignore").read_text().splitlines()}
    assert {"lab/nats/secrets", "lab/certs", ".venv", "**/node_modules"} <= patterns


def test_the_image_installs_exactly_the_pinned_versions() -> None:
    constraints: dict[str, str] = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            name, _, version = line.partition("==")
            assert version, f"constraints.txt: {line!r} is not pinned with =="
            constraints[name.lower().replace("_", "-")] = version
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    for text in project["dependencies"]:
        requirement = Requirement(text)
        name = requirement.name.lower().replace("_", "-")
        assert name in constraints, f"{name} is not in constraints.txt (scripts/lock-deps.sh)"
        assert requirement.specifier.contains(constraints[name]), (name, constraints[name])
        for extra in requirement.extras:  # uvicorn[standard]: its extras' packages too
            assert extra == "standard" and {"uvloop", "httptools", "watchfiles"} <= set(constraints)
    final = "\n".join(_stages()["final"])
    assert "pip install --no-cache-dir -r constraints.txt" in final
    assert "--no-deps" in final and "pip check" in final


# --- 5. Caddy's certificate issuer is a setting --------------------------------------------


@pytest.mark.parametrize("caddyfile", ["Caddyfile", "Caddyfile.hub"])
@pytest.mark.parametrize(
    ("setting", "expected"),
    [
        (None, {"issuers": [{"module": "internal"}]}),
        ("lab-admin@example.org", {"module": "acme", "email": "lab-admin@example.org"}),
        ("/certs/cert.pem /certs/key.pem", {"certificate": "/certs/cert.pem"}),
    ],
)
def test_the_caddyfile_issuer_follows_servotune_lab_tls(
    caddyfile: str, setting: str | None, expected: dict[str, object]
) -> None:
    caddy = shutil.which("caddy")
    if caddy is None:
        pytest.skip("no caddy here (Debian: apt-get install caddy) to adapt the Caddyfile")
    env = {k: v for k, v in os.environ.items() if not k.startswith("SERVOTUNE_LAB_")}
    env["SERVOTUNE_LAB_HOST"] = "rig1.lab.example"
    if setting is not None:
        env["SERVOTUNE_LAB_TLS"] = setting
    result = subprocess.run(
        [caddy, "adapt", "--config", str(ROOT / "lab" / caddyfile)],
        capture_output=True, text=True, env=env, timeout=60, check=True,
    )  # fmt: skip
    tls = json.loads(result.stdout)["apps"]["tls"]
    if "certificate" in expected:
        assert tls["certificates"]["load_files"][0]["certificate"] == expected["certificate"]
        return
    (policy,) = tls["automation"]["policies"]
    assert policy["subjects"] == ["rig1.lab.example"]
    if "issuers" in expected:
        assert policy["issuers"] == expected["issuers"]
    else:
        assert {"module": "acme", "email": expected["email"]} in policy["issuers"]


# --- docker compose config, per profile -------------------------------------------------------


def _compose_clients() -> list[tuple[str, list[str]]]:
    clients = []
    if shutil.which("docker"):
        probe = subprocess.run(["docker", "compose", "version"], capture_output=True, check=False)
        if probe.returncode == 0:
            clients.append(("v2", ["docker", "compose"]))
    if shutil.which("docker-compose"):
        clients.append(("v1", ["docker-compose"]))
    return clients


PROFILE_SERVICES = {
    "": {"servotune-demo"},
    "lab": {"servotune-demo", "lab-net", "servotune-lab", "caddy"},
    "nats-lab": {"servotune-demo", "nats", "hub-net", "servotune-hub", "caddy-hub",
                 "rig-1-net", "rig-1-nats", "rig-1", "rig-2-net", "rig-2-nats", "rig-2"},
}  # fmt: skip


@pytest.mark.parametrize("profile", sorted(PROFILE_SERVICES))
def test_docker_compose_config_of_each_profile(profile: str) -> None:
    clients = _compose_clients()
    if not clients:
        pytest.skip("no compose client here (docker compose plugin or docker-compose)")
    env = {k: v for k, v in os.environ.items() if not k.startswith("COMPOSE_")}
    for version, client in clients:
        argv = [*client, *(["--profile", profile] if profile else [])]
        quiet = subprocess.run(
            [*argv, "config", "-q"], cwd=ROOT, env=env, capture_output=True, text=True,
            timeout=120, check=False,
        )  # fmt: skip
        assert quiet.returncode == 0, (version, quiet.stderr)
        if version == "v1":
            continue  # v1's `config --services` lists every profile's services
        listed = subprocess.run(
            [*argv, "config", "--services"], cwd=ROOT, env=env, capture_output=True,
            text=True, timeout=120, check=True,
        )  # fmt: skip
        assert set(listed.stdout.split()) == PROFILE_SERVICES[profile]
