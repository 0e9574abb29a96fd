"""CPU-heavy pure functions in a worker process: model fits, gain searches, FRF analysis.

Why a process and not a thread: these functions are mostly Python bytecode (scipy's
optimisers call a Python residual thousands of times, the gain searches simulate
the discrete loop per candidate), so a worker *thread* holds the interpreter lock
most of the time. The event loop then waits for the lock after every system call
it makes, and STOP answers and telemetry wait with it.
``tests/integration/perf/test_loop_latency.py`` measures both (figures in
docs/architecture.md, "Heavy work").

Contract of ``ComputePool.run(fn, *args, **kwargs)``: ``fn`` is a module-level
function whose arguments and result pickle; exceptions it raises are raised to the
caller as they were. One worker: two fits queue rather than compete with the event
loop for the second core. A worker that died (killed, out of memory) is replaced and
the call made once more. The worker is started on the first call, from a thread, so
the start never holds the event loop; until then nothing runs.

Start method: ``forkserver`` where the platform has it, with the tuning modules
preloaded in the fork server, so each app's worker is a fork of an interpreter
that has numpy and scipy imported (the import costs ~1.5 s of CPU once per
process, not once per app: the test suite builds hundreds of apps); ``spawn``
elsewhere.

The modules named in ``PRELOAD`` are imported by the fork server and the worker,
never here: importing this module costs nothing.
"""

from __future__ import annotations

import asyncio
import functools
import importlib
import multiprocessing
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from multiprocessing.context import BaseContext
from typing import ParamSpec, TypeVar

P = ParamSpec("P")
T = TypeVar("T")

# Where the functions run here live: imported once in the fork server. The devices'
# own (their gain searches) are added by the app from the registry
# (``DeviceEntry.compute_modules``).
PRELOAD = (
    "servotune.tuning.threads",  # first: one BLAS thread, set before numpy loads
    "servotune.tuning.identify",
    "servotune.bench.frf",
    "servotune.bench.files",  # the bench's import processes (bench.service)
)


def worker_context(preload: tuple[str, ...] = PRELOAD) -> BaseContext:
    """The start method of the server's worker processes: ``forkserver`` with
    ``PRELOAD`` and ``preload`` imported in the fork server, ``spawn`` where the
    platform has no fork server.

    The preload is only effective before the process' fork server starts; a later
    call (another pool, or a fork server already running) leaves the imports to the
    worker. Whichever pool starts it first preloads what every pool needs."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    forkserver = multiprocessing.get_context("forkserver")
    # In PRELOAD's order, not sorted: ``tuning.threads`` must come before numpy.
    forkserver.set_forkserver_preload(list(dict.fromkeys((*PRELOAD, *preload))))
    return forkserver


def _warm(modules: tuple[str, ...]) -> None:
    """Run in the new worker: import what the calls will need, before the first one."""
    for name in modules:
        importlib.import_module(name)


class ComputePool:
    """Worker processes for CPU-heavy pure functions (see the module docstring).

    ``workers`` processes (one by default); ``initializer``, a module-level function,
    runs first in each (``servotune.auth.passwords`` lowers their CPU priority).
    """

    def __init__(
        self,
        *,
        preload: tuple[str, ...] = PRELOAD,
        workers: int = 1,
        initializer: Callable[[], None] | None = None,
    ) -> None:
        self._preload = preload
        self._workers = workers
        self._initializer = initializer
        self._pool: ProcessPoolExecutor | None = None
        self._starting = asyncio.Lock()
        self._closed = False

    async def run(self, fn: Callable[P, T], /, *args: P.args, **kwargs: P.kwargs) -> T:
        """``fn(*args, **kwargs)`` in the worker; its result or its exception."""
        call = functools.partial(fn, *args, **kwargs)
        loop = asyncio.get_running_loop()
        for attempt in range(2):
            pool = await self._started()
            try:
                return await loop.run_in_executor(pool, call)
            except BrokenProcessPool:
                # The worker died under this call (killed, out of memory): a new one,
                # and the call once more; a second death is the caller's error.
                self._pool = None
                await asyncio.to_thread(pool.shutdown, wait=False, cancel_futures=True)
                if attempt == 1:
                    raise
        raise AssertionError("unreachable")

    async def start(self) -> None:
        """Start the workers now (they start on the first call otherwise)."""
        await self._started()

    async def _started(self) -> ProcessPoolExecutor:
        if self._closed:
            raise RuntimeError("the compute pool is closed")
        async with self._starting:
            if self._pool is None:
                # In a thread: creating the worker may wait for the fork server's
                # imports (about a second, once), and submit() does that in the
                # calling thread.
                self._pool = await asyncio.to_thread(self._start)
            return self._pool

    def _start(self) -> ProcessPoolExecutor:
        pool = ProcessPoolExecutor(
            max_workers=self._workers,
            mp_context=worker_context(self._preload),
            initializer=self._initializer,
        )
        pool.submit(_warm, self._preload).result()
        return pool

    async def close(self) -> None:
        """Stop the worker once a call still running has ended; later calls fail."""
        self._closed = True
        async with self._starting:
            pool, self._pool = self._pool, None
        if pool is not None:
            await asyncio.to_thread(pool.shutdown, wait=True, cancel_futures=True)
