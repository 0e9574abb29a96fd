"""FastAPI app factory. The lifespan owns storage, simulators (demo), links and the hub."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse
from fastapi.staticfiles import StaticFiles

from servotune import __version__
from servotune.api.autotune_routes import router as autotune_router
from servotune.api.bench_routes import router as bench_router
from servotune.api.param_set_routes import router as param_set_router
from servotune.api.routes import router
from servotune.api.twin_routes import router as twin_router
from servotune.autotune import AutoTuner
from servotune.config import LinkSpec
from servotune.drivers.base import (
    DeviceRefusedError,
    DeviceTimeoutError,
    InvalidArgumentError,
    LinkDownError,
    ProtocolError,
)
from servotune.hub import Hub, NotFoundError, UnknownAxisError
from servotune.links import build_link
from servotune.storage import Storage, default_data_dir
from servotune.testbench import TestBench
from servotune.twin import Twin

logger = logging.getLogger(__name__)

WEB_DIST = Path(__file__).resolve().parent.parent / "web_dist"


@dataclass(slots=True)
class AppConfig:
    """What the app runs. ``simulators`` start before the links (demo)."""

    links: list[LinkSpec] = field(default_factory=list)
    data_dir: Path = field(default_factory=default_data_dir)
    autopilot: bool = False
    simulators: list[Callable[[], contextlib.AbstractContextManager[list[LinkSpec]]]] = field(
        default_factory=list
    )
    web_dir: Path = WEB_DIST
    twin: bool = True  # the 3D twin (viser on 127.0.0.1, proxied at /twin/)


def _error(status: int, detail: str, field_name: str | None = None) -> JSONResponse:
    return JSONResponse(status_code=status, content={"detail": detail, "field": field_name})


def create_app(config: AppConfig) -> FastAPI:
    """Build the app; nothing is opened until the lifespan starts."""

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        storage = Storage(config.data_dir / "servotune.db")
        with contextlib.ExitStack() as simulators:
            specs = list(config.links)
            for start_simulator in config.simulators:
                specs.extend(simulators.enter_context(start_simulator()))
            hub = Hub([], storage, autopilot=config.autopilot)
            for spec in specs:
                hub.add_link(build_link(spec, hub))
            bench = TestBench(hub, storage)
            app.state.hub = hub
            app.state.bench = bench
            app.state.autotuner = AutoTuner(hub, bench)
            app.state.storage = storage
            await hub.start()
            await bench.start()
            app.state.twin = await Twin.start(hub) if config.twin else None
            try:
                yield
            finally:
                if app.state.twin is not None:
                    await app.state.twin.stop()
                await bench.stop()
                await hub.stop()
                # Let pending storage writes finish before the database closes.
                await asyncio.sleep(0)
                storage.close()

    app = FastAPI(
        title="servotune",
        version=__version__,
        summary="Tuning dashboard for servo motor controllers",
        lifespan=lifespan,
    )
    app.include_router(router)
    app.include_router(bench_router)
    app.include_router(autotune_router)
    app.include_router(param_set_router)
    app.include_router(twin_router)

    @app.exception_handler(InvalidArgumentError)
    async def invalid(_: Request, exc: InvalidArgumentError) -> JSONResponse:
        return _error(422, str(exc), exc.field)

    @app.exception_handler(RequestValidationError)
    async def malformed(_: Request, exc: RequestValidationError) -> JSONResponse:
        first = exc.errors()[0] if exc.errors() else {}
        location = [str(p) for p in first.get("loc", ()) if p != "body"]
        name = ".".join(location) or None
        message = first.get("msg", "malformed request")
        return _error(422, f"{name}: {message}" if name else str(message), name)

    @app.exception_handler(DeviceRefusedError)
    async def refused(_: Request, exc: DeviceRefusedError) -> JSONResponse:
        return _error(409, str(exc))

    @app.exception_handler(LinkDownError)
    async def link_down(_: Request, exc: LinkDownError) -> JSONResponse:
        return _error(503, str(exc))

    @app.exception_handler(DeviceTimeoutError)
    async def timeout(_: Request, exc: DeviceTimeoutError) -> JSONResponse:
        return _error(504, f"device did not answer: {exc}")

    @app.exception_handler(ProtocolError)
    async def protocol(_: Request, exc: ProtocolError) -> JSONResponse:
        return _error(502, f"device protocol error: {exc}")

    @app.exception_handler(NotFoundError)
    async def not_found(_: Request, exc: NotFoundError) -> JSONResponse:
        return _error(404, str(exc), exc.field)

    @app.exception_handler(UnknownAxisError)
    async def unknown_axis(_: Request, exc: UnknownAxisError) -> JSONResponse:
        return _error(404, f"no axis {exc.args[0]!r}", "axis")

    if (config.web_dir / "index.html").exists():
        app.mount("/", StaticFiles(directory=config.web_dir, html=True), name="web")
    else:

        @app.get("/", response_class=HTMLResponse, include_in_schema=False)
        async def no_bundle() -> str:
            return (
                "<h1>servotune</h1><p>The web bundle is not built. Run "
                "<code>scripts/demo.sh</code> (or <code>npm --prefix web ci && npm --prefix "
                "web run build</code>). The API is at <a href='/docs'>/docs</a>.</p>"
            )

    return app
