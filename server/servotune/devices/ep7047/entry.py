"""Beckhoff EP7047-1032's registry entry: how its link specs read, how its link is built,
how its simulator is served and what the demo runs (builders import their modules when
called, see ``devices/slap2/entry.py``).

The link spec's path is the master's network interface, or a simulated slave:
``ep7047:sim`` in the link's cycle process (tests, trying the page without hardware), or
``ep7047:sim:PATH`` in a process of its own behind a Unix socket (the demo, ``servotune
sim ep7047 --socket PATH``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sys
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Final

from servotune.config import LinkRules, LinkSpec
from servotune.devices.ep7047 import NAME
from servotune.link.base import DriverSink, Link
from servotune.registry import (
    DemoArgs,
    DeviceEntry,
    SimArgs,
    SimulatorEntry,
    StopAxis,
    StopCase,
    StopRig,
    StopRigArgs,
)

if TYPE_CHECKING:
    from servotune.sim.trace import ShaftPoint
    from servotune.transports.ethercat import EthercatMaster

logger = logging.getLogger(__name__)

# ``ep7047:sim`` runs the simulated slave in the cycle process instead of a NIC.
SIMULATED_NIC: Final = "sim"


def build_link(spec: LinkSpec, sink: DriverSink) -> Link:
    import functools

    from servotune.devices.ep7047.link import build_ep7047_link
    from servotune.devices.ep7047.sim.process import (
        ADDRESS_PREFIX,
        ProcessMaster,
        is_process_address,
    )
    from servotune.devices.ep7047.sim.slave import (
        DEMO_COUNTS_PER_REV,
        DEMO_SPEED_RANGE_STEPS_S,
        demo_master,
    )
    from servotune.transports.ethercat_cycle import CycleProcessMaster

    slave, name = spec.addresses[0], spec.names.get(spec.addresses[0])
    master: EthercatMaster
    if is_process_address(spec.path):
        # The simulated slave in a process of its own, behind the same master interface
        # pysoem offers; the cycle in a process of its own too (a loaded server cannot
        # stall it), talking to the simulator process through the seam.
        master = CycleProcessMaster(
            functools.partial(ProcessMaster, spec.path.removeprefix(ADDRESS_PREFIX)),
            name="ec-cycle-sim",
        )
    elif spec.path == SIMULATED_NIC:
        # The simulated slave in the cycle process, paced like a real NIC's master: a
        # stall of this process (a full garbage collection holds the interpreter lock
        # for hundreds of ms on a loaded host) then delays the link's requests, as with
        # real hardware, but never starves the drive's 100 ms watchdog (a false trip
        # that a real installation would not see).
        master = CycleProcessMaster(demo_master, name="ec-cycle-sim")
    else:
        return build_ep7047_link(
            spec.link_id, spec.path, slave, sink, counts_per_rev=4 * spec.lines, name=name
        )
    return build_ep7047_link(
        spec.link_id,
        spec.path,
        slave,
        sink,
        master=master,
        speed_range_steps_s=DEMO_SPEED_RANGE_STEPS_S,
        counts_per_rev=DEMO_COUNTS_PER_REV,
        name=name,
    )


def serve(args: SimArgs) -> int:
    """``servotune sim ep7047``: on a network interface (``--ifname``) or behind the
    master seam on a Unix socket (``--socket``)."""
    if args.ifname:
        return _serve_on_wire(args)
    if not args.socket:
        print(
            "servotune sim ep7047: give --ifname IF (an EtherCAT slave on a network "
            "interface) or --socket PATH (behind the master seam, a Unix socket)"
        )
        return 2
    from servotune.devices.ep7047.sim.process import run_ep7047_simulator

    run_ep7047_simulator(args.socket)
    return 0


def _serve_on_wire(args: SimArgs) -> int:
    from servotune.devices.ep7047.sim.sii import Identity
    from servotune.devices.ep7047.sim.wire_loop import run_wire_simulator
    from servotune.transports.ethercat import raw_socket_problem

    assert args.ifname is not None
    problem = raw_socket_problem(args.ifname)
    if problem is not None:
        print(f"servotune sim ep7047: {problem}", file=sys.stderr)
        return 2
    identity = Identity()
    if args.product is not None:
        identity = Identity(product=args.product, name=f"product 0x{args.product:08X}")
    run_wire_simulator(
        args.ifname, control_path=args.control, identity=identity, realtime=args.realtime
    )
    return 0


@contextlib.contextmanager
def demo_slave(state_dir: Path) -> Iterator[list[LinkSpec]]:
    """One simulated EP7047-1032 (stepper, encoder, cam, C track) in its own process,
    reached through ``ProcessMaster`` (the link spec's NIC is ``sim:<socket>``)."""
    from servotune.devices.ep7047.sim.process import ep7047_sim_process
    from servotune.sim.process import record_path

    with ep7047_sim_process(record_path(state_dir, NAME)) as simulator:
        yield [
            LinkSpec(
                device=NAME,
                path=simulator.ready["path"],
                link_id="demo-ep7047",
                baud=0,
                addresses=[1],
                names={1: "EP7047 stepper"},
            )
        ]


@contextlib.contextmanager
def wire_demo_slave(state_dir: Path) -> Iterator[list[LinkSpec]]:
    """``--ethercat-wire``: the EP7047-1032 as a real EtherCAT slave on a veth pair (its
    own network namespace, ``servotune sim ep7047 --ifname``), driven by the real
    pysoem master - every frame crosses a network interface. Needs root (namespaces,
    raw sockets) and pysoem; where either is missing the demo says why and keeps the
    simulated slave behind the master seam."""
    from servotune.devices.ep7047.sim.netns import netns_problem, slave_process, veth_pair
    from servotune.devices.ep7047.sim.slave import DEMO_COUNTS_PER_REV

    problem = netns_problem()
    if problem is None:
        try:
            import pysoem  # noqa: F401 - only checked here
        except ImportError:
            problem = "pysoem is not installed (pip install -e '.[ethercat]')"
    if problem is not None:
        logger.warning("--ethercat-wire: %s; the EP7047 stays behind the master seam", problem)
        with demo_slave(state_dir) as specs:
            yield specs
        return
    state_dir.mkdir(parents=True, exist_ok=True)
    with veth_pair() as pair, slave_process(pair, state_dir, name="ep7047-wire"):
        logger.info(
            "EP7047-1032 on a real EtherCAT wire: slave in namespace %s on %s, master on %s",
            pair.namespace,
            pair.slave_if,
            pair.master_if,
        )
        yield [
            LinkSpec(
                device=NAME,
                path=pair.master_if,
                link_id="demo-ep7047",
                baud=0,
                addresses=[1],
                lines=DEMO_COUNTS_PER_REV // 4,
                names={1: "EP7047 stepper (EtherCAT wire)"},
            )
        ]


@contextlib.asynccontextmanager
async def stop_rig(args: StopRigArgs) -> AsyncIterator[StopRig]:
    """The demo's drive in-process (``ep7047:sim``) behind a master tracing its shaft;
    ``args.axis`` is ``<link>-<slave>``. The link and the drive use the rig's watchdog
    (``STOP_PLANT_WATCHDOG_S``)."""
    from servotune.devices.ep7047.link import build_ep7047_link
    from servotune.devices.ep7047.sim.slave import DEMO_COUNTS_PER_REV, DEMO_SPEED_RANGE_STEPS_S
    from servotune.devices.ep7047.sim.stop_plant import STOP_PLANT_WATCHDOG_S, StopPlant

    slave = int(args.axis.rsplit("-", 1)[1])
    plant = StopPlant()

    def link(sink: DriverSink) -> Link:
        return build_ep7047_link(
            args.link_id,
            SIMULATED_NIC,
            slave,
            sink,
            master=plant.master,
            speed_range_steps_s=DEMO_SPEED_RANGE_STEPS_S,
            counts_per_rev=DEMO_COUNTS_PER_REV,
            watchdog_s=STOP_PLANT_WATCHDOG_S,
        )

    async def trace() -> list[ShaftPoint]:
        return list(plant.master.points)

    async def powered() -> bool:
        return plant.powered()

    yield StopRig(link, trace, powered, plant.reached, plant.arm, plant.disarm, plant.unpowered)


async def _top_speed(axis: StopAxis) -> None:
    """Enabled, then an endless move (start type 3) at 10 000 steps/s."""
    await axis.command("enable", {})
    # Until the drive says Ready to execute (a fixed wait was too short on a loaded
    # host: the start was then refused with "not enabled").
    deadline = time.monotonic() + 10
    while not axis.flag("ready_to_execute"):
        if time.monotonic() > deadline:
            raise RuntimeError("the drive did not become ready")
        await asyncio.sleep(0.02)
    await axis.command(
        "execute_move",
        {
            "start_type": 3,
            "target": 0,
            "velocity": 10000,
            "acceleration_ms": 300,
            "deceleration_ms": 300,
        },
    )
    await asyncio.sleep(1.5)


STOP_CASES: Final = (
    StopCase("top-speed", "1", "EP7047 stepper", "top speed", {}, "endless, 10 000 bp", _top_speed),
)


def demo(args: DemoArgs) -> contextlib.AbstractContextManager[list[LinkSpec]]:
    if args.ethercat_wire:
        return wire_demo_slave(args.state_dir)
    return demo_slave(args.state_dir)


ENTRY: Final = DeviceEntry(
    name=NAME,
    title="Beckhoff EP7047-1032",
    link_rules=LinkRules(
        default_baud=None,
        addressing="slave",
        # addresses= is ignored (the axis is the slave= position); still accepted in
        # 0..15, as link specs always took it, so configs that list it keep loading.
        address_range=(0, 15),
        slave_range=(1, 65535),
        example="ep7047:eth0?slave=1",
    ),
    build_link=build_link,
    simulator=SimulatorEntry(
        serve=serve, demo=demo, pty=False, stop_rig=stop_rig, stop_cases=STOP_CASES
    ),
)
