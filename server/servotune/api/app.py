"""FastAPI app factory. The lifespan owns storage, simulators (demo), links and the hub."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import BaseRoute, Match, Mount
from starlette.types import Scope

from servotune import __version__
from servotune.api.auth_routes import router as auth_router
from servotune.api.autotune_routes import router as autotune_router
from servotune.api.bench_routes import router as bench_router
from servotune.api.frf_routes import router as frf_router
from servotune.api.openapi import device_openapi
from servotune.api.param_set_routes import router as param_set_router
from servotune.api.responses import errors
from servotune.api.routes import router
from servotune.api.twin_routes import router as twin_router
from servotune.api.ws import router as ws_router
from servotune.auth.install import install_security
from servotune.auth.passwords import PRODUCT_PASSWORD_COST, PasswordCost
from servotune.auth.security import SecurityConfig
from servotune.autotune.service import AutoTuner
from servotune.bench.service import TestBench
from servotune.compute import PRELOAD, ComputePool
from servotune.config import LinkSpec
from servotune.devices import default_registry
from servotune.hub.control_client import AuditSink, ControlSettings
from servotune.hub.control_lock import ControlLock
from servotune.hub.hub import Hub, NotFoundError
from servotune.hub.state import UnknownAxisError
from servotune.link.base import (
    DeviceRefusedError,
    DeviceTimeoutError,
    DriverError,
    InvalidArgumentError,
    LinkDownError,
    MeasurementError,
    ProtocolError,
)
from servotune.storage import Storage, StorageError, default_data_dir
from servotune.twin.service import Twin

if TYPE_CHECKING:
    from servotune.bus.connection import BusSettings
    from servotune.registry import Registry

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
    # Local or exposed mode, TLS, reverse proxy (servotune.auth.security).
    security: SecurityConfig = field(default_factory=SecurityConfig)
    control: ControlSettings = field(default_factory=ControlSettings)
    # The control lock's clock (its leases, the dead-man): tests inject one they step,
    # so the dead-man's rule is checked on the server's own time, not on how fast a
    # loaded machine runs the test.
    control_clock: Callable[[], float] = time.monotonic
    # The Argon2id cost of new password hashes and of the unknown-user check. Decision:
    # a field the code building the app sets, never an option of the CLI or the config
    # file, so no deployment can weaken it; the tests pass a cheap one, except where
    # the real cost is what they test (tests/support/auth.py).
    password_cost: PasswordCost = PRODUCT_PASSWORD_COST
    twin: bool = True  # the 3D twin (viser on 127.0.0.1, proxied at /twin/)
    bus: BusSettings | None = None  # bus: a rig on NATS, or the lab's hub (docs/lab.md)
    # The devices the links may name (None: servotune.devices.default_registry()).
    devices: Registry | None = None


def _error(
    status: int, detail: str, field_name: str | None = None, kind: str | None = None
) -> JSONResponse:
    content: dict[str, str | None] = {"detail": detail, "field": field_name}
    if kind is not None:
        content["kind"] = kind
    return JSONResponse(status_code=status, content=content)


HTTP_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")


def allowed_methods(routes: list[BaseRoute], scope: Scope) -> list[str]:
    """Every method some route answers at the request's path (the ``Allow`` of a 405).

    Starlette's own 405 lists only the methods of the first route whose path matched,
    but GET and PATCH of one path are two routes here. Each method is probed through
    the routes' own matching, so included routers and path converters count as they
    do for real requests; the static bundle's mount (which takes any path) counts only
    where no API route matches: GET and HEAD."""
    allowed = []
    for method in HTTP_METHODS:
        probe = {**scope, "method": method}
        for route in routes:
            if not isinstance(route, Mount) and route.matches(probe)[0] is Match.FULL:
                allowed.append(method)
                break
    if not allowed and any(
        isinstance(r, Mount) and r.matches(scope)[0] is not Match.NONE for r in routes
    ):
        allowed = ["GET", "HEAD"]
    return allowed


def create_app(config: AppConfig) -> FastAPI:
    """Build the app; nothing is opened until the lifespan starts."""
    devices = config.devices if config.devices is not None else default_registry()

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        storage = Storage(config.data_dir / "servotune.db")
        async with security.running(app), contextlib.AsyncExitStack() as simulators:
            specs = list(config.links)
            for start_simulator in config.simulators:
                specs.extend(simulators.enter_context(start_simulator()))
            hub = Hub([], storage, autopilot=config.autopilot)
            for spec in specs:
                hub.add_link(devices.build_link(spec, hub))
            # bus: the hub registers the rigs' links before it starts (servotune.bus).
            bus = None
            if config.bus is not None:
                from servotune.bus.lifecycle import BusLifecycle  # nats-py only when used

                bus = BusLifecycle(config.bus)
            app.state.bus = bus
            if bus is not None:
                await bus.prepare(hub, storage)
            bench = TestBench(hub, storage, devices)
            app.state.hub = hub
            app.state.devices = devices
            app.state.bench = bench
            # Fits, gain searches and FRF analysis: in a worker process, never on the
            # loop or in a thread that holds the interpreter lock (servotune.compute).
            compute = ComputePool(preload=(*PRELOAD, *devices.compute_modules()))
            app.state.compute = compute
            autotuner = AutoTuner(hub, bench, tuners=devices, compute=compute)
            app.state.autotuner = autotuner
            if config.bus is not None:
                from servotune.bus.lifecycle import make_autotuner  # the hub forwards

                app.state.autotuner = make_autotuner(config.bus, autotuner, hub)
            app.state.storage = storage

            # The control lock and dead-man (servotune.hub.control_lock); it sends every axis a
            # STOP first thing when its link is up, and again at shutdown.
            def audit() -> AuditSink | None:
                return getattr(app.state, "audit", None)

            if config.bus is not None:
                from servotune.bus.lifecycle import make_control  # lab hub: no start-up STOP

                control = make_control(
                    config.bus, hub, config.control, audit=audit, clock=config.control_clock
                )
            else:
                control = ControlLock(hub, config.control, audit=audit, clock=config.control_clock)
            app.state.control = control
            await hub.start()
            await control.start()
            await bench.start()
            app.state.twin = await Twin.start(hub) if config.twin else None
            if bus is not None:
                await bus.start(hub, control, storage, bench, app.state.autotuner)
            # Decision: the heap built by start-up (modules, descriptors, the hub) lives as
            # long as the app, so it is frozen: full collections then skip it instead of
            # holding the interpreter lock while they walk it (docs/performance.md,
            # "Garbage collection"). Unfrozen at shutdown, so that nothing stays frozen
            # past the app (a test process runs many apps one after the other).
            gc.freeze()
            try:
                yield
            finally:
                gc.unfreeze()
                if bus is not None:
                    await bus.stop()
                await control.shutdown()
                if app.state.twin is not None:
                    await app.state.twin.stop()
                await bench.stop()
                await hub.stop()
                await compute.close()
                # Let pending storage writes finish before the database closes.
                await asyncio.sleep(0)
                storage.close()

    app = FastAPI(
        title="servotune",
        version=__version__,
        summary="Tuning dashboard for servo motor controllers",
        lifespan=lifespan,
        # Any route: not logged in (exposed mode), refused by a permission or by the
        # Host / Origin / CSRF checks, or a body over the cap (servotune.auth).
        responses=errors(401, 403, 413),
        # Served below: the schema is built in a worker thread, not on the event loop.
        openapi_url=None,
        docs_url=None,
        redoc_url=None,
    )
    # Before every include_router: the authorization dependency is app-wide.
    security = install_security(
        app, config.security, config.data_dir, password_cost=config.password_cost
    )
    app.include_router(router)
    app.include_router(bench_router)
    app.include_router(frf_router)
    app.include_router(autotune_router)
    app.include_router(param_set_router)
    app.include_router(auth_router)
    app.include_router(ws_router)
    app.include_router(twin_router)

    def openapi() -> dict[str, Any]:
        """The live OpenAPI: once the hub runs, command and params bodies per device."""
        if app.openapi_schema is not None:
            return app.openapi_schema
        hub: Hub | None = getattr(app.state, "hub", None)
        axes = [(a.id, hub.descriptor(a.id)) for a in hub.axes_info()] if hub else []
        schema = device_openapi(app, axes)
        if hub is not None:
            app.openapi_schema = schema  # the axes do not change while the app runs
        return schema

    app.openapi = openapi  # type: ignore[method-assign]

    if not config.security.exposed:
        # The schema and its interactive page are a local-mode convenience; exposed,
        # only the API behind the login is served (docs/remote-lab.md).
        @app.get("/openapi.json", include_in_schema=False)
        async def openapi_json() -> JSONResponse:
            # Building the schema takes hundreds of milliseconds (seconds on a loaded
            # machine): in a worker thread, so it never holds a STOP back on the loop.
            return JSONResponse(await asyncio.to_thread(openapi))

        @app.get("/docs", include_in_schema=False)
        async def docs() -> HTMLResponse:
            return get_swagger_ui_html(openapi_url="/openapi.json", title="servotune API")

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        headers = dict(exc.headers or {})
        if exc.status_code == 400:
            # A body that is not JSON (or not UTF-8): bad input like any other, 422.
            return _error(422, f"body: {exc.detail}", "body")
        if exc.status_code == 405:
            headers["Allow"] = ", ".join(allowed_methods(app.router.routes, request.scope))
        return JSONResponse(
            status_code=exc.status_code,
            content={"detail": str(exc.detail), "field": None},
            headers=headers,
        )

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
        # A refusal that a confirmation lifts names the flag that confirms.
        return _error(409, str(exc), getattr(exc, "field", None))

    @app.exception_handler(MeasurementError)
    async def measurement(_: Request, exc: MeasurementError) -> JSONResponse:
        return _error(409, str(exc), kind="measurement")

    @app.exception_handler(LinkDownError)
    async def link_down(_: Request, exc: LinkDownError) -> JSONResponse:
        return _error(503, str(exc))

    @app.exception_handler(DeviceTimeoutError)
    async def timeout(_: Request, exc: DeviceTimeoutError) -> JSONResponse:
        return _error(504, f"device did not answer: {exc}")

    @app.exception_handler(ProtocolError)
    async def protocol(_: Request, exc: ProtocolError) -> JSONResponse:
        return _error(502, f"device protocol error: {exc}")

    @app.exception_handler(DriverError)
    async def driver_error(_: Request, exc: DriverError) -> JSONResponse:
        # Any other device error (the subclasses above have their own codes): JSON,
        # never a plain-text 500.
        return _error(502, f"device error: {exc}")

    @app.exception_handler(StorageError)
    async def not_stored(_: Request, exc: StorageError) -> JSONResponse:
        # 507 Insufficient Storage: the request was understood, nothing was saved.
        return _error(507, str(exc))

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
