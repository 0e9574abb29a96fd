"""Shared pieces of the access-control tests: accounts, an exposed app, logging in.

Password cost: the product hashes at RFC 9106's cost (``PRODUCT_PASSWORD_COST``,
0.1-0.2 s of CPU and 64 MiB a hash, on purpose). Tests use ``TEST_PASSWORD_COST``, the
same algorithm and hash format at the smallest cost, both for the accounts they write
(``make_accounts``) and for the apps they build (``AppConfig.password_cost``), because
a check costs what its stored hash says and an unknown user's what the app's cost says.
The tests whose point is the real cost (a login flood against STOP, concurrent guesses
against the throttle) pass ``PRODUCT_PASSWORD_COST`` to both.

Hashes are made once per process and cost, and written straight into each test's
fresh ``auth.db``.
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
from servotune.auth.passwords import PasswordCost, hash_password
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

# Argon2id as the product's (same type, version, salt and digest lengths), at the least
# time and memory argon2 allows (t=1, 8 KiB, one lane): microseconds a hash.
TEST_PASSWORD_COST = PasswordCost(time_cost=1, memory_kib=8, parallelism=1)


@functools.cache
def _hash(password: str, cost: PasswordCost) -> str:
    return hash_password(password, cost)


def make_accounts(
    data_dir: Path,
    names: tuple[str, ...] = tuple(PASSWORDS),
    *,
    cost: PasswordCost = TEST_PASSWORD_COST,
) -> None:
    """The accounts of ``names`` (``PASSWORDS``, ``ROLES``), hashed at ``cost``."""
    store = AuthStore(data_dir / AUTH_DB)
    try:
        for name in names:
            store.add_user(name, ROLES[name], _hash(PASSWORDS[name], cost))
    finally:
        store.close()


def exposed_config(
    data_dir: Path, *, password_cost: PasswordCost = TEST_PASSWORD_COST, **security: Any
) -> AppConfig:
    """An exposed app behind a TLS proxy on 127.0.0.1, reached as https://lab.example."""
    options: dict[str, Any] = {"host": "0.0.0.0", "proxy": ["127.0.0.1"], "public_hosts": [LAB]}
    options.update(security)
    return AppConfig(
        data_dir=data_dir,
        web_dir=data_dir / "no-web",
        security=SecurityConfig(**options),
        password_cost=password_cost,
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


async def exposed_app(
    data_dir: Path, *, password_cost: PasswordCost = TEST_PASSWORD_COST, **security: Any
) -> FastAPI:
    """``make_accounts`` and ``exposed_config``, both at ``password_cost``."""
    make_accounts(data_dir, cost=password_cost)
    return create_app(exposed_config(data_dir, password_cost=password_cost, **security))


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
