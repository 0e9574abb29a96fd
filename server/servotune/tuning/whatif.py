"""Identified plant models as loop models, and what the bench's what-if view needs.

The auto-tune's identification (``autotune.fit_plant`` for the SLAP2,
``autotune_z1100.fit_plant_closed_loop`` for the Z1100) fits a first-order velocity
model, ``tau dv/dt = gain u - v``, position integrating velocity. As a transfer
function in counts per controller output unit (PWM units, full scale 255)::

    P(s) = g / (s (tau s + 1))

with ``g`` the SLAP2's counts/s per PWM unit, or the Z1100's counts/s per duty / 255.
Friction (the SLAP2 fit's ``friction_pwm``) and the PWM limit are nonlinear: the
margins and the Bode model leave them out; the browser's step prediction keeps the
PWM limit (``whatif.ts``) and the docs say what friction does (docs/frequency-response.md).

``browser_model`` is what the server sends the what-if view: the plant discretised
with a zero-order hold at the controller period, as difference-equation coefficients
in powers of z^-1, and the law's name and period. The browser runs the exact
controller arithmetic on it at every slider move (a few hundred to a few thousand
ticks: well under a millisecond) and evaluates the open loop on a frequency grid for
the margins, so no request is needed per update.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import control
import numpy as np

from servotune.tuning.frf import FloatArray
from servotune.tuning.loops import (
    PWM_FULL_SCALE,
    SLAP2_TICK_S,
    Z1100_TICK_S,
    LoopModel,
    slap2_loop_for,
    z1100_loop_for,
)

Law = Literal["slap2_pid", "z1100_kab"]


@dataclass(frozen=True, slots=True)
class IdentifiedPlant:
    """First-order velocity plant: counts/s per controller output unit, time constant."""

    gain_counts_s_per_unit: float
    tau_s: float
    source: str  # where the numbers come from, shown to the user

    def transfer_function(self) -> control.TransferFunction:
        return control.tf([self.gain_counts_s_per_unit], [self.tau_s, 1.0, 0.0])


def plant_from_identification(device: str, model: Mapping[str, Any] | None) -> IdentifiedPlant:
    """The plant of an auto-tune identification (``session.model``); ValueError when
    there is none or it lacks the fields of ``device``'s fit."""
    if not model:
        raise ValueError("no identified plant model: run the auto-tune's Identify first")
    tau = float(model.get("tau_s", 0.0))
    if device == "slap2" and "gain_counts_s_per_pwm" in model:
        gain = float(model["gain_counts_s_per_pwm"])
    elif device == "z1100" and "gain_counts_s_per_duty" in model:
        gain = float(model["gain_counts_s_per_duty"]) / PWM_FULL_SCALE
    else:
        raise ValueError(f"the identified model does not describe a {device} plant")
    if not (gain > 0 and tau > 0 and math.isfinite(gain) and math.isfinite(tau)):
        raise ValueError(f"implausible identified model: gain {gain}, tau {tau} s")
    return IdentifiedPlant(gain, tau, "auto-tune identification")


def loop_for(device: str, plant: IdentifiedPlant, gains: Mapping[str, int]) -> LoopModel:
    """The device's exact discrete law with ``gains`` (device parameter names) around
    ``plant``. The Z1100 is modelled with its hold gains (KABD): the set in force when
    the axis stands, which is where a frequency response around a held position is."""
    tf = plant.transfer_function()
    if device == "slap2":
        return slap2_loop_for(tf, gains["kp"], gains["ki"], gains["kd"])
    if device == "z1100":
        return z1100_loop_for(
            tf, gains["kabd_k"], gains["kabd_a"], gains["kabd_b"], max(1, gains.get("stm", 1))
        )
    raise ValueError(f"no controller law for {device}")


def law_of(device: str) -> Law:
    if device == "slap2":
        return "slap2_pid"
    if device == "z1100":
        return "z1100_kab"
    raise ValueError(f"no controller law for {device}")


def browser_model(device: str, plant: IdentifiedPlant, params: Mapping[str, int]) -> dict[str, Any]:
    """The discrete plant and the law for the what-if view (see the module docstring).

    ``plant_num``/``plant_den``: ``y[n] = sum(num[i] u[n-i]) - sum(den[i] y[n-i], i>=1)``
    with ``den[0] == 1``."""
    stm = max(1, params.get("stm", 1))
    period = SLAP2_TICK_S if device == "slap2" else stm * Z1100_TICK_S
    pd = control.c2d(plant.transfer_function(), period, "zoh")
    num, den = (np.asarray(c[0][0], dtype=np.float64) for c in control.tfdata(pd))
    # tf coefficients are in descending powers of z; pad num to den's length so both
    # read as powers of z^-1 after dividing by z^order.
    num = np.concatenate([np.zeros(den.size - num.size), num])
    scale = den[0]
    return {
        "device": device,
        "law": law_of(device),
        "period_s": period,
        "plant_num": (num / scale).tolist(),
        "plant_den": (den / scale).tolist(),
        "pwm_limit": PWM_FULL_SCALE,
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
