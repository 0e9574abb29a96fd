"""Is a gain set predicted to hold an identified plant, or to make it oscillate?

The step response of the device's exact discrete law (``tuning.whatif.loop_for``) around
the auto-tune's identified plant, linear (no PWM limit, no friction), over
``DURATION_S``: gains are *predicted unstable* when that response does not settle - its
error in the last quarter is not below half of the error in the second quarter (a
growing or a sustained oscillation) - or the numbers overflow. Judged on the simulated
response rather than on the characteristic polynomial's roots, which the discrete law's
integrator and derivative window put on or near the unit circle in ways that do not
decide anything (a root at z = 1 cancelled by a zero). A slow loop that settles
decreases its error and passes.

A what-if or a proposal predicted unstable is never written without the user's
explicit confirmation (``PATCH /api/axes/{id}/params?confirm_unstable=true``, the
auto-tune's accept with ``confirm_unstable``). Pure and cheap (one short simulation of
the discrete loop): a thread beside the event loop runs it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Final

import numpy as np

from servotune.tuning.law import DeviceLaw
from servotune.tuning.whatif import loop_for, plant_from_identification

DURATION_S: Final = 3.0
# Below this error (a share of the step) nothing is left to judge: it settled.
SETTLED: Final = 0.02


def unstable_reason(law: DeviceLaw, model: Mapping[str, Any], gains: Mapping[str, int]) -> str:
    """Why ``gains`` are predicted unstable on ``model`` under ``law`` ("" when they
    settle)."""
    plant = plant_from_identification(law, model)
    _, y = loop_for(law, plant, gains).step(DURATION_S)
    if not np.all(np.isfinite(y)) or float(np.max(np.abs(y))) > 100.0:
        return "the predicted step response grows without bound (identified plant, exact law)"
    error = np.abs(1.0 - y)
    quarter = max(1, error.size // 4)
    middle = float(np.max(error[quarter : 2 * quarter]))
    late = float(np.max(error[3 * quarter :]))
    if late < SETTLED or late < 0.5 * middle:
        return ""
    growing = "grows" if late > middle else "does not die out"
    return (
        f"the predicted step response with these gains {growing}: error {100 * late:.0f} % "
        f"of the step after {DURATION_S:g} s (identified plant, exact law, no limits)"
    )
