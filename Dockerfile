# servotune demo image: builds the web bundle, installs the server, runs the demo.
FROM node:20-bookworm-slim AS web
WORKDIR /src/web
COPY web/package.json web/package-lock.json ./
RUN npm ci --no-audit --no-fund
COPY web/ ./
COPY server/ /src/server/
RUN npm run build

FROM python:3.11-slim-bookworm
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 SERVOTUNE_DATA=/data
WORKDIR /app
COPY pyproject.toml README.md ./
COPY server/ server/
COPY --from=web /src/server/servotune/web_dist/ server/servotune/web_dist/
RUN pip install --no-cache-dir . && useradd --create-home servotune && mkdir -p /data \
    && chown servotune /data
USER servotune
VOLUME ["/data"]
EXPOSE 8000
# Inside the container the server must listen on all interfaces; the compose file
# publishes it on the host's loopback only, hence local mode (no login) on 0.0.0.0.
# The lab profile (docker-compose.yml) runs exposed mode behind Caddy instead.
CMD ["servotune", "demo", "--host", "0.0.0.0", "--port", "8000", "--mode", "local"]
