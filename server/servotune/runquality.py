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
  measurements, e.g. of a limit cycle) and loses the steady-state error. Sampling nulls
  a metric the samples are too sparse for: the rise time needs ``MIN_RISE_SAMPLES``
  samples between 10 % and 90 % of the step; a time (settling, peak, time to a flag)
  is null when the gap between the samples that locate it is longer than the time
  itself — the value is then mostly sampling, not response. The overshoot is null
  when the lateness the record shows in the stamps around its peak could move it by
  more than ``MAX_OVERSHOOT_UNCERTAINTY_PP`` (``metrics.overshoot_stamp_uncertainty_pct``:
  a busy host reads a reply late, and the peak's neighbours lie on steep flanks), and
  when a sample next to the highest one is more than ``MAX_PEAK_GAP_RATIO`` times the
  record's usual spacing away (the host missed polls there: the peak may lie between
  samples, where no refinement can see it).

Facts that stay true whatever happened (step, band, samples, max gap, following error,
time in flags) are never nulled.
"""

from __future__ import annotations

import statistics
from collections.abc import Mapping, Sequence
from itertools import pairwise
from typing import Any, Final

from .metrics import overshoot_stamp_uncertainty_pct

MIN_SAMPLES: Final = 10
MIN_RISE_SAMPLES: Final = 10
MOVED_FRACTION: Final = 0.1  # less travel than this fraction of the step: did not move
PWM_MOVED_COUNTS: Final = 2.0
MAX_OVERSHOOT_UNCERTAINTY_PP: Final = 0.5
"""Half of issue 9's repeatability bound (1 pp between identical runs): two runs each
within it of the truth agree within the bound."""
MAX_PEAK_GAP_RATIO: Final = 1.9
"""Measured on 50 steps of the demo SLAP2 (22 % overshoot, 6 ms spacing) at load 10:
every overshoot off by more than 0.5 pp from the median had a gap next to its highest
sample of 1.94..5.1 times the median spacing (peak low by 0.7..7 pp); with gaps up to
1.9 (the capture's interleaved ``rss`` makes 1.6..1.8) all were within 0.44 pp."""
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
) -> tuple[dict[str, Any] | None, dict[str, Any]]:
    """(metrics with untrusted values set to None, quality) of one finished run.

    ``rows`` are the stored sample rows ``[t_s, value per column..., [flags 0/1]]``."""
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
    if not distorting:
        _sampling_trust(out, points, after, flag_names, t0_s, y0, step, band, untrusted)
    return out, _quality(bad, doubts, untrusted)


def _sampling_trust(
    out: dict[str, Any],
    points: list[tuple[float, float]],
    after: Sequence[Sequence[Any]],
    flag_names: Sequence[str],
    t0_s: float,
    y0: float,
    step: float,
    band: float | None,
    untrusted: dict[str, str],
) -> None:
    """Null the metrics the sampling cannot support (see the module doc)."""
    curve = points if points and points[0][0] == 0 else [(0.0, y0), *points]
    rise = out.get("rise_time_s")
    if rise is not None and step != 0:
        lo, hi = 0.1 * abs(step), 0.9 * abs(step)
        direction = 1.0 if step > 0 else -1.0
        n = sum(1 for _, y in points if lo <= (y - y0) * direction <= hi)
        if n < MIN_RISE_SAMPLES:
            untrusted["rise_time_s"] = (
                f"only {n} samples between 10 % and 90 % of the step (needs "
                f"{MIN_RISE_SAMPLES}): the rise is faster than the telemetry resolves"
            )
            out["rise_time_s"] = None
    overshoot = out.get("overshoot_pct")
    if overshoot is not None and overshoot > 0 and step != 0:
        gap_s, usual_s, drop = _peak_gaps(points, 1.0 if step > 0 else -1.0)
        drop_pp = drop / abs(step) * 100.0
        # The refined peak rises above the highest sample by at most the larger drop to
        # a neighbour: a gap matters only where the curve bends that much across it.
        if (
            usual_s > 0
            and gap_s > MAX_PEAK_GAP_RATIO * usual_s
            and drop_pp > MAX_OVERSHOOT_UNCERTAINTY_PP
        ):
            untrusted["overshoot_pct"] = (
                f"a gap of {gap_s * 1000:.0f} ms next to the peak sample (the record's usual "
                f"spacing is {usual_s * 1000:.1f} ms): the peak may lie between samples"
            )
            out["overshoot_pct"] = None
        elif (
            spread := overshoot_stamp_uncertainty_pct(
                [t for t, _ in points], [y for _, y in points], t0_s=0.0, y0=y0, y_final=y0 + step
            )
        ) is not None and spread > MAX_OVERSHOOT_UNCERTAINTY_PP:
            untrusted["overshoot_pct"] = (
                f"samples around the peak were stamped late (a busy host): the overshoot "
                f"could be off by {spread:.1f} percentage points (at most "
                f"{MAX_OVERSHOOT_UNCERTAINTY_PP} trusted)"
            )
            out["overshoot_pct"] = None
    peak_t = out.get("peak_time_s")
    if peak_t is not None:
        k = next((i for i, (t, _) in enumerate(curve) if t == peak_t), None)
        if k is not None:
            gaps = [curve[k][0] - curve[k - 1][0] if k > 0 else 0.0]
            if k + 1 < len(curve):
                gaps.append(curve[k + 1][0] - curve[k][0])
            if max(gaps) > peak_t:
                untrusted["peak_time_s"] = (
                    f"a gap of {max(gaps) * 1000:.0f} ms between samples around the peak is "
                    f"longer than the peak time ({peak_t * 1000:.0f} ms)"
                )
                out["peak_time_s"] = None
    settle = out.get("settling_time_s")
    if settle is not None and settle > 0 and band is not None:
        gap = _bracketing_gap(curve, settle)
        if gap > settle:
            untrusted["settling_time_s"] = (
                f"the samples that locate the settling are {gap * 1000:.0f} ms apart, more "
                f"than the settling time ({settle * 1000:.0f} ms)"
            )
            out["settling_time_s"] = None
    times = out["time_to_flag_s"]
    for name, value in list(times.items()):
        if value is None or name not in flag_names:
            continue
        i = flag_names.index(name)
        rel = [r[0] - t0_s for r in after]
        k = next((j for j, t in enumerate(rel) if t == value and after[j][-1][i]), None)
        gap = rel[k] - rel[k - 1] if k else value
        if gap > value:
            untrusted[f"time_to_flag_s.{name}"] = (
                f"the flag's sample came {gap * 1000:.0f} ms after the one before it, more "
                f"than the time to it ({value * 1000:.0f} ms)"
            )
            times[name] = None


def _peak_gaps(points: list[tuple[float, float]], direction: float) -> tuple[float, float, float]:
    """(the longer gap next to the sample furthest in the step direction, from the
    command point on; the median gap of the record; the larger drop, in the step
    direction, from that sample to a neighbour): zeros with fewer than 3 samples."""
    if len(points) < 3:
        return 0.0, 0.0, 0.0
    times = [0.0, *(t for t, _ in points)]
    gaps = [b - a for a, b in pairwise(times)]
    travel = [y * direction for _, y in points]
    k = max(range(len(points)), key=lambda i: travel[i])
    around = [gaps[k], *(gaps[k + 1 : k + 2])]
    drops = [travel[k] - travel[j] for j in (k - 1, k + 1) if 0 <= j < len(points)]
    return max(around), statistics.median(gaps[1:]), max(drops)


def _bracketing_gap(curve: list[tuple[float, float]], t: float) -> float:
    for (ta, _), (tb, _) in pairwise(curve):
        if ta <= t <= tb:
            return tb - ta
    return 0.0


def _quality(
    bad: list[dict[str, str]], doubts: list[dict[str, str]], untrusted: dict[str, str]
) -> dict[str, Any]:
    status = "bad" if bad else "doubtful" if doubts else "good"
    return {"status": status, "reasons": [*bad, *doubts], "untrusted": untrusted}
