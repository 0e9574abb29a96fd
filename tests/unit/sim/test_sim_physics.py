"""DC motor plant of the simulators: datasheet sanity, encoder, index, friction, limit."""

from __future__ import annotations

import itertools
import math

import pytest

from servotune.sim.physics import DcMotor, DcMotorParams

TICK_S = 841.5e-6
RPM_PER_RAD_S = 60 / (2 * math.pi)


def run(motor: DcMotor, seconds: float, duty: float | None, limit_a: float | None = None) -> None:
    for _ in range(round(seconds / TICK_S)):
        motor.step(TICK_S, duty, limit_a)


def test_no_load_speed_matches_the_2224_datasheet() -> None:
    motor = DcMotor()
    run(motor, 0.2, 1.0)
    speed_rpm = motor.speed_rad_s * RPM_PER_RAD_S
    # Faulhaber 2224 U 024 SR: no-load speed ~7800 rpm at 24 V, no-load current ~10 mA.
    assert speed_rpm == pytest.approx(7800, rel=0.03)
    assert 0.003 < motor.current_a < 0.015


def test_steady_state_power_balance() -> None:
    """Electrical input = copper loss + friction loss once the speed is constant."""
    params = DcMotorParams()
    motor = DcMotor(params)
    run(motor, 0.2, 0.5)
    voltage = 0.5 * params.supply_v
    current = motor.current_a
    speed = motor.speed_rad_s
    friction_w = (params.coulomb_friction_nm + params.viscous_friction_nm_s_per_rad * speed) * speed
    assert voltage * current == pytest.approx(
        params.resistance_ohm * current**2 + friction_w, rel=0.01
    )


def test_speed_rises_with_the_mechanical_time_constant() -> None:
    params = DcMotorParams()
    tau_s = params.resistance_ohm * params.inertia_kg_m2 / params.torque_constant_nm_per_a**2
    motor = DcMotor(params, max_step_s=50e-6)
    final = params.no_load_speed_rad_s
    t = 0.0
    while motor.speed_rad_s < (1 - math.exp(-1)) * final:
        motor.step(50e-6, 1.0)
        t += 50e-6
    assert t == pytest.approx(tau_s, rel=0.15)


def test_load_inertia_slows_the_start() -> None:
    light = DcMotor()
    heavy = DcMotor(DcMotorParams(load_inertia_kg_m2=10 * 3.8e-7))
    run(light, 0.005, 1.0)
    run(heavy, 0.005, 1.0)
    assert heavy.speed_rad_s < 0.5 * light.speed_rad_s


def test_encoder_quantises_to_four_counts_per_line() -> None:
    params = DcMotorParams(encoder_lines=512)
    motor = DcMotor(params)
    counts_per_rad = 2048 / (2 * math.pi)
    for _ in range(400):
        motor.step(TICK_S, 0.3)
        assert motor.count == math.floor(motor.angle_rad * counts_per_rad)
    revolutions = motor.angle_rad / (2 * math.pi)
    assert revolutions > 3
    assert motor.count == pytest.approx(revolutions * 2048, abs=1)
    assert DcMotorParams(encoder_lines=100).counts_per_rev == 400


@pytest.mark.parametrize("duty", [0.4, -0.4])
def test_index_pulse_once_per_revolution(duty: float) -> None:
    params = DcMotorParams(index_count=300)
    motor = DcMotor(params)
    crossings = []
    start = motor.count
    for _ in range(1200):
        motor.step(TICK_S, duty)
        if motor.index_crossed is not None:
            crossings.append(motor.index_crossed)
    revolutions = abs(motor.count - start) / 2048
    assert len(crossings) in (math.floor(revolutions), math.ceil(revolutions))
    assert len(crossings) >= 5
    assert all((c - 300) % 2048 == 0 for c in crossings)
    steps = {b - a for a, b in itertools.pairwise(crossings)}
    assert steps == {2048 if duty > 0 else -2048}


def test_index_pulse_seen_even_when_crossed_within_one_step() -> None:
    motor = DcMotor(DcMotorParams(index_count=300))
    motor.set_count(290)
    motor.speed_rad_s = 20.0  # ~6 counts per 1 ms step
    seen = None
    for _ in range(5):
        motor.step(1e-3, None)
        seen = seen if motor.index_crossed is None else motor.index_crossed
    assert seen == 300


def test_coulomb_friction_holds_a_small_torque() -> None:
    params = DcMotorParams(coulomb_friction_nm=0.2e-3)
    motor = DcMotor(params)
    motor.set_count(1000)
    motor.external_torque_nm = 0.15e-3
    run(motor, 1.0, None)
    assert motor.count == 1000
    assert motor.speed_rad_s == 0.0
    motor.external_torque_nm = 0.25e-3
    run(motor, 0.2, None)
    assert motor.count > 1100


def test_a_coasting_motor_stops_and_stays_stopped() -> None:
    motor = DcMotor()
    run(motor, 0.1, 0.5)
    assert motor.speed_rad_s > 100
    run(motor, 1.5, None)  # bridge open: friction alone brakes the rotor
    assert motor.speed_rad_s == 0.0
    resting = motor.count
    run(motor, 0.2, None)
    assert motor.count == resting


def test_current_limit_chops_and_reports() -> None:
    params = DcMotorParams(load_inertia_kg_m2=1e3)  # practically a locked rotor
    stalled = DcMotor(params)
    run(stalled, 0.05, 1.0)
    assert stalled.current_a == pytest.approx(params.supply_v / params.resistance_ohm, rel=0.01)
    assert not stalled.current_limited
    limited = DcMotor(params)
    run(limited, 0.05, 1.0, limit_a=0.5)
    assert limited.current_a == pytest.approx(0.5, rel=1e-6)
    assert limited.current_limited


def test_pwm_saturates_at_the_supply() -> None:
    full = DcMotor()
    beyond = DcMotor()
    run(full, 0.1, 1.0)
    run(beyond, 0.1, 3.0)
    assert beyond.speed_rad_s == pytest.approx(full.speed_rad_s)


def test_limit_switches_at_their_counts() -> None:
    motor = DcMotor(DcMotorParams(limit1_count=-100, limit2_count=100))
    motor.set_count(0)
    assert not motor.limit1_actuated and not motor.limit2_actuated
    motor.set_count(-100)
    assert motor.limit1_actuated
    motor.set_count(100)
    assert motor.limit2_actuated
    free = DcMotor(DcMotorParams(limit1_count=None, limit2_count=None))
    free.set_count(10**7)
    assert not free.limit1_actuated and not free.limit2_actuated


def test_open_bridge_carries_no_current() -> None:
    motor = DcMotor()
    run(motor, 0.05, 1.0)
    motor.step(TICK_S, None)
    assert motor.current_a == 0.0
