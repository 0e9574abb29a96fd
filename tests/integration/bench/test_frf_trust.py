"""A measured frequency response is right where it says it is trusted.

* The physical check: on every demo SLAP2 plant (the unloaded module; the loaded one,
  with its Coulomb friction) with stable gains, a run of the bench (1-10 Hz, 200
  counts, 6 s, the SLAP2 firmware simulator on a scripted wire: ``tests/support/frf_harness.py``)
  reads, at every tone it marks trusted, the simulator's closed loop within 0.5 dB
  and 5 deg, and 0 dB / 0 deg within the same where the loop follows its input (the
  model's T within 0.1 dB and 2 deg of 1: well below the bandwidth) - quiet, and with
  host stalls injected (a share of the exchanges stamped up to 80 ms late), on every
  run. A quiet run trusts most of its tones (the check is not passed by trusting
  none); a stalled one says what it left out and bounded.
* The coherence is the magnitude-squared coherence (``scipy.signal.coherence`` on the
  same samples, one segment per period, rectangular window).
* An input the capture contradicts (a wrong profile, targets stamped late while the
  capture read the true setpoint) is not trusted, and the run says why.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy import signal

from servotune.devices.slap2.codec import TICK_S
from servotune.devices.slap2.injection import TrapezoidInput
from servotune.devices.slap2.law import slap2_loop
from servotune.devices.slap2.sim.demo import SLAP2_LOADED
from servotune.sim.physics import DcMotorParams
from servotune.tuning import frfrun, frftrust
from servotune.tuning.injection import HeldTargets
from servotune.tuning.loops import MotorModel
from tests.support.frf_harness import Stalls, scripted_run, simulator_response

PLANTS = {"unloaded": DcMotorParams(), "loaded": SLAP2_LOADED}
# stable gains on each demo plant (the model's margins): the factory set where it is
# stable, the gains of the issue, the auto-tune's proposal for the loaded module
STABLE = [
    ("unloaded", (40, 40, 80)),
    ("unloaded", (600, 10, 1500)),
    ("loaded", (600, 10, 1500)),
    ("loaded", (1950, 0, 880)),
]
STALLS = {
    "quiet": None,
    "stalls": Stalls(10, (0.02, 0.08), seed=1),
    "heavy stalls": Stalls(5, (0.01, 0.05), seed=2),
}


def _model(params: DcMotorParams, gains: tuple[int, int, int]) -> np.ndarray:
    motor = MotorModel(
        params.resistance_ohm,
        params.inductance_h,
        params.torque_constant_nm_per_a,
        params.inertia_kg_m2,
        params.viscous_friction_nm_s_per_rad,
        params.supply_v,
        params.counts_per_rev,
    )
    loop = slap2_loop(motor, *gains)
    assert loop.margins().stable
    return loop


def _errors(measured: np.ndarray, expected: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    db = np.abs(20 * np.log10(np.abs(measured)) - 20 * np.log10(np.abs(expected)))
    deg = np.abs(np.degrees(np.angle(measured / expected)))
    return db, deg


@pytest.mark.parametrize("case", list(STALLS))
@pytest.mark.parametrize(("plant", "gains"), STABLE)
def test_trusted_tones_are_right_on_every_demo_plant(
    plant: str, gains: tuple[int, int, int], case: str
) -> None:
    params = PLANTS[plant]
    loop = _model(params, gains)
    for seed in (1, 2) if case != "heavy stalls" else (1,):
        run = scripted_run(params, gains, seed=seed, stalls=STALLS[case])
        result = run.analyse()
        closed = result["closed_loop"]
        f = np.asarray(closed["frequency_hz"])
        measured = 10 ** (np.asarray(closed["magnitude_db"]) / 20) * np.exp(
            1j * np.radians(np.asarray(closed["phase_deg"]))
        )
        trusted = np.asarray(closed["trusted"])
        truth = loop.closed_loop_response(f).response
        where = f"{plant} {gains} {case} seed {seed}: {result['trust']}"
        # where the loop follows its input (well below the bandwidth): 0 dB and 0 deg
        follows = _errors(truth, np.ones(f.size))
        below = (follows[0] <= 0.1) & (follows[1] <= 2.0)
        assert below[0], (f, follows)
        zero_db, zero_deg = _errors(measured, np.ones(f.size))
        low = trusted & below
        assert (zero_db[low] <= 0.5).all() and (zero_deg[low] <= 5.0).all(), (
            where,
            f[low],
            zero_db[low],
            zero_deg[low],
        )
        # every trusted tone's bound is within the instrument's limits, and stated
        assert all(
            e is not None and e <= frftrust.MAX_TRUSTED_DB
            for e, t in zip(closed["error_db"], trusted, strict=True)
            if t
        )
        if case == "quiet":
            assert trusted[below].sum() >= min(3, below.sum()), where
            assert result["trust"]["stalled_samples_left_out"] == 0, where
        else:
            assert run.stalled_samples and run.stalled_commands
            assert result["trust"]["stalled_samples_left_out"] >= 1, where
            assert result["trust"]["stalled_targets_bounded"] >= 1, where
        for tone, why in zip(f, closed["not_trusted_because"], strict=True):
            assert (why is None) == bool(trusted[f == tone][0])


@pytest.mark.parametrize("case", list(STALLS))
@pytest.mark.parametrize(("plant", "gains"), STABLE)
def test_trusted_tones_match_the_simulator_without_friction(
    plant: str, gains: tuple[int, int, int], case: str
) -> None:
    """The same runs on the demo plants without their Coulomb friction (which bends the
    response by whole dB at coherence > 0.9, docs/frequency-response.md), against the
    simulator's own response (its position against its setpoint, every tick, no wire:
    ``simulator_response``): every trusted tone, at any frequency, within 0.5 dB and
    5 deg."""
    params = dataclasses.replace(PLANTS[plant], coulomb_friction_nm=0.0)
    run = scripted_run(params, gains, seed=2, stalls=STALLS[case])
    result = run.analyse()
    closed = result["closed_loop"]
    f = np.asarray(closed["frequency_hz"])
    measured = 10 ** (np.asarray(closed["magnitude_db"]) / 20) * np.exp(
        1j * np.radians(np.asarray(closed["phase_deg"]))
    )
    trusted = np.asarray(closed["trusted"])
    db, deg = _errors(measured, simulator_response(params, gains, run.excitation))
    assert (db[trusted] <= 0.5).all() and (deg[trusted] <= 5.0).all(), (
        f"{plant} {gains} {case}: {result['trust']}",
        f[trusted],
        db[trusted],
        deg[trusted],
    )
    if case == "quiet":
        assert trusted.sum() >= 5, result["trust"]


def test_the_coherence_is_the_magnitude_squared_coherence() -> None:
    """Uniform samples at 200/s of a loop driven by the multisine (an input known at
    every sample, noise on the output): the run's coherence at the tones is scipy's
    magnitude-squared coherence of the same input and output with one period per
    segment and a rectangular window (the H1 estimator's coherence)."""
    rate, period = 200.0, 1.0
    excitation = frfrun.design(0.0, 200.0, 1.0 / period, 20.0)
    periods = 6
    t = np.arange(0.0, (periods + 1) * period, 1.0 / rate)
    # targets on every sample, latched at it: the rebuilt input at the samples is them
    targets = np.asarray([float(excitation.target(float(x))) for x in t])
    sent = [[float(x), float(u), float(x) - 1e-9] for x, u in zip(t, targets, strict=True)]
    b, a = signal.butter(2, 8.0, fs=rate)
    rng = np.random.default_rng(7)
    y = signal.lfilter(b, a, targets) + rng.normal(0.0, 20.0, t.size)
    result = frfrun.analyse(
        t + 0.0004, y, None, sent, 0.0, excitation, HeldTargets(TICK_S), estimator="tones"
    )
    coherence = np.asarray(result["closed_loop"]["coherence"], dtype=float)
    analysed = (t + 0.0004 >= period) & (t + 0.0004 < period * (1 + result["periods"]))
    u_at = np.interp(
        t[analysed] + 0.0004, *frfrun.rebuild_input(sent, 0.0, 0.0, HeldTargets(TICK_S), t[-1] + 1)
    )
    f, msc = signal.coherence(
        u_at,
        y[analysed],
        fs=rate,
        window="boxcar",
        nperseg=int(rate * period),
        noverlap=0,
        detrend="constant",
    )
    expected = np.interp(excitation.tones_hz, f, msc)
    np.testing.assert_allclose(coherence, expected, atol=1e-4)  # rounded to 4 digits
    assert coherence.min() < 0.9 < coherence.max()  # the noise matters at some tones


def test_an_input_the_capture_contradicts_is_not_trusted() -> None:
    """The loaded plant, quiet: analysed with a wrong profile (sv/sa 1000 instead of
    the test's maximum: the rebuilt input lags the setpoint the capture recorded by
    tens of counts), no tone is trusted and the run names the input check."""
    run = scripted_run(SLAP2_LOADED, (600, 10, 1500), setpoint_from_pe=True)
    right = run.analyse()
    assert right["trust"]["trusted_tones"] >= 8
    wrong = frfrun.analyse(
        run.t_s,
        run.position,
        run.setpoint,
        run.sent,
        run.t0_s,
        run.excitation,
        model=TrapezoidInput(1000, 1000),
        sample_spans_s=run.spans_s,
    )
    trust = wrong["trust"]
    assert trust["input_check_excess_counts"] > 10 and trust["input_check_samples_over"] > 10
    assert trust["trusted_tones"] == 0
    assert any("input check" in why for why in trust["not_trusted"]), trust


def test_late_stamped_targets_the_capture_saw_are_caught() -> None:
    """Targets stamped late by stalls, the setpoint column read from the device
    (``rp + pe``, as the capture records it when its own checks fail) and the spans not
    recorded (an older run): the spans are inferred from the gaps, and no tone is
    trusted beyond what its bound allows."""
    run = scripted_run(
        SLAP2_LOADED,
        (600, 10, 1500),
        stalls=Stalls(6, (0.03, 0.08), after_cr=1.0, seed=3),
        setpoint_from_pe=True,
    )
    result = frfrun.analyse(
        run.t_s,
        run.position,
        run.setpoint,
        run.sent[:],
        run.t0_s,
        run.excitation,
        model=TrapezoidInput(65535, 65535),
    )
    trust = result["trust"]
    assert trust["spans"].startswith("recorded") or "gaps" in trust["spans"]
    closed = result["closed_loop"]
    f = np.asarray(closed["frequency_hz"])
    trusted = np.asarray(closed["trusted"])
    measured = 10 ** (np.asarray(closed["magnitude_db"]) / 20) * np.exp(
        1j * np.radians(np.asarray(closed["phase_deg"]))
    )
    truth = _model(SLAP2_LOADED, (600, 10, 1500)).closed_loop_response(f).response
    db, deg = _errors(measured, truth)
    assert (db[trusted] <= 0.5).all() and (deg[trusted] <= 5.0).all(), (f[trusted], trust)
    assert trust["stalled_targets_bounded"] + trust["stalled_samples_left_out"] > 0


def test_spans_inferred_from_gaps_flag_the_exchange_that_ends_a_gap() -> None:
    samples = np.arange(0.0, 1.0, 0.013)
    samples[40:] += 0.06  # a 60 ms stall before sample 40
    commands = samples[:-1] + 0.006
    sample_spans, command_spans = frftrust.spans_from_gaps(samples, commands)
    assert sample_spans[40] == pytest.approx(0.06 - frftrust.GAP_STALL_S, abs=0.008)
    assert np.count_nonzero(sample_spans > frftrust.STALL_SPAN_S) == 1
    assert np.count_nonzero(command_spans > frftrust.STALL_SPAN_S) == 0
    assert math.isfinite(frftrust.timing_s(sample_spans, command_spans, TICK_S))
