"""Which axes of one link are being captured (``link.base.Capturer``), and the
bookkeeping every capturing link shares: nesting, pausing the others, statistics.

A link owns one ``CaptureRegistry``. ``hold(address, reason)`` is the context manager
an axis' ``capture()`` returns. It changes only in-memory state (no wire I/O, so
entering or leaving never waits behind the line and never fails for a link fault);
the link's owner task looks at ``addresses`` between two transactions and polls
accordingly. ``on_change`` tells the link to publish the paused / resumed state of
its other axes.
"""

from __future__ import annotations

import contextlib
from collections import Counter
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field


@dataclass(slots=True)
class CaptureStats:
    """What one capture of one axis did on the wire (for the benchmark and the log).

    ``wire_chars`` counts every character time the capture's transactions took on the
    wire (sent, echoed and replied), so ``samples / (wire_chars * char_s)`` is the
    ratio of the achieved rate to the wire limit of exactly the poll mix used.
    """

    started_s: float
    ended_s: float | None = None
    samples: int = 0
    transactions: Counter[str] = field(default_factory=Counter)
    wire_chars: int = 0
    # The reconstructed setpoint checked against interleaved following-error reads.
    setpoint_checks: int = 0
    setpoint_mismatches: int = 0
    max_setpoint_residual: float = 0.0

    def add(self, mnemonic: str, chars: int) -> None:
        self.transactions[mnemonic] += 1
        self.wire_chars += chars


class CaptureRegistry:
    """The captured addresses of one link, with a nesting count each."""

    def __init__(self, on_change: Callable[[], None]) -> None:
        self._counts: Counter[int] = Counter()
        self._reasons: dict[int, str] = {}
        self._on_change = on_change

    @property
    def addresses(self) -> list[int]:
        """Captured addresses, in the order captures began."""
        return list(self._counts)

    @property
    def active(self) -> bool:
        return bool(self._counts)

    def reason(self, address: int) -> str:
        return self._reasons.get(address, "")

    @contextlib.asynccontextmanager
    async def hold(self, address: int, reason: str) -> AsyncIterator[None]:
        first = self._counts[address] == 0
        self._counts[address] += 1
        if first:
            self._reasons[address] = reason
            self._on_change()
        try:
            yield
        finally:
            self._counts[address] -= 1
            if self._counts[address] <= 0:
                del self._counts[address]
                self._reasons.pop(address, None)
                self._on_change()
