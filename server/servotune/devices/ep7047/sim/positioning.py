"""The positioning state machine of the EP7047 engine: commands, motion, calibration.

What lives here: :class:`Positioning`, the part of ``Ep7047Engine`` that decides what
the drive does - what a start type, a _CHANGE or a falling Execute does to the running
move (commands), how the setpoint moves each cycle (the trapezoid planned online,
ENDLESS, the halt and emergency ramps, settling into In-Target) and the calibration
runs - and the modes and phases both use. The modulo rule itself (``modulo_travel``)
is in ``servotune.devices.ep7047.modulo``, shared with the driver.

Why this seam: ``devices.ep7047.sim.engine`` is the drive's face - the edges of the
outputs, the cycle and its fast paths, the SDO objects and the inputs image - and has a
``Positioning`` it calls into; nothing here reads the outputs' control bits, the edge
memory or the inputs.
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
_NOT_BUSY = (_Mode.IDLE, _Mode.INIT, _Mode.END)


class _Phase(enum.Enum):
    NONE = enum.auto()
    ACCEL = enum.auto()
    CONST = enum.auto()
    DECEL = enum.auto()


def _sign(value: float) -> int:
    return (value > 0) - (value < 0)


class Positioning:
    """Commands, motion and calibration of one drive (the state machine behind
    :class:`~servotune.devices.ep7047.sim.engine.Ep7047Engine`).

    Contract: the engine has one and calls it from its cycle: ``begin_cycle`` first,
    then what the outputs' edges and levels ask (``start``, ``change``,
    ``abort_by_execute``, ``emergency_stop``, ``driver_off``, ``clear_flags``,
    ``set_counter``), ``advance_motion``, ``watch_calibration_sensors``, and
    ``end_cycle`` last. The public attributes are the state the engine reports (and
    reads for its fast paths); only these methods change them. ``settings`` may be
    replaced between cycles and is read live; ``cycle`` arguments are the engine's
    cycle count. Nothing here reads the outputs' control bits, keeps edges or builds
    the inputs.
    """

    def __init__(self, settings: PosSettings, config: DriveConfig, plant: StepperPlant) -> None:
        self.settings = settings
        self.config = config
        self.plant = plant
        self.setpoint = plant.commanded_counts
        self.velocity = 0.0  # counts/s, signed
        self.mode = _Mode.INIT
        self.finish_state = DriveState.END
        self.finish_shown = False
        self.label: DriveState | None = None
        self.phase = _Phase.NONE
        self.last_phase = _Phase.NONE
        # the running move
        self.target = self.setpoint
        self.cruise = 0.0
        self._acc_ms = 0
        self._dec_ms = 0
        self.margin = 0.0
        self.braking = False
        self.endless_direction = 0
        self._has_target = True  # False while ENDLESS: nothing for ADDITIVE to add to
        self._taken: tuple[int, int, int, int, int] | None = None
        self.start_cycle = 0
        self._timer_cycle = 0
        self._cali_sync = False
        self._cali_pulse: float | None = None
        # remembered across moves
        self._last_target = round(plant.actual_counts)
        self._last_direction = 1  # decision: MODULO_CURRENT before any move goes positive
        self.drive_time_ms = 0
        self.in_target = False
        self.error = False
        self.calibrated = False
        self.diag = PosDiag.NONE

    @property
    def busy(self) -> bool:
        return self.mode not in _NOT_BUSY

    # --- the cycle's frame --------------------------------------------------------------

    def begin_cycle(self) -> None:
        """A new cycle: no label yet, the phase of the last one remembered, and the
        finishing states advanced (``_advance_transient``)."""
        self.label = None
        self.last_phase = self.phase
        self.phase = _Phase.NONE
        self._advance_transient()

    def end_cycle(self, cycle: int) -> None:
        """The cycle is over: the drive time of a busy move, and a finishing state
        shown for the cycle it was reported in."""
        if self.mode not in _NOT_BUSY:
            self.drive_time_ms = int((cycle - self.start_cycle) * CYCLE_S * 1000)
        if self.mode is _Mode.FINISH and self.label is None:
            self.finish_shown = True

    def enable_seen(self) -> None:
        """The first rising Enable: SET_CALIBRATION_AUTO as the default start type
        calibrates the drive."""
        if self.settings.start_type == StartType.SET_CALIBRATION_AUTO:
            self.calibrated = True

    def driver_off(self) -> None:
        """Enable fell during a move: the move fails, the trajectory is gone (the shaft
        coasts on by itself)."""
        self.velocity = 0.0
        self.diag |= PosDiag.COMMAND_ABORTED
        self.error = True
        self._finish(DriveState.ERROR)

    def emergency_stop(self) -> None:
        """Emergency stop held: a busy move ramps down with the emergency deceleration."""
        if self.mode not in _NOT_BUSY and self.mode not in (_Mode.FINISH, _Mode.EMCY):
            self.diag |= PosDiag.COMMAND_ABORTED
            self.mode = _Mode.EMCY

    def follow_shaft(self) -> None:
        """Unpowered: the setpoint follows the coasting shaft, so that Enable takes it
        over where it is."""
        self.setpoint = self.plant.commanded_counts

    def cruised(self, setpoint: float) -> None:
        """The engine's fast path ran cycles at cruise velocity up to ``setpoint``."""
        self.setpoint = setpoint
        self.last_phase = _Phase.CONST

    # --- commands -----------------------------------------------------------------------

    def start(self, outputs: Outputs, cycle: int, *, enabled: bool, emergency: bool) -> None:
        """A rising Execute while not busy: the start type in ``outputs`` (0: the
        default, 0x8021:01); ``enabled``/``emergency``: the levels of this cycle."""
        self.clear_flags()
        self.start_cycle = cycle
        self.drive_time_ms = 0
        self._taken = self._signature(outputs)
        self.label = DriveState.START
        code = int(outputs.start_type) or self.settings.start_type
        if not enabled:
            self._fail()  # decision: a start without Enable is an error, nothing moves
            return
        if emergency:
            self.diag |= PosDiag.COMMAND_ABORTED
            self.mode = _Mode.EMCY
            return
        try:
            start_type = StartType(code)
        except ValueError:
            self._fail()
            return
        if start_type in CHANGE_START_TYPES:
            # At standstill a plain start is expected (manual).
            self.diag |= PosDiag.COMMAND_REJECTED
            self._finish(DriveState.WARNING)
            return
        if start_type in (StartType.SET_CALIBRATION, StartType.SET_CALIBRATION_AUTO):
            # Decision: SET_CALIBRATION_AUTO sent through the PDO acts like SET_CALIBRATION.
            self.calibrated = True
            self._finish(DriveState.CALIBRATED)
            return
        if start_type is StartType.CLEAR_CALIBRATION:
            self.calibrated = False
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
            self.endless_direction = 1 if start_type is StartType.ENDLESS_PLUS else -1
            self._last_direction = self.endless_direction
            self._has_target = False
            self.mode = _Mode.ENDLESS
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
        self.target = target
        self._has_target = True
        self._last_target = round(target)
        self.margin = EARLY_BRAKING_FRACTION * abs(target - self.setpoint)
        self.braking = False
        self.mode = _Mode.MOVE

    def _set_dynamics(self, outputs: Outputs, velocity_bp: int) -> None:
        self.cruise = velocity_bp / SPEED_RANGE_FULL_SCALE_BP * self.config.full_scale_counts_s
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

    def is_new_change(self, outputs: Outputs) -> bool:
        # Decision: with Execute high, a change is taken when the outputs hold a _CHANGE
        # start type and differ from the command last taken; the same values again are
        # not a new command (so repeat an ADDITIVE_CHANGE by altering something).
        return (
            int(outputs.start_type) in CHANGE_START_TYPES
            and self._signature(outputs) != self._taken
        )

    def change(self, outputs: Outputs) -> None:
        self._taken = self._signature(outputs)
        code = StartType(int(outputs.start_type))
        velocity_bp = min(abs(outputs.velocity_bp), self.settings.velocity_max_bp)
        moving = self.mode in (_Mode.MOVE, _Mode.ENDLESS) and self.velocity != 0.0
        # Rejected at standstill and while accelerating (the braking point is not known
        # yet); decision: also for velocity 0 and, for ADDITIVE_CHANGE, during an
        # ENDLESS move, which has no active target to add to.
        if (
            not moving
            or self.last_phase is _Phase.ACCEL
            or velocity_bp <= 0
            or (code is StartType.ADDITIVE_CHANGE and self.mode is _Mode.ENDLESS)
        ):
            self.diag |= PosDiag.COMMAND_REJECTED
            self.label = DriveState.WARNING
            return
        operand = outputs.target_position_counts
        if code is StartType.ABSOLUTE_CHANGE:
            target: float = operand
        elif code is StartType.RELATIVE_CHANGE:
            target = round(self.plant.actual_counts) + operand
        else:
            target = self.target + operand
        self._set_dynamics(outputs, velocity_bp)
        self._begin_move(target)
        if target != self.setpoint:
            self._last_direction = _sign(target - self.setpoint)
        if self._needs_reversal():
            self.diag |= PosDiag.TARGET_OVERRUN
        self.label = DriveState.TARGET_RESTART

    def _needs_reversal(self) -> bool:
        """True when the new target cannot be reached without passing it and coming back."""
        direction = _sign(self.velocity)
        remaining = self.target - self.setpoint
        speed = abs(self.velocity)
        _, dec = self.rates(direction)
        creep = self.creep()
        if remaining * direction <= 0:
            return not (abs(remaining) <= _EPS_COUNTS and speed <= max(creep, dec * CYCLE_S))
        return speed > creep and (speed * speed - creep * creep) / (2 * dec) > abs(remaining)

    def abort_by_execute(self) -> None:
        if self.mode in _DRIVING and self.mode is not _Mode.HALT:
            if self.mode is not _Mode.ENDLESS:
                self.diag |= PosDiag.COMMAND_ABORTED
            self.mode = _Mode.HALT
        elif self.mode in (_Mode.PRE_TARGET, _Mode.CALI_STOP):
            self.diag |= PosDiag.COMMAND_ABORTED
            self._finish(DriveState.STOP)

    def _start_calibration(self, *, sync: bool) -> None:
        self.label = DriveState.CALI_START
        self.calibrated = False
        self._cali_sync = sync
        self._cali_pulse = None
        self._acc_ms = self._dec_ms = 0  # an aborted calibration ramps with 0x8020 values
        # Decision: starting on the cam skips the search for it.
        self.mode = _Mode.CALI_LEAVE_CAM if self.plant.cam_on else _Mode.CALI_GO_CAM

    def _fail(self) -> None:
        self.error = True
        self._finish(DriveState.ERROR)

    def _finish(self, state: DriveState) -> None:
        self.mode = _Mode.FINISH
        self.finish_state = state
        self.finish_shown = False
        if not self._has_target:
            # Decision: after an ENDLESS move, ADDITIVE adds to where it stopped.
            self._last_target = round(self.plant.actual_counts)
            self._has_target = True

    def clear_flags(self) -> None:
        self.diag = PosDiag.NONE
        self.error = False
        self.in_target = False

    def set_counter(self, value_counts: float) -> None:
        self.plant.set_counter(value_counts)
        self.setpoint = self.plant.commanded_counts
        self.target = self.setpoint
        # Decision: after the counter is set, ADDITIVE counts from the new position.
        self._last_target = round(self.plant.actual_counts)

    # --- motion -------------------------------------------------------------------------

    def _advance_transient(self) -> None:
        # The finishing state (TARGET, STOP, ERROR, ...) is shown for one cycle of its
        # own, also when it was entered in a cycle that reported START.
        if self.mode is _Mode.FINISH:
            if self.finish_shown:
                self.mode = _Mode.END
        elif self.mode is _Mode.END:
            self.mode = _Mode.INIT
        elif self.mode is _Mode.INIT:
            self.mode = _Mode.IDLE

    def advance_motion(self, cycle: int) -> None:
        mode = self.mode
        if mode is _Mode.MOVE:
            self._advance_move(cycle)
        elif mode is _Mode.ENDLESS:
            self._advance_endless()
        elif mode is _Mode.HALT:
            _, dec = self.rates(_sign(self.velocity))
            self._ramp_to_standstill(dec)
        elif mode is _Mode.EMCY:
            self._ramp_to_standstill(self._rate(self.settings.emergency_deceleration_ms))
        elif mode is _Mode.PRE_TARGET:
            self._settle(cycle)
        elif mode in _CALIBRATION_SEARCH:
            self._advance_calibration()
        elif mode is _Mode.CALI_STOP:
            self._finish_calibration(cycle)

    def _rate(self, ramp_ms: int) -> float:
        """counts/s^2 of a ramp that takes ``ramp_ms`` for 100 % of the speed range."""
        if ramp_ms <= 0:
            return math.inf
        return self.config.full_scale_counts_s / (ramp_ms / 1000)

    def rates(self, direction: int) -> tuple[float, float]:
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

    def creep(self) -> float:
        # Decision: Velocity min. 0 creeps at 1 bp, or a move braked 0.5 % early would
        # never arrive; a move slower than Velocity min. creeps at its own velocity.
        velocity_min_bp = max(self.settings.velocity_min_bp, 1)
        creep = velocity_min_bp / SPEED_RANGE_FULL_SCALE_BP * self.config.full_scale_counts_s
        return min(creep, self.cruise) if self.cruise > 0 else creep

    def _set_velocity(self, velocity: float) -> None:
        old, new = abs(self.velocity), abs(velocity)
        if new > old:
            self.phase = _Phase.ACCEL
        elif new < old:
            self.phase = _Phase.DECEL
        else:
            self.phase = _Phase.CONST
        self.velocity = velocity
        self.setpoint += velocity * CYCLE_S

    def _advance_move(self, cycle: int) -> None:
        """One cycle of a positioning move towards ``_target``.

        Trapezoid planned online, so changes and reversals need no special profile:
        accelerate while a brake to Velocity min. still fits before the target less the
        0.5 % early-braking margin; else hold; else brake, and once braking never
        accelerate again (no hunting between the two). After the ramp the remaining
        margin is crept at Velocity min., from which the motor may stop abruptly.
        """
        remaining = self.target - self.setpoint
        speed = abs(self.velocity)
        moving = _sign(self.velocity)
        creep = self.creep()
        if abs(remaining) <= _EPS_COUNTS:
            _, dec = self.rates(moving)
            if speed <= max(creep, dec * CYCLE_S):
                self._arrive(cycle)
                return
        direction = _sign(remaining)
        if moving and moving != direction:
            # Past the target (a late change): brake to a standstill, then turn round.
            _, dec = self.rates(moving)
            self.braking = False
            self._set_velocity(moving * max(speed - dec * CYCLE_S, 0.0))
            return
        acc, dec = self.rates(direction)
        distance = abs(remaining)
        margin = self.margin

        def fits(candidate: float) -> bool:
            if candidate <= creep:
                return True
            braking_distance = (candidate * candidate - creep * creep) / (2 * dec)
            return distance - candidate * CYCLE_S - margin >= braking_distance

        if self.braking:
            new_speed = max(speed - dec * CYCLE_S, creep)
        elif speed > self.cruise:
            # a change lowered the velocity: ramp down to it, or brake if that is due
            new_speed = max(speed - dec * CYCLE_S, self.cruise)
            if not fits(new_speed):
                self.braking = True
                new_speed = max(speed - dec * CYCLE_S, creep)
        else:
            accelerated = min(speed + acc * CYCLE_S, self.cruise)
            if accelerated > speed and fits(accelerated):
                new_speed = accelerated
            elif speed >= creep and fits(speed):
                new_speed = speed
            else:
                self.braking = speed > creep
                new_speed = max(speed - dec * CYCLE_S, creep)
        if new_speed * CYCLE_S >= distance and new_speed <= max(creep, dec * CYCLE_S):
            self._arrive(cycle)
            return
        self._set_velocity(direction * new_speed)

    def _arrive(self, cycle: int) -> None:
        self.setpoint = self.target
        self.velocity = 0.0
        self.mode = _Mode.PRE_TARGET
        self._timer_cycle = cycle

    def _settle(self, cycle: int) -> None:
        # "In-Target" needs the actual position in the window within the timeout
        # (the ideal plant is at standstill as soon as the setpoint is).
        error = abs(self.plant.actual_counts - self.target)
        if error <= self.settings.target_window_counts:
            self.in_target = True
            self._finish(DriveState.TARGET)
        elif self._elapsed_ms(self._timer_cycle, cycle) >= self.settings.in_target_timeout_ms:
            self.mode = _Mode.END  # only the falling Busy tells (manual)

    def _advance_endless(self) -> None:
        direction = self.endless_direction
        speed = abs(self.velocity)
        acc, dec = self.rates(direction)
        if speed < self.cruise:
            new_speed = min(speed + acc * CYCLE_S, self.cruise)
        else:
            new_speed = max(speed - dec * CYCLE_S, self.cruise)
        self._set_velocity(direction * new_speed)

    def _ramp_to_standstill(self, dec: float) -> None:
        if self.velocity == 0.0:
            self._finish(DriveState.STOP)
            self.target = self.setpoint
            return
        moving = _sign(self.velocity)
        self._set_velocity(moving * max(abs(self.velocity) - dec * CYCLE_S, 0.0))

    @staticmethod
    def _elapsed_ms(since_cycle: int, cycle: int) -> float:
        return (cycle - since_cycle) * CYCLE_S * 1000

    # --- calibration --------------------------------------------------------------------

    def _advance_calibration(self) -> None:
        # Decision: calibration runs at its two creep velocities without ramps: they
        # are meant to be slow enough to start and stop abruptly, like Velocity min.
        s = self.settings
        scale = self.config.full_scale_counts_s / SPEED_RANGE_FULL_SCALE_BP
        if self.mode is _Mode.CALI_GO_CAM:
            direction = -1 if s.invert_calibration_cam_search else 1
            speed = abs(s.calibration_velocity_towards_cam_bp) * scale
        else:
            direction = -1 if s.invert_sync_impulse_search else 1
            speed = abs(s.calibration_velocity_off_cam_bp) * scale
        self.velocity = direction * speed
        self.setpoint += self.velocity * CYCLE_S

    def watch_calibration_sensors(self, pulse: float | None, cycle: int) -> None:
        # The cam input is polled once a cycle (the manual's systematic error); the
        # C-track pulse position comes latched by hardware.
        if self.mode is _Mode.CALI_GO_CAM and self.plant.cam_on:
            self.mode = _Mode.CALI_LEAVE_CAM
            self.label = DriveState.CALI_ON_CAM
        elif self.mode is _Mode.CALI_LEAVE_CAM and not self.plant.cam_on:
            if self._cali_sync:
                self.mode = _Mode.CALI_GO_SYNC
            else:
                self._stop_calibration_drive(cycle)
        elif self.mode is _Mode.CALI_GO_SYNC and pulse is not None:
            self._cali_pulse = pulse
            self._stop_calibration_drive(cycle)

    def _stop_calibration_drive(self, cycle: int) -> None:
        self.velocity = 0.0
        self.mode = _Mode.CALI_STOP
        self._timer_cycle = cycle

    def _finish_calibration(self, cycle: int) -> None:
        self.velocity = 0.0
        if self._elapsed_ms(self._timer_cycle, cycle) < self.settings.in_target_timeout_ms:
            return
        value = float(self.settings.calibration_position_counts)
        if self._cali_pulse is not None:
            # Decision: with the C track the calibration position belongs to the pulse
            # itself, not to where the motor came to rest a fraction of a cycle later;
            # that is what makes this calibration the accurate one.
            value += self.plant.actual_counts - self._cali_pulse
        self.set_counter(value)
        self.calibrated = True
        self._finish(DriveState.CALIBRATED)
