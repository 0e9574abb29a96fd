"""REST resources of the frequency response and the what-if view.

* ``GET /api/bench/runs/{run_id}/frf``: the Bode/Nyquist data of a frequency-response
  run (measured FRF with coherence and the open loop's margins; the identified model
  under the device's exact law beside it). Computed in a worker thread: spectra and
  margins are milliseconds to tens of milliseconds, never on the event loop.
* ``GET /api/axes/{axis_id}/whatif``: the identified plant, discretised at the
  controller period, and the law, for the browser's what-if view, which predicts the
  step and the margins at every slider move without a request.
"""

from __future__ import annotations

import asyncio
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request

from servotune.api.bench_routes import BenchDep
from servotune.api.gains_check import device_law, identified_model
from servotune.api.responses import errors
from servotune.autotune.service import AutoTuning
from servotune.bench import frf
from servotune.compute import ComputePool
from servotune.hub.hub import Hub, NotFoundError
from servotune.link.base import DeviceRefusedError, DriverError, InvalidArgumentError
from servotune.schema import FrfData, WhatIfInfo
from servotune.tuning.targets import DEFAULT_PRESET, PRESETS
from servotune.tuning.whatif import browser_model, plant_from_identification

router = APIRouter(tags=["bench"])


def _session(request: Request, axis_id: str) -> dict[str, Any]:
    autotuner: AutoTuning | None = getattr(request.app.state, "autotuner", None)
    if autotuner is None:
        return {}
    try:
        return autotuner.session(axis_id)
    except DriverError:
        return {}  # a device the auto-tune does not handle


def margin_preset(request: Request, axis_id: str) -> str:
    """The margin target of the axis' auto-tune session (its request), else the
    default (``tuning.targets``)."""
    asked = (_session(request, axis_id).get("request") or {}).get("margins")
    return str(asked) if asked in PRESETS else DEFAULT_PRESET


def get_hub(request: Request) -> Hub:
    hub: Hub = request.app.state.hub
    return hub


HubDep = Annotated[Hub, Depends(get_hub)]


def get_compute(request: Request) -> ComputePool:
    compute: ComputePool = request.app.state.compute
    return compute


ComputeDep = Annotated[ComputePool, Depends(get_compute)]


@router.get(
    "/api/bench/runs/{run_id}/frf",
    responses={**errors(404, 422), 200: {"model": FrfData, "description": "the analysis"}},
)
async def run_frf(
    run_id: str, request: Request, bench: BenchDep, compute: ComputeDep
) -> dict[str, Any]:
    """Bode and Nyquist data of a frequency-response run.

    ``measured`` (SLAP2): the closed loop at the tones with coherence, the open loop
    ``T / (1 - T)``, margins, crossover, -3 dB bandwidth and resonance over the tones
    with coherence >= 0.9, the usable band ``usable_from_hz``..``usable_until_hz``,
    the requested tones the wire could not resolve (``not_measured_hz``, with
    ``not_measured_reason`` and the ``wire`` plan: not sent, not measured);
    ``model``: the identified plant under the exact law with the run's gains (dense
    curves, margins). Either is null with a ``measured_problem`` / ``model_problem``
    sentence. 404 for an unknown run, 422 for a run of another kind."""
    try:
        run = await bench.get_run(run_id)
    except KeyError:
        raise NotFoundError("run", f"no run {run_id!r}") from None
    if (run.get("test") or {}).get("kind") != frf.KIND:
        raise InvalidArgumentError("run_id", f"run {run_id} is not a frequency_response run")
    axis_id = str(run.get("axis_id", ""))
    identified = identified_model(request, axis_id)
    preset = margin_preset(request, axis_id)
    # The analysis of a long run takes seconds of numpy and Python: in the worker.
    law = device_law(request, str(run.get("device", "")))
    return await compute.run(frf.analyse_run, law, run, identified, preset)


def _proposal_gains(request: Request, axis_id: str) -> dict[str, int] | None:
    """The auto-tune's proposed gains for the axis, if there is a proposal (the what-if
    view's ranges cover them)."""
    proposal = _session(request, axis_id).get("proposal") or {}
    gains = proposal.get("gains")
    return dict(gains) if isinstance(gains, dict) else None


@router.get(
    "/api/axes/{axis_id}/whatif", response_model=WhatIfInfo, responses=errors(404, 409, 422)
)
async def whatif_model(axis_id: str, request: Request, hub: HubDep) -> dict[str, Any]:
    """The what-if view's model: the identified plant discretised at the controller
    period (difference-equation coefficients in z^-1), the law, the gains now and
    their ranges, and the verification step's profile (counts/s, counts/s^2).
    ``model`` is null with ``problem`` when the plant is not identified yet."""
    entry = hub.entry(axis_id)
    device = entry.info.device
    law = device_law(request, device)
    if law is None:
        raise DeviceRefusedError(f"no what-if view for {device} yet (no identification)")
    values = entry.device_values
    descriptor = entry.driver.descriptor
    ranges = {
        name: [descriptor.parameter(name).minimum, descriptor.parameter(name).maximum]
        for name in law.gain_names
    }
    preset = margin_preset(request, axis_id)
    out: dict[str, Any] = {
        "axis_id": axis_id,
        "device": device,
        "gains": {name: values.get(name) for name in law.gain_names},
        "ranges": ranges,
        "model": None,
        "problem": None,
        # what the margins are read against (the auto-tune session's preset), and the
        # presets to choose from
        "target": PRESETS[preset].to_dict(),
        "targets": {name: t.to_dict() for name, t in PRESETS.items()},
        "proposal": _proposal_gains(request, axis_id),
    }
    out["verify"] = law.verify_profile(values).to_dict()
    try:
        plant = plant_from_identification(law, identified_model(request, axis_id))
    except ValueError as exc:
        out["problem"] = str(exc)
        return out
    out["model"] = await asyncio.to_thread(browser_model, law, plant, values)
    return out
