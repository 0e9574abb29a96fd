# The servotune image: the web bundle, the server with pinned dependencies, the demo as
# its default command. docs/containers.md: the compose profiles, restarts, what it refuses.
FROM node:20-bookworm-slim AS web
WORKDIR /src/web
COPY web/package.json web/package-lock.json ./
RUN npm ci --no-audit --no-fund
# The client's sources only: an edit to the server does not run the bundle's build again.
COPY web/ ./
RUN npm run build
# (vite writes the bundle to ../server/servotune/web_dist, as in a checkout)

FROM python:3.11-slim-bookworm
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 SERVOTUNE_DATA=/data
WORKDIR /app
# Every package at the version in constraints.txt (scripts/lock-deps.sh), in a layer of
# its own that only a change of the versions rebuilds; `pip check` fails the build when
# they no longer satisfy pyproject.toml.
COPY constraints.txt ./
RUN pip install --no-cache-dir -r constraints.txt
COPY pyproject.toml README.md ./
COPY server/ server/
COPY --from=web /src/server/servotune/web_dist/ server/servotune/web_dist/
RUN pip install --no-cache-dir --no-deps --no-build-isolation . && pip check \
    && useradd --create-home --uid 1000 servotune && mkdir -p /data && chown servotune /data
# uid 1000: the compose secrets (lab/nats/secrets) must be readable by it (docs/lab.md).
USER servotune
VOLUME ["/data"]
EXPOSE 8000
# The demo, local mode (no login) on 0.0.0.0: servotune refuses to start so unless
# SERVOTUNE_LOOPBACK_PUBLISHED=1 says the port is published on the host's loopback only
# (docker-compose.yml sets it beside "127.0.0.1:8000:8000"). `docker run -p 8000:8000`
# without it stops with that message instead of putting motor control on the LAN.
CMD ["servotune", "demo", "--host", "0.0.0.0", "--port", "8000", "--mode", "local"]
