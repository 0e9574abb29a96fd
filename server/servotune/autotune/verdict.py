"""Is the tuned run better than the baseline? (docs/autotune.md, "Predicted vs
measured, and better"; the Z1100's rule in its section).

Both rules read the bench's measured metrics (``metrics.Metrics`` as dicts) and the
run quality's reason when a settling time could not be measured.
"""

from __future__ import annotations

from typing import Any


def verdict(
    baseline: dict[str, Any] | None,
    tuned: dict[str, Any] | None,
    *,
    baseline_unmeasured: str | None = None,
    tuned_unmeasured: str | None = None,
) -> str:
    """``better``, ``not better`` or ``unknown``: docs/autotune.md.

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
        return "unknown"
    if tuned_unmeasured or baseline_unmeasured:
        return "unknown"
    tuned_settle = tuned.get("settling_time_s")
    base_settle = baseline.get("settling_time_s")
    if tuned_settle is None:
        return "not better"
    if base_settle is None or tuned_settle < base_settle:
        return "better"
    resolution = max(tuned.get("max_sample_gap_s") or 0.0, baseline.get("max_sample_gap_s") or 0.0)
    base_os = baseline.get("overshoot_pct")
    tuned_os = tuned.get("overshoot_pct")
    if base_os is None or tuned_os is None:
        # the bench could not trust an overshoot (run quality): no evidence either way
        return "unknown"
    if tuned_settle <= base_settle + resolution and base_os >= 1.0 and tuned_os <= 0.5 * base_os:
        return "better"
    return "not better"


def verdict_z1100(
    baseline: dict[str, Any] | None,
    tuned: dict[str, Any] | None,
    *,
    baseline_unmeasured: str | None = None,
    tuned_unmeasured: str | None = None,
) -> str:
    """``better`` when the tuned run settles and the baseline does not or settles later,
    or settles no later than one sample spacing after it with a peak following error at
    most 3/4 of the baseline's; ``not better``; ``unknown`` without a baseline or when
    a settling time could not be measured (see ``verdict``)."""
    if tuned is None or baseline is None:
        return "unknown"
    if tuned_unmeasured or baseline_unmeasured:
        return "unknown"
    ts, bs = tuned.get("settling_time_s"), baseline.get("settling_time_s")
    if ts is None:
        return "not better"
    if bs is None or ts < bs:
        return "better"
    resolution = max(tuned.get("max_sample_gap_s") or 0.0, baseline.get("max_sample_gap_s") or 0.0)
    tf = abs(tuned.get("peak_following_error") or 0.0)
    bf = abs(baseline.get("peak_following_error") or 0.0)
    if ts <= bs + resolution and tf <= 0.75 * bf:
        return "better"
    return "not better"
