"""The namespace, veth pair and wire-slave process for the EP7047 wire tests: they live
in ``servotune.devices.ep7047.sim.netns`` (the demo and the benchmark use them too)."""

from servotune.devices.ep7047.sim.netns import (
    SlaveProcess,
    VethPair,
    netns_problem,
    slave_process,
    veth_pair,
)

__all__ = ["SlaveProcess", "VethPair", "netns_problem", "slave_process", "veth_pair"]
