"""Is an axis' position loop working? Judged from telemetry, for every device alike.

The hub asks before a STOP (a loop that works brakes the axis shortest; one that does
not must lose its power at once, IEC 60204-1 category 0), while it watches the axis
come to rest after a stop, and after every bench run and auto-tune step (nothing the
product starts is left oscillating). What to look at comes from the descriptor
(``LoopSignals``); nothing here knows a device. Pure: samples in, a verdict out.

A loop is *not working* when, over the samples judged, with the loop on:

* **oscillation**: the following error swings back and forth at least
  ``OSCILLATION_SWINGS`` times by at least ``oscillation_counts`` each, the swings do
  not die out (the newer half of the last swings is at least half as large as the
  older half, on average), and the
  setpoint itself did not go back and forth by half a swing meanwhile (a loop that
  follows a multisine or a back-and-forth jog is not oscillating: its error swings with
  the reference; one that oscillates around a held position or a constant velocity
  is);
* **diverging**: the following error grows in one direction for
  ``DIVERGING_S`` without turning back, by at least twice ``oscillation_counts``, and
  is still growing, to more than twice ``oscillation_counts`` while the position is
  held, to more than ``MOVING_ERROR_SWINGS`` times it while the reference moves (a
  runaway: encoder or motor leads crossed, a loop pushed past its stability; a fast
  move's transient error turns back well within that time);
* **current limit held**: the current-limit flag is on in every sample of the last
  ``CURRENT_LIMIT_HELD_S`` (a jam, a stall, a loop that saturates for good).

"Working" needs evidence, judged on the samples' own timestamps, not on their count:
the newest stretch with the loop on must cover ``EVIDENCE_S`` (two cycles of the
slowest limit cycle seen) with no gap longer than ``MAX_GAP_S`` between two samples,
nor between the newest sample and the judgement (``age_s``: telemetry that stopped
coming says nothing about now), and an error that still swings by
``oscillation_counts`` or more in the newer half of that stretch, while the reference
holds, must be seen dying out in samples that resolve it (at least
``RESOLVED_SAMPLES`` samples per swing): a steady limit cycle sampled about as fast
as it swings (a starved host polling slowly) aliases into swings of any size, which
can look like a dying ring. Short of that the verdict is ``working`` None with
``sparse`` set (the caller chooses the stop that is safe either way: hub.stops) -
except where the samples are dense and the loop simply came on less than
``EVIDENCE_S`` ago: not judged yet, ``sparse`` False (the device's normal stop, watched:
no hole in the telemetry, so nothing says the host missed a swing). A
fault seen in sparse samples is still a fault. With the loop off there is no loop to
judge: ``working`` None, ``sparse`` False, and the caller keeps the device's normal
stop. The thresholds are the descriptor's
(``oscillation_counts``, ``rest_velocity``); how they were chosen per device is in
docs/control.md next to the measured stops.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final, Literal

from servotune.descriptor import LoopSignals
from servotune.link.base import Sample

# Half cycles of the following error that make an oscillation (two full cycles).
OSCILLATION_SWINGS: Final = 4
# A runaway: the error grows this long without turning back; while the reference
# moves, to at least this many times ``oscillation_counts``.
DIVERGING_S: Final = 0.5
MOVING_ERROR_SWINGS: Final = 20.0
# The current limit acting in every sample for this long is held, not a transient.
CURRENT_LIMIT_HELD_S: Final = 0.3
# At rest: position still (below rest_velocity) and the error small for this long.
REST_S: Final = 0.25
# Evidence that a loop works: samples covering this long (four swings, i.e. two cycles,
# of the slowest limit cycle seen, ~3 Hz) without a gap longer than MAX_GAP_S (about
# a half cycle of it: a longer gap can hide a whole swing); a swinging error must be
# resolved by this many samples per swing, on average, to be seen dying out.
EVIDENCE_S: Final = 0.7
MAX_GAP_S: Final = 0.2
RESOLVED_SAMPLES: Final = 3.0

LoopFault = Literal["oscillation", "diverging", "current_limit"]


@dataclass(frozen=True, slots=True)
class LoopVerdict:
    """``working``: True (judged, fine), False (not working: ``fault`` and ``reason``
    say why, in words for the event log), None (no evidence either way). ``sparse``:
    None because the loop is on but the telemetry is too sparse or too late to tell
    (``reason`` says what was missing); False with None: the loop is off (or no
    telemetry at all), nothing to judge."""

    working: bool | None
    fault: LoopFault | None = None
    reason: str = ""
    sparse: bool = False


NO_EVIDENCE: Final = LoopVerdict(None, None, "")


@dataclass(frozen=True, slots=True)
class _Series:
    t: list[float]
    position: list[float]
    error: list[float]
    reference: list[float]
    limited: list[bool]
    held_from: int | None  # from this index on no moving flag is on (None: not known)
    loop_came_on: bool = False  # a sample with the loop off came right before the first


def _series(samples: Sequence[Sample], signals: LoopSignals, since: float) -> _Series | None:
    """The newest stretch of samples at or after ``since`` with the loop on and position
    and error known, oldest first, as plain lists (a sample with the loop off ends the
    stretch: before it the error was not the loop's); None when the newest sample has
    the loop off."""
    stretch: list[Sample] = []
    came_on = False
    for sample in reversed(samples):
        if sample.t < since:
            break
        if signals.closed_loop_flags and not any(
            sample.flags.get(name) for name in signals.closed_loop_flags
        ):
            if not stretch:
                return None
            came_on = True
            break
        stretch.append(sample)
    t: list[float] = []
    position: list[float] = []
    error: list[float] = []
    reference: list[float] = []
    limited: list[bool] = []
    held_from: int | None = 0 if signals.moving_flags else None
    for sample in reversed(stretch):
        p = sample.channels.get(signals.position_channel)
        e = sample.channels.get(signals.following_error_channel)
        if p is None or e is None:
            continue
        r = sample.channels.get(signals.reference_channel) if signals.reference_channel else None
        t.append(sample.t)
        position.append(float(p))
        error.append(float(e))
        reference.append(float(r) if r is not None else float(p) + float(e))
        flag = signals.current_limit_flag
        limited.append(bool(sample.flags.get(flag)) if flag else False)
        if held_from is not None and any(sample.flags.get(n) for n in signals.moving_flags):
            held_from = len(t)
    return _Series(t, position, error, reference, limited, held_from, came_on)


def swings(values: Sequence[float], hysteresis: float) -> list[tuple[int, float]]:
    """The confirmed turning points of ``values``, at least ``hysteresis`` apart: a
    list of (index, value) of successive extremes, each one confirmed by the signal
    having come back from it by ``hysteresis`` (so the running extreme at the end is
    not in it). Noise smaller than ``hysteresis`` makes no extreme."""
    extremes: list[tuple[int, float]] = []
    if not values:
        return extremes
    lo_i = hi_i = anchor = 0
    direction = 0
    for i, value in enumerate(values):
        if direction == 0:
            if value > values[hi_i]:
                hi_i = i
            if value < values[lo_i]:
                lo_i = i
            if values[hi_i] - values[lo_i] >= hysteresis:
                first, anchor = (lo_i, hi_i) if lo_i < hi_i else (hi_i, lo_i)
                extremes.append((first, values[first]))
                direction = 1 if lo_i < hi_i else -1
            continue
        if (value - values[anchor]) * direction > 0:
            anchor = i  # still going the same way: the extreme moves on
        elif abs(value - values[anchor]) >= hysteresis:
            extremes.append((anchor, values[anchor]))
            direction = -direction
            anchor = i
    return extremes


@dataclass(frozen=True, slots=True)
class _Swinging:
    """Sustained swings of a signal: their peak-to-peak amplitudes (newest last) and
    the indexes of the first and last extreme they span."""

    amplitudes: list[float]
    first: int
    last: int

    @property
    def mean(self) -> float:
        return sum(self.amplitudes) / len(self.amplitudes)


def _sustained(values: Sequence[float], hysteresis: float, needed: int) -> _Swinging | None:
    """At least ``needed`` swings of ``hysteresis`` or more among ``values``, not dying
    out. Sampled at a few samples per cycle, the extremes seen scatter (where the
    samples fall in the cycle), so "not dying out" compares the halves of the newest
    swings (up to twice ``needed``) on average, not single swings."""
    extremes = swings(values, hysteresis)
    amplitudes = [abs(b[1] - a[1]) for a, b in itertools.pairwise(extremes)]
    if len(amplitudes) < needed:
        return None
    count = min(len(amplitudes), 2 * needed)
    recent = amplitudes[-count:]
    older, newer = recent[: count // 2], recent[count // 2 :]
    if sum(newer) / len(newer) < 0.5 * sum(older) / len(older):
        return None  # dying out: ringing of a loop that works
    return _Swinging(recent, extremes[-count - 1][0], extremes[-1][0])


def _oscillation(series: _Series, signals: LoopSignals) -> str:
    h = signals.oscillation_counts
    found: _Swinging | None = None
    what = ""
    held = series.held_from
    if held is not None and len(series.t) - held >= 2 * OSCILLATION_SWINGS:
        # The newest stretch in which the loop holds a fixed position (no profile, no
        # velocity mode): any sustained swinging is the loop's own. Seen in the error,
        # or in the position: that also shows it where the error is read at another
        # moment than the position (their pairing scatters), or where the oscillation
        # is faster than the samples (aliased).
        found = _sustained(series.error[held:], h, OSCILLATION_SWINGS)
        what = "the following error (position held)"
        if found is None:
            found = _sustained(series.position[held:], h, OSCILLATION_SWINGS - 1)
            what = "the position (held)"
        if found is not None:
            found = _Swinging(found.amplitudes, found.first + held, found.last + held)
    if found is None:
        found = _sustained(series.error, h, OSCILLATION_SWINGS)
        what = "the following error"
        reference = series.reference[found.first : found.last + 1] if found else []
        if found is not None and len(swings(reference, 0.5 * found.mean)) >= 2:
            return ""  # the reference itself goes back and forth: the loop follows it
    if found is None:
        return ""
    span_s = series.t[found.last] - series.t[found.first]
    cycles = len(found.amplitudes) / 2
    frequency = f" at ~{cycles / span_s:.1f} Hz as sampled" if span_s > 0 else ""
    return (
        f"{what} oscillates ±{max(found.amplitudes) / 2:.0f} counts{frequency} "
        f"({len(found.amplitudes)} swings, not dying out)"
    )


def _diverging(series: _Series, signals: LoopSignals) -> str:
    error = series.error
    if len(error) < 3:
        return ""
    # Holding a fixed position the error must not keep growing at all; while the
    # reference moves it may (a loop without integral lags in proportion to the speed
    # it is ramped to), so there only an error of MOVING_ERROR_SWINGS swings counts.
    holding = series.held_from is not None and series.held_from < len(error) - 2
    bound = 2.0 if holding else MOVING_ERROR_SWINGS
    if abs(error[-1]) < bound * signals.oscillation_counts:
        return ""
    # Walk back from the newest sample while |error| kept growing (allowing noise of a
    # tenth of the oscillation threshold) in one direction.
    sign = 1.0 if error[-1] > 0 else -1.0
    slack = signals.oscillation_counts / 10
    start = len(error) - 1
    while start > 0 and sign * error[start - 1] <= sign * error[start] + slack:
        start -= 1
    grown = sign * (error[-1] - error[start])
    lasted = series.t[-1] - series.t[start]
    if lasted >= DIVERGING_S and grown >= 2 * signals.oscillation_counts:
        return (
            f"the following error grows without turning back: {error[start]:.0f} -> "
            f"{error[-1]:.0f} counts in {lasted:.2f} s"
        )
    return ""


def _current_limit(series: _Series) -> str:
    if not series.limited or not series.limited[-1]:
        return ""
    start = len(series.limited) - 1
    while start > 0 and series.limited[start - 1]:
        start -= 1
    held = series.t[-1] - series.t[start]
    if held >= CURRENT_LIMIT_HELD_S and len(series.limited) - start >= 3:
        return f"the current limit has been acting for {held:.2f} s without a break"
    return ""


def _coverage(series: _Series, since: float, age_s: float) -> tuple[str, bool]:
    """Why the newest samples do not cover ``EVIDENCE_S`` densely up to the judgement
    (``age_s`` after the newest), and whether for holes in the telemetry (True) or
    because the loop came on too recently to tell (False); ("", False) when they do."""
    if age_s > MAX_GAP_S:
        return f"no telemetry for the last {age_s:.2f} s", True
    t = series.t
    start = len(t) - 1
    while start > 0 and t[start] - t[start - 1] <= MAX_GAP_S:
        start -= 1
    covered = t[-1] - t[start]
    if covered >= EVIDENCE_S:
        return "", False
    if start > 0:
        gap = t[start] - t[start - 1]
        return f"a gap of {gap:.2f} s in the telemetry {covered:.2f} s before its newest", True
    if not series.loop_came_on and t[0] - since > MAX_GAP_S:
        return f"no telemetry for {t[0] - since:.2f} s before {covered:.2f} s of it", True
    return f"the loop has been on for {covered:.2f} s only", False


def _unresolved(series: _Series, signals: LoopSignals) -> str:
    """Why a swinging error cannot be seen dying out (see the module docstring), or ""
    when it does not swing in the newer half of the stretch (by time), or the
    reference swings with it (a loop following it), or the samples resolve it."""
    h = signals.oscillation_counts
    t = series.t
    middle = t[-1] - (t[-1] - t[0]) / 2
    newer = next(i for i, ti in enumerate(t) if ti >= middle)
    tail = series.error[newer:]
    if not tail or max(tail) - min(tail) < h:
        return ""  # quiet by the end: died out, or never swung
    extremes = swings(series.error, h)
    if len(extremes) < 2:
        return ""  # one excursion (a step's transient), not a swinging error
    amplitude = max(tail) - min(tail)
    if len(swings(series.reference[newer:], 0.5 * amplitude)) >= 2:
        return ""  # the reference goes back and forth: the loop follows it
    per_swing = (extremes[-1][0] - extremes[0][0]) / (len(extremes) - 1)
    if per_swing >= RESOLVED_SAMPLES:
        return ""
    return (
        f"the following error still swings by {amplitude:.0f} counts with "
        f"{per_swing:.1f} samples per swing: too few to tell a dying ring from a "
        f"limit cycle"
    )


def judge(
    samples: Sequence[Sample], signals: LoopSignals, *, since: float, age_s: float = 0.0
) -> LoopVerdict:
    """The verdict on the samples at or after ``since`` (see the module docstring);
    ``age_s``: how long before the judgement the newest sample came (0: just now)."""
    series = _series(samples, signals, since)
    if series is None or not series.t:
        return NO_EVIDENCE
    if len(series.t) >= 3:
        for fault, reason in (
            ("current_limit", _current_limit(series)),
            ("oscillation", _oscillation(series, signals)),
            ("diverging", _diverging(series, signals)),
        ):
            if reason:
                return LoopVerdict(False, fault, reason)  # type: ignore[arg-type]
    missing, sparse = _coverage(series, since, age_s)
    if not missing:
        missing, sparse = _unresolved(series, signals), True
    if missing and sparse:
        return LoopVerdict(None, None, f"telemetry too sparse to judge the loop: {missing}", True)
    if missing:
        return LoopVerdict(None, None, f"not judged yet: {missing}")
    return LoopVerdict(True)


def at_rest(samples: Sequence[Sample], signals: LoopSignals, *, since: float) -> bool:
    """The axis has been at rest for ``REST_S`` by its newest sample: the position moved
    slower than ``rest_velocity`` between every two samples of that stretch (and, with
    the loop on, the following error stayed within ``oscillation_counts``)."""
    recent = [s for s in samples if s.t >= since]
    if len(recent) < 2:
        return False
    newest = recent[-1].t
    stretch = [s for s in recent if s.t >= newest - REST_S]
    if len(stretch) < 2 or stretch[0].t > newest - REST_S * 0.8:
        return False  # too short a stretch of samples to say
    for a, b in itertools.pairwise(stretch):
        pa = a.channels.get(signals.position_channel)
        pb = b.channels.get(signals.position_channel)
        if pa is None or pb is None or b.t <= a.t:
            continue
        if abs(pb - pa) / (b.t - a.t) > signals.rest_velocity:
            return False
    loop_on = not signals.closed_loop_flags or any(
        stretch[-1].flags.get(name) for name in signals.closed_loop_flags
    )
    if loop_on:
        error = stretch[-1].channels.get(signals.following_error_channel)
        if error is not None and abs(error) > signals.oscillation_counts:
            return False
    return True
