"""Data only its owner can read: the data directory 0700, the databases 0600.

``servotune.db`` holds the runs and settings, ``auth.db`` the password hashes, sessions
and the audit log; neither is anyone else's business on a shared lab machine. New
files are created with these modes before SQLite opens them (SQLite gives its -wal and
-shm files the database's own mode), and an existing directory or file that is more
open is tightened at start-up, with a warning that says so. Where that is not allowed
(a volume owned by someone else) the warning says why and the server still starts.
"""

from __future__ import annotations

import logging
import os
import stat
from pathlib import Path

logger = logging.getLogger(__name__)

PRIVATE_DIR_MODE = 0o700
PRIVATE_FILE_MODE = 0o600


def private_dir(path: Path) -> None:
    """Create ``path`` (with its parents) when missing, and make ``path`` 0700.

    Raises OSError when it cannot be created (a read-only file system)."""
    path.mkdir(parents=True, exist_ok=True, mode=PRIVATE_DIR_MODE)
    _tighten(path, PRIVATE_DIR_MODE)


def private_file(path: Path) -> None:
    """Create ``path`` empty with mode 0600 when missing, and make it (and SQLite's
    -wal and -shm beside it) 0600. Raises OSError when it cannot be created."""
    if not path.exists():
        os.close(os.open(path, os.O_CREAT | os.O_WRONLY, PRIVATE_FILE_MODE))
    for candidate in (path, path.with_name(path.name + "-wal"), path.with_name(path.name + "-shm")):
        if candidate.exists():
            _tighten(candidate, PRIVATE_FILE_MODE)


def _tighten(path: Path, mode: int) -> None:
    try:
        current = stat.S_IMODE(path.stat().st_mode)
        if current & ~mode:
            os.chmod(path, current & mode)
            logger.warning("%s was mode %03o: now %03o (only its owner may read it)", path,
                           current, current & mode)  # fmt: skip
    except OSError as exc:
        logger.warning("%s cannot be made mode %03o (%s): others may read it", path, mode, exc)
