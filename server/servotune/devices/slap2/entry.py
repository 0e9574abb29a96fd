"""gräbner SLAP2's registry entry: how its link specs read and how its link is built.

Builders import their modules when called: the registry is read by every command
(``servotune --help`` included), which must not load every device's link for it.
"""

from __future__ import annotations

from typing import Final

from servotune.config import LinkRules, LinkSpec
from servotune.devices.slap2.codec import MAX_ADDRESS
from servotune.link.base import DriverSink, Link
from servotune.registry import DeviceEntry

NAME: Final = "slap2"
DEFAULT_BAUD: Final = 19200  # the manual's 19200 8N1


def build_link(spec: LinkSpec, sink: DriverSink) -> Link:
    from servotune.devices.slap2.link import Slap2Link, Slap2LinkConfig
    from servotune.transports.serial import SerialConnector

    config = Slap2LinkConfig(
        link_id=spec.link_id,
        path=spec.path,
        addresses=list(spec.addresses),
        baud=spec.baud,
        lines=spec.lines,
        names=dict(spec.names),
    )
    return Slap2Link(config, SerialConnector(spec.path, spec.baud), sink)


ENTRY: Final = DeviceEntry(
    name=NAME,
    title="gräbner SLAP2",
    link_rules=LinkRules(
        default_baud=DEFAULT_BAUD,
        addressing="modules",
        address_range=(0, MAX_ADDRESS),
        example="slap2:/dev/ttyUSB0?addresses=0,1",
    ),
    build_link=build_link,
)
