"""SLAP2 gain rule: search kp/ki/kd by simulating the firmware's loop on the model.

docs/autotune.md ("The rule") explains the method and why it is a grid and minimax
rather than a formula. The law, its simulation and the model come from the shared
core (``devices.slap2.law``, ``tuning.plants``); this module only ranks candidates.
Pure: no I/O (it runs in a worker thread).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Final

import control

from servotune.autotune.proposal import Response
from servotune.devices.slap2.law import (
    D_MUL,
    GAIN_MAX,
    P_MUL,
    PID_SHIFT,
    SETTLED_HOLD_S,
    TICK_S,
    Gains,
    MoveSpec,
    pwm_per_count,
    simulate_response,
    slap2_pid_polynomials,
)
from servotune.schema import RunMetrics
from servotune.tuning.loops import ZERO, Margins, MarginSearch
from servotune.tuning.plants import IdentifiedPlant, PlantModel
from servotune.tuning.targets import DEFAULT_PRESET, PRESETS, MarginTarget, margin_report

OVERSHOOT_LIMIT_PCT: Final[dict[str, float]] = {"no_overshoot": 1.0, "fast": 10.0}
ROBUST_GAIN_FACTORS: Final = (0.75, 1.33)  # the plant gain K may be off by this much ...
ROBUST_TAU_FACTORS: Final = (0.5, 2.0)  # ... and the time constant this much
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
MAX_RELAXATIONS: Final = 8  # shares of an unreachable margin target tried, largest first
_REJECTIONS: Final = {
    "pwm_per_count": "more than 24 PWM per count",
    "friction": "too weak against friction (friction/P > window/2)",
    "not_settled": "not settled",
    "overshoot": "overshoot > {limit:g} %",
    "excursion": "travelled too far",
    "not_robust": "not settled with the model's gain -25 %/+33 %, tau -50 %/+100 %",
    "margins": "margins below the target",
}


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


def settles(model: PlantModel, gains: Gains, spec: MoveSpec) -> bool:
    """Whether ``gains`` settle ``spec`` on ``model`` (and stay in the band)."""
    return _score(model, gains, spec).settled


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
    limit = MAX_PWM_PER_COUNT * (1 << PID_SHIFT)
    kp_max = min(GAIN_MAX, int(limit / P_MUL))
    kd_max = min(GAIN_MAX, int(limit / D_MUL))
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
    "Gains by simulation, to margin targets: the SLAP2 firmware's discrete loop "
    f"({TICK_S * 1e6:.1f} us tick, integer PID law, anti-windup, PWM saturation, "
    "count quantisation, "
    "the same profile generator) runs the test on the identified model for each "
    "candidate of a kp/kd/ki grid (coarse, then finer around the best). A candidate "
    "qualifies if it settles into the in-position window and stays there, overshoots "
    "at most {limit}, changes the PWM by at most 24 per count of error, has a kp that "
    "alone holds the axis within half the window against the identified friction, "
    "still settles with the plant gain off by -25 %/+33 % and the time constant by "
    "-50 %/+100 %, and on the model's linear part keeps the loop stable with the "
    "target's margins ({margins}; where no candidate reaches them, the closest any "
    "does, said). Of the 40 fastest qualifying candidates, the proposal is the one "
    "whose slowest settling on those perturbed models is shortest; within 5 ms of "
    "that, the one with the fewest PWM per count."
)


@dataclass(frozen=True, slots=True)
class Slap2Proposal:
    """What ``propose_gains`` returns: the gains and everything the user is shown."""

    model: PlantModel
    spec: MoveSpec
    response: Response
    gains: Gains
    current_gains: Gains
    predicted: RunMetrics
    predicted_default: RunMetrics
    predicted_peak_pwm: int
    predicted_excursion: int
    default_excursion: int
    design: dict[str, Any]
    rule: str
    candidates: int
    simulations: int
    # the margins of the proposal and of the gains in use against the target
    margins: dict[str, Any] = field(default_factory=dict)
    margins_default: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "model": self.model.to_dict(),
            "test": asdict(self.spec),
            "response": self.response,
            "gains": self.gains.to_dict(),
            "current_gains": self.current_gains.to_dict(),
            "predicted": self.predicted.model_dump(),
            "predicted_default": self.predicted_default.model_dump(),
            "predicted_peak_pwm": self.predicted_peak_pwm,
            "predicted_excursion": self.predicted_excursion,
            "default_excursion": self.default_excursion,
            "design": self.design,
            "rule": self.rule,
            "candidates": self.candidates,
            "simulations": self.simulations,
            "margins": self.margins,
            "margins_default": self.margins_default,
        }


def propose_gains(
    model: PlantModel,
    spec: MoveSpec,
    response: Response,
    current: Gains,
    *,
    max_excursion: int | None = None,
    target: MarginTarget = PRESETS[DEFAULT_PRESET],
) -> Slap2Proposal:
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

    Margins: a candidate qualifies only if, on the model's linear part under the exact
    law, the loop is stable with at least ``target``'s phase and gain margins
    (``tuning.targets``). When no candidate reaches them (the device does not allow
    it on this model), the search is made without them and the proposal says so
    (``margins.meets_target`` false, with the warning).
    """
    if spec.distance == 0:
        raise ValueError("the test distance must not be 0")
    limit_pct = OVERSHOOT_LIMIT_PCT[response]
    excursion_limit = max_excursion if max_excursion is not None else 1 << 30
    kp_floor = friction_floor(model, spec.band)
    scores: dict[Gains, _Score] = {}
    simulations = 0
    plant_d = control.c2d(
        IdentifiedPlant(model.gain, model.tau_s, "").transfer_function(), TICK_S, "zoh"
    )
    margin_cache: dict[Gains, Margins] = {}
    enforce_margins = True
    search_margins = MarginSearch(plant_d, TICK_S)

    def margins_of(gains: Gains) -> Margins:
        found = margin_cache.get(gains)
        if found is None:
            pid = slap2_pid_polynomials(gains.kp, gains.ki, gains.kd)
            found = margin_cache[gains] = search_margins.margins(pid, ZERO)
        return found

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
        if enforce_margins and not target.met_by(margins_of(gains)):
            return "margins"
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

    def search() -> tuple[dict[Gains, str | None], list[tuple[float, int, Gains]]]:
        reasons: dict[Gains, str | None] = {}
        for gains in [*candidate_grid(model, spec.band), current]:
            reasons.setdefault(gains, rejection(gains))
        coarse = sorted((g for g, why in reasons.items() if why is None), key=key)
        seeds = [seed for _, _, seed in robust_ranking(coarse)[:FINE_SEEDS]]
        if not seeds:
            # nothing of the coarse grid qualifies: refine around those that only
            # overshoot (a finer kd may not), fastest first
            near = sorted((g for g, why in reasons.items() if why == "overshoot"), key=key)
            seeds = near[:FINE_SEEDS]
        for seed in seeds:
            for gains in _neighbours(seed):
                reasons.setdefault(gains, rejection(gains))
        ranked = sorted((g for g, why in reasons.items() if why is None), key=key)
        return reasons, robust_ranking(ranked)

    wanted = target
    reasons, robust = search()
    margin_rejections = sum(1 for why in reasons.values() if why == "margins")
    if not robust and margin_rejections:
        # The device cannot reach the target on this model: the margins closest to it
        # that a robust candidate reaches (the same share of both), said.
        enforce_margins = False
        free_reasons, free_robust = search()
        reasons, robust = free_reasons, free_robust
        if free_robust:
            # the largest share of the target a qualifying candidate reaches that a
            # robust one does too (the robust ranking looks at the fastest 40 only)
            shares = sorted(
                {wanted.share(margins_of(g)) for g, why in free_reasons.items() if why is None},
                reverse=True,
            )
            enforce_margins = True
            for share in shares[:MAX_RELAXATIONS]:
                target = MarginTarget(
                    wanted.preset,
                    wanted.phase_margin_deg * share * 0.999,
                    wanted.gain_margin_db * share * 0.999,
                )
                reasons, robust = search()
                if robust:
                    break
            target = wanted
            if not robust:
                # no relaxed search found a robust candidate: of the robust ones found
                # without margins, those closest to the target (never simply the
                # fastest, which is often the thinnest)
                closest = max(wanted.share(margins_of(g)) for _, _, g in free_robust)
                reasons = free_reasons
                robust = [
                    r for r in free_robust if wanted.share(margins_of(r[2])) >= 0.999 * closest
                ]
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
        "margin_target": target.to_dict(),
        "rejected_for_margins": margin_rejections,
    }
    predicted_run = simulate_response(model, best, spec)
    default_run = simulate_response(model, current, spec)
    return Slap2Proposal(
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
        rule=RULE_TEXT.format(
            limit=f"{limit_pct:g} %",
            margins=f"{target.preset}: PM {target.phase_margin_deg:g} deg, "
            f"GM {target.gain_margin_db:g} dB",
        ),
        candidates=len(reasons),
        simulations=simulations,
        margins=margin_report(margins_of(best), target),
        margins_default=margin_report(margins_of(current), target),
    )
