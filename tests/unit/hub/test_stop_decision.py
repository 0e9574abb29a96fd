"""What STOP sends, from the loop check's verdict (servotune.hub.stops.StopService), on a
driver that records the stops it is asked for and telemetry injected with its own
timestamps and arrival times (an injected clock: nothing depends on the host's speed)."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable

import pytest

from servotune.devices.slap2.descriptor import slap2_descriptor
from servotune.hub.stops import StopService
from servotune.link.base import Sample, StopOutcome
from tests.support.stop_driver import RecordingStops


class Recorder(RecordingStops):
    """A driver with the stop modes and no stop for an unjudged loop (a Z1100-like one):
    its stops say what they are and send nothing."""


class Slap2Like(Recorder):
    """... and one with it (a SLAP2-like one: its brake)."""

    async def unjudged_stop(self) -> StopOutcome:
        return await self._say("unjudged_stop", "brake")


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def limit_cycle(times: list[float]) -> list[Sample]:
    """The loaded SLAP2's limit cycle (±1900 counts at 9.7 Hz around a held setpoint)."""
    out = []
    for t in times:
        e = 1900 * math.sin(2 * math.pi * 9.7 * t)
        out.append(
            Sample(
                t,
                {"position": 2000 - e, "following_error": e, "setpoint": 2000.0},
                {"pm": True, "vm": False, "move": False, "oc": False},
            )
        )
    return out


def quiet(times: list[float]) -> list[Sample]:
    return [
        Sample(
            t,
            {"position": 2000.0, "following_error": 3.0, "setpoint": 2003.0},
            {"pm": True, "vm": False, "move": False, "oc": False},
        )
        for t in times
    ]


async def stop_after(
    samples: list[Sample], *, kind: str = "stop", unjudged: bool = True, late_s: float = 0.0
) -> tuple[list[str], list[str]]:
    """Feed ``samples`` as they would arrive (the service's clock follows their own
    timestamps, then ``late_s`` more), STOP, and return (what the driver was asked for,
    the events)."""
    clock = Clock()
    events: list[str] = []
    service = StopService(lambda level, axis, message: events.append(message), clock=clock)
    driver = Slap2Like() if unjudged else Recorder()
    service.add_axis("a", driver, slap2_descriptor(1))  # type: ignore[arg-type]
    for sample in samples:
        clock.now = 100.0 + sample.t
        service.on_sample("a", sample)
    clock.now += late_s
    await service.stop("a", kind, "STOP")  # type: ignore[arg-type]
    await service.close()
    return driver.asked, events


def every(gap_s: float, span_s: float = 1.5) -> list[float]:
    return [i * gap_s for i in range(int(span_s / gap_s) + 1)]


async def test_a_limit_cycle_densely_seen_gets_the_brake() -> None:
    asked, events = await stop_after(limit_cycle(every(1 / 68)))
    assert asked == ["brake"] and "not working" in events[0], (asked, events)


async def test_a_working_loop_densely_seen_holds() -> None:
    asked, _ = await stop_after(quiet(every(0.04)))
    assert asked == ["stop"]


@pytest.mark.parametrize(
    ("samples", "late_s"),
    [
        # A starved host polled every ~0.3 s: six samples of the limit cycle.
        (limit_cycle([0.0, 0.3, 0.55, 0.9, 1.2, 1.5]), 0.0),
        # A quiet loop densely seen - but the telemetry stopped 0.5 s before the STOP.
        (quiet(every(0.04)), 0.5),
    ],
    ids=["sparse", "late"],
)
async def test_a_loop_the_telemetry_cannot_judge_gets_the_stop_safe_either_way(
    samples: list[Sample], late_s: float
) -> None:
    asked, events = await stop_after(samples, late_s=late_s)
    assert asked == ["unjudged_stop"], (asked, events)
    assert "telemetry too sparse" in events[0]
    # A device without such a stop gets its STOP (watched), and every other stop holds
    # as asked (it must keep a vertical axis up).
    assert (await stop_after(samples, late_s=late_s, unjudged=False))[0] == ["stop"]
    controlled, _ = await stop_after(samples, late_s=late_s, kind="controlled")
    assert controlled == ["controlled_stop"]


async def test_a_quiet_loop_seen_with_a_hole_is_not_judged_working() -> None:
    asked, _ = await stop_after(quiet([*every(0.04, 0.6), *[0.9 + t for t in every(0.04, 0.6)]]))
    assert asked == ["unjudged_stop"]


async def test_a_stop_after_an_outage_is_the_stop_safe_either_way() -> None:
    # A pending STOP delivered when the link is back, the loop last seen on and quiet
    # 3 s ago: what it does now is unknown.
    asked, events = await stop_after(quiet(every(0.04)), late_s=3.0)
    assert asked == ["unjudged_stop"] and "no telemetry for the last 3.00 s" in events[0]


# --- the watch after a stop that holds, when its telemetry stops ------------------------


class World:
    """The watch's pause, injected: each pause moves the service's clock and delivers the
    samples due by then (``(arrival on the clock, sample)``), so the watch runs through
    any length of (simulated) time at once and exactly the same way every time."""

    def __init__(self, clock: Clock, service: StopService) -> None:
        self.clock = clock
        self.service = service
        self.due: list[tuple[float, Sample]] = []

    async def sleep(self, seconds: float) -> None:
        self.clock.now += seconds
        while self.due and self.due[0][0] <= self.clock.now:
            _, sample = self.due.pop(0)
            self.service.on_sample("a", sample)
        await asyncio.sleep(0)


async def watched_stop(
    later: list[Sample], *, arrive_from: float, run_for_s: float
) -> tuple[StopService, Recorder, list[tuple[str, str]], World]:
    """A quiet axis STOPped (it holds) at clock 101.5; ``later`` samples (their own time
    stamps, on the stop's time line) arrive from ``arrive_from`` s after the stop, as
    they are due; the world runs ``run_for_s`` s of the service's clock (or until the
    watch ends). Returns the service (still running its watch, if it does), the driver,
    the events (level, message) and the world."""
    clock = Clock()
    events: list[tuple[str, str]] = []
    world: World
    service = StopService(
        lambda level, axis, message: events.append((level, message)),
        clock=clock,
        sleep=lambda s: world.sleep(s),
    )
    world = World(clock, service)
    driver = Recorder()
    service.add_axis("a", driver, slap2_descriptor(1))  # type: ignore[arg-type]
    for sample in quiet(every(0.04)):
        clock.now = 100.0 + sample.t
        service.on_sample("a", sample)
    stopped_at = clock.now
    assert await service.stop("a", "stop", "STOP") is not None
    world.due = [(stopped_at + arrive_from + (s.t - later[0].t), s) for s in later]
    end = stopped_at + run_for_s
    for _ in range(100_000):
        if clock.now >= end or not service.watching("a"):
            break
        await asyncio.sleep(0)
    return service, driver, events, world


def after_stop(make: Callable[[list[float]], list[Sample]], from_s: float) -> list[Sample]:
    """1.5 s of samples every 20 ms, stamped from ``from_s`` after the stop (1.5 s)."""
    return make([1.5 + from_s + t for t in every(0.02, 1.5)])


async def test_a_watch_without_telemetry_says_the_hold_is_unverified_and_keeps_watching() -> None:
    # The link goes down with the STOP: nothing for a minute.
    service, driver, events, _ = await watched_stop(
        after_stop(quiet, 100.0), arrive_from=100.0, run_for_s=60.0
    )
    assert service.watching("a") and service.unverified("a")
    assert driver.asked == ["stop"]  # nothing sent on no evidence
    warnings = [m for level, m in events if level == "warning"]
    assert len(warnings) == 1 and "hold is not verified" in warnings[0], events
    await service.close()


async def test_telemetry_back_at_rest_is_told_and_ends_the_watch() -> None:
    service, driver, events, _ = await watched_stop(
        after_stop(quiet, 10.0), arrive_from=10.0, run_for_s=30.0
    )
    assert not service.watching("a") and not service.unverified("a")
    assert driver.asked == ["stop"]
    assert [level for level, _ in events] == ["warning", "info"], events
    assert "telemetry back after 10.0 s without: the axis is at rest" in events[1][1]


async def test_telemetry_back_oscillating_gets_the_brake() -> None:
    # The loop broke into a limit cycle while nobody could see it.
    service, driver, events, _ = await watched_stop(
        after_stop(limit_cycle, 10.0), arrive_from=10.0, run_for_s=30.0
    )
    assert driver.asked[:2] == ["stop", "brake"], (driver.asked, events)
    assert any(level == "error" and "does not hold the axis" in m for level, m in events)
    await service.close()


async def test_a_brake_switched_off_without_telemetry_does_not_claim_rest() -> None:
    # Half a second of a limit cycle after the STOP (the watch brakes it), then nothing.
    cycle = limit_cycle([1.5 + t for t in every(0.02, 0.5)])
    service, driver, events, _ = await watched_stop(cycle, arrive_from=0.0, run_for_s=30.0)
    assert not service.watching("a")
    assert driver.asked == ["stop", "brake", "power_off"], (driver.asked, events)
    level, last = events[-1]
    assert level == "warning" and "not seen at rest" in last, events
