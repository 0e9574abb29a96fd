"""Stopping distance and time on the demo plants: STOP against the power-off alone.

Each run starts one simulated device (the demo's plants, limit switches removed so that
nothing but the stop ends the motion) in a process of its own (as the demo runs it:
``servotune.sim.process``, so a busy host process cannot starve the device and make
its echoes late), its real driver on a pseudo-terminal (or the EtherCAT seam), and a
real ``Hub``; brings one axis into a state (``top speed``, or a
``limit cycle``: a loop whose gains oscillate around a held position); then asks the
hub for ``STOP`` (the product's STOP, ``Hub.command(axis, "stop")``) or for the
explicit power-off (``power_off``: SLAP2 ``st`` alone, Z1100 Job 0, EP7047 Enable off),
and records the shaft as the simulated device sees it until it is at rest.

* distance: the largest excursion of the shaft from where it was when the stop was
  asked for, until it is at rest (counts); a limit cycle is pressed near its highest
  speed, the same worst phase for both methods (``_near_peak_speed``);
* time: from the request until the shaft speed stays below ``REST_COUNTS_S`` (s);
* holds: the motor is under power at the end (held by its loop);
* on the wire (``wire_*``): the same from the moment the stop's first command reached
  the simulated device, with the shaft's position and speed at that moment, as the
  device's own process (or, for the EP7047, the exchange that carried it) recorded
  them: what the method itself does, the host's latency left out; that latency is
  ``wire_latency_s``.

A composition root: the hub is built here, each device's plant, link and shaft trace
come from its registry entry (``SimulatorEntry.stop_rig``); used by
``scripts/perf_stops.py`` (the table in docs/control.md) and tests/integration/hub/test_stops.py
(ratios against the power-off measured in the same test). Figures depend on the host
only through the host's latency (a STOP's few milliseconds on the wire).
"""

from __future__ import annotations

import asyncio
import contextlib
import tempfile
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final, Literal

from servotune.devices import default_registry
from servotune.hub.hub import Hub
from servotune.link.base import Sample
from servotune.registry import Registry, StopMethod, StopRigArgs
from servotune.sim.trace import ShaftPoint
from servotune.storage import Storage

State = Literal["top speed", "limit cycle"]
Method = StopMethod

# Below this shaft speed the axis counts as at rest (counts/s), for this long.
REST_COUNTS_S: Final = 200.0
REST_FOR_S: Final = 0.15
# A run ends this long after the request at the latest.
MAX_STOP_S: Final = 8.0


@dataclass(frozen=True, slots=True, eq=False)
class Case:
    """One demo plant in one state; ``setup`` are (what, args) steps for the hub."""

    device: str
    axis: str  # axis id on the bench's link
    label: str
    state: State
    gains: dict[str, int]
    speed: str  # in words, for the table


@dataclass(slots=True)
class Result:
    case: Case
    method: Method
    speed_counts_s: float  # shaft speed when the stop was asked for
    distance_counts: float
    time_s: float | None  # None: not at rest within MAX_STOP_S
    holds: bool
    sent: list[str] = field(default_factory=list)
    events: list[str] = field(default_factory=list)
    # From the stop's arrival at the device (the host's latency left out: what the
    # method itself does); None where the rig did not see it on the wire.
    wire_latency_s: float | None = None
    wire_distance_counts: float | None = None
    wire_speed_counts_s: float | None = None
    wire_time_s: float | None = None  # from the arrival until at rest


SLAP2_TOP_SV: Final = 20000  # the sv slider's end: 187 000 counts/s (5 500 rpm)
SLAP2_GOOD = {"kp": 600, "ki": 10, "kd": 1500}  # a stable loop on both modules
SLAP2_FACTORY = {"kp": 40, "ki": 40, "kd": 80}

# A slow sampling time stretches the chip's derivative window: with the unloaded
# motor's K at its maximum the loop settles into a limit cycle (docs/z1100-simulator.md).
Z1100_OSCILLATING = {"stm": 16} | {
    f"{s}_{g}": v for s in ("kabh", "kabd") for g, v in (("k", 255), ("a", 64), ("b", 8))
}
SLAP2_OSCILLATING = {"kp": 2000, "ki": 0, "kd": 0}

CASES: Final[tuple[Case, ...]] = (
    Case("slap2", "bench-0", "SLAP2 #0 unloaded", "top speed", SLAP2_FACTORY, "vm sv 20000"),
    Case("slap2", "bench-0", "SLAP2 #0 unloaded", "limit cycle", SLAP2_OSCILLATING, "±190"),
    Case("slap2", "bench-1", "SLAP2 #1 with load", "top speed", SLAP2_GOOD, "vm sv 20000"),
    Case("slap2", "bench-1", "SLAP2 #1 with load", "top speed", SLAP2_FACTORY, "vm sv 20000"),
    Case("slap2", "bench-1", "SLAP2 #1 with load", "limit cycle", SLAP2_FACTORY, "±1900 @ step"),
    Case("z1100", "bench-x", "Z1100 X unloaded", "top speed", {}, "Vmax 100 000"),
    Case("z1100", "bench-y", "Z1100 Y 5x load", "top speed", {}, "Vmax 100 000"),
    Case("z1100", "bench-z", "Z1100 Z 20x load", "top speed", {}, "Vmax 100 000"),
    Case("z1100", "bench-x", "Z1100 X unloaded", "limit cycle", Z1100_OSCILLATING, "±600"),
    Case("ep7047", "bench-1", "EP7047 stepper", "top speed", {}, "endless, 10 000 bp"),
)  # fmt: skip


Trace = Callable[[], Awaitable[list[ShaftPoint]]]
Powered = Callable[[], Awaitable[bool]]
# (method, asked at, the commands it sent) -> (time, position, speed) at its arrival
Reached = Callable[[Method, float, list[str]], Awaitable["ShaftPoint | None"]]


@contextlib.asynccontextmanager
async def _rig(
    case: Case, data_dir: Path, registry: Registry | None = None
) -> AsyncIterator[tuple[Hub, Trace, Powered, Reached]]:
    """A hub with the device of ``case`` on the device's stop rig (its registry entry's
    ``simulator.stop_rig``); yields (hub, trace of the axis, powered?, when a stop
    reached the device)."""
    entry = (registry or default_registry()).get(case.device)
    if entry.simulator is None or entry.simulator.stop_rig is None:
        raise ValueError(f"{entry.title} has no stop rig")
    link_id = case.axis.rsplit("-", 1)[0]
    async with entry.simulator.stop_rig(StopRigArgs(link_id, case.axis, data_dir)) as rig:
        storage = Storage(data_dir / "servotune.db")
        hub = Hub([], storage)
        hub.add_link(rig.build_link(hub))
        await hub.start()
        try:
            deadline = time.monotonic() + 20
            while (
                hub.entry(case.axis).latest is None or hub.link_status(link_id).state != "connected"
            ):
                if time.monotonic() > deadline:
                    raise RuntimeError(f"{case.label}: the link did not come up")
                await asyncio.sleep(0.05)
            yield hub, rig.trace, rig.powered, rig.reached
        finally:
            await hub.stop()
            await hub.stops.close()


async def _bring_into_state(hub: Hub, case: Case) -> None:
    axis = case.axis
    if case.device == "slap2":
        await hub.command(axis, "power_off", {})
        await hub.write_params(axis, dict(case.gains))
        if case.state == "top speed":
            await hub.write_params(axis, {"velocity": SLAP2_TOP_SV, "acceleration": 65535})
            await hub.command(axis, "velocity_mode", {})
            # Long enough for the loop check to see the loop work (loopcheck.EVIDENCE_S).
            await asyncio.sleep(1.2)
        else:
            await hub.write_params(axis, {"velocity": 65535, "acceleration": 65535})
            await hub.command(axis, "position_mode", {})
            await hub.command(axis, "move_relative", {"distance": 2000})
            await asyncio.sleep(1.5)  # the step's limit cycle settles in
    elif case.device == "z1100":
        if case.gains:
            await hub.write_params(axis, dict(case.gains))
        if case.state == "top speed":
            await hub.command(axis, "constant_velocity", {"direction": 1})
            await asyncio.sleep(1.0)
        else:
            position = (hub.entry(axis).latest or Sample(0, {}, {})).channels.get("position") or 0
            await hub.command(axis, "go_to_target", {"target": int(position) + 20000})
            await asyncio.sleep(1.5)
    else:
        await hub.command(axis, "enable", {})
        # Until the drive says Ready to execute (a fixed wait was too short on a loaded
        # host: the start was then refused with "not enabled").
        deadline = time.monotonic() + 10
        while not _flag(hub, axis, "ready_to_execute"):
            if time.monotonic() > deadline:
                raise RuntimeError(f"{case.label}: the drive did not become ready")
            await asyncio.sleep(0.02)
        await hub.command(
            axis,
            "execute_move",
            {
                "start_type": 3,
                "target": 0,
                "velocity": 10000,
                "acceleration_ms": 300,
                "deceleration_ms": 300,
            },
        )
        await asyncio.sleep(1.5)


async def _near_peak_speed(trace: Trace) -> None:
    """Wait (at most 2 s) until the shaft runs at 80 % or more of the highest speed of its
    last 0.3 s: a limit cycle is pressed at the same, worst phase for every method (a
    power cut then lets the shaft coast from near its top speed)."""
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        points = await trace()
        recent = [abs(p[2]) for p in points if p[0] >= points[-1][0] - 0.3]
        if recent and recent[-1] >= 0.8 * max(recent) > 0:
            return
        await asyncio.sleep(0.001)


def _flag(hub: Hub, axis: str, name: str) -> bool:
    latest = hub.entry(axis).latest
    return bool(latest is not None and latest.flags.get(name))


def _at(points: Sequence[tuple[float, float, float]], t: float) -> tuple[float, float]:
    """Position and speed at host time ``t``: the last point before it, carried on at
    its own speed to ``t`` (every rig records the shaft's exact speed with the point;
    a point can be old when the bench's thread was held on a loaded host)."""
    before = [p for p in points if p[0] <= t]
    if not before:
        return points[0][1], points[0][2]
    t1, x1, v1 = before[-1]
    return x1 + v1 * (t - t1), v1


async def measure(
    case: Case, method: Method, data_dir: Path | None = None, registry: Registry | None = None
) -> Result:
    """One stop of ``case`` by ``method`` (see the module docstring) on the stop rig of
    ``case.device`` in ``registry`` (default: ``default_registry()``)."""
    with tempfile.TemporaryDirectory() as scratch:
        rig = _rig(case, data_dir or Path(scratch), registry)
        async with rig as (hub, trace, powered, reached):
            await _bring_into_state(hub, case)
            events_before = len(hub._events)
            if case.state == "limit cycle":
                await _near_peak_speed(trace)
            asked = time.monotonic()
            name = "stop" if method == "STOP" else "power_off"
            # The command first: the trace keeps its stamped points, and reading it
            # (a request to the simulator's process) must not delay the press.
            outcome = await hub.command(case.axis, name, {})
            position0, speed0 = _at(await trace(), asked)
            rest_since: float | None = None
            rested_at: float | None = None
            distance = 0.0
            while time.monotonic() - asked < MAX_STOP_S:
                await asyncio.sleep(0.05)
                everything = await trace()
                # The points up to the press may arrive after it (see _at).
                position0, speed0 = _at(everything, asked)
                points = [p for p in everything if p[0] >= asked]
                if not points:
                    continue
                distance = max(abs(p[1] - position0) for p in points)
                rest_since = None
                for t, _, speed in points:
                    if abs(speed) < REST_COUNTS_S:
                        rest_since = t if rest_since is None else rest_since
                    else:
                        rest_since = None
                if rest_since is not None and points[-1][0] - rest_since >= REST_FOR_S:
                    rested_at = rest_since
                    if not hub.stops.watching(case.axis):
                        break
            await asyncio.sleep(0.2)  # let a watch's last command land
            events = [e.message for e in list(hub._events)[events_before:]]
            result = Result(
                case,
                method,
                speed0,
                distance,
                None if rested_at is None else rested_at - asked,
                await powered(),
                outcome.sent,
                events,
            )
            on_wire = await reached(method, asked, outcome.sent)
            if on_wire is not None:
                t1, position1, result.wire_speed_counts_s = on_wire
                after = [p for p in await trace() if p[0] >= t1]
                result.wire_latency_s = t1 - asked
                result.wire_distance_counts = max(
                    (abs(p[1] - position1) for p in after), default=0.0
                )
                if rested_at is not None:
                    result.wire_time_s = max(rested_at, t1) - t1
            return result


async def measure_all(
    cases: Sequence[Case] = CASES, methods: Sequence[Method] = ("power off", "STOP")
) -> list[Result]:
    results = []
    for case in cases:
        for method in methods:
            results.append(await measure(case, method))
    return results


def table(results: Sequence[Result]) -> str:
    """A markdown table: per case, the power-off and STOP side by side (one row per
    round: the n-th power-off of a case beside its n-th STOP)."""
    lines = [
        "| plant | state | gains | speed at the press (counts/s) | power off alone: "
        "distance / time | STOP: distance / time | ratio | STOP ends |",
        "|---|---|---|---|---|---|---|---|",
    ]
    rounds: dict[tuple[Case, str], int] = {}
    by_case: dict[tuple[Case, int], dict[str, Result]] = {}
    for result in results:
        n = rounds[result.case, result.method] = rounds.get((result.case, result.method), -1) + 1
        by_case.setdefault((result.case, n), {})[result.method] = result

    def cell(r: Result | None) -> str:
        if r is None:
            return "–"
        t = f"{r.time_s:.2f} s" if r.time_s is not None else f"> {MAX_STOP_S:g} s"
        text = f"{r.distance_counts:,.0f} counts / {t}"
        if r.wire_distance_counts is not None and r.wire_latency_s is not None:
            text += (
                f" ({r.wire_distance_counts:,.0f} from the wire at "
                f"{abs(r.wire_speed_counts_s or 0):,.0f} counts/s, "
                f"{r.wire_latency_s * 1000:.0f} ms after the press)"
            )
        return text

    for (case, _), pair in by_case.items():
        off, stop = pair.get("power off"), pair.get("STOP")
        ratio = (
            f"{stop.distance_counts / off.distance_counts:.3f}"
            if off is not None and stop is not None and off.distance_counts > 0
            else "–"
        )
        gains = " ".join(f"{k} {v}" for k, v in case.gains.items()) or "demo"
        ends = ""
        if stop is not None:
            ends = ("holding: " if stop.holds else "unpowered: ") + ", ".join(stop.sent)
            if any("not working" in e or "does not hold" in e for e in stop.events):
                ends += " (loop not working: brake, then off)"
        either = off or stop
        speed = either.speed_counts_s if either is not None else 0.0
        lines.append(
            f"| {case.label} | {case.state} | {gains} | {abs(speed):,.0f} | {cell(off)} | "
            f"{cell(stop)} | {ratio} | {ends} |"
        )
    return "\n".join(lines)
