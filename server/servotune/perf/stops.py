"""Stopping distance and time on the demo plants: STOP against the power-off alone.

Each run starts one simulated device (the demo's plants, limit switches removed so that
nothing but the stop ends the motion) in a process of its own (as the demo runs it:
``servotune.sim.process``, so a busy host process cannot starve the device and make
its echoes late), its real driver on a pseudo-terminal (or the EtherCAT seam), and a
real ``Hub``; brings one axis into a state (a case of the device's registry entry,
``SimulatorEntry.stop_cases``: ``top speed``, or a ``limit cycle``: a loop whose gains
oscillate around a held position); then asks the hub for ``STOP`` (the product's STOP,
``Hub.command(axis, "stop")``) or for the explicit power-off (``power_off``: SLAP2
``st`` alone, Z1100 Job 0, EP7047 Enable off), and records the shaft as the simulated
device sees it until it is at rest.

* distance: the largest excursion of the shaft from where it was when the stop was
  asked for, until it is at rest (counts); a limit cycle is pressed near its highest
  speed, the same worst phase for both methods (``_near_peak_speed``);
* time: from the request until the shaft speed stays below ``REST_COUNTS_S`` (s);
* holds: the motor is under power at the end (held by its loop);
* on the wire (``wire_*``): the same from the moment the stop's first command reached
  the simulated device, with the shaft's position and speed at that moment, as the
  device's own process (or, for the EP7047, the exchange that carried it) recorded
  them: what the method itself does, the host's latency left out; that latency is
  ``wire_latency_s``;
* unpowered (``unpowered_*``): where the rig offers it (``StopRig.unpowered``), the
  power-off alone from the very state that stop arrived in: a copy of the simulated
  device taken as the stop's first command reached it (position, speed, currents, the
  loop's state and its phase in a limit cycle), powered off as the device's power-off
  command does and run forward in the simulator's process. The method's distance and
  time from its arrival against these share their start, whatever the host's latency.

A composition root: the hub is built here; the cases, and each device's plant, link
and shaft trace come from its registry entry (``SimulatorEntry.stop_cases``,
``stop_rig``): this module names no device. Used by ``scripts/perf_stops.py`` (the
table in docs/control.md) and tests/integration/hub/test_stops.py (ratios against the
power-off alone measured in the same test). Figures from the press depend on the
host's latency; those from the arrival, and the copy's, do not.
"""

from __future__ import annotations

import asyncio
import contextlib
import tempfile
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

from servotune.devices import default_registry
from servotune.hub.hub import Hub
from servotune.registry import Registry, StopCase, StopMethod, StopRig, StopRigArgs, StopState
from servotune.sim.trace import ShaftPoint
from servotune.storage import Storage

State = StopState
Method = StopMethod
# The bench's link id on every stop rig: an axis is ``bench-<the case's axis>``.
LINK_ID: Final = "bench"

# Below this shaft speed the axis counts as at rest (counts/s), for this long.
REST_COUNTS_S: Final = 200.0
REST_FOR_S: Final = 0.15
# A run ends this long after the request at the latest.
MAX_STOP_S: Final = 8.0


@dataclass(frozen=True, slots=True, eq=False)
class Case:
    """A device's stop case (``SimulatorEntry.stop_cases``) on that device's stop rig."""

    device: str  # the registry's name of the device
    stop: StopCase

    @property
    def name(self) -> str:
        return self.stop.name

    @property
    def axis(self) -> str:  # axis id on the rig's link
        return f"{LINK_ID}-{self.stop.axis}"

    @property
    def label(self) -> str:
        return self.stop.label

    @property
    def state(self) -> State:
        return self.stop.state

    @property
    def gains(self) -> Mapping[str, int]:
        return self.stop.gains

    @property
    def speed(self) -> str:  # in words, for the table
        return self.stop.speed


def cases(registry: Registry | None = None) -> tuple[Case, ...]:
    """Every stop case of every device in ``registry`` (default: ``default_registry()``),
    in the registry's order."""
    return tuple(
        Case(entry.name, stop)
        for entry in (registry or default_registry())
        if entry.simulator is not None
        for stop in entry.simulator.stop_cases
    )


def case(device: str, name: str, registry: Registry | None = None) -> Case:
    """The stop case ``name`` of ``device``; KeyError naming the known ones if none."""
    known = [c for c in cases(registry) if c.device == device]
    for found in known:
        if found.name == name:
            return found
    raise KeyError(f"{device} has no stop case {name!r} (it has {[c.name for c in known]})")


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
    # The power-off alone from the state the stop arrived in (a copy of the device);
    # None where the rig offers no copy.
    unpowered_distance_counts: float | None = None
    unpowered_time_s: float | None = None  # None also: not at rest within MAX_STOP_S


Trace = Callable[[], Awaitable[list[ShaftPoint]]]


@contextlib.asynccontextmanager
async def _rig(
    case: Case, data_dir: Path, registry: Registry | None = None
) -> AsyncIterator[tuple[Hub, StopRig]]:
    """A hub with the device of ``case`` on the device's stop rig (its registry entry's
    ``simulator.stop_rig``); yields (hub, rig)."""
    entry = (registry or default_registry()).get(case.device)
    if entry.simulator is None or entry.simulator.stop_rig is None:
        raise ValueError(f"{entry.title} has no stop rig")
    async with entry.simulator.stop_rig(StopRigArgs(LINK_ID, case.axis, data_dir)) as rig:
        storage = Storage(data_dir / "servotune.db")
        hub = Hub([], storage)
        hub.add_link(rig.build_link(hub))
        await hub.start()
        try:
            deadline = time.monotonic() + 20
            while (
                hub.entry(case.axis).latest is None or hub.link_status(LINK_ID).state != "connected"
            ):
                if time.monotonic() > deadline:
                    raise RuntimeError(f"{case.label}: the link did not come up")
                await asyncio.sleep(0.05)
            yield hub, rig
        finally:
            await hub.stop()
            await hub.stops.close()


class _HubAxis:
    """``registry.StopAxis`` on a hub's axis."""

    def __init__(self, hub: Hub, axis: str) -> None:
        self._hub = hub
        self._axis = axis

    async def command(self, name: str, args: dict[str, Any]) -> None:
        await self._hub.command(self._axis, name, args)

    async def write_params(self, values: dict[str, int]) -> None:
        await self._hub.write_params(self._axis, values)

    def channel(self, name: str) -> float | None:
        latest = self._hub.entry(self._axis).latest
        return None if latest is None else latest.channels.get(name)

    def flag(self, name: str) -> bool:
        latest = self._hub.entry(self._axis).latest
        return bool(latest is not None and latest.flags.get(name))


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


def _at(points: Sequence[tuple[float, float, float]], t: float) -> tuple[float, float]:
    """Position and speed at host time ``t``: the last point before it, carried on at
    its own speed to ``t`` (every rig records the shaft's exact speed with the point;
    a point can be old when the bench's thread was held on a loaded host)."""
    before = [p for p in points if p[0] <= t]
    if not before:
        return points[0][1], points[0][2]
    t1, x1, v1 = before[-1]
    return x1 + v1 * (t - t1), v1


def _rested_at(points: Sequence[ShaftPoint]) -> float | None:
    """When the shaft of ``points`` came to rest: the start of the last run of points
    below ``REST_COUNTS_S`` if that run lasts ``REST_FOR_S``; None otherwise."""
    rest_since: float | None = None
    for t, _, speed in points:
        if abs(speed) < REST_COUNTS_S:
            rest_since = t if rest_since is None else rest_since
        else:
            rest_since = None
    if rest_since is not None and points[-1][0] - rest_since >= REST_FOR_S:
        return rest_since
    return None


async def measure(
    case: Case, method: Method, data_dir: Path | None = None, registry: Registry | None = None
) -> Result:
    """One stop of ``case`` by ``method`` (see the module docstring) on the stop rig of
    ``case.device`` in ``registry`` (default: ``default_registry()``)."""
    with tempfile.TemporaryDirectory() as scratch:
        async with _rig(case, data_dir or Path(scratch), registry) as (hub, rig):
            await case.stop.setup(_HubAxis(hub, case.axis))
            events_before = len(hub._events)
            await rig.arm()
            if case.state == "limit cycle":
                await _near_peak_speed(rig.trace)
            asked = time.monotonic()
            name = "stop" if method == "STOP" else "power_off"
            # The command first: the trace keeps its stamped points, and reading it
            # (a request to the simulator's process) must not delay the press.
            outcome = await hub.command(case.axis, name, {})
            # What the stop sent has reached the device (its echoes or replies are in).
            await rig.disarm()
            position0, speed0 = _at(await rig.trace(), asked)
            rested_at: float | None = None
            distance = 0.0
            while time.monotonic() - asked < MAX_STOP_S:
                await asyncio.sleep(0.05)
                everything = await rig.trace()
                # The points up to the press may arrive after it (see _at).
                position0, speed0 = _at(everything, asked)
                points = [p for p in everything if p[0] >= asked]
                if not points:
                    continue
                distance = max(abs(p[1] - position0) for p in points)
                rested_at = _rested_at(points)
                if rested_at is not None and not hub.stops.watching(case.axis):
                    break
            await asyncio.sleep(0.2)  # let a watch's last command land
            events = [e.message for e in list(hub._events)[events_before:]]
            result = Result(
                case,
                method,
                speed0,
                distance,
                None if rested_at is None else rested_at - asked,
                await rig.powered(),
                outcome.sent,
                events,
            )
            on_wire = await rig.reached(method, asked, outcome.sent)
            if on_wire is not None:
                t1, position1, result.wire_speed_counts_s = on_wire
                after = [p for p in await rig.trace() if p[0] >= t1]
                result.wire_latency_s = t1 - asked
                result.wire_distance_counts = max(
                    (abs(p[1] - position1) for p in after), default=0.0
                )
                if rested_at is not None:
                    result.wire_time_s = max(rested_at, t1) - t1
                unpowered = await rig.unpowered(t1, REST_COUNTS_S, REST_FOR_S, MAX_STOP_S)
                if unpowered:
                    result.unpowered_distance_counts = max(abs(p[1] - position1) for p in unpowered)
                    unpowered_rest = _rested_at(unpowered)
                    if unpowered_rest is not None:
                        result.unpowered_time_s = unpowered_rest - t1
            return result


async def measure_all(
    chosen: Sequence[Case], methods: Sequence[Method] = ("power off", "STOP")
) -> list[Result]:
    results = []
    for one in chosen:
        for method in methods:
            results.append(await measure(one, method))
    return results


def table(results: Sequence[Result]) -> str:
    """A markdown table: per case, the power-off run and the STOP run side by side (one
    row per round: the n-th power-off of a case beside its n-th STOP), each from the
    press and from its arrival on the wire, and the power-off alone from the STOP's
    arrival (the copy). The ratio is the STOP's distance from its arrival over the
    copy's, where the rig offers a copy; else over the power-off run's, per unit of the
    speed each found at its arrival."""
    lines = [
        "| plant | state | gains | speed at the STOP's arrival (counts/s) | power off "
        "alone, its own run: distance / time | power off alone from the STOP's arrival "
        "(copy) | STOP: distance / time | ratio | STOP ends |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    rounds: dict[tuple[Case, str], int] = {}
    by_case: dict[tuple[Case, int], dict[str, Result]] = {}
    for result in results:
        n = rounds[result.case, result.method] = rounds.get((result.case, result.method), -1) + 1
        by_case.setdefault((result.case, n), {})[result.method] = result

    def seconds(t: float | None) -> str:
        return f"{t:.2f} s" if t is not None else f"> {MAX_STOP_S:g} s"

    def cell(r: Result | None) -> str:
        if r is None:
            return "–"
        text = f"{r.distance_counts:,.0f} counts / {seconds(r.time_s)} from the press"
        if r.wire_distance_counts is not None and r.wire_latency_s is not None:
            text += (
                f"; {r.wire_distance_counts:,.0f} / {seconds(r.wire_time_s)} from its "
                f"arrival {r.wire_latency_s * 1000:.0f} ms later at "
                f"{abs(r.wire_speed_counts_s or 0):,.0f} counts/s"
            )
        if r.method == "power off" and r.unpowered_distance_counts is not None:
            text += f" (its copy: {r.unpowered_distance_counts:,.0f})"
        return text

    def ratio(stop: Result | None, off: Result | None) -> str:
        if stop is None or stop.wire_distance_counts is None:
            return "–"
        if stop.unpowered_distance_counts:
            return f"{stop.wire_distance_counts / stop.unpowered_distance_counts:.3f}"
        if (
            off is None
            or not off.wire_distance_counts
            or not off.wire_speed_counts_s
            or not stop.wire_speed_counts_s
        ):
            return "–"
        per_speed_stop = stop.wire_distance_counts / abs(stop.wire_speed_counts_s)
        return f"{per_speed_stop / (off.wire_distance_counts / abs(off.wire_speed_counts_s)):.3f}"

    for (one, _), pair in by_case.items():
        off, stop = pair.get("power off"), pair.get("STOP")
        gains = " ".join(f"{k} {v}" for k, v in one.gains.items()) or "demo"
        ends, copy = "", "–"
        if stop is not None:
            ends = ("holding: " if stop.holds else "unpowered: ") + ", ".join(stop.sent)
            if any("not working" in e or "does not hold" in e for e in stop.events):
                ends += " (loop not working: brake, then off)"
            if stop.unpowered_distance_counts is not None:
                copy = (
                    f"{stop.unpowered_distance_counts:,.0f} counts / "
                    f"{seconds(stop.unpowered_time_s)}"
                )
        speed = abs(stop.wire_speed_counts_s or 0) if stop is not None else 0.0
        lines.append(
            f"| {one.label} | {one.state} | {gains} | {speed:,.0f} | {cell(off)} | {copy} | "
            f"{cell(stop)} | {ratio(stop, off)} | {ends} |"
        )
    return "\n".join(lines)
