"""How a user's move ended: arrived, stopped short, stopped by a limit switch or a STOP.

A command whose descriptor has a ``target`` (SLAP2 ``move_absolute``/``move_relative``,
Z1100 ``go_to_target``) answers as soon as the device took it: the move itself runs on.
A "✓" then would only mean "sent". The hub plans the move with the device's own bench
planner (where it ends, its window, the flag set while it runs, its fault flags) from
the sample before the command, and ``watch_move`` follows the samples until the move
ended, then says how: a ``MoveOutcome`` message (the command strip turns its "moving…"
into ✓ or ⚠), and an event for every end that is not "arrived" — a limit switch with
the position where the axis stopped.

Decisions where the devices are silent: the move has ended when the moving flag is
clear and successive samples have stayed within half the window of each other for
``REST_S`` of sample time (flags are polled, and the SLAP2 shows ``move`` for up to
200 ms after the profile ended; judged on new samples only, so a host that is slow to
look sees no false rest); a move is not watched for longer than ``WATCH_S``
after the command (then "still moving ... not watched further", not a verdict); a
later command on the axis ends the watch of the earlier one (a jog's steps).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Final, Literal

from servotune.descriptor import DeviceDescriptor
from servotune.hub.state import AxisEntry
from servotune.link.base import BenchPlan, BenchPlanner, BenchTest, DriverError, Sample

REST_S: Final = 0.15
POLL_S: Final = 0.02
WATCH_S: Final = 120.0  # a slow move (sv 100: ~940 counts/s) of 30 000 counts takes 32 s
START_GRACE_S: Final = 0.3  # the first samples after a command may not show the move yet

Outcome = Literal["arrived", "short", "limit", "fault", "stopped", "timeout"]


@dataclass(frozen=True, slots=True)
class MovePlan:
    """Where a commanded move should end and what the device says while it runs."""

    label: str  # "Move to 30000"
    start: float
    target: float
    band: float
    moving_flag: str | None
    fault_flags: tuple[str, ...]
    timeout_s: float


def plan_move(entry: AxisEntry, name: str, args: Mapping[str, int]) -> MovePlan | None:
    """The plan of a command that moves to a target, from the axis' latest sample before
    it is sent; None for any other command, or when the device cannot plan it."""
    descriptor = entry.driver.descriptor
    command = descriptor.command(name)
    target = command.target
    latest = entry.latest
    if target is None or latest is None or not isinstance(entry.driver, BenchPlanner):
        return None
    value = args.get(target.argument)
    if value is None:
        return None
    try:
        # The device's own move planning: its reference position, window, flags.
        reference = entry.driver.bench_plan(
            BenchTest(kind="move", distance=1), latest, entry.device_values
        )
    except DriverError:
        return None  # moving, or a device that cannot plan moves: not watched
    end = reference.y0 + value if target.relative else float(value)
    return _plan(command.label, value, end, reference, descriptor)


def _plan(
    label: str,
    value: int,
    end: float,
    reference: BenchPlan,
    descriptor: DeviceDescriptor,
) -> MovePlan:
    flags = {f.name for f in descriptor.flags}
    return MovePlan(
        label=f"{label} {value}",
        start=reference.y0,
        target=end,
        band=reference.band if reference.band is not None else 0.0,
        moving_flag=reference.moving_flag if reference.moving_flag in flags else None,
        fault_flags=tuple(f for f in reference.fault_flags if f in flags),
        timeout_s=WATCH_S,
    )


@dataclass(frozen=True, slots=True)
class MoveEnd:
    outcome: Outcome
    position: float | None
    message: str


async def watch_move(
    entry: AxisEntry,
    plan: MovePlan,
    generation: int,
    clock: Callable[[], float],
) -> MoveEnd:
    """Follow the axis' samples until the move has ended; how it ended."""
    descriptor = entry.driver.descriptor
    labels = {f.name: f.label for f in descriptor.flags}
    started = clock()
    rest_since: float | None = None  # the sample time the axis has rested since
    last: Sample | None = None
    while True:
        await asyncio.sleep(POLL_S)
        now = clock()
        sample = entry.latest
        position = _position(sample)
        if entry.stop_generation != generation:
            await _rest(entry, clock)
            position = _position(entry.latest)
            return MoveEnd(
                "stopped",
                position,
                f"{plan.label}: {entry.stop_cause} at {_at(position)}{_short(position, plan)}",
            )
        if sample is None or position is None or sample is last:
            pass  # judged on new samples only: a host that polls late sees no rest
        else:
            before, last = _position(last), sample
            moving = bool(plan.moving_flag and sample.flags.get(plan.moving_flag))
            still = before is not None and abs(position - before) <= max(plan.band, 1.0) / 2
            if moving or not still or now - started < START_GRACE_S:
                rest_since = None
            else:
                rest_since = rest_since if rest_since is not None else sample.t
                if sample.t - rest_since >= REST_S:
                    return _ended(plan, sample, position, labels)
        if now - started > plan.timeout_s:
            return MoveEnd(
                "timeout",
                position,
                f"{plan.label}: still moving after {now - started:.0f} s (at {_at(position)}): "
                "not watched further",
            )


def _ended(plan: MovePlan, sample: Sample, position: float, labels: Mapping[str, str]) -> MoveEnd:
    """The axis came to rest: at the target, or where a fault flag (a limit switch, a
    stall) or nothing known stopped it."""
    if abs(position - plan.target) <= plan.band:
        return MoveEnd("arrived", position, f"{plan.label}: at {_at(position)}")
    faults = [f for f in plan.fault_flags if sample.flags.get(f)]
    if faults:
        names = ", ".join(labels.get(f, f) for f in faults)
        kind: Outcome = "limit" if any(f.startswith("limit") for f in faults) else "fault"
        what = f"the limit switch {names}" if kind == "limit" else names
        return MoveEnd(
            kind,
            position,
            f"{plan.label}: stopped by {what} at {_at(position)}{_short(position, plan)}",
        )
    return MoveEnd(
        "short", position, f"{plan.label}: came to rest at {_at(position)}{_short(position, plan)}"
    )


async def _rest(entry: AxisEntry, clock: Callable[[], float], limit_s: float = 2.0) -> None:
    """Wait (bounded) until the position stops changing: where a stop left the axis."""
    deadline = clock() + limit_s
    last = _position(entry.latest)
    since = clock()
    while clock() < deadline:
        await asyncio.sleep(POLL_S)
        position = _position(entry.latest)
        if position != last:
            last, since = position, clock()
        elif clock() - since >= REST_S:
            return


def _position(sample: Sample | None) -> float | None:
    value = sample.channels.get("position") if sample is not None else None
    return None if value is None else float(value)


def _at(position: float | None) -> str:
    return "an unknown position" if position is None else f"{position:.0f}"


def _short(position: float | None, plan: MovePlan) -> str:
    if position is None:
        return ""
    off = position - plan.target
    if abs(off) <= plan.band:
        return ""
    # short of the target: still on the side it started from
    short = (plan.target - position) * (plan.target - plan.start) > 0
    return f", {abs(off):.0f} {'short of' if short else 'past'} the target {plan.target:.0f}"
