"""The shared tuning core's pieces (server/servotune/tuning): the fits recover known
plants, each device's law is the simulator's law tick for tick, the device interface
gives the linear loops, and the import graph runs one way.

The fits are checked against data made by other code than the model they fit:
scipy's own simulation of the linear plant (``scipy.signal.lsim``), and the firmware
and chip simulators (``sim/``) for the laws.
"""

from __future__ import annotations

import ast
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from servotune.devices import default_registry
from servotune.devices.slap2.codec import (
    ACCELERATION_MAX,
    COUNTS_S2_PER_SA,
    COUNTS_S_PER_SV,
    VELOCITY_MAX,
)
from servotune.devices.slap2.law import (
    Gains,
    MoveSpec,
    PidLaw,
    Staircase,
    simulate_response,
    slap2_loop_for,
)
from servotune.devices.slap2.sim.controller import TICK_S
from servotune.devices.slap2.sim.module import Slap2Module
from servotune.devices.z1100 import codec
from servotune.devices.z1100.codec import Gains as ChipGains
from servotune.devices.z1100.law import Kab, KabLaw, z1100_loop_for
from servotune.devices.z1100.sim.chip import Z1100Chip
from servotune.devices.z1100.sim.demo import Z1100_LOADS_KG_M2
from servotune.devices.z1100.sim.servo import AxisParameters
from servotune.tuning.identify import fit_closed_loop, fit_plant
from servotune.tuning.plants import IdentifiedPlant, PlantModel
from tests.support.paths import PACKAGE as SERVER

# The devices' controller laws, looked up as the app does.
LAW = default_registry().law


# --- fits ----------------------------------------------------------------------------


def test_open_loop_fit_recovers_a_plant_simulated_by_scipy() -> None:
    """P(s) = K / (s (tau s + 1)) under a PWM staircase, simulated by scipy (lsim with a
    zero-order hold of the staircase), sampled every ~23 ms and quantised to counts:
    the fit finds K within 1 %, tau within 5 %, no friction."""
    gain, tau = 950.0, 0.024
    levels = [2, 3, 4, 6, 9, 14, 0]
    schedule = [(0.1 + 0.15 * k, float(u)) for k, u in enumerate(levels)]
    t = np.arange(0.0, 1.3, 1e-4)
    u = np.zeros_like(t)
    for when, level in schedule:
        u[t >= when] = level
    system = signal.lti([gain], [tau, 1.0, 0.0])
    _, y, _ = signal.lsim(system, u, t, interp=False)
    rng = np.random.default_rng(4)
    idx = np.unique(np.cumsum(rng.integers(150, 300, 80)))
    idx = idx[idx < t.size]
    fitted = fit_plant(list(t[idx]), list(np.floor(y[idx] + 0.5)), schedule)
    assert fitted.gain == pytest.approx(gain, rel=0.01)
    assert fitted.tau_s == pytest.approx(tau, rel=0.05)
    assert fitted.friction_pwm < 0.05
    assert fitted.rms_error_counts < 1.0


def test_closed_loop_fit_recovers_gain_tau_and_delay() -> None:
    """``fit_closed_loop`` with a simulation whose answer is known (a first-order lag
    of a known gain, read 15 ms late): gain, tau and delay come back."""

    def simulate(gain: float, tau: float) -> tuple[list[float], list[float]]:
        ts = np.arange(0.001, 0.5, 0.001)
        return list(ts), list(gain * 1e-3 * (1.0 - np.exp(-ts / tau)))

    true_t, true_y = simulate(200_000.0, 0.03)
    times = [t + 0.015 for t in true_t[::20]]
    values = true_y[::20]
    starts = [(g, tau, d) for g in (1e5, 4e5) for tau in (0.01, 0.1) for d in (0.0, 0.02)]
    fit = fit_closed_loop(times, values, simulate, starts)
    assert fit.gain == pytest.approx(200_000.0, rel=0.01)
    assert fit.tau_s == pytest.approx(0.03, rel=0.02)
    assert fit.delay_s == pytest.approx(0.015, abs=0.001)


def test_staircase_levels_and_brake() -> None:
    plan = Staircase(max_pwm=20, max_distance_counts=4000)
    levels = [plan.first_pwm()]
    while levels[-1] < 20:
        levels.append(plan.next_pwm(levels[-1]))
    assert levels == [2, 3, 4, 6, 9, 14, 20]
    assert not plan.must_brake(travel=1000, speed=1000, gap_s=0.05)  # 1150 < 2000
    assert plan.must_brake(travel=1900, speed=1000, gap_s=0.05)
    assert plan.finished(6, travel=601, elapsed_s=0.5, braked=False)  # 30 % of 2000
    assert not plan.finished(6, travel=599, elapsed_s=0.5, braked=False)


# --- the laws, tick for tick ------------------------------------------------------------


def _send(module: Slap2Module, line: str) -> None:
    for byte in f"{line}\r".encode():
        module.receive(byte)


@pytest.mark.parametrize(
    ("gains", "saturates"),
    [(Gains(40, 40, 80), False), (Gains(2000, 100, 1500), True), (Gains(60, 2000, 0), True)],
)
def test_slap2_law_is_the_firmware_simulators_tick_for_tick(gains: Gains, saturates: bool) -> None:
    """The firmware simulator's PWM at every tick of a position step equals ``PidLaw``
    fed with the error it saw (setpoint after the generator minus the count before the
    tick), including integral clamping and PWM saturation."""
    module = Slap2Module(0)
    module.take_output()
    profile = (f"sv{VELOCITY_MAX}", f"sa{ACCELERATION_MAX}", "pm")
    for line in (f"kp{gains.kp}", f"ki{gains.ki}", f"kd{gains.kd}", *profile):
        _send(module, line)
    law = PidLaw(gains)
    _send(module, "mr1500")
    saturated = 0
    peak = 0
    for _ in range(600):
        before = module.position
        module.tick()
        e = module.setpoint - before
        assert law.step(e) == module.pwm
        saturated += abs(module.pwm) == 255
        peak = max(peak, abs(module.pwm))
    assert peak > 20  # the step did move the loop
    assert (saturated > 0) == saturates  # where expected, the clamp is exercised


def test_simulated_response_runs_the_same_law() -> None:
    """``simulate_response`` (the law inlined for speed) agrees with ``PidLaw`` at every
    tick of its own record."""
    model = PlantModel(gain=950.0, tau_s=0.024, friction_pwm=1.2)
    gains = Gains(300, 40, 400)
    run = simulate_response(model, gains, MoveSpec(1000, VELOCITY_MAX, ACCELERATION_MAX))
    law = PidLaw(gains)
    count = 0  # the motor starts at x = 0.5
    for setpoint, position, pwm in zip(run.setpoint, run.position, run.pwm, strict=True):
        assert law.step(setpoint - count) == pwm
        count = position


def test_z1100_law_is_the_chip_simulators_sample_for_sample(tmp_path: Path) -> None:
    """The chip simulator's PWM at every sample of a 10 000-count move equals
    ``KabLaw`` fed with the error and position it saw, KABH while the profile runs and
    KABD (different gains here) after it."""
    kabh, kabd = Kab(32, 16, 8), Kab(12, 64, 4)
    params = AxisParameters(
        kabh=ChipGains(kabh.k, kabh.a, kabh.b),
        kabd=ChipGains(kabd.k, kabd.a, kabd.b),
        vmax_counts_s=100_000,
        acc_counts_s2=1_000_000,
        limit_counts=4000,
        hvm_counts_s=20_000,
        hac_counts_s2=200_000,
    )
    flash = tmp_path / "flash.json"
    flash.write_text(json.dumps({"axes": [params.to_json()] * 3}))
    chip = Z1100Chip.with_loads(Z1100_LOADS_KG_M2, flash_path=flash)
    sample_s = 32e-6
    t = 0.0
    for request in (
        codec.make_set_job(0, codec.Job.TARGET),
        codec.make_set_target(0, 10_000),
        codec.make_start([0]),
    ):
        for byte in request.encode():
            t += 1e-5
            chip.advance_to(t)
            chip.receive(byte)
    assert chip.axis_state(0).encoder_counts == 0  # at rest: the windows hold zeros
    law = KabLaw(kabh, kabd)
    tick = math.floor(t / sample_s)
    ran_kabd = 0
    for _ in range(int(0.3 / sample_s)):
        tick += 1
        chip.advance_to(tick * sample_s + 1e-9)
        state = chip.axis_state(0)
        pwm = law.step(state.error_counts, state.encoder_counts, state.running)
        assert pwm == round(state.duty * 255)
        ran_kabd += not state.running
    assert ran_kabd > 1000  # the hold gains were exercised too


# --- the device interface ------------------------------------------------------------


def test_device_laws_give_the_loops_of_tuning_loops() -> None:
    plant = IdentifiedPlant(950.0, 0.024, "test")
    slap2 = LAW("slap2").loop(plant, {"kp": 40, "ki": 40, "kd": 80})
    direct = slap2_loop_for(plant.transfer_function(), 40, 40, 80)
    f = np.geomspace(1.0, 200.0, 50)
    assert np.allclose(slap2.open_loop_response(f).response, direct.open_loop_response(f).response)
    assert LAW("slap2").period_s({}) == TICK_S
    params = {"kabd_k": 12, "kabd_a": 64, "kabd_b": 4, "stm": 2}
    z = LAW("z1100").loop(IdentifiedPlant(1000.0, 0.01, "test"), params)
    zdirect = z1100_loop_for(
        IdentifiedPlant(1000.0, 0.01, "test").transfer_function(), 12, 64, 4, 2
    )
    assert np.allclose(z.open_loop_response(f).response, zdirect.open_loop_response(f).response)
    assert LAW("z1100").period_s(params) == pytest.approx(64e-6)
    assert LAW("z1100").linear_plant({"gain_counts_s_per_duty": 255_000.0, "tau_s": 0.01}) == (
        IdentifiedPlant(1000.0, 0.01, "auto-tune identification")
    )
    with pytest.raises(ValueError, match="does not describe a slap2"):
        LAW("slap2").linear_plant({"gain_counts_s_per_duty": 1.0, "tau_s": 0.01})
    assert LAW("ep7047") is None and LAW("modbus") is None
    # what the what-if route and the gains check read of a law (unchanged API values)
    assert LAW("slap2").gain_names == ("kp", "ki", "kd")
    assert LAW("z1100").gain_names == ("kabh_k", "kabh_a", "kabh_b", "kabd_k", "kabd_a", "kabd_b")
    assert LAW("slap2").verify_profile({"vmax": 1}).to_dict() == {
        "kind": "position_step",
        "velocity_counts_s": VELOCITY_MAX * COUNTS_S_PER_SV,
        "acceleration_counts_s2": ACCELERATION_MAX * COUNTS_S2_PER_SA,
    }
    assert LAW("z1100").verify_profile({"vmax": 5000, "acc": 70_000}).to_dict() == {
        "kind": "move",
        "velocity_counts_s": 5000.0,
        "acceleration_counts_s2": 70000.0,
    }


# --- layering ------------------------------------------------------------------------


def _imports(path: Path) -> set[str]:
    """Every servotune module a file imports, at any depth (function-level included)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("servotune"))
        elif (
            isinstance(node, ast.ImportFrom)
            and node.module
            and node.level == 0
            and node.module.startswith("servotune")
        ):
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names)
    return found


def _module_graph() -> dict[str, set[str]]:
    modules: dict[str, Path] = {}
    for path in SERVER.rglob("*.py"):
        parts = path.relative_to(SERVER.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        modules[name] = path
    return {name: {m for m in _imports(p) if m in modules} for name, p in modules.items()}


def test_tuning_and_autotune_import_one_way() -> None:
    """No import cycle through the tuning core or the auto-tune (not even a lazy,
    function-level one), and the core imports nothing of the auto-tune, drivers, hub
    or api."""
    graph = _module_graph()
    ours = [m for m in graph if m.startswith(("servotune.tuning", "servotune.autotune"))]
    assert "servotune.autotune.service" in ours and "servotune.tuning.identify" in ours
    for start in ours:
        # every module reachable from start; start must not be among them
        seen: set[str] = set()
        todo = [m for m in graph[start] if m != start and not start.startswith(m + ".")]
        while todo:
            m = todo.pop()
            if m in seen:
                continue
            seen.add(m)
            todo.extend(n for n in graph.get(m, ()) if not m.startswith(n + "."))
        assert start not in seen, f"{start} imports itself through {sorted(seen & set(ours))}"
    # The link layer and every device's driver side (link, axis, exchange, cycle...);
    # a law or a codec of a device is not a driver.
    drivers = tuple(
        f"servotune.devices.{device}.{part}"
        for device, parts in {
            "slap2": ("exchange", "link", "axis", "capture", "descriptor"),
            "z1100": ("link", "axis", "descriptor"),
            "ep7047": ("link", "requests", "handshakes", "cycle", "descriptor"),
        }.items()
        for part in parts
    )
    forbidden = ("servotune.autotune", "servotune.link", *drivers, "servotune.hub", "servotune.api")
    for module in ours:
        if module.startswith("servotune.tuning"):
            bad = {m for m in graph[module] if m.startswith(forbidden)}
            assert not bad, f"{module} imports {bad}"
