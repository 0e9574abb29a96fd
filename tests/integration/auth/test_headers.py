"""Frames, HSTS and body caps.

A foreign page framed the local dashboard at opacity 0.0001 over a decoy button: one
click sent ``vm``. Every page now forbids framing by another site; a 50 MB JSON body
was parsed whole before its 422: every route now refuses it before any parser.
"""

from __future__ import annotations

from pathlib import Path

import httpx

from servotune.api.app import AppConfig, create_app
from servotune.auth.middleware import MAX_BODY_BYTES, MAX_UPLOAD_BYTES
from servotune.bench.files import MAX_IMPORT_BYTES
from tests.support.auth import client, exposed_app, login, running
from tests.support.servers import local_client, use_csrf_token

PAGES = ["/", "/api/axes", "/api/auth/session", "/openapi.json", "/nope", "/twin/"]


def _framing(response: httpx.Response) -> tuple[str, str]:
    return response.headers.get("x-frame-options", ""), response.headers.get(
        "content-security-policy", ""
    )


async def test_no_page_may_be_framed_by_another_site_in_local_mode(tmp_path: Path) -> None:
    (tmp_path / "web").mkdir()
    (tmp_path / "web" / "index.html").write_text("<html>dashboard</html>")
    app = create_app(AppConfig(data_dir=tmp_path, web_dir=tmp_path / "web", twin=False))
    async with running(app), local_client(app) as http:
        for path in PAGES:
            response = await http.get(path)
            if path.startswith("/twin"):
                # The dashboard frames its own 3D twin; nobody else may.
                assert _framing(response) == ("SAMEORIGIN", "frame-ancestors 'self'"), path
            else:
                assert _framing(response) == ("DENY", "frame-ancestors 'none'"), path
        # Refusals carry them too (a CSRF refusal, a foreign Host).
        refused = await http.post("/api/stop")
        assert refused.status_code == 403
        assert _framing(refused) == ("DENY", "frame-ancestors 'none'")
        foreign = await http.get("/", headers={"Host": "evil.example"})
        assert foreign.status_code == 403
        assert _framing(foreign) == ("DENY", "frame-ancestors 'none'")
        assert "strict-transport-security" not in response.headers  # plain http


async def test_exposed_mode_frames_and_hsts_under_tls(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)  # behind a TLS proxy: X-Forwarded-Proto https
    async with running(app), client(app) as http:
        https = {"X-Forwarded-Proto": "https"}
        for path in ("/", "/api/auth/session", "/api/axes"):
            response = await http.get(path, headers=https)
            assert _framing(response) == ("DENY", "frame-ancestors 'none'"), path
            assert response.headers["strict-transport-security"].startswith("max-age="), path
        plain = await http.get("/api/auth/session", headers={"X-Forwarded-Proto": "http"})
        assert "strict-transport-security" not in plain.headers


async def test_bodies_over_the_cap_are_refused_before_parsing(tmp_path: Path) -> None:
    assert MAX_UPLOAD_BYTES > MAX_IMPORT_BYTES  # the import keeps its own, larger limit
    app = create_app(AppConfig(data_dir=tmp_path, web_dir=tmp_path / "no-web", twin=False))
    async with running(app), local_client(app) as http:
        await use_csrf_token(http)
        big = b'{"command": "stop", "x": "' + b"a" * MAX_BODY_BYTES + b'"}'
        for path in ("/api/axes/any/commands", "/api/stop", "/api/axes/any/console"):
            response = await http.post(
                path, content=big, headers={"Content-Type": "application/json"}
            )
            assert response.status_code == 413, (path, response.text)
        # Without a length (chunked): counted as it arrives, refused at the cap.

        async def chunks():  # type: ignore[no-untyped-def]
            for _ in range(MAX_BODY_BYTES // 65536 + 2):
                yield b" " * 65536

        response = await http.post(
            "/api/axes/any/commands", content=chunks(), headers={"Content-Type": "application/json"}
        )
        assert response.status_code == 413, response.text


async def test_an_exposed_login_body_over_the_cap_is_refused(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    async with running(app), client(app) as http:
        body = b'{"user": "olga", "password": "' + b"p" * MAX_BODY_BYTES + b'"}'
        response = await http.post(
            "/api/auth/login", content=body, headers={"Content-Type": "application/json"}
        )
        assert response.status_code == 413
        await login(http, "olga")
