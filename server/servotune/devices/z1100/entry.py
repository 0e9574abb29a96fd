"""CNC Designer Z1100's registry entry: how its link specs read and how its link is
built (builders import their modules when called, see ``devices/slap2/entry.py``)."""

from __future__ import annotations

from typing import Final

from servotune.config import LinkRules, LinkSpec
from servotune.devices.z1100.codec import DEFAULT_BAUD
from servotune.link.base import DriverSink, Link
from servotune.registry import DeviceEntry

NAME: Final = "z1100"
# One chip, three motors: there is nothing to address.
AXES: Final = (0, 1, 2)


def build_link(spec: LinkSpec, sink: DriverSink) -> Link:
    from servotune.devices.z1100.link import Z1100Link, Z1100LinkConfig
    from servotune.transports.serial import SerialConnector

    config = Z1100LinkConfig(
        link_id=spec.link_id,
        path=spec.path,
        baud=spec.baud,
        lines=spec.lines,
        names=dict(spec.names),
    )
    return Z1100Link(config, SerialConnector(spec.path, spec.baud), sink)


ENTRY: Final = DeviceEntry(
    name=NAME,
    title="CNC Designer Z1100",
    link_rules=LinkRules(
        default_baud=DEFAULT_BAUD,
        addressing="fixed",
        fixed_addresses=AXES,
        example="z1100:/dev/ttyUSB0",
    ),
    build_link=build_link,
)
