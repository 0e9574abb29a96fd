"""The check after a bench run or an auto-tune step (``StopService.settle_check``) acts
on evidence only: telemetry too sparse to judge the loop is never passed as "at rest" or
"working". Telemetry is injected with its own timestamps on virtual time (the service's
clock and pauses are the test's), so nothing depends on the host's speed."""

from __future__ import annotations

import asyncio
import math
from collections import deque
from typing import Any

from servotune.bench.runner import left_oscillating
from servotune.devices.slap2.descriptor import slap2_descriptor
from servotune.hub.stops import SETTLE_EVIDENCE_S, SETTLE_WATCH_S, Settled, StopService
from servotune.link.base import Sample
from tests.support.stop_driver import RecordingStops

T0 = 100.0  # the virtual clock when the run ended
BEFORE = {"kp": 600, "ki": 10, "kd": 1500}  # the gains in force before the run
NOW = {"kp": 900, "ki": 10, "kd": 1500}  # the gains the run left


class Driver(RecordingStops):
    """A driver with the stop modes whose brake is its power-off (a Z1100-like one):
    records what it is asked for and sends nothing."""

    def __init__(self) -> None:
        super().__init__(brake_action="power_off")
        self.written: list[dict[str, int]] = []

    async def write_params(self, values: dict[str, int]) -> dict[str, Any]:
        self.written.append(dict(values))
        return {}


class VirtualTime:
    """The service's clock and its pause: a pause moves the clock on and delivers the
    samples due by then (each arrives at ``T0`` plus its own timestamp)."""

    def __init__(self, samples: list[Sample]) -> None:
        self.now = T0
        self.due: deque[Sample] = deque(samples)
        self.service: StopService | None = None

    def __call__(self) -> float:
        return self.now

    async def sleep(self, delay_s: float) -> None:
        self.now += delay_s
        assert self.service is not None
        while self.due and T0 + self.due[0].t <= self.now:
            self.service.on_sample("a", self.due.popleft())
        await asyncio.sleep(0)


def held(t: float, error: float) -> Sample:
    return Sample(
        t,
        {"position": 2000.0 - error, "following_error": error, "setpoint": 2000.0},
        {"pm": True, "vm": False, "move": False, "oc": False},
    )


def quiet(times: list[float]) -> list[Sample]:
    return [held(t, 3.0) for t in times]


def limit_cycle(times: list[float]) -> list[Sample]:
    """The loaded SLAP2's limit cycle (±1900 counts at 9.7 Hz around a held setpoint)."""
    return [held(t, 1900 * math.sin(2 * math.pi * 9.7 * t)) for t in times]


def every(gap_s: float, start_s: float = 0.01, end_s: float = 8.0) -> list[float]:
    return [start_s + i * gap_s for i in range(int((end_s - start_s) / gap_s) + 1)]


async def settle(
    samples: list[Sample], gains_now: dict[str, int] = NOW
) -> tuple[Settled | None, Driver, list[tuple[str, str]]]:
    """One sample before the run's end (the service's mark), then ``samples`` as they
    arrive while the check runs (the run left ``gains_now``); returns what it found,
    the driver and the events."""
    time = VirtualTime(samples)
    events: list[tuple[str, str]] = []
    service = StopService(
        lambda level, axis, message: events.append((level, message)),
        clock=time,
        sleep=time.sleep,
    )
    time.service = service
    driver = Driver()
    service.add_axis("a", driver, slap2_descriptor(1))  # type: ignore[arg-type]
    service.on_sample("a", held(-0.01, 3.0))
    settled = await service.settle_check(
        "a", gains_now=gains_now, restore=BEFORE, reason="bench run r1"
    )
    await service.close()
    return settled, driver, events


async def test_a_quiet_loop_densely_seen_is_at_rest_and_nothing_is_sent() -> None:
    settled, driver, events = await settle(quiet(every(0.05)))
    assert settled is None and driver.asked == [] and events == []


async def test_a_limit_cycle_densely_seen_is_braked_and_holds_with_the_gains_before() -> None:
    settled, driver, events = await settle(limit_cycle(every(1 / 68)))
    assert settled is not None and settled.found == "oscillating", settled
    assert driver.asked == ["brake", "hold_here"] and driver.written == [BEFORE]
    assert events[0][0] == "error" and "left the axis oscillating" in events[0][1]


async def test_telemetry_with_holes_throughout_is_not_verified_and_acted_on() -> None:
    # A starved host: a quiet axis seen every 0.22 s - two samples 0.22 s apart look
    # "at rest", but a gap that long can hide a whole swing of a limit cycle.
    settled, driver, events = await settle(quiet(every(0.22)))
    assert settled is not None and settled.found == "unverified", settled
    assert "telemetry too sparse" in settled.reason
    # As if it oscillated: brought to rest without the loop, the gains in force before
    # the run written back, and holding again (watched).
    assert driver.asked == ["brake", "hold_here"] and driver.written == [BEFORE]
    assert settled.restored == BEFORE and settled.holds
    level, message = events[0]
    assert level == "warning" and "could not verify that the loop works" in message
    assert "holding under power" in message


async def test_no_telemetry_after_the_run_is_not_verified() -> None:
    settled, driver, _ = await settle([])
    assert settled is not None and settled.found == "unverified"
    assert "no telemetry came after it" in settled.reason
    assert driver.asked == ["brake", "hold_here"]


async def test_unverified_with_no_other_gains_still_holds() -> None:
    # Nothing showed the gains in force to oscillate: the axis holds with them again
    # (only a loop seen not working is left unpowered).
    settled, driver, _ = await settle(quiet(every(0.3)), gains_now=BEFORE)
    assert settled is not None and settled.found == "unverified" and settled.holds
    assert settled.restored is None and driver.written == []
    assert driver.asked == ["brake", "hold_here"]


async def test_holes_that_end_in_time_are_waited_out_and_judged() -> None:
    # Sparse for longer than the watch, then dense and quiet: more telemetry, in the
    # bounded time, settles it without acting.
    sparse_until = SETTLE_WATCH_S + 1.0
    assert sparse_until + 0.5 < SETTLE_WATCH_S + SETTLE_EVIDENCE_S
    samples = quiet(every(0.3, end_s=sparse_until) + every(0.05, start_s=sparse_until + 0.05))
    settled, driver, events = await settle(samples)
    assert settled is None and driver.asked == [] and events == []


def test_the_runs_quality_says_the_loop_was_not_verified() -> None:
    unverified = Settled(
        "too sparse", "bench run r1: could not verify ...", BEFORE, True, "unverified"
    )
    quality = left_oscillating({"status": "good", "reasons": []}, unverified)
    assert quality["status"] == "doubtful"
    assert quality["reasons"][0] == {"code": "loop_unverified", "message": unverified.message}
    bad = left_oscillating(
        {"status": "bad", "reasons": [{"code": "x", "message": "y"}]}, unverified
    )
    assert bad["status"] == "bad" and [r["code"] for r in bad["reasons"]] == [
        "loop_unverified",
        "x",
    ]
    oscillating = Settled("swings", "left the axis oscillating", BEFORE, True)
    assert left_oscillating({"status": "good"}, oscillating)["status"] == "bad"
