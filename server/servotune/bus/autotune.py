"""Auto-tune of a rig's axis from the hub: the rig runs it, the hub forwards.

The hub's ``AutoTuner`` cannot tune a rig's axis itself (the tests are planned and
recorded by the rig's bench, the rig's limits apply, and the sequence must not depend
on the lab network between its steps). ``HubAutoTuner`` sends identify, accept, keep
and revert to the rig as NATS requests (``cmd.autotune_identify`` ...); the rig checks
them exactly as its REST routes do (permission, control lock, the limits against its
bench limits and the device) and runs them with its own ``AutoTuner``. The hub
session becomes the axis' mover on the rig, so while the tests run the rig's dead-man
applies: the hub's keep-alives missing for the rig's lease stop the axis.

The requests are long (identify about 2-4 s, accept 3-8 s on a simulated line, more on
a loaded host): they wait ``AUTOTUNE_TIMEOUT_S``, not the port's 5 s. A reply that
never comes (the lab network cut meanwhile) is a timeout at the hub; the rig finishes
or stops on its own (its dead-man, its AutoTuner's own failure path).

The session the hub shows is the one the rig sent with its last reply (``session()``
is synchronous): a tuning run from the rig's own dashboard is not seen at the hub
until the hub asks the rig again.
"""

from __future__ import annotations

from typing import Any, Final

from servotune.autotune.service import AutoTuner
from servotune.autotune.session import IdentifyRequest, Session
from servotune.bus import subjects
from servotune.bus.remote import RemoteAxis
from servotune.hub.hub import Hub
from servotune.link.base import DriverError

AUTOTUNE_TIMEOUT_S: Final = 120.0


class HubAutoTuner:
    """The auto-tune at the lab hub (``AutoTuning``): a rig's axis is tuned by the rig,
    every other axis by ``local``."""

    def __init__(self, hub: Hub, local: AutoTuner) -> None:
        self._hub = hub
        self.local = local
        # The session each rig sent with its last auto-tune reply, by the hub's axis id.
        self._remote_sessions: dict[str, dict[str, Any]] = {}

    def _remote(self, axis_id: str) -> RemoteAxis | None:
        driver = getattr(self._hub.entry(axis_id), "driver", None)
        return driver if isinstance(driver, RemoteAxis) else None

    def session(self, axis_id: str) -> dict[str, Any]:
        if self._remote(axis_id) is None:
            return self.local.session(axis_id)
        known = self._remote_sessions.get(axis_id)
        return dict(known) if known is not None else Session(axis_id).to_dict()

    async def _forward(
        self, axis: RemoteAxis, axis_id: str, verb: str, args: dict[str, object]
    ) -> Any:
        sessions = self._remote_sessions
        try:
            reply = await axis.autotune(verb, args, AUTOTUNE_TIMEOUT_S)
        except DriverError as exc:
            # Shown as the rig's state is unknown: the error, not a stale proposal.
            previous = sessions.get(axis_id) or Session(axis_id).to_dict()
            sessions[axis_id] = {**previous, "message": f"auto-tune on the rig: {exc}"}
            raise
        session = reply.get("session")
        if isinstance(session, dict):
            sessions[axis_id] = {**session, "axis": axis_id}
        return reply.get("result")

    async def identify(self, axis_id: str, request: IdentifyRequest) -> dict[str, Any]:
        axis = self._remote(axis_id)
        if axis is None:
            return await self.local.identify(axis_id, request)
        result = await self._forward(
            axis, axis_id, subjects.AUTOTUNE_IDENTIFY, request.model_dump(exclude_none=True)
        )
        return result if isinstance(result, dict) else {}

    async def accept(self, axis_id: str, *, confirm_unstable: bool = False) -> dict[str, Any]:
        axis = self._remote(axis_id)
        if axis is None:
            return await self.local.accept(axis_id, confirm_unstable=confirm_unstable)
        args: dict[str, object] = {"confirm_unstable": True} if confirm_unstable else {}
        result = await self._forward(axis, axis_id, subjects.AUTOTUNE_ACCEPT, args)
        return result if isinstance(result, dict) else {}

    async def keep(self, axis_id: str) -> dict[str, Any]:
        axis = self._remote(axis_id)
        if axis is None:
            return await self.local.keep(axis_id)
        result = await self._forward(axis, axis_id, subjects.AUTOTUNE_KEEP, {})
        return result if isinstance(result, dict) else {}

    async def revert(self, axis_id: str) -> dict[str, int]:
        axis = self._remote(axis_id)
        if axis is None:
            return await self.local.revert(axis_id)
        result = await self._forward(axis, axis_id, subjects.AUTOTUNE_REVERT, {})
        if not isinstance(result, dict):
            return {}
        return {str(k): int(v) for k, v in result.items()}
