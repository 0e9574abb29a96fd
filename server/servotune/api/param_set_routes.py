"""Named parameter sets per axis: save what the device has now, compare, restore.

Restoring goes through the hub's one command path (validated against the descriptor,
written, read back). Persisting in the device is a separate, explicit step: the
device's own save command (SLAP2 ``save_eeprom``, Z1100 ``save_flash``) with its own
conditions, e.g. the SLAP2 refuses ``pg`` while pm or vm is on.
"""

from __future__ import annotations

import asyncio
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Request

from servotune.api.deps import HubDep
from servotune.api.responses import errors
from servotune.api.routes import ERRORS
from servotune.hub.hub import NotFoundError
from servotune.link.base import InvalidArgumentError
from servotune.schema import (
    SET_NAME_MAX,
    SET_NAME_PATTERN,
    ParamSet,
    ParamSetComparison,
    SavedSet,
    SaveSetRequest,
)
from servotune.storage import Storage

router = APIRouter(tags=["parameter sets"])


def get_storage(request: Request) -> Storage:
    storage: Storage = request.app.state.storage
    return storage


StorageDep = Annotated[Storage, Depends(get_storage)]

SetName = Annotated[
    str,
    Path(
        min_length=1,
        max_length=SET_NAME_MAX,
        pattern=SET_NAME_PATTERN,
        description="name of the set as saved (URL-encoded)",
    ),
]


@router.get(
    "/api/axes/{axis_id}/param-sets", response_model=list[ParamSet], responses=errors(404, 422)
)
async def list_sets(axis_id: str, hub: HubDep, storage: StorageDep) -> list[dict[str, Any]]:
    entry = hub.entry(axis_id)
    return await asyncio.to_thread(storage.list_param_sets, entry.storage_key)


@router.post(
    "/api/axes/{axis_id}/param-sets", status_code=201, response_model=SavedSet, responses=ERRORS
)
async def save_set(
    axis_id: str, body: SaveSetRequest, hub: HubDep, storage: StorageDep
) -> dict[str, Any]:
    """Read every parameter from the device now and store them under ``name``."""
    entry = hub.entry(axis_id)
    params = await hub.read_params(axis_id)
    await asyncio.to_thread(
        storage.save_param_set, entry.storage_key, body.name, entry.info.device, params, body.note
    )
    return {"name": body.name, "params": params}


async def _find(storage: Storage, key: str, name: str) -> dict[str, Any] | None:
    sets = await asyncio.to_thread(storage.list_param_sets, key)
    return next((s for s in sets if s["name"] == name), None)


@router.get(
    "/api/axes/{axis_id}/param-sets/{name}/compare",
    response_model=ParamSetComparison,
    responses=ERRORS,
)
async def compare_set(
    axis_id: str, name: SetName, hub: HubDep, storage: StorageDep
) -> ParamSetComparison:
    entry = hub.entry(axis_id)
    found = await _find(storage, entry.storage_key, name)
    if found is None:
        raise NotFoundError("name", f"no parameter set {name!r} for this axis")
    device = await hub.read_params(axis_id)
    saved: dict[str, int] = found["params"]
    differing = sorted(k for k in set(device) | set(saved) if device.get(k) != saved.get(k))
    return ParamSetComparison(name=name, device=device, saved=saved, differing=differing)


@router.post("/api/axes/{axis_id}/param-sets/{name}/restore", responses=ERRORS)
async def restore_set(
    axis_id: str, name: SetName, hub: HubDep, storage: StorageDep
) -> dict[str, int]:
    """Write the set to the device through the normal path (validated, read back).

    Does not persist it in the device: that is the device's save command."""
    entry = hub.entry(axis_id)
    found = await _find(storage, entry.storage_key, name)
    if found is None:
        raise NotFoundError("name", f"no parameter set {name!r} for this axis")
    if found["device"] != entry.info.device:
        raise InvalidArgumentError(
            "name", f"set {name!r} is for a {found['device']}, this axis is a {entry.info.device}"
        )
    return await hub.write_params(axis_id, found["params"])


@router.delete(
    "/api/axes/{axis_id}/param-sets/{name}",
    status_code=204,
    response_model=None,
    responses=errors(404, 422),
)
async def delete_set(axis_id: str, name: str, hub: HubDep, storage: StorageDep) -> None:
    """Delete a set. Any name is accepted here (not only ``SET_NAME_PATTERN``), so a
    set saved under an older, looser rule (e.g. with a leading space) can be removed."""
    entry = hub.entry(axis_id)
    if not await asyncio.to_thread(storage.delete_param_set, entry.storage_key, name):
        raise NotFoundError("name", f"no parameter set {name!r} for this axis")
