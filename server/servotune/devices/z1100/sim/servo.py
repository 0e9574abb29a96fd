"""Z1100 simulator, lower half: one servo axis - the firmware's per-axis state, its
servo law and motion profiles, and the motor it drives (sans-IO, no clock).

The seam: this module is what happens *inside one axis* between two servo samples;
``servotune.devices.z1100.sim.chip`` is the chip around the three axes (the serial packets, the
command interpreter, the flash, the reset and fault injections). The chip sets an
axis's parameters and mode and calls :meth:`_Axis.run_until`; nothing here knows
about packets, replies or the flash file (``AxisParameters.to_json``/``from_json``
is the flash's entry format, kept on the data it describes).

The chip uses the package-private ``_Axis``, ``_positive`` and the mode/phase
constants; callers that build or inspect a chip use ``AxisHardware``,
``AxisParameters`` and ``AxisState``.

Each axis is a ``DcMotor`` (``servotune.sim.physics``) under a servo law stepped at
the axis's own sampling time, Stm x 32 us. The manual gives no equations; the law
chosen here (docs/z1100-simulator.md has the reasoning and the tuning landscape) is,
per sample, with ``e`` = profile position - encoder position and ``y`` = encoder
position, differences taken over the last ``DERIVATIVE_WINDOW`` samples::

    u    = K * (16 * e + A * delta(e)) - B * delta(y)
    pwm  = clamp(trunc(u / 64), -255, 255)          # 8-bit PWM magnitude + DIR
    duty = pwm / 255

K = 0 never turns the motor; A is derivative action on the forward path (it scales
with K); B is velocity ("tachometric") feedback. The derivative window (about 1 ms at
Stm = 1) is what a real chip needs to get usable speed resolution from an encoder
sampled every 32 us; its delay is also what makes a large K oscillate, as the manual
warns.

Decisions where the spec is silent are listed in docs/z1100-simulator.md and repeated
next to the code that implements them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Final

from servotune.devices.z1100.codec import (
    CAB_MASK,
    LIMIT_MAX_COUNTS,
    STM_DEFAULT,
    STM_TICK_S,
    Cab,
    Gains,
    Job,
    unpack_int32,
)
from servotune.sim.physics import DcMotor, DcMotorParams

# --- servo law constants (see the module docstring) ----------------------------------
DERIVATIVE_WINDOW: Final = 32  # samples: 1.024 ms at Stm = 1
ERROR_WEIGHT: Final = 16  # weight of e against A * delta(e)
OUTPUT_SHIFT_DIVISOR: Final = 64  # u / 64 -> PWM units
PWM_FULL_SCALE: Final = 255

_ZERO_GAINS: Final = Gains(0, 0, 0)


@dataclass(frozen=True, slots=True)
class AxisHardware:
    """What is wired to one axis: motor and load, home switch, wiring mistakes.

    ``motor``: plant parameters (``None``: the physics module's default motor, an
    unloaded Faulhaber 2224 at 24 V with a 512-line encoder); ``load_inertia_kg_m2``
    is added to it, so axes can carry different loads and need different gains.
    The home switch sits at the negative end: it is pressed while the physical encoder
    count is at or below ``home_switch_counts`` (the manual: counts increase away from
    the switch). ``start_counts``: physical shaft position at construction.
    ``motor_leads_reversed`` / ``encoder_swapped`` are wiring mistakes that the
    matching Cab bits undo; ``switch_active_high``: the switch input reads 1 when
    pressed (Cab bit 2 must then be set).
    """

    motor: DcMotorParams | None = None
    load_inertia_kg_m2: float = 0.0
    home_switch_counts: int = -2048
    start_counts: int = 0
    motor_leads_reversed: bool = False
    encoder_swapped: bool = False
    switch_active_high: bool = False

    def motor_params(self) -> DcMotorParams:
        """The plant: ``motor`` plus the load; the physics' limit switches E1/E2 are
        not used by the Z1100 (it has one home switch, modelled here)."""
        base = self.motor if self.motor is not None else DcMotorParams()
        return replace(
            base,
            load_inertia_kg_m2=base.load_inertia_kg_m2 + self.load_inertia_kg_m2,
            limit1_count=None,
            limit2_count=None,
        )


@dataclass(slots=True)
class AxisParameters:
    """The RAM parameters of one axis that SetFlash saves (all zero after a reset with
    a blank flash, except Stm = 1, the manual's power-on value)."""

    kabh: Gains = _ZERO_GAINS
    kabd: Gains = _ZERO_GAINS
    vmax_counts_s: int = 0
    acc_counts_s2: int = 0
    stm: int = STM_DEFAULT
    hvm_counts_s: int = 0
    hac_counts_s2: int = 0
    limit_counts: int = 0
    cab: int = 0
    busy: bool = False

    def to_json(self) -> dict[str, Any]:
        """The flash file's entry for this axis."""
        return {
            "kabh": [self.kabh.k, self.kabh.a, self.kabh.b],
            "kabd": [self.kabd.k, self.kabd.a, self.kabd.b],
            "vmax_counts_s": self.vmax_counts_s,
            "acc_counts_s2": self.acc_counts_s2,
            "stm": self.stm,
            "hvm_counts_s": self.hvm_counts_s,
            "hac_counts_s2": self.hac_counts_s2,
            "limit_counts": self.limit_counts,
            "cab": self.cab,
            "busy": self.busy,
        }

    @classmethod
    def from_json(cls, document: object) -> AxisParameters:
        """Parse one axis of a flash file; raises ``ValueError`` if anything is off
        (the caller treats the whole flash as blank then, like a corrupt page)."""
        if not isinstance(document, dict):
            raise ValueError("axis entry is not an object")
        entry: dict[str, Any] = document

        def number(name: str, maximum: int, minimum: int = 0) -> int:
            value = entry.get(name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f"{name} is not an integer")
            if not minimum <= value <= maximum:
                raise ValueError(f"{name} out of range")
            return value

        def gains(name: str) -> Gains:
            value = entry.get(name)
            if not isinstance(value, list) or len(value) != 3:
                raise ValueError(f"{name} is not [K, A, B]")
            if not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
                raise ValueError(f"{name} is not [K, A, B]")
            return Gains(*value)  # Gains checks 0..255 (CodecError is a ValueError)

        busy = entry.get("busy")
        if not isinstance(busy, bool):
            raise ValueError("busy is not a boolean")
        return cls(
            kabh=gains("kabh"),
            kabd=gains("kabd"),
            vmax_counts_s=number("vmax_counts_s", 0xFFFF_FFFF),
            acc_counts_s2=number("acc_counts_s2", 0xFFFF_FFFF),
            stm=number("stm", 255),
            hvm_counts_s=number("hvm_counts_s", 0xFFFF_FFFF),
            hac_counts_s2=number("hac_counts_s2", 0xFFFF_FFFF),
            limit_counts=number("limit_counts", LIMIT_MAX_COUNTS),
            cab=number("cab", CAB_MASK),
            busy=busy,
        )


@dataclass(frozen=True, slots=True)
class AxisState:
    """A snapshot of one axis for tests, demos and plots (not on the wire)."""

    encoder_counts: int  # the chip's counter (what GetEncoder reads, before wrapping)
    physical_counts: int  # the shaft's own count (0 = angle 0), unaffected by Cab/Zero
    reference_counts: float  # profile position in the chip's frame
    error_counts: int  # last position error computed (what GetError reads)
    running: bool  # start bit (GetStart)
    powered: bool  # servo engaged
    stalled: bool
    stopped_by_command: bool
    homing: bool
    duty: float  # -1..1 as applied to the motor terminals
    switch_pressed: bool  # as the chip reads it (after Cab bit 2)
    job: int
    speed_counts_s: float


# Profile modes.
_IDLE, _MOVE, _VELOCITY, _HOME = range(4)
# Homing phases: leave the switch (if pressed at Zero), brake, seek it, brake, return.
_H_LEAVE, _H_LEAVE_BRAKE, _H_SEEK, _H_BRAKE, _H_RETURN = range(5)


def _positive(value: int) -> int:
    """Speeds and accelerations are signed 32-bit on the chip; a negative one
    ("must always be positive") is used as 0: the motor never turns."""
    return max(0, unpack_int32(value))


class _Axis:
    """Firmware state of one axis plus its motor. Internal: the chip drives it."""

    def __init__(self, index: int, hardware: AxisHardware) -> None:
        self.index = index
        self.hardware = hardware
        self.params_base = hardware.motor_params()
        self.motor = DcMotor(self.params_base)
        self.motor.prepare(STM_TICK_S)  # the slow part (importing scipy) before going online
        self.motor.set_count(hardware.start_counts)
        self.samples = 0
        self.p = AxisParameters()
        self.reset()

    # --- state -----------------------------------------------------------------------

    def reset(self) -> None:
        """As after a chip reset: servo off, counter 0 wherever the shaft is."""
        self.job = int(Job.FREE)
        self.target_counts = 0
        self.running = False
        self.powered = False
        self.stalled = False
        self.stopped_by_command = False
        self.direction_positive = False
        self.mode = _IDLE
        self.home_phase = _H_SEEK
        self.home_edge = 0
        self.stopping = False
        self.counter = 0
        self.last_phys = self.motor.count
        self.ref = 0.0
        self.ref_v = 0.0  # counts per sample
        self.error = 0
        self.duty = 0.0
        self.e_hist = [0] * DERIVATIVE_WINDOW
        self.y_hist = [0] * DERIVATIVE_WINDOW
        self.hist_i = 0
        self.still = 0
        self.e_last = 0
        self.y_last = 0
        self.frozen: tuple[int, float, float, object] | None = None
        self.next_tick = 0
        self._per_sample_key: tuple[int, int, int] | None = None
        self._per_sample_value = (0.0, 0.0)
        self.update_signs()
        self.motor.current_a = 0.0  # the bridge is off

    def update_signs(self) -> None:
        """Directions after Cab: the wiring mistake and the Cab bit cancel out."""
        cab = self.p.cab
        hw = self.hardware
        self.out_sign = -1.0 if hw.motor_leads_reversed != bool(cab & Cab.MOTOR_REVERSED) else 1.0
        self.enc_sign = -1 if hw.encoder_swapped != bool(cab & Cab.ENCODER_SWAPPED) else 1

    @property
    def sample_s(self) -> float:
        """The sampling period, Stm x 32 us."""
        return max(1, self.p.stm) * STM_TICK_S  # Stm 0 cannot be a period: used as 1

    @property
    def switch_pressed(self) -> bool:
        """The home switch as the chip reads it: pin level interpreted with Cab bit 2
        (0: pressed reads 0, the manual's default wiring; 1: pressed reads 1)."""
        hw = self.hardware
        pressed = self.motor.count <= hw.home_switch_counts
        level = pressed if hw.switch_active_high else not pressed
        return level if self.p.cab & Cab.SWITCH_ACTIVE_HIGH else not level

    def engage(self) -> None:
        """Servo on, holding the current position (no derivative kick)."""
        self.sync_counter()
        self.powered = True
        self.ref = float(self.counter)
        self.ref_v = 0.0
        self.error = 0
        self.e_hist = [0] * DERIVATIVE_WINDOW
        self.y_hist = [self.counter] * DERIVATIVE_WINDOW
        self.still = 0
        self.wake()

    def power_off(self) -> None:
        """Motor power off (free shaft); the move, if any, ends."""
        self.powered = False
        self.running = False
        self.mode = _IDLE
        self.stopping = False
        self.duty = 0.0
        self.wake()

    def wake(self) -> None:
        """Leave the idle fast path: something may have changed."""
        self.frozen = None
        self.still = 0

    def sync_counter(self) -> None:
        """Bring the chip's counter up to the shaft (it counts edges continuously)."""
        phys = self.motor.count
        delta = phys - self.last_phys
        if delta:
            self.last_phys = phys
            self.counter += delta * self.enc_sign

    # --- profile -----------------------------------------------------------------------

    def _per_sample(self, speed_counts_s: int, acc_counts_s2: int) -> tuple[float, float]:
        # Cached: called every sample (31250 a second at Stm 1) with the same inputs.
        key = (speed_counts_s, acc_counts_s2, self.p.stm)
        if key != self._per_sample_key:
            ts = self.sample_s
            self._per_sample_key = key
            self._per_sample_value = (
                _positive(speed_counts_s) * ts,
                _positive(acc_counts_s2) * ts * ts,
            )
        return self._per_sample_value

    def _ramp(self, v_goal: float, acc: float) -> None:
        v = self.ref_v
        if v < v_goal:
            v = min(v + acc, v_goal)
        elif v > v_goal:
            v = max(v - acc, v_goal)
        self.ref_v = v
        self.ref += v

    def _approach(self, goal: float, vmax: float, acc: float) -> bool:
        """One trapezoid step towards ``goal`` (from rest or moving towards it); True
        when it is reached with zero speed. ``sqrt(2 a d)`` caps the speed so that the
        motor can still stop at the goal: short moves never reach vmax."""
        remaining = goal - self.ref
        distance = abs(remaining)
        speed = min(abs(self.ref_v) + acc, vmax, math.sqrt(2.0 * acc * distance))
        if speed >= distance:
            self.ref = goal
            self.ref_v = 0.0
            return True
        step = speed if remaining > 0 else -speed
        self.ref += step
        self.ref_v = step
        return False

    def profile_step(self) -> None:
        """Advance the reference by one sample in the current mode."""
        p = self.p
        if self.mode == _MOVE:
            vmax, acc = self._per_sample(p.vmax_counts_s, p.acc_counts_s2)
            if self._approach(float(self.target_counts), vmax, acc):
                self.finish()
        elif self.mode == _VELOCITY:
            vmax, acc = self._per_sample(p.vmax_counts_s, p.acc_counts_s2)
            if self.stopping:
                self._ramp(0.0, acc)
                if self.ref_v == 0.0:
                    self.finish()
            else:
                self._ramp(vmax if self.direction_positive else -vmax, acc)
        elif self.mode == _HOME:
            self._home_step()

    def _home_step(self) -> None:
        vmax, acc = self._per_sample(self.p.hvm_counts_s, self.p.hac_counts_s2)
        phase = self.home_phase
        pressed = self.switch_pressed
        if phase == _H_LEAVE:
            # Zero with the switch already pressed: move off it first, so that the
            # edge is always found from the same side.
            self._ramp(vmax, acc)
            if not pressed:
                self.home_phase = _H_LEAVE_BRAKE
        elif phase == _H_LEAVE_BRAKE:
            self._ramp(0.0, acc)
            if self.ref_v == 0.0:
                self.home_phase = _H_SEEK
        elif phase == _H_SEEK:
            self._ramp(-vmax, acc)
            if pressed:
                self.home_edge = self.counter  # the first count that presses it
                self.home_phase = _H_BRAKE
        elif phase == _H_BRAKE:
            self._ramp(0.0, acc)
            if self.ref_v == 0.0:
                self.home_phase = _H_RETURN
        elif self._approach(float(self.home_edge), vmax, acc):
            # Home reached: the switch edge becomes position 0.
            edge = self.home_edge
            self.counter -= edge
            self.ref -= edge
            self.y_hist = [y - edge for y in self.y_hist]
            self.y_last -= edge
            self.finish()

    def finish(self) -> None:
        """The move ended: the start bit clears itself, KABD takes over."""
        self.running = False
        self.mode = _IDLE
        self.stopping = False
        self.ref_v = 0.0

    # --- one servo sample ------------------------------------------------------------

    def sample(self) -> None:
        """Run one sample (encoder, profile, stall check, law) and integrate the motor
        over the sampling period with the PWM just computed held (zero-order hold)."""
        self.samples += 1
        motor = self.motor
        stm = self.p.stm
        ts = (stm if stm > 1 else 1) * STM_TICK_S  # sample_s, inlined: this runs 31 kHz
        phys = motor.count
        delta = phys - self.last_phys
        if delta:
            self.last_phys = phys
            self.counter += delta * self.enc_sign
        y = self.counter
        if not self.powered:
            motor.step(ts, None)
            if motor.speed_rad_s == 0.0 and abs(motor.external_torque_nm) <= (
                motor.params.coulomb_friction_nm
            ):
                self._freeze()
            return
        if self.running:
            self.profile_step()
        e = math.floor(self.ref + 0.5) - y
        self.error = e
        limit = self.p.limit_counts
        if e > limit or e < -limit:
            # Stall protection: motor power off, reply bit 7, GetStop bit 4..6.
            self.power_off()
            self.stalled = True
            motor.step(ts, None)
            return
        i = self.hist_i
        de = e - self.e_hist[i]
        dy = y - self.y_hist[i]
        self.e_hist[i] = e
        self.y_hist[i] = y
        self.hist_i = i + 1 if i + 1 < DERIVATIVE_WINDOW else 0
        gains = self.p.kabh if self.running else self.p.kabd
        u = gains.k * (ERROR_WEIGHT * e + gains.a * de) - gains.b * dy
        pwm = int(u / OUTPUT_SHIFT_DIVISOR)  # truncates towards zero, like a shift of |u|
        if pwm > PWM_FULL_SCALE:
            pwm = PWM_FULL_SCALE
        elif pwm < -PWM_FULL_SCALE:
            pwm = -PWM_FULL_SCALE
        duty = self.out_sign * pwm / PWM_FULL_SCALE
        self.duty = duty
        motor.step(ts, duty)
        if self.running or e != self.e_last or y != self.y_last:
            self.still = 0
        else:
            self.still += 1
            if self.still >= DERIVATIVE_WINDOW and motor.speed_rad_s == 0.0:
                self._freeze_if_stuck(duty)
        self.e_last = e
        self.y_last = y

    # --- idle fast path ------------------------------------------------------------------
    # An axis at rest whose inputs have not changed for a whole derivative window puts
    # out a constant PWM; if friction holds the shaft against the resulting torque,
    # every further sample is identical, so they are skipped until a command, a fault
    # injection or an outside change (load torque, shaft moved) wakes the axis.

    def _freeze_if_stuck(self, duty: float) -> None:
        motor = self.motor
        params = motor.params
        i_ss = duty * params.supply_v / params.resistance_ohm
        kt = params.torque_constant_nm_per_a
        ext = motor.external_torque_nm
        tc = params.coulomb_friction_nm
        if abs(kt * i_ss + ext) <= tc and abs(kt * motor.current_a + ext) <= tc:
            motor.current_a = i_ss  # where the current settles anyway
            self._freeze()

    def _freeze(self) -> None:
        motor = self.motor
        self.frozen = (motor.count, motor.angle_rad, motor.external_torque_nm, motor.params)

    def still_frozen(self) -> bool:
        """Whether the frozen axis may keep skipping samples (nothing moved it)."""
        frozen = self.frozen
        if frozen is None:
            return False
        motor = self.motor
        if frozen != (motor.count, motor.angle_rad, motor.external_torque_nm, motor.params):
            self.wake()
            return False
        return True

    def run_until(self, due_tick: int) -> None:
        """Run the samples due up to ``due_tick`` (in 32 us ticks)."""
        stm = max(1, self.p.stm)
        while self.next_tick <= due_tick:
            if self.still_frozen():
                skipped = (due_tick - self.next_tick) // stm + 1
                self.next_tick += skipped * stm
                break
            if self.running and self.powered and self.mode == _MOVE:
                done = self._move_samples((due_tick - self.next_tick) // stm + 1)
                if done:
                    self.next_tick += done * stm
                    continue
            self.sample()
            self.next_tick += stm

    # --- the move fast path ----------------------------------------------------------------
    # Most samples of a busy axis are samples of a positioning move with the shaft
    # turning. ``_move_samples`` runs them with the state in local variables and the
    # motor's step inlined (the "bridge on, shaft turning" case of DcMotor._advance,
    # one piece, no chopper): the same operations in the same order as ``sample`` ->
    # ``profile_step`` -> ``_approach`` -> ``DcMotor.step``, so the results are the same
    # bit for bit (tests/device/z1100/test_sim.py compares the two). It hands over to
    # ``sample`` - before changing anything - for every sample that may take another
    # branch: the shaft at rest, the move ending, the stall limit exceeded.

    def _move_samples(self, n: int) -> int:
        """Run up to ``n`` samples of a running move on the fast path; returns how many."""
        motor = self.motor
        params = motor.params
        stm = self.p.stm
        ts = (stm if stm > 1 else 1) * STM_TICK_S
        f = motor._decay_cache.get(ts) or motor._factors(ts)
        if f.n != 1:
            return 0
        p = self.p
        vmax, acc = self._per_sample(p.vmax_counts_s, p.acc_counts_s2)
        goal = float(self.target_counts)
        limit = p.limit_counts
        gains = p.kabh
        gk, ga, gb = gains.k, gains.a, gains.b
        out_sign = self.out_sign
        enc_sign = self.enc_sign
        supply = params.supply_v
        tc = params.coulomb_friction_nm
        ext = motor.external_torque_nm
        cpr_rad = motor._counts_per_rad
        on_ii, on_iw, on_iv, on_it = f.on_ii, f.on_iw, f.on_iv, f.on_it
        on_wi, on_ww, on_wv, on_wt = f.on_wi, f.on_ww, f.on_wv, f.on_wt
        on_ai, on_aw, on_av, on_at = f.on_ai, f.on_aw, f.on_av, f.on_at
        e_hist, y_hist = self.e_hist, self.y_hist
        hist_i = self.hist_i
        counter, last_phys = self.counter, self.last_phys
        ref, ref_v = self.ref, self.ref_v
        count = motor.count
        i, w, angle = motor.current_a, motor.speed_rad_s, motor.angle_rad
        crossed = motor.index_crossed
        duty = self.duty
        e = self.error
        y = self.y_last
        floor, sqrt = math.floor, math.sqrt
        done = 0
        while done < n:
            if w == 0.0:
                break  # at rest: stiction decides (DcMotor._advance's other branch)
            # encoder
            delta = count - last_phys
            y_new = counter
            if delta:
                y_new = counter + delta * enc_sign
            # profile (_approach towards the target)
            remaining = goal - ref
            distance = abs(remaining)
            speed = min(abs(ref_v) + acc, vmax, sqrt(2.0 * acc * distance))
            if speed >= distance:
                break  # the move ends in this sample: ``sample`` does it (finish)
            step = speed if remaining > 0 else -speed
            ref_new = ref + step
            e_new = floor(ref_new + 0.5) - y_new
            if e_new > limit or e_new < -limit:
                break  # stall protection: ``sample`` does it
            # committed from here on
            if delta:
                last_phys = count
                counter = y_new
            ref, ref_v = ref_new, step
            e, y = e_new, y_new
            de = e - e_hist[hist_i]
            dy = y - y_hist[hist_i]
            e_hist[hist_i] = e
            y_hist[hist_i] = y
            hist_i = hist_i + 1 if hist_i + 1 < DERIVATIVE_WINDOW else 0
            u = gk * (ERROR_WEIGHT * e + ga * de) - gb * dy
            pwm = int(u / OUTPUT_SHIFT_DIVISOR)
            if pwm > PWM_FULL_SCALE:
                pwm = PWM_FULL_SCALE
            elif pwm < -PWM_FULL_SCALE:
                pwm = -PWM_FULL_SCALE
            duty = out_sign * pwm / PWM_FULL_SCALE
            # DcMotor.step(ts, duty): one piece, bridge on, shaft turning
            d = 1.0 if duty > 1.0 else -1.0 if duty < -1.0 else duty
            v = d * supply
            direction = 1.0 if w > 0.0 else -1.0
            torque = ext - direction * tc
            free = on_ii * i + on_iw * w + on_it * torque
            i_end = free + on_iv * v
            w_new = on_wi * i + on_ww * w + on_wv * v + on_wt * torque
            d_angle = on_ai * i + on_aw * w + on_av * v + on_at * torque
            i = i_end
            if w_new != 0.0 and (w_new > 0.0) != (direction > 0.0):
                w_new = 0.0
            angle += d_angle
            w = w_new
            new_count = floor(angle * cpr_rad)
            if new_count != count:
                crossed = motor._index_between(count, new_count, None)
                count = new_count
            else:
                crossed = None
            done += 1
        if done:
            self.samples += done
            self.hist_i = hist_i
            self.counter, self.last_phys = counter, last_phys
            self.ref, self.ref_v = ref, ref_v
            self.error = e
            self.duty = duty
            self.still = 0  # running: as in ``sample``
            self.e_last, self.y_last = e, y
            motor.count = count
            motor.current_a, motor.speed_rad_s, motor.angle_rad = i, w, angle
            motor.index_crossed = crossed
            motor.current_limited = False
        return done

    def state(self) -> AxisState:
        """A snapshot for observers."""
        return AxisState(
            encoder_counts=self.counter,
            physical_counts=self.motor.count,
            reference_counts=self.ref,
            error_counts=self.error,
            running=self.running,
            powered=self.powered,
            stalled=self.stalled,
            stopped_by_command=self.stopped_by_command,
            homing=self.mode == _HOME,
            duty=self.duty if self.powered else 0.0,
            switch_pressed=self.switch_pressed,
            job=self.job,
            speed_counts_s=self.motor.speed_rad_s * self.params_base.counts_per_rev / math.tau,
        )
