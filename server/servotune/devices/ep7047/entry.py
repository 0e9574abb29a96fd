"""Beckhoff EP7047-1032's registry entry: how its link specs read and how its link is
built (builders import their modules when called, see ``devices/slap2/entry.py``).

The link spec's path is the master's network interface, or a simulated slave:
``ep7047:sim`` in-process (tests, trying the page without hardware), or
``ep7047:sim:PATH`` in a process of its own behind a Unix socket (the demo, ``servotune
sim ep7047 --socket PATH``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final

from servotune.config import LinkRules, LinkSpec
from servotune.link.base import DriverSink, Link
from servotune.registry import DeviceEntry

if TYPE_CHECKING:
    from servotune.transports.ethercat import EthercatMaster

NAME: Final = "ep7047"
# ``ep7047:sim`` runs the simulated slave in-process instead of a NIC.
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
        master = demo_master()  # in-process, behind the same master interface
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


ENTRY: Final = DeviceEntry(
    name=NAME,
    title="Beckhoff EP7047-1032",
    link_rules=LinkRules(
        default_baud=None,
        addressing="slave",
        slave_range=(1, 65535),
        example="ep7047:eth0?slave=1",
    ),
    build_link=build_link,
)
