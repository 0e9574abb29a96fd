"""Z1100: the chip's K/A/B servo law, its closed loop on the identified model, the
closed-loop fit, and the limits (docs/autotune.md, "Z1100").

**The Z1100 manual gives no law**; this is the simulator's (``devices/z1100/sim/servo.py``,
docs/z1100-simulator.md), every Stm x 32 us sample::

    u = K (16 e + A (e - e[-32])) - B (y - y[-32]),  pwm = clamp(trunc(u / 64), +-255)

with KABH while the profile runs and KABD at rest. ``KabLaw`` is that arithmetic, one
call per sample (the reference; a test checks it against the chip simulator sample
for sample). ``simulate_move`` runs it at a coarser step (``COARSE`` samples, the
32-sample window becoming 32/COARSE steps) on ``Z1100Plant``, inlined: like the
SLAP2's loop it is nonlinear (integer arithmetic, clamps, the gain switch at the
profile's end), so a linear simulation cannot replace it; its linear view is
``z1100_loop_for`` (below), which ``Z1100Law.loop`` uses.

Units: counts, counts/s, duty -1..1, seconds.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final, Literal

import control
import numpy as np

from servotune.bench.metrics import compute_metrics
from servotune.devices.z1100 import NAME
from servotune.devices.z1100.frame import STM_TICK_S
from servotune.schema import ControllerLaw, LawGainSet, LawTerm, RunMetrics
from servotune.tuning.frf import ComplexArray, FloatArray
from servotune.tuning.identify import fit_closed_loop
from servotune.tuning.law import VerifyProfile
from servotune.tuning.loops import LoopModel, MotorModel, Polynomial
from servotune.tuning.plants import IdentifiedPlant, Z1100Plant

# --- the law (devices/z1100/sim/servo.py; assumed, the manual gives none) --------------------
SAMPLE_UNIT_S: Final = STM_TICK_S  # one sample is Stm x 32 us (the frame's fact)
WINDOW: Final = 32  # samples of the derivative difference
ERROR_WEIGHT: Final = 16
OUTPUT_DIVISOR: Final = 64
PWM_FULL_SCALE: Final = 255
# The same law as data, for the what-if view (``tuning.law.DeviceLaw.controller``):
# u = 16 K e + K A e - K A e[-32] - B y + B y[-32], pwm = trunc(u / 64).
CONTROLLER: Final = ControllerLaw(
    terms=[
        LawTerm(coefficient=ERROR_WEIGHT, gains=["k"], signal="error"),
        LawTerm(coefficient=1, gains=["k", "a"], signal="error"),
        LawTerm(coefficient=-1, gains=["k", "a"], signal="error", delay=WINDOW),
        LawTerm(coefficient=-1, gains=["b"], signal="position"),
        LawTerm(coefficient=1, gains=["b"], signal="position", delay=WINDOW),
    ],
    divisor=OUTPUT_DIVISOR,
    rounding="trunc",
    gain_sets=[
        LawGainSet(when="moving", prefix="kabh_"),
        LawGainSet(when="holding", prefix="kabd_"),
    ],
)
COARSE: Final = 4  # chip samples per simulation step (window 32 -> 8 steps)
KABD_FRACTION: Final = 0.75  # KABD = KABH with K x 3/4 (as the demo's integrator did)
HOLD_S: Final = 0.1  # simulated after the profile's end

# --- limits and the fit ------------------------------------------------------------------
BAND_COUNTS: Final = 20.0  # the bench's move band (devices/z1100/link.py)
MAX_FIT_RMS_COUNTS: Final = 10.0  # a worse fit (and > 15 % of the peak error) is flagged
FIT_STARTS: Final = 2  # least-squares runs from the best points of the start grid
FIT_TAIL_S: Final = 0.3  # samples fitted after the profile's end
IDENT_MIN_DISTANCE: Final = 400


@dataclass(frozen=True, slots=True)
class Kab:
    k: int
    a: int
    b: int

    def kabd(self) -> Kab:
        return Kab(max(1, round(self.k * KABD_FRACTION)), self.a, self.b)


def kab_dict(kabh: Kab, kabd: Kab) -> dict[str, int]:
    """The device parameters of a KABH/KABD pair."""
    return {
        "kabh_k": kabh.k,
        "kabh_a": kabh.a,
        "kabh_b": kabh.b,
        "kabd_k": kabd.k,
        "kabd_a": kabd.a,
        "kabd_b": kabd.b,
    }


class KabLaw:
    """The chip's law, one ``step`` per sample: the 32-sample windows of error and
    position, KABH while the profile runs, KABD at rest. Returns the PWM, -255..255."""

    __slots__ = ("_e", "_i", "_y", "kabd", "kabh")

    def __init__(self, kabh: Kab, kabd: Kab, window: int = WINDOW) -> None:
        self.kabh = kabh
        self.kabd = kabd
        self._e = [0] * window
        self._y = [0] * window
        self._i = 0

    def step(self, e: int, y: int, running: bool) -> int:
        i = self._i
        de = e - self._e[i]
        dy = y - self._y[i]
        self._e[i] = e
        self._y[i] = y
        self._i = i + 1 if i + 1 < len(self._e) else 0
        g = self.kabh if running else self.kabd
        u = g.k * (ERROR_WEIGHT * e + g.a * de) - g.b * dy
        return max(-PWM_FULL_SCALE, min(PWM_FULL_SCALE, int(u / OUTPUT_DIVISOR)))


@dataclass(frozen=True, slots=True)
class MoveProfile:
    distance: int
    vmax: float  # counts/s
    acc: float  # counts/s^2
    stm: int = 1

    def time_s(self) -> float:
        """Duration of the trapezoid (or triangle) profile."""
        d, v, a = abs(self.distance), abs(self.vmax), abs(self.acc)
        if v * v / a >= d:
            return 2 * math.sqrt(d / a)
        return d / v + v / a

    def positive(self) -> MoveProfile:
        """The profile with a positive distance (the model is symmetric)."""
        return MoveProfile(abs(self.distance), self.vmax, self.acc, self.stm)


@dataclass(slots=True)
class SimulatedMove:
    t: list[float]
    position: list[float]
    error: list[float]
    moving: list[bool]
    peak_duty: float


def simulate_move(
    plant: Z1100Plant,
    kabh: Kab,
    kabd: Kab,
    profile: MoveProfile,
    *,
    hold_s: float = HOLD_S,
    record_every: int = 4,
    coarse: int = COARSE,
) -> SimulatedMove:
    """A go-to-target move from rest at 0 by ``profile.distance``, then ``hold_s``.

    The profile generator advances per chip sample (the chip's trapezoid rule); the law
    runs once per step of ``coarse`` samples, on the first sample's reference against
    the position at the step's start (the chip's timing), with the derivative window
    in steps (32 / coarse), and its duty is held for the whole step. Checked against
    the chip simulator in tests/device/z1100/test_autotune.py: coarse 4 and 1 agree with it
    equally well (about 2 counts rms on a 10 000-count move). Records every
    ``record_every`` steps: time, position, following error (reference - position).
    """
    h = max(1, profile.stm) * SAMPLE_UNIT_S * coarse
    window = max(1, WINDOW // coarse)
    ts = h / coarse  # the chip's sample: the profile advances per sample, as on the chip
    vmax = abs(profile.vmax) * ts
    acc = abs(profile.acc) * ts * ts
    goal = float(profile.distance)
    sign = 1.0 if goal >= 0 else -1.0
    decay = -math.expm1(-h / plant.tau_s)
    lag = plant.tau_s * decay
    gain = plant.gain
    x = 0.0
    v = 0.0
    ref = 0.0
    ref_v = 0.0
    running = True
    e_hist = [0] * window
    y_hist = [0] * window
    hi = 0
    end_steps: int | None = None
    hold_steps = int(hold_s / h)
    out_t: list[float] = []
    out_x: list[float] = []
    out_e: list[float] = []
    out_m: list[bool] = []
    peak = 0.0
    n = 0
    max_steps = int(10.0 / h)
    while n < max_steps:
        duty = 0.0
        for sub in range(coarse):  # the profile advances per chip sample
            if running:
                remaining = goal - ref
                dist = abs(remaining)
                speed = min(abs(ref_v) + acc, vmax, math.sqrt(2.0 * acc * dist))
                if speed >= dist:
                    ref = goal
                    ref_v = 0.0
                    running = False
                    end_steps = n
                else:
                    ref_v = speed * sign
                    ref += ref_v
            if sub:
                continue
            # KabLaw.step, inlined, once per step, one sample after the step's start (as
            # on the chip: the reference of this sample against the position at its start)
            y = math.floor(x)
            e = math.floor(ref + 0.5) - y
            de = e - e_hist[hi]
            dy = y - y_hist[hi]
            e_hist[hi] = e
            y_hist[hi] = y
            hi = hi + 1 if hi + 1 < window else 0
            g = kabh if running else kabd
            u = g.k * (ERROR_WEIGHT * e + g.a * de) - g.b * dy
            pwm = int(u / OUTPUT_DIVISOR)
            if pwm > PWM_FULL_SCALE:
                pwm = PWM_FULL_SCALE
            elif pwm < -PWM_FULL_SCALE:
                pwm = -PWM_FULL_SCALE
            duty = pwm / PWM_FULL_SCALE
            if abs(duty) > peak:
                peak = abs(duty)
        v_inf = gain * duty
        x += v_inf * h + (v - v_inf) * lag
        v += (v_inf - v) * decay
        n += 1
        if n % record_every == 0:
            out_t.append(n * h)
            out_x.append(x)
            out_e.append(ref - x)
            out_m.append(running)
        if end_steps is not None and n - end_steps >= hold_steps:
            break
    return SimulatedMove(out_t, out_x, out_e, out_m, peak)


def move_metrics(sim: SimulatedMove, distance: int, band: float = BAND_COUNTS) -> RunMetrics:
    return compute_metrics(
        sim.t,
        sim.position,
        t0_s=0.0,
        y0=0.0,
        y_final=float(distance),
        band=band,
        following_error=list(sim.error),
        flags={"running": sim.moving},
    )


def fit_plant_closed_loop(
    times: Sequence[float],
    errors: Sequence[float],
    kabh: Kab,
    kabd: Kab,
    profile: MoveProfile,
) -> Z1100Plant:
    """Fit gain, tau and a delay to the following error of a move with known gains.

    ``times``: seconds after the move's trigger was sent; ``errors``: the chip's
    following error (profile - position, sign of the move). The delay (0..60 ms) is when
    the move started after the trigger time stamp. Starts: the gain from the largest
    error (the duty it takes to follow at the peak speed), a 3 x 4 x 4 grid (gain x
    0.5/1/2, tau 3/10/30/100 ms, delay 0/10/20/40 ms); ``tuning.identify.fit_closed_loop``
    (least squares over log gain, log tau and the delay) from the ``FIT_STARTS`` best.
    """
    if len(times) != len(errors):
        raise ValueError("times and errors differ in length")
    # the move and FIT_TAIL_S after it (later samples hold still and cost time)
    end = profile.time_s() + FIT_TAIL_S
    kept = [(t, e) for t, e in zip(times, errors, strict=True) if t <= end]
    times, errors = [t for t, _ in kept], [e for _, e in kept]
    if len(times) < 5:
        raise ValueError("too few samples to fit a plant model")
    peak_e = max(abs(e) for e in errors)
    if peak_e < 1:
        raise ValueError("no following error recorded: cannot identify the plant")
    peak_v = min(abs(profile.vmax), math.sqrt(abs(profile.acc) * abs(profile.distance)))
    window_counts = peak_v * WINDOW * max(1, profile.stm) * SAMPLE_UNIT_S
    u0 = kabh.k * ERROR_WEIGHT * peak_e - kabh.b * window_counts
    duty0 = u0 / OUTPUT_DIVISOR / PWM_FULL_SCALE
    gain0 = peak_v / min(1.0, max(duty0, 0.02))
    horizon = max(times) + 0.02
    hold = max(0.02, horizon - profile.time_s())

    def simulate(gain: float, tau: float) -> tuple[list[float], list[float]]:
        sim = simulate_move(Z1100Plant(gain, tau), kabh, kabd, profile, hold_s=hold)
        return sim.t, sim.error

    starts = [
        (gain0 * gain_factor, tau0, delay0)
        for gain_factor in (0.5, 1.0, 2.0)
        for tau0 in (0.003, 0.01, 0.03, 0.1)
        for delay0 in (0.0, 0.01, 0.02, 0.04)
    ]
    fit = fit_closed_loop(times, errors, simulate, starts, keep=FIT_STARTS)
    return Z1100Plant(
        fit.gain, fit.tau_s, rms_error_counts=fit.rms, samples=fit.samples, delay_s=fit.delay_s
    )


# =====================================================================================
# The device behind the common interface (tuning.law.DeviceLaw)
# =====================================================================================


class Z1100Law:
    """The Z1100 as ``tuning.law.DeviceLaw``: K/A/B every Stm x 32 us, modelled
    with its hold gains (KABD): the set in force when the axis stands, which is where
    a frequency response around a held position is."""

    device: Final = NAME
    law: Final[Literal["z1100_kab"]] = "z1100_kab"
    description: Final = "KABD (hold) gains"
    gain_names: Final = ("kabh_k", "kabh_a", "kabh_b", "kabd_k", "kabd_a", "kabd_b")
    output_limit: Final = PWM_FULL_SCALE
    controller: Final = CONTROLLER
    # go-to targets only, through the Z1100's own profile: nothing can be streamed on
    # its wire, so its frequency response is the identified model's
    injection: Final = None

    def period_s(self, params: Mapping[str, int]) -> float:
        return max(1, params.get("stm", 1)) * SAMPLE_UNIT_S

    def linear_plant(self, model: Mapping[str, Any]) -> IdentifiedPlant:
        """The closed-loop fit (``Z1100Plant.to_dict``) per PWM unit (duty / 255)."""
        if "gain_counts_s_per_duty" not in model:
            raise ValueError("the identified model does not describe a z1100 plant")
        return IdentifiedPlant(
            float(model["gain_counts_s_per_duty"]) / PWM_FULL_SCALE,
            float(model.get("tau_s", 0.0)),
            "auto-tune identification",
        )

    def loop(self, plant: IdentifiedPlant, params: Mapping[str, int]) -> LoopModel:
        return z1100_loop_for(
            plant.transfer_function(),
            params["kabd_k"],
            params["kabd_a"],
            params["kabd_b"],
            max(1, params.get("stm", 1)),
        )

    def controller_response(
        self, frequency_hz: FloatArray, params: Mapping[str, int]
    ) -> ComplexArray | None:
        """None: K/A/B acts on the position as well as on the error (its B term)."""
        return None

    def verify_profile(self, params: Mapping[str, int]) -> VerifyProfile:
        """A move with the axis' own vmax/acc (counts/s, counts/s^2)."""
        return VerifyProfile("move", float(params.get("vmax", 0)), float(params.get("acc", 0)))


# =====================================================================================
# The law as a linear loop (tuning.loops.LoopModel): every Stm x 32 us
# ``u = (K (16 e + A (e - e[-32])) - B (y - y[-32])) / 64``: a forward path
# ``Cf(z) = K (16 + A (1 - z^-32)) / 64`` on the error and velocity feedback
# ``Cb(z) = B (1 - z^-32) / 64`` on the position.
# =====================================================================================


def z1100_loop(
    motor: MotorModel, k: int, a: int, b: int, stm: int = 1, window: int = 32
) -> LoopModel:
    """The Z1100 K/A/B law (above) sampled every ``stm`` x 32 us."""
    return z1100_loop_for(motor.plant(), k, a, b, stm, window)


def z1100_loop_for(
    plant: control.TransferFunction, k: int, a: int, b: int, stm: int = 1, window: int = 32
) -> LoopModel:
    """The Z1100 K/A/B law around a continuous plant (counts per PWM unit)."""
    plant_d = control.c2d(plant, max(1, stm) * SAMPLE_UNIT_S, "zoh")
    return z1100_loop_on(plant_d, k, a, b, stm, window)


def z1100_loop_on(
    plant_d: control.TransferFunction, k: int, a: int, b: int, stm: int = 1, window: int = 32
) -> LoopModel:
    """The Z1100 law around a plant already discretised at Stm x 32 us."""
    ts = max(1, stm) * SAMPLE_UNIT_S
    forward, feedback = z1100_kab_polynomials(k, a, b, window)
    return LoopModel(control.tf(*forward, ts), control.tf(*feedback, ts), plant_d, ts)


def z1100_kab_polynomials(
    k: int, a: int, b: int, window: int = 32
) -> tuple[Polynomial, Polynomial]:
    """The Z1100 law: ``Cf = K (16 + A (1 - z^-w)) / 64``, ``Cb = B (1 - z^-w) / 64``."""
    shift = np.zeros(window + 1)
    shift[0] = 1.0  # z^window
    delta = shift.copy()
    delta[-1] = -1.0  # z^window - 1: (1 - z^-window) over z^window
    den = shift * 64.0
    return (k * (16 * shift + a * delta), den), (b * delta, den.copy())
