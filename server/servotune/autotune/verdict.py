"""Is the tuned run better than the baseline? (docs/autotune.md, "Predicted vs
measured, and better"; the Z1100's rule in its section).

Both rules read the bench's measured metrics (``schema.RunMetrics`` as dicts) and the
run quality's reason when a settling time could not be measured. Each verdict comes
with the sentence that says what it rests on (``*_with_reason``): the UI shows it next
to the badge, so a "better" won over a settling time that is no better than the
baseline's (within the sample spacing) says so instead of contradicting the numbers.
"""

from __future__ import annotations

from typing import Any


def _ms(seconds: float) -> str:
    return f"{seconds * 1000:.0f} ms"


def verdict_with_reason(
    baseline: dict[str, Any] | None,
    tuned: dict[str, Any] | None,
    *,
    baseline_unmeasured: str | None = None,
    tuned_unmeasured: str | None = None,
) -> tuple[str, str]:
    """(``better``, ``not better`` or ``unknown``, why): docs/autotune.md.

    The tuned run is better when it settles and the baseline does not, or settles
    sooner; or when it settles no later than one sample spacing after the baseline
    (the time resolution of polled telemetry) with at most half of the baseline's
    overshoot, the baseline's being at least 1 %.

    ``unknown`` without a baseline, and when a settling time is null because the
    bench could not *measure* it (``*_unmeasured``: the run quality's reason, e.g. the
    samples that would locate it are too far apart): a measurement failure is no
    evidence that either run is worse. A null settling time that was measured (the
    record ends outside the window) stays a real "did not settle".
    """
    if tuned is None or baseline is None:
        return "unknown", "no baseline run to compare with"
    if tuned_unmeasured or baseline_unmeasured:
        return "unknown", str(tuned_unmeasured or baseline_unmeasured)
    tuned_settle = tuned.get("settling_time_s")
    base_settle = baseline.get("settling_time_s")
    if tuned_settle is None:
        return "not better", "the tuned run did not settle into the window"
    if base_settle is None:
        return "better", "the tuned run settles, the baseline did not"
    if tuned_settle < base_settle:
        return "better", f"settles in {_ms(tuned_settle)} against {_ms(base_settle)}"
    resolution = max(tuned.get("max_sample_gap_s") or 0.0, baseline.get("max_sample_gap_s") or 0.0)
    base_os = baseline.get("overshoot_pct")
    tuned_os = tuned.get("overshoot_pct")
    if base_os is None or tuned_os is None:
        # the bench could not trust an overshoot (run quality): no evidence either way
        return "unknown", "an overshoot could not be measured"
    if tuned_settle <= base_settle + resolution and base_os >= 1.0 and tuned_os <= 0.5 * base_os:
        return "better", (
            f"settles as fast within the sample spacing ({_ms(tuned_settle)} against "
            f"{_ms(base_settle)}, ±{_ms(resolution)}) with {tuned_os:.1f} % overshoot "
            f"against {base_os:.1f} %"
        )
    return "not better", f"settles in {_ms(tuned_settle)} against {_ms(base_settle)}"


def verdict(
    baseline: dict[str, Any] | None,
    tuned: dict[str, Any] | None,
    *,
    baseline_unmeasured: str | None = None,
    tuned_unmeasured: str | None = None,
) -> str:
    """The verdict of ``verdict_with_reason`` alone."""
    return verdict_with_reason(
        baseline,
        tuned,
        baseline_unmeasured=baseline_unmeasured,
        tuned_unmeasured=tuned_unmeasured,
    )[0]


def verdict_z1100_with_reason(
    baseline: dict[str, Any] | None,
    tuned: dict[str, Any] | None,
    *,
    baseline_unmeasured: str | None = None,
    tuned_unmeasured: str | None = None,
) -> tuple[str, str]:
    """``better`` when the tuned run settles and the baseline does not or settles later,
    or settles no later than one sample spacing after it with a peak following error at
    most 3/4 of the baseline's; ``not better``; ``unknown`` without a baseline, when a
    settling time could not be measured (see ``verdict_with_reason``), or when the
    comparison rests on a peak following error the bench could not resolve (null)."""
    if tuned is None or baseline is None:
        return "unknown", "no baseline run to compare with"
    if tuned_unmeasured or baseline_unmeasured:
        return "unknown", str(tuned_unmeasured or baseline_unmeasured)
    ts, bs = tuned.get("settling_time_s"), baseline.get("settling_time_s")
    if ts is None:
        return "not better", "the tuned run did not settle into the window"
    if bs is None:
        return "better", "the tuned run settles, the baseline did not"
    if ts < bs:
        return "better", f"settles in {_ms(ts)} against {_ms(bs)}"
    resolution = max(tuned.get("max_sample_gap_s") or 0.0, baseline.get("max_sample_gap_s") or 0.0)
    if ts > bs + resolution:
        return "not better", f"settles in {_ms(ts)} against {_ms(bs)}"
    tf, bf = tuned.get("peak_following_error"), baseline.get("peak_following_error")
    if tf is None or bf is None:
        return "unknown", (
            f"settles as fast within the sample spacing ({_ms(ts)} against {_ms(bs)}, "
            f"±{_ms(resolution)}) and a peak following error could not be measured"
        )
    if abs(tf) <= 0.75 * abs(bf):
        return "better", (
            f"settles as fast within the sample spacing ({_ms(ts)} against {_ms(bs)}, "
            f"±{_ms(resolution)}) with a peak following error of {abs(tf):.0f} against "
            f"{abs(bf):.0f}"
        )
    return "not better", (
        f"settles no faster ({_ms(ts)} against {_ms(bs)}) and its peak following error "
        f"({abs(tf):.0f} against {abs(bf):.0f}) is not clearly smaller"
    )


def verdict_z1100(
    baseline: dict[str, Any] | None,
    tuned: dict[str, Any] | None,
    *,
    baseline_unmeasured: str | None = None,
    tuned_unmeasured: str | None = None,
) -> str:
    """The verdict of ``verdict_z1100_with_reason`` alone."""
    return verdict_z1100_with_reason(
        baseline,
        tuned,
        baseline_unmeasured=baseline_unmeasured,
        tuned_unmeasured=tuned_unmeasured,
    )[0]
