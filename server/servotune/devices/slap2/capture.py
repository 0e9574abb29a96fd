"""SLAP2 capture: the focused poll of a captured module and its reconstructed setpoint.

Split from ``devices/slap2/link.py`` along the seam "what to poll and what a sample says
while an axis is captured"; the wire exchange stays there. Decisions (docs/capture.md):

* **Poll mix.** Every step reads ``rp`` (one sample per ``rp``); for
  ``QUIET_AFTER_MOVE_S`` after a move command nothing else. ``rss`` is read at
  most every ``RSS_PERIOD_S`` (the flags: in position, moving, faults; the limit
  switches stop the axis in the firmware, the host only reports them). ``pe`` is read
  only as often as needed to check the reconstructed setpoint: a few times right after
  a move command (``PE_FIRST_CHECKS``, every ``PE_EVERY_NEW``-th sample), then every
  ``PE_CHECK_PERIOD_S``; every ``PE_EVERY_UNTRUSTED``-th sample while no profile can
  be trusted in pm or vm; never outside pm/vm (the following error means nothing then).
  ``rve`` is not read: the velocity comes from the dense positions.
* **Setpoint.** A move (``ma``/``mr``) the driver sent, with the ``sv``/``sa`` it last
  read or wrote, is replayed through the firmware's trapezoid law
  (``servotune.devices.slap2.profile``) from the command's latch time: the setpoint at every
  sample, and the following error = setpoint - position. The start is the end of the
  previous reconstructed move, or, from rest, ``rp + pe`` of the last poll (exact at
  rest). A move commanded during a move replans from the generator's state then.
* **Check.** Each ``pe`` read (latched at ``t_pe``) is compared, at the next ``rp``, with
  the reconstruction: position interpolated between the ``rp`` before and after, plus
  ``pe``, against the profile at ``t_pe``. The tolerance covers what the host cannot
  know: 2 counts, half the motion between the two ``rp`` (interpolation), the profile's
  motion in one tick either way (tick phase). Two misses in a row (a limit switch
  aborted the move, a setting changed behind servotune's back) and the profile is
  dropped: samples then carry ``pe`` as read (a slow channel), as without capture.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

from servotune.devices.slap2.profile import (
    TICK_S,
    ProfileTrack,
    TrapezoidGenerator,
    firmware_setpoint,
)
from servotune.link.capture import CaptureStats

logger = logging.getLogger(__name__)

# While a module is captured its syscon ucon is on (ssb5; rsb5 after, if it was off):
# a refused command then answers -1UC, so a move (an injection sends one every few
# samples) needs no rss after it to tell whether it was taken.
CAPTURE_UCON = True
# rss (the flags) every RSS_PERIOD_S; right after a move once sooner (at most every
# RSS_AFTER_MOVE_S), so the flags show the move (not in position, moving) at once.
RSS_PERIOD_S = 0.2
RSS_AFTER_MOVE_S = 0.05
# Arrival: while a move the driver commanded has not yet arrived (the last rss shows
# in position clear) and the axis is inside the in-position window of its target
# (where in position can rise: the firmware sets it after sipt ticks inside it), for at
# most ARRIVAL_WATCH_S after the command, quiet time included: rss every
# RSS_ARRIVAL_PERIOD_S, so that the time to in position is located to ±12.5 ms, not
# ±100 ms. Each rss costs about one rp: a gap of ~2 sample periods every 25 ms, only
# inside the window, so never in the rise nor at an overshoot larger than the window.
RSS_ARRIVAL_PERIOD_S = 0.025
ARRIVAL_WATCH_S = 3.0
# After a move command only rp for this long: the rise and the first peak of a step
# are what the metrics need densest, and any other read there is a gap of one more
# transaction right where the response is fastest (docs/capture.md: interleaved reads
# misread the overshoot). The firmware, not the host, acts on a limit switch.
QUIET_AFTER_MOVE_S = 0.2
PE_CHECK_PERIOD_S = 0.1
PE_FIRST_CHECKS = 3
PE_EVERY_NEW = 3
PE_EVERY_UNTRUSTED = 2
CHECK_TOLERANCE_COUNTS = 2.0
MISSES_TO_DROP = 2
MOVE_MNEMONICS = ("ma", "mr")
# Commands after which the setpoint is no longer the replayed profile: st and vm/spwm
# leave position control, pm re-engages at the shaft position, sp/zp move the origin,
# calibrations run their own moves.
PROFILE_BREAKERS = frozenset({"st", "pm", "vm", "spwm", "cal", "ca", "sp", "zp"})


@dataclass(slots=True)
class ProfileState:
    """The reconstructed profile of one module (owner task only)."""

    track: ProfileTrack | None = None
    checks: int = 0
    misses: int = 0

    def clear(self) -> None:
        self.track = None
        self.checks = self.misses = 0

    def start(
        self,
        mnemonic: str,
        value: int,
        t_latch_s: float,
        sv: int | None,
        sa: int | None,
        resting_setpoint: float | None,
    ) -> None:
        """A move was accepted by the module at ``t_latch_s`` (see the module doc)."""
        previous = self.track
        self.clear()
        if not sv or not sa:
            return
        generator: TrapezoidGenerator | None = None
        base: float | None = None
        if previous is not None:
            if previous.finished_by(t_latch_s):
                base = previous.target
                generator = TrapezoidGenerator.from_wire(base, base, sv, sa)
            else:
                generator = previous.state_at(t_latch_s)
                base = previous.target
        elif resting_setpoint is not None:
            base = float(round(resting_setpoint))
            generator = TrapezoidGenerator.from_wire(base, base, sv, sa)
        if generator is None or base is None:
            return
        target = float(value) if mnemonic == "ma" else base + value
        generator.replan(target, sv, sa)
        self.track = ProfileTrack(t_latch_s, generator)

    def setpoint_at(self, t_s: float) -> float | None:
        return self.track.setpoint_at(t_s) if self.track is not None else None

    def hold(self, t_s: float, setpoint: int) -> None:
        """The module holds ``setpoint`` at rest in pm (seen twice in a row)."""
        self.clear()
        generator = TrapezoidGenerator(float(setpoint), float(setpoint), 0.0, 0.0, moving=False)
        self.track = ProfileTrack(t_s, generator)


def _quiet(profile: ProfileState, now_s: float) -> bool:
    track = profile.track
    return track is not None and track.moved and now_s - track.t_command_s < QUIET_AFTER_MOVE_S


@dataclass(slots=True)
class ModuleCapture:
    """Per-capture state of one captured module."""

    stats: CaptureStats
    last_rss_s: float = -math.inf
    last_pe_s: float = -math.inf
    samples_since_pe: int = 0
    previous: tuple[float, int] | None = None  # the last rp: (latch time, position)
    pending: tuple[float, int] | None = None  # a pe read after it: (latch time, pe)
    residuals: list[float] = field(default_factory=list)
    resting: int | None = None  # rp + pe at rest in pm without a profile, seen once

    def note_rest(
        self, profile: ProfileState, flags: dict[str, bool], t_s: float, setpoint: int
    ) -> None:
        """Without a profile, at rest in pm, the setpoint is the held target: the same
        ``rp + pe`` twice in a row starts a resting profile (checked like any other)."""
        if profile.track is not None or not flags.get("pm") or flags.get("move"):
            self.resting = None
            return
        if self.resting == setpoint:
            profile.hold(t_s, setpoint)
            self.resting = None
        else:
            self.resting = setpoint

    def wants_rss(
        self,
        profile: ProfileState,
        now_s: float,
        *,
        flags_fresh: bool,
        arrived: bool,
        inside_window: bool,
    ) -> bool:
        """``flags_fresh``: the driver read rss right after the move command (ucon
        off), so the flags are current; with ucon on nothing read them since: one
        rss after the move's first sample (no sooner than ``RSS_AFTER_MOVE_S`` after
        the last), then nothing in the quiet time but the arrival watch.
        ``arrived``: the last rss showed in position; ``inside_window``: the last
        position is within the in-position window of the move's target (the arrival
        watch, see ``RSS_ARRIVAL_PERIOD_S``)."""
        since = now_s - self.last_rss_s
        track = profile.track
        watching = (
            not arrived
            and inside_window
            and track is not None
            and track.moved
            and now_s - track.t_command_s < ARRIVAL_WATCH_S
        )
        if watching and since >= RSS_ARRIVAL_PERIOD_S:
            return True
        if _quiet(profile, now_s):
            assert track is not None
            stale = not flags_fresh and self.last_rss_s < track.t_command_s
            return stale and since >= RSS_AFTER_MOVE_S
        return since >= RSS_PERIOD_S

    def wants_pe(self, profile: ProfileState, flags: dict[str, bool], now_s: float) -> bool:
        if _quiet(profile, now_s) or not (flags.get("pm") or flags.get("vm")):
            return False
        if profile.track is None:
            return self.samples_since_pe + 1 >= PE_EVERY_UNTRUSTED
        if profile.checks < PE_FIRST_CHECKS:
            return self.samples_since_pe + 1 >= PE_EVERY_NEW
        return now_s - self.last_pe_s >= PE_CHECK_PERIOD_S

    def resolve(self, profile: ProfileState, t_s: float, position: int) -> str:
        """Check a pending ``pe`` now that the ``rp`` after it is known; returns why
        the profile was dropped ("" if it was not)."""
        pending, previous = self.pending, self.previous
        self.pending = None
        track = profile.track
        if pending is None or previous is None or track is None:
            return ""
        t_pe, pe = pending
        t0, p0 = previous
        if not t0 <= t_pe <= t_s or t_s <= t0:
            return ""
        interpolated = p0 + (position - p0) * (t_pe - t0) / (t_s - t0)
        predicted = firmware_setpoint(track.setpoint_at(t_pe))
        residual = interpolated + pe - predicted
        tolerance = (
            CHECK_TOLERANCE_COUNTS
            + 0.5 * abs(position - p0)
            + abs(track.setpoint_at(t_pe + TICK_S) - track.setpoint_at(t_pe - TICK_S))
        )
        self.stats.setpoint_checks += 1
        self.stats.max_setpoint_residual = max(self.stats.max_setpoint_residual, abs(residual))
        self.residuals.append(residual)
        if abs(residual) <= tolerance:
            profile.checks += 1
            profile.misses = 0
            return ""
        self.stats.setpoint_mismatches += 1
        profile.misses += 1
        if profile.misses < MISSES_TO_DROP:
            return ""
        why = (
            f"the reconstructed setpoint is {residual:+.0f} counts off the measured one "
            f"(pe {pe}, tolerance {tolerance:.0f}): following error taken from pe again"
        )
        profile.clear()
        return why
