"""A device's controller law as data (served by the what-if view, evaluated by
``servotune.tuning``)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field


class LawTerm(BaseModel):
    """One term of a controller law: ``coefficient x product(gains) x signal[n - delay]``."""

    coefficient: float
    gains: list[str] = Field(
        description="gain names, each read as the law's gain set prefix + name"
    )
    signal: Literal["error", "error_sum", "position"] = Field(
        description="error: target - position (counts); error_sum: the running sum of the "
        "error including this tick; position: the measured position (counts)"
    )
    delay: int = Field(default=0, ge=0, description="ticks")


class LawGainSet(BaseModel):
    """Which device parameters a law's gains are while the target moves or holds."""

    when: Literal["moving", "holding", "always"]
    prefix: str = Field(description="prepended to a term's gain names (e.g. 'kabh_')")


class ControllerLaw(BaseModel):
    """A device's controller law as data, every tick (the what-if view evaluates it):
    ``u = round(sum(terms) / divisor)``, clamped to the output limit. A linear analysis
    uses the holding gain set (else the one for always)."""

    terms: list[LawTerm]
    divisor: float
    rounding: Literal["none", "trunc"] = Field(
        description="none: u is the exact quotient; trunc: rounded towards zero"
    )
    gain_sets: list[LawGainSet]
