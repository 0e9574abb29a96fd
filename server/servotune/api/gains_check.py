"""Gains predicted unstable on an axis' identified plant are written only when confirmed.

``check_predicted_stable`` is asked before ``PATCH /api/axes/{id}/params`` writes: if
the gains in the write (with the axis' other gains as they are) make the auto-tune's
identified plant unstable under the device's exact law (``tuning.predicted``), the write
answers 409 naming ``confirm_unstable`` and nothing is sent; the same request with
``confirm_unstable=true`` writes. The prediction is one short simulation of the
discrete loop: it runs in a thread beside the event loop, not in the compute worker,
so that a gains write answers at once instead of waiting for the worker's start (its
imports) or for a fit or gain search queued in it. Also here: which parameters are a
device's gains (its law's), and the identified model of an axis (used by the what-if
and frequency-response routes).
"""

from __future__ import annotations

import asyncio
from collections.abc import Mapping
from typing import Any

from fastapi import Request

from servotune.autotune.service import AutoTuning
from servotune.hub.hub import Hub
from servotune.link.base import ConfirmationRequiredError, DriverError
from servotune.tuning.law import DeviceLaw, DeviceLaws
from servotune.tuning.predicted import unstable_reason


def device_law(request: Request, device: str) -> DeviceLaw | None:
    """The controller law of ``device`` (the app's registry); None: it has none."""
    laws: DeviceLaws = request.app.state.devices
    return laws.law(device)


def identified_model(request: Request, axis_id: str) -> dict[str, Any] | None:
    """The auto-tune's identified plant of the axis in this server's session, if any."""
    autotuner: AutoTuning | None = getattr(request.app.state, "autotuner", None)
    if autotuner is None:
        return None
    try:
        model: dict[str, Any] | None = autotuner.session(axis_id).get("model")
    except DriverError:
        return None  # a device the auto-tune does not handle
    return model


async def check_predicted_stable(
    request: Request, axis_id: str, values: Mapping[str, Any], confirmed: bool
) -> None:
    """Refuse (409, field ``confirm_unstable``) a write of gains predicted unstable on
    the axis' identified plant (``tuning.predicted``) unless ``confirmed``; nothing to
    judge without an identification or without gains among ``values``."""
    hub: Hub = request.app.state.hub
    entry = hub.entry(axis_id)
    law = device_law(request, entry.info.device)
    names = law.gain_names if law is not None else ()
    if law is None or confirmed or not any(name in values for name in names):
        return
    model = identified_model(request, axis_id)
    if not model:
        return
    gains = {n: entry.device_values.get(n, 0) for n in names}
    gains.update({n: int(values[n]) for n in names if isinstance(values.get(n), int)})
    try:
        why = await asyncio.to_thread(unstable_reason, law, model, gains)
    except ValueError:
        return  # an identified model that describes no such plant: nothing predicted
    if why:
        raise ConfirmationRequiredError(
            "confirm_unstable",
            f"{why}. Write them anyway only if you mean it: confirm (the request with "
            "confirm_unstable=true); the axis is watched and braked if it oscillates",
        )
