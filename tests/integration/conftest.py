"""Fixtures of the integration tests."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from tests.support.servers import LiveServer, live_server
from tests.support.sim_lines import running_simulator


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[LiveServer]:
    """A live server on one SLAP2 line of two simulated modules (``line-0``, ``line-1``)
    on a real pseudo-terminal."""
    with running_simulator([0, 1], tmp_path, link_path=str(tmp_path / "tty")) as (sim, bus):
        async with live_server(sim, bus, tmp_path / "data") as server:
            yield server
