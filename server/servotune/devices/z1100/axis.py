"""Z1100 axis driver (one motor of the chip) and the console's parsing and replies.

The link (``devices.z1100.link.Z1100Link``) owns the line; a ``Z1100Axis`` turns descriptor
commands, the bench's plans and the demo autopilot's moves into requests and hands
them to the link through ``Z1100AxisLink``, the Protocol declared here (the link imports
this module, never the other way).
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping
from typing import Protocol

from servotune.descriptor import DeviceDescriptor
from servotune.devices.z1100 import codec
from servotune.devices.z1100.descriptor import MOVING_COMMANDS
from servotune.link.base import (
    AxisDriver,
    BenchKind,
    BenchPlan,
    BenchTest,
    CommandOutcome,
    DeviceRefusedError,
    InvalidArgumentError,
    Sample,
    StopOutcome,
)

request_name = codec.request_name

_BY_NAME = {info.name.lower(): info for info in codec.COMMANDS.values()}


def parse_console_line(line: str, axis: int) -> codec.Request:
    """``GetKABH``, ``SetVmax 20000``, ``SetKABH 40 10 20``: a request for ``axis``.

    Raises InvalidArgumentError naming the problem; nothing is sent then.
    """
    words = line.split()
    if not words:
        raise InvalidArgumentError("line", "empty line: type a command name, e.g. GetEncoder")
    info = _BY_NAME.get(words[0].lower())
    if info is None:
        known = ", ".join(sorted(i.name for i in codec.COMMANDS.values()))
        raise InvalidArgumentError("line", f"unknown command {words[0]!r}; known: {known}")
    try:
        numbers = [int(w, 0) for w in words[1:]]
    except ValueError:
        raise InvalidArgumentError("line", "data must be integers (decimal or 0x hex)") from None
    try:
        if info.request is codec.Field.KAB:
            if len(numbers) != 3:
                raise InvalidArgumentError("line", f"{info.name} takes K A B (0..255 each)")
            data = codec.pack_kab(codec.Gains(*numbers))
        elif info.request is codec.Field.INT32:
            data = codec.pack_int32(numbers[0]) if numbers else 0
        elif info.request is codec.Field.NONE:
            if numbers:
                raise InvalidArgumentError("line", f"{info.name} takes no data")
            data = 0
        else:
            if len(numbers) != 1:
                raise InvalidArgumentError("line", f"{info.name} takes one number")
            data = numbers[0]
        command_byte = info.command + (axis if info.per_axis else 0)
        return codec.Request(command_byte, data)
    except codec.CodecError as exc:
        raise InvalidArgumentError("line", str(exc)) from None


def describe_reply(request: codec.Request, reply: codec.Reply) -> list[str]:
    """The console's view of a reply: code, raw data and the decoded value."""
    lines = [f"code 0x{int(reply.code):02X} data 0x{reply.data:08X}"]
    command = request.command
    if command is not None and command.is_get:
        lines.append(f"= {codec.decode_get(command, reply.data)}")
    if reply.stall:
        lines.append(f"bit 7: {codec.stall_message(reply.code)}")
    return lines


class Z1100MotorView(Protocol):
    """What the axis reads of its motor's state as the link knows it."""

    @property
    def running(self) -> bool: ...
    @property
    def stall(self) -> bool: ...
    @property
    def job(self) -> int: ...
    @property
    def known(self) -> Mapping[str, int]: ...


class Z1100AxisLink(Protocol):
    """What a ``Z1100Axis`` needs of its link (``Z1100Link``): identity, the motor's
    state, and the operations that run as jobs on the line's owner task."""

    @property
    def descriptor(self) -> DeviceDescriptor: ...

    def axis_id(self, axis: int) -> str: ...

    def axis_name(self, axis: int) -> str: ...

    def motor(self, axis: int) -> Z1100MotorView: ...

    async def op_read_params(self, axis: int) -> dict[str, int]: ...

    async def op_write_params(
        self, axis: int, values: Mapping[str, int], source: str
    ) -> dict[str, int]: ...

    async def op_requests(
        self,
        axis: int,
        requests: list[codec.Request],
        *,
        urgent: bool = False,
        starts: bool = False,
        stop: bool | None = None,
    ) -> list[str]: ...

    async def op_console(self, axis: int, line: str) -> tuple[str, list[str]]: ...

    def capture(self, axis: int, reason: str) -> contextlib.AbstractAsyncContextManager[None]: ...


class Z1100Axis(AxisDriver):
    """One motor of a Z1100 chip."""

    def __init__(self, link: Z1100AxisLink, axis: int) -> None:
        self._link = link
        self._axis = axis

    @property
    def id(self) -> str:
        return self._link.axis_id(self._axis)

    @property
    def name(self) -> str:
        return self._link.axis_name(self._axis)

    @property
    def address(self) -> int:
        return self._axis

    @property
    def descriptor(self) -> DeviceDescriptor:
        return self._link.descriptor

    async def read_params(self) -> dict[str, int]:
        return await self._link.op_read_params(self._axis)

    async def write_params(
        self, values: Mapping[str, int], source: str = "write"
    ) -> dict[str, int]:
        return await self._link.op_write_params(self._axis, values, source)

    def make_command(self, name: str, args: Mapping[str, int]) -> list[codec.Request]:
        """Build the requests of a descriptor command (pure; no I/O)."""
        axis = self._axis
        if name == "stop":
            return [codec.make_estop([axis])]
        if name == "power_off":
            return [codec.make_set_job(axis, codec.Job.FREE)]
        if name == "decelerate":
            return [codec.make_stop([axis])]
        if name == "go_to_target":
            return [
                codec.make_set_job(axis, codec.Job.TARGET),
                codec.make_set_target(axis, args["target"]),
                codec.make_start([axis]),
            ]
        if name == "constant_velocity":
            positive = [axis] if args["direction"] else []
            return [
                codec.make_set_job(axis, codec.Job.VELOCITY),
                codec.make_start([axis], positive=positive),
            ]
        if name == "free":
            return [codec.make_set_job(axis, codec.Job.FREE)]
        if name == "home":
            return [codec.make_zero(axis)]
        if name == "clear_errors":
            return [codec.make_clr()]
        if name == "save_flash":
            return [codec.make_flash()]
        raise InvalidArgumentError("command", f"unknown command {name!r}")

    async def command(self, name: str, args: Mapping[str, int]) -> CommandOutcome:
        if name in ("stop", "power_off"):
            outcome = await (self.stop() if name == "stop" else self.power_off())
            return CommandOutcome(outcome.sent, outcome.message)
        motor = self._link.motor(self._axis)
        if name in MOVING_COMMANDS and motor.running:
            raise DeviceRefusedError(
                f"motor {self._axis + 1} is moving: the chip forbids Job, Target, Start and "
                "Zero while it moves — wait for the move to end or press STOP"
            )
        if name == "go_to_target" or name == "constant_velocity":
            known = motor.known
            missing = [n for n in ("kabh_k", "vmax", "acc", "limit") if not known.get(n)]
            if missing:
                raise DeviceRefusedError(
                    f"set {', '.join(missing)} first: the chip needs K, A, B, Vmax, Acc and "
                    "the error limit non-zero before Start"
                )
        requests = self.make_command(name, args)
        sent = await self._link.op_requests(
            self._axis, requests, urgent=name == "stop", starts=name in MOVING_COMMANDS
        )
        return CommandOutcome(sent, "ok")

    async def console(self, line: str) -> tuple[str, list[str]]:
        return await self._link.op_console(self._axis, line)

    # --- stops (drivers.base.StopModes; docs/control.md "Stops") ----------------------

    async def stop(self) -> StopOutcome:
        """Estop: the reference jumps to where the shaft is and the servo brakes as hard
        as it can, then holds (the chip's shortest stop); a free shaft stays free."""
        motor = self._link.motor(self._axis)
        sent = await self._link.op_requests(
            self._axis, [codec.make_estop([self._axis])], urgent=True
        )
        if motor.job in (codec.Job.TARGET, codec.Job.VELOCITY) and not motor.stall:
            return StopOutcome(sent, "hold", "stopped at once: holding under power")
        return StopOutcome(sent, "power_off", "the motor is unpowered (free shaft)")

    async def controlled_stop(self) -> StopOutcome:
        """The chip's shortest stop already holds (``stop``)."""
        return await self.stop()

    async def power_off(self) -> StopOutcome:
        """Job 0: motor power off at once, the shaft turns freely (allowed while moving)."""
        sent = await self._link.op_requests(
            self._axis,
            [codec.make_set_job(self._axis, codec.Job.FREE)],
            urgent=True,
            stop=True,
        )
        return StopOutcome(sent, "power_off", "motor power off (Job 0: free shaft)")

    async def brake(self) -> StopOutcome:
        """No brake without the loop on this chip: power off."""
        return await self.power_off()

    async def hold_here(self) -> StopOutcome:
        """Job 2 (go to target) without Start: the servo engages holding where the shaft
        is (the job alone moves nothing)."""
        sent = await self._link.op_requests(
            self._axis, [codec.make_set_job(self._axis, codec.Job.TARGET)]
        )
        return StopOutcome(sent, "hold", "holding under power (Job 2)")

    def capture(self, reason: str) -> contextlib.AbstractAsyncContextManager[None]:
        """``link.base.Capturer``: the line polls this motor only while open."""
        return self._link.capture(self._axis, reason)

    # --- demo autopilot (drivers.base.Autopilot) -----------------------------------

    def autopilot_amplitude(self) -> int:
        return 4096 * (self._axis + 1)

    def autopilot_commands(self, latest: Sample, target: int) -> list[tuple[str, dict[str, int]]]:
        return [("go_to_target", {"target": target})]

    # --- test bench (drivers.base.BenchPlanner) ----------------------------------------

    def bench_kinds(self) -> list[BenchKind]:
        return ["move", "velocity_step", "frequency_response"]

    def bench_plan(self, test: BenchTest, latest: Sample, params: Mapping[str, int]) -> BenchPlan:
        """Z1100 tests: a move is go-to-target by ``distance`` with Vmax/Acc as set;
        a velocity step is the constant-velocity job at ``velocity`` counts/s (Vmax
        for the test), ended with Stop (decelerate). The chip has no open-loop mode."""
        if latest.flags.get("running"):
            raise DeviceRefusedError("the motor is moving: wait for it to stop")
        position = latest.channels.get("position") or 0.0
        if test.kind == "move":
            if test.distance == 0:
                raise InvalidArgumentError("distance", "distance must not be 0")
            target = int(position) + test.distance
            return BenchPlan(
                setup=[],
                trigger=[("go_to_target", {"target": target})],
                finish=[],
                response="position",
                y0=position,
                y_final=float(target),
                band=20.0,
                moving_flag="running",
                fault_flags=["stall"],
            )
        if test.kind == "velocity_step":
            if test.velocity == 0:
                raise InvalidArgumentError("velocity", "velocity must not be 0")
            return BenchPlan(
                setup=[],
                overrides={"vmax": abs(test.velocity)},
                trigger=[("constant_velocity", {"direction": int(test.velocity > 0)})],
                finish=[("decelerate", {})],
                response="velocity",
                y0=0.0,
                y_final=float(test.velocity),
                band=None,
                fault_flags=["stall"],
            )
        raise DeviceRefusedError(f"the Z1100 cannot run a {test.kind} test (no open-loop mode)")

    def autopilot_settled(self, latest: Sample) -> bool:
        error = latest.channels.get("following_error")
        return not latest.flags.get("running") and error is not None and abs(error) < 50
