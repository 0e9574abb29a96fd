"""Bench runs through the API: start one, wait for it to finish, read its frequency
response.

Every body read here is checked against its documented shape (``schema.BenchRun``,
``schema.BenchRunDetail``, ``schema.FrfData``: no key the shape does not name, the
types it states), so the generated TypeScript the web client reads them with stays
true."""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from typing import Any

import pytest

from servotune.bench.metrics import compute_metrics
from servotune.bench.quality import assess
from servotune.schema import BenchRun, BenchRunDetail, FrfData, RunMetrics
from tests.support.servers import LiveServer


async def finished_run(server: LiveServer, axis_id: str, run_id: str) -> dict[str, Any]:
    for _ in range(400):
        runs = (await server.client.get(f"/api/axes/{axis_id}/bench/runs")).json()
        run = next(r for r in runs if r["id"] == run_id)
        BenchRun.model_validate(run, strict=True)
        if run["status"] != "recording":
            full: dict[str, Any] = (await server.client.get(f"/api/bench/runs/{run_id}")).json()
            BenchRunDetail.model_validate(full, strict=True)
            return full
        await asyncio.sleep(0.05)
    pytest.fail(f"run {run_id} never finished")


async def start(server: LiveServer, axis_id: str, **test: Any) -> str:
    response = await server.client.post(f"/api/axes/{axis_id}/bench/runs", json=test)
    assert response.status_code == 202, response.text
    BenchRun.model_validate(response.json(), strict=True)
    run_id: str = response.json()["id"]
    return run_id


async def frf_analysis(client: Any, run_id: str) -> dict[str, Any]:
    """``GET /api/bench/runs/{run_id}/frf`` (the analysis runs in the compute worker:
    seconds on a loaded host), checked against ``schema.FrfData``."""
    response = await client.get(f"/api/bench/runs/{run_id}/frf", timeout=60)
    assert response.status_code == 200, response.text
    analysis: dict[str, Any] = response.json()
    FrfData.model_validate(analysis, strict=True)
    return analysis


def judge_step(
    times: list[float],
    positions: list[float],
    *,
    t0_s: float,
    y0: float,
    step: float,
    spans: Sequence[Sequence[float]] = (),
) -> tuple[dict[str, Any], dict[str, Any], RunMetrics]:
    """A position step record as the bench judges a move run: (the metrics it keeps,
    its quality, the metrics as computed). ``spans``: ``[t, t_span_s]`` per sample."""
    m = compute_metrics(times, positions, t0_s=t0_s, y0=y0, y_final=y0 + step)
    judged, quality = assess(
        kind="move",
        columns=["t_s", "position"],
        flag_names=[],
        rows=[[t, p, []] for t, p in zip(times, positions, strict=True)],
        t0_s=t0_s,
        response="position",
        y0=y0,
        y_final=y0 + step,
        band=m.band,
        fault_flags=[],
        done_flag=None,
        metrics=m.model_dump(),
        status="complete",
        message="",
        spans=spans,
    )
    assert judged is not None
    return judged, quality, m
