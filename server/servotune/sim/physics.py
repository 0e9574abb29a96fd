"""A brushed DC motor with encoder, index track and limit switches (sans-IO plant model).

Used by the SLAP2 simulator (one motor per module) and meant for the Z1100 simulator
(one per axis). The model, per integration step ``h`` (the caller's step is split into
steps of at most ``max_step_s``):

* Electrical: ``L di/dt = V - R i - ke w``. With the speed ``w`` held over the step the
  RL circuit is solved exactly: ``i(h) = i_ss + (i0 - i_ss) exp(-h R / L)`` with
  ``i_ss = (V - ke w) / R``. The exact solution matters: the electrical time constant
  (~80 us) is far shorter than a controller tick (841.5 us), so explicit Euler would
  blow up. The torque uses the *mean* current over the step, also exact.
* Driver: ``V = duty * supply`` with ``duty`` saturated to -1..1 (PWM cannot exceed
  the supply). With a current limit the driver chops: when the current at the end of
  the step would exceed the limit the applied voltage is lowered (down to -supply) so
  the current lands exactly on the limit, and the step reports "limited". ``duty`` of
  ``None`` means the bridge is off (open circuit): the current is zero.
* Mechanical: ``J dw/dt = kt i_mean + T_ext - b w - Tc sgn(w)`` with rotor plus load
  inertia, viscous friction ``b`` and Coulomb friction ``Tc``. Stiction: a shaft at rest
  stays at rest while the driving torque does not exceed ``Tc``; a speed that would
  change sign within a step is clamped to zero (the shaft sticks for that step and may
  break away in the next), so Coulomb friction never makes the shaft oscillate.
* Encoder: ``count = floor(angle * 4 * lines / 2 pi)`` (quadrature: 4 counts per line).
  The index track is one count wide and sits at ``index_count`` (mod counts/rev); a
  step reports the last index count the encoder passed through. Limit switches are
  actuated at or beyond their count positions (E1 at the negative end, E2 positive).

All counts here are *physical*: 0 is the shaft angle 0. A controller that keeps its own
position counter (set to 0 at power-on, changed by ``sp``) maps between the two.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

TWO_PI = 2.0 * math.pi


@dataclass(frozen=True, slots=True)
class DcMotorParams:
    """Plant parameters. Defaults: an unloaded Faulhaber 2224 U 024 SR at 24 V.

    Numbers follow the Faulhaber 2224 SR datasheet for the 24 V winding (see
    docs/simulator.md): terminal resistance 19.8 ohm, inductance 590 uH, torque
    constant 29 mNm/A (so back-EMF 29 mV s/rad, no-load speed ~7800 rpm at 24 V),
    rotor inertia 3.8 g cm^2, friction torque 0.2 mNm. The SLAP2 manual requires at
    least 1 mH in the motor circuit, so a 1 mH series choke is included by default.
    The encoder has 512 lines (2048 counts/rev) as in the manual's tuning example.
    """

    resistance_ohm: float = 19.8
    motor_inductance_h: float = 0.59e-3
    # The SLAP2 manual demands >= 1 mH total; the 2224 alone has 0.59 mH.
    choke_inductance_h: float = 1.0e-3
    torque_constant_nm_per_a: float = 29.0e-3  # equals the back-EMF constant in V s/rad
    rotor_inertia_kg_m2: float = 3.8e-7  # 3.8 g cm^2
    load_inertia_kg_m2: float = 0.0
    coulomb_friction_nm: float = 0.2e-3
    # ~0.012 mNm at no-load speed: small against the Coulomb part, as for this motor.
    viscous_friction_nm_s_per_rad: float = 1.5e-8
    supply_v: float = 24.0
    encoder_lines: int = 512
    # Physical count of the index pulse (mod counts/rev). Not 0, so that the shaft
    # does not start exactly on the index.
    index_count: int = 300
    limit1_count: int | None = -20000  # E1: actuated at counts <= this (negative end)
    limit2_count: int | None = 20000  # E2: actuated at counts >= this (positive end)

    def __post_init__(self) -> None:
        if self.resistance_ohm <= 0 or self.inductance_h <= 0:
            raise ValueError("resistance and inductance must be positive")
        if self.torque_constant_nm_per_a <= 0 or self.inertia_kg_m2 <= 0:
            raise ValueError("torque constant and inertia must be positive")
        if self.coulomb_friction_nm < 0 or self.viscous_friction_nm_s_per_rad < 0:
            raise ValueError("friction cannot be negative")
        if self.supply_v <= 0 or self.encoder_lines <= 0:
            raise ValueError("supply voltage and encoder lines must be positive")
        if (
            self.limit1_count is not None
            and self.limit2_count is not None
            and self.limit1_count >= self.limit2_count
        ):
            raise ValueError("limit switch E1 must lie below E2")

    @property
    def inductance_h(self) -> float:
        """Total inductance of the motor circuit (motor plus series choke)."""
        return self.motor_inductance_h + self.choke_inductance_h

    @property
    def inertia_kg_m2(self) -> float:
        """Total inertia seen by the shaft (rotor plus load)."""
        return self.rotor_inertia_kg_m2 + self.load_inertia_kg_m2

    @property
    def counts_per_rev(self) -> int:
        """Quadrature counts per revolution: 4 x lines."""
        return 4 * self.encoder_lines

    @property
    def no_load_speed_rad_s(self) -> float:
        """Steady speed at full supply with friction only (what a datasheet lists)."""
        kt = self.torque_constant_nm_per_a
        b = self.viscous_friction_nm_s_per_rad
        r = self.resistance_ohm
        # kt (V - kt w) / R = Tc + b w  ->  w = (kt V / R - Tc) / (kt^2 / R + b)
        return (kt * self.supply_v / r - self.coulomb_friction_nm) / (kt * kt / r + b)

    @property
    def stall_current_a(self) -> float:
        return self.supply_v / self.resistance_ohm


class DcMotor:
    """State and integration of one motor; see the module docstring for the model.

    Attributes after each ``step``: ``current_a``, ``speed_rad_s``, ``angle_rad``,
    ``count`` (encoder count), ``index_crossed`` (the last index count the encoder
    passed through during the step, or ``None``) and ``current_limited`` (the driver
    chopped during the step). ``external_torque_nm`` is a load torque the caller may
    set (positive drives towards positive counts).
    """

    __slots__ = (
        "_counts_per_rad",
        "_cpr",
        "_decay_cache",
        "_max_step_s",
        "angle_rad",
        "count",
        "current_a",
        "current_limited",
        "external_torque_nm",
        "index_crossed",
        "params",
        "speed_rad_s",
    )

    def __init__(
        self,
        params: DcMotorParams | None = None,
        *,
        angle_rad: float = 0.0,
        max_step_s: float = 250e-6,
    ) -> None:
        if max_step_s <= 0:
            raise ValueError("max_step_s must be positive")
        self.params = params if params is not None else DcMotorParams()
        self._max_step_s = max_step_s
        self._cpr = self.params.counts_per_rev
        self._counts_per_rad = self._cpr / TWO_PI
        # Per step length: (substeps, h, exp(-h R/L), mean factor). Callers use one or
        # two step lengths, so the exponentials are computed once.
        self._decay_cache: dict[float, tuple[int, float, float, float]] = {}
        self.current_a = 0.0
        self.speed_rad_s = 0.0
        self.angle_rad = angle_rad
        self.external_torque_nm = 0.0
        self.count = math.floor(angle_rad * self._counts_per_rad)
        self.index_crossed: int | None = None
        self.current_limited = False

    # --- sensors -----------------------------------------------------------------------

    @property
    def limit1_actuated(self) -> bool:
        """E1 (negative end) is pressed: the count is at or below its position."""
        position = self.params.limit1_count
        return position is not None and self.count <= position

    @property
    def limit2_actuated(self) -> bool:
        """E2 (positive end) is pressed: the count is at or above its position."""
        position = self.params.limit2_count
        return position is not None and self.count >= position

    def set_count(self, count: int) -> None:
        """Put the shaft at rest in the middle of encoder count ``count`` (test setup)."""
        self.angle_rad = (count + 0.5) / self._counts_per_rad
        self.count = count
        self.speed_rad_s = 0.0
        self.current_a = 0.0

    # --- integration -------------------------------------------------------------------

    def _factors(self, dt_s: float) -> tuple[int, float, float, float]:
        factors = self._decay_cache.get(dt_s)
        if factors is None:
            n = max(1, math.ceil(dt_s / self._max_step_s - 1e-9))
            h = dt_s / n
            tau_s = self.params.inductance_h / self.params.resistance_ohm
            decay = math.exp(-h / tau_s)
            # mean of exp(-t/tau) over [0, h], as a fraction of the initial value
            mean = (1.0 - decay) * tau_s / h
            factors = (n, h, decay, mean)
            if len(self._decay_cache) < 16:
                self._decay_cache[dt_s] = factors
        return factors

    def step(self, dt_s: float, duty: float | None, current_limit_a: float | None = None) -> bool:
        """Advance ``dt_s`` seconds with the bridge at ``duty`` (-1..1, saturated).

        ``duty=None`` opens the bridge (no current). ``current_limit_a`` (>= 0) makes
        the driver chop at that current. Returns ``current_limited``.
        """
        n, h, decay, mean = self._factors(dt_s)
        p = self.params
        r = p.resistance_ohm
        kt = p.torque_constant_nm_per_a
        tc = p.coulomb_friction_nm
        b = p.viscous_friction_nm_s_per_rad
        h_over_j = h / p.inertia_kg_m2
        supply = p.supply_v
        cpr_rad = self._counts_per_rad
        ext = self.external_torque_nm
        i = self.current_a
        w = self.speed_rad_s
        angle = self.angle_rad
        count = self.count
        limited = False
        crossed: int | None = None
        if duty is not None:
            duty = 1.0 if duty > 1.0 else -1.0 if duty < -1.0 else duty
            v_cmd = duty * supply
        else:
            v_cmd = 0.0
        for _ in range(n):
            if duty is None:
                i = 0.0
                i_mean = 0.0
            else:
                emf = kt * w
                i_ss = (v_cmd - emf) / r
                i_end = i_ss + (i - i_ss) * decay
                if current_limit_a is not None and abs(i_end) > current_limit_a:
                    # Chopping: find the voltage that ends the step on the limit.
                    target = math.copysign(current_limit_a, i_end)
                    v = r * (target - i * decay) / (1.0 - decay) + emf
                    v = supply if v > supply else -supply if v < -supply else v
                    i_ss = (v - emf) / r
                    i_end = i_ss + (i - i_ss) * decay
                    limited = True
                i_mean = i_ss + (i - i_ss) * mean
                i = i_end
            drive = kt * i_mean + ext
            if w == 0.0:
                if -tc <= drive <= tc:
                    continue  # stiction holds: the shaft stays where it is
                net = drive - math.copysign(tc, drive)
                w_new = h_over_j * net
            else:
                net = drive - b * w - math.copysign(tc, w)
                w_new = w + h_over_j * net
                if (w_new > 0.0) != (w > 0.0):
                    w_new = 0.0  # the speed crosses zero: friction stops the shaft here
            angle += 0.5 * (w + w_new) * h
            w = w_new
            new_count = math.floor(angle * cpr_rad)
            if new_count != count:
                crossed = self._index_between(count, new_count, crossed)
                count = new_count
        self.current_a = i
        self.speed_rad_s = w
        self.angle_rad = angle
        self.count = count
        self.index_crossed = crossed
        self.current_limited = limited
        return limited

    def _index_between(self, old: int, new: int, previous: int | None) -> int | None:
        """The last index count visited moving from ``old`` to ``new`` (exclusive of old)."""
        cpr = self._cpr
        index = self.params.index_count
        if new > old:
            # largest k*cpr + index <= new; visited if > old
            candidate = new - (new - index) % cpr
            return candidate if candidate > old else previous
        # moving down: smallest k*cpr + index >= new; visited if < old
        candidate = new + (index - new) % cpr
        return candidate if candidate < old else previous
