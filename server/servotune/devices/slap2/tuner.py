"""The SLAP2 half of the auto-tune: open-loop staircase, fit, proposal, verification.

docs/autotune.md describes what the user sees. The science is in the shared core:
the staircase, the driver's timing and the law in ``devices.slap2.law``, the fit
in ``tuning.identify``, the rule in ``devices.slap2.gain_rule``; this module sequences it
on a live axis through ``TuningContext`` (hub and bench). The fit and the gain search
run in the worker process (``servotune.compute``): nothing heavy on the event loop,
and no thread that holds the interpreter lock against it.
"""

from __future__ import annotations

import asyncio
from dataclasses import replace
from typing import Any, Final

from servotune.autotune.context import TuningContext
from servotune.autotune.recording import IdentificationRun
from servotune.autotune.session import IdentifyRequest, Session
from servotune.autotune.verdict import verdict_with_reason
from servotune.bench.metrics import unmeasured
from servotune.devices.slap2.codec import ACCELERATION_MAX, DEFAULT_BAUD, VELOCITY_MAX
from servotune.devices.slap2.gain_rule import Slap2Proposal, propose_gains, settles
from servotune.devices.slap2.law import (
    IDENT_MIN_DISTANCE,
    STAIRCASE_START_PWM,
    Gains,
    MoveSpec,
    Slap2Law,
    Staircase,
    align_identification,
    command_tail_s,
    model_doubt,
)
from servotune.hub.state import AxisEntry
from servotune.link.base import (
    CommandClock,
    DeviceRefusedError,
    DriverError,
    InvalidArgumentError,
    capture_of,
)
from servotune.schema import AutoTuneTestKind
from servotune.tuning.identify import fit_plant
from servotune.tuning.plants import PlantModel
from servotune.tuning.targets import target_for

IDENT_ATTEMPTS: Final = 2  # a doubtful fit is repeated once
MAX_SLOWDOWN: Final = 1.3  # cap of the per-character stretch of the command tail
UCON_BIT: Final = 1 << 5  # syscon: the module replies -1UC itself (no rss check)
SETTLE_TIMEOUT_S: Final = 3.0
RETURN_HORIZON_S: Final = 2.0  # a return move must settle this soon on the model
TEST_RECORD_S: Final = 1.5  # recorded after the profile's end (ends earlier once settled)
DEFAULT_TEST_DISTANCE: Final = 1000
SETTINGS: Final = ("kp", "ki", "kd", "velocity", "acceleration", "inpos_window", "inpos_time")


class Slap2Tuner:
    """identify -> propose -> accept -> verify on SLAP2 axes (``autotune.DeviceTuner``)."""

    identifying_message: Final = "identifying the plant (open-loop PWM staircase)"
    law: Final = Slap2Law()  # tuning.law.DeviceLaw: the proposal's stability check

    def __init__(self, ctx: TuningContext) -> None:
        self._ctx = ctx

    def accepts(self, entry: AxisEntry) -> bool:
        return True  # any SLAP2 axis the hub has

    # --- checks before anything moves -------------------------------------------------

    async def check_request(self, entry: AxisEntry, request: IdentifyRequest) -> int:
        """Refusals (422 naming the limit, 409 for state); returns the test distance."""
        limits = await self._ctx.bench.limits(entry.info.id)
        if request.max_pwm > limits.max_pwm:
            raise InvalidArgumentError(
                "max_pwm",
                f"max_pwm {request.max_pwm} exceeds your bench limit of ±{limits.max_pwm}",
            )
        distance = request.checked_distance(
            limits.max_distance_counts, IDENT_MIN_DISTANCE, DEFAULT_TEST_DISTANCE
        )
        self._ctx.check_idle(entry)
        self._current_gains(entry)  # read before anything moves
        await self._ctx.check_at_rest(entry)
        return distance

    @staticmethod
    def _current_gains(entry: AxisEntry) -> Gains:
        values = entry.device_values
        try:
            return Gains(values["kp"], values["ki"], values["kd"])
        except KeyError:
            raise DeviceRefusedError("the axis' gains are not read yet") from None

    @staticmethod
    def _spec(
        entry: AxisEntry, test: AutoTuneTestKind, distance: int, latency_s: float
    ) -> MoveSpec:
        values = entry.device_values
        if test == "position_step":
            velocity, acceleration = VELOCITY_MAX, ACCELERATION_MAX
        else:
            velocity, acceleration = values.get("velocity", 0), values.get("acceleration", 0)
            if velocity == 0 or acceleration == 0:
                raise DeviceRefusedError("the axis' velocity or acceleration is 0: no move")
        return MoveSpec(
            distance=distance,
            velocity=velocity,
            acceleration=acceleration,
            band=values.get("inpos_window", 5),
            inpos_ticks=values.get("inpos_time", 50),
            latency_s=latency_s,
        )

    # --- identify ---------------------------------------------------------------------

    async def identify(
        self, entry: AxisEntry, session: Session, request: IdentifyRequest, distance: int
    ) -> dict[str, Any]:
        """Staircase and fit (repeated once if doubtful), then the proposal."""
        ctx = self._ctx
        axis_id = entry.info.id
        current = self._current_gains(entry)
        start = ctx.position(entry.latest)
        attempts: list[tuple[PlantModel, float, int, str]] = []
        for attempt in range(IDENT_ATTEMPTS):
            model, latency, travel, run_id = await self._identify_once(entry, request, start)
            session.identification_run_id = run_id
            attempts.append((model, latency, travel, run_id))
            doubt = model_doubt(model, travel)
            ctx.hub.on_event(
                "info" if doubt is None else "warning",
                axis_id,
                f"auto-tune: model K={model.gain:.0f} counts/s per PWM, tau="
                f"{model.tau_s * 1000:.1f} ms, friction {model.friction_pwm:.1f} PWM (rms "
                f"{model.rms_error_counts:.1f} counts)" + (f": {doubt}" if doubt else ""),
            )
            await self._return_to(entry, start, model, current)
            if doubt is None or attempt + 1 == IDENT_ATTEMPTS:
                break
        model, latency, travel, run_id = min(
            attempts, key=lambda a: (model_doubt(a[0], a[2]) is not None, a[0].rms_error_counts)
        )
        session.model = model.to_dict()
        doubt = model_doubt(model, travel)
        spec = self._spec(entry, request.test, request.direction * distance, latency)
        proposal = await self._ctx.compute.run(
            propose_gains,
            model,
            spec,
            request.response,
            current,
            max_excursion=request.max_distance_counts,
            target=target_for(request.margins),
        )
        body = proposal.to_dict()
        body["identification_run_id"] = run_id
        body["identification_run_ids"] = [a[3] for a in attempts]
        body["travel_counts"] = travel
        body["warnings"] = [] if doubt is None else [doubt]
        body["baseline_possible"] = proposal.default_excursion <= request.max_distance_counts
        session.proposal = proposal
        session.proposal_dict = body
        session.device_settings = {k: v for k, v in entry.device_values.items() if k in SETTINGS}
        return body

    @staticmethod
    def proposed_message(body: dict[str, Any]) -> str:
        g, c = body["gains"], body["current_gains"]
        return (
            f"proposed kp={g['kp']} ki={g['ki']} kd={g['kd']} "
            f"(now kp={c['kp']} ki={c['ki']} kd={c['kd']})"
        )

    async def _identify_once(
        self, entry: AxisEntry, request: IdentifyRequest, start: float
    ) -> tuple[PlantModel, float, int, str]:
        """One recorded staircase and its fit: (model, command latency, travel, run id)."""
        ctx = self._ctx
        status_now = ctx.hub.link_status(entry.link.id)
        slowdown = 1.0
        if status_now.rate_hz > 0 and status_now.wire_limit_hz > 0:
            ratio = status_now.wire_limit_hz / status_now.rate_hz
            slowdown = min(MAX_SLOWDOWN, max(1.0, ratio))
        baud = entry.link.baud or DEFAULT_BAUD
        rss_check = not entry.device_values.get("syscon", 0) & UCON_BIT
        run = IdentificationRun(ctx.bench, entry, start, request.max_pwm, STAIRCASE_START_PWM)
        await run.open(ctx.clock)
        status, message = "incomplete", "identification failed"
        extra: dict[str, Any] = {"timing": {"baud": baud, "slowdown": slowdown}}
        try:
            for _ in range(2):  # the shaft at rest before the first step
                await ctx.next_sample(entry)
            schedule, round_trips, travel = await self._staircase(entry, request, start, run)
            status, message = "complete", ""
            extra["schedule"] = [[round(t, 6), u] for t, u in schedule]
            extra["travel_counts"] = travel
        finally:
            await run.close(status, message, extra)
        index = run.columns.index("position")
        rows = [row for row in run.samples if row[index] is not None]
        times, positions, effective = align_identification(
            [row[0] for row in rows],
            [row[index] for row in rows],
            schedule,
            baud=baud,
            rss_check=rss_check,
            slowdown=slowdown,
            commands_latched=isinstance(getattr(entry, "driver", None), CommandClock),
        )
        try:
            # the model is symmetric: a negative staircase is fitted mirrored
            sign = request.direction
            model = await self._ctx.compute.run(
                fit_plant,
                times,
                [sign * p for p in positions],
                [(t, sign * u) for t, u in effective],
            )
        except ValueError as exc:
            raise InvalidArgumentError("max_pwm", f"{exc} (max_pwm {request.max_pwm})") from None
        # A bench test stamps t0 before sending its trigger: its round trip less the
        # part after the command took effect.
        tail = command_tail_s(baud, rss_check=rss_check)
        trips = sorted(round_trips)
        latency = max(0.0, trips[len(trips) // 2] - tail * slowdown)
        extra["model"] = model.to_dict()
        return model, latency, travel, run.run_id

    def _command_moment(self, entry: AxisEntry) -> float:
        """When the last command took effect: the driver's latch estimate where it
        has one (``CommandClock``), else now (``align_identification`` corrects it)."""
        driver = getattr(entry, "driver", None)
        if isinstance(driver, CommandClock) and driver.last_command_latch_s is not None:
            return driver.last_command_latch_s
        return self._ctx.clock()

    async def _staircase(
        self, entry: AxisEntry, request: IdentifyRequest, start: float, run: IdentificationRun
    ) -> tuple[list[tuple[float, int]], list[float], int]:
        """The ``Staircase`` excitation on the axis, then PWM 0 (the bridge shorts the
        motor: it brakes) until the shaft stands still, then ``st``. Returns the
        (return time, PWM) schedule, the command round trips and the travel."""
        ctx = self._ctx
        plan = Staircase(request.max_pwm, request.max_distance_counts)
        schedule: list[tuple[float, int]] = []
        round_trips: list[float] = []
        u = plan.first_pwm()
        began = ctx.clock()
        last = entry.latest
        travel = 0.0
        while True:
            signed = request.direction * u
            round_trips.append(await ctx.command(entry, "open_loop_pwm", {"pwm": signed}))
            schedule.append((self._command_moment(entry), signed))
            run.progress(f"PWM {u}, travel {round(travel)} counts")
            level_end = ctx.clock() + plan.dwell_s
            brake = False
            while not brake and ctx.clock() < level_end:
                sample = await ctx.sample_before(entry, level_end)
                if sample is None:
                    break
                position = ctx.position(sample)
                travel = abs(position - start)
                speed, gap = 0.0, 0.05
                if last is not None and sample.t > last.t:
                    gap = sample.t - last.t
                    speed = abs(position - ctx.position(last)) / gap
                last = sample
                brake = plan.must_brake(travel, speed, gap)
            if plan.finished(u, travel, ctx.clock() - began, brake):
                break
            u = plan.next_pwm(u)
        round_trips.append(await ctx.command(entry, "open_loop_pwm", {"pwm": 0}))
        schedule.append((self._command_moment(entry), 0))
        still_since: float | None = None
        previous = ctx.position(entry.latest)
        deadline = ctx.clock() + 1.0
        while ctx.clock() < deadline:
            sample = await ctx.next_sample(entry)
            position = ctx.position(sample)
            if position == previous:
                still_since = still_since or sample.t
                if sample.t - still_since >= 0.15:
                    break
            else:
                still_since = None
            previous = position
        await ctx.command(entry, "stop", {})
        return schedule, round_trips, round(abs(ctx.position(entry.latest) - start))

    # --- moves ------------------------------------------------------------------------

    async def _return_to(
        self, entry: AxisEntry, target: float, model: PlantModel, gains: Gains
    ) -> None:
        """Move back to ``target`` with ``gains`` if the model says they hold the axis."""
        position = self._ctx.position(entry.latest)
        distance = round(target - position)
        if distance == 0:
            await self._ctx.command(entry, "position_mode", {})
            return
        spec = replace(self._spec(entry, "move", distance, 0.0), horizon_s=RETURN_HORIZON_S)
        if not settles(model, gains, spec):
            self._ctx.hub.on_event(
                "warning",
                entry.info.id,
                "auto-tune: the model predicts the current gains do not settle: the axis "
                "stays stopped where it is",
            )
            return
        await self._move_and_wait(entry, round(target), spec.profile_time_s())

    async def _move_and_wait(self, entry: AxisEntry, target: int, profile_s: float) -> None:
        ctx = self._ctx
        latest = entry.latest
        # The line is devoted to the axis for the move too (docs/capture.md): its end is
        # seen at once, and a host slow to poll two modules cannot starve the wait.
        async with capture_of(entry.driver, reason="auto-tune move"):
            if latest is None or not latest.flags.get("pm"):
                await ctx.command(entry, "position_mode", {})
            await ctx.command(entry, "move_absolute", {"position": target})
            deadline = ctx.clock() + profile_s + SETTLE_TIMEOUT_S
            await asyncio.sleep(0.1)
            while ctx.clock() < deadline:
                sample = await ctx.next_sample(entry)
                if sample.flags.get("inpos") and not sample.flags.get("move"):
                    return
        raise DriverError(f"the axis did not settle at {target} within {SETTLE_TIMEOUT_S} s")

    async def move_back(self, entry: AxisEntry, target: float) -> None:
        """Hold (pm) and move to ``target`` with the axis' own profile."""
        distance = round(target - self._ctx.position(entry.latest)) or 1
        spec = self._spec(entry, "move", distance, 0.0)
        await self._move_and_wait(entry, round(target), spec.profile_time_s())

    # --- accept, verify, revert -------------------------------------------------------

    @staticmethod
    def check_accept(entry: AxisEntry, session: Session) -> None:
        """409 without a proposal, or with settings changed since it."""
        if session.state != "proposed" or session.proposal is None or session.request is None:
            raise DeviceRefusedError("no proposal to accept: run identify first")
        changed = {
            k: (v, entry.device_values.get(k))
            for k, v in session.device_settings.items()
            if entry.device_values.get(k) != v
        }
        if changed:
            listing = ", ".join(f"{k} {now} (was {was})" for k, (was, now) in changed.items())
            raise DeviceRefusedError(
                f"settings changed since the proposal ({listing}): identify again"
            )

    @staticmethod
    def previous_gains(entry: AxisEntry, session: Session) -> dict[str, int]:
        return _proposal(session).current_gains.to_dict()

    async def restore(self, entry: AxisEntry, previous: dict[str, int]) -> dict[str, int]:
        return await self._ctx.hub.write_params(entry.info.id, previous)

    async def verify(self, entry: AxisEntry, session: Session) -> dict[str, Any]:
        """Baseline test (previous gains), write the proposal, verification test."""
        ctx = self._ctx
        proposal = _proposal(session)
        assert session.request is not None
        axis_id = entry.info.id
        kind = session.request.test
        spec = proposal.spec
        start = round(ctx.position(entry.latest))
        if not entry.latest or not entry.latest.flags.get("pm"):
            await ctx.command(entry, "position_mode", {})
        baseline: dict[str, Any] | None = None
        baseline_note = ""
        duration = spec.profile_time_s() + TEST_RECORD_S
        if proposal.default_excursion <= session.request.max_distance_counts:
            ctx.hub.on_event("info", axis_id, "auto-tune: baseline test with the previous gains")
            # The previous gains may be the reason for the auto-tune (the loaded demo
            # axis' factory gains limit-cycle): a baseline they leave oscillating is a
            # result to compare with, not a failure; the bench has braked the axis.
            baseline = await ctx.run_test(
                entry,
                kind,
                spec.distance,
                duration,
                "auto-tune baseline (previous gains)",
                oscillation_is_a_result=True,
            )
            if baseline.get("left_oscillating"):
                ctx.hub.on_event(
                    "warning",
                    axis_id,
                    "auto-tune: the previous gains left the axis oscillating (the baseline "
                    "is recorded so); verifying the proposal",
                )
        else:
            baseline_note = (
                f"baseline skipped: the previous gains are predicted to travel "
                f"{proposal.default_excursion} counts, beyond your max_distance_counts"
            )
            ctx.hub.on_event("warning", axis_id, f"auto-tune: {baseline_note}")
        await ctx.hub.write_params(axis_id, proposal.gains.to_dict())
        if not entry.latest or not entry.latest.flags.get("pm"):
            # Braked and unpowered after an oscillating baseline: the loop comes back
            # on with the proposed gains, never with the ones that oscillated.
            await ctx.command(entry, "position_mode", {})
        back = start - round(ctx.position(entry.latest)) or 1
        gentle = self._spec(entry, "move", back, 0.0)
        await self._move_and_wait(entry, start, gentle.profile_time_s())
        ctx.hub.on_event("info", axis_id, "auto-tune: verification test with the new gains")
        # Left oscillating, the run puts the previous gains back (and fails here).
        verification = await ctx.run_test(
            entry,
            kind,
            spec.distance,
            duration,
            "auto-tune verification (proposed gains)",
            restore_gains=proposal.current_gains.to_dict(),
        )
        await self._move_and_wait(entry, start, gentle.profile_time_s())
        measured = verification.get("metrics") or {}
        baseline_measured = baseline.get("metrics") if baseline else None
        decided, why = verdict_with_reason(
            baseline_measured,
            measured,
            baseline_unmeasured=unmeasured(baseline),
            tuned_unmeasured=unmeasured(verification),
        )
        return {
            "gains": proposal.gains.to_dict(),
            "previous_gains": proposal.current_gains.to_dict(),
            "predicted": proposal.predicted.model_dump(),
            "measured": measured,
            "predicted_default": proposal.predicted_default.model_dump(),
            "baseline_measured": baseline_measured,
            "verification_run_id": verification["id"],
            "baseline_run_id": baseline["id"] if baseline else None,
            "baseline_note": baseline_note,
            "verdict": decided,
            "verdict_reason": why,
        }

    @staticmethod
    def verified_message(result: dict[str, Any]) -> str:
        tuned_settle = result["measured"].get("settling_time_s")
        base_settle = (result["baseline_measured"] or {}).get("settling_time_s")

        def ms(value: float | None) -> str:
            return "never" if value is None else f"{value * 1000:.0f} ms"

        return (
            f"verified: {result['verdict']} (settles in {ms(tuned_settle)}; with the "
            f"previous gains {ms(base_settle)})"
        )

    @staticmethod
    def check_revert(session: Session) -> None:
        if session.proposal is None or session.state not in ("verified", "failed"):
            raise DeviceRefusedError("nothing to revert: no accepted proposal")

    async def revert(self, entry: AxisEntry, session: Session) -> tuple[dict[str, int], str]:
        """Write the gains that were in use before the accepted proposal."""
        gains = _proposal(session).current_gains.to_dict()
        written = await self._ctx.hub.write_params(entry.info.id, gains)
        return written, f"reverted to kp={gains['kp']} ki={gains['ki']} kd={gains['kd']}"


def _proposal(session: Session) -> Slap2Proposal:
    """The session's proposal, which this tuner made (``identify``)."""
    proposal = session.proposal
    assert isinstance(proposal, Slap2Proposal), "no SLAP2 proposal in this session"
    return proposal
