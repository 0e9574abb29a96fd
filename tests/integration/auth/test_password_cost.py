"""The password cost: the product hashes at RFC 9106's; code that builds the app (the
tests) may pass another, and then new hashes and the unknown-user check use it."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
from argon2 import Type, extract_parameters, profiles

from servotune.api.app import AppConfig, create_app
from servotune.auth.passwords import (
    PRODUCT_PASSWORD_COST,
    PasswordCost,
    PasswordWorkers,
    dummy_hash,
    hash_password,
    verify_password,
)
from servotune.auth.security import AUTH_DB, SecurityConfig
from servotune.auth.store import AuthStore
from servotune.cli import main
from tests.support.auth import LAB, TEST_PASSWORD_COST, client, login, make_accounts, running

# RFC 9106, section 4, the second recommended option: Argon2id, t=3, m=64 MiB, p=4
# (written out here, not taken from argon2-cffi, so a change of its profile shows).
# Each hash also carries the version (0x13) and the salt and digest lengths (16 and
# 32 bytes), whatever its cost.
RFC_9106_SECOND = (Type.ID, 19, 3, 64 * 1024, 4, 16, 32)


def cost_of(stored: str) -> tuple[object, ...]:
    """What a stored hash says: type, version, t, m (KiB), p, salt and digest bytes."""
    p = extract_parameters(stored)
    return (p.type, p.version, p.time_cost, p.memory_cost, p.parallelism, p.salt_len, p.hash_len)


def expected(cost: PasswordCost) -> tuple[object, ...]:
    return (Type.ID, 19, cost.time_cost, cost.memory_kib, cost.parallelism, 16, 32)


def stored_hash(data_dir: Path, user: str) -> str:
    store = AuthStore(data_dir / AUTH_DB)
    try:
        stored = store.password_hash(user)
    finally:
        store.close()
    assert stored is not None
    return stored


def test_the_product_cost_is_rfc_9106s_and_the_default_of_every_app() -> None:
    assert expected(PRODUCT_PASSWORD_COST) == RFC_9106_SECOND
    low_memory = profiles.RFC_9106_LOW_MEMORY  # argon2-cffi's name for the same option
    assert (
        low_memory.type,
        low_memory.version,
        low_memory.time_cost,
        low_memory.memory_cost,
        low_memory.parallelism,
        low_memory.salt_len,
        low_memory.hash_len,
    ) == RFC_9106_SECOND
    assert AppConfig().password_cost == PRODUCT_PASSWORD_COST
    assert PasswordWorkers().cost == PRODUCT_PASSWORD_COST


@pytest.mark.parametrize("injected", [None, TEST_PASSWORD_COST], ids=["product", "injected"])
async def test_an_apps_new_passwords_are_hashed_at_its_cost(
    tmp_path: Path, injected: PasswordCost | None
) -> None:
    """A user created through the API and a changed password are hashed at the app's cost
    (the product's when nothing is passed), and the new password logs in."""
    make_accounts(tmp_path, ("alice",))
    security = SecurityConfig(host="0.0.0.0", proxy=["127.0.0.1"], public_hosts=[LAB])
    config = AppConfig(data_dir=tmp_path, web_dir=tmp_path / "no-web", security=security)
    if injected is not None:
        config.password_cost = injected
    cost = injected or PRODUCT_PASSWORD_COST
    app = create_app(config)
    async with running(app), client(app) as admin, client(app) as nina:
        assert app.state.security.passwords.cost == cost
        await login(admin, "alice")
        user = {"name": "nina", "role": "viewer", "password": "nina-first-pw-1"}
        assert (await admin.post("/api/users", json=user)).status_code == 201
        assert cost_of(stored_hash(tmp_path, "nina")) == expected(cost)
        await login(nina, "nina", "nina-first-pw-1")
        change = {"current_password": "nina-first-pw-1", "new_password": "nina-second-pw-2"}
        assert (await nina.post("/api/auth/password", json=change)).status_code == 204
        assert cost_of(stored_hash(tmp_path, "nina")) == expected(cost)


def test_the_cli_hashes_at_the_product_cost(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``servotune users add`` has no cost option: its hashes are the product's."""
    monkeypatch.setattr("sys.stdin", io.StringIO("correct horse battery staple\n"))
    argv = ["users", "add", "alice", "--role", "admin", "--data-dir", str(tmp_path)]
    assert main([*argv, "--password-stdin"]) == 0
    stored = stored_hash(tmp_path, "alice")
    assert cost_of(stored) == RFC_9106_SECOND
    assert verify_password(stored, "correct horse battery staple")


@pytest.mark.parametrize(
    "cost", [PRODUCT_PASSWORD_COST, TEST_PASSWORD_COST], ids=["product", "test"]
)
def test_the_unknown_user_hash_costs_what_a_real_one_does_and_matches_nothing(
    cost: PasswordCost,
) -> None:
    """The hash an unknown name is checked against: a well-formed Argon2id hash at the
    cost given (so the check does the same work as a real one) that no password matches;
    a new one each time (random salt and digest)."""
    dummy = dummy_hash(cost)
    assert cost_of(dummy) == expected(cost)
    assert cost_of(dummy) == cost_of(hash_password("x", cost))
    for guess in ("", "servotune-no-such-user", "correct horse battery staple"):
        assert not verify_password(dummy, guess)
    assert dummy_hash(cost) != dummy


async def test_the_workers_refuse_an_unknown_user_and_hash_at_their_cost() -> None:
    """An unknown name costs one check, like a known one, and is refused; new hashes
    are at the workers' cost."""
    workers = PasswordWorkers(workers=1, cost=TEST_PASSWORD_COST)
    try:
        assert not await workers.verify(None, "anything-at-all")
        known = await workers.hash("the-right-password")
        assert cost_of(known) == expected(TEST_PASSWORD_COST)
        assert await workers.verify(known, "the-right-password")
        assert not await workers.verify(known, "a-wrong-password")
        assert workers.checks == 3
    finally:
        await workers.close()
