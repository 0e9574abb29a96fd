"""Auto-tune failure paths: a STOP during ``accept`` answers
normally and leaves the previous gains in force; a failed identification returns the
axis to its start and answers its whole message."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from servotune.devices.slap2 import tuner as slap2_tuner
from servotune.devices.slap2.sim.line import Slap2Line
from servotune.devices.slap2.sim.module import Slap2Module
from servotune.schema import AutoTuneSession, AutoTuneStopped
from servotune.sim.pty import PtySimulator
from tests.support.servers import live_server

LIMITS = {"max_pwm": 60, "max_distance_counts": 4000, "response": "no_overshoot"}


async def test_stop_during_accept_answers_normally_and_restores_the_previous_gains(
    tmp_path: Path,
) -> None:
    bus = Slap2Line([Slap2Module(0), Slap2Module(1)])
    module = bus.module(0)
    with PtySimulator(bus, baud=19200) as sim:
        async with live_server(sim, bus, tmp_path / "data") as server:
            client = server.client
            response = await client.post(
                "/api/axes/line-0/autotune/identify", json=LIMITS, timeout=90
            )
            assert response.status_code == 200, response.text
            proposal = response.json()
            previous = proposal["current_gains"]
            assert proposal["gains"] != previous
            accept = asyncio.ensure_future(
                client.post("/api/axes/line-0/autotune/accept", timeout=90)
            )
            # STOP once the proposed gains are on the device (the verification runs).
            for _ in range(1500):
                if module.settings["kp"] == proposal["gains"]["kp"]:
                    break
                await asyncio.sleep(0.01)
            assert module.settings["kp"] == proposal["gains"]["kp"], "the gains were never written"
            assert (await client.post("/api/stop")).json() == {"failed": []}
            response = await accept
            assert response.status_code == 200, response.text
            body = response.json()
            AutoTuneStopped.model_validate(body, strict=True)  # the generated type's
            assert body["stopped"] is True and body["unverified"] is False
            assert "STOP" in body["message"] and "previous gains are in force" in body["message"]
            assert {k: module.settings[k] for k in ("kp", "ki", "kd")} == previous
            assert body["gains_in_force"] == previous
            session = (await client.get("/api/axes/line-0/autotune")).json()
            AutoTuneSession.model_validate(session, strict=True)
            assert session["state"] == "failed" and "STOP" in session["message"]
            assert session["result"] == body


def failing_fit(*args: object, **kwargs: object) -> object:
    """A fit that fails (module level: the fit runs in the compute worker, which gets
    the function by its name)."""
    raise ValueError("injected: the fit did not converge")


async def test_a_failed_identification_returns_the_axis_and_says_everything(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(slap2_tuner, "fit_plant", failing_fit)
    bus = Slap2Line([Slap2Module(0), Slap2Module(1)])
    module = bus.module(0)
    with PtySimulator(bus, baud=19200) as sim:
        async with live_server(sim, bus, tmp_path / "data") as server:
            start = module.position
            response = await server.client.post(
                "/api/axes/line-0/autotune/identify", json=LIMITS, timeout=90
            )
            assert response.status_code == 422, response.text
            detail = response.json()["detail"]
            assert "injected: the fit did not converge" in detail
            assert "axis stopped" in detail and "returned to its start" in detail
            band = int(module.settings.get("sipw", 5))
            assert abs(module.position - start) <= 2 * max(band, 5)
            session = (await server.client.get("/api/axes/line-0/autotune")).json()
            AutoTuneSession.model_validate(session, strict=True)
            assert session["state"] == "failed" and session["message"].endswith(detail[-40:])
            assert session["proposal"] is None and session["result"] is None
