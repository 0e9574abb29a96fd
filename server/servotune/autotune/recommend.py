"""Write the proposal or keep the gains in use? The auto-tune's recommendation.

A proposal is designed to a margin target on the identified model; when the search
cannot reach the target (a poor model, a loaded host during the identification) it
proposes the closest it found, and that can be thinner than what the axis runs with
(the demo under load: 1548/0/1210 at PM 17.4 deg against 600/10/1500 at 41.1 deg).
A tuning engineer then keeps what they have. The rule, on the model's margins against
the target (``tuning.targets``) and the predicted step of both sets of gains:

1. the proposal is the gains in use: keep (nothing to write);
2. the proposal's loop is unstable on the model: keep;
3. the proposal misses the target: keep when the gains in use meet it, or reach at
   least as large a share of it (``MarginTarget.share``: the smaller of PM/PM_target
   and GM/GM_target); else write (it is closer to the target than what runs now,
   e.g. factory gains that oscillate) - the warning stays;
4. the proposal meets the target: write, unless its margins are thinner than the
   gains in use (a smaller share) and it is not predicted to settle sooner on the
   model: a change that buys nothing with margin.

The same rule answers the API (``proposal.recommendation``) and decides the UI's
default button; the user's choice is recorded either way (``decision``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal

from servotune.tuning.targets import MarginTarget, target_for

Action = Literal["keep", "write"]


def share_of(report: Mapping[str, Any], target: MarginTarget) -> float:
    """``MarginTarget.share`` of a ``margin_report`` dict (its null margins are
    infinite: no crossover); 0 for an unstable loop."""
    if not report.get("stable"):
        return 0.0
    pm, gm = report.get("phase_margin_deg"), report.get("gain_margin_db")
    pm_share = math.inf if pm is None else float(pm) / target.phase_margin_deg
    gm_share = math.inf if gm is None else float(gm) / target.gain_margin_db
    return max(0.0, min(pm_share, gm_share))


def _summary(report: Mapping[str, Any], predicted: Mapping[str, Any] | None) -> dict[str, Any]:
    predicted = predicted or {}
    return {
        "phase_margin_deg": report.get("phase_margin_deg"),
        "gain_margin_db": report.get("gain_margin_db"),
        "stable": report.get("stable"),
        "meets_target": report.get("meets_target"),
        "settling_time_s": predicted.get("settling_time_s"),
        "overshoot_pct": predicted.get("overshoot_pct"),
    }


def _margins_text(report: Mapping[str, Any]) -> str:
    if not report.get("stable"):
        return "unstable"
    pm, gm = report.get("phase_margin_deg"), report.get("gain_margin_db")
    return (
        f"PM {'inf' if pm is None else f'{pm:.1f}'} deg / "
        f"GM {'inf' if gm is None else f'{gm:.1f}'} dB"
    )


def _ms(seconds: float | None) -> str:
    return "never" if seconds is None else f"{seconds * 1000:.0f} ms"


def recommend(proposal: Mapping[str, Any]) -> dict[str, Any]:
    """The recommendation for a proposal body (both devices' ``Proposal.to_dict()``):
    ``{action: "keep" | "write", reason, target, proposal: {...}, current: {...}}``,
    each side with its margins and predicted settling/overshoot (see the module doc)."""
    mine: Mapping[str, Any] = proposal.get("margins") or {}
    now: Mapping[str, Any] = proposal.get("margins_default") or {}
    target = (
        MarginTarget(**mine["target"]) if isinstance(mine.get("target"), dict) else target_for(None)
    )
    out: dict[str, Any] = {
        "target": target.to_dict(),
        "proposal": _summary(mine, proposal.get("predicted")),
        "current": _summary(now, proposal.get("predicted_default")),
    }

    def said(action: Action, reason: str) -> dict[str, Any]:
        return out | {"action": action, "reason": reason}

    target_text = (
        f"the target ({target.preset}: PM {target.phase_margin_deg:g} deg / "
        f"GM {target.gain_margin_db:g} dB)"
    )
    if proposal.get("gains") == proposal.get("current_gains"):
        return said("keep", "the proposal is the gains in use: nothing to write")
    if not mine or not now:
        return said("write", "no margins on the model to compare: the rule's proposal")
    share, share_now = share_of(mine, target), share_of(now, target)
    ours, theirs = _margins_text(mine), _margins_text(now)
    if not mine.get("stable"):
        return said("keep", "the proposal's loop is unstable on the identified model")
    if not mine.get("meets_target"):
        if now.get("meets_target"):
            return said(
                "keep",
                f"the proposal ({ours}) misses {target_text}; the gains in use ({theirs}) meet it",
            )
        if share <= share_now:
            return said(
                "keep",
                f"the proposal ({ours}) misses {target_text} and has thinner margins than "
                f"the gains in use ({theirs})",
            )
        return said(
            "write",
            f"the proposal ({ours}) misses {target_text}, but is closer to it than the "
            f"gains in use ({theirs})",
        )
    settle = out["proposal"]["settling_time_s"]
    settle_now = out["current"]["settling_time_s"]
    sooner = settle is not None and (settle_now is None or settle < settle_now)
    if share < share_now and not sooner:
        return said(
            "keep",
            f"the proposal ({ours}) meets {target_text} but has thinner margins than the "
            f"gains in use ({theirs}) and is not predicted to settle sooner "
            f"({_ms(settle)} against {_ms(settle_now)})",
        )
    return said(
        "write",
        f"the proposal ({ours}) meets {target_text}; predicted to settle in {_ms(settle)} "
        f"(the gains in use: {theirs}, {_ms(settle_now)})",
    )


def decision_record(
    action: Action,
    recommendation: Mapping[str, Any] | None,
    gains: Mapping[str, int],
    *,
    at_s: float,
    identification_run_id: str | None,
) -> dict[str, Any]:
    """What the user chose for a proposal, as the session and the identification run
    keep it: the action, the gains kept or written, what was recommended and why."""
    recommended = (recommendation or {}).get("action")
    return {
        "action": action,
        "gains": dict(gains),
        "recommended": recommended,
        "followed": recommended is None or recommended == action,
        "reason": (recommendation or {}).get("reason"),
        "at_s": round(at_s, 3),
        "identification_run_id": identification_run_id,
    }


def decision_text(decision: Mapping[str, Any]) -> str:
    """The decision in words (events, the identification run's note)."""
    gains = " ".join(f"{k}={v}" for k, v in decision["gains"].items())
    what = (
        f"kept the gains in use ({gains}): nothing written"
        if decision["action"] == "keep"
        else f"wrote the proposal ({gains})"
    )
    if decision.get("recommended") is None:
        return what
    return what + (
        " as recommended"
        if decision["followed"]
        else f" against the recommendation to {decision['recommended']}"
    )
