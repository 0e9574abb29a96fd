"""Margin targets: the presets a proposal is designed to, and how a set of gains reads
against one.

Drive tools tune to margins as well as to the step: Kollmorgen WorkBench's auto-tuner
defaults to GM 8 dB / PM 45 deg (softer presets up to 65 deg / 35 dB), TwinCAT offers
stiff / medium / soft load presets (docs/autotune.md). Here: ``stiff`` PM 40 deg /
GM 6 dB (a rigid load, faster, thinner), ``medium`` PM 45 deg / GM 8 dB (the default),
``soft`` PM 60 deg / GM 12 dB (compliant or uncertain loads). Margins are those of the
identified model under the device's exact law (``tuning.loops``), read by the one rule
(``tuning.stability.loop_margins``), on the Z1100 with its hold gains (KABD).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final

from servotune.schema import MarginPreset
from servotune.tuning.loops import Margins

Preset = MarginPreset


@dataclass(frozen=True, slots=True)
class MarginTarget:
    preset: Preset
    phase_margin_deg: float
    gain_margin_db: float

    def to_dict(self) -> dict[str, Any]:
        return {
            "preset": self.preset,
            "phase_margin_deg": self.phase_margin_deg,
            "gain_margin_db": self.gain_margin_db,
        }

    def share(self, margins: Margins) -> float:
        """How much of this target ``margins`` reach: the smaller share of the two
        margins (0 for an unstable loop) - how gain searches rank candidates that
        cannot reach it."""
        if not margins.stable:
            return 0.0
        return max(
            0.0,
            min(
                margins.phase_margin_deg / self.phase_margin_deg,
                margins.gain_margin_db / self.gain_margin_db,
            ),
        )

    def met_by(self, margins: Margins) -> bool:
        """Stable, and both margins at least the target's."""
        return (
            margins.stable
            and margins.phase_margin_deg >= self.phase_margin_deg
            and margins.gain_margin_db >= self.gain_margin_db
        )


PRESETS: Final[dict[str, MarginTarget]] = {
    "stiff": MarginTarget("stiff", 40.0, 6.0),
    "medium": MarginTarget("medium", 45.0, 8.0),
    "soft": MarginTarget("soft", 60.0, 12.0),
}
DEFAULT_PRESET: Final[Preset] = "medium"


def _finite(x: float) -> float | None:
    return round(float(x), 3) if math.isfinite(x) else None


def margin_report(margins: Margins, target: MarginTarget) -> dict[str, Any]:
    """The margins of a set of gains against ``target`` (JSON-ready): the numbers, the
    target, whether it is met and, when not, the warning in words."""
    short: list[str] = []
    if not margins.stable:
        short.append("the closed loop is unstable")
    else:
        if margins.phase_margin_deg < target.phase_margin_deg:
            short.append(
                f"phase margin {margins.phase_margin_deg:.1f} deg is below "
                f"{target.phase_margin_deg:g} deg"
            )
        if margins.gain_margin_db < target.gain_margin_db:
            short.append(
                f"gain margin {margins.gain_margin_db:.1f} dB is below {target.gain_margin_db:g} dB"
            )
    return {
        "gain_margin_db": _finite(margins.gain_margin_db),
        "phase_margin_deg": _finite(margins.phase_margin_deg),
        "gain_crossover_hz": _finite(margins.gain_crossover_hz),
        "phase_crossover_hz": _finite(margins.phase_crossover_hz),
        "stable": margins.stable,
        "target": target.to_dict(),
        "meets_target": not short,
        "warning": None
        if not short
        else f"{'; '.join(short)} (target: {target.preset}, PM {target.phase_margin_deg:g} deg"
        f" / GM {target.gain_margin_db:g} dB)",
    }


def target_for(preset: str | None) -> MarginTarget:
    """The preset's target; the default for None. ValueError for an unknown name."""
    try:
        return PRESETS[preset or DEFAULT_PRESET]
    except KeyError:
        raise ValueError(f"unknown margin preset {preset!r}: {', '.join(PRESETS)}") from None
