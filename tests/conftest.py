"""Shared fixtures: simulated SLAP2 lines on real pseudo-terminals, a recording sink."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import multiprocessing
import threading
import time
from collections import defaultdict
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from hypothesis import settings

# One BLAS thread (servotune.tuning.threads): set before anything loads numpy.
import servotune.tuning.threads  # noqa: F401
from servotune.devices.slap2.link import Slap2Link, Slap2LinkConfig
from servotune.devices.slap2.sim.line import Slap2Bus
from servotune.link.base import Sample
from servotune.schema import AxisHealth, EventLevel, LinkState
from servotune.sim.base import SimDevice
from servotune.sim.process import Remote, SerialSimSpec, SimProcess, serve_serial
from servotune.sim.pty import PtySimulator
from servotune.transports.serial import SerialConnector

from . import sim_lines

# No per-example deadline for hypothesis anywhere: its 200 ms default is a machine-speed
# limit, and on a loaded host a 24-byte codec round trip took 1.1 s once (a false
# failure, not a slow codec). Tests that measure speed are benchmarks, not examples.
settings.register_profile("servotune", deadline=None)
settings.load_profile("servotune")


@pytest.fixture(autouse=True)
def no_leaked_threads() -> Iterator[None]:
    """Fail a test that leaves threads running (simulators must be stopped)."""
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 2
    leaked: set[threading.Thread] = set()
    while time.monotonic() < deadline:
        leaked = {
            t
            for t in set(threading.enumerate()) - before
            if t.is_alive() and not t.name.startswith(("asyncio_", "ThreadPoolExecutor"))
        }
        if not leaked:
            return
        time.sleep(0.05)
    pytest.fail(f"threads leaked by the test: {sorted(t.name for t in leaked)}")


@dataclass
class RecordingSink:
    """A DriverSink that keeps everything a driver reports."""

    samples: dict[str, list[Sample]] = field(default_factory=lambda: defaultdict(list))
    states: list[tuple[LinkState, str]] = field(default_factory=list)
    health: dict[str, tuple[AxisHealth, str]] = field(default_factory=dict)
    health_log: list[tuple[str, AxisHealth, str]] = field(default_factory=list)
    params: dict[str, dict[str, int]] = field(default_factory=lambda: defaultdict(dict))
    events: list[tuple[EventLevel, str | None, str]] = field(default_factory=list)

    def on_sample(self, axis_id: str, sample: Sample) -> None:
        self.samples[axis_id].append(sample)

    def on_link_status(
        self,
        link_id: str,
        state: LinkState,
        message: str,
        rate_hz: float,
        wire_limit_hz: float,
        errors: int,
    ) -> None:
        if not self.states or self.states[-1] != (state, message):
            self.states.append((state, message))

    def on_axis_health(self, axis_id: str, health: AxisHealth, message: str) -> None:
        self.health[axis_id] = (health, message)
        self.health_log.append((axis_id, health, message))

    def on_params(self, axis_id: str, values: Mapping[str, int], source: str) -> None:
        self.params[axis_id].update(values)

    def on_event(self, level: EventLevel, axis_id: str | None, message: str) -> None:
        self.events.append((level, axis_id, message))


async def wait_for(
    condition: Callable[[], bool], timeout_s: float = 5.0, what: str = "condition"
) -> None:
    """Poll ``condition`` until true; fail the test with ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s} s waiting for {what}")
        await asyncio.sleep(0.02)


# The test simulators' processes are forks of multiprocessing's fork server (started
# clean once per session), which has the simulators imported already.
multiprocessing.set_forkserver_preload(["servotune.sim.process", sim_lines.__name__])


@contextlib.contextmanager
def simulator_process(
    name: str, build: Callable[[], SimDevice], baud: int, link_path: str | None = None
) -> Iterator[tuple[Remote, Remote]]:
    """``build()`` (picklable) on a pty in a process of its own, scheduled as the demo's
    simulators are (its own session, real-time priority where granted), so that a
    loaded test process cannot starve the device. Yields (its ``PtySimulator``, the
    device), both as :class:`Remote` views read through the process' lifeline."""
    spec = SerialSimSpec(name, build, baud, link_path=link_path)
    with SimProcess(name, serve_serial, spec, start_method="forkserver") as process:
        yield Remote(process, "simulator"), Remote(process, "device")


@contextlib.contextmanager
def running_simulator(
    addresses: list[int], tmp_path: Path, *, baud: int = 19200, link_path: str | None = None
) -> Iterator[tuple[Remote, Remote]]:
    """SLAP2 modules at ``addresses`` on a pty, in a process of their own
    (``simulator_process``): its ``PtySimulator`` and ``Slap2Bus`` as ``Remote`` views.
    A test that must reach into a simulator's internals (a closure on its thread, a
    patched method) runs a ``PtySimulator`` of its own."""
    build = functools.partial(sim_lines.slap2_bus, addresses, tmp_path)
    with simulator_process("slap2-line", build, baud, link_path) as pair:
        yield pair


@pytest.fixture
def sim_line(tmp_path: Path) -> Iterator[tuple[PtySimulator, Slap2Bus]]:
    """Two simulated modules (0 and 1) on one line, behind a stable symlink."""
    with running_simulator([0, 1], tmp_path, link_path=str(tmp_path / "ttySLAP2")) as pair:
        yield pair


@dataclass
class RunningLink:
    link: Slap2Link
    sink: RecordingSink
    simulator: PtySimulator
    bus: Slap2Bus

    async def until(self, condition: Callable[[], bool], what: str, timeout_s: float = 5) -> None:
        await wait_for(condition, timeout_s, what)

    async def connected(self) -> None:
        await self.until(lambda: self.link.state == "connected", "the link to connect")


@contextlib.asynccontextmanager
async def run_link(
    simulator: PtySimulator, bus: Slap2Bus, addresses: list[int], **config: object
) -> AsyncIterator[RunningLink]:
    sink = RecordingSink()
    link_config = Slap2LinkConfig(
        link_id="line", path=simulator.path, addresses=addresses, baud=simulator.baud, **config
    )  # type: ignore[arg-type]
    link = Slap2Link(link_config, SerialConnector(simulator.path, simulator.baud), sink)
    task = asyncio.create_task(link.run())
    try:
        yield RunningLink(link, sink, simulator, bus)
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


@pytest.fixture
async def line(sim_line: tuple[PtySimulator, Slap2Bus]) -> AsyncIterator[RunningLink]:
    """A connected Slap2Link on the two-module simulated line."""
    simulator, bus = sim_line
    async with run_link(simulator, bus, [0, 1]) as running:
        await running.connected()
        yield running


async def gather_in_order(*jobs: Awaitable[object]) -> list[int]:
    """Run awaitables concurrently; return their indexes in completion order."""
    order: list[int] = []

    async def run(index: int, job: Awaitable[object]) -> None:
        with contextlib.suppress(Exception):
            await job
        order.append(index)

    await asyncio.gather(*(run(i, j) for i, j in enumerate(jobs)))
    return order


def local_client(app: Any, **kwargs: Any) -> Any:
    """An httpx client of ``app`` as a browser on this machine reaches it: a local Host
    name (the DNS-rebinding check refuses others). Call ``use_csrf_token`` on it before
    any state-changing request."""
    import httpx

    transport = httpx.ASGITransport(app=app)
    return httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1", **kwargs)


async def use_csrf_token(client: Any) -> None:
    """Make an httpx client send the server's CSRF token on every request (local mode).

    The token comes from ``GET /api/auth/session``, as the web client gets it; a page on
    another site cannot read that answer.
    """
    response = await client.get("/api/auth/session")
    assert response.status_code == 200, response.text
    client.headers["X-CSRF-Token"] = response.json()["csrf_token"]
