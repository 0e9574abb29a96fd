"""EP7047-1032 positioning engine (sans-IO): the drive's motion controller, one cycle a call.

Source: ``shared/spec/ep7047.md`` and the vendor manual. :class:`Ep7047Engine` is what
sits behind the "Positioning interface" process data: ``step(outputs) -> inputs``
advances it by one 250 us controller cycle. It is pure and deterministic (no clock, no
randomness), so a simulator can drive it from any loop and tests can replay it exactly.
:class:`StepperPlant` is the minimal mechanics it moves: an ideal stepper that follows
the setpoint, with an optional encoder offset, a calibration cam and a C-track pulse.

Decisions where the spec and the manual are silent are written next to the code and
listed in ``docs/ep7047.md``.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, replace
from typing import Any

from servotune.protocols.ep7047 import (
    CHANGE_START_TYPES,
    CYCLE_S,
    DIAG_COMMAND_ABORTED,
    DIAG_COMMAND_REJECTED,
    DIAG_TARGET_OVERRUN,
    DRIVE_STATE,
    INT16_MAX,
    INT16_MIN,
    MODULO_START_TYPES,
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
    StartType,
    StmControl,
    StmStatus,
    enc_status_of,
    encode_sdo,
    pos_status_of,
    stm_status_of,
    wrap_int32,
)

# Share of the move distance by which braking starts early (manual: 0.5 %); the rest is
# crept at Velocity min.
EARLY_BRAKING_FRACTION = 0.005
_EPS_COUNTS = 1e-6

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


@dataclass(slots=True)
class StepperPlant:
    """An ideal stepper: the shaft follows the engine's setpoint exactly, every cycle.

    Two frames: ``shaft_counts`` is the machine's fixed frame, where the cam and the
    C-track marks are; the counter (what the drive reports) reads
    ``shaft + counter_shift + encoder_offset``. ``counter_shift_counts`` changes when
    the counter is set (calibration, ENC "Set counter"). ``encoder_offset_counts``
    models what a real drive cannot pull in - lost steps, a slipped encoder: the actual
    position stays that far from the setpoint, which is how a test makes In-Target fail.

    ``cam_counts`` is the shaft interval [low, high] on which the cam (digital input 1)
    is on; ``sync_period_counts`` > 0 puts a C-track pulse at ``sync_phase_counts`` plus
    every whole period.
    """

    shaft_counts: float = 0.0
    encoder_offset_counts: float = 0.0
    cam_counts: tuple[float, float] | None = None
    sync_period_counts: float = 0.0
    sync_phase_counts: float = 0.0
    counter_shift_counts: float = 0.0

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


class ModuloError(ValueError):
    """A modulo start the drive refuses with Error."""


def modulo_travel(
    start_type: StartType,
    start_counts: int,
    target_counts: int,
    modulo_factor_counts: int,
    window_counts: int,
    last_direction: int,
) -> tuple[int, int]:
    """Relative travel of a modulo move, and the direction it was ordered in (+1/-1).

    ``target_counts`` is a modulo position; each whole ``modulo_factor_counts`` in it
    adds a revolution in PLUS/MINUS/CURRENT. A target equal to the current modulo
    position does not move. Non-_EXT types treat a start within ``window_counts`` past
    the target (in the ordered direction) as standing on it, so they move back by that
    little instead of a whole extra turn; _EXT types ignore the window. CURRENT uses
    ``last_direction``. Raises :class:`ModuloError` for a modulo factor <= 0, a negative
    target, or a SHORT target outside [0, modulo factor).

    Decisions (manual silent): the window is closed (a start exactly ``window`` past the
    target is inside); SHORT picks the positive direction on an exact half turn; SHORT
    and SHORT_EXT behave alike, because the shortest way never costs a whole turn.
    """
    m = modulo_factor_counts
    if m <= 0:
        raise ModuloError("modulo factor (0x8020:0E) is not set")
    if target_counts < 0:
        raise ModuloError(f"modulo target {target_counts} is negative")
    revolutions, target_mod = divmod(target_counts, m)
    start_mod = start_counts % m
    base = start_type & ~0x0010  # the _EXT bit
    window = 0 if start_type & 0x0010 else window_counts
    if base == StartType.MODULO_SHORT:
        if revolutions:
            raise ModuloError(f"MODULO_SHORT target {target_counts} is not below {m}")
        ahead = (target_mod - start_mod) % m
        if ahead == 0:
            return 0, last_direction
        return (ahead, 1) if ahead <= m - ahead else (ahead - m, -1)
    if base == StartType.MODULO_PLUS:
        direction = 1
    elif base == StartType.MODULO_MINUS:
        direction = -1
    else:
        direction = last_direction
    # distance still to go in the ordered direction, within one turn
    to_go = ((target_mod - start_mod) * direction) % m
    if to_go and m - to_go <= window:
        to_go -= m  # just past the target: step back instead of a whole turn
    return direction * (to_go + revolutions * m), direction


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
_NOT_BUSY = (_Mode.IDLE, _Mode.INIT, _Mode.END)
_DRIVING = (
    _Mode.MOVE,
    _Mode.ENDLESS,
    _Mode.HALT,
    _Mode.CALI_GO_CAM,
    _Mode.CALI_LEAVE_CAM,
    _Mode.CALI_GO_SYNC,
)
_SETTING_NAMES = {obj: name for name, obj in POS_SETTINGS_SDO.items()}
_CALIBRATION_SEARCH = (_Mode.CALI_GO_CAM, _Mode.CALI_LEAVE_CAM, _Mode.CALI_GO_SYNC)
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


class _Phase(enum.Enum):
    NONE = enum.auto()
    ACCEL = enum.auto()
    CONST = enum.auto()
    DECEL = enum.auto()


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


def _sign(value: float) -> int:
    return (value > 0) - (value < 0)


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
        self.settings = settings if settings is not None else PosSettings()
        self.config = config if config is not None else DriveConfig()
        self.plant = plant if plant is not None else StepperPlant()
        self.cycles = 0
        self._setpoint = self.plant.commanded_counts
        self._velocity = 0.0  # counts/s, signed
        self._mode = _Mode.INIT
        self._finish_state = DriveState.END
        self._finish_shown = False
        self._label: DriveState | None = None
        self._phase = _Phase.NONE
        self._last_phase = _Phase.NONE
        # the running move
        self._target = self._setpoint
        self._cruise = 0.0
        self._acc_ms = 0
        self._dec_ms = 0
        self._margin = 0.0
        self._braking = False
        self._endless_direction = 0
        self._has_target = True  # False while ENDLESS: nothing for ADDITIVE to add to
        self._taken: tuple[int, int, int, int, int] | None = None
        self._start_cycle = 0
        self._timer_cycle = 0
        self._cali_sync = False
        self._cali_pulse: float | None = None
        # remembered across moves
        self._last_target = round(self.plant.actual_counts)
        self._last_direction = 1  # decision: MODULO_CURRENT before any move goes positive
        self._drive_time_ms = 0
        self._in_target = False
        self._error = False
        self._calibrated = False
        self._diag = PosDiag.NONE
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
    def time_s(self) -> float:
        """Controller time: cycles stepped so far times 250 us."""
        return self.cycles * CYCLE_S

    @property
    def state(self) -> DriveState:
        """0x9020:03 as of the last step."""
        if self._label is not None:
            return self._label
        if self._mode is _Mode.FINISH:
            return self._finish_state
        if self._mode in (_Mode.MOVE, _Mode.ENDLESS, _Mode.HALT):
            return _PHASE_STATE[self._phase]
        return _MODE_STATE[self._mode]

    @property
    def diag(self) -> PosDiag:
        """0x9020:01 (= 0xA020:01..03)."""
        return self._diag

    @property
    def setpoint_counts(self) -> float:
        return self._setpoint

    @property
    def velocity_counts_s(self) -> float:
        """Setpoint velocity of the last cycle, signed."""
        return self._velocity

    @property
    def busy(self) -> bool:
        return self._mode not in _NOT_BUSY

    def read_sdo(self, obj: SdoObject) -> int:
        """The value of a 0x8020/0x8021 setting or a 0x9020/0xA020 entry.

        Raises KeyError for objects the engine does not hold.
        """
        name = _SETTING_NAMES.get(obj)  # a dict: the drive state is read every 10 ms
        if name is not None:
            return int(getattr(self.settings, name))
        if obj == POS_STATUS_WORD:
            return int(self._diag)
        if obj == DRIVE_STATE:
            return int(self.state)
        if obj in _DIAG_SDO:
            return int(bool(self._diag & _DIAG_SDO[obj]))
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
        simulator's CPU (profiled: ~9 us each against ~1 us here).
        """
        mode = self._mode
        velocity = self._velocity
        if (
            (mode is not _Mode.ENDLESS and mode is not _Mode.MOVE)
            or velocity == 0.0
            or abs(velocity) != self._cruise
            or self._phase is not _Phase.CONST
            or self._label is not None
            or self._pulse_seen
            or self._braking
        ):
            return 0
        previous = self._prev_outputs
        if previous is None or (previous is not outputs and previous != outputs):
            return 0
        if (
            not int(outputs.pos_control) & _EXECUTE
            or not int(outputs.stm_control) & _ENABLE
            or self._emergency
            or self._is_new_change(outputs)
        ):
            return 0
        speed = abs(velocity)
        direction = _sign(velocity)
        if mode is _Mode.ENDLESS and direction != self._endless_direction:
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
        setpoint = self._setpoint
        done = 0
        if mode is _Mode.ENDLESS:
            while done < limit:
                if abs(pulse_ahead - (setpoint - shift)) <= reach:
                    break
                setpoint += step
                done += 1
        else:
            target = self._target
            creep = self._creep()
            _, dec = self._rates(direction)
            margin = self._margin
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
            self._setpoint = setpoint
            self._last_phase = _Phase.CONST
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
        if (
            self._mode is not _Mode.IDLE
            or self._velocity != 0.0
            or self._label is not None
            or self._phase is not _Phase.NONE
            or self._last_phase is not _Phase.NONE
            or self._pulse_seen
        ):
            return False
        previous = self._prev_outputs
        if previous is None or (previous is not outputs and previous != outputs):
            return False
        return not (int(outputs.pos_control) & _EXECUTE and self._is_new_change(outputs))

    def _cycle(self, outputs: Outputs) -> None:
        """One 250 us cycle with ``outputs`` applied (the inputs are computed apart)."""
        self.cycles += 1
        self._label = None
        self._last_phase = self._phase
        self._phase = _Phase.NONE
        self._pulse_seen = False
        self._advance_transient()

        # Plain ints for the bit tests: IntFlag operators cost microseconds each.
        stm = int(outputs.stm_control)
        pos = int(outputs.pos_control)
        enc = int(outputs.enc_control)
        enable = bool(stm & _ENABLE)
        reset = bool(stm & _RESET)
        execute = bool(pos & _EXECUTE)
        self._emergency = bool(pos & _EMERGENCY_STOP)
        set_counter = bool(enc & _SET_COUNTER)
        latch_enabled = bool(enc & _ENABLE_LATCH_C)
        self._enabled = enable

        if enable and not self._prev_enable and not self._enable_seen:
            self._enable_seen = True
            if self.settings.start_type == StartType.SET_CALIBRATION_AUTO:
                self._calibrated = True
        if not enable and self.busy and self._mode is not _Mode.FINISH:
            # The driver stage switches off: the motor stops where it is, the move fails.
            self._velocity = 0.0
            self._diag |= PosDiag.COMMAND_ABORTED
            self._error = True
            self._finish(DriveState.ERROR)
        if reset and not self._prev_reset and not self.busy:
            self._clear_flags()
        if set_counter and not self._prev_set_counter and not self.busy:
            self._set_counter(outputs.set_counter_counts)
            self._counter_set = True
        elif not set_counter:
            self._counter_set = False
        if not latch_enabled:
            self._latch = None
        if self._emergency and self.busy and self._mode not in (_Mode.FINISH, _Mode.EMCY):
            self._diag |= PosDiag.COMMAND_ABORTED
            self._mode = _Mode.EMCY

        started = False
        if execute and not self._prev_execute:
            if not self.busy:
                self._start(outputs)
                started = True
            # Decision: a rising edge while Busy is ignored; the PLC waits for Busy = 0.
        elif not execute and self._prev_execute:
            self._abort_by_execute()
        elif execute and self._is_new_change(outputs):
            self._change(outputs)

        if not started:
            self._advance_motion()
        pulse = self.plant.follow(self._setpoint)
        if pulse is not None:
            self._pulse_seen = True
            if latch_enabled and self._latch is None:
                self._latch = pulse
        if self._mode in _CALIBRATION_SEARCH:  # the only modes it acts in
            self._watch_calibration_sensors(pulse)

        if self.busy:
            self._drive_time_ms = int((self.cycles - self._start_cycle) * CYCLE_S * 1000)
        if self._mode is _Mode.FINISH and self._label is None:
            self._finish_shown = True
        self._prev_execute = execute
        self._prev_enable = enable
        self._prev_reset = reset
        self._prev_set_counter = set_counter
        self._prev_outputs = outputs

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

    # --- inputs -------------------------------------------------------------------------

    def _inputs(self, outputs: Outputs) -> Inputs:
        busy = self.busy
        pos = 0
        if busy:
            pos |= _POS_BUSY
        if self._in_target:
            pos |= _POS_IN_TARGET
        if self._diag:
            pos |= _POS_WARNING
        if self._error:
            pos |= _POS_ERROR
        if self._calibrated:
            pos |= _POS_CALIBRATED
        if self._phase is _Phase.ACCEL:
            pos |= _POS_ACCELERATE
        elif self._phase is _Phase.DECEL:
            pos |= _POS_DECELERATE
        if self._enabled and not busy and not self._emergency:
            pos |= _POS_READY_TO_EXECUTE

        toggle = self.cycles & 1
        stm = _STM_READY_TO_ENABLE
        if self._enabled:
            stm |= _STM_READY
            if int(outputs.stm_control) & _REDUCE_TORQUE:
                stm |= _STM_TORQUE_REDUCED
        if self._velocity > 0:
            stm |= _STM_MOVING_POSITIVE
        elif self._velocity < 0:
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
        velocity_bp = max(INT16_MIN, min(INT16_MAX, round(self._velocity * scale)))
        return Inputs(
            enc_status=enc_status_of(enc),  # memoised: the plain call costs microseconds
            counter_counts=position,
            latch_counts=wrap_int32(round(self._latch)) if self._latch is not None else 0,
            stm_status=stm_status_of(stm),
            pos_status=pos_status_of(pos),
            actual_position_counts=position,
            actual_velocity_bp=velocity_bp,
            actual_drive_time_ms=self._drive_time_ms,
        )
