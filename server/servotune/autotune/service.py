"""``AutoTuner``: the auto-tune sessions, one per axis, on top of the device tuners.

identify -> propose -> (accept) -> verify, the same API and response shapes for every
device (docs/autotune.md). What is common lives here: the per-axis session and lock,
the stop generation, refusals of state, the failure paths (stop the axis, return it
to its start, put the previous gains back, say everything). What differs per device
(excitation, fit, rule, writes) is a ``DeviceTuner`` (``devices/<name>/tuner.py``), which
the registry gives (``Tuners``, injected by the app).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable, Coroutine, Sequence
from typing import Any, Literal, Protocol

from servotune.autotune.context import TuningContext
from servotune.autotune.recommend import Action, decision_record, decision_text, recommend
from servotune.autotune.session import IdentifyRequest, Session
from servotune.bench.service import TestBench
from servotune.compute import ComputePool
from servotune.hub.hub import Hub
from servotune.hub.state import AxisEntry
from servotune.hub.stops import Settled, gains_of
from servotune.link.base import (
    ConfirmationRequiredError,
    DeviceRefusedError,
    DeviceTimeoutError,
    DriverError,
    InvalidArgumentError,
    LinkDownError,
    MeasurementError,
)
from servotune.schema import AutoTuneState
from servotune.storage import StorageError
from servotune.tuning.law import DeviceLaw
from servotune.tuning.predicted import unstable_reason


class DeviceTuner(Protocol):
    """What one device contributes to an auto-tune session (see ``Slap2Tuner``)."""

    @property
    def identifying_message(self) -> str: ...

    @property
    def law(self) -> DeviceLaw:
        """The device's controller law (the proposal's predicted stability)."""
        ...

    def accepts(self, entry: AxisEntry) -> bool:
        """Whether this tuner can drive the axis of ``entry`` (its device's own driver,
        not e.g. a rig's axis seen through the lab bus)."""
        ...

    async def check_request(self, entry: AxisEntry, request: IdentifyRequest) -> int:
        """Refusals before anything moves (422/409); returns the test distance."""
        ...

    async def identify(
        self, entry: AxisEntry, session: Session, request: IdentifyRequest, distance: int
    ) -> dict[str, Any]:
        """Excite, fit, propose; fills the session; returns the proposal's body."""
        ...

    def proposed_message(self, body: dict[str, Any]) -> str: ...

    async def move_back(self, entry: AxisEntry, target: float) -> None:
        """Return to ``target`` with the gains in use (after a failed identification)."""
        ...

    def check_accept(self, entry: AxisEntry, session: Session) -> None: ...

    def previous_gains(self, entry: AxisEntry, session: Session) -> dict[str, int]: ...

    def verify(self, entry: AxisEntry, session: Session) -> Coroutine[Any, Any, dict[str, Any]]:
        """Baseline test, write the proposal, verification test: the result's body."""
        ...

    async def restore(self, entry: AxisEntry, previous: dict[str, int]) -> dict[str, int]: ...

    def verified_message(self, result: dict[str, Any]) -> str: ...

    def check_revert(self, session: Session) -> None: ...

    async def revert(self, entry: AxisEntry, session: Session) -> tuple[dict[str, int], str]:
        """Write the previous gains: (what was written, the session's message)."""
        ...


class Tuners(Protocol):
    """What the auto-tune needs of the registry."""

    def tuner(self, device: str, ctx: TuningContext) -> DeviceTuner | None:
        """A tuner for the axes of ``device``; None: it has none."""
        ...

    def tuned(self) -> Sequence[str]:
        """The devices (titles) that have a tuner, for the refusal of the others."""
        ...


class AutoTuning(Protocol):
    """What the API asks of the auto-tune (``AutoTuner``, or at the lab hub
    ``bus.autotune.HubAutoTuner``, which forwards a rig's axis to the rig)."""

    def session(self, axis_id: str) -> dict[str, Any]: ...

    async def identify(self, axis_id: str, request: IdentifyRequest) -> dict[str, Any]: ...

    async def accept(self, axis_id: str, *, confirm_unstable: bool = False) -> dict[str, Any]: ...

    async def keep(self, axis_id: str) -> dict[str, Any]: ...

    async def revert(self, axis_id: str) -> dict[str, int]: ...


class AutoTuner:
    """identify -> propose -> accept -> verify, one session per axis of a device that
    has a tuner (``Tuners``).

    Everything that changes the device goes through the hub (``write_params``,
    ``command``) or the bench (recorded tests). Refusals (limits, wrong device, busy)
    happen before anything moves. On any error the axis is stopped (``st``); a stop
    that cannot reach the axis is repeated when its link is back.
    """

    def __init__(
        self,
        hub: Hub,
        bench: TestBench,
        *,
        tuners: Tuners,
        clock: Callable[[], float] = time.monotonic,
        compute: ComputePool | None = None,
    ) -> None:
        """``tuners``: the devices' tuners (the registry); ``compute``: the app's worker
        process for the fits (a pool of its own if none is given; its worker starts only
        when a fit runs)."""
        self._hub = hub
        self._ctx = TuningContext(hub, bench, clock, compute or ComputePool())
        self._sessions: dict[str, Session] = {}
        self._locks: dict[str, asyncio.Lock] = {}
        self._tuner_source = tuners
        self._tuners: dict[str, DeviceTuner | None] = {}

    # --- queries ----------------------------------------------------------------------

    def session(self, axis_id: str) -> dict[str, Any]:
        self._check_device(axis_id)
        return self._session(axis_id).to_dict()

    def _session(self, axis_id: str) -> Session:
        session = self._sessions.get(axis_id)
        if session is None:
            session = self._sessions[axis_id] = Session(axis_id)
        return session

    def _check_device(self, axis_id: str) -> tuple[AxisEntry, DeviceTuner]:
        entry = self._hub.entry(axis_id)
        device = entry.info.device
        if device not in self._tuners:
            self._tuners[device] = self._tuner_source.tuner(device, self._ctx)
        tuner = self._tuners[device]
        if tuner is None or not tuner.accepts(entry):
            tuned = " and ".join(self._tuner_source.tuned())
            raise DeviceRefusedError(f"auto-tune supports {tuned} axes so far")
        return entry, tuner

    def _lock(self, axis_id: str) -> asyncio.Lock:
        lock = self._locks.get(axis_id)
        if lock is None:
            lock = self._locks[axis_id] = asyncio.Lock()
        if lock.locked():
            raise DeviceRefusedError("auto-tune is already running on this axis")
        return lock

    def _set(self, session: Session, state: AutoTuneState, message: str) -> None:
        session.set(state, message)
        level: Literal["info", "error"] = "error" if state == "failed" else "info"
        self._hub.on_event(level, session.axis_id, f"auto-tune: {message}")

    # --- identify ---------------------------------------------------------------------

    async def identify(self, axis_id: str, request: IdentifyRequest) -> dict[str, Any]:
        """Identify the plant within the user's limits and propose gains."""
        entry, tuner = self._check_device(axis_id)
        ctx = self._ctx
        async with self._lock(axis_id):  # acquired at once: a second call is refused
            await self._hub.take_over(entry)  # the demo autopilot lets go, moves end
            ctx.started(entry)
            distance = await tuner.check_request(entry, request)
            session = self._session(axis_id)
            session.reset(request)
            self._set(session, "identifying", tuner.identifying_message)
            start = ctx.position(entry.latest)
            try:
                body = await tuner.identify(entry, session, request, distance)
                # the tuner's body is the session's proposal_dict: both carry it
                body["recommendation"] = recommend(body)
            except asyncio.CancelledError:
                await ctx.safe_stop(entry)
                self._set(session, "failed", "cancelled: the axis was stopped")
                raise
            except (DriverError, ValueError) as exc:
                await ctx.safe_stop(entry)
                back = await self._return_after_failure(entry, start, request, tuner.move_back)
                message = f"identification failed: {exc}; axis stopped{back}"
                self._set(session, "failed", message)
                if isinstance(exc, InvalidArgumentError):
                    raise InvalidArgumentError(exc.field, message) from exc
                if isinstance(exc, LinkDownError | DeviceTimeoutError):
                    raise type(exc)(message) from exc
                if isinstance(exc, MeasurementError | ValueError):
                    # The fit or the record could not support a model: nothing refused.
                    raise MeasurementError(message) from exc
                raise DeviceRefusedError(message) from exc
            settled = await self._settle(entry, "auto-tune identification")
            if settled is not None:
                self._set(session, "failed", settled.message)
                raise DeviceRefusedError(settled.message)
            self._set(session, "proposed", tuner.proposed_message(body))
            return body

    async def _settle(self, entry: AxisEntry, reason: str) -> Settled | None:
        """Nothing an auto-tune step set going is left oscillating (the hub's stop
        service): the gains it had found, else the last verified ones, are put back."""
        gains = gains_of(entry.driver.descriptor, entry.device_values)
        restore = self._hub.verified_gains.get(entry.info.id, gains)
        try:
            return await self._hub.stops.settle_check(
                entry.info.id, gains_now=gains, restore=restore, reason=reason
            )
        except DriverError as exc:
            self._hub.on_event("error", entry.info.id, f"{reason}: after the step: {exc}")
            return None

    async def _return_after_failure(
        self,
        entry: AxisEntry,
        start: float,
        request: IdentifyRequest,
        move_back: Callable[[AxisEntry, float], Coroutine[Any, Any, None]],
    ) -> str:
        """After a failed identification: move the axis back to ``start`` with the gains
        in use (they held it there before), unless the user pressed STOP, the link is
        down or the way back is longer than the user's limit. Returns what happened,
        as the tail of the failure message."""
        ctx = self._ctx
        if ctx.stopped(entry):
            return " (STOP: it stays where it is)"
        if self._hub.link_status(entry.link.id).state != "connected" or entry.latest is None:
            return " (the link is down: it stays where it is)"
        try:
            away = abs(ctx.position(entry.latest) - start)
        except DriverError:
            return " (no position: it stays where it is)"
        if away < 1:
            return " at its start"
        if away > request.max_distance_counts * 1.05 + 100:
            return (
                f" {away:.0f} counts from its start, more than your max_distance_counts: "
                "it stays where it is"
            )
        try:
            await move_back(entry, start)
        except DriverError as exc:
            await ctx.safe_stop(entry)
            return f"; returning to its start failed ({exc}): it stays where it is"
        return f", then returned to its start ({away:.0f} counts back)"

    # --- accept and verify ------------------------------------------------------------

    async def accept(self, axis_id: str, *, confirm_unstable: bool = False) -> dict[str, Any]:
        """Baseline test (previous gains), write the proposal, verification test.

        A proposal its own identified plant predicts unstable (``tuning.predicted``) is
        refused (``ConfirmationRequiredError``, field ``confirm_unstable``) unless
        ``confirm_unstable``."""
        entry, tuner = self._check_device(axis_id)
        lock = self._lock(axis_id)
        session = self._session(axis_id)
        if session.state == "kept":
            raise DeviceRefusedError(
                "this proposal was declined (the gains in use were kept): identify again "
                "for a new one"
            )
        # From now on a user's STOP ends the verification (see TuningContext.command).
        self._ctx.started(entry)
        tuner.check_accept(entry, session)
        self._ctx.check_idle(entry)
        gains = (session.proposal_dict or {}).get("gains")
        if not confirm_unstable and gains and session.model:
            why = await self._ctx.compute.run(unstable_reason, tuner.law, session.model, gains)
            if why:
                raise ConfirmationRequiredError(
                    "confirm_unstable",
                    f"the proposed gains: {why}. Accept them only if you mean it "
                    "(confirm_unstable=true); the verification's axis is watched and "
                    "braked if it oscillates, and the previous gains are put back",
                )
        async with lock:
            await self._decide(entry, session, "write", dict(gains or {}))
            previous = tuner.previous_gains(entry, session)
            result = await self._guarded_verify(
                entry,
                session,
                tuner.verify(entry, session),
                previous=previous,
                restore=lambda: tuner.restore(entry, previous),
            )
            if result.get("stopped"):
                return result
            self._hub.verified_gains[axis_id] = dict(result.get("gains") or {})
            self._set(session, "verified", tuner.verified_message(result))
            return result

    async def keep(self, axis_id: str) -> dict[str, Any]:
        """Decline the proposal: the gains in use stay, nothing is written to the
        device. The decision is recorded (session, history, the identification run)."""
        entry, _tuner = self._check_device(axis_id)
        session = self._session(axis_id)
        async with self._lock(axis_id):
            proposal = session.proposal_dict
            if session.state != "proposed" or proposal is None:
                raise DeviceRefusedError("no proposal to decide on: run identify first")
            decision = await self._decide(
                entry, session, "keep", dict(proposal.get("current_gains") or {})
            )
            self._set(session, "kept", decision_text(decision))
            return decision

    async def _decide(
        self, entry: AxisEntry, session: Session, action: Action, gains: dict[str, int]
    ) -> dict[str, Any]:
        """Record the user's choice for the session's proposal: in the session (and its
        history), as an event, and on the identification run (its ``autotune.decision``
        and its note), so the run list shows what became of the proposal."""
        proposal = session.proposal_dict or {}
        run_id = session.identification_run_id
        decision = decision_record(
            action,
            proposal.get("recommendation"),
            gains,
            at_s=time.time(),
            identification_run_id=run_id,
        )
        session.decide(decision)
        self._hub.on_event(
            "info" if decision["followed"] else "warning",
            entry.info.id,
            f"auto-tune: {decision_text(decision)}",
        )
        if run_id is not None:
            bench = self._ctx.bench
            try:
                meta = await bench.get_run_meta(run_id)
                test = dict(meta.get("test") or {})
                note = str(test.get("note") or "").split(" · decision: ")[0]
                test["note"] = f"{note} · decision: {decision_text(decision)}"
                autotune = dict(meta.get("autotune") or {}) | {"decision": decision}
                await bench.update_run_meta(run_id, {"test": test, "autotune": autotune})
            except (KeyError, StorageError) as exc:
                # the decision stands (session, event); only its copy on the run is lost
                self._hub.on_event(
                    "warning",
                    entry.info.id,
                    f"auto-tune: the decision was not recorded on run {run_id}: {exc}",
                )
        return decision

    async def _guarded_verify(
        self,
        entry: AxisEntry,
        session: Session,
        verification: Coroutine[Any, Any, dict[str, Any]],
        *,
        previous: dict[str, int],
        restore: Callable[[], Coroutine[Any, Any, dict[str, int]]],
    ) -> dict[str, Any]:
        """Run a device's verification; on any failure stop the axis, put the previous
        gains back (the new ones were not verified) and say so.

        A user's STOP is not an error of the server: the answer is a normal result
        with ``stopped: true``, ``message`` and ``gains_in_force``. If the previous
        gains cannot be written back, ``unverified: true`` and the message says
        loudly that the new gains are in force unverified (``revert`` puts them
        back). Other failures answer an error naming the same."""
        ctx = self._ctx
        self._set(session, "verifying", "baseline and verification tests")
        try:
            result = await verification
        except asyncio.CancelledError:
            await ctx.safe_stop(entry)
            with contextlib.suppress(DriverError):
                await restore()
            self._set(session, "failed", "cancelled: the axis was stopped")
            raise
        except DriverError as exc:
            stopped = ctx.stopped(entry)
            await ctx.safe_stop(entry)
            unverified = False
            restored_note = "the previous gains are in force again"
            if any(entry.device_values.get(k) != v for k, v in previous.items()):
                try:
                    await restore()
                except DriverError as restore_exc:
                    unverified = True
                    restored_note = (
                        f"THE NEW GAINS ARE IN FORCE, UNVERIFIED: writing back the previous "
                        f"gains failed ({restore_exc}); press Revert when the axis is back"
                    )
            cause = entry.stop_cause if stopped else str(exc)
            message = f"verification ended: {cause}; axis stopped; {restored_note}"
            self._set(session, "failed", message)
            body = {
                "stopped": stopped,
                "unverified": unverified,
                "message": message,
                "verdict": "stopped" if stopped else "failed",
                "previous_gains": previous,
                "gains_in_force": {k: entry.device_values.get(k) for k in previous},
            }
            session.result = body
            if stopped:
                return body
            if isinstance(exc, LinkDownError):
                raise LinkDownError(message) from exc
            if isinstance(exc, DeviceTimeoutError):
                raise DeviceTimeoutError(message) from exc
            raise DeviceRefusedError(message) from exc
        session.result = result
        return result

    async def revert(self, axis_id: str) -> dict[str, int]:
        """Write the gains that were in use before the accepted proposal."""
        entry, tuner = self._check_device(axis_id)
        lock = self._lock(axis_id)
        session = self._session(axis_id)
        tuner.check_revert(session)
        async with lock:
            written, message = await tuner.revert(entry, session)
            self._set(session, "idle", message)
            return written
