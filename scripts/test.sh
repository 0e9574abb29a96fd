#!/usr/bin/env bash
# Quick start 2: the whole test suite — lint, format, types, generated types, unit,
# simulator, driver-on-pty, API, websocket and headless-browser tests.
# Extra arguments go to pytest (e.g. -k codec).
source "$(dirname "${BASH_SOURCE[0]}")/_env.sh"
ensure_venv "[dev]"
ensure_web
ensure_chromium
ensure_nats
ensure_caddy
cd "$ROOT"
echo "==> ruff"
"$VENV/bin/ruff" check server tests
"$VENV/bin/ruff" format --check server tests
echo "==> mypy"
"$VENV/bin/mypy"
echo "==> generated TypeScript schema types are current"
"$VENV/bin/python" -m servotune.schema_ts --check web/src/schema.gen.ts
echo "==> pytest"
# Two worker processes (pytest-xdist): most tests wait on devices that run in real
# time, so two workers halve the wall time on two cores (docs/architecture.md, "Tests").
# SERVOTUNE_TEST_WORKERS=0 runs in one process (e.g. with -x or --pdb).
"$VENV/bin/pytest" -n "${SERVOTUNE_TEST_WORKERS:-2}" "$@"
