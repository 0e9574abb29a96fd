"""Turn link specs into running drivers: the only place that picks a transport."""

from __future__ import annotations

import functools

from servotune.config import SIMULATED_NIC, LinkSpec
from servotune.devices.ep7047.link import build_ep7047_link
from servotune.devices.ep7047.sim.process import ADDRESS_PREFIX, ProcessMaster, is_process_address
from servotune.devices.ep7047.sim.slave import (
    DEMO_COUNTS_PER_REV,
    DEMO_SPEED_RANGE_STEPS_S,
    demo_master,
)
from servotune.devices.slap2.link import Slap2Link, Slap2LinkConfig
from servotune.devices.z1100.link import Z1100Link, Z1100LinkConfig
from servotune.link.base import DriverSink, Link
from servotune.transports.ethercat_cycle import CycleProcessMaster
from servotune.transports.serial import SerialConnector


def build_link(spec: LinkSpec, sink: DriverSink) -> Link:
    """Build the driver for ``spec`` with its transport injected."""
    if spec.device == "slap2":
        config = Slap2LinkConfig(
            link_id=spec.link_id,
            path=spec.path,
            addresses=list(spec.addresses),
            baud=spec.baud,
            lines=spec.lines,
            names=dict(spec.names),
        )
        return Slap2Link(config, SerialConnector(spec.path, spec.baud), sink)
    if spec.device == "z1100":
        z_config = Z1100LinkConfig(
            link_id=spec.link_id,
            path=spec.path,
            baud=spec.baud,
            lines=spec.lines,
            names=dict(spec.names),
        )
        return Z1100Link(z_config, SerialConnector(spec.path, spec.baud), sink)
    if spec.device == "ep7047":
        if is_process_address(spec.path):
            # The simulated slave in a process of its own (the demo, or `servotune sim
            # ep7047 --socket PATH`), behind the same master interface pysoem offers.
            return build_ep7047_link(
                spec.link_id,
                spec.path,
                spec.addresses[0],
                sink,
                # The cycle in a process of its own (a loaded server cannot stall it),
                # talking to the simulator process through the seam.
                master=CycleProcessMaster(
                    functools.partial(ProcessMaster, spec.path.removeprefix(ADDRESS_PREFIX)),
                    name="ec-cycle-sim",
                ),
                speed_range_steps_s=DEMO_SPEED_RANGE_STEPS_S,
                counts_per_rev=DEMO_COUNTS_PER_REV,
                name=spec.names.get(spec.addresses[0]),
            )
        if spec.path == SIMULATED_NIC:
            # The simulated slave in-process, behind the same master interface pysoem
            # offers: tests, or trying the page without hardware.
            return build_ep7047_link(
                spec.link_id,
                spec.path,
                spec.addresses[0],
                sink,
                master=demo_master(),
                speed_range_steps_s=DEMO_SPEED_RANGE_STEPS_S,
                counts_per_rev=DEMO_COUNTS_PER_REV,
                name=spec.names.get(spec.addresses[0]),
            )
        return build_ep7047_link(
            spec.link_id,
            spec.path,
            spec.addresses[0],
            sink,
            counts_per_rev=4 * spec.lines,
            name=spec.names.get(spec.addresses[0]),
        )
    raise ValueError(f"unsupported device {spec.device!r}")
