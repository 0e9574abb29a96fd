"""The data directory is 0700 and its databases 0600 (the data dir
was 0755 and servotune.db 0644 on a shared lab machine)."""

from __future__ import annotations

import os
import sqlite3
import stat
from pathlib import Path

from servotune.api.app import AppConfig, create_app
from tests.support.auth import running
from tests.support.servers import local_client, use_csrf_token


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def _files(data_dir: Path) -> list[Path]:
    return sorted(p for p in data_dir.iterdir() if p.is_file())


async def _start_and_write(data_dir: Path) -> None:
    app = create_app(AppConfig(data_dir=data_dir, web_dir=data_dir / "no-web", twin=False))
    async with running(app), local_client(app) as http:
        await use_csrf_token(http)
        assert (await http.post("/api/stop")).status_code == 200  # an audited write


async def test_a_new_data_directory_is_private(tmp_path: Path) -> None:
    old_umask = os.umask(0o022)  # the usual umask: files 0644, directories 0755
    try:
        data_dir = tmp_path / "lab" / "data"
        await _start_and_write(data_dir)
    finally:
        os.umask(old_umask)
    assert _mode(data_dir) == 0o700
    files = _files(data_dir)
    assert {"servotune.db", "auth.db"} <= {p.name for p in files}
    for path in files:  # the databases and SQLite's -wal / -shm beside them
        assert _mode(path) == 0o600, path


async def test_an_existing_open_data_directory_is_tightened(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    data_dir.mkdir(mode=0o755)
    os.chmod(data_dir, 0o755)
    db = sqlite3.connect(data_dir / "servotune.db")
    db.execute("PRAGMA journal_mode=WAL")
    db.close()
    os.chmod(data_dir / "servotune.db", 0o644)
    await _start_and_write(data_dir)
    assert _mode(data_dir) == 0o700
    for path in _files(data_dir):
        assert _mode(path) == 0o600, path
