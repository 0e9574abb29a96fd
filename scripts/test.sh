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
"$VENV/bin/pytest" "$@"
