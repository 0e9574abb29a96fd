# Shared by scripts/demo.sh and scripts/test.sh: install what is missing, idempotently.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
PY="${PYTHON:-python3}"

ensure_venv() {  # $1: pip extras, e.g. "" or "[dev]"
  local extras="$1"
  local stamp="$VENV/.servotune-installed$extras"
  if [ ! -x "$VENV/bin/python" ]; then
    echo "==> creating $VENV"
    "$PY" -m venv "$VENV"
  fi
  if [ ! -f "$stamp" ] || [ "$ROOT/pyproject.toml" -nt "$stamp" ]; then
    echo "==> installing servotune$extras into .venv"
    "$VENV/bin/pip" install -q --upgrade pip
    "$VENV/bin/pip" install -q -e "$ROOT$extras"
    touch "$stamp"
  fi
}

ensure_web() {
  local stamp="$ROOT/web/node_modules/.servotune-installed"
  if [ ! -f "$stamp" ] || [ "$ROOT/web/package-lock.json" -nt "$stamp" ]; then
    echo "==> npm ci (web)"
    (cd "$ROOT/web" && npm ci --no-audit --no-fund --loglevel=error)
    touch "$stamp"
  fi
  # The build (`tsc --noEmit && vite build`) runs again only when what it reads changed:
  # the digest of its inputs is kept beside a bundle that was built from them.
  local digest_file="$ROOT/server/servotune/web_dist/.servotune-inputs"
  local digest
  digest="$(web_inputs_digest)"
  if [ -f "$ROOT/server/servotune/web_dist/index.html" ] && [ -f "$digest_file" ] \
    && [ "$(cat "$digest_file")" = "$digest" ]; then
    echo "==> the web bundle is up to date (type-checked and built from these sources)"
    return
  fi
  echo "==> building the web bundle"
  (cd "$ROOT/web" && npm run --silent build)
  echo "$digest" > "$digest_file"
}

web_inputs_digest() {  # what the web build reads: sources, configs, locked packages, node
  (
    cd "$ROOT/web"
    node --version
    find src index.html package.json package-lock.json tsconfig.json vite.config.ts \
      node_modules/.package-lock.json -type f -print0 | LC_ALL=C sort -z | xargs -0 sha256sum
  ) | sha256sum | cut -d' ' -f1
}

ensure_chromium() {
  if [ -x /usr/bin/chromium ]; then return; fi
  echo "==> installing Debian's chromium for the browser tests"
  local sudo=""
  if [ "$(id -u)" != 0 ]; then sudo="sudo"; fi
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq chromium >/dev/null
}

ensure_nats() {  # the bus tests start nats-server themselves (tests/support/nats.py)
  if command -v nats-server >/dev/null || [ -x /usr/sbin/nats-server ]; then return; fi
  echo "==> installing Debian's nats-server for the bus tests"
  local sudo=""
  if [ "$(id -u)" != 0 ]; then sudo="sudo"; fi
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq nats-server >/dev/null
}

ensure_caddy() {  # tests/integration/deploy/test_containers.py adapts the lab's Caddyfiles with the real caddy
  if command -v caddy >/dev/null; then return; fi
  echo "==> installing Debian's caddy for the Caddyfile tests"
  local sudo=""
  if [ "$(id -u)" != 0 ]; then sudo="sudo"; fi
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq caddy >/dev/null
}
