"""The device registry's contract: what one device gives servotune, and the lookup.

A device is one folder under ``servotune/devices/`` with an ``entry.py`` whose
``ENTRY`` is a ``DeviceEntry``; ``servotune.devices.default_registry()`` lists them and
is the only place that names the devices. This module names none: generic code may
name the contract without importing a device folder.

Generic layers do not import this module either: each declares the small Protocol it
needs beside itself (``config.LinkRulesSource``, ...) and a composition root (the app
factory, the CLI, the benchmarks) injects a ``Registry``, which implements them all.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass

from servotune.config import LinkRules, LinkSpec
from servotune.link.base import DriverSink, Link


@dataclass(frozen=True, slots=True)
class DeviceEntry:
    """One device: everything generic code asks of it, as data and builders.

    ``name`` is the link spec's device (``slap2:/dev/ttyUSB0``), ``AxisInfo.device`` and
    the descriptor's ``device``; it is stored with runs, so it never changes.
    """

    name: str
    title: str  # for people: CLI help, error messages ("gräbner SLAP2")
    link_rules: LinkRules
    build_link: Callable[[LinkSpec, DriverSink], Link]


class Registry:
    """The devices one composition root works with, in the order they are listed.

    Built fresh by each root (``servotune.devices.default_registry()``); a test adds a
    device with ``with_devices``.
    """

    def __init__(self, entries: Iterable[DeviceEntry]) -> None:
        self._entries: dict[str, DeviceEntry] = {}
        for entry in entries:
            if entry.name in self._entries:
                raise ValueError(f"device {entry.name!r} is registered twice")
            self._entries[entry.name] = entry

    def __iter__(self) -> Iterator[DeviceEntry]:
        return iter(self._entries.values())

    def names(self) -> Sequence[str]:
        return tuple(self._entries)

    def get(self, name: str) -> DeviceEntry:
        """The entry of device ``name``; KeyError naming the known devices."""
        try:
            return self._entries[name]
        except KeyError:
            raise KeyError(f"unknown device {name!r} (known: {', '.join(self._entries)})") from None

    def with_devices(self, *extra: DeviceEntry) -> Registry:
        """This registry and ``extra`` (ValueError on a name already listed)."""
        return Registry((*self, *extra))

    # --- the consumers' Protocols (config.LinkRulesSource, ...)

    def link_rules(self, device: str) -> LinkRules:
        return self.get(device).link_rules

    def build_link(self, spec: LinkSpec, sink: DriverSink) -> Link:
        """The driver for ``spec`` with its transport injected."""
        return self.get(spec.device).build_link(spec, sink)
