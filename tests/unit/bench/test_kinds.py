"""The bench's test kinds as objects (servotune.bench.kinds): which object a kind name
gets, and what each computes from a record."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from servotune.bench.kinds import (
    FLAGS_T_COLUMN,
    DriverPlannedKind,
    FrequencyResponseKind,
    KindTable,
)
from servotune.link.base import BenchPlan
from servotune.tuning.law import DeviceLaw


class NoLaws:
    def law(self, device: str) -> DeviceLaw | None:
        return None


@dataclass
class Record:
    plan: BenchPlan
    columns: list[str]
    flags: list[str]
    samples: list[list[Any]] = field(default_factory=list)
    t0: float | None = 0.0


def step_record() -> Record:
    """A position step 0 -> 1000 that settles after 0.2 s, sampled every 10 ms."""
    plan = BenchPlan(
        setup=[], trigger=[], finish=[], response="position", y0=0.0, y_final=1000.0, band=5.0
    )
    rows: list[list[Any]] = []
    for i in range(60):
        t = i * 0.01
        position = min(1000.0, 5000.0 * t)
        rows.append([t, position, 1000.0 - position, t, [int(position >= 1000.0)]])
    return Record(plan, ["t_s", "position", "following_error", FLAGS_T_COLUMN], ["inpos"], rows)


def test_the_frequency_response_is_the_benchs_own_kind_every_other_the_drivers() -> None:
    table = KindTable.standard(NoLaws())
    assert isinstance(table.get("frequency_response"), FrequencyResponseKind)
    for name, returns in (
        ("move", True),
        ("position_step", True),
        ("velocity_step", False),
        ("pwm_step", False),
    ):
        kind = table.get(name)
        assert kind == DriverPlannedKind(name) and kind.returns_to_start is returns
    assert table.get("frequency_response").returns_to_start is False


def test_a_driver_planned_kind_has_the_step_metrics_of_its_record() -> None:
    metrics = DriverPlannedKind("position_step").metrics(step_record())
    assert metrics is not None
    assert metrics["rise_time_s"] is not None and 0.1 < metrics["rise_time_s"] < 0.2
    assert metrics["overshoot_pct"] == 0.0
    # Too short a record, or none triggered: no metrics.
    short = step_record()
    short.samples = short.samples[:2]
    assert DriverPlannedKind("position_step").metrics(short) is None
    untriggered = step_record()
    untriggered.t0 = None
    assert DriverPlannedKind("position_step").metrics(untriggered) is None


def test_a_frequency_response_has_no_step_metrics() -> None:
    assert FrequencyResponseKind(NoLaws()).metrics(step_record()) is None
