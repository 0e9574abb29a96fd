"""Where a wall-clock interval of this test process went: the machine's share and ours.

A test that times the product in real time (the dead-man's 500 ms, a STOP's latency)
runs the product in its own process, on its event loop's thread. On a shared, loaded
machine that thread can be ready to run and wait for a CPU (other processes); Linux
counts that wait per thread (``/proc/thread-self/schedstat``, field 2: time spent on a
run queue). That time is the machine's, not the product's: nothing of ours could run.
``CpuAccount`` measures it over an interval, and the garbage collector's pauses in it
(``gc.callbacks``: those are this process's own time, reported, never subtracted), so
that a test judges the product on ``own_s`` = wall time less the loop thread's run-queue
wait, and says where the time went when it fails.

Where schedstat is missing (not Linux, no schedstats) the wait is unknown and counts as
our own (the strict reading). The measurement is the kernel's, not the product's.
"""

from __future__ import annotations

import gc
import threading
import time
from dataclasses import dataclass, field
from typing import Any


def thread_runqueue_wait_s() -> float | None:
    """Time the calling thread has spent ready but waiting for a CPU, or None."""
    try:
        with open("/proc/thread-self/schedstat", encoding="ascii") as f:
            return int(f.read().split()[1]) / 1e9
    except (OSError, IndexError, ValueError):
        return None


@dataclass
class CpuAccount:
    """Open with ``start()`` on the event loop's thread at the interval's start (when
    ``time.monotonic()`` is ``t0``); ``close(t1)`` on the same thread after its end.

    ``wait_s``: the loop thread's run-queue wait within the interval (0 if unknown).
    The close may come after ``t1`` (a test polls for the event it times); the wait
    can only be read then, and as much of it as the time since ``t1`` may have fallen
    after the interval, so that much is not counted (the machine's share is never
    overstated).
    """

    t0: float = 0.0
    t1: float = 0.0
    wait_s: float = 0.0
    known: bool = False
    gc_pauses: list[tuple[float, float, int]] = field(default_factory=list)
    _wait0: float | None = None
    _gc_started: float = 0.0
    _thread: int = 0

    def start(self) -> float:
        """Start the account now; returns ``t0`` (``time.monotonic()``)."""
        self._thread = threading.get_ident()
        self.gc_pauses.clear()
        gc.callbacks.append(self._on_gc)
        self._wait0 = thread_runqueue_wait_s()
        self.t0 = time.monotonic()
        return self.t0

    def close(self, t1: float) -> CpuAccount:
        """End the account for the interval ``[t0, t1]``."""
        assert threading.get_ident() == self._thread, "close on the thread that started"
        wait1 = thread_runqueue_wait_s()
        late_s = max(0.0, time.monotonic() - t1)
        with_callback = self._on_gc in gc.callbacks
        if with_callback:
            gc.callbacks.remove(self._on_gc)
        self.t1 = t1
        self.known = self._wait0 is not None and wait1 is not None
        if self._wait0 is not None and wait1 is not None:
            self.wait_s = min(max(0.0, wait1 - self._wait0 - late_s), max(0.0, t1 - self.t0))
        return self

    def _on_gc(self, phase: str, info: dict[str, Any]) -> None:
        now = time.monotonic()
        if phase == "start":
            self._gc_started = now
        else:
            self.gc_pauses.append((self._gc_started, now, int(info.get("generation", -1))))

    @property
    def took_s(self) -> float:
        return self.t1 - self.t0

    @property
    def own_s(self) -> float:
        """The interval less the time the loop's thread waited for a CPU."""
        return self.took_s - self.wait_s

    @property
    def gc_s(self) -> float:
        """Garbage-collector pauses (this process's own time) within the interval."""
        return sum(
            max(0.0, min(end, self.t1) - max(start, self.t0)) for start, end, _ in self.gc_pauses
        )

    def describe(self) -> str:
        wait = f"{1000 * self.wait_s:.0f} ms" if self.known else "unknown (counted as ours)"
        pauses = [
            f"gen {g} {1000 * (end - start):.0f} ms at +{1000 * (start - self.t0):.0f} ms"
            for start, end, g in self.gc_pauses
            if end >= self.t0 and start <= self.t1
        ]
        return (
            f"{1000 * self.took_s:.0f} ms on the wall clock: the loop's thread waited "
            f"{wait} for a CPU (the machine's), {1000 * self.own_s:.0f} ms our own"
            f" (garbage collection {1000 * self.gc_s:.0f} ms of it"
            f"{': ' + ', '.join(pauses) if pauses else ''})"
        )
