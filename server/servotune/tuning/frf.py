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
linear interpolation before the spectra (the bench's frequency response does better:
``tone_fit``, least squares at the actual sample times). The usable band is the
longest run of coherent points below the capture's Nyquist frequency
(``usable_band``, the one definition used everywhere).
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

    def usable_band(self, min_coherence: float = 0.9) -> tuple[float, float]:
        """The usable band of this response (``usable_band`` below, with the capture's
        Nyquist frequency ``sample_rate_hz / 2``)."""
        return usable_band(
            self.frequency_hz, self.coherence, self.sample_rate_hz / 2.0, min_coherence
        )


def usable_band(
    frequency_hz: npt.ArrayLike,
    coherence: npt.ArrayLike,
    nyquist_hz: float,
    min_coherence: float = 0.9,
) -> tuple[float, float]:
    """The one definition of a measurement's usable band, used by the bench's analysis
    and the Bode view alike: the longest run of consecutive points with coherence >=
    ``min_coherence`` at or below ``nyquist_hz``, as (first, last) frequency; the
    lowest such run on a tie; (0, 0) when no point qualifies.

    A run, not "from the lowest point on": one poor point at the bottom (drift over
    few periods, friction at the slowest tone) must not hide a good band above it,
    and a run, not "every good point": the band is where the curve can be read as a
    curve (interpolated between neighbours), so a lone good point between poor ones
    does not extend it."""
    f = np.asarray(frequency_hz, dtype=np.float64)
    good = (np.asarray(coherence, dtype=np.float64) >= min_coherence) & (f <= nyquist_hz)
    return usable_run(f, good)


def usable_run(frequency_hz: npt.ArrayLike, good: npt.ArrayLike) -> tuple[float, float]:
    """The longest run of consecutive ``good`` points as (first, last) frequency; the
    lowest such run on a tie; (0, 0) when no point is good. ``usable_band`` with the
    points chosen by the caller (the bench: the tones it trusts)."""
    f = np.asarray(frequency_hz, dtype=np.float64)
    good = np.asarray(good, dtype=np.bool_)
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


@dataclass(frozen=True, slots=True)
class ToneFit:
    """Complex amplitudes of a sum of tones fitted to samples: ``x(t) ~ c0 + c1 (t -
    t_ref) + sum_k Re(amplitude_k e^{j w_k (t - t_ref)})``, and each amplitude's
    standard error (per real component, from the residual and the design matrix)."""

    amplitude: ComplexArray
    standard_error: FloatArray
    residual_rms: float
    samples: int


def tone_fit(
    t_s: npt.ArrayLike,
    x: npt.ArrayLike,
    tones_hz: npt.ArrayLike,
    t_ref_s: float,
    *,
    differenced: bool = False,
) -> ToneFit:
    """Least-squares fit of all ``tones_hz`` at once (with an offset and a linear trend)
    to samples taken at the times ``t_s`` — any times, uniform or not.

    This is the honest estimator for irregular samples: no interpolation onto a grid
    (which low-passes the samples by an amount that depends on their spacing, and
    folds what lies above the grid's Nyquist frequency into the tones), and the tones
    are fitted jointly, so with uneven spacing one tone does not leak into another.
    The standard errors are the usual ones, ``s^2 (A^T A)^-1`` with ``s^2`` the
    residual variance: whatever the tones do not explain (noise, quantisation, the
    response to a non-periodic part of the input) counts as error. Raises ValueError
    when there are fewer samples than unknowns.

    ``differenced``: fit the increments between consecutive samples instead (the same
    unknowns; the offset drops out). For an integrating plant driven open loop the
    position wanders like a random walk (it integrates whatever in the input is not
    periodic), which no tone explains: its increments are white, so the fit and its
    standard errors stay honest."""
    t = np.asarray(t_s, dtype=np.float64) - t_ref_s
    xs = np.asarray(x, dtype=np.float64)
    w = 2.0 * np.pi * np.asarray(tones_hz, dtype=np.float64)
    columns = 2 + 2 * w.size
    if t.size <= columns:
        raise ValueError(
            f"{t.size} samples cannot fit {w.size} tones ({columns} unknowns): "
            "record longer or fewer tones"
        )
    phase = np.outer(t, w)
    design = np.empty((t.size, columns))
    design[:, 0] = 1.0
    design[:, 1] = t
    design[:, 2::2] = np.cos(phase)
    design[:, 3::2] = np.sin(phase)
    first = 2
    if differenced:
        design = np.diff(design, axis=0)[:, 1:]
        xs = np.diff(xs)
        first = 1
    coef, *_ = np.linalg.lstsq(design, xs, rcond=None)
    residual = xs - design @ coef
    variance = float(residual @ residual) / (xs.size - design.shape[1])
    cov_diag = variance * np.diag(np.linalg.pinv(design.T @ design))
    # x = a cos + b sin = Re((a - j b) e^{j w t})
    amplitude = coef[first::2] - 1j * coef[first + 1 :: 2]
    error = np.sqrt(0.5 * (cov_diag[first::2] + cov_diag[first + 1 :: 2]))
    return ToneFit(
        amplitude=np.asarray(amplitude, dtype=np.complex128),
        standard_error=np.asarray(error, dtype=np.float64),
        residual_rms=float(np.sqrt(np.mean(residual**2))),
        samples=int(t.size),
    )


def coherence_from_error(relative_error: npt.ArrayLike, averages: int) -> FloatArray:
    """The coherence an H1 estimate with ``averages`` averages has when the normalised
    random error of its magnitude is ``relative_error``: the standard error bound
    (Bendat & Piersol) ``e = sqrt(1 - g^2) / (|g| sqrt(2 n))`` solved for ``g^2``.
    ``frf_relative_error`` is its inverse."""
    e = np.asarray(relative_error, dtype=np.float64)
    with np.errstate(over="ignore"):  # an infinite error: coherence 0
        return np.asarray(1.0 / (1.0 + 2.0 * averages * e * e), dtype=np.float64)


def frf_relative_error(coherence: npt.ArrayLike, averages: int) -> FloatArray:
    """Normalised random error of an H1 estimate's magnitude (and its phase's standard
    deviation in radians) from its coherence and number of averages (Bendat &
    Piersol, Random Data, 9.3): ``sqrt(1 - g^2) / (|g| sqrt(2 n))``; infinite at zero
    coherence."""
    g2 = np.clip(np.asarray(coherence, dtype=np.float64), 0.0, 1.0)
    with np.errstate(divide="ignore"):
        return np.asarray(
            np.where(g2 > 0, np.sqrt(1.0 - g2) / np.sqrt(g2 * 2.0 * max(averages, 1)), np.inf),
            dtype=np.float64,
        )


@dataclass(frozen=True, slots=True)
class ImpulseFit:
    """An impulse response fitted to irregular samples of a system's output against
    its input known on a uniform grid (``impulse_fit``).

    ``impulse`` is piecewise constant: ``impulse[j]`` per grid step over the ``j``-th
    box of ``box_steps`` grid steps back from a sample (the first box starts at the
    last grid point at or before the sample). ``covariance`` is that of ``impulse``
    (``s^2 (A^T A + R)^-1``, s^2 the residual variance)."""

    impulse: FloatArray
    box_steps: int
    step_s: float
    covariance: FloatArray
    residual_rms: float
    samples: int

    def response(self, frequency_hz: npt.ArrayLike) -> tuple[ComplexArray, FloatArray]:
        """The frequency response of the fitted impulse response at ``frequency_hz``
        (output per input of the discrete system on the grid) and each value's
        standard error per real component (propagated from ``covariance``)."""
        f = np.asarray(frequency_hz, dtype=np.float64)
        n = self.impulse.size * self.box_steps
        z = np.exp(-2j * np.pi * np.outer(f, np.arange(n)) * self.step_s)
        # d T / d impulse[j]: the sum of the box's grid terms, each a step's weight
        g = z.reshape(f.size, self.impulse.size, self.box_steps).sum(axis=2)
        response = g @ self.impulse
        var_re = np.einsum("fi,ij,fj->f", g.real, self.covariance, g.real)
        var_im = np.einsum("fi,ij,fj->f", g.imag, self.covariance, g.imag)
        error = np.sqrt(0.5 * np.clip(var_re + var_im, 0.0, None))
        return np.asarray(response, dtype=np.complex128), np.asarray(error, dtype=np.float64)


def impulse_fit(
    t_s: npt.ArrayLike,
    y: npt.ArrayLike,
    grid_t0_s: float,
    step_s: float,
    u: npt.ArrayLike,
    *,
    taps: int,
    box_steps: int = 1,
    ridge: float = 1e-4,
) -> ImpulseFit:
    """Least-squares fit of an impulse response (``taps`` boxes of ``box_steps`` grid
    steps each, plus an offset and a linear trend) from samples ``y`` at any times
    ``t_s`` of the output of a system whose input ``u`` is known on the uniform grid
    ``grid_t0_s + i * step_s`` (a controller's ticks):
    ``y(t_k) ~ c0 + c1 t_k + sum_j impulse[j] sum_{i in box j} u[n_k - i]``,
    ``n_k`` the last grid point at or before ``t_k`` (least squares, by the normal
    equations with the ridge term below).

    Why, rather than a per-tone fit (``tone_fit``) of input and output: an input that
    is a staircase of targets sent over a slow wire has power at images of its tones
    around multiples of the target rate, and output samples taken at about the same
    rate fold the response to those images back onto the tones. A tone fit counts it
    as response at the tone; the impulse response explains the output from the whole
    input, images included, so they do not bias it. The fit needs the impulse
    response to have died out within ``taps * box_steps`` grid steps.

    ``ridge`` is a light Tikhonov term, relative to the mean diagonal of ``A^T A``:
    a periodic input excites few directions of a long impulse response, and the
    others are left small rather than arbitrary (at the excited frequencies the
    data dominate). ValueError when there are fewer samples than unknowns or
    samples before the grid holds a whole impulse response."""
    t = np.asarray(t_s, dtype=np.float64)
    ys = np.asarray(y, dtype=np.float64)
    us = np.asarray(u, dtype=np.float64)
    # The input's mean is removed (the offset column takes it): the ridge is relative
    # to the boxes' power, which must be the excitation's, not where the input sits.
    us = us - float(np.mean(us)) if us.size else us
    length = taps * box_steps
    columns = 2 + taps
    if t.size <= columns:
        raise ValueError(
            f"{t.size} samples cannot fit an impulse response of {taps} taps "
            f"({columns} unknowns): record longer"
        )
    n_k = np.floor((t - grid_t0_s) / step_s + 1e-9).astype(np.int64)
    if n_k.min() < length - 1 or n_k.max() >= us.size:
        raise ValueError("the input grid does not cover every sample's impulse response")
    # sum of u over the box ending `lag` steps back: differences of a cumulative sum
    cumulative = np.concatenate([[0.0], np.cumsum(us)])
    lags = np.arange(taps) * box_steps
    upper = n_k[:, None] - lags[None, :] + 1
    boxes = cumulative[upper] - cumulative[upper - box_steps]
    t_mid = 0.5 * (t[0] + t[-1])
    design = np.empty((t.size, columns))
    design[:, 0] = 1.0
    design[:, 1] = t - t_mid
    design[:, 2:] = boxes
    gram = design.T @ design
    penalty = np.zeros(columns)
    penalty[2:] = ridge * float(np.mean(np.diag(gram)[2:]))
    # The normal equations of min |A c - y|^2 + c^T R c: with the ridge they are well
    # conditioned, and one (2 + taps)-square inverse gives the fit and its covariance
    # (an SVD of the tall A costs far more).
    inverse = np.linalg.pinv(gram + np.diag(penalty), hermitian=True)
    coef = inverse @ (design.T @ ys)
    residual = ys - design @ coef
    variance = float(residual @ residual) / max(ys.size - columns, 1)
    covariance = variance * inverse
    return ImpulseFit(
        impulse=np.asarray(coef[2:], dtype=np.float64),
        box_steps=box_steps,
        step_s=step_s,
        covariance=np.asarray(covariance[2:, 2:], dtype=np.float64),
        residual_rms=float(np.sqrt(np.mean(residual**2))),
        samples=int(t.size),
    )
