"""The positioning state machine of the EP7047 engine: commands, motion, calibration.

What lives here: :class:`_Positioning`, the half of ``Ep7047Engine`` that decides what
the drive does - what a start type, a _CHANGE or a falling Execute does to the running
move (commands), how the setpoint moves each cycle (the trapezoid planned online,
ENDLESS, the halt and emergency ramps, settling into In-Target) and the calibration
runs - and the modes and phases both halves use. The modulo rule itself
(``modulo_travel``) is in ``servotune.devices.ep7047.modulo``, shared with the driver.

Why this seam: ``devices.ep7047.sim.engine`` is the drive's face - the edges of the outputs, the
cycle and its fast paths, the SDO objects and the inputs image - and calls in here;
nothing here reads the outputs' control bits, the edge memory or the inputs. The two
are one object (the engine inherits this class), so the state the methods share is
declared below and set by ``Ep7047Engine.__init__``.
"""

from __future__ import annotations

import enum
import math

from servotune.devices.ep7047.codec import (
    CHANGE_START_TYPES,
    CYCLE_S,
    MODULO_START_TYPES,
    SPEED_RANGE_FULL_SCALE_BP,
    DriveState,
    Outputs,
    PosDiag,
    PosSettings,
    StartType,
)
from servotune.devices.ep7047.modulo import ModuloError, modulo_travel
from servotune.devices.ep7047.sim.plant import DriveConfig, StepperPlant

# Share of the move distance by which braking starts early (manual: 0.5 %); the rest is
# crept at Velocity min.
EARLY_BRAKING_FRACTION = 0.005
_EPS_COUNTS = 1e-6


class _Mode(enum.Enum):
    IDLE = enum.auto()
    INIT = enum.auto()
    END = enum.auto()
    FINISH = enum.auto()  # last busy cycle; reported as _finish_state
    MOVE = enum.auto()
    ENDLESS = enum.auto()
    HALT = enum.auto()  # Execute dropped: ramp down, then STOP
    EMCY = enum.auto()
    PRE_TARGET = enum.auto()
    CALI_GO_CAM = enum.auto()
    CALI_LEAVE_CAM = enum.auto()
    CALI_GO_SYNC = enum.auto()
    CALI_STOP = enum.auto()


# Tuples, not sets: ``in`` a tuple compares by identity first, ``in`` a set hashes the
# member with Enum.__hash__, a Python-level call (several per 250 us cycle).
_DRIVING = (
    _Mode.MOVE,
    _Mode.ENDLESS,
    _Mode.HALT,
    _Mode.CALI_GO_CAM,
    _Mode.CALI_LEAVE_CAM,
    _Mode.CALI_GO_SYNC,
)
_CALIBRATION_SEARCH = (_Mode.CALI_GO_CAM, _Mode.CALI_LEAVE_CAM, _Mode.CALI_GO_SYNC)


class _Phase(enum.Enum):
    NONE = enum.auto()
    ACCEL = enum.auto()
    CONST = enum.auto()
    DECEL = enum.auto()


def _sign(value: float) -> int:
    return (value > 0) - (value < 0)


class _Positioning:
    """Commands, motion and calibration of
    :class:`~servotune.devices.ep7047.sim.engine.Ep7047Engine`.

    Contract: a mixin, not usable on its own; every attribute below is set by
    ``Ep7047Engine.__init__``. Its methods are called from the engine's cycle (and
    each other) and call nothing of the engine's own.
    """

    settings: PosSettings
    config: DriveConfig
    plant: StepperPlant
    cycles: int
    _setpoint: float
    _velocity: float  # counts/s, signed
    _mode: _Mode
    _finish_state: DriveState
    _finish_shown: bool
    _label: DriveState | None
    _phase: _Phase
    _last_phase: _Phase
    # the running move
    _target: float
    _cruise: float
    _acc_ms: int
    _dec_ms: int
    _margin: float
    _braking: bool
    _endless_direction: int
    _has_target: bool
    _taken: tuple[int, int, int, int, int] | None
    _start_cycle: int
    _timer_cycle: int
    _cali_sync: bool
    _cali_pulse: float | None
    # remembered across moves
    _last_target: int
    _last_direction: int
    _drive_time_ms: int
    _in_target: bool
    _error: bool
    _calibrated: bool
    _diag: PosDiag
    # levels of this cycle's outputs
    _enabled: bool
    _emergency: bool

    # --- commands -----------------------------------------------------------------------

    def _start(self, outputs: Outputs) -> None:
        self._clear_flags()
        self._start_cycle = self.cycles
        self._drive_time_ms = 0
        self._taken = self._signature(outputs)
        self._label = DriveState.START
        code = int(outputs.start_type) or self.settings.start_type
        if not self._enabled:
            self._fail()  # decision: a start without Enable is an error, nothing moves
            return
        if self._emergency:
            self._diag |= PosDiag.COMMAND_ABORTED
            self._mode = _Mode.EMCY
            return
        try:
            start_type = StartType(code)
        except ValueError:
            self._fail()
            return
        if start_type in CHANGE_START_TYPES:
            # At standstill a plain start is expected (manual).
            self._diag |= PosDiag.COMMAND_REJECTED
            self._finish(DriveState.WARNING)
            return
        if start_type in (StartType.SET_CALIBRATION, StartType.SET_CALIBRATION_AUTO):
            # Decision: SET_CALIBRATION_AUTO sent through the PDO acts like SET_CALIBRATION.
            self._calibrated = True
            self._finish(DriveState.CALIBRATED)
            return
        if start_type is StartType.CLEAR_CALIBRATION:
            self._calibrated = False
            self._finish(DriveState.NOT_CALIBRATED)
            return
        if start_type in (StartType.CALI_PLC_CAM, StartType.CALI_HW_SYNC):
            self._start_calibration(sync=start_type is StartType.CALI_HW_SYNC)
            return

        velocity_bp = min(abs(outputs.velocity_bp), self.settings.velocity_max_bp)
        if velocity_bp <= 0:
            self._fail()  # decision: velocity 0 is an error, never "use Velocity max."
            return
        self._set_dynamics(outputs, velocity_bp)
        actual = round(self.plant.actual_counts)
        operand = outputs.target_position_counts
        if start_type in (StartType.ENDLESS_PLUS, StartType.ENDLESS_MINUS):
            self._endless_direction = 1 if start_type is StartType.ENDLESS_PLUS else -1
            self._last_direction = self._endless_direction
            self._has_target = False
            self._mode = _Mode.ENDLESS
            return
        if start_type is StartType.ABSOLUTE:
            target = operand
        elif start_type is StartType.RELATIVE:
            target = actual + operand
        elif start_type is StartType.ADDITIVE:
            target = self._last_target + operand
        else:
            assert start_type in MODULO_START_TYPES
            try:
                travel, direction = modulo_travel(
                    start_type,
                    actual,
                    operand,
                    self.settings.modulo_factor_counts,
                    self.settings.modulo_tolerance_window_counts,
                    self._last_direction,
                )
            except ModuloError:
                self._fail()
                return
            target = actual + travel
            self._last_direction = direction
        if target != actual and start_type not in MODULO_START_TYPES:
            self._last_direction = _sign(target - actual)
        self._begin_move(target)

    def _begin_move(self, target: float) -> None:
        self._target = target
        self._has_target = True
        self._last_target = round(target)
        self._margin = EARLY_BRAKING_FRACTION * abs(target - self._setpoint)
        self._braking = False
        self._mode = _Mode.MOVE

    def _set_dynamics(self, outputs: Outputs, velocity_bp: int) -> None:
        self._cruise = velocity_bp / SPEED_RANGE_FULL_SCALE_BP * self.config.full_scale_counts_s
        self._acc_ms = outputs.acceleration_ms
        self._dec_ms = outputs.deceleration_ms

    @staticmethod
    def _signature(outputs: Outputs) -> tuple[int, int, int, int, int]:
        return (
            int(outputs.start_type),
            outputs.target_position_counts,
            outputs.velocity_bp,
            outputs.acceleration_ms,
            outputs.deceleration_ms,
        )

    def _is_new_change(self, outputs: Outputs) -> bool:
        # Decision: with Execute high, a change is taken when the outputs hold a _CHANGE
        # start type and differ from the command last taken; the same values again are
        # not a new command (so repeat an ADDITIVE_CHANGE by altering something).
        return (
            int(outputs.start_type) in CHANGE_START_TYPES
            and self._signature(outputs) != self._taken
        )

    def _change(self, outputs: Outputs) -> None:
        self._taken = self._signature(outputs)
        code = StartType(int(outputs.start_type))
        velocity_bp = min(abs(outputs.velocity_bp), self.settings.velocity_max_bp)
        moving = self._mode in (_Mode.MOVE, _Mode.ENDLESS) and self._velocity != 0.0
        # Rejected at standstill and while accelerating (the braking point is not known
        # yet); decision: also for velocity 0 and, for ADDITIVE_CHANGE, during an
        # ENDLESS move, which has no active target to add to.
        if (
            not moving
            or self._last_phase is _Phase.ACCEL
            or velocity_bp <= 0
            or (code is StartType.ADDITIVE_CHANGE and self._mode is _Mode.ENDLESS)
        ):
            self._diag |= PosDiag.COMMAND_REJECTED
            self._label = DriveState.WARNING
            return
        operand = outputs.target_position_counts
        if code is StartType.ABSOLUTE_CHANGE:
            target: float = operand
        elif code is StartType.RELATIVE_CHANGE:
            target = round(self.plant.actual_counts) + operand
        else:
            target = self._target + operand
        self._set_dynamics(outputs, velocity_bp)
        self._begin_move(target)
        if target != self._setpoint:
            self._last_direction = _sign(target - self._setpoint)
        if self._needs_reversal():
            self._diag |= PosDiag.TARGET_OVERRUN
        self._label = DriveState.TARGET_RESTART

    def _needs_reversal(self) -> bool:
        """True when the new target cannot be reached without passing it and coming back."""
        direction = _sign(self._velocity)
        remaining = self._target - self._setpoint
        speed = abs(self._velocity)
        _, dec = self._rates(direction)
        creep = self._creep()
        if remaining * direction <= 0:
            return not (abs(remaining) <= _EPS_COUNTS and speed <= max(creep, dec * CYCLE_S))
        return speed > creep and (speed * speed - creep * creep) / (2 * dec) > abs(remaining)

    def _abort_by_execute(self) -> None:
        if self._mode in _DRIVING and self._mode is not _Mode.HALT:
            if self._mode is not _Mode.ENDLESS:
                self._diag |= PosDiag.COMMAND_ABORTED
            self._mode = _Mode.HALT
        elif self._mode in (_Mode.PRE_TARGET, _Mode.CALI_STOP):
            self._diag |= PosDiag.COMMAND_ABORTED
            self._finish(DriveState.STOP)

    def _start_calibration(self, *, sync: bool) -> None:
        self._label = DriveState.CALI_START
        self._calibrated = False
        self._cali_sync = sync
        self._cali_pulse = None
        self._acc_ms = self._dec_ms = 0  # an aborted calibration ramps with 0x8020 values
        # Decision: starting on the cam skips the search for it.
        self._mode = _Mode.CALI_LEAVE_CAM if self.plant.cam_on else _Mode.CALI_GO_CAM

    def _fail(self) -> None:
        self._error = True
        self._finish(DriveState.ERROR)

    def _finish(self, state: DriveState) -> None:
        self._mode = _Mode.FINISH
        self._finish_state = state
        self._finish_shown = False
        if not self._has_target:
            # Decision: after an ENDLESS move, ADDITIVE adds to where it stopped.
            self._last_target = round(self.plant.actual_counts)
            self._has_target = True

    def _clear_flags(self) -> None:
        self._diag = PosDiag.NONE
        self._error = False
        self._in_target = False

    def _set_counter(self, value_counts: float) -> None:
        self.plant.set_counter(value_counts)
        self._setpoint = self.plant.commanded_counts
        self._target = self._setpoint
        # Decision: after the counter is set, ADDITIVE counts from the new position.
        self._last_target = round(self.plant.actual_counts)

    # --- motion -------------------------------------------------------------------------

    def _advance_transient(self) -> None:
        # The finishing state (TARGET, STOP, ERROR, ...) is shown for one cycle of its
        # own, also when it was entered in a cycle that reported START.
        if self._mode is _Mode.FINISH:
            if self._finish_shown:
                self._mode = _Mode.END
        elif self._mode is _Mode.END:
            self._mode = _Mode.INIT
        elif self._mode is _Mode.INIT:
            self._mode = _Mode.IDLE

    def _advance_motion(self) -> None:
        mode = self._mode
        if mode is _Mode.MOVE:
            self._advance_move()
        elif mode is _Mode.ENDLESS:
            self._advance_endless()
        elif mode is _Mode.HALT:
            _, dec = self._rates(_sign(self._velocity))
            self._ramp_to_standstill(dec)
        elif mode is _Mode.EMCY:
            self._ramp_to_standstill(self._rate(self.settings.emergency_deceleration_ms))
        elif mode is _Mode.PRE_TARGET:
            self._settle()
        elif mode in _CALIBRATION_SEARCH:
            self._advance_calibration()
        elif mode is _Mode.CALI_STOP:
            self._finish_calibration()

    def _rate(self, ramp_ms: int) -> float:
        """counts/s^2 of a ramp that takes ``ramp_ms`` for 100 % of the speed range."""
        if ramp_ms <= 0:
            return math.inf
        return self.config.full_scale_counts_s / (ramp_ms / 1000)

    def _rates(self, direction: int) -> tuple[float, float]:
        """(acceleration, deceleration) in counts/s^2 for travel in ``direction``.

        Decision (spec silent on how the PDO ramps and the 0x8020 ramps combine): the
        Acceleration/Deceleration outputs apply to both directions; a 0 there selects
        Acceleration/Deceleration pos. or neg. (0x8020:03..06) by direction of travel,
        as the compact interface (no ramps in the PDO) must. 0 there too: no ramp.
        """
        s = self.settings
        acc_ms = self._acc_ms or (s.acceleration_neg_ms if direction < 0 else s.acceleration_pos_ms)
        dec_ms = self._dec_ms or (s.deceleration_neg_ms if direction < 0 else s.deceleration_pos_ms)
        return self._rate(acc_ms), self._rate(dec_ms)

    def _creep(self) -> float:
        # Decision: Velocity min. 0 creeps at 1 bp, or a move braked 0.5 % early would
        # never arrive; a move slower than Velocity min. creeps at its own velocity.
        velocity_min_bp = max(self.settings.velocity_min_bp, 1)
        creep = velocity_min_bp / SPEED_RANGE_FULL_SCALE_BP * self.config.full_scale_counts_s
        return min(creep, self._cruise) if self._cruise > 0 else creep

    def _set_velocity(self, velocity: float) -> None:
        old, new = abs(self._velocity), abs(velocity)
        if new > old:
            self._phase = _Phase.ACCEL
        elif new < old:
            self._phase = _Phase.DECEL
        else:
            self._phase = _Phase.CONST
        self._velocity = velocity
        self._setpoint += velocity * CYCLE_S

    def _advance_move(self) -> None:
        """One cycle of a positioning move towards ``_target``.

        Trapezoid planned online, so changes and reversals need no special profile:
        accelerate while a brake to Velocity min. still fits before the target less the
        0.5 % early-braking margin; else hold; else brake, and once braking never
        accelerate again (no hunting between the two). After the ramp the remaining
        margin is crept at Velocity min., from which the motor may stop abruptly.
        """
        remaining = self._target - self._setpoint
        speed = abs(self._velocity)
        moving = _sign(self._velocity)
        creep = self._creep()
        if abs(remaining) <= _EPS_COUNTS:
            _, dec = self._rates(moving)
            if speed <= max(creep, dec * CYCLE_S):
                self._arrive()
                return
        direction = _sign(remaining)
        if moving and moving != direction:
            # Past the target (a late change): brake to a standstill, then turn round.
            _, dec = self._rates(moving)
            self._braking = False
            self._set_velocity(moving * max(speed - dec * CYCLE_S, 0.0))
            return
        acc, dec = self._rates(direction)
        distance = abs(remaining)
        margin = self._margin

        def fits(candidate: float) -> bool:
            if candidate <= creep:
                return True
            braking_distance = (candidate * candidate - creep * creep) / (2 * dec)
            return distance - candidate * CYCLE_S - margin >= braking_distance

        if self._braking:
            new_speed = max(speed - dec * CYCLE_S, creep)
        elif speed > self._cruise:
            # a change lowered the velocity: ramp down to it, or brake if that is due
            new_speed = max(speed - dec * CYCLE_S, self._cruise)
            if not fits(new_speed):
                self._braking = True
                new_speed = max(speed - dec * CYCLE_S, creep)
        else:
            accelerated = min(speed + acc * CYCLE_S, self._cruise)
            if accelerated > speed and fits(accelerated):
                new_speed = accelerated
            elif speed >= creep and fits(speed):
                new_speed = speed
            else:
                self._braking = speed > creep
                new_speed = max(speed - dec * CYCLE_S, creep)
        if new_speed * CYCLE_S >= distance and new_speed <= max(creep, dec * CYCLE_S):
            self._arrive()
            return
        self._set_velocity(direction * new_speed)

    def _arrive(self) -> None:
        self._setpoint = self._target
        self._velocity = 0.0
        self._mode = _Mode.PRE_TARGET
        self._timer_cycle = self.cycles

    def _settle(self) -> None:
        # "In-Target" needs the actual position in the window within the timeout
        # (the ideal plant is at standstill as soon as the setpoint is).
        error = abs(self.plant.actual_counts - self._target)
        if error <= self.settings.target_window_counts:
            self._in_target = True
            self._finish(DriveState.TARGET)
        elif self._elapsed_ms(self._timer_cycle) >= self.settings.in_target_timeout_ms:
            self._mode = _Mode.END  # only the falling Busy tells (manual)

    def _advance_endless(self) -> None:
        direction = self._endless_direction
        speed = abs(self._velocity)
        acc, dec = self._rates(direction)
        if speed < self._cruise:
            new_speed = min(speed + acc * CYCLE_S, self._cruise)
        else:
            new_speed = max(speed - dec * CYCLE_S, self._cruise)
        self._set_velocity(direction * new_speed)

    def _ramp_to_standstill(self, dec: float) -> None:
        if self._velocity == 0.0:
            self._finish(DriveState.STOP)
            self._target = self._setpoint
            return
        moving = _sign(self._velocity)
        self._set_velocity(moving * max(abs(self._velocity) - dec * CYCLE_S, 0.0))

    def _elapsed_ms(self, since_cycle: int) -> float:
        return (self.cycles - since_cycle) * CYCLE_S * 1000

    # --- calibration --------------------------------------------------------------------

    def _advance_calibration(self) -> None:
        # Decision: calibration runs at its two creep velocities without ramps: they
        # are meant to be slow enough to start and stop abruptly, like Velocity min.
        s = self.settings
        scale = self.config.full_scale_counts_s / SPEED_RANGE_FULL_SCALE_BP
        if self._mode is _Mode.CALI_GO_CAM:
            direction = -1 if s.invert_calibration_cam_search else 1
            speed = abs(s.calibration_velocity_towards_cam_bp) * scale
        else:
            direction = -1 if s.invert_sync_impulse_search else 1
            speed = abs(s.calibration_velocity_off_cam_bp) * scale
        self._velocity = direction * speed
        self._setpoint += self._velocity * CYCLE_S

    def _watch_calibration_sensors(self, pulse: float | None) -> None:
        # The cam input is polled once a cycle (the manual's systematic error); the
        # C-track pulse position comes latched by hardware.
        if self._mode is _Mode.CALI_GO_CAM and self.plant.cam_on:
            self._mode = _Mode.CALI_LEAVE_CAM
            self._label = DriveState.CALI_ON_CAM
        elif self._mode is _Mode.CALI_LEAVE_CAM and not self.plant.cam_on:
            if self._cali_sync:
                self._mode = _Mode.CALI_GO_SYNC
            else:
                self._stop_calibration_drive()
        elif self._mode is _Mode.CALI_GO_SYNC and pulse is not None:
            self._cali_pulse = pulse
            self._stop_calibration_drive()

    def _stop_calibration_drive(self) -> None:
        self._velocity = 0.0
        self._mode = _Mode.CALI_STOP
        self._timer_cycle = self.cycles

    def _finish_calibration(self) -> None:
        self._velocity = 0.0
        if self._elapsed_ms(self._timer_cycle) < self.settings.in_target_timeout_ms:
            return
        value = float(self.settings.calibration_position_counts)
        if self._cali_pulse is not None:
            # Decision: with the C track the calibration position belongs to the pulse
            # itself, not to where the motor came to rest a fraction of a cycle later;
            # that is what makes this calibration the accurate one.
            value += self.plant.actual_counts - self._cali_pulse
        self._set_counter(value)
        self._calibrated = True
        self._finish(DriveState.CALIBRATED)
