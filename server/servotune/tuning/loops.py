"""Exact discrete controller laws around a linear DC-motor plant (``LoopModel``).

A ``LoopModel`` holds the plant discretised with a zero-order hold at the
controller's period (python-control ``c2d``) and the controller as the transfer
function the firmware computes, so the same object answers "what does the loop do
with these gains": the open-loop response and its gain and phase margins and
crossover, the closed-loop response, its -3 dB bandwidth and resonance peak, a
Nyquist curve and a predicted step response.

Plant (position in encoder counts per controller output unit)::

    P(s) = g kt / (s ((L s + R)(J s + b) + kt ke)),   g = (V_supply / 255) * counts/rad

i.e. the DC motor of ``servotune.sim.physics`` without its two nonlinear parts,
Coulomb friction and the PWM/current limits; predictions hold for moves small enough
that the controller does not saturate (the bench checks the PWM it saw).

A device's law gives the controller as polynomials in z: a forward path ``Cf`` on the
error and a feedback path ``Cb`` on the position (``ZERO`` where there is none). The
loop seen at the plant input is ``L = (Cf + Cb) P``; the closed loop from setpoint to
position is ``T = Cf P / (1 + L)``. The devices' laws live in their folders
(``devices/slap2/law.py``, ``devices/z1100/law.py``); the simulators implement the same
arithmetic independently (docs/simulator.md, docs/z1100-simulator.md).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import control
import numpy as np
import numpy.typing as npt
import scipy.signal

from servotune.schema import ControllerLaw
from servotune.tuning.frf import FloatArray, FrequencyResponse
from servotune.tuning.plants import OUTPUT_FULL_SCALE
from servotune.tuning.stability import loop_margins, margin_grid, schur_stable


@dataclass(frozen=True, slots=True)
class MotorModel:
    """Linear DC motor: electrical and mechanical constants, supply, encoder."""

    resistance_ohm: float
    inductance_h: float
    torque_constant_nm_per_a: float
    inertia_kg_m2: float
    viscous_friction_nm_s_per_rad: float
    supply_v: float
    counts_per_rev: int

    def plant(self) -> control.TransferFunction:
        """Counts per controller output unit (full scale 255), continuous time."""
        r, ind = self.resistance_ohm, self.inductance_h
        kt, j, b = (
            self.torque_constant_nm_per_a,
            self.inertia_kg_m2,
            self.viscous_friction_nm_s_per_rad,
        )
        gain = (self.supply_v / OUTPUT_FULL_SCALE) * self.counts_per_rev / (2.0 * math.pi)
        # s ((L s + R)(J s + b) + kt^2) = L J s^3 + (L b + R J) s^2 + (R b + kt^2) s
        den = [ind * j, ind * b + r * j, r * b + kt * kt, 0.0]
        return control.tf([gain * kt], den)


@dataclass(frozen=True, slots=True)
class Margins:
    """Stability margins of an open loop (inf where a crossover does not exist)."""

    gain_margin_db: float
    phase_margin_deg: float
    gain_crossover_hz: float
    phase_crossover_hz: float
    stable: bool


@dataclass(frozen=True, slots=True)
class LoopModel:
    """A plant under a device's controller; see the module docstring."""

    forward: control.TransferFunction  # Cf: acts on the error
    feedback: control.TransferFunction  # Cb: acts on the position (0 for the SLAP2)
    plant_d: control.TransferFunction
    period_s: float

    @property
    def open_loop(self) -> control.TransferFunction:
        return (self.forward + self.feedback) * self.plant_d

    def closed_loop_response(self, frequency_hz: npt.ArrayLike) -> FrequencyResponse:
        """Setpoint -> position, as a model-based ``FrequencyResponse``."""
        f = np.asarray(frequency_hz, dtype=np.float64)
        z = np.exp(2j * np.pi * f * self.period_s)
        cf, cb, p = (_at(tf, z) for tf in (self.forward, self.feedback, self.plant_d))
        with np.errstate(divide="ignore", invalid="ignore"):
            t = cf * p / (1.0 + (cf + cb) * p)
        return _model_response(f, t, self.period_s)

    def open_loop_response(self, frequency_hz: npt.ArrayLike) -> FrequencyResponse:
        f = np.asarray(frequency_hz, dtype=np.float64)
        z = np.exp(2j * np.pi * f * self.period_s)
        cf, cb, p = (_at(tf, z) for tf in (self.forward, self.feedback, self.plant_d))
        return _model_response(f, (cf + cb) * p, self.period_s)

    def margins(self) -> Margins:
        """Gain and phase margins of the open loop and their crossovers, read by the one
        rule (``tuning.stability.loop_margins`` on ``margin_grid``: the what-if view
        reads them the same way), and whether the closed loop is stable (``stable``)."""
        f = margin_grid(self.period_s)
        gm, pm, wgc, wpc = loop_margins(f, self.open_loop_response(f).response)
        return Margins(
            gain_margin_db=float(gm),
            phase_margin_deg=float(pm),
            gain_crossover_hz=float(wgc),
            phase_crossover_hz=float(wpc),
            stable=self.stable,
        )

    @property
    def stable(self) -> bool:
        """The one stability verdict (``tuning.stability``): every root of the closed
        loop's characteristic polynomial, from the exact component polynomials, strictly
        inside the unit circle."""
        return schur_stable(self._closed_loop_polynomials()[1])

    def bandwidth_hz(self, frequency_hz: npt.ArrayLike | None = None) -> tuple[float, float]:
        """(-3 dB bandwidth, resonance peak in dB) of the closed loop, from its response
        on a dense logarithmic grid up to Nyquist (bandwidth nan if it never drops)."""
        nyquist = 0.5 / self.period_s
        f = (
            np.asarray(frequency_hz, dtype=np.float64)
            if frequency_hz is not None
            else np.logspace(-1, math.log10(nyquist * 0.999), 4000)
        )
        mag = np.abs(self.closed_loop_response(f).response)
        dc = mag[0]
        below = np.nonzero(mag < dc * 10 ** (-3 / 20))[0]
        bw = float(f[below[0]]) if below.size else math.nan
        return bw, float(20 * math.log10(np.max(mag) / dc))

    def step(self, duration_s: float, amplitude: float = 1.0) -> tuple[FloatArray, FloatArray]:
        """Predicted response of the position to a setpoint step (linear, no limits)."""
        n = max(2, round(duration_s / self.period_s))
        return self.response(np.full(n, amplitude))

    def response(self, setpoint: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Predicted position for a setpoint given at every controller tick from rest at
        0 (a profiled move: the verification step's trapezoid); linear, no limits.
        Returns (tick times from 0, positions)."""
        u = np.asarray(setpoint, dtype=np.float64)
        t = np.arange(u.size, dtype=np.float64) * self.period_s
        # T's own difference equation (lfilter), not control.forced_response: that
        # realises T in state space and scipy's dlsim keeps every state at every tick
        # (python-control a second copy), so a Z1100 loop (T of order 34, from the
        # 32-sample window) over a few seconds of 32 us ticks would take gigabytes; this
        # keeps the output array only. Same output from rest.
        num, den = self._closed_loop_polynomials()
        num = np.concatenate([np.zeros(den.size - num.size), num])  # powers of z^-1
        y = scipy.signal.lfilter(num / den[0], den / den[0], u)
        return t, np.asarray(y, dtype=np.float64)

    def nyquist(self, frequency_hz: npt.ArrayLike) -> npt.NDArray[np.complex128]:
        """Open-loop L(e^{jwT}) at the given frequencies (a Nyquist curve)."""
        return self.open_loop_response(frequency_hz).response

    def _closed_loop_tf(self) -> control.TransferFunction:
        num, den = self._closed_loop_polynomials()
        return control.tf(num, den, self.period_s)

    def _closed_loop_polynomials(self) -> tuple[FloatArray, FloatArray]:
        """T = Cf P / (1 + (Cf + Cb) P) as (num, den) in descending powers of z, from
        the polynomials with exact arithmetic only: no ``control.minreal``, whose
        tolerance cancelled the SLAP2 integrator's pole near z = 1 against a nearby
        zero and left a slow error (176 counts of a 2000-count ramp after 17 s)."""
        return closed_loop_polynomials(
            *(_polynomials(tf) for tf in (self.forward, self.feedback, self.plant_d))
        )


Polynomial = tuple[FloatArray, FloatArray]  # (numerator, denominator), descending powers of z


def _polynomials(tf: control.TransferFunction) -> Polynomial:
    num, den = (np.asarray(c[0][0], dtype=np.float64) for c in control.tfdata(tf))
    return num, den


def closed_loop_polynomials(
    forward: Polynomial, feedback: Polynomial, plant: Polynomial
) -> Polynomial:
    """``T = Cf P / (1 + (Cf + Cb) P)`` as (num, den) from the components' exact
    polynomials (``LoopModel``; gain searches call it without building the loop)."""
    (nf, df), (nb, db), (npl, dpl) = forward, feedback, plant
    if np.array_equal(df, db):
        d = df  # one denominator (the Z1100's 64 z^32): T = Nf Np / (D Dp + (Nf+Nb) Np)
        num = np.polymul(nf, npl)
        den = np.polyadd(np.polymul(d, dpl), np.polymul(np.polyadd(nf, nb), npl))
    else:  # T = Nf Db Np / (Df Db Dp + (Nf Db + Nb Df) Np)
        num = np.polymul(np.polymul(nf, db), npl)
        den = np.polyadd(
            np.polymul(np.polymul(df, db), dpl),
            np.polymul(np.polyadd(np.polymul(nf, db), np.polymul(nb, df)), npl),
        )
    num, den = np.trim_zeros(num, "f"), np.trim_zeros(den, "f")
    # common roots at z = 0 (trailing zero coefficients) cancel exactly
    while num.size > 1 and den.size > 1 and num[-1] == 0.0 and den[-1] == 0.0:
        num, den = num[:-1], den[:-1]
    return np.asarray(num, dtype=np.float64), np.asarray(den, dtype=np.float64)


class MarginSearch:
    """The margins and the verdict of many controllers around one discrete plant, by
    the rules of ``LoopModel.margins`` (the same polynomials, grid and tests) without
    building python-control objects per candidate: what a gain search needs."""

    def __init__(self, plant_d: control.TransferFunction, period_s: float) -> None:
        self._plant = _polynomials(plant_d)
        self._f = margin_grid(period_s)
        self._z = np.exp(2j * np.pi * self._f * period_s)
        with np.errstate(divide="ignore", invalid="ignore"):
            self._p = np.polyval(self._plant[0], self._z) / np.polyval(self._plant[1], self._z)

    def margins(self, forward: Polynomial, feedback: Polynomial) -> Margins:
        z = self._z
        with np.errstate(divide="ignore", invalid="ignore"):
            c = np.polyval(forward[0], z) / np.polyval(forward[1], z) + np.polyval(
                feedback[0], z
            ) / np.polyval(feedback[1], z)
        gm, pm, wgc, wpc = loop_margins(self._f, c * self._p)
        stable = schur_stable(closed_loop_polynomials(forward, feedback, self._plant)[1])
        return Margins(float(gm), float(pm), float(wgc), float(wpc), stable)


def _at(tf: control.TransferFunction, z: npt.NDArray[np.complex128]) -> npt.NDArray[np.complex128]:
    num, den = control.tfdata(tf)
    # z = 1 (0 Hz) is a pole of an integrating controller: inf there, not a warning.
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(np.polyval(num[0][0], z) / np.polyval(den[0][0], z), dtype=np.complex128)


def _model_response(
    f: FloatArray, h: npt.NDArray[np.complex128], period_s: float
) -> FrequencyResponse:
    return FrequencyResponse(
        frequency_hz=f,
        response=np.asarray(h, dtype=np.complex128),
        coherence=np.ones_like(f),
        sample_rate_hz=1.0 / period_s,
        model_based=True,
    )


ZERO: Polynomial = (np.zeros(1), np.ones(1))  # a controller path that is not there


def linear_gain_prefix(controller: ControllerLaw) -> str:
    """The gain set a linear analysis uses: the holding one, else the one for always
    (a frequency response is taken around a held position)."""
    for when in ("holding", "always"):
        for gain_set in controller.gain_sets:
            if gain_set.when == when:
                return gain_set.prefix
    raise ValueError("the law has no holding gain set")


def law_polynomials(
    controller: ControllerLaw, gains: Mapping[str, int]
) -> tuple[Polynomial, Polynomial]:
    """The law's linear view, ``u = Cf e - Cb y``: (forward ``Cf``, feedback ``Cb``) in
    descending powers of z with the holding gains (``linear_gain_prefix``), as the
    devices' own polynomials. An error_sum term with a zero gain adds no integrator.
    KeyError for a gain missing from ``gains``."""
    prefix = linear_gain_prefix(controller)
    size = 1 + max(term.delay for term in controller.terms)
    paths = {name: np.zeros(size) for name in ("error", "error_sum", "position")}
    for term in controller.terms:
        value = term.coefficient * math.prod(gains[prefix + g] for g in term.gains)
        paths[term.signal][term.delay] += value
    one = np.ones(1)
    if paths["error_sum"].any():
        # (E + S / (1 - z^-1)) / d  =  (E (1 - z^-1) + S) / (d (1 - z^-1))
        integrator = np.array([1.0, -1.0])
        num = np.convolve(paths["error"], integrator)
        num[:size] += paths["error_sum"]  # coefficients of z^-k: aligned at k = 0
        forward = (num, integrator)
    else:
        forward = (paths["error"], one)
    feedback = (-paths["position"], one)
    return _descending(forward, controller.divisor), _descending(feedback, controller.divisor)


def _descending(ratio: tuple[FloatArray, FloatArray], divisor: float) -> Polynomial:
    """``num(z^-1) / (divisor den(z^-1))`` as coefficients of descending powers of z."""
    num, den = np.trim_zeros(ratio[0], "b"), ratio[1] * divisor
    if num.size == 0:
        return ZERO
    size = max(num.size, den.size)

    def pad(c: FloatArray) -> FloatArray:
        return np.asarray(np.concatenate([c, np.zeros(size - c.size)]), dtype=np.float64)

    return pad(num), pad(den)
