"""The auto-tune's REST bodies (``servotune.api.autotune_routes``).

The request is validated by its model; the answers are built as dicts by the generic
auto-tune (``autotune.service``, ``autotune.recommend``) around a device tuner's proposal
and verification, and documented by the shapes below. They are device-neutral: gains
are ``{parameter: value}`` under the descriptor's names, the identified model, the
test tuned for and the rule's design notes are ``{name: value}`` maps the page lists
as they come, so a new device's tuner needs no new type and the page no device branch.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field

from servotune.schema.base import Number, _Shape
from servotune.schema.runs import RunMetrics
from servotune.schema.whatif import MarginPreset, MarginReport, MarginTarget

AutoTuneAction = Literal["keep", "write"]
AutoTuneGoal = Literal["no_overshoot", "fast"]
"""no_overshoot: at most 1 % overshoot; fast: at most 10 % (each rule's limit)."""
AutoTuneTestKind = Literal["position_step", "move"]
AutoTuneState = Literal[
    "idle", "identifying", "proposed", "kept", "verifying", "verified", "failed"
]
AutoTuneVerdict = Literal["better", "not better", "unknown"]


class AutoTuneRequest(BaseModel):
    """``POST /api/axes/{id}/autotune/identify``: the user's limits and the goal."""

    # le: tuning.plants.OUTPUT_FULL_SCALE (the schema imports no tuning; a unit test
    # checks the two agree)
    max_pwm: int = Field(ge=1, le=255, description="largest open-loop PWM (-255..255)")
    max_distance_counts: int = Field(
        ge=1,
        le=1 << 24,
        description="no test travels further than this from where it starts (counts)",
    )
    response: AutoTuneGoal = Field(
        default="no_overshoot", description="no_overshoot (<= 1 %) or fast (<= 10 %)"
    )
    test: AutoTuneTestKind = Field(
        default="position_step",
        description="the test the gains are tuned for: position_step (sv/sa at maximum) "
        "or move (the axis' own sv/sa)",
    )
    direction: Literal[1, -1] = Field(
        default=1, description="1: identify and test towards positive counts, -1: negative"
    )
    # default: tuning.targets.DEFAULT_PRESET (checked by the same unit test)
    margins: MarginPreset = Field(
        default="medium",
        description="the margin target the gains are designed to: stiff (PM 40 deg / GM 6 dB), "
        "medium (45 deg / 8 dB) or soft (60 deg / 12 dB)",
    )
    distance: int | None = Field(
        default=None,
        ge=1,
        le=1 << 24,
        description="distance of the baseline and verification tests, counts "
        "(default: the device's, e.g. 1000 for a SLAP2, or half of max_distance_counts "
        "if smaller)",
    )


class AutoTuneSide(_Shape):
    """One side of the recommendation's comparison: margins on the model, predicted step."""

    phase_margin_deg: Number | None
    gain_margin_db: Number | None
    stable: bool | None
    meets_target: bool | None
    settling_time_s: Number | None
    overshoot_pct: Number | None


class AutoTuneRecommendation(_Shape):
    """Keep the gains in use or write the proposal, and why (``autotune.recommend``)."""

    action: AutoTuneAction
    reason: str
    target: MarginTarget
    proposal: AutoTuneSide
    current: AutoTuneSide


class AutoTuneDecision(_Shape):
    """What the user chose for a proposal (``POST .../autotune/keep`` answers it; the
    session's ``decision`` and ``history`` keep it)."""

    action: AutoTuneAction
    gains: dict[str, int]
    recommended: AutoTuneAction | None
    followed: bool
    reason: str | None
    at_s: Number = Field(description="unix seconds")
    identification_run_id: str | None


class AutoTuneProposal(_Shape):
    """``POST .../autotune/identify`` (and the session's ``proposal``): the identified
    model, the proposed gains against the ones in use, both predicted on the model."""

    model: dict[str, Number] = Field(description="the identified plant's parameters by name")
    test: dict[str, Number] = Field(
        description="the move tuned for: distance (counts, signed), band, velocity, ..."
    )
    response: AutoTuneGoal
    gains: dict[str, int] = Field(description="proposed, by the descriptor's parameter names")
    current_gains: dict[str, int] = Field(description="in use when identified")
    predicted: RunMetrics = Field(description="the proposal's step on the model")
    predicted_default: RunMetrics = Field(description="the gains in use, on the same model")
    predicted_peak_pwm: int
    predicted_excursion: int = Field(description="counts the proposal's test travels")
    default_excursion: int = Field(description="counts the gains in use would travel")
    design: dict[str, Any] = Field(description="the rule's notes, by name (shown as they come)")
    rule: str
    candidates: int
    simulations: int
    margins: MarginReport
    margins_default: MarginReport
    identification_run_id: str
    identification_run_ids: list[str] = Field(
        description="every attempt (a doubtful fit is repeated)"
    )
    travel_counts: Number
    warnings: list[str] = Field(description="doubts about the model, in words")
    baseline_possible: bool = Field(
        description="the gains in use stay within max_distance_counts: a baseline test runs"
    )
    recommendation: AutoTuneRecommendation
    device: str | None = Field(default=None, description="the tuner's device, where it says")
    model_samples: int | None = Field(
        default=None, description="samples the model was fitted to, where the tuner says"
    )


class AutoTuneResult(_Shape):
    """``POST .../autotune/accept`` after the verification: the baseline test with the
    previous gains, then the test with the proposal; predicted against measured."""

    gains: dict[str, int]
    previous_gains: dict[str, int]
    predicted: RunMetrics
    measured: RunMetrics | dict[str, None] = Field(
        description="the verification run's metrics; {} when the run has none (too few samples)"
    )
    predicted_default: RunMetrics
    baseline_measured: RunMetrics | None = Field(description="null: no baseline, or no metrics")
    verification_run_id: str
    baseline_run_id: str | None = Field(description="null: the baseline was skipped")
    baseline_note: str = Field(description="why the baseline was skipped; empty when it ran")
    verdict: AutoTuneVerdict
    verdict_reason: str | None = Field(description="why the verdict is what it is")


class AutoTuneStopped(_Shape):
    """``POST .../autotune/accept`` when the verification ended early (a 200 for a
    user's STOP; the session's ``result`` for any failure): the axis is stopped and the
    previous gains are written back (``unverified``: that failed, press Revert)."""

    stopped: bool
    unverified: bool
    message: str
    verdict: Literal["stopped", "failed"]
    previous_gains: dict[str, int]
    gains_in_force: dict[str, int | None]


class AutoTuneSession(_Shape):
    """``GET /api/axes/{id}/autotune``: the axis' auto-tune state, its last request,
    proposal, result and the user's decisions (``history``: newest last)."""

    axis: str
    state: AutoTuneState
    message: str
    request: AutoTuneRequest | None
    identification_run_id: str | None
    model: dict[str, Number] | None
    proposal: AutoTuneProposal | None
    result: AutoTuneResult | AutoTuneStopped | None
    decision: AutoTuneDecision | None
    history: list[AutoTuneDecision]
    updated_s: Number = Field(description="unix seconds; 0 before the first request")
