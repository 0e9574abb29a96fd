"""Turn link specs into running drivers: the only place that picks a transport."""

from __future__ import annotations

from servotune.config import LinkSpec
from servotune.drivers.base import DriverSink, Link
from servotune.drivers.slap2 import Slap2Link, Slap2LinkConfig
from servotune.drivers.z1100 import Z1100Link, Z1100LinkConfig
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
    raise ValueError(f"unsupported device {spec.device!r}")
