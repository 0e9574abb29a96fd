"""REST routes. Handlers only translate HTTP to hub calls (the websocket: ``api.ws``)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body

from servotune.api.deps import HubDep
from servotune.descriptor import DeviceDescriptor
from servotune.drivers.base import (
    DeviceRefusedError,
    DriverError,
    InvalidArgumentError,
    LinkDownError,
)
from servotune.wire import (
    AxisInfo,
    AxisState,
    CommandRequest,
    CommandResult,
    ConsoleReply,
    ConsoleRequest,
    ErrorBody,
    LinkInfo,
    LinkStatus,
)

router = APIRouter(prefix="")

ERRORS: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorBody, "description": "no such axis"},
    409: {"model": ErrorBody, "description": "the device refused (reason in detail)"},
    422: {"model": ErrorBody, "description": "bad input: detail names the field and range"},
    503: {"model": ErrorBody, "description": "link down: nothing was sent"},
    504: {"model": ErrorBody, "description": "the device did not answer"},
}


@router.get("/api/axes", response_model=list[AxisInfo], tags=["axes"])
async def list_axes(hub: HubDep) -> list[AxisInfo]:
    """Every axis of every link."""
    return hub.axes_info()


@router.get("/api/links", response_model=list[LinkInfo], tags=["links"])
async def list_links(hub: HubDep) -> list[LinkInfo]:
    return hub.links_info()


@router.get("/api/links/{link_id}/status", response_model=LinkStatus, tags=["links"])
async def link_status(link_id: str, hub: HubDep) -> LinkStatus:
    try:
        return hub.link_status(link_id)
    except KeyError:
        raise InvalidArgumentError("link", f"no link {link_id!r}") from None


@router.get(
    "/api/axes/{axis_id}/descriptor",
    response_model=DeviceDescriptor,
    responses=ERRORS,
    tags=["axes"],
)
async def descriptor(axis_id: str, hub: HubDep) -> DeviceDescriptor:
    """The device descriptor the UI renders (parameters, channels, flags, commands)."""
    return hub.descriptor(axis_id)


@router.get("/api/axes/{axis_id}/params", responses=ERRORS, tags=["params"])
async def read_params(axis_id: str, hub: HubDep) -> dict[str, int]:
    """Read every parameter from the device now."""
    return await hub.read_params(axis_id)


@router.patch("/api/axes/{axis_id}/params", responses=ERRORS, tags=["params"])
async def write_params(
    axis_id: str,
    hub: HubDep,
    values: Annotated[dict[str, Any], Body(examples=[{"kp": 60, "kd": 120}])],
) -> dict[str, int]:
    """Write parameters, read them back from the device and return the read-back values.

    All values are checked against the descriptor first: one bad value answers 422
    naming the field and its range, and then nothing is written.
    """
    return await hub.write_params(axis_id, values)


@router.get("/api/axes/{axis_id}/state", response_model=AxisState, responses=ERRORS, tags=["axes"])
async def axis_state(axis_id: str, hub: HubDep) -> AxisState:
    """The latest telemetry sample (503 until the first one arrived)."""
    state = hub.axis_state(axis_id)
    if state is None:
        raise LinkDownError(f"no telemetry from {axis_id} yet")
    return state


@router.post(
    "/api/axes/{axis_id}/commands",
    response_model=CommandResult,
    responses=ERRORS,
    tags=["commands"],
)
async def command(axis_id: str, hub: HubDep, request: CommandRequest) -> CommandResult:
    """Run a descriptor command: ``{"command": "move_absolute", "position": 1000}``."""
    args = dict(request.model_extra or {})
    outcome = await hub.command(axis_id, request.command, args)
    return CommandResult(command=request.command, sent=outcome.sent, message=outcome.message)


@router.post("/api/stop", tags=["commands"])
async def stop_all(hub: HubDep) -> dict[str, list[str]]:
    """STOP every axis now (the UI's STOP button and Esc key)."""
    failed = await hub.stop_all()
    return {"failed": failed}


@router.post(
    "/api/axes/{axis_id}/console",
    response_model=ConsoleReply,
    responses=ERRORS,
    tags=["console"],
)
async def console(axis_id: str, hub: HubDep, request: ConsoleRequest) -> ConsoleReply:
    """Send one raw line to the axis' module; returns every reply line.

    Errors of the exchange (no echo, refused) come back in ``error`` with status 200
    so the console can show them next to the line.
    """
    try:
        sent, reply = await hub.console(axis_id, request.line)
    except (DeviceRefusedError, InvalidArgumentError, LinkDownError):
        raise
    except DriverError as exc:
        return ConsoleReply(line=request.line, sent=request.line, reply=[], error=str(exc))
    return ConsoleReply(line=request.line, sent=sent, reply=reply, error=None)
