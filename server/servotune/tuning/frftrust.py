"""What can bias a measured frequency response, and whether a tone can be trusted.

A bench run's response (``tuning.frfrun``) rests on three things besides the fit's
noise: the loop's input rebuilt from the targets sent, the host's time stamps of the
samples and of the targets, and samples dense enough. Each can be wrong without the
fit noticing (a deterministic error repeats every period, so neither the residual nor
the spread over periods shows it). This module turns each into a bound on the
response at every tone, so that a tone is shown trusted only when all of them are
small:

* **Host stalls (the latch-time uncertainty).** The driver stamps every exchange with
  an upper bound of when the device latched it (its echo and reply came back by
  then) and records the span down to a lower bound (the CR was written then): a
  quiet host spans well under a millisecond; a host that ran the exchange's receive
  callback late spans the stall. A *sample* whose span exceeds ``STALL_SPAN_S`` is
  left out (one fewer sample costs nothing); a *target* cannot be left out (it moved
  the axis): the response is fitted again with that target at the start of its span,
  and the change, summed over such targets, is a bound of their effect
  (``command_stall_bias``). Runs recorded before the spans were (and imported ones
  without them) get spans from the gaps in the stamps: a stall is also a gap
  (``spans_from_gaps``).
* **The input check.** The capture reconstructs the setpoint at every sample on its
  own (the same profile law, or ``rp + pe`` read from the device when its checks
  failed). Where it differs from the rebuilt input by more than the tick phase
  explains (``CHECK_TOLERANCE_COUNTS`` plus the input's motion in one tick either
  way), the excess is an error of the input the fit was given; its content at a tone
  over the input's is a bound of the response's error there (``input_check``).
* **Timing.** The tick phase is unknown (half a tick) and the stamps that are kept are
  late by up to their spans: a phase error of ``2 pi f dt`` (``timing_s``).
* **Noise and gaps.** The fit's standard error, or the spread over periods when larger
  (``tuning.frfrun``); gaps in the samples widen both.

The coherence is the magnitude-squared coherence of input and output over the
analysed periods, one segment per period (``period_coherence``): the H1 estimator's
coherence with a rectangular window and the tones on its bins.

A tone is **trusted** when its magnitude is known within ``MAX_TRUSTED_DB`` and its
phase within ``MAX_TRUSTED_DEG`` (``TRUST_COVERAGE`` standard errors plus every bias
bound), its coherence is at least ``MIN_COHERENCE`` and it lies below the capture's
Nyquist frequency.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from servotune.tuning.frf import ComplexArray, FloatArray, tone_fit

# A latch estimate spanning more than this was stalled (well above a quiet host's spans,
# docs/frequency-response.md).
STALL_SPAN_S = 0.002
# Without recorded spans: a gap longer than the 90th percentile of the gaps by more
# than this is a stall of the exchange that ends it.
GAP_STALL_S = 0.004
# Targets whose stall is bounded by a refit each; more: not bounded (run again).
MAX_STALL_REFITS = 60
# The capture's own check of its reconstruction allows 2 counts plus the profile's
# motion in one tick either way (devices/slap2/capture.py); so does this one.
CHECK_TOLERANCE_COUNTS = 2.0
TRUST_COVERAGE = 2.0
MAX_TRUSTED_DB = 0.5
MAX_TRUSTED_DEG = 5.0
MIN_COHERENCE = 0.9


def nan_array(values: Sequence[float | None] | None, size: int) -> FloatArray:
    if values is None:
        return np.full(size, np.nan)
    return np.asarray([math.nan if v is None else float(v) for v in values], dtype=np.float64)


def command_spans(sent: Sequence[Sequence[float | None]]) -> FloatArray:
    """The recorded latch span of each sent row (``[acknowledged, target, latched,
    span]``), NaN where it was not recorded."""
    return np.asarray(
        [float(r[3]) if len(r) > 3 and r[3] is not None else math.nan for r in sent],
        dtype=np.float64,
    )


def spans_from_gaps(sample_t: FloatArray, command_t: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Spans inferred from the stamps alone (a run without recorded spans): each
    exchange cannot have latched before the one before it on the line was stamped,
    so the excess of its gap over the usual one (the 90th percentile: other reads
    the capture interleaves make gaps longer than the wire time) bounds a stall.
    Returns (sample spans, command spans)."""
    stamps = np.concatenate([sample_t, command_t])
    if stamps.size < 3:
        return np.zeros(sample_t.size), np.zeros(command_t.size)
    order = np.argsort(stamps, kind="stable")
    gaps = np.diff(stamps[order], prepend=stamps[order][0])
    usual = float(np.quantile(gaps[1:], 0.9))
    excess = np.maximum(0.0, gaps - usual - GAP_STALL_S)
    spans = np.empty(stamps.size)
    spans[order] = excess
    return spans[: sample_t.size], spans[sample_t.size :]


def timing_s(sample_spans: FloatArray, command_spans_s: FloatArray, tick_s: float) -> float:
    """The timing uncertainty of the kept stamps: half a controller tick ``tick_s`` and
    half the spread of their spans (stamps late by a common amount cancel in ``Y / U``;
    what differs between them does not).

    Half a tick: the phase of the controller's tick against the host's stamps is
    unknown, half a tick either way. (The SLAP2 simulator applies a target one tick
    sooner than the firmware law the rebuild follows: measured on it, T leads by up to
    a tick more, docs/frequency-response.md; the tests compare with that.)"""
    spans = np.concatenate([sample_spans, command_spans_s])
    kept = spans[spans <= STALL_SPAN_S]
    kept = kept[np.isfinite(kept)]
    spread = float(np.quantile(kept, 0.9)) if kept.size else 0.0
    return tick_s / 2 + 0.5 * spread


def command_stall_bias(
    latched_s: FloatArray,
    spans: FloatArray,
    respond: Callable[[int, float], tuple[ComplexArray, FloatArray]],
    response: ComplexArray,
    t_k: FloatArray,
    tick_t: FloatArray,
    u_ticks: FloatArray,
) -> tuple[FloatArray, int, npt.NDArray[np.bool_]]:
    """The bound of what stalled targets (span > ``STALL_SPAN_S``) can have done to the
    response, relative to it: for each, the response fitted again with that target
    latched at the start of its span (``respond(index, latched_s)`` gives that
    response and the input on the ticks); their sum, or ``TRUST_COVERAGE`` times their
    root sum of squares when that is smaller (each stall falls at a random phase of
    the excitation, so their effects add as random vectors). Infinite when there are
    more than ``MAX_STALL_REFITS``. Returns (bound per tone, stalled targets, the
    samples ``t_k`` at which the input is not known because of them)."""
    stalled = np.nonzero(spans > STALL_SPAN_S)[0]
    unknown = np.zeros(t_k.size, dtype=np.bool_)
    if stalled.size == 0:
        return np.zeros(response.size), 0, unknown
    if stalled.size > MAX_STALL_REFITS:
        return np.full(response.size, np.inf), int(stalled.size), unknown
    total = np.zeros(response.size)
    squares = np.zeros(response.size)
    base = np.interp(t_k, tick_t, u_ticks)
    for j in stalled:
        try:
            moved, u_moved = respond(int(j), float(latched_s[j] - spans[j]))
        except ValueError:
            return np.full(response.size, np.inf), int(stalled.size), unknown
        change = np.abs(moved - response)
        total += change
        squares += change**2
        unknown |= np.abs(np.interp(t_k, tick_t, u_moved) - base) > 0.5
    bound = np.minimum(total, TRUST_COVERAGE * np.sqrt(squares))
    with np.errstate(divide="ignore", invalid="ignore"):
        relative = np.asarray(bound / np.abs(response), dtype=np.float64)
    return relative, int(stalled.size), unknown


@dataclass(frozen=True, slots=True)
class InputCheck:
    """The rebuilt input against the capture's setpoint column at the kept samples."""

    max_counts: float | None  # largest difference
    excess_counts: float | None  # largest difference beyond the tick-phase tolerance
    samples_over: int  # samples beyond it
    bias: FloatArray  # bound of the response's relative error per tone


def input_check(
    t_k: FloatArray,
    setpoint_k: FloatArray,
    tick_t: FloatArray,
    u_ticks: FloatArray,
    tones: FloatArray,
    t_ref: float,
    input_amplitude: ComplexArray,
    tick_s: float,
) -> InputCheck:
    """See the module docstring (``tick_s``: the controller's tick, the grid of
    ``tick_t``); no setpoint column: nothing checked (bias 0)."""
    ok = np.isfinite(setpoint_k)
    if not ok.any():
        return InputCheck(None, None, 0, np.zeros(tones.size))
    t = t_k[ok]
    rebuilt = np.interp(t, tick_t, u_ticks)
    difference = setpoint_k[ok] - rebuilt
    motion = np.abs(np.interp(t + tick_s, tick_t, u_ticks) - np.interp(t - tick_s, tick_t, u_ticks))
    tolerance = CHECK_TOLERANCE_COUNTS + motion
    excess = np.sign(difference) * np.maximum(0.0, np.abs(difference) - tolerance)
    over = int(np.count_nonzero(excess))
    bias = np.zeros(tones.size)
    if over:
        try:
            fit = tone_fit(t, excess, tones, t_ref)
            with np.errstate(divide="ignore", invalid="ignore"):
                bias = (np.abs(fit.amplitude) + 2.0 * fit.standard_error) / np.abs(input_amplitude)
        except ValueError:
            bias = np.full(tones.size, np.inf)
    return InputCheck(
        float(np.max(np.abs(difference))),
        float(np.max(np.abs(excess))),
        over,
        np.asarray(bias, dtype=np.float64),
    )


def period_coherence(
    t_k: FloatArray,
    y_k: FloatArray,
    u_k: FloatArray,
    tones: FloatArray,
    start_s: float,
    period_s: float,
    periods: int,
    *,
    trend: bool = False,
) -> FloatArray:
    """Magnitude-squared coherence of ``u_k`` and ``y_k`` (both at the sample times) at
    the tones: ``|sum_p conj(U_p) Y_p|^2 / (sum_p |U_p|^2 sum_p |Y_p|^2)`` over the
    analysed periods, ``U_p``/``Y_p`` the tones' complex amplitudes in period ``p``
    (least squares with an offset, and a trend with ``trend``: an integrating output).
    On uniform samples over whole periods with the tones on their bins that is the
    Welch estimate with a rectangular window one period long (``scipy.signal.
    coherence``). NaN where fewer than two periods hold enough samples."""
    w = 2.0 * np.pi * tones
    period_of = np.floor((t_k - start_s) / period_s)
    cross = np.zeros(tones.size, dtype=np.complex128)
    power_u = np.zeros(tones.size)
    power_y = np.zeros(tones.size)
    used = 0
    extra = 2 if trend else 1
    for p in range(periods):
        sel = period_of == p
        n = int(sel.sum())
        if n <= extra + 2 * tones.size:
            continue
        t = t_k[sel] - start_s
        design = np.empty((n, extra + 2 * tones.size))
        design[:, 0] = 1.0
        if trend:
            design[:, 1] = t
        design[:, extra::2] = np.cos(np.outer(t, w))
        design[:, extra + 1 :: 2] = np.sin(np.outer(t, w))
        coef, *_ = np.linalg.lstsq(design, np.column_stack([u_k[sel], y_k[sel]]), rcond=None)
        a_u = coef[extra::2, 0] - 1j * coef[extra + 1 :: 2, 0]
        a_y = coef[extra::2, 1] - 1j * coef[extra + 1 :: 2, 1]
        cross += np.conj(a_u) * a_y
        power_u += np.abs(a_u) ** 2
        power_y += np.abs(a_y) ** 2
        used += 1
    if used < 2:
        return np.full(tones.size, np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        msc = np.abs(cross) ** 2 / (power_u * power_y)
    return np.asarray(np.clip(np.nan_to_num(msc, nan=0.0), 0.0, 1.0), dtype=np.float64)


@dataclass(frozen=True, slots=True)
class ToneTrust:
    """Per tone: the bounds and whether the tone is trusted (see the module doc)."""

    error_db: FloatArray
    error_deg: FloatArray
    trusted: npt.NDArray[np.bool_]
    limited_by: list[str | None]  # why a tone is not trusted (None: it is)


def tone_trust(
    tones: FloatArray,
    random: FloatArray,
    input_bias: FloatArray,
    stall_bias: FloatArray,
    timing: float,
    coherence: FloatArray,
    nyquist_hz: float,
) -> ToneTrust:
    """Magnitude bound ``-20 log10(1 - b)`` and phase bound ``asin(b) + 2 pi f dt``
    with ``b = TRUST_COVERAGE * random + input_bias + stall_bias`` (relative)."""
    relative = TRUST_COVERAGE * np.where(np.isfinite(random), random, np.inf)
    b = relative + input_bias + stall_bias
    with np.errstate(divide="ignore", invalid="ignore"):
        error_db = np.where(b < 1.0, -20.0 * np.log10(np.clip(1.0 - b, 1e-300, None)), np.inf)
        error_deg = np.where(
            b < 1.0, np.degrees(np.arcsin(np.clip(b, 0.0, 1.0))), np.inf
        ) + np.degrees(2.0 * np.pi * tones * timing)
    coherent = np.isfinite(coherence) & (coherence >= MIN_COHERENCE)
    within = (error_db <= MAX_TRUSTED_DB) & (error_deg <= MAX_TRUSTED_DEG)
    trusted = within & coherent & (tones <= nyquist_hz)
    limited: list[str | None] = []
    for i in range(tones.size):
        if trusted[i]:
            limited.append(None)
        elif tones[i] > nyquist_hz:
            limited.append("above the capture's Nyquist frequency")
        elif not coherent[i]:
            limited.append("coherence below 0.9")
        else:
            parts = {
                "noise (spread of the fit)": relative[i],
                "the input check (rebuilt input vs captured setpoint)": input_bias[i],
                "host stalls (targets stamped late)": stall_bias[i],
                "timing (tick phase and stamps)": 2.0 * np.pi * tones[i] * timing,
            }
            limited.append(max(parts, key=lambda k: parts[k]))
    return ToneTrust(
        np.asarray(error_db, dtype=np.float64),
        np.asarray(error_deg, dtype=np.float64),
        np.asarray(trusted, dtype=np.bool_),
        limited,
    )


def summary(
    tones: FloatArray,
    trust: ToneTrust,
    check: InputCheck,
    stalled_samples: int,
    stalled_commands: int,
    max_span_s: float | None,
    spans_source: str,
    gaps_s: FloatArray,
) -> dict[str, Any]:
    """The run-level account of its trust (JSON-ready), with the reasons in words."""
    trusted = int(trust.trusted.sum())
    reasons: dict[str, list[float]] = {}
    for f, why in zip(tones, trust.limited_by, strict=True):
        if why is not None:
            reasons.setdefault(why, []).append(float(f))
    words = [
        f"{why} at {', '.join(f'{f:g}' for f in fs[:8])}{' ...' if len(fs) > 8 else ''} Hz"
        for why, fs in reasons.items()
    ]
    return {
        "trusted_tones": trusted,
        "tones": int(tones.size),
        "max_error_db": MAX_TRUSTED_DB,
        "max_error_deg": MAX_TRUSTED_DEG,
        "coverage": TRUST_COVERAGE,
        "not_trusted": words,
        "input_check_counts": None if check.max_counts is None else round(check.max_counts, 2),
        "input_check_excess_counts": None
        if check.excess_counts is None
        else round(check.excess_counts, 2),
        "input_check_samples_over": check.samples_over,
        "stalled_samples_left_out": stalled_samples,
        "stalled_targets_bounded": stalled_commands,
        "max_latch_span_ms": None if max_span_s is None else round(max_span_s * 1000.0, 2),
        "spans": spans_source,
        "max_gap_ms": round(float(gaps_s.max()) * 1000.0, 1) if gaps_s.size else None,
        "gaps_over_50_ms": int(np.count_nonzero(gaps_s > 0.05)),
    }
