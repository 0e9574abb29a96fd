"""The tuning test bench: repeatable tests, every sample recorded, metrics, runs kept.

A test arms a recorder on the axis' sample stream (every sample the link delivers,
not the plot's view), writes the test's parameter overrides, sends the trigger
command, records for the requested duration or until the axis has settled, leaves
the axis in a safe state, restores the parameters it changed and computes the
metrics. The run is stored in SQLite as soon as it starts and its samples follow in
chunks every half second, so a link loss or a crash keeps what was recorded; such a
run is marked incomplete, and the axis is stopped.

Refusals happen before anything moves: a test beyond the user's limits (422 naming
the limit), a kind the device cannot run or an axis already under test (409).

The seam: this module is the bench's front desk — what the API and the hub's peers
call: the request model, the refusals, the plan and the stored run, then the stored
runs (list, read, export, import). ``TestBench`` has the parts: a ``LimitsStore``
(``servotune.bench.limits``, the per-axis limits in storage), the ``KindTable``
(``servotune.bench.kinds``: what differs per kind of test — its checks, its plan, its
metrics), the ``ActiveRuns`` table and the ``Runner`` (``servotune.bench.runner``: what
happens once a test has started — the recorder, the test's sequence, the checks while
it runs, the metrics).

"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import time
import uuid
from collections.abc import AsyncIterator, Callable, Mapping
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict
from pathlib import Path
from typing import Any, Protocol, TypeVar, runtime_checkable

from servotune.bench import files
from servotune.bench.kinds import KindTable, TestKind
from servotune.bench.limits import BenchLimits, LimitsStore
from servotune.bench.runner import ActiveRuns, ExternalRecording, Recording, Runner, run_meta
from servotune.compute import worker_context
from servotune.hub.hub import Hub
from servotune.hub.state import AxisEntry
from servotune.link.base import (
    BenchPlan,
    BenchPlanner,
    BenchTest,
    DeviceRefusedError,
    DriverError,
    InvalidArgumentError,
    Sample,
)
from servotune.link.validation import validate_command, validate_params
from servotune.schema import BenchTestRequest as BenchTestRequest  # importable from here too
from servotune.schema import StorageStatus
from servotune.storage import Storage, StorageError
from servotune.tuning.law import DeviceLaws

logger = logging.getLogger(__name__)

T = TypeVar("T")


@runtime_checkable
class BenchDelegate(Protocol):
    """Optional for a driver: an axis whose tests run where the axis is (a rig's axis
    seen from the lab's hub, ``servotune.bus.remote``): that server plans, checks
    (limits, control lock) and records them; its runs reach this store later."""

    def bench_kinds(self) -> list[str]: ...

    async def bench_start(self, request: Mapping[str, Any]) -> dict[str, Any]: ...

    async def bench_runs(self) -> list[dict[str, Any]]: ...


class TestBench:
    """Runs bench tests on the hub's axes; one test at a time per axis."""

    __test__ = False  # not a pytest class

    def __init__(
        self, hub: Hub, storage: Storage, laws: DeviceLaws, clock: Any = time.monotonic
    ) -> None:
        """``laws``: the devices' controller laws (the registry): which axes take a
        measured frequency response, and the model of the others."""
        self._hub = hub
        self._storage = storage
        self.laws = laws
        self._kinds = KindTable.standard(laws)
        self._clock = clock
        self._active = ActiveRuns()
        self._limits = LimitsStore(hub, storage)
        self._runner = Runner(hub, storage, clock, self._active, self._limits)
        self._tasks: set[asyncio.Task[None]] = set()
        self._pool: ProcessPoolExecutor | None = None
        hub.add_sample_listener(self._runner.on_sample)

    async def start(self) -> None:
        if self._storage.problem:
            # Told at start-up (log, event, banner via storage_status / GET
            # /api/storage): the server runs, but nothing it changes is saved.
            self._hub.on_event(
                "error", None, f"settings are not being saved: {self._storage.problem}"
            )
            self._hub.broadcast_model(StorageStatus(writable=False, message=self._storage.problem))
            return
        try:
            interrupted = await asyncio.to_thread(self._storage.mark_interrupted_runs)
        except StorageError as exc:
            self._hub.on_event("error", None, f"settings are not being saved: {exc}")
            return
        if interrupted:
            self._hub.on_event(
                "warning",
                None,
                f"{interrupted} bench run(s) were cut off by a restart: kept as incomplete",
            )
        task = asyncio.create_task(self._rejudge_stored(), name="rejudge stored runs")
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _rejudge_stored(self) -> None:
        """Runs stored by an older version are judged by today's sampling rule
        (runquality.rejudge), in a process of their own, like an import; the process
        is started only when some run needs it (a look at the stored metadata)."""
        if not await asyncio.to_thread(self._any_to_rejudge):
            return
        try:
            changed = await self._in_import_process(
                functools.partial(files.rejudge_in_process, str(self._storage.path))
            )
        except StorageError as exc:
            self._hub.on_event("error", None, f"stored runs not judged again: {exc}")
            return
        if changed:
            self._hub.on_event(
                "info",
                None,
                f"{changed} stored bench run(s) judged again by today's sampling rule "
                "(metrics the samples cannot resolve are now null, with the reason)",
            )

    def _any_to_rejudge(self) -> bool:
        for run_id in self._storage.run_ids():
            run = self._storage.get_run_meta(run_id)
            if run is not None and files.needs_rejudging(run):
                return True
        return False

    async def _in_import_process(self, call: Callable[[], T]) -> T:
        """``call()`` in an import process: one at a time, each process fresh.

        Fresh per call (``bench.files``): its own interpreter (a parse never holds the
        event loop's), at nice 10, and its memory goes with it. The processes are
        forks of the server's fork server (``compute.worker_context``), which has
        ``bench.files`` imported, so a refused file costs a fork rather than an
        interpreter start and its imports (docs/bench.md). Submitted from a worker
        thread: the first fork may wait for the fork server's own start.

        A process that died under the call (killed, out of memory) is a
        ``StorageError`` (507; what it stored is the caller's to remove, see
        ``import_run``), and the next call gets a new pool."""
        if self._pool is None:
            self._pool = ProcessPoolExecutor(
                max_workers=1, mp_context=worker_context(), max_tasks_per_child=1
            )
        pool = self._pool
        try:
            return await asyncio.wrap_future(await asyncio.to_thread(pool.submit, call))
        except BrokenProcessPool:
            if self._pool is pool:
                self._pool = None
            await asyncio.to_thread(pool.shutdown, wait=False, cancel_futures=True)
            raise StorageError(
                "not saved: the import process ended before it answered (killed, or out of memory?)"
            ) from None

    async def stop(self) -> None:
        if self._pool is not None:
            await asyncio.to_thread(self._pool.shutdown, wait=True, cancel_futures=True)
            self._pool = None
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            with contextlib.suppress(asyncio.CancelledError):
                await task

    # --- limits -----------------------------------------------------------------------

    async def limits(self, axis_id: str) -> BenchLimits:
        return await self._limits.get(axis_id)

    async def set_limits(self, axis_id: str, limits: BenchLimits) -> BenchLimits:
        return await self._limits.set(axis_id, limits)

    # --- runs -------------------------------------------------------------------------

    def check_axis(self, axis_id: str) -> None:
        """UnknownAxisError (404) for an axis that does not exist."""
        self._hub.entry(axis_id)

    def kinds(self, axis_id: str) -> list[str]:
        driver = self._hub.entry(axis_id).driver
        if isinstance(driver, BenchDelegate):
            return driver.bench_kinds()
        return list(driver.bench_kinds()) if isinstance(driver, BenchPlanner) else []

    async def start_run(
        self,
        axis_id: str,
        request: BenchTestRequest,
        identified: Mapping[str, Any] | None = None,
        *,
        restore_gains: Mapping[str, int] | None = None,
    ) -> dict[str, Any]:
        """Check, plan and start a test; returns the run summary (status 'recording').

        ``identified``: the auto-tune's plant model of the axis, which a model-based
        frequency response (a device the bench cannot inject into) is computed from.
        ``restore_gains``: what to write back if the run leaves the axis oscillating
        (default: the gains in force when it started; ``Runner._settle``)."""
        entry = self._hub.entry(axis_id)
        driver = entry.driver
        if isinstance(driver, BenchDelegate):
            return await driver.bench_start(request.model_dump(mode="json"))
        if not isinstance(driver, BenchPlanner):
            raise DeviceRefusedError(f"{entry.info.device} has no bench tests yet")
        kinds = driver.bench_kinds()
        if request.kind not in kinds:
            raise InvalidArgumentError(
                "kind", f"kind must be one of {', '.join(kinds)} for this device"
            )
        limits = await self.limits(axis_id)
        self._check_limits(request, limits)
        kind = self._kinds.get(request.kind)
        kind.check(entry, request, limits, identified)
        if self._active.busy(axis_id):
            raise DeviceRefusedError("a test is already running on this axis")
        # Claimed before the first await, so a second request cannot slip in.
        with self._active.claim(axis_id):
            return await self._start_claimed(
                axis_id, entry, driver, kind, request, limits, identified, restore_gains
            )

    async def _start_claimed(
        self,
        axis_id: str,
        entry: AxisEntry,
        driver: BenchPlanner,
        kind: TestKind,
        request: BenchTestRequest,
        limits: BenchLimits,
        identified: Mapping[str, Any] | None = None,
        restore_gains: Mapping[str, int] | None = None,
    ) -> dict[str, Any]:
        await self._hub.take_over(entry)
        if entry.latest is None or self._hub.link_status(entry.link.id).state != "connected":
            raise DeviceRefusedError("the axis is not connected: no telemetry")
        test = BenchTest(
            kind=request.kind,
            distance=request.distance,
            velocity=request.velocity,
            pwm=request.pwm,
            duration_s=request.duration_s,
        )
        planned = kind.plan(entry, driver, test, request, entry.latest, limits)
        plan = planned.plan
        self._check_window(kind, test, plan, entry.latest, limits)
        # The plan is checked like user input before anything moves (422 naming the
        # field): a test must not put a value on the wire the descriptor forbids.
        if plan.overrides:
            validate_params(entry.driver.descriptor, plan.overrides)
        for name, args in (*plan.setup, *plan.trigger, *plan.finish):
            validate_command(entry.driver.descriptor, name, args)
        self._hub.mark_operated(entry)
        run_id = uuid.uuid4().hex[:12]
        test_dict = asdict(test) | {"note": request.note} | planned.test
        meta = run_meta(entry, test_dict, plan)
        columns, flags = meta["columns"], meta["flags"]
        created_s = time.time()
        if planned.model_based:
            return await self._model_run(run_id, entry, axis_id, created_s, meta, identified)
        await asyncio.to_thread(
            self._storage.create_run, run_id, entry.storage_key, axis_id, created_s, meta
        )
        recording = Recording(
            run_id,
            entry,
            plan,
            columns,
            flags,
            stop_generation=entry.stop_generation,
            excitation=planned.excitation,
            restore_gains=dict(restore_gains) if restore_gains else None,
        )
        self._active.add(axis_id, recording)
        task = asyncio.create_task(self._runner.run(recording, test, meta, kind))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        self._runner.update(recording, "recording", "armed")
        return {
            "id": run_id,
            "axis_id": axis_id,
            "created_s": created_s,
            "status": "recording",
            **meta,
        }

    def test_running(self, axis_id: str) -> bool:
        """Whether a run records on the axis (a bench test or a ``record``)."""
        return self._active.running(axis_id)

    async def record(
        self, entry: AxisEntry, test: dict[str, Any], plan: BenchPlan
    ) -> ExternalRecording:
        """Store a run of ``test`` on the axis that the caller drives itself, recorded
        by the bench's recorder and reported with its ``run`` messages; the bench
        refuses other tests on the axis until the recording is finished (409 if a test
        already records there)."""
        axis_id = entry.info.id
        meta = run_meta(entry, test, plan)
        recording = Recording(uuid.uuid4().hex[:12], entry, plan, meta["columns"], meta["flags"])
        if self._active.running(axis_id):
            raise DeviceRefusedError("a test is already running on this axis")
        self._active.add(axis_id, recording)
        try:
            await asyncio.to_thread(
                self._storage.create_run,
                recording.run_id,
                entry.storage_key,
                axis_id,
                time.time(),
                meta,
            )
        except BaseException:
            self._active.discard(axis_id)
            raise
        return ExternalRecording(self._runner, self._active, recording, meta)

    async def _model_run(
        self,
        run_id: str,
        entry: AxisEntry,
        axis_id: str,
        created_s: float,
        meta: dict[str, Any],
        identified: Mapping[str, Any] | None,
    ) -> dict[str, Any]:
        """A model-based frequency response: stored at once, nothing sent to the device
        (the response is computed from ``meta["plant_model"]`` when it is read)."""
        meta["plant_model"] = dict(identified or {})
        meta["message"] = "model-based: the identified plant under the device's law"
        meta["quality"] = {"status": "good", "reasons": [], "untrusted": {}}
        await asyncio.to_thread(
            self._storage.create_run, run_id, entry.storage_key, axis_id, created_s, meta
        )
        await asyncio.to_thread(self._storage.finish_run, run_id, "complete", meta)
        return {
            "id": run_id,
            "axis_id": axis_id,
            "created_s": created_s,
            "status": "complete",
            **meta,
        }

    @staticmethod
    def _check_window(
        kind: TestKind, test: BenchTest, plan: BenchPlan, latest: Sample, limits: BenchLimits
    ) -> None:
        """Refuse a test that starts or ends outside the user's travel window (422)."""
        position = latest.channels.get("position")
        if position is not None and (why := limits.outside(position)):
            raise InvalidArgumentError(
                "distance", f"the axis stands outside your travel window: {why}"
            )
        if kind.returns_to_start and (why := limits.outside(plan.y_final)):
            raise InvalidArgumentError(
                "distance", f"distance {test.distance} would end at {why} (bench limits)"
            )

    def _check_limits(self, request: BenchTestRequest, limits: BenchLimits) -> None:
        if abs(request.distance) > limits.max_distance_counts:
            raise InvalidArgumentError(
                "distance",
                f"distance {request.distance} exceeds your limit of ±{limits.max_distance_counts}"
                " counts (bench limits)",
            )
        if abs(request.velocity) > limits.max_velocity:
            raise InvalidArgumentError(
                "velocity",
                f"velocity {request.velocity} exceeds your limit of ±{limits.max_velocity}",
            )
        if abs(request.pwm) > limits.max_pwm:
            raise InvalidArgumentError(
                "pwm", f"pwm {request.pwm} exceeds your limit of ±{limits.max_pwm}"
            )
        if request.duration_s > limits.max_duration_s:
            raise InvalidArgumentError(
                "duration_s",
                f"duration {request.duration_s} s exceeds your limit of {limits.max_duration_s} s",
            )

    # --- stored runs ------------------------------------------------------------------
    # Reading, exporting and importing go through worker threads in small pieces
    # (servotune.bench.files): a run of tens of megabytes must never hold the event loop.

    async def list_runs(self, axis_id: str) -> list[dict[str, Any]]:
        entry = self._hub.entry(axis_id)
        stored = await asyncio.to_thread(self._storage.list_runs, entry.storage_key)
        if isinstance(entry.driver, BenchDelegate):
            # The runs still on their way here (recording, or not yet collected).
            ids = {run["id"] for run in stored}
            with contextlib.suppress(DriverError):
                stored += [r for r in await entry.driver.bench_runs() if r.get("id") not in ids]
        return stored

    async def get_run(self, run_id: str) -> dict[str, Any]:
        """One run with all its samples as Python objects (for small runs: tests, tools)."""
        run = await asyncio.to_thread(self._storage.get_run, run_id)
        if run is None:
            raise KeyError(run_id)
        return run

    async def get_run_meta(self, run_id: str) -> dict[str, Any]:
        """One run without its samples (status, metrics, quality): cheap to poll."""
        run = await asyncio.to_thread(self._storage.get_run_meta, run_id)
        if run is None:
            raise KeyError(run_id)
        return run

    async def iter_run_json(self, run_id: str) -> AsyncIterator[bytes]:
        """The run with its samples as JSON text, chunk by chunk (KeyError if missing).

        The stored chunks are valid JSON arrays already and are passed on verbatim:
        no parse of the samples, no big response object."""
        run = await self.get_run_meta(run_id)
        seqs = await asyncio.to_thread(self._storage.chunk_seqs, run_id)

        async def body() -> AsyncIterator[bytes]:
            yield (await asyncio.to_thread(files.run_json_head, run)).encode()
            first = True
            for seq in seqs:
                rows = await asyncio.to_thread(files.chunk_rows_text, self._storage, run_id, seq)
                if rows:
                    yield (rows if first else "," + rows).encode()
                    first = False
            yield b"]}"

        return body()

    async def iter_run_csv(self, run_id: str) -> AsyncIterator[bytes]:
        """The samples as CSV, chunk by chunk (KeyError if missing)."""
        run = await self.get_run_meta(run_id)
        seqs = await asyncio.to_thread(self._storage.chunk_seqs, run_id)

        async def body() -> AsyncIterator[bytes]:
            yield files.csv_header(run).encode()
            for seq in seqs:
                text = await asyncio.to_thread(files.chunk_csv, self._storage, run_id, seq)
                yield text.encode()

        return body()

    async def update_run_meta(self, run_id: str, changes: dict[str, Any]) -> None:
        """Replace top-level keys of a stored run's metadata (e.g. the auto-tune's
        decision on its identification run); KeyError if there is no such run."""
        if not await asyncio.to_thread(self._storage.update_run_meta, run_id, changes):
            raise KeyError(run_id)

    async def delete_run(self, run_id: str) -> None:
        if not await asyncio.to_thread(self._storage.delete_run, run_id):
            raise KeyError(run_id)

    async def set_baseline(self, run_id: str) -> None:
        if not await asyncio.to_thread(self._storage.set_baseline, run_id):
            raise KeyError(run_id)

    async def import_run(self, axis_id: str, body_path: Path, meta: bytes | None = None) -> str:
        """Import a run in a separate process (see ``bench.files``); returns the new run id.

        ``body_path``: the JSON body ``{"meta", "csv"}``, or with ``meta`` (the
        run.json of a multipart upload) the CSV file. 422 naming the field, 507 if the
        database cannot be written."""
        entry = self._hub.entry(axis_id)
        if self._storage.problem:
            raise StorageError(f"not saved: {self._storage.problem}")
        run_id = uuid.uuid4().hex[:12]
        try:
            outcome = await self._in_import_process(
                functools.partial(
                    files.import_in_process,
                    str(self._storage.path),
                    entry.storage_key,
                    axis_id,
                    entry.info.device,
                    str(body_path),
                    meta,
                    run_id,
                ),
            )
        except StorageError:
            # The process died under the import: what it had stored goes too.
            with contextlib.suppress(StorageError):
                await asyncio.to_thread(self._storage.delete_run, run_id)
            raise
        kind, value, message = outcome
        if kind == "invalid":
            raise InvalidArgumentError(value, message)
        if kind == "storage":
            raise StorageError(message)
        return value
