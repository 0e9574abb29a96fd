"""The frequency response of a run (``GET /api/bench/runs/{id}/frf``).

Built in the compute worker by ``servotune.bench.frf.analyse_run`` (measured: from the
run's samples; model: the identified plant under the device's law); documented shapes.
Every non-finite number is sent as null.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field

from servotune.schema.base import Number, _Shape
from servotune.schema.whatif import MarginReport, WhatIfPlant


class FrfBode(_Shape):
    """A Bode curve: magnitude (dB) and phase (deg) over frequency; the per-tone lists
    only on measured curves."""

    frequency_hz: list[float | None]
    magnitude_db: list[float | None]
    phase_deg: list[float | None]
    coherence: list[float | None] = Field(
        default_factory=list, description="magnitude-squared coherence over the periods"
    )
    relative_error: list[float | None] = Field(default_factory=list)
    error_db: list[float | None] = Field(
        default_factory=list, description="error bounds (about 95 %)"
    )
    error_deg: list[float | None] = Field(default_factory=list)
    trusted: list[bool] = Field(
        default_factory=list, description="known within the instrument's limits"
    )
    not_trusted_because: list[str | None] = Field(default_factory=list)
    measurable: list[bool] = Field(
        default_factory=list, description="open loop: L is known at the tone"
    )


class FrfNyquist(_Shape):
    """The open loop in the complex plane."""

    frequency_hz: list[float | None]
    re: list[float | None]
    im: list[float | None]
    measurable: list[bool] = Field(default_factory=list)


class FrfMargins(MarginReport):
    """Margins of the open loop against the target; a measured run says why a margin is
    null (``*_problem``) and how uncertain it is (``*_error_*``, about 95 %)."""

    gain_margin_problem: str | None = None
    phase_margin_problem: str | None = None
    gain_margin_error_db: Number | None = None
    phase_margin_error_deg: Number | None = None


class FrfTrust(_Shape):
    """Why a measured run's tones are (not) trusted (``servotune.tuning.frftrust``)."""

    trusted_tones: int
    tones: int
    max_error_db: Number
    max_error_deg: Number
    coverage: Number
    not_trusted: list[str]
    input_check_counts: Number | None
    input_check_excess_counts: Number | None
    input_check_samples_over: int
    stalled_samples_left_out: int
    stalled_targets_bounded: int
    max_latch_span_ms: Number | None
    spans: str
    max_gap_ms: Number | None
    gaps_over_50_ms: int


class FrfModel(_Shape):
    """The identified plant under the device's exact law with the run's gains."""

    margins: MarginReport
    bandwidth_hz: Number | None
    resonance_db: Number | None
    closed_loop: FrfBode
    open_loop: FrfBode
    nyquist: FrfNyquist
    plant: WhatIfPlant
    law: str


class FrfMeasured(_Shape):
    """The response measured from the run's samples at its tones: closed loop (targets
    injected) or open loop (``plant`` measured, the loop closed with the run's gains)."""

    loop: Literal["closed", "open"]
    closed_loop: FrfBode
    open_loop: FrfBode
    plant: FrfBode | None = Field(default=None, description="open loop: the plant measured")
    nyquist: FrfNyquist
    margins: FrfMargins
    input: str = Field(description="pwm (open loop), or the input model of the targets")
    usable_from_hz: Number | None
    usable_until_hz: Number | None
    sample_rate_hz: Number | None
    nyquist_hz: Number | None
    periods: int
    samples: int
    input_check_counts: Number | None
    trust: FrfTrust
    estimator: str
    not_measured_hz: list[Number | None] = Field(
        description="requested tones the wire cannot resolve: not sent, not measured"
    )
    not_measured_reason: str | None
    wire: dict[str, Any] | None = Field(description="the wire plan of the tones")
    bandwidth_hz: Number | None
    resonance_db: Number | None


class FrfData(_Shape):
    """``GET /api/bench/runs/{id}/frf``: either part may be null with a ``*_problem``."""

    run_id: str | None
    device: str
    model_based: bool
    loop: str
    low_hz: Number
    high_hz: Number
    measured: FrfMeasured | None
    measured_problem: str | None
    model: FrfModel | None
    model_problem: str | None
