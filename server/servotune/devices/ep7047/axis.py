"""The EP7047-1032 axis driver: parameters, commands, console and bench plans of the one
axis of an ``Ep7047Link`` (devices/ep7047/link.py). Every transfer goes through the
link's cycle; the axis needs of its link only ``Ep7047AxisLink``, declared here.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

from servotune.descriptor import DeviceDescriptor
from servotune.devices.ep7047 import codec
from servotune.devices.ep7047.codec import CodecError, PosDiag, SdoObject, StartType
from servotune.devices.ep7047.descriptor import (
    CALIBRATION_COMMANDS,
    INVERSION_BITS,
    INVERSION_PARAMETER,
    NOT_A_DEFAULT_START_TYPE,
    PARAMETER_SDO,
)
from servotune.devices.ep7047.requests import (
    _NEEDS_VELOCITY,
    DriveRefusedValueError,
    SdoValueRefusedError,
    _Kind,
    _Request,
    _state_label,
    diag_text,
)
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
    check_console_line,
)
from servotune.link.validation import validate_command


class Ep7047AxisLink(Protocol):
    """What an ``Ep7047Axis`` needs of its link (``Ep7047Link``)."""

    @property
    def axis_id(self) -> str: ...

    @property
    def descriptor(self) -> DeviceDescriptor: ...

    @property
    def slave_position(self) -> int: ...

    @property
    def counts_per_rev(self) -> int: ...

    def report_params(self, values: Mapping[str, int], source: str) -> None: ...

    def new_request(self, kind: _Kind, **values: Any) -> _Request: ...

    async def submit(self, request: _Request) -> Any: ...

    async def sdo_read(self, obj: SdoObject) -> int: ...

    async def sdo_write(self, obj: SdoObject, value: int) -> None: ...


def _parse_address(text: str) -> tuple[int, int]:
    index_text, _, sub_text = text.partition(":")
    try:
        return int(index_text, 16), int(sub_text, 16)
    except ValueError:
        raise InvalidArgumentError(
            "line", f"{text!r} is not an object address like 0x8020:0E"
        ) from None


class Ep7047Axis(AxisDriver):
    """The one axis of an EP7047-1032 link. All I/O goes through the link's cycle thread."""

    def __init__(self, link: Ep7047AxisLink, name: str) -> None:
        self._link = link
        self._name = name

    @property
    def id(self) -> str:
        return self._link.axis_id

    @property
    def name(self) -> str:
        return self._name

    @property
    def address(self) -> int:
        return self._link.slave_position

    @property
    def descriptor(self) -> DeviceDescriptor:
        return self._link.descriptor

    # --- parameters ---------------------------------------------------------------------

    async def read_params(self) -> dict[str, int]:
        values: dict[str, int] = {}
        for name, obj in PARAMETER_SDO.items():
            values[name] = await self._link.sdo_read(obj)
        bits = 0
        for bit, obj in INVERSION_BITS.items():
            bits |= (await self._link.sdo_read(obj) & 1) << bit
        values[INVERSION_PARAMETER] = bits
        self._link.report_params(values, "read")
        return values

    def _check_params(self, values: Mapping[str, int]) -> None:
        """Everything the hub cannot know from the descriptor ranges; raises 422."""
        for name, value in values.items():
            if name == INVERSION_PARAMETER:
                if not 0 <= value <= 3:
                    raise InvalidArgumentError(name, f"{name} = {value}: allowed 0..3 (two bits)")
                continue
            obj = PARAMETER_SDO.get(name)
            if obj is None:
                known = ", ".join([*PARAMETER_SDO, INVERSION_PARAMETER])
                raise InvalidArgumentError(name, f"{name}: unknown parameter (known: {known})")
            parameter = self.descriptor.parameter(name)
            if not parameter.minimum <= value <= parameter.maximum:
                raise InvalidArgumentError(
                    name,
                    f"{name} = {value} is out of range: allowed "
                    f"{parameter.minimum}..{parameter.maximum} {parameter.unit}".rstrip(),
                )
            if name == "default_start_type":
                try:
                    start_type = StartType(value)
                except ValueError:
                    raise InvalidArgumentError(
                        name, f"{name} = {value} is not a start type of the manual"
                    ) from None
                if start_type in NOT_A_DEFAULT_START_TYPE:
                    raise InvalidArgumentError(
                        name,
                        f"{start_type.name} changes a running move; it cannot be the "
                        "default start type",
                    )

    async def write_params(
        self, values: Mapping[str, int], source: str = "write"
    ) -> dict[str, int]:
        self._check_params(values)
        readback: dict[str, int] = {}
        for name, value in values.items():
            try:
                if name == INVERSION_PARAMETER:
                    bits = 0
                    for bit, obj in INVERSION_BITS.items():
                        await self._link.sdo_write(obj, (value >> bit) & 1)
                        bits |= (await self._link.sdo_read(obj) & 1) << bit
                    readback[name] = bits
                else:
                    obj = PARAMETER_SDO[name]
                    await self._link.sdo_write(obj, value)
                    readback[name] = await self._link.sdo_read(obj)
            except DeviceRefusedError as exc:
                if readback:
                    self._link.report_params(readback, source)
                if isinstance(exc, SdoValueRefusedError):
                    raise DriveRefusedValueError(
                        name, f"{name} = {value}: the drive refused the value: {exc.reason}"
                    ) from exc
                raise DeviceRefusedError(f"{name} = {value}: {exc}") from exc
        self._link.report_params(readback, source)
        return readback

    # --- commands -------------------------------------------------------------------------

    def _check_args(self, name: str, args: Mapping[str, int]) -> dict[str, int]:
        """The hub checks too; a direct caller (tests, scripts) gets the same checks."""
        return validate_command(self.descriptor, name, args)

    def _start_request(self, args: Mapping[str, int]) -> _Request:
        code = args["start_type"]
        try:
            start_type = StartType(code)
        except ValueError:
            choices = ", ".join(f"{s.name} {int(s)}" for s in StartType)
            raise InvalidArgumentError(
                "start_type", f"start_type {code} is not a start type of the manual ({choices})"
            ) from None
        if start_type is StartType.SET_CALIBRATION_AUTO:
            raise DeviceRefusedError(
                "SET_CALIBRATION_AUTO is meant as default start type only (manual): use the "
                "'Calibrated at Enable' command, which writes it to 0x8021:01"
            )
        velocity = args["velocity"]
        if start_type in _NEEDS_VELOCITY and velocity <= 0:
            raise InvalidArgumentError(
                "velocity",
                f"velocity must be 1..{codec.SPEED_RANGE_FULL_SCALE_BP} bp for "
                f"{start_type.name} (0 is an Error on the drive)",
            )
        return self._link.new_request(
            _Kind.START,
            start_type=start_type,
            target=args["target"],
            velocity_bp=velocity,
            acceleration_ms=args["acceleration_ms"],
            deceleration_ms=args["deceleration_ms"],
        )

    async def command(self, name: str, args: Mapping[str, int]) -> CommandOutcome:
        checked = self._check_args(name, args)
        link = self._link
        if name == "stop":
            stopped = await self.stop()
            return CommandOutcome(stopped.sent, "STOP sent")
        if name == "power_off":
            stopped = await self.power_off()
            return CommandOutcome(stopped.sent, stopped.message)
        if name == "emergency_stop":
            await link.submit(link.new_request(_Kind.EMERGENCY_STOP))
            return CommandOutcome(["Emergency stop"], "emergency stop sent")
        if name == "halt":
            await link.submit(link.new_request(_Kind.HALT))
            return CommandOutcome(["Execute off"], "halt sent")
        if name == "enable":
            message = await link.submit(link.new_request(_Kind.ENABLE))
            return CommandOutcome(["Enable on"], str(message))
        if name == "disable":
            await link.submit(link.new_request(_Kind.DISABLE))
            return CommandOutcome(["Enable off"], "disabled")
        if name == "reset_error":
            message = await link.submit(link.new_request(_Kind.RESET))
            return CommandOutcome(["Reset pulse"], str(message))
        if name == "execute_move":
            request = self._start_request(checked)
            message = await link.submit(request)
            sent = (
                f"Execute {request.start_type.name} target={request.target} "
                f"velocity={request.velocity_bp} acc={request.acceleration_ms} "
                f"dec={request.deceleration_ms}"
            )
            return CommandOutcome([sent], str(message))
        if name in CALIBRATION_COMMANDS:
            start_type = CALIBRATION_COMMANDS[name]
            request = link.new_request(_Kind.START, start_type=start_type)
            message = await link.submit(request)
            return CommandOutcome([f"Execute {start_type.name}"], str(message))
        if name == "set_calibration_auto":
            readback = await self.write_params(
                {"default_start_type": int(StartType.SET_CALIBRATION_AUTO)}
            )
            return CommandOutcome(
                [f"SDO 0x8021:01 := 0x{int(StartType.SET_CALIBRATION_AUTO):04X}"],
                f"default start type reads 0x{readback['default_start_type']:04X}: Calibrated "
                "is set at the next first Enable edge after power-on",
            )
        raise InvalidArgumentError(
            "command", f"{name} is handled by the hub, not by the EP7047 driver"
        )

    async def console(self, line: str) -> tuple[str, list[str]]:
        check_console_line(line)
        text = " ".join(line.split())
        if not text:
            raise InvalidArgumentError("line", "empty line: try 'list' or '0x9020:03'")
        if text.lower() in ("list", "help"):
            return text, [
                f"0x{o.index:04X}:{o.subindex:02X} {o.name}"
                + (f" [{o.unit}]" if o.unit else "")
                + ("" if o.writable else " (read only)")
                for o in codec.SDO_OBJECTS
            ]
        address, _, value_text = text.partition("=")
        index, subindex = _parse_address(address.strip())
        obj = next(
            (o for o in codec.SDO_OBJECTS if (o.index, o.subindex) == (index, subindex)), None
        )
        if obj is None:
            raise InvalidArgumentError(
                "line",
                f"0x{index:04X}:{subindex:02X} is not an object of the positioning interface "
                "('list' names them)",
            )
        label = f"0x{obj.index:04X}:{obj.subindex:02X} {obj.name}"
        if value_text.strip():
            if not obj.writable:
                raise InvalidArgumentError("line", f"{label} is read only")
            try:
                value = int(value_text.strip(), 0)
                codec.encode_sdo(obj, value)
            except (ValueError, CodecError) as exc:
                raise InvalidArgumentError("line", f"{label}: {exc}") from None
            # A refusal (an SDO abort) is raised: the console shows it as the answer.
            try:
                await self._link.sdo_write(obj, value)
            except SdoValueRefusedError as exc:
                raise DriveRefusedValueError(
                    "line", f"{label} = {value}: the drive refused the value: {exc.reason}"
                ) from exc
        readback = await self._link.sdo_read(obj)
        self._report_console_value(obj, readback)
        unit = f" {obj.unit}" if obj.unit else ""
        shown = f"{readback} (0x{readback:X})" if obj.index >= 0x9000 else str(readback)
        if obj == codec.DRIVE_STATE:
            shown = _state_label(readback)
        elif obj == codec.POS_STATUS_WORD:
            shown += f": {diag_text(PosDiag(readback & 0x7))}"
        return text, [f"{label} = {shown}{unit}"]

    def _report_console_value(self, obj: SdoObject, value: int) -> None:
        for name, parameter_obj in PARAMETER_SDO.items():
            if parameter_obj == obj:
                self._link.report_params({name: value}, "read")

    # --- stops (drivers.base.StopModes; docs/control.md "Stops") ----------------------

    async def stop(self) -> StopOutcome:
        """STOP: the emergency ramp on the next cycle, then Enable off (category 1: a
        stepper's safe state is unpowered)."""
        link = self._link
        await link.submit(link.new_request(_Kind.STOP))
        return StopOutcome(
            ["Emergency stop", "Execute off", "Enable off at standstill"],
            "ramp",
            "emergency ramp, then Enable off",
        )

    async def controlled_stop(self) -> StopOutcome:
        """The emergency ramp with Enable kept on: the motor holds where it stops."""
        link = self._link
        await link.submit(link.new_request(_Kind.EMERGENCY_STOP))
        return StopOutcome(["Emergency stop"], "hold", "emergency ramp, then holding (Enable on)")

    async def power_off(self) -> StopOutcome:
        """Enable off: the driver stage unpowers the motor at once (category 0)."""
        link = self._link
        await link.submit(link.new_request(_Kind.DISABLE))
        return StopOutcome(["Enable off"], "power_off", "Enable off: motor unpowered")

    async def brake(self) -> StopOutcome:
        """A stepper has no position loop to fail: its STOP ramp is its brake."""
        return await self.stop()

    async def hold_here(self) -> StopOutcome:
        link = self._link
        await link.submit(link.new_request(_Kind.ENABLE))
        return StopOutcome(["Enable on"], "hold", "Enable on: holding torque")

    # --- demo autopilot (drivers.base.Autopilot) ----------------------------------------

    def autopilot_amplitude(self) -> int:
        return self._link.counts_per_rev

    def autopilot_commands(self, latest: Sample, target: int) -> list[tuple[str, dict[str, int]]]:
        commands: list[tuple[str, dict[str, int]]] = []
        if not latest.flags.get("enable_out") or not latest.flags.get("stm_ready"):
            commands.append(("enable", {}))
        move = {
            "start_type": int(StartType.ABSOLUTE),
            "target": target,
            "velocity": 3000,
            "acceleration_ms": 400,
            "deceleration_ms": 400,
        }
        commands.append(("execute_move", move))
        return commands

    def autopilot_settled(self, latest: Sample) -> bool:
        return not latest.flags.get("busy") and not latest.flags.get("execute_out")

    # --- test bench (drivers.base.BenchPlanner) --------------------------------------

    def bench_kinds(self) -> list[BenchKind]:
        return ["move"]

    def bench_plan(self, test: BenchTest, latest: Sample, params: Mapping[str, int]) -> BenchPlan:
        """EP7047: a RELATIVE move by ``distance`` with the profile of the settings
        (velocity max, the per-direction ramps: acceleration/deceleration 0 in the
        outputs selects them). Tuning this drive means its profile, so the metrics to
        watch are time to In-Target, drive time and the approach; the band is the
        target window."""
        if latest.flags.get("busy"):
            raise DeviceRefusedError("the drive is busy with a move: wait, or press STOP")
        if test.distance == 0:
            raise InvalidArgumentError("distance", "distance must not be 0")
        position = float(latest.channels.get("position") or 0.0)
        velocity = int(params.get("velocity_max_bp", 10000)) or 10000
        setup: list[tuple[str, dict[str, int]]] = []
        if not latest.flags.get("enable_out") or not latest.flags.get("stm_ready"):
            setup.append(("enable", {}))
        move = {
            "start_type": int(StartType.RELATIVE),
            "target": test.distance,
            "velocity": min(velocity, 10000),
            "acceleration_ms": 0,
            "deceleration_ms": 0,
        }
        window = params.get("target_window_counts")
        return BenchPlan(
            setup=setup,
            trigger=[("execute_move", move)],
            finish=[],
            response="position",
            y0=position,
            y_final=position + test.distance,
            band=float(window) if window else None,
            done_flag="in_target",
            moving_flag="busy",
            fault_flags=["motor_stall", "error", "warning"],
        )


# --- glue ---------------------------------------------------------------------------------------
