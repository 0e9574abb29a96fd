"""Is a bench run good enough to compare? Run-level faults and per-metric trust (sans-IO).

``assess`` looks at a finished run's samples next to its metrics and says two things
(docs/bench.md, "Quality"):

* ``quality.status``: ``bad`` when the run itself cannot be compared with another —
  it hit a limit switch, stalled, ended in current limit or with a drive error, did
  not move, ended outside the in-position window, or was cut off (incomplete);
  ``doubtful`` when it ran but something may have shaped the response (current limit
  on the way, a drive warning, fewer than ``MIN_SAMPLES`` samples); else ``good``.
  ``quality.reasons`` lists why, each with a ``code`` and a sentence.
* ``quality.untrusted``: metric name -> reason for every metric that is set to null
  because it cannot be trusted. A fault (limit switch, stall, current limit at the end,
  drive error, no movement, cut off) nulls every metric derived from the response
  (rise, overshoot, peak, settling, steady-state error, oscillations); a run that only
  ended outside the window keeps its rise, overshoot and oscillations (true
  measurements, e.g. of a limit cycle) and loses the steady-state error.

  Sampling, one rule for every metric and every run kind (``_unresolved``): a value is
  kept only when the samples resolve it — enough samples in the interval that defines
  it (``MIN_RISE_SAMPLES`` for the rise, ``MIN_INTERVAL_SAMPLES`` for the others: the
  rise between its 10 % and 90 % crossings; peak and
  settling time from the command on; oscillations and the following error over the
  move, until it settled), and no gap across that interval wider than the quantity
  (for the oscillations: than the shortest half-cycle counted). A flag's time is
  located between two reads of the flag; it is null when those reads are further
  apart than the time itself (its ± is reported with it). The overshoot also needs its
  peak located: null when the lateness the record shows in the stamps around the peak
  could move it by more than ``MAX_OVERSHOOT_UNCERTAINTY_PP``
  (``bench.metrics.overshoot_stamp_uncertainty_pct``), or when a sample next to the highest
  one is more than ``MAX_PEAK_GAP_RATIO`` times the record's usual spacing away and
  the curve bends enough around the peak for the peak to hide in that gap
  (``_peak_bound_pp``), or, for a response that ended in the band, when a gap before it
  could hold a higher peak (``_hidden_peak``:
  a hole over the first lobe leaves a lower lobe as the highest sample; the peak time
  goes with it). The settling time also needs the record after it: no gap between the
  instant and the end of the record wider than the settling time (the response may
  have left the band in it).

Facts that stay true whatever happened (step, band, samples, max gap, time in flags
with its ±) are never nulled.
"""

from __future__ import annotations

import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from itertools import pairwise
from typing import Any, Final

from servotune.bench.metrics import overshoot_stamp_uncertainty_pct, rise_crossings

MIN_SAMPLES: Final = 10
MIN_RISE_SAMPLES: Final = 10
"""Samples the rise time needs between its 10 % and 90 % crossings: the rise is the
shape of the motion itself, a spacing of about a tenth of it."""
MIN_INTERVAL_SAMPLES: Final = 3
"""Samples every other metric needs inside the interval that defines it (peak and
settling time: from the command to the instant; oscillations and following error: the
move, until it settled): the response seen at all before the instant, which the gap
rule then bounds (no gap across the interval wider than the quantity). The instant
itself is located to one bracketing gap, never wider than the quantity."""
MOVED_FRACTION: Final = 0.1  # less travel than this fraction of the step: did not move
PWM_MOVED_COUNTS: Final = 2.0
MAX_OVERSHOOT_UNCERTAINTY_PP: Final = 0.5
"""Half of the repeatability bound (1 pp between identical runs): two runs each within
it of the truth agree within the bound."""
MAX_PEAK_GAP_RATIO: Final = 1.9
"""The widest gap next to the highest sample, in median spacings, that still trusts
the overshoot: wider gaps can hide the peak between samples by more than
``MAX_OVERSHOOT_UNCERTAINTY_PP``, and the capture's interleaved ``rss`` reads must stay
below it (docs/bench.md, "Quality", has the measurement)."""
MAX_STAMP_SPAN_RATIO: Final = 1.0
"""The most a sample that locates the settling instant may have been latched before its
stamp, in the record's usual spacings: the instant is then off by at most one spacing,
half of the repeatability bound (identical steps settle within 2 spacings), as
``MAX_OVERSHOOT_UNCERTAINTY_PP`` is for the overshoot."""
SAMPLING_RULE: Final = 4
"""The version of the sampling rule (``_sampling_trust``) stored with a run's quality
(``quality.sampling_rule``): a stored or imported run judged by an older one is judged
again (``rejudge``), so the same rule holds for every run on the page."""
POSITION_KINDS: Final = frozenset({"move", "position_step"})
RESPONSE_METRICS: Final = (
    "rise_time_s",
    "overshoot_pct",
    "peak_time_s",
    "peak_value",
    "settling_time_s",
    "steady_state_error",
    "oscillations",
)

# Fault flags by what they mean for a run (names of the device descriptors).
_STALL_FLAGS: Final = frozenset({"stall", "motor_stall"})
_CURRENT_FLAGS: Final = frozenset({"oc"})
_ERROR_FLAGS: Final = frozenset({"error"})
_WARNING_FLAGS: Final = frozenset({"warning"})


def _reason(code: str, message: str) -> dict[str, str]:
    return {"code": code, "message": message}


def assess(
    *,
    kind: str,
    columns: Sequence[str],
    flag_names: Sequence[str],
    rows: Sequence[Sequence[Any]],
    t0_s: float | None,
    response: str,
    y0: float,
    y_final: float,
    band: float | None,
    fault_flags: Sequence[str],
    done_flag: str | None,
    metrics: Mapping[str, Any] | None,
    status: str,
    message: str,
    spans: Sequence[Sequence[float]] = (),
) -> tuple[dict[str, Any] | None, dict[str, Any]]:
    """(metrics with untrusted values set to None, quality) of one finished run.

    ``rows`` are the stored sample rows ``[t_s, value per column..., [flags 0/1]]``;
    ``spans``: ``[t_s, span_s]`` for the rows (same ``t_s``) whose latch the driver
    places up to ``span_s`` before ``t_s`` (``Sample.t_span_s``; rows without one are
    taken as stamped where they were latched)."""
    bad: list[dict[str, str]] = []
    doubts: list[dict[str, str]] = []
    untrusted: dict[str, str] = {}
    if status != "complete":
        bad.append(_reason("incomplete", f"the test did not complete: {message or status}"))
    if t0_s is None:
        return None, _quality(bad or [_reason("no_trigger", "the test never started")], [], {})
    after = [r for r in rows if r[0] >= t0_s]
    index = columns.index(response) if response in columns else None
    points = [
        (r[0] - t0_s, float(r[index])) for r in after if index is not None and r[index] is not None
    ]

    for i, name in enumerate(flag_names):
        if name not in fault_flags:
            continue
        on = [r for r in after if r[-1][i]]
        if not on:
            continue
        at_end = bool(after[-1][-1][i])
        span_s = on[-1][0] - on[0][0]
        if name.startswith("limit"):
            bad.append(_reason("limit_switch", f"limit switch {name} was active during the test"))
        elif name in _STALL_FLAGS:
            bad.append(_reason("stall", f"{name}: the motor stalled during the test"))
        elif name in _CURRENT_FLAGS and at_end:
            bad.append(_reason("current_limit", "the test ended in current limit (oc)"))
        elif name in _CURRENT_FLAGS:
            doubts.append(
                _reason(
                    "current_limit",
                    f"in current limit for about {span_s * 1000:.0f} ms: the response is "
                    "limited by the current, not by the gains",
                )
            )
        elif name in _ERROR_FLAGS:
            bad.append(_reason("drive_error", f"the drive reported {name} during the test"))
        elif name in _WARNING_FLAGS:
            doubts.append(_reason("drive_warning", f"the drive reported {name} during the test"))
        else:
            bad.append(_reason("fault", f"fault flag {name} was set during the test"))

    step = y_final - y0
    if kind in POSITION_KINDS or (kind == "velocity_step" and step != 0):
        travel = max((abs(y - y0) for _, y in points), default=0.0)
        if travel < MOVED_FRACTION * abs(step):
            bad.append(
                _reason(
                    "did_not_move",
                    f"did not move: {response} changed by {travel:.0f} of the commanded "
                    f"{abs(step):.0f}",
                )
            )
    elif kind == "pwm_step" and "position" in columns:
        p = columns.index("position")
        positions = [float(r[p]) for r in after if r[p] is not None]
        travel = max(positions) - min(positions) if positions else 0.0
        if travel < PWM_MOVED_COUNTS:
            bad.append(_reason("did_not_move", f"did not move: {travel:.0f} counts of travel"))

    if kind in POSITION_KINDS and points and status == "complete":
        error = points[-1][1] - y_final
        if band is not None and abs(error) > band:
            bad.append(
                _reason(
                    "outside_window",
                    f"ended {error:+.0f} from the target, outside the in-position window ±{band:g}",
                )
            )
        elif done_flag in flag_names and not after[-1][-1][flag_names.index(done_flag)]:
            bad.append(
                _reason("outside_window", f"{done_flag} was not set at the end of the record")
            )

    if len(points) < MIN_SAMPLES:
        doubts.append(
            _reason(
                "sparse",
                f"only {len(points)} samples after the trigger (at least {MIN_SAMPLES} "
                "needed to judge a response)",
            )
        )

    if metrics is None:
        return None, _quality(bad, doubts, untrusted)
    out = dict(metrics)
    out["time_to_flag_s"] = dict(metrics.get("time_to_flag_s") or {})
    if "time_to_flag_resolution_s" in metrics:
        out["time_to_flag_resolution_s"] = dict(metrics.get("time_to_flag_resolution_s") or {})
    # A fault distorts the whole response: every response metric goes. A run that
    # merely ended outside the window still shows a true rise and overshoot (e.g. the
    # limit cycle of poor gains): only what assumes a settled end goes.
    distorting = [r for r in bad if r["code"] != "outside_window"]
    nulled = RESPONSE_METRICS if distorting else ("steady_state_error",)
    why = (distorting or bad)[0]["message"] if bad else ""
    for name in nulled if bad else ():
        if out.get(name) is not None:
            untrusted[name] = why
            out[name] = None
    fe = columns.index("following_error") if "following_error" in columns else None
    span_at = {float(t): float(span) for t, span in spans}
    series = _Series(
        following_error_t=[r[0] - t0_s for r in rows if fe is not None and r[fe] is not None],
        spans=[
            span_at.get(float(r[0]), 0.0)
            for r in after
            if index is not None and r[index] is not None
        ],
    )
    _sampling_trust(out, points, series, y0, step, band, untrusted)
    return out, _quality(bad, doubts, untrusted)


@dataclass(frozen=True, slots=True)
class _Series:
    """The times (after t0, the whole record) of the slower series a metric may rest on,
    and how far before its stamp each response point may have been latched (``spans``,
    aligned with the points; empty: not known, as for a stored run)."""

    following_error_t: list[float]
    spans: list[float] = field(default_factory=list)


def _sampling_trust(
    out: dict[str, Any],
    points: list[tuple[float, float]],
    series: _Series,
    y0: float,
    step: float,
    band: float | None,
    untrusted: dict[str, str],
) -> None:
    """Null the metrics the sampling cannot support: the one rule of the module doc
    (``_unresolved``) for each metric's interval, plus the overshoot's own checks."""
    curve = points if points and points[0][0] == 0 else [(0.0, y0), *points]
    curve_t = [t for t, _ in curve]
    sample_t = [t for t, _ in points]

    def null(name: str, why: str | None) -> None:
        if why is not None:
            untrusted[name] = why
            out[name] = None

    rise = out.get("rise_time_s")
    if rise is not None and step != 0:
        direction = 1.0 if step > 0 else -1.0
        crossings = rise_crossings(curve_t, [(y - y0) * direction for _, y in curve], abs(step))
        if crossings is not None:
            t10, t90 = crossings
            null(
                "rise_time_s",
                _unresolved(
                    sample_t,
                    curve_t,
                    t10,
                    t90,
                    rise,
                    "rise",
                    "between 10 % and 90 %",
                    min_samples=MIN_RISE_SAMPLES,
                ),
            )
    overshoot = out.get("overshoot_pct")
    # Only for a response that ended in the band (a decaying step: its later lobes are
    # lower); a sustained oscillation's lobes are alike and stay judged as before.
    ended_in_band = band is not None and bool(points) and abs(points[-1][1] - y0 - step) <= band
    hidden = _hidden_peak(points, y0, step) if step != 0 and ended_in_band else None
    if overshoot is not None and overshoot > 0 and step != 0:
        null("overshoot_pct", hidden or _overshoot_unresolved(points, y0, step))
    peak_t = out.get("peak_time_s")
    if peak_t is not None and peak_t > 0:
        null(
            "peak_time_s",
            _unresolved(sample_t, curve_t, 0.0, peak_t, peak_t, "peak time", "up to the peak")
            or hidden,
        )
    settle = out.get("settling_time_s")
    if settle is not None and settle > 0 and band is not None:
        null(
            "settling_time_s",
            _unresolved(sample_t, curve_t, 0.0, settle, settle, "settling time", "until it settled")
            # "settled" says the response stayed in the band to the end of the record:
            # a hole after the instant wider than the settling time could hide it leaving
            or _unresolved(
                sample_t,
                curve_t,
                settle,
                sample_t[-1],
                settle,
                "settling time",
                "after it settled",
                "nothing shows the response stayed in the band",
                min_samples=1,
                bounded=True,
            )
            or _stamp_unvouched(points, series.spans, y0 + step, band),
        )
    # The move, for the metrics over it: from the command until the response settled
    # (the settling time before this rule judged it), else the whole record.
    settled = settle is not None and settle > 0
    oscillations = out.get("oscillations")
    if oscillations is not None and band is not None and step != 0 and sample_t:
        end = settle if settle is not None and settled else sample_t[-1]
        beyond = [((y - y0 - step) * (1.0 if step > 0 else -1.0)) for _, y in points]
        half_cycle = _shortest_half_cycle(sample_t, beyond, band)
        null(
            "oscillations",
            _unresolved(
                sample_t,
                curve_t,
                0.0,
                end,
                half_cycle if half_cycle is not None else end,
                "shortest half-cycle" if half_cycle is not None else "response",
                "until it settled" if settled else "in the record",
                bounded=True,
            ),
        )
    if out.get("peak_following_error") is not None or out.get("rms_following_error") is not None:
        fe_t = series.following_error_t
        end = settle if settle is not None and settled else (fe_t[-1] if fe_t else 0.0)
        why = (
            _unresolved(
                [t for t in fe_t if t >= 0],
                fe_t,
                0.0,
                end,
                end,
                "move",
                "of following error " + ("until the axis settled" if settled else "in the record"),
                "the following error was read too rarely to show the move's",
                bounded=True,
            )
            if end > 0
            else "no following-error sample after the command"
        )
        if why is not None:
            for name in ("peak_following_error", "rms_following_error"):
                null(name, why)
    times = out.get("time_to_flag_s") or {}
    resolutions = out.get("time_to_flag_resolution_s") or {}
    for name, value in list(times.items()):
        resolution = resolutions.get(name)
        if value is None or resolution is None:
            continue
        if 2 * resolution > value:
            untrusted[f"time_to_flag_s.{name}"] = (
                f"the flag was read {2 * resolution * 1000:.0f} ms apart around its rise, "
                f"more than the time to it ({value * 1000:.0f} ms)"
            )
            times[name] = None
            resolutions[name] = None


def _unresolved(
    samples: Sequence[float],
    points: Sequence[float],
    start: float,
    end: float,
    quantity_s: float,
    name: str,
    where: str,
    too_few: str = "",
    min_samples: int = MIN_INTERVAL_SAMPLES,
    bounded: bool = False,
) -> str | None:
    """Why ``name`` (``quantity_s`` long, defined by the interval ``start``..``end``
    after t0) is not resolved by the samples, or None when it is: at least
    ``min_samples`` of ``samples`` in the interval, and no gap between the
    ``points`` (the samples and any point the metric interpolates from, e.g. the
    command point) from the last one at or before ``start`` to the first one at or
    after ``end`` wider than ``quantity_s``; ``bounded``: a metric over the interval
    (a peak, a count) rather than an instant interpolated between samples: the spans
    are measured from ``start`` and to ``end`` themselves (before the command nothing
    moved; after ``end`` the metric does not look). ``too_few`` ends the reason for
    too few samples (default: the metric is faster than the telemetry resolves)."""
    inside = sum(1 for t in samples if start <= t <= end)
    if inside < min_samples:
        return (
            f"only {inside} sample{'' if inside == 1 else 's'} {where} "
            f"({start * 1000:.0f}..{end * 1000:.0f} ms; needs "
            f"{min_samples}): " + (too_few or f"the {name} is faster than the telemetry resolves")
        )
    inner = [t for t in points if start < t < end]
    if bounded:
        span = sorted({start, *inner, end})
    else:
        before = [t for t in points if t <= start]
        after = [t for t in points if t >= end]
        span = sorted({*(before[-1:]), *inner, *(after[:1])})
    gap = max((b - a for a, b in pairwise(span)), default=0.0)
    if gap > quantity_s:
        return (
            f"the samples {where} are up to {gap * 1000:.0f} ms apart, more than the "
            f"{name} itself ({quantity_s * 1000:.0f} ms)"
        )
    return None


def _stamp_unvouched(
    points: Sequence[tuple[float, float]], spans: Sequence[float], y_final: float, band: float
) -> str | None:
    """Why the settling instant is not located by the stamps of the samples that bracket
    it (``bench.metrics``' last sample outside the band and the one after it), or None:
    one of them may have been latched more than ``MAX_STAMP_SPAN_RATIO`` times the
    record's usual spacing before its stamp (``spans``, aligned with ``points``)."""
    if len(spans) != len(points) or len(points) < 3:
        return None
    last_out = next(
        (i for i in range(len(points) - 1, -1, -1) if abs(points[i][1] - y_final) > band), None
    )
    bracket = [0] if last_out is None else [last_out, last_out + 1]
    usual = statistics.median(b - a for (a, _), (b, _) in pairwise(points))
    worst = max((spans[i] for i in bracket if i < len(spans)), default=0.0)
    if worst <= MAX_STAMP_SPAN_RATIO * usual:
        return None
    return (
        f"a sample that locates it may have been latched up to {worst * 1000:.0f} ms before "
        f"its stamp (a host that read the reply late; the record's usual spacing is "
        f"{usual * 1000:.1f} ms): the axis may have settled that much earlier"
    )


def _shortest_half_cycle(t: Sequence[float], beyond: Sequence[float], band: float) -> float | None:
    """The shortest time between two successive band exits the oscillation count
    counts (``bench.metrics._oscillations``' hysteresis), None with fewer than two."""
    side = -1
    exits: list[float] = []
    for ti, e in zip(t, beyond, strict=True):
        if e > band and side < 0:
            side = 1
            exits.append(ti)
        elif e < -band and side > 0:
            side = -1
            exits.append(ti)
    return min((b - a for a, b in pairwise(exits)), default=None)


def _overshoot_unresolved(points: list[tuple[float, float]], y0: float, step: float) -> str | None:
    """Why the overshoot's peak is not located by the samples (a gap next to the highest
    sample where the curve bends, or late stamps around it), None when it is."""
    gap_s, usual_s, bound = _peak_gaps(points, 1.0 if step > 0 else -1.0)
    bound_pp = bound / abs(step) * 100.0
    if (
        usual_s > 0
        and gap_s > MAX_PEAK_GAP_RATIO * usual_s
        and bound_pp > MAX_OVERSHOOT_UNCERTAINTY_PP
    ):
        return (
            f"a gap of {gap_s * 1000:.0f} ms next to the peak sample (the record's usual "
            f"spacing is {usual_s * 1000:.1f} ms) where the curve bends enough to hide "
            f"up to {bound_pp:.1f} percentage points: the peak may lie between samples"
        )
    spread = overshoot_stamp_uncertainty_pct(
        [t for t, _ in points], [y for _, y in points], t0_s=0.0, y0=y0, y_final=y0 + step
    )
    if spread is not None and spread > MAX_OVERSHOOT_UNCERTAINTY_PP:
        return (
            f"samples around the peak were stamped late (a busy host): the overshoot "
            f"could be off by {spread:.1f} percentage points (at most "
            f"{MAX_OVERSHOOT_UNCERTAINTY_PP} trusted)"
        )
    return None


def _hidden_peak(points: list[tuple[float, float]], y0: float, step: float) -> str | None:
    """Why a peak higher than the highest sample may lie in a gap before it (a hole
    over the first lobe leaves a later, lower lobe as the highest sample, with the usual
    spacing around it), None when no gap can hide one. Only the gaps before the highest
    sample, and not the one next to it (``_peak_gaps``' job): the caller asks only for a
    response that ended in the band, a decaying step whose later lobes are lower. The
    curve in a gap rises above
    its higher end by at most ``A g² / 8`` (``A``: the largest curvature of the
    parabolas through three successive samples with the gap among them), the bound
    ``_peak_gaps`` uses next to the peak. A gap counts when it is wider than
    ``MAX_PEAK_GAP_RATIO`` usual spacings and could rise above the highest sample by
    more than ``MAX_OVERSHOOT_UNCERTAINTY_PP`` of the step."""
    if len(points) < 3:
        return None
    direction = 1.0 if step > 0 else -1.0
    curve = [(0.0, 0.0), *((t, (y - y0) * direction) for t, y in points)]
    gaps = [b - a for (a, _), (b, _) in pairwise(curve)]
    usual = statistics.median(gaps[1:])
    k = max(range(len(curve)), key=lambda i: curve[i][1])
    top = curve[k][1]
    margin = MAX_OVERSHOOT_UNCERTAINTY_PP / 100.0 * abs(step)
    for i, gap in enumerate(gaps[: max(0, k - 1)]):
        if usual <= 0 or gap <= MAX_PEAK_GAP_RATIO * usual:
            continue
        curvature = _max_curvature(curve[max(0, i - 1) : i + 3])  # parabolas across gap i
        rise = max(curve[i][1], curve[i + 1][1]) + curvature * gap * gap / 8.0 - top
        if rise > margin:
            return (
                f"a hole of {gap * 1000:.0f} ms in the record ({curve[i][0] * 1000:.0f}.."
                f"{curve[i + 1][0] * 1000:.0f} ms; the usual spacing is {usual * 1000:.1f} ms) "
                f"where the curve bends enough to rise {rise / abs(step) * 100:.1f} percentage "
                "points above the highest sample: the peak may lie in it"
            )
    return None


def _peak_gaps(points: list[tuple[float, float]], direction: float) -> tuple[float, float, float]:
    """(the longer gap next to the sample furthest in the step direction, from the
    command point on; the median gap of the record; how far, in counts, the true peak
    may rise above that sample): zeros with fewer than 3 samples.

    The true peak lies between the highest sample's neighbours and, where the curve
    is a parabola over them, no further from the highest sample than half the gap on
    its side (that neighbour is lower). With the curvature bounded by ``A`` there, the
    peak rises above the sample by at most ``A (gap / 2)² / 2``; ``A`` is the largest
    curvature of the parabolas through three successive samples around the peak (two
    samples either side). A regular schedule with longer gaps (the Z1100 capture
    reads its following error every third sample) then costs the overshoot nothing
    where the curve is flat over them, and a gap over a sharp peak still does."""
    if len(points) < 3:
        return 0.0, 0.0, 0.0
    times = [0.0, *(t for t, _ in points)]
    gaps = [b - a for a, b in pairwise(times)]
    travel = [y * direction for _, y in points]
    k = max(range(len(points)), key=lambda i: travel[i])
    around = [gaps[k], *(gaps[k + 1 : k + 2])]
    curvature = _max_curvature(points[max(0, k - 2) : k + 3])
    gap_s = max(around)
    return gap_s, statistics.median(gaps[1:]), curvature * (gap_s / 2.0) ** 2 / 2.0


def _max_curvature(window: Sequence[tuple[float, float]]) -> float:
    """The largest curvature of the parabolas through three successive points of
    ``window`` (0 with fewer than three)."""
    return max(
        (
            abs(2.0 * ((y2 - y1) / (t2 - t1) - (y1 - y0) / (t1 - t0)) / (t2 - t0))
            for (t0, y0), (t1, y1), (t2, y2) in zip(window, window[1:], window[2:], strict=False)
            if t0 < t1 < t2
        ),
        default=0.0,
    )


def _quality(
    bad: list[dict[str, str]], doubts: list[dict[str, str]], untrusted: dict[str, str]
) -> dict[str, Any]:
    status = "bad" if bad else "doubtful" if doubts else "good"
    return {
        "status": status,
        "reasons": [*bad, *doubts],
        "untrusted": untrusted,
        "sampling_rule": SAMPLING_RULE,
    }


def rejudge(
    run: Mapping[str, Any], rows: Sequence[Sequence[Any]]
) -> tuple[dict[str, Any], dict[str, Any]] | None:
    """(metrics, quality) of a stored run with today's sampling rule applied on top of
    what was stored (its faults and reasons stay as they were: the fault flags a test
    watched are not stored), or None when there is nothing to judge (no metrics, no
    trigger) or it was judged by this rule already. ``rows``: the run's sample rows."""
    metrics = run.get("metrics")
    quality = dict(run.get("quality") or {"status": "good", "reasons": [], "untrusted": {}})
    t0_s, plan = run.get("t0_s"), run.get("plan") or {}
    columns: list[str] = list(run.get("columns") or [])
    if quality.get("sampling_rule") == SAMPLING_RULE or not metrics or t0_s is None:
        return None
    response = plan.get("response")
    if response not in columns:
        return None
    index = columns.index(response)
    points = [
        (float(r[0]) - t0_s, float(r[index]))
        for r in rows
        if r[0] is not None and r[0] >= t0_s and r[index] is not None
    ]
    fe = columns.index("following_error") if "following_error" in columns else None
    series = _Series(
        following_error_t=[float(r[0]) - t0_s for r in rows if fe is not None and r[fe] is not None]
    )
    out = dict(metrics)
    out["time_to_flag_s"] = dict(metrics.get("time_to_flag_s") or {})
    if "time_to_flag_resolution_s" in metrics:
        out["time_to_flag_resolution_s"] = dict(metrics.get("time_to_flag_resolution_s") or {})
    untrusted = dict(quality.get("untrusted") or {})
    y0, y_final = float(plan.get("y0", 0.0)), float(plan.get("y_final", 0.0))
    band = plan.get("band")
    _sampling_trust(out, points, series, y0, y_final - y0, band, untrusted)
    quality["untrusted"] = untrusted
    quality["sampling_rule"] = SAMPLING_RULE
    return out, quality
