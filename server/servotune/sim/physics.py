"""A brushed DC motor with encoder, index track and limit switches (sans-IO plant model).

Used by the SLAP2 simulator (one motor per module) and the Z1100 simulator (one per
axis). The model, per integration step ``h`` (the caller's step, split into steps of
at most ``max_step_s``, 1 ms by default, so a SLAP2 tick is one step):

* Electrical: ``L di/dt = V - R i - ke w``; mechanical:
  ``J dw/dt = kt i + T_ext - b w - Tc sgn(w)`` with rotor plus load inertia, viscous
  friction ``b`` and Coulomb friction ``Tc``; the angle integrates ``w``. With the
  voltage and the friction's sign held over the step the system is linear, and it is
  solved *exactly* by its zero-order-hold discretisation (the matrix exponential of
  the augmented system matrix, ``scipy.linalg.expm``, computed once per step length):
  no integration error, whatever the ratio of ``h`` to the electrical time constant
  (~80 us, far shorter than a controller tick of 841.5 us, where explicit Euler would
  blow up) or the mechanical one. One step per tick is what makes the plant fast
  (docs/simulator.md has the speed).
* Driver: ``V = duty * supply`` with ``duty`` saturated to -1..1 (PWM cannot exceed
  the supply). With a current limit the driver chops: when the current at the end of
  the step would exceed the limit the applied voltage is lowered (down to -supply) so
  the current lands exactly on the limit, and the step reports "limited". ``duty`` of
  ``None`` means the bridge is off (open circuit): the current is zero.
* Stiction: a shaft at rest stays at rest while the driving torque (from the mean
  current of the step, the RL circuit solved exactly with no back-EMF) does not exceed
  ``Tc``; a speed that would change sign within a step is clamped to zero (the shaft
  sticks for that step and may break away in the next), so Coulomb friction never
  makes the shaft oscillate. This decision is taken once per step, so a break-away
  or a stop is resolved to one step (one tick) - the only approximation left.
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
# Longest step over which the friction (its sign, stiction) is decided once. The linear
# part is exact over any step; 1 ms covers the SLAP2 tick (841.5 us) in one step.
MAX_STEP_S = 1e-3
# While the driver chops, the current limit is enforced at least this often (a peak
# inside a longer step would otherwise pass unseen).
CHOP_STEP_S = 250e-6


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
        max_step_s: float = MAX_STEP_S,
    ) -> None:
        if max_step_s <= 0:
            raise ValueError("max_step_s must be positive")
        self.params = params if params is not None else DcMotorParams()
        self._max_step_s = max_step_s
        self._cpr = self.params.counts_per_rev
        self._counts_per_rad = self._cpr / TWO_PI
        # Per step length: the exact discretisation. Callers use one or two step
        # lengths, so the matrix exponentials are computed once.
        self._decay_cache: dict[float, _Discrete] = {}
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

    def prepare(self, dt_s: float) -> None:
        """Discretise for steps of ``dt_s`` now (cached), so that the first such step
        does not pay for it - nor for importing scipy, which takes a second or more on
        a busy host. Simulators call this before they go on the line."""
        self._factors(dt_s)

    def _factors(self, dt_s: float) -> _Discrete:
        factors = self._decay_cache.get(dt_s)
        if factors is None:
            factors = _discretise(self.params, dt_s, self._max_step_s)
            if len(self._decay_cache) < 16:
                self._decay_cache[dt_s] = factors
        return factors

    def step(self, dt_s: float, duty: float | None, current_limit_a: float | None = None) -> bool:
        """Advance ``dt_s`` seconds with the bridge at ``duty`` (-1..1, saturated).

        ``duty=None`` opens the bridge (no current). ``current_limit_a`` (>= 0) makes
        the driver chop at that current. Returns ``current_limited``.
        """
        f = self._decay_cache.get(dt_s) or self._factors(dt_s)
        if duty is not None:
            duty = 1.0 if duty > 1.0 else -1.0 if duty < -1.0 else duty
            v_cmd: float | None = duty * self.params.supply_v
        else:
            v_cmd = None
        cpr_rad = self._counts_per_rad
        if f.n == 1 and current_limit_a is None:
            # The common case of the servo-loop simulators (one piece, no chopper): the
            # loop below without its bookkeeping, the same arithmetic.
            limited = self._advance(f, v_cmd, None)
            count = self.count
            new_count = math.floor(self.angle_rad * cpr_rad)
            self.index_crossed = (
                self._index_between(count, new_count, None) if new_count != count else None
            )
            self.count = new_count
            self.current_limited = limited
            return limited
        kt = self.params.torque_constant_nm_per_a
        r = self.params.resistance_ohm
        count = self.count
        crossed: int | None = None
        limited = False
        for _ in range(f.n):
            fine = f.fine
            if (
                fine is not None
                and current_limit_a is not None
                and v_cmd is not None
                # cheap bound first: |i| never exceeds max(|i0|, |v - ke w| / R)
                and max(abs(self.current_a), abs(v_cmd - kt * self.speed_rad_s) / r)
                > current_limit_a
                and self._peaks_over(f, v_cmd, current_limit_a)
            ):
                # The current would pass the limit inside the step and fall below it by
                # its end (it rises with ~80 us, the back-EMF then lowers it): a real
                # chopper acts at that instant, so the step is taken in short pieces.
                pieces = fine.n
                factors = fine
            else:
                pieces = 1
                factors = f
            for _ in range(pieces):
                limited = self._advance(factors, v_cmd, current_limit_a) or limited
                new_count = math.floor(self.angle_rad * cpr_rad)
                if new_count != count:
                    crossed = self._index_between(count, new_count, crossed)
                    count = new_count
        self.count = count
        self.index_crossed = crossed
        self.current_limited = limited
        return limited

    def _peaks_over(self, f: _Discrete, v: float | None, limit_a: float) -> bool:
        """Whether the current half-way through the step exceeds ``limit_a``."""
        w = self.speed_rad_s
        if v is None or w == 0.0:
            return False  # no current, or the RL circuit alone: monotonic, its end is its peak
        tc = self.params.coulomb_friction_nm
        torque = self.external_torque_nm - (tc if w > 0.0 else -tc)
        i_mid = f.half_ii * self.current_a + f.half_iw * w + f.half_iv * v + f.half_it * torque
        return abs(i_mid) > limit_a

    def _advance(self, f: _Discrete, v_cmd: float | None, current_limit_a: float | None) -> bool:
        """One step of ``f.h`` (see the module docstring); returns whether it chopped."""
        p = self.params
        tc = p.coulomb_friction_nm
        ext = self.external_torque_nm
        i = self.current_a
        w = self.speed_rad_s
        limited = False
        # Friction acts against the motion, or at rest against the driving torque.
        if v_cmd is None:
            self.current_a = 0.0
            if w == 0.0:
                if -tc <= ext <= tc:
                    return False  # stiction holds: the shaft stays where it is
                direction = 1.0 if ext > 0.0 else -1.0
            else:
                direction = 1.0 if w > 0.0 else -1.0
            torque = ext - direction * tc
            w_new = f.off_ww * w + f.off_wt * torque
            d_angle = f.off_aw * w + f.off_at * torque
        else:
            v = v_cmd
            supply = p.supply_v
            if w == 0.0:
                # At rest the back-EMF is 0: the RL circuit alone, solved exactly.
                r = p.resistance_ohm
                decay = f.decay
                i_ss = v / r
                i_end = i_ss + (i - i_ss) * decay
                if current_limit_a is not None and abs(i_end) > current_limit_a:
                    target = math.copysign(current_limit_a, i_end)
                    v = r * (target - i * decay) / (1.0 - decay)
                    v = supply if v > supply else -supply if v < -supply else v
                    i_ss = v / r
                    i_end = i_ss + (i - i_ss) * decay
                    limited = True
                drive = p.torque_constant_nm_per_a * (i_ss + (i - i_ss) * f.mean) + ext
                if -tc <= drive <= tc:
                    self.current_a = i_end
                    return limited  # stiction holds against the mean torque of the step
                direction = 1.0 if drive > 0.0 else -1.0
            else:
                direction = 1.0 if w > 0.0 else -1.0
            torque = ext - direction * tc
            free = f.on_ii * i + f.on_iw * w + f.on_it * torque
            i_end = free + f.on_iv * v
            if current_limit_a is not None and abs(i_end) > current_limit_a:
                # Chopping: the voltage that ends the step on the limit (linear in v).
                target = math.copysign(current_limit_a, i_end)
                v = (target - free) / f.on_iv
                v = supply if v > supply else -supply if v < -supply else v
                i_end = free + f.on_iv * v
                limited = True
            w_new = f.on_wi * i + f.on_ww * w + f.on_wv * v + f.on_wt * torque
            d_angle = f.on_ai * i + f.on_aw * w + f.on_av * v + f.on_at * torque
            self.current_a = i_end
        if tc > 0.0 and w_new != 0.0 and (w_new > 0.0) != (direction > 0.0):
            # The speed would cross zero within the step: friction stops the shaft
            # here (it sticks for the rest of the step and may break away in the
            # next). The angle keeps the exact travel up to about that turn. Without
            # friction nothing stops it: the motor is then the linear plant of
            # tuning.loops (a reversal within a tick - a loop oscillating near its
            # Nyquist frequency - is not damped here; tests/unit/tuning/test_stability.py).
            w_new = 0.0
        self.angle_rad += d_angle
        self.speed_rad_s = w_new
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


@dataclass(frozen=True, slots=True)
class _Discrete:
    """The linear part of the model over one step ``h``, exact for inputs held constant.

    Bridge on, state (i, w) and the angle travelled, inputs v (terminal voltage) and
    the constant torque ``T = T_ext - Tc sgn`` (friction with the sign of the motion):
    ``i' = on_ii i + on_iw w + on_iv v + on_it T`` and so on. Bridge open (i = 0): the
    ``off_*`` terms. At rest (back-EMF 0) the RL circuit alone: ``decay`` and ``mean``
    (the mean current over the step as a fraction, for the stiction test).
    """

    n: int
    h: float
    decay: float
    mean: float
    on_ii: float
    on_iw: float
    on_iv: float
    on_it: float
    on_wi: float
    on_ww: float
    on_wv: float
    on_wt: float
    on_ai: float
    on_aw: float
    on_av: float
    on_at: float
    off_ww: float
    off_wt: float
    off_aw: float
    off_at: float
    half_ii: float  # the current after h/2 (bridge on), to find a peak inside the step
    half_iw: float
    half_iv: float
    half_it: float
    fine: _Discrete | None  # pieces of at most CHOP_STEP_S, used while chopping


def _discretise(params: DcMotorParams, dt_s: float, max_step_s: float) -> _Discrete:
    n = max(1, math.ceil(dt_s / max_step_s - 1e-9))
    h = dt_s / n
    pieces = math.ceil(h / CHOP_STEP_S - 1e-9)
    fine = _exact(params, h / pieces, pieces, None) if pieces > 1 else None
    return _exact(params, h, n, fine)


def _exact(params: DcMotorParams, h: float, n: int, fine: _Discrete | None) -> _Discrete:
    """Zero-order-hold discretisation: ``expm`` of the augmented system matrix.

    For ``x' = A x + B u`` with ``u`` constant over ``h``,
    ``expm([[A, B], [0, 0]] h) = [[Phi, Gamma], [0, I]]`` and ``x(h) = Phi x + Gamma u``
    exactly (no integration error whatever the ratio of ``h`` to the time constants).
    """
    from scipy.linalg import expm  # here: importing the simulators must stay cheap

    r = params.resistance_ohm
    ind = params.inductance_h
    kt = params.torque_constant_nm_per_a
    j = params.inertia_kg_m2
    b = params.viscous_friction_nm_s_per_rad
    # x = (i, w, angle), u = (v, T)
    on = [
        [-r / ind, -kt / ind, 0.0, 1.0 / ind, 0.0],
        [kt / j, -b / j, 0.0, 0.0, 1.0 / j],
        [0.0, 1.0, 0.0, 0.0, 0.0],
        [0.0] * 5,
        [0.0] * 5,
    ]
    m = expm([[value * h for value in row] for row in on])
    half = expm([[value * h / 2 for value in row] for row in on])
    # x = (w, angle), u = (T,)
    off = [[-b / j, 0.0, 1.0 / j], [1.0, 0.0, 0.0], [0.0] * 3]
    o = expm([[value * h for value in row] for row in off])
    tau_s = ind / r
    decay = math.exp(-h / tau_s)
    return _Discrete(
        n=n,
        h=h,
        decay=decay,
        mean=(1.0 - decay) * tau_s / h,  # mean of exp(-t/tau) over [0, h]
        on_ii=float(m[0, 0]),
        on_iw=float(m[0, 1]),
        on_iv=float(m[0, 3]),
        on_it=float(m[0, 4]),
        on_wi=float(m[1, 0]),
        on_ww=float(m[1, 1]),
        on_wv=float(m[1, 3]),
        on_wt=float(m[1, 4]),
        on_ai=float(m[2, 0]),
        on_aw=float(m[2, 1]),
        on_av=float(m[2, 3]),
        on_at=float(m[2, 4]),
        off_ww=float(o[0, 0]),
        off_wt=float(o[0, 2]),
        off_aw=float(o[1, 0]),
        off_at=float(o[1, 2]),
        half_ii=float(half[0, 0]),
        half_iw=float(half[0, 1]),
        half_iv=float(half[0, 3]),
        half_it=float(half[0, 4]),
        fine=fine,
    )
