"""A driver with the stop modes that records what it is asked for and sends nothing
(the hub's stop decisions and checks, tested without a device)."""

from __future__ import annotations

from servotune.link.base import StopOutcome


class RecordingStops:
    """Its stops say what they are; ``brake_action``: what its brake leaves the axis in
    (``"brake"``, or ``"power_off"`` for a device whose brake is its power-off)."""

    def __init__(self, brake_action: str = "brake") -> None:
        self.asked: list[str] = []
        self._brake_action = brake_action

    async def _say(self, name: str, action: str) -> StopOutcome:
        self.asked.append(name)
        return StopOutcome([name], action, name)  # type: ignore[arg-type]

    async def stop(self) -> StopOutcome:
        return await self._say("stop", "hold")

    async def controlled_stop(self) -> StopOutcome:
        return await self._say("controlled_stop", "hold")

    async def power_off(self) -> StopOutcome:
        return await self._say("power_off", "power_off")

    async def brake(self) -> StopOutcome:
        return await self._say("brake", self._brake_action)

    async def hold_here(self) -> StopOutcome:
        return await self._say("hold_here", "hold")
