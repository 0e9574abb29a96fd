"""Password hashing with Argon2id (argon2-cffi), the rule a new password must meet, and
the bounded pool the server hashes in.

Hashing takes tens to hundreds of milliseconds of CPU and 64 MiB on purpose (argon2
computes its 4 lanes in 4 threads). The server never runs it on the event loop nor in
the shared default thread pool: :class:`PasswordWorkers` hashes in worker processes of
their own, with a bounded queue, in two lanes:

- the *prompt* lane, one process at normal priority, takes a check when no other is
  running and none started in the last PROMPT_INTERVAL_S: a login on a quiet server
  is as fast as the machine allows, and this lane never takes more than a fraction of
  a core (0.2 s of CPU per hash here, at most one per second);
- the *low* lane takes every other check: processes in a session (so an autogroup) of
  their own at nice 10, whose hashes take only CPU the rest of the machine leaves.

Why processes in a session of their own and not threads: a hashing thread, even at
nice 10, belongs to the server's scheduling entity (its autogroup or cgroup). On a
loaded machine a server that keeps the cores busy with hashes loses its "sleeper"
credit, and the event loop then waits behind every other runnable process each time it
wakes. Measured on the 2-core VM at a load of 15-20 (tests/integration/auth/test_flood.py,
alternating runs): STOP answered median 219 and 243 ms during a flood of 20 checks
against 59 and 38 ms without it with nice-10 threads, 45 and 44 ms against 41 and
42 ms with a nice-10 process of its own; with a nice-0 process of its own (single
threaded hash) 175 ms against 59 ms. The low lane's price is paid by concurrent logins
on a saturated machine (seconds each): the prompt lane is why a single login is not.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import math
import os
import secrets
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final, TypeVar

from argon2 import PasswordHasher, profiles
from argon2.exceptions import InvalidHashError, VerificationError, VerifyMismatchError
from argon2.low_level import ARGON2_VERSION

from servotune.compute import ComputePool

MIN_PASSWORD_LENGTH = 10
MAX_PASSWORD_LENGTH = 1024


@dataclass(frozen=True, slots=True)
class PasswordCost:
    """The work of one Argon2id hash: ``time_cost`` passes over ``memory_kib`` KiB in
    ``parallelism`` lanes. Algorithm (Argon2id), salt (16 bytes) and digest (32 bytes)
    are argon2-cffi's and never change with the cost."""

    time_cost: int
    memory_kib: int
    parallelism: int

    def hasher(self) -> PasswordHasher:
        return PasswordHasher(
            time_cost=self.time_cost, memory_cost=self.memory_kib, parallelism=self.parallelism
        )


# The cost every password is hashed at: RFC 9106's "second recommended option"
# (Argon2id, t=3, m=64 MiB, p=4), argon2-cffi's own default. No option of the CLI or
# the config file changes it; only code that builds the app (the tests) passes another.
PRODUCT_PASSWORD_COST: Final = PasswordCost(
    time_cost=profiles.RFC_9106_LOW_MEMORY.time_cost,
    memory_kib=profiles.RFC_9106_LOW_MEMORY.memory_cost,
    parallelism=profiles.RFC_9106_LOW_MEMORY.parallelism,
)

# Nice value of the hashing processes (and of their autogroup on Linux).
HASH_NICE = 10

T = TypeVar("T")


class WeakPasswordError(ValueError):
    """A password that is too short or too long; the message says the rule."""


class PasswordWorkersBusyError(RuntimeError):
    """More password checks are waiting than the pool queues: try again later."""

    retry_after_s = 5


def check_password_rule(password: str) -> None:
    """Raise WeakPasswordError unless ``password`` has 10..1024 characters."""
    if not MIN_PASSWORD_LENGTH <= len(password) <= MAX_PASSWORD_LENGTH:
        raise WeakPasswordError(
            f"password must have {MIN_PASSWORD_LENGTH}..{MAX_PASSWORD_LENGTH} characters"
        )


def hash_password(password: str, cost: PasswordCost = PRODUCT_PASSWORD_COST) -> str:
    """The Argon2id hash string (salt and parameters included) of ``password``."""
    return cost.hasher().hash(password)


def verify_password(stored_hash: str, password: str) -> bool:
    """True when ``password`` matches ``stored_hash``; the parameters written in the hash
    decide what the check costs, whatever the cost new hashes are made at."""
    try:
        return PasswordHasher().verify(stored_hash, password)
    except (VerifyMismatchError, VerificationError, InvalidHashError):
        return False


def dummy_hash(cost: PasswordCost) -> str:
    """A well-formed Argon2id hash string at ``cost`` that no password matches.

    Verified against when a user name does not exist, so that a login for an unknown
    name costs what one for a known name costs (no user enumeration by timing). Its salt
    and digest are random bytes: verifying it computes a full hash like any other, and
    making it costs nothing (no hash at import or start-up).
    """
    hasher = cost.hasher()

    def b64(size: int) -> str:
        return base64.b64encode(secrets.token_bytes(size)).decode("ascii").rstrip("=")

    return (
        f"$argon2id$v={ARGON2_VERSION}$m={cost.memory_kib},t={cost.time_cost},"
        f"p={cost.parallelism}${b64(hasher.salt_len)}${b64(hasher.hash_len)}"
    )


def _isolate() -> None:
    """Initializer of a hashing process: a session (and so an autogroup) of its own and
    nice HASH_NICE, so a flood of hashes competes with the machine, not with the server.

    Linux only: elsewhere the worker keeps the server's priority (not measured there).
    """
    if not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(OSError):
        os.setsid()
    # The autogroup's own nice value (``sched(7)``): raising it needs no privilege.
    with (
        contextlib.suppress(OSError),
        open("/proc/self/autogroup", "w", encoding="ascii") as autogroup,
    ):
        autogroup.write(str(HASH_NICE))
    with contextlib.suppress(OSError):
        os.nice(HASH_NICE)


def _own_session() -> None:
    """Initializer of a prompt-lane process: a session of its own (Linux: its own
    autogroup), so even it does not count as the server's own work."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError):
            os.setsid()


def default_workers() -> int:
    """Low-lane processes: one per two cores (at least one)."""
    return max(1, (os.cpu_count() or 1) // 2)


PROMPT_INTERVAL_S = 1.0


class PasswordWorkers:
    """Argon2id hashing and verification in worker processes of their own (bounded).

    Two lanes (see the module doc). At most ``max_waiting`` calls wait beyond the ones
    running; a call beyond that raises :class:`PasswordWorkersBusyError` at once (the
    route answers 429 with ``Retry-After``): a flood costs a queue of bounded length,
    never the memory and CPU of an unbounded one. ``checks`` counts verifications
    started. The processes start on :meth:`start` or on the first call
    (``servotune.compute.ComputePool``). New hashes are made at ``cost``; a check costs
    what its stored hash says, and a check for an unknown user what ``cost`` says.
    """

    def __init__(
        self,
        workers: int | None = None,
        max_waiting: int = 32,
        clock: Callable[[], float] = time.monotonic,
        cost: PasswordCost = PRODUCT_PASSWORD_COST,
    ) -> None:
        self.cost = cost
        self._dummy_hash = dummy_hash(cost)
        self.workers = workers or default_workers()
        self.max_waiting = max_waiting
        self.checks = 0
        self.in_flight = 0
        self.prompt_calls = 0
        self.low_calls = 0
        self._clock = clock
        self._prompt_busy = False
        self._prompt_next_s = -math.inf
        preload = ("servotune.auth.passwords",)
        self._prompt = ComputePool(preload=preload, workers=1, initializer=_own_session)
        self._low = ComputePool(preload=preload, workers=self.workers, initializer=_isolate)

    async def start(self) -> None:
        """Start the workers now, so the first login does not wait for them."""
        await asyncio.gather(self._prompt.start(), self._low.start())

    async def verify(self, stored_hash: str | None, password: str) -> bool:
        """``verify_password`` in a worker (see the class doc for the bound).

        ``stored_hash`` None (no such user) verifies a dummy hash at ``cost``: the same
        work, and False."""
        self._admit()
        self.checks += 1
        matches = await self._run(verify_password, stored_hash or self._dummy_hash, password)
        return matches and stored_hash is not None

    async def hash(self, password: str) -> str:
        """``hash_password`` at ``cost``, in a worker."""
        self._admit()
        return await self._run(hash_password, password, self.cost)

    def _admit(self) -> None:
        if self.in_flight >= 1 + self.workers + self.max_waiting:
            raise PasswordWorkersBusyError("too many password checks at once: try again shortly")

    async def _run(self, fn: Callable[..., T], *args: str | PasswordCost) -> T:
        now = self._clock()
        prompt = not self._prompt_busy and now >= self._prompt_next_s
        self.in_flight += 1
        try:
            if prompt:
                self._prompt_busy = True
                self._prompt_next_s = now + PROMPT_INTERVAL_S
                self.prompt_calls += 1
                try:
                    return await self._prompt.run(fn, *args)
                finally:
                    self._prompt_busy = False
            self.low_calls += 1
            return await self._low.run(fn, *args)
        finally:
            self.in_flight -= 1

    async def close(self) -> None:
        """Stop the workers once the hashes running have ended."""
        await asyncio.gather(self._prompt.close(), self._low.close())
