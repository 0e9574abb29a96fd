"""The settling time against stamps the driver cannot vouch for (``bench.quality``,
``_stamp_unvouched``): a sample whose latch may lie well before its stamp (a host that
stalled after writing the command, ``Sample.t_span_s``) must not locate a trusted
settling instant. Records are synthetic: a damped step sampled every 6 ms."""

from __future__ import annotations

import math
from typing import Any

from servotune.bench.metrics import compute_metrics
from servotune.bench.quality import assess
from tests.support.bench import judge_step

PERIOD_S = 0.006
STEP = 2000.0


def _position(t_s: float) -> float:
    """A 2000-count step with about 22 % overshoot, out of the 2 % band until ~0.12 s."""
    zeta, omega = 0.43, 60.0
    wd = omega * math.sqrt(1 - zeta * zeta)
    decay = math.exp(-zeta * omega * t_s)
    return STEP * (1 - decay * (math.cos(wd * t_s) + zeta * omega / wd * math.sin(wd * t_s)))


def _judge(times: list[float], spans: list[list[float]]) -> tuple[dict[str, Any], Any, Any]:
    positions = [_position(t) for t in times]
    return judge_step(times, positions, t0_s=0.0, y0=0.0, step=STEP, spans=spans)


def _clean_times() -> list[float]:
    return [PERIOD_S * (k + 1) for k in range(100)]


def _last_outside(times: list[float], band: float) -> int:
    return max(i for i, t in enumerate(times) if abs(_position(t) - STEP) > band)


def test_a_clean_record_with_short_spans_keeps_its_settling_time() -> None:
    times = _clean_times()
    judged, quality, m = _judge(times, [[t, 0.0006] for t in times])
    assert m.settling_time_s is not None and 0.08 < m.settling_time_s < 0.2
    assert judged["settling_time_s"] == m.settling_time_s, quality


def test_a_late_stamp_on_the_last_sample_outside_the_band_nulls_the_settling_time() -> None:
    """The CI case: the host stalled 0.13 s after the CR of the last read outside the
    band; that read is stamped after the stall, the next one follows it at once."""
    clean = _clean_times()
    _, _, m = _judge(clean, [])
    assert m.band is not None
    k = _last_outside(clean, m.band)
    stall_s = 0.13
    latched = clean[: k + 1]
    after = [t + stall_s for t in clean[k + 1 :]]
    # what the host recorded: the held read's value under a stamp 0.13 s late
    times = [*latched[:k], latched[k] + stall_s - 0.002, *after]
    positions_at = latched + [t - stall_s for t in after]  # when each was latched
    shown = [_position(t) for t in positions_at]
    m_late = compute_metrics(times, shown, t0_s=0.0, y0=0.0, y_final=STEP)
    assert m_late.settling_time_s is not None and m.settling_time_s is not None
    assert m_late.settling_time_s - m.settling_time_s > 0.1  # the record settles late
    rows = [[t, p, []] for t, p in zip(times, shown, strict=True)]
    common: dict[str, Any] = dict(
        kind="move",
        columns=["t_s", "position"],
        flag_names=[],
        rows=rows,
        t0_s=0.0,
        response="position",
        y0=0.0,
        y_final=STEP,
        band=m_late.band,
        fault_flags=[],
        done_flag=None,
        metrics=m_late.model_dump(),
        status="complete",
        message="",
    )
    spans = [[t, 0.0006] for t in times]
    spans[k] = [times[k], stall_s - 0.001]
    judged, quality = assess(**common, spans=spans)
    assert judged is not None
    assert judged["settling_time_s"] is None
    assert "before its stamp" in quality["untrusted"]["settling_time_s"]
    # Without the spans (a stored run) the record alone cannot tell: kept, as before.
    judged, _ = assess(**common)
    assert judged is not None and judged["settling_time_s"] == m_late.settling_time_s


def test_a_long_span_away_from_the_settling_instant_costs_it_nothing() -> None:
    times = _clean_times()
    spans = [[t, 0.0006] for t in times]
    spans[3] = [times[3], 0.05]  # in the rise, far from the instant
    spans[-5] = [times[-5], 0.05]  # long after it
    judged, quality, m = _judge(times, spans)
    assert judged["settling_time_s"] == m.settling_time_s, quality


# Holes: a starved host reads nothing for a while (p4 beside a CPU hog: a record of
# 0.1..0.4 s with no sample, and records whose first lobe fell in a hole). The metric
# the record shows is then the wrong one, yet every sample bracketing it is on time.


def test_a_hole_over_the_first_peak_nulls_the_overshoot_and_the_peak_time() -> None:
    """The highest sample is the second lobe (~5 % on this plant, not ~22 %): the gaps
    next to it are the usual ones, but the hole before it could hold a higher peak."""
    times = [t for t in _clean_times() if not 0.035 < t < 0.1]
    judged, quality, m = _judge(times, [[t, 0.0006] for t in times])
    assert m.overshoot_pct is not None and m.overshoot_pct < 10  # what the record shows
    assert judged["overshoot_pct"] is None, quality
    assert "hole" in quality["untrusted"]["overshoot_pct"]
    assert judged["peak_time_s"] is None, quality


def test_a_hole_after_the_settling_instant_nulls_the_settling_time() -> None:
    """A sample inside the band at a zero crossing of the ringing, then nothing for
    0.3 s: the record settles there, but the ringing left the band in the hole."""
    clean = _clean_times()
    _, _, m = _judge(clean, [])
    assert m.band is not None and m.settling_time_s is not None
    last_out = _last_outside(clean, m.band)
    k = max(
        i for i in range(last_out) if abs(_position(clean[i]) - STEP) <= m.band
    )  # inside the band, with the ringing still to leave it
    times = [t for t in clean if not clean[k] < t < clean[k] + 0.3]
    judged, quality, m_hole = _judge(times, [[t, 0.0006] for t in times])
    assert m_hole.settling_time_s is not None
    assert m_hole.settling_time_s < m.settling_time_s - 0.01  # the record settles early
    assert judged["settling_time_s"] is None, quality
    assert "after" in quality["untrusted"]["settling_time_s"]


def test_sparse_reads_at_rest_cost_the_overshoot_and_settling_nothing() -> None:
    """Gaps of 10 spacings once the axis rests (a loaded host late in a record) hide
    nothing: no metric is lost to them."""
    times = [t for t in _clean_times() if t < 0.3 or round(t / PERIOD_S) % 10 == 0]
    judged, quality, m = _judge(times, [[t, 0.0006] for t in times])
    assert judged["overshoot_pct"] == m.overshoot_pct, quality
    assert judged["settling_time_s"] == m.settling_time_s, quality
