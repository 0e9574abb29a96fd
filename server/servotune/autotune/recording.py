"""The SLAP2 identification recorded as an ordinary bench run."""

from __future__ import annotations

import asyncio
import contextlib
import time
import uuid
from collections.abc import Callable
from typing import Any

from servotune.bench.runner import _Recording, run_meta
from servotune.bench.service import TestBench
from servotune.hub.state import AxisEntry
from servotune.link.base import BenchPlan, DeviceRefusedError, capture_of


class IdentificationRun:
    """The identification recorded as a bench run, with the bench's own recorder.

    ``TestBench`` has no public way to record a sequence it does not drive itself, so
    this registers a recording in the bench's table of active runs (which also makes
    the bench refuse other tests on the axis meanwhile), stores it like any run and
    reports it with the bench's ``run`` messages. It uses TestBench internals on
    purpose, in one place: the candidate for a ``TestBench.record()`` method.
    """

    def __init__(
        self, bench: TestBench, entry: AxisEntry, p0: float, max_pwm: int, start_pwm: int
    ) -> None:
        """``start_pwm``: the staircase's first step (the recording's trigger)."""
        self.bench = bench
        self.entry = entry
        plan = BenchPlan(
            setup=[],
            trigger=[("open_loop_pwm", {"pwm": start_pwm})],
            finish=[("open_loop_pwm", {"pwm": 0}), ("stop", {})],
            response="position",
            y0=p0,
            y_final=p0,
            band=None,
        )
        self.run_id = uuid.uuid4().hex[:12]
        test = {
            "kind": "pwm_step",
            "distance": 0,
            "velocity": 0,
            "pwm": max_pwm,
            "duration_s": 0.0,
            "note": "auto-tune identification: open-loop PWM staircase",
        }
        self.meta: dict[str, Any] = run_meta(entry, test, plan)
        self.recording = _Recording(
            self.run_id, entry, plan, self.meta["columns"], self.meta["flags"]
        )
        # The link polls this axis only while the run records (docs/capture.md).
        self._capture = contextlib.AsyncExitStack()

    @property
    def samples(self) -> list[list[Any]]:
        return self.recording.samples

    @property
    def columns(self) -> list[str]:
        return self.recording.columns

    async def open(self, clock: Callable[[], float]) -> None:
        axis_id = self.entry.info.id
        if axis_id in self.bench._active:
            raise DeviceRefusedError("a test is already running on this axis")
        self.bench._active[axis_id] = self.recording  # the bench refuses tests from now
        try:
            await asyncio.to_thread(
                self.bench._storage.create_run,
                self.run_id,
                self.entry.storage_key,
                axis_id,
                time.time(),
                self.meta,
            )
        except BaseException:
            self.bench._active.pop(axis_id, None)
            raise
        await self._capture.enter_async_context(
            capture_of(self.entry.driver, reason="auto-tune identification")
        )
        self.recording.t0 = clock()
        self.bench._update(self.recording, "recording", "auto-tune identification")

    def progress(self, message: str) -> None:
        self.bench._update(self.recording, "recording", message)

    async def close(self, status: str, message: str, extra: dict[str, Any]) -> None:
        try:
            await self._capture.aclose()
            await self.bench._flush(self.recording)
        finally:
            self.bench._active.pop(self.entry.info.id, None)
            self.meta["message"] = message
            self.meta["autotune"] = extra
            if self.recording.t0 is not None:
                self.meta["test"]["duration_s"] = round(
                    self.samples[-1][0] - self.recording.t0 if self.samples else 0.0, 3
                )
            await asyncio.to_thread(self.bench._storage.finish_run, self.run_id, status, self.meta)
            self.bench._update(self.recording, status, message or "done")
