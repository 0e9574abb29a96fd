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
# Two worker processes (pytest-xdist): most tests wait on devices that run in real
# time, so two workers halve the wall time on two cores. The tests marked host_timing
# measure this host's own timing (capture stamps, loop lag, STOP time): they run after
# the others, alone (docs/architecture.md, "Tests"). SERVOTUNE_TEST_WORKERS=0 runs the
# first part in one process too (e.g. with -x or --pdb). Exit status 5 (no test
# selected, e.g. by -k) of one part is not a failure.
run_pytest() {
    local status=0
    "$VENV/bin/pytest" "$@" || status=$?
    if [ "$status" -eq 5 ]; then status=0; fi
    return "$status"
}
echo "==> pytest: all but host_timing, ${SERVOTUNE_TEST_WORKERS:-2} workers"
status=0
run_pytest -n "${SERVOTUNE_TEST_WORKERS:-2}" -m "not host_timing" "$@" || status=$?
echo "==> pytest: host_timing, alone"
run_pytest -m host_timing "$@" || status=$?
exit "$status"
