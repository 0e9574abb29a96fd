"""REST routes (the websocket: ``api.ws``). Handlers only translate HTTP to hub calls.

Every route states the error codes it can answer (``responses=``, see
``servotune.api.responses``); the command and params bodies are stated per device in
the live OpenAPI (``servotune.api.openapi``).
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body, Query, Request

from servotune.api.deps import HubDep
from servotune.api.gains_check import check_predicted_stable
from servotune.api.responses import DEVICE_ERRORS, NOT_FOUND, errors
from servotune.descriptor import DeviceDescriptor
from servotune.hub.hub import NotFoundError
from servotune.link.base import DeviceRefusedError, DriverError, InvalidArgumentError, LinkDownError
from servotune.link.validation import validate_params
from servotune.schema import (
    AxisInfo,
    AxisState,
    CommandRequest,
    CommandResult,
    ConsoleReply,
    ConsoleRequest,
    LinkInfo,
    LinkStatus,
    StopResult,
)

router = APIRouter(prefix="")

# Kept for the routers that import it: the answers of a route that talks to a device.
ERRORS = DEVICE_ERRORS


@router.get("/api/axes", response_model=list[AxisInfo], tags=["axes"])
async def list_axes(hub: HubDep) -> list[AxisInfo]:
    """Every axis of every link."""
    return hub.axes_info()


@router.get("/api/links", response_model=list[LinkInfo], tags=["links"])
async def list_links(hub: HubDep) -> list[LinkInfo]:
    return hub.links_info()


@router.get(
    "/api/links/{link_id}/status", response_model=LinkStatus, responses=NOT_FOUND, tags=["links"]
)
async def link_status(link_id: str, hub: HubDep) -> LinkStatus:
    try:
        return hub.link_status(link_id)
    except KeyError:
        raise NotFoundError("link", f"no link {link_id!r}") from None


@router.get(
    "/api/axes/{axis_id}/descriptor",
    response_model=DeviceDescriptor,
    responses=NOT_FOUND,
    tags=["axes"],
)
async def descriptor(axis_id: str, hub: HubDep) -> DeviceDescriptor:
    """The device descriptor the UI renders (parameters, channels, flags, commands,
    the STOP's effect and the cross-field constraints)."""
    return hub.descriptor(axis_id)


@router.get("/api/axes/{axis_id}/params", responses=DEVICE_ERRORS, tags=["params"])
async def read_params(axis_id: str, hub: HubDep) -> dict[str, int]:
    """Read every parameter from the device now."""
    return await hub.read_params(axis_id)


@router.patch("/api/axes/{axis_id}/params", responses=DEVICE_ERRORS, tags=["params"])
async def write_params(
    axis_id: str,
    hub: HubDep,
    request: Request,
    values: Annotated[dict[str, Any], Body(examples=[{"kp": 60, "kd": 120}])],
    confirm_unstable: Annotated[
        bool,
        Query(description="write gains the identified plant predicts unstable all the same"),
    ] = False,
) -> dict[str, int]:
    """Write parameters, read them back from the device and return the read-back values.

    All values are checked against the descriptor first: one bad value (unknown name,
    not an integer, out of range, or breaking a descriptor ``constraint`` together with
    the device's current values) answers 422 naming the field and its range, and then
    nothing is written. Gains that the axis' identified plant predicts unstable
    (``tuning.predicted``) answer 409 naming ``confirm_unstable`` unless it is set.
    The body's schema per device is in the live OpenAPI.
    """
    validate_params(hub.descriptor(axis_id), values, hub.entry(axis_id).device_values)
    await check_predicted_stable(request, axis_id, values, confirm_unstable)
    return await hub.write_params(axis_id, values)


@router.get(
    "/api/axes/{axis_id}/state",
    response_model=AxisState,
    responses=errors(404, 422, 503),
    tags=["axes"],
)
async def axis_state(axis_id: str, hub: HubDep) -> AxisState:
    """The latest telemetry sample (503 until the first one arrived)."""
    state = hub.axis_state(axis_id)
    if state is None:
        raise LinkDownError(f"no telemetry from {axis_id} yet")
    return state


@router.post(
    "/api/axes/{axis_id}/commands",
    response_model=CommandResult,
    responses=DEVICE_ERRORS,
    tags=["commands"],
)
async def command(axis_id: str, hub: HubDep, request: CommandRequest) -> CommandResult:
    """Run a descriptor command: ``{"command": "move_absolute", "position": 1000}``.

    Arguments are integers in the descriptor's ranges; one marked ``required`` must be
    given, any other may be omitted and takes its ``default``. 422 names the argument.
    """
    args = dict(request.model_extra or {})
    outcome = await hub.command(axis_id, request.command, args)
    return CommandResult(
        command=request.command,
        sent=outcome.sent,
        message=outcome.message,
        outcome_pending=outcome.outcome_pending,
    )


@router.post("/api/stop", response_model=StopResult, tags=["commands"])
async def stop_all(hub: HubDep) -> StopResult:
    """STOP every axis now (the UI's STOP button and Esc key). What the stop does on
    each device is the descriptor's ``stop`` (e.g. SLAP2: motor unpowered)."""
    failed = await hub.stop_all()
    return StopResult(failed=failed)


@router.post(
    "/api/axes/{axis_id}/console",
    response_model=ConsoleReply,
    responses=errors(403, 404, 409, 422, 503),
    tags=["console"],
)
async def console(
    axis_id: str, hub: HubDep, request: ConsoleRequest, http: Request
) -> ConsoleReply:
    """Send one raw line to the axis' module; returns every reply line.

    The line must be printable (no CR, LF, Ctrl-X or other control characters: 422
    naming ``line``), and one whose effect the device's descriptor states (a read, a
    parameter write, a command, storing settings): it needs the permission of what it
    is, as the same action through its own route would (``pg`` on a SLAP2 needs
    'persist' like ``save_eeprom``); any other line is refused with 422 naming
    ``line``, nothing sent. Errors of the exchange (no echo, refused by the protocol)
    come back in ``error`` with status 200 so the console can show them next to the
    line. After a parameter write the parameters are read back for the audit log.
    """
    try:
        sent, reply = await hub.console(axis_id, request.line)
    except (DeviceRefusedError, InvalidArgumentError, LinkDownError):
        raise
    except DriverError as exc:
        return ConsoleReply(line=request.line, sent=request.line, reply=[], error=str(exc))
    audit: dict[str, Any] | None = getattr(http.state, "audit", None)
    written = hub.descriptor(axis_id).console.parameters_set(request.line)
    if audit is not None and written:
        try:
            values = await hub.read_params(axis_id)
            audit["after"] = {name: values.get(name) for name in written}
        except DriverError as exc:
            audit["after"] = {"read_back_failed": str(exc)}
    return ConsoleReply(line=request.line, sent=sent, reply=reply, error=None)
