"""Step-response metrics against analytic responses sampled at irregular (polled) times."""

from __future__ import annotations

import math
import random
import re

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from servotune.bench.metrics import (
    DEFINITIONS,
    compute_metrics,
    predict_first_order,
    predict_second_order,
)
from servotune.bench.quality import assess
from servotune.schema import RunMetrics
from tests.support.paths import DOCS

METRICS_MD = DOCS / "metrics.md"

DENSE = (0.0005, 0.0015)  # s between samples: jittered around 1 ms
POLLED_20MS = (0.015, 0.025)  # about 20 ms
POLLED = (0.010, 0.060)  # serial polling of the real devices


def sample_times(rng: random.Random, duration_s: float, gaps: tuple[float, float]) -> list[float]:
    """Irregular sample times after a command at t = 0: each gap uniform in ``gaps``."""
    lo, hi = gaps
    t = rng.uniform(0.0, hi)
    out: list[float] = []
    while t <= duration_s:
        out.append(t)
        t += rng.uniform(lo, hi)
    return out


def overshoot_2nd(zeta: float) -> float:
    """Peak overshoot (fraction of the step) of the standard second-order system."""
    return math.exp(-zeta * math.pi / math.sqrt(1 - zeta * zeta))


def envelope_settling_2nd(wn: float, zeta: float, band_fraction: float) -> float:
    """Time after which the decay envelope exp(-zeta wn t) / sqrt(1 - zeta²) stays in the band."""
    return math.log(1 / (band_fraction * math.sqrt(1 - zeta * zeta))) / (zeta * wn)


def lobes_beyond_band_2nd(zeta: float, band_fraction: float) -> int:
    """Extrema of the step response are at k pi / wd with |y - 1| = overshoot^k exactly."""
    mp = overshoot_2nd(zeta)
    return sum(1 for k in range(1, 200) if mp**k > band_fraction)


# --- first order --------------------------------------------------------------------


@pytest.mark.parametrize("tau", [0.05, 0.2, 1.0])
@pytest.mark.parametrize("seed", [1, 2])
def test_first_order_dense(tau: float, seed: int) -> None:
    rng = random.Random(seed)
    t = sample_times(rng, 8 * tau, DENSE)
    y = predict_first_order(tau, 1000.0, t, y0=200.0)
    m = compute_metrics(t, y, t0_s=0.0, y0=200.0, y_final=1200.0)
    assert m.rise_time_s == pytest.approx(tau * math.log(9), rel=0.02)
    assert m.overshoot_pct == 0.0
    assert m.settling_time_s == pytest.approx(tau * math.log(50), rel=0.02)
    assert m.oscillations == 0
    assert m.band == pytest.approx(20.0)
    assert m.peak_time_s == pytest.approx(t[-1])  # monotonic: the last sample
    assert m.samples == len(t)


@pytest.mark.parametrize("gaps", [POLLED_20MS, POLLED], ids=["20ms", "10-60ms"])
@pytest.mark.parametrize("seed", range(5))
def test_first_order_polled(gaps: tuple[float, float], seed: int) -> None:
    """Linear interpolation on the exponential misses a crossing by at most about
    gap² / (8 tau) (curvature over slope), so the rise time is within gap² / (4 tau)."""
    tau = 0.3
    t = sample_times(random.Random(seed), 3.0, gaps)
    m = compute_metrics(t, predict_first_order(tau, 1000.0, t), t0_s=0.0, y0=0.0, y_final=1000.0)
    assert m.max_sample_gap_s is not None
    assert gaps[0] <= m.max_sample_gap_s <= gaps[1]
    tol = 0.5 * m.max_sample_gap_s**2 / tau
    assert m.rise_time_s == pytest.approx(tau * math.log(9), abs=tol)
    assert m.settling_time_s == pytest.approx(tau * math.log(50), abs=tol)
    assert m.overshoot_pct == 0.0
    assert m.oscillations == 0


def test_device_window_is_the_band() -> None:
    tau = 0.2
    t = sample_times(random.Random(3), 3.0, DENSE)
    y = predict_first_order(tau, 1000.0, t)
    m = compute_metrics(t, y, t0_s=0.0, y0=0.0, y_final=1000.0, band=5.0)
    assert m.band == 5.0
    assert m.settling_time_s == pytest.approx(tau * math.log(1000 / 5), rel=0.01)


# --- second order -------------------------------------------------------------------


@pytest.mark.parametrize("zeta", [0.2, 0.5, 0.7])
def test_second_order_dense(zeta: float) -> None:
    wn = 10.0
    t = sample_times(random.Random(7), 4.0, DENSE)
    y = predict_second_order(wn, zeta, 1000.0, t, y0=-300.0)
    m = compute_metrics(t, y, t0_s=0.0, y0=-300.0, y_final=700.0)
    assert m.max_sample_gap_s is not None
    gap = m.max_sample_gap_s
    wd = wn * math.sqrt(1 - zeta * zeta)
    assert m.overshoot_pct == pytest.approx(overshoot_2nd(zeta) * 100, abs=1.0)
    assert m.peak_time_s == pytest.approx(math.pi / wd, abs=gap)
    assert m.peak_value == pytest.approx(700.0 + 1000.0 * overshoot_2nd(zeta), abs=1.0)
    # Inside the envelope bound, and no earlier than its last touch of the response
    # (the response touches the envelope every half period pi / wd).
    bound = envelope_settling_2nd(wn, zeta, 0.02)
    assert m.settling_time_s is not None
    assert bound - math.pi / wd - gap <= m.settling_time_s <= bound + gap
    assert m.oscillations == lobes_beyond_band_2nd(zeta, 0.02)


def test_second_order_oscillation_counts() -> None:
    """The brief's expectations, spelled out: several lobes at 0.2, at most one at 0.7."""
    assert lobes_beyond_band_2nd(0.2, 0.02) == 6
    assert lobes_beyond_band_2nd(0.5, 0.02) == 2
    assert lobes_beyond_band_2nd(0.7, 0.02) == 1
    assert lobes_beyond_band_2nd(0.7, 0.05) == 0
    t = sample_times(random.Random(8), 3.0, DENSE)
    y = predict_second_order(10.0, 0.7, 1000.0, t)
    m = compute_metrics(t, y, t0_s=0.0, y0=0.0, y_final=1000.0, band=50.0)
    assert m.oscillations == 0  # 4.6 % overshoot stays inside a 5 % band


@pytest.mark.parametrize("zeta", [0.2, 0.5, 0.7])
@pytest.mark.parametrize("seed", range(4))
def test_second_order_polled(zeta: float, seed: int) -> None:
    """At 10..60 ms the peak sample is within half a gap of the true peak, so the
    overshoot is low by at most |y''| (gap/2)² / 2 with |y''| <= wn² (1 + Mp) step."""
    wn = 8.0
    t = sample_times(random.Random(seed), 4.0, POLLED)
    m = compute_metrics(
        t, predict_second_order(wn, zeta, 1000.0, t), t0_s=0.0, y0=0.0, y_final=1000.0
    )
    assert m.max_sample_gap_s is not None
    gap = m.max_sample_gap_s
    mp = overshoot_2nd(zeta)
    wd = wn * math.sqrt(1 - zeta * zeta)
    tol_pct = 100 * 0.5 * wn**2 * (1 + mp) * (gap / 2) ** 2
    # The parabola through the peak sample and its neighbours is off the curve by at
    # most |y'''| |x (x - a) (x - b)| / 6 <= |y'''| 0.385 gap^3 / 6, |y'''| <= wn^3 (1 + Mp).
    over_pct = 100 * wn**3 * (1 + mp) * 0.385 * gap**3 / 6
    assert m.overshoot_pct is not None
    assert mp * 100 - tol_pct <= m.overshoot_pct <= mp * 100 + over_pct
    assert m.peak_time_s == pytest.approx(math.pi / wd, abs=gap)
    bound = envelope_settling_2nd(wn, zeta, 0.02)
    assert m.settling_time_s is not None
    assert bound - math.pi / wd - gap <= m.settling_time_s <= bound + gap
    assert m.oscillations is not None
    assert 0 < m.oscillations <= lobes_beyond_band_2nd(zeta, 0.02)
    if zeta == 0.7:
        assert m.oscillations in (0, 1)


def test_never_settling() -> None:
    t = sample_times(random.Random(4), 3.0, POLLED)
    t.append(2 * math.pi / 10.0 * math.ceil((t[-1] + 0.01) * 10.0 / (2 * math.pi)))
    undamped = predict_second_order(10.0, 0.0, 100.0, t)  # 1 - cos(10 t): back at 0
    m = compute_metrics(t, undamped, t0_s=0.0, y0=0.0, y_final=100.0)
    assert undamped[-1] == pytest.approx(0.0, abs=1e-9)
    assert m.settling_time_s is None
    assert m.oscillations is not None and m.oscillations > 5
    slow = predict_first_order(1.0, 100.0, t)  # 3 s = 3 tau: still 5 % short
    m = compute_metrics(t, slow, t0_s=0.0, y0=0.0, y_final=100.0)
    assert m.settling_time_s is None
    assert m.rise_time_s == pytest.approx(math.log(9), rel=0.01)


def test_settling_needs_the_end_inside_the_band() -> None:
    t = [0.1, 0.2, 0.3, 0.4, 0.5]
    m = compute_metrics(t, [50, 99, 100, 100, 97], t0_s=0.0, y0=0.0, y_final=100.0, band=2.0)
    assert m.settling_time_s is None
    m = compute_metrics(t, [50, 99, 100, 103, 100], t0_s=0.0, y0=0.0, y_final=100.0, band=2.0)
    # last point outside: 103 at 0.4; crosses 102 a third of the way to 100 at 0.5
    assert m.settling_time_s == pytest.approx(0.4 + 0.1 / 3)
    # already inside the band from the command point on (a step smaller than the band)
    m = compute_metrics(t, [1, 1, 1, 1, 1], t0_s=0.0, y0=0.0, y_final=1.0, band=2.0)
    assert m.settling_time_s == 0.0


def test_a_band_edge_hit_exactly_by_integer_counts_is_inside_the_band() -> None:
    # Pinned rule: positions are integer counts and the in-position window
    # an integer, so a response that comes to rest exactly on the window's edge is
    # common (5 counts off a ±5 window). The band is closed: |e| <= band is inside.
    t = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
    up = [50, 90, 106, 105, 105, 105]
    down = [-50, -90, -94, -95, -95, -95]
    for target, y in ((100.0, up), (-100.0, down)):
        m = compute_metrics(t, y, t0_s=0.0, y0=0.0, y_final=target, band=5.0)
        # the last point outside is 106 (-94) at 0.3; the edge is reached at 0.4 exactly
        assert m.settling_time_s == pytest.approx(0.4), target
        assert m.oscillations == (1 if target > 0 else 0)
    # On the edge from the first sample on: settled where the curve from the command
    # point reaches the edge, at that sample.
    m = compute_metrics(t, [95] * 6, t0_s=0.0, y0=0.0, y_final=100.0, band=5.0)
    assert m.settling_time_s == pytest.approx(0.1)
    # The bench's window check takes the same edge as inside: a good run.
    rows = [[ti, float(v), [1]] for ti, v in zip(t, up, strict=True)]
    _, quality = assess(
        kind="move",
        columns=["t_s", "position"],
        flag_names=["inpos"],
        rows=rows,
        t0_s=0.0,
        response="position",
        y0=0.0,
        y_final=100.0,
        band=5.0,
        fault_flags=[],
        done_flag="inpos",
        metrics=None,
        status="complete",
        message="",
    )
    assert "outside_window" not in [r["code"] for r in quality["reasons"]]


# --- symmetry and invariance (hypothesis) ---------------------------------------------

responses = st.one_of(
    st.tuples(st.just("first"), st.floats(0.02, 1.0), st.just(0.0)),
    st.tuples(st.just("second"), st.floats(3.0, 60.0), st.floats(0.0, 2.0)),
)


def _counts(kind: str, p: float, zeta: float, step: int, t: list[float]) -> list[int]:
    """Response in whole encoder counts relative to the start (exactly mirrorable)."""
    if kind == "first":
        unit = predict_first_order(p, 1.0, t)
    else:
        unit = predict_second_order(p, zeta, 1.0, t)
    return [round(step * u) for u in unit]


@settings(max_examples=150, deadline=None)
@given(
    response=responses,
    y0=st.integers(-1_000_000, 1_000_000),
    step=st.integers(20, 200_000),
    band=st.one_of(st.none(), st.integers(0, 50)),
    seed=st.integers(0, 2**32 - 1),
)
def test_negative_step_mirrors_positive(
    response: tuple[str, float, float], y0: int, step: int, band: int | None, seed: int
) -> None:
    kind, p, zeta = response
    t = sample_times(random.Random(seed), 2.0, POLLED)
    d = _counts(kind, p, zeta, step, t)
    band_f = None if band is None else float(band)
    up = compute_metrics(
        t, [float(y0 + v) for v in d], t0_s=0.0, y0=y0, y_final=y0 + step, band=band_f
    )
    down = compute_metrics(
        t, [float(y0 - v) for v in d], t0_s=0.0, y0=y0, y_final=y0 - step, band=band_f
    )
    for name in RunMetrics.model_fields:
        a, b = getattr(up, name), getattr(down, name)
        if name in ("step", "steady_state_error"):
            assert b == -a, name
        elif name == "peak_value":
            assert b == 2 * y0 - a, name
        else:
            assert b == a, name


@settings(max_examples=60, deadline=None)
@given(
    response=responses,
    offset_s=st.floats(-1e5, 1e5),
    seed=st.integers(0, 2**32 - 1),
)
def test_only_time_since_the_command_matters(
    response: tuple[str, float, float], offset_s: float, seed: int
) -> None:
    kind, p, zeta = response
    t = sample_times(random.Random(seed), 2.0, POLLED)
    y = [float(v) for v in _counts(kind, p, zeta, 1000, t)]
    ref = compute_metrics(t, y, t0_s=0.0, y0=0.0, y_final=1000.0)
    shifted = compute_metrics([ti + offset_s for ti in t], y, t0_s=offset_s, y0=0.0, y_final=1000.0)
    for name in RunMetrics.model_fields:
        a, b = getattr(ref, name), getattr(shifted, name)
        if isinstance(a, float):
            assert b == pytest.approx(a, rel=1e-6, abs=1e-6), name
        else:
            assert b == a, name


finite = st.floats(-1e9, 1e9)
sample_rows = st.lists(
    st.tuples(
        st.one_of(st.floats(0.0, 0.1), st.just(math.nan)),  # time increment, or lost
        st.one_of(finite, st.sampled_from([math.nan, math.inf, -math.inf])),
        st.one_of(st.none(), finite, st.just(math.nan)),
        st.booleans(),
        st.booleans(),
    ),
    max_size=60,
)


@settings(max_examples=300, deadline=None)
@given(
    rows=sample_rows,
    t_start=st.floats(-1.0, 1.0),
    t0=st.floats(-1.0, 2.0),
    y0=finite,
    y_final=st.one_of(finite, st.just(0.0), st.just(5e-324), st.just(1e-300)),
    band=st.one_of(st.none(), st.floats(0.0, 1e6)),
)
def test_arbitrary_data_never_raises(
    rows: list[tuple[float, float, float | None, bool, bool]],
    t_start: float,
    t0: float,
    y0: float,
    y_final: float,
    band: float | None,
) -> None:
    t: list[float] = []
    clock = t_start
    for dt, *_ in rows:
        if math.isnan(dt):
            t.append(math.nan)
        else:
            clock += dt
            t.append(clock)
    m = compute_metrics(
        t,
        [r[1] for r in rows],
        t0_s=t0,
        y0=y0,
        y_final=y_final,
        band=band,
        following_error=[r[2] for r in rows],
        flags={"inpos": [r[3] for r in rows], "oc": [r[4] for r in rows]},
    )
    duration = max(0.0, clock - t0)
    for name in RunMetrics.model_fields:
        value = getattr(m, name)
        assert not isinstance(value, float) or math.isfinite(value), name
    assert 0 <= m.samples <= len(rows)
    assert m.rise_time_s is None or m.rise_time_s >= 0
    assert m.overshoot_pct is None or m.overshoot_pct >= 0
    assert m.settling_time_s is None or 0 <= m.settling_time_s <= duration + 1e-9
    assert m.peak_time_s is None or 0 <= m.peak_time_s <= duration + 1e-9
    assert m.oscillations is None or m.oscillations >= 0
    if m.samples == 0:
        assert m.rise_time_s is m.settling_time_s is m.peak_value is None
    if y_final == y0:
        assert m.rise_time_s is m.overshoot_pct is m.oscillations is None
    if m.rms_following_error is not None:
        assert m.peak_following_error is not None
        assert m.rms_following_error <= m.peak_following_error * (1 + 1e-12)
    assert 0 <= m.time_in_flag_s["oc"] <= duration + 1e-9
    inpos = m.time_to_flag_s["inpos"]
    assert inpos is None or 0 <= inpos <= duration + 1e-9


# --- steady state, flags, following error --------------------------------------------


def test_steady_state_error_of_a_response_ending_short() -> None:
    tau = 0.1
    t = sample_times(random.Random(5), 1.5, POLLED)
    y = [float(round(v)) for v in predict_first_order(tau, 997.0, t)]
    m = compute_metrics(t, y, t0_s=0.0, y0=0.0, y_final=1000.0, band=5.0)
    assert m.steady_state_error == pytest.approx(3.0, abs=0.05)
    assert m.settling_time_s is not None  # 3 counts short is inside a 5-count window
    # negative step ending 3 counts short: y_final - y is negative (signed in units of y)
    y = [float(round(v)) for v in predict_first_order(tau, -997.0, t, y0=1000.0)]
    m = compute_metrics(t, y, t0_s=0.0, y0=1000.0, y_final=0.0, band=5.0)
    assert m.steady_state_error == pytest.approx(-3.0, abs=0.05)


def test_steady_state_window_takes_at_least_three_samples() -> None:
    t = [0.0, 1.0, 2.0, 3.0, 4.0, 10.0]  # only the last sample is in the last 10 %
    m = compute_metrics(t, [0, 5, 6, 7, 8, 9], t0_s=0.0, y0=0.0, y_final=10.0)
    assert m.steady_state_error == pytest.approx((3 + 2 + 1) / 3)
    m = compute_metrics(t[:2], [0.0, 5.0], t0_s=0.0, y0=0.0, y_final=10.0)
    assert m.steady_state_error is None


T0 = 12.5
FLAG_T = [T0 + dt for dt in (-0.10, -0.02, 0.03, 0.07, 0.12, 0.20, 0.26, 0.31)]


def test_time_in_fault_flag() -> None:
    oc = [False, True, True, False, True, True, False, True]
    m = compute_metrics(
        FLAG_T,
        [0.0] * 8,
        t0_s=T0,
        y0=0.0,
        y_final=100.0,
        flags={"oc": oc, "stall": [False] * 8},
    )
    # Each change midway between the reads around it: set from -0.06 (held into t0) to
    # 0.05, from 0.095 to 0.23, from 0.285 to the last read at 0.31.
    assert m.time_in_flag_s["oc"] == pytest.approx(0.05 + 0.135 + 0.025)
    # ± half of each bracketing interval: 0.02 + 0.025 + 0.03 + 0.025 (the rise before
    # t0 is no part of the time after it)
    assert m.time_in_flag_resolution_s["oc"] == pytest.approx(0.1)
    assert m.time_in_flag_s["stall"] == 0.0
    assert m.time_to_flag_s == {}


@pytest.mark.parametrize(
    ("series", "expected", "resolution"),
    [
        # stale "in position" at the first poll after the command, drops, rises
        # between the reads at 0.20 and 0.26
        ([True, True, True, False, False, False, True, True], 0.23, 0.03),
        ([True, True, False, True, False, True, True, True], 0.05, 0.02),  # first rise counts
        ([True] * 8, None, None),  # never dropped: the move was not seen
        ([True, True, False, False, False, False, False, False], None, None),  # never arrived
        ([False] * 8, None, None),
    ],
)
@pytest.mark.parametrize("name", ["inpos", "in_target"])
def test_time_to_arrival_flag(
    name: str, series: list[bool], expected: float | None, resolution: float | None
) -> None:
    m = compute_metrics(FLAG_T, [0.0] * 8, t0_s=T0, y0=0.0, y_final=100.0, flags={name: series})
    assert set(m.time_to_flag_s) == {name}
    assert m.time_in_flag_s == {}
    if expected is None:
        assert m.time_to_flag_s[name] is None
        assert m.time_to_flag_resolution_s[name] is None
    else:
        assert m.time_to_flag_s[name] == pytest.approx(expected)
        assert m.time_to_flag_resolution_s[name] == pytest.approx(resolution)


def test_flags_held_between_status_polls_are_timed_by_their_reads() -> None:
    # The position is read every 10 ms, the flags every 200 ms (SLAP2 rss in
    # a capture); every sample carries the last read. The axis arrives at 90 ms.
    # Timed at the first *sample* that shows it, in-position read 200+ ms; timed by
    # its reads it is 100 ms ± 100 (between the clear read at 0 and the set read at
    # 200 ms): the truth lies inside, and the ± says how little that is.
    t = [i * 0.01 for i in range(40)]
    reads = [0.0 if ti < 0.2 else 0.2 for ti in t]
    inpos = [ti >= 0.2 for ti in t]  # the read at 0.2 is the first that can show it
    held = [ti + 0.005 for ti in t]  # the samples come 5 ms after each read
    m = compute_metrics(
        held,
        [0.0] * 40,
        t0_s=0.0,
        y0=0.0,
        y_final=100.0,
        flags={"inpos": inpos, "oc": inpos},
        flags_t_s=reads,
    )
    assert m.time_to_flag_s["inpos"] == pytest.approx(0.1)
    assert m.time_to_flag_resolution_s["inpos"] == pytest.approx(0.1)
    truth = 0.09
    assert abs(m.time_to_flag_s["inpos"] - truth) <= m.time_to_flag_resolution_s["inpos"]
    # Without the read times the sample's own time is taken: 205 ms, not within ±.
    m = compute_metrics(held, [0.0] * 40, t0_s=0.0, y0=0.0, y_final=100.0, flags={"inpos": inpos})
    assert m.time_to_flag_s["inpos"] == pytest.approx(0.2)
    # The fault flag set by the same read: from 0.1 (± 0.1) to its last read (0.2).
    m = compute_metrics(
        held, [0.0] * 40, t0_s=0.0, y0=0.0, y_final=100.0, flags={"oc": inpos}, flags_t_s=reads
    )
    assert m.time_in_flag_s["oc"] == pytest.approx(0.1)
    assert m.time_in_flag_resolution_s["oc"] == pytest.approx(0.1)
    with pytest.raises(ValueError, match="flags_t_s"):
        compute_metrics(t, [0.0] * 40, t0_s=0.0, y0=0.0, y_final=1.0, flags_t_s=reads[:-1])


def test_following_error_statistics() -> None:
    t = [-0.1, 0.0, 0.1, 0.2, 0.3, 0.4]
    fe: list[float | None] = [100.0, 3.0, None, -4.0, math.nan, 0.0]  # -0.1 is before t0
    m = compute_metrics(t, [0.0] * 6, t0_s=0.0, y0=0.0, y_final=10.0, following_error=fe)
    assert m.peak_following_error == 4.0
    assert m.rms_following_error == pytest.approx(math.sqrt((9 + 16 + 0) / 3))
    m = compute_metrics(t, [0.0] * 6, t0_s=0.0, y0=0.0, y_final=10.0, following_error=[None] * 6)
    assert m.peak_following_error is None and m.rms_following_error is None
    m = compute_metrics(t, [0.0] * 6, t0_s=0.0, y0=0.0, y_final=10.0)
    assert m.peak_following_error is None and m.rms_following_error is None


# --- edge cases -------------------------------------------------------------------


def test_empty_record() -> None:
    m = compute_metrics(
        [],
        [],
        t0_s=0.0,
        y0=0.0,
        y_final=100.0,
        following_error=[],
        flags={"inpos": [], "oc": []},
    )
    assert m.samples == 0
    assert m.band == 2.0
    for name in (
        "max_sample_gap_s",
        "rise_time_s",
        "overshoot_pct",
        "peak_time_s",
        "peak_value",
        "settling_time_s",
        "steady_state_error",
        "oscillations",
        "peak_following_error",
        "rms_following_error",
    ):
        assert getattr(m, name) is None, name
    assert m.time_to_flag_s == {"inpos": None}
    assert m.time_in_flag_s == {"oc": 0.0}


def test_too_short_record() -> None:
    t = sample_times(random.Random(6), 0.5, POLLED)  # half a time constant: 39 %
    m = compute_metrics(t, predict_first_order(1.0, 100.0, t), t0_s=0.0, y0=0.0, y_final=100.0)
    assert m.rise_time_s is None
    assert m.settling_time_s is None
    assert m.overshoot_pct == 0.0
    assert m.steady_state_error is not None and m.steady_state_error > 55
    for n in (1, 2):
        m = compute_metrics(t[:n], [90.0] * n, t0_s=0.0, y0=0.0, y_final=100.0)
        assert m.rise_time_s is not None  # crossed 10 % and 90 % from the command point
        assert m.steady_state_error is None


def test_first_sample_past_both_levels_interpolates_from_the_command_point() -> None:
    m = compute_metrics([0.05, 0.10], [100.0, 100.0], t0_s=0.0, y0=0.0, y_final=100.0)
    assert m.rise_time_s == pytest.approx(0.05 * 0.8)
    assert m.settling_time_s == pytest.approx(0.05 * 0.98)


def test_zero_step() -> None:
    t = [0.0, 0.1, 0.2, 0.3, 0.4]
    y = [500.0, 503.0, 492.0, 501.0, 500.0]
    m = compute_metrics(t, y, t0_s=0.0, y0=500.0, y_final=500.0, band=5.0)
    assert m.rise_time_s is None and m.overshoot_pct is None and m.oscillations is None
    assert m.peak_value == 492.0 and m.peak_time_s == 0.2  # furthest from y_final
    assert m.settling_time_s == pytest.approx(0.2 + 0.1 * 3 / 9)
    m = compute_metrics(t, y, t0_s=0.0, y0=500.0, y_final=500.0)
    assert m.band is None and m.settling_time_s is None


def test_nan_samples_are_skipped() -> None:
    t = sample_times(random.Random(9), 2.0, POLLED)
    y = predict_second_order(12.0, 0.4, 1000.0, t)
    holed_t, holed_y = list(t), list(y)
    for i in range(3, len(t), 7):
        holed_y[i] = math.nan
    for i in range(5, len(t), 11):
        holed_t[i] = math.nan
    kept = [i for i in range(len(t)) if not (math.isnan(holed_t[i]) or math.isnan(holed_y[i]))]
    expected = compute_metrics(
        [t[i] for i in kept], [y[i] for i in kept], t0_s=0.0, y0=0.0, y_final=1000.0
    )
    assert compute_metrics(holed_t, holed_y, t0_s=0.0, y0=0.0, y_final=1000.0) == expected


def test_samples_before_the_command_are_ignored() -> None:
    t = [-0.2, -0.1, 0.1, 0.2, 0.3]
    y = [900.0, -50.0, 60.0, 100.0, 100.0]
    m = compute_metrics(t, y, t0_s=0.0, y0=0.0, y_final=100.0)
    assert m.samples == 3
    assert m.peak_value == 100.0 and m.overshoot_pct == 0.0
    assert m.rise_time_s == pytest.approx((0.1 + 0.1 * 30 / 40) - 0.1 * 10 / 60)


def test_peak_is_the_first_of_equal_samples() -> None:
    t = [0.1, 0.2, 0.3, 0.4]
    # The overshoot is refined between the tied samples: the parabola symmetric about
    # t = 0.25 through (0.2, 120), (0.3, 120) and (0.4, 100) peaks at 122.5 (the one
    # through (0.1, 50) would rise further: the smaller rise is taken).
    m = compute_metrics(t, [50.0, 120.0, 120.0, 100.0], t0_s=0.0, y0=0.0, y_final=100.0)
    assert (m.peak_time_s, m.peak_value, m.overshoot_pct) == (0.2, 120.0, pytest.approx(22.5))
    m = compute_metrics(t, [-50.0, -120.0, -120.0, -100.0], t0_s=0.0, y0=0.0, y_final=-100.0)
    assert (m.peak_time_s, m.peak_value, m.overshoot_pct) == (0.2, -120.0, pytest.approx(22.5))


def test_unsorted_time_raises() -> None:
    with pytest.raises(ValueError, match=r"non-decreasing.*t_s\[3\] = 0\.15.*t_s\[2\] = 0\.2"):
        compute_metrics([0.0, 0.1, 0.2, 0.15], [0.0] * 4, t0_s=0.0, y0=0.0, y_final=1.0)
    # repeated timestamps and lost ones (NaN) are fine
    compute_metrics([0.0, 0.1, 0.1, math.nan, 0.2], [0.0] * 5, t0_s=0.0, y0=0.0, y_final=1.0)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"y": [0.0]}, "t_s and y differ"),
        ({"following_error": [0.0]}, "following_error and t_s differ"),
        ({"flags": {"oc": [True]}}, "'oc' and t_s differ"),
        ({"band": -1.0}, "band must be"),
        ({"band": math.nan}, "band must be"),
        ({"y_final": math.nan}, "y_final must be finite"),
    ],
)
def test_bad_arguments_raise(kwargs: dict[str, object], message: str) -> None:
    args: dict[str, object] = {
        "t_s": [0.0, 0.1],
        "y": [0.0, 1.0],
        "t0_s": 0.0,
        "y0": 0.0,
        "y_final": 1.0,
    }
    args.update(kwargs)
    with pytest.raises(ValueError, match=re.escape(message)):
        compute_metrics(**args)  # type: ignore[arg-type]


# --- analytic predictions ------------------------------------------------------------


def test_predict_first_order() -> None:
    y = predict_first_order(0.5, 200.0, [-1.0, 0.0, 0.5, 50.0], y0=10.0)
    assert y == pytest.approx([10.0, 10.0, 10.0 + 200.0 * (1 - math.exp(-1)), 210.0])
    with pytest.raises(ValueError, match="tau_s"):
        predict_first_order(0.0, 1.0, [0.0])


@pytest.mark.parametrize("zeta", [0.0, 0.3, 0.999, 1.0, 1.001, 2.5])
def test_predict_second_order_solves_the_ode(zeta: float) -> None:
    """y'' + 2 zeta wn y' + wn² y = wn² step, y(0) = y'(0) = 0 (finite differences)."""
    wn, step, h = 7.0, 3.0, 1e-4
    for t in (0.05, 0.3, 1.1):
        ym, y, yp = predict_second_order(wn, zeta, step, [t - h, t, t + h])
        d1 = (yp - ym) / (2 * h)
        d2 = (yp - 2 * y + ym) / (h * h)
        assert d2 + 2 * zeta * wn * d1 + wn * wn * y == pytest.approx(wn * wn * step, rel=1e-4)
    start = predict_second_order(wn, zeta, step, [0.0, h, 1e3])
    assert start[0] == 0.0
    assert abs(start[1]) < step * (wn * h) ** 2  # zero slope at t = 0
    if zeta > 0:
        assert start[2] == pytest.approx(step)


def test_predict_second_order_is_continuous_through_critical_damping() -> None:
    t = [0.01 * k for k in range(1, 300)]
    under, critical, over = (
        predict_second_order(5.0, z, 1.0, t) for z in (1 - 2e-6, 1.0, 1 + 2e-6)
    )
    assert under == pytest.approx(critical, abs=1e-5)
    assert over == pytest.approx(critical, abs=1e-5)
    with pytest.raises(ValueError, match="zeta"):
        predict_second_order(5.0, -0.1, 1.0, t)
    with pytest.raises(ValueError, match="wn_rad_s"):
        predict_second_order(0.0, 0.5, 1.0, t)


# --- definitions --------------------------------------------------------------------


def test_every_field_has_a_definition_repeated_in_the_docs() -> None:
    names = set(RunMetrics.model_fields)
    assert set(DEFINITIONS) == names
    docs = " ".join(METRICS_MD.read_text(encoding="utf-8").split())
    for name, sentence in DEFINITIONS.items():
        assert sentence.endswith("."), name
        assert " ".join(sentence.split()) in docs, f"docs/metrics.md lacks the definition of {name}"


def test_two_tied_peak_samples_are_refined_between_them() -> None:
    """Integer counts tie where the true peak falls between two samples: the peak of
    y = 1100 - 4 (t - 2.5)^2 (step 0 -> 1000, counts floored) is 10 % overshoot,
    found between the tied samples, not read as the tie's 9.9 %."""
    t = [0.5, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0]
    y = [600.0, 1091.0, 1099.0, 1099.0, 1091.0, 1000.0, 1000.0]
    m = compute_metrics(t, y, t0_s=0.0, y0=0.0, y_final=1000.0)
    assert m.overshoot_pct == pytest.approx(10.0, abs=1e-6)
    # a longer plateau is not refined (nothing says where in it the peak is)
    y3 = [600.0, 1091.0, 1099.0, 1099.0, 1099.0, 1000.0, 1000.0]
    m3 = compute_metrics(t, y3, t0_s=0.0, y0=0.0, y_final=1000.0)
    assert m3.overshoot_pct == pytest.approx(9.9)


# --- the refined peak ---------------------------------------------------------------

# A step like the demo's captured position steps: 2000 counts, 25 % overshoot, the
# peak 69 ms after the command, sampled at 120 samples/s (8 samples to the peak).
PEAK_WN_RAD_S = 50.0
PEAK_ZETA = 0.4
PEAK_STEP = 2000.0
PEAK_RATE_HZ = 120.0


def _overshoots(records: list[tuple[list[float], list[float]]]) -> list[float]:
    out = []
    for t, y in records:
        m = compute_metrics(t, y, t0_s=0.0, y0=0.0, y_final=PEAK_STEP)
        assert m.overshoot_pct is not None
        out.append(m.overshoot_pct)
    return out


def _assert_peaks_agree(
    records: list[tuple[list[float], list[float]]], spread_pp: float, error_pp: float
) -> None:
    """The records' overshoots spread by at most ``spread_pp`` and each is within
    ``error_pp`` of the exact 2nd-order overshoot."""
    overshoots = _overshoots(records)
    exact = overshoot_2nd(PEAK_ZETA) * 100
    assert max(overshoots) - min(overshoots) <= spread_pp
    assert max(abs(o - exact) for o in overshoots) <= error_pp


@pytest.mark.parametrize(
    ("counts", "spread_pp", "error_pp"),
    [
        # exact values: what is left is the spline's own error (measured: 0.003 pp
        # of spread, 0.002 pp off; the 3-point parabola: 0.18 pp, 0.10 pp off)
        (False, 0.01, 0.005),
        # integer counts, as rp reads them: each sample is off by up to half a count
        # (0.025 pp), so 2 counts of spread is the bound (measured: 0.047 pp, 0.026
        # pp off; the parabola: 0.20 pp, 0.11 pp off)
        (True, 0.1, 0.06),
    ],
)
def test_dense_peak_does_not_follow_the_sampling_phase(
    counts: bool, spread_pp: float, error_pp: float
) -> None:
    """The same step sampled at 40 phases of the sample period: the refined peak
    (the spline through the highest sample and 3 either side) hardly depends on
    where the samples fall; the raw highest sample would be up to 0.4 pp low."""
    gap_s = 1 / PEAK_RATE_HZ
    records = []
    for k in range(40):
        t = [gap_s * (k / 40 + j) for j in range(120)]
        y = predict_second_order(PEAK_WN_RAD_S, PEAK_ZETA, PEAK_STEP, t)
        records.append((t, [float(round(v)) for v in y] if counts else y))
    _assert_peaks_agree(records, spread_pp, error_pp)


@pytest.mark.parametrize(
    ("counts", "spread_pp", "error_pp"),
    # measured: 0.006 pp of spread, 0.004 pp off; counts 0.053, 0.029 pp (the parabola:
    # 0.26, 0.15 pp; counts 0.31, 0.18 pp)
    [(False, 0.02, 0.01), (True, 0.1, 0.06)],
)
def test_peak_of_irregular_samples_with_known_times(
    counts: bool, spread_pp: float, error_pp: float
) -> None:
    """Timing jitter on the samples, their times known (stamped at the moment they were
    taken): each gap uniform in 0.5..1.5 sample periods of 120 samples/s, 40 records.
    The spline goes through the samples at their own times, so the irregular spacing
    costs it little."""
    gap_s = 1 / PEAK_RATE_HZ
    records = []
    for seed in range(40):
        t = sample_times(random.Random(seed), 1.0, (0.5 * gap_s, 1.5 * gap_s))
        y = predict_second_order(PEAK_WN_RAD_S, PEAK_ZETA, PEAK_STEP, t)
        records.append((t, [float(round(v)) for v in y] if counts else y))
    _assert_peaks_agree(records, spread_pp, error_pp)


def test_spline_peak_rises_no_more_than_the_larger_drop_to_a_neighbour() -> None:
    """Noisy samples must not make a peak up: the spline through these rises 1.46
    above the highest sample, more than the drop of 1 to either neighbour."""
    t = [float(x) for x in range(-5, 6)]
    y = [1000.0 + v for v in (-60, -50, -40, -30, -1, 0, -1, -30, -40, -50, -60)]
    m = compute_metrics(t, y, t0_s=-6.0, y0=0.0, y_final=1000.0)
    assert m.overshoot_pct == pytest.approx(0.1)  # 1001 of a 1000 step


def test_peak_near_the_record_ends_is_refined_by_the_parabola() -> None:
    """Too few samples for the spline (the highest sample one from an end): the vertex
    of the parabola through it and its neighbours, exact for a parabolic peak; the
    same where a repeated time stamp in the spline's reach leaves no spline (a
    spline through it would raise ValueError)."""

    def y_of(t: list[float]) -> list[float]:
        return [1100.0 - 4.0 * (x - 2.3) ** 2 for x in t]

    t = [0.5, 1.0, 2.0, 3.0]
    m = compute_metrics(t, y_of(t), t0_s=0.0, y0=0.0, y_final=1000.0)
    assert m.overshoot_pct == pytest.approx(10.0)
    t = [-2.0, -1.0, 1.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0]  # t = 1 stamped twice
    m = compute_metrics(t, y_of(t), t0_s=-3.0, y0=0.0, y_final=1000.0)
    assert m.overshoot_pct == pytest.approx(10.0)


def test_spline_peak_of_extreme_data_stays_finite() -> None:
    """Differences to the highest sample that overflow leave it to the parabola, and
    the spline is computed on scaled data: no overflow (warnings are errors here)."""
    t = [float(i) for i in range(9)]
    huge = [-1e308, -1e308, -1e308, 0.0, 1e308, 0.0, -1e308, -1e308, -1e308]
    m = compute_metrics(t, huge, t0_s=0.0, y0=0.0, y_final=1e308)
    assert m.overshoot_pct == 0.0  # the peak sample is y_final itself, never passed
    m = compute_metrics(t, [v / 10 for v in huge], t0_s=0.0, y0=-1e307, y_final=0.0)
    assert m.overshoot_pct is not None and math.isfinite(m.overshoot_pct)
    assert m.overshoot_pct == pytest.approx(100.0, rel=0.5)
    tiny = [i * 1e-300 for i in range(8)]
    y = [0.0, 1.0, 2.0, 3.0, 5.0, 3.0, 2.0, 1.0]
    m = compute_metrics(tiny, y, t0_s=0.0, y0=0.0, y_final=1.0)
    scaled = compute_metrics([i * 1.0 for i in range(8)], y, t0_s=0.0, y0=0.0, y_final=1.0)
    assert m.overshoot_pct == pytest.approx(scaled.overshoot_pct)
