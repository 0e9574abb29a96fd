"""The control-lock check on REST routes that change an axis (423 when another tab holds it).

``require_axis_control`` is applied to the axis routers in ``api.app``. It passes reads
(GET/HEAD), routes without an ``axis_id``, the routes in ``NO_LOCK_ROUTES`` (they change
stored things, not the device), and commands of the descriptor's ``stop`` group: stopping
is the safe direction and stays live for everyone. Everything else asks
``app.state.control.require`` with the ``X-Servotune-Client`` header.

MERGE NOTE: once the auth branch's global dependency calls ``control.require`` itself
(with the real principal), drop this dependency from ``app.include_router``; until then
the principal is local mode's (``request_principal``).
"""

from __future__ import annotations

import json

from fastapi import Request
from fastapi.routing import APIRoute

from servotune.auth.principal import LOCAL_PRINCIPAL, Principal
from servotune.control import CLIENT_HEADER, ControlManager
from servotune.hub import Hub

# (method, path template) of axis routes that change no device.
NO_LOCK_ROUTES = frozenset(
    {
        ("PUT", "/api/axes/{axis_id}/bench/limits"),
        ("POST", "/api/axes/{axis_id}/bench/runs/import"),
        ("POST", "/api/axes/{axis_id}/param-sets"),
        ("DELETE", "/api/axes/{axis_id}/param-sets/{name}"),
    }
)


def request_principal(request: Request) -> Principal:
    """MERGE SEAM: the auth branch resolves the real principal; local mode until then."""
    principal = getattr(request.state, "principal", None)
    return principal if isinstance(principal, Principal) else LOCAL_PRINCIPAL


async def _is_stop_command(request: Request, hub: Hub, axis_id: str) -> bool:
    try:
        body = json.loads(await request.body() or b"{}")
    except ValueError:
        return False  # the route answers 422
    name = body.get("command") if isinstance(body, dict) else None
    if not isinstance(name, str):
        return False
    try:
        return hub.descriptor(axis_id).command(name).group == "stop"
    except KeyError:
        return False  # unknown axis or command: the route answers 404 / 422


async def require_axis_control(request: Request) -> None:
    """Refuse (423, naming the holder) a change of an axis another client holds."""
    if request.method in ("GET", "HEAD", "OPTIONS"):
        return
    axis_id = request.path_params.get("axis_id")
    if not isinstance(axis_id, str):
        return
    route = request.scope.get("route")
    template = route.path if isinstance(route, APIRoute) else request.url.path
    if (request.method, template) in NO_LOCK_ROUTES:
        return
    hub: Hub = request.app.state.hub
    if template.endswith("/commands") and await _is_stop_command(request, hub, axis_id):
        return
    control: ControlManager = request.app.state.control
    await control.require(axis_id, request.headers.get(CLIENT_HEADER), request_principal(request))
