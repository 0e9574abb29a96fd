"""EP7047-1032 positioning engine (sans-IO): the drive's motion controller, one cycle a call.

Source: ``shared/spec/ep7047.md`` and the vendor manual. :class:`Ep7047Engine` is what
sits behind the "Positioning interface" process data: ``step(outputs) -> inputs``
advances it by one 250 us controller cycle. It is pure and deterministic (no clock, no
randomness), so a simulator can drive it from any loop and tests can replay it exactly.
:class:`~servotune.devices.ep7047.sim.plant.StepperPlant` is the minimal mechanics it moves: a
stepper that follows the setpoint while Enable is on and coasts on its load's inertia
when it is off, with an optional encoder offset, a calibration cam and a C-track pulse.

The engine is split in three modules. This one is the drive's face: the cycle (edges of
the outputs, :meth:`Ep7047Engine.step`/:meth:`Ep7047Engine.run` and their fast paths),
the read-outs, the SDO objects and the inputs image. What a command does and how the
setpoint moves is ``servotune.devices.ep7047.sim.positioning`` (the engine has a
``Positioning``); the mechanics and the scale are ``servotune.devices.ep7047.sim.plant``.

Decisions where the spec and the manual are silent are written next to the code and
listed in ``docs/ep7047.md``.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

from servotune.devices.ep7047.codec import (
    CYCLE_S,
    DIAG_COMMAND_ABORTED,
    DIAG_COMMAND_REJECTED,
    DIAG_TARGET_OVERRUN,
    DRIVE_STATE,
    INT16_MAX,
    INT16_MIN,
    POS_SETTINGS_SDO,
    POS_STATUS_WORD,
    SPEED_RANGE_FULL_SCALE_BP,
    DataType,
    DriveState,
    EncControl,
    EncStatus,
    Inputs,
    Outputs,
    PosControl,
    PosDiag,
    PosSettings,
    PosStatus,
    SdoObject,
    StmControl,
    StmStatus,
    enc_status_of,
    encode_sdo,
    pos_status_of,
    stm_status_of,
    wrap_int32,
)
from servotune.devices.ep7047.sim.plant import DriveConfig, StepperPlant
from servotune.devices.ep7047.sim.positioning import (
    _CALIBRATION_SEARCH,
    _EPS_COUNTS,
    _NOT_BUSY,
    Positioning,
    _Mode,
    _Phase,
    _sign,
)

# Bits as plain ints for the per-cycle code (see Ep7047Engine._cycle and _inputs).
_POS_BUSY = int(PosStatus.BUSY)
_POS_IN_TARGET = int(PosStatus.IN_TARGET)
_POS_WARNING = int(PosStatus.WARNING)
_POS_ERROR = int(PosStatus.ERROR)
_POS_CALIBRATED = int(PosStatus.CALIBRATED)
_POS_ACCELERATE = int(PosStatus.ACCELERATE)
_POS_DECELERATE = int(PosStatus.DECELERATE)
_POS_READY_TO_EXECUTE = int(PosStatus.READY_TO_EXECUTE)
_STM_READY_TO_ENABLE = int(StmStatus.READY_TO_ENABLE)
_STM_READY = int(StmStatus.READY)
_STM_TORQUE_REDUCED = int(StmStatus.TORQUE_REDUCED)
_STM_MOVING_POSITIVE = int(StmStatus.MOVING_POSITIVE)
_STM_MOVING_NEGATIVE = int(StmStatus.MOVING_NEGATIVE)
_STM_DIGITAL_INPUT_1 = int(StmStatus.DIGITAL_INPUT_1)
_STM_TXPDO_TOGGLE = int(StmStatus.TXPDO_TOGGLE)
_ENC_LATCH_C_VALID = int(EncStatus.LATCH_C_VALID)
_ENC_SET_COUNTER_DONE = int(EncStatus.SET_COUNTER_DONE)
_ENC_INPUT_C = int(EncStatus.INPUT_C)
_ENC_TXPDO_TOGGLE = int(EncStatus.TXPDO_TOGGLE)
_ENABLE = int(StmControl.ENABLE)
_RESET = int(StmControl.RESET)
_REDUCE_TORQUE = int(StmControl.REDUCE_TORQUE)
_EXECUTE = int(PosControl.EXECUTE)
_EMERGENCY_STOP = int(PosControl.EMERGENCY_STOP)
_SET_COUNTER = int(EncControl.SET_COUNTER)
_ENABLE_LATCH_C = int(EncControl.ENABLE_LATCH_C)

# Tuples, not sets: ``in`` a tuple compares by identity first, ``in`` a set hashes the
# member with Enum.__hash__, a Python-level call (several per 250 us cycle).
_SETTING_NAMES = {obj: name for name, obj in POS_SETTINGS_SDO.items()}
_MODE_STATE = {
    _Mode.IDLE: DriveState.IDLE,
    _Mode.INIT: DriveState.INIT,
    _Mode.END: DriveState.END,
    _Mode.EMCY: DriveState.EMCY,
    _Mode.PRE_TARGET: DriveState.PRE_TARGET,
    _Mode.CALI_GO_CAM: DriveState.CALI_GO_CAM,
    _Mode.CALI_LEAVE_CAM: DriveState.CALI_LEAVE_CAM,
    _Mode.CALI_GO_SYNC: DriveState.CALI_GO_SYNC,
    _Mode.CALI_STOP: DriveState.CALI_STOP,
}


_PHASE_STATE = {
    _Phase.ACCEL: DriveState.ACCEL,
    _Phase.CONST: DriveState.CONST,
    _Phase.DECEL: DriveState.DECEL,
    _Phase.NONE: DriveState.CONST,
}

_DIAG_SDO = {
    DIAG_COMMAND_REJECTED: PosDiag.COMMAND_REJECTED,
    DIAG_COMMAND_ABORTED: PosDiag.COMMAND_ABORTED,
    DIAG_TARGET_OVERRUN: PosDiag.TARGET_OVERRUN,
}


class Ep7047Engine:
    """The positioning interface of one EP7047-1032, stepped one 250 us cycle at a time.

    Contract: ``step(outputs)`` takes the decoded outputs the master wrote for this
    cycle and returns the decoded inputs the drive shows after it; nothing else moves
    the engine, so equal output sequences give equal input sequences. ``settings``
    (0x8020/0x8021) may be replaced between steps and is read live; ``config`` and the
    plant are fixed at construction (the plant's cam/sync/offset may be edited).

    Behaviour in one paragraph: a rising edge of Execute starts the start type in the
    outputs (0 selects the default 0x8021:01); Busy rises in that cycle and falls
    when the move has ended; In-Target is set when the actual position settles in the
    target window within the In-Target timeout. With Execute held high, writing a
    _CHANGE start type (or new values with one) changes the running move. Execute
    falling while Busy ramps the move down and sets Command aborted (except for an
    ENDLESS move, which is stopped that way); Emergency stop ramps down with the
    emergency deceleration and sets Command aborted. Warning is set whenever a
    diagnosis bit (0x9020:01) is; diagnosis, Warning, Error and In-Target are cleared by
    the next start or by a rising edge of STM Reset while not Busy.
    """

    def __init__(
        self,
        settings: PosSettings | None = None,
        config: DriveConfig | None = None,
        plant: StepperPlant | None = None,
    ) -> None:
        config = config if config is not None else DriveConfig()
        plant = plant if plant is not None else StepperPlant()
        self.config = config
        self.plant = plant
        self.positioning = Positioning(
            settings if settings is not None else PosSettings(), config, plant
        )
        self.cycles = 0
        self._latch: float | None = None
        self._counter_set = False
        self._pulse_seen = False
        # edge detection
        self._prev_execute = False
        self._prev_enable = False
        self._prev_reset = False
        self._prev_set_counter = False
        self._prev_outputs: Outputs | None = None  # those of the last cycle
        self._enable_seen = False
        self._enabled = False
        self._emergency = False

    # --- public read-outs ---------------------------------------------------------------

    @property
    def settings(self) -> PosSettings:
        """0x8020/0x8021 as in force (``Positioning.settings``)."""
        return self.positioning.settings

    @settings.setter
    def settings(self, settings: PosSettings) -> None:
        self.positioning.settings = settings

    @property
    def time_s(self) -> float:
        """Controller time: cycles stepped so far times 250 us."""
        return self.cycles * CYCLE_S

    @property
    def state(self) -> DriveState:
        """0x9020:03 as of the last step."""
        pos = self.positioning
        if pos.label is not None:
            return pos.label
        if pos.mode is _Mode.FINISH:
            return pos.finish_state
        if pos.mode in (_Mode.MOVE, _Mode.ENDLESS, _Mode.HALT):
            return _PHASE_STATE[pos.phase]
        return _MODE_STATE[pos.mode]

    @property
    def diag(self) -> PosDiag:
        """0x9020:01 (= 0xA020:01..03)."""
        return self.positioning.diag

    @property
    def setpoint_counts(self) -> float:
        return self.positioning.setpoint

    @property
    def velocity_counts_s(self) -> float:
        """Setpoint velocity of the last cycle, signed."""
        return self.positioning.velocity

    @property
    def busy(self) -> bool:
        return self.positioning.mode not in _NOT_BUSY

    def read_sdo(self, obj: SdoObject) -> int:
        """The value of a 0x8020/0x8021 setting or a 0x9020/0xA020 entry.

        Raises KeyError for objects the engine does not hold.
        """
        name = _SETTING_NAMES.get(obj)  # a dict: the drive state is read every 10 ms
        if name is not None:
            return int(getattr(self.settings, name))
        if obj == POS_STATUS_WORD:
            return int(self.positioning.diag)
        if obj == DRIVE_STATE:
            return int(self.state)
        if obj in _DIAG_SDO:
            return int(bool(self.positioning.diag & _DIAG_SDO[obj]))
        raise KeyError(f"0x{obj.index:04X}:{obj.subindex:02X} is not held by the engine")

    def write_sdo(self, obj: SdoObject, value: int) -> None:
        """Write a 0x8020/0x8021 setting; it applies from the next cycle.

        Raises KeyError for other objects and CodecError for a value out of range.
        """
        for name, setting in POS_SETTINGS_SDO.items():
            if setting == obj:
                encode_sdo(obj, value)  # range check only
                typed: int | bool = bool(value) if obj.data_type is DataType.BOOLEAN else value
                changes: dict[str, Any] = {name: typed}
                self.settings = replace(self.settings, **changes)
                return
        raise KeyError(f"0x{obj.index:04X}:{obj.subindex:02X} cannot be written")

    # --- the cycle ----------------------------------------------------------------------

    def step(self, outputs: Outputs) -> Inputs:
        """Advance one 250 us cycle with ``outputs`` applied; return the inputs after it."""
        self._cycle(outputs)
        return self._inputs(outputs)

    def run(self, outputs: Outputs, cycles: int) -> Inputs:
        """Advance ``cycles`` (>= 1) cycles with the same ``outputs``; the inputs after the
        last one.

        Exactly what ``cycles`` calls of :meth:`step` would do (tests compare the two),
        but cheaper: the inputs are only computed once, and a quiet stretch - the drive
        idle and the outputs the same as in the cycle before (see :meth:`_quiescent`) -
        is skipped in one go instead of cycle by cycle, because nothing but the cycle
        counter changes in it. A simulator that is polled every 2 ms with unchanged
        outputs then costs one cycle per exchange instead of eight.
        """
        if cycles < 1:
            raise ValueError(f"cycles must be at least 1, got {cycles}")
        remaining = cycles
        while remaining > 1:
            if self._quiescent(outputs):
                self.cycles += remaining - 1
                break
            cruised = self._cruise_cycles(outputs, remaining - 1)
            if cruised:
                remaining -= cruised
                continue
            self._cycle(outputs)
            remaining -= 1
        self._cycle(outputs)
        return self._inputs(outputs)

    def _cruise_cycles(self, outputs: Outputs, limit: int) -> int:
        """Run up to ``limit`` cycles of a move at constant velocity in a tight loop;
        returns how many (0: not cruising, run :meth:`_cycle`).

        Exactly what :meth:`_cycle` would do (``test_run_equals_stepping_cycle_by_cycle``
        compares every field): it applies only to an ENDLESS move or a positioning move
        at its cruise velocity, Execute high, the same outputs as in the cycle before
        and no _CHANGE to take - so no edge, no level-driven assignment and no timer
        can act - and it stops before the first cycle that would do anything but add
        ``velocity * CYCLE_S`` to the setpoint: a C-track pulse within reach, the
        braking point (the ``fits`` test of :meth:`_advance_move`, here with the
        constants of the stretch), the arrival. The same float additions in the same
        order, so the setpoint comes out bit for bit. Why: the demo's axis moves most
        of the time, and eight full cycles per 2 ms exchange were most of the
        simulator's CPU (docs/ep7047.md has the profile).
        """
        pos = self.positioning
        mode = pos.mode
        velocity = pos.velocity
        if (
            (mode is not _Mode.ENDLESS and mode is not _Mode.MOVE)
            or velocity == 0.0
            or abs(velocity) != pos.cruise
            or pos.phase is not _Phase.CONST
            or pos.label is not None
            or self._pulse_seen
            or pos.braking
        ):
            return 0
        previous = self._prev_outputs
        if previous is None or (previous is not outputs and previous != outputs):
            return 0
        if (
            not int(outputs.pos_control) & _EXECUTE
            or not int(outputs.stm_control) & _ENABLE
            or self._emergency
            or pos.is_new_change(outputs)
        ):
            return 0
        speed = abs(velocity)
        direction = _sign(velocity)
        if mode is _Mode.ENDLESS and direction != pos.endless_direction:
            return 0
        step = velocity * CYCLE_S
        plant = self.plant
        shift = plant.counter_shift_counts
        # The next C-track pulse ahead: the cruise stops a whole step short of it, and
        # the cycle that passes it is a full one (which latches it).
        period = plant.sync_period_counts
        if period > 0:
            phase = plant.sync_phase_counts
            shaft = plant.shaft_counts
            if direction > 0:
                pulse_ahead = phase + (math.floor((shaft - phase) / period) + 1) * period
            else:
                pulse_ahead = phase + (math.ceil((shaft - phase) / period) - 1) * period
        else:
            pulse_ahead = math.inf * direction
        reach = 2 * abs(step)
        setpoint = pos.setpoint
        done = 0
        if mode is _Mode.ENDLESS:
            while done < limit:
                if abs(pulse_ahead - (setpoint - shift)) <= reach:
                    break
                setpoint += step
                done += 1
        else:
            target = pos.target
            creep = pos.creep()
            _, dec = pos.rates(direction)
            margin = pos.margin
            braking_distance = (speed * speed - creep * creep) / (2 * dec)
            arrive_speed = max(creep, dec * CYCLE_S)
            while done < limit:
                remaining = target - setpoint
                distance = abs(remaining)
                if (
                    distance <= _EPS_COUNTS * 2
                    or _sign(remaining) != direction
                    or speed < creep
                    or (speed > creep and distance - speed * CYCLE_S - margin < braking_distance)
                    or (speed * CYCLE_S >= distance and speed <= arrive_speed)
                    or abs(pulse_ahead - (setpoint - shift)) <= reach
                ):
                    break
                setpoint += step
                done += 1
        if done:
            self.cycles += done
            pos.cruised(setpoint)
            self._prev_outputs = outputs
            plant.shaft_counts = setpoint - shift
        return done

    def _quiescent(self, outputs: Outputs) -> bool:
        """True when a cycle with ``outputs`` would change nothing but ``cycles``.

        That holds in IDLE at standstill with the same outputs as in the cycle before:
        no edge of Execute, Enable, Reset or Set counter can occur, every level-driven
        assignment of :meth:`_cycle` (latch cleared, counter-set flag, Emergency,
        Enable) already happened in that cycle, the setpoint stands still (no C-track
        pulse), no timer runs in IDLE, and a _CHANGE start type that differs from the
        command last taken (which a cycle would reject and then remember) is excluded.
        The one thing a skipped cycle would alter, the TxPDO toggle bit, follows
        ``cycles`` and comes out right in the cycle that is computed.
        """
        pos = self.positioning
        if (
            pos.mode is not _Mode.IDLE
            or pos.velocity != 0.0
            or self.plant.speed_counts_s != 0.0  # a shaft coasting unpowered
            or pos.label is not None
            or pos.phase is not _Phase.NONE
            or pos.last_phase is not _Phase.NONE
            or self._pulse_seen
        ):
            return False
        previous = self._prev_outputs
        if previous is None or (previous is not outputs and previous != outputs):
            return False
        return not (int(outputs.pos_control) & _EXECUTE and pos.is_new_change(outputs))

    def _cycle(self, outputs: Outputs) -> None:
        """One 250 us cycle with ``outputs`` applied (the inputs are computed apart)."""
        pos = self.positioning
        self.cycles += 1
        cycle = self.cycles
        self._pulse_seen = False
        pos.begin_cycle()

        # Plain ints for the bit tests: IntFlag operators cost microseconds each.
        stm = int(outputs.stm_control)
        posc = int(outputs.pos_control)
        enc = int(outputs.enc_control)
        enable = bool(stm & _ENABLE)
        reset = bool(stm & _RESET)
        execute = bool(posc & _EXECUTE)
        self._emergency = bool(posc & _EMERGENCY_STOP)
        set_counter = bool(enc & _SET_COUNTER)
        latch_enabled = bool(enc & _ENABLE_LATCH_C)
        self._enabled = enable

        if enable and not self._prev_enable and not self._enable_seen:
            self._enable_seen = True
            pos.enable_seen()
        if not enable and pos.busy and pos.mode is not _Mode.FINISH:
            # The driver stage switches off: the move fails, the trajectory is gone (the
            # shaft coasts on by itself, below).
            pos.driver_off()
        if reset and not self._prev_reset and not pos.busy:
            pos.clear_flags()
        if set_counter and not self._prev_set_counter and not pos.busy:
            pos.set_counter(outputs.set_counter_counts)
            self._counter_set = True
        elif not set_counter:
            self._counter_set = False
        if not latch_enabled:
            self._latch = None
        if self._emergency:
            pos.emergency_stop()

        started = False
        if execute and not self._prev_execute:
            if not pos.busy:
                pos.start(outputs, cycle, enabled=enable, emergency=self._emergency)
                started = True
            # Decision: a rising edge while Busy is ignored; the PLC waits for Busy = 0.
        elif not execute and self._prev_execute:
            pos.abort_by_execute()
        elif execute and pos.is_new_change(outputs):
            pos.change(outputs)

        if not started:
            pos.advance_motion(cycle)
        plant = self.plant
        if enable:
            pulse = plant.follow(pos.setpoint)
            plant.speed_counts_s = pos.velocity
        else:
            # Unpowered: nothing holds the shaft; it coasts on its own inertia and the
            # setpoint follows it, so that Enable takes it over where it is (decision:
            # the drive catches a shaft that still turns without a jump).
            pulse = plant.coast(CYCLE_S)
            pos.follow_shaft()
        if pulse is not None:
            self._pulse_seen = True
            if latch_enabled and self._latch is None:
                self._latch = pulse
        if pos.mode in _CALIBRATION_SEARCH:  # the only modes it acts in
            pos.watch_calibration_sensors(pulse, cycle)

        pos.end_cycle(cycle)
        self._prev_execute = execute
        self._prev_enable = enable
        self._prev_reset = reset
        self._prev_set_counter = set_counter
        self._prev_outputs = outputs

    # --- inputs -------------------------------------------------------------------------

    def _inputs(self, outputs: Outputs) -> Inputs:
        part = self.positioning
        busy = part.mode not in _NOT_BUSY
        pos = 0
        if busy:
            pos |= _POS_BUSY
        if part.in_target:
            pos |= _POS_IN_TARGET
        if part.diag:
            pos |= _POS_WARNING
        if part.error:
            pos |= _POS_ERROR
        if part.calibrated:
            pos |= _POS_CALIBRATED
        if part.phase is _Phase.ACCEL:
            pos |= _POS_ACCELERATE
        elif part.phase is _Phase.DECEL:
            pos |= _POS_DECELERATE
        if self._enabled and not busy and not self._emergency:
            pos |= _POS_READY_TO_EXECUTE

        toggle = self.cycles & 1
        stm = _STM_READY_TO_ENABLE
        if self._enabled:
            stm |= _STM_READY
            if int(outputs.stm_control) & _REDUCE_TORQUE:
                stm |= _STM_TORQUE_REDUCED
        velocity = part.velocity
        if velocity > 0:
            stm |= _STM_MOVING_POSITIVE
        elif velocity < 0:
            stm |= _STM_MOVING_NEGATIVE
        if self.plant.cam_on:
            stm |= _STM_DIGITAL_INPUT_1
        if toggle:
            stm |= _STM_TXPDO_TOGGLE

        enc = 0
        if self._latch is not None:
            enc |= _ENC_LATCH_C_VALID
        if self._counter_set:
            enc |= _ENC_SET_COUNTER_DONE
        if self._pulse_seen:
            enc |= _ENC_INPUT_C
        if toggle:
            enc |= _ENC_TXPDO_TOGGLE

        position = wrap_int32(round(self.plant.actual_counts))
        scale = SPEED_RANGE_FULL_SCALE_BP / self.config.full_scale_counts_s
        velocity_bp = max(INT16_MIN, min(INT16_MAX, round(velocity * scale)))
        return Inputs(
            enc_status=enc_status_of(enc),  # memoised: the plain call costs microseconds
            counter_counts=position,
            latch_counts=wrap_int32(round(self._latch)) if self._latch is not None else 0,
            stm_status=stm_status_of(stm),
            pos_status=pos_status_of(pos),
            actual_position_counts=position,
            actual_velocity_bp=velocity_bp,
            actual_drive_time_ms=part.drive_time_ms,
        )
