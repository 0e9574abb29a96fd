"""The setpoint of a polled axis, when it is made of two reads taken at different times.

A device that reports its profile setpoint only as a following error (SLAP2 ``pe``,
Z1100 GetError) gives ``setpoint = position + following error`` from two reads a
transaction apart (SLAP2 at 19200 baud: ~6 ms; Z1100 at 9600: 13.5 ms). Stamped at the
position's time, that sum is off by the change of the following error between the two
reads, ``dFE/dt * dt``: nothing while the axis tracks a smooth profile or rests, but
on a ringing axis (the loaded SLAP2 at factory gains: the following error swings by
±1000 counts at tens of Hz) the "setpoint" drew a wiggle of ±1000 counts while the
target stood still.

``SkewedSetpoint`` shows the sum only where the skew cannot matter: while the
profile runs, when the following error changed by at most ``STEADY_ERROR_COUNTS`` since
its previous read (which bounds the change within one transaction as long as the error
does not swing back and forth between two reads); once the profile has ended, only
when the position is steady as well (a resting axis; a ringing one moves by hundreds of
counts between two polls). Else nothing. A driver that can reconstruct the profile
(SLAP2: the moves it commanded, ``devices.slap2.capture``) uses that instead.
"""

from __future__ import annotations

from typing import Final

STEADY_ERROR_COUNTS: Final = 5.0


class SkewedSetpoint:
    """``position + error`` of one axis, or None where the reads' skew could matter."""

    def __init__(self) -> None:
        self._last: tuple[float, float | None] | None = None  # (error, position)

    def reset(self) -> None:
        self._last = None

    def setpoint(
        self, position: float | None, error: float | None, *, profile_running: bool = False
    ) -> float | None:
        """The setpoint from a position and the error read after it; None if either is
        missing, if the error changed by more than ``STEADY_ERROR_COUNTS`` since its
        previous read, or, once the profile has ended, if the position did."""
        if error is None:
            return None
        previous, self._last = self._last, (error, position)
        if position is None or previous is None:
            return None
        last_error, last_position = previous
        if abs(error - last_error) > STEADY_ERROR_COUNTS:
            return None
        if not profile_running and (
            last_position is None or abs(position - last_position) > STEADY_ERROR_COUNTS
        ):
            return None
        return position + error
