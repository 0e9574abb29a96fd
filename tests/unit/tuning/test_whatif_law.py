"""The controller law as data (``schema.ControllerLaw``, each device's ``CONTROLLER``)
is the law the server computes with, in Python and in the browser.

* Its linear view (``tuning.loops.law_polynomials``) has the frequency response of the
  devices' own polynomials (``slap2_pid_polynomials``, ``z1100_kab_polynomials``) to
  1e-12 on a grid, for several gains (ki = 0, b = 0 included).
* The browser's generic evaluation (web/src/stability.ts, compiled and run under node):
  ``openLoop`` equals the server's open loop (``DeviceLaw.loop`` around the identified
  plant, python-control) at several frequencies and gains, SLAP2 and Z1100 (Stm 1 and
  4); ``LawRunner`` tick by tick equals the Z1100's ``KabLaw`` (the chip's arithmetic,
  KABH while moving, KABD at rest) output for output, and the SLAP2's ``PidLaw`` (the
  firmware's) wherever the firmware neither shifts away a fraction nor clamps.
* The bench info says what the web client no longer decides by device name: the
  velocity field's parameter and unit, whether the what-if works, and whether the
  frequency response is measured.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import control
import httpx
import numpy as np
import pytest

from servotune.api.app import AppConfig, create_app
from servotune.api.bench_routes import bench_fields
from servotune.config import LinkSpec
from servotune.demo import demo_simulators
from servotune.devices import default_registry
from servotune.devices.slap2.law import CONTROLLER as SLAP2_CONTROLLER
from servotune.devices.slap2.law import Gains, PidLaw, slap2_pid_polynomials
from servotune.devices.z1100.law import CONTROLLER as Z1100_CONTROLLER
from servotune.devices.z1100.law import Kab, KabLaw, z1100_kab_polynomials
from servotune.link.base import BenchPlanner, BenchTest, Sample
from servotune.tuning.loops import law_polynomials
from servotune.tuning.whatif import browser_model, loop_for, plant_from_identification
from tests.support import stability_ts

LAW = default_registry().law
IDENTIFIED = {
    "slap2": {"gain_counts_s_per_pwm": 1058.307, "tau_s": 0.024},
    "z1100": {"gain_counts_s_per_duty": 30000.0, "tau_s": 0.012},
}
SLAP2_GAINS = [(600, 10, 1500), (1676, 0, 1100), (40, 40, 80), (1, 3000, 0), (2500, 1, 3000)]
Z1100_GAINS = [(24, 16, 8), (96, 64, 8), (1, 0, 0), (255, 255, 64), (8, 0, 0)]


def _response(poly: tuple[np.ndarray, np.ndarray], z: np.ndarray) -> np.ndarray:
    return np.asarray(np.polyval(poly[0], z) / np.polyval(poly[1], z))


@pytest.mark.parametrize("gains", SLAP2_GAINS)
def test_the_slap2_terms_are_its_pid(gains: tuple[int, int, int]) -> None:
    period = LAW("slap2").period_s({})
    z = np.exp(2j * np.pi * np.geomspace(0.1, 0.49 / period, 200) * period)
    forward, feedback = law_polynomials(
        SLAP2_CONTROLLER, dict(zip(("kp", "ki", "kd"), gains, strict=True))
    )
    truth = _response(slap2_pid_polynomials(*gains), z)
    assert np.max(np.abs(_response(forward, z) - truth) / np.abs(truth)) < 1e-12
    assert not np.any(feedback[0])  # the PID acts on the error only
    # an integrator only where ki is not 0 (a pole at z = 1 otherwise read as unstable)
    assert (forward[1].size > 1 and np.polyval(forward[1], 1.0) == 0) == (gains[1] != 0)


@pytest.mark.parametrize("gains", Z1100_GAINS)
def test_the_z1100_terms_are_its_kab_law_with_the_hold_gains(gains: tuple[int, int, int]) -> None:
    k, a, b = gains
    period = LAW("z1100").period_s({})
    z = np.exp(2j * np.pi * np.geomspace(0.1, 0.49 / period, 200) * period)
    # KABH differs: the linear view must read KABD
    params = {"kabd_k": k, "kabd_a": a, "kabd_b": b, "kabh_k": 7 * k + 1, "kabh_a": 3, "kabh_b": 99}
    forward, feedback = law_polynomials(Z1100_CONTROLLER, params)
    truth_f, truth_b = z1100_kab_polynomials(k, a, b)
    for got, truth in ((forward, truth_f), (feedback, truth_b)):
        want = _response(truth, z)
        assert np.max(np.abs(_response(got, z) - want)) <= 1e-12 * max(1.0, np.max(np.abs(want)))


def _server_open_loop(device: str, gains: dict[str, int], f: np.ndarray) -> np.ndarray:
    """The server's open loop ``(Cf + Cb) P`` of the device's law around the identified
    plant, python-control's transfer functions evaluated at ``e^{jwT}``."""
    law = LAW(device)
    assert law is not None
    loop = loop_for(law, plant_from_identification(law, IDENTIFIED[device]), gains)
    z = np.exp(2j * np.pi * f * loop.period_s)
    num, den = control.tfdata(loop.open_loop)
    return np.asarray(np.polyval(num[0][0], z) / np.polyval(den[0][0], z))


def test_the_browser_open_loop_is_the_servers(tmp_path: Path) -> None:
    cases: list[dict[str, Any]] = []
    truths: list[np.ndarray] = []
    for device, grid, stms in (
        ("slap2", [dict(zip(("kp", "ki", "kd"), g, strict=True)) for g in SLAP2_GAINS], (1,)),
        (
            "z1100",
            [dict(zip(("kabd_k", "kabd_a", "kabd_b"), g, strict=True)) for g in Z1100_GAINS],
            (1, 4),
        ),
    ):
        law = LAW(device)
        assert law is not None
        plant = plant_from_identification(law, IDENTIFIED[device])
        for stm in stms:
            for gains in grid:
                params = gains | {"stm": stm} if device == "z1100" else gains
                model = browser_model(law, plant, params)
                f = np.geomspace(0.5, 0.45 / model["period_s"], 9)
                cases.append({"model": model, "gains": params, "f": f.tolist()})
                truths.append(_server_open_loop(device, params, f))
    got = stability_ts.evaluate(cases, tmp_path, "c.f.map((f) => s.openLoop(c.model, c.gains, f))")
    for case, values, truth in zip(cases, got, truths, strict=True):
        browser = np.array([v["re"] + 1j * v["im"] for v in values])
        error = np.abs(browser - truth) / np.abs(truth)
        assert np.max(error) < 1e-9, (case["model"]["device"], case["gains"], error)


def _sequence(seed: int, ticks: int) -> list[tuple[int, int, bool]]:
    """Errors and positions of a move and its settling: moving for the first half."""
    rng = np.random.default_rng(seed)
    position = np.cumsum(rng.integers(-40, 41, ticks))
    error = np.round(300 * np.exp(-np.arange(ticks) / (ticks / 5)) * np.cos(np.arange(ticks) / 7))
    error = error.astype(int) + rng.integers(-3, 4, ticks)
    return [
        (int(e), int(y), n < ticks // 2)
        for n, (e, y) in enumerate(zip(error, position, strict=True))
    ]


def _runner_outputs(cases: list[dict[str, Any]], tmp_path: Path) -> list[list[float]]:
    expression = (
        "(() => { const r = new s.LawRunner(c.controller, c.gains);"
        " return c.sequence.map(([e, y, moving]) => r.step(e, y, moving)); })()"
    )
    outputs: list[list[float]] = stability_ts.evaluate(cases, tmp_path, expression)
    return outputs


def test_the_browser_runs_the_z1100_chips_law_tick_by_tick(tmp_path: Path) -> None:
    cases = []
    for seed, (k, a, b) in enumerate(Z1100_GAINS):
        kabh = Kab(k, a, b)
        kabd = Kab(max(1, k // 2), a + 5, b + 1)
        params = {f"kabh_{n}": v for n, v in zip("kab", (kabh.k, kabh.a, kabh.b), strict=True)}
        params |= {f"kabd_{n}": v for n, v in zip("kab", (kabd.k, kabd.a, kabd.b), strict=True)}
        cases.append(
            {
                "controller": Z1100_CONTROLLER.model_dump(),
                "gains": params,
                "sequence": _sequence(seed, 400),
                "kab": (kabh, kabd),
            }
        )
    outputs = _runner_outputs([{k: v for k, v in c.items() if k != "kab"} for c in cases], tmp_path)
    limit = LAW("z1100").output_limit  # type: ignore[union-attr]
    clamped = 0
    for case, got in zip(cases, outputs, strict=True):
        chip = KabLaw(*case["kab"])
        want = [chip.step(e, y, moving) for e, y, moving in case["sequence"]]
        assert [max(-limit, min(limit, u)) for u in got] == want, case["gains"]
        clamped += sum(abs(u) > limit for u in got)
    assert clamped  # the clamp is part of what was compared


def test_the_browser_runs_the_slap2_pid_tick_by_tick(tmp_path: Path) -> None:
    cases = [
        {
            "controller": SLAP2_CONTROLLER.model_dump(),
            "gains": dict(zip(("kp", "ki", "kd"), gains, strict=True)),
            "sequence": _sequence(seed, 400),
        }
        for seed, gains in enumerate(SLAP2_GAINS)
    ]
    outputs = _runner_outputs(cases, tmp_path)
    compared = 0
    for case, got in zip(cases, outputs, strict=True):
        g = case["gains"]
        firmware = PidLaw(Gains(g["kp"], g["ki"], g["kd"]))
        integral, e_prev = 0, 0
        for (e, _y, _moving), u in zip(case["sequence"], got, strict=True):
            # the what-if's law: the exact quotient (no shift, no clamp of the sum)
            integral += e
            exact = (16 * g["kp"] * e + g["ki"] * integral + 32 * g["kd"] * (e - e_prev)) / 4096
            e_prev = e
            assert u == exact
            pwm = firmware.step(e)
            if abs(exact) < 255 and firmware.integral == integral:
                assert pwm == np.floor(exact)  # the firmware's >> 12
                compared += 1
    assert compared > 1000


async def test_the_bench_info_says_what_the_client_no_longer_decides_by_name(
    tmp_path: Path,
) -> None:
    """Through the API of the demo's six axes: velocity field, what-if, FRF kind."""
    data_dir = tmp_path / "data"
    config = AppConfig(
        data_dir=data_dir,
        simulators=demo_simulators(data_dir),
        web_dir=tmp_path / "no-web",
        twin=False,
    )
    app = create_app(config)
    transport = httpx.ASGITransport(app=app)
    async with (
        app.router.lifespan_context(app),
        httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1") as client,
    ):
        infos = {}
        for axis in (await client.get("/api/axes")).json():
            response = await client.get(f"/api/axes/{axis['id']}/bench")
            assert response.status_code == 200, response.text
            infos[axis["id"]] = (axis["device"], response.json())
    seen = {device: info for device, info in infos.values()}
    assert set(seen) == {"slap2", "z1100", "ep7047"}
    slap2, z1100, ep7047 = seen["slap2"], seen["z1100"], seen["ep7047"]
    assert slap2["fields"]["velocity"]["parameter"] == "velocity"
    assert z1100["fields"]["velocity"]["parameter"] == "vmax"
    assert slap2["fields"]["velocity"]["unit"] != z1100["fields"]["velocity"]["unit"]
    assert ep7047["fields"]["velocity"]["parameter"] is None
    assert (slap2["whatif"], z1100["whatif"], ep7047["whatif"]) == (True, True, False)
    assert slap2["frequency_response"] == "measured"
    assert z1100["frequency_response"] == "model"
    assert ep7047["frequency_response"] is None
    for _device, info in infos.values():
        assert set(info["fields"]) == {"distance", "velocity", "pwm"}
        assert info["fields"]["distance"]["unit"]


@pytest.mark.parametrize("device", ["slap2", "z1100"])
def test_the_velocity_field_is_the_parameter_a_velocity_step_sets(device: str) -> None:
    """The descriptor's ``bench_velocity_parameter`` is what the axis' bench plan of a
    velocity step writes, and the field has that parameter's unit and conversions."""
    spec = LinkSpec(device, "/dev/null", "line", 9600, [0, 1, 2] if device == "z1100" else [0], 64)
    axis = default_registry().get(device).build_link(spec, None).axes[0]  # type: ignore[arg-type]
    assert isinstance(axis, BenchPlanner)
    latest = Sample(0.0, {"position": 0.0, "velocity": 0.0}, {})
    plan = axis.bench_plan(BenchTest("velocity_step", velocity=3), latest, {})
    descriptor = axis.descriptor
    assert set(plan.overrides) == {descriptor.bench_velocity_parameter}
    parameter = descriptor.parameter(descriptor.bench_velocity_parameter or "")
    field = bench_fields(descriptor)["velocity"]
    assert (field.parameter, field.unit) == (parameter.name, parameter.unit)
    assert field.conversions == parameter.conversions
