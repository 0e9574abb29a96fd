"""Exposed mode in headless Chromium: login page, user menu, read-only controls, audit page."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import uvicorn
from playwright.async_api import Browser, Page, expect

from servotune.api.app import WEB_DIST, AppConfig, create_app
from servotune.auth.security import SecurityConfig
from servotune.config import LinkSpec
from tests.support.auth import PASSWORDS, TEST_PASSWORD_COST, make_accounts
from tests.support.paths import ARTIFACTS
from tests.support.servers import bound_socket
from tests.support.sim_lines import running_simulator
from tests.support.waiting import wait_for

pytestmark = pytest.mark.browser
# Argon2id makes a login cost ~0.1-0.5 s on purpose; on a loaded machine a login plus
# the page reload can pass Playwright's default 5 s.
expect.set_options(timeout=30_000)


@contextlib.asynccontextmanager
async def exposed_server(tmp_path: Path) -> AsyncIterator[str]:
    with running_simulator([0, 1], tmp_path) as (sim, _bus):
        data_dir = tmp_path / "data"
        make_accounts(data_dir)
        spec = LinkSpec("slap2", sim.path, "line", sim.baud, [0, 1], 512)
        security = SecurityConfig(mode="exposed", proxy=["127.0.0.1"], public_hosts=["127.0.0.1"])
        app = create_app(
            AppConfig(
                links=[spec],
                data_dir=data_dir,
                web_dir=WEB_DIST,
                security=security,
                password_cost=TEST_PASSWORD_COST,
            )
        )
        sock = bound_socket()
        port = sock.getsockname()[1]
        server = uvicorn.Server(
            uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", lifespan="on")
        )
        task = asyncio.create_task(server.serve(sockets=[sock]))
        try:
            await wait_for(lambda: server.started, 20, "the server to start")
            yield f"http://127.0.0.1:{port}"
        finally:
            server.should_exit = True
            await task


async def log_in(page: Page, base: str, user: str, password: str) -> None:
    await page.goto(base)
    await expect(page.get_by_test_id("login-page")).to_be_visible()
    await page.get_by_test_id("login-user").fill(user)
    await page.get_by_test_id("login-password").fill(password)
    await page.get_by_test_id("login-submit").click()


async def test_login_page_viewer_and_admin_audit(
    tmp_path: Path,
    browser: Browser,
) -> None:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    async with exposed_server(tmp_path) as base:
        viewer_context = await browser.new_context(viewport={"width": 1400, "height": 900})
        viewer = await viewer_context.new_page()
        errors: list[str] = []
        viewer.on("pageerror", lambda exc: errors.append(str(exc)))
        # Wrong password: an error, still on the login page, no stream started.
        await log_in(viewer, base, "victor", "not-the-password")
        await expect(viewer.get_by_test_id("login-error")).to_contain_text("wrong")
        await viewer.screenshot(path=str(ARTIFACTS / "auth-login.png"))
        assert await viewer.evaluate("window.__servotune.wsState()") != "open"
        # Right password: the dashboard, as a viewer.
        await viewer.get_by_test_id("login-password").fill(PASSWORDS["victor"])
        await viewer.get_by_test_id("login-submit").click()
        await expect(viewer.get_by_test_id("login-page")).to_have_count(0)
        await expect(viewer.get_by_test_id("user-name")).to_have_text("victor")
        await expect(viewer.get_by_test_id("user-role")).to_have_text("viewer")
        await viewer.wait_for_function("window.__servotune.wsState() === 'open'")
        move = viewer.get_by_test_id("cmd-position_mode")
        await expect(move).to_be_disabled()
        await expect(viewer.get_by_test_id("cmd-stop")).to_be_enabled()
        await expect(viewer.get_by_test_id("stop-all")).to_be_enabled()
        await viewer.get_by_test_id("stop-all").click()
        await expect(viewer.get_by_test_id("stop-note")).to_contain_text("STOPPED")
        await viewer.get_by_test_id("user-menu").click()
        await expect(viewer.get_by_test_id("readonly-note")).to_be_visible()
        await viewer.screenshot(path=str(ARTIFACTS / "auth-viewer.png"))
        # The cookie is HttpOnly: the page's scripts cannot read it.
        assert "servotune_session" not in await viewer.evaluate("document.cookie")
        cookies = await viewer_context.cookies()
        session = next(c for c in cookies if c["name"] == "servotune_session")
        assert session["httpOnly"] and session["sameSite"] == "Strict"

        admin_context = await browser.new_context(viewport={"width": 1400, "height": 900})
        admin = await admin_context.new_page()
        await log_in(admin, base, "alice", PASSWORDS["alice"])
        await expect(admin.get_by_test_id("user-role")).to_have_text("admin")
        await expect(admin.get_by_test_id("cmd-position_mode")).to_be_enabled()
        await admin.get_by_test_id("user-menu").click()
        await admin.get_by_test_id("open-audit").click()
        rows = admin.get_by_test_id("audit-rows")
        await expect(rows).to_contain_text("victor")
        await expect(rows).to_contain_text("POST /api/stop")
        await expect(rows).to_contain_text("failed")
        await admin.screenshot(path=str(ARTIFACTS / "auth-audit.png"))
        # Logging out ends the viewer's session: the next load shows the login page.
        await viewer.get_by_test_id("logout").click()
        await expect(viewer.get_by_test_id("login-page")).to_be_visible()
        assert not errors, errors
        await viewer_context.close()
        await admin_context.close()
