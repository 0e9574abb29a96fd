"""A rig's clock seen from the hub, estimated from round trips (``cmd.clock``).

The hub sends a probe at ``sent`` (its own monotonic clock), the rig answers with its
clock ``rig_now`` (the rig server's ``Hub.now()``, the clock its telemetry, presence
and deadlines are stamped in), the answer arrives at ``received``. Whatever the
delays, the rig read its clock between ``sent`` and ``received``, so the offset
``rig - hub`` lies in ``[rig_now - received, rig_now - sent]``. Every probe narrows the
interval; the quickest round trip decides. Nothing here is guessed from how late a
message seems: a message that was held up (a rig's client buffering through an
outage, a hub whose loop was busy) cannot move the estimate.

Both clocks are monotonic and tick at the same rate to within ``DRIFT`` (crystal
tolerance plus NTP slewing: 200 ppm is generous), so an old probe's interval is
widened by that much per second of its age. A probe that contradicts the others
(the intervals no longer overlap: another clock, a rig process restarted) starts the
estimate again from that probe.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

DRIFT = 200e-6
# Probes older than this no longer narrow the estimate (their widened interval would not).
PROBE_WINDOW_S = 60.0


@dataclass(frozen=True, slots=True)
class Probe:
    sent: float
    rig_now: float
    received: float

    def bounds(self, now: float) -> tuple[float, float]:
        """This probe's interval of the offset ``rig - hub``, widened for its age."""
        widen = DRIFT * max(0.0, now - self.received)
        return self.rig_now - self.received - widen, self.rig_now - self.sent + widen


class RigClock:
    """The offset ``rig clock - hub clock`` of one rig process, as an interval."""

    def __init__(self) -> None:
        self._probes: deque[Probe] = deque()

    @property
    def known(self) -> bool:
        return bool(self._probes)

    def add(self, sent: float, rig_now: float, received: float) -> bool:
        """Take in one round trip; False (and the estimate restarted from it) when it
        contradicts the earlier ones."""
        probe = Probe(sent, rig_now, received)
        while self._probes and received - self._probes[0].received > PROBE_WINDOW_S:
            self._probes.popleft()
        consistent = True
        if self._probes:
            low, high = self.bounds(received)
            p_low, p_high = probe.bounds(received)
            consistent = p_low <= high and low <= p_high
            if not consistent:
                self._probes.clear()
        self._probes.append(probe)
        return consistent

    def reset(self) -> None:
        self._probes.clear()

    def bounds(self, now: float) -> tuple[float, float]:
        """``(low, high)``: the offset ``rig - hub`` lies in between. ValueError if no
        probe came back yet."""
        if not self._probes:
            raise ValueError("no round trip to the rig yet")
        lows, highs = zip(*(p.bounds(now) for p in self._probes), strict=True)
        return max(lows), min(highs)

    def to_hub(self, rig_t: float, now: float) -> float:
        """A rig time on the hub's clock (the middle of the interval)."""
        low, high = self.bounds(now)
        return rig_t - (low + high) / 2

    def uncertainty_s(self, now: float) -> float:
        """Half the interval's width: how far ``to_hub`` can be off."""
        low, high = self.bounds(now)
        return (high - low) / 2
