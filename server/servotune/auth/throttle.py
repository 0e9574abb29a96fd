"""Login throttling per client address and per user name (answers 429, never locks for good).

Failed logins are counted in a sliding window. Over the limit, further attempts are
refused with a ``retry_after_s`` until the oldest failure in the window has aged out:
a brute force gets a handful of guesses per window, while the operator who mistyped
their own password waits minutes, not forever (nothing is stored, a restart clears it).
A successful login clears the user name's counter and the address's counter.

Limits (OctoPrint's are 3/min, 5/10 min, 10/h on failures; these are close):
- per user name: 5 failures per 5 minutes (stops guessing one account from many places),
- per address: 20 failures per 5 minutes (stops one place guessing many accounts; a
  shared lab NAT is why it is higher than the per-name limit).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

WINDOW_S = 300.0
PER_USER = 5
PER_ADDRESS = 20
_MAX_KEYS = 10_000  # bound the memory a scan over random names can take


@dataclass
class LoginThrottle:
    window_s: float = WINDOW_S
    per_user: int = PER_USER
    per_address: int = PER_ADDRESS
    clock: Callable[[], float] = time.monotonic
    _failures: dict[str, deque[float]] = field(default_factory=dict)

    def retry_after_s(self, address: str, user: str) -> float:
        """0 when an attempt may go ahead, else the seconds until one may."""
        now = self.clock()
        waits = [
            self._wait(f"addr:{address}", self.per_address, now),
            self._wait(f"user:{user.lower()}", self.per_user, now),
        ]
        return max(waits)

    def failed(self, address: str, user: str) -> None:
        now = self.clock()
        if len(self._failures) > _MAX_KEYS:
            self._prune(now)
        for key in (f"addr:{address}", f"user:{user.lower()}"):
            self._failures.setdefault(key, deque()).append(now)

    def succeeded(self, address: str, user: str) -> None:
        self._failures.pop(f"addr:{address}", None)
        self._failures.pop(f"user:{user.lower()}", None)

    def _wait(self, key: str, limit: int, now: float) -> float:
        stamps = self._failures.get(key)
        if not stamps:
            return 0.0
        while stamps and now - stamps[0] >= self.window_s:
            stamps.popleft()
        if len(stamps) < limit:
            return 0.0
        return self.window_s - (now - stamps[0])

    def _prune(self, now: float) -> None:
        for key in list(self._failures):
            stamps = self._failures[key]
            if not stamps or now - stamps[-1] >= self.window_s:
                del self._failures[key]
