"""SLAP2 firmware emulation, lowest layer: the controller cycle (``Slap2Controller``).

The seam: a SLAP2 module is a motion controller with a host interface in front of it.
This module is the controller - the manual's constants it runs on, the settings table,
and every 841.5 us tick: profile generator (ma/mr, vm), integer PID, in-position
timer, limit switches, the calibration phases, and the idle fast path that skips the
ticks of a fixed point. ``devices/slap2/sim/module.py`` is the host interface on top of it
(``Slap2Module``: line parser, command table, replies, EEPROM, reset), and
``devices/slap2/sim/line.py`` the multi-drop line on top of that (``Slap2Line``).

``Slap2Module`` has a ``Slap2Controller`` and commands it through its public methods
(the "host side" section of the class): the settings, the modes, moves, the counter,
calibration, reset. The manual's constants (``TICK_S``, ``FACTORY_DEFAULTS`` ...) are
public for the module, the line and tests.

This is the firmware oracle: ``devices/slap2/law.py`` computes the same PID law apart,
and ``devices/slap2/profile.py`` the same profile, on purpose (a shared mistake would
hide); the tests compare them tick for tick.

Sans-IO: nothing here reads a clock or touches a file descriptor.

Units: positions in encoder counts, time in 841.5 us controller ticks inside the
firmware (``TICK_S``), velocities in counts/tick, accelerations in counts/tick^2. The
wire units (``sv``, ``sa``) are converted with the manual's formulas, in which the
encoder line count cancels: counts/s = SV * 140.417 * 4 / 60, counts/s^2 =
SA * 35946.7 * 4 / 3600.
"""

from __future__ import annotations

import math
from typing import Final

from servotune.devices.slap2.codec import (
    ACCELERATION_MAX,
    CURRENT_LIMIT_MAX_MA,
    GAIN_MAX,
    VELOCITY_MAX,
    WINDOW_MAX,
)
from servotune.devices.slap2.codec import COUNTS_S2_PER_SA as COUNTS_S2_PER_SA
from servotune.devices.slap2.codec import COUNTS_S_PER_SV as COUNTS_S_PER_SV
from servotune.devices.slap2.codec import PWM_MAX as PWM_MAX
from servotune.devices.slap2.codec import TICK_S as TICK_S
from servotune.sim.physics import DcMotor

# The manual's constants come from the codec, their one home (re-exported here for the
# line and tests). The simulator stays the codec's and the driver's test oracle through
# its behaviour - its own parser, replies, profile generator and PID - which share no
# code with them; a number copied from the same manual would catch nothing.

_COUNTS_TICK_PER_SV: Final = COUNTS_S_PER_SV * TICK_S
_COUNTS_TICK2_PER_SA: Final = COUNTS_S2_PER_SA * TICK_S * TICK_S

# Settings stored by ``pg`` and their factory (EEPROM) defaults, straight from the manual.
FACTORY_DEFAULTS: Final[dict[str, int]] = {
    "kp": 40,
    "ki": 40,
    "kd": 80,
    "sipw": 5,
    "sipt": 50,
    "scv": 500,
    "sca": 200,
    "scl": 2000,
    "syscon": 3,
    "sv": 2000,
    "sa": 1000,
}
# Accepted ranges. The manual gives none for sv/sa/scv/sca/sipw/sipt: 16 bits, the
# codec's decision (its constants). sv is a speed without a sign: the manual
# defines it as the maximum travel velocity / motor speed (an rpm by its formula) and
# never shows a negative one; its own way to drive towards E1 is pm + ma -8000000. So
# a negative sv is refused (uc) and velocity mode turns towards positive counts.
SETTING_RANGES: Final[dict[str, tuple[int, int]]] = {
    "kp": (0, GAIN_MAX),
    "ki": (0, GAIN_MAX),
    "kd": (0, GAIN_MAX),
    "sipw": (0, WINDOW_MAX),
    "sipt": (0, WINDOW_MAX),
    "scv": (0, VELOCITY_MAX),
    "sca": (0, ACCELERATION_MAX),
    "scl": (0, CURRENT_LIMIT_MAX_MA),
    "syscon": (0, 63),
    "sv": (0, VELOCITY_MAX),
    "sa": (0, ACCELERATION_MAX),
}

# syscon bits
L1ON: Final = 1 << 0
L2ON: Final = 1 << 1
INV1: Final = 1 << 2
INV2: Final = 1 << 3
HEX: Final = 1 << 4
UCON: Final = 1 << 5

# PID law (LM628-like integer arithmetic, see docs/simulator.md):
#   u = (16 kp e + ki S + 32 kd (e - e_prev)) >> 12,   S = sum of e, clamped
# i.e. P = kp/256, I = ki/4096 per tick, D = kd/128 PWM units per count. The shifts
# were chosen so that the manual's P=40 I=40 D=80 settle the default unloaded 2224.
_P_MUL: Final = 16
_D_MUL: Final = 32
_PID_SHIFT: Final = 12
_I_TERM_MAX: Final = PWM_MAX << _PID_SHIFT  # anti-windup: |ki S| may not exceed full PWM

_VEL_FILTER: Final = 1.0 / 16.0  # rve: first-order filter over ~16 ticks (13 ms)

_MODE_OFF: Final = 0
_MODE_PM: Final = 1
_MODE_VM: Final = 2
_MODE_PWM: Final = 3

_CAL_NONE: Final = 0
_CAL_SEEK: Final = 1  # towards the reference switch with full cal speed
_CAL_BACKOFF: Final = 2  # out of the switch with 1/16 speed and acceleration
_CAL_INDEX: Final = 3  # until the index pulse


class Slap2Controller:
    """The motion controller of one SLAP2 module driving one simulated motor.

    Contract:

    * ``tick()`` runs one 841.5 us controller cycle (profile generator, PID, inpos,
      limit switches, calibration) and integrates the motor over the cycle;
      ``run_ticks(n)`` is ``n`` of them, the ticks of a fixed point skipped.
    * The read-only properties (``position``, ``in_position``, ``pwm`` ...) observe the
      controller without going through the wire.
    * It has no host interface of its own: ``Slap2Module`` (``devices/slap2/sim/module.py``)
      decides what a command may do (the refusals) and then commands the controller
      through the methods of the "host side" section, which apply the settings, leave
      the idle fast path where needed and keep the controller's state consistent;
      ``wake`` before anything else changes what ``tick`` reads (the motor, a setting).
      The controller never calls the host side.
    """

    def __init__(self, motor: DcMotor) -> None:
        """``motor`` is the plant, prepared here for the tick length."""
        self.motor = motor
        self.motor.prepare(TICK_S)
        # Everything below is (re)initialised by reset(); listed for clarity.
        self._settings: dict[str, int] = dict(FACTORY_DEFAULTS)
        self._mode = _MODE_OFF
        self._pwm = 0
        self._pwm_out = 0
        self._offset = 0
        self._sp = 0.0
        self._sp_vel = 0.0
        self._target = 0
        self._move_vmax = 0.0
        self._move_acc = 0.0
        self._moving = False
        self._decel = False
        self._cal_phase = _CAL_NONE
        self._cal_mode = 0
        self._cal_dir = 1
        self._cal_vmax = 0.0
        self._cal_acc = 0.0
        self._cal_index_armed = False
        self._calibrated = False
        self._integral = 0
        self._e_prev = 0
        self._inpos_timer = 0
        self._inpos = False
        self._oc = False
        self._level1 = False
        self._level2 = False
        self._last_count = 0
        self._vel_filt = 0.0
        # the idle fast path (run_ticks): the state fingerprint of a fixed point
        self._frozen: tuple[object, ...] | None = None
        self._last_fingerprint: tuple[object, ...] | None = None
        # derived from settings by _apply_settings()
        self._kp = self._ki = self._kd = 0
        self._integral_limit = 0
        self._current_limit_a = 0.0
        self._vm_vel = 0.0
        self._vm_acc = 0.0
        self._inv1 = self._inv2 = False
        self._l1on = self._l2on = False

    # --- observation ----------------------------------------------------------------

    @property
    def position(self) -> int:
        """The position counter as ``rp`` reports it."""
        return self.motor.count - self._offset

    @property
    def setpoint(self) -> int:
        """The profile generator's setpoint in counter units."""
        return math.floor(self._sp + 0.5) - self._offset

    @property
    def following_error(self) -> int:
        """``pe``: setpoint minus actual position."""
        return math.floor(self._sp + 0.5) - self.motor.count

    @property
    def in_position(self) -> bool:
        return self._inpos

    @property
    def moving(self) -> bool:
        return self._moving

    @property
    def calibrated(self) -> bool:
        return self._calibrated

    @property
    def calibrating(self) -> bool:
        return self._cal_phase != _CAL_NONE

    @property
    def current_limited(self) -> bool:
        return self._oc

    @property
    def pwm(self) -> int:
        """The PWM value applied during the last tick (-255..255, 0 when unpowered)."""
        return self._pwm_out

    @property
    def limit1_level(self) -> bool:
        """Limit switch 1 as the firmware sees it (after ``inv1``)."""
        return self._level1

    @property
    def limit2_level(self) -> bool:
        """Limit switch 2 as the firmware sees it (after ``inv2``)."""
        return self._level2

    @property
    def position_mode(self) -> bool:
        """``pm`` (also while a calibration runs)."""
        return self._mode == _MODE_PM

    @property
    def velocity_mode(self) -> bool:
        return self._mode == _MODE_VM

    @property
    def decelerating(self) -> bool:
        """The profile generator slows down (the ``ss`` byte's bit 5)."""
        return self._decel

    @property
    def target(self) -> int:
        """The profile generator's target in counter units."""
        return self._target - self._offset

    @property
    def settings(self) -> dict[str, int]:
        """A copy of the RAM settings (the ``pg`` set)."""
        return dict(self._settings)

    def setting(self, name: str) -> int:
        return self._settings[name]

    def measured_velocity_sv(self) -> int:
        """``rve``: the filtered velocity in ``sv`` units."""
        return round(self._vel_filt / _COUNTS_TICK_PER_SV)

    # --- host side: what the module commands --------------------------------------------
    # Each method applies a command the module has already accepted; none refuses.

    def reset(self, settings: dict[str, int]) -> None:
        """Power-on: ``settings`` in RAM, modes off, cal flag 0, the counter 0 wherever
        the shaft is, the bridge off."""
        self._settings = dict(settings)
        self._apply_settings()
        self._mode = _MODE_OFF
        self._pwm = self._pwm_out = 0
        self._moving = self._decel = False
        self._cal_phase = _CAL_NONE
        self._calibrated = False
        self._oc = False
        self._inpos = False
        self._inpos_timer = 0
        count = self.motor.count
        self._offset = count  # the counter starts at 0 wherever the shaft is
        self._sp = float(count)
        self._sp_vel = 0.0
        self._target = count
        self._integral = self._e_prev = 0
        self._last_count = count
        self._vel_filt = 0.0
        self.motor.current_a = 0.0  # the bridge was off
        self._update_levels()
        self.wake()

    def set_setting(self, name: str, value: int) -> None:
        """Write one RAM setting (checked by the caller) and apply it."""
        self._settings[name] = value
        self._apply_settings()

    def engage_position_mode(self) -> None:
        """``pm``: hold the current position (a controller already in pm is left alone)."""
        if self._mode != _MODE_PM:
            self._engage(hold=True)
            self._mode = _MODE_PM

    def engage_velocity_mode(self) -> None:
        """``vm``: turn at ``sv``; from pm the generator keeps its state, so the speed
        changes smoothly."""
        if self._mode in (_MODE_OFF, _MODE_PWM):
            self._engage(hold=True)
        self._mode = _MODE_VM
        self._moving = False
        self._inpos = False
        self._inpos_timer = 0

    def open_loop(self, pwm: int) -> None:
        """``spwm``: the bridge at ``pwm`` (-255..255), no control loop."""
        self._pwm = pwm
        self._cal_phase = _CAL_NONE
        self._mode = _MODE_PWM
        self._moving = self._decel = self._inpos = False

    def stop(self) -> None:
        """``st``: the bridge off."""
        self._mode = _MODE_OFF
        self._cal_phase = _CAL_NONE
        self._moving = self._decel = self._inpos = False
        self._sp_vel = 0.0

    def move_to(self, target: int) -> None:
        """``ma``/``mr`` in pm: a profile to ``target`` (counter units) with ``sv`` and
        ``sa``, replanned from the generator's current position and velocity (no jump)."""
        self._target = target + self._offset
        self._move_vmax = abs(self._settings["sv"]) * _COUNTS_TICK_PER_SV
        self._move_acc = self._settings["sa"] * _COUNTS_TICK2_PER_SA
        self._moving = True
        self._inpos = False
        self._inpos_timer = 0

    def set_position(self, position: int) -> None:
        """``sp``: the counter reads ``position`` here. Setpoint and target live in
        physical counts, so only the offset changes and a running move or the held
        position is not disturbed."""
        self._offset = self.motor.count - position

    def start_calibration(
        self, cal_mode: int, direction: int, speed: int, acceleration: int
    ) -> None:
        """``cal``/``ca``: run calibration ``cal_mode`` (0..5) towards ``direction``
        (-1: limit 1, +1: limit 2) at ``speed`` (sv units) and ``acceleration`` (sa
        units), in pm. In pm the generator keeps its velocity: a cal during a move
        ramps smoothly."""
        if self._mode != _MODE_PM:
            self._engage(hold=True)
        self._mode = _MODE_PM
        self._cal_mode = cal_mode
        self._cal_dir = direction
        self._cal_vmax = speed * _COUNTS_TICK_PER_SV
        self._cal_acc = acceleration * _COUNTS_TICK2_PER_SA
        self._calibrated = False  # stays 0 unless this calibration succeeds
        self._moving = True
        self._inpos = False
        self._inpos_timer = 0
        self._update_levels()
        reference = self._level1 if direction < 0 else self._level2
        if cal_mode >= 4:
            self._cal_phase = _CAL_INDEX
        elif reference:
            self._cal_phase = _CAL_BACKOFF  # already standing in the switch: drive out
        else:
            self._cal_phase = _CAL_SEEK
        self._cal_index_armed = False

    def abort_calibration(self) -> None:
        """Ctrl-K: stop at once, stay in pm holding, cal flag stays 0."""
        self._stop_here(self.motor.count)
        self._cal_phase = _CAL_NONE
        self._calibrated = False

    # --- settings and engaging --------------------------------------------------------

    def _apply_settings(self) -> None:
        s = self._settings
        self._kp, self._ki, self._kd = s["kp"], s["ki"], s["kd"]
        self._integral_limit = _I_TERM_MAX // max(self._ki, 1)
        self._current_limit_a = s["scl"] / 1000.0
        self._vm_vel = s["sv"] * _COUNTS_TICK_PER_SV
        self._vm_acc = s["sa"] * _COUNTS_TICK2_PER_SA
        syscon = s["syscon"]
        self._l1on = bool(syscon & L1ON)
        self._l2on = bool(syscon & L2ON)
        self._inv1 = bool(syscon & INV1)
        self._inv2 = bool(syscon & INV2)
        self._update_levels()

    def _update_levels(self) -> None:
        self._level1 = self.motor.limit1_actuated != self._inv1
        self._level2 = self.motor.limit2_actuated != self._inv2

    def _engage(self, *, hold: bool) -> None:
        """Switch the controller on, holding the current position."""
        count = self.motor.count
        if hold:
            self._sp = float(count)
            self._target = count
        self._sp_vel = 0.0
        self._integral = 0
        self._e_prev = self._target - count  # no derivative kick on the first tick
        self._moving = self._decel = False
        self._inpos = False
        self._inpos_timer = 0

    # --- the 841.5 us cycle -----------------------------------------------------------

    def tick(self) -> None:
        """One controller cycle: sample, generate, control, then integrate the motor."""
        motor = self.motor
        count = motor.count
        self._vel_filt += (count - self._last_count - self._vel_filt) * _VEL_FILTER
        self._last_count = count
        level1 = self._level1 = motor.limit1_actuated != self._inv1
        level2 = self._level2 = motor.limit2_actuated != self._inv2
        mode = self._mode
        duty: float | None
        if mode == _MODE_OFF:
            duty = None
            self._pwm_out = 0
        elif mode == _MODE_PWM:
            duty = self._pwm / PWM_MAX
            self._pwm_out = self._pwm
        else:
            block_neg = level1 and self._l1on
            block_pos = level2 and self._l2on
            if self._cal_phase != _CAL_NONE:
                self._cal_tick(count, level1, level2, block_neg, block_pos)
            elif mode == _MODE_VM:
                self._vm_tick(count, block_neg, block_pos)
            elif self._moving:
                self._move_tick(count, block_neg, block_pos)
            e = math.floor(self._sp + 0.5) - count
            integral = self._integral + e
            limit = self._integral_limit
            if integral > limit:
                integral = limit
            elif integral < -limit:
                integral = -limit
            self._integral = integral
            u = (
                _P_MUL * self._kp * e + self._ki * integral + _D_MUL * self._kd * (e - self._e_prev)
            ) >> _PID_SHIFT
            self._e_prev = e
            if u > PWM_MAX:
                u = PWM_MAX
            elif u < -PWM_MAX:
                u = -PWM_MAX
            self._pwm_out = u
            duty = u / PWM_MAX
            if mode == _MODE_PM and not self._moving:
                # inpos (manual appendix): after the generator has finished, count the
                # consecutive ticks inside +-sipw of the target; sipt of them -> inpos.
                sipw = self._settings["sipw"]
                if -sipw <= e <= sipw:
                    self._inpos_timer += 1
                    self._inpos = self._inpos_timer >= self._settings["sipt"]
                else:
                    self._inpos_timer = 0
                    self._inpos = False
        self._oc = motor.step(TICK_S, duty, self._current_limit_a)

    # --- idle fast path ------------------------------------------------------------------
    # A module at rest whose controller state did not change over a whole tick is at a
    # fixed point of ``tick``: every later tick is identical until a command or an
    # outside change (load torque, shaft moved, settings) - except two quantities that
    # nothing else reads back into the controller: the in-position timer (it counts
    # ticks, so it is advanced by the number skipped) and the velocity filter (it
    # decays towards 0; iterated exactly, a float multiply per tick, until it stops
    # changing). So ``run_ticks`` skips such ticks with the same results, bit for bit,
    # as running them. This is most of a demo axis's time between moves.

    def _fingerprint(self) -> tuple[object, ...]:
        """Everything ``tick`` reads or writes, except the timer and the filter."""
        motor = self.motor
        settings = self._settings
        return (
            self._mode, self._pwm, self._pwm_out, self._sp, self._sp_vel, self._target,
            self._moving, self._decel, self._cal_phase, self._integral, self._e_prev,
            self._inpos, self._oc, self._level1, self._level2, self._last_count,
            self._kp, self._ki, self._kd, self._integral_limit, self._current_limit_a,
            self._vm_vel, self._vm_acc, self._inv1, self._inv2, self._l1on, self._l2on,
            settings["sipw"], settings["sipt"],
            motor.count, motor.angle_rad, motor.speed_rad_s, motor.current_a,
            motor.external_torque_nm, motor.params, motor.current_limited, motor.index_crossed,
        )  # fmt: skip

    def wake(self) -> None:
        """Leave the idle fast path: something ``tick`` reads may change."""
        self._frozen = None
        self._last_fingerprint = None

    def run_ticks(self, n: int) -> None:
        """Run ``n`` controller ticks: the same as ``n`` calls of ``tick``, with the
        ticks of a fixed point skipped (see above)."""
        frozen = self._frozen
        if frozen is not None:
            if n > 0 and self._fingerprint() == frozen:
                self._skip_ticks(n)
                return
            self.wake()
        while n > 0:
            self.tick()
            n -= 1
            if (
                self._moving
                or self._cal_phase != _CAL_NONE
                or self.motor.speed_rad_s != 0.0
                or self.motor.index_crossed is not None
            ):
                self._last_fingerprint = None
                continue
            fingerprint = self._fingerprint()
            if fingerprint == self._last_fingerprint:
                self._frozen = fingerprint
                if n > 0:
                    self._skip_ticks(n)
                return
            self._last_fingerprint = fingerprint

    def _skip_ticks(self, n: int) -> None:
        """What ``n`` ticks at the frozen fixed point would change."""
        v = self._vel_filt
        for _ in range(n):  # the count does not change: count - last_count is 0
            v_next = v + (0 - v) * _VEL_FILTER
            if v_next == v:
                break
            v = v_next
        self._vel_filt = v
        if self._mode == _MODE_OFF or self._mode == _MODE_PWM:
            return
        if self._mode == _MODE_PM and not self._moving:
            sipw = self._settings["sipw"]
            e = math.floor(self._sp + 0.5) - self.motor.count
            if -sipw <= e <= sipw:
                self._inpos_timer += n
                self._inpos = self._inpos_timer >= self._settings["sipt"]
            else:
                self._inpos_timer = 0
                self._inpos = False

    def _stop_here(self, count: int) -> None:
        """Abrupt stop: the setpoint jumps to the actual position."""
        self._sp = float(count)
        self._target = count
        self._sp_vel = 0.0
        self._moving = self._decel = False

    def _ramp(self, target_vel: float, acceleration: float) -> float:
        """Move the generator velocity towards ``target_vel``; returns the new one."""
        v = self._sp_vel
        if v < target_vel:
            nv = v + acceleration
            if nv > target_vel:
                nv = target_vel
        else:
            nv = v - acceleration
            if nv < target_vel:
                nv = target_vel
        self._decel = abs(nv) < abs(v)
        self._sp_vel = nv
        self._sp += nv
        return nv

    def _move_tick(self, count: int, block_neg: bool, block_pos: bool) -> None:
        a = self._move_acc
        d = self._target - self._sp
        distance = -d if d < 0 else d
        # Highest speed from which decelerating by a per tick still stops at the target
        # (discrete: v^2/2a + v/2 <= d), capped by sv and by the distance itself.
        allowed = math.sqrt(0.25 * a * a + 2.0 * a * distance) - 0.5 * a
        if allowed > self._move_vmax:
            allowed = self._move_vmax
        if allowed > distance:
            allowed = distance
        nv = self._ramp(-allowed if d < 0 else allowed, a)
        if (nv < 0 and block_neg) or (nv > 0 and block_pos):
            self._stop_here(count)  # limit switch: abort the move at once
            return
        rest = self._target - self._sp
        if -1e-6 < rest < 1e-6 and -a <= nv <= a:
            self._sp = float(self._target)
            self._sp_vel = 0.0
            self._moving = self._decel = False

    def _vm_tick(self, count: int, block_neg: bool, block_pos: bool) -> None:
        was_moving = self._sp_vel != 0.0
        nv = self._ramp(self._vm_vel, self._vm_acc)
        if (nv < 0 and block_neg) or (nv > 0 and block_pos):
            if was_moving:
                self._stop_here(count)
            else:
                self._sp -= nv  # stay where the switch stopped us
                self._sp_vel = 0.0
                self._decel = False

    def _cal_tick(
        self, count: int, level1: bool, level2: bool, block_neg: bool, block_pos: bool
    ) -> None:
        direction = self._cal_dir
        reference = level1 if direction < 0 else level2
        phase = self._cal_phase
        if phase == _CAL_SEEK:
            if reference:
                self._stop_here(count)  # in the switch: stop at once, then back off
                self._moving = True
                self._cal_phase = _CAL_BACKOFF
                return
            nv = self._ramp(direction * self._cal_vmax, self._cal_acc)
        elif phase == _CAL_BACKOFF:
            if not reference:
                if self._cal_mode < 2:
                    self._finish_calibration(count)
                    return
                # cal 2/3: keep turning (same slow speed) until the index pulse
                self._cal_phase = _CAL_INDEX
                self._cal_index_armed = False
            nv = self._ramp(-direction * self._cal_vmax / 16, self._cal_acc / 16)
        else:
            crossed = self.motor.index_crossed
            if self._cal_index_armed and crossed is not None:
                self._finish_calibration(crossed)
                return
            # Crossings reported before this phase's first motor step do not count.
            self._cal_index_armed = True
            if self._cal_mode < 4:
                nv = self._ramp(-direction * self._cal_vmax / 16, self._cal_acc / 16)
            else:
                nv = self._ramp(direction * self._cal_vmax, self._cal_acc)
        if (nv < 0 and block_neg) or (nv > 0 and block_pos):
            # An enabled switch other than the reference stops the axis: cal failed.
            self._stop_here(count)
            self._cal_phase = _CAL_NONE

    def _finish_calibration(self, stop_count: int) -> None:
        """Success: stop at ``stop_count`` (physical) and hold it in pm."""
        self._stop_here(stop_count)
        self._cal_phase = _CAL_NONE
        self._calibrated = True
