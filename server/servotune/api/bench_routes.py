"""REST resources of the tuning test bench under ``/api/axes/{id}/bench`` and ``/api/bench``."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse, PlainTextResponse
from pydantic import BaseModel, Field

from servotune.api.responses import NOT_FOUND, errors, json_errors
from servotune.api.routes import ERRORS
from servotune.hub import NotFoundError
from servotune.metrics import Metrics
from servotune.testbench import BenchLimits, BenchTestRequest, TestBench

router = APIRouter(tags=["bench"])


def get_bench(request: Request) -> TestBench:
    bench: TestBench = request.app.state.bench
    return bench


BenchDep = Annotated[TestBench, Depends(get_bench)]


class BenchInfo(BaseModel):
    kinds: list[str]
    limits: BenchLimits
    definitions: dict[str, str] = Field(description="how each metric is computed")


class ImportRequest(BaseModel):
    meta: dict[str, Any]
    csv: str


def _missing(run_id: str) -> NotFoundError:
    return NotFoundError("run", f"no run {run_id!r}")


@router.get("/api/axes/{axis_id}/bench", response_model=BenchInfo, responses=ERRORS)
async def bench_info(axis_id: str, bench: BenchDep) -> BenchInfo:
    """The tests this axis' device can run, and the user's limits for them."""
    return BenchInfo(
        kinds=bench.kinds(axis_id),
        limits=await bench.limits(axis_id),
        definitions=dict(Metrics.definitions),
    )


@router.put("/api/axes/{axis_id}/bench/limits", response_model=BenchLimits, responses=ERRORS)
async def set_limits(axis_id: str, limits: BenchLimits, bench: BenchDep) -> BenchLimits:
    """Limits every test on this axis is checked against before anything moves."""
    return await bench.set_limits(axis_id, limits)


@router.post("/api/axes/{axis_id}/bench/runs", status_code=202, responses=ERRORS)
async def start_run(axis_id: str, test: BenchTestRequest, bench: BenchDep) -> dict[str, Any]:
    """Start a test. 202 with the run (status 'recording'); progress comes over the
    websocket as ``run`` messages; the finished run (metrics) via GET."""
    return await bench.start_run(axis_id, test)


@router.get("/api/axes/{axis_id}/bench/runs", responses=ERRORS)
async def list_runs(axis_id: str, bench: BenchDep) -> list[dict[str, Any]]:
    """Every stored run of this axis, oldest first, without samples."""
    return await bench.list_runs(axis_id)


@router.post(
    "/api/axes/{axis_id}/bench/runs/import",
    status_code=201,
    responses={**ERRORS, **errors(413)},
)
async def import_run(axis_id: str, body: ImportRequest, bench: BenchDep) -> dict[str, str]:
    """Import a run exported as JSON (``meta``) + CSV (``csv``)."""
    return {"id": await bench.import_run(axis_id, body.meta, body.csv)}


@router.get("/api/bench/runs/{run_id}", responses=ERRORS)
async def get_run(run_id: str, bench: BenchDep) -> dict[str, Any]:
    """One run with its samples: ``columns`` name the values of each sample row, the
    last element of a row is the list of flag values in ``flags`` order."""
    try:
        return await bench.get_run(run_id)
    except KeyError:
        raise _missing(run_id) from None


@router.delete(
    "/api/bench/runs/{run_id}", status_code=204, response_model=None, responses=NOT_FOUND
)
async def delete_run(run_id: str, bench: BenchDep) -> None:
    try:
        await bench.delete_run(run_id)
    except KeyError:
        raise _missing(run_id) from None


@router.post(
    "/api/bench/runs/{run_id}/baseline", status_code=204, response_model=None, responses=NOT_FOUND
)
async def set_baseline(run_id: str, bench: BenchDep) -> None:
    """Mark this run as the baseline of its axis."""
    try:
        await bench.set_baseline(run_id)
    except KeyError:
        raise _missing(run_id) from None


@router.get(
    "/api/bench/runs/{run_id}/samples.csv",
    response_class=PlainTextResponse,
    responses={200: {"content": {"text/csv": {}}}, **json_errors(404, 422)},
)
async def export_csv(run_id: str, bench: BenchDep) -> PlainTextResponse:
    try:
        run = await bench.get_run(run_id)
    except KeyError:
        raise _missing(run_id) from None
    return PlainTextResponse(
        TestBench.to_csv(run),
        media_type="text/csv",
        headers={"Content-Disposition": f'attachment; filename="run-{run_id}.csv"'},
    )


@router.get("/api/bench/runs/{run_id}/run.json", response_model=None, responses=NOT_FOUND)
async def export_json(run_id: str, bench: BenchDep) -> JSONResponse:
    try:
        run = await bench.get_run(run_id)
    except KeyError:
        raise _missing(run_id) from None
    return JSONResponse(
        TestBench.to_json(run),
        headers={"Content-Disposition": f'attachment; filename="run-{run_id}.json"'},
    )
