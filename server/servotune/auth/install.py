"""Wiring of the security layer into the app: ``install_security`` and its lifespan part."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path

from fastapi import Depends, FastAPI

from servotune.auth.authz import authorize
from servotune.auth.middleware import SecurityMiddleware
from servotune.auth.passwords import PRODUCT_PASSWORD_COST, PasswordCost
from servotune.auth.security import SecurityConfig, SecurityState, check_exposed_startup
from servotune.auth.store import AuthStore
from servotune.auth.ws_auth import recheck_websockets


class InstalledSecurity:
    """Returned by :func:`install_security`; the app's lifespan enters :meth:`running`."""

    def __init__(self, state: SecurityState) -> None:
        self.state = state

    @contextlib.asynccontextmanager
    async def running(self, app: FastAPI) -> AsyncIterator[SecurityState]:
        """Open the accounts database and the audit writer for the app's lifetime, and
        re-check open websockets against it."""
        self.state.open()
        app.state.audit = self.state.audit
        loop = asyncio.get_running_loop()
        recheck = loop.create_task(recheck_websockets(self.state))
        # Exposed: the hashing workers start now, in the background, so the first login
        # does not wait for a process to start (seconds on a loaded machine). Awaited,
        # never cancelled, before closing: a start cut short would orphan its process.
        passwords = self.state.require_passwords()
        start = loop.create_task(passwords.start()) if self.state.exposed else None
        try:
            yield self.state
        finally:
            recheck.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await recheck
            if start is not None:
                with contextlib.suppress(Exception):
                    await start
            await self.state.close()


def install_security(
    app: FastAPI,
    config: SecurityConfig,
    data_dir: Path,
    *,
    password_cost: PasswordCost = PRODUCT_PASSWORD_COST,
) -> InstalledSecurity:
    """Add the checks to ``app``. Call it BEFORE ``include_router``: the authorization
    dependency is app-wide and FastAPI copies router dependencies when a router is
    included. Raises SecurityConfigError when exposed mode would start unsafe.
    ``password_cost``: see ``SecurityState``."""
    state = SecurityState(config, data_dir, password_cost=password_cost)
    if config.exposed:
        # Fail at creation (before uvicorn binds the port), not in the lifespan.
        store = AuthStore(state.auth_path)
        try:
            check_exposed_startup(config, store)
        finally:
            store.close()
        # The interactive docs are a local-mode convenience; exposed, only the API
        # (behind a login) is served. The schema is in docs/ and at /openapi.json locally.
        hidden = {app.openapi_url, app.docs_url, app.redoc_url, app.swagger_ui_oauth2_redirect_url}
        app.router.routes[:] = [
            r for r in app.router.routes if getattr(r, "path", None) not in hidden
        ]
    app.state.security = state
    app.router.dependencies.append(Depends(authorize))
    app.add_middleware(SecurityMiddleware, security=state)
    return InstalledSecurity(state)
