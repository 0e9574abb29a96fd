"""REST resources of the auto-tune assistant under ``/api/axes/{id}/autotune`` (every
device whose registry entry has a tuner). The bodies' shapes are ``schema.AutoTune*``.

The calls are synchronous: ``identify`` returns when the proposal is ready (about
2-4 s: the staircase, the return move and the gain search), ``accept`` when the
verification is done (about 3-8 s: two recorded tests and two return moves). Progress
comes over the websocket meanwhile: ``event`` messages for each phase and ``run``
messages for the recorded runs. See docs/autotune.md.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Request

from servotune.api.routes import ERRORS
from servotune.autotune.service import AutoTuning
from servotune.autotune.session import IdentifyRequest
from servotune.schema import (
    AutoTuneDecision,
    AutoTuneProposal,
    AutoTuneResult,
    AutoTuneSession,
    AutoTuneStopped,
    ErrorBody,
)

TUNE_ERRORS: dict[int | str, dict[str, Any]] = {
    **ERRORS,
    502: {"model": ErrorBody, "description": "the device answered something unexpected"},
    507: {"model": ErrorBody, "description": "the database cannot be written"},
}

router = APIRouter(tags=["autotune"])


def get_autotuner(request: Request) -> AutoTuning:
    autotuner: AutoTuning = request.app.state.autotuner
    return autotuner


AutoTunerDep = Annotated[AutoTuning, Depends(get_autotuner)]


@router.get(
    "/api/axes/{axis_id}/autotune",
    responses={**TUNE_ERRORS, 200: {"model": AutoTuneSession, "description": "the session"}},
)
async def autotune_session(axis_id: str, autotuner: AutoTunerDep) -> dict[str, Any]:
    """The axis' auto-tune session: state (idle, identifying, proposed, verifying,
    verified, failed), message, the last request, proposal and verification result."""
    return autotuner.session(axis_id)


@router.post(
    "/api/axes/{axis_id}/autotune/identify",
    responses={**TUNE_ERRORS, 200: {"model": AutoTuneProposal, "description": "the proposal"}},
)
async def autotune_identify(
    axis_id: str, body: IdentifyRequest, autotuner: AutoTunerDep
) -> dict[str, Any]:
    """Run the identification within the given limits, fit the plant model and
    propose gains: ``{model, gains, current_gains, predicted, predicted_default, rule,
    margins, margins_default, recommendation, identification_run_id, ...}``
    (``recommendation``: ``{action: keep | write, reason, ...}``, see ``keep``).
    422 naming the limit; 409 for an axis whose device has no tuner (the registry
    says which do), or a busy, moving or disconnected one; nothing moves before these
    checks."""
    return await autotuner.identify(axis_id, body)


@router.post(
    "/api/axes/{axis_id}/autotune/accept",
    responses={
        **TUNE_ERRORS,
        200: {
            "model": AutoTuneResult | AutoTuneStopped,
            "description": "the verification, or how a user's STOP ended it",
        },
    },
)
async def autotune_accept(
    axis_id: str,
    autotuner: AutoTunerDep,
    confirm_unstable: Annotated[
        bool, Query(description="accept a proposal its identified plant predicts unstable")
    ] = False,
) -> dict[str, Any]:
    """Baseline test with the previous gains, write the proposed gains (validated
    path), verification test: ``{predicted, measured, predicted_default,
    baseline_measured, verification_run_id, baseline_run_id, verdict, ...}``.

    A user's STOP meanwhile answers 200 with ``{stopped: true, message,
    previous_gains, gains_in_force, unverified}``: the axis is stopped and the
    previous gains are written back (``unverified`` true if that failed: revert).
    Other failures put the previous gains back too and answer an error."""
    return await autotuner.accept(axis_id, confirm_unstable=confirm_unstable)


@router.post(
    "/api/axes/{axis_id}/autotune/keep",
    responses={**TUNE_ERRORS, 200: {"model": AutoTuneDecision, "description": "the decision"}},
)
async def autotune_keep(axis_id: str, autotuner: AutoTunerDep) -> dict[str, Any]:
    """Decline the proposal and keep the gains in use: nothing is written to the device.
    The proposal's ``recommendation`` says which of keep and accept the rule advises
    and why; either choice is recorded (``decision`` and ``history`` of the session,
    ``autotune.decision`` and the note of the identification run). Returns the
    decision; 409 without a proposal to decide on."""
    return await autotuner.keep(axis_id)


@router.post("/api/axes/{axis_id}/autotune/revert", responses=TUNE_ERRORS)
async def autotune_revert(axis_id: str, autotuner: AutoTunerDep) -> dict[str, int]:
    """Write back the gains in use before the accepted proposal; returns the read-back."""
    return await autotuner.revert(axis_id)
