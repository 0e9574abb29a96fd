"""Identified plant models as loop models, and what the bench's what-if view needs.

The auto-tune's identification (``tuning.identify.fit_plant`` for the SLAP2,
``devices.z1100.law.fit_plant_closed_loop`` for the Z1100) fits a first-order
velocity model, ``tau dv/dt = gain u - v``, position integrating velocity. As a transfer
function in counts per controller output unit (PWM units, full scale 255)::

    P(s) = g / (s (tau s + 1))

with ``g`` the SLAP2's counts/s per PWM unit, or the Z1100's counts/s per duty / 255.
Friction (the SLAP2 fit's ``friction_pwm``) and the PWM limit are nonlinear: the
margins and the Bode model leave them out; the browser's step prediction keeps the
PWM limit (``whatif.ts``) and the docs say what friction does (docs/frequency-response.md).

``browser_model`` is what the server sends the what-if view: the plant discretised
with a zero-order hold at the controller period, as difference-equation coefficients
in powers of z^-1, the law's name and period, and the law as data (``controller``:
``schema.ControllerLaw`` terms). The browser evaluates those terms at every slider
move (a few hundred to a few thousand ticks: well under a millisecond) and the open
loop on a frequency grid for the margins, so no request is needed per update.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import control
import numpy as np

from servotune.tuning.frf import FloatArray
from servotune.tuning.law import DeviceLaw, Law
from servotune.tuning.loops import LoopModel
from servotune.tuning.plants import IdentifiedPlant

__all__ = [
    "IdentifiedPlant",
    "Law",
    "bode_dict",
    "browser_model",
    "loop_for",
    "margins_dict",
    "model_summary",
    "plant_from_identification",
]


def plant_from_identification(law: DeviceLaw, model: Mapping[str, Any] | None) -> IdentifiedPlant:
    """The plant of an auto-tune identification (``session.model``); ValueError when
    there is none or it lacks the fields of the fit of ``law``'s device."""
    if not model:
        raise ValueError("no identified plant model: run the auto-tune's Identify first")
    try:
        plant = law.linear_plant(model)
    except ValueError:
        raise ValueError(f"the identified model does not describe a {law.device} plant") from None
    gain, tau = plant.gain_counts_s_per_unit, plant.tau_s
    if not (gain > 0 and tau > 0 and math.isfinite(gain) and math.isfinite(tau)):
        raise ValueError(f"implausible identified model: gain {gain}, tau {tau} s")
    return plant


def loop_for(law: DeviceLaw, plant: IdentifiedPlant, gains: Mapping[str, int]) -> LoopModel:
    """The device's exact discrete law with ``gains`` (device parameter names) around
    ``plant`` (``DeviceLaw.loop``: the Z1100 with its hold gains, KABD)."""
    return law.loop(plant, gains)


def browser_model(
    law: DeviceLaw, plant: IdentifiedPlant, params: Mapping[str, int]
) -> dict[str, Any]:
    """The discrete plant and the law for the what-if view (see the module docstring).

    ``plant_num``/``plant_den``: ``y[n] = sum(num[i] u[n-i]) - sum(den[i] y[n-i], i>=1)``
    with ``den[0] == 1``."""
    period = law.period_s(params)
    pd = control.c2d(plant.transfer_function(), period, "zoh")
    num, den = (np.asarray(c[0][0], dtype=np.float64) for c in control.tfdata(pd))
    # tf coefficients are in descending powers of z; pad num to den's length so both
    # read as powers of z^-1 after dividing by z^order.
    num = np.concatenate([np.zeros(den.size - num.size), num])
    scale = den[0]
    return {
        "device": law.device,
        "law": law.law,
        "controller": law.controller.model_dump(),
        "period_s": period,
        "plant_num": (num / scale).tolist(),
        "plant_den": (den / scale).tolist(),
        "pwm_limit": law.output_limit,
        "plant": {
            "gain_counts_s_per_unit": plant.gain_counts_s_per_unit,
            "tau_s": plant.tau_s,
            "source": plant.source,
        },
    }


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def model_summary(loop: LoopModel, frequency_hz: FloatArray) -> dict[str, Any]:
    """Margins, crossovers, bandwidth, resonance and the model's closed- and open-loop
    responses on ``frequency_hz`` (JSON-ready; infinities and NaN as null)."""
    margins = loop.margins()
    bandwidth, peak_db = loop.bandwidth_hz()
    closed = loop.closed_loop_response(frequency_hz)
    open_ = loop.open_loop_response(frequency_hz)
    nyquist_f = np.geomspace(max(0.2, float(frequency_hz[0])), 0.45 / loop.period_s, 400)
    curve = loop.nyquist(nyquist_f)
    return {
        "margins": margins_dict(
            margins.gain_margin_db,
            margins.phase_margin_deg,
            margins.gain_crossover_hz,
            margins.phase_crossover_hz,
            margins.stable,
        ),
        "bandwidth_hz": _finite(bandwidth),
        "resonance_db": _finite(peak_db),
        "closed_loop": bode_dict(frequency_hz, closed.magnitude_db, closed.phase_deg),
        "open_loop": bode_dict(frequency_hz, open_.magnitude_db, open_.phase_deg),
        "nyquist": {
            "frequency_hz": _rounded(nyquist_f),
            "re": _rounded(np.real(curve)),
            "im": _rounded(np.imag(curve)),
        },
    }


def margins_dict(
    gm_db: float, pm_deg: float, wgc_hz: float, wpc_hz: float, stable: bool | None
) -> dict[str, Any]:
    return {
        "gain_margin_db": _finite(gm_db),
        "phase_margin_deg": _finite(pm_deg),
        "gain_crossover_hz": _finite(wgc_hz),
        "phase_crossover_hz": _finite(wpc_hz),
        "stable": stable,
    }


def _rounded(values: FloatArray) -> list[float | None]:
    return [round(float(v), 5) if math.isfinite(v) else None for v in values]


def bode_dict(f: FloatArray, mag_db: FloatArray, phase_deg: FloatArray) -> dict[str, Any]:
    return {
        "frequency_hz": _rounded(f),
        "magnitude_db": _rounded(mag_db),
        "phase_deg": _rounded(phase_deg),
    }
