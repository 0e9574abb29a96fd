"""What every device driver offers the hub, and what the hub offers drivers.

A *link* owns one physical connection (a serial line with several SLAP2 modules, a
Z1100 chip, an EtherCAT slave) and runs one owner task; its *axes* are what the user
tunes. Drivers report telemetry and state changes through a ``DriverSink`` the hub
implements, so drivers never import the hub (one-way layering).
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal, Protocol, runtime_checkable

from servotune.descriptor import DeviceDescriptor
from servotune.schema import AxisHealth, EventLevel, LinkState
from servotune.schema import BenchKind as BenchKind  # importable from here too


class DriverError(Exception):
    """Base of the errors a driver reports to a user."""


class DeviceRefusedError(DriverError):
    """The device (or the server on its behalf) refused a command; ``str`` says why."""


class ConfirmationRequiredError(DeviceRefusedError):
    """Refused until the user confirms (HTTP 409 naming ``field``, the flag that
    confirms), e.g. gains predicted unstable; nothing was sent."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(message)
        self.field = field


class LinkDownError(DriverError):
    """The link is not connected; nothing was sent."""


class DeviceTimeoutError(DriverError):
    """The device did not answer in time (no echo, no reply)."""


class ProtocolError(DriverError):
    """The device answered something the protocol does not allow (bad echo, garbage)."""


class MeasurementError(DriverError):
    """A measurement cannot support its result (too few samples, nothing moved): the
    device refused nothing; ``str`` says what was measured and what to change."""


class InvalidArgumentError(DriverError):
    """An argument is missing or out of range; nothing was sent."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(message)
        self.field = field


def check_console_line(line: str) -> None:
    """Refuse a console line with control characters (CR, LF, Ctrl-X, TAB, DEL ...).

    One console line is one command: a CR or LF inside it would run two commands
    as one (``rp\\rsv0`` went out as ``rpsv0``), and a Ctrl-X would desynchronise
    the echo exchange. The explicit control commands a device defines (SLAP2
    Ctrl-K: ``abort_calibration``) are descriptor commands. Raises
    InvalidArgumentError (field ``line``); nothing is sent.
    """
    for index, char in enumerate(line):
        if ord(char) < 32 or ord(char) == 127:
            raise InvalidArgumentError(
                "line",
                f"control character 0x{ord(char):02X} at position {index}: a console line "
                "is one command of printable characters (no CR, LF, Ctrl-X, TAB ...); "
                "nothing was sent",
            )


@dataclass(frozen=True, slots=True)
class Sample:
    """One telemetry sample of one axis, in device units.

    ``t`` is when the device latched the sample's position (the driver's best
    estimate, which a busy host can only make late); ``t_span_s``, where the driver
    knows it, how far before ``t`` the latch may lie (a captured SLAP2 sample: down to
    when its command's CR was written). ``flags_t`` is when its flags were read, on the
    same clock: a driver that polls the flags less often than the position carries the
    last read on every sample and says when it was taken; None means "read with the
    sample" (a cyclic device)."""

    t: float
    channels: Mapping[str, float | None]
    flags: Mapping[str, bool]
    t_span_s: float | None = None
    flags_t: float | None = None


@dataclass(slots=True)
class CommandOutcome:
    sent: list[str] = field(default_factory=list)
    message: str = ""
    # The hub watches the move the command started (servotune.hub.movewatch).
    outcome_pending: bool = False


# What an axis does after a stop went out (``StopOutcome.action``):
#   hold: brought to rest under power by its loop, and holding there;
#   brake: braking without its loop (SLAP2: the winding shorted), to be switched off
#          once at rest (the caller does that: ``StopModes.power_off``);
#   power_off: unpowered (it may still coast to rest);
#   ramp: ramping down by itself, then unpowered by the drive's own sequence (EP7047).
StopAction = Literal["hold", "brake", "power_off", "ramp"]


@dataclass(frozen=True, slots=True)
class StopOutcome:
    """What a stop sent and what the axis does now (see ``StopAction``)."""

    sent: list[str]
    action: StopAction
    message: str = ""


class DriverSink(Protocol):
    """Callbacks from a link's owner task to the hub. They must not block."""

    def on_sample(self, axis_id: str, sample: Sample) -> None: ...

    def on_link_status(
        self,
        link_id: str,
        state: LinkState,
        message: str,
        rate_hz: float,
        wire_limit_hz: float,
        errors: int,
    ) -> None: ...

    def on_axis_health(self, axis_id: str, health: AxisHealth, message: str) -> None: ...

    def on_params(self, axis_id: str, values: Mapping[str, int], source: str) -> None: ...

    def on_event(self, level: EventLevel, axis_id: str | None, message: str) -> None: ...


class AxisDriver(Protocol):
    """One tunable axis. All methods go through the link's command queue."""

    @property
    def id(self) -> str: ...

    @property
    def name(self) -> str: ...

    @property
    def address(self) -> int: ...

    @property
    def descriptor(self) -> DeviceDescriptor: ...

    async def read_params(self) -> dict[str, int]:
        """Read every descriptor parameter from the device."""
        ...

    async def write_params(self, values: Mapping[str, int]) -> dict[str, int]:
        """Write validated values, then read them back; returns the read-back values."""
        ...

    async def command(self, name: str, args: Mapping[str, int]) -> CommandOutcome:
        """Run a descriptor command with validated arguments.

        Raises DeviceRefusedError when the device refuses or a device rule forbids it.
        """
        ...

    async def console(self, line: str) -> tuple[str, list[str]]:
        """Send one raw line; return it as sent on the wire and the reply lines.

        Raises InvalidArgumentError (field ``line``) for a line that cannot be sent.
        """
        ...

    async def stop(self) -> StopOutcome | None:
        """STOP: bring the axis to rest in the shortest distance the device allows with
        its loop working, then into the device's safe state; never powers a motor that
        is unpowered. Goes to the wire ahead of every queued poll or command. (Where
        the loop is not working the hub cuts the power instead, ``StopModes``.)"""
        ...


@runtime_checkable
class StopModes(Protocol):
    """Optional for an axis: its stops besides STOP (docs/control.md, "Stops").

    Every method goes to the wire ahead of everything queued (like ``stop``) and fails
    the axis' queued motion.
    """

    async def controlled_stop(self) -> StopOutcome:
        """To rest under power, then keep holding there (IEC 60204-1 category 2): every
        stop that is not the STOP button (a jog release, a hand-over, the dead-man, the
        end of a bench run). Never powers a motor that is unpowered."""
        ...

    async def power_off(self) -> StopOutcome:
        """Cut the motor's power at once (category 0), whatever the axis does."""
        ...

    async def brake(self) -> StopOutcome:
        """Stop as short as the device can without its position loop (the loop is not
        working), ending unpowered or braking (``action``); a device without such a
        brake powers off (``power_off``)."""
        ...

    async def hold_here(self) -> StopOutcome:
        """Power the motor and hold where the shaft is (after gains were restored on an
        axis that was brought to rest unpowered). Powers a motor: only for a sequence
        the user started with control of the axis (a bench run, an auto-tune step)."""
        ...


@runtime_checkable
class UnjudgedStop(Protocol):
    """Optional beside ``StopModes``: the STOP for an axis whose loop is on but whose
    telemetry is too sparse to tell whether it works (docs/control.md, "Stops")."""

    async def unjudged_stop(self) -> StopOutcome:
        """Stop in a way that is safe whether the loop works or not: never longer than
        the power-off, and short where the loop works. A device without such a stop
        does not implement this (its STOP goes out, watched)."""
        ...


@runtime_checkable
class Autopilot(Protocol):
    """Optional: how the demo autopilot moves an axis of this device back and forth."""

    def autopilot_amplitude(self) -> int:
        """Half the stroke of the demo moves, in position units."""
        ...

    def autopilot_commands(self, latest: Sample, target: int) -> list[tuple[str, dict[str, int]]]:
        """Descriptor commands that move the axis to ``target`` from its state now."""
        ...

    def autopilot_settled(self, latest: Sample) -> bool:
        """The move has ended and the axis is at rest."""
        ...


@dataclass(frozen=True, slots=True)
class BenchTest:
    """A test of the bench (validated against the user's limits by the caller)."""

    kind: BenchKind
    distance: int = 0
    velocity: int = 0
    pwm: int = 0
    duration_s: float = 2.0


@dataclass(slots=True)
class BenchPlan:
    """How a device runs a bench test, in descriptor commands and parameters.

    ``overrides`` are written before the test and the previous values restored after
    it, whatever happens. ``trigger`` is sent at t0. ``finish`` leaves the axis in a
    safe state. ``response`` is the channel the metrics look at, ``y_final`` its
    commanded final value; ``done_flag`` (e.g. in-position) lets a recording end
    early once the axis has settled.
    """

    setup: list[tuple[str, dict[str, int]]]
    trigger: list[tuple[str, dict[str, int]]]
    finish: list[tuple[str, dict[str, int]]]
    response: str
    y0: float
    y_final: float
    band: float | None
    overrides: dict[str, int] = field(default_factory=dict)
    done_flag: str | None = None
    moving_flag: str | None = None
    fault_flags: list[str] = field(default_factory=list)


@runtime_checkable
class BenchPlanner(Protocol):
    """Optional: the bench tests a device can run and how."""

    def bench_kinds(self) -> list[BenchKind]: ...

    def bench_plan(self, test: BenchTest, latest: Sample, params: Mapping[str, int]) -> BenchPlan:
        """Plan ``test`` from the axis' state now; DeviceRefusedError if it cannot run."""
        ...


@runtime_checkable
class HasCounters(Protocol):
    """Optional for a link: what it retried, resynchronised or dropped since start."""

    @property
    def counters(self) -> Mapping[str, int]: ...


@runtime_checkable
class HasWireBusy(Protocol):
    """Optional for a link: the share of the last seconds its wire was busy (0..1),
    ``None`` when not known (see ``link.engine.LinkEngine.wire_busy``)."""

    @property
    def wire_busy(self) -> float | None: ...


@runtime_checkable
class WireStats(Protocol):
    """Optional for a link (a polled serial line): the telemetry samples/s per axis its
    wire allows for the current poll set, and its wire errors since start."""

    def wire_limit_hz(self) -> float: ...

    @property
    def errors(self) -> int: ...


class Link(Protocol):
    """One physical connection and its owner task."""

    @property
    def id(self) -> str: ...

    @property
    def device(self) -> str: ...

    @property
    def path(self) -> str: ...

    @property
    def baud(self) -> int: ...

    @property
    def axes(self) -> list[AxisDriver]: ...

    @property
    def state(self) -> LinkState: ...

    async def run(self) -> None:
        """Connect, poll and reconnect until cancelled; never raises for link faults."""
        ...


@runtime_checkable
class Capturer(Protocol):
    """Optional for an axis: devote its link to it while a measurement records it.

    ``async with axis.capture(reason="bench test"):`` polls only what the
    measurement needs of this axis, as fast as the wire allows (SLAP2: ``rp``, with
    ``rss`` and ``pe`` interleaved at low rates; Z1100: GetEncoder with GetError
    interleaved); the other axes of the link pause (health ``paused``, message
    "paused: capture on ...") and resume when the last capture of the link ends.
    Captures nest and several axes of one link may be captured at once (they share
    the line). A STOP still goes to the wire first. Entering never waits for the
    wire and never raises for a link fault; docs/capture.md.
    """

    def capture(self, reason: str) -> contextlib.AbstractAsyncContextManager[None]: ...


@runtime_checkable
class CommandClock(Protocol):
    """Optional for an axis: when the device executed the last command sent to it.

    The best estimate on the driver's clock (SLAP2: the end of the command's CR echo
    less one character), None before the first command. Identification uses it to
    place its input steps instead of guessing from round trips.
    """

    @property
    def last_command_latch_s(self) -> float | None: ...

    @property
    def last_command_latch_span_s(self) -> float | None:
        """How far before ``last_command_latch_s`` the device may have executed it
        (down to when the command's last byte was written; None: not known)."""
        ...


def capture_of(axis: object, reason: str) -> contextlib.AbstractAsyncContextManager[None]:
    """``axis.capture(reason)`` for a ``Capturer``, else a context that does nothing
    (the device is polled as usual, e.g. the EP7047 whose cycle is already dense)."""
    if isinstance(axis, Capturer):
        return axis.capture(reason)
    return contextlib.nullcontext()
