"""One stability verdict, the same on the server and in the browser, and
true of the simulator's plant.

* The verdict (``tuning.stability.schur_stable`` on the closed loop's characteristic
  polynomial, ``LoopModel.stable``) against a direct simulation of the simulator's
  plant (``sim.physics.DcMotor``, the motor the SLAP2 simulator integrates, without its
  Coulomb friction, under the firmware's PID law in exact arithmetic: no integer
  rounding, whose one-count dead band hides small oscillations) on a grid of gains
  on both demo SLAP2 plants: stable (the error decays) vs growing (the oscillation
  reaches the PWM limit): 100 % agreement, from the server's rule and from the
  browser's (``web/src/stability.ts``, compiled and run under node).
* ki = 0 is not "unstable": the auto-tune's proposal of the issue (1676/0/1100 on the
  loaded module's identified model) is stable in the margins table, the model Bode and
  the browser alike.
* The browser's and the server's verdicts agree on the what-if's own inputs (the
  identified plants of the demo, SLAP2 and Z1100) over dense gain grids.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from pathlib import Path
from typing import Any

import control
import numpy as np
import pytest

from servotune.bench import frf
from servotune.devices import default_registry
from servotune.devices.slap2.law import slap2_loop
from servotune.devices.slap2.sim.demo import SLAP2_LOADED
from servotune.sim.physics import DcMotor, DcMotorParams
from servotune.tuning.loops import MotorModel
from servotune.tuning.stability import schur_stable
from servotune.tuning.whatif import browser_model, loop_for, plant_from_identification
from tests.support import stability_ts

# The devices' controller laws, looked up as the app does.
LAW = default_registry().law

TICK_S = 841.5e-6
PLANTS = {"unloaded": DcMotorParams(), "loaded": SLAP2_LOADED}
GRID = list(itertools.product((10, 150, 600, 2000, 3000), (0, 40, 3000), (0, 80, 600, 2000)))
# the identified models the demo's auto-tune gives (SLAP2 loaded: the session)
IDENTIFIED = {
    "slap2": {"gain_counts_s_per_pwm": 1058.307, "tau_s": 0.024},
    "z1100": {"gain_counts_s_per_duty": 30000.0, "tau_s": 0.012},
}


def _motor(p: DcMotorParams) -> MotorModel:
    return MotorModel(
        p.resistance_ohm,
        p.inductance_h,
        p.torque_constant_nm_per_a,
        p.inertia_kg_m2,
        p.viscous_friction_nm_s_per_rad,
        p.supply_v,
        p.counts_per_rev,
    )


def _simulate(params: DcMotorParams, gains: tuple[int, int, int], seconds: float = 10.0) -> str:
    """The shaft bumped 20 counts off the held position, the PID law (firmware scaling,
    PWM clamped at 255) every tick on the simulator's motor: "stable" if the error over
    the last quarter stays within half a count, "growing" if the oscillation reaches
    the PWM limit or twice the bump, else "undecided"."""
    motor = DcMotor(params)
    motor.prepare(TICK_S)
    counts_per_rad = params.counts_per_rev / (2 * math.pi)
    kp, ki, kd = gains
    bump = 20.0
    motor.angle_rad = bump / counts_per_rad
    integral = 0.0
    previous = -bump
    n = int(seconds / TICK_S)
    late_error = late_pwm = 0.0
    for i in range(n):
        e = -motor.angle_rad * counts_per_rad
        integral += e
        u = (16 * kp * e + ki * integral + 32 * kd * (e - previous)) / 4096
        previous = e
        u = max(-255.0, min(255.0, u))
        motor.step(TICK_S, u / 255.0)
        if i >= 3 * n // 4:
            late_error, late_pwm = max(late_error, abs(e)), max(late_pwm, abs(u))
    if late_error >= 2 * bump or late_pwm >= 255.0:
        return "growing"
    return "stable" if late_error <= 0.5 else "undecided"


def _browser_plant(plant_d: control.TransferFunction) -> tuple[list[float], list[float]]:
    """A discrete plant as the what-if view gets it (``whatif.browser_model``)."""
    num, den = (np.asarray(c[0][0], dtype=np.float64) for c in control.tfdata(plant_d))
    num = np.concatenate([np.zeros(den.size - num.size), num])
    return list(num / den[0]), list(den / den[0])


def _browser_verdicts(cases: list[dict[str, Any]], tmp_path: Path) -> list[bool]:
    """``loopStable`` of web/src/stability.ts for each case (``stability_ts.evaluate``)."""
    verdicts: list[bool] = stability_ts.evaluate(cases, tmp_path, "loopStable(c.model, c.gains)")
    return verdicts


def test_schur_cohn_agrees_with_the_roots() -> None:
    rng = np.random.default_rng(1)
    checked = 0
    for _ in range(5000):
        n = int(rng.integers(1, 9))
        radius = rng.uniform(0.2, 1.3, n)
        roots = radius * np.exp(1j * rng.uniform(0.0, np.pi, n))
        coefficients = np.real(np.poly(np.concatenate([roots, roots.conj()]))) * 3.0
        largest = float(np.max(np.abs(np.roots(coefficients))))
        if abs(largest - 1.0) < 1e-6:
            continue
        assert schur_stable(coefficients) == (largest < 1.0), (coefficients, largest)
        checked += 1
    assert checked > 4900
    assert not schur_stable([1.0, -1.0])  # a pole on the circle is not stable
    assert schur_stable([1.0, 0.0, 0.0])  # poles at 0


def test_the_verdict_agrees_with_a_simulation_of_the_simulators_plant(tmp_path: Path) -> None:
    cases: list[dict[str, Any]] = []
    simulated: list[str] = []
    server: list[bool] = []
    for name, with_friction in PLANTS.items():
        params = dataclasses.replace(
            with_friction, coulomb_friction_nm=0.0, limit1_count=None, limit2_count=None
        )
        for gains in GRID:
            loop = slap2_loop(_motor(params), *gains)
            num, den = _browser_plant(loop.plant_d)
            cases.append(
                {
                    "plant": name,
                    "gains": dict(zip(("kp", "ki", "kd"), gains, strict=True)),
                    "model": {
                        "controller": LAW("slap2").controller.model_dump(),
                        "plant_num": num,
                        "plant_den": den,
                    },
                }
            )
            simulated.append(_simulate(params, gains))
            server.append(loop.stable)
    browser = _browser_verdicts(cases, tmp_path)
    assert "undecided" not in simulated
    truth = [s == "stable" for s in simulated]
    wrong = [
        (c["plant"], c["gains"], s, v)
        for c, s, v in zip(cases, simulated, server, strict=True)
        if (s == "stable") != v
    ]
    assert not wrong, wrong
    assert browser == truth
    # both verdicts occur on the grid, and ki = 0 is among the stable ones
    assert 0.2 < sum(truth) / len(truth) < 0.9
    assert any(t and c["gains"]["ki"] == 0 for c, t in zip(cases, truth, strict=True))


def test_ki_zero_is_not_unstable_anywhere() -> None:
    """The issue: kp/ki/kd 1676/0/1100 (the auto-tune's own proposal, measured 0.63 %
    overshoot) read "CLOSED LOOP: UNSTABLE" beside GM 10.8 dB / PM 18.1 deg."""
    plant = plant_from_identification(LAW("slap2"), IDENTIFIED["slap2"])
    gains = {"kp": 1676, "ki": 0, "kd": 1100}
    loop = loop_for(LAW("slap2"), plant, gains)
    assert loop.stable
    margins = loop.margins()
    assert margins.stable and margins.gain_margin_db > 0 and margins.phase_margin_deg > 0
    run = {
        "device": "slap2",
        "test": {"kind": "frequency_response", "low_hz": 1.0, "high_hz": 10.0},
        "params": gains,
        "plant_model": IDENTIFIED["slap2"] | {"friction_pwm": 3.6},
    }
    model = frf.analyse_run(LAW(run["device"]), run, None)["model"]
    assert model["margins"]["stable"] is True


def test_browser_and_server_agree_on_the_what_ifs_inputs(tmp_path: Path) -> None:
    cases: list[dict[str, Any]] = []
    server: list[bool] = []
    slap2 = plant_from_identification(LAW("slap2"), IDENTIFIED["slap2"])
    slap2_model = browser_model(LAW("slap2"), slap2, {})
    for kp, ki, kd in itertools.product(
        (1, 20, 100, 400, 1000, 1676, 2500, 4000), (0, 1, 10, 100, 1000), (0, 50, 300, 1100, 3000)
    ):
        gains = {"kp": kp, "ki": ki, "kd": kd}
        cases.append({"model": slap2_model, "gains": gains})
        server.append(loop_for(LAW("slap2"), slap2, gains).stable)
    z1100 = plant_from_identification(LAW("z1100"), IDENTIFIED["z1100"])
    for stm in (1, 4):
        z_model = browser_model(LAW("z1100"), z1100, {"stm": stm})
        for k, a, b in itertools.product((1, 8, 32, 96, 255), (0, 16, 64, 255), (0, 8, 64)):
            gains = {"kabd_k": k, "kabd_a": a, "kabd_b": b, "stm": stm}
            cases.append({"model": z_model, "gains": gains})
            server.append(loop_for(LAW("z1100"), z1100, gains).stable)
    browser = _browser_verdicts(cases, tmp_path)
    assert browser == server
    assert 0.1 < sum(server) / len(server) < 0.95


@pytest.mark.parametrize("ki", [0, 10])
def test_the_model_bode_margins_table_and_verdict_agree(ki: int) -> None:
    plant = plant_from_identification(LAW("slap2"), IDENTIFIED["slap2"])
    loop = loop_for(LAW("slap2"), plant, {"kp": 600, "ki": ki, "kd": 1500})
    assert loop.margins().stable is loop.stable is True


def test_browser_and_server_read_the_same_margins(tmp_path: Path) -> None:
    """The what-if's margins (web/src/stability.ts ``modelMargins``) are the server's
    (``LoopModel.margins``: the margins table, the model Bode, the auto-tune) for the
    same plant and gains: the same grid, interpolation and rule."""
    plant = plant_from_identification(LAW("slap2"), IDENTIFIED["slap2"])
    model = browser_model(LAW("slap2"), plant, {})
    cases = [
        {"model": model, "gains": {"kp": kp, "ki": ki, "kd": kd}}
        for kp, ki, kd in [
            (40, 40, 80),
            (600, 10, 1500),
            (1676, 0, 1100),
            (600, 3000, 1500),
            (361, 0, 2815),
        ]
    ]
    z_plant = plant_from_identification(LAW("z1100"), IDENTIFIED["z1100"])
    cases += [
        {
            "model": browser_model(LAW("z1100"), z_plant, {}),
            "gains": {"kabd_k": k, "kabd_a": a, "kabd_b": b},
        }
        for k, a, b in [(24, 16, 8), (96, 64, 8)]
    ]
    browser = stability_ts.evaluate(cases, tmp_path, "modelMargins(c.model, c.gains)")
    for case, got in zip(cases, browser, strict=True):
        device = "slap2" if case["model"]["law"] == "slap2_pid" else "z1100"
        truth = loop_for(
            LAW(device), plant if device == "slap2" else z_plant, case["gains"]
        ).margins()
        for key, value in (
            ("phaseMarginDeg", truth.phase_margin_deg),
            ("gainMarginDb", truth.gain_margin_db),
            ("crossoverHz", truth.gain_crossover_hz),
        ):
            assert got[key] == pytest.approx(value, abs=1e-6, rel=1e-6), (case["gains"], key, got)
