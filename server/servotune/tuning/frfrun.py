"""A frequency-response bench run: its excitation and its analysis (sans-IO).

Excitation: a periodic multisine with Schroeder phases around the held position,
``y0 + amplitude * x(t)``, ``|x| <= 1``. Its fundamental is the frequency resolution
``df`` (the lowest tone, or a divisor of it, so that at most ``MAX_TONES`` log-spaced
tones fall on multiples of ``df`` between the user's low and high frequencies). The
first period lets the loop's transient die out; the following whole periods are
analysed. Because the signal is periodic and every tone is on a bin of a segment one
period long, the spectra use a rectangular window: no leakage between tones (a Hann
window would mix neighbouring tones' bins, which a periodic excitation does not
average out).

Analysis: the loop's input is rebuilt on the controller's tick grid from the targets
sent, at the times the device latched them, through the firmware's profile law at the
test's sv/sa (``rebuild_input``); the output is the position samples at their latch
times, irregular as the wire delivered them. Closed loop: an impulse response on the
tick grid is fitted at the sample times against that input by least squares
(``tuning.frf.impulse_fit``) and ``T`` is its frequency response at the tones: a
staircase of targets sent at a few tens per second has images of its tones around
multiples of the target rate, which output samples at about the same rate fold back
onto the tones; a per-tone fit of input and output (``tuning.frf.tone_fit``, still
used open loop, where the input is PWM held by the firmware) counts them as response.
The relative error is the fit's standard error, the jackknife over periods when
larger, and the host's timing uncertainty; the coherence is the one equivalent to
that error. Welch spectra of samples interpolated onto a uniform grid, against the
targets stamped when acknowledged, are biased (docs/frequency-response.md says why).

Open loop from the measurement: for a loop whose controller acts on the error only
(the SLAP2, ``Cb = 0``), ``L = T / (1 - T)`` exactly, so margins and crossover come
from the measured T without any plant model — but only at tones where L is
measurable: near T = 1 the division amplifies T's error (``measured_margins``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from servotune.tuning import frftrust
from servotune.tuning.frf import (
    ComplexArray,
    FloatArray,
    ImpulseFit,
    impulse_fit,
    tone_fit,
    usable_run,
)
from servotune.tuning.injection import HeldTargets, InputModel, SetpointGenerator
from servotune.tuning.whatif import bode_dict, margins_dict

MAX_TONES = 24
MIN_COHERENCE = frftrust.MIN_COHERENCE
MIN_PERIODS = 3  # analysed, after the settling period (coherence needs averages)
# L = T / (1 - T) is used for margins at a tone only where its relative error, at
# ERROR_COVERAGE standard errors (about 95 %), is at most MAX_LOOP_ERROR: |L| within
# about +-2 dB and its phase within about +-14 deg.
ERROR_COVERAGE = 2.0
MAX_LOOP_ERROR = 0.25
# The closed loop's impulse response fitted by ``_impulse_estimate``: IMPULSE_TAPS
# boxes of IMPULSE_BOX_TICKS ticks (about 270 ms: the SLAP2 loops of the demo and
# the tests decay to 1e-3 of their impulse response's area within 150-230 ms).
IMPULSE_TAPS = 80
IMPULSE_BOX_TICKS = 4
IMPULSE_RIDGE = 1e-4
ESTIMATORS = {
    "impulse": "impulse response fitted at the sample times (least squares)",
    "tones": "tones fitted at the sample times (least squares)",
}


@dataclass(frozen=True, slots=True)
class Excitation:
    """The multisine of a run: ``target(t) = y0 + amplitude * x(t)`` (t from t0)."""

    y0: float
    amplitude: float
    tones_hz: tuple[float, ...]
    phases_rad: tuple[float, ...]
    scale: float  # 1 / peak of the raw sum, so |x| <= 1
    period_s: float
    settle_periods: int = 1
    # What each value is sent as: a position target (closed loop, ``ma``) or an
    # open-loop PWM (``spwm``, the plant alone; see ``analyse_open``).
    command: str = "move_absolute"
    argument: str = "position"
    # Tones of the requested band left out because the wire cannot resolve them
    # (``tuning.injection.WirePlan``), why, and the wire plan itself.
    not_measured_hz: tuple[float, ...] = ()
    not_measured_reason: str | None = None
    wire: Mapping[str, Any] | None = None

    def target(self, t_s: float) -> int:
        f = np.asarray(self.tones_hz)
        x = float(np.sum(np.cos(2 * np.pi * f * t_s + np.asarray(self.phases_rad))))
        return round(self.y0 + self.amplitude * self.scale * x)

    def to_dict(self) -> dict[str, Any]:
        return {
            "y0": self.y0,
            "amplitude": self.amplitude,
            "tones_hz": list(self.tones_hz),
            "phases_rad": list(self.phases_rad),
            "scale": self.scale,
            "period_s": self.period_s,
            "settle_periods": self.settle_periods,
            "command": self.command,
            "argument": self.argument,
            "not_measured_hz": list(self.not_measured_hz),
            "not_measured_reason": self.not_measured_reason,
            "wire": None if self.wire is None else dict(self.wire),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Excitation:
        return cls(
            float(d["y0"]),
            float(d["amplitude"]),
            tuple(float(x) for x in d["tones_hz"]),
            tuple(float(x) for x in d["phases_rad"]),
            float(d["scale"]),
            float(d["period_s"]),
            int(d.get("settle_periods", 1)),
            str(d.get("command", "move_absolute")),
            str(d.get("argument", "position")),
            tuple(float(x) for x in d.get("not_measured_hz") or ()),
            d.get("not_measured_reason"),
            d.get("wire"),
        )


def design(
    y0: float,
    amplitude: float,
    low_hz: float,
    high_hz: float,
    command: str = "move_absolute",
    argument: str = "position",
) -> Excitation:
    """The multisine for a band (callers check the ranges; see the module docstring)."""
    df = low_hz
    # At most MAX_TONES log-spaced tones on multiples of df (duplicates merged).
    ks = np.unique(np.round(np.geomspace(1.0, high_hz / df, MAX_TONES))).astype(int)
    tones = ks * df
    n = tones.size
    k = np.arange(1, n + 1)
    phases = -np.pi * k * (k - 1) / n
    period = 1.0 / df
    t = np.linspace(0.0, period, 4096, endpoint=False)
    raw = np.sum(np.cos(2 * np.pi * tones[:, None] * t[None, :] + phases[:, None]), axis=0)
    peak = float(np.max(np.abs(raw))) or 1.0
    return Excitation(
        y0=float(y0),
        amplitude=float(amplitude),
        tones_hz=tuple(float(x) for x in tones),
        phases_rad=tuple(float(x) for x in phases),
        scale=1.0 / (peak * 1.02),  # margin: the sampled peak may miss the true one
        period_s=period,
        command=command,
        argument=argument,
    )


def periods_in(duration_s: float, excitation: Excitation) -> int:
    """Whole periods analysed in a record of ``duration_s``."""
    return int(duration_s / excitation.period_s + 1e-9) - excitation.settle_periods


def _nan_inf(x: npt.ArrayLike) -> FloatArray:
    """NaN (an estimate that could not be made) as an infinite error."""
    a = np.asarray(x, dtype=np.float64)
    return np.asarray(np.where(np.isnan(a), np.inf, a), dtype=np.float64)


def rebuild_input(
    sent: Sequence[Sequence[float]],
    t0_s: float,
    y0: float,
    model: InputModel,
    t_end_s: float,
) -> tuple[FloatArray, FloatArray]:
    """The loop's input (the position setpoint) on the controller's tick grid
    (``model.tick_s``), from the targets sent: ``(t_s, setpoint)`` with t from ``t0_s``.

    Each row of ``sent`` is ``[acknowledged, target]`` or ``[acknowledged, target,
    latched, ...]``; a target takes effect at the first tick after its latch time (the
    acknowledgement when the latch is unknown), and the input follows it as ``model``
    says: through the device's profile generator (the injection's ``input_model``), or
    held (``tuning.injection.HeldTargets``)."""
    rebuild = InputRebuild(sent, t0_s, y0, model, t_end_s)
    return rebuild.t, rebuild.u


class InputRebuild:
    """``rebuild_input`` that can also give the input with one target latched at
    another time (``moved``), replaying only the ticks that change: from that target's
    earlier latch until the generator is back in the state it had."""

    def __init__(
        self,
        sent: Sequence[Sequence[float]],
        t0_s: float,
        y0: float,
        model: InputModel,
        t_end_s: float,
    ) -> None:
        latched = [float(r[2] if len(r) > 2 else r[0]) - t0_s for r in sent]
        if not latched:
            raise ValueError("no excitation was sent")
        self._targets = [float(r[1]) for r in sent]
        self._latched = latched
        self._model = model
        self._y0 = y0
        start = min(min(latched), 0.0)
        tick_s = model.tick_s
        n = int((t_end_s - start) / tick_s) + 2
        self.t = np.asarray(start + np.arange(n) * tick_s, dtype=np.float64)
        self.u = np.empty(n)
        self._states: list[Hashable] = []
        order = sorted(range(len(latched)), key=lambda i: latched[i])
        self._play(order, 0, model.start(y0), 0, self.u, self._states, None)

    def _play(
        self,
        order: list[int],
        i0: int,
        generator: SetpointGenerator,
        j0: int,
        out: FloatArray,
        states: list[Hashable] | None,
        settle_after: int | None,
    ) -> int:
        """Run ticks from ``i0`` (``generator`` in the state before it, rows
        ``order[j0:]`` still to come) into ``out``; with ``settle_after``, stop once past
        that tick the state equals the recorded one. Returns the first tick not written."""
        t, latched, targets = self.t, self._latched, self._targets
        step, state = generator.step, generator.state
        j = j0
        for i in range(i0, t.size):
            while j < len(order) and latched[order[j]] <= t[i]:
                generator.retarget(targets[order[j]])
                j += 1
            out[i] = step()
            now = state()
            if states is not None:
                states.append(now)
            elif settle_after is not None and i > settle_after and now == self._states[i]:
                return i + 1
        return t.size

    def moved(self, index: int, latched_s: float) -> FloatArray:
        """The input with row ``index`` of ``sent`` latched at ``latched_s`` (from t0)."""
        latched = list(self._latched)
        old, latched[index] = latched[index], latched_s
        first = min(old, latched_s)
        i0 = max(0, int(np.searchsorted(self.t, first, side="left")) - 1)
        model = self._model
        generator = model.resume(self._states[i0 - 1]) if i0 > 0 else model.start(self._y0)
        saved = self._latched
        self._latched = latched
        try:
            order = sorted(range(len(latched)), key=lambda i: latched[i])
            t_before = self.t[i0 - 1] if i0 > 0 else -math.inf
            j0 = sum(1 for i in order if latched[i] <= t_before)
            out = self.u.copy()
            last = int(np.searchsorted(self.t, max(old, latched_s), side="right"))
            self._play(order, i0, generator, j0, out, None, last)
        finally:
            self._latched = saved
        return out


@dataclass(frozen=True, slots=True)
class _Measured:
    """Output per input at the tones, from one record (see ``_measure``)."""

    tones_hz: FloatArray
    response: ComplexArray
    relative_error: FloatArray
    coherence: FloatArray
    trust: frftrust.ToneTrust
    summary: dict[str, Any]
    periods: int
    samples: int
    rate_hz: float
    input_check_counts: float | None
    estimator: str

    def tone_fields(self) -> dict[str, Any]:
        """The per-tone coherence, errors and trust of a Bode dict."""
        return {
            "coherence": _rounded(self.coherence, 4),
            "relative_error": _rounded(self.relative_error, 4),
            "error_db": _rounded(self.trust.error_db, 3),
            "error_deg": _rounded(self.trust.error_deg, 2),
            "trusted": [bool(v) for v in self.trust.trusted],
            "not_trusted_because": list(self.trust.limited_by),
        }


def _rounded(values: FloatArray, digits: int) -> list[float | None]:
    return [round(float(v), digits) if np.isfinite(v) else None for v in values]


def _jackknife(partial: ComplexArray, response: ComplexArray, periods: int) -> FloatArray:
    """Relative error per tone from leave-one-period-out estimates (the spread Welch
    averaging over periods would see); NaN rows (a refit that failed) count as
    infinite error."""
    spread = np.sqrt(
        (periods - 1) / periods * np.sum(np.abs(partial - partial.mean(axis=0)) ** 2, axis=0)
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        return _nan_inf(spread / (np.sqrt(2.0) * np.abs(response)))


def _tone_estimate(
    t_k: FloatArray,
    y_k: FloatArray,
    u_t: FloatArray,
    u: FloatArray,
    tones: FloatArray,
    start: float,
    t_mid: float,
    period_s: float,
    periods: int,
    differenced: bool,
) -> tuple[ComplexArray, FloatArray]:
    """``Y / U`` per tone from joint tone fits of output and input (``tone_fit``), and
    its relative error: the fits' standard errors, or the jackknife over periods when
    larger (the standard errors assume white residuals; gaps, a host that stalled the
    driver, and the response to the non-periodic part of the input are not)."""
    fit_u = tone_fit(u_t, u, tones, t_mid)
    fit_y = tone_fit(t_k, y_k, tones, t_mid, differenced=differenced)
    response = fit_y.amplitude / fit_u.amplitude
    with np.errstate(divide="ignore", invalid="ignore"):
        fit_error = np.hypot(
            fit_y.standard_error / np.abs(fit_y.amplitude),
            fit_u.standard_error / np.abs(fit_u.amplitude),
        )
    if periods >= 2:
        period_of_sample = np.floor((t_k - start) / period_s)
        period_of_tick = np.floor((u_t - start) / period_s)
        partial = np.empty((periods, tones.size), dtype=np.complex128)
        for i in range(periods):
            ys, us = period_of_sample != i, period_of_tick != i
            try:
                fy = tone_fit(t_k[ys], y_k[ys], tones, t_mid, differenced=differenced)
                fu = tone_fit(u_t[us], u[us], tones, t_mid)
            except ValueError:
                partial[i] = np.nan
                continue
            partial[i] = fy.amplitude / fu.amplitude
        fit_error = np.fmax(_nan_inf(fit_error), _jackknife(partial, response, periods))
    return np.asarray(response, dtype=np.complex128), np.asarray(fit_error, dtype=np.float64)


def _impulse_estimate(
    t_k: FloatArray,
    y_k: FloatArray,
    tick_t: FloatArray,
    u_ticks: FloatArray,
    tones: FloatArray,
    start: float,
    period_s: float,
    periods: int,
    tick_s: float,
) -> tuple[ComplexArray, FloatArray]:
    """The closed loop at the tones from an impulse response fitted at the sample
    times against the input on the tick grid (``tuning.frf.impulse_fit``, see there
    why), with its relative error: the fit's standard error, or the jackknife over
    periods (leave one period's samples out, refit) when larger."""
    lead = IMPULSE_TAPS * IMPULSE_BOX_TICKS
    # the input before the grid: the first value held (the position the test held)
    u = np.concatenate([np.full(lead, u_ticks[0]), u_ticks])
    grid_t0 = float(tick_t[0]) - lead * tick_s

    def fit(t: FloatArray, y: FloatArray) -> ImpulseFit:
        return impulse_fit(
            t,
            y,
            grid_t0,
            tick_s,
            u,
            taps=IMPULSE_TAPS,
            box_steps=IMPULSE_BOX_TICKS,
            ridge=IMPULSE_RIDGE,
        )

    response, error = fit(t_k, y_k).response(tones)
    with np.errstate(divide="ignore", invalid="ignore"):
        fit_error = _nan_inf(error / np.abs(response))
    if periods >= 2:
        period_of_sample = np.floor((t_k - start) / period_s)
        partial = np.empty((periods, tones.size), dtype=np.complex128)
        for i in range(periods):
            keep = period_of_sample != i
            try:
                partial[i] = fit(t_k[keep], y_k[keep]).response(tones)[0]
            except ValueError:
                partial[i] = np.nan
        fit_error = np.fmax(fit_error, _jackknife(partial, response, periods))
    return response, fit_error


def _measure(
    t_s: Sequence[float],
    output: Sequence[float],
    setpoint: Sequence[float | None] | None,
    sent: Sequence[Sequence[float]],
    t0_s: float,
    excitation: Excitation,
    model: InputModel,
    *,
    differenced: bool = False,
    estimator: str = "tones",
    sample_spans_s: Sequence[float | None] | None = None,
) -> _Measured:
    """The estimator shared by the closed-loop and the open-loop runs (``analyse``):
    ``estimator`` "impulse" (``_impulse_estimate``) or "tones" (``_tone_estimate``);
    ``differenced`` for an integrating output (tones only, ``tone_fit``). Samples the
    host stalled on are left out and stalled targets bounded (``tuning.frftrust``);
    ``sample_spans_s`` are the samples' latch spans (None: inferred from the gaps)."""
    t = np.asarray(t_s, dtype=np.float64) - t0_s
    y = np.asarray(output, dtype=np.float64)
    start = excitation.settle_periods * excitation.period_s
    after = t >= start
    if int(after.sum()) < 8:
        raise ValueError(
            f"{int(after.sum())} samples after the settling period: too few for a response"
        )
    periods = int((t[after][-1] - start) / excitation.period_s + 1e-9)
    if periods < 1:
        raise ValueError("the record does not hold one whole period after the settling one")
    end = start + periods * excitation.period_s
    keep = after & (t < end)
    # the host's latch spans (tuning.frftrust): recorded, or inferred from the gaps
    spans = frftrust.nan_array(sample_spans_s, t.size)
    command_spans = frftrust.command_spans(sent)
    latched = np.asarray([float(r[2] if len(r) > 2 else r[0]) for r in sent]) - t0_s
    missing = np.isnan(spans[keep]).any() or np.isnan(command_spans).any()
    spans_source = "recorded by the driver"
    if missing:
        from_gaps = frftrust.spans_from_gaps(t, latched)
        recorded_any = np.isfinite(spans).any() or np.isfinite(command_spans).any()
        spans = np.where(np.isnan(spans), from_gaps[0], spans)
        command_spans = np.where(np.isnan(command_spans), from_gaps[1], command_spans)
        spans_source = (
            "recorded; inferred from the gaps where missing"
            if recorded_any
            else "inferred from the gaps (not recorded)"
        )
    stalled = keep & (spans > frftrust.STALL_SPAN_S)
    use = keep & ~stalled
    t_k, y_k = t[use], y[use]
    kept_t = t[keep]
    rate_measured = float(1.0 / np.median(np.diff(kept_t))) if kept_t.size > 1 else 0.0
    tones = np.asarray(excitation.tones_hz, dtype=np.float64)
    tick_s = model.tick_s
    rebuild = InputRebuild(sent, t0_s, excitation.y0, model, end + tick_s)
    tick_t, u_ticks = rebuild.t, rebuild.u
    on_ticks = (tick_t >= start) & (tick_t < end)
    t_mid = 0.5 * (start + end)

    def estimate(
        ticks: FloatArray, u: FloatArray, jackknife: int
    ) -> tuple[ComplexArray, FloatArray]:
        if estimator == "impulse":
            return _impulse_estimate(
                t_k, y_k, ticks, u, tones, start, excitation.period_s, jackknife, tick_s
            )
        on = (ticks >= start) & (ticks < end)
        return _tone_estimate(
            t_k,
            y_k,
            ticks[on],
            u[on],
            tones,
            start,
            t_mid,
            excitation.period_s,
            jackknife,
            differenced,
        )

    try:
        response, fit_error = estimate(tick_t, u_ticks, periods)
    except ValueError as exc:
        # Too few samples for the fit: say how sparse the capture was, which is what a
        # user can act on (a starved host polls far below the wire's rate: run again).
        span_s = end - start
        raise ValueError(
            f"{exc}: the capture holds {t_k.size} samples in the {span_s:.2f} s measured "
            f"({t_k.size / span_s:.0f} per s), too sparse to measure; run it again"
        ) from exc

    def respond(index: int, latched_s: float) -> tuple[ComplexArray, FloatArray]:
        u = rebuild.moved(index, latched_s)
        return estimate(tick_t, u, 1)[0], u

    # only targets that reach the analysed samples matter
    reach = IMPULSE_TAPS * IMPULSE_BOX_TICKS * tick_s if estimator == "impulse" else 0.0
    relevant = (latched >= start - reach - excitation.period_s) & (latched < end)
    stall_bias, stalled_targets, input_unknown = frftrust.command_stall_bias(
        latched, np.where(relevant, command_spans, 0.0), respond, response, t_k, tick_t, u_ticks
    )
    timing = frftrust.timing_s(spans[use], command_spans[relevant], tick_s)
    random = _nan_inf(fit_error)
    input_amplitude = tone_fit(tick_t[on_ticks], u_ticks[on_ticks], tones, t_mid).amplitude
    # where a stalled target leaves the input unknown, neither the check nor the
    # coherence can say anything (the stall bound covers it)
    known = ~input_unknown
    sp = frftrust.nan_array(setpoint, t.size)[use]
    check = frftrust.input_check(
        t_k[known], sp[known], tick_t, u_ticks, tones, t_mid, input_amplitude, tick_s
    )
    coherence = frftrust.period_coherence(
        t_k[known],
        y_k[known],
        np.interp(t_k[known], tick_t, u_ticks),
        tones,
        start,
        excitation.period_s,
        periods,
        trend=differenced,
    )
    trust = frftrust.tone_trust(
        tones, random, check.bias, stall_bias, timing, coherence, rate_measured / 2.0
    )
    timing_error = 2.0 * np.pi * tones * timing
    relative_error = np.hypot(random, timing_error) + (check.bias + stall_bias) / ERROR_COVERAGE
    spanned = spans[keep]
    summary = frftrust.summary(
        tones,
        trust,
        check,
        int(stalled.sum()),
        stalled_targets,
        float(np.nanmax(np.concatenate([spanned, command_spans[relevant]])))
        if spanned.size
        else None,
        spans_source,
        np.diff(kept_t),
    )
    return _Measured(
        tones,
        np.asarray(response, dtype=np.complex128),
        np.asarray(relative_error, dtype=np.float64),
        coherence,
        trust,
        summary,
        periods,
        int(t_k.size),
        rate_measured,
        check.max_counts,
        estimator,
    )


def _bode(f: FloatArray, response: ComplexArray) -> dict[str, Any]:
    """Magnitude (dB) and phase (deg, unwrapped, then shifted by whole turns so that
    the first tone lies in (-270, 90]: T near 0 deg, L near -180 deg, a plant with an
    integrator near -90 deg, as the model curves beside them are drawn)."""
    phase = np.degrees(np.unwrap(np.angle(response)))
    if phase.size:
        phase = phase - 360.0 * np.ceil((phase[0] - 90.0) / 360.0)
    return bode_dict(f, 20 * np.log10(np.maximum(np.abs(response), 1e-300)), phase)


def _common(m: _Measured, excitation: Excitation) -> tuple[dict[str, Any], npt.NDArray[np.bool_]]:
    """The fields every measured run shows, and the tones margins and bandwidth are read
    from: coherent, below Nyquist, with a finite error (whether L is known there is
    ``open_loop_from_closed``'s call, from that error)."""
    nyquist = m.rate_hz / 2.0
    usable_from, usable = usable_run(m.tones_hz, m.trust.trusted)
    good = (
        (np.nan_to_num(m.coherence) >= MIN_COHERENCE)
        & (m.tones_hz <= nyquist)
        & np.isfinite(m.relative_error)
    )
    return {
        "usable_from_hz": usable_from,
        "usable_until_hz": usable,
        "sample_rate_hz": round(m.rate_hz, 2),
        "nyquist_hz": round(nyquist, 2),
        "periods": m.periods,
        "samples": m.samples,
        "input_check_counts": None
        if m.input_check_counts is None
        else round(m.input_check_counts, 2),
        "trust": m.summary,
        "estimator": ESTIMATORS[m.estimator],
        # the requested tones the wire could not resolve: not sent, not measured
        "not_measured_hz": list(excitation.not_measured_hz),
        "not_measured_reason": excitation.not_measured_reason,
        "wire": None if excitation.wire is None else dict(excitation.wire),
    }, good


def analyse(
    t_s: Sequence[float],
    position: Sequence[float],
    setpoint: Sequence[float | None] | None,
    sent: Sequence[Sequence[float]],
    t0_s: float,
    excitation: Excitation,
    model: InputModel,
    *,
    estimator: str = "impulse",
    sample_spans_s: Sequence[float | None] | None = None,
) -> dict[str, Any]:
    """The measured closed loop at the tones, each with its coherence, error bounds and
    whether it is trusted (``tuning.frftrust``), the usable band (the longest run of
    trusted tones), the run's ``trust`` account, and (Cb = 0) the open loop with margins
    where it is measurable; ValueError when the record cannot give a response.

    Estimator (docs/frequency-response.md): the input is rebuilt from the sent targets
    on the tick grid (``rebuild_input``), the output is the position samples at their
    latch times (less those the host stalled on); ``estimator`` "impulse" fits the
    closed loop's impulse response at the sample times (``tuning.frf.impulse_fit``),
    "tones" fits the tones of input and output and takes ``T = Y / U``.
    ``relative_error`` combines the fit's standard error (or the spread over periods),
    the timing uncertainty and the bias bounds (input check, stalled targets) divided
    by ``ERROR_COVERAGE``; ``coherence`` is the magnitude-squared coherence over the
    periods. ``setpoint`` (the capture's per-sample reconstruction), when recorded,
    checks the rebuilt input; ``sample_spans_s`` are the samples' latch spans."""
    m = _measure(
        t_s,
        position,
        setpoint,
        sent,
        t0_s,
        excitation,
        model,
        estimator=estimator,
        sample_spans_s=sample_spans_s,
    )
    common, good = _common(m, excitation)
    open_loop = open_loop_from_closed(m.tones_hz, m.response, m.relative_error, good)
    return {
        "loop": "closed",
        "closed_loop": _bode(m.tones_hz, m.response) | m.tone_fields(),
        "open_loop": open_loop["bode"],
        "nyquist": open_loop["nyquist"],
        "margins": open_loop["margins"],
        "input": model.name,
        **common,
        **_bandwidth(m.tones_hz[good], np.abs(m.response[good])),
    }


def analyse_open(
    t_s: Sequence[float],
    position: Sequence[float],
    sent: Sequence[Sequence[float]],
    t0_s: float,
    excitation: Excitation,
    controller: Callable[[FloatArray], ComplexArray] | None,
    *,
    tick_s: float,
    sample_spans_s: Sequence[float | None] | None = None,
) -> dict[str, Any]:
    """An open-loop run (PWM held by the device between the values sent, on its tick
    ``tick_s``, no controller): the plant ``P`` = position / PWM at the tones,
    measured; with ``controller`` (the device's law with the run's gains at given
    frequencies: ``DeviceLaw.controller_response``) the loop it would close,
    ``L = C P`` (C exact) and ``T = L / (1 + L)``, margins from the tones where P is
    coherent. Here L's relative error is P's (C is exact), so no tone is lost near
    T = 1; T's error is ``e_P / |1 + L|``. ValueError without a controller (a run that
    did not record its gains)."""
    # the position integrates the PWM: fitted on its increments (tone_fit)
    m = _measure(
        t_s,
        position,
        None,
        sent,
        t0_s,
        excitation,
        HeldTargets(tick_s),
        differenced=True,
        sample_spans_s=sample_spans_s,
    )
    common, good = _common(m, excitation)
    plant = _bode(m.tones_hz, m.response) | m.tone_fields()
    out: dict[str, Any] = {"loop": "open", "plant": plant, "input": "pwm", **common}
    if controller is None:
        raise ValueError("the run's PID gains are not recorded: no loop to close around the plant")
    loop = controller(m.tones_hz) * m.response
    closed = loop / (1.0 + loop)
    measurable = good & (ERROR_COVERAGE * m.relative_error <= MAX_LOOP_ERROR)
    with np.errstate(divide="ignore", invalid="ignore"):
        closed_error = m.relative_error / np.abs(1.0 + loop)
    return out | {
        # T's error is P's over |1 + L|: where P is trusted, so is T
        "closed_loop": _bode(m.tones_hz, closed)
        | m.tone_fields()
        | {"relative_error": _rounded(closed_error, 4)},
        "open_loop": _bode(m.tones_hz, loop)
        | {
            "relative_error": plant["relative_error"],
            "measurable": [bool(v) for v in measurable],
        },
        "nyquist": {
            "frequency_hz": [round(float(v), 5) for v in m.tones_hz],
            "re": [round(float(v), 5) for v in np.real(loop)],
            "im": [round(float(v), 5) for v in np.imag(loop)],
            "measurable": [bool(v) for v in measurable],
        },
        "margins": measured_margins(m.tones_hz, loop, m.relative_error, good, measurable),
        **_bandwidth(m.tones_hz[good], np.abs(closed[good])),
    }


def open_loop_from_closed(
    f: FloatArray,
    closed: ComplexArray,
    relative_error: FloatArray,
    good: npt.NDArray[np.bool_],
) -> dict[str, Any]:
    """``L = T / (1 - T)`` at the tones, its relative error, which tones measure it,
    and the margins read from those only (see ``measurable_loop``)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        loop = closed / (1.0 - closed)
        loop_error = relative_error * np.abs(closed) / np.abs(1.0 - closed)
    measurable = good & (ERROR_COVERAGE * _nan_inf(loop_error) <= MAX_LOOP_ERROR)
    bode = _bode(f, loop) | {
        "relative_error": [round(float(e), 4) if np.isfinite(e) else None for e in loop_error],
        "measurable": [bool(m) for m in measurable],
    }
    nyquist = {
        "frequency_hz": [round(float(v), 5) for v in f],
        "re": [round(float(v), 5) for v in np.real(loop)],
        "im": [round(float(v), 5) for v in np.imag(loop)],
        "measurable": [bool(m) for m in measurable],
    }
    return {
        "bode": bode,
        "nyquist": nyquist,
        "margins": measured_margins(f, loop, loop_error, good, measurable),
    }


def _crossings(
    f: FloatArray, values: FloatArray, level: float, pairs: npt.NDArray[np.bool_]
) -> list[tuple[float, int, float]]:
    """Where ``values`` crosses ``level`` between neighbouring tones i, i+1 with
    ``pairs[i]``: (frequency interpolated linearly in log f, i, fraction)."""
    out: list[tuple[float, int, float]] = []
    for i in np.nonzero(pairs)[0]:
        a, b = values[i] - level, values[i + 1] - level
        if a == 0 or a * b < 0:
            frac = a / (a - b) if a != b else 0.0
            hz = math.exp(math.log(f[i]) + frac * (math.log(f[i + 1]) - math.log(f[i])))
            out.append((hz, int(i), float(frac)))
    return out


def measured_margins(
    f: FloatArray,
    loop: ComplexArray,
    loop_error: FloatArray,
    good: npt.NDArray[np.bool_],
    measurable: npt.NDArray[np.bool_],
) -> dict[str, Any]:
    """Gain and phase margins of a measured open loop, read only between neighbouring
    tones that both measure L; each margin null with a reason when the run does not
    measure it, never a number from tones where L is unknown.

    Why: near T = 1 (below the crossover, where a PID's integrator makes |L| large and
    its phase close to -180 deg) ``L = T / (1 - T)`` divides by a small difference, so
    a 1-2 dB error of T swings L's phase across -180 deg by chance and reads a gain
    margin far from the model's (docs/frequency-response.md). A first-order
    propagation gives L's relative error ``e_L = e_T |T| / |1 - T|``; L is measurable
    at a tone with good coherence where ``ERROR_COVERAGE * e_L <= MAX_LOOP_ERROR``.
    Crossings are interpolated linearly in log f (dB for |L|, degrees for its phase);
    the smallest margin wins when there are several. ``*_error_*`` are the margins'
    uncertainties at the same coverage."""
    out: dict[str, Any] = margins_dict(math.nan, math.nan, math.nan, math.nan, None)
    pairs = measurable[:-1] & measurable[1:]
    band = f[measurable]
    where = (
        f"L is measurable at {band.size} tones between {band[0]:g} and {band[-1]:g} Hz"
        if band.size
        else "L is measurable at no tone"
    )
    uncertain = f[good & ~measurable]
    why_not = (
        f"; at {', '.join(f'{v:g}' for v in uncertain[:6])}{' ...' if uncertain.size > 6 else ''}"
        " Hz |1 - T| is too small against T's error"
        if uncertain.size
        else ""
    )
    db = 20 * np.log10(np.maximum(np.abs(loop), 1e-300))
    # phase unwrapped over the measurable tones only, then shifted so that -180 deg
    # (mod 360) is the level to cross
    phase = np.full(f.size, np.nan)
    if band.size:
        phase[measurable] = np.degrees(np.unwrap(np.angle(loop[measurable])))
    out["gain_margin_problem"] = out["phase_margin_problem"] = None
    out["gain_margin_error_db"] = out["phase_margin_error_deg"] = None
    phase_hits: list[tuple[float, float, float]] = []  # (hz, gm_db, error)
    if band.size:
        lo = math.floor((np.nanmin(phase) + 180.0) / 360.0)
        hi = math.ceil((np.nanmax(phase) + 180.0) / 360.0)
        for k in range(lo, hi + 1):
            for hz, i, frac in _crossings(f, phase, -180.0 + 360.0 * k, pairs):
                gm = -(db[i] + frac * (db[i + 1] - db[i]))
                e = ERROR_COVERAGE * max(loop_error[i], loop_error[i + 1])
                phase_hits.append((hz, gm, 20 * math.log10(1.0 + e)))
    if phase_hits:
        hz, gm, err = min(phase_hits, key=lambda hit: abs(hit[1]))
        out["gain_margin_db"], out["phase_crossover_hz"] = gm, hz
        out["gain_margin_error_db"] = round(err, 2)
    else:
        out["gain_margin_problem"] = (
            "not measurable from this run: the phase of L does not cross -180 deg between "
            f"tones where L is measurable ({where}{why_not})"
        )
    gain_hits: list[tuple[float, float, float]] = []  # (hz, pm_deg, error)
    for hz, i, frac in _crossings(f, db, 0.0, pairs):
        ph = phase[i] + frac * (phase[i + 1] - phase[i])
        pm = (ph + 180.0) % 360.0
        pm = pm - 360.0 if pm > 180.0 else pm
        e = ERROR_COVERAGE * max(loop_error[i], loop_error[i + 1])
        gain_hits.append((hz, pm, math.degrees(e)))
    if gain_hits:
        hz, pm, err = min(gain_hits, key=lambda hit: hit[1])
        out["phase_margin_deg"], out["gain_crossover_hz"] = pm, hz
        out["phase_margin_error_deg"] = round(err, 2)
    else:
        out["phase_margin_problem"] = (
            "not measurable from this run: |L| does not cross 1 (0 dB) between tones "
            f"where L is measurable ({where}{why_not})"
        )
    return out


def _bandwidth(f: FloatArray, magnitude: FloatArray) -> dict[str, Any]:
    """-3 dB bandwidth (interpolated between tones; null when the band never drops
    below it) and resonance peak of the measured closed loop, relative to the lowest
    good tone."""
    if f.size < 2:
        return {"bandwidth_hz": None, "resonance_db": None}
    ref = magnitude[0]
    db = 20 * np.log10(np.maximum(magnitude / ref, 1e-300))
    below = np.nonzero(db < -3.0)[0]
    bw: float | None = None
    if below.size:
        i = int(below[0])
        lo, hi = db[i - 1], db[i]
        frac = (-3.0 - lo) / (hi - lo) if hi != lo else 0.0
        bw = float(math.exp(math.log(f[i - 1]) + frac * (math.log(f[i]) - math.log(f[i - 1]))))
    return {"bandwidth_hz": bw, "resonance_db": round(float(np.max(db)), 3)}
