"""One bench test while it runs: the recorder, the test's sequence and its record.

What lives here is everything between "the test is planned and stored" and "the run is
finished in the store": the recording of every sample the link delivers
(``Recording``, ``Runner.on_sample``), the chunks flushed to SQLite every half
second, the sequence of one test (overrides written, setup, trigger, the record until
the duration is over or the axis has settled, the multisine of a frequency response,
finish, the return to the start, the overrides restored), the checks that stop a test
while it runs (link down, STOP, travel window, distance), its metrics and quality, and
the ``run`` messages. The limits the run is held to are ``servotune.bench.limits``
(``BenchLimits`` is importable from here too).

The seam: ``servotune.bench.service`` is the bench's front desk (refusals before anything
moves, planning, the stored runs, export and import); this module is what happens after
the desk has said yes. ``TestBench`` has one ``Runner``, the ``ActiveRuns`` it shares
with it (which axis records what) and the ``LimitsStore`` both read.

``ExternalRecording`` records with this recorder a sequence its caller drives itself
(the auto-tune's identification, through ``TestBench.record``).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from servotune.bench.kinds import FLAGS_T_COLUMN, TestKind
from servotune.bench.limits import BenchLimits as BenchLimits  # importable from here too
from servotune.bench.limits import LimitsStore
from servotune.bench.quality import assess
from servotune.hub.hub import Hub
from servotune.hub.state import AxisEntry
from servotune.hub.stops import Settled, gains_of
from servotune.link.base import (
    BenchPlan,
    BenchPlanner,
    BenchTest,
    CommandClock,
    DeviceRefusedError,
    DriverError,
    Sample,
    capture_of,
)
from servotune.link.validation import validate_command
from servotune.schema import RunUpdate
from servotune.storage import Storage
from servotune.tuning.frfrun import Excitation

PRE_TRIGGER_S = 0.2
FLUSH_PERIOD_S = 0.5
SETTLED_HOLD_S = 0.3
RETURN_TIMEOUT_S = 5.0  # after the return move's profile time


@dataclass(slots=True)
class Recording:
    """One run while it records: its plan, its samples and how it went."""

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
    # [t, span] of the samples whose latch span the driver knows (the quality judgement
    # of every run; stored with a frequency_response's excitation)
    spans: list[list[float]] = field(default_factory=list)
    trigger_acked: float | None = None  # when the device acknowledged the trigger
    abort: str | None = None  # why the exciter stopped the axis (ends the record)
    # The gains to put back if the run leaves the axis oscillating (None: the gains in
    # force when the run started; the auto-tune passes the ones before its proposal).
    restore_gains: dict[str, int] | None = None


def left_oscillating(quality: dict[str, Any], settled: Settled) -> dict[str, Any]:
    """The run's quality with what the check after it found first: the axis left
    oscillating (``bad``), or its loop not verified (``loop_unverified``: at least
    ``doubtful``)."""
    if settled.found == "oscillating":
        code, status = "left_oscillating", "bad"
    else:
        code = "loop_unverified"
        status = "bad" if quality.get("status") == "bad" else "doubtful"
    reason = {"code": code, "message": settled.message}
    return {**quality, "status": status, "reasons": [reason, *quality.get("reasons", [])]}


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
        "columns": ["t_s", *(c.name for c in descriptor.channels), FLAGS_T_COLUMN],
        "flags": [f.name for f in descriptor.flags],
        "metrics": None,
        "message": "",
    }


def _value(x: float | None) -> float | None:
    return None if x is None or (isinstance(x, float) and math.isnan(x)) else float(x)


class ActiveRuns:
    """Which axis records which run: one test at a time per axis.

    An axis is *running* from the moment its recording is registered until the run is
    finished in the store; it is *busy* also while a start is being checked and planned
    (claimed before the first await, so a second request cannot slip in)."""

    def __init__(self) -> None:
        self._recordings: dict[str, Recording] = {}
        self._claimed: set[str] = set()

    def running(self, axis_id: str) -> bool:
        return axis_id in self._recordings

    def busy(self, axis_id: str) -> bool:
        return axis_id in self._recordings or axis_id in self._claimed

    def get(self, axis_id: str) -> Recording | None:
        return self._recordings.get(axis_id)

    def add(self, axis_id: str, recording: Recording) -> None:
        self._recordings[axis_id] = recording

    def discard(self, axis_id: str) -> None:
        self._recordings.pop(axis_id, None)

    @contextlib.contextmanager
    def claim(self, axis_id: str) -> Iterator[None]:
        """Hold ``axis_id`` busy for the block (the caller checked ``busy`` first)."""
        self._claimed.add(axis_id)
        try:
            yield
        finally:
            self._claimed.discard(axis_id)


class Runner:
    """Runs one planned test on its axis and records it.

    ``run`` is the whole test, started as a task once the run is stored; it always
    finishes the run in the store (complete or incomplete, with its metrics) and leaves
    the axis stopped (or to be stopped when its link is back) if anything went wrong.
    ``on_sample`` is the hub's sample listener that feeds every running recording."""

    def __init__(
        self,
        hub: Hub,
        storage: Storage,
        clock: Callable[[], float],
        active: ActiveRuns,
        limits: LimitsStore,
    ) -> None:
        """``clock``: monotonic seconds; ``limits``: the user's limits of each axis (a
        run reads them after the trigger, the exciter when it starts)."""
        self._hub = hub
        self._storage = storage
        self._clock = clock
        self._active = active
        self._limits = limits

    @property
    def storage(self) -> Storage:
        return self._storage

    async def _excite(self, recording: Recording) -> None:
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
        limits = await self._limits.get(axis)
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
                await self._hub.stops.stop(axis, "controlled", "bench: travel window")
                return
            await self._hub.command(
                axis,
                excitation.command,
                {excitation.argument: target},
                origin="bench",
                stop_generation=recording.stop_generation,
            )
            # [acknowledged, target, latched, span]: the analysis replays the profile
            # from the latch, which lies up to span before it (a host stall,
            # tuning.frftrust). The acknowledgement is stamped when the command returns,
            # after the status read (rss) the driver may send right after the ma: late
            # and jittery.
            driver = recording.entry.driver
            latch = driver.last_command_latch_s if isinstance(driver, CommandClock) else None
            span = driver.last_command_latch_span_s if isinstance(driver, CommandClock) else None
            recording.sent.append(
                [round(self._clock(), 6), float(target)]
                + ([round(latch, 6)] if latch is not None else [])
                + ([round(span, 6)] if latch is not None and span is not None else [])
            )
            last = target

    def on_sample(self, axis_id: str, sample: Sample) -> None:
        recording = self._active.get(axis_id)
        if recording is None or recording.ended:
            return
        row: list[Any] = [round(sample.t, 6)]
        row += [
            round(sample.t if sample.flags_t is None else sample.flags_t, 6)
            if name == FLAGS_T_COLUMN
            else _value(sample.channels.get(name))
            for name in recording.columns[1:]
        ]
        row.append([int(bool(sample.flags.get(name))) for name in recording.flags])
        recording.samples.append(row)
        if sample.t_span_s is not None:
            recording.spans.append([row[0], round(sample.t_span_s, 6)])

    async def flush(self, recording: Recording) -> None:
        rows = recording.samples[recording.flushed :]
        if not rows:
            return
        recording.flushed = len(recording.samples)
        seq = recording.chunk_seq
        recording.chunk_seq += 1
        await asyncio.to_thread(self._storage.append_samples, recording.run_id, seq, rows)

    async def _send(self, recording: Recording, steps: list[tuple[str, dict[str, int]]]) -> None:
        for name, args in steps:
            await self._hub.command(
                recording.entry.info.id,
                name,
                args,
                origin="bench",
                stop_generation=recording.stop_generation,
            )

    async def run(
        self, recording: Recording, test: BenchTest, meta: dict[str, Any], kind: TestKind
    ) -> None:
        entry, plan = recording.entry, recording.plan
        status, message = "complete", ""
        saved: dict[str, int] = {}
        gains_before = gains_of(entry.driver.descriptor, entry.device_values)
        settled: Settled | None = None
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
                self.update(recording, "recording", "triggered")
                limits = await self._limits.get(entry.info.id)
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
            if kind.returns_to_start:
                # The profile of the test stays in force only for the test: the way
                # back is an ordinary move with the axis' own profile.
                if saved:
                    await self._restore(entry, saved)
                    saved = {}
                recording.returned = await self._return_to_start(recording, limits)
        except DriverError as exc:
            status, message = "incomplete", f"test stopped: {exc}"
            try:
                await self._hub.stops.stop(entry.info.id, "controlled", "bench: test stopped")
            except DriverError:
                # The link is down: stop the axis the moment it is back.
                self._hub.pend_stop(entry)
                message += "; the axis will be stopped when its link is back"
        except asyncio.CancelledError:
            status, message = "incomplete", "server stopped during the test"
            with contextlib.suppress(DriverError):
                await self._hub.stops.stop(entry.info.id, "controlled", "bench: server stopping")
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
                await self.flush(recording)
                settled = await self._settle(recording, gains_before)
            finally:
                self._active.discard(entry.info.id)
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
                    meta["excitation"] = recording.excitation.to_dict() | {
                        "sent": recording.sent,
                        "spans": recording.spans,
                    }
                meta["metrics"], meta["quality"] = self._metrics(
                    recording, test, kind, status, message
                )
                if settled is not None:
                    key = (
                        "left_oscillating" if settled.found == "oscillating" else "loop_unverified"
                    )
                    meta[key] = settled.as_dict()
                    meta["quality"] = left_oscillating(meta["quality"], settled)
                await asyncio.to_thread(self._storage.finish_run, recording.run_id, status, meta)
                self.update(recording, status, message or "done")

    async def _settle(self, recording: Recording, gains_before: dict[str, int]) -> Settled | None:
        """Nothing the bench started is left oscillating (``StopService.settle_check``):
        unless the user's STOP ended the run (its own watch follows it) or the link is
        down. The gains put back: the caller's, else those in force before the run, else
        (when the run did not change them) the last verified ones."""
        entry = recording.entry
        generation = recording.stop_generation
        if generation is not None and entry.stop_generation != generation:
            return None
        if self._hub.link_status(entry.link.id).state != "connected":
            return None
        restore = recording.restore_gains or gains_before
        now = gains_of(entry.driver.descriptor, entry.device_values)
        if restore == now:
            restore = self._hub.verified_gains.get(entry.info.id, restore)
        try:
            return await self._hub.stops.settle_check(
                entry.info.id,
                gains_now=now,
                restore=restore,
                reason=f"bench run {recording.run_id}",
            )
        except DriverError as exc:
            self._hub.on_event(
                "error", entry.info.id, f"bench run {recording.run_id}: after the run: {exc}"
            )
            return None

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

    async def _record(self, recording: Recording, test: BenchTest, limits: BenchLimits) -> None:
        # capture: whatever records an axis has its link devoted to it (docs/capture.md)
        async with capture_of(recording.entry.driver, reason="bench recording"):
            await self._record_samples(recording, test, limits)

    async def _record_samples(
        self, recording: Recording, test: BenchTest, limits: BenchLimits
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
                await self.flush(recording)
                self.update(recording, "recording", f"{now - start:.1f} s")
            if self._hub.link_status(recording.entry.link.id).state != "connected":
                raise DriverError("the link went down during the test")
            if recording.abort is not None:
                raise DriverError(recording.abort)
            generation = recording.stop_generation
            if generation is not None and recording.entry.stop_generation != generation:
                raise DriverError(f"{recording.entry.stop_cause} during the test")
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
        self, recording: Recording, test: BenchTest, kind: TestKind, status: str, message: str
    ) -> tuple[dict[str, Any] | None, dict[str, Any]]:
        """The run's metrics (the kind's; untrusted ones null) and its quality
        (``bench.quality``)."""
        plan = recording.plan
        raw = kind.metrics(recording)
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
            spans=recording.spans,
        )

    async def _wait_settled(
        self,
        recording: Recording,
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
                raise DriverError(f"{entry.stop_cause} during the test")
            if self._hub.stops.verdict(entry.info.id).working is False:
                return False  # it oscillates: no use waiting (``_settle`` acts on it)
            await asyncio.sleep(0.05)
        return False

    async def _return_to_start(self, recording: Recording, limits: BenchLimits) -> dict[str, Any]:
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
        self.update(recording, "recording", "returning to the start")
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

    def update(self, recording: Recording, status: str, message: str) -> None:
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


class ExternalRecording:
    """A run recorded by the bench's recorder while its caller drives the axis.

    Made by ``TestBench.record``: the run is stored and the axis counts as running (the
    bench refuses other tests on it) from then until ``finish``. The caller stamps the
    start with ``begin``, reports with ``progress`` and always calls ``finish``."""

    def __init__(
        self, runner: Runner, active: ActiveRuns, recording: Recording, meta: dict[str, Any]
    ) -> None:
        self._runner = runner
        self._active = active
        self.recording = recording
        self.meta = meta

    @property
    def run_id(self) -> str:
        return self.recording.run_id

    @property
    def samples(self) -> list[list[Any]]:
        return self.recording.samples

    @property
    def columns(self) -> list[str]:
        return self.recording.columns

    def begin(self, t0: float, message: str) -> None:
        """The record starts at ``t0`` (the runner's clock)."""
        self.recording.t0 = t0
        self._runner.update(self.recording, "recording", message)

    def progress(self, message: str) -> None:
        self._runner.update(self.recording, "recording", message)

    async def finish(self, status: str, message: str, meta: Mapping[str, Any]) -> None:
        """Flush the samples, free the axis and finish the run in the store with
        ``meta`` added to its metadata; the test's duration becomes the recorded span."""
        try:
            await self._runner.flush(self.recording)
        finally:
            self._active.discard(self.recording.entry.info.id)
            self.meta["message"] = message
            self.meta.update(meta)
            if self.recording.t0 is not None:
                self.meta["test"]["duration_s"] = round(
                    self.samples[-1][0] - self.recording.t0 if self.samples else 0.0, 3
                )
            await asyncio.to_thread(self._runner.storage.finish_run, self.run_id, status, self.meta)
            self._runner.update(self.recording, status, message or "done")
