"""Z1100 gain rule: search KABH (and KABD = KABH with K x 3/4) by simulating the
chip's K/A/B law on the model (docs/autotune.md, "Z1100", "The rule").

The law, its simulation, the plant and its fit come from the shared core
(``devices.z1100.law``, ``tuning.plants``); this module only ranks candidates.
Pure: no I/O (it runs in a worker thread).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Final

import control

from servotune.devices.z1100 import NAME
from servotune.devices.z1100.law import (
    BAND_COUNTS,
    KABD_FRACTION,
    PWM_FULL_SCALE,
    SAMPLE_UNIT_S,
    Kab,
    MoveProfile,
    kab_dict,
    move_metrics,
    simulate_move,
    z1100_kab_polynomials,
)
from servotune.schema import RunMetrics
from servotune.tuning.loops import Margins, MarginSearch
from servotune.tuning.plants import IdentifiedPlant, Z1100Plant
from servotune.tuning.targets import DEFAULT_PRESET, PRESETS, MarginTarget, margin_report

K_GRID: Final = (4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 160, 192, 255)
A_GRID: Final = (8, 16, 32, 64, 128)
B_GRID: Final = (4, 8, 16)
OVERSHOOT_LIMIT_BAND: Final = {"no_overshoot": 0.25, "fast": 1.0}  # x the settling band
ROBUST_GAIN_FACTORS: Final = (0.75, 1.33)
ROBUST_TAU_FACTORS: Final = (0.5, 2.0)
ROBUST_CHECKS: Final = 60  # the best nominal candidates checked on the perturbed models
FEASIBLE_DUTY: Final = 0.9  # perturbed models needing more duty for the profile are skipped
TIE_S: Final = 0.01  # settling times this close count as equal


def _overshoot_counts(m: RunMetrics) -> float:
    return (m.overshoot_pct or 0.0) / 100.0 * abs(m.step)


@dataclass(slots=True)
class Z1100Proposal:
    gains: Kab
    current: Kab
    current_kabd: Kab
    plant: Z1100Plant
    profile: MoveProfile
    predicted: RunMetrics
    predicted_default: RunMetrics
    worst_case_settling_s: float | None
    candidates: int
    simulations: int
    response: str
    rule: str
    peak_pwm: int = 0
    excursion: int = 0
    default_excursion: int = 0
    margins: dict[str, Any] = field(default_factory=dict)
    margins_default: dict[str, Any] = field(default_factory=dict)
    rejected_for_margins: int = 0

    def gains_dict(self) -> dict[str, int]:
        return kab_dict(self.gains, self.gains.kabd())

    def to_dict(self) -> dict[str, Any]:
        return {
            "device": NAME,
            "model": self.plant.to_dict(),
            "gains": self.gains_dict(),
            "current_gains": kab_dict(self.current, self.current_kabd),
            "predicted": self.predicted.model_dump(),
            "predicted_default": self.predicted_default.model_dump(),
            "rule": self.rule,
            "design": {
                "worst_case_settling_s": self.worst_case_settling_s,
                "unchanged": self.gains == self.current,
                "kabd_fraction": KABD_FRACTION,
                "margin_target": self.margins.get("target"),
                "rejected_for_margins": self.rejected_for_margins,
            },
            "margins": self.margins,
            "margins_default": self.margins_default,
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


def _acceptable(m: RunMetrics, limit_counts: float) -> bool:
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
    target: MarginTarget = PRESETS[DEFAULT_PRESET],
) -> Z1100Proposal:
    """The rule (docs/autotune.md, Z1100): among K x A x B of the grid, with KABD =
    KABH with K x 3/4, keep those that settle on the model within the band with
    overshoot <= the response's limit and travel <= ``max_excursion``; check the
    ``ROBUST_CHECKS`` best (settling in ``TIE_S`` buckets, then peak following error)
    also on the model with gain -25 %/+33 % and tau -50 %/+100 % (those on which the
    move needs more than ``FEASIBLE_DUTY`` are left out); propose the smallest
    worst-case settling time (ties within ``TIE_S``: the smaller peak following error,
    then the smaller K). Margins: only candidates whose hold loop (KABD on the model's
    linear part, ``tuning.targets``) is stable with ``target``'s margins; where none
    is, those closest to it (the same share of both), and the proposal says so."""
    limit = OVERSHOOT_LIMIT_BAND[response] * band
    sims = 0
    plant_d = control.c2d(
        IdentifiedPlant(plant.gain / PWM_FULL_SCALE, plant.tau_s, "").transfer_function(),
        max(1, profile.stm) * SAMPLE_UNIT_S,
        "zoh",
    )

    search_margins = MarginSearch(plant_d, max(1, profile.stm) * SAMPLE_UNIT_S)

    def margins_of(gains: Kab) -> Margins:
        hold = gains.kabd() if gains != current else current_kabd
        return search_margins.margins(*z1100_kab_polynomials(hold.k, hold.a, hold.b))

    settling: list[tuple[float, float, Kab, RunMetrics]] = []
    for k in K_GRID:
        for a in A_GRID:
            for b in B_GRID:
                gains = Kab(k, a, b)
                sim = simulate_move(plant, gains, gains.kabd(), profile)
                m = move_metrics(sim, profile.distance, band)
                sims += 1
                if _acceptable(m, limit) and max(abs(x) for x in sim.position) <= max_excursion:
                    assert m.settling_time_s is not None
                    settling.append((m.settling_time_s, m.peak_following_error or 0.0, gains, m))
    margins = {c[2]: margins_of(c[2]) for c in settling}
    nominal = [c for c in settling if target.met_by(margins[c[2]])]
    rejected_for_margins = len(settling) - len(nominal)
    if not nominal and settling:
        # the chip cannot reach the target on this model: the closest any candidate does
        share = max(target.share(margins[c[2]]) for c in settling)
        nominal = [c for c in settling if target.share(margins[c[2]]) >= 0.999 * share]
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
    ranked: list[tuple[float, float, int, Kab, RunMetrics]] = []
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
    rule += (
        f"; the hold loop stable with the target's margins ({target.preset}: PM "
        f"{target.phase_margin_deg:g} deg, GM {target.gain_margin_db:g} dB; where no "
        "candidate reaches them, the closest any does, said)"
    )
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
        margins=margin_report(margins_of(chosen), target),
        margins_default=margin_report(margins_of(current), target),
        rejected_for_margins=rejected_for_margins,
    )
