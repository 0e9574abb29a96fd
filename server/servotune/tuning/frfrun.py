"""A frequency-response bench run: its excitation and its analysis (sans-IO).

Excitation: a periodic multisine with Schroeder phases around the held position,
``y0 + amplitude * x(t)``, ``|x| <= 1``. Its fundamental is the frequency resolution
``df`` (the lowest tone, or a divisor of it, so that at most ``MAX_TONES`` log-spaced
tones fall on multiples of ``df`` between the user's low and high frequencies). The
first period lets the loop's transient die out; the following whole periods are
analysed. Because the signal is periodic and every tone is on a bin of a segment one
period long, the spectra use a rectangular window: no leakage between tones (a Hann
window would mix neighbouring tones' bins, which a periodic excitation does not
average out).

Analysis: the samples (irregular: a serial poll) are interpolated onto a uniform grid
with a whole number of points per period, then H1 with Welch averaging
(``tuning.frf.estimate_frf``) at the tones gives the closed loop T (setpoint ->
position) and its coherence. The input is the profile setpoint when the run recorded
it densely (the capture branch reconstructs it sample by sample), else the targets
the server sent, held between sends (zero-order hold at the times the device
acknowledged them): then the measured response includes the SLAP2's profile generator
at its maximum velocity and acceleration.

Open loop from the measurement: for a loop whose controller acts on the error only
(the SLAP2, ``Cb = 0``), ``L = T / (1 - T)`` exactly, so margins and crossover come
from the measured T without any plant model, inside the usable band.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import control
import numpy as np

from servotune.tuning.frf import FloatArray, estimate_frf
from servotune.tuning.whatif import bode_dict, margins_dict

MAX_TONES = 24
MIN_COHERENCE = 0.9
MIN_PERIODS = 3  # analysed, after the settling period (coherence needs averages)


@dataclass(frozen=True, slots=True)
class Excitation:
    """The multisine of a run: ``target(t) = y0 + amplitude * x(t)`` (t from t0)."""

    y0: float
    amplitude: float
    tones_hz: tuple[float, ...]
    phases_rad: tuple[float, ...]
    scale: float  # 1 / peak of the raw sum, so |x| <= 1
    period_s: float
    settle_periods: int = 1

    def target(self, t_s: float) -> int:
        f = np.asarray(self.tones_hz)
        x = float(np.sum(np.cos(2 * np.pi * f * t_s + np.asarray(self.phases_rad))))
        return round(self.y0 + self.amplitude * self.scale * x)

    def to_dict(self) -> dict[str, Any]:
        return {
            "y0": self.y0,
            "amplitude": self.amplitude,
            "tones_hz": list(self.tones_hz),
            "phases_rad": list(self.phases_rad),
            "scale": self.scale,
            "period_s": self.period_s,
            "settle_periods": self.settle_periods,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Excitation:
        return cls(
            float(d["y0"]),
            float(d["amplitude"]),
            tuple(float(x) for x in d["tones_hz"]),
            tuple(float(x) for x in d["phases_rad"]),
            float(d["scale"]),
            float(d["period_s"]),
            int(d.get("settle_periods", 1)),
        )


def design(y0: float, amplitude: float, low_hz: float, high_hz: float) -> Excitation:
    """The multisine for a band (callers check the ranges; see the module docstring)."""
    df = low_hz
    # At most MAX_TONES log-spaced tones on multiples of df (duplicates merged).
    ks = np.unique(np.round(np.geomspace(1.0, high_hz / df, MAX_TONES))).astype(int)
    tones = ks * df
    n = tones.size
    k = np.arange(1, n + 1)
    phases = -np.pi * k * (k - 1) / n
    period = 1.0 / df
    t = np.linspace(0.0, period, 4096, endpoint=False)
    raw = np.sum(np.cos(2 * np.pi * tones[:, None] * t[None, :] + phases[:, None]), axis=0)
    peak = float(np.max(np.abs(raw))) or 1.0
    return Excitation(
        y0=float(y0),
        amplitude=float(amplitude),
        tones_hz=tuple(float(x) for x in tones),
        phases_rad=tuple(float(x) for x in phases),
        scale=1.0 / (peak * 1.02),  # margin: the sampled peak may miss the true one
        period_s=period,
    )


def periods_in(duration_s: float, excitation: Excitation) -> int:
    """Whole periods analysed in a record of ``duration_s``."""
    return int(duration_s / excitation.period_s + 1e-9) - excitation.settle_periods


def _held(times: Sequence[float], values: Sequence[float], at: FloatArray) -> FloatArray:
    """Zero-order hold of (times, values) at ``at`` (the value before the first time:
    the first value)."""
    tt = np.asarray(times, dtype=np.float64)
    vv = np.asarray(values, dtype=np.float64)
    index = np.searchsorted(tt, at, side="right") - 1
    return np.asarray(vv[np.clip(index, 0, vv.size - 1)], dtype=np.float64)


def analyse(
    t_s: Sequence[float],
    position: Sequence[float],
    setpoint: Sequence[float | None] | None,
    sent: Sequence[Sequence[float]],
    t0_s: float,
    excitation: Excitation,
) -> dict[str, Any]:
    """The measured closed loop at the tones, coherence, usable band and (Cb = 0)
    the open loop's margins; ValueError when the record cannot give a spectrum."""
    t = np.asarray(t_s, dtype=np.float64) - t0_s
    y = np.asarray(position, dtype=np.float64)
    start = excitation.settle_periods * excitation.period_s
    keep = t >= start
    t, y = t[keep], y[keep]
    if t.size < 8:
        raise ValueError(f"{t.size} samples after the settling period: too few for a spectrum")
    dense_setpoint = False
    if setpoint is not None:
        sp = np.asarray([math.nan if v is None else v for v in setpoint], dtype=np.float64)[keep]
        dense_setpoint = bool(np.mean(np.isfinite(sp)) >= 0.9)
    rate_measured = float(1.0 / np.median(np.diff(t))) if t.size > 1 else 0.0
    periods = int((t[-1] - start) / excitation.period_s + 1e-9)
    if periods < 1:
        raise ValueError("the record does not hold one whole period after the settling one")
    per_period = max(8, round(excitation.period_s * rate_measured))
    rate = per_period / excitation.period_s
    grid = start + np.arange(periods * per_period) / rate
    grid = grid[grid <= t[-1]]
    # The input is taken at the same sample instants as the output and both are
    # interpolated the same way: the interpolation's smoothing (large when the poll is
    # sparse) then acts on both alike and cancels in Puy / Puu.
    if dense_setpoint:
        ok = np.isfinite(sp)
        u_at = np.interp(t, t[ok], sp[ok])
        source = "setpoint"
    else:
        sent_t = [row[0] - t0_s for row in sent]
        sent_v = [row[1] for row in sent]
        if not sent_t:
            raise ValueError("no excitation was sent")
        u_at = _held(sent_t, sent_v, t)
        source = "targets"
    y_u = np.interp(grid, t, y)
    u_u = np.interp(grid, t, u_at)
    measured = estimate_frf(
        u_u, y_u, rate, segment_samples=per_period, detrend="constant", window="boxcar"
    ).at_tones(excitation.tones_hz)
    nyquist = rate_measured / 2.0
    in_band = measured.frequency_hz <= nyquist
    coherence = measured.coherence
    usable_from, usable = _usable_band(measured.frequency_hz, coherence, nyquist)
    t_resp = measured.response
    with np.errstate(divide="ignore", invalid="ignore"):
        loop = t_resp / (1.0 - t_resp)
    good = (coherence >= MIN_COHERENCE) & in_band
    return {
        "closed_loop": bode_dict(measured.frequency_hz, measured.magnitude_db, measured.phase_deg)
        | {"coherence": [round(float(c), 4) for c in coherence]},
        "open_loop": bode_dict(
            measured.frequency_hz,
            20 * np.log10(np.maximum(np.abs(loop), 1e-300)),
            np.degrees(np.unwrap(np.angle(loop))),
        ),
        "nyquist": {
            "frequency_hz": [round(float(f), 5) for f in measured.frequency_hz],
            "re": [round(float(v), 5) for v in np.real(loop)],
            "im": [round(float(v), 5) for v in np.imag(loop)],
        },
        "usable_from_hz": usable_from,
        "usable_until_hz": usable,
        "sample_rate_hz": round(rate_measured, 2),
        "nyquist_hz": round(nyquist, 2),
        "periods": periods,
        "input": source,
        "margins": _margins(measured.frequency_hz[good], loop[good]),
        **_bandwidth(measured.frequency_hz[good], np.abs(t_resp[good])),
    }


def _usable_band(f: FloatArray, coherence: FloatArray, nyquist_hz: float) -> tuple[float, float]:
    """The longest run of consecutive tones with coherence >= MIN_COHERENCE below
    Nyquist, as (first, last) tone frequency; the lowest such run on a tie; (0, 0)
    when no tone qualifies. A run, not "from the lowest tone on": one poor tone at
    the bottom (drift, friction at the slowest tone) must not hide a good band above."""
    good = (np.asarray(coherence) >= MIN_COHERENCE) & (np.asarray(f) <= nyquist_hz)
    best: tuple[int, int] | None = None
    start: int | None = None
    for i, ok in enumerate([*good.tolist(), False]):
        if ok and start is None:
            start = i
        elif not ok and start is not None:
            if best is None or i - start > best[1] - best[0] + 1:
                best = (start, i - 1)
            start = None
    if best is None:
        return 0.0, 0.0
    return float(f[best[0]]), float(f[best[1]])


def _margins(f: FloatArray, loop: np.ndarray[Any, np.dtype[np.complex128]]) -> dict[str, Any]:
    """Margins of the measured open loop over the tones with good coherence (null
    where a crossover lies outside them)."""
    if f.size < 2:
        return margins_dict(math.nan, math.nan, math.nan, math.nan, None)
    data = control.frd(loop, 2 * np.pi * f)
    gm, pm, _sm, wpc, wgc, _wms = control.stability_margins(data)
    return margins_dict(
        20 * math.log10(gm) if np.isfinite(gm) and gm > 0 else math.nan,
        float(pm),
        float(wgc) / (2 * math.pi),
        float(wpc) / (2 * math.pi),
        None,
    )


def _bandwidth(f: FloatArray, magnitude: FloatArray) -> dict[str, Any]:
    """-3 dB bandwidth (interpolated between tones; null when the band never drops
    below it) and resonance peak of the measured closed loop, relative to the lowest
    good tone."""
    if f.size < 2:
        return {"bandwidth_hz": None, "resonance_db": None}
    ref = magnitude[0]
    db = 20 * np.log10(np.maximum(magnitude / ref, 1e-300))
    below = np.nonzero(db < -3.0)[0]
    bw: float | None = None
    if below.size:
        i = int(below[0])
        lo, hi = db[i - 1], db[i]
        frac = (-3.0 - lo) / (hi - lo) if hi != lo else 0.0
        bw = float(math.exp(math.log(f[i - 1]) + frac * (math.log(f[i]) - math.log(f[i - 1]))))
    return {"bandwidth_hz": bw, "resonance_db": round(float(np.max(db)), 3)}
