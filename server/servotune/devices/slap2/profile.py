"""The SLAP2 firmware's trapezoid profile law, as a pure function of what was commanded.

Pure (no I/O, no clock; only the codec's constants imported), so both the driver
(which reconstructs the setpoint of a captured axis from the ``ma``/``mr`` it sent and
the ``sv``/``sa`` in force) and the simulator may use it without breaking the layering.
The law is the one ``devices/slap2/sim/controller.py`` implements tick by tick (``_move_tick`` and
``_ramp``); tests/device/slap2/test_capture.py checks this copy against the simulator's
firmware on the same commands, tick for tick, so the two cannot drift apart silently.

Law, per 841.5 us controller tick, in counts and counts/tick (``TICK_S``):

* ``d`` = target - setpoint; the highest speed from which decelerating by ``a`` per
  tick still stops at the target is ``sqrt(a^2/4 + 2 a |d|) - a/2`` (the discrete form
  of ``v^2 / 2a``), capped by ``vmax`` and by ``|d|`` itself;
* the generator velocity ramps towards that speed (signed towards the target) by at
  most ``a`` per tick, and the setpoint advances by the new velocity;
* the move ends when the setpoint is (within 1e-6) at the target and the velocity is
  at most ``a``: the setpoint is then exactly the target and the velocity 0.

A move commanded while another runs replans from the generator's current setpoint
and velocity (no jump), which ``TrapezoidGenerator.replan`` reproduces. Limit
switches abort a move in the firmware; the reconstruction does not model them (the
driver's check against the measured ``pe`` notices it and stops trusting the profile).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

# The manual's facts, one home (the codec); re-exported for the profile's users.
from servotune.devices.slap2.codec import COUNTS_S2_PER_SA as COUNTS_S2_PER_SA
from servotune.devices.slap2.codec import COUNTS_S_PER_SV as COUNTS_S_PER_SV
from servotune.devices.slap2.codec import TICK_S as TICK_S

COUNTS_TICK_PER_SV = COUNTS_S_PER_SV * TICK_S
COUNTS_TICK2_PER_SA = COUNTS_S2_PER_SA * TICK_S * TICK_S


def ramp(velocity: float, target_velocity: float, acceleration: float) -> float:
    """The generator velocity after one tick: towards ``target_velocity`` by at most
    ``acceleration`` (counts/tick^2)."""
    if velocity < target_velocity:
        return min(velocity + acceleration, target_velocity)
    return max(velocity - acceleration, target_velocity)


def move_tick(
    setpoint: float, velocity: float, target: float, vmax: float, acceleration: float
) -> tuple[float, float, bool]:
    """One tick of a running move: ``(setpoint, velocity, still_moving)`` after it.

    ``vmax`` in counts/tick, ``acceleration`` in counts/tick^2, both > 0.
    """
    d = target - setpoint
    distance = -d if d < 0 else d
    allowed = math.sqrt(0.25 * acceleration * acceleration + 2.0 * acceleration * distance)
    allowed -= 0.5 * acceleration
    if allowed > vmax:
        allowed = vmax
    if allowed > distance:
        allowed = distance
    nv = ramp(velocity, -allowed if d < 0 else allowed, acceleration)
    setpoint += nv
    rest = target - setpoint
    if -1e-6 < rest < 1e-6 and -acceleration <= nv <= acceleration:
        return float(target), 0.0, False
    return setpoint, nv, True


@dataclass(slots=True)
class TrapezoidGenerator:
    """The firmware's profile generator as a small state machine (see module doc)."""

    setpoint: float
    target: float
    vmax: float
    acceleration: float
    velocity: float = 0.0
    moving: bool = True

    @classmethod
    def from_wire(
        cls, setpoint: float, target: float, sv: int, sa: int, velocity: float = 0.0
    ) -> TrapezoidGenerator:
        """A move to ``target`` with ``sv``/``sa`` in wire units (the sign of sv is
        the vm direction; a move uses its magnitude). Raises ValueError for sv or sa 0
        (the firmware refuses such a move)."""
        if sv == 0 or sa == 0:
            raise ValueError("a move needs sv and sa other than 0")
        return cls(
            setpoint=float(setpoint),
            target=float(target),
            vmax=abs(sv) * COUNTS_TICK_PER_SV,
            acceleration=sa * COUNTS_TICK2_PER_SA,
            velocity=velocity,
            moving=float(setpoint) != float(target) or velocity != 0.0,
        )

    def step(self) -> float:
        """Run one tick; returns the setpoint after it."""
        if self.moving:
            self.setpoint, self.velocity, self.moving = move_tick(
                self.setpoint, self.velocity, self.target, self.vmax, self.acceleration
            )
        return self.setpoint

    def replan(self, target: float, sv: int, sa: int) -> None:
        """A new move commanded while this one runs: same setpoint and velocity."""
        if sv == 0 or sa == 0:
            raise ValueError("a move needs sv and sa other than 0")
        self.target = float(target)
        self.vmax = abs(sv) * COUNTS_TICK_PER_SV
        self.acceleration = sa * COUNTS_TICK2_PER_SA
        self.moving = True


def firmware_setpoint(setpoint: float) -> int:
    """The integer setpoint the firmware compares with the counter (``pe`` uses it)."""
    return math.floor(setpoint + 0.5)


class ProfileTrack:
    """A reconstructed profile on the host's clock: the setpoint at any time after the
    command took effect.

    ``t_command_s`` is the best estimate of when the module executed the command
    (it acts on the CR); the first tick after it is the first step of the move. The
    tick phase is unknown to the host: evaluation assumes the ticks fall half a tick
    after the command on average, an error of at most half a tick (0.42 ms).
    Ticks are generated lazily as later times are asked for, so a long move costs
    only the ticks actually looked at.
    """

    def __init__(self, t_command_s: float, generator: TrapezoidGenerator) -> None:
        self.t_command_s = t_command_s
        self._generator = generator
        self._setpoints: list[float] = [generator.setpoint]
        self.done_tick: int | None = None if generator.moving else 0
        self.moved = generator.moving  # a move, not a held position

    @property
    def target(self) -> float:
        return self._generator.target

    def _tick(self, index: int) -> float:
        while len(self._setpoints) <= index:
            if self.done_tick is not None:
                return self._setpoints[-1]
            self._setpoints.append(self._generator.step())
            if not self._generator.moving:
                self.done_tick = len(self._setpoints) - 1
        return self._setpoints[index]

    def setpoint_at(self, t_s: float) -> float:
        """The setpoint at host time ``t_s`` (before the command: the start value)."""
        x = (t_s - self.t_command_s) / TICK_S - 0.5
        if x <= 0:
            return self._setpoints[0]
        i = int(x)
        a = self._tick(i)
        b = self._tick(i + 1)
        return a + (b - a) * (x - i)

    def state_at(self, t_s: float) -> TrapezoidGenerator:
        """The generator's state at ``t_s`` (to replan a move commanded then)."""
        x = max(0.0, (t_s - self.t_command_s) / TICK_S - 0.5)
        i = int(x)
        sp = self._tick(i)
        v = self._tick(i) - self._tick(i - 1) if i > 0 else 0.0
        g = self._generator
        moving = self.done_tick is None or i < self.done_tick
        return TrapezoidGenerator(
            sp, g.target, g.vmax, g.acceleration, v if moving else 0.0, moving
        )

    def finished_by(self, t_s: float) -> bool:
        """The move has ended (setpoint at the target) by host time ``t_s``."""
        x = (t_s - self.t_command_s) / TICK_S - 0.5
        self._tick(max(0, int(x)) + 1)
        return self.done_tick is not None and x >= self.done_tick
