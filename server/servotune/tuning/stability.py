"""The one stability verdict of a discrete loop - every root of its characteristic
polynomial strictly inside the unit circle, decided by the Schur-Cohn step-down test -
and its gain and phase margins, read one way (``loop_margins``).

Why a test on the coefficients and not ``numpy.roots``: the verdict must be the same
wherever it is shown - the margins table and the model Bode (server), the what-if view
(``web/src/stability.ts``, the same steps in TypeScript, checked against the same cases
in tests/unit/tuning/test_stability.py) and the auto-tune's proposals - and a root finder's error
near the unit circle (the slow mode of a small integral gain sits at |z| = 0.9999)
would make "stable" depend on round-off. The step-down needs nothing but arithmetic.

The characteristic polynomial is the closed loop's denominator built from the exact
polynomials of controller and plant (``tuning.loops``); a factor ``z - 1`` common to a
controller's numerator and denominator (the SLAP2 PID with ``ki = 0``: the running sum
is multiplied by zero) is not built in at all, so it cannot read as a pole on the unit
circle - "unstable whenever ki = 0" was that.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

# The frequencies margins are read on: log-spaced from MARGIN_GRID_FROM_HZ to just below
# the controller's Nyquist frequency (web/src/stability.ts uses the same grid).
MARGIN_GRID_POINTS = 1000
MARGIN_GRID_FROM_HZ = 0.1


def schur_stable(coefficients: npt.ArrayLike) -> bool:
    """Whether every root of ``a0 z^n + a1 z^(n-1) + ... + an`` lies strictly inside
    the unit circle (Schur-Cohn): with ``k = an / a0``, the roots are inside iff
    ``|k| < 1`` and those of the degree-(n-1) polynomial ``(a_i - k a_(n-i)) / (1 - k^2)``
    are. Leading zeros are dropped; trailing zeros are roots at 0 (inside)."""
    a = np.trim_zeros(np.asarray(coefficients, dtype=np.float64), "f")
    a = np.trim_zeros(a, "b")
    if a.size == 0 or not np.all(np.isfinite(a)):
        return False
    while a.size > 1:
        k = a[-1] / a[0]
        if not abs(k) < 1.0:
            return False
        a = (a[:-1] - k * a[::-1][:-1]) / (1.0 - k * k)
    return True


def margin_grid(period_s: float) -> npt.NDArray[np.float64]:
    """The frequencies ``loop_margins`` reads a loop of controller period ``period_s``
    on (Hz)."""
    nyquist = 0.5 / period_s
    return np.geomspace(MARGIN_GRID_FROM_HZ, 0.999 * nyquist, MARGIN_GRID_POINTS)


def loop_margins(
    frequency_hz: npt.ArrayLike, loop: npt.ArrayLike
) -> tuple[float, float, float, float]:
    """Gain and phase margins of an open loop ``L`` given on a rising frequency grid:
    ``(gain_margin_db, phase_margin_deg, gain_crossover_hz, phase_crossover_hz)``.

    Crossings are interpolated linearly in log f (dB for |L|, degrees for its phase,
    unwrapped along the grid). The phase margin is the smallest of ``180 deg + phase``
    (wrapped to -180..180) over every frequency where |L| crosses 1; the gain margin
    the smallest ``-20 log10 |L|`` over every frequency where the phase crosses -180
    deg (mod 360) with |L| < 1 - how much more gain the loop takes (a crossing with
    |L| > 1, below the crossover of a loop with an integrator, is no such margin).
    ``inf`` (and NaN crossover) where there is none."""
    f = np.asarray(frequency_hz, dtype=np.float64)
    values = np.asarray(loop, dtype=np.complex128)
    with np.errstate(divide="ignore"):
        db = 20.0 * np.log10(np.abs(values))
    phase = np.degrees(np.unwrap(np.angle(values)))
    logf = np.log(f)
    pm, wgc = math.inf, math.nan
    gm, wpc = math.inf, math.nan
    a, b = db[:-1], db[1:]
    with np.errstate(invalid="ignore", divide="ignore"):
        # gain crossovers: |L| crosses 1 between neighbours
        i = np.nonzero(np.isfinite(a) & np.isfinite(b) & ((a >= 0.0) != (b >= 0.0)))[0]
        if i.size:
            x = a[i] / (a[i] - b[i])
            margins = (phase[i] + x * (phase[i + 1] - phase[i]) + 180.0) % 360.0
            margins = np.where(margins > 180.0, margins - 360.0, margins)
            j = int(np.argmin(margins))
            pm = float(margins[j])
            wgc = math.exp(float(logf[i[j]] + x[j] * (logf[i[j] + 1] - logf[i[j]])))
        # phase crossovers: the phase passes -180 + 360 k between neighbours (a level
        # on the right end belongs to the next interval)
        p, q = phase[:-1], phase[1:]
        first = np.ceil((np.minimum(p, q) + 180.0) / 360.0)
        last = np.floor((np.maximum(p, q) + 180.0) / 360.0)
        hits: list[tuple[float, float]] = []
        for n in np.nonzero(first <= last)[0].tolist():
            pn, qn = float(p[n]), float(q[n])
            for k in range(int(first[n]), int(last[n]) + 1):
                level = -180.0 + 360.0 * k
                if qn == level and pn != level:
                    continue
                frac = 0.0 if pn == qn else (level - pn) / (qn - pn)
                gain_db = float(a[n] + frac * (b[n] - a[n]))
                if math.isfinite(gain_db) and gain_db < 0.0:
                    at = math.exp(float(logf[n] + frac * (logf[n + 1] - logf[n])))
                    hits.append((-gain_db, at))
        if hits:
            gm, wpc = min(hits)
    return gm, pm, wgc, wpc
