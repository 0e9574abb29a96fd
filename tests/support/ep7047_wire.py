"""Shared by the EP7047 wire tests: a namespace + veth pair with the simulated slave on
one end (``servotune sim ep7047 --ifname``), and the real driver over pysoem on the
other. See ``tests/support/netns.py`` for the namespace and the slave process.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from servotune.devices.ep7047.codec import StartType
from servotune.devices.ep7047.link import Ep7047Axis, Ep7047Link, build_ep7047_link
from servotune.devices.ep7047.sim.slave import DEMO_COUNTS_PER_REV, DEMO_SPEED_RANGE_STEPS_S
from servotune.hub.hub import Hub
from servotune.link.base import Sample
from servotune.storage import Storage
from tests.support.netns import SlaveProcess, VethPair, netns_problem, slave_process, veth_pair
from tests.support.sink import RecordingSink
from tests.support.waiting import wait_for


def require_netns() -> None:
    """Skip with the reason where namespaces cannot be made - never on CI (CI runs as
    root: a missing capability there is a broken CI, not a reason to skip)."""
    problem = netns_problem()
    if problem is None:
        return
    try:
        import pysoem  # noqa: F401
    except ImportError:
        problem = "pysoem is not installed (pip install -e '.[dev]')"
    if os.environ.get("CI"):
        pytest.fail(f"CI must run the EtherCAT wire tests: {problem}")
    pytest.skip(problem)


@dataclass
class Wire:
    pair: VethPair
    slave: SlaveProcess
    tmp_path: Path


@contextlib.contextmanager
def wire_setup(tmp_path: Path, *slave_args: str) -> Iterator[Wire]:
    require_netns()
    with veth_pair() as pair, slave_process(pair, tmp_path, *slave_args) as slave:
        yield Wire(pair, slave, tmp_path)


@dataclass
class WireRun:
    link: Ep7047Link
    axis: Ep7047Axis
    sink: RecordingSink
    wire: Wire

    @property
    def samples(self) -> list[Sample]:
        return self.sink.samples[self.axis.id]

    def flag(self, name: str) -> bool:
        return bool(self.samples[-1].flags[name])

    def position(self) -> float:
        value = self.samples[-1].channels["position"]
        assert value is not None
        return value

    def record(self) -> dict[str, Any]:
        return self.wire.slave.record()

    async def connected(self, timeout_s: float = 10) -> None:
        await wait_for(
            lambda: self.link.state == "connected",
            timeout_s,
            f"OP (states so far: {self.sink.states[-3:]})",
        )

    async def move(
        self,
        start_type: StartType,
        target: int,
        velocity: int = 5000,
        acceleration_ms: int = 200,
        deceleration_ms: int = 200,
    ) -> str:
        outcome = await self.axis.command(
            "execute_move",
            {
                "start_type": int(start_type),
                "target": target,
                "velocity": velocity,
                "acceleration_ms": acceleration_ms,
                "deceleration_ms": deceleration_ms,
            },
        )
        return outcome.message

    async def move_ended(self, timeout_s: float = 10) -> None:
        await wait_for(
            lambda: not self.flag("busy") and not self.flag("execute_out"),
            timeout_s,
            "the move to end (Busy low, Execute dropped)",
        )

    async def move_and_wait(self, start_type: StartType, target: int, **kw: int) -> None:
        await self.move(start_type, target, **kw)
        await self.move_ended()


@contextlib.asynccontextmanager
async def wire_link(wire: Wire, *, connect: bool = True, **options: Any) -> AsyncIterator[WireRun]:
    """The real driver (pysoem) on the master's end of the pair."""
    sink = RecordingSink()
    link = build_ep7047_link(
        "wire",
        wire.pair.master_if,
        1,
        sink,
        speed_range_steps_s=DEMO_SPEED_RANGE_STEPS_S,
        counts_per_rev=DEMO_COUNTS_PER_REV,
        **options,
    )
    axis = link.axes[0]
    assert isinstance(axis, Ep7047Axis)
    task = asyncio.create_task(link.run())
    run = WireRun(link, axis, sink, wire)
    try:
        if connect:
            await run.connected()
        yield run
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


@contextlib.asynccontextmanager
async def wire_hub(
    wire: Wire, tmp_path: Path, **options: Any
) -> AsyncIterator[tuple[Hub, Ep7047Link]]:
    """The real driver behind a Hub (STOP handling, events, health), connected."""
    storage = Storage(tmp_path / "servotune.db")
    hub = Hub([], storage)
    link = build_ep7047_link(
        "wire",
        wire.pair.master_if,
        1,
        hub,
        speed_range_steps_s=DEMO_SPEED_RANGE_STEPS_S,
        counts_per_rev=DEMO_COUNTS_PER_REV,
        **options,
    )
    hub.add_link(link)
    await hub.start()
    try:
        await wait_for(lambda: link.state == "connected", 10, "OP")
        yield hub, link
    finally:
        await hub.stop()
        storage.close()


async def start_endless(hub: Hub, axis_id: str, velocity: int) -> None:
    """Enable, then an ENDLESS_PLUS move at ``velocity`` bp, through the hub."""
    await hub.command(axis_id, "enable", {})
    move = {
        "start_type": int(StartType.ENDLESS_PLUS),
        "target": 0,
        "velocity": velocity,
        "acceleration_ms": 100,
        "deceleration_ms": 100,
    }
    await hub.command(axis_id, "execute_move", move)
