"""REST resources of the auto-tune assistant under ``/api/axes/{id}/autotune`` (SLAP2).

The calls are synchronous: ``identify`` returns when the proposal is ready (about
2-4 s: the staircase, the return move and the gain search), ``accept`` when the
verification is done (about 3-8 s: two recorded tests and two return moves). Progress
comes over the websocket meanwhile: ``event`` messages for each phase and ``run``
messages for the recorded runs. See docs/autotune.md.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request

from servotune.api.routes import ERRORS
from servotune.autotune import AutoTuner, IdentifyRequest

router = APIRouter(tags=["autotune"])


def get_autotuner(request: Request) -> AutoTuner:
    autotuner: AutoTuner = request.app.state.autotuner
    return autotuner


AutoTunerDep = Annotated[AutoTuner, Depends(get_autotuner)]


@router.get("/api/axes/{axis_id}/autotune", responses=ERRORS)
async def autotune_session(axis_id: str, autotuner: AutoTunerDep) -> dict[str, Any]:
    """The axis' auto-tune session: state (idle, identifying, proposed, verifying,
    verified, failed), message, the last request, proposal and verification result."""
    return autotuner.session(axis_id)


@router.post("/api/axes/{axis_id}/autotune/identify", responses=ERRORS)
async def autotune_identify(
    axis_id: str, body: IdentifyRequest, autotuner: AutoTunerDep
) -> dict[str, Any]:
    """Run the identification within the given limits, fit the plant model and
    propose gains: ``{model, gains, current_gains, predicted, predicted_default, rule,
    identification_run_id, ...}``. 422 naming the limit; 409 for an axis that is
    neither a SLAP2 module nor a Z1100 motor, or a busy, moving or disconnected one;
    nothing moves before these checks."""
    return await autotuner.identify(axis_id, body)


@router.post("/api/axes/{axis_id}/autotune/accept", responses=ERRORS)
async def autotune_accept(axis_id: str, autotuner: AutoTunerDep) -> dict[str, Any]:
    """Baseline test with the previous gains, write the proposed gains (validated
    path), verification test: ``{predicted, measured, predicted_default,
    baseline_measured, verification_run_id, baseline_run_id, verdict, ...}``."""
    return await autotuner.accept(axis_id)


@router.post("/api/axes/{axis_id}/autotune/revert", responses=ERRORS)
async def autotune_revert(axis_id: str, autotuner: AutoTunerDep) -> dict[str, int]:
    """Write back the gains in use before the accepted proposal; returns the read-back."""
    return await autotuner.revert(axis_id)
