"""The mechanics and the scale of the EP7047 engine: what it moves, and in which units.

What lives here: :class:`DriveConfig` (the speed range and counts per full step, which
scale velocities and positions) and :class:`StepperPlant` (an ideal stepper that
follows the setpoint, with an encoder offset, a calibration cam and a C-track pulse).

Why this seam: the plant is not the drive. It has no modes, takes no commands and
knows nothing of the process data; the engine only calls :meth:`StepperPlant.follow`
and :meth:`StepperPlant.set_counter` and reads the counter, the cam and the pulses.

Imports: the standard library only. Imported by: ``servotune.devices.ep7047.sim.positioning``,
``servotune.devices.ep7047.sim.engine``, ``servotune.devices.ep7047.sim.slave`` (builds the demo's
plant) and the tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class DriveConfig:
    """What the engine needs besides 0x8020/0x8021: the scale of velocities and positions.

    ``speed_range_steps_s`` is the speed range 0x8012:05 in full steps per second
    (10000 bp); ``counts_per_full_step`` relates the counter to full steps (4 x encoder
    lines / full steps per turn with an encoder; the microstep resolution with the
    internal counter).
    """

    speed_range_steps_s: int = 2000
    counts_per_full_step: float = 64.0

    @property
    def full_scale_counts_s(self) -> float:
        """Counter speed at 10000 bp (100 % of the speed range)."""
        return self.speed_range_steps_s * self.counts_per_full_step


@dataclass(slots=True)
class StepperPlant:
    """An ideal stepper: the shaft follows the engine's setpoint exactly, every cycle.

    Two frames: ``shaft_counts`` is the machine's fixed frame, where the cam and the
    C-track marks are; the counter (what the drive reports) reads
    ``shaft + counter_shift + encoder_offset``. ``counter_shift_counts`` changes when
    the counter is set (calibration, ENC "Set counter"). ``encoder_offset_counts``
    models what a real drive cannot pull in - lost steps, a slipped encoder: the actual
    position stays that far from the setpoint, which is how a test makes In-Target fail.

    ``cam_counts`` is the shaft interval [low, high] on which the cam (digital input 1)
    is on; ``sync_period_counts`` > 0 puts a C-track pulse at ``sync_phase_counts`` plus
    every whole period.
    """

    shaft_counts: float = 0.0
    encoder_offset_counts: float = 0.0
    cam_counts: tuple[float, float] | None = None
    sync_period_counts: float = 0.0
    sync_phase_counts: float = 0.0
    counter_shift_counts: float = 0.0

    @property
    def commanded_counts(self) -> float:
        """The setpoint (counter frame) that holds the shaft where it is."""
        return self.shaft_counts + self.counter_shift_counts

    @property
    def actual_counts(self) -> float:
        """What the counter reads."""
        return self.commanded_counts + self.encoder_offset_counts

    @property
    def cam_on(self) -> bool:
        if self.cam_counts is None:
            return False
        low, high = self.cam_counts
        return low <= self.shaft_counts <= high

    def follow(self, setpoint_counts: float) -> float | None:
        """Move the shaft to ``setpoint_counts`` (counter frame, before the encoder offset).

        Returns the counter value at the first C-track pulse passed on the way (as the
        hardware latches it, exact, not polled), or None.
        """
        old = self.shaft_counts
        new = setpoint_counts - self.counter_shift_counts
        self.shaft_counts = new
        pulse = self._first_pulse(old, new)
        if pulse is None:
            return None
        return pulse + self.counter_shift_counts + self.encoder_offset_counts

    def set_counter(self, value_counts: float) -> None:
        """Make the counter read ``value_counts`` now; the shaft does not move."""
        self.counter_shift_counts = value_counts - self.shaft_counts - self.encoder_offset_counts

    def _first_pulse(self, old: float, new: float) -> float | None:
        period = self.sync_period_counts
        if period <= 0 or new == old:
            return None
        phase = self.sync_phase_counts
        if new > old:
            pulse = phase + (math.floor((old - phase) / period) + 1) * period
            return pulse if pulse <= new else None
        pulse = phase + (math.ceil((old - phase) / period) - 1) * period
        return pulse if pulse >= new else None
