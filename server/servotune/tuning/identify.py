"""Fits of the plant models to recorded runs (scipy.optimize.least_squares).

* ``fit_plant``: the SLAP2's open-loop identification. Positions recorded under a PWM
  staircase against ``PlantModel``'s exact piecewise solution (so sample spacing does
  not matter), over log gain, friction, log tau and a small common delay of the steps.
* ``fit_closed_loop``: any closed-loop identification. A recorded trace (e.g. the
  Z1100's following error during a move with known gains) against a simulation of the
  device's loop on a first-order plant, over log gain, log tau and a delay; the device
  supplies the simulation (``devices.z1100.law.fit_plant_closed_loop``).

Why least squares on positions (not velocities): differences of positions polled
20-60 ms apart are noisy; the model's position is exact for any spacing. Why
``least_squares`` with bounds (trust-region reflective) instead of a simplex: the
residuals are sums of squares by construction, the bounds (tau and delay) are hard,
and the fits take fewer model evaluations. Pure: numpy/scipy, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares, minimize

from servotune.tuning.plants import PlantModel, model_positions

FloatArray = npt.NDArray[np.float64]

MAX_DELAY_S: Final = 0.02  # the open-loop fit's delay stays within +-this
DELAY_PRIOR_S: Final = 0.002  # ... with a prior of 0 +- this
TAU_RANGE_S: Final = (2e-4, 2.0)


def _slope(ts: Sequence[float], ys: Sequence[float]) -> float:
    """Least-squares slope of ``ys`` over ``ts`` (0 for a single instant)."""
    t = np.asarray(ts, dtype=np.float64)
    if t.size < 2 or np.ptp(t) == 0:
        return 0.0
    slope, _ = np.polyfit(t, np.asarray(ys, dtype=np.float64), 1)
    return float(slope)


def fit_plant(
    times: Sequence[float],
    positions: Sequence[float],
    schedule: Sequence[tuple[float, float]],
) -> PlantModel:
    """Least-squares fit of a ``PlantModel`` to positions recorded under a PWM schedule.

    ``times``/``positions``: the samples (any spacing, sorted; samples before the first
    step show the shaft at rest). ``schedule``: (time, pwm) at which each PWM level took
    effect, on the same clock. ``least_squares`` over log(gain), friction and log(tau),
    started from the slopes of the staircase levels (gain, friction) and the coast-down
    distance after the last step (tau, three starts); then also over a common delay of
    the steps (within ``MAX_DELAY_S``, with a prior of 0 +- ``DELAY_PRIOR_S`` as one
    more residual: the timestamps are already corrected, see
    ``devices.slap2.align_identification``). Raises ``ValueError`` when the data cannot
    determine a model (the shaft never moved).
    """
    if len(times) != len(positions) or len(times) < 5:
        raise ValueError("too few samples to fit a plant model")
    if not schedule:
        raise ValueError("no PWM steps to fit")
    events = sorted(schedule)
    t_first = events[0][0]
    before = [p for t, p in zip(times, positions, strict=True) if t <= t_first]
    x0 = before[-1] if before else positions[0]
    use = [(t, p) for t, p in zip(times, positions, strict=True) if t > t_first - 0.1]
    ts = [t for t, _ in use]
    ps = np.asarray([p for _, p in use], dtype=np.float64)
    if float(np.max(np.abs(ps - x0))) < 20:
        raise ValueError("the shaft did not move: raise max_pwm or check the mechanics")
    k0, uc0, tau0 = _initial_guess(events, use, x0)

    n = len(ts)
    prior_weight = math.sqrt(n) / DELAY_PRIOR_S  # as costly as 1 count on every sample

    def residuals(theta: FloatArray) -> FloatArray:
        """Model minus record, and the delay's prior; ``theta`` without a delay (stage
        1) means the step times as measured."""
        gain, uc, tau = math.exp(theta[0]), theta[1], math.exp(theta[2])
        delay = theta[3] if len(theta) > 3 else 0.0
        shifted = [(t + delay, u) for t, u in events]
        predicted = model_positions(PlantModel(gain, tau, max(uc, 0.0)), shifted, ts, x0=x0)
        return np.append(np.asarray(predicted) - ps, prior_weight * delay)

    log_tau = (math.log(TAU_RANGE_S[0]), math.log(TAU_RANGE_S[1]))
    u_max = max(abs(u) for _, u in events)
    scale = [0.2, max(0.5, 0.2 * uc0), 0.4, 0.002]
    # Stage 1: gain, friction and tau with the step times as measured; stage 2 also
    # frees a small common delay (what the timestamp correction missed), which the
    # curvature right after each step separates from tau.
    lo, hi = _bounds(log_tau, u_max)
    best: FloatArray | None = None
    best_cost = math.inf
    for tau_start in (tau0, tau0 * 0.5, tau0 * 2.0):
        start = [math.log(k0), uc0, math.log(tau_start)]
        theta, c = _solve(residuals, start, (lo[:3], hi[:3]), scale[:3])
        if c < best_cost:
            best, best_cost = theta, c
    assert best is not None
    stage1 = best[:3]
    best = np.append(best, 0.0)
    for delay_start in (0.0, -0.002, 0.003):
        theta, c = _solve(residuals, [*stage1, delay_start], (lo, hi), scale)
        if c < best_cost:
            best, best_cost = theta, c
    prior = (prior_weight * best[3]) ** 2
    return PlantModel(
        gain=math.exp(best[0]),
        tau_s=math.exp(best[2]),
        friction_pwm=max(0.0, float(best[1])),
        rms_error_counts=math.sqrt(max(0.0, best_cost - prior) / n),
        samples=n,
        delay_s=float(best[3]),
    )


def _bounds(log_tau: tuple[float, float], u_max: float) -> tuple[list[float], list[float]]:
    """(lower, upper) of log gain, friction, log tau, delay. Friction up to the largest
    PWM applied (the shaft moved: friction was below it)."""
    return (
        [-math.inf, 0.0, log_tau[0], -MAX_DELAY_S],
        [math.inf, max(u_max, 1e-6), log_tau[1], MAX_DELAY_S],
    )


def _solve(
    residuals: Callable[[FloatArray], FloatArray],
    start: Sequence[float],
    bounds: tuple[Sequence[float], Sequence[float]],
    scale: Sequence[float],
) -> tuple[FloatArray, float]:
    """``least_squares`` from ``start`` clipped into ``bounds``: (theta, sum of squares)."""
    lo, hi = np.asarray(bounds[0], dtype=np.float64), np.asarray(bounds[1], dtype=np.float64)
    x0 = np.clip(np.asarray(start, dtype=np.float64), lo, hi)
    result = least_squares(
        residuals, x0, bounds=(lo, hi), x_scale=np.asarray(scale), method="trf", max_nfev=400
    )
    theta = np.asarray(result.x, dtype=np.float64)
    return theta, float(np.sum(residuals(theta) ** 2))


def _initial_guess(
    events: list[tuple[float, float]], use: list[tuple[float, float]], x0: float
) -> tuple[float, float, float]:
    """(gain, friction, tau) from the staircase: a steady slope per level (second half
    of each level's samples) and the coast-down distance after the last step."""
    ts = [t for t, _ in use]
    ps = [p for _, p in use]
    t_first = events[0][0]
    levels: list[tuple[float, float]] = []
    for k, (start, u) in enumerate(events):
        end = events[k + 1][0] if k + 1 < len(events) else math.inf
        seg = [(t, p) for t, p in use if start + 0.5 * (min(end, ts[-1]) - start) <= t < end]
        if len(seg) >= 2 and u != 0:
            levels.append((u, _slope([t for t, _ in seg], [p for _, p in seg])))
    moving = [(u, s) for u, s in levels if abs(s) > 50]
    if len(moving) >= 2:
        us = [u for u, _ in moving]
        ss = [s for _, s in moving]
        k0 = _slope(us, ss)
        uc0 = sum(us) / len(us) - sum(ss) / len(ss) / k0 if k0 > 0 else 0.0
    elif moving:
        k0 = moving[0][1] / moving[0][0]
        uc0 = 0.0
    else:
        u_max = max(abs(u) for _, u in events) or 1.0
        k0 = (ps[-1] - x0) / max(ts[-1] - t_first, 1e-3) / u_max
        uc0 = 0.0
    if not k0 > 0:
        k0 = 100.0
    uc0 = min(max(uc0, 0.0), max(abs(u) for _, u in events))
    tau0 = 0.02
    last_t, last_u = events[-1]
    if last_u == 0 and moving:
        # Coast-down: distance after the last step ~ v0 * tau.
        pre = [(t, p) for t, p in use if t <= last_t][-3:]
        if len(pre) >= 2:
            v0 = _slope([t for t, _ in pre], [p for _, p in pre])
            p_at = pre[-1][1] + v0 * (last_t - pre[-1][0])
            if abs(v0) > 50:
                tau0 = min(max((ps[-1] - p_at) / v0, 0.002), 0.5)
    return k0, uc0, tau0


# =====================================================================================
# Closed loop: a trace against a simulation of the device's loop
# =====================================================================================


@dataclass(frozen=True, slots=True)
class ClosedLoopFit:
    """Result of ``fit_closed_loop``: the plant's gain and tau, the trace's delay."""

    gain: float
    tau_s: float
    delay_s: float
    rms: float
    samples: int


Simulation = Callable[[float, float], tuple[Sequence[float], Sequence[float]]]


def interpolate(ts: Sequence[float], ys: Sequence[float], t: float) -> float:
    """``ys`` at ``t``, linear between samples; before the trace's start ``ys[0]``,
    before time 0 (the loop at rest) 0, after its end ``ys[-1]``."""
    if t < 0 and t <= ts[0]:
        return 0.0
    return float(np.interp(t, ts, ys))


def fit_closed_loop(
    times: Sequence[float],
    values: Sequence[float],
    simulate: Simulation,
    starts: Sequence[tuple[float, float, float]],
    *,
    keep: int = 2,
    gain_range: tuple[float, float] = (1e3, 1e8),
    tau_range_s: tuple[float, float] = (5e-4, 1.0),
    delay_range_s: tuple[float, float] = (-0.005, 0.06),
) -> ClosedLoopFit:
    """Fit gain, tau and a delay so that ``simulate(gain, tau)`` matches a trace.

    ``simulate`` returns (times, values) of the device's loop on the plant (times from
    the trigger); the simulated trace is read at ``t - delay`` (``interpolate``), and
    the cost is the sum of squared differences. Every point of the ``starts`` grid
    (gain, tau, delay) is evaluated, then scipy's Nelder-Mead (bounded) runs from the
    ``keep`` best, coarse then fine.

    Why a simplex here and not ``least_squares`` as in ``fit_plant``: the simulation
    quantises (counts, integer PWM, the gain switch at the profile's end), so the cost
    is piecewise constant at the scale of a finite-difference step; gradient steps
    stopped early in local plateaus (tried: rms 1-50 counts where the simplex reaches
    0.1), a derivative-free method does not.
    """
    t_obs = np.asarray(times, dtype=np.float64)
    y_obs = np.asarray(values, dtype=np.float64)

    def cost(theta: FloatArray) -> float:
        sim_t, sim_y = simulate(math.exp(theta[0]), math.exp(theta[1]))
        shifted = t_obs - theta[2]
        predicted = np.interp(shifted, np.asarray(sim_t), np.asarray(sim_y))
        first = sim_t[0] if len(sim_t) else 0.0
        predicted[(shifted < 0) & (shifted <= first)] = 0.0
        return float(np.sum((predicted - y_obs) ** 2))

    bounds = [
        (math.log(gain_range[0]), math.log(gain_range[1])),
        (math.log(tau_range_s[0]), math.log(tau_range_s[1])),
        delay_range_s,
    ]
    lo = np.array([b[0] for b in bounds])
    hi = np.array([b[1] for b in bounds])
    grid: list[tuple[float, FloatArray]] = []
    for gain, tau, delay in starts:
        theta = np.clip(np.array([math.log(gain), math.log(tau), delay]), lo, hi)
        grid.append((cost(theta), theta))
    grid.sort(key=lambda g: g[0])
    results: list[tuple[float, FloatArray]] = list(grid[:1])
    for _, start in grid[:keep]:
        theta = start
        # coarse then fine simplex (steps in log gain, log tau, delay in s)
        for steps, iterations in (((0.2, 0.4, 0.006), 100), ((0.05, 0.1, 0.002), 60)):
            theta = _simplex(cost, theta, steps, iterations, lo, hi)
        results.append((cost(theta), theta))
    best_cost, best = min(results, key=lambda r: r[0])
    return ClosedLoopFit(
        gain=math.exp(best[0]),
        tau_s=math.exp(best[1]),
        delay_s=float(best[2]),
        rms=math.sqrt(best_cost / max(1, t_obs.size)),
        samples=int(t_obs.size),
    )


def _simplex(
    cost: Callable[[FloatArray], float],
    start: FloatArray,
    steps: Sequence[float],
    iterations: int,
    lo: FloatArray,
    hi: FloatArray,
) -> FloatArray:
    """scipy's bounded Nelder-Mead from ``start`` with a simplex of ``steps``; stops
    when the values differ by less than 1e-4 of the best (relative, as the costs'
    scale depends on the record)."""
    x0 = np.clip(start, lo, hi)
    simplex = np.vstack(
        [x0] + [np.clip(x0 + np.eye(x0.size)[i] * steps[i], lo, hi) for i in range(x0.size)]
    )
    scale = max(cost(x0), 1e-12)
    result = minimize(
        lambda th: cost(th) / scale,
        x0,
        method="Nelder-Mead",
        bounds=list(zip(lo, hi, strict=True)),
        options={"initial_simplex": simplex, "maxiter": iterations, "fatol": 1e-7, "xatol": 1e-9},
    )
    return np.asarray(result.x, dtype=np.float64)
