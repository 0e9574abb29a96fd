"""Nothing holds STOP back: a loop-lag watchdog around every bench
test kind and every auto-tune step.

The server runs in this process; the simulated SLAP2 line runs in a process of its own
(a device on a wire). While each phase runs - a move, a position step, a velocity
step, a PWM step, a frequency response (closed loop, open loop, and closed loop after
an identification, which adds the model to its analysis), the auto-tune's
identification with its proposal, and its verification - the product's loop-lag meter
(``servotune.perf.looplag``) runs on the server's loop, a STOP goes to the other module
every 0.2 s, and the phase's analysis is fetched as the page does.

Asserted, whatever the machine's load: the loop's *own* lag (what it spent running or
blocked inside this process, not waiting for a CPU: ``/proc/thread-self/schedstat``)
stays under 100 ms; the STOPs of each phase are answered within 50 ms of their own share
(the median of their latency less the time the loop's thread and the simulator's
threads waited for a CPU meanwhile), none beyond 250 ms. The raw figures are printed per
phase.
"""

from __future__ import annotations

import asyncio
import os
import statistics
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from servotune.config import LinkSpec
from servotune.perf.looplag import LoopLagMeter
from tests.support.bench import finished_run, start
from tests.support.servers import serve, sim_process

# The product's own loop lag and STOP time on this host: run alone (scripts/test.sh).
pytestmark = [pytest.mark.slow, pytest.mark.host_timing]

OWN_LAG_MAX_S = 0.1
STOP_OWN_MAX_S = 0.05  # the median of a phase's STOPs
# No single STOP waits longer than this of its own: what the estimate leaves in (the
# exchange in flight, the simulator's own pty round trips) stays well under it; a
# stalled loop (the 1.5-25 s freezes) does not.
STOP_OWN_WORST_S = 0.25


def _process_runqueue_wait_s(pid: int) -> float:
    """Time every thread of process ``pid`` has spent ready but waiting for a CPU."""
    total = 0
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{tid}/schedstat", encoding="ascii") as f:
                total += int(f.read().split()[1])
    except (OSError, IndexError, ValueError):
        pass
    return total / 1e9


def _sim_pid(path: str) -> int:
    """The pid of the simulator process that holds pty ``path`` open."""
    target = os.path.realpath(path)
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            for fd in os.listdir(f"/proc/{pid}/fd"):
                if os.readlink(f"/proc/{pid}/fd/{fd}") == target and int(pid) != os.getpid():
                    return int(pid)
        except OSError:
            continue
    return -1


async def test_stop_and_the_loop_are_never_held_back_by_a_test_or_a_tuning_step(
    tmp_path: Path,
) -> None:
    with sim_process(tmp_path / "sim") as path:
        spec = LinkSpec("slap2", path, "line", 19200, [0, 1], 512)
        async with serve(spec, tmp_path / "data") as (_app, client, _ws):
            sim_pid = _sim_pid(path)
            server = SimpleNamespace(client=client)
            meter = LoopLagMeter()
            stops: list[tuple[float, float, float]] = []  # (sent, latency, own)
            done = asyncio.Event()

            async def send_stops() -> None:
                while not done.is_set():
                    loop_wait, sim_wait = _runqueue_loop_and_sim(sim_pid)
                    sent = time.perf_counter()
                    response = await client.post(
                        "/api/axes/line-0/commands", json={"command": "stop"}
                    )
                    latency = time.perf_counter() - sent
                    loop_after, sim_after = _runqueue_loop_and_sim(sim_pid)
                    machine = (loop_after - loop_wait) + (sim_after - sim_wait)
                    assert response.status_code == 200, response.text
                    stops.append((sent, latency, max(0.0, latency - machine)))
                    await asyncio.sleep(0.2)

            phases: list[tuple[str, float, float]] = []

            async def phase(name: str, job: Any) -> Any:
                began = time.perf_counter()
                result = await job
                phases.append((name, began, time.perf_counter()))
                return result

            async def bench(axis: str, **test: Any) -> dict[str, Any]:
                run = await finished_run(server, axis, await start(server, axis, **test))
                if test["kind"] == "frequency_response":
                    analysis = await client.get(f"/api/bench/runs/{run['id']}/frf", timeout=120)
                    assert analysis.status_code == 200, analysis.text
                return run

            limits = {
                "max_distance_counts": 20000,
                "max_velocity": 20000,
                "max_pwm": 60,
                "max_duration_s": 8,
                # Wide: this test times the loop and STOP, not the window. The open-loop
                # phases carry the axis by a distance that depends on when their commands
                # land (62 344 counts was seen at load 8-10); a narrow window then refused
                # the next phase (422) instead of measuring it.
                "min_position_counts": -1_000_000,
                "max_position_counts": 1_000_000,
            }
            response = await client.put("/api/axes/line-1/bench/limits", json=limits)
            assert response.status_code == 200, response.text
            async with meter.running():
                stopper = asyncio.create_task(send_stops())
                await asyncio.sleep(0.5)
                frf = {"amplitude": 200, "low_hz": 1.0, "high_hz": 10.0, "duration_s": 4.0}
                for name, test in (
                    ("move", {"kind": "move", "distance": 2000}),
                    ("position step", {"kind": "position_step", "distance": -2000}),
                    ("velocity step", {"kind": "velocity_step", "velocity": 2000, "duration_s": 1}),
                    ("pwm step", {"kind": "pwm_step", "pwm": 30, "duration_s": 1.0}),
                    ("frequency response", {"kind": "frequency_response", **frf}),
                ):
                    await phase(name, bench("line-1", **test))
                await phase(
                    "frequency response, open loop",
                    bench(
                        "line-1",
                        kind="frequency_response",
                        loop="open",
                        pwm=30,
                        low_hz=1.0,
                        high_hz=10.0,
                        duration_s=4.0,
                        confirm_open_loop=True,
                    ),
                )
                identified = await phase(
                    "auto-tune identification + proposal",
                    client.post(
                        "/api/axes/line-1/autotune/identify",
                        json={"max_pwm": 60, "max_distance_counts": 4000},
                        timeout=180,
                    ),
                )
                await phase(
                    "frequency response with the identified model",
                    bench("line-1", kind="frequency_response", **frf),
                )
                if identified.status_code == 200:
                    await phase(
                        "auto-tune verification",
                        client.post("/api/axes/line-1/autotune/accept", timeout=180),
                    )
                done.set()
                await stopper

    print(f"\nload average {os.getloadavg()[0]:.1f}; identify -> {identified.status_code}")
    for name, t_from, t_to in phases:
        lags = meter.between(t_from, t_to)
        worst = meter.worst(t_from, t_to)
        in_phase = [s for s in stops if t_from <= s[0] < t_to]
        lag_ms = max([s.lag_s for s in lags] or [0.0]) * 1000
        print(
            f"{name}: {t_to - t_from:.1f} s; loop lag max {lag_ms:.0f} ms"
            f" (own {worst.own_s * 1000 if worst else 0:.0f} ms); {len(in_phase)} STOPs, "
            f"latency median {statistics.median([s[1] for s in in_phase] or [0]) * 1000:.0f} ms "
            f"max {max([s[1] for s in in_phase] or [0]) * 1000:.0f} ms "
            f"(own max {max([s[2] for s in in_phase] or [0]) * 1000:.0f} ms)"
        )
    assert identified.status_code == 200 or (
        identified.status_code == 409 and "no gains meet the rule" in identified.text
    ), identified.text
    for name, t_from, t_to in phases:
        worst = meter.worst(t_from, t_to)
        assert worst is not None and worst.own_s < OWN_LAG_MAX_S, (name, worst)
        in_phase = [s for s in stops if t_from <= s[0] < t_to]
        assert in_phase, f"{name}: no STOP was answered"
        own = statistics.median(s[2] for s in in_phase)
        assert own < STOP_OWN_MAX_S, f"{name}: STOPs took {own * 1000:.0f} ms of their own"
        worst_stop = max(s[2] for s in in_phase)
        assert worst_stop < STOP_OWN_WORST_S, f"{name}: a STOP took {worst_stop:.2f} s"


def _runqueue_loop_and_sim(sim_pid: int) -> tuple[float, float]:
    """(this thread's, the simulator's threads') time waiting for a CPU so far."""
    try:
        with open("/proc/thread-self/schedstat", encoding="ascii") as f:
            mine = int(f.read().split()[1]) / 1e9
    except (OSError, IndexError, ValueError):
        mine = 0.0
    return mine, _process_runqueue_wait_s(sim_pid) if sim_pid > 0 else 0.0
