"""Login throttling: how many password checks a place and an account get (429, never for good).

Every password check (login, re-authentication, password change) first *reserves* an
attempt with :meth:`LoginThrottle.begin`, before anything is hashed and without an
``await`` between the check and the count, so concurrent tries cannot all pass the
check before the first failure is counted. A reservation counts as a failure until
:meth:`LoginThrottle.succeeded` takes it back. Over a limit, ``begin`` raises
:class:`ThrottledError` with the seconds until the oldest counted attempt ages out of
the sliding window: a brute force gets a handful of guesses per window, while someone
who mistyped waits minutes, not forever (nothing is stored; a restart clears it).

Limits per WINDOW_S (OctoPrint's are 3/min, 5/10 min, 10/h on failures):

- per account **and** address: 5. Guessing one account from one place. Keyed by both so
  that an attacker elsewhere cannot lock the owner out: 5 wrong passwords from one
  address do not stop the right one from another.
- per address: 20, whatever the account (one place guessing many accounts; a lab's NAT
  is why it is higher than the per-account limit).
- per account from *untrusted* addresses: 20. Guessing one account from many places.
  An address is trusted for an account for TRUST_S after a successful login of that
  account from it, so the owner at their usual desk is not affected by a distributed
  attack; from a new address during one they wait like the attacker.

A success clears the account-and-address counter and takes its own reservation back;
it does not clear the address counter (a guesser with an account of their own must not
reset their budget by logging in to it).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

WINDOW_S = 300.0
PER_ACCOUNT_ADDRESS = 5
PER_ADDRESS = 20
PER_ACCOUNT_UNTRUSTED = 20
TRUST_S = 30 * 86400.0
_MAX_KEYS = 10_000  # bound the memory a scan over random names or addresses can take


class ThrottledError(Exception):
    """Too many attempts: ``retry_after_s`` until the next one may be made."""

    def __init__(self, retry_after_s: float) -> None:
        super().__init__(f"too many failed attempts: try again in {retry_after_s:.0f} s")
        self.retry_after_s = retry_after_s


@dataclass(frozen=True, slots=True)
class Attempt:
    """A reserved password check: the counters it was added to, and when."""

    address: str
    user: str
    keys: tuple[str, ...]
    stamp: float


@dataclass
class LoginThrottle:
    window_s: float = WINDOW_S
    per_account_address: int = PER_ACCOUNT_ADDRESS
    per_address: int = PER_ADDRESS
    per_account_untrusted: int = PER_ACCOUNT_UNTRUSTED
    trust_s: float = TRUST_S
    clock: Callable[[], float] = time.monotonic
    _attempts: dict[str, deque[float]] = field(default_factory=dict)
    _trusted: dict[str, float] = field(default_factory=dict)

    def begin(self, address: str, user: str) -> Attempt:
        """Reserve one password check now, or raise ThrottledError (nothing counted)."""
        now = self.clock()
        if len(self._attempts) > _MAX_KEYS:
            self._prune(now)
        limits = self._limits(address, user, now)
        wait_s = max((self._wait(key, limit, now) for key, limit in limits), default=0.0)
        if wait_s > 0:
            raise ThrottledError(wait_s)
        for key, _ in limits:
            self._attempts.setdefault(key, deque()).append(now)
        return Attempt(address, user, tuple(key for key, _ in limits), now)

    def succeeded(self, attempt: Attempt) -> None:
        """The password was right: take the reservation back, trust the address."""
        self.cancel(attempt)
        self._attempts.pop(_pair(attempt.address, attempt.user), None)
        now = self.clock()
        if len(self._trusted) > _MAX_KEYS:
            self._trusted = {k: t for k, t in self._trusted.items() if now - t < self.trust_s}
            while len(self._trusted) > _MAX_KEYS:
                del self._trusted[min(self._trusted, key=self._trusted.__getitem__)]
        self._trusted[_pair(attempt.address, attempt.user)] = now

    def cancel(self, attempt: Attempt) -> None:
        """The check did not run after all (the hashing pool was full): uncount it."""
        for key in attempt.keys:
            stamps = self._attempts.get(key)
            if stamps is not None and attempt.stamp in stamps:
                stamps.remove(attempt.stamp)

    def retry_after_s(self, address: str, user: str) -> float:
        """0 when an attempt may go ahead now, else the seconds until one may (no count)."""
        now = self.clock()
        return max(
            (self._wait(key, limit, now) for key, limit in self._limits(address, user, now)),
            default=0.0,
        )

    def _limits(self, address: str, user: str, now: float) -> list[tuple[str, int]]:
        limits = [
            (_pair(address, user), self.per_account_address),
            (f"addr:{address}", self.per_address),
        ]
        trusted_at = self._trusted.get(_pair(address, user))
        if trusted_at is None or now - trusted_at >= self.trust_s:
            limits.append((f"acct:{user.lower()}", self.per_account_untrusted))
        return limits

    def _wait(self, key: str, limit: int, now: float) -> float:
        stamps = self._attempts.get(key)
        if not stamps:
            return 0.0
        while stamps and now - stamps[0] >= self.window_s:
            stamps.popleft()
        if len(stamps) < limit:
            return 0.0
        return self.window_s - (now - stamps[0])

    def _prune(self, now: float) -> None:
        for key in list(self._attempts):
            stamps = self._attempts[key]
            if not stamps or now - stamps[-1] >= self.window_s:
                del self._attempts[key]


def _pair(address: str, user: str) -> str:
    return f"pair:{user.lower()}|{address}"
