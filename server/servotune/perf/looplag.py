"""How late the event loop wakes up, and whose fault it is.

A task sleeps ``period_s`` again and again and records how late each wake-up came
(the loop *lag*). On a shared machine most of a lag can be the machine's: the loop's
thread was ready but waited for a CPU (other processes). Linux counts that wait per
thread (``/proc/thread-self/schedstat``: time on a run queue), so the meter splits each
lag into the machine's share and the process's own (``own``): what the loop spent
running callbacks or blocked inside this process (a callback computing, a blocking
call, the interpreter lock held by another thread). ``own`` is what the product
answers for; it does not grow with the load of other processes. Where schedstat is
missing the whole lag counts as own (the strict reading).

Used by the test suite's loop-lag watchdog (tests/integration/perf/test_loop_watchdog.py)
around bench runs and auto-tune steps, and by ``scripts/perf_stops.py``-style tools; pure asyncio
and the standard library.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field


def _runqueue_wait_s() -> float | None:
    """Time this thread has spent ready but waiting for a CPU, or None if unknown."""
    try:
        with open("/proc/thread-self/schedstat", encoding="ascii") as f:
            return int(f.read().split()[1]) / 1e9
    except (OSError, IndexError, ValueError):
        return None


@dataclass(slots=True)
class LagSample:
    t: float  # when the wake-up came (time.perf_counter)
    lag_s: float  # how late it came
    own_s: float  # the share of the lag not spent waiting for a CPU


@dataclass(slots=True)
class LoopLagMeter:
    """Runs while its ``running()`` context is open, on the current event loop."""

    period_s: float = 0.01
    samples: list[LagSample] = field(default_factory=list)

    async def _run(self) -> None:
        while True:
            before = time.perf_counter()
            waited = _runqueue_wait_s()
            await asyncio.sleep(self.period_s)
            now = time.perf_counter()
            lag = max(0.0, now - before - self.period_s)
            after = _runqueue_wait_s()
            machine = after - waited if after is not None and waited is not None else 0.0
            self.samples.append(LagSample(now, lag, max(0.0, lag - machine)))

    @contextlib.asynccontextmanager
    async def running(self) -> AsyncIterator[LoopLagMeter]:
        task = asyncio.get_running_loop().create_task(self._run(), name="loop lag meter")
        try:
            yield self
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    def between(self, t_from: float, t_to: float) -> list[LagSample]:
        return [s for s in self.samples if t_from <= s.t <= t_to]

    def worst(self, t_from: float, t_to: float) -> LagSample | None:
        """The sample with the largest own lag between the two times."""
        found = self.between(t_from, t_to)
        return max(found, key=lambda s: s.own_s) if found else None
