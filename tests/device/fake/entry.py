"""The fake servo's registry entry: how its link specs read and how its link is built.
No simulator entry (the test serves ``sim.FakeServo`` itself), law or tuner."""

from __future__ import annotations

from servotune.config import LinkRules, LinkSpec
from servotune.link.base import DriverSink, Link
from servotune.registry import DeviceEntry

from . import NAME


def build_link(spec: LinkSpec, sink: DriverSink) -> Link:
    from servotune.transports.serial import SerialConnector

    from .link import FakeLink

    return FakeLink(spec, SerialConnector(spec.path, spec.baud), sink)


ENTRY = DeviceEntry(
    name=NAME,
    title="Fake servo (test)",
    link_rules=LinkRules(
        default_baud=9600,
        addressing="fixed",
        fixed_addresses=(0,),
        address_range=(0, 0),
        example="fake:/dev/ttyUSB0",
    ),
    build_link=build_link,
)
