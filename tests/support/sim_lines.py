"""Simulated device lines on real pseudo-terminals, and links running on them."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import multiprocessing
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from servotune.compute import PRELOAD
from servotune.devices.slap2.link import Slap2Link, Slap2LinkConfig
from servotune.devices.slap2.sim.line import Slap2Line
from servotune.devices.z1100.link import Z1100Axis, Z1100Link, Z1100LinkConfig
from servotune.devices.z1100.sim.chip import Z1100Chip
from servotune.devices.z1100.sim.demo import Z1100_LOADS_KG_M2, write_demo_flash
from servotune.sim.base import SimDevice
from servotune.sim.process import Remote, SerialSimSpec, SimProcess, serve_serial
from servotune.sim.pty import PtySimulator
from servotune.transports.serial import SerialConnector
from tests.support import sim_builders
from tests.support.autotune import MEDIOCRE
from tests.support.sink import RecordingSink
from tests.support.waiting import wait_for

# The test simulators' processes are forks of multiprocessing's fork server (started
# clean once per session), which has the simulators imported already, and what the
# servers' worker processes import (``compute.PRELOAD``: fits, bench imports): the
# first to start the fork server decides what it preloads. Last, ``frozen_heap``
# freezes all of it, so that a simulator's garbage collections do not walk numpy's.
multiprocessing.set_forkserver_preload(
    [*PRELOAD, "servotune.sim.process", sim_builders.__name__, "tests.support.frozen_heap"]
)


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
    (``simulator_process``): its ``PtySimulator`` and ``Slap2Line`` as ``Remote`` views.
    A test that must reach into a simulator's internals (a closure on its thread, a
    patched method) runs a ``PtySimulator`` of its own."""
    build = functools.partial(sim_builders.slap2_line, addresses, tmp_path)
    with simulator_process("slap2-line", build, baud, link_path) as pair:
        yield pair


@dataclass
class RunningLink:
    link: Slap2Link
    sink: RecordingSink
    simulator: PtySimulator
    bus: Slap2Line

    async def until(self, condition: Callable[[], bool], what: str, timeout_s: float = 5) -> None:
        await wait_for(condition, timeout_s, what)

    async def connected(self) -> None:
        await self.until(lambda: self.link.state == "connected", "the link to connect")


@contextlib.asynccontextmanager
async def run_link(
    simulator: PtySimulator, bus: Slap2Line, addresses: list[int], **config: object
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


@contextlib.contextmanager
def demo_line(tmp_path: Path) -> Iterator[tuple[Remote, Remote]]:
    """The demo's SLAP2 line (``sim_builders.demo_slap2_line_with_eeproms``) on a pty, in a
    process of its own (``simulator_process``): its ``PtySimulator`` and ``Slap2Line`` as
    ``Remote`` views."""
    build = functools.partial(sim_builders.demo_slap2_line_with_eeproms, tmp_path)
    with simulator_process("slap2-demo", build, 19200) as pair:
        yield pair


Z1100_BAUD = 38400  # the fastest jumper setting keeps the tests short


@contextlib.contextmanager
def mediocre_chip_line(tmp_path: Path) -> Iterator[Remote]:
    """The demo's Z1100 with every motor at the ``MEDIOCRE`` gains, in a process of its
    own (``z1100_chip_process``): its ``PtySimulator`` as a ``Remote`` view."""
    with z1100_chip_process(tmp_path, (MEDIOCRE.k, MEDIOCRE.a, MEDIOCRE.b)) as (simulator, _):
        yield simulator


@contextlib.contextmanager
def z1100_chip_process(
    tmp_path: Path, kab: tuple[int, int, int] | None = None
) -> Iterator[tuple[Remote, Remote]]:
    """The demo's Z1100 (``sim_builders.z1100_chip``: the demo's flash gains, or ``kab``
    on every motor) at ``Z1100_BAUD`` on a pty, in a process of its own
    (``simulator_process``): its ``PtySimulator`` and chip as ``Remote`` views."""
    build = functools.partial(sim_builders.z1100_chip, tmp_path / "flash.json", Z1100_BAUD, kab)
    with simulator_process("z1100-chip", build, Z1100_BAUD) as pair:
        yield pair


class Z1100Run:
    def __init__(self, link: Z1100Link, sink: RecordingSink, sim: PtySimulator, chip: Z1100Chip):
        self.link, self.sink, self.sim, self.chip = link, sink, sim, chip

    def axis(self, index: int) -> Z1100Axis:
        axis = self.link.axes[index]
        assert isinstance(axis, Z1100Axis)
        return axis

    def samples(self, index: int) -> list[float | None]:
        return [s.channels["position"] for s in self.sink.samples[self.link.axis_id(index)]]


@contextlib.asynccontextmanager
async def chip_line(tmp_path: Path, *, flash: bool = True) -> AsyncIterator[Z1100Run]:
    path = tmp_path / "flash.json"
    if flash:
        write_demo_flash(path)
    chip = Z1100Chip.with_loads(Z1100_LOADS_KG_M2, flash_path=path, jumper_baud=Z1100_BAUD)
    sim = PtySimulator(chip, baud=Z1100_BAUD)
    sim.start()
    sink = RecordingSink()
    config = Z1100LinkConfig(link_id="chip", path=sim.path, baud=Z1100_BAUD, verify_period_s=0.3)
    link = Z1100Link(config, SerialConnector(sim.path, Z1100_BAUD), sink)
    task = asyncio.create_task(link.run())
    try:
        await wait_for(lambda: link.state == "connected", 5, "the chip link")
        # Tests look at the latest sample of every axis: wait for the first ones.
        await wait_for(
            lambda: all(sink.samples[link.axis_id(i)] for i in range(3)), 5, "first samples"
        )
        yield Z1100Run(link, sink, sim, chip)
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        sim.stop()
