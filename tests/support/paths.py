"""Paths of the repository as the tests see it, wherever a test module sits under tests/."""

from __future__ import annotations

import os
from pathlib import Path

SUPPORT = Path(__file__).resolve().parent
TESTS = SUPPORT.parent
REPO = TESTS.parent
SERVER = REPO / "server"
PACKAGE = SERVER / "servotune"
DOCS = REPO / "docs"
# Screenshots and traces of the browser tests (CI keeps them).
ARTIFACTS = Path(os.environ.get("SERVOTUNE_ARTIFACTS", REPO / "artifacts"))
