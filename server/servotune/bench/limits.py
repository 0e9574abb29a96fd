"""What the user allows the bench to do on one axis, and where it is kept."""

from __future__ import annotations

import asyncio

from servotune.hub.hub import Hub
from servotune.hub.state import AxisEntry
from servotune.schema import BenchLimits as BenchLimits  # importable from here too
from servotune.storage import Storage


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
