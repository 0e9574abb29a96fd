"""SLAP2: the firmware's PID law, its closed loop on the identified model, the
identification's excitation and timing, and the limits (docs/autotune.md).

**The SLAP2 manual does not give the scaling of its PID law**; this is the law the
simulator implements (``devices/slap2/sim/controller.py``, docs/simulator.md), every 841.5 us tick::

    u = (16 kp e + ki S + 32 kd (e - e_prev)) >> 12,  |ki S| <= 255 << 12,  |u| <= 255

``PidLaw`` is that arithmetic, one call per tick (the reference; a test checks it
against the simulator tick for tick). ``simulate_response`` runs it inlined (it runs
some 10^6 ticks per gain search) together with the trapezoid generator, the
in-position logic, count quantisation and ``FrictionMotor``: it is nonlinear (integer
arithmetic, clamps, stiction), so a linear simulation (``scipy.signal.dlsim``) cannot
replace it; the linear view of the same law is ``slap2_loop_for`` (below)
(margins, Bode, linear step), which ``Slap2Law.loop`` uses.

Units: counts, counts/s, PWM -255..255, seconds.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final, Literal

import control
import numpy as np

from servotune.bench.metrics import compute_metrics
from servotune.devices.slap2 import NAME
from servotune.devices.slap2.codec import (
    ACCELERATION_MAX,
    COUNTS_S2_PER_SA,
    COUNTS_S_PER_SV,
    GAIN_MAX,
    PWM_MAX,
    TICK_S,
    VELOCITY_MAX,
)
from servotune.devices.slap2.injection import Slap2Injection
from servotune.schema import ControllerLaw, LawGainSet, LawTerm, RunMetrics
from servotune.tuning.frf import ComplexArray, FloatArray
from servotune.tuning.law import VerifyProfile
from servotune.tuning.loops import ZERO, LoopModel, MotorModel, Polynomial
from servotune.tuning.plants import FrictionMotor, IdentifiedPlant, PlantModel

__all__ = [
    "GAIN_MAX",
    "PWM_MAX",
    "TICK_S",
    "Gains",
    "MoveSpec",
    "PidLaw",
    "SimulatedResponse",
    "Slap2Law",
    "Staircase",
    "align_identification",
    "model_doubt",
    "pwm_per_count",
    "simulate_response",
]

# --- the law -------------------------------------------------------------------------
P_MUL: Final = 16
D_MUL: Final = 32
PID_SHIFT: Final = 12
I_TERM_MAX: Final = PWM_MAX << PID_SHIFT
# The same law as data, for the what-if view (``tuning.law.DeviceLaw.controller``):
# u = (16 kp e + ki S + 32 kd e - 32 kd e[-1]) / 4096, without the integer shift (the
# linear view, as ``slap2_pid_polynomials``).
CONTROLLER: Final = ControllerLaw(
    terms=[
        LawTerm(coefficient=P_MUL, gains=["kp"], signal="error"),
        LawTerm(coefficient=1, gains=["ki"], signal="error_sum"),
        LawTerm(coefficient=D_MUL, gains=["kd"], signal="error"),
        LawTerm(coefficient=-D_MUL, gains=["kd"], signal="error", delay=1),
    ],
    divisor=1 << PID_SHIFT,
    rounding="none",
    gain_sets=[LawGainSet(when="always", prefix="")],
)
SETTLED_HOLD_S: Final = 0.25  # a response counts as settled if it stays in band this long

# --- limits ----------------------------------------------------------------------------
MAX_FIT_RMS_COUNTS: Final = 10.0  # a worse fit (plus 1 % of the travel) is doubtful
IDENT_MIN_DISTANCE: Final = 400  # less travel than this identifies nothing
STAIRCASE_START_PWM: Final = 2  # the first level of the identification's staircase


@dataclass(frozen=True, slots=True)
class Gains:
    kp: int
    ki: int
    kd: int

    def to_dict(self) -> dict[str, int]:
        return {"kp": self.kp, "ki": self.ki, "kd": self.kd}


class PidLaw:
    """The firmware's PID, one ``step`` per 841.5 us tick (state: the clamped running
    sum ``S`` and the previous error). ``step(e)`` returns the PWM, -255..255."""

    __slots__ = ("_limit", "e_prev", "gains", "integral")

    def __init__(self, gains: Gains, e_prev: int = 0) -> None:
        self.gains = gains
        self._limit = I_TERM_MAX // max(gains.ki, 1)
        self.integral = 0
        self.e_prev = e_prev

    def step(self, e: int) -> int:
        g = self.gains
        self.integral = max(-self._limit, min(self._limit, self.integral + e))
        u = (P_MUL * g.kp * e + g.ki * self.integral + D_MUL * g.kd * (e - self.e_prev)) >> (
            PID_SHIFT
        )
        self.e_prev = e
        return max(-PWM_MAX, min(PWM_MAX, u))


def pwm_per_count(gains: Gains) -> float:
    """PWM change caused by a one-count step of the error (P, I and D together)."""
    return (P_MUL * gains.kp + gains.ki + D_MUL * gains.kd) / (1 << PID_SHIFT)


# =====================================================================================
# The closed loop on the model
# =====================================================================================


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

    def metrics(self) -> RunMetrics:
        """The bench's metrics of the simulated record, except the overshoot: the one
        the rule judges (``overshoot_pct``, the largest tick), not a spline's peak drawn
        between the model's exact tick positions (it rose 3e-5 pp above a 1 % limit
        the rule had kept)."""
        measured = compute_metrics(
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
        if measured.overshoot_pct is None:
            return measured
        return measured.model_copy(update={"overshoot_pct": self.overshoot_pct()})

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
    """The SLAP2 firmware (as ``devices/slap2/sim/controller.py`` implements it) running
    ``spec`` on ``model``.

    Each 841.5 us tick: sample the count, run the trapezoid generator, ``PidLaw``
    (inlined), then integrate the plant over the tick with that PWM. In pm holding at
    count 0 until the move command executes at ``spec.latency_s``. ``record=False``
    keeps only the summary (faster); the simulation stops early when the response
    runs away, or is still outside the band after ``give_up_s`` (it cannot settle
    sooner than that any more), or, with ``stop_when_settled``, has been inside the
    band for ``SETTLED_HOLD_S`` after the profile's end.
    """
    motor = FrictionMotor(model, 0.5, tick_s=TICK_S)
    kp, ki, kd = gains.kp, gains.ki, gains.kd
    limit = I_TERM_MAX // max(ki, 1)
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
        # PidLaw.step, inlined (the hot loop of the gain search)
        e = math.floor(sp + 0.5) - count
        integral += e
        if integral > limit:
            integral = limit
        elif integral < -limit:
            integral = -limit
        u = (P_MUL * kp * e + ki * integral + D_MUL * kd * (e - e_prev)) >> PID_SHIFT
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


# =====================================================================================
# The identification: excitation, timing, doubt
# =====================================================================================


@dataclass(frozen=True, slots=True)
class Staircase:
    """The open-loop PWM staircase (docs/autotune.md, "Experiment"): levels 2, 3, 4,
    6, 9 ... (x1.5, capped at ``max_pwm``), ``dwell_s`` each; it brakes (PWM 0) as soon
    as the travel plus ``stop_margin_s`` at the present speed could pass
    ``travel_fraction`` of max_distance, and ends after the level that passed
    ``done_fraction`` of that budget, at ``max_pwm`` or after ``max_s``."""

    max_pwm: int
    max_distance_counts: int
    start_pwm: int = STAIRCASE_START_PWM
    step_factor: float = 1.5
    dwell_s: float = 0.15
    max_s: float = 1.5
    stop_margin_s: float = 0.1  # latency + braking, as time at the present speed
    travel_fraction: float = 0.5
    done_fraction: float = 0.3

    @property
    def budget_counts(self) -> float:
        return self.travel_fraction * self.max_distance_counts

    def first_pwm(self) -> int:
        return min(self.start_pwm, self.max_pwm)

    def next_pwm(self, u: int) -> int:
        return min(self.max_pwm, max(u + 1, round(u * self.step_factor)))

    def must_brake(self, travel: float, speed: float, gap_s: float) -> bool:
        return travel + speed * (self.stop_margin_s + gap_s) >= self.budget_counts

    def finished(self, u: int, travel: float, elapsed_s: float, braked: bool) -> bool:
        return (
            braked
            or u >= self.max_pwm
            or travel >= self.done_fraction * self.budget_counts
            or elapsed_s >= self.max_s
        )


# Timing of the SLAP2 driver's exchanges, in characters on the wire (docs/autotune.md).
# After a command executes: the echo of its CR and the bare CR reply, then (unless the
# module replies -1UC itself) the driver's "rss" check: 4 characters echoed one by one
# (2 character times each) and a reply of about 2 digits + CR.
COMMAND_TAIL_CHARS: Final = 2
RSS_CHECK_CHARS: Final = 2 * 4 + 3


def command_tail_s(baud: int, *, rss_check: bool = True) -> float:
    """Time between a command taking effect and its return to the host, seconds."""
    return (COMMAND_TAIL_CHARS + (RSS_CHECK_CHARS if rss_check else 0)) * 10.0 / baud


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
    A command returns after its CR's echo, the bare CR reply and the driver's ``rss``
    check: it took effect ``command_tail_s`` (stretched by ``slowdown``, the ratio of
    the wire's sample rate to the achieved one: host latency per echoed character)
    before it returned, at the next 841.5 us tick, while a position reply reports the
    last tick: one tick between the two on average. With ``commands_latched`` the
    command times are already the driver's latch estimates (``CommandClock``): only
    the tick is added.
    """
    times = [float(t) for t in sample_times]
    values = [float(p) for p in positions]
    if len(times) != len(values):
        raise ValueError("sample times and positions differ in length")
    tail = 0.0 if commands_latched else command_tail_s(baud, rss_check=rss_check) * slowdown
    schedule = [(t - tail + TICK_S, float(u)) for t, u in command_returns]
    return times, values, schedule


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


# =====================================================================================
# The device behind the common interface (tuning.law.DeviceLaw)
# =====================================================================================


class Slap2Law:
    """The SLAP2 as ``tuning.law.DeviceLaw``: the PID at the firmware's tick."""

    device: Final = NAME
    law: Final[Literal["slap2_pid"]] = "slap2_pid"
    description: Final = f"PID at {TICK_S * 1e6:.1f} us"
    gain_names: Final = ("kp", "ki", "kd")
    output_limit: Final = PWM_MAX
    controller: Final = CONTROLLER
    # targets through ma, PWM through spwm (docs/frequency-response.md)
    injection: Final = Slap2Injection()

    def period_s(self, params: Mapping[str, int]) -> float:
        return TICK_S

    def linear_plant(self, model: Mapping[str, Any]) -> IdentifiedPlant:
        """The open-loop fit (``PlantModel.to_dict``) without its friction term."""
        if "gain_counts_s_per_pwm" not in model:
            raise ValueError("the identified model does not describe a slap2 plant")
        return IdentifiedPlant(
            float(model["gain_counts_s_per_pwm"]),
            float(model.get("tau_s", 0.0)),
            "auto-tune identification",
        )

    def loop(self, plant: IdentifiedPlant, params: Mapping[str, int]) -> LoopModel:
        return slap2_loop_for(plant.transfer_function(), params["kp"], params["ki"], params["kd"])

    def controller_response(
        self, frequency_hz: FloatArray, params: Mapping[str, int]
    ) -> ComplexArray | None:
        """The PID at ``z = e^{jwT}`` (T the tick), error counts -> PWM: the firmware
        arithmetic ``(16 kp + ki z/(z-1) + 32 kd (1 - 1/z)) / 4096`` that
        ``slap2_loop_for`` (below) models (and the simulator runs)."""
        kp, ki, kd = params["kp"], params["ki"], params["kd"]
        z = np.exp(2j * np.pi * np.asarray(frequency_hz, dtype=np.float64) * TICK_S)
        c = (16 * kp + ki * z / (z - 1) + 32 * kd * (1 - 1 / z)) / 4096
        return np.asarray(c, dtype=np.complex128)

    def verify_profile(self, params: Mapping[str, int]) -> VerifyProfile:
        """A position step at the maximum sv/sa (what the verification sets)."""
        return VerifyProfile(
            "position_step", VELOCITY_MAX * COUNTS_S_PER_SV, ACCELERATION_MAX * COUNTS_S2_PER_SA
        )


# =====================================================================================
# The law as a linear loop (tuning.loops.LoopModel): every 841.5 us
# ``u = (16 kp e + ki S + 32 kd (e - e_prev)) / 4096`` with ``S`` the running sum of ``e``
# including this tick, so ``C(z) = (16 kp + ki z/(z-1) + 32 kd (1 - 1/z)) / 4096``;
# ``e = setpoint - count``.
# =====================================================================================


def slap2_loop(motor: MotorModel, kp: int, ki: int, kd: int) -> LoopModel:
    """The SLAP2 PID (firmware arithmetic, above) around ``motor``."""
    return slap2_loop_for(motor.plant(), kp, ki, kd)


def slap2_loop_for(plant: control.TransferFunction, kp: int, ki: int, kd: int) -> LoopModel:
    """The SLAP2 PID around a continuous plant (counts per controller output unit)."""
    return slap2_loop_on(control.c2d(plant, TICK_S, "zoh"), kp, ki, kd)


def slap2_loop_on(plant_d: control.TransferFunction, kp: int, ki: int, kd: int) -> LoopModel:
    """The SLAP2 PID around a plant already discretised at its tick (a gain search
    discretises once)."""
    ts = TICK_S
    forward = control.tf(*slap2_pid_polynomials(kp, ki, kd), ts)
    zero = control.tf(*ZERO, ts)
    return LoopModel(forward, zero, plant_d, ts)


def slap2_pid_polynomials(kp: int, ki: int, kd: int) -> Polynomial:
    """The SLAP2 PID ``C(z) = (16 kp + ki z/(z-1) + 32 kd (z-1)/z) / 4096``."""
    if ki:
        # over the common denominator z (z-1)
        num = [16 * kp + ki + 32 * kd, -16 * kp - 64 * kd, 32 * kd]
        den = [4096.0, -4096.0, 0.0]
    else:
        # ki = 0: the running sum is multiplied by 0, there is no integrator - and no
        # factor z - 1 in numerator and denominator to read as a pole on the circle
        num = [16 * kp + 32 * kd, -32 * kd]
        den = [4096.0, 0.0]
    return np.asarray(num, dtype=np.float64), np.asarray(den, dtype=np.float64)
