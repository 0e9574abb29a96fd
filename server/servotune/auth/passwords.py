"""Password hashing with Argon2id (argon2-cffi), the rule a new password must meet, and
the bounded pool the server hashes in.

Hashing takes tens to hundreds of milliseconds of CPU and 64 MiB on purpose (argon2-cffi
releases the interpreter lock meanwhile and computes the 4 lanes in 4 threads). The
server never runs it on the event loop nor in the shared default thread pool:
:class:`PasswordWorkers` is a pool of its own, of few threads at a lower CPU priority,
with a bounded queue. A login flood then queues behind itself only, and the event loop
(STOP, the dead-man, the links) takes the CPU first.

Measured (tests/test_auth_flood.py, 2-core VM at a load of 15-18, 100 concurrent
logins from one address, 20 of them checked): STOP answered median 55-65 ms during
the flood against 44 ms without it, with nice-10 threads. Hashing in a worker process
in a session (autogroup) of its own at nice 10 gave 38-62 ms, but a login then took
6-11 s on that machine instead of about 1 s, and the first one waited for the
process to start: threads it is.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import os
import sys
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError, VerifyMismatchError

MIN_PASSWORD_LENGTH = 10
MAX_PASSWORD_LENGTH = 1024

# argon2-cffi's defaults are RFC 9106's "second recommended option" (Argon2id,
# t=3, m=64 MiB, p=4), kept as they are.
_HASHER = PasswordHasher()

# Verified against when the user name does not exist, so a login for an unknown name
# costs as long as one for a known name (no user enumeration by timing).
_DUMMY_HASH = _HASHER.hash("servotune-no-such-user")

# Nice value of the hashing threads (Linux: per thread).
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


def hash_password(password: str) -> str:
    """The Argon2id hash string (salt and parameters included) of ``password``."""
    return _HASHER.hash(password)


def verify_password(stored_hash: str | None, password: str) -> bool:
    """True when ``password`` matches; ``stored_hash`` None verifies a dummy (same cost)."""
    try:
        return _HASHER.verify(stored_hash or _DUMMY_HASH, password) and stored_hash is not None
    except (VerifyMismatchError, VerificationError, InvalidHashError):
        return False


def _lower_priority() -> None:
    """Initializer of a hashing thread: nice HASH_NICE for this thread only (Linux keeps
    a nice value per thread, and argon2's lane threads inherit it). Elsewhere the same
    call would renice the whole process, so nothing is done there."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), HASH_NICE)


def default_workers() -> int:
    """One hashing thread per two cores (at least one): argon2 computes its 4 lanes in
    threads of its own, so one hash already uses every core of a small machine."""
    return max(1, (os.cpu_count() or 1) // 2)


class PasswordWorkers:
    """Argon2id hashing and verification in a bounded pool of its own.

    ``workers`` threads hash; at most ``max_waiting`` further calls wait for one, and a
    call beyond that raises :class:`PasswordWorkersBusyError` at once (the route answers
    429 with ``Retry-After``): a flood costs a queue of bounded length, never the
    memory and CPU of an unbounded one. ``checks`` counts verifications started.
    """

    def __init__(self, workers: int | None = None, max_waiting: int = 32) -> None:
        self.workers = workers or default_workers()
        self.max_waiting = max_waiting
        self.checks = 0
        self.in_flight = 0
        self._pool = ThreadPoolExecutor(
            max_workers=self.workers,
            thread_name_prefix="servotune-argon2",
            initializer=_lower_priority,
        )

    async def verify(self, stored_hash: str | None, password: str) -> bool:
        """``verify_password`` in the pool (see the class doc for the bound)."""
        self._admit()
        self.checks += 1
        return await self._run(functools.partial(verify_password, stored_hash, password))

    async def hash(self, password: str) -> str:
        """``hash_password`` in the pool."""
        self._admit()
        return await self._run(functools.partial(hash_password, password))

    def _admit(self) -> None:
        if self.in_flight >= self.workers + self.max_waiting:
            raise PasswordWorkersBusyError("too many password checks at once: try again shortly")

    async def _run(self, job: Callable[[], T]) -> T:
        self.in_flight += 1
        try:
            return await asyncio.get_running_loop().run_in_executor(self._pool, job)
        finally:
            self.in_flight -= 1

    async def close(self) -> None:
        """Drop queued calls; wait (in a thread) for the hashes running to end."""
        await asyncio.to_thread(self._pool.shutdown, wait=True, cancel_futures=True)
