"""The one stability verdict of a discrete loop: every root of its characteristic
polynomial strictly inside the unit circle, decided by the Schur-Cohn step-down test.

Why a test on the coefficients and not ``numpy.roots``: the verdict must be the same
wherever it is shown - the margins table and the model Bode (server), the what-if view
(``web/src/stability.ts``, the same steps in TypeScript, checked against the same cases
in tests/test_stability.py) and the auto-tune's proposals - and a root finder's error
near the unit circle (the slow mode of a small integral gain sits at |z| = 0.9999)
would make "stable" depend on round-off. The step-down needs nothing but arithmetic.

The characteristic polynomial is the closed loop's denominator built from the exact
polynomials of controller and plant (``tuning.loops``); a factor ``z - 1`` common to a
controller's numerator and denominator (the SLAP2 PID with ``ki = 0``: the running sum
is multiplied by zero) is not built in at all, so it cannot read as a pole on the unit
circle - "unstable whenever ki = 0" was that.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt


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
