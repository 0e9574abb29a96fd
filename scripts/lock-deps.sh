#!/usr/bin/env bash
# Writes constraints.txt: the exact version of every package the servotune image
# installs (the runtime dependencies of pyproject.toml and theirs, plus the build
# backend), so that `docker build` is reproducible. The versions are those of this
# checkout's .venv (the ones the test suite ran with) where it has them.
#
#   bash scripts/lock-deps.sh        # after changing pyproject.toml's dependencies
#
# tests/integration/deploy/test_containers.py checks that every dependency is pinned and satisfies
# pyproject.toml.
source "$(dirname "${BASH_SOURCE[0]}")/_env.sh"
ensure_venv "[dev]"
cd "$ROOT"
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT
"$VENV/bin/pip" freeze --exclude-editable | grep -v '^servotune' >"$scratch/tested.txt"
"$PY" -m venv "$scratch/venv"
"$scratch/venv/bin/pip" install -q --upgrade pip
# Runtime dependencies only, at the tested versions; setuptools is the build backend.
"$scratch/venv/bin/pip" install -q -c "$scratch/tested.txt" . "setuptools>=77"
{
    echo "# Exact versions for the servotune image (Dockerfile: PIP_CONSTRAINT)."
    echo "# Written by scripts/lock-deps.sh from the tested .venv; do not edit by hand."
    "$scratch/venv/bin/pip" freeze --all --exclude-editable \
        | grep -v -E '^(servotune|pip)( @|==)' | LC_ALL=C sort -f
} >constraints.txt
echo "wrote constraints.txt ($(grep -c '==' constraints.txt) packages)"
