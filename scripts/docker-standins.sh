#!/usr/bin/env bash
# Test helper, NOT part of the product: builds local stand-ins for the four base images
# the Dockerfile and docker-compose.yml name (python:3.11-slim-bookworm,
# node:20-bookworm-slim, caddy:2, nats:2.9-alpine) from Debian bookworm packages, for a
# machine that runs Docker but cannot pull from Docker Hub (this project's development
# machines). The real images are what a lab uses; these only let the container build,
# the compose profiles and their restarts be tried here. docs/containers.md says how.
#
#   sudo bash scripts/docker-standins.sh          # needs debootstrap and a running dockerd
#
# What differs from the real images: Debian's Python 3.11.2 (pip may install system-wide,
# as in the official image), the host's Node 20 (copied from its nodejs package),
# Debian's caddy 2.6 and nats-server 2.9 on Debian instead of Alpine. Builds use the
# host's network (`--network host`: the daemon may have no bridge).
set -euo pipefail

work=${STANDIN_WORK:-/var/tmp/servotune-standins}
mkdir -p "$work"
rootfs=$work/bookworm-rootfs
tarball=$work/bookworm-rootfs.tar

if ! docker image inspect servotune-standin/bookworm:base >/dev/null 2>&1; then
    if [ ! -f "$tarball" ]; then
        rm -rf "$rootfs"
        debootstrap --variant=minbase --include=ca-certificates bookworm "$rootfs" \
            http://deb.debian.org/debian
        # The host's extra CA certificates (a TLS-intercepting egress proxy trusts
        # through them): without them apt/pip/npm inside the builds cannot verify.
        if compgen -G "/usr/local/share/ca-certificates/*.crt" >/dev/null; then
            cp /usr/local/share/ca-certificates/*.crt "$rootfs/usr/local/share/ca-certificates/"
            chroot "$rootfs" update-ca-certificates
        fi
        if [ -f /etc/apt/sources.list.d/debian.sources ]; then  # bookworm, -updates, -security
            cp /etc/apt/sources.list.d/debian.sources "$rootfs/etc/apt/sources.list.d/"
            rm -f "$rootfs/etc/apt/sources.list"
        fi
        chroot "$rootfs" apt-get clean
        tar -C "$rootfs" -cf "$tarball" .
    fi
    docker import "$tarball" servotune-standin/bookworm:base
fi

build() {  # build TAG <<Dockerfile
    local tag=$1 ctx
    ctx=$(mktemp -d)
    cat >"$ctx/Dockerfile"
    if [ -n "${2:-}" ]; then cp -a "$2" "$ctx/"; fi
    docker build --network host -t "$tag" "$ctx"
    rm -rf "$ctx"
}

build python:3.11-slim-bookworm <<'EOF'
FROM servotune-standin/bookworm:base
RUN apt-get update && apt-get install -y --no-install-recommends python3 python3-pip \
    python3-venv && rm -rf /var/lib/apt/lists/* \
    && ln -s /usr/bin/python3 /usr/local/bin/python && ln -s /usr/bin/pip3 /usr/local/bin/pip \
    && rm -f /usr/lib/python3.11/EXTERNALLY-MANAGED
ENV LANG=C.UTF-8
CMD ["python3"]
EOF

# Node 20 is not in bookworm: the host's own (node, and npm as installed now).
nodetar=$work/node.tar
tar -C / -cf "$nodetar" usr/bin/node usr/bin/npm usr/bin/npx usr/lib/node_modules
build node:20-bookworm-slim "$nodetar" <<'EOF'
FROM servotune-standin/bookworm:base
ADD node.tar /
# npm trusts its own CA list, not the system's (with the host's CAs added above).
ENV NODE_EXTRA_CA_CERTS=/etc/ssl/certs/ca-certificates.crt
RUN apt-get update && apt-get install -y --no-install-recommends libstdc++6 \
    && rm -rf /var/lib/apt/lists/* && node --version && npm --version
CMD ["node"]
EOF

build caddy:2 <<'EOF'
FROM servotune-standin/bookworm:base
RUN apt-get update && apt-get install -y --no-install-recommends caddy \
    && rm -rf /var/lib/apt/lists/* && mkdir -p /config/caddy /data/caddy /etc/caddy
ENV XDG_CONFIG_HOME=/config XDG_DATA_HOME=/data
EXPOSE 80 443
WORKDIR /srv
CMD ["caddy", "run", "--config", "/etc/caddy/Caddyfile", "--adapter", "caddyfile"]
EOF

build nats:2.9-alpine <<'EOF'
FROM servotune-standin/bookworm:base
RUN apt-get update && apt-get install -y --no-install-recommends nats-server \
    && rm -rf /var/lib/apt/lists/*
EXPOSE 4222 6222 8222
ENTRYPOINT ["nats-server"]
CMD ["-c", "/etc/nats/nats-server.conf"]
EOF

docker images --format '{{.Repository}}:{{.Tag}}  {{.Size}}' \
    | grep -E '^(python|node|caddy|nats|servotune-standin)'
