"""What-if prediction against the measured verification run, on every demo plant
(issue 9, "3. What-if gains" and "Tests").

For each demo plant (the SLAP2 line's unloaded module 0 and loaded module 1; the
Z1100's motors x, y, z with 0, 5x and 20x the rotor inertia and the demo's flash
gains), end to end through the API on a real pty: the auto-tune's Identify fits the
plant, the server-side model the what-if view uses (``plant_from_identification``,
``loop_for``: the identified plant discretised with a zero-order hold at the
controller period under the device's exact law) predicts the verification step of
the gains in use, driven by the verification step's own profile (the SLAP2
firmware's trapezoid at sv/sa maximum, the Z1100 chip's at its Vmax/Acc), and the
bench runs that step on the simulator. Predicted overshoot and settling time must
agree with the measured run within the tolerances below.

The Z1100's prediction is ``simulate_move`` at the chip's sample (``predict``): the law
with KABH during the move and KABD at rest, as the chip and the browser's
``predictStep`` run it (the linear KABD-only ``loop`` agreed with it within 0.04 pp and
0 ms on these moves when this test was written). Where the model's loop is unstable (the
loaded SLAP2 module with the default gains: phase margin about -4 deg) the test checks
that the measured run does not settle either.

The samples carry host-clock stamps; the horizon is the last one minus the run's
``t0_s`` (the first version took the stamp itself, some thousand seconds of 32-us
ticks, and the state-space simulation then in ``LoopModel.response`` grew to 17 GB).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from servotune.bench.metrics import compute_metrics
from servotune.config import LinkSpec
from servotune.devices import default_registry
from servotune.devices.slap2.codec import ACCELERATION_MAX, VELOCITY_MAX
from servotune.devices.slap2.profile import TrapezoidGenerator
from servotune.devices.z1100.law import Kab, MoveProfile, simulate_move
from servotune.tuning.loops import LoopModel
from servotune.tuning.plants import Z1100Plant
from servotune.tuning.whatif import loop_for, plant_from_identification
from tests.support.autotune import LIMITS as SLAP2_LIMITS
from tests.support.bench import finished_run, start
from tests.support.servers import LiveServer, live_server
from tests.support.sim_lines import Z1100_BAUD, demo_line, z1100_chip_process

# The devices' controller laws, looked up as the app does.
LAW = default_registry().law

Z1100_LIMITS = {"max_pwm": 80, "max_distance_counts": 20_000, "response": "no_overshoot"}
DISTANCE = {"slap2": 2000, "z1100": 2000}  # the what-if view's default step
RETAKES = 2  # a run whose overshoot or settling the bench nulls as untrusted

# Tolerances per device, from 6 runs of each plant (2026-12-03; measured - predicted):
#   slap2-unloaded  overshoot +1.7..+3.4 pp   settling +47, -3, +72, +43, +66, +65 ms
#   z1100-x/y/z     overshoot -0.11..+0.23 pp settling -3..0 ms
# SLAP2 overshoot: the model leaves out Coulomb friction (identified 1.45 PWM) and the
#   firmware's integer PWM; the measured peak came 1.7-3.4 pp above the linear one
#   each time. 5 pp: 1.5x the worst.
# SLAP2 settling: the step's error rings with a half period of 29 ms, each lobe a third
#   of the one before, and the +-5-count band sits at the 5th lobe (4 to 7 counts for
#   tau 7.6 to 8.1 ms): one lobe more or less is +-29 ms. Friction (not in the model)
#   holds the last small lobes outside the band until the integrator has wound up, so
#   the measured settling comes later, by up to two lobes seen (+72 ms); it can also
#   damp a lobe into the band (-3 ms). Window: one lobe early, three late.
# Z1100 (overshoot 0-0.5 %: these plants follow the profile within the 20-count band,
#   so settling is about the profile's end plus the trigger latency, a weak check of
#   the loop): 0.5 pp (2x the worst), settling +-10 ms.
# Both settling windows are widened by the record's largest sample gap: the measured
#   settling is the first sample back in the band, so it is quantised by the sample
#   spacing, which depends on the host's load, not on the loop.
OVERSHOOT_TOLERANCE_PP = {"slap2": 5.0, "z1100": 0.5}
SETTLING_WINDOW_S = {"slap2": (-0.035, 0.10), "z1100": (-0.01, 0.01)}  # measured - predicted

PLANTS = {
    "slap2-unloaded": ("slap2", "line-0"),
    "slap2-loaded": ("slap2", "line-1"),
    "z1100-x": ("z1100", "line-x"),
    "z1100-y": ("z1100", "line-y"),
    "z1100-z": ("z1100", "line-z"),
}


@contextlib.asynccontextmanager
async def demo_server(tmp_path: Path, device: str) -> AsyncIterator[LiveServer]:
    if device == "slap2":
        with demo_line(tmp_path) as (simulator, bus):
            async with live_server(simulator, bus, tmp_path / "data") as server:
                yield server
    else:
        with z1100_chip_process(tmp_path) as (simulator, _):
            spec = LinkSpec("z1100", simulator.path, "line", Z1100_BAUD, [0, 1, 2], 512)
            async with live_server(simulator, None, tmp_path / "data", spec=spec) as server:
                yield server


def slap2_setpoint_per_tick(distance: int, ticks: int) -> np.ndarray:
    """The SLAP2 verification step's setpoint at every controller tick from its start
    (the firmware's trapezoid at sv/sa maximum)."""
    generator = TrapezoidGenerator.from_wire(0.0, distance, VELOCITY_MAX, ACCELERATION_MAX)
    return np.array([generator.step() for _ in range(ticks)])


async def measured_run(server: LiveServer, axis_id: str, kind: str, distance: int) -> Any:
    """The verification step, retaken (at most RETAKES times) while the bench nulls its
    overshoot or settling time as untrusted (a starved host's sparse samples)."""
    for _ in range(1 + RETAKES):
        run = await finished_run(
            server, axis_id, await start(server, axis_id, kind=kind, distance=distance)
        )
        assert run["status"] == "complete", run["message"]
        untrusted = run["quality"]["untrusted"]
        if "overshoot_pct" not in untrusted and "settling_time_s" not in untrusted:
            return run
        print(f"\n{axis_id}: retaking a run with untrusted metrics: {untrusted}")
    pytest.fail(f"{axis_id}: {1 + RETAKES} runs, each with untrusted metrics: {untrusted}")


def predict(
    device: str,
    loop: LoopModel,
    plant: dict[str, Any],
    params: dict[str, Any],
    verify: dict[str, Any],
    distance: int,
    horizon_s: float,
) -> tuple[np.ndarray, np.ndarray, str]:
    """The predicted verification step from rest at 0, per controller tick: (times
    from the step's start, positions, what predicted it).

    SLAP2: ``loop.response`` (the linear law, one gain set) on the firmware's trapezoid.
    Z1100: ``simulate_move`` at the chip's own sample (coarse 1): its law with KABH while
    the profile runs and KABD at rest, as the chip and the what-if view's
    ``predictStep`` (web/src/ui/whatif.ts) switch them (``loop``, ``Z1100Law.loop``, is
    linear with KABD only: on these moves it agreed within 0.04 pp and 0 ms, measured
    when this test was written)."""
    ticks = max(2, round(horizon_s / loop.period_s))
    if device == "slap2":
        t, y = loop.response(slap2_setpoint_per_tick(distance, ticks))
        return t, y, "linear"
    kabh, kabd = (
        Kab(params[f"{g}_k"], params[f"{g}_a"], params[f"{g}_b"]) for g in ("kabh", "kabd")
    )
    profile = MoveProfile(
        distance, verify["velocity_counts_s"], verify["acceleration_counts_s2"], params["stm"]
    )
    sim = simulate_move(
        Z1100Plant(float(plant["gain_counts_s_per_duty"]), float(plant["tau_s"])),
        kabh,
        kabd,
        profile,
        hold_s=max(0.0, horizon_s - profile.time_s()),
        record_every=1,
        coarse=1,
    )
    return np.asarray(sim.t), np.asarray(sim.position), "KABH/KABD"


def metrics_of(t: np.ndarray, y: np.ndarray, latency_s: float, distance: int, band: float) -> Any:
    return compute_metrics(
        (t + latency_s).tolist(), y.tolist(), t0_s=0.0, y0=0.0, y_final=float(distance), band=band
    )


@pytest.mark.parametrize("plant", list(PLANTS))
async def test_whatif_predicts_the_verification_step_on_each_demo_plant(
    tmp_path: Path, plant: str
) -> None:
    started = time.monotonic()
    device, axis_id = PLANTS[plant]
    limits = SLAP2_LIMITS if device == "slap2" else Z1100_LIMITS
    async with demo_server(tmp_path, device) as server:
        client = server.client
        response = await client.post(
            f"/api/axes/{axis_id}/autotune/identify", json=limits, timeout=120
        )
        assert response.status_code == 200, response.text
        info = (await client.get(f"/api/axes/{axis_id}/whatif")).json()
        assert info["model"] is not None, info["problem"]
        params = (await client.get(f"/api/axes/{axis_id}/params")).json()
        session = (await client.get(f"/api/axes/{axis_id}/autotune")).json()
        identified = plant_from_identification(LAW(device), session["model"])
        loop = loop_for(LAW(device), identified, params)
        assert loop.period_s == info["model"]["period_s"]

        distance = DISTANCE[device]
        run = await measured_run(server, axis_id, info["verify"]["kind"], distance)
        measured = run["metrics"]
        band = float(measured["band"])
        latency_s = run.get("trigger_latency_s") or 0.0
        # the samples carry the host clock's stamps (time.monotonic), the step starts
        # at the run's t0_s; the prediction starts when the device latched the trigger
        horizon_s = max(0.3, run["samples"][-1][0] - run["t0_s"]) - latency_s
        margins = loop.margins()
        if not margins.stable:
            print(
                f"\n{plant}: the model's loop is unstable with {info['gains']} "
                f"(phase margin {margins.phase_margin_deg:.1f} deg, gain margin "
                f"{margins.gain_margin_db:.1f} dB); measured overshoot "
                f"{measured['overshoot_pct']} %, settling {measured['settling_time_s']}, "
                f"oscillations {measured['oscillations']}, untrusted {run['quality']['untrusted']}"
            )
            assert measured["settling_time_s"] is None
            return
        t, y, how = predict(
            device, loop, session["model"], params, info["verify"], distance, horizon_s
        )
        predicted = metrics_of(t, y, latency_s, distance, band)

        def ms(value: float | None) -> str:
            return "never" if value is None else f"{value * 1000:.0f} ms"

        def pct(value: float | None) -> str:
            return "  none" if value is None else f"{value:6.2f}"

        print(
            f"\n{plant:15s} gains {info['gains']} plant {session['model']}"
            f"\n  {'':20s} overshoot   settling  (band ±{band}, latency "
            f"{latency_s * 1000:.0f} ms, horizon {horizon_s:.2f} s, samples "
            f"{len(run['samples'])}, max gap {measured['max_sample_gap_s']} s)"
            f"\n  {'predicted ' + how:20s} {pct(predicted.overshoot_pct)} %   "
            f"{ms(predicted.settling_time_s)}"
            f"\n  {'measured':20s} {pct(measured['overshoot_pct'])} %   "
            f"{ms(measured['settling_time_s'])}"
            f"\n  case time {time.monotonic() - started:.1f} s"
        )
        assert predicted.overshoot_pct is not None and measured["overshoot_pct"] is not None
        assert predicted.settling_time_s is not None and measured["settling_time_s"] is not None
        assert predicted.overshoot_pct == pytest.approx(
            measured["overshoot_pct"], abs=OVERSHOOT_TOLERANCE_PP[device]
        )
        early_s, late_s = SETTLING_WINDOW_S[device]
        gap_s = float(measured["max_sample_gap_s"] or 0.0)
        late_by_s = measured["settling_time_s"] - predicted.settling_time_s
        assert early_s - gap_s <= late_by_s <= late_s + gap_s, (
            f"measured settling {late_by_s * 1000:+.0f} ms from the prediction, outside "
            f"{early_s * 1000:+.0f}..{late_s * 1000:+.0f} ms (+- max gap {gap_s * 1000:.0f} ms)"
        )
