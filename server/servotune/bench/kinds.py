"""The bench's test kinds as objects: what differs from one kind of test to another.

A kind checks a request before anything moves (``check``: 422 naming the field, 409),
plans the test on the axis (``plan``: the device's commands, a signal to stream, or a
run computed from a model instead of recorded, and what the stored test says besides
the request) and computes the step metrics of its record (``metrics``; None where the
analysis is made when the run is read). ``returns_to_start``: a position test, which
ends at its target (checked against the travel window before it starts) and moves back
to its start after the record.

``KindTable`` gives the kind of a name: the frequency response (``FrequencyResponseKind``,
planned by the bench from the device's controller law, ``servotune.bench.frf``), or a
kind the axis' own driver plans (``DriverPlannedKind``: move, position, velocity and PWM
steps, ``link.base.BenchPlanner``). Which kinds an axis offers is its driver's list;
nothing here knows a device.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final, Protocol

from servotune.bench import frf
from servotune.bench.limits import BenchLimits
from servotune.bench.metrics import compute_metrics
from servotune.bench.quality import POSITION_KINDS
from servotune.hub.records import AxisEntry
from servotune.link.base import (
    BenchPlan,
    BenchPlanner,
    BenchTest,
    DeviceRefusedError,
    InvalidArgumentError,
    Sample,
)
from servotune.schema import BenchTestRequest
from servotune.tuning.frfrun import Excitation
from servotune.tuning.law import DeviceLaws

FLAGS_T_COLUMN: Final = "flags_t_s"
"""The recorded column of when each sample's flags were read (``Sample.flags_t``; the
sample's own time where the driver reads them with it): time to a polled flag is
located between its reads, not at the samples that carry an older read."""


@dataclass(frozen=True, slots=True)
class KindPlan:
    """A planned test: the device's ``plan``; the signal to stream while it records
    (``excitation``, None: none); ``model_based``: nothing is sent, the run is computed
    from the identified plant; ``test``: what the stored test says besides the
    request's kind, distance, velocity, pwm, duration and note."""

    plan: BenchPlan
    excitation: Excitation | None = None
    model_based: bool = False
    test: dict[str, Any] = field(default_factory=dict)


class Record(Protocol):
    """A run's record as a kind reads it (``bench.runner.Recording``): the rows, one per
    sample, as ``columns`` (the last item of a row: the ``flags``, 0/1)."""

    @property
    def plan(self) -> BenchPlan: ...

    @property
    def columns(self) -> list[str]: ...

    @property
    def flags(self) -> list[str]: ...

    @property
    def samples(self) -> list[list[Any]]: ...

    @property
    def t0(self) -> float | None: ...


class TestKind(Protocol):
    """One kind of bench test (see the module docstring)."""

    @property
    def name(self) -> str: ...

    @property
    def returns_to_start(self) -> bool: ...

    def check(
        self,
        entry: AxisEntry,
        request: BenchTestRequest,
        limits: BenchLimits,
        identified: Mapping[str, Any] | None,
    ) -> None:
        """Refuse a request this kind cannot run on the axis (InvalidArgumentError:
        422, DeviceRefusedError: 409), before anything moves. The user's limits on
        distance, velocity, pwm and duration are the bench's, checked for every kind."""
        ...

    def plan(
        self,
        entry: AxisEntry,
        planner: BenchPlanner,
        test: BenchTest,
        request: BenchTestRequest,
        latest: Sample,
        limits: BenchLimits,
    ) -> KindPlan:
        """Plan the test from the axis' state now (``latest``); DeviceRefusedError if it
        cannot run, InvalidArgumentError if it would leave the user's limits."""
        ...

    def metrics(self, record: Record) -> dict[str, Any] | None:
        """The step metrics of the record (``bench.metrics``), None when this kind has
        none or the record is too short."""
        ...


@dataclass(frozen=True, slots=True)
class DriverPlannedKind:
    """A kind the axis' driver plans (``BenchPlanner.bench_plan``): move, position,
    velocity and PWM steps, with the step metrics of their record."""

    name: str

    @property
    def returns_to_start(self) -> bool:
        return self.name in POSITION_KINDS

    def check(
        self,
        entry: AxisEntry,
        request: BenchTestRequest,
        limits: BenchLimits,
        identified: Mapping[str, Any] | None,
    ) -> None:
        """Nothing besides the bench's limits: the driver refuses when it plans."""

    def plan(
        self,
        entry: AxisEntry,
        planner: BenchPlanner,
        test: BenchTest,
        request: BenchTestRequest,
        latest: Sample,
        limits: BenchLimits,
    ) -> KindPlan:
        return KindPlan(planner.bench_plan(test, latest, entry.device_values))

    def metrics(self, record: Record) -> dict[str, Any] | None:
        plan, columns = record.plan, record.columns
        if record.t0 is None or not record.samples:
            return None
        index = columns.index(plan.response)
        rows = [r for r in record.samples if r[index] is not None]
        if len(rows) < 3:
            return None
        error_index = columns.index("following_error") if "following_error" in columns else None
        flag_series = {name: [bool(r[-1][i]) for r in rows] for i, name in enumerate(record.flags)}
        flags_t_index = columns.index(FLAGS_T_COLUMN) if FLAGS_T_COLUMN in columns else None
        metrics = compute_metrics(
            [r[0] for r in rows],
            [r[index] for r in rows],
            t0_s=record.t0,
            y0=plan.y0,
            y_final=plan.y_final,
            band=plan.band,
            following_error=([r[error_index] for r in rows] if error_index is not None else None),
            flags=flag_series,
            flags_t_s=([r[flags_t_index] for r in rows] if flags_t_index is not None else None),
        )
        return metrics.model_dump()


@dataclass(frozen=True, slots=True)
class FrequencyResponseKind:
    """The frequency response (``servotune.bench.frf``): a multisine streamed to a
    device that takes an excitation on its wire (``DeviceLaw.injection``: closed loop
    as position targets, or open loop as PWM), else the identified plant under the
    device's law, computed and stored as a run (model-based). Analysed when read."""

    laws: DeviceLaws
    name: str = frf.KIND
    returns_to_start: bool = False

    def check(
        self,
        entry: AxisEntry,
        request: BenchTestRequest,
        limits: BenchLimits,
        identified: Mapping[str, Any] | None,
    ) -> None:
        inject = frf.injection_for(self.laws.law(entry.info.device))
        frf.check_request(
            entry.info.device,
            inject,
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
        if inject is None and not identified:
            raise DeviceRefusedError(
                f"a {entry.info.device} frequency response is model-based: identify the "
                "plant first (auto-tune, Identify)"
            )

    def plan(
        self,
        entry: AxisEntry,
        planner: BenchPlanner,
        test: BenchTest,
        request: BenchTestRequest,
        latest: Sample,
        limits: BenchLimits,
    ) -> KindPlan:
        inject = frf.injection_for(self.laws.law(entry.info.device))
        excitation: Excitation | None = None
        model_based = False
        if inject is not None and request.loop == "open":
            plan, excitation = frf.plan_open(
                inject, latest, request.pwm, request.low_hz, request.high_hz, entry.link.baud
            )
        elif inject is not None:
            plan, excitation = frf.plan_closed(
                inject,
                latest,
                entry.device_values,
                request.amplitude,
                request.low_hz,
                request.high_hz,
                entry.link.baud,
            )
            _check_excursion(plan.y0, request.amplitude, limits)
        else:
            plan, model_based = frf.model_plan(latest), True
        described = {
            "amplitude": request.amplitude,
            "low_hz": request.low_hz,
            "high_hz": request.high_hz,
            "model_based": model_based,
            "loop": request.loop,
        }
        return KindPlan(plan, excitation, model_based, described)

    def metrics(self, record: Record) -> dict[str, Any] | None:
        return None  # analysed when the run is read (bench.frf.analyse_run)


def _check_excursion(y0: float, amplitude: int, limits: BenchLimits) -> None:
    """A multisine must stay inside the travel window at its peaks (422)."""
    for edge in (y0 - amplitude, y0 + amplitude):
        if why := limits.outside(edge):
            raise InvalidArgumentError(
                "amplitude",
                f"amplitude {amplitude} around {y0:.0f} would reach {why} (bench limits)",
            )


class KindTable:
    """The kind object of each kind name: the ones the bench plans itself, and any
    other kind planned by the axis' driver."""

    def __init__(self, kinds: Sequence[TestKind]) -> None:
        self._kinds = {kind.name: kind for kind in kinds}

    @classmethod
    def standard(cls, laws: DeviceLaws) -> KindTable:
        """The bench's kinds: the frequency response, from the devices' ``laws``."""
        return cls([FrequencyResponseKind(laws)])

    def get(self, name: str) -> TestKind:
        return self._kinds.get(name) or DriverPlannedKind(name)
