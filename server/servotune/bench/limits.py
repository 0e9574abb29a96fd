"""What the user allows the bench to do on one axis, and where it is kept."""

from __future__ import annotations

import asyncio

from pydantic import BaseModel, Field, model_validator

from servotune.hub.hub import Hub
from servotune.hub.state import AxisEntry
from servotune.storage import Storage
from servotune.tuning.plants import OUTPUT_FULL_SCALE


class BenchLimits(BaseModel):
    """What the user allows the bench to do on one axis (checked before every test)."""

    max_distance_counts: int = Field(default=20_000, ge=1, le=1 << 25)
    max_velocity: int = Field(default=20_000, ge=1, le=1 << 31)
    max_pwm: int = Field(default=80, ge=1, le=OUTPUT_FULL_SCALE)
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


class LimitsStore:
    """Each axis' ``BenchLimits`` in storage, under the axis' storage key (the defaults
    until the user sets them); read and written in a worker thread."""

    def __init__(self, hub: Hub, storage: Storage) -> None:
        self._hub = hub
        self._storage = storage

    @staticmethod
    def _key(entry: AxisEntry) -> str:
        return f"bench-limits:{entry.storage_key}"

    async def get(self, axis_id: str) -> BenchLimits:
        """UnknownAxisError (404) for an axis that does not exist."""
        entry = self._hub.entry(axis_id)
        stored = await asyncio.to_thread(self._storage.get_meta, self._key(entry))
        return BenchLimits.model_validate(stored) if stored else BenchLimits()

    async def set(self, axis_id: str, limits: BenchLimits) -> BenchLimits:
        entry = self._hub.entry(axis_id)
        await asyncio.to_thread(self._storage.set_meta, self._key(entry), limits.model_dump())
        return limits
