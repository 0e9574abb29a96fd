"""The Z1100 half of the auto-tune: closed-loop identification with the gains in use,
fit, proposal, verification (docs/autotune.md, "Z1100"; same API and shapes as the
SLAP2's).

The science is in the shared core: the K/A/B law, its simulation and the closed-loop
fit in ``devices.z1100.law``, the rule in ``devices.z1100.gain_rule``; this module
sequences it on a live axis through ``TuningContext``. The fit and the gain search
run in worker threads.
"""

from __future__ import annotations

import asyncio
from typing import Any, Final

from servotune.autotune.context import TuningContext
from servotune.autotune.session import IdentifyRequest, Session
from servotune.autotune.verdict import verdict_z1100_with_reason
from servotune.bench.metrics import unmeasured
from servotune.devices.z1100.gain_rule import Z1100Proposal, propose_kab
from servotune.devices.z1100.law import (
    BAND_COUNTS,
    IDENT_MIN_DISTANCE,
    MAX_FIT_RMS_COUNTS,
    Kab,
    MoveProfile,
    Z1100Law,
    fit_plant_closed_loop,
    kab_dict,
)
from servotune.devices.z1100.link import Z1100Axis
from servotune.hub.state import AxisEntry
from servotune.link.base import DeviceRefusedError, DriverError, MeasurementError
from servotune.tuning.targets import target_for

DEFAULT_DISTANCE: Final = 10_000
SETTLE_TIMEOUT_S: Final = 3.0
TEST_RECORD_S: Final = 1.0  # recorded after the profile's end
# Following-error samples the identification needs *while the profile moves*: the fit
# has three unknowns (gain, tau, delay) that mostly the motion shows (at rest the error
# is ~0 whatever the plant; the decay after the profile's end adds tau). Fewer than
# MIN_MOVE_ERROR_SAMPLES: refused, naming what was recorded (accelerate, cruise,
# decelerate need at least a few each); fewer than WELL_SAMPLED_MOVE: the model is
# proposed with a warning. A capture reads GetError every 3rd sample while the motor
# runs: at 9600 baud (13.5 ms per read) a 2000-count move of the demo's X motor (0.12 s)
# got 3; at 38400 baud a 10 000-count move (0.2 s) gets 7-11 on a loaded 2-core host
# (tests/device/z1100/test_autotune.py), whose models verify better.
MIN_MOVE_ERROR_SAMPLES: Final = 5
WELL_SAMPLED_MOVE: Final = 12


def _gains_of(values: dict[str, int], prefix: str) -> Kab:
    try:
        return Kab(values[f"{prefix}_k"], values[f"{prefix}_a"], values[f"{prefix}_b"])
    except KeyError:
        raise DeviceRefusedError("the axis' gains are not read yet") from None


class Z1100Tuner:
    """identify -> propose -> accept -> verify on Z1100 motors (``autotune.DeviceTuner``)."""

    identifying_message: Final = "identifying the plant (closed-loop move, gains in use)"
    law: Final = Z1100Law()  # tuning.law.DeviceLaw: the proposal's stability check

    def __init__(self, ctx: TuningContext) -> None:
        self._ctx = ctx
        self._proposals: dict[str, Z1100Proposal] = {}

    def accepts(self, entry: AxisEntry) -> bool:
        """The chip's own axes (``Z1100Axis``), not a rig's seen through the bus."""
        return isinstance(getattr(entry, "driver", None), Z1100Axis)

    @staticmethod
    def _profile(entry: AxisEntry, distance: int) -> MoveProfile:
        values = entry.device_values
        vmax, acc = values.get("vmax", 0), values.get("acc", 0)
        if not vmax or not acc:
            raise DeviceRefusedError("the axis' Vmax or Acc is 0: no move")
        return MoveProfile(distance, float(vmax), float(acc), max(1, values.get("stm", 1)))

    async def check_request(self, entry: AxisEntry, request: IdentifyRequest) -> int:
        ctx = self._ctx
        limits = await ctx.bench.limits(entry.info.id)
        distance = request.checked_distance(
            limits.max_distance_counts, IDENT_MIN_DISTANCE, DEFAULT_DISTANCE
        )
        if ctx.test_running(entry):
            raise DeviceRefusedError("a test is already running on this axis")
        if not ctx.connected(entry):
            raise DeviceRefusedError("the axis is not connected: no telemetry")
        assert entry.latest is not None
        if entry.latest.flags.get("running"):
            raise DeviceRefusedError("the axis is moving: wait until it stands still")
        await ctx.check_at_rest(entry)
        return distance

    async def identify(
        self, entry: AxisEntry, session: Session, request: IdentifyRequest, distance: int
    ) -> dict[str, Any]:
        ctx = self._ctx
        values = entry.device_values
        current, current_kabd = _gains_of(values, "kabh"), _gains_of(values, "kabd")
        signed = request.direction * distance
        profile = self._profile(entry, signed)
        start = round(ctx.position(entry.latest))
        run = await self._run_test(entry, signed, "auto-tune identification (gains in use)")
        await self._return(entry, start)
        times, errors = _trace(run, request.direction)
        during = _samples_during(times, profile.time_s())
        if during < MIN_MOVE_ERROR_SAMPLES:
            raise MeasurementError(
                f"the capture read the following error {during} "
                f"time{'' if during == 1 else 's'} during the "
                f"{profile.time_s() * 1000:.0f} ms move ({abs(signed)} counts; at least "
                f"{MIN_MOVE_ERROR_SAMPLES} are needed to fit the plant): a longer move (raise "
                "max_distance_counts or set a longer distance), a lower Vmax or a faster "
                "baud rate gives it more"
            )
        plant = await self._ctx.compute.run(
            fit_plant_closed_loop, times, errors, current, current_kabd, profile.positive()
        )
        session.model = plant.to_dict()
        ctx.hub.on_event(
            "info",
            entry.info.id,
            f"auto-tune: model {plant.gain:.0f} counts/s per duty, tau "
            f"{plant.tau_s * 1000:.1f} ms (rms {plant.rms_error_counts:.1f} counts)",
        )
        proposal = await self._ctx.compute.run(
            propose_kab,
            plant,
            profile.positive(),
            request.response,
            current,
            current_kabd,
            BAND_COUNTS,
            request.max_distance_counts,
            target_for(request.margins),
        )
        self._proposals[entry.info.id] = proposal
        body = proposal.to_dict()
        body["identification_run_id"] = run["id"]
        body["identification_run_ids"] = [run["id"]]
        body["travel_counts"] = _travel(run, start)
        peak_error = max((abs(e) for e in errors), default=0.0)
        body["warnings"] = [
            *(
                [
                    f"the model fits the recorded following error poorly (rms "
                    f"{plant.rms_error_counts:.1f} counts of a peak {peak_error:.0f}): check "
                    "the proposal's prediction against the verification"
                ]
                if plant.rms_error_counts > max(MAX_FIT_RMS_COUNTS, 0.15 * peak_error)
                else []
            ),
            *(
                [
                    f"the model rests on {during} following-error samples during the move "
                    f"(fewer than {WELL_SAMPLED_MOVE}): check its prediction against the "
                    "verification, or identify again with a longer move"
                ]
                if during < WELL_SAMPLED_MOVE
                else []
            ),
        ]
        body["model_samples"] = during
        body["baseline_possible"] = proposal.default_excursion <= request.max_distance_counts
        session.identification_run_id = run["id"]
        session.proposal_dict = body
        session.device_settings = {
            k: v
            for k, v in values.items()
            if k.startswith("kabh") or k.startswith("kabd") or k in ("vmax", "acc", "stm")
        }
        return body

    @staticmethod
    def proposed_message(body: dict[str, Any]) -> str:
        g, c = body["gains"], body["current_gains"]
        return (
            f"proposed KABH {g['kabh_k']}/{g['kabh_a']}/{g['kabh_b']} KABD "
            f"{g['kabd_k']}/{g['kabd_a']}/{g['kabd_b']} (now KABH "
            f"{c['kabh_k']}/{c['kabh_a']}/{c['kabh_b']})"
        )

    async def move_back(self, entry: AxisEntry, target: float) -> None:
        """Move back to ``target`` with the gains in use (after a failed identification)."""
        await self._return(entry, round(target))

    async def _run_test(
        self,
        entry: AxisEntry,
        distance: int,
        note: str,
        restore_gains: dict[str, int] | None = None,
    ) -> dict[str, Any]:
        profile = self._profile(entry, distance)
        return await self._ctx.run_test(
            entry,
            "move",
            distance,
            profile.time_s() + TEST_RECORD_S,
            note,
            samples=True,
            restore_gains=restore_gains,
        )

    async def _return(self, entry: AxisEntry, target: int) -> None:
        ctx = self._ctx
        position = round(ctx.position(entry.latest))
        if position == target:
            return
        # With the sequence's stop generation: a STOP pressed after the failure ends
        # the way back too, instead of being overtaken by it.
        await ctx.command(entry, "go_to_target", {"target": target})
        await asyncio.sleep(0.1)
        deadline = ctx.clock() + SETTLE_TIMEOUT_S + 2.0
        while ctx.clock() < deadline:
            sample = await ctx.next_sample(entry)
            error = sample.channels.get("following_error")
            if not sample.flags.get("running") and error is not None and abs(error) <= BAND_COUNTS:
                return
        raise DriverError(f"the axis did not settle at {target}")

    # --- accept, verify, revert -------------------------------------------------------

    @staticmethod
    def check_accept(entry: AxisEntry, session: Session) -> None:
        """409 without a proposal, or with gains or profile changed since it."""
        if session.state != "proposed":
            raise DeviceRefusedError("no proposal to accept: run identify first")
        changed = [k for k, v in session.device_settings.items() if entry.device_values.get(k) != v]
        if changed:
            raise DeviceRefusedError(
                f"settings changed since the proposal ({', '.join(changed)}): identify again"
            )

    def previous_gains(self, entry: AxisEntry, session: Session) -> dict[str, int]:
        """KABH/KABD in use before the proposal (what a failed accept writes back)."""
        proposal = self._proposals.get(entry.info.id)
        if proposal is None:
            raise DeviceRefusedError("no proposal to accept: run identify first")
        return kab_dict(proposal.current, proposal.current_kabd)

    async def restore(self, entry: AxisEntry, previous: dict[str, int]) -> dict[str, int]:
        return await self._write_previous(entry)

    async def verify(self, entry: AxisEntry, session: Session) -> dict[str, Any]:
        proposal = self._proposals.get(entry.info.id)
        if proposal is None or session.request is None:
            raise DeviceRefusedError("no proposal to accept: run identify first")
        ctx = self._ctx
        hub = ctx.hub
        axis_id = entry.info.id
        distance = proposal.profile.distance * session.request.direction
        start = round(ctx.position(entry.latest))
        baseline: dict[str, Any] | None = None
        baseline_note = ""
        if proposal.default_excursion <= session.request.max_distance_counts:
            hub.on_event("info", axis_id, "auto-tune: baseline test with the previous gains")
            baseline = await self._run_test(entry, distance, "auto-tune baseline (previous gains)")
            await self._return(entry, start)
        else:
            baseline_note = (
                f"baseline skipped: the previous gains are predicted to travel "
                f"{proposal.default_excursion} counts, beyond your max_distance_counts"
            )
            hub.on_event("warning", axis_id, f"auto-tune: {baseline_note}")
        gains = proposal.gains
        # KABH first: the chip copies KABH into KABD, so KABD must follow it.
        await hub.write_params(axis_id, {"kabh_k": gains.k, "kabh_a": gains.a, "kabh_b": gains.b})
        kabd = gains.kabd()
        await hub.write_params(axis_id, {"kabd_k": kabd.k, "kabd_a": kabd.a, "kabd_b": kabd.b})
        hub.on_event("info", axis_id, "auto-tune: verification test with the new gains")
        # Left oscillating, the run puts the previous gains back (and fails here).
        verification = await self._run_test(
            entry,
            distance,
            "auto-tune verification (proposed gains)",
            restore_gains=kab_dict(proposal.current, proposal.current_kabd),
        )
        await self._return(entry, start)
        measured = verification.get("metrics") or {}
        baseline_measured = baseline.get("metrics") if baseline else None
        decided, why = verdict_z1100_with_reason(
            baseline_measured,
            measured,
            baseline_unmeasured=unmeasured(baseline),
            tuned_unmeasured=unmeasured(verification),
        )
        return {
            "gains": proposal.gains_dict(),
            "previous_gains": kab_dict(proposal.current, proposal.current_kabd),
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
        return f"verified: {result['verdict']}"

    @staticmethod
    def check_revert(session: Session) -> None:
        if session.state not in ("verified", "failed"):
            raise DeviceRefusedError("nothing to revert: no accepted proposal")

    async def revert(self, entry: AxisEntry, session: Session) -> tuple[dict[str, int], str]:
        return await self._write_previous(entry), "reverted to the previous KABH/KABD"

    async def _write_previous(self, entry: AxisEntry) -> dict[str, int]:
        """The previous KABH, then KABD (SetKABH overwrites KABD on the chip)."""
        proposal = self._proposals.get(entry.info.id)
        if proposal is None:
            raise DeviceRefusedError("nothing to revert: no accepted proposal")
        hub = self._ctx.hub
        c, d = proposal.current, proposal.current_kabd
        written = await hub.write_params(
            entry.info.id, {"kabh_k": c.k, "kabh_a": c.a, "kabh_b": c.b}
        )
        written |= await hub.write_params(
            entry.info.id, {"kabd_k": d.k, "kabd_a": d.a, "kabd_b": d.b}
        )
        return written


def _samples_during(times: list[float], move_s: float) -> int:
    """Following-error samples from the trigger to the end of the profile."""
    return sum(1 for t in times if 0.0 <= t <= move_s)


def _travel(run: dict[str, Any], start: float) -> int:
    """The largest distance from ``start`` the run recorded."""
    index = run["columns"].index("position")
    positions = [row[index] for row in run["samples"] if row[index] is not None]
    return round(max((abs(p - start) for p in positions), default=0.0))


def _trace(run: dict[str, Any], direction: int) -> tuple[list[float], list[float]]:
    """Times after the trigger and following errors (in the move's sense) of a run."""
    columns: list[str] = run["columns"]
    index = columns.index("following_error")
    t0 = float(run.get("t0_s") or run["samples"][0][0])
    times: list[float] = []
    errors: list[float] = []
    for row in run["samples"]:
        value = row[index]
        if value is None or row[0] < t0:
            continue
        times.append(row[0] - t0)
        errors.append(direction * float(value))
    return times, errors
