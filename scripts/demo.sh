#!/usr/bin/env bash
# Quick start 1: the demo dashboard with simulated controllers at http://127.0.0.1:8000
# Extra arguments go to `servotune demo` (e.g. --port 8080, --no-autopilot).
source "$(dirname "${BASH_SOURCE[0]}")/_env.sh"
ensure_venv ""
ensure_web
exec "$VENV/bin/servotune" demo "$@"
