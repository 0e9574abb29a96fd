"""Frequency-response estimation from captured samples (sans-IO, numpy/scipy).

The estimator is the standard H1 estimate with Welch averaging: ``H = Puy / Puu``
(cross-spectrum of input and output over the auto-spectrum of the input, both from
``scipy.signal.csd`` with the same Hann window, segment length and overlap) and the
magnitude-squared coherence ``|Puy|^2 / (Puu Pyy)`` from the same spectra. H1 is
unbiased for noise on the output (encoder quantisation, load disturbances), which is
where the noise of a position loop lives; the input (a setpoint the server computed)
is exact.

Captured samples are not equally spaced (a serial poll loop latches them when the
wire allows): ``resample_uniform`` puts them on a uniform grid at their median rate by
linear interpolation before the spectra. The usable band ends where the coherence
falls below a threshold or at the Nyquist frequency of the capture rate, whichever
comes first (``FrequencyResponse.usable_until_hz``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy import signal

FloatArray = npt.NDArray[np.float64]
ComplexArray = npt.NDArray[np.complex128]


@dataclass(frozen=True, slots=True)
class FrequencyResponse:
    """A measured (or model) frequency response on a frequency grid.

    ``response`` is complex (output per input); ``coherence`` is 1.0 everywhere for a
    model. Magnitude in dB and phase in degrees (unwrapped) are derived.
    """

    frequency_hz: FloatArray
    response: ComplexArray
    coherence: FloatArray
    sample_rate_hz: float
    model_based: bool = False

    @property
    def magnitude_db(self) -> FloatArray:
        return np.asarray(20.0 * np.log10(np.maximum(np.abs(self.response), 1e-300)))

    @property
    def phase_deg(self) -> FloatArray:
        return np.asarray(np.degrees(np.unwrap(np.angle(self.response))))

    def at_tones(self, tones_hz: npt.ArrayLike) -> FrequencyResponse:
        """The points nearest to the excitation's tones (a multisine puts its power
        there; the bins between carry only leakage and distortion)."""
        tones = np.asarray(tones_hz, dtype=np.float64)
        index = np.unique(
            np.searchsorted(self.frequency_hz, tones).clip(0, self.frequency_hz.size - 1)
        )
        return FrequencyResponse(
            self.frequency_hz[index],
            self.response[index],
            self.coherence[index],
            self.sample_rate_hz,
            self.model_based,
        )

    def usable_until_hz(self, min_coherence: float = 0.9) -> float:
        """Upper end of the band from the lowest frequency on where every point has at
        least ``min_coherence`` (0 when even the first point does not), never above the
        capture's Nyquist frequency."""
        nyquist = self.sample_rate_hz / 2.0
        bad = np.nonzero(self.coherence[1:] < min_coherence)[0]
        if self.coherence.size < 2 or self.coherence[1] < min_coherence:
            return 0.0
        end = self.frequency_hz[bad[0]] if bad.size else self.frequency_hz[-1]
        return float(min(end, nyquist))


def resample_uniform(
    t_s: npt.ArrayLike, *series: npt.ArrayLike, rate_hz: float | None = None
) -> tuple[FloatArray, list[FloatArray], float]:
    """Put irregular samples on a uniform grid (linear interpolation).

    ``rate_hz`` defaults to the median sample rate. Returns (grid, series, rate).
    Raises ValueError for fewer than 8 samples or times that do not increase.
    """
    t = np.asarray(t_s, dtype=np.float64)
    if t.size < 8:
        raise ValueError(f"need at least 8 samples for a spectrum, got {t.size}")
    dt = np.diff(t)
    if np.any(dt <= 0):
        raise ValueError("sample times must increase strictly")
    rate = float(rate_hz) if rate_hz is not None else float(1.0 / np.median(dt))
    grid = np.arange(t[0], t[-1], 1.0 / rate)
    return grid, [np.interp(grid, t, np.asarray(s, dtype=np.float64)) for s in series], rate


def estimate_frf(
    u: npt.ArrayLike,
    y: npt.ArrayLike,
    sample_rate_hz: float,
    *,
    segment_samples: int | None = None,
    detrend: str = "linear",
    window: str = "hann",
) -> FrequencyResponse:
    """H1 estimate of y/u with Welch averaging and its coherence.

    ``segment_samples`` is the Welch segment length (default: an eighth of the record,
    at least 64 samples, so about 15 averages with 50 % overlap); the frequency
    resolution is ``sample_rate_hz / segment_samples``. Linear trends (a drift of the
    held position) are removed per segment. ``window="boxcar"`` with segments of whole
    periods of a periodic excitation (tones on the bins) has no leakage at all; a Hann
    window would smear each tone into its neighbours' bins.
    """
    u_arr = np.asarray(u, dtype=np.float64)
    y_arr = np.asarray(y, dtype=np.float64)
    if u_arr.shape != y_arr.shape or u_arr.ndim != 1:
        raise ValueError("u and y must be one-dimensional and of the same length")
    n = u_arr.size
    nperseg = segment_samples or max(64, n // 8)
    nperseg = min(nperseg, n)
    kwargs = {"fs": sample_rate_hz, "nperseg": nperseg, "window": window, "detrend": detrend}
    f, p_uy = signal.csd(u_arr, y_arr, **kwargs)
    _, p_uu = signal.csd(u_arr, u_arr, **kwargs)
    _, p_yy = signal.csd(y_arr, y_arr, **kwargs)
    p_uu_r = np.real(p_uu)
    with np.errstate(divide="ignore", invalid="ignore"):
        h = np.where(p_uu_r > 0, p_uy / p_uu_r, 0.0)
        coh = np.where(
            (p_uu_r > 0) & (np.real(p_yy) > 0),
            np.abs(p_uy) ** 2 / (p_uu_r * np.real(p_yy)),
            0.0,
        )
    return FrequencyResponse(
        frequency_hz=np.asarray(f, dtype=np.float64),
        response=np.asarray(h, dtype=np.complex128),
        coherence=np.clip(np.asarray(coh, dtype=np.float64), 0.0, 1.0),
        sample_rate_hz=float(sample_rate_hz),
    )


def multisine(
    frequencies_hz: npt.ArrayLike, amplitude: float, duration_s: float, sample_rate_hz: float
) -> tuple[FloatArray, FloatArray]:
    """A multisine with Schroeder phases (low crest factor), peak ``amplitude``.

    Returns (t_s, values). The crest-factor-optimal phases keep the peak close to the
    RMS, so the excitation stays inside a travel window at a useful level. For a
    leakage-free estimate put the tones on the Welch grid (``tone_grid``) and record
    whole segments.
    """
    f = np.asarray(frequencies_hz, dtype=np.float64)
    k = np.arange(1, f.size + 1)
    phases = -np.pi * k * (k - 1) / f.size
    t = np.arange(0.0, duration_s, 1.0 / sample_rate_hz)
    x = np.sum(np.cos(2 * np.pi * f[:, None] * t[None, :] + phases[:, None]), axis=0)
    peak = float(np.max(np.abs(x))) or 1.0
    return t, np.asarray(x * (amplitude / peak), dtype=np.float64)


def tone_grid(
    low_hz: float, high_hz: float, count: int, sample_rate_hz: float, segment: int
) -> FloatArray:
    """About ``count`` log-spaced tones between ``low_hz`` and ``high_hz``, each on a
    bin of a ``segment``-sample Welch grid (duplicates removed)."""
    resolution = sample_rate_hz / segment
    bins = np.unique(np.round(np.geomspace(low_hz, high_hz, count) / resolution)).astype(int)
    return np.asarray(bins[bins > 0] * resolution, dtype=np.float64)
