"""Access control over HTTP, tested as an attacker and as colleagues with the wrong role.

The route lists are generated from the app's own route table, so a route added later
is attacked too (and a route without a declared permission fails the first test).
"""

from __future__ import annotations

import asyncio
import base64
import sqlite3
import time
from pathlib import Path

import pytest
from fastapi.routing import APIRoute, APIWebSocketRoute, iter_route_contexts
from starlette.routing import Mount, Route

from servotune.api.app import AppConfig, create_app
from servotune.auth.passwords import PRODUCT_PASSWORD_COST
from servotune.auth.permissions import ROLES
from servotune.auth.routes_table import COMMAND, CONSOLE_LINE, PUBLIC, ROUTE_PERMISSIONS
from servotune.auth.security import AUTH_DB, SecurityConfig, SecurityConfigError
from tests.support.auth import (
    LAB,
    PASSWORDS,
    TEST_PASSWORD_COST,
    client,
    exposed_app,
    exposed_config,
    login,
    make_accounts,
    route_calls,
    running,
)

# Starlette routes FastAPI adds itself (local mode only; exposed mode removes them).
DOC_ROUTES = {"/openapi.json", "/docs", "/docs/oauth2-redirect", "/redoc"}


def _bodies(template: str) -> dict[str, object] | None:
    """A well-formed body where the route has one, so validation cannot answer first."""
    if template.endswith("/commands"):
        return {"command": "move_absolute", "position": 10}
    return {}


# --- the table ----------------------------------------------------------------------


def test_every_route_declares_a_permission(tmp_path: Path) -> None:
    app = create_app(AppConfig(data_dir=tmp_path, web_dir=tmp_path / "no-web"))
    declared = set()
    for context in iter_route_contexts(app.routes):
        route = context.original_route
        # The dependency looks routes up by the matched route's own path: a router
        # with a prefix would make that differ from the served path.
        assert getattr(route, "path", context.path) == context.path, context.path
        if isinstance(route, APIRoute):
            for method in route.methods - {"HEAD"}:
                key = (method, route.path)
                assert key in ROUTE_PERMISSIONS, f"{key} has no entry in ROUTE_PERMISSIONS"
                declared.add(key)
        elif isinstance(route, APIWebSocketRoute):
            assert ("WS", route.path) in ROUTE_PERMISSIONS, f"websocket {route.path}"
            declared.add(("WS", route.path))
        elif isinstance(route, Route):
            assert route.path in DOC_ROUTES, f"unexpected non-API route {route.path}"
        else:
            assert isinstance(route, Mount) and route.path == "", route
    assert set(ROUTE_PERMISSIONS) == declared, "stale entries in ROUTE_PERMISSIONS"
    all_permissions = ROLES["admin"]
    for permission in ROUTE_PERMISSIONS.values():
        assert permission in all_permissions | {PUBLIC, COMMAND, CONSOLE_LINE}


async def test_a_route_added_without_a_permission_answers_500(tmp_path: Path) -> None:
    app = create_app(AppConfig(data_dir=tmp_path, web_dir=tmp_path / "no-web"))

    @app.post("/api/new-feature")
    async def new_feature() -> dict[str, str]:
        return {"moved": "yes"}

    async with running(app), client(app, base="http://localhost") as http:
        token = (await http.get("/api/auth/session")).json()["csrf_token"]
        response = await http.post("/api/new-feature", headers={"X-CSRF-Token": token})
        assert response.status_code == 500
        assert "declares no permission" in response.json()["detail"]


# --- strangers ----------------------------------------------------------------------


async def test_exposed_every_route_without_credentials_is_401(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    async with running(app), client(app) as http:
        # Even with a valid anonymous CSRF token the auth layer must refuse.
        http.headers["X-CSRF-Token"] = (await http.get("/api/auth/session")).json()["csrf_token"]
        calls = route_calls(app)
        assert len(calls) > 40
        for method, template, path in calls:
            if ROUTE_PERMISSIONS[(method, template)] == PUBLIC:
                continue
            body = _bodies(template) if method in ("POST", "PUT", "PATCH") else None
            response = await http.request(method, path, json=body)
            assert response.status_code == 401, (method, template, response.text)
        # The interactive docs and the schema are not served in exposed mode.
        for path in DOC_ROUTES:
            assert (await http.get(path)).status_code == 404, path


async def test_exposed_telemetry_needs_a_login(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    async with running(app), client(app) as http:
        assert (await http.get("/api/axes")).status_code == 401
        await login(http, "victor")
        assert (await http.get("/api/axes")).status_code == 200


# --- colleagues with a smaller role -----------------------------------------------


@pytest.mark.parametrize("user", ["victor", "olga"])
async def test_role_cannot_call_what_it_lacks(tmp_path: Path, user: str) -> None:
    app = await exposed_app(tmp_path)
    async with running(app), client(app) as http:
        info = await login(http, user)
        allowed = set(info["permissions"])
        assert allowed == set(ROLES[info["role"]])
        tried = 0
        for method, template, path in route_calls(app):
            needed = ROUTE_PERMISSIONS[(method, template)]
            if needed == COMMAND:
                needed = "move"  # a move command (stop is tested below)
            elif needed == CONSOLE_LINE:
                # and then what the line is (tests/integration/auth/test_console.py)
                needed = "console"
            if needed == PUBLIC or needed in allowed:
                continue
            body = _bodies(template) if method in ("POST", "PUT", "PATCH") else None
            response = await http.request(method, path, json=body)
            assert response.status_code == 403, (user, method, template, response.text)
            tried += 1
        assert tried >= (20 if user == "victor" else 8)


async def test_viewer_may_stop(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    async with running(app), client(app) as http:
        await login(http, "victor")
        assert (await http.post("/api/stop")).status_code == 200
        # Stop-group commands pass the permission check (the unknown axis is then 404).
        response = await http.post("/api/axes/x-0/commands", json={"command": "stop"})
        assert response.status_code in (403, 404)


async def test_refusals_are_audited(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    async with running(app), client(app) as http:
        await login(http, "victor")
        assert (await http.patch("/api/axes/x-0/params", json={"kp": 1})).status_code == 403
        app.state.audit.flush()
        rows = app.state.audit.query(__import__("servotune.auth.audit").auth.audit.AuditQuery())
        refused = [r for r in rows if r["result"] == "refused" and r["who"] == "victor"]
        assert refused and "tune" in refused[0]["detail"]


# --- CSRF and cross-site requests ---------------------------------------------------


async def test_cookie_mutation_needs_the_csrf_token(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    async with running(app), client(app) as http:
        await login(http, "olga")
        token = http.headers.pop("X-CSRF-Token")
        assert (await http.post("/api/stop")).status_code == 403
        wrong = {"X-CSRF-Token": "0" * 64}
        assert (await http.post("/api/stop", headers=wrong)).status_code == 403
        ok = {"X-CSRF-Token": token}
        text = {**ok, "Content-Type": "text/plain"}
        response = await http.post("/api/stop", content=b'{"x":1}', headers=text)
        assert response.status_code == 415
        form = {**ok, "Content-Type": "application/x-www-form-urlencoded"}
        assert (await http.post("/api/stop", content=b"a=1", headers=form)).status_code == 415
        cross = {**ok, "Sec-Fetch-Site": "cross-site"}
        assert (await http.post("/api/stop", headers=cross)).status_code == 403
        same_site = {**ok, "Sec-Fetch-Site": "same-site"}
        assert (await http.post("/api/stop", headers=same_site)).status_code == 403
        for origin in ("https://evil.example", "null", f"http://{LAB}"):
            response = await http.post("/api/stop", headers={**ok, "Origin": origin})
            assert response.status_code == 403, origin
        good = {**ok, "Origin": f"https://{LAB}", "Sec-Fetch-Site": "same-origin"}
        assert (await http.post("/api/stop", headers=good)).status_code == 200
        # No CORS: a preflight gets nothing that would let another origin read answers.
        preflight = await http.options(
            "/api/stop",
            headers={"Origin": "https://evil.example", "Access-Control-Request-Method": "POST"},
        )
        assert not any(k.lower().startswith("access-control") for k in preflight.headers)


async def test_only_a_bearer_authorization_skips_the_csrf_check(tmp_path: Path) -> None:
    """Pinned rule: a browser never attaches ``Authorization: Bearer`` on its
    own, so a bearer call needs no CSRF token; it does attach ``Basic`` credentials it
    has cached (a proxy's, a page's), so a ``Basic`` header proves nothing and the
    logged-in session still needs its token."""
    app = await exposed_app(tmp_path)
    async with running(app), client(app) as admin, client(app) as olga:
        await login(admin, "alice")
        created = await admin.post("/api/auth/tokens", json={"name": "bench", "user": "olga"})
        secret = created.json()["token"]
        await login(olga, "olga")
        olga.headers.pop("X-CSRF-Token")
        basic = "Basic " + base64.b64encode(b"olga:whatever").decode()
        for header in (basic, "basic b2xnYTp4", "Bearerstk_x", "Digest username=olga"):
            response = await olga.post("/api/stop", headers={"Authorization": header})
            assert response.status_code == 403, (header, response.text)
            assert "CSRF" in response.json()["detail"], header
        for header in (f"Bearer {secret}", f"bearer {secret}"):
            response = await olga.post("/api/stop", headers={"Authorization": header})
            assert response.status_code == 200, (header, response.text)


async def test_csrf_token_of_another_session_does_not_work(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    async with running(app), client(app) as olga, client(app) as oscar:
        await login(olga, "olga")
        await login(oscar, "oscar")
        headers = {"X-CSRF-Token": oscar.headers["X-CSRF-Token"]}
        assert (await olga.post("/api/stop", headers=headers)).status_code == 403


async def test_local_mode_csrf_host_and_cors(tmp_path: Path) -> None:
    app = create_app(AppConfig(data_dir=tmp_path, web_dir=tmp_path / "no-web"))
    async with running(app), client(app, base="http://127.0.0.1:8000") as http:
        session = (await http.get("/api/auth/session")).json()
        assert session["mode"] == "local" and session["role"] == "admin"
        assert (await http.post("/api/stop")).status_code == 403
        headers = {"X-CSRF-Token": session["csrf_token"]}
        assert (await http.post("/api/stop", headers=headers)).status_code == 200
        cross = {**headers, "Origin": "http://evil.example"}
        assert (await http.post("/api/stop", headers=cross)).status_code == 403
        # DNS rebinding: the page's own name reaches 127.0.0.1 and is refused.
        rebound = {**headers, "Host": "evil.example:8000"}
        assert (await http.get("/api/axes", headers={"Host": "evil.example"})).status_code == 403
        assert (await http.post("/api/stop", headers=rebound)).status_code == 403
        for name in ("localhost:8000", "[::1]:8000", "127.0.0.1"):
            assert (await http.get("/api/axes", headers={"Host": name})).status_code == 200
        # The docs stay available locally.
        assert (await http.get("/openapi.json")).status_code == 200


async def test_exposed_foreign_host_is_refused(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    async with running(app), client(app) as http:
        await login(http, "alice")
        response = await http.get("/api/axes", headers={"Host": "evil.example"})
        assert response.status_code == 403


# --- proxies -------------------------------------------------------------------------


async def test_forwarded_headers_only_from_the_proxy(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    async with running(app):
        # A peer that is not the proxy: refused, whatever it claims to be.
        async with client(app, peer="203.0.113.9") as direct:
            spoof = {"X-Forwarded-For": "127.0.0.1", "X-Forwarded-Proto": "https"}
            response = await direct.post(
                "/api/auth/login", json={"user": "alice", "password": "x"}, headers=spoof
            )
            assert response.status_code == 403
        # Through the proxy: the right-most forwarded address is the client's.
        async with client(app) as proxied:
            headers = {"X-Forwarded-For": "10.66.66.66, 198.51.100.7"}
            response = await proxied.post(
                "/api/auth/login", json={"user": "alice", "password": "wrong-pw"}, headers=headers
            )
            assert response.status_code == 401
        app.state.audit.flush()
        from servotune.auth.audit import AuditQuery

        failed = app.state.audit.query(AuditQuery(action="login"))
        assert failed[0]["address"] == "198.51.100.7"


async def test_forwarded_headers_ignored_without_proxy(tmp_path: Path) -> None:
    make_accounts(tmp_path)
    app = create_app(
        AppConfig(
            data_dir=tmp_path,
            web_dir=tmp_path / "no-web",
            security=SecurityConfig(
                mode="exposed", tls_cert=tmp_path / "c", tls_key=tmp_path / "k"
            ),
            password_cost=TEST_PASSWORD_COST,
        )
    )
    async with running(app), client(app, base="https://127.0.0.1", peer="203.0.113.9") as http:
        response = await http.post(
            "/api/auth/login",
            json={"user": "alice", "password": "wrong-pw"},
            headers={"X-Forwarded-For": "127.0.0.1"},
        )
        assert response.status_code == 401
        app.state.audit.flush()
        from servotune.auth.audit import AuditQuery

        assert app.state.audit.query(AuditQuery(action="login"))[0]["address"] == "203.0.113.9"


# --- sessions -----------------------------------------------------------------------


async def test_cookie_flags_and_rotation(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    async with running(app), client(app) as http:
        response = await http.post(
            "/api/auth/login", json={"user": "olga", "password": PASSWORDS["olga"]}
        )
        cookie = response.headers["set-cookie"]
        assert "servotune_session=" in cookie
        flags = {part.strip().lower() for part in cookie.split(";")}
        assert {"httponly", "samesite=strict", "secure", "path=/"} <= flags
        first = http.cookies["servotune_session"]
        await login(http, "olga")
        second = http.cookies["servotune_session"]
        assert first != second
        # The old session ended at the second login (rotation, no fixation).
        async with client(app) as stale:
            stale.cookies.set("servotune_session", first, domain=LAB)
            assert (await stale.get("/api/auth/session")).json()["user"] is None
            assert (await stale.get("/api/axes")).status_code == 401
        # The stored id is a digest, never the cookie.
        db = sqlite3.connect(tmp_path / AUTH_DB)
        stored = [row[0] for row in db.execute("SELECT digest FROM sessions")]
        db.close()
        assert second not in stored and len(stored) == 1


async def test_no_secure_flag_on_plain_http_through_proxy(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    async with running(app), client(app, base=f"http://{LAB}") as http:
        response = await http.post(
            "/api/auth/login",
            json={"user": "olga", "password": PASSWORDS["olga"]},
            headers={"X-Forwarded-Proto": "https"},
        )
        assert "secure" in response.headers["set-cookie"].lower()
        response = await http.post(
            "/api/auth/login", json={"user": "olga", "password": PASSWORDS["olga"]}
        )
        assert "secure" not in response.headers["set-cookie"].lower()


async def test_logout_idle_and_lifetime_end_sessions(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    async with running(app), client(app) as http:
        await login(http, "olga")
        assert (await http.post("/api/auth/logout")).status_code == 204
        assert (await http.get("/api/axes")).status_code == 401
        for column in ("last_seen_s", "created_s"):
            await login(http, "olga")
            db = sqlite3.connect(tmp_path / AUTH_DB)
            with db:
                db.execute(f"UPDATE sessions SET {column} = ?", (time.time() - 13 * 3600,))
            db.close()
            assert (await http.get("/api/axes")).status_code == 401, column


async def test_password_change_and_role_change_end_sessions(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    async with running(app), client(app) as admin, client(app) as olga:
        await login(admin, "alice")
        await login(olga, "olga")
        response = await admin.patch("/api/users/olga", json={"role": "viewer"})
        assert response.status_code == 200
        assert (await olga.get("/api/axes")).status_code == 401
        info = await login(olga, "olga")
        assert info["role"] == "viewer"
        response = await olga.post(
            "/api/auth/password",
            json={"current_password": PASSWORDS["olga"], "new_password": "a-new-long-password"},
        )
        assert response.status_code == 204
        assert (await olga.get("/api/axes")).status_code == 401
        await login(olga, "olga", "a-new-long-password")


async def test_last_admin_stays(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    async with running(app), client(app) as admin:
        await login(admin, "alice")
        assert (await admin.patch("/api/users/alice", json={"role": "viewer"})).status_code == 409
        assert (await admin.delete("/api/users/alice")).status_code == 409


async def test_dangerous_action_asks_the_password_again(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    async with running(app), client(app) as admin:
        await login(admin, "alice")
        new_user = {"name": "newbie", "role": "viewer", "password": "newbie-password-1"}
        assert (await admin.post("/api/users", json=new_user)).status_code == 201
        db = sqlite3.connect(tmp_path / AUTH_DB)
        with db:
            db.execute("UPDATE sessions SET password_s = ?", (time.time() - 301,))
        db.close()
        again = {**new_user, "name": "newbie2"}
        response = await admin.post("/api/users", json=again)
        assert response.status_code == 401 and "password again" in response.json()["detail"]
        bad = await admin.post("/api/auth/reauth", json={"password": "not-it"})
        assert bad.status_code == 401
        ok = await admin.post("/api/auth/reauth", json={"password": PASSWORDS["alice"]})
        assert ok.status_code == 204
        assert (await admin.post("/api/users", json=again)).status_code == 201


# --- login throttling -------------------------------------------------------------


async def test_login_throttling_per_account_and_address_then_recovers(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    now = [1000.0]
    app.state.security.throttle.clock = lambda: now[0]
    attacker = {"X-Forwarded-For": "203.0.113.9"}
    async with running(app), client(app) as http:
        for _ in range(5):
            response = await http.post(
                "/api/auth/login",
                json={"user": "olga", "password": "guess-guess"},
                headers=attacker,
            )
            assert response.status_code == 401
        right = {"user": "olga", "password": PASSWORDS["olga"]}
        response = await http.post("/api/auth/login", json=right, headers=attacker)
        assert response.status_code == 429
        assert int(response.headers["retry-after"]) > 0
        # Another account from the same place is not blocked by olga's counter.
        oscar = {"user": "oscar", "password": PASSWORDS["oscar"]}
        assert (await http.post("/api/auth/login", json=oscar, headers=attacker)).status_code == 200
        # The attacker's failures do not lock olga out from her own address (finding 7:
        # 5 wrong passwords from one address made the right one from another 429).
        own = {"X-Forwarded-For": "192.0.2.1"}
        assert (await http.post("/api/auth/login", json=right, headers=own)).status_code == 200
        now[0] += 301  # not for good: the window passes
        assert (await http.post("/api/auth/login", json=right, headers=attacker)).status_code == 200


async def test_concurrent_guesses_of_one_account_get_the_limit_and_no_more(tmp_path: Path) -> None:
    """Finding 1: 30 concurrent guesses for one account all passed the throttle's check
    (29 x 401 and 1 x 200, the right password being the 20th). The attempt is reserved
    before hashing now: 5 are checked, the rest answer 429 unchecked.

    At the product's password cost: a check that takes real time (0.1-0.3 s, not the
    tests' microseconds) is the window the guesses raced through, so a regression shows
    however the requests are scheduled."""
    app = await exposed_app(tmp_path, password_cost=PRODUCT_PASSWORD_COST)
    async with running(app), client(app) as http:
        passwords = [f"guess-number-{i:02d}" for i in range(30)]
        passwords[19] = PASSWORDS["olga"]
        responses = await asyncio.gather(
            *(http.post("/api/auth/login", json={"user": "olga", "password": p}) for p in passwords)
        )
        statuses = [r.status_code for r in responses]
        assert app.state.security.passwords.checks == 5
        assert statuses.count(429) == 25
        assert statuses.count(401) + statuses.count(200) == 5


def test_throttle_per_address_counts_every_name() -> None:
    from servotune.auth.throttle import LoginThrottle, ThrottledError

    now = [0.0]
    throttle = LoginThrottle(clock=lambda: now[0])
    for i in range(20):
        throttle.begin("198.51.100.7", f"user{i}")  # reserved: counts until it succeeds
    with pytest.raises(ThrottledError):
        throttle.begin("198.51.100.7", "someone-else")
    throttle.begin("198.51.100.8", "someone-else")
    now[0] = 300.0
    throttle.begin("198.51.100.7", "someone-else")


def test_throttle_reserves_before_the_check_and_a_success_gives_it_back() -> None:
    from servotune.auth.throttle import LoginThrottle, ThrottledError

    throttle = LoginThrottle(clock=lambda: 0.0)
    # Five checks in flight at once (none has failed yet): the sixth is refused, which
    # a count of failures made after hashing could not do.
    attempts = [throttle.begin("192.0.2.1", "olga") for _ in range(5)]
    with pytest.raises(ThrottledError):
        throttle.begin("192.0.2.1", "olga")
    throttle.succeeded(attempts[0])  # a right password: its reservation is given back
    throttle.begin("192.0.2.1", "olga")


def test_throttle_a_lockout_from_one_address_does_not_lock_the_owner_out() -> None:
    from servotune.auth.throttle import LoginThrottle, ThrottledError

    now = [0.0]
    throttle = LoginThrottle(clock=lambda: now[0])
    for _ in range(5):
        throttle.begin("203.0.113.9", "olga")  # an attacker's wrong guesses
    with pytest.raises(ThrottledError):
        throttle.begin("203.0.113.9", "olga")
    throttle.succeeded(throttle.begin("192.0.2.1", "olga"))  # olga at her desk
    # Guessing olga from many addresses: 20 untrusted attempts in the window, then
    # a new address waits too, while olga's own (trusted) address is not affected.
    for i in range(15):
        throttle.begin(f"203.0.113.{100 + i}", "olga")
    with pytest.raises(ThrottledError):
        throttle.begin("203.0.113.200", "olga")
    throttle.begin("192.0.2.1", "olga")


# --- API tokens ---------------------------------------------------------------------


async def test_tokens_bearer_role_ceiling_expiry_revocation(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    async with running(app), client(app) as admin, client(app) as script:
        await login(admin, "alice")
        too_high = await admin.post(
            "/api/auth/tokens", json={"name": "x", "user": "victor", "role": "operator"}
        )
        assert too_high.status_code == 422
        created = await admin.post("/api/auth/tokens", json={"name": "bench", "user": "olga"})
        assert created.status_code == 201
        secret = created.json()["token"]
        token_id = created.json()["id"]
        assert created.json()["role"] == "operator"
        listed = (await admin.get("/api/auth/tokens")).json()
        assert secret not in str(listed) and listed[0]["id"] == token_id
        bearer = {"Authorization": f"Bearer {secret}"}
        # A bearer call needs no CSRF token (a browser never attaches it on its own).
        assert (await script.post("/api/stop", headers=bearer)).status_code == 200
        assert (await script.get("/api/users", headers=bearer)).status_code == 403
        # Right id, wrong secret; a truncated token.
        forged = {"Authorization": f"Bearer stk_{token_id}_{'A' * 43}"}
        assert (await script.get("/api/axes", headers=forged)).status_code == 401
        cut = {"Authorization": f"Bearer {secret[:-1]}"}
        assert (await script.get("/api/axes", headers=cut)).status_code == 401
        # Stored as a digest only.
        db = sqlite3.connect(tmp_path / AUTH_DB)
        dump = "\n".join(str(row) for row in db.execute("SELECT * FROM tokens"))
        assert secret.split("_")[-1] not in dump
        with db:
            db.execute("UPDATE tokens SET expires_s = ?", (time.time() - 1,))
        assert (await script.get("/api/axes", headers=bearer)).status_code == 401
        with db:
            db.execute("UPDATE tokens SET expires_s = ?", (time.time() + 3600,))
        db.close()
        assert (await script.get("/api/axes", headers=bearer)).status_code == 200
        assert (await admin.delete(f"/api/auth/tokens/{token_id}")).status_code == 204
        assert (await script.get("/api/axes", headers=bearer)).status_code == 401


async def test_token_above_a_demoted_users_role_stops_working(tmp_path: Path) -> None:
    app = await exposed_app(tmp_path)
    async with running(app), client(app) as admin, client(app) as script:
        await login(admin, "alice")
        secret = (await admin.post("/api/auth/tokens", json={"name": "t", "user": "olga"})).json()[
            "token"
        ]
        await admin.patch("/api/users/olga", json={"role": "viewer"})
        bearer = {"Authorization": f"Bearer {secret}"}
        assert (await script.get("/api/axes", headers=bearer)).status_code == 401


# --- start-up -------------------------------------------------------------------


def test_exposed_mode_refuses_to_start_unsafe(tmp_path: Path) -> None:
    with pytest.raises(SecurityConfigError, match="without TLS"):
        create_app(AppConfig(data_dir=tmp_path, security=SecurityConfig(host="0.0.0.0")))
    with pytest.raises(SecurityConfigError, match="without accounts"):
        create_app(exposed_config(tmp_path))
    with pytest.raises(SecurityConfigError, match="go together"):
        create_app(
            AppConfig(
                data_dir=tmp_path,
                security=SecurityConfig(host="192.0.2.1", tls_cert=tmp_path / "cert.pem"),
            )
        )
    make_accounts(tmp_path, ("alice",))
    create_app(exposed_config(tmp_path))  # accounts + proxy: starts
    # A loopback bind with nothing else stays local mode, no accounts needed.
    local = SecurityConfig(host="127.0.0.1")
    assert not local.exposed
    assert SecurityConfig(host="127.0.0.1", proxy=["127.0.0.1"]).exposed


def test_cli_refuses_exposed_start(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from servotune.cli import main

    with pytest.raises(SystemExit) as exc:
        main(
            ["serve", "--host", "0.0.0.0", "--data-dir", str(tmp_path), "--link", "slap2:/dev/null"]
        )
    assert exc.value.code == 2
    assert "without TLS" in capsys.readouterr().err
