"""What every device's tuner needs from the live system, in one place.

``TuningContext`` wraps the ``Hub`` (validated commands and writes, the samples, the
stop generations) and the ``TestBench`` (recorded tests). The service
(``autotune.service.AutoTuner``) owns one and hands it to each device's tuner, so
the tuners never reach into the service: the imports run one way,
service -> device tuners -> context.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from itertools import pairwise
from typing import Any, Final

from servotune.bench.service import BenchTestRequest, TestBench
from servotune.compute import ComputePool
from servotune.hub.hub import Hub
from servotune.hub.state import AxisEntry
from servotune.link.base import BenchKind, DeviceRefusedError, DriverError, Sample

# "No telemetry" means the link is down, not that a loaded host polled late: a link
# that delivers nothing for this long is also shown down by its status.
SAMPLE_TIMEOUT_S: Final = 2.0
RUN_GRACE_S: Final = 15.0  # a recorded test may finish this much after its duration
# At rest before an identification: the position watched this long (and over at least
# REST_SAMPLES samples) must stay within REST_SPREAD_COUNTS. An axis ringing in a limit
# cycle shows no move flag (the profile has ended) and may read no velocity at the
# sample that happens to fall on a turning point; an identification started on it
# would fit the ring and report "the shaft did not move".
REST_WINDOW_S: Final = 0.3
REST_SAMPLES: Final = 3
REST_SPREAD_COUNTS: Final = 20.0


class TuningContext:
    """Hub, bench, clock, the worker process for fits and gain searches (``compute``:
    never a thread, see servotune.compute) and the per-axis stop generation of the
    running sequence."""

    def __init__(
        self, hub: Hub, bench: TestBench, clock: Callable[[], float], compute: ComputePool
    ) -> None:
        self.hub = hub
        self.bench = bench
        self.clock = clock
        self.compute = compute
        # Per axis: the stop generation when the running sequence started.
        self.generations: dict[str, int] = {}
        self._sample_events: dict[str, asyncio.Event] = {}
        self._watched: dict[str, list[tuple[float, float]]] = {}  # axis -> (t, position)
        hub.add_sample_listener(self._on_sample)

    # --- samples ----------------------------------------------------------------------

    def _on_sample(self, axis_id: str, sample: Sample) -> None:
        event = self._sample_events.get(axis_id)
        if event is not None:
            event.set()
        watched = self._watched.get(axis_id)
        position = sample.channels.get("position")
        if watched is not None and position is not None:
            watched.append((sample.t, float(position)))

    async def next_sample(self, entry: AxisEntry) -> Sample:
        """The axis' next sample; DriverError if none comes for ``SAMPLE_TIMEOUT_S``."""
        sample = await self.sample_before(entry, self.clock() + SAMPLE_TIMEOUT_S)
        if sample is None:
            raise DriverError("no telemetry from the axis: is the link up?")
        return sample

    async def sample_before(self, entry: AxisEntry, until: float) -> Sample | None:
        """The axis' next sample, or None if the clock reaches ``until`` first."""
        event = self._sample_events.setdefault(entry.info.id, asyncio.Event())
        event.clear()
        try:
            await asyncio.wait_for(event.wait(), max(0.0, until - self.clock()))
        except TimeoutError:
            return None
        return entry.latest

    @staticmethod
    def position(sample: Sample | None) -> float:
        value = sample.channels.get("position") if sample is not None else None
        if value is None:
            raise DeviceRefusedError("the axis reports no position yet")
        return float(value)

    # --- commands ---------------------------------------------------------------------

    def started(self, entry: AxisEntry) -> None:
        """A sequence starts: from now on a user's STOP ends it (see ``command``)."""
        self.generations[entry.info.id] = entry.stop_generation

    def stopped(self, entry: AxisEntry) -> bool:
        """Whether the user pressed STOP since the sequence started."""
        return self.generations.get(entry.info.id) != entry.stop_generation

    async def command(self, entry: AxisEntry, name: str, args: dict[str, int]) -> float:
        """Send a command through the hub (validated); returns its round trip."""
        sent = self.clock()
        # A user's STOP during identification or verification ends the sequence:
        # the hub refuses every later step (stop generation), nothing moves again.
        await self.hub.command(
            entry.info.id,
            name,
            args,
            origin="autotune",
            stop_generation=self.generations.get(entry.info.id),
        )
        return self.clock() - sent

    async def safe_stop(self, entry: AxisEntry) -> None:
        """A controlled stop that keeps holding (the hub's stop service), unless the loop
        is not working; the axis is watched until it is at rest."""
        try:
            await self.hub.stops.stop(entry.info.id, "controlled", "auto-tune: stop")
        except DriverError:
            self.hub.pend_stop(entry)
            self.hub.on_event(
                "error", entry.info.id, "auto-tune: stop failed; repeated when the link is back"
            )

    # --- checks and tests -------------------------------------------------------------

    def test_running(self, entry: AxisEntry) -> bool:
        return self.bench.test_running(entry.info.id)

    def connected(self, entry: AxisEntry) -> bool:
        return entry.latest is not None and self.hub.link_status(entry.link.id).state == "connected"

    async def check_at_rest(self, entry: AxisEntry) -> None:
        """Refuse (409) an axis whose position moves by more than
        ``REST_SPREAD_COUNTS`` over ``REST_WINDOW_S``, whatever its flags say."""
        watched = self._watched[entry.info.id] = []
        try:
            deadline = self.clock() + REST_WINDOW_S + SAMPLE_TIMEOUT_S
            while self.clock() < deadline:
                await self.sample_before(entry, deadline)
                if len(watched) >= REST_SAMPLES and watched[-1][0] - watched[0][0] >= REST_WINDOW_S:
                    break
        finally:
            self._watched.pop(entry.info.id, None)
        if len(watched) < 2:
            raise DriverError("no telemetry from the axis: is the link up?")
        positions = [p for _, p in watched]
        spread = max(positions) - min(positions)
        if spread <= REST_SPREAD_COUNTS:
            return
        speed = max(
            (abs(pb - pa) / (tb - ta) for (ta, pa), (tb, pb) in pairwise(watched) if tb > ta),
            default=0.0,
        )
        raise DeviceRefusedError(
            f"the axis is moving: up to {speed:,.0f} counts/s, {spread:,.0f} counts of travel "
            f"in {watched[-1][0] - watched[0][0]:.1f} s although no move is running (ringing?): "
            "an identification needs it at rest — stop or hold it first"
        )

    def check_idle(self, entry: AxisEntry) -> None:
        if self.test_running(entry):
            raise DeviceRefusedError("a test is already running on this axis")
        if entry.latest is None or not self.connected(entry):
            raise DeviceRefusedError("the axis is not connected: no telemetry")
        flags = entry.latest.flags
        # SLAP2: a move or velocity mode; Z1100: a running motor.
        if flags.get("move") or flags.get("vm") or flags.get("running"):
            raise DeviceRefusedError("the axis is moving: wait until it stands still")

    async def run_test(
        self,
        entry: AxisEntry,
        kind: BenchKind,
        distance: int,
        wanted_s: float,
        note: str,
        *,
        samples: bool = False,
        restore_gains: dict[str, int] | None = None,
        oscillation_is_a_result: bool = False,
    ) -> dict[str, Any]:
        """Run a bench test of ``kind`` (recorded like any other) and wait for it:
        ``wanted_s`` long at most the bench's duration limit. Returns its metadata
        (with ``samples``: the whole run); DriverError when it does not complete, or
        when it left the axis oscillating or its loop could not be verified after it
        (the bench then brought it to rest and put ``restore_gains`` back, default the
        gains in force when it started) unless ``oscillation_is_a_result`` (a baseline
        of gains that may oscillate: the run, with its ``left_oscillating`` or
        ``loop_unverified``, is returned; the axis is at rest, maybe unpowered)."""
        limits = await self.bench.limits(entry.info.id)
        duration = min(limits.max_duration_s, wanted_s)
        started = await self.bench.start_run(
            entry.info.id,
            BenchTestRequest(kind=kind, distance=distance, duration_s=duration, note=note),
            restore_gains=restore_gains,
        )
        run_id: str = started["id"]
        deadline = self.clock() + duration + RUN_GRACE_S
        while self.clock() < deadline:
            await asyncio.sleep(0.1)
            run = await self.bench.get_run_meta(run_id)  # status only: no samples
            if run["status"] != "recording":
                if run["status"] != "complete":
                    raise DriverError(f"test {run_id} {run['status']}: {run.get('message')}")
                left = run.get("left_oscillating") or run.get("loop_unverified")
                if left and not oscillation_is_a_result:
                    raise DriverError(f"test {run_id}: {left['message']}")
                return await self.bench.get_run(run_id) if samples else run
        raise DriverError(f"test {run_id} did not finish")
