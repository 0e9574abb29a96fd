"""REST resources of the tuning test bench under ``/api/axes/{id}/bench`` and ``/api/bench``."""

from __future__ import annotations

import asyncio
import contextlib
import shutil
import tempfile
from collections.abc import Awaitable, Callable, MutableMapping
from pathlib import Path
from typing import IO, Annotated, Any, Literal

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse, Response, StreamingResponse
from starlette.datastructures import UploadFile

from servotune.api.gains_check import device_law
from servotune.api.responses import json_errors
from servotune.api.routes import ERRORS
from servotune.bench.files import MAX_IMPORT_BYTES, MAX_IMPORT_JSON_BYTES, MAX_META_BYTES
from servotune.bench.metrics import DEFINITIONS
from servotune.bench.runner import BenchLimits
from servotune.bench.service import BenchTestRequest, TestBench
from servotune.descriptor import DeviceDescriptor
from servotune.hub.hub import Hub, NotFoundError
from servotune.link.base import DriverError, InvalidArgumentError
from servotune.schema import (
    BenchField,
    BenchInfo,
    BenchRun,
    BenchRunDetail,
    ErrorBody,
    StorageStatus,
)
from servotune.storage import Storage, dumps_strict

STORE_ERRORS: dict[int | str, dict[str, Any]] = {
    **ERRORS,
    507: {"model": ErrorBody, "description": "the database cannot be written: nothing saved"},
}

router = APIRouter(tags=["bench"])


def get_bench(request: Request) -> TestBench:
    bench: TestBench = request.app.state.bench
    return bench


BenchDep = Annotated[TestBench, Depends(get_bench)]


def bench_fields(descriptor: DeviceDescriptor) -> dict[str, BenchField]:
    """The units of the bench form's fields, from the axis' descriptor: the distance in
    the position channel's, the velocity in the parameter a velocity step sets (else the
    velocity channel's), the PWM in its command argument's."""
    channels = {c.name: c for c in descriptor.channels}
    position = channels.get("position")
    parameters = {p.name: p for p in descriptor.parameters}
    velocity_parameter = parameters.get(descriptor.bench_velocity_parameter or "")
    velocity = velocity_parameter or channels.get("velocity")
    pwm = next((a for c in descriptor.commands for a in c.arguments if a.name == "pwm"), None)
    return {
        "distance": BenchField(
            parameter=None,
            unit=position.unit if position else "counts",
            conversions=list(position.conversions) if position else [],
        ),
        "velocity": BenchField(
            parameter=velocity_parameter.name if velocity_parameter else None,
            unit=velocity.unit if velocity else "",
            conversions=list(velocity.conversions) if velocity else [],
        ),
        "pwm": BenchField(parameter=None, unit=pwm.unit if pwm else "", conversions=[]),
    }


class _BodyTooLargeError(Exception):
    pass


def _too_large(limit: int) -> JSONResponse:
    return JSONResponse(
        status_code=413,
        content={
            "detail": f"the import is larger than {limit // (1024 * 1024)} MiB"
            + (
                f"; send it as multipart (meta + csv files, up to "
                f"{MAX_IMPORT_BYTES // (1024 * 1024)} MiB)"
                if limit < MAX_IMPORT_BYTES
                else ""
            ),
            "field": "body",
        },
    )


Receive = Callable[[], Awaitable[MutableMapping[str, Any]]]


def _limited(receive: Receive, limit: int) -> Receive:
    """``receive`` that raises _BodyTooLargeError once more than ``limit`` bytes came in."""
    total = 0

    async def limited_receive() -> MutableMapping[str, Any]:
        nonlocal total
        message = await receive()
        total += len(message.get("body", b""))
        if total > limit:
            raise _BodyTooLargeError
        return message

    return limited_receive


def _missing(run_id: str) -> NotFoundError:
    return NotFoundError("run", f"no run {run_id!r}")


async def _body_to_file(request: Request, limit: int, path: Path) -> None:
    """Stream the body into ``path`` (page cache writes of the ~64 KiB chunks the
    server receives are short); _BodyTooLargeError beyond ``limit``."""
    size = 0
    with path.open("wb") as out:
        async for chunk in request.stream():
            size += len(chunk)
            if size > limit:
                raise _BodyTooLargeError
            out.write(chunk)


def _copy_to(source: IO[bytes], path: Path) -> None:
    source.seek(0)
    with path.open("wb") as out:
        shutil.copyfileobj(source, out, 1 << 20)


@router.get("/api/axes/{axis_id}/bench", response_model=BenchInfo, responses=ERRORS)
async def bench_info(axis_id: str, bench: BenchDep, request: Request) -> BenchInfo:
    """The tests this axis' device can run, the user's limits for them, the form's
    units, and whether the what-if view and a measured frequency response work here."""
    kinds = bench.kinds(axis_id)
    hub: Hub = request.app.state.hub
    entry = hub.entry(axis_id)
    law = device_law(request, entry.info.device)
    frequency_response: Literal["measured", "model"] | None = None
    if "frequency_response" in kinds:
        frequency_response = "measured" if law is not None and law.injection else "model"
    return BenchInfo(
        kinds=kinds,
        limits=await bench.limits(axis_id),
        definitions=dict(DEFINITIONS),
        fields=bench_fields(entry.driver.descriptor),
        whatif=law is not None,
        frequency_response=frequency_response,
    )


@router.put("/api/axes/{axis_id}/bench/limits", response_model=BenchLimits, responses=STORE_ERRORS)
async def set_limits(axis_id: str, limits: BenchLimits, bench: BenchDep) -> BenchLimits:
    """Limits every test on this axis is checked against before anything moves."""
    return await bench.set_limits(axis_id, limits)


@router.post(
    "/api/axes/{axis_id}/bench/runs",
    status_code=202,
    responses={**STORE_ERRORS, 202: {"model": BenchRun, "description": "the run, recording"}},
)
async def start_run(
    axis_id: str, test: BenchTestRequest, bench: BenchDep, request: Request
) -> dict[str, Any]:
    """Start a test. 202 with the run (status 'recording'); progress comes over the
    websocket as ``run`` messages; the finished run (metrics) via GET. A model-based
    ``frequency_response`` (a device the bench cannot inject into) is complete at once;
    its Bode data: ``GET /api/bench/runs/{id}/frf``."""
    autotuner = getattr(request.app.state, "autotuner", None)
    identified = None
    if test.kind == "frequency_response" and autotuner is not None:
        with contextlib.suppress(DriverError):
            identified = autotuner.session(axis_id).get("model")
    return await bench.start_run(axis_id, test, identified)


@router.get(
    "/api/axes/{axis_id}/bench/runs",
    responses={**ERRORS, 200: {"model": list[BenchRun], "description": "the runs"}},
)
async def list_runs(axis_id: str, bench: BenchDep) -> list[dict[str, Any]]:
    """Every stored run of this axis, oldest first, without samples."""
    return await bench.list_runs(axis_id)


_IMPORT_BODY = {
    "requestBody": {
        "required": True,
        "description": (
            f"Either JSON ``{{meta, csv}}`` (at most {MAX_IMPORT_JSON_BYTES // 2**20} MiB) or "
            f"multipart/form-data with the parts ``meta`` (run.json, at most "
            f"{MAX_META_BYTES // 2**20} MiB) and ``csv`` (samples.csv), at most "
            f"{MAX_IMPORT_BYTES // 2**20} MiB in all. Larger: 413."
        ),
        "content": {
            "application/json": {
                "schema": {
                    "type": "object",
                    "required": ["meta", "csv"],
                    "properties": {
                        "meta": {"type": "object", "description": "the run.json export"},
                        "csv": {"type": "string", "description": "the samples.csv export"},
                    },
                }
            },
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["meta", "csv"],
                    "properties": {
                        "meta": {"type": "string", "format": "binary"},
                        "csv": {"type": "string", "format": "binary"},
                    },
                }
            },
        },
    }
}


@router.post(
    "/api/axes/{axis_id}/bench/runs/import",
    status_code=201,
    responses={
        **STORE_ERRORS,
        413: {"model": ErrorBody, "description": "body too large (limit in detail)"},
        415: {"model": ErrorBody, "description": "neither JSON nor multipart"},
    },
    openapi_extra=_IMPORT_BODY,
)
async def import_run(axis_id: str, request: Request, bench: BenchDep) -> dict[str, str]:
    """Import a run exported as JSON (``meta``) + CSV (``csv``), checked completely
    (422 naming the field: strict, finite numbers, a finished run of this axis' device,
    the CSV matching the JSON). Parsed and stored off the event loop, chunk by chunk."""
    bench.check_axis(axis_id)
    content_type = request.headers.get("content-type", "")
    multipart = content_type.startswith("multipart/form-data")
    limit = MAX_IMPORT_BYTES if multipart else MAX_IMPORT_JSON_BYTES
    try:
        declared = int(request.headers.get("content-length", "0"))
    except ValueError:
        declared = 0
    if declared > limit:
        return _too_large(limit)  # type: ignore[return-value]
    with tempfile.TemporaryDirectory(prefix="servotune-import-") as scratch:
        body_path = Path(scratch) / "body"
        try:
            if multipart:
                limited = Request(request.scope, _limited(request.receive, limit))
                async with limited.form(
                    max_files=2, max_fields=2, max_part_size=MAX_META_BYTES
                ) as form:
                    meta, samples = form.get("meta"), form.get("csv")
                    if not isinstance(samples, UploadFile):
                        raise InvalidArgumentError("csv", "csv: the samples.csv file is missing")
                    if isinstance(meta, UploadFile):
                        meta_bytes = await meta.read(MAX_META_BYTES + 1)
                    elif isinstance(meta, str):
                        meta_bytes = meta.encode()
                    else:
                        raise InvalidArgumentError("meta", "meta: the run.json part is missing")
                    await asyncio.to_thread(_copy_to, samples.file, body_path)
                run_id = await bench.import_run(axis_id, body_path, meta_bytes)
            elif content_type.startswith("application/json"):
                await _body_to_file(request, limit, body_path)
                run_id = await bench.import_run(axis_id, body_path)
            else:
                return JSONResponse(  # type: ignore[return-value]
                    status_code=415,
                    content={
                        "detail": "send application/json or multipart/form-data",
                        "field": None,
                    },
                )
        except _BodyTooLargeError:
            return _too_large(limit)  # type: ignore[return-value]
    return {"id": run_id}


@router.get("/api/storage", response_model=StorageStatus, tags=["bench"])
async def storage_status(request: Request) -> StorageStatus:
    """Whether settings, sets and runs are being saved (``writable``), and why not."""
    storage: Storage = request.app.state.storage
    return StorageStatus(writable=storage.problem is None, message=storage.problem or "")


@router.get(
    "/api/bench/runs/{run_id}",
    responses={**ERRORS, 200: {"model": BenchRunDetail, "description": "the run"}},
    response_class=StreamingResponse,
)
async def get_run(run_id: str, bench: BenchDep) -> StreamingResponse:
    """One run with its samples: ``columns`` name the values of each sample row, the
    last element of a row is the list of flag values in ``flags`` order. Streamed."""
    try:
        body = await bench.iter_run_json(run_id)
    except KeyError:
        raise _missing(run_id) from None
    return StreamingResponse(body, media_type="application/json")


@router.delete(
    "/api/bench/runs/{run_id}", status_code=204, response_model=None, responses=STORE_ERRORS
)
async def delete_run(run_id: str, bench: BenchDep) -> None:
    try:
        await bench.delete_run(run_id)
    except KeyError:
        raise _missing(run_id) from None


@router.post(
    "/api/bench/runs/{run_id}/baseline",
    status_code=204,
    response_model=None,
    responses=STORE_ERRORS,
)
async def set_baseline(run_id: str, bench: BenchDep) -> None:
    """Mark this run as the baseline of its axis."""
    try:
        await bench.set_baseline(run_id)
    except KeyError:
        raise _missing(run_id) from None


@router.get(
    "/api/bench/runs/{run_id}/samples.csv",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/csv": {}}}, **json_errors(404, 422)},
)
async def export_csv(run_id: str, bench: BenchDep) -> StreamingResponse:
    """The samples as CSV (the run's columns, then one 0/1 column per flag), streamed."""
    try:
        body = await bench.iter_run_csv(run_id)
    except KeyError:
        raise _missing(run_id) from None
    return StreamingResponse(
        body,
        media_type="text/csv",
        headers={"Content-Disposition": f'attachment; filename="run-{run_id}.csv"'},
    )


@router.get("/api/bench/runs/{run_id}/run.json", response_model=None, responses=ERRORS)
async def export_json(run_id: str, bench: BenchDep) -> Response:
    """Everything but the samples (those go to CSV); what the import takes as ``meta``."""
    try:
        run = await bench.get_run_meta(run_id)
    except KeyError:
        raise _missing(run_id) from None
    return Response(
        dumps_strict(run),
        media_type="application/json",
        headers={"Content-Disposition": f'attachment; filename="run-{run_id}.json"'},
    )
