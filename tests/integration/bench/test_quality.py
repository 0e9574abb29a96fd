"""Bad bench runs are marked bad (``quality``), untrusted metrics are null with the reason,
and relative moves return to their start.

The unit tests feed ``bench.quality.assess`` synthetic runs with known answers; the
simulator tests provoke each bad case on a simulated SLAP2 line."""

from __future__ import annotations

import asyncio
import json
import math
from typing import Any

import numpy as np
import pytest
import websockets
from scipy import signal

from servotune.bench.metrics import compute_metrics, predict_second_order
from servotune.bench.quality import (
    MAX_OVERSHOOT_UNCERTAINTY_PP,
    MIN_INTERVAL_SAMPLES,
    MIN_RISE_SAMPLES,
    SAMPLING_RULE,
    assess,
)
from tests.support.bench import finished_run, start
from tests.support.servers import LiveServer

COLUMNS = ["t_s", "position", "following_error", "flags_t_s"]
FLAGS = ["limit1", "limit2", "oc", "inpos", "move"]


def _run(
    times: list[float],
    positions: list[float],
    *,
    flags: dict[str, list[int]] | None = None,
    target: float = 1000.0,
    band: float = 5.0,
    status: str = "complete",
    following_error: list[float | None] | None = None,
    flags_t: list[float] | None = None,
) -> tuple[dict[str, Any] | None, dict[str, Any]]:
    flags = flags or {}
    series = {name: flags.get(name, [0] * len(times)) for name in FLAGS}
    if "inpos" not in flags:
        series["inpos"] = [int(abs(p - target) <= band) for p in positions]
        series["inpos"][0] = 0
    fe = following_error or [None] * len(times)
    read = flags_t or times
    rows = [
        [t, p, fe[i], read[i], [series[name][i] for name in FLAGS]]
        for i, (t, p) in enumerate(zip(times, positions, strict=True))
    ]
    metrics = compute_metrics(
        times,
        positions,
        t0_s=0.0,
        y0=0.0,
        y_final=target,
        band=band,
        following_error=fe,
        flags={name: [bool(v) for v in series[name]] for name in FLAGS},
        flags_t_s=read,
    ).model_dump()
    return assess(
        kind="move",
        columns=COLUMNS,
        flag_names=FLAGS,
        rows=rows,
        t0_s=0.0,
        response="position",
        y0=0.0,
        y_final=target,
        band=band,
        fault_flags=["oc", "limit1", "limit2"],
        done_flag="inpos",
        metrics=metrics,
        status=status,
        message="",
    )


def _first_order(
    n: int, dt: float, tau: float = 0.3, target: float = 1000.0
) -> tuple[list[float], list[float]]:
    times = [i * dt for i in range(n)]
    return times, [round(target * -math.expm1(-t / tau)) if t > 0 else 0.0 for t in times]


def test_a_well_sampled_settled_move_is_good_and_keeps_its_metrics() -> None:
    times, positions = _first_order(200, 0.01)
    metrics, quality = _run(times, positions)
    assert quality == {
        "status": "good",
        "reasons": [],
        "untrusted": {},
        "sampling_rule": SAMPLING_RULE,
    }
    assert metrics is not None and metrics["rise_time_s"] == pytest.approx(0.3 * math.log(9), 0.05)
    assert metrics["settling_time_s"] is not None


@pytest.mark.parametrize(("flag", "code"), [("limit2", "limit_switch"), ("limit1", "limit_switch")])
def test_a_limit_switch_makes_the_run_bad_and_nulls_the_response_metrics(
    flag: str, code: str
) -> None:
    times, positions = _first_order(200, 0.01)
    metrics, quality = _run(times, positions, flags={flag: [0] * 150 + [1] * 50})
    assert quality["status"] == "bad"
    assert quality["reasons"][0]["code"] == code and flag in quality["reasons"][0]["message"]
    assert metrics is not None
    for name in ("rise_time_s", "overshoot_pct", "settling_time_s", "steady_state_error"):
        assert metrics[name] is None and flag in quality["untrusted"][name]
    assert metrics["samples"] == 200  # facts stay


def test_ending_in_current_limit_is_bad_passing_through_it_is_doubtful() -> None:
    times, positions = _first_order(200, 0.01)
    _, ended = _run(times, positions, flags={"oc": [0] * 190 + [1] * 10})
    assert ended["status"] == "bad" and ended["reasons"][0]["code"] == "current_limit"
    metrics, passed = _run(times, positions, flags={"oc": [0] * 5 + [1] * 20 + [0] * 175})
    assert passed["status"] == "doubtful" and passed["reasons"][0]["code"] == "current_limit"
    assert metrics is not None and metrics["settling_time_s"] is not None


def test_a_run_that_did_not_move_is_bad() -> None:
    times = [i * 0.02 for i in range(50)]
    metrics, quality = _run(times, [0.0] * 50, flags={"inpos": [0] * 50})
    assert quality["status"] == "bad"
    assert quality["reasons"][0]["code"] == "did_not_move"
    assert metrics is not None and metrics["overshoot_pct"] is None


def test_ending_outside_the_window_is_bad() -> None:
    times, positions = _first_order(40, 0.01)  # cut off at 0.4 s, at 74 % of the step
    _, quality = _run(times, positions)
    assert quality["status"] == "bad"
    assert quality["reasons"][0]["code"] == "outside_window"
    assert "±5" in quality["reasons"][0]["message"]


def test_a_run_that_only_ended_outside_the_window_keeps_rise_overshoot_and_oscillations() -> None:
    # Pinned rule: poor gains make a limit cycle that never enters the
    # window. The run is bad (not comparable), but its rise, overshoot and oscillation
    # count are true measurements of that cycle and stay; only what assumes a settled
    # end (steady-state error, settling) goes.
    times = [0.0005 + 0.001 * i for i in range(1500)]
    positions = [float(round(v)) for v in predict_second_order(60.0, 0.01, 1000.0, times)]
    metrics, quality = _run(times, positions)
    assert quality["status"] == "bad"
    assert [r["code"] for r in quality["reasons"]] == ["outside_window"]
    assert metrics is not None
    raw = compute_metrics(times, positions, t0_s=0.0, y0=0.0, y_final=1000.0, band=5.0)
    assert metrics["rise_time_s"] == raw.rise_time_s == pytest.approx(0.0171, abs=0.001)
    assert metrics["overshoot_pct"] == raw.overshoot_pct == pytest.approx(96.9, abs=0.5)
    assert metrics["oscillations"] == raw.oscillations and raw.oscillations > 20
    assert metrics["steady_state_error"] is None and metrics["settling_time_s"] is None
    assert set(quality["untrusted"]) == {"steady_state_error"}


def test_an_incomplete_run_is_bad() -> None:
    times, positions = _first_order(200, 0.01)
    _, quality = _run(times, positions, status="incomplete")
    assert quality["status"] == "bad" and quality["reasons"][0]["code"] == "incomplete"


def test_sparse_samples_null_the_rise_and_times_shorter_than_their_gaps() -> None:
    # 120 ms polling of a 33 ms rise: no sample in the rise, and the first sample
    # after the command is already settled.
    times, positions = _first_order(20, 0.12, tau=0.015)
    metrics, quality = _run(times, positions)
    assert metrics is not None
    assert metrics["rise_time_s"] is None
    assert f"needs {MIN_RISE_SAMPLES}" in quality["untrusted"]["rise_time_s"]
    # the settling crossing lies between the command and a sample 120 ms later
    assert metrics["settling_time_s"] is None
    assert "only 1 sample until it settled" in quality["untrusted"]["settling_time_s"]
    assert quality["status"] == "good"  # the run is fine, the sampling is not enough
    # Ten or more samples in the rise: trusted.
    times, positions = _first_order(300, 0.01)
    metrics, quality = _run(times, positions)
    assert metrics is not None and metrics["rise_time_s"] is not None
    assert "rise_time_s" not in quality["untrusted"]


# --- one rule for every metric (bench.quality._unresolved) ----------------------------


def test_a_rise_interpolated_across_a_gap_wider_than_itself_is_null() -> None:
    # A baseline showed a 135 ms rise across a 581 ms gap: the host read nothing from
    # the command to 581 ms (the axis at 10.3 % then), then every 5 ms. The 10 %
    # crossing is interpolated inside the gap, and 24 samples lie between 10 % and
    # 90 %: the sample count alone let it through.
    times = [0.0, 0.581, *(0.581 + 0.005 * i for i in range(1, 200))]
    positions = [0.0]
    for t in times[1:]:
        if t <= 0.70:
            positions.append(round(1000 * (0.1028 + (t - 0.581) / 0.119 * 0.7972)))
        else:
            positions.append(round(1000 - 100 * math.exp(-(t - 0.70) / 0.02)))
    metrics, quality = _run(times, positions)
    raw = compute_metrics(times, positions, t0_s=0.0, y0=0.0, y_final=1000.0, band=5.0)
    assert raw.rise_time_s == pytest.approx(0.135, abs=0.002)
    assert metrics is not None and metrics["rise_time_s"] is None
    assert "up to 581 ms apart" in quality["untrusted"]["rise_time_s"]
    assert "more than the rise itself" in quality["untrusted"]["rise_time_s"]


def test_a_ringing_rise_counts_only_the_samples_of_the_rise_itself() -> None:
    # The factory gains on the loaded SLAP2: a 17-18 ms rise caught by 3 samples, then
    # a ring that passes 10..90 % of the step 38 times. Counting every sample between
    # 10 % and 90 % of the step (the old rule) trusted it; the rule counts the samples
    # in the interval that defines the rise.
    times = [0.0035 + 0.007 * i for i in range(300)]
    positions = predict_second_order(60.0, 0.05, 1000.0, times)
    assert sum(1 for p in positions if 100 <= p <= 900) >= MIN_RISE_SAMPLES
    metrics, quality = _run(times, positions)
    assert metrics is not None and metrics["rise_time_s"] is None
    assert "only 3 samples between 10 % and 90 %" in quality["untrusted"]["rise_time_s"]
    # Where the record resolves it (1 ms spacing: 18 samples), the same ring keeps it.
    times = [0.0005 + 0.001 * i for i in range(2000)]
    metrics, quality = _run(times, predict_second_order(60.0, 0.05, 1000.0, times))
    assert metrics is not None
    assert metrics["rise_time_s"] == pytest.approx(0.0185, abs=0.001)
    assert "rise_time_s" not in quality["untrusted"]


def test_a_following_error_peak_in_a_gap_around_the_whole_move_is_null() -> None:
    # A 40 ms move fell entirely in a 54 ms gap: the only following-error samples
    # are at rest, before and after it; a peak of them says nothing of the move.
    times = [-0.1 + 0.005 * i for i in range(21)] + [0.054 + 0.005 * i for i in range(100)]
    positions = [0.0 if t <= 0 else 100.0 for t in times]
    fe: list[float | None] = [0.0 if t <= 0 else (3.0 if t < 0.06 else 0.0) for t in times]
    metrics, quality = _run(times, positions, target=100.0, following_error=fe)
    assert metrics is not None
    assert metrics["peak_following_error"] is None and metrics["rms_following_error"] is None
    why = quality["untrusted"]["peak_following_error"]
    assert "only 1 sample of following error until the axis settled" in why
    # The same move sampled through: a slow move (0.5 s, FE read every 10 ms) keeps it.
    times = [0.01 * i for i in range(100)]
    positions = [min(100.0, 200.0 * t) for t in times]
    fe = [(2.0 if t < 0.5 else 0.0) for t in times]
    metrics, quality = _run(times, positions, target=100.0, following_error=fe)
    assert metrics is not None and metrics["peak_following_error"] == 2.0
    assert "peak_following_error" not in quality["untrusted"]
    # ... unless its following error was read once in 300 ms (a slow channel): two
    # reads in the 475 ms move.
    sparse: list[float | None] = [v if i % 30 == 0 else None for i, v in enumerate(fe)]
    metrics, quality = _run(times, positions, target=100.0, following_error=sparse)
    assert metrics is not None and metrics["peak_following_error"] is None
    why = quality["untrusted"]["peak_following_error"]
    assert "only 2 samples of following error" in why and f"needs {MIN_INTERVAL_SAMPLES}" in why


def test_a_flag_polled_slower_than_its_rise_is_timed_by_its_reads() -> None:
    # In-position rises at 90 ms; positions every 5 ms, the flags read every 200 ms
    # and held between the reads (rss): timed at the samples it read 200+ ms.
    times, positions = _first_order(200, 0.005, tau=0.015)
    reads = [0.2 * math.floor(t / 0.2 + 1e-9) for t in times]
    inpos = [int(r >= 0.09 and r > 0) for r in reads]
    metrics, quality = _run(times, positions, flags={"inpos": inpos}, flags_t=reads)
    assert metrics is not None
    # between the clear read at 0 and the set read at 200 ms: 100 ± 100 ms, wider
    # than the time itself: null, with the reason.
    assert metrics["time_to_flag_s"]["inpos"] is None
    assert "read 200 ms apart around its rise" in quality["untrusted"]["time_to_flag_s.inpos"]
    # Read every 20 ms: 100 ± 10 ms (the truth, 90 ms, within it): shown.
    reads = [0.02 * math.floor(t / 0.02 + 1e-9) for t in times]
    inpos = [int(r >= 0.09) for r in reads]
    metrics, quality = _run(times, positions, flags={"inpos": inpos}, flags_t=reads)
    assert metrics is not None
    value = metrics["time_to_flag_s"]["inpos"]
    resolution = metrics["time_to_flag_resolution_s"]["inpos"]
    assert value == pytest.approx(0.09) and resolution == pytest.approx(0.01)
    assert "time_to_flag_s.inpos" not in quality["untrusted"]


def _trapezoid_followed(times: list[float], target: float) -> tuple[list[float], float]:
    """A trapezoidal move to ``target`` (10⁶ counts/s², 60 000 counts/s) followed by
    a damped loop (150 rad/s, ζ 0.6), as the demo Z1100 axis moves: the positions
    at ``times`` in whole counts, and the true overshoot (%) from a 20 µs grid."""
    acc, vmax, wn, zeta = 1_000_000.0, 60_000.0, 150.0, 0.6
    grid = np.arange(0.0, times[-1] + 0.01, 20e-6)
    t_acc = min(vmax / acc, math.sqrt(target / acc))
    v_top = acc * t_acc
    t_flat = (target - acc * t_acc**2) / v_top
    t_end = 2 * t_acc + t_flat
    tc = np.clip(grid, 0.0, t_end)
    profile = np.where(
        tc < t_acc,
        0.5 * acc * tc**2,
        np.where(
            tc < t_acc + t_flat,
            0.5 * acc * t_acc**2 + v_top * (tc - t_acc),
            target - 0.5 * acc * (t_end - tc) ** 2,
        ),
    )
    loop = signal.lti([wn * wn], [1.0, 2 * zeta * wn, wn * wn])
    _, y, _ = signal.lsim(loop, profile, grid)
    overshoot_pct = 100.0 * (float(np.max(y)) - target) / target
    return [float(round(v)) for v in np.interp(times, grid, y)], overshoot_pct


@pytest.mark.parametrize("phase", [0, 1, 2])
@pytest.mark.parametrize("offset_s", [0.0, 0.0011, 0.0023])
def test_a_regular_schedule_with_longer_gaps_keeps_a_flat_peaks_overshoot(
    phase: int, offset_s: float
) -> None:
    # The Z1100 capture reads GetError every third sample, so every third gap between
    # positions is two transactions (7.2 ms, twice the median). Where the peak is a
    # gentle hump after a hard deceleration, the gap next to it hides far less than
    # 0.5 pp: the overshoot stays trusted, and right, whichever sample it falls next to.
    target = 2000.0
    times, t = [], 0.0036 + offset_s
    for i in range(120):
        times.append(t)
        t += 0.0072 if (i + phase) % 3 == 2 else 0.0036
    positions, truth_pct = _trapezoid_followed(times, target)
    assert 0.05 < truth_pct < 3.0  # a small overshoot, as on the demo axis
    metrics, quality = _run(times, positions, target=target, band=20.0)
    assert metrics is not None
    assert "overshoot_pct" not in quality["untrusted"], quality["untrusted"]
    assert metrics["overshoot_pct"] == pytest.approx(truth_pct, abs=MAX_OVERSHOOT_UNCERTAINTY_PP)


@pytest.mark.parametrize("shift", [-1, 0, 1])
def test_a_gap_over_a_sharp_peak_makes_the_overshoot_untrusted(shift: int) -> None:
    # The demo SLAP2's factory gains (22 % overshoot, 6 ms spacing) with four samples
    # missing around the peak (a 30 ms gap): the peak may lie anywhere in it.
    times = [0.0035 + 0.006 * i for i in range(60)]
    positions = [float(round(v)) for v in predict_second_order(60.0, 0.43, 1000.0, times)]
    k = max(range(len(positions)), key=lambda i: positions[i]) + shift
    keep = [i for i in range(len(times)) if not k - 2 <= i <= k + 1]
    metrics, quality = _run([times[i] for i in keep], [positions[i] for i in keep])
    assert metrics is not None and metrics["overshoot_pct"] is None
    assert "may lie between samples" in quality["untrusted"]["overshoot_pct"]


def test_an_overshoot_whose_peak_samples_were_stamped_late_is_not_trusted() -> None:
    # A 22 % overshoot (the demo SLAP2's factory gains) sampled every 6 ms: trusted.
    times = [0.0035 + 0.006 * i for i in range(60)]
    positions = [float(round(v)) for v in predict_second_order(60.0, 0.43, 1000.0, times)]
    metrics, quality = _run(times, positions)
    assert metrics is not None and metrics["overshoot_pct"] == pytest.approx(22.4, abs=0.2)
    assert "overshoot_pct" not in quality["untrusted"]
    clean_doubts = set(quality["untrusted"])
    # The sample after the peak read 4 ms late (a busy host): the same values at a
    # later stamp move the spline's peak by ~0.8 pp, more than the bound.
    k = max(range(len(positions)), key=lambda i: positions[i])
    late = list(times)
    late[k + 1] += 0.004
    wrong = compute_metrics(late, positions, t0_s=0.0, y0=0.0, y_final=1000.0)
    assert wrong.overshoot_pct is not None
    assert abs(wrong.overshoot_pct - metrics["overshoot_pct"]) > MAX_OVERSHOOT_UNCERTAINTY_PP
    metrics, quality = _run(late, positions)
    assert metrics is not None and metrics["overshoot_pct"] is None
    assert "stamped late" in quality["untrusted"]["overshoot_pct"]
    assert set(quality["untrusted"]) == clean_doubts | {"overshoot_pct"}  # only it
    assert quality["status"] == "good"
    # A late stamp far from the peak does not matter to it.
    late = list(times)
    late[k + 15] += 0.004
    metrics, quality = _run(late, positions)
    assert metrics is not None and metrics["overshoot_pct"] is not None


def test_fewer_than_ten_samples_is_doubtful() -> None:
    times, positions = [0.0, 0.5, 1.0, 1.5, 2.0], [0.0, 900.0, 1000.0, 1000.0, 1000.0]
    _, quality = _run(times, positions)
    assert quality["status"] == "doubtful" and quality["reasons"][0]["code"] == "sparse"


# --- on the simulated SLAP2 line -------------------------------------------------------


async def test_sim_runs_hitting_the_switch_not_moving_or_cut_short_are_bad(
    api: LiveServer,
) -> None:
    # E2 of the simulated motor is at +20000 counts: a move there ends in the switch.
    run = await finished_run(api, "line-0", await start(api, "line-0", kind="move", distance=20000))
    codes = [r["code"] for r in run["quality"]["reasons"]]
    assert run["quality"]["status"] == "bad" and "limit_switch" in codes, run["quality"]
    assert run["metrics"]["settling_time_s"] is None
    assert "limit2" in run["quality"]["untrusted"]["steady_state_error"]

    # PWM 1 does not overcome the motor's friction. (Not necessarily the first reason:
    # a host too loaded to poll the axis during the check after the run adds
    # loop_unverified, which the quality names first - bench.runner.left_oscillating.)
    run = await finished_run(
        api, "line-1", await start(api, "line-1", kind="pwm_step", pwm=1, duration_s=0.6)
    )
    assert run["quality"]["status"] == "bad", run["quality"]
    assert "did_not_move" in [r["code"] for r in run["quality"]["reasons"]], run["quality"]

    # A long move recorded for 0.3 s ends far from its target.
    run = await finished_run(
        api, "line-1", await start(api, "line-1", kind="move", distance=15000, duration_s=0.3)
    )
    assert run["quality"]["status"] == "bad", run["quality"]
    assert "outside_window" in [r["code"] for r in run["quality"]["reasons"]], run["quality"]


async def test_sim_position_step_rise_is_too_fast_for_the_telemetry(api: LiveServer) -> None:
    # sv/sa at maximum: 1000 counts in a few tens of ms, polled at most ~50 Hz per axis
    # at 19200 baud: fewer than 10 samples in the rise, whatever the host's speed.
    run = await finished_run(
        api, "line-0", await start(api, "line-0", kind="position_step", distance=1000)
    )
    assert run["metrics"]["rise_time_s"] is None
    why = run["quality"]["untrusted"]["rise_time_s"]
    assert " between 10 % and 90 % " in why and f"needs {MIN_RISE_SAMPLES}" in why, why


async def test_a_move_stopped_by_a_limit_switch_is_a_warning_with_where_it_stopped(
    api: LiveServer,
) -> None:
    """Seen once: "Move to 30000" showed a green ✓ although the E2 switch stopped the
    axis at 20012 and no event said so. The command's answer now says only that the
    move was sent (``outcome_pending``); a ``move_outcome`` message and a warning event
    say where the switch stopped it. A move that arrives says so, without an event."""
    async with websockets.connect(api.ws_url, origin=api.base_url) as ws:
        response = await api.client.post(
            "/api/axes/line-0/commands", json={"command": "position_mode"}
        )
        assert response.status_code == 200
        assert response.json()["outcome_pending"] is False  # not a move: done when it answers
        response = await api.client.post(
            "/api/axes/line-0/commands", json={"command": "move_absolute", "position": 30000}
        )
        assert response.status_code == 200, response.text
        body = response.json()
        assert body["outcome_pending"] is True and body["message"] == "moving to 30000"
        outcome, warning = await _move_end(ws, "line-0")
        assert outcome["outcome"] == "limit", outcome
        assert 19_900 <= outcome["position"] <= 20_100, outcome
        message = outcome["message"]
        assert message.startswith("Move to 30000: stopped by the limit switch "), message
        assert f"at {outcome['position']:.0f}" in message and "short of the target 30000" in message
        assert warning is not None and warning["message"] == message

        response = await api.client.post(
            "/api/axes/line-0/commands", json={"command": "move_absolute", "position": 5000}
        )
        assert response.json()["outcome_pending"] is True
        outcome, warning = await _move_end(ws, "line-0")
        assert outcome["outcome"] == "arrived", outcome
        assert abs(outcome["position"] - 5000) <= 5 and warning is None


async def _move_end(
    ws: Any, axis: str, timeout_s: float = 20.0
) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """The next move_outcome of ``axis`` and the warning event that came before it."""
    warning = None
    deadline = asyncio.get_running_loop().time() + timeout_s
    while True:
        remaining = deadline - asyncio.get_running_loop().time()
        message = json.loads(await asyncio.wait_for(ws.recv(), max(remaining, 0.01)))
        if (
            message["type"] == "event"
            and message["axis"] == axis
            and message["level"] == "warning"
            and message["message"].startswith("Move to")
        ):
            warning = message
        if message["type"] == "move_outcome" and message["axis"] == axis:
            return message, warning


async def test_relative_moves_return_to_their_start(api: LiveServer) -> None:
    module = api.bus.module(0)
    before = module.position
    for distance in (3000, 3000, -2000):
        run = await finished_run(
            api, "line-0", await start(api, "line-0", kind="move", distance=distance)
        )
        assert run["status"] == "complete", run["message"]
        assert run["return"]["ok"], run["return"]
        assert abs(module.position - before) <= 2 * run["plan"]["band"]
        # The way back is not part of the record: the run ends near its target.
        last = run["samples"][-1][run["columns"].index("position")]
        assert abs(last - run["plan"]["y_final"]) <= run["plan"]["band"]


async def test_the_travel_window_refuses_targets_outside_before_anything_moves(
    api: LiveServer,
) -> None:
    position = (await api.state("line-1"))["position"]
    limits = {
        "max_distance_counts": 20000,
        "max_velocity": 20000,
        "max_pwm": 80,
        "max_duration_s": 10,
        "min_position_counts": round(position) - 1000,
        "max_position_counts": round(position) + 1000,
    }
    assert (await api.client.put("/api/axes/line-1/bench/limits", json=limits)).status_code == 200
    response = await api.client.post(
        "/api/axes/line-1/bench/runs", json={"kind": "move", "distance": 5000}
    )
    assert response.status_code == 422 and response.json()["field"] == "distance"
    assert "max_position_counts" in response.json()["detail"]
    assert not api.bus.module(1).rss & 0b1100  # nothing moved
    bad = {**limits, "min_position_counts": 10, "max_position_counts": 5}
    response = await api.client.put("/api/axes/line-1/bench/limits", json=bad)
    assert response.status_code == 422
