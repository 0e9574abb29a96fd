"""The SLAP2 identification recorded as an ordinary bench run."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Any

from servotune.bench.runner import ExternalRecording
from servotune.bench.service import TestBench
from servotune.hub.state import AxisEntry
from servotune.link.base import BenchPlan, capture_of


class IdentificationRun:
    """The identification recorded as a bench run, with the bench's own recorder
    (``TestBench.record``): stored like any run, reported with the bench's ``run``
    messages, and the bench refuses other tests on the axis meanwhile."""

    def __init__(
        self, bench: TestBench, entry: AxisEntry, p0: float, max_pwm: int, start_pwm: int
    ) -> None:
        """``start_pwm``: the staircase's first step (the recording's trigger)."""
        self.bench = bench
        self.entry = entry
        self._plan = BenchPlan(
            setup=[],
            trigger=[("open_loop_pwm", {"pwm": start_pwm})],
            finish=[("open_loop_pwm", {"pwm": 0}), ("stop", {})],
            response="position",
            y0=p0,
            y_final=p0,
            band=None,
        )
        self._test: dict[str, Any] = {
            "kind": "pwm_step",
            "distance": 0,
            "velocity": 0,
            "pwm": max_pwm,
            "duration_s": 0.0,
            "note": "auto-tune identification: open-loop PWM staircase",
        }
        self._run: ExternalRecording | None = None
        # The link polls this axis only while the run records (docs/capture.md).
        self._capture = contextlib.AsyncExitStack()

    @property
    def run(self) -> ExternalRecording:
        if self._run is None:
            raise RuntimeError("the identification run is not open")
        return self._run

    @property
    def run_id(self) -> str:
        return self.run.run_id

    @property
    def samples(self) -> list[list[Any]]:
        return self.run.samples

    @property
    def columns(self) -> list[str]:
        return self.run.columns

    async def open(self, clock: Callable[[], float]) -> None:
        """409 if a test already records on the axis."""
        self._run = await self.bench.record(self.entry, self._test, self._plan)
        await self._capture.enter_async_context(
            capture_of(self.entry.driver, reason="auto-tune identification")
        )
        self._run.begin(clock(), "auto-tune identification")

    def progress(self, message: str) -> None:
        self.run.progress(message)

    async def close(self, status: str, message: str, extra: dict[str, Any]) -> None:
        try:
            await self._capture.aclose()
        finally:
            await self.run.finish(status, message, {"autotune": extra})
