"""EP7047-1032 positioning engine: the manual's tables and examples, and the decisions.

Modulo moves run in counts with 3600 counts per turn, so the manual's degrees (with
two decimals, all multiples of 0.1°) become exact integers: 90.90° = 909 counts.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from typing import NamedTuple

import pytest
from scipy.integrate import solve_ivp

from servotune.devices.ep7047 import codec
from servotune.devices.ep7047.codec import (
    CYCLE_S,
    DriveState,
    EncControl,
    Inputs,
    Outputs,
    PosControl,
    PosDiag,
    PosSettings,
    PosStatus,
    StartType,
    StmControl,
    StmStatus,
)
from servotune.devices.ep7047.modulo import modulo_travel
from servotune.devices.ep7047.sim.engine import Ep7047Engine
from servotune.devices.ep7047.sim.plant import DEMO_MECHANICS, DriveConfig, Mechanics, StepperPlant
from servotune.devices.ep7047.sim.slave import DEMO_FULL_STEPS_PER_REV, DEMO_SETTINGS
from tests.support.ep7047_cases import ModuloCase, load_cases

TURN = 3600  # counts per 360°
# 4000 full steps/s speed range (the spec's example) at 18 counts per full step
# (a 200-step motor with 3600 counts per turn): 10000 bp = 72000 counts/s.
MODULO_CONFIG = DriveConfig(speed_range_steps_s=4000, counts_per_full_step=18)
# For the manual's examples in raw counts: 10000 bp = 256000 counts/s.
FAST_CONFIG = DriveConfig(speed_range_steps_s=4000, counts_per_full_step=64)
# The demo's drive: 2000 full steps/s, 200 steps and 4096 encoder counts a turn.
DEMO_CONFIG = DriveConfig(
    speed_range_steps_s=2000,
    counts_per_full_step=DEMO_MECHANICS.counts_per_rev / DEMO_FULL_STEPS_PER_REV,
)


class Sample(NamedTuple):
    inputs: Inputs
    state: DriveState
    diag: PosDiag
    shaft_counts: float

    def has(self, flag: PosStatus) -> bool:
        return bool(self.inputs.pos_status & flag)

    @property
    def position(self) -> int:
        return self.inputs.actual_position_counts

    @property
    def velocity_bp(self) -> int:
        return self.inputs.actual_velocity_bp


def command(
    start_type: StartType | int,
    target: int = 0,
    *,
    velocity_bp: int = 10000,
    acceleration_ms: int = 100,
    deceleration_ms: int = 100,
    execute: bool = True,
    emergency_stop: bool = False,
    enable: bool = True,
) -> Outputs:
    pos = PosControl.NONE
    if execute:
        pos |= PosControl.EXECUTE
    if emergency_stop:
        pos |= PosControl.EMERGENCY_STOP
    return Outputs(
        stm_control=StmControl.ENABLE if enable else StmControl.NONE,
        pos_control=pos,
        target_position_counts=target,
        velocity_bp=velocity_bp,
        start_type=start_type,
        acceleration_ms=acceleration_ms,
        deceleration_ms=deceleration_ms,
    )


IDLE = Outputs(stm_control=StmControl.ENABLE)


def run(
    engine: Ep7047Engine,
    outputs: Outputs,
    *,
    until: Callable[[Sample], bool] = lambda s: not s.inputs.busy,
    max_cycles: int = 40_000,
) -> list[Sample]:
    """Step with ``outputs`` until ``until`` holds (default: Busy has fallen)."""
    trace: list[Sample] = []
    for _ in range(max_cycles):
        inputs = engine.step(outputs)
        sample = Sample(inputs, engine.state, engine.diag, engine.plant.shaft_counts)
        trace.append(sample)
        if until(sample):
            return trace
    raise AssertionError(f"not done after {max_cycles} cycles; last {trace[-1]}")


def move(engine: Ep7047Engine, outputs: Outputs, max_cycles: int = 40_000) -> list[Sample]:
    """One complete command: Execute low for a cycle, then high until Busy falls."""
    engine.step(IDLE)
    return run(engine, outputs, max_cycles=max_cycles)


def states(trace: list[Sample]) -> list[DriveState]:
    """The states a trace went through, consecutive repeats removed."""
    seen: list[DriveState] = []
    for sample in trace:
        if not seen or seen[-1] != sample.state:
            seen.append(sample.state)
    return seen


def is_subsequence(wanted: list[DriveState], seen: list[DriveState]) -> bool:
    remaining = iter(seen)
    return all(state in remaining for state in wanted)


def modulo_engine(start_counts: int, window_counts: int = 0) -> Ep7047Engine:
    settings = PosSettings(modulo_factor_counts=TURN, modulo_tolerance_window_counts=window_counts)
    return Ep7047Engine(settings, MODULO_CONFIG, StepperPlant(shaft_counts=start_counts))


def assert_clean_arrival(trace: list[Sample], position: int) -> None:
    end = trace[-1]
    assert end.position == position
    assert end.has(PosStatus.IN_TARGET)
    assert not end.has(PosStatus.ERROR) and not end.has(PosStatus.WARNING)


# --- modulo: the manual's tables ------------------------------------------------------------


CASES = load_cases()


def test_the_csv_holds_both_manual_tables() -> None:
    assert len(CASES) == 37
    assert sum(case.window == 10 for case in CASES) == 30


@pytest.mark.parametrize(
    "case",
    CASES,
    ids=[f"{c.start_type.name}-w{c.window}-{c.start}to{c.target}" for c in CASES],
)
def test_modulo_table_row(case: ModuloCase) -> None:
    engine = modulo_engine(case.start, case.window)
    trace = move(engine, command(case.start_type, case.target))

    assert_clean_arrival(trace, case.abs_end)
    assert trace[-1].position - case.start == case.relative
    assert trace[-1].position % TURN == case.mod_end
    velocities = [s.velocity_bp for s in trace]
    if case.relative > 0:
        assert min(velocities) == 0 and max(velocities) > 0
    elif case.relative < 0:
        assert max(velocities) == 0 and min(velocities) < 0
    else:  # "If the target equals the current modulo position, nothing moves."
        assert set(velocities) == {0}
        assert {s.position for s in trace} == {case.start}


# --- modulo: further cases ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("start_type", "start", "target", "window", "end"),
    [
        # negative start positions: -270° is 90° modulo
        (StartType.MODULO_PLUS, -2700, 0, 0, 0),
        (StartType.MODULO_MINUS, -2700, 0, 0, -3600),
        (StartType.MODULO_SHORT, -2700, 0, 0, -3600),
        (StartType.MODULO_PLUS, -3595, 0, 10, -3600),  # 0.5° past 0: back, not a turn
        (StartType.MODULO_MINUS, -3605, 0, 10, -3600),
        # several revolutions
        (StartType.MODULO_PLUS, 900, 3 * TURN + 1800, 0, 3 * TURN + 1800),
        (StartType.MODULO_MINUS, 900, 3 * TURN + 1800, 0, -3 * TURN - 1800),
        (StartType.MODULO_PLUS, 5 * TURN + 900, 2 * TURN + 900, 0, 7 * TURN + 900),
        # _EXT ignores the window: the same starts as the table's in-window rows
        (StartType.MODULO_PLUS_EXT, 909, 900, 10, 4500),
        (StartType.MODULO_MINUS_EXT, 891, 900, 10, -2700),
        (StartType.MODULO_PLUS_EXT, 909, 4500, 10, 8100),
        (StartType.MODULO_SHORT_EXT, 909, 900, 10, 900),
        # decisions: the window is closed; SHORT takes the positive way on a half turn
        (StartType.MODULO_PLUS, 910, 900, 10, 900),
        (StartType.MODULO_PLUS, 911, 900, 10, 4500),
        (StartType.MODULO_SHORT, 0, 1800, 0, 1800),
        (StartType.MODULO_SHORT, 100, 3500, 0, -100),
    ],
    ids=lambda v: v.name if isinstance(v, StartType) else str(v),
)
def test_modulo_more_cases(
    start_type: StartType, start: int, target: int, window: int, end: int
) -> None:
    trace = move(modulo_engine(start, window), command(start_type, target))
    assert_clean_arrival(trace, end)


def test_modulo_current_follows_the_last_direction() -> None:
    engine = modulo_engine(900, window_counts=10)
    assert_clean_arrival(move(engine, command(StartType.ABSOLUTE, 450)), 450)  # negative
    # 90° is 45° ahead, but the last travel was negative: the long way round, negative.
    trace = move(engine, command(StartType.MODULO_CURRENT, 900))
    assert_clean_arrival(trace, -2700)
    assert max(s.velocity_bp for s in trace) == 0
    assert_clean_arrival(move(engine, command(StartType.MODULO_PLUS, 1800)), -1800)
    assert_clean_arrival(move(engine, command(StartType.MODULO_CURRENT, 900)), 900)
    # 0.5° short of the last target: the window steps back, _EXT goes round once more
    assert_clean_arrival(move(engine, command(StartType.MODULO_CURRENT, 895)), 895)
    assert_clean_arrival(move(engine, command(StartType.MODULO_CURRENT_EXT, 890)), 895 + 3595)


def test_modulo_current_keeps_the_ordered_direction_after_a_window_step_back() -> None:
    engine = modulo_engine(909, window_counts=10)
    assert_clean_arrival(move(engine, command(StartType.MODULO_PLUS, 900)), 900)  # moved -9
    assert_clean_arrival(move(engine, command(StartType.MODULO_CURRENT, 1000)), 1000)


def test_modulo_current_before_any_move_goes_positive() -> None:
    trace = move(modulo_engine(900), command(StartType.MODULO_CURRENT, 0))
    assert_clean_arrival(trace, 3600)


@pytest.mark.parametrize("target", [TURN, TURN + 900, -1])
def test_modulo_short_refuses_targets_outside_one_turn(target: int) -> None:
    engine = modulo_engine(900)
    trace = move(engine, command(StartType.MODULO_SHORT, target))
    end = trace[-1]
    assert end.has(PosStatus.ERROR)
    assert not end.has(PosStatus.IN_TARGET)
    assert DriveState.ERROR in states(trace)
    assert {s.position for s in trace} == {900}
    assert len(trace) < 10  # refused at once, Busy fell
    # the next valid start clears the error
    assert_clean_arrival(move(engine, command(StartType.MODULO_SHORT, 1800)), 1800)


def test_modulo_without_a_modulo_factor_is_an_error() -> None:
    engine = Ep7047Engine(PosSettings(), MODULO_CONFIG, StepperPlant(shaft_counts=900))
    trace = move(engine, command(StartType.MODULO_PLUS, 0))
    assert trace[-1].has(PosStatus.ERROR) and trace[-1].position == 900


def test_modulo_travel_directly() -> None:
    assert modulo_travel(StartType.MODULO_MINUS, 891, 900, TURN, 10, 1) == (9, -1)
    assert modulo_travel(StartType.MODULO_CURRENT_EXT, 100, 0, TURN, 10, -1) == (-100, -1)


# --- the manual's dynamic-change examples --------------------------------------------------


def run_change_example(
    first: tuple[int, int, int], change: tuple[int, int, int]
) -> tuple[list[Sample], int]:
    """Start to 200000, change to 100000 once the first ramp-up has ended.

    Returns the trace and the index of the cycle the change was written in.
    """
    velocity, acc, dec = first
    engine = Ep7047Engine(PosSettings(), FAST_CONFIG)
    start = command(
        StartType.ABSOLUTE,
        200000,
        velocity_bp=velocity,
        acceleration_ms=acc,
        deceleration_ms=dec,
    )
    trace = run(engine, start, until=lambda s: s.has(PosStatus.ACCELERATE))
    assert trace[0].has(PosStatus.BUSY)  # t1: Busy = 1 with the Execute edge
    trace += run(engine, start, until=lambda s: not s.has(PosStatus.ACCELERATE))  # t2
    velocity, acc, dec = change
    changed = command(
        StartType.ABSOLUTE_CHANGE,
        100000,
        velocity_bp=velocity,
        acceleration_ms=acc,
        deceleration_ms=dec,
    )
    change_at = len(trace)
    trace += run(engine, changed)
    return trace, change_at


def test_manual_dynamic_change_without_overrun() -> None:
    trace, change_at = run_change_example((2000, 1000, 1000), (1500, 2000, 2000))
    after = trace[change_at:]
    assert after[0].state is DriveState.TARGET_RESTART
    assert not any(s.has(PosStatus.WARNING) for s in trace)
    assert all(s.diag == PosDiag.NONE for s in trace)
    # t4: it decelerates onto the new target, never passing it, never reversing
    assert any(s.has(PosStatus.DECELERATE) for s in after)
    assert max(s.position for s in trace) == 100000
    assert min(s.velocity_bp for s in trace) >= 0
    assert max(s.velocity_bp for s in after[-4000:]) <= 1500  # the new velocity holds
    # t5: Busy 0, In-Target 1, Decelerate 0
    end = trace[-1]
    assert not end.has(PosStatus.BUSY) and end.has(PosStatus.IN_TARGET)
    assert not end.has(PosStatus.DECELERATE)
    assert end.position == 100000


def test_manual_dynamic_change_with_overrun() -> None:
    trace, change_at = run_change_example((5000, 3000, 5000), (1500, 1000, 2000))
    # t3: the change is taken with Warning (Target overrun) and braking starts at once
    at_change = trace[change_at]
    assert at_change.has(PosStatus.WARNING) and at_change.has(PosStatus.DECELERATE)
    assert at_change.diag == PosDiag.TARGET_OVERRUN
    assert at_change.position < 100000  # a warning before passing the target
    after = trace[change_at:]
    assert max(s.position for s in after) > 100000  # overran it ...
    reversal = next(i for i, s in enumerate(after) if s.velocity_bp < 0)
    # t4: end of the first deceleration, acceleration the other way
    assert after[reversal].has(PosStatus.ACCELERATE)
    # t5/t6: decelerates again and arrives, Warning still set
    assert any(s.has(PosStatus.DECELERATE) for s in after[reversal:])
    assert min(s.velocity_bp for s in after) >= -1500
    end = trace[-1]
    assert end.position == 100000
    assert end.has(PosStatus.IN_TARGET) and end.has(PosStatus.WARNING)
    assert not end.has(PosStatus.BUSY) and not end.has(PosStatus.ERROR)


def test_change_during_acceleration_is_rejected_and_the_move_goes_on() -> None:
    engine = Ep7047Engine(PosSettings(), FAST_CONFIG)
    start = command(StartType.ABSOLUTE, 200000, velocity_bp=5000, acceleration_ms=3000)
    trace = run(engine, start, until=lambda s: s.has(PosStatus.ACCELERATE) and s.position > 1000)
    trace += run(engine, command(StartType.ABSOLUTE_CHANGE, 100000, velocity_bp=5000))
    rejected = next(s for s in trace if s.has(PosStatus.WARNING))
    assert rejected.state is DriveState.WARNING
    assert rejected.diag == PosDiag.COMMAND_REJECTED
    assert trace[-1].position == 200000 and trace[-1].has(PosStatus.IN_TARGET)
    assert engine.read_sdo(codec.DIAG_COMMAND_REJECTED) == 1
    assert engine.read_sdo(codec.POS_STATUS_WORD) == 1


def test_change_at_standstill_is_rejected() -> None:
    engine = Ep7047Engine(PosSettings(), FAST_CONFIG)
    trace = move(engine, command(StartType.ABSOLUTE_CHANGE, 5000))
    assert trace[-1].diag == PosDiag.COMMAND_REJECTED and trace[-1].has(PosStatus.WARNING)
    assert {s.position for s in trace} == {0}
    # Execute still high after a finished move: a change is rejected too
    engine = Ep7047Engine(PosSettings(), FAST_CONFIG)
    move(engine, command(StartType.ABSOLUTE, 1000))
    after = run(engine, command(StartType.ABSOLUTE_CHANGE, 5000), until=lambda s: True)
    assert after[-1].diag == PosDiag.COMMAND_REJECTED and after[-1].position == 1000


def test_additive_and_relative_change() -> None:
    engine = Ep7047Engine(PosSettings(), FAST_CONFIG)
    start = command(StartType.ABSOLUTE, 100000, velocity_bp=2000)
    run(engine, start, until=lambda s: s.state is DriveState.CONST)
    trace = run(engine, command(StartType.ADDITIVE_CHANGE, 20000, velocity_bp=2000))
    assert_clean_arrival(trace, 120000)

    engine = Ep7047Engine(PosSettings(), FAST_CONFIG)
    run(engine, start, until=lambda s: s.state is DriveState.CONST)
    here = run(engine, start, until=lambda s: s.position >= 30000)[-1].position
    # RELATIVE_CHANGE adds to the actual position the drive sees when it takes the change
    trace = run(engine, command(StartType.RELATIVE_CHANGE, 10000, velocity_bp=2000))
    assert abs(trace[-1].position - (here + 10000)) <= 2 * 51200 * CYCLE_S
    assert trace[-1].has(PosStatus.IN_TARGET)


# --- calibration -----------------------------------------------------------------------------


def calibration_engine(plant: StepperPlant, **settings: int | bool) -> Ep7047Engine:
    base = PosSettings(
        calibration_position_counts=100000,
        calibration_velocity_towards_cam_bp=1000,  # 6.4 counts per cycle
        calibration_velocity_off_cam_bp=100,  # 0.64 counts per cycle
        in_target_timeout_ms=100,
    )
    return Ep7047Engine(replace(base, **settings), FAST_CONFIG, plant)


OFF_CAM_STEP = 0.64  # counts per cycle at 100 bp


def test_calibration_on_cam() -> None:
    plant = StepperPlant(cam_counts=(5000.0, 6000.0))
    engine = calibration_engine(plant)
    assert not move(engine, command(StartType.SET_CALIBRATION))[-1].has(PosStatus.ERROR)
    trace = move(engine, command(StartType.CALI_PLC_CAM))
    assert is_subsequence(
        [
            DriveState.CALI_START,
            DriveState.CALI_GO_CAM,
            DriveState.CALI_ON_CAM,
            DriveState.CALI_LEAVE_CAM,
            DriveState.CALI_STOP,
            DriveState.CALIBRATED,
            DriveState.END,
        ],
        states(trace),
    )
    # Calibrated is cleared while calibrating, set at the end
    assert not trace[1].has(PosStatus.CALIBRATED)
    end = trace[-1]
    assert end.has(PosStatus.CALIBRATED) and not end.has(PosStatus.ERROR)
    assert end.position == 100000 == end.inputs.counter_counts
    # it drove through the cam (both directions positive) and stopped just off it
    assert 6000 < end.shaft_counts <= 6000 + OFF_CAM_STEP + 1e-9
    # the calibration position is taken after the In-Target timeout at rest
    stop_cycles = sum(s.state is DriveState.CALI_STOP for s in trace)
    assert stop_cycles == pytest.approx(0.100 / CYCLE_S, abs=2)
    # the cam shows as digital input 1 while the shaft is on it
    assert any(s.inputs.stm_status & StmStatus.DIGITAL_INPUT_1 for s in trace)
    # positions now refer to the calibration: 1000 counts back is on the cam's edge
    move(engine, command(StartType.ABSOLUTE, 99000, velocity_bp=1000))
    assert plant.shaft_counts == pytest.approx(end.shaft_counts - 1000)


@pytest.mark.parametrize(
    ("invert_cam", "invert_sync", "stop_low", "stop_high"),
    [
        (True, False, 6000.0, 6000.0 + OFF_CAM_STEP),  # back onto the cam, off the far side
        (True, True, 5000.0 - OFF_CAM_STEP, 5000.0),  # onto the cam, off the near side
    ],
)
def test_calibration_search_directions(
    invert_cam: bool, invert_sync: bool, stop_low: float, stop_high: float
) -> None:
    plant = StepperPlant(shaft_counts=10000, cam_counts=(5000.0, 6000.0))
    engine = calibration_engine(
        plant, invert_calibration_cam_search=invert_cam, invert_sync_impulse_search=invert_sync
    )
    trace = move(engine, command(StartType.CALI_PLC_CAM))
    going = [s for s in trace if s.state is DriveState.CALI_GO_CAM]
    assert going and all(s.velocity_bp < 0 for s in going)
    assert stop_low - 1e-9 <= trace[-1].shaft_counts <= stop_high + 1e-9
    assert trace[-1].has(PosStatus.CALIBRATED) and trace[-1].position == 100000


def test_calibration_on_cam_and_sync_pulse_is_exact_at_the_pulse() -> None:
    # C-track pulses every 3600 counts at 1900, 5500 (on the cam), 9100, ...
    plant = StepperPlant(
        cam_counts=(5000.0, 6000.0), sync_period_counts=3600.0, sync_phase_counts=1900.0
    )
    engine = calibration_engine(plant)
    trace = move(engine, command(StartType.CALI_HW_SYNC))
    assert is_subsequence(
        [
            DriveState.CALI_START,
            DriveState.CALI_GO_CAM,
            DriveState.CALI_ON_CAM,
            DriveState.CALI_LEAVE_CAM,
            DriveState.CALI_GO_SYNC,
            DriveState.CALI_STOP,
            DriveState.CALIBRATED,
        ],
        states(trace),
    )
    end = trace[-1]
    assert end.has(PosStatus.CALIBRATED)
    # pulses before leaving the cam were ignored: it stopped just past the one at 9100
    assert 9100 <= end.shaft_counts <= 9100 + OFF_CAM_STEP
    # the calibration position belongs to the pulse itself: going there hits it exactly
    move(engine, command(StartType.ABSOLUTE, 100000, velocity_bp=1000))
    assert plant.shaft_counts == pytest.approx(9100)


def test_calibration_aborted_by_emergency_stop_stays_uncalibrated() -> None:
    engine = calibration_engine(StepperPlant(cam_counts=(5000.0, 6000.0)))
    move(engine, command(StartType.SET_CALIBRATION))
    engine.step(IDLE)
    run(engine, command(StartType.CALI_PLC_CAM), until=lambda s: s.position > 1000)
    trace = run(engine, command(StartType.CALI_PLC_CAM, emergency_stop=True))
    end = trace[-1]
    assert not end.has(PosStatus.CALIBRATED)
    assert end.diag == PosDiag.COMMAND_ABORTED and end.has(PosStatus.WARNING)


def test_set_and_clear_calibration() -> None:
    engine = Ep7047Engine(PosSettings(), FAST_CONFIG)
    assert not engine.step(IDLE).pos_status & PosStatus.CALIBRATED
    trace = move(engine, command(StartType.SET_CALIBRATION))
    assert trace[-1].has(PosStatus.CALIBRATED) and DriveState.CALIBRATED in states(trace)
    trace = move(engine, command(StartType.CLEAR_CALIBRATION))
    assert not trace[-1].has(PosStatus.CALIBRATED)
    assert DriveState.NOT_CALIBRATED in states(trace)
    assert {s.position for s in trace} == {0}


def test_set_calibration_auto_on_the_first_enable_edge_only() -> None:
    settings = PosSettings(start_type=StartType.SET_CALIBRATION_AUTO)
    engine = Ep7047Engine(settings, FAST_CONFIG)
    disabled = Outputs()
    assert not engine.step(disabled).pos_status & PosStatus.CALIBRATED
    assert engine.step(IDLE).pos_status & PosStatus.CALIBRATED
    move(engine, command(StartType.CLEAR_CALIBRATION))
    engine.step(disabled)
    assert not engine.step(IDLE).pos_status & PosStatus.CALIBRATED  # not the second edge
    # without it as the default start type, Enable does nothing to Calibrated
    engine = Ep7047Engine(PosSettings(), FAST_CONFIG)
    engine.step(disabled)
    assert not engine.step(IDLE).pos_status & PosStatus.CALIBRATED


# --- motion -----------------------------------------------------------------------------------


def test_velocity_min_creep_after_braking_half_a_percent_early() -> None:
    engine = Ep7047Engine(PosSettings(velocity_min_bp=500), FAST_CONFIG)
    trace = move(engine, command(StartType.ABSOLUTE, 100000, acceleration_ms=200))
    assert_clean_arrival(trace, 100000)
    last_braking = max(i for i, s in enumerate(trace) if s.has(PosStatus.DECELERATE))
    # braking ends about 0.5 % of the distance (500 counts) before the target ...
    assert 99400 <= trace[last_braking].position <= 99500
    creep = [s for s in trace[last_braking + 1 :] if s.inputs.busy and s.velocity_bp]
    # ... and the rest is crept at Velocity min. (500 bp) without braking
    assert {s.velocity_bp for s in creep} == {500}
    assert not any(s.has(PosStatus.DECELERATE) for s in creep)
    assert len(creep) * 12800 * CYCLE_S == pytest.approx(
        100000 - trace[last_braking].position, abs=4
    )


def test_in_target_timeout_without_reaching_the_window() -> None:
    plant = StepperPlant(encoder_offset_counts=50)  # 50 counts the drive cannot pull in
    engine = Ep7047Engine(
        PosSettings(target_window_counts=10, in_target_timeout_ms=200), FAST_CONFIG, plant
    )
    trace = move(engine, command(StartType.ABSOLUTE, 20000))
    end = trace[-1]
    assert not end.has(PosStatus.IN_TARGET) and not end.has(PosStatus.BUSY)
    assert not end.has(PosStatus.WARNING) and not end.has(PosStatus.ERROR)  # only Busy tells
    assert end.position == 20050
    waited = sum(s.state is DriveState.PRE_TARGET for s in trace)
    assert waited == pytest.approx(0.200 / CYCLE_S, abs=2)
    assert DriveState.TARGET not in states(trace)

    plant = StepperPlant(encoder_offset_counts=8)  # inside the window: In-Target at once
    engine = Ep7047Engine(
        PosSettings(target_window_counts=10, in_target_timeout_ms=200), FAST_CONFIG, plant
    )
    trace = move(engine, command(StartType.ABSOLUTE, 20000))
    assert trace[-1].has(PosStatus.IN_TARGET)
    assert sum(s.state is DriveState.PRE_TARGET for s in trace) == 1


def test_emergency_stop_aborts_and_additive_continues_from_the_old_target() -> None:
    settings = PosSettings(emergency_deceleration_ms=50)
    engine = Ep7047Engine(settings, FAST_CONFIG)
    go = command(StartType.ABSOLUTE, 100000, velocity_bp=5000, acceleration_ms=500)
    run(engine, go, until=lambda s: s.state is DriveState.CONST)
    trace = run(engine, command(StartType.ABSOLUTE, 100000, velocity_bp=5000, emergency_stop=True))
    assert is_subsequence([DriveState.EMCY, DriveState.STOP, DriveState.END], states(trace))
    end = trace[-1]
    assert end.diag == PosDiag.COMMAND_ABORTED
    assert end.has(PosStatus.WARNING) and not end.has(PosStatus.IN_TARGET)
    assert not end.has(PosStatus.ERROR)
    # 50 % of the range in 50 ms x 50 % = 25 ms = 100 cycles
    braking = [s for s in trace if s.state is DriveState.EMCY]
    assert len(braking) == pytest.approx(100, abs=2)
    assert all(s.has(PosStatus.DECELERATE) for s in braking[:-1])
    stopped_at = end.position
    assert 0 < stopped_at < 100000
    # while Emergency stop is held nothing starts
    held = move(engine, command(StartType.ABSOLUTE, 0, emergency_stop=True))
    assert {s.position for s in held} == {stopped_at}
    assert held[-1].diag == PosDiag.COMMAND_ABORTED
    assert not any(s.has(PosStatus.READY_TO_EXECUTE) for s in held)
    # ADDITIVE adds to the last target (100000), RELATIVE to where it stands
    assert_clean_arrival(move(engine, command(StartType.ADDITIVE, 1000)), 101000)
    assert_clean_arrival(move(engine, command(StartType.RELATIVE, 1000)), 102000)


def test_execute_edge_semantics() -> None:
    engine = Ep7047Engine(PosSettings(), FAST_CONFIG)
    first = engine.step(command(StartType.ABSOLUTE, 5000))
    assert first.busy and engine.state is DriveState.START  # Busy with the rising edge
    trace = run(engine, command(StartType.ABSOLUTE, 5000))
    assert trace[-1].position == 5000
    # Execute held high: nothing restarts, new values with a plain type are ignored
    held = [engine.step(command(StartType.ABSOLUTE, 9000)) for _ in range(200)]
    assert {i.actual_position_counts for i in held} == {5000}
    assert not any(i.busy for i in held)
    # a new rising edge starts it
    assert_clean_arrival(move(engine, command(StartType.ABSOLUTE, 9000)), 9000)


def test_dropping_execute_early_ramps_down_and_aborts() -> None:
    engine = Ep7047Engine(PosSettings(), FAST_CONFIG)
    go = command(StartType.ABSOLUTE, 200000, velocity_bp=5000, acceleration_ms=500)
    run(engine, go, until=lambda s: s.state is DriveState.CONST)
    trace = run(engine, command(StartType.ABSOLUTE, 200000, velocity_bp=5000, execute=False))
    end = trace[-1]
    assert end.diag == PosDiag.COMMAND_ABORTED and not end.has(PosStatus.IN_TARGET)
    assert end.position < 200000
    # ramped down with the deceleration (100 ms for 100 %: 50 ms = 200 cycles from 50 %)
    assert sum(s.has(PosStatus.DECELERATE) for s in trace) == pytest.approx(200, abs=2)
    # a rising edge while still Busy is ignored
    engine = Ep7047Engine(PosSettings(), FAST_CONFIG)
    run(engine, go, until=lambda s: s.state is DriveState.CONST)
    engine.step(IDLE)
    engine.step(command(StartType.ABSOLUTE, 0, velocity_bp=5000))
    trace = run(engine, command(StartType.ABSOLUTE, 0, velocity_bp=5000))
    assert trace[-1].position > 0 and not trace[-1].has(PosStatus.IN_TARGET)


@pytest.mark.parametrize(
    ("start_type", "sign"), [(StartType.ENDLESS_PLUS, 1), (StartType.ENDLESS_MINUS, -1)]
)
def test_endless_runs_until_execute_drops(start_type: StartType, sign: int) -> None:
    engine = Ep7047Engine(PosSettings(), FAST_CONFIG)
    go = command(start_type, 123456, velocity_bp=-2500)  # target ignored, sign of velocity too
    trace = run(engine, go, until=lambda s: s.state is DriveState.CONST)
    trace += run(engine, go, until=lambda s: s.position * sign > 20000)
    assert trace[-1].velocity_bp == sign * 2500 and trace[-1].has(PosStatus.BUSY)
    assert trace[-1].state is DriveState.CONST
    stop = run(engine, command(start_type, 0, velocity_bp=2500, execute=False))
    end = stop[-1]
    assert end.velocity_bp == 0 and end.diag == PosDiag.NONE  # stopping is not an abort
    assert not end.has(PosStatus.IN_TARGET) and not end.has(PosStatus.WARNING)
    assert DriveState.STOP in states(stop)
    # ADDITIVE after an endless move adds to where it stopped
    assert_clean_arrival(
        move(engine, command(StartType.ADDITIVE, sign * 100)), end.position + sign * 100
    )


def test_ramp_times_are_relative_to_the_speed_range() -> None:
    engine = Ep7047Engine(PosSettings(), FAST_CONFIG)
    trace = move(
        engine, command(StartType.ABSOLUTE, 200000, velocity_bp=5000, acceleration_ms=1000)
    )
    # 1000 ms for 0..100 %: 0..50 % takes 500 ms = 2000 cycles
    assert sum(s.has(PosStatus.ACCELERATE) for s in trace) == pytest.approx(2000, abs=2)
    assert max(s.velocity_bp for s in trace) == 5000


def test_coe_ramps_apply_per_direction_when_the_pdo_gives_none() -> None:
    settings = PosSettings(acceleration_pos_ms=1000, acceleration_neg_ms=250)
    engine = Ep7047Engine(settings, FAST_CONFIG)
    up = move(engine, command(StartType.ABSOLUTE, 200000, velocity_bp=5000, acceleration_ms=0))
    down = move(engine, command(StartType.ABSOLUTE, 0, velocity_bp=5000, acceleration_ms=0))
    assert sum(s.has(PosStatus.ACCELERATE) for s in up) == pytest.approx(2000, abs=2)
    assert sum(s.has(PosStatus.ACCELERATE) for s in down) == pytest.approx(500, abs=2)
    assert down[-1].position == 0


def test_velocity_is_limited_to_velocity_max() -> None:
    engine = Ep7047Engine(PosSettings(velocity_max_bp=2500), FAST_CONFIG)
    trace = move(engine, command(StartType.ABSOLUTE, 100000, velocity_bp=10000))
    assert max(s.velocity_bp for s in trace) == 2500
    assert_clean_arrival(trace, 100000)


@pytest.mark.parametrize(
    "outputs",
    [
        command(0x0007, 1000),  # unknown start type
        command(StartType.ABSOLUTE, 1000, velocity_bp=0),
        command(StartType.ABSOLUTE, 1000, enable=False),
    ],
    ids=["unknown-start-type", "velocity-0", "not-enabled"],
)
def test_refused_starts_set_error_and_reset_clears_it(outputs: Outputs) -> None:
    engine = Ep7047Engine(PosSettings(), FAST_CONFIG)
    trace = move(engine, outputs)
    assert trace[-1].has(PosStatus.ERROR) and {s.position for s in trace} == {0}
    engine.step(IDLE)
    reset = Outputs(stm_control=StmControl.ENABLE | StmControl.RESET)
    assert not engine.step(reset).pos_status & PosStatus.ERROR


def test_default_start_type_applies_when_the_output_is_zero() -> None:
    settings = PosSettings(start_type=StartType.RELATIVE)
    engine = Ep7047Engine(settings, FAST_CONFIG, StepperPlant(shaft_counts=1000))
    assert_clean_arrival(move(engine, command(0, 500)), 1500)


def test_losing_enable_mid_move_is_an_error() -> None:
    engine = Ep7047Engine(PosSettings(), FAST_CONFIG)
    go = command(StartType.ABSOLUTE, 100000)
    run(engine, go, until=lambda s: s.position > 1000)
    trace = run(engine, command(StartType.ABSOLUTE, 100000, enable=False))
    end = trace[-1]
    assert end.has(PosStatus.ERROR) and end.diag == PosDiag.COMMAND_ABORTED
    assert end.velocity_bp == 0 and not end.inputs.stm_status & StmStatus.READY


def test_actual_drive_time_is_the_elapsed_time_of_the_move() -> None:
    engine = Ep7047Engine(PosSettings(), FAST_CONFIG)
    trace = move(engine, command(StartType.ABSOLUTE, 50000))
    busy = sum(s.has(PosStatus.BUSY) for s in trace)
    assert trace[-1].inputs.actual_drive_time_ms == pytest.approx(
        (busy - 1) * CYCLE_S * 1000, abs=1
    )
    later = [engine.step(IDLE) for _ in range(100)]
    assert later[-1].actual_drive_time_ms == trace[-1].inputs.actual_drive_time_ms  # frozen
    assert move(engine, command(StartType.ABSOLUTE, 50000))[0].inputs.actual_drive_time_ms == 0


def test_set_counter_and_c_latch() -> None:
    plant = StepperPlant(sync_period_counts=1000.0, sync_phase_counts=500.0)
    engine = Ep7047Engine(PosSettings(), FAST_CONFIG, plant)
    set_counter = Outputs(
        stm_control=StmControl.ENABLE, enc_control=EncControl.SET_COUNTER, set_counter_counts=-7000
    )
    inputs = engine.step(set_counter)
    assert inputs.actual_position_counts == -7000 == inputs.counter_counts
    assert inputs.enc_status & codec.EncStatus.SET_COUNTER_DONE
    latch = Outputs(stm_control=StmControl.ENABLE, enc_control=EncControl.ENABLE_LATCH_C)
    engine.step(latch)
    go = Outputs(
        stm_control=StmControl.ENABLE,
        enc_control=EncControl.ENABLE_LATCH_C,
        pos_control=PosControl.EXECUTE,
        target_position_counts=-5000,
        velocity_bp=1000,
        start_type=StartType.ABSOLUTE,
    )
    trace = run(engine, go)
    end = trace[-1].inputs
    assert end.enc_status & codec.EncStatus.LATCH_C_VALID
    assert end.latch_counts == -6500  # the first pulse passed: shaft 500
    assert_clean_arrival(trace, -5000)


def test_inputs_always_fit_the_wire_and_runs_are_deterministic() -> None:
    def replay() -> list[bytes]:
        engine = Ep7047Engine(PosSettings(), FAST_CONFIG)
        trace = move(engine, command(StartType.ABSOLUTE, 30000, velocity_bp=-8000))
        engine.step(IDLE)
        trace += run(
            engine,
            command(StartType.ENDLESS_MINUS, velocity_bp=32767),
            until=lambda s: s.position < -1_000_000,
        )
        return [codec.encode_inputs(s.inputs) for s in trace]

    assert replay() == replay()


def test_sdo_access() -> None:
    engine = Ep7047Engine(PosSettings(), MODULO_CONFIG, StepperPlant(shaft_counts=900))
    engine.write_sdo(codec.MODULO_FACTOR, TURN)
    engine.write_sdo(codec.INVERT_SYNC_IMPULSE_SEARCH, 1)
    assert engine.settings.modulo_factor_counts == TURN
    assert engine.settings.invert_sync_impulse_search is True
    assert engine.read_sdo(codec.MODULO_FACTOR) == TURN
    assert_clean_arrival(move(engine, command(StartType.MODULO_PLUS, 0)), TURN)
    assert engine.read_sdo(codec.DRIVE_STATE) == DriveState.END
    with pytest.raises(codec.CodecError):
        engine.write_sdo(codec.TARGET_WINDOW, -1)
    with pytest.raises(KeyError):
        engine.write_sdo(codec.DRIVE_STATE, 1)
    with pytest.raises(KeyError):
        engine.read_sdo(codec.IDENTITY_VENDOR_ID)


def test_run_equals_stepping_cycle_by_cycle() -> None:
    """``run(outputs, n)`` (which skips quiet stretches) gives exactly what ``n`` calls
    of ``step`` give, through enable, a move, a _CHANGE, Execute dropped, a reset,
    idle stretches and the watchdog's all-zero outputs."""
    enabled = Outputs(stm_control=StmControl.ENABLE)
    move = Outputs(
        stm_control=StmControl.ENABLE,
        pos_control=PosControl.EXECUTE,
        target_position_counts=20_000,
        velocity_bp=4000,
        start_type=StartType.ABSOLUTE,
        acceleration_ms=100,
        deceleration_ms=100,
    )
    change = Outputs(
        stm_control=StmControl.ENABLE,
        pos_control=PosControl.EXECUTE,
        target_position_counts=5_000,
        velocity_bp=2000,
        start_type=StartType.ABSOLUTE_CHANGE,
        acceleration_ms=100,
        deceleration_ms=100,
    )
    reset = Outputs(stm_control=StmControl.ENABLE | StmControl.RESET)
    script = [
        (Outputs(), 40),
        (enabled, 1),
        (enabled, 400),
        (move, 1),
        (move, 600),
        (change, 3000),
        (enabled, 7),
        (enabled, 2000),
        (reset, 5),
        (enabled, 1000),
        (Outputs(), 900),
        (move, 50),  # a start without Enable: Error
        (Outputs(), 300),
    ]
    stepped, skipped = Ep7047Engine(), Ep7047Engine()
    for outputs, cycles in script:
        for _ in range(cycles):
            expected = stepped.step(outputs)
        assert skipped.run(outputs, cycles) == expected
        assert skipped.cycles == stepped.cycles
        assert skipped.state == stepped.state
        assert skipped.setpoint_counts == stepped.setpoint_counts
    assert stepped.plant.actual_counts != 0  # the script did move the axis


def _engine_state(engine: Ep7047Engine) -> dict[str, object]:
    """Every field of the engine and its plant (what a cycle may change)."""
    every = vars(engine) | vars(engine.positioning)
    fields = {
        k: v for k, v in every.items() if k not in ("positioning", "plant", "settings", "config")
    }
    fields["plant"] = (
        engine.plant.shaft_counts,
        engine.plant.counter_shift_counts,
        engine.plant.encoder_offset_counts,
        engine.plant.speed_counts_s,
    )
    return fields


def _demo_like_engine() -> Ep7047Engine:
    # The demo's mechanics: a C-track pulse every turn (4096 counts), a cam, the rotor
    # and load that coast unpowered.
    plant = StepperPlant(
        cam_counts=(6000.0, 6800.0),
        sync_period_counts=4096.0,
        sync_phase_counts=1024.0,
        mechanics=DEMO_MECHANICS,
    )
    settings = PosSettings(velocity_min_bp=50, target_window_counts=10)
    config = DriveConfig(speed_range_steps_s=2000, counts_per_full_step=4096 / 200)
    return Ep7047Engine(settings, config, plant)


@pytest.mark.parametrize("chunk", [8, 3, 1000])
def test_run_cruising_equals_stepping_field_by_field(chunk: int) -> None:
    """The cruise stretches of ``run`` (ENDLESS, and a positioning move at its velocity)
    leave every field of the engine exactly as cycle-by-cycle stepping does: checked
    after every ``run`` of ``chunk`` cycles (8: one 2 ms exchange) through C-track
    pulses with the latch armed, ENDLESS both ways, a long move in each direction,
    a _CHANGE of velocity while cruising, Execute dropped, and an emergency stop."""
    enable = StmControl.ENABLE
    run_bits = PosControl.EXECUTE

    def outputs(
        start: StartType, target: int, velocity: int, pos: PosControl = run_bits
    ) -> Outputs:
        return Outputs(
            enc_control=EncControl.ENABLE_LATCH_C,
            stm_control=enable,
            pos_control=pos,
            target_position_counts=target,
            velocity_bp=velocity,
            start_type=start,
            acceleration_ms=200,
            deceleration_ms=300,
        )

    idle = Outputs(stm_control=enable)
    script = [
        (idle, 400),
        (outputs(StartType.ENDLESS_PLUS, 0, 3000, PosControl.NONE), 1),
        (outputs(StartType.ENDLESS_PLUS, 0, 3000), 8000),  # several turns: pulses
        (outputs(StartType.ENDLESS_PLUS, 0, 3000, PosControl.NONE), 2000),  # Execute low
        (idle, 200),
        (outputs(StartType.ABSOLUTE, 40_000, 4000, PosControl.NONE), 1),
        (outputs(StartType.ABSOLUTE, 40_000, 4000), 6000),  # cruise, brake, arrive
        (idle, 300),
        (outputs(StartType.ABSOLUTE, -30_000, 2500, PosControl.NONE), 1),
        (outputs(StartType.ABSOLUTE, -30_000, 2500), 2500),
        (outputs(StartType.ABSOLUTE_CHANGE, -30_000, 1200), 9000),  # slower, to the end
        (idle, 300),
        (outputs(StartType.ENDLESS_MINUS, 0, 5000, PosControl.NONE), 1),
        (outputs(StartType.ENDLESS_MINUS, 0, 5000), 3000),
        (outputs(StartType.ENDLESS_MINUS, 0, 5000, run_bits | PosControl.EMERGENCY_STOP), 2000),
        (idle, 100),
        (outputs(StartType.ENDLESS_PLUS, 0, 8000, PosControl.NONE), 1),
        (outputs(StartType.ENDLESS_PLUS, 0, 8000), 3000),
        (Outputs(enc_control=EncControl.ENABLE_LATCH_C), 2000),  # unpowered: the coast
        (idle, 100),
    ]
    stepped, chunked = _demo_like_engine(), _demo_like_engine()
    latches = 0
    for out, cycles in script:
        left = cycles
        while left:
            n = min(chunk, left)
            for _ in range(n):
                expected = stepped.step(out)
            latches += expected.enc_status & 1
            assert chunked.run(out, n) == expected
            assert _engine_state(chunked) == _engine_state(stepped)
            left -= n
    # The script went through what the cruise has to stop for, and a coast.
    assert latches > 0
    assert stepped.plant.shaft_counts != 0
    assert stepped.plant.speed_counts_s == 0.0


# --- unpowered: the rotor and load coast ------------------------------------------------


def _coast_reference(
    mechanics: Mechanics, speed_counts_s: float, until_s: float = 60.0
) -> tuple[float, float | None]:
    """(distance, time) to standstill - or the distance at ``until_s`` and None if it
    turns still - integrated numerically (scipy) from the equation of motion,
    independent of the closed form in ``Mechanics.coast``."""
    counts_per_rad = mechanics.counts_per_rev / (2 * math.pi)
    j, tc, b = mechanics.inertia_kg_m2, mechanics.friction_nm, mechanics.viscous_nm_s_per_rad

    def motion(t: float, y: list[float]) -> list[float]:
        return [y[1], -(tc * math.copysign(1.0, y[1]) + b * y[1]) / j]

    def stopped(t: float, y: list[float]) -> float:
        return y[1]

    stopped.terminal = True  # type: ignore[attr-defined]
    solution = solve_ivp(
        motion, (0, until_s), [0.0, speed_counts_s / counts_per_rad], events=stopped,
        rtol=1e-10, atol=1e-12,
    )  # fmt: skip
    if len(solution.t_events[0]) == 0:
        return float(solution.y[0][-1]) * counts_per_rad, None
    return float(solution.y_events[0][0][0]) * counts_per_rad, float(solution.t_events[0][0])


@pytest.mark.parametrize("speed", [40_960.0, -12_000.0, 300.0])
@pytest.mark.parametrize(
    "mechanics",
    [
        DEMO_MECHANICS,
        Mechanics(
            inertia_kg_m2=1e-3, friction_nm=0, viscous_nm_s_per_rad=2e-3, counts_per_rev=1000
        ),
        Mechanics(
            inertia_kg_m2=1e-4, friction_nm=0.02, viscous_nm_s_per_rad=0, counts_per_rev=4096
        ),
    ],
    ids=["demo", "viscous-only", "coulomb-only"],
)
def test_the_coast_follows_the_equation_of_motion(mechanics: Mechanics, speed: float) -> None:
    cycles = 8000  # 2 s
    distance, t_stop = _coast_reference(mechanics, speed, cycles * CYCLE_S)
    travelled, v, moving = 0.0, speed, 0
    for _ in range(cycles):
        step, v = mechanics.coast(v, CYCLE_S)
        travelled += step
        if v:
            moving += 1
            assert abs(v) < abs(speed) and v * speed > 0  # slows down, never reverses
    assert travelled == pytest.approx(distance, rel=1e-6, abs=1e-6)
    if t_stop is None:  # viscous friction alone never quite stops it
        assert v != 0.0 and mechanics.friction_nm == 0
    else:
        assert v == 0.0 and (moving + 1) * CYCLE_S == pytest.approx(t_stop, abs=CYCLE_S)


def test_mechanics_refuse_values_without_meaning() -> None:
    with pytest.raises(ValueError, match="inertia"):
        Mechanics(inertia_kg_m2=0, friction_nm=0.1, viscous_nm_s_per_rad=0, counts_per_rev=1)
    with pytest.raises(ValueError, match="never stop"):
        Mechanics(inertia_kg_m2=1, friction_nm=0, viscous_nm_s_per_rad=0, counts_per_rev=1)


def _at_top_speed(plant: StepperPlant) -> tuple[Ep7047Engine, list[Sample]]:
    engine = Ep7047Engine(DEMO_SETTINGS, DEMO_CONFIG, plant)
    endless = command(StartType.ENDLESS_PLUS, velocity_bp=10_000, acceleration_ms=400)
    engine.step(IDLE)
    trace = run(engine, endless, until=lambda s: s.state == DriveState.CONST)
    return engine, trace


def test_enable_off_at_speed_lets_the_shaft_coast_and_the_encoder_counts_it() -> None:
    engine, trace = _at_top_speed(StepperPlant(mechanics=DEMO_MECHANICS))
    speed = engine.velocity_counts_s
    assert speed == pytest.approx(DEMO_CONFIG.full_scale_counts_s)
    start = trace[-1].position
    coast: list[Sample] = []
    for _ in range(4000):  # 1 s unpowered
        inputs = engine.step(Outputs())
        coast.append(Sample(inputs, engine.state, engine.diag, engine.plant.shaft_counts))
    distance, t_stop = _coast_reference(DEMO_MECHANICS, speed)
    assert t_stop is not None
    # The encoder counts the shaft's coast: the distance the equation of motion gives.
    assert coast[-1].position - start == pytest.approx(distance, abs=2)
    moving = [s for s in coast if s.position != coast[-1].position]
    assert len(moving) * CYCLE_S == pytest.approx(t_stop, abs=2 * CYCLE_S)
    positions = [s.position for s in coast]
    assert positions == sorted(positions)  # slows down, never turns back
    # Decision: the drive's own velocity and direction bits are its trajectory's, which
    # ends with the output stage: 0 at once, while the shaft coasts on.
    assert all(s.velocity_bp == 0 for s in coast)
    assert not coast[0].inputs.stm_status & (StmStatus.MOVING_POSITIVE | StmStatus.READY)
    assert coast[-1].has(PosStatus.ERROR)  # the move failed (as before)


def test_an_ideal_plant_stops_dead_and_an_internal_counter_misses_the_coast() -> None:
    engine, _ = _at_top_speed(StepperPlant())  # no mechanics: massless
    engine.step(Outputs())
    shaft = engine.plant.shaft_counts
    engine.run(Outputs(), 4000)
    assert engine.plant.shaft_counts == shaft
    # Without an encoder the counter is the drive's step count: the shaft coasts on, the
    # counter stands where the steps stopped (the position is lost, as on a real drive).
    engine, _ = _at_top_speed(StepperPlant(mechanics=DEMO_MECHANICS, encoder=False))
    first = engine.step(Outputs())
    shaft = engine.plant.shaft_counts
    last = engine.run(Outputs(), 4000)
    assert last.actual_position_counts == first.actual_position_counts
    assert engine.plant.shaft_counts - shaft > 1000


def test_enable_again_while_coasting_catches_the_shaft_where_it_is() -> None:
    engine, _ = _at_top_speed(StepperPlant(mechanics=DEMO_MECHANICS))
    engine.run(Outputs(), 200)  # 50 ms unpowered: still turning
    assert engine.plant.speed_counts_s > 1000
    caught = engine.plant.actual_counts
    held = [engine.step(IDLE).actual_position_counts for _ in range(400)]
    # Held where it was caught (no jump back to where the trajectory ended), and a
    # relative move then starts from there.
    assert set(held) == {round(caught)}
    reset = Outputs(stm_control=StmControl.ENABLE | StmControl.RESET)
    engine.step(reset)
    assert_clean_arrival(move(engine, command(StartType.RELATIVE, 1000)), round(caught) + 1000)


def test_run_skips_a_quiet_stretch_in_one_go() -> None:
    engine = Ep7047Engine()
    enabled = Outputs(stm_control=StmControl.ENABLE)
    engine.run(enabled, 10)
    assert engine._quiescent(enabled)
    engine.run(enabled, 4_000_000)  # 1000 s of idle: instant, not four million cycles
    assert engine.cycles == 4_000_010
    assert not engine._quiescent(Outputs())  # other outputs: Enable falls, not quiet
