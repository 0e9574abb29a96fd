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
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import multiprocessing
import time
import uuid
from collections.abc import AsyncIterator, Mapping
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable

from pydantic import BaseModel, Field, model_validator

from servotune import frfbench, runio
from servotune.drivers.base import (
    BenchKind,
    BenchPlan,
    BenchPlanner,
    BenchTest,
    CommandClock,
    DeviceRefusedError,
    DriverError,
    InvalidArgumentError,
    Sample,
    capture_of,
)
from servotune.drivers.validation import validate_command, validate_params
from servotune.hub import Hub
from servotune.hub_state import AxisEntry
from servotune.metrics import compute_metrics
from servotune.runquality import POSITION_KINDS, assess
from servotune.storage import Storage, StorageError
from servotune.tuning.frfrun import Excitation
from servotune.wire import RunUpdate, StorageStatus

logger = logging.getLogger(__name__)

PRE_TRIGGER_S = 0.2
FLUSH_PERIOD_S = 0.5
SETTLED_HOLD_S = 0.3
RETURN_TIMEOUT_S = 5.0  # after the return move's profile time


class BenchLimits(BaseModel):
    """What the user allows the bench to do on one axis (checked before every test)."""

    max_distance_counts: int = Field(default=20_000, ge=1, le=1 << 25)
    max_velocity: int = Field(default=20_000, ge=1, le=1 << 31)
    max_pwm: int = Field(default=80, ge=1, le=255)
    max_duration_s: float = Field(default=10.0, gt=0, le=60)
    min_position_counts: int | None = Field(
        default=None,
        ge=-(1 << 31),
        le=(1 << 31) - 1,
        description="travel window: no test starts outside it, targets a position outside "
        "it or travels out of it (counts, with max_position_counts; null: no window)",
    )
    max_position_counts: int | None = Field(default=None, ge=-(1 << 31), le=(1 << 31) - 1)

    @model_validator(mode="after")
    def _window(self) -> BenchLimits:
        low, high = self.min_position_counts, self.max_position_counts
        if low is not None and high is not None and low >= high:
            raise ValueError(f"min_position_counts {low} must be below max_position_counts {high}")
        return self

    def outside(self, position: float) -> str | None:
        """Why ``position`` is outside the travel window, or None."""
        if self.min_position_counts is not None and position < self.min_position_counts:
            return f"{position:.0f} is below your min_position_counts {self.min_position_counts}"
        if self.max_position_counts is not None and position > self.max_position_counts:
            return f"{position:.0f} is above your max_position_counts {self.max_position_counts}"
        return None


@runtime_checkable
class BenchDelegate(Protocol):
    """Optional for a driver: an axis whose tests run where the axis is (a rig's axis
    seen from the lab's hub, ``servotune.bus.remote``): that server plans, checks
    (limits, control lock) and records them; its runs reach this store later."""

    def bench_kinds(self) -> list[str]: ...

    async def bench_start(self, request: Mapping[str, Any]) -> dict[str, Any]: ...

    async def bench_runs(self) -> list[dict[str, Any]]: ...


class BenchTestRequest(BaseModel):
    """``POST /api/axes/{id}/bench/runs``: what to run (units are the device's)."""

    kind: BenchKind = Field(
        description="move | position_step | velocity_step | pwm_step | frequency_response"
    )
    distance: int = 0
    velocity: int = 0
    pwm: int = 0
    duration_s: float = Field(default=2.0, gt=0)
    amplitude: int = Field(
        default=0,
        description="frequency_response: peak of the multisine around the held "
        "position, counts (1..max_distance_counts)",
    )
    low_hz: float = Field(default=1.0, description="frequency_response: lowest tone, Hz")
    high_hz: float = Field(default=40.0, description="frequency_response: highest tone, Hz")
    loop: Literal["closed", "open"] = Field(
        default="closed",
        description="frequency_response: closed (position targets, ma) or open (PWM "
        "through spwm, peak `pwm`; SLAP2 only, needs a travel window and confirmation)",
    )
    confirm_open_loop: bool = Field(
        default=False, description="frequency_response, loop open: the user confirmed"
    )
    note: str = Field(default="", max_length=200)


@dataclass(slots=True)
class _Recording:
    run_id: str
    entry: AxisEntry
    plan: BenchPlan
    columns: list[str]
    flags: list[str]
    t0: float | None = None
    # The axis' stop generation when the test started (None: not checked).
    stop_generation: int | None = None
    samples: list[list[Any]] = field(default_factory=list)
    flushed: int = 0
    chunk_seq: int = 0
    returned: dict[str, Any] | None = None  # how the return to the start went
    ended: bool = False  # the record is over (the return move is not recorded)
    excitation: Excitation | None = None  # frequency_response: the targets to stream
    sent: list[list[float]] = field(default_factory=list)  # [t, target] as acknowledged
    trigger_acked: float | None = None  # when the device acknowledged the trigger
    abort: str | None = None  # why the exciter stopped the axis (ends the record)


def run_meta(entry: AxisEntry, test: dict[str, Any], plan: BenchPlan) -> dict[str, Any]:
    """Everything stored with a run besides its samples (the JSON export)."""
    descriptor = entry.driver.descriptor
    return {
        "axis_key": entry.storage_key,
        "device": entry.info.device,
        "model": descriptor.model,
        "identity": {
            "link": entry.info.link,
            "path": entry.link.path,
            "address": entry.info.address,
            "name": entry.info.name,
        },
        "test": test,
        "params": dict(entry.device_values),
        "plan": {
            "response": plan.response,
            "y0": plan.y0,
            "y_final": plan.y_final,
            "band": plan.band,
            "overrides": plan.overrides,
        },
        "columns": ["t_s", *(c.name for c in descriptor.channels)],
        "flags": [f.name for f in descriptor.flags],
        "metrics": None,
        "message": "",
    }


def _value(x: float | None) -> float | None:
    return None if x is None or (isinstance(x, float) and math.isnan(x)) else float(x)


class TestBench:
    """Runs bench tests on the hub's axes; one test at a time per axis."""

    __test__ = False  # not a pytest class

    def __init__(self, hub: Hub, storage: Storage, clock: Any = time.monotonic) -> None:
        self._hub = hub
        self._storage = storage
        self._clock = clock
        self._active: dict[str, _Recording] = {}
        self._claimed: set[str] = set()
        self._tasks: set[asyncio.Task[None]] = set()
        self._pool: ProcessPoolExecutor | None = None
        hub.add_sample_listener(self._on_sample)

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

    def _limits_key(self, entry: AxisEntry) -> str:
        return f"bench-limits:{entry.storage_key}"

    async def limits(self, axis_id: str) -> BenchLimits:
        entry = self._hub.entry(axis_id)
        stored = await asyncio.to_thread(self._storage.get_meta, self._limits_key(entry))
        return BenchLimits.model_validate(stored) if stored else BenchLimits()

    async def set_limits(self, axis_id: str, limits: BenchLimits) -> BenchLimits:
        entry = self._hub.entry(axis_id)
        await asyncio.to_thread(
            self._storage.set_meta, self._limits_key(entry), limits.model_dump()
        )
        return limits

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
    ) -> dict[str, Any]:
        """Check, plan and start a test; returns the run summary (status 'recording').

        ``identified``: the auto-tune's plant model of the axis, which a model-based
        frequency response (a device the bench cannot inject into) is computed from."""
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
        if request.kind == frfbench.KIND:
            frfbench.check_request(
                entry.info.device,
                request.amplitude,
                request.low_hz,
                request.high_hz,
                request.duration_s,
                limits.max_distance_counts,
                loop=request.loop,
                pwm=request.pwm,
                max_pwm=limits.max_pwm,
                confirm_open_loop=request.confirm_open_loop,
                window=(limits.min_position_counts, limits.max_position_counts),
                baud=entry.link.baud,
            )
            if not frfbench.measured(entry.info.device) and not identified:
                raise DeviceRefusedError(
                    f"a {entry.info.device} frequency response is model-based: identify the "
                    "plant first (auto-tune, Identify)"
                )
        if axis_id in self._active or axis_id in self._claimed:
            raise DeviceRefusedError("a test is already running on this axis")
        # Claimed before the first await, so a second request cannot slip in.
        self._claimed.add(axis_id)
        try:
            return await self._start_claimed(axis_id, entry, driver, request, limits, identified)
        finally:
            self._claimed.discard(axis_id)

    async def _start_claimed(
        self,
        axis_id: str,
        entry: AxisEntry,
        driver: BenchPlanner,
        request: BenchTestRequest,
        limits: BenchLimits,
        identified: Mapping[str, Any] | None = None,
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
        excitation: Excitation | None = None
        model_based = False
        inject = frfbench.injection_for(entry.info.device)
        if test.kind == frfbench.KIND:
            if inject is not None and request.loop == "open":
                plan, excitation = frfbench.plan_open(
                    inject,
                    entry.latest,
                    request.pwm,
                    request.low_hz,
                    request.high_hz,
                    entry.link.baud,
                )
            elif inject is not None:
                plan, excitation = frfbench.plan_closed(
                    inject,
                    entry.latest,
                    entry.device_values,
                    request.amplitude,
                    request.low_hz,
                    request.high_hz,
                    entry.link.baud,
                )
                self._check_excursion(plan.y0, request.amplitude, limits)
            else:
                plan, model_based = frfbench.model_plan(entry.latest), True
        else:
            plan = driver.bench_plan(test, entry.latest, entry.device_values)
        self._check_window(test, plan, entry.latest, limits)
        # The plan is checked like user input before anything moves (422 naming the
        # field): a test must not put a value on the wire the descriptor forbids.
        if plan.overrides:
            validate_params(entry.driver.descriptor, plan.overrides)
        for name, args in (*plan.setup, *plan.trigger, *plan.finish):
            validate_command(entry.driver.descriptor, name, args)
        self._hub.mark_operated(entry)
        run_id = uuid.uuid4().hex[:12]
        test_dict = asdict(test) | {"note": request.note}
        if test.kind == frfbench.KIND:
            test_dict |= {
                "amplitude": request.amplitude,
                "low_hz": request.low_hz,
                "high_hz": request.high_hz,
                "model_based": model_based,
                "loop": request.loop,
            }
        meta = run_meta(entry, test_dict, plan)
        columns, flags = meta["columns"], meta["flags"]
        created_s = time.time()
        if model_based:
            return await self._model_run(run_id, entry, axis_id, created_s, meta, identified)
        await asyncio.to_thread(
            self._storage.create_run, run_id, entry.storage_key, axis_id, created_s, meta
        )
        recording = _Recording(
            run_id,
            entry,
            plan,
            columns,
            flags,
            stop_generation=entry.stop_generation,
            excitation=excitation,
        )
        self._active[axis_id] = recording
        task = asyncio.create_task(self._run(recording, test, meta))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        self._update(recording, "recording", "armed")
        return {
            "id": run_id,
            "axis_id": axis_id,
            "created_s": created_s,
            "status": "recording",
            **meta,
        }

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
    def _check_excursion(y0: float, amplitude: int, limits: BenchLimits) -> None:
        """A multisine must stay inside the travel window at its peaks (422)."""
        for edge in (y0 - amplitude, y0 + amplitude):
            if why := limits.outside(edge):
                raise InvalidArgumentError(
                    "amplitude",
                    f"amplitude {amplitude} around {y0:.0f} would reach {why} (bench limits)",
                )

    async def _excite(self, recording: _Recording) -> None:
        """Stream the multisine as position targets for the whole record.

        One ``ma`` per changed target, as fast as the wire takes them (each command
        waits for its reply); each send is stamped when the device acknowledged it,
        with the device's latch time when the driver knows it (``CommandClock``),
        which is what the analysis replays the profile from. STOP still goes first: the
        hub's STOP bumps the stop generation and every later command is refused."""
        excitation, t0 = recording.excitation, recording.t0
        assert excitation is not None and t0 is not None
        last: int | None = None
        axis = recording.entry.info.id
        limits = await self.limits(axis)
        open_loop = excitation.command != "move_absolute"
        while not recording.ended:
            target = excitation.target(self._clock() - t0)
            if target == last:
                await asyncio.sleep(0.001)
                continue
            # Open loop: nothing holds the axis but this check, at every PWM sent
            # (the record loop checks only every 50 ms).
            latest = recording.entry.latest
            position = latest.channels.get("position") if latest is not None else None
            if open_loop and position is not None and (why := limits.outside(position)):
                recording.abort = f"left your travel window: {why}: axis stopped"
                await recording.entry.driver.stop()
                return
            await self._hub.command(
                axis,
                excitation.command,
                {excitation.argument: target},
                origin="bench",
                stop_generation=recording.stop_generation,
            )
            # [acknowledged, target, latched]: the analysis replays the profile from
            # the latch. The acknowledgement is stamped when the command returns, after
            # the status read (rss) the driver sends right after the ma: 10-15 ms late
            # and jittery.
            driver = recording.entry.driver
            latch = driver.last_command_latch_s if isinstance(driver, CommandClock) else None
            recording.sent.append(
                [round(self._clock(), 6), float(target)]
                + ([round(latch, 6)] if latch is not None else [])
            )
            last = target

    @staticmethod
    def _check_window(
        test: BenchTest, plan: BenchPlan, latest: Sample, limits: BenchLimits
    ) -> None:
        """Refuse a test that starts or ends outside the user's travel window (422)."""
        position = latest.channels.get("position")
        if position is not None and (why := limits.outside(position)):
            raise InvalidArgumentError(
                "distance", f"the axis stands outside your travel window: {why}"
            )
        if test.kind in POSITION_KINDS and (why := limits.outside(plan.y_final)):
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

    def _on_sample(self, axis_id: str, sample: Sample) -> None:
        recording = self._active.get(axis_id)
        if recording is None or recording.ended:
            return
        row: list[Any] = [round(sample.t, 6)]
        row += [_value(sample.channels.get(name)) for name in recording.columns[1:]]
        row.append([int(bool(sample.flags.get(name))) for name in recording.flags])
        recording.samples.append(row)

    async def _flush(self, recording: _Recording) -> None:
        rows = recording.samples[recording.flushed :]
        if not rows:
            return
        recording.flushed = len(recording.samples)
        seq = recording.chunk_seq
        recording.chunk_seq += 1
        await asyncio.to_thread(self._storage.append_samples, recording.run_id, seq, rows)

    async def _send(self, recording: _Recording, steps: list[tuple[str, dict[str, int]]]) -> None:
        for name, args in steps:
            await self._hub.command(
                recording.entry.info.id,
                name,
                args,
                origin="bench",
                stop_generation=recording.stop_generation,
            )

    async def _run(self, recording: _Recording, test: BenchTest, meta: dict[str, Any]) -> None:
        entry, plan = recording.entry, recording.plan
        status, message = "complete", ""
        saved: dict[str, int] = {}
        try:
            if plan.overrides:
                saved = {
                    k: entry.device_values[k] for k in plan.overrides if k in entry.device_values
                }
                await entry.driver.write_params(plan.overrides)
            # capture: the line is devoted to this axis from before the trigger to the
            # end of the recording (docs/capture.md); _record holds one too (nested).
            async with capture_of(entry.driver, reason=f"bench test ({test.kind})"):
                await self._send(recording, plan.setup)
                await asyncio.sleep(PRE_TRIGGER_S)
                recording.t0 = self._clock()
                await self._send(recording, plan.trigger)
                if plan.trigger:
                    recording.trigger_acked = self._clock()
                self._update(recording, "recording", "triggered")
                limits = await self.limits(entry.info.id)
                exciter = (
                    asyncio.create_task(self._excite(recording))
                    if recording.excitation is not None
                    else None
                )
                try:
                    await self._record(recording, test, limits)
                    if exciter is not None and exciter.done():
                        exciter.result()  # a refused target ends the test (DriverError)
                finally:
                    if exciter is not None:
                        recording.ended = True
                        exciter.cancel()
                        with contextlib.suppress(asyncio.CancelledError, DriverError):
                            await exciter
            await self._send(recording, plan.finish)
            recording.ended = True
            if test.kind in POSITION_KINDS:
                # The profile of the test stays in force only for the test: the way
                # back is an ordinary move with the axis' own profile.
                if saved:
                    await self._restore(entry, saved)
                    saved = {}
                recording.returned = await self._return_to_start(recording, limits)
        except DriverError as exc:
            status, message = "incomplete", f"test stopped: {exc}"
            try:
                await entry.driver.stop()
            except DriverError:
                # The link is down: stop the axis the moment it is back.
                entry.stop_on_reconnect = True
                message += "; the axis will be stopped when its link is back"
        except asyncio.CancelledError:
            status, message = "incomplete", "server stopped during the test"
            with contextlib.suppress(DriverError):
                await entry.driver.stop()
            raise
        finally:
            try:
                if saved and status == "complete":
                    try:
                        await self._restore(entry, saved)
                    except DriverError as exc:
                        status = "incomplete"
                        changed = ", ".join(f"{k}={v}" for k, v in saved.items())
                        message = (
                            f"could not restore {changed} after the test ({exc}): re-apply them"
                        )
                elif saved:
                    try:
                        await self._restore(entry, saved)
                    except DriverError:
                        changed = ", ".join(f"{k}={v}" for k, v in saved.items())
                        message += f"; could not restore {changed}: re-apply them"
                await self._flush(recording)
            finally:
                self._active.pop(entry.info.id, None)
                if recording.returned is not None:
                    meta["return"] = recording.returned
                    if not recording.returned["ok"]:
                        message = "; ".join(
                            m for m in (message, recording.returned["message"]) if m
                        )
                meta["message"] = message
                meta["t0_s"] = recording.t0
                if recording.trigger_acked is not None and recording.t0 is not None:
                    # t0 is stamped before the trigger is sent; the device latched it
                    # before its reply came: the bound a prediction is aligned at.
                    meta["trigger_latency_s"] = round(recording.trigger_acked - recording.t0, 6)
                if recording.excitation is not None:
                    meta["excitation"] = recording.excitation.to_dict() | {"sent": recording.sent}
                meta["metrics"], meta["quality"] = self._metrics(recording, test, status, message)
                await asyncio.to_thread(self._storage.finish_run, recording.run_id, status, meta)
                self._update(recording, status, message or "done")

    async def _restore(self, entry: AxisEntry, saved: Mapping[str, int]) -> None:
        """Restore test overrides; some devices refuse while the axis still moves."""
        for attempt in range(20):
            try:
                await entry.driver.write_params(saved)
                return
            except DeviceRefusedError:
                if attempt == 19:
                    raise
                await asyncio.sleep(0.25)

    async def _record(self, recording: _Recording, test: BenchTest, limits: BenchLimits) -> None:
        # capture: whatever records an axis has its link devoted to it (docs/capture.md)
        async with capture_of(recording.entry.driver, reason="bench recording"):
            await self._record_samples(recording, test, limits)

    async def _record_samples(
        self, recording: _Recording, test: BenchTest, limits: BenchLimits
    ) -> None:
        plan = recording.plan
        assert recording.t0 is not None
        start = recording.t0
        first = recording.entry.latest
        origin = first.channels.get("position") if first is not None else None
        settled_since: float | None = None
        last_flush = self._clock()
        while True:
            await asyncio.sleep(0.05)
            now = self._clock()
            if now - last_flush >= FLUSH_PERIOD_S:
                last_flush = now
                await self._flush(recording)
                self._update(recording, "recording", f"{now - start:.1f} s")
            if self._hub.link_status(recording.entry.link.id).state != "connected":
                raise DriverError("the link went down during the test")
            if recording.abort is not None:
                raise DriverError(recording.abort)
            generation = recording.stop_generation
            if generation is not None and recording.entry.stop_generation != generation:
                raise DriverError("STOP was pressed during the test")
            if now - start >= test.duration_s:
                return
            latest = recording.entry.latest
            position = latest.channels.get("position") if latest is not None else None
            if position is not None and (why := limits.outside(position)):
                raise DriverError(f"left your travel window: {why}: axis stopped")
            if origin is not None and position is not None:
                # Velocity and PWM tests have no end position of their own: the travel
                # limit stops them. Moves are checked before they start.
                travel = abs(position - origin)
                if travel > limits.max_distance_counts * 1.05 + 100:
                    raise DriverError(
                        f"travel {travel:.0f} counts exceeded your limit of "
                        f"{limits.max_distance_counts}: axis stopped"
                    )
            if plan.done_flag and latest is not None and now - start > SETTLED_HOLD_S:
                moving = bool(plan.moving_flag and latest.flags.get(plan.moving_flag))
                if latest.flags.get(plan.done_flag) and not moving:
                    settled_since = settled_since or now
                    if now - settled_since >= SETTLED_HOLD_S:
                        return
                else:
                    settled_since = None

    def _metrics(
        self, recording: _Recording, test: BenchTest, status: str, message: str
    ) -> tuple[dict[str, Any] | None, dict[str, Any]]:
        """The run's metrics (untrusted ones null) and its quality (``runquality``)."""
        plan = recording.plan
        raw: dict[str, Any] | None = None
        if test.kind != frfbench.KIND and recording.t0 is not None and recording.samples:
            index = recording.columns.index(plan.response)
            rows = [r for r in recording.samples if r[index] is not None]
            if len(rows) >= 3:
                error_index = (
                    recording.columns.index("following_error")
                    if "following_error" in recording.columns
                    else None
                )
                flag_series = {
                    name: [bool(r[-1][i]) for r in rows] for i, name in enumerate(recording.flags)
                }
                raw = asdict(
                    compute_metrics(
                        [r[0] for r in rows],
                        [r[index] for r in rows],
                        t0_s=recording.t0,
                        y0=plan.y0,
                        y_final=plan.y_final,
                        band=plan.band,
                        following_error=(
                            [r[error_index] for r in rows] if error_index is not None else None
                        ),
                        flags=flag_series,
                    )
                )
        return assess(
            kind=test.kind,
            columns=recording.columns,
            flag_names=recording.flags,
            rows=recording.samples,
            t0_s=recording.t0,
            response=plan.response,
            y0=plan.y0,
            y_final=plan.y_final,
            band=plan.band,
            fault_flags=plan.fault_flags,
            done_flag=plan.done_flag,
            metrics=raw,
            status=status,
            message=message,
        )

    async def _wait_settled(
        self,
        recording: _Recording,
        timeout_s: float,
        target: float | None = None,
        tolerance: float = 0.0,
    ) -> bool:
        """Wait until the axis stands (done flag set, moving flag clear, and within
        ``tolerance`` of ``target`` if given) for SETTLED_HOLD_S; False on timeout.

        The target matters after a command: the next samples may still be the old ones
        (a polled line shows a move start only a poll later), which stand still too."""
        plan, entry = recording.plan, recording.entry
        deadline = self._clock() + timeout_s
        since: float | None = None
        while self._clock() < deadline:
            latest = entry.latest
            position = latest.channels.get("position") if latest is not None else None
            done = latest is not None and (
                (plan.done_flag is None or bool(latest.flags.get(plan.done_flag)))
                and not (plan.moving_flag and latest.flags.get(plan.moving_flag))
                and (
                    target is None or (position is not None and abs(position - target) <= tolerance)
                )
            )
            if done:
                since = since or self._clock()
                if self._clock() - since >= SETTLED_HOLD_S:
                    return True
            else:
                since = None
            generation = recording.stop_generation
            if generation is not None and entry.stop_generation != generation:
                raise DriverError("STOP was pressed during the test")
            await asyncio.sleep(0.05)
        return False

    async def _return_to_start(self, recording: _Recording, limits: BenchLimits) -> dict[str, Any]:
        """Move back to where the test started (a relative test must not walk the axis
        towards an end switch run by run), with the axis' own profile. Returns what
        happened: ``{"ok", "to", "error", "message"}``."""
        entry, plan = recording.entry, recording.plan
        driver = entry.driver
        assert isinstance(driver, BenchPlanner)
        if not await self._wait_settled(recording, RETURN_TIMEOUT_S):
            return {
                "ok": False,
                "to": plan.y0,
                "error": None,
                "message": "did not return to "
                "the start: the axis did not come to rest after the test",
            }
        latest = entry.latest
        assert latest is not None
        reference = latest.channels.get("setpoint")
        if reference is None:
            reference = latest.channels.get("position") or 0.0
        back = round(plan.y0 - reference)
        if back == 0:
            return {"ok": True, "to": plan.y0, "error": 0.0, "message": ""}
        if abs(back) > limits.max_distance_counts * 1.05 + 100:
            return {
                "ok": False,
                "to": plan.y0,
                "error": None,
                "message": f"did not return to "
                f"the start: {abs(back)} counts back exceed your max_distance_counts",
            }
        test = BenchTest(kind="move", distance=back, velocity=0, pwm=0, duration_s=0.0)
        way_back = driver.bench_plan(test, latest, entry.device_values)
        if why := limits.outside(way_back.y_final):
            return {
                "ok": False,
                "to": plan.y0,
                "error": None,
                "message": f"did not return to the start: {why}",
            }
        for name, args in (*way_back.setup, *way_back.trigger):
            validate_command(entry.driver.descriptor, name, args)
        self._update(recording, "recording", "returning to the start")
        await self._send(recording, way_back.setup)
        await self._send(recording, way_back.trigger)
        tolerance = max(plan.band or 0.0, 1.0) * 2
        settled = await self._wait_settled(
            recording, RETURN_TIMEOUT_S + 5.0, target=plan.y0, tolerance=tolerance
        )
        position = (entry.latest.channels.get("position") if entry.latest else None) or 0.0
        error = position - plan.y0
        if not settled or abs(error) > tolerance:
            return {
                "ok": False,
                "to": plan.y0,
                "error": round(error, 3),
                "message": f"did not return to the start: {error:+.0f} counts from it",
            }
        return {"ok": True, "to": plan.y0, "error": round(error, 3), "message": ""}

    def _update(self, recording: _Recording, status: str, message: str) -> None:
        elapsed = self._clock() - recording.t0 if recording.t0 is not None else 0.0
        self._hub.broadcast_model(
            RunUpdate(
                axis=recording.entry.info.id,
                run_id=recording.run_id,
                status=status,  # type: ignore[arg-type]
                elapsed_s=round(elapsed, 2),
                samples=len(recording.samples),
                message=message,
            )
        )

    # --- stored runs ------------------------------------------------------------------
    # Reading, exporting and importing go through worker threads in small pieces
    # (servotune.runio): a run of tens of megabytes must never hold the event loop.

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
            yield (await asyncio.to_thread(runio.run_json_head, run)).encode()
            first = True
            for seq in seqs:
                rows = await asyncio.to_thread(runio.chunk_rows_text, self._storage, run_id, seq)
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
            yield runio.csv_header(run).encode()
            for seq in seqs:
                text = await asyncio.to_thread(runio.chunk_csv, self._storage, run_id, seq)
                yield text.encode()

        return body()

    async def delete_run(self, run_id: str) -> None:
        if not await asyncio.to_thread(self._storage.delete_run, run_id):
            raise KeyError(run_id)

    async def set_baseline(self, run_id: str) -> None:
        if not await asyncio.to_thread(self._storage.set_baseline, run_id):
            raise KeyError(run_id)

    async def import_run(self, axis_id: str, body_path: Path, meta: bytes | None = None) -> str:
        """Import a run in a separate process (see ``runio``); returns the new run id.

        ``body_path``: the JSON body ``{"meta", "csv"}``, or with ``meta`` (the
        run.json of a multipart upload) the CSV file. 422 naming the field, 507 if the
        database cannot be written."""
        entry = self._hub.entry(axis_id)
        if self._storage.problem:
            raise StorageError(f"not saved: {self._storage.problem}")
        if self._pool is None:
            # One import at a time, each in a fresh process (its memory goes with it).
            self._pool = ProcessPoolExecutor(
                max_workers=1,
                mp_context=multiprocessing.get_context("spawn"),
                max_tasks_per_child=1,
            )
        outcome = await asyncio.get_running_loop().run_in_executor(
            self._pool,
            functools.partial(
                runio.import_in_process,
                str(self._storage.path),
                entry.storage_key,
                axis_id,
                entry.info.device,
                str(body_path),
                meta,
            ),
        )
        kind, value, message = outcome
        if kind == "invalid":
            raise InvalidArgumentError(value, message)
        if kind == "storage":
            raise StorageError(message)
        return value
