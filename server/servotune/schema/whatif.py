"""The what-if view (``GET /api/axes/{id}/whatif``) and the margins a set of gains is
designed to and reaches (the auto-tune and the frequency response report them too)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from servotune.schema.base import Number, _Shape
from servotune.schema.law import ControllerLaw

MarginPreset = Literal["stiff", "medium", "soft"]


class MarginTarget(BaseModel):
    """The phase and gain margins a set of gains is designed to (a preset)."""

    model_config = ConfigDict(extra="forbid")

    preset: MarginPreset
    phase_margin_deg: Number
    gain_margin_db: Number


class VerifyProfile(BaseModel):
    """The move of an auto-tune verification step, as the what-if view replays it."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["position_step", "move"]
    velocity_counts_s: Number
    acceleration_counts_s2: Number


class WhatIfPlant(BaseModel):
    """The identified velocity plant ``g / (s (tau s + 1))`` and where it comes from."""

    model_config = ConfigDict(extra="forbid")

    gain_counts_s_per_unit: Number
    tau_s: Number
    source: str


class WhatIfModel(BaseModel):
    """The plant discretised at the controller period and the device's law as data.

    ``plant_num``/``plant_den``: ``y[n] = sum(num[i] u[n-i]) - sum(den[i] y[n-i], i>=1)``
    with ``den[0] == 1``."""

    model_config = ConfigDict(extra="forbid")

    device: str
    law: str
    controller: ControllerLaw
    period_s: Number
    plant_num: list[float]
    plant_den: list[float]
    pwm_limit: Number
    plant: WhatIfPlant


class WhatIfInfo(BaseModel):
    """``GET /api/axes/{id}/whatif``: the gains now and their ranges, the margin targets,
    the verification move and the model (null with ``problem`` until identified)."""

    model_config = ConfigDict(extra="forbid")

    axis_id: str
    device: str
    gains: dict[str, Number | None]
    ranges: dict[str, tuple[Number, Number]]
    model: WhatIfModel | None
    problem: str | None
    target: MarginTarget = Field(description="what the margins are read against")
    targets: dict[str, MarginTarget]
    proposal: dict[str, Number] | None = Field(
        description="the auto-tune's proposed gains, if there is a proposal"
    )
    verify: VerifyProfile


class MarginReport(_Shape):
    """A set of gains' margins on the identified model against a target: null margins
    where there is no crossover; ``warning`` says what misses the target."""

    gain_margin_db: Number | None
    phase_margin_deg: Number | None
    gain_crossover_hz: Number | None
    phase_crossover_hz: Number | None
    stable: bool | None
    target: MarginTarget
    meets_target: bool | None = Field(description="null: a margin could not be measured")
    warning: str | None
