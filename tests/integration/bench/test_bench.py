"""The tuning test bench through the API, on simulated SLAP2 modules on a real pty."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from servotune.storage import Storage
from tests.support.bench import finished_run, start
from tests.support.servers import LiveServer, live_server
from tests.support.sim_lines import running_simulator
from tests.support.waiting import wait_for

VM, PM = 1 << 2, 1 << 3  # rss bits


async def test_moves_with_different_kp_give_different_metrics(api: LiveServer) -> None:
    info = (await api.client.get("/api/axes/line-1/bench")).json()
    assert "move" in info["kinds"] and "pwm_step" in info["kinds"]
    first = await finished_run(
        api, "line-1", await start(api, "line-1", kind="move", distance=2000)
    )
    await api.client.patch("/api/axes/line-1/params", json={"kp": 160, "kd": 300})
    second = await finished_run(
        api, "line-1", await start(api, "line-1", kind="move", distance=2000)
    )
    for run in (first, second):
        assert run["status"] == "complete", run["message"]
        # How many samples a move gets depends on the host's speed (the poll rate: on
        # a loaded host a short move may end between two polls); what is guaranteed
        # is a recording in time order.
        times = [row[0] for row in run["samples"]]
        assert times and times == sorted(times)
        metrics = run["metrics"]
        untrusted = run["quality"]["untrusted"]
        # A time metric is either measured or null with the reason (too few samples in
        # the rise, or a gap wider than the value: how many there are is the host's
        # speed); the final position is guaranteed.
        for name in ("rise_time_s", "settling_time_s"):
            assert (metrics[name] is not None) != (name in untrusted), (name, untrusted)
        inpos = metrics["time_to_flag_s"]["inpos"]
        assert (inpos is not None) != ("time_to_flag_s.inpos" in untrusted), untrusted
        assert run["quality"]["status"] != "bad", run["quality"]
        assert abs(metrics["steady_state_error"]) <= 5
    assert first["params"]["kp"] == 40 and second["params"]["kp"] == 160
    assert first["metrics"] != second["metrics"]
    # Every sample row: time, one value per column, then the flags.
    row = first["samples"][-1]
    assert len(row) == len(first["columns"]) + 1
    assert len(row[-1]) == len(first["flags"])


async def test_limits_refuse_before_anything_moves(api: LiveServer) -> None:
    response = await api.client.put(
        "/api/axes/line-0/bench/limits",
        json={
            "max_distance_counts": 1000,
            "max_velocity": 5000,
            "max_pwm": 40,
            "max_duration_s": 5,
        },
    )
    assert response.status_code == 200
    response = await api.client.post(
        "/api/axes/line-0/bench/runs", json={"kind": "move", "distance": 5000}
    )
    assert response.status_code == 422
    assert response.json()["field"] == "distance"
    assert "1000" in response.json()["detail"]
    response = await api.client.post(
        "/api/axes/line-0/bench/runs", json={"kind": "pwm_step", "pwm": 200}
    )
    assert response.status_code == 422 and response.json()["field"] == "pwm"
    assert not api.bus.module(0).rss & 0b1100  # neither pm nor vm: nothing moved
    assert (await api.client.get("/api/axes/line-0/bench/runs")).json() == []


async def test_export_import_round_trip(api: LiveServer) -> None:
    run = await finished_run(api, "line-0", await start(api, "line-0", kind="move", distance=-1500))
    csv_text = (await api.client.get(f"/api/bench/runs/{run['id']}/samples.csv")).text
    meta = (await api.client.get(f"/api/bench/runs/{run['id']}/run.json")).json()
    response = await api.client.post(
        "/api/axes/line-1/bench/runs/import", json={"meta": meta, "csv": csv_text}
    )
    assert response.status_code == 201, response.text
    imported = (await api.client.get(f"/api/bench/runs/{response.json()['id']}")).json()
    assert imported["samples"] == run["samples"]
    for key in ("test", "params", "metrics", "columns", "flags", "plan"):
        assert imported[key] == run[key], key
    assert imported["imported_from"] == run["id"]


async def test_link_loss_keeps_samples_marks_incomplete_and_stops(api: LiveServer) -> None:
    run_id = await start(api, "line-0", kind="velocity_step", velocity=3000, duration_s=5)
    for _ in range(100):
        if api.bus.module(0).rss & 0b0100:  # vm on
            break
        await asyncio.sleep(0.02)
    # Unplug once some samples are stored (chunks are flushed every 0.5 s): every one
    # of them must still be there afterwards.
    stored: list[Any] = []
    for _ in range(200):
        stored = (await api.client.get(f"/api/bench/runs/{run_id}")).json()["samples"]
        if len(stored) >= 3:
            break
        await asyncio.sleep(0.05)
    api.simulator.unplug()
    run = await finished_run(api, "line-0", run_id)
    assert run["status"] == "incomplete"
    assert len(stored) >= 3 and run["samples"][: len(stored)] == stored
    api.simulator.replug()
    module = api.bus.module(0)
    for _ in range(200):
        if not module.rss & VM:
            break
        await asyncio.sleep(0.05)
    # Stopped the moment the link was back: out of velocity mode. Its loop was last
    # seen a second or more before, so the STOP is the one safe whether the loop works
    # or not (docs/control.md, "Stops"): the brake, then unpowered at rest.
    assert not module.rss & VM, "the axis was not stopped after the link came back"

    def events() -> list[str]:
        return [e.message for e in api.app.state.hub._events if e.axis == "line-0"]

    # The hub records the STOP's event when the device's reply is in, which can be just
    # after the module left vm.
    await wait_for(
        lambda: any("STOP: telemetry too sparse" in e and "spwm0" in e for e in events()),
        5,
        f"the STOP's event (events so far: {events()})",
    )


async def test_runs_survive_restart_and_cut_runs_become_incomplete(tmp_path: Path) -> None:
    with running_simulator([0, 1], tmp_path, link_path=str(tmp_path / "tty")) as (sim, bus):
        async with live_server(sim, bus, tmp_path / "data") as server:
            run = await finished_run(
                server, "line-0", await start(server, "line-0", kind="move", distance=800)
            )
        storage = Storage(tmp_path / "data" / "servotune.db")
        storage.create_run("cut", "slap2/line/0", "line-0", 1.0, {"test": {}, "metrics": None})
        storage.close()
        async with live_server(sim, bus, tmp_path / "data") as server:
            runs = (await server.client.get("/api/axes/line-0/bench/runs")).json()
            by_id = {r["id"]: r for r in runs}
            assert by_id[run["id"]]["status"] == "complete"
            assert by_id["cut"]["status"] == "incomplete"


async def test_velocity_test_is_stopped_at_the_travel_limit(api: LiveServer) -> None:
    limits = {"max_distance_counts": 3000, "max_velocity": 5000, "max_pwm": 40, "max_duration_s": 5}
    assert (await api.client.put("/api/axes/line-1/bench/limits", json=limits)).status_code == 200
    run_id = await start(api, "line-1", kind="velocity_step", velocity=3000, duration_s=4)
    run = await finished_run(api, "line-1", run_id)
    assert run["status"] == "incomplete"
    assert "exceeded your limit" in run["message"]
    module = api.bus.module(1)
    assert not module.rss & VM and module.rss & PM, "the axis was left running, or unpowered"
    # Stopped near the limit and held there (pm where the shaft is), far from the
    # ~110000 counts four seconds at this speed would have covered.
    assert abs(module.position) < 6_000


async def test_a_test_is_refused_while_the_axis_moves(api: LiveServer) -> None:
    await api.client.post("/api/axes/line-0/commands", json={"command": "position_mode"})
    await api.client.post(
        "/api/axes/line-0/commands", json={"command": "move_relative", "distance": 15000}
    )
    for _ in range(100):  # the server knows the axis moves once a sample shows it
        if (await api.state("line-0"))["flags"]["move"]:
            break
        await asyncio.sleep(0.02)
    response = await api.client.post(
        "/api/axes/line-0/bench/runs", json={"kind": "move", "distance": 1000}
    )
    assert response.status_code == 409
    assert "moving" in response.json()["detail"]


async def test_stop_ends_a_running_test(api: LiveServer) -> None:
    run_id = await start(api, "line-0", kind="velocity_step", velocity=2000, duration_s=4)
    for _ in range(100):
        if api.bus.module(0).rss & 0b0100:  # vm on
            break
        await asyncio.sleep(0.02)
    assert (await api.client.post("/api/stop")).json() == {"failed": []}
    run = await finished_run(api, "line-0", run_id)
    assert run["status"] == "incomplete"
    assert "STOP" in run["message"]
    await asyncio.sleep(0.3)
    module = api.bus.module(0)
    assert not module.rss & VM, "the test went on after STOP"
    assert module.rss & PM and abs(module.motor.speed_rad_s) < 1.0, "STOP did not hold the axis"


async def test_ep7047_move_on_the_bench_ends_in_target(tmp_path: Path) -> None:
    from servotune.config import LinkSpec

    spec = LinkSpec("ep7047", "sim", "ep", 0, [1])
    async with live_server(None, None, tmp_path / "data", spec=spec) as server:
        info = (await server.client.get("/api/axes/ep-1/bench")).json()
        assert info["kinds"] == ["move"]
        run = await finished_run(
            server, "ep-1", await start(server, "ep-1", kind="move", distance=2048)
        )
        assert run["status"] == "complete", run["message"]
        assert run["metrics"]["time_to_flag_s"]["in_target"] is not None
        assert abs(run["metrics"]["steady_state_error"]) <= (run["plan"]["band"] or 5)
        assert run["samples"][-1][-1][run["flags"].index("in_target")] == 1
