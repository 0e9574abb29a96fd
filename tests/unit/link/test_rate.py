"""The link rate shown (drivers.engine.recent_rate_hz): a steady link reads its true
rate whenever it is asked, a link that stops delivering reads a falling rate, then 0."""

from __future__ import annotations

import numpy as np
import pytest

from servotune.link.engine import RATE_WINDOW_S, recent_rate_hz


@pytest.mark.parametrize("period_s", [0.002, 0.043, 0.0914, 0.5])
def test_a_steady_link_reads_its_rate_at_every_phase(period_s: float) -> None:
    """Samples every ``period_s`` (with 5 % jitter), latched 10 ms before they are
    known; asked at 500 moments spread over the sample phase. Counting the window to
    *now* read the 11 Hz (0.0914 s) case up to 6 % low and the 2 Hz case 37 % low."""
    rng = np.random.default_rng(7)
    times = np.arange(0.0, 30.0, period_s)
    times = np.sort(times + rng.normal(0, 0.05 * period_s, times.size))
    ratios = []
    for now in rng.uniform(5.0, 29.0, 500):
        known = times[times <= now - 0.01]
        ratios.append(recent_rate_hz(known.tolist(), float(now)) * period_s)
    # What is left: where the window's edge cuts the intervals, and the jitter.
    tolerance = 0.3 * period_s / RATE_WINDOW_S + 0.01
    assert abs(np.mean(ratios) - 1.0) < 0.01
    assert min(ratios) > 1.0 - tolerance and max(ratios) < 1.0 + tolerance


def test_a_link_that_stops_reads_a_falling_rate_then_zero() -> None:
    period_s = 0.1
    times = [i * period_s for i in range(101)]  # the last at t = 10 s
    steady = recent_rate_hz(times, 10.05)
    assert steady == pytest.approx(10.0, rel=0.01)
    readings = [recent_rate_hz(times, 10.0 + dt) for dt in (0.3, 0.6, 1.0, 1.5)]
    assert readings == sorted(readings, reverse=True)
    assert readings[0] < 0.95 * steady  # within a few intervals, not a frozen value
    assert recent_rate_hz(times, 12.01) == 0.0  # nothing left in the window
    assert recent_rate_hz([], 1.0) == 0.0 and recent_rate_hz([0.5], 1.0) == 0.0
