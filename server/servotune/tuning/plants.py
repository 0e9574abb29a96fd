"""Plant models the identification fits and every prediction runs on.

Two nonlinear device-unit models (what the auto-tune fits, with what the linear view
leaves out) and their common linear form (what margins, Bode plots and the what-if
view use):

* ``PlantModel`` (SLAP2, open-loop fit): PWM -> velocity first order with Coulomb
  friction and stiction, ``tau dv/dt = gain (u - uc sgn v) - v``, counts/s per PWM.
* ``Z1100Plant`` (Z1100, closed-loop fit): ``tau dv/dt = gain duty - v``, counts/s
  per unit duty (no friction term: docs/autotune.md, Z1100).
* ``IdentifiedPlant``: ``P(s) = g / (s (tau s + 1))`` in counts per controller output
  unit (PWM, full scale 255).

``FrictionMotor`` integrates ``PlantModel`` exactly over intervals of constant PWM
(the piecewise-exponential solution, including the stop at zero speed), so neither a
fit nor a tick simulation depends on a step size. Pure: no I/O, no clocks.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import control

# The controller output's full scale, in the units every model here takes (PWM: the
# SLAP2 and the Z1100 drive -255..255).
OUTPUT_FULL_SCALE: Final = 255


@dataclass(frozen=True, slots=True)
class PlantModel:
    """PWM -> velocity first order with Coulomb friction; position integrates velocity.

    ``tau dv/dt = gain * (u - friction_pwm * sgn(v)) - v``; at rest the shaft stays at
    rest while ``|u| <= friction_pwm`` (stiction), and a velocity that would change sign
    stops at zero. ``gain`` is counts/s per PWM unit, ``friction_pwm`` the PWM that just
    overcomes friction, ``tau_s`` the mechanical time constant.
    """

    gain: float
    tau_s: float
    friction_pwm: float
    rms_error_counts: float = 0.0
    samples: int = 0
    delay_s: float = 0.0  # fit only: when the PWM steps took effect, after their timestamps

    def __post_init__(self) -> None:
        if not (self.gain > 0 and self.tau_s > 0 and self.friction_pwm >= 0):
            raise ValueError(f"implausible plant model {self!r}")

    def scaled(self, gain_factor: float, tau_factor: float) -> PlantModel:
        return PlantModel(self.gain * gain_factor, self.tau_s * tau_factor, self.friction_pwm)

    def to_dict(self) -> dict[str, float | int]:
        return {
            "gain_counts_s_per_pwm": round(self.gain, 3),
            "tau_s": round(self.tau_s, 5),
            "friction_pwm": round(self.friction_pwm, 3),
            "rms_error_counts": round(self.rms_error_counts, 2),
            "samples": self.samples,
            "delay_s": round(self.delay_s, 5),
        }


@dataclass(frozen=True, slots=True)
class Z1100Plant:
    """``tau dv/dt = gain * duty - v``: velocity in counts/s, duty -1..1."""

    gain: float
    tau_s: float
    rms_error_counts: float = 0.0
    samples: int = 0
    delay_s: float = 0.0

    def scaled(self, gain_factor: float, tau_factor: float) -> Z1100Plant:
        return Z1100Plant(self.gain * gain_factor, self.tau_s * tau_factor)

    def to_dict(self) -> dict[str, float | int]:
        return {
            "gain_counts_s_per_duty": round(self.gain, 1),
            "tau_s": round(self.tau_s, 5),
            "rms_error_counts": round(self.rms_error_counts, 2),
            "samples": self.samples,
            "delay_s": round(self.delay_s, 5),
        }


@dataclass(frozen=True, slots=True)
class IdentifiedPlant:
    """First-order velocity plant: counts/s per controller output unit, time constant."""

    gain_counts_s_per_unit: float
    tau_s: float
    source: str  # where the numbers come from, shown to the user

    def transfer_function(self) -> control.TransferFunction:
        """``g / (s (tau s + 1))``: counts per controller output unit."""
        return control.tf([self.gain_counts_s_per_unit], [self.tau_s, 1.0, 0.0])


class FrictionMotor:
    """Exact integration of ``PlantModel`` over intervals with a constant PWM.

    ``tick_s`` is the step ``tick`` advances by: the controller period of the loop it
    runs in, the device's fact, given by the caller; None for a motor only ``advance``d
    by given intervals (its ``tick`` raises AttributeError). ``advance`` takes any
    interval.
    """

    __slots__ = ("_tick_decay", "_tick_lag", "_tick_s", "gain", "tau", "uc", "v", "x")

    def __init__(self, model: PlantModel, x: float = 0.0, *, tick_s: float | None) -> None:
        self.gain = model.gain
        self.tau = model.tau_s
        self.uc = model.friction_pwm
        self.x = x
        self.v = 0.0
        if tick_s is not None:  # left unset otherwise: ``tick`` cannot run by mistake
            self._tick_s = tick_s
            self._tick_decay = -math.expm1(-tick_s / self.tau)
            self._tick_lag = self.tau * self._tick_decay

    def tick(self, u: float) -> None:
        """``advance(u, tick_s)``, with the common case (moving on, no stop) inlined:
        this runs hundreds of thousands of times per gain search."""
        v = self.v
        if v > 0.0:
            v_inf = self.gain * (u - self.uc)
            if v_inf >= 0.0:
                self.x += v_inf * self._tick_s + (v - v_inf) * self._tick_lag
                self.v = v + (v_inf - v) * self._tick_decay
                return
        elif v < 0.0:
            v_inf = self.gain * (u + self.uc)
            if v_inf <= 0.0:
                self.x += v_inf * self._tick_s + (v - v_inf) * self._tick_lag
                self.v = v + (v_inf - v) * self._tick_decay
                return
        self.advance(u, self._tick_s)

    def advance(self, u: float, dt: float) -> None:
        v = self.v
        if v == 0.0:
            if -self.uc <= u <= self.uc or dt <= 0.0:
                return  # stiction
            direction = 1.0 if u > 0 else -1.0
        else:
            direction = 1.0 if v > 0 else -1.0
        v_inf = self.gain * (u - self.uc * direction)
        tau = self.tau
        if v != 0.0 and v_inf * direction < 0.0:
            # decelerating towards the other direction: the speed reaches zero at tz
            tz = tau * math.log((v - v_inf) / -v_inf)
            if tz < dt:
                self.x += v_inf * tz + (v - v_inf) * tau * -math.expm1(-tz / tau)
                self.v = 0.0
                self.advance(u, dt - tz)  # stuck, or breaks away the other way
                return
        decay = -math.expm1(-dt / tau)
        self.x += v_inf * dt + (v - v_inf) * tau * decay
        self.v = v + (v_inf - v) * decay


def model_positions(
    model: PlantModel,
    schedule: Sequence[tuple[float, float]],
    times: Sequence[float],
    *,
    x0: float = 0.0,
) -> list[float]:
    """Model positions at ``times`` (sorted) for a PWM ``schedule`` of (time, pwm) steps.

    Before the first step the PWM is 0 and the shaft at rest at ``x0``.
    """
    motor = FrictionMotor(model, x0, tick_s=None)
    events = sorted(schedule)
    out: list[float] = []
    now = min(events[0][0], times[0]) if events and times else 0.0
    u = 0.0
    k = 0
    for t in times:
        while k < len(events) and events[k][0] <= t:
            motor.advance(u, events[k][0] - now)
            now = max(now, events[k][0])
            u = events[k][1]
            k += 1
        motor.advance(u, t - now)
        now = max(now, t)
        out.append(motor.x)
    return out
