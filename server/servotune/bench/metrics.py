"""Step-response metrics of a recorded run (sans-IO, no clocks; scipy for the peak).

A run is the telemetry of one axis during a test: a position step or move, or a
velocity step. The samples are *polled* (serial telemetry at tens of Hz, irregular
spacing of about 10..60 ms), so every time below is quantised to the sample spacing;
crossings of a level are located by linear interpolation between the two samples that
bracket them, the overshoot's peak by a cubic spline through the samples around the
highest one (at their own times, so neither the sampling phase nor an irregular
spacing moves it), flags (booleans) cannot be interpolated and are timed at the first
sample that shows them.

Conventions shared by every metric (``docs/metrics.md`` repeats them with formulas):

* Times are seconds after the command time ``t0_s``. Samples before ``t0_s`` are ignored
  by the response metrics (a flag sample before ``t0_s`` still holds its value into it).
* ``step = y_final - y0``; its sign is the step direction. The directional metrics work
  on ``(y - y0) * sign(step)`` and ``(y - y_final) * sign(step)``, so a negative step
  gives exactly the numbers of the mirrored positive one.
* The command point ``(t0, y0)`` is the first point of the response (the axis cannot
  have moved before the command): the first 10 % crossing and the settling crossing
  can be interpolated from it when the first sample is already past the level.
* Samples whose time or value is not finite (NaN, inf) are skipped; times must be in
  non-decreasing order (``ValueError`` otherwise).

``compute_metrics`` is the entry point; ``predict_first_order`` and
``predict_second_order`` give the analytic step responses the metrics are tested
against (and that an auto-tune assistant can fit).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from itertools import pairwise
from typing import Any, Final

import numpy as np
from scipy.interpolate import CubicSpline

from servotune.schema import RunMetrics

ARRIVAL_FLAGS: Final = frozenset({"inpos", "in_target"})
"""Flags that drop at move start and rise on arrival: timed by ``time_to_flag_s``.
Every other flag (``oc``, ``stall``, ...) is totalled by ``time_in_flag_s``."""

RISE_LOW: Final = 0.1
RISE_HIGH: Final = 0.9
DEFAULT_BAND_FRACTION: Final = 0.02
STEADY_STATE_FRACTION: Final = 0.1
STEADY_STATE_MIN_SAMPLES: Final = 3
_CRITICAL_ZETA_TOLERANCE: Final = 1e-6
PEAK_SPLINE_HALF_WIDTH: Final = 3
"""Samples either side of the highest one that the overshoot's spline goes through
(``overshoot_pct``; docs/metrics.md "The peak" says why three)."""


DEFINITIONS: Final[Mapping[str, str]] = {
    "step": (
        "Commanded step y_final − y0 in units of y; its sign is the step direction "
        "used by the directional metrics."
    ),
    "band": (
        "Settling band ± in units of y: the in-position window passed in, or 2 % of "
        "|step| when none is given (None for a zero step without a window)."
    ),
    "samples": ("Number of samples used: finite time and value, at or after the command time t0."),
    "max_sample_gap_s": (
        "Largest interval between consecutive samples from t0 (counted as the first "
        "point) to the last sample: every time metric is quantised to about this."
    ),
    "rise_time_s": (
        "Time from the first 10 % crossing of the step to the first 90 % crossing "
        "after it, both in the step direction and located by linear interpolation "
        "between the two samples around them, with (t0, y0) as the first point "
        "(None for a zero step or when 90 % is never reached)."
    ),
    "overshoot_pct": (
        "Largest excursion of y beyond y_final in the step direction as a percentage "
        "of |step|, 0 when y never passes y_final (None for a zero step). The peak "
        "is the maximum, between the highest sample's neighbours, of the not-a-knot "
        "cubic spline through that sample and 3 samples either side at their own "
        "times; nearer the record's ends (or with a repeated time among them) the "
        "vertex of the parabola through it and its two neighbours when both are "
        "lower and the vertex lies between them (for two equal highest samples: the "
        "parabola symmetric about their midpoint through the outer neighbour giving "
        "the smaller rise); either raised above the highest sample by no more than "
        "the larger drop to a neighbour (a sampled peak is low by up to |y''| "
        "(gap/2)^2 / 2), else the highest sample (a plateau of three or more)."
    ),
    "peak_time_s": (
        "Time after t0 of the first sample furthest in the step direction (for a "
        "zero step: furthest from y_final)."
    ),
    "peak_value": "Value of y at the sample of peak_time_s.",
    "settling_time_s": (
        "Time after which |y − y_final| ≤ band to the end of the record, linearly "
        "interpolated between the last point outside the band and the next sample "
        "(0 when no point from (t0, y0) on is outside; None when the last sample is "
        "outside the band or there is no band)."
    ),
    "steady_state_error": (
        "Mean of (y_final − y) over the samples in the last 10 % of the time from t0 "
        "to the last sample, at least the last 3 samples, signed and in units of y "
        "(None with fewer than 3 samples)."
    ),
    "oscillations": (
        "Number of sign changes of y − y_final with a hysteresis of ± band, starting "
        "from the side the response approaches from, i.e. the overshoot and "
        "undershoot half-cycles that leave the band (None for a zero step)."
    ),
    "peak_following_error": (
        "Largest |following error| over the samples from t0 on, missing values "
        "skipped (None without data)."
    ),
    "rms_following_error": (
        "Root mean square of the following error over the same samples, each sample "
        "weighted equally (None without data)."
    ),
    "time_to_flag_s": (
        "For the arrival flags inpos and in_target: time after t0 at which the flag "
        "rose, taken midway between the last read that showed it clear (from t0 on) "
        "and the first read that showed it set after that, None if it never drops and "
        "rises again. Flags are polled: the reads are the times the flags were read, "
        "not the times of the samples that carry them."
    ),
    "time_in_flag_s": (
        "For every other flag (oc, stall, ...): total time it was set between t0 and "
        "its last read, each change taken midway between the read before it and the "
        "read that showed it (a spell shorter than the flag's poll period can fall "
        "between two reads and is not seen)."
    ),
    "time_to_flag_resolution_s": (
        "± of time_to_flag_s: half the time between the two reads the rise lies "
        "between (half the flag's poll period there)."
    ),
    "time_in_flag_resolution_s": (
        "± of time_in_flag_s: the sum of half the time between the two reads around "
        "each change counted."
    ),
}
"""What each field of ``RunMetrics`` is, in words (``GET /api/axes/{id}/bench``
serves it; docs/metrics.md repeats it with formulas)."""


def compute_metrics(
    t_s: Sequence[float],
    y: Sequence[float],
    *,
    t0_s: float,
    y0: float,
    y_final: float,
    band: float | None = None,
    following_error: Sequence[float | None] | None = None,
    flags: Mapping[str, Sequence[bool]] | None = None,
    flags_t_s: Sequence[float | None] | None = None,
) -> RunMetrics:
    """Metrics of one run; see ``DEFINITIONS`` for what each one is.

    ``band`` is the settling band (± in units of y, e.g. the device's in-position
    window); without it 2 % of ``|y_final - y0|``. ``following_error``, each
    ``flags`` series and ``flags_t_s`` are aligned with ``t_s`` (same length).
    ``flags_t_s`` is when each sample's flags were read (same clock as ``t_s``; a
    driver that polls its flags less often than the position carries the last read
    on every sample); None, or a non-finite entry, means "with the sample itself".

    Raises ``ValueError`` for times out of order, series of different lengths, a
    non-finite ``t0_s``/``y0``/``y_final`` or a negative or non-finite ``band``. Data
    edge cases (no samples, NaN samples, a zero step, a record that ends before the
    step completes) give None metrics instead.
    """
    n = len(t_s)
    if len(y) != n:
        raise ValueError(f"t_s and y differ in length: {n} != {len(y)}")
    if following_error is not None and len(following_error) != n:
        raise ValueError(f"following_error and t_s differ in length: {len(following_error)} != {n}")
    for name, series in (flags or {}).items():
        if len(series) != n:
            raise ValueError(f"flag series {name!r} and t_s differ in length: {len(series)} != {n}")
    if flags_t_s is not None and len(flags_t_s) != n:
        raise ValueError(f"flags_t_s and t_s differ in length: {len(flags_t_s)} != {n}")
    for name, value in (("t0_s", t0_s), ("y0", y0), ("y_final", y_final)):
        if not math.isfinite(value):
            raise ValueError(f"{name} must be finite, got {value!r}")
    if band is not None and not (math.isfinite(band) and band >= 0):
        raise ValueError(f"band must be finite and >= 0, got {band!r}")

    rel = _relative_times(t_s, t0_s)
    step = y_final - y0
    if band is None and step != 0:
        band = DEFAULT_BAND_FRACTION * abs(step)

    ts: list[float] = []
    ys: list[float] = []
    for tr, v in zip(rel, y, strict=True):
        if tr is not None and tr >= 0 and math.isfinite(v):
            ts.append(tr)
            ys.append(v)
    # The response as a curve starts at the command point (t0, y0).
    if ts and ts[0] == 0:
        curve_t, curve_y = ts, ys
    else:
        curve_t, curve_y = [0.0, *ts], [y0, *ys]

    rise: float | None = None
    overshoot: float | None = None
    peak_t: float | None = None
    peak_v: float | None = None
    settling: float | None = None
    sse: float | None = None
    max_gap: float | None = None
    oscillations: int | None = None
    if ts:
        max_gap = max(b - a for a, b in pairwise(curve_t)) if len(curve_t) > 1 else 0.0
        errors = [v - y_final for v in curve_y]
        if band is not None:
            settling = _settling_time(curve_t, errors, band)
        sse = _steady_state_error(ts, ys, y_final)
        if step != 0:
            direction = 1.0 if step > 0 else -1.0
            # Distances travelled in the step direction, compared with fractions of
            # |step| (no division by the step: a tiny step cannot overflow).
            rise = _rise_time(curve_t, [(v - y0) * direction for v in curve_y], abs(step))
            beyond = [(v - y_final) * direction for v in ys]
            overshoot = max(0.0, _refined_peak(ts, beyond)) / abs(step) * 100.0
            if not math.isfinite(overshoot):  # a step too small to be a reference
                overshoot = None
            i_peak = _argmax([(v - y0) * direction for v in ys])
            oscillations = None if band is None else _oscillations(beyond, band)
        else:
            i_peak = _argmax([abs(v - y_final) for v in ys])
        peak_t, peak_v = ts[i_peak], ys[i_peak]

    peak_fe, rms_fe = _following_error_stats(rel, following_error)
    time_to: dict[str, float | None] = {}
    time_in: dict[str, float] = {}
    to_resolution: dict[str, float | None] = {}
    in_resolution: dict[str, float] = {}
    for name, series in (flags or {}).items():
        reads = flag_reads(rel, series, flags_t_s, t0_s)
        if name in ARRIVAL_FLAGS:
            time_to[name], to_resolution[name] = _time_to_flag(reads)
        else:
            time_in[name], in_resolution[name] = _time_in_flag(reads)

    # Built without validation: the inputs were checked above, every value is a float,
    # an int or None by construction, and only data near the float range's ends (1e308)
    # can overflow to inf, as before the model existed; an import, which reads JSON
    # from outside, validates it (strict, finite).
    return RunMetrics.model_construct(
        step=step,
        band=band,
        samples=len(ts),
        max_sample_gap_s=max_gap,
        rise_time_s=rise,
        overshoot_pct=overshoot,
        peak_time_s=peak_t,
        peak_value=peak_v,
        settling_time_s=settling,
        steady_state_error=sse,
        oscillations=oscillations,
        peak_following_error=peak_fe,
        rms_following_error=rms_fe,
        time_to_flag_s=time_to,
        time_in_flag_s=time_in,
        time_to_flag_resolution_s=to_resolution,
        time_in_flag_resolution_s=in_resolution,
    )


def overshoot_stamp_uncertainty_pct(
    t_s: Sequence[float], y: Sequence[float], *, t0_s: float, y0: float, y_final: float
) -> float | None:
    """How far ``overshoot_pct`` could move, in percentage points, for the lateness the
    record shows in the stamps of the samples that locate the peak (None when there is
    no refined peak to judge: no step, no overshoot, too few samples).

    A stamp is never early (it is taken when the host has read the reply, at or after
    the device latched it) and nothing polls faster than the record's usual spacing,
    so a sample followed by a *shorter* gap than the median is late by at least the
    shortfall (its successor on time). The peak is recomputed with each such stamp
    moved back by its shortfall, one at a time, and the changes are summed (a bound,
    linear in small moves). On a busy host the peak's neighbours lie on steep flanks:
    3 ms on one of them moved a 22 % overshoot by 1.3-1.8 pp (docs/metrics.md)."""
    step = y_final - y0
    if step == 0 or len(t_s) != len(y):
        return None
    direction = 1.0 if step > 0 else -1.0
    pairs = [
        (t - t0_s, (v - y_final) * direction)
        for t, v in zip(t_s, y, strict=True)
        if math.isfinite(t) and math.isfinite(v) and t >= t0_s
    ]
    if len(pairs) < 3:
        return None
    ts = [t for t, _ in pairs]
    beyond = [v for _, v in pairs]
    peak = _refined_peak(ts, beyond)
    if peak <= 0:
        return None
    gaps = [b - a for a, b in pairwise(ts)]
    usual = float(np.median(gaps))
    i = _argmax(beyond)
    h = PEAK_SPLINE_HALF_WIDTH
    total = 0.0
    for k in range(max(0, i - h), min(len(ts) - 1, i + h + 1)):
        late = usual - gaps[k]
        if late <= 0:
            continue
        moved = list(ts)
        moved[k] = max(ts[k] - late, ts[k - 1] if k else -math.inf)
        total += abs(_refined_peak(moved, beyond) - peak)
    return total / abs(step) * 100.0


def unmeasured(run: Mapping[str, Any] | None, metric: str = "settling_time_s") -> str | None:
    """Why the bench could not measure ``metric`` of ``run`` (its quality's
    ``untrusted`` reason, e.g. samples too sparse to locate it), None if it could."""
    if not run:
        return None
    untrusted = (run.get("quality") or {}).get("untrusted") or {}
    reason = untrusted.get(metric)
    return str(reason) if reason else None


def predict_first_order(
    tau_s: float, step: float, t_s: Sequence[float], *, y0: float = 0.0
) -> list[float]:
    """``y0 + step * (1 - exp(-t / tau))`` for t >= 0, ``y0`` before (t relative to the step)."""
    if not (math.isfinite(tau_s) and tau_s > 0):
        raise ValueError(f"tau_s must be finite and > 0, got {tau_s!r}")
    return [y0 + step * -math.expm1(-t / tau_s) if t > 0 else y0 for t in t_s]


def predict_second_order(
    wn_rad_s: float, zeta: float, step: float, t_s: Sequence[float], *, y0: float = 0.0
) -> list[float]:
    """Step response of ``wn² / (s² + 2 zeta wn s + wn²)`` (unity DC gain), scaled by ``step``.

    Underdamped (zeta < 1): ``1 - exp(-zeta wn t) / sqrt(1 - zeta²) * sin(wd t + acos zeta)``
    with ``wd = wn sqrt(1 - zeta²)``; critically damped: ``1 - (1 + wn t) exp(-wn t)``;
    overdamped: ``1 + (s2 exp(s1 t) - s1 exp(s2 t)) / (s1 - s2)`` with the real poles
    ``s1,2 = -wn (zeta -+ sqrt(zeta² - 1))``. ``y0`` before t = 0 (t relative to the step).
    """
    if not (math.isfinite(wn_rad_s) and wn_rad_s > 0):
        raise ValueError(f"wn_rad_s must be finite and > 0, got {wn_rad_s!r}")
    if not (math.isfinite(zeta) and zeta >= 0):
        raise ValueError(f"zeta must be finite and >= 0, got {zeta!r}")

    if abs(zeta - 1.0) < _CRITICAL_ZETA_TOLERANCE:

        def unit(t: float) -> float:
            return 1.0 - (1.0 + wn_rad_s * t) * math.exp(-wn_rad_s * t)

    elif zeta < 1.0:
        root = math.sqrt(1.0 - zeta * zeta)
        wd = wn_rad_s * root
        phase = math.acos(zeta)

        def unit(t: float) -> float:
            return 1.0 - math.exp(-zeta * wn_rad_s * t) / root * math.sin(wd * t + phase)

    else:
        root = math.sqrt(zeta * zeta - 1.0)
        s1 = -wn_rad_s * (zeta - root)
        s2 = -wn_rad_s * (zeta + root)

        def unit(t: float) -> float:
            return 1.0 + (s2 * math.exp(s1 * t) - s1 * math.exp(s2 * t)) / (s1 - s2)

    return [y0 + step * unit(t) if t > 0 else y0 for t in t_s]


def _relative_times(t_s: Sequence[float], t0_s: float) -> list[float | None]:
    """``t - t0`` per sample, None where t is not finite; ValueError if out of order."""
    out: list[float | None] = []
    prev_i = -1
    prev = -math.inf
    for i, t in enumerate(t_s):
        if not math.isfinite(t):
            out.append(None)
            continue
        if t < prev:
            raise ValueError(
                f"t_s must be in non-decreasing order: t_s[{i}] = {t!r} "
                f"comes after t_s[{prev_i}] = {prev!r}"
            )
        prev_i, prev = i, t
        out.append(t - t0_s)
    return out


def _crossing(
    t: list[float], values: list[float], level: float, start: int
) -> tuple[float, int] | None:
    """First time from index ``start`` on where ``values`` reach ``level`` from below.

    Linear interpolation between the sample before and the first sample at or above
    ``level``; returns (time, index of that sample), None if never reached.
    """
    for i in range(start, len(values)):
        if values[i] >= level:
            if i == 0:
                return t[0], 0
            ta, ua, tb, ub = t[i - 1], values[i - 1], t[i], values[i]
            # ua < level <= ub: the first sample at or above level is i, and the 90 %
            # search starts at the 10 % sample, whose predecessor is below 10 %.
            return ta + (level - ua) / (ub - ua) * (tb - ta), i
    return None


def rise_crossings(
    t: Sequence[float], travel: Sequence[float], size: float
) -> tuple[float, float] | None:
    """(t10, t90): the first crossings of 10 % and then 90 % of ``size`` by ``travel``
    (the distance moved in the step direction; the command point first), as
    ``rise_time_s`` locates them; None when 90 % is never reached."""
    t_list, values = list(t), list(travel)
    low = _crossing(t_list, values, RISE_LOW * size, 0)
    if low is None:
        return None
    high = _crossing(t_list, values, RISE_HIGH * size, low[1])
    if high is None:
        return None
    return low[0], high[0]


def _rise_time(t: list[float], travel: list[float], size: float) -> float | None:
    crossings = rise_crossings(t, travel, size)
    return None if crossings is None else crossings[1] - crossings[0]


def _settling_time(t: list[float], errors: list[float], band: float) -> float | None:
    last_out = next((i for i in range(len(errors) - 1, -1, -1) if abs(errors[i]) > band), None)
    if last_out is None:
        return t[0]
    if last_out == len(errors) - 1:
        return None
    ea, eb = errors[last_out], errors[last_out + 1]
    edge = band if ea > 0 else -band
    ta, tb = t[last_out], t[last_out + 1]
    return ta + (ea - edge) / (ea - eb) * (tb - ta)


def _steady_state_error(t: list[float], y: list[float], y_final: float) -> float | None:
    n = len(t)
    if n < STEADY_STATE_MIN_SAMPLES:
        return None
    t_from = t[-1] * (1.0 - STEADY_STATE_FRACTION)  # t relative to t0
    start = next(i for i, ti in enumerate(t) if ti >= t_from)
    start = min(start, n - STEADY_STATE_MIN_SAMPLES)
    window = y[start:]
    return sum(y_final - v for v in window) / len(window)


def _oscillations(beyond: list[float], band: float) -> int:
    """Sign changes of ``beyond`` (y - y_final in the step direction) with hysteresis ±band.

    Starts on the approach side (below), so the first overshoot beyond the band counts 1.
    """
    side = -1
    count = 0
    for e in beyond:
        if e > band and side < 0:
            side, count = 1, count + 1
        elif e < -band and side > 0:
            side, count = -1, count + 1
    return count


def _refined_peak(t: list[float], values: list[float]) -> float:
    """The largest of ``values``, refined between its sampled neighbours (see
    ``overshoot_pct``): the maximum of the not-a-knot cubic spline through it and
    ``PEAK_SPLINE_HALF_WIDTH`` samples either side, or, nearer the record's ends, the
    vertex of the parabola through it and its two neighbours; the sample itself where
    neither gives a concave peak between the neighbours."""
    i = _argmax(values)
    best = values[i]
    if not 0 < i < len(values) - 1:
        return best
    if values[i + 1] == best and i + 2 < len(values) and values[i + 2] == best:
        return best  # a plateau of three or more: nothing says where in it the peak is
    h = PEAK_SPLINE_HALF_WIDTH
    if h <= i < len(values) - h:
        refined = _spline_peak(t[i - h : i + h + 1], values[i - h : i + h + 1])
        if refined is not None:
            return refined
    if values[i + 1] == best and i + 2 < len(values):
        return _refined_plateau(t[i - 1 : i + 3], values[i - 1 : i + 3])
    return _parabola_peak(t[i - 1 : i + 2], values[i - 1 : i + 2])


def _spline_peak(t: list[float], values: list[float]) -> float | None:
    """The maximum, between the middle sample's neighbours, of the not-a-knot cubic
    spline through the samples (the middle one the highest, its successor possibly
    tied with it), capped like the parabola's vertex; None when the times are not
    strictly increasing (a repeated time stamp: the parabola decides) or the
    differences to the middle sample overflow."""
    h = len(values) // 2
    best = values[h]
    # Relative to the peak sample (no cancellation in the times of a long record) and
    # scaled to [-1, 1]: the spline's arithmetic cannot overflow for any finite data.
    dx = [v - t[h] for v in t]
    dy = [v - best for v in values]
    if not all(math.isfinite(d) for d in (*dx, *dy)):
        return None
    if not all(a < b for a, b in pairwise(dx)):
        return None
    x_scale = max(-dx[0], dx[-1])
    y_scale = max(-d for d in dy)  # > 0: the sample before the peak is lower
    x = np.asarray(dx) / x_scale
    y = np.asarray(dy) / y_scale
    if not np.all(np.diff(x) > 0):  # a spacing lost to the scaling
        return None
    spline = CubicSpline(x, y, bc_type="not-a-knot")
    # y[h - 1] < 0 = y[h] >= y[h + 1]: the spline has a maximum strictly between
    # the neighbours, where its derivative vanishes.
    roots = spline.derivative().roots(extrapolate=False)
    inside = roots[(roots > x[h - 1]) & (roots < x[h + 1])]
    rise = float(np.max(spline(inside))) if inside.size else 0.0
    return best + _capped_rise(rise * y_scale, -dy[h - 1], -dy[h + 1])


def _parabola_peak(t: list[float], values: list[float]) -> float:
    """The vertex of the parabola through three samples, the middle one the highest
    (a record edge: too few samples for the spline), or that sample where the
    parabola is not concave with its vertex between the outer two."""
    best = values[1]
    ta, tb = t[0] - t[1], t[2] - t[1]  # relative to the peak sample: no cancellation
    ya, yb = values[0] - best, values[2] - best
    if ta >= 0 or tb <= 0 or not (ya < 0 and yb < 0):
        return best  # a repeated time or a tie at the record's end: nothing to refine
    # y = a x^2 + b x through (ta, ya), (0, 0), (tb, yb)
    a = (ya / ta - yb / tb) / (ta - tb)
    b = ya / ta - a * ta
    if not a < 0:
        return best
    x = -b / (2 * a)
    if not ta < x < tb:
        return best
    return best + _capped_rise(-b * b / (4 * a), -ya, -yb)


def _capped_rise(rise: float, drop_before: float, drop_after: float) -> float:
    """The refinement's rise above the peak sample, at least 0 and never more than the
    larger drop to a neighbour: sparse or noisy samples must not make a peak up.
    (Not the smaller drop: when the true peak lies nearly midway to a neighbour, a
    true parabola rises above the peak sample by more than the drop to that
    neighbour, up to (1 + sqrt 2)^-2 of the gap's curvature, and that cap cut 8-12
    counts off a 435-count peak in one of five identical steps.)"""
    return min(max(0.0, rise), max(drop_before, drop_after))


def _refined_plateau(t: list[float], values: list[float]) -> float:
    """Two equal highest samples between two lower ones (integer counts tie where the
    true peak falls between two samples): the vertex of a parabola symmetric about the
    midpoint of the tied samples, through them and through an outer neighbour — the
    one that gives the smaller rise (conservative: a coarse record must not make a
    peak up)."""
    best = values[1]
    if not (values[0] < best and values[3] < best and t[0] < t[1] < t[2] < t[3]):
        return best
    mid, half = (t[1] + t[2]) / 2, (t[2] - t[1]) / 2
    # y = best + r - k (x - mid)^2 through (mid +- half, best) gives r = k half^2; the
    # outer neighbour at distance D with drop d gives k = d / (D^2 - half^2).
    rises = [
        (best - v) * half**2 / ((x - mid) ** 2 - half**2)
        for x, v in ((t[0], values[0]), (t[3], values[3]))
    ]
    return best + min(rises)


def _argmax(values: list[float]) -> int:
    best = 0
    for i, v in enumerate(values):
        if v > values[best]:
            best = i
    return best


def _following_error_stats(
    rel: list[float | None], following_error: Sequence[float | None] | None
) -> tuple[float | None, float | None]:
    if following_error is None:
        return None, None
    values = [
        e
        for tr, e in zip(rel, following_error, strict=True)
        if tr is not None and tr >= 0 and e is not None and math.isfinite(e)
    ]
    if not values:
        return None, None
    peak = max(abs(e) for e in values)
    if peak == 0:
        return 0.0, 0.0
    # scaled by the peak so that squaring cannot overflow
    rms = peak * math.sqrt(sum((e / peak) ** 2 for e in values) / len(values))
    return peak, rms


def flag_reads(
    rel: Sequence[float | None],
    series: Sequence[bool],
    flags_t_s: Sequence[float | None] | None,
    t0_s: float,
) -> list[tuple[float, bool]]:
    """The reads of one flag, ``(time after t0, value)`` in order: one per distinct read
    time (samples that carry the same read are one read), from each sample's
    ``flags_t_s`` or, without it, the sample's own time ``rel``. Samples without a
    finite time are skipped; a read stamped after its sample is taken at the sample."""
    reads: list[tuple[float, bool]] = []
    for i, (tr, value) in enumerate(zip(rel, series, strict=True)):
        if tr is None:
            continue
        read = flags_t_s[i] if flags_t_s is not None else None
        at = tr if read is None or not math.isfinite(read) else min(read - t0_s, tr)
        if reads and at <= reads[-1][0]:
            continue  # the same read again (or a stamp out of order: the first counts)
        reads.append((at, bool(value)))
    return reads


def _time_to_flag(reads: list[tuple[float, bool]]) -> tuple[float | None, float | None]:
    """(time of the rise, ± half the interval between the reads around it)."""
    last_clear: float | None = None
    for at, value in reads:
        if at < 0:
            continue
        if not value:
            last_clear = at
        elif last_clear is not None:
            return (last_clear + at) / 2, (at - last_clear) / 2
    return None, None


def _time_in_flag(reads: list[tuple[float, bool]]) -> tuple[float, float]:
    """(time set between t0 and the last read, ± the sum of half the interval around
    each change counted)."""
    if not reads:
        return 0.0, 0.0
    end = reads[-1][0]
    total = resolution = 0.0
    since: float | None = 0.0 if reads[0][1] else None
    for (ta, a), (tb, b) in pairwise(reads):
        if a == b:
            continue
        edge = (ta + tb) / 2
        if tb > 0:  # a change before t0 is no part of the time after it
            resolution += (tb - max(ta, 0.0)) / 2
        if b:
            since = edge
        elif since is not None:
            total += max(0.0, min(edge, end) - max(since, 0.0))
            since = None
    if since is not None:
        total += max(0.0, end - max(since, 0.0))
    return total, resolution
