"""Auto-tune assistant for Z1100 axes (KABH/KABD gains): closed-loop identification.

docs/autotune.md ("Z1100") explains the method, the rule and its limits. Two layers:

* A pure core: ``simulate_move`` runs the servo law of the simulator
  (``sim/z1100.py``, docs/z1100-simulator.md; **the Z1100 manual gives no law**, so it
  is assumed) on a first-order velocity plant, at a coarser step than the chip's
  Stm x 32 us sample (``COARSE`` samples per step, the 32-sample derivative window
  becoming 32/COARSE steps); ``fit_plant_closed_loop`` fits gain, time constant and a
  timing offset to the following error recorded during a bench move with known gains;
  ``propose_kab`` searches K/A/B by the documented rule and predicts the metrics.
* ``Z1100Tuner``: identify -> propose -> accept -> verify on a live axis, used by
  ``autotune.AutoTuner`` for axes whose device is ``z1100`` (same API and shapes).

Units: counts, counts/s, duty -1..1, seconds.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any, Final

from servotune.drivers.base import DeviceRefusedError, DriverError, InvalidArgumentError
from servotune.metrics import Metrics, compute_metrics, unmeasured
from servotune.testbench import BenchTestRequest

if TYPE_CHECKING:
    from servotune.autotune import AutoTuner, IdentifyRequest, _Session
    from servotune.hub import AxisEntry

# --- the law (sim/z1100.py; assumed, the manual gives none) --------------------------
SAMPLE_UNIT_S: Final = 32e-6  # one sample is Stm x 32 us
WINDOW: Final = 32  # samples of the derivative difference
ERROR_WEIGHT: Final = 16
OUTPUT_DIVISOR: Final = 64
PWM_FULL_SCALE: Final = 255
COARSE: Final = 4  # chip samples per simulation step (window 32 -> 8 steps)

# --- the rule ---------------------------------------------------------------------------
K_GRID: Final = (4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 160, 192, 255)
A_GRID: Final = (8, 16, 32, 64, 128)
B_GRID: Final = (4, 8, 16)
KABD_FRACTION: Final = 0.75  # KABD = KABH with K x 3/4 (as the demo's integrator did)
OVERSHOOT_LIMIT_BAND: Final = {"no_overshoot": 0.25, "fast": 1.0}  # x the settling band
ROBUST_GAIN_FACTORS: Final = (0.75, 1.33)
ROBUST_TAU_FACTORS: Final = (0.5, 2.0)
ROBUST_CHECKS: Final = 60  # the best nominal candidates checked on the perturbed models
FEASIBLE_DUTY: Final = 0.9  # perturbed models needing more duty for the profile are skipped
TIE_S: Final = 0.01  # settling times this close count as equal
HOLD_S: Final = 0.1  # simulated after the profile's end
DEFAULT_DISTANCE: Final = 10_000
BAND_COUNTS: Final = 20.0  # the bench's move band (drivers/z1100.py)
SETTLE_TIMEOUT_S: Final = 3.0
MAX_FIT_RMS_COUNTS: Final = 10.0  # a worse fit (and > 15 % of the peak error) is flagged
FIT_STARTS: Final = 2  # Nelder-Mead runs from the best points of the start grid
FIT_TAIL_S: Final = 0.3  # samples fitted after the profile's end


@dataclass(frozen=True, slots=True)
class Kab:
    k: int
    a: int
    b: int

    def kabd(self) -> Kab:
        return Kab(max(1, round(self.k * KABD_FRACTION)), self.a, self.b)


@dataclass(frozen=True, slots=True)
class Z1100Plant:
    """``tau dv/dt = gain * duty - v``: velocity in counts/s, duty -1..1."""

    gain: float
    tau_s: float
    rms_error_counts: float = 0.0
    samples: int = 0
    delay_s: float = 0.0

    def scaled(self, gain_factor: float, tau_factor: float) -> Z1100Plant:
        return Z1100Plant(self.gain * gain_factor, self.tau_s * tau_factor)

    def to_dict(self) -> dict[str, float | int]:
        return {
            "gain_counts_s_per_duty": round(self.gain, 1),
            "tau_s": round(self.tau_s, 5),
            "rms_error_counts": round(self.rms_error_counts, 2),
            "samples": self.samples,
            "delay_s": round(self.delay_s, 5),
        }


@dataclass(frozen=True, slots=True)
class MoveProfile:
    distance: int
    vmax: float  # counts/s
    acc: float  # counts/s^2
    stm: int = 1


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
    the chip simulator in tests/test_autotune_z1100.py: coarse 4 and 1 agree with it
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
            # the law, once per step, one sample after the step's start (as on the chip:
            # the reference of this sample against the position at its start)
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


def move_metrics(sim: SimulatedMove, distance: int, band: float = BAND_COUNTS) -> Metrics:
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


def _overshoot_counts(m: Metrics) -> float:
    return (m.overshoot_pct or 0.0) / 100.0 * abs(m.step)


# =====================================================================================
# The fit
# =====================================================================================


def _nelder_mead(f: Any, x0: list[float], steps: list[float], iterations: int = 120) -> list[float]:
    from servotune.autotune import _nelder_mead as nm

    result: list[float] = nm(f, x0, steps, iterations=iterations, tolerance=1e-4)
    return result


def interpolate(ts: Sequence[float], ys: Sequence[float], t: float) -> float:
    if t <= ts[0]:
        return 0.0 if t < 0 else ys[0]
    if t >= ts[-1]:
        return ys[-1]
    lo, hi = 0, len(ts) - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if ts[mid] <= t:
            lo = mid
        else:
            hi = mid
    f = (t - ts[lo]) / (ts[hi] - ts[lo])
    return ys[lo] + f * (ys[hi] - ys[lo])


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
    error (the duty it takes to follow at the peak speed), tau on a grid; Nelder-Mead
    over log gain, log tau and the delay minimises the squared error difference.
    """
    if len(times) != len(errors):
        raise ValueError("times and errors differ in length")
    # the move and FIT_TAIL_S after it (later samples hold still and cost time)
    end = _profile_time(profile) + FIT_TAIL_S
    kept = [(t, e) for t, e in zip(times, errors, strict=True) if t <= end]
    times, errors = [t for t, _ in kept], [e for _, e in kept]
    if len(times) < 5:
        raise ValueError("too few samples to fit a plant model")
    peak_e = max(abs(e) for e in errors)
    if peak_e < 1:
        raise ValueError("no following error recorded: cannot identify the plant")
    peak_v = min(abs(profile.vmax), math.sqrt(abs(profile.acc) * abs(profile.distance)))
    window_counts = peak_v * WINDOW * max(1, profile.stm) * SAMPLE_UNIT_S
    duty0 = (kabh.k * ERROR_WEIGHT * peak_e - kabh.b * window_counts) / OUTPUT_DIVISOR / 255
    gain0 = peak_v / min(1.0, max(duty0, 0.02))
    horizon = max(times) + 0.02
    hold = max(0.02, horizon - _profile_time(profile))

    def cost(theta: list[float]) -> float:
        gain, tau, delay = math.exp(theta[0]), math.exp(theta[1]), theta[2]
        if not (5e-4 <= tau <= 1.0 and -0.005 <= delay <= 0.06 and 1e3 <= gain <= 1e8):
            return 1e30
        sim = simulate_move(Z1100Plant(gain, tau), kabh, kabd, profile, hold_s=hold)
        return sum(
            (interpolate(sim.t, sim.error, t - delay) - e) ** 2
            for t, e in zip(times, errors, strict=True)
        )

    grid: list[tuple[float, list[float]]] = []
    for gain_factor in (0.5, 1.0, 2.0):
        for tau0 in (0.003, 0.01, 0.03, 0.1):
            for delay0 in (0.0, 0.01, 0.02, 0.04):
                theta = [math.log(gain0 * gain_factor), math.log(tau0), delay0]
                grid.append((cost(theta), theta))
    grid.sort(key=lambda g: g[0])
    results: list[tuple[float, list[float]]] = []
    for _, start in grid[:FIT_STARTS]:
        theta = _nelder_mead(cost, start, [0.2, 0.4, 0.006], iterations=70)
        theta = _nelder_mead(cost, theta, [0.05, 0.1, 0.002], iterations=50)
        results.append((cost(theta), theta))
    theta = min(results, key=lambda r: r[0])[1]
    c = cost(theta)
    return Z1100Plant(
        math.exp(theta[0]),
        math.exp(theta[1]),
        rms_error_counts=math.sqrt(c / len(times)),
        samples=len(times),
        delay_s=theta[2],
    )


def _profile_time(profile: MoveProfile) -> float:
    d, v, a = abs(profile.distance), abs(profile.vmax), abs(profile.acc)
    if v * v / a >= d:
        return 2 * math.sqrt(d / a)
    return d / v + v / a


# =====================================================================================
# The proposal
# =====================================================================================


@dataclass(slots=True)
class Z1100Proposal:
    gains: Kab
    current: Kab
    current_kabd: Kab
    plant: Z1100Plant
    profile: MoveProfile
    predicted: Metrics
    predicted_default: Metrics
    worst_case_settling_s: float | None
    candidates: int
    simulations: int
    response: str
    rule: str
    peak_pwm: int = 0
    excursion: int = 0
    default_excursion: int = 0

    def gains_dict(self) -> dict[str, int]:
        return _kab_dict(self.gains, self.gains.kabd())

    def to_dict(self) -> dict[str, Any]:
        return {
            "device": "z1100",
            "model": self.plant.to_dict(),
            "gains": self.gains_dict(),
            "current_gains": _kab_dict(self.current, self.current_kabd),
            "predicted": asdict(self.predicted),
            "predicted_default": asdict(self.predicted_default),
            "rule": self.rule,
            "design": {
                "worst_case_settling_s": self.worst_case_settling_s,
                "unchanged": self.gains == self.current,
                "kabd_fraction": KABD_FRACTION,
            },
            "test": {
                "distance": self.profile.distance,
                "velocity": self.profile.vmax,
                "acceleration": self.profile.acc,
                "stm": self.profile.stm,
                "band": BAND_COUNTS,
            },
            "response": self.response,
            "predicted_peak_pwm": self.peak_pwm,
            "predicted_excursion": self.excursion,
            "default_excursion": self.default_excursion,
            "candidates": self.candidates,
            "simulations": self.simulations,
        }


def _kab_dict(kabh: Kab, kabd: Kab) -> dict[str, int]:
    return {
        "kabh_k": kabh.k,
        "kabh_a": kabh.a,
        "kabh_b": kabh.b,
        "kabd_k": kabd.k,
        "kabd_a": kabd.a,
        "kabd_b": kabd.b,
    }


def _acceptable(m: Metrics, limit_counts: float) -> bool:
    if m.settling_time_s is None or m.steady_state_error is None:
        return False
    return _overshoot_counts(m) <= limit_counts and (m.oscillations or 0) <= 1


def propose_kab(
    plant: Z1100Plant,
    profile: MoveProfile,
    response: str,
    current: Kab,
    current_kabd: Kab,
    band: float = BAND_COUNTS,
    max_excursion: float = math.inf,
) -> Z1100Proposal:
    """The rule (docs/autotune.md, Z1100): among K x A x B of the grid, with KABD =
    KABH with K x 3/4, keep those that settle on the model within the band with
    overshoot <= the response's limit and travel <= ``max_excursion``; check the
    ``ROBUST_CHECKS`` best (settling in ``TIE_S`` buckets, then peak following error)
    also on the model with gain -25 %/+33 % and tau -50 %/+100 % (those on which the
    move needs more than ``FEASIBLE_DUTY`` are left out); propose the smallest
    worst-case settling time (ties within ``TIE_S``: the smaller peak following error,
    then the smaller K)."""
    limit = OVERSHOOT_LIMIT_BAND[response] * band
    sims = 0
    nominal: list[tuple[float, float, Kab, Metrics]] = []
    for k in K_GRID:
        for a in A_GRID:
            for b in B_GRID:
                gains = Kab(k, a, b)
                sim = simulate_move(plant, gains, gains.kabd(), profile)
                m = move_metrics(sim, profile.distance, band)
                sims += 1
                if _acceptable(m, limit) and max(abs(x) for x in sim.position) <= max_excursion:
                    assert m.settling_time_s is not None
                    nominal.append((m.settling_time_s, m.peak_following_error or 0.0, gains, m))
    nominal.sort(key=lambda c: (round(c[0] / TIE_S), c[1], c[2].k))
    peak_v = min(abs(profile.vmax), math.sqrt(abs(profile.acc) * abs(profile.distance)))
    perturbed = [
        plant.scaled(gf, tf)
        for gf in ROBUST_GAIN_FACTORS
        for tf in ROBUST_TAU_FACTORS
        # a model on which the profile needs more than FEASIBLE_DUTY would fail any
        # gains: it says nothing about robustness
        if (peak_v + plant.tau_s * tf * abs(profile.acc)) / (plant.gain * gf) <= FEASIBLE_DUTY
    ]
    ranked: list[tuple[float, float, int, Kab, Metrics]] = []
    for settle, peak_fe, gains, m in nominal[:ROBUST_CHECKS]:
        worst = settle
        for model in perturbed:
            pm = move_metrics(
                simulate_move(model, gains, gains.kabd(), profile), profile.distance, band
            )
            sims += 1
            if not _acceptable(pm, 2 * limit + band) or pm.settling_time_s is None:
                worst = math.inf
                break
            worst = max(worst, pm.settling_time_s)
        ranked.append((worst, peak_fe, gains.k, gains, m))
    default_sim = simulate_move(plant, current, current_kabd, profile)
    default = move_metrics(default_sim, profile.distance, band)
    sims += 1
    finite = [r for r in ranked if r[0] < math.inf]
    if finite:
        best_worst = min(r[0] for r in finite)
        ties = [r for r in finite if r[0] <= best_worst + TIE_S]
        worst, _, _, chosen, predicted = min(ties, key=lambda r: (r[1], r[2]))
        worst_case: float | None = worst
    elif nominal:  # none is robust: the nominal ranking
        chosen, predicted, worst_case = nominal[0][2], nominal[0][3], None
    else:
        raise ValueError("no gains of the grid settle on the fitted model")
    rule = (
        f"KABH from K {K_GRID[0]}..{K_GRID[-1]} x A {A_GRID} x B {B_GRID}, KABD = KABH "
        f"with K x {KABD_FRACTION:g}; settles within ±{band:g} counts with overshoot <= "
        f"{limit:g} counts on the model and on it with gain -25 %/+33 %, tau -50 %/+100 %; "
        f"smallest worst-case settling time, ties ({TIE_S * 1000:g} ms): smaller peak "
        "following error, then smaller K (perturbed models on which the move needs more "
        f"than {FEASIBLE_DUTY:g} duty are left out)"
    )
    chosen_sim = simulate_move(plant, chosen, chosen.kabd(), profile)
    sims += 1
    return Z1100Proposal(
        chosen,
        current,
        current_kabd,
        plant,
        profile,
        predicted,
        default,
        worst_case,
        len(K_GRID) * len(A_GRID) * len(B_GRID),
        sims,
        response,
        rule,
        peak_pwm=round(chosen_sim.peak_duty * PWM_FULL_SCALE),
        excursion=round(max(abs(x) for x in chosen_sim.position)),
        default_excursion=round(max(abs(x) for x in default_sim.position)),
    )


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
    a settling time could not be measured (see ``autotune.verdict``)."""
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


# =====================================================================================
# The service part
# =====================================================================================


def _gains_of(values: dict[str, int], prefix: str) -> Kab:
    try:
        return Kab(values[f"{prefix}_k"], values[f"{prefix}_a"], values[f"{prefix}_b"])
    except KeyError:
        raise DeviceRefusedError("the axis' gains are not read yet") from None


class Z1100Tuner:
    """The Z1100 half of ``AutoTuner`` (it owns sessions, locks and the checks)."""

    def __init__(self, tuner: AutoTuner) -> None:
        self._t = tuner
        self._proposals: dict[str, Z1100Proposal] = {}

    def _profile(self, entry: AxisEntry, distance: int) -> MoveProfile:
        values = entry.device_values
        vmax, acc = values.get("vmax", 0), values.get("acc", 0)
        if not vmax or not acc:
            raise DeviceRefusedError("the axis' Vmax or Acc is 0: no move")
        return MoveProfile(distance, float(vmax), float(acc), max(1, values.get("stm", 1)))

    async def check_request(self, entry: AxisEntry, request: IdentifyRequest) -> int:
        limits = await self._t._bench.limits(entry.info.id)
        if request.max_distance_counts > limits.max_distance_counts:
            raise InvalidArgumentError(
                "max_distance_counts",
                f"max_distance_counts {request.max_distance_counts} exceeds your bench limit "
                f"of ±{limits.max_distance_counts} counts",
            )
        if request.max_distance_counts < 400:
            raise InvalidArgumentError(
                "max_distance_counts",
                f"max_distance_counts {request.max_distance_counts} is too small: at least 400",
            )
        distance = request.distance or min(DEFAULT_DISTANCE, request.max_distance_counts // 2)
        if distance > request.max_distance_counts:
            raise InvalidArgumentError(
                "distance",
                f"distance {distance} exceeds your limit max_distance_counts of "
                f"±{request.max_distance_counts}",
            )
        entry_latest = entry.latest
        if entry.info.id in self._t._bench._active:
            raise DeviceRefusedError("a test is already running on this axis")
        if entry_latest is None or self._t._hub.link_status(entry.link.id).state != "connected":
            raise DeviceRefusedError("the axis is not connected: no telemetry")
        if entry_latest.flags.get("running"):
            raise DeviceRefusedError("the axis is moving: wait until it stands still")
        return distance

    async def identify(
        self, entry: AxisEntry, session: _Session, request: IdentifyRequest, distance: int
    ) -> dict[str, Any]:
        values = entry.device_values
        current, current_kabd = _gains_of(values, "kabh"), _gains_of(values, "kabd")
        signed = request.direction * distance
        profile = self._profile(entry, signed)
        start = round(self._t._position(entry.latest))
        run = await self._run_test(entry, signed, "auto-tune identification (gains in use)")
        await self._return(entry, start)
        times, errors = _trace(run, request.direction)
        plant = await asyncio.to_thread(
            fit_plant_closed_loop,
            times,
            errors,
            current,
            current_kabd,
            replace_distance(profile, distance),
        )
        session.model = plant.to_dict()
        self._t._hub.on_event(
            "info",
            entry.info.id,
            f"auto-tune: model {plant.gain:.0f} counts/s per duty, tau "
            f"{plant.tau_s * 1000:.1f} ms (rms {plant.rms_error_counts:.1f} counts)",
        )
        proposal = await asyncio.to_thread(
            propose_kab,
            plant,
            replace_distance(profile, distance),
            request.response,
            current,
            current_kabd,
            BAND_COUNTS,
            request.max_distance_counts,
        )
        self._proposals[entry.info.id] = proposal
        body = proposal.to_dict()
        body["identification_run_id"] = run["id"]
        body["identification_run_ids"] = [run["id"]]
        body["travel_counts"] = _travel(run, start)
        peak_error = max((abs(e) for e in errors), default=0.0)
        body["warnings"] = (
            [
                f"the model fits the recorded following error poorly (rms "
                f"{plant.rms_error_counts:.1f} counts of a peak {peak_error:.0f}): check "
                "the proposal's prediction against the verification"
            ]
            if plant.rms_error_counts > max(MAX_FIT_RMS_COUNTS, 0.15 * peak_error)
            else []
        )
        body["baseline_possible"] = proposal.default_excursion <= request.max_distance_counts
        session.identification_run_id = run["id"]
        session.proposal_dict = body
        session.device_settings = {
            k: v
            for k, v in values.items()
            if k.startswith("kabh") or k.startswith("kabd") or k in ("vmax", "acc", "stm")
        }
        return body

    def previous_gains(self, entry: AxisEntry) -> dict[str, int]:
        """KABH/KABD in use before the proposal (what a failed accept writes back)."""
        proposal = self._proposals.get(entry.info.id)
        if proposal is None:
            raise DeviceRefusedError("no proposal to accept: run identify first")
        return _kab_dict(proposal.current, proposal.current_kabd)

    async def return_to(self, entry: AxisEntry, target: int) -> None:
        """Move back to ``target`` with the gains in use (after a failed identification)."""
        await self._return(entry, target)

    async def _run_test(self, entry: AxisEntry, distance: int, note: str) -> dict[str, Any]:
        bench = self._t._bench
        limits = await bench.limits(entry.info.id)
        profile = self._profile(entry, distance)
        duration = min(limits.max_duration_s, _profile_time(profile) + 1.0)
        started = await bench.start_run(
            entry.info.id,
            BenchTestRequest(kind="move", distance=distance, duration_s=duration, note=note),
        )
        run_id: str = started["id"]
        deadline = self._t._clock() + duration + 10.0
        while self._t._clock() < deadline:
            await asyncio.sleep(0.1)
            run = await bench.get_run_meta(run_id)  # status only: no samples
            if run["status"] != "recording":
                if run["status"] != "complete":
                    raise DriverError(f"test {run_id} {run['status']}: {run.get('message')}")
                return await bench.get_run(run_id)
        raise DriverError(f"test {run_id} did not finish")

    async def _return(self, entry: AxisEntry, target: int) -> None:
        position = round(self._t._position(entry.latest))
        if position == target:
            return
        await self._t._hub.command(entry.info.id, "go_to_target", {"target": target})
        await asyncio.sleep(0.1)
        deadline = self._t._clock() + SETTLE_TIMEOUT_S + 2.0
        while self._t._clock() < deadline:
            sample = await self._t._next_sample(entry)
            error = sample.channels.get("following_error")
            if not sample.flags.get("running") and error is not None and abs(error) <= BAND_COUNTS:
                return
        raise DriverError(f"the axis did not settle at {target}")

    def check_unchanged(self, entry: AxisEntry, session: _Session) -> None:
        """409 when gains or profile changed since the proposal."""
        changed = [k for k, v in session.device_settings.items() if entry.device_values.get(k) != v]
        if changed:
            raise DeviceRefusedError(
                f"settings changed since the proposal ({', '.join(changed)}): identify again"
            )

    async def accept(self, entry: AxisEntry, session: _Session) -> dict[str, Any]:
        proposal = self._proposals.get(entry.info.id)
        if proposal is None or session.request is None:
            raise DeviceRefusedError("no proposal to accept: run identify first")
        axis_id = entry.info.id
        distance = proposal.profile.distance * session.request.direction
        start = round(self._t._position(entry.latest))
        hub = self._t._hub
        baseline: dict[str, Any] | None = None
        baseline_note = ""
        if proposal.default_excursion <= session.request.max_distance_counts:
            hub.on_event("info", axis_id, "auto-tune: baseline test with the previous gains")
            baseline = await self._run_test(entry, distance, "auto-tune baseline (previous gains)")
            await self._return(entry, start)
        else:
            baseline_note = (
                f"baseline skipped: the previous gains are predicted to travel "
                f"{proposal.default_excursion} counts, beyond your max_distance_counts"
            )
            hub.on_event("warning", axis_id, f"auto-tune: {baseline_note}")
        gains = proposal.gains
        # KABH first: the chip copies KABH into KABD, so KABD must follow it.
        await hub.write_params(axis_id, {"kabh_k": gains.k, "kabh_a": gains.a, "kabh_b": gains.b})
        kabd = gains.kabd()
        await hub.write_params(axis_id, {"kabd_k": kabd.k, "kabd_a": kabd.a, "kabd_b": kabd.b})
        hub.on_event("info", axis_id, "auto-tune: verification test with the new gains")
        verification = await self._run_test(
            entry, distance, "auto-tune verification (proposed gains)"
        )
        await self._return(entry, start)
        measured = verification.get("metrics") or {}
        baseline_measured = baseline.get("metrics") if baseline else None
        return {
            "gains": proposal.gains_dict(),
            "previous_gains": _kab_dict(proposal.current, proposal.current_kabd),
            "predicted": asdict(proposal.predicted),
            "measured": measured,
            "predicted_default": asdict(proposal.predicted_default),
            "baseline_measured": baseline_measured,
            "verification_run_id": verification["id"],
            "baseline_run_id": baseline["id"] if baseline else None,
            "baseline_note": baseline_note,
            "verdict": verdict_z1100(
                baseline_measured,
                measured,
                baseline_unmeasured=unmeasured(baseline),
                tuned_unmeasured=unmeasured(verification),
            ),
            "verdict_reason": unmeasured(verification) or unmeasured(baseline),
        }

    async def revert(self, entry: AxisEntry) -> dict[str, int]:
        proposal = self._proposals.get(entry.info.id)
        if proposal is None:
            raise DeviceRefusedError("nothing to revert: no accepted proposal")
        hub = self._t._hub
        c, d = proposal.current, proposal.current_kabd
        written = await hub.write_params(
            entry.info.id, {"kabh_k": c.k, "kabh_a": c.a, "kabh_b": c.b}
        )
        written |= await hub.write_params(
            entry.info.id, {"kabd_k": d.k, "kabd_a": d.a, "kabd_b": d.b}
        )
        return written


def replace_distance(profile: MoveProfile, distance: int) -> MoveProfile:
    """The profile with a positive distance (the model is symmetric)."""
    return MoveProfile(abs(distance), profile.vmax, profile.acc, profile.stm)


def _travel(run: dict[str, Any], start: float) -> int:
    """The largest distance from ``start`` the run recorded."""
    index = run["columns"].index("position")
    positions = [row[index] for row in run["samples"] if row[index] is not None]
    return round(max((abs(p - start) for p in positions), default=0.0))


def _trace(run: dict[str, Any], direction: int) -> tuple[list[float], list[float]]:
    """Times after the trigger and following errors (in the move's sense) of a run."""
    columns: list[str] = run["columns"]
    index = columns.index("following_error")
    t0 = float(run.get("t0_s") or run["samples"][0][0])
    times: list[float] = []
    errors: list[float] = []
    for row in run["samples"]:
        value = row[index]
        if value is None or row[0] < t0:
            continue
        times.append(row[0] - t0)
        errors.append(direction * float(value))
    return times, errors
