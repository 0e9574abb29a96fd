"""Fixtures for every test: no leaked threads, a simulated SLAP2 line and a link on it.

Shared helpers live in ``tests/support/`` and are imported from there; shared fixtures
are defined there too and registered here (``pytest_plugins``), so that no test module
imports another test module or this file.
"""

from __future__ import annotations

import threading
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import pytest
from hypothesis import settings

# One BLAS thread (servotune.tuning.threads): set before anything loads numpy.
import servotune.tuning.threads  # noqa: F401
from servotune.devices.slap2.sim.line import Slap2Line
from servotune.sim.pty import PtySimulator
from tests.support.sim_lines import RunningLink, run_link, running_simulator

# No per-example deadline for hypothesis anywhere: its 200 ms default is a machine-speed
# limit, and on a loaded host a 24-byte codec round trip took 1.1 s once (a false
# failure, not a slow codec). Tests that measure speed are benchmarks, not examples.
settings.register_profile("servotune", deadline=None)
settings.load_profile("servotune")

# Fixtures of the support modules, found by name like this file's own.
pytest_plugins = ["tests.support.browser", "tests.support.bus_lab"]


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


@pytest.fixture
def sim_line(tmp_path: Path) -> Iterator[tuple[PtySimulator, Slap2Line]]:
    """Two simulated modules (0 and 1) on one line, behind a stable symlink."""
    with running_simulator([0, 1], tmp_path, link_path=str(tmp_path / "ttySLAP2")) as pair:
        yield pair


@pytest.fixture
async def line(sim_line: tuple[PtySimulator, Slap2Line]) -> AsyncIterator[RunningLink]:
    """A connected Slap2Link on the two-module simulated line."""
    simulator, bus = sim_line
    async with run_link(simulator, bus, [0, 1]) as running:
        await running.connected()
        yield running
