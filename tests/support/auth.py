"""Shared pieces of the access-control tests: accounts, an exposed app, logging in.

Password hashes are made once per process (Argon2id costs ~0.1 s each by design) and
written straight into each test's fresh ``auth.db``.
"""

from __future__ import annotations

import contextlib
import functools
import re
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
from fastapi import FastAPI
from fastapi.routing import APIRoute, APIWebSocketRoute, iter_route_contexts

from servotune.api.app import AppConfig, create_app
from servotune.auth.passwords import hash_password
from servotune.auth.security import AUTH_DB, SecurityConfig
from servotune.auth.store import AuthStore

PASSWORDS = {
    "alice": "alice-admin-pw-123",
    "olga": "olga-operator-pw-456",
    "oscar": "oscar-operator-pw-789",
    "victor": "victor-viewer-pw-000",
}
ROLES = {"alice": "admin", "olga": "operator", "oscar": "operator", "victor": "viewer"}
LAB = "lab.example"


@functools.cache
def _hash(password: str) -> str:
    return hash_password(password)


def make_accounts(data_dir: Path, names: tuple[str, ...] = tuple(PASSWORDS)) -> None:
    store = AuthStore(data_dir / AUTH_DB)
    try:
        for name in names:
            store.add_user(name, ROLES[name], _hash(PASSWORDS[name]))
    finally:
        store.close()


def exposed_config(data_dir: Path, **security: Any) -> AppConfig:
    """An exposed app behind a TLS proxy on 127.0.0.1, reached as https://lab.example."""
    options: dict[str, Any] = {"host": "0.0.0.0", "proxy": ["127.0.0.1"], "public_hosts": [LAB]}
    options.update(security)
    return AppConfig(
        data_dir=data_dir, web_dir=data_dir / "no-web", security=SecurityConfig(**options)
    )


@contextlib.asynccontextmanager
async def running(app: FastAPI) -> AsyncIterator[FastAPI]:
    async with app.router.lifespan_context(app):
        yield app


def client(
    app: FastAPI, *, base: str = f"https://{LAB}", peer: str = "127.0.0.1"
) -> httpx.AsyncClient:
    transport = httpx.ASGITransport(app=app, client=(peer, 40000))
    return httpx.AsyncClient(transport=transport, base_url=base, timeout=20)


async def login(http: httpx.AsyncClient, user: str, password: str | None = None) -> dict[str, Any]:
    """Log in and make the client send the new session's CSRF token."""
    response = await http.post(
        "/api/auth/login", json={"user": user, "password": password or PASSWORDS[user]}
    )
    assert response.status_code == 200, response.text
    info: dict[str, Any] = response.json()
    http.headers["X-CSRF-Token"] = info["csrf_token"]
    return info


async def exposed_app(data_dir: Path, **security: Any) -> FastAPI:
    make_accounts(data_dir)
    return create_app(exposed_config(data_dir, **security))


def route_calls(app: FastAPI) -> list[tuple[str, str, str]]:
    """(method, template, concrete path) of every HTTP route; path params filled in."""
    calls = []
    for context in iter_route_contexts(app.routes):
        route = context.original_route
        if isinstance(route, APIRoute):
            concrete = re.sub(r"\{[^}]+\}", "x-0", route.path)
            for method in sorted(route.methods - {"HEAD"}):
                calls.append((method, route.path, concrete))
    return calls


def websocket_paths(app: FastAPI) -> list[str]:
    return [
        c.path
        for c in iter_route_contexts(app.routes)
        if isinstance(c.original_route, APIWebSocketRoute)
    ]
