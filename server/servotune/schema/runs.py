"""Stored bench runs (``GET /api/axes/{id}/bench/runs``, ``GET /api/bench/runs/{id}``).

These bodies are built by the bench from the stored run, not serialised through a model:
the models below state their shape (the routes document them, tests check real runs
against them). A field with a default may be absent from a body; every other one is
there. ``RunMetrics`` aside: the bench computes and validates with that model itself.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import ConfigDict, Field

from servotune.schema.base import FiniteFloat, _Shape
from servotune.schema.bench import BenchKind

RunStatus = Literal["recording", "complete", "incomplete"]


class RunIdentity(_Shape):
    """Where the run was recorded: the link, its device path, the axis' address and name."""

    link: str
    path: str
    address: int
    name: str


class RunTest(_Shape):
    """The test as recorded (units are the device's); the frequency-response fields only
    on a ``frequency_response`` run."""

    kind: BenchKind
    distance: int
    velocity: int
    pwm: int
    duration_s: float
    note: str
    amplitude: int | None = None
    low_hz: float | None = None
    high_hz: float | None = None
    model_based: bool | None = Field(
        default=None, description="computed from the identified plant, nothing was sent"
    )
    loop: Literal["closed", "open"] | None = None


class RunPlan(_Shape):
    """What the metrics are computed on: the response column, its start and final
    values, the settling band (null: 2 % of the step) and the parameters the test set."""

    response: str
    y0: float
    y_final: float
    band: float | None
    overrides: dict[str, int]


class RunMetrics(_Shape):
    """The step-response metrics of a run, the one definition: ``bench.metrics.
    compute_metrics`` returns it, the bench stores and lists it, the auto-tune predicts
    it, an imported run's are checked against it. Times in s after the trigger t0; null
    where not defined, not reached or not trusted (``RunQuality.untrusted`` says why).
    What each one is: ``bench.metrics.DEFINITIONS`` (served as ``BenchInfo.definitions``).

    Strict (a number is a JSON number, not a string) and finite (NaN and infinities are
    refused: JSON has none), immutable once computed."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    step: FiniteFloat
    band: FiniteFloat | None
    samples: int = Field(ge=0)
    max_sample_gap_s: FiniteFloat | None
    rise_time_s: FiniteFloat | None
    overshoot_pct: FiniteFloat | None
    peak_time_s: FiniteFloat | None
    peak_value: FiniteFloat | None
    settling_time_s: FiniteFloat | None
    steady_state_error: FiniteFloat | None
    oscillations: int | None
    peak_following_error: FiniteFloat | None
    rms_following_error: FiniteFloat | None
    time_to_flag_s: dict[str, FiniteFloat | None]
    time_in_flag_s: dict[str, FiniteFloat]
    time_to_flag_resolution_s: dict[str, FiniteFloat | None] = Field(
        default_factory=dict,
        description="the ± of the flag times (flags are polled); absent on older runs",
    )
    time_in_flag_resolution_s: dict[str, FiniteFloat] = Field(default_factory=dict)


class RunReason(_Shape):
    code: str
    message: str


class RunQuality(_Shape):
    """How far the run's metrics can be trusted (``servotune.bench.quality``): ``bad`` runs
    are not comparable; ``untrusted`` names the metrics set to null and why."""

    status: Literal["good", "doubtful", "bad"]
    reasons: list[RunReason]
    untrusted: dict[str, str] = Field(default_factory=dict)
    sampling_rule: int | None = Field(
        default=None, description="the version of the sampling rule that judged the run"
    )


class RunReturn(_Shape):
    """The move back to where the test started, after the record."""

    ok: bool
    to: float
    error: float | None
    message: str


class BenchRun(_Shape):
    """A stored run without its samples (``GET /api/axes/{id}/bench/runs``; ``POST`` there
    answers the new run, without ``baseline``). ``columns[0]`` is ``t_s``."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True)

    id: str
    axis_id: str
    created_s: float | None = Field(description="unix seconds")
    status: RunStatus
    baseline: bool = False
    axis_key: str
    device: str
    model: str
    identity: RunIdentity | None = None
    test: RunTest
    params: dict[str, int]
    plan: RunPlan
    columns: list[str]
    flags: list[str]
    metrics: RunMetrics | None
    quality: RunQuality | None = None
    message: str
    t0_s: float | None = Field(default=None, description="the trigger, server clock")
    imported_from: str | None = None
    autotune: dict[str, Any] | None = Field(
        default=None, description="what the auto-tune recorded with its runs"
    )
    excitation: dict[str, Any] | None = Field(
        default=None, description="frequency_response: the multisine and the targets sent"
    )
    plant_model: dict[str, Any] | None = Field(
        default=None, description="model-based frequency_response: the identified plant"
    )
    trigger_latency_s: float | None = None
    left_oscillating: dict[str, Any] | None = Field(
        default=None, description="the run left the axis oscillating: what was done"
    )
    loop_unverified: dict[str, Any] | None = Field(
        default=None,
        description="the check after the run could not tell whether the loop is at rest "
        "(telemetry too sparse): what was done",
    )
    return_: RunReturn | None = Field(default=None, alias="return")


class BenchRunDetail(BenchRun):
    """``GET /api/bench/runs/{id}``: the run with its sample rows, each ``[t_s, one value
    per columns[1..], [a 0/1 per flag, in flags order]]``."""

    samples: list[list[float | list[int] | None]]
