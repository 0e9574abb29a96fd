"""Auto-tune assistant for SLAP2 axes: identify the plant, propose gains, verify them.

Two layers (docs/autotune.md explains the method, the rule and its limits):

* A pure, sans-IO core: ``fit_plant`` fits a DC-motor model (first-order velocity
  response with Coulomb friction and stiction, in device units) to the positions
  recorded during an open-loop PWM staircase; ``simulate_response`` runs the SLAP2
  firmware's discrete loop (profile generator, integer PID law, anti-windup clamp,
  PWM saturation, 841.5 us tick, counts quantisation) on that model; ``propose_gains``
  searches kp/ki/kd by the documented rule and returns a ``Proposal`` with predicted
  metrics. No clocks, no I/O, pure Python.
* ``AutoTuner``: the async service that runs identify -> propose -> (accept) -> verify
  on a live axis through the ``Hub`` (validated writes and commands) and the
  ``TestBench`` (recorded runs), keeping one session per axis.

Units: positions in encoder counts, velocities in counts/s, PWM in the SLAP2's
-255..255 units, times in seconds.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
import uuid
from collections.abc import Callable, Coroutine, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Final, Literal

from pydantic import BaseModel, Field

from servotune.drivers.base import (
    BenchPlan,
    CommandClock,
    DeviceRefusedError,
    DeviceTimeoutError,
    DriverError,
    InvalidArgumentError,
    LinkDownError,
    Sample,
    capture_of,
)
from servotune.hub import AxisEntry, Hub
from servotune.metrics import Metrics, compute_metrics, unmeasured
from servotune.protocols.slap2 import (
    ACCELERATION_MAX,
    COUNTS_S2_PER_SA,
    COUNTS_S_PER_SV,
    GAIN_MAX,
    PWM_MAX,
    TICK_S,
    VELOCITY_MAX,
)
from servotune.testbench import BenchTestRequest, TestBench, _Recording, run_meta

logger = logging.getLogger(__name__)

Response = Literal["no_overshoot", "fast"]
TestKind = Literal["position_step", "move"]

# --- the firmware's PID law (docs/simulator.md; the SLAP2 manual gives no scaling) -------
_P_MUL: Final = 16
_D_MUL: Final = 32
_PID_SHIFT: Final = 12
_I_TERM_MAX: Final = PWM_MAX << _PID_SHIFT

# --- the rule (docs/autotune.md) ---------------------------------------------------
OVERSHOOT_LIMIT_PCT: Final[dict[str, float]] = {"no_overshoot": 1.0, "fast": 10.0}
ROBUST_GAIN_FACTORS: Final = (0.75, 1.33)  # the plant gain K may be off by this much ...
ROBUST_TAU_FACTORS: Final = (0.5, 2.0)  # ... and the time constant this much
SETTLED_HOLD_S: Final = 0.25  # a response counts as settled if it stays in band this long
# A one-count change of the error may move the PWM by at most this much (about 10 % of
# full scale): higher gains turn count quantisation into audible buzz and heat.
MAX_PWM_PER_COUNT: Final = 24.0
KI_RATIOS: Final = (0.0, 0.125, 0.5)  # ki as a fraction of kp
COARSE_FACTOR: Final = 1.6  # grid steps of kp and kd
FINE_FACTORS: Final = (0.8, 0.9, 1.0, 1.1, 1.25)  # around the best coarse candidates
FINE_SEEDS: Final = 3
MAX_ROBUST_CHECKS: Final = 40  # the fastest ones are compared on the perturbed models
ROBUST_TIE_S: Final = 0.005  # worst cases this close count as equal: gentler gains win
KD_FLOOR: Final = 16  # the smallest nonzero kd of the grid
_REJECTIONS: Final = {
    "pwm_per_count": "more than 24 PWM per count",
    "friction": "too weak against friction (friction/P > window/2)",
    "not_settled": "not settled",
    "overshoot": "overshoot > {limit:g} %",
    "excursion": "travelled too far",
    "not_robust": "not settled with the model's gain -25 %/+33 %, tau -50 %/+100 %",
}
MAX_FIT_RMS_COUNTS: Final = 10.0
MAX_DELAY_S: Final = 0.02  # the fit's delay stays within +-this
DELAY_PRIOR_S: Final = 0.002


# =====================================================================================
# Plant model and its fit
# =====================================================================================


@dataclass(frozen=True, slots=True)
class PlantModel:
    """PWM -> velocity first order with Coulomb friction; position integrates velocity.

    ``tau dv/dt = gain * (u - friction_pwm * sgn(v)) - v``; at rest the shaft stays at
    rest while ``|u| <= friction_pwm`` (stiction), and a velocity that would change sign
    stops at zero. ``gain`` is counts/s per PWM unit, ``friction_pwm`` the PWM that just
    overcomes friction, ``tau_s`` the mechanical time constant.
    """

    gain: float
    tau_s: float
    friction_pwm: float
    rms_error_counts: float = 0.0
    samples: int = 0
    delay_s: float = 0.0  # fit only: when the PWM steps took effect, after their timestamps

    def __post_init__(self) -> None:
        if not (self.gain > 0 and self.tau_s > 0 and self.friction_pwm >= 0):
            raise ValueError(f"implausible plant model {self!r}")

    def scaled(self, gain_factor: float, tau_factor: float) -> PlantModel:
        return PlantModel(self.gain * gain_factor, self.tau_s * tau_factor, self.friction_pwm)

    def to_dict(self) -> dict[str, float | int]:
        return {
            "gain_counts_s_per_pwm": round(self.gain, 3),
            "tau_s": round(self.tau_s, 5),
            "friction_pwm": round(self.friction_pwm, 3),
            "rms_error_counts": round(self.rms_error_counts, 2),
            "samples": self.samples,
            "delay_s": round(self.delay_s, 5),
        }


class _Motor:
    """Exact integration of ``PlantModel`` over intervals with a constant PWM."""

    __slots__ = ("_tick_decay", "_tick_lag", "gain", "tau", "uc", "v", "x")

    def __init__(self, model: PlantModel, x: float = 0.0) -> None:
        self.gain = model.gain
        self.tau = model.tau_s
        self.uc = model.friction_pwm
        self.x = x
        self.v = 0.0
        self._tick_decay = -math.expm1(-TICK_S / self.tau)
        self._tick_lag = self.tau * self._tick_decay

    def tick(self, u: float) -> None:
        """``advance(u, TICK_S)``, with the common case (moving on, no stop) inlined."""
        v = self.v
        if v > 0.0:
            v_inf = self.gain * (u - self.uc)
            if v_inf >= 0.0:
                self.x += v_inf * TICK_S + (v - v_inf) * self._tick_lag
                self.v = v + (v_inf - v) * self._tick_decay
                return
        elif v < 0.0:
            v_inf = self.gain * (u + self.uc)
            if v_inf <= 0.0:
                self.x += v_inf * TICK_S + (v - v_inf) * self._tick_lag
                self.v = v + (v_inf - v) * self._tick_decay
                return
        self.advance(u, TICK_S)

    def advance(self, u: float, dt: float) -> None:
        v = self.v
        if v == 0.0:
            if -self.uc <= u <= self.uc or dt <= 0.0:
                return  # stiction
            direction = 1.0 if u > 0 else -1.0
        else:
            direction = 1.0 if v > 0 else -1.0
        v_inf = self.gain * (u - self.uc * direction)
        tau = self.tau
        if v != 0.0 and v_inf * direction < 0.0:
            # decelerating towards the other direction: the speed reaches zero at tz
            tz = tau * math.log((v - v_inf) / -v_inf)
            if tz < dt:
                self.x += v_inf * tz + (v - v_inf) * tau * -math.expm1(-tz / tau)
                self.v = 0.0
                self.advance(u, dt - tz)  # stuck, or breaks away the other way
                return
        decay = -math.expm1(-dt / tau)
        self.x += v_inf * dt + (v - v_inf) * tau * decay
        self.v = v + (v_inf - v) * decay


def model_positions(
    model: PlantModel,
    schedule: Sequence[tuple[float, float]],
    times: Sequence[float],
    *,
    x0: float = 0.0,
) -> list[float]:
    """Model positions at ``times`` (sorted) for a PWM ``schedule`` of (time, pwm) steps.

    Before the first step the PWM is 0 and the shaft at rest at ``x0``.
    """
    motor = _Motor(model, x0)
    events = sorted(schedule)
    out: list[float] = []
    now = min(events[0][0], times[0]) if events and times else 0.0
    u = 0.0
    k = 0
    for t in times:
        while k < len(events) and events[k][0] <= t:
            motor.advance(u, events[k][0] - now)
            now = max(now, events[k][0])
            u = events[k][1]
            k += 1
        motor.advance(u, t - now)
        now = max(now, t)
        out.append(motor.x)
    return out


def _nelder_mead(
    f: Callable[[list[float]], float],
    x0: list[float],
    steps: list[float],
    *,
    iterations: int = 400,
    tolerance: float = 1e-10,
) -> list[float]:
    """Minimise ``f`` from ``x0`` (plain Nelder-Mead, standard coefficients)."""
    n = len(x0)
    simplex = [list(x0)]
    for i in range(n):
        point = list(x0)
        point[i] += steps[i]
        simplex.append(point)
    values = [f(p) for p in simplex]
    for _ in range(iterations):
        order = sorted(range(n + 1), key=values.__getitem__)
        simplex = [simplex[i] for i in order]
        values = [values[i] for i in order]
        if abs(values[-1] - values[0]) <= tolerance * (abs(values[0]) + tolerance):
            break
        centroid = [sum(p[i] for p in simplex[:-1]) / n for i in range(n)]
        worst = simplex[-1]
        reflected = [c + (c - w) for c, w in zip(centroid, worst, strict=True)]
        fr = f(reflected)
        if fr < values[0]:
            expanded = [c + 2 * (c - w) for c, w in zip(centroid, worst, strict=True)]
            fe = f(expanded)
            simplex[-1], values[-1] = (expanded, fe) if fe < fr else (reflected, fr)
        elif fr < values[-2]:
            simplex[-1], values[-1] = reflected, fr
        else:
            contracted = [c + 0.5 * (w - c) for c, w in zip(centroid, worst, strict=True)]
            fc = f(contracted)
            if fc < values[-1]:
                simplex[-1], values[-1] = contracted, fc
            else:
                best = simplex[0]
                simplex = [best] + [
                    [b + 0.5 * (p - b) for b, p in zip(best, point, strict=True)]
                    for point in simplex[1:]
                ]
                values = [values[0]] + [f(p) for p in simplex[1:]]
    return simplex[min(range(n + 1), key=values.__getitem__)]


def _slope(ts: Sequence[float], ys: Sequence[float]) -> float:
    n = len(ts)
    mt = sum(ts) / n
    my = sum(ys) / n
    den = sum((t - mt) ** 2 for t in ts)
    return sum((t - mt) * (y - my) for t, y in zip(ts, ys, strict=True)) / den if den else 0.0


def fit_plant(
    times: Sequence[float],
    positions: Sequence[float],
    schedule: Sequence[tuple[float, float]],
) -> PlantModel:
    """Least-squares fit of a ``PlantModel`` to positions recorded under a PWM schedule.

    ``times``/``positions``: the samples (any spacing, sorted; samples before the first
    step show the shaft at rest). ``schedule``: (time, pwm) at which each PWM level took
    effect, on the same clock. Positions are fitted directly (the reliable channel; a
    velocity from differences of polled positions would add noise). Nelder-Mead over
    log(gain), friction and log(tau), started from the slopes of the staircase levels
    (gain, friction) and the coast-down distance after the last step (tau); then also
    over a common delay of the steps (within ``MAX_DELAY_S``, with a prior of 0 +-
    ``DELAY_PRIOR_S``: the timestamps are already corrected, see
    ``align_identification``). Raises ``ValueError`` when the data cannot determine a
    model (the shaft never moved).
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
    ps = [p for _, p in use]
    if max(abs(p - x0) for p in ps) < 20:
        raise ValueError("the shaft did not move: raise max_pwm or check the mechanics")

    # Initial guess: a steady slope per level (second half of each level's samples).
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

    def cost(theta: list[float]) -> float:
        gain, uc, tau, delay = math.exp(theta[0]), theta[1], math.exp(theta[2]), theta[3]
        if uc < 0 or not 2e-4 <= tau <= 2.0 or not -MAX_DELAY_S <= delay <= MAX_DELAY_S:
            return 1e30
        shifted = [(t + delay, u) for t, u in events]
        predicted = model_positions(PlantModel(gain, tau, uc), shifted, ts, x0=x0)
        sse = sum((a - b) ** 2 for a, b in zip(predicted, ps, strict=True))
        # prior: the delay is 0 +- DELAY_PRIOR_S (as costly as 1 count on every sample)
        return sse + len(ts) * (delay / DELAY_PRIOR_S) ** 2

    # Stage 1: gain, friction and tau with the step times as measured; stage 2 also
    # frees a small common delay (what the timestamp correction missed), which the
    # curvature right after each step separates from tau.
    best: list[float] | None = None
    best_cost = math.inf
    for tau_start in (tau0, tau0 * 0.5, tau0 * 2.0):
        theta = [math.log(k0), uc0, math.log(tau_start), 0.0]
        theta = _nelder_mead(
            lambda th: cost([*th, 0.0]), theta[:3], [0.2, max(0.5, 0.2 * uc0), 0.4]
        )
        c = cost([*theta, 0.0])
        if c < best_cost:
            best, best_cost = [*theta, 0.0], c
    assert best is not None
    stage1 = best
    for delay_start in (0.0, -0.002, 0.003):
        theta = _nelder_mead(
            cost, [*stage1[:3], delay_start], [0.05, max(0.2, 0.1 * stage1[1]), 0.2, 0.002]
        )
        theta = _nelder_mead(cost, theta, [0.02, 0.1, 0.05, 0.001])
        c = cost(theta)
        if c < best_cost:
            best, best_cost = theta, c
    prior = len(ts) * (best[3] / DELAY_PRIOR_S) ** 2
    return PlantModel(
        gain=math.exp(best[0]),
        tau_s=math.exp(best[2]),
        friction_pwm=best[1],
        rms_error_counts=math.sqrt(max(0.0, best_cost - prior) / len(ts)),
        samples=len(ts),
        delay_s=best[3],
    )


def model_doubt(model: PlantModel, travel: float) -> str | None:
    """Why a fitted model is implausible (None: it is not). A time constant below two
    controller ticks cannot be resolved from polled telemetry and means the timing of
    the steps was off (a busy host); a residual above ``MAX_FIT_RMS_COUNTS`` plus 1 %
    of the travel means the model does not describe the record."""
    if model.tau_s < 2 * TICK_S:
        return f"time constant {model.tau_s * 1000:.1f} ms is below two ticks"
    if model.rms_error_counts > MAX_FIT_RMS_COUNTS + 0.01 * travel:
        return f"the fit is poor (rms {model.rms_error_counts:.1f} counts)"
    return None


# Timing of the SLAP2 driver's exchanges, in characters on the wire (docs/autotune.md).
# After a command executes: the echo of its CR and the bare CR reply, then (unless the
# module replies -1UC itself) the driver's "rss" check: 4 characters echoed one by one
# (2 character times each) and a reply of about 2 digits + CR.
_COMMAND_TAIL_CHARS: Final = 2
_RSS_CHECK_CHARS: Final = 2 * 4 + 3


def align_identification(
    sample_times: Sequence[float],
    positions: Sequence[float],
    command_returns: Sequence[tuple[float, int]],
    *,
    baud: int,
    rss_check: bool = True,
    slowdown: float = 1.0,
    commands_latched: bool = False,
) -> tuple[list[float], list[float], list[tuple[float, float]]]:
    """Move the host's timestamps to the device's moments (SLAP2 driver timing).

    A position sample already carries the driver's estimate of when the module latched
    it (the end of its CR echo less one character, docs/capture.md): kept as it is.
    A command returns after its CR's echo, the bare
    CR reply and the driver's ``rss`` check: it took effect ``_COMMAND_TAIL_CHARS +
    _RSS_CHECK_CHARS`` character times (stretched by ``slowdown``, the ratio of the
    wire's sample rate to the achieved one: host latency per echoed character)
    before it returned, at the next 841.5 us tick, while a position reply reports the
    last tick: one tick between the two on average. With ``commands_latched`` the
    command times are already the driver's latch estimates (``CommandClock``): only
    the tick is added.
    """
    char_s = 10.0 / baud
    times: list[float] = []
    values: list[float] = []
    for t, p in zip(sample_times, positions, strict=True):
        times.append(t)
        values.append(float(p))
    tail = (_COMMAND_TAIL_CHARS + (_RSS_CHECK_CHARS if rss_check else 0)) * char_s * slowdown
    if commands_latched:
        tail = 0.0
    schedule = [(t - tail + TICK_S, float(u)) for t, u in command_returns]
    return times, values, schedule


# =====================================================================================
# The firmware's closed loop on the model
# =====================================================================================


@dataclass(frozen=True, slots=True)
class Gains:
    kp: int
    ki: int
    kd: int

    def to_dict(self) -> dict[str, int]:
        return {"kp": self.kp, "ki": self.ki, "kd": self.kd}


@dataclass(frozen=True, slots=True)
class MoveSpec:
    """The test the gains are tuned for and verified with (a relative move ``mr``).

    ``velocity``/``acceleration`` in the SLAP2's sv/sa units (a position step uses
    their maxima), ``band`` the in-position window (sipw, counts), ``inpos_ticks`` the
    in-position time (sipt), ``latency_s`` the time from the test's t0 to the command's
    execution (the bench stamps t0 just before sending it), ``horizon_s`` how long after
    the profile's end the response is simulated.
    """

    distance: int
    velocity: int
    acceleration: int
    band: int = 5
    inpos_ticks: int = 50
    latency_s: float = 0.0
    horizon_s: float = 0.6

    def profile_time_s(self) -> float:
        """Duration of the trapezoid (or triangle) profile for ``distance``."""
        d = abs(self.distance)
        v = abs(self.velocity) * COUNTS_S_PER_SV
        a = self.acceleration * COUNTS_S2_PER_SA
        if d == 0 or v <= 0 or a <= 0:
            return 0.0
        if v * v / a >= d:
            return 2.0 * math.sqrt(d / a)
        return d / v + v / a

    def ticks(self) -> int:
        total = self.latency_s + self.profile_time_s() + self.horizon_s
        return math.ceil(total / TICK_S) + 1


@dataclass(slots=True)
class SimulatedResponse:
    """One simulated test; times relative to the test's t0.

    The per-tick series are empty when simulated with ``record=False``; the summary
    fields (every tick) are always there: ``ticks`` simulated (fewer than
    ``spec.ticks()`` after a runaway), the last tick outside the band (-1: none),
    the largest positions in and against the step direction, the largest |PWM|.
    """

    spec: MoveSpec
    t_s: list[float]
    position: list[int]
    setpoint: list[int]
    pwm: list[int]
    inpos: list[bool]
    ticks: int
    last_out_tick: int
    peak_forward: int
    peak_backward: int
    peak_pwm: int

    def metrics(self) -> Metrics:
        return compute_metrics(
            self.t_s,
            [float(p) for p in self.position],
            t0_s=0.0,
            y0=0.0,
            y_final=float(self.spec.distance),
            band=float(self.spec.band),
            following_error=[
                float(s - p) for s, p in zip(self.setpoint, self.position, strict=True)
            ],
            flags={"inpos": self.inpos},
        )

    def peak_excursion(self) -> int:
        """Largest distance from the start position, counts (either direction)."""
        return max(self.peak_forward, self.peak_backward)

    def overshoot_pct(self) -> float:
        """Largest travel beyond the target, in % of the distance."""
        beyond = self.peak_forward - abs(self.spec.distance)
        return 100.0 * max(0, beyond) / abs(self.spec.distance)


def simulate_response(
    model: PlantModel,
    gains: Gains,
    spec: MoveSpec,
    *,
    record: bool = True,
    give_up_s: float = math.inf,
    stop_when_settled: bool = False,
) -> SimulatedResponse:
    """The SLAP2 firmware (as ``sim/slap2.py`` implements it) running ``spec`` on ``model``.

    Each 841.5 us tick: sample the count, run the trapezoid generator, the integer PID
    ``u = (16 kp e + ki S + 32 kd (e - e_prev)) >> 12`` with ``S`` clamped so that
    ``|ki S| <= 255 << 12``, saturate to +-255, then integrate the plant over the tick
    with that PWM. In pm holding at count 0 until the move command executes at
    ``spec.latency_s``. ``record=False`` keeps only the summary (faster); the
    simulation stops early when the response runs away, or is still outside the band
    after ``give_up_s`` (it cannot settle sooner than that any more), or, with
    ``stop_when_settled``, has been inside the band for ``SETTLED_HOLD_S`` after the
    profile's end.
    """
    motor = _Motor(model, 0.5)
    kp, ki, kd = gains.kp, gains.ki, gains.kd
    limit = _I_TERM_MAX // max(ki, 1)
    start_tick = round(spec.latency_s / TICK_S)
    vmax = abs(spec.velocity) * COUNTS_S_PER_SV * TICK_S
    acc = spec.acceleration * COUNTS_S2_PER_SA * TICK_S * TICK_S
    target = float(spec.distance)
    direction = 1 if spec.distance >= 0 else -1
    sipw, sipt, band = spec.band, spec.inpos_ticks, spec.band
    sp = 0.0
    sp_vel = 0.0
    moving = False
    integral = 0
    e_prev = 0
    timer = 0
    inpos = True
    n = spec.ticks()
    runaway = 20 * abs(target) + 1000
    last_out = -1
    forward = backward = 0
    peak_pwm = 0
    t_s: list[float] = []
    position: list[int] = []
    setpoint: list[int] = []
    pwm: list[int] = []
    inpos_series: list[bool] = []
    ticks = 0
    for k in range(n):
        count = math.floor(motor.x)
        if k == start_tick:
            moving = True
            inpos = False
            timer = 0
        if moving:
            d = target - sp
            distance = -d if d < 0 else d
            allowed = math.sqrt(0.25 * acc * acc + 2.0 * acc * distance) - 0.5 * acc
            if allowed > vmax:
                allowed = vmax
            if allowed > distance:
                allowed = distance
            goal = -allowed if d < 0 else allowed
            sp_vel = min(sp_vel + acc, goal) if sp_vel < goal else max(sp_vel - acc, goal)
            sp += sp_vel
            rest = target - sp
            if -1e-6 < rest < 1e-6 and -acc <= sp_vel <= acc:
                sp = target
                sp_vel = 0.0
                moving = False
        e = math.floor(sp + 0.5) - count
        integral += e
        if integral > limit:
            integral = limit
        elif integral < -limit:
            integral = -limit
        u = (_P_MUL * kp * e + ki * integral + _D_MUL * kd * (e - e_prev)) >> _PID_SHIFT
        e_prev = e
        if u > PWM_MAX:
            u = PWM_MAX
        elif u < -PWM_MAX:
            u = -PWM_MAX
        if not moving and k >= start_tick:
            if -sipw <= e <= sipw:
                timer += 1
                inpos = timer >= sipt
            else:
                timer = 0
                inpos = False
        motor.tick(u)
        ticks = k + 1
        p = math.floor(motor.x)
        travelled = p * direction
        if travelled > forward:
            forward = travelled
        elif -travelled > backward:
            backward = -travelled
        if not -band <= p - target <= band:
            last_out = k
            if ticks * TICK_S > give_up_s:
                break
        if u > peak_pwm or -u > peak_pwm:
            peak_pwm = abs(u)
        if record:
            t_s.append(ticks * TICK_S)
            position.append(p)
            setpoint.append(math.floor(sp + 0.5))
            pwm.append(u)
            inpos_series.append(inpos)
        if abs(motor.x) > runaway:
            break  # no need to simulate further
        if stop_when_settled and not moving and (k - last_out) * TICK_S >= SETTLED_HOLD_S:
            break
    return SimulatedResponse(
        spec,
        t_s,
        position,
        setpoint,
        pwm,
        inpos_series,
        ticks=ticks,
        last_out_tick=last_out,
        peak_forward=forward,
        peak_backward=backward,
        peak_pwm=peak_pwm,
    )


@dataclass(frozen=True, slots=True)
class _Score:
    settled: bool
    settling_s: float
    overshoot_pct: float
    excursion: int


def _score(model: PlantModel, gains: Gains, spec: MoveSpec, give_up_s: float = math.inf) -> _Score:
    """Settling time into the band (settled: in it for the last ``SETTLED_HOLD_S``),
    overshoot and excursion of one simulated test, every tick counted. Not settled
    either when it does not settle, or not by ``give_up_s``."""
    response = simulate_response(
        model, gains, spec, record=False, give_up_s=give_up_s, stop_when_settled=True
    )
    overshoot = response.overshoot_pct()
    excursion = response.peak_excursion()
    settling = (response.last_out_tick + 1) * TICK_S
    held = response.ticks * TICK_S - settling
    settled = held >= SETTLED_HOLD_S - 1e-9  # a runaway or a give-up ends outside
    return _Score(settled, settling if settled else math.inf, overshoot, excursion)


# =====================================================================================
# The rule
# =====================================================================================


def pwm_per_count(gains: Gains) -> float:
    """PWM change caused by a one-count step of the error (P, I and D together)."""
    return (_P_MUL * gains.kp + gains.ki + _D_MUL * gains.kd) / (1 << _PID_SHIFT)


def friction_floor(model: PlantModel, band: int) -> int:
    """The smallest kp that holds the axis within half the in-position window against
    the model's friction (friction can stop the axis anywhere within +-friction/P)."""
    return max(1, math.ceil(model.friction_pwm * 256 / (band / 2))) if band > 0 else 1


def _geometric(start: float, stop: float, factor: float) -> list[int]:
    values: list[int] = []
    value = start
    while value <= stop:
        if not values or round(value) != values[-1]:
            values.append(round(value))
        value *= factor
    return values


def candidate_grid(model: PlantModel, band: int) -> list[Gains]:
    """The coarse grid: kp geometric from the friction floor, kd 0 and geometric from
    ``KD_FLOOR``, ki a fixed fraction of kp, all within ``MAX_PWM_PER_COUNT``."""
    limit = MAX_PWM_PER_COUNT * (1 << _PID_SHIFT)
    kp_max = min(GAIN_MAX, int(limit / _P_MUL))
    kd_max = min(GAIN_MAX, int(limit / _D_MUL))
    grid: list[Gains] = []
    for kp in _geometric(friction_floor(model, band), kp_max, COARSE_FACTOR):
        for kd in [0, *_geometric(KD_FLOOR, kd_max, COARSE_FACTOR)]:
            for ratio in KI_RATIOS:
                gains = Gains(kp, round(kp * ratio), kd)
                if pwm_per_count(gains) <= MAX_PWM_PER_COUNT:
                    grid.append(gains)
    return grid


def _neighbours(gains: Gains) -> list[Gains]:
    """The fine grid around ``gains``: kp and kd times ``FINE_FACTORS``, ki scaled with
    kp, and ki halved or doubled."""
    out: list[Gains] = []
    for fp in FINE_FACTORS:
        kp = max(1, min(GAIN_MAX, round(gains.kp * fp)))
        for fd in FINE_FACTORS:
            kd = min(GAIN_MAX, round(gains.kd * fd))
            for fi in (0.5, 1.0, 2.0):
                ki = min(GAIN_MAX, round(gains.ki * fp * fi))
                out.append(Gains(kp, ki, kd))
    return out


RULE_TEXT: Final = (
    "Gains by simulation: the SLAP2 firmware's discrete loop (841.5 us tick, integer PID "
    "law, anti-windup, PWM saturation, count quantisation, the same profile generator) "
    "runs the test on the identified model for each candidate of a kp/kd/ki grid "
    "(coarse, then finer around the best). A candidate qualifies if it settles into the "
    "in-position window and stays there, overshoots at most {limit}, changes the PWM by "
    "at most 24 per count of error, has a kp that alone holds the axis within half the "
    "window against the identified friction, and still settles with the plant gain off "
    "by -25 %/+33 % and the time constant by -50 %/+100 %. Of the 40 fastest "
    "qualifying candidates, the proposal is the one whose slowest settling on those "
    "perturbed models is shortest; within 5 ms of that, the one with the fewest PWM "
    "per count."
)


@dataclass(frozen=True, slots=True)
class Proposal:
    """What ``propose_gains`` returns: the gains and everything the user is shown."""

    model: PlantModel
    spec: MoveSpec
    response: Response
    gains: Gains
    current_gains: Gains
    predicted: Metrics
    predicted_default: Metrics
    predicted_peak_pwm: int
    predicted_excursion: int
    default_excursion: int
    design: dict[str, Any]
    rule: str
    candidates: int
    simulations: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "model": self.model.to_dict(),
            "test": asdict(self.spec),
            "response": self.response,
            "gains": self.gains.to_dict(),
            "current_gains": self.current_gains.to_dict(),
            "predicted": asdict(self.predicted),
            "predicted_default": asdict(self.predicted_default),
            "predicted_peak_pwm": self.predicted_peak_pwm,
            "predicted_excursion": self.predicted_excursion,
            "default_excursion": self.default_excursion,
            "design": self.design,
            "rule": self.rule,
            "candidates": self.candidates,
            "simulations": self.simulations,
        }


def propose_gains(
    model: PlantModel,
    spec: MoveSpec,
    response: Response,
    current: Gains,
    *,
    max_excursion: int | None = None,
) -> Proposal:
    """Search gains by the rule (``RULE_TEXT``, docs/autotune.md) for ``spec`` on ``model``.

    Candidates: ``candidate_grid``, then ``_neighbours`` of the ``FINE_SEEDS`` fastest
    qualifying ones, and the gains in use ("no change" is a possible answer). A
    candidate qualifies if, on the model, it settles into the in-position window (and
    stays there for ``SETTLED_HOLD_S``), overshoots at most the response's limit,
    travels no further than ``max_excursion`` (counts), changes the PWM by at most
    ``MAX_PWM_PER_COUNT`` per count of error and has at least the ``friction_floor``
    kp. The ``MAX_ROBUST_CHECKS`` fastest qualifying candidates (ties: lower overshoot,
    then gentler gains) are simulated on the eight models with the gain and the time
    constant off by ``ROBUST_*_FACTORS``; those that settle on all of them compete on
    their slowest settling time there (ties: the nominal ranking): the proposal is the
    one that settles soonest in the worst case. Raises ``ValueError`` if none
    qualifies.
    """
    if spec.distance == 0:
        raise ValueError("the test distance must not be 0")
    limit_pct = OVERSHOOT_LIMIT_PCT[response]
    excursion_limit = max_excursion if max_excursion is not None else 1 << 30
    kp_floor = friction_floor(model, spec.band)
    scores: dict[Gains, _Score] = {}
    simulations = 0

    def score(gains: Gains, plant: PlantModel | None = None) -> _Score:
        nonlocal simulations
        if plant is not None:
            simulations += 1
            return _score(plant, gains, spec)
        cached = scores.get(gains)
        if cached is None:
            simulations += 1
            cached = scores[gains] = _score(model, gains, spec)
        return cached

    def rejection(gains: Gains) -> str | None:
        """Why ``gains`` do not qualify on the nominal model (None: they do)."""
        if pwm_per_count(gains) > MAX_PWM_PER_COUNT:
            return "pwm_per_count"
        if gains.kp < kp_floor:
            return "friction"
        s = score(gains)
        if not s.settled:
            return "not_settled"
        if s.overshoot_pct > limit_pct:
            return "overshoot"
        if s.excursion > excursion_limit:
            return "excursion"
        return None

    def key(gains: Gains) -> tuple[float, float, float]:
        s = score(gains)
        return (round(s.settling_s, 6), round(s.overshoot_pct, 1), pwm_per_count(gains))

    perturbed = [
        model.scaled(gf, tf)
        for gf in (1.0, *ROBUST_GAIN_FACTORS)
        for tf in (1.0, *ROBUST_TAU_FACTORS)
        if (gf, tf) != (1.0, 1.0)
    ]

    def worst_case(gains: Gains, bound: float) -> float:
        """Slowest settling over the perturbed models; inf if one does not settle, or
        not by ``bound`` (then it cannot beat the best so far)."""
        nonlocal simulations
        worst = 0.0
        for plant in perturbed:
            simulations += 1
            s = _score(plant, gains, spec, give_up_s=bound)
            if not s.settled:
                return math.inf
            worst = max(worst, s.settling_s)
        return worst

    robust_scores: dict[Gains, float] = {}
    unstable: set[Gains] = set()

    def robust_ranking(ranked: list[Gains]) -> list[tuple[float, int, Gains]]:
        """(worst-case settling, nominal rank, gains) for the ``MAX_ROBUST_CHECKS``
        fastest candidates that settle on every perturbed model, best first. Each
        check gives up as soon as a perturbed model is slower than the best so far."""
        found: list[tuple[float, int, Gains]] = []
        best = math.inf
        for i, gains in enumerate(ranked[:MAX_ROBUST_CHECKS]):
            worst = robust_scores.get(gains)
            if worst is None and gains not in unstable:
                worst = worst_case(gains, best)
                if math.isfinite(worst):
                    robust_scores[gains] = worst
                elif math.isinf(best):
                    unstable.add(gains)  # no bound applied: it really does not settle
            if worst is not None and math.isfinite(worst):
                found.append((worst, i, gains))
                best = min(best, worst)
        return sorted(found)

    reasons: dict[Gains, str | None] = {}
    for gains in [*candidate_grid(model, spec.band), current]:
        reasons.setdefault(gains, rejection(gains))
    coarse = sorted((g for g, why in reasons.items() if why is None), key=key)
    for _, _, seed in robust_ranking(coarse)[:FINE_SEEDS]:
        for gains in _neighbours(seed):
            reasons.setdefault(gains, rejection(gains))
    ranked = sorted((g for g, why in reasons.items() if why is None), key=key)
    robust = robust_ranking(ranked)
    if not robust:
        counts = {why: 0 for why in _REJECTIONS}
        for why in reasons.values():
            if why is not None:
                counts[why] += 1
        counts["not_robust"] = len(unstable)
        excursion = "" if max_excursion is None else f", travel <= {max_excursion}"
        detail = ", ".join(
            _REJECTIONS[why].format(limit=limit_pct, band=spec.band) + f": {n}"
            for why, n in counts.items()
            if n
        )
        raise ValueError(
            f"no gains meet the rule ({response}: overshoot <= {limit_pct:g} %, settling "
            f"within ±{spec.band} counts{excursion}) on the identified model; of "
            f"{len(reasons)} candidates: {detail}. Try a longer test distance, 'fast', or "
            "a wider in-position window"
        )
    # the fastest in the worst case; within ROBUST_TIE_S of it, the gentlest gains
    fastest = robust[0][0]
    worst, _, best = min(
        (f for f in robust if f[0] <= fastest + ROBUST_TIE_S),
        key=lambda f: (pwm_per_count(f[2]), f[0], f[1]),
    )
    design = {
        "kp_floor": kp_floor,
        "pwm_per_count": round(pwm_per_count(best), 2),
        "worst_case_settling_s": round(worst, 4),
        "unchanged": best == current,
    }
    predicted_run = simulate_response(model, best, spec)
    default_run = simulate_response(model, current, spec)
    return Proposal(
        model=model,
        spec=spec,
        response=response,
        gains=best,
        current_gains=current,
        predicted=predicted_run.metrics(),
        predicted_default=default_run.metrics(),
        predicted_peak_pwm=predicted_run.peak_pwm,
        predicted_excursion=predicted_run.peak_excursion(),
        default_excursion=default_run.peak_excursion(),
        design=design,
        rule=RULE_TEXT.format(limit=f"{limit_pct:g} %"),
        candidates=len(reasons),
        simulations=simulations,
    )


# =====================================================================================
# The service
# =====================================================================================

IDENT_TRAVEL_FRACTION: Final = 0.5  # the staircase brakes before half of max_distance
IDENT_DONE_FRACTION: Final = 0.3  # ... and ends after a level that passed 30 % of it
IDENT_START_PWM: Final = 2
IDENT_STEP_FACTOR: Final = 1.5
IDENT_DWELL_S: Final = 0.15
IDENT_MAX_S: Final = 1.5
IDENT_STOP_MARGIN_S: Final = 0.1  # latency + braking, as time at the present speed
IDENT_MIN_DISTANCE: Final = 400
IDENT_ATTEMPTS: Final = 2  # a doubtful fit is repeated once
MAX_SLOWDOWN: Final = 1.3  # cap of the per-character stretch of the command tail
UCON_BIT: Final = 1 << 5  # syscon: the module replies -1UC itself (no rss check)
# "No telemetry" means the link is down, not that a loaded host polled late: a link
# that delivers nothing for this long is also shown down by its status.
SAMPLE_TIMEOUT_S: Final = 2.0
SETTLE_TIMEOUT_S: Final = 3.0
RETURN_HORIZON_S: Final = 2.0  # a return move must settle this soon on the model
TEST_RECORD_S: Final = 1.5  # recorded after the profile's end (ends earlier once settled)
DEFAULT_TEST_DISTANCE: Final = 1000

SessionState = Literal["idle", "identifying", "proposed", "verifying", "verified", "failed"]


class IdentifyRequest(BaseModel):
    """``POST /api/axes/{id}/autotune/identify``: the user's limits and the goal."""

    max_pwm: int = Field(ge=1, le=PWM_MAX, description="largest open-loop PWM (-255..255)")
    max_distance_counts: int = Field(
        ge=1,
        le=1 << 24,
        description="no test travels further than this from where it starts (counts)",
    )
    response: Response = Field(
        default="no_overshoot", description="no_overshoot (<= 1 %) or fast (<= 10 %)"
    )
    test: TestKind = Field(
        default="position_step",
        description="the test the gains are tuned for: position_step (sv/sa at maximum) "
        "or move (the axis' own sv/sa)",
    )
    direction: Literal[1, -1] = Field(
        default=1, description="1: identify and test towards positive counts, -1: negative"
    )
    distance: int | None = Field(
        default=None,
        ge=1,
        le=1 << 24,
        description="distance of the baseline and verification tests, counts "
        f"(default: {DEFAULT_TEST_DISTANCE} or half of max_distance_counts if smaller)",
    )


@dataclass(slots=True)
class _Session:
    axis_id: str
    state: SessionState = "idle"
    message: str = ""
    request: IdentifyRequest | None = None
    identification_run_id: str | None = None
    proposal: Proposal | None = None
    proposal_dict: dict[str, Any] | None = None
    model: dict[str, Any] | None = None
    device_settings: dict[str, int] = field(default_factory=dict)
    result: dict[str, Any] | None = None
    updated_s: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "axis": self.axis_id,
            "state": self.state,
            "message": self.message,
            "request": self.request.model_dump() if self.request else None,
            "identification_run_id": self.identification_run_id,
            "model": self.model,
            "proposal": self.proposal_dict,
            "result": self.result,
            "updated_s": self.updated_s,
        }


class _IdentificationRun:
    """The identification recorded as a bench run, with the bench's own recorder.

    ``TestBench`` has no public way to record a sequence it does not drive itself, so
    this registers a recording in the bench's table of active runs (which also makes
    the bench refuse other tests on the axis meanwhile), stores it like any run and
    reports it with the bench's ``run`` messages. It uses TestBench internals on
    purpose, in one place: the candidate for a ``TestBench.record()`` method.
    """

    def __init__(self, bench: TestBench, entry: AxisEntry, p0: float, max_pwm: int) -> None:
        self.bench = bench
        self.entry = entry
        plan = BenchPlan(
            setup=[],
            trigger=[("open_loop_pwm", {"pwm": IDENT_START_PWM})],
            finish=[("open_loop_pwm", {"pwm": 0}), ("stop", {})],
            response="position",
            y0=p0,
            y_final=p0,
            band=None,
        )
        self.run_id = uuid.uuid4().hex[:12]
        test = {
            "kind": "pwm_step",
            "distance": 0,
            "velocity": 0,
            "pwm": max_pwm,
            "duration_s": 0.0,
            "note": "auto-tune identification: open-loop PWM staircase",
        }
        self.meta: dict[str, Any] = run_meta(entry, test, plan)
        self.recording = _Recording(
            self.run_id, entry, plan, self.meta["columns"], self.meta["flags"]
        )
        # The link polls this axis only while the run records (docs/capture.md).
        self._capture = contextlib.AsyncExitStack()

    @property
    def samples(self) -> list[list[Any]]:
        return self.recording.samples

    @property
    def columns(self) -> list[str]:
        return self.recording.columns

    async def open(self, clock: Callable[[], float]) -> None:
        axis_id = self.entry.info.id
        if axis_id in self.bench._active:
            raise DeviceRefusedError("a test is already running on this axis")
        self.bench._active[axis_id] = self.recording  # the bench refuses tests from now
        try:
            await asyncio.to_thread(
                self.bench._storage.create_run,
                self.run_id,
                self.entry.storage_key,
                axis_id,
                time.time(),
                self.meta,
            )
        except BaseException:
            self.bench._active.pop(axis_id, None)
            raise
        await self._capture.enter_async_context(
            capture_of(self.entry.driver, reason="auto-tune identification")
        )
        self.recording.t0 = clock()
        self.bench._update(self.recording, "recording", "auto-tune identification")

    def progress(self, message: str) -> None:
        self.bench._update(self.recording, "recording", message)

    async def close(self, status: str, message: str, extra: dict[str, Any]) -> None:
        try:
            await self._capture.aclose()
            await self.bench._flush(self.recording)
        finally:
            self.bench._active.pop(self.entry.info.id, None)
            self.meta["message"] = message
            self.meta["autotune"] = extra
            if self.recording.t0 is not None:
                self.meta["test"]["duration_s"] = round(
                    self.samples[-1][0] - self.recording.t0 if self.samples else 0.0, 3
                )
            await asyncio.to_thread(self.bench._storage.finish_run, self.run_id, status, self.meta)
            self.bench._update(self.recording, status, message or "done")


def _metrics_dict(metrics: Metrics) -> dict[str, Any]:
    return asdict(metrics)


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
    base_os = baseline.get("overshoot_pct") or 0.0
    tuned_os = tuned.get("overshoot_pct") or 0.0
    if tuned_settle <= base_settle + resolution and base_os >= 1.0 and tuned_os <= 0.5 * base_os:
        return "better"
    return "not better"


class AutoTuner:
    """identify -> propose -> accept -> verify, one session per axis (SLAP2 only).

    Everything that changes the device goes through the hub (``write_params``,
    ``command``) or the bench (recorded tests). Refusals (limits, wrong device, busy)
    happen before anything moves. On any error the axis is stopped (``st``); a stop
    that cannot reach the axis is repeated when its link is back.
    """

    def __init__(
        self, hub: Hub, bench: TestBench, *, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self._hub = hub
        self._bench = bench
        self._clock = clock
        self._sessions: dict[str, _Session] = {}
        self._locks: dict[str, asyncio.Lock] = {}
        self._sample_events: dict[str, asyncio.Event] = {}
        # Per axis: the stop generation when the running sequence started.
        self._generations: dict[str, int] = {}
        hub.add_sample_listener(self._on_sample)
        from servotune.autotune_z1100 import Z1100Tuner

        self._z1100 = Z1100Tuner(self)

    # --- queries ----------------------------------------------------------------------

    def session(self, axis_id: str) -> dict[str, Any]:
        self._check_device(axis_id)
        return self._session(axis_id).to_dict()

    def _session(self, axis_id: str) -> _Session:
        session = self._sessions.get(axis_id)
        if session is None:
            session = self._sessions[axis_id] = _Session(axis_id)
        return session

    def _check_device(self, axis_id: str) -> AxisEntry:
        entry = self._hub.entry(axis_id)
        if entry.info.device == "slap2" or self._is_z1100(entry):
            return entry
        raise DeviceRefusedError("auto-tune supports SLAP2 so far (and Z1100 chip axes)")

    @staticmethod
    def _is_z1100(entry: AxisEntry) -> bool:
        from servotune.drivers.z1100 import Z1100Axis

        return entry.info.device == "z1100" and isinstance(
            getattr(entry, "driver", None), Z1100Axis
        )

    def _lock(self, axis_id: str) -> asyncio.Lock:
        lock = self._locks.get(axis_id)
        if lock is None:
            lock = self._locks[axis_id] = asyncio.Lock()
        if lock.locked():
            raise DeviceRefusedError("auto-tune is already running on this axis")
        return lock

    def _set(self, session: _Session, state: SessionState, message: str) -> None:
        session.state = state
        session.message = message
        session.updated_s = time.time()
        level: Literal["info", "error"] = "error" if state == "failed" else "info"
        self._hub.on_event(level, session.axis_id, f"auto-tune: {message}")

    # --- samples ----------------------------------------------------------------------

    def _on_sample(self, axis_id: str, sample: Sample) -> None:
        event = self._sample_events.get(axis_id)
        if event is not None:
            event.set()

    async def _next_sample(self, entry: AxisEntry) -> Sample:
        """The axis' next sample; DriverError if none comes for ``SAMPLE_TIMEOUT_S``."""
        sample = await self._sample_before(entry, self._clock() + SAMPLE_TIMEOUT_S)
        if sample is None:
            raise DriverError("no telemetry from the axis: is the link up?")
        return sample

    async def _sample_before(self, entry: AxisEntry, until: float) -> Sample | None:
        """The axis' next sample, or None if the clock reaches ``until`` first."""
        event = self._sample_events.setdefault(entry.info.id, asyncio.Event())
        event.clear()
        try:
            await asyncio.wait_for(event.wait(), max(0.0, until - self._clock()))
        except TimeoutError:
            return None
        return entry.latest

    @staticmethod
    def _position(sample: Sample | None) -> float:
        value = sample.channels.get("position") if sample is not None else None
        if value is None:
            raise DeviceRefusedError("the axis reports no position yet")
        return float(value)

    # --- checks before anything moves -------------------------------------------------

    async def _check_request(self, entry: AxisEntry, request: IdentifyRequest) -> int:
        """Refusals (422 naming the limit, 409 for state); returns the test distance."""
        limits = await self._bench.limits(entry.info.id)
        if request.max_pwm > limits.max_pwm:
            raise InvalidArgumentError(
                "max_pwm",
                f"max_pwm {request.max_pwm} exceeds your bench limit of ±{limits.max_pwm}",
            )
        if request.max_distance_counts > limits.max_distance_counts:
            raise InvalidArgumentError(
                "max_distance_counts",
                f"max_distance_counts {request.max_distance_counts} exceeds your bench limit "
                f"of ±{limits.max_distance_counts} counts",
            )
        if request.max_distance_counts < IDENT_MIN_DISTANCE:
            raise InvalidArgumentError(
                "max_distance_counts",
                f"max_distance_counts {request.max_distance_counts} is too small to identify "
                f"the axis: at least {IDENT_MIN_DISTANCE} counts",
            )
        distance = request.distance or min(DEFAULT_TEST_DISTANCE, request.max_distance_counts // 2)
        if distance > request.max_distance_counts:
            raise InvalidArgumentError(
                "distance",
                f"distance {distance} exceeds your limit max_distance_counts of "
                f"±{request.max_distance_counts}",
            )
        self._check_idle(entry)
        return distance

    def _check_idle(self, entry: AxisEntry) -> None:
        if entry.info.id in self._bench._active:
            raise DeviceRefusedError("a test is already running on this axis")
        if entry.latest is None or self._hub.link_status(entry.link.id).state != "connected":
            raise DeviceRefusedError("the axis is not connected: no telemetry")
        flags = entry.latest.flags
        # SLAP2: a move or velocity mode; Z1100: a running motor.
        if flags.get("move") or flags.get("vm") or flags.get("running"):
            raise DeviceRefusedError("the axis is moving: wait until it stands still")

    def _current_gains(self, entry: AxisEntry) -> Gains:
        values = entry.device_values
        try:
            return Gains(values["kp"], values["ki"], values["kd"])
        except KeyError:
            raise DeviceRefusedError("the axis' gains are not read yet") from None

    def _spec(self, entry: AxisEntry, test: TestKind, distance: int, latency_s: float) -> MoveSpec:
        values = entry.device_values
        if test == "position_step":
            velocity, acceleration = VELOCITY_MAX, ACCELERATION_MAX
        else:
            velocity, acceleration = values.get("velocity", 0), values.get("acceleration", 0)
            if velocity == 0 or acceleration == 0:
                raise DeviceRefusedError("the axis' velocity or acceleration is 0: no move")
        return MoveSpec(
            distance=distance,
            velocity=velocity,
            acceleration=acceleration,
            band=values.get("inpos_window", 5),
            inpos_ticks=values.get("inpos_time", 50),
            latency_s=latency_s,
        )

    # --- identify ---------------------------------------------------------------------

    async def identify(self, axis_id: str, request: IdentifyRequest) -> dict[str, Any]:
        """Identify the plant within the user's limits and propose gains (see module doc)."""
        entry = self._check_device(axis_id)
        async with self._lock(axis_id):  # acquired at once: a second call is refused
            await self._hub.take_over(entry)  # the demo autopilot lets go, moves end
            self._generations[axis_id] = entry.stop_generation
            if self._is_z1100(entry):
                return await self._identify_z1100(entry, request)
            distance = await self._check_request(entry, request)
            current = self._current_gains(entry)
            session = self._session(axis_id)
            session.request = request
            session.proposal = session.proposal_dict = session.result = session.model = None
            session.identification_run_id = None
            self._set(session, "identifying", "identifying the plant (open-loop PWM staircase)")
            start = self._position(entry.latest)
            try:
                proposal = await self._identify(entry, session, request, distance, current)
            except asyncio.CancelledError:
                await self._safe_stop(entry)
                self._set(session, "failed", "cancelled: the axis was stopped")
                raise
            except (DriverError, ValueError) as exc:
                await self._safe_stop(entry)
                back = await self._return_after_failure(entry, start, request, self._move_back)
                message = f"identification failed: {exc}; axis stopped{back}"
                self._set(session, "failed", message)
                if isinstance(exc, InvalidArgumentError):
                    raise InvalidArgumentError(exc.field, message) from exc
                if isinstance(exc, LinkDownError | DeviceTimeoutError):
                    raise type(exc)(message) from exc
                raise DeviceRefusedError(message) from exc
            return proposal

    async def _identify_z1100(self, entry: AxisEntry, request: IdentifyRequest) -> dict[str, Any]:
        distance = await self._z1100.check_request(entry, request)
        session = self._session(entry.info.id)
        session.request = request
        session.proposal = session.proposal_dict = session.result = session.model = None
        session.identification_run_id = None
        self._set(session, "identifying", "identifying the plant (closed-loop move, gains in use)")
        start = self._position(entry.latest)
        try:
            body = await self._z1100.identify(entry, session, request, distance)
        except asyncio.CancelledError:
            await self._safe_stop(entry)
            self._set(session, "failed", "cancelled: the axis was stopped")
            raise
        except (DriverError, ValueError) as exc:
            await self._safe_stop(entry)
            back = await self._return_after_failure(
                entry, start, request, lambda e, target: self._z1100.return_to(e, round(target))
            )
            message = f"identification failed: {exc}; axis stopped{back}"
            self._set(session, "failed", message)
            if isinstance(exc, InvalidArgumentError):
                raise InvalidArgumentError(exc.field, message) from exc
            if isinstance(exc, LinkDownError | DeviceTimeoutError):
                raise type(exc)(message) from exc
            raise DeviceRefusedError(message) from exc
        g, c = body["gains"], body["current_gains"]
        self._set(
            session,
            "proposed",
            f"proposed KABH {g['kabh_k']}/{g['kabh_a']}/{g['kabh_b']} KABD "
            f"{g['kabd_k']}/{g['kabd_a']}/{g['kabd_b']} (now KABH "
            f"{c['kabh_k']}/{c['kabh_a']}/{c['kabh_b']})",
        )
        return body

    async def _identify(
        self,
        entry: AxisEntry,
        session: _Session,
        request: IdentifyRequest,
        distance: int,
        current: Gains,
    ) -> dict[str, Any]:
        axis_id = entry.info.id
        start = self._position(entry.latest)
        attempts: list[tuple[PlantModel, float, int, str]] = []
        for attempt in range(IDENT_ATTEMPTS):
            model, latency, travel, run_id = await self._identify_once(entry, request, start)
            session.identification_run_id = run_id
            attempts.append((model, latency, travel, run_id))
            doubt = model_doubt(model, travel)
            self._hub.on_event(
                "info" if doubt is None else "warning",
                axis_id,
                f"auto-tune: model K={model.gain:.0f} counts/s per PWM, tau="
                f"{model.tau_s * 1000:.1f} ms, friction {model.friction_pwm:.1f} PWM (rms "
                f"{model.rms_error_counts:.1f} counts)" + (f": {doubt}" if doubt else ""),
            )
            await self._return_to(entry, start, model, current)
            if doubt is None or attempt + 1 == IDENT_ATTEMPTS:
                break
        model, latency, travel, run_id = min(
            attempts, key=lambda a: (model_doubt(a[0], a[2]) is not None, a[0].rms_error_counts)
        )
        session.model = model.to_dict()
        warnings = [] if model_doubt(model, travel) is None else [str(model_doubt(model, travel))]
        spec = self._spec(entry, request.test, request.direction * distance, latency)
        proposal = await asyncio.to_thread(
            propose_gains,
            model,
            spec,
            request.response,
            current,
            max_excursion=request.max_distance_counts,
        )
        body = proposal.to_dict()
        body["identification_run_id"] = run_id
        body["identification_run_ids"] = [a[3] for a in attempts]
        body["travel_counts"] = travel
        body["warnings"] = warnings
        body["baseline_possible"] = proposal.default_excursion <= request.max_distance_counts
        session.proposal = proposal
        session.proposal_dict = body
        session.device_settings = {
            k: v
            for k, v in entry.device_values.items()
            if k in ("kp", "ki", "kd", "velocity", "acceleration", "inpos_window", "inpos_time")
        }
        self._set(
            session,
            "proposed",
            f"proposed kp={proposal.gains.kp} ki={proposal.gains.ki} kd={proposal.gains.kd} "
            f"(now kp={current.kp} ki={current.ki} kd={current.kd})",
        )
        return body

    async def _identify_once(
        self, entry: AxisEntry, request: IdentifyRequest, start: float
    ) -> tuple[PlantModel, float, int, str]:
        """One recorded staircase and its fit: (model, command latency, travel, run id)."""
        status_now = self._hub.link_status(entry.link.id)
        slowdown = 1.0
        if status_now.rate_hz > 0 and status_now.wire_limit_hz > 0:
            ratio = status_now.wire_limit_hz / status_now.rate_hz
            slowdown = min(MAX_SLOWDOWN, max(1.0, ratio))
        baud = entry.link.baud or 19200
        rss_check = not entry.device_values.get("syscon", 0) & UCON_BIT
        run = _IdentificationRun(self._bench, entry, start, request.max_pwm)
        await run.open(self._clock)
        status, message = "incomplete", "identification failed"
        extra: dict[str, Any] = {"timing": {"baud": baud, "slowdown": slowdown}}
        try:
            for _ in range(2):  # the shaft at rest before the first step
                await self._next_sample(entry)
            schedule, round_trips, travel = await self._staircase(entry, request, start, run)
            status, message = "complete", ""
            extra["schedule"] = [[round(t, 6), u] for t, u in schedule]
            extra["travel_counts"] = travel
        finally:
            await run.close(status, message, extra)
        index = run.columns.index("position")
        rows = [row for row in run.samples if row[index] is not None]
        times, positions, effective = align_identification(
            [row[0] for row in rows],
            [row[index] for row in rows],
            schedule,
            baud=baud,
            rss_check=rss_check,
            slowdown=slowdown,
            commands_latched=isinstance(getattr(entry, "driver", None), CommandClock),
        )
        try:
            # the model is symmetric: a negative staircase is fitted mirrored
            sign = request.direction
            model = await asyncio.to_thread(
                fit_plant,
                times,
                [sign * p for p in positions],
                [(t, sign * u) for t, u in effective],
            )
        except ValueError as exc:
            raise InvalidArgumentError("max_pwm", f"{exc} (max_pwm {request.max_pwm})") from None
        # A bench test stamps t0 before sending its trigger: its round trip less the
        # part after the command took effect.
        tail = (_COMMAND_TAIL_CHARS + (_RSS_CHECK_CHARS if rss_check else 0)) * 10.0 / baud
        trips = sorted(round_trips)
        latency = max(0.0, trips[len(trips) // 2] - tail * slowdown)
        extra["model"] = model.to_dict()
        return model, latency, travel, run.run_id

    async def _command(self, entry: AxisEntry, name: str, args: dict[str, int]) -> float:
        """Send a command through the hub (validated); returns its round trip."""
        sent = self._clock()
        # A user's STOP during identification or verification ends the sequence:
        # the hub refuses every later step (stop generation), nothing moves again.
        await self._hub.command(
            entry.info.id,
            name,
            args,
            origin="autotune",
            stop_generation=self._generations.get(entry.info.id),
        )
        return self._clock() - sent

    def _command_moment(self, entry: AxisEntry) -> float:
        """When the last command took effect: the driver's latch estimate where it
        has one (``CommandClock``), else now (``align_identification`` corrects it)."""
        driver = getattr(entry, "driver", None)
        if isinstance(driver, CommandClock) and driver.last_command_latch_s is not None:
            return driver.last_command_latch_s
        return self._clock()

    async def _staircase(
        self, entry: AxisEntry, request: IdentifyRequest, start: float, run: _IdentificationRun
    ) -> tuple[list[tuple[float, int]], list[float], int]:
        """PWM levels 2, 3, 4, 6, 9 ... up to max_pwm, each for ``IDENT_DWELL_S``, then
        PWM 0 (the bridge shorts the motor: it brakes) until the shaft stands still,
        then ``st``. It brakes at once when the travel plus ``IDENT_STOP_MARGIN_S`` at
        the present speed could pass ``IDENT_TRAVEL_FRACTION`` of max_distance, and
        ends after the level that passed ``IDENT_DONE_FRACTION`` of it.
        Returns the (return time, PWM) schedule, the command round trips and the travel.
        """
        budget = IDENT_TRAVEL_FRACTION * request.max_distance_counts
        schedule: list[tuple[float, int]] = []
        round_trips: list[float] = []
        u = min(IDENT_START_PWM, request.max_pwm)
        began = self._clock()
        last = entry.latest
        travel = 0.0
        while True:
            signed = request.direction * u
            round_trips.append(await self._command(entry, "open_loop_pwm", {"pwm": signed}))
            schedule.append((self._command_moment(entry), signed))
            run.progress(f"PWM {u}, travel {round(travel)} counts")
            level_end = self._clock() + IDENT_DWELL_S
            brake = False
            while not brake and self._clock() < level_end:
                sample = await self._sample_before(entry, level_end)
                if sample is None:
                    break
                position = self._position(sample)
                travel = abs(position - start)
                speed, gap = 0.0, 0.05
                if last is not None and sample.t > last.t:
                    gap = sample.t - last.t
                    speed = abs(position - self._position(last)) / gap
                last = sample
                brake = travel + speed * (IDENT_STOP_MARGIN_S + gap) >= budget
            if (
                brake
                or u >= request.max_pwm
                or travel >= IDENT_DONE_FRACTION * budget
                or self._clock() - began >= IDENT_MAX_S
            ):
                break
            u = min(request.max_pwm, max(u + 1, round(u * IDENT_STEP_FACTOR)))
        round_trips.append(await self._command(entry, "open_loop_pwm", {"pwm": 0}))
        schedule.append((self._command_moment(entry), 0))
        still_since: float | None = None
        previous = self._position(entry.latest)
        deadline = self._clock() + 1.0
        while self._clock() < deadline:
            sample = await self._next_sample(entry)
            position = self._position(sample)
            if position == previous:
                still_since = still_since or sample.t
                if sample.t - still_since >= 0.15:
                    break
            else:
                still_since = None
            previous = position
        await self._command(entry, "stop", {})
        return schedule, round_trips, round(abs(self._position(entry.latest) - start))

    async def _return_to(
        self, entry: AxisEntry, target: float, model: PlantModel, gains: Gains
    ) -> None:
        """Move back to ``target`` with ``gains`` if the model says they hold the axis."""
        position = self._position(entry.latest)
        distance = round(target - position)
        if distance == 0:
            await self._command(entry, "position_mode", {})
            return
        spec = replace(self._spec(entry, "move", distance, 0.0), horizon_s=RETURN_HORIZON_S)
        if not _score(model, gains, spec).settled:
            self._hub.on_event(
                "warning",
                entry.info.id,
                "auto-tune: the model predicts the current gains do not settle: the axis "
                "stays stopped where it is",
            )
            return
        await self._move_and_wait(entry, round(target), spec.profile_time_s())

    async def _move_and_wait(self, entry: AxisEntry, target: int, profile_s: float) -> None:
        latest = entry.latest
        # The line is devoted to the axis for the move too (docs/capture.md): its end is
        # seen at once, and a host slow to poll two modules cannot starve the wait.
        async with capture_of(entry.driver, reason="auto-tune move"):
            if latest is None or not latest.flags.get("pm"):
                await self._command(entry, "position_mode", {})
            await self._command(entry, "move_absolute", {"position": target})
            deadline = self._clock() + profile_s + SETTLE_TIMEOUT_S
            await asyncio.sleep(0.1)
            while self._clock() < deadline:
                sample = await self._next_sample(entry)
                if sample.flags.get("inpos") and not sample.flags.get("move"):
                    return
        raise DriverError(f"the axis did not settle at {target} within {SETTLE_TIMEOUT_S} s")

    async def _move_back(self, entry: AxisEntry, target: float) -> None:
        """SLAP2: hold (pm) and move to ``target`` with the axis' own profile."""
        distance = round(target - self._position(entry.latest)) or 1
        spec = self._spec(entry, "move", distance, 0.0)
        await self._move_and_wait(entry, round(target), spec.profile_time_s())

    async def _return_after_failure(
        self,
        entry: AxisEntry,
        start: float,
        request: IdentifyRequest,
        move_back: Callable[[AxisEntry, float], Coroutine[Any, Any, None]],
    ) -> str:
        """After a failed identification: move the axis back to ``start`` with the gains
        in use (they held it there before), unless the user pressed STOP, the link is
        down or the way back is longer than the user's limit. Returns what happened,
        as the tail of the failure message."""
        axis_id = entry.info.id
        if self._generations.get(axis_id) != entry.stop_generation:
            return " (STOP: it stays where it is)"
        if self._hub.link_status(entry.link.id).state != "connected" or entry.latest is None:
            return " (the link is down: it stays where it is)"
        try:
            away = abs(self._position(entry.latest) - start)
        except DriverError:
            return " (no position: it stays where it is)"
        if away < 1:
            return " at its start"
        if away > request.max_distance_counts * 1.05 + 100:
            return (
                f" {away:.0f} counts from its start, more than your max_distance_counts: "
                "it stays where it is"
            )
        try:
            await move_back(entry, start)
        except DriverError as exc:
            await self._safe_stop(entry)
            return f"; returning to its start failed ({exc}): it stays where it is"
        return f", then returned to its start ({away:.0f} counts back)"

    async def _safe_stop(self, entry: AxisEntry) -> None:
        try:
            await entry.driver.stop()
        except DriverError:
            entry.stop_on_reconnect = True
            self._hub.on_event(
                "error", entry.info.id, "auto-tune: stop failed; repeated when the link is back"
            )

    # --- accept and verify ------------------------------------------------------------

    async def accept(self, axis_id: str) -> dict[str, Any]:
        """Baseline test (previous gains), write the proposal, verification test."""
        entry = self._check_device(axis_id)
        lock = self._lock(axis_id)
        session = self._session(axis_id)
        # From now on a user's STOP ends the verification (see _command).
        self._generations[axis_id] = entry.stop_generation
        if self._is_z1100(entry):
            return await self._accept_z1100(entry, session, lock)
        proposal = session.proposal
        if session.state != "proposed" or proposal is None or session.request is None:
            raise DeviceRefusedError("no proposal to accept: run identify first")
        changed = {
            k: (v, entry.device_values.get(k))
            for k, v in session.device_settings.items()
            if entry.device_values.get(k) != v
        }
        if changed:
            listing = ", ".join(f"{k} {now} (was {was})" for k, (was, now) in changed.items())
            raise DeviceRefusedError(
                f"settings changed since the proposal ({listing}): identify again"
            )
        self._check_idle(entry)
        async with lock:
            previous = proposal.current_gains.to_dict()
            result = await self._guarded_verify(
                entry,
                session,
                self._verify(entry, session, proposal),
                previous=previous,
                restore=lambda: self._hub.write_params(axis_id, previous),
            )
            if result.get("stopped"):
                return result
            tuned_settle = result["measured"].get("settling_time_s")
            base_settle = (result["baseline_measured"] or {}).get("settling_time_s")

            def ms(value: float | None) -> str:
                return "never" if value is None else f"{value * 1000:.0f} ms"

            self._set(
                session,
                "verified",
                f"verified: {result['verdict']} (settles in {ms(tuned_settle)}; with the "
                f"previous gains {ms(base_settle)})",
            )
            return result

    async def _guarded_verify(
        self,
        entry: AxisEntry,
        session: _Session,
        verification: Coroutine[Any, Any, dict[str, Any]],
        *,
        previous: dict[str, int],
        restore: Callable[[], Coroutine[Any, Any, dict[str, int]]],
    ) -> dict[str, Any]:
        """Run a device's verification; on any failure stop the axis, put the previous
        gains back (the new ones were not verified) and say so.

        A user's STOP is not an error of the server: the answer is a normal result
        with ``stopped: true``, ``message`` and ``gains_in_force``. If the previous
        gains cannot be written back, ``unverified: true`` and the message says
        loudly that the new gains are in force unverified (``revert`` puts them
        back). Other failures answer an error naming the same."""
        axis_id = entry.info.id
        self._set(session, "verifying", "baseline and verification tests")
        try:
            result = await verification
        except asyncio.CancelledError:
            await self._safe_stop(entry)
            with contextlib.suppress(DriverError):
                await restore()
            self._set(session, "failed", "cancelled: the axis was stopped")
            raise
        except DriverError as exc:
            stopped = self._generations.get(axis_id) != entry.stop_generation
            await self._safe_stop(entry)
            unverified = False
            restored_note = "the previous gains are in force again"
            if any(entry.device_values.get(k) != v for k, v in previous.items()):
                try:
                    await restore()
                except DriverError as restore_exc:
                    unverified = True
                    restored_note = (
                        f"THE NEW GAINS ARE IN FORCE, UNVERIFIED: writing back the previous "
                        f"gains failed ({restore_exc}); press Revert when the axis is back"
                    )
            cause = "STOP was pressed" if stopped else str(exc)
            message = f"verification ended: {cause}; axis stopped; {restored_note}"
            self._set(session, "failed", message)
            body = {
                "stopped": stopped,
                "unverified": unverified,
                "message": message,
                "verdict": "stopped" if stopped else "failed",
                "previous_gains": previous,
                "gains_in_force": {k: entry.device_values.get(k) for k in previous},
            }
            session.result = body
            if stopped:
                return body
            if isinstance(exc, LinkDownError):
                raise LinkDownError(message) from exc
            if isinstance(exc, DeviceTimeoutError):
                raise DeviceTimeoutError(message) from exc
            raise DeviceRefusedError(message) from exc
        session.result = result
        return result

    async def _accept_z1100(
        self, entry: AxisEntry, session: _Session, lock: asyncio.Lock
    ) -> dict[str, Any]:
        if session.state != "proposed":
            raise DeviceRefusedError("no proposal to accept: run identify first")
        self._z1100.check_unchanged(entry, session)
        self._check_idle(entry)
        async with lock:
            previous = self._z1100.previous_gains(entry)
            result = await self._guarded_verify(
                entry,
                session,
                self._z1100.accept(entry, session),
                previous=previous,
                restore=lambda: self._z1100.revert(entry),
            )
            if result.get("stopped"):
                return result
            self._set(session, "verified", f"verified: {result['verdict']}")
            return result

    async def _run_test(
        self, entry: AxisEntry, spec: MoveSpec, kind: TestKind, note: str
    ) -> dict[str, Any]:
        limits = await self._bench.limits(entry.info.id)
        duration = min(limits.max_duration_s, spec.profile_time_s() + TEST_RECORD_S)
        started = await self._bench.start_run(
            entry.info.id,
            BenchTestRequest(kind=kind, distance=spec.distance, duration_s=duration, note=note),
        )
        run_id: str = started["id"]
        deadline = self._clock() + duration + 10.0
        while self._clock() < deadline:
            await asyncio.sleep(0.1)
            run = await self._bench.get_run_meta(run_id)  # status only: no samples
            if run["status"] != "recording":
                if run["status"] != "complete":
                    raise DriverError(f"test {run_id} {run['status']}: {run.get('message')}")
                return run
        raise DriverError(f"test {run_id} did not finish")

    async def _verify(
        self, entry: AxisEntry, session: _Session, proposal: Proposal
    ) -> dict[str, Any]:
        assert session.request is not None
        axis_id = entry.info.id
        kind = session.request.test
        spec = proposal.spec
        start = round(self._position(entry.latest))
        if not entry.latest or not entry.latest.flags.get("pm"):
            await self._command(entry, "position_mode", {})
        baseline: dict[str, Any] | None = None
        baseline_note = ""
        if proposal.default_excursion <= session.request.max_distance_counts:
            self._hub.on_event("info", axis_id, "auto-tune: baseline test with the previous gains")
            baseline = await self._run_test(
                entry, spec, kind, "auto-tune baseline (previous gains)"
            )
        else:
            baseline_note = (
                f"baseline skipped: the previous gains are predicted to travel "
                f"{proposal.default_excursion} counts, beyond your max_distance_counts"
            )
            self._hub.on_event("warning", axis_id, f"auto-tune: {baseline_note}")
        await self._hub.write_params(axis_id, proposal.gains.to_dict())
        gentle = self._spec(entry, "move", start - round(self._position(entry.latest)) or 1, 0.0)
        await self._move_and_wait(entry, start, gentle.profile_time_s())
        self._hub.on_event("info", axis_id, "auto-tune: verification test with the new gains")
        verification = await self._run_test(
            entry, spec, kind, "auto-tune verification (proposed gains)"
        )
        await self._move_and_wait(entry, start, gentle.profile_time_s())
        measured = verification.get("metrics") or {}
        baseline_measured = baseline.get("metrics") if baseline else None
        return {
            "gains": proposal.gains.to_dict(),
            "previous_gains": proposal.current_gains.to_dict(),
            "predicted": _metrics_dict(proposal.predicted),
            "measured": measured,
            "predicted_default": _metrics_dict(proposal.predicted_default),
            "baseline_measured": baseline_measured,
            "verification_run_id": verification["id"],
            "baseline_run_id": baseline["id"] if baseline else None,
            "baseline_note": baseline_note,
            "verdict": verdict(
                baseline_measured,
                measured,
                baseline_unmeasured=unmeasured(baseline),
                tuned_unmeasured=unmeasured(verification),
            ),
            "verdict_reason": unmeasured(verification) or unmeasured(baseline),
        }

    async def revert(self, axis_id: str) -> dict[str, int]:
        """Write the gains that were in use before the accepted proposal."""
        entry = self._check_device(axis_id)
        lock = self._lock(axis_id)
        session = self._session(axis_id)
        if self._is_z1100(entry):
            if session.state not in ("verified", "failed"):
                raise DeviceRefusedError("nothing to revert: no accepted proposal")
            async with lock:
                written = await self._z1100.revert(entry)
                self._set(session, "idle", "reverted to the previous KABH/KABD")
                return written
        if session.proposal is None or session.state not in ("verified", "failed"):
            raise DeviceRefusedError("nothing to revert: no accepted proposal")
        async with lock:
            gains = session.proposal.current_gains.to_dict()
            written = await self._hub.write_params(axis_id, gains)
            self._set(
                session, "idle", f"reverted to kp={gains['kp']} ki={gains['ki']} kd={gains['kd']}"
            )
            return written
