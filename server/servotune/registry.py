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

from collections.abc import Awaitable, Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import AbstractAsyncContextManager, AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Protocol, TypeAlias

from servotune.config import LinkRules, LinkSpec
from servotune.link.base import DriverSink, Link

if TYPE_CHECKING:
    from servotune.autotune.context import TuningContext
    from servotune.autotune.service import DeviceTuner
    from servotune.sim.trace import ShaftPoint
    from servotune.tuning.law import DeviceLaw

# How perf.stops ends a motion: the product's STOP, or the device's power-off alone.
StopMethod: TypeAlias = Literal["STOP", "power off"]
# The state perf.stops stops an axis from.
StopState: TypeAlias = Literal["top speed", "limit cycle"]


@dataclass(frozen=True, slots=True)
class SimArgs:
    """The options of ``servotune sim <device>``; a simulator reads those it has."""

    addresses: tuple[int, ...] = (0, 1)
    baud: int | None = None  # None: the device's default
    state_dir: Path | None = None  # EEPROM/flash files (None: in memory)
    link: str | None = None  # also create this symlink to the pty
    socket: str | None = None  # a Unix socket to serve on
    ifname: str | None = None  # a network interface to serve on
    control: str | None = None  # a Unix socket for fault injection
    product: int | None = None  # another product code in the device's identity
    realtime: bool = True


@dataclass(frozen=True, slots=True)
class DemoArgs:
    """The options of ``servotune demo`` a simulator reads."""

    state_dir: Path  # EEPROM/flash files and records (``sim.process.record_path``)
    ethercat_wire: bool = False  # an EtherCAT slave on a real wire (veth) if it can


@dataclass(frozen=True, slots=True)
class PollSet:
    """What a serial link polls, for ``servotune perf <device>`` (perf.link_rate)."""

    description: str  # one line for people: device, baud, axes, what each cycle reads
    turns_per_sample: float  # host/device turns per telemetry sample of each axis


@dataclass(frozen=True, slots=True)
class StopRigArgs:
    """What ``perf.stops`` asks a stop rig for: the link it will build and the axis on
    it whose shaft to trace (``<link_id>-<the device's axis suffix>``)."""

    link_id: str
    axis: str
    data_dir: Path  # scratch files (a flash, an EEPROM) for this rig's lifetime


class StopAxis(Protocol):
    """The axis a ``StopCase.setup`` brings into its state: the product's own commands
    and parameter writes, and its latest telemetry."""

    async def command(self, name: str, args: dict[str, Any]) -> None: ...

    async def write_params(self, values: dict[str, int]) -> None: ...

    def channel(self, name: str) -> float | None:
        """The latest sample's channel ``name`` (None: none yet)."""
        ...

    def flag(self, name: str) -> bool:
        """The latest sample's flag ``name`` (False: none yet)."""
        ...


@dataclass(frozen=True, slots=True, eq=False)
class StopCase:
    """One of a device's demo plants in one state, as ``perf.stops`` stops it."""

    name: str  # unique among the device's cases ("loaded-limit-cycle")
    axis: str  # the axis's suffix on the stop rig's link ("1", "x")
    label: str  # the plant, for people ("SLAP2 #1 with load")
    state: StopState
    gains: Mapping[str, int]  # the gains ``setup`` writes ({}: the demo's own)
    speed: str  # the state in words, for the table ("vm sv 20000", "±1900 @ step")
    # Brings the axis (on the stop rig, link up, telemetry flowing) into ``state``.
    setup: Callable[[StopAxis], Awaitable[None]]


@dataclass(frozen=True, slots=True)
class StopRig:
    """A device's demo plant set up to measure a stop on (``perf.stops``): limit
    switches removed, so that nothing but the stop ends a motion, and the shaft traced
    as the simulated device sees it."""

    # The device's link to the simulated plant (spec'd for ``StopRigArgs.link_id``).
    build_link: Callable[[DriverSink], Link]
    # Every shaft point so far, oldest first.
    trace: Callable[[], Awaitable[list[ShaftPoint]]]
    # The traced motor is under power (held by its loop, or driven).
    powered: Callable[[], Awaitable[bool]]
    # (method, asked at, the commands it sent) -> the shaft point (host monotonic time,
    # counts, counts/s) when the stop reached the device on its wire; None where the
    # rig did not see it arrive.
    reached: Callable[[StopMethod, float, list[str]], Awaitable[ShaftPoint | None]]
    # From arming until disarming, the rig keeps a copy of the device as each command
    # finds it (no-ops where ``unpowered`` is not offered).
    arm: Callable[[], Awaitable[None]]
    disarm: Callable[[], Awaitable[None]]
    # (a ``reached`` time, rest speed in counts/s, rest for s, at most s) -> the shaft
    # of the copy taken then, powered off as the device's power-off alone does and run
    # forward until at rest (the same start as the stop that arrived then); None where
    # the rig took no copy then.
    unpowered: Callable[[float, float, float, float], Awaitable[list[ShaftPoint] | None]]


@dataclass(frozen=True, slots=True)
class SimulatorEntry:
    """A device's simulator, as the CLI and the demo start it."""

    # ``servotune sim <device>`` in the foreground; returns the exit code.
    serve: Callable[[SimArgs], int]
    # The demo's simulated device(s): started on entering (a child process stopped on
    # leaving), yielding the link specs that reach them.
    demo: Callable[[DemoArgs], AbstractContextManager[list[LinkSpec]]]
    # ``serve`` puts a serial device on a pty (``servotune perf <device>`` measures it).
    pty: bool
    # The poll set of a link built by the entry (``servotune perf <device>``).
    poll_set: Callable[[Link], PollSet] | None = None
    # The demo plant as ``perf.stops`` measures a stop on it: entered, it has started
    # the simulated device; leaving it (after the link was stopped) powers it off.
    stop_rig: Callable[[StopRigArgs], AbstractAsyncContextManager[StopRig]] | None = None
    # The states of the demo plants ``perf.stops`` measures on the stop rig.
    stop_cases: tuple[StopCase, ...] = ()


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
    simulator: SimulatorEntry | None = None
    # Its controller law for the what-if, the frequency response and the gains check
    # (None: it has none). A loader, called once per registry: a law brings numpy,
    # scipy and python-control, which the CLI's other commands do not need.
    law: Callable[[], DeviceLaw] | None = None
    # Its auto-tune (None: it has none); imports the tuner when called.
    tuner: Callable[[TuningContext], DeviceTuner] | None = None
    # Modules whose functions its tuner runs in the compute worker (preloaded there).
    compute_modules: tuple[str, ...] = ()


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
        self._laws: dict[str, DeviceLaw] = {}

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

    def simulated(self, *, pty: bool = False) -> Sequence[DeviceEntry]:
        """The devices with a simulator (``pty``: one on a pseudo-terminal)."""
        return tuple(e for e in self if e.simulator is not None and (e.simulator.pty or not pty))

    def link_rules(self, device: str) -> LinkRules:
        return self.get(device).link_rules

    def law(self, device: str) -> DeviceLaw | None:
        """The controller law of ``device``; None for a device without one, or one this
        registry does not list (a stored run, a remote rig's axis)."""
        law = self._laws.get(device)
        if law is None:
            entry = self._entries.get(device)
            if entry is None or entry.law is None:
                return None
            law = self._laws[device] = entry.law()
        return law

    def tuner(self, device: str, ctx: TuningContext) -> DeviceTuner | None:
        """A new auto-tuner for the axes of ``device`` (None: it has none)."""
        entry = self._entries.get(device)
        return entry.tuner(ctx) if entry is not None and entry.tuner is not None else None

    def tuned(self) -> Sequence[str]:
        """The devices (titles) that have an auto-tune."""
        return tuple(e.title for e in self if e.tuner is not None)

    def compute_modules(self) -> tuple[str, ...]:
        """Every device's ``compute_modules``, for the compute worker to preload."""
        return tuple(m for e in self for m in e.compute_modules)

    def build_link(self, spec: LinkSpec, sink: DriverSink) -> Link:
        """The driver for ``spec`` with its transport injected."""
        return self.get(spec.device).build_link(spec, sink)
