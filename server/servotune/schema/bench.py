"""The bench's REST bodies: the test form's fields, the user's limits, a test request
and the bench's description of one axis."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field, model_validator

from servotune.descriptor import Conversion

BenchKind = Literal["move", "position_step", "velocity_step", "pwm_step", "frequency_response"]


class BenchField(BaseModel):
    """A field of the bench's test form (``GET /api/axes/{id}/bench``: ``fields``): the
    unit its number is in, and what it reads as in other units."""

    parameter: str | None = Field(
        description="the device parameter the test sets to this value (its unit and "
        "conversions are the field's); null: the field is not a device parameter"
    )
    unit: str
    conversions: list[Conversion]


class BenchLimits(BaseModel):
    """What the user allows the bench to do on one axis (checked before every test)."""

    max_distance_counts: int = Field(default=20_000, ge=1, le=1 << 25)
    max_velocity: int = Field(default=20_000, ge=1, le=1 << 31)
    # le: tuning.plants.OUTPUT_FULL_SCALE (the schema imports no tuning; a unit test
    # holds the two equal).
    max_pwm: int = Field(default=80, ge=1, le=255)
    max_duration_s: float = Field(default=10.0, gt=0, le=60)
    min_position_counts: int | None = Field(
        default=None,
        ge=-(1 << 31),
        le=(1 << 31) - 1,
        description="travel window: no test starts outside it, targets a position outside "
        "it or travels out of it (counts, with max_position_counts; null: no window)",
    )
    max_position_counts: int | None = Field(default=None, ge=-(1 << 31), le=(1 << 31) - 1)

    @model_validator(mode="after")
    def _window(self) -> BenchLimits:
        low, high = self.min_position_counts, self.max_position_counts
        if low is not None and high is not None and low >= high:
            raise ValueError(f"min_position_counts {low} must be below max_position_counts {high}")
        return self

    def outside(self, position: float) -> str | None:
        """Why ``position`` is outside the travel window, or None."""
        if self.min_position_counts is not None and position < self.min_position_counts:
            return f"{position:.0f} is below your min_position_counts {self.min_position_counts}"
        if self.max_position_counts is not None and position > self.max_position_counts:
            return f"{position:.0f} is above your max_position_counts {self.max_position_counts}"
        return None


class BenchTestRequest(BaseModel):
    """``POST /api/axes/{id}/bench/runs``: what to run (units are the device's)."""

    kind: BenchKind = Field(
        description="move | position_step | velocity_step | pwm_step | frequency_response"
    )
    distance: int = 0
    velocity: int = 0
    pwm: int = 0
    duration_s: float = Field(default=2.0, gt=0)
    amplitude: int = Field(
        default=0,
        description="frequency_response: peak of the multisine around the held "
        "position, counts (1..max_distance_counts)",
    )
    low_hz: float = Field(default=1.0, description="frequency_response: lowest tone, Hz")
    high_hz: float = Field(default=40.0, description="frequency_response: highest tone, Hz")
    loop: Literal["closed", "open"] = Field(
        default="closed",
        description="frequency_response: closed (position targets, ma) or open (PWM "
        "through spwm, peak `pwm`; SLAP2 only, needs a travel window and confirmation)",
    )
    confirm_open_loop: bool = Field(
        default=False, description="frequency_response, loop open: the user confirmed"
    )
    note: str = Field(default="", max_length=200)


class BenchInfo(BaseModel):
    """``GET /api/axes/{id}/bench``: the tests, limits and form fields of one axis."""

    kinds: list[str]
    limits: BenchLimits
    definitions: dict[str, str] = Field(description="how each metric is computed")
    fields: dict[str, BenchField] = Field(
        default_factory=dict,
        description="the test form's fields (distance, velocity, pwm): unit, conversions "
        "and the device parameter a field sets",
    )
    whatif: bool = Field(
        default=False, description="the what-if view works here (the device has a law)"
    )
    frequency_response: Literal["measured", "model"] | None = Field(
        default=None,
        description="measured: a multisine injected around the held position; model: the "
        "identified plant under the device's law; null: no frequency_response test",
    )
