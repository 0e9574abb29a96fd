"""The mechanics and the scale of the EP7047 engine: what it moves, and in which units.

What lives here: :class:`DriveConfig` (the speed range and counts per full step, which
scale velocities and positions), :class:`StepperPlant` (a stepper that follows the
setpoint while its output stage is on, with an encoder offset, a calibration cam and a
C-track pulse) and :class:`Mechanics` (the rotor and load it carries: what happens when
the output stage is switched off at speed).

Why this seam: the plant is not the drive. It has no modes, takes no commands and
knows nothing of the process data; the engine only calls :meth:`StepperPlant.follow`
(output stage on), :meth:`StepperPlant.coast` (off) and :meth:`StepperPlant.set_counter`
and reads the counter, the cam and the pulses.
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


@dataclass(frozen=True, slots=True)
class Mechanics:
    """The rotor and its load, as the shaft feels them with the motor unpowered.

    While the drive's output stage is on, the stepper follows its setpoint (this plant
    has no step loss); when it is switched off at speed nothing holds the shaft: rotor
    and load coast down from their speed under friction, d(omega)/dt = -(friction_nm *
    sign(omega) + viscous_nm_s_per_rad * omega) / inertia_kg_m2, until they stop.

    ``inertia_kg_m2`` is the rotor plus the load as seen at the motor shaft;
    ``friction_nm`` the Coulomb part (bearings, the load's guides, and the average
    drag of the unpowered motor's detent torque); ``viscous_nm_s_per_rad`` the part
    that grows with speed; ``counts_per_rev`` converts the shaft angle to counts.
    """

    inertia_kg_m2: float
    friction_nm: float
    viscous_nm_s_per_rad: float
    counts_per_rev: float

    def __post_init__(self) -> None:
        if self.inertia_kg_m2 <= 0 or self.counts_per_rev <= 0:
            raise ValueError("inertia_kg_m2 and counts_per_rev must be > 0")
        if self.friction_nm < 0 or self.viscous_nm_s_per_rad < 0:
            raise ValueError("friction_nm and viscous_nm_s_per_rad must be >= 0")
        if self.friction_nm == 0 and self.viscous_nm_s_per_rad == 0:
            raise ValueError("without friction an unpowered shaft would never stop")

    @property
    def friction_counts_s2(self) -> float:
        """The Coulomb friction's deceleration, in counts/s^2."""
        return self.friction_nm / self.inertia_kg_m2 * self.counts_per_rev / (2 * math.pi)

    @property
    def viscous_per_s(self) -> float:
        """The viscous friction's rate (1/s): speed decays as exp(-rate * t) by it."""
        return self.viscous_nm_s_per_rad / self.inertia_kg_m2

    def coast(self, speed_counts_s: float, dt_s: float) -> tuple[float, float]:
        """(distance in counts, speed after) of a shaft coasting ``dt_s`` from
        ``speed_counts_s``: the exact solution of the equation above, piecewise up to
        standstill (where Coulomb friction holds it)."""
        if speed_counts_s == 0.0 or dt_s <= 0:
            return 0.0, speed_counts_s
        direction = 1.0 if speed_counts_s > 0 else -1.0
        w0 = abs(speed_counts_s)
        a = self.friction_counts_s2
        k = self.viscous_per_s
        if k == 0.0:
            t_stop = w0 / a
            t = min(dt_s, t_stop)
            w = 0.0 if t >= t_stop else w0 - a * t
            return direction * (w0 * t - a * t * t / 2), direction * w
        bias = a / k  # speed offset of the Coulomb part
        t_stop = math.log((w0 + bias) / bias) / k if a > 0 else math.inf
        t = min(dt_s, t_stop)
        decay = math.exp(-k * t)
        distance = (w0 + bias) * (1 - decay) / k - bias * t
        w = 0.0 if t >= t_stop else (w0 + bias) * decay - bias
        return direction * distance, direction * w


# The demo's motor and load (``devices.ep7047.sim.slave.demo_slave``; docs/control.md):
# a NEMA 23 class hybrid stepper (rotor 0.3-0.5 kg cm^2, 1-2 N m holding torque, the
# size an EP7047's 5 A drives) with a load of about three times the rotor's inertia (a
# small leadscrew table; the usual "keep the inertia ratio under 10" well met), so
# 2e-4 kg m^2 at the shaft; 0.05 N m of Coulomb friction (about 4 % of the holding torque: the
# unpowered detent drag plus bearings and the guide) and 1e-4 N m s/rad viscous.
# Unpowered at the demo's top speed (10 rev/s) it coasts ~0.25 s and ~1.3 turns; the
# emergency ramp (100 ms to standstill from the full speed range) needs only
# 2.5 x 10^-4 * 628 = 0.13 N m, well inside the motor's torque at that speed.
DEMO_MECHANICS = Mechanics(
    inertia_kg_m2=2.0e-4, friction_nm=0.05, viscous_nm_s_per_rad=1.0e-4, counts_per_rev=4096
)


@dataclass(slots=True)
class StepperPlant:
    """A stepper on its load: while the output stage is on, the shaft follows the
    engine's setpoint exactly, every cycle (no step loss); when it is off, the shaft
    coasts under ``mechanics`` (None: an ideal massless shaft that stops dead - only for
    tests that want the positioning logic alone).

    Two frames: ``shaft_counts`` is the machine's fixed frame, where the cam and the
    C-track marks are; the counter (what the drive reports) reads
    ``shaft + counter_shift + encoder_offset``. ``counter_shift_counts`` changes when
    the counter is set (calibration, ENC "Set counter"). ``encoder_offset_counts``
    models what a real drive cannot pull in - lost steps, a slipped encoder: the actual
    position stays that far from the setpoint, which is how a test makes In-Target fail.

    ``cam_counts`` is the shaft interval [low, high] on which the cam (digital input 1)
    is on; ``sync_period_counts`` > 0 puts a C-track pulse at ``sync_phase_counts`` plus
    every whole period.

    ``encoder``: the counter is an encoder on the shaft (True), which counts whatever
    moves the shaft, powered or not; or the drive's internal step counter (False),
    which counts only the steps it makes - a coast is then lost to it (the shaft moves,
    the counter stands), as on a real drive without an encoder.
    """

    shaft_counts: float = 0.0
    encoder_offset_counts: float = 0.0
    cam_counts: tuple[float, float] | None = None
    sync_period_counts: float = 0.0
    sync_phase_counts: float = 0.0
    counter_shift_counts: float = 0.0
    mechanics: Mechanics | None = None
    encoder: bool = True
    speed_counts_s: float = 0.0  # the shaft's, signed (set by follow's caller, or coast)

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

    def coast(self, dt_s: float) -> float | None:
        """The output stage is off: the shaft coasts ``dt_s`` from ``speed_counts_s``
        under :attr:`mechanics` (no mechanics: it stops dead). Returns the counter
        value at the first C-track pulse passed, or None (as :meth:`follow`)."""
        if self.speed_counts_s == 0.0:
            return None
        if self.mechanics is None:
            self.speed_counts_s = 0.0
            return None
        distance, self.speed_counts_s = self.mechanics.coast(self.speed_counts_s, dt_s)
        old = self.shaft_counts
        self.shaft_counts = old + distance
        if not self.encoder:
            self.counter_shift_counts -= distance  # the step counter does not see it
        pulse = self._first_pulse(old, self.shaft_counts)
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
