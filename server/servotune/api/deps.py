"""FastAPI dependencies: the hub lives on ``app.state``, owned by the lifespan."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request, WebSocket

from servotune.hub.hub import Hub


def get_hub(request: Request) -> Hub:
    hub: Hub = request.app.state.hub
    return hub


def get_ws_hub(websocket: WebSocket) -> Hub:
    hub: Hub = websocket.app.state.hub
    return hub


HubDep = Annotated[Hub, Depends(get_hub)]
WsHubDep = Annotated[Hub, Depends(get_ws_hub)]
