"""The SLAP2 axis driver: one module as the user tunes it (split from drivers/slap2.py).

Descriptor commands become wire commands here (pure), and every exchange goes through
the module's ``Slap2Link`` (drivers/slap2.py), which owns the line. Also the demo
autopilot, the bench plans and the capture capability of a SLAP2 axis.
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping
from typing import TYPE_CHECKING

from servotune.drivers.base import (
    AxisDriver,
    BenchKind,
    BenchPlan,
    BenchTest,
    CommandOutcome,
    DeviceRefusedError,
    InvalidArgumentError,
    Sample,
)
from servotune.drivers.engine import EngineAxis
from servotune.protocols import slap2 as codec

if TYPE_CHECKING:
    from servotune.drivers.slap2 import Slap2Link


class Slap2Axis(EngineAxis, AxisDriver):
    """One SLAP2 module: the axis the user tunes. All I/O goes through its link."""

    _link: Slap2Link

    def make_command(self, name: str, args: Mapping[str, int]) -> list[codec.Command]:
        """Build the wire commands for a descriptor command (pure; no I/O)."""
        if name == "stop":
            return [codec.make_simple("st")]
        if name == "position_mode":
            return [codec.make_simple("pm")]
        if name == "velocity_mode":
            return [codec.make_simple("vm")]
        if name == "move_absolute":
            return [codec.make_move_absolute(args["position"])]
        if name == "move_relative":
            return [codec.make_move_relative(args["distance"])]
        if name == "set_position":
            return [codec.make_set_position(args["position"])]
        if name == "open_loop_pwm":
            return [codec.make_pwm(args["pwm"])]
        if name == "calibrate":
            return [codec.make_calibrate(args["mode"])]
        if name == "save_eeprom":
            return [codec.make_simple("pg")]
        raise InvalidArgumentError("command", f"unknown command {name!r}")

    async def command(self, name: str, args: Mapping[str, int]) -> CommandOutcome:
        if name == "abort_calibration":
            await self._link.op_raw_byte(self._address, codec.CTRL_K, urgent=True)
            return CommandOutcome(["<Ctrl-K>"], "calibration aborted")
        if name == "save_eeprom":
            rss = self._link.module_state(self._address).rss
            flags = codec.decode_rss(rss or 0)
            if flags["pm"] or flags["vm"]:
                mode = "position mode" if flags["pm"] else "velocity mode"
                raise DeviceRefusedError(
                    f"pg is not allowed while {mode} is on (manual: 'nicht während pm oder "
                    "vm'): press STOP, then save"
                )
        if name == "hold":
            return await self._hold()
        commands = self.make_command(name, args)
        sent = await self._link.op_execute(self._address, commands, urgent=name == "stop")
        return CommandOutcome(sent, "ok")

    async def _hold(self) -> CommandOutcome:
        """Descriptor ``hold`` (stop and hold, motor powered; see slap2_descriptor):
        ``pm`` turns the controller on at the current position; in pm a running move
        is replanned with ``ma`` to the last polled position (brakes with sa, returns
        there), because a second ``pm`` in pm changes nothing. Urgent like STOP."""
        module = self._link.module_state(self._address)
        flags = codec.decode_rss(module.rss or 0)
        if flags["pm"] and flags["move"] and module.position is not None:
            commands = [codec.make_move_absolute(module.position)]
        else:
            commands = [codec.make_simple("pm")]
        sent = await self._link.op_execute(self._address, commands, urgent=True)
        return CommandOutcome(sent, "holding the position, motor powered")

    async def console(self, line: str) -> tuple[str, list[str]]:
        return await self._link.op_console(self._address, line)

    async def stop(self) -> None:
        await self._link.op_execute(self._address, [codec.make_simple("st")], urgent=True)

    def capture(self, reason: str) -> contextlib.AbstractAsyncContextManager[None]:
        """``drivers.base.Capturer``: the line polls this module only while open."""
        return self._link.capture(self._address, reason)

    @property
    def last_command_latch_s(self) -> float | None:
        """``drivers.base.CommandClock``: when the module executed the last command."""
        return self._link.module_state(self._address).last_command_latch_s

    @property
    def last_command_latch_span_s(self) -> float | None:
        """``drivers.base.CommandClock``: how far before that it may have been."""
        return self._link.module_state(self._address).last_command_latch_span_s

    # --- demo autopilot (drivers.base.Autopilot) -----------------------------------

    def autopilot_amplitude(self) -> int:
        return 1500 + 700 * (self._address % 3)

    def autopilot_commands(self, latest: Sample, target: int) -> list[tuple[str, dict[str, int]]]:
        steps: list[tuple[str, dict[str, int]]] = []
        if not latest.flags.get("pm"):
            steps.append(("position_mode", {}))
        steps.append(("move_absolute", {"position": target}))
        return steps

    def autopilot_settled(self, latest: Sample) -> bool:
        return bool(latest.flags.get("inpos")) and not latest.flags.get("move")

    # --- test bench (drivers.base.BenchPlanner) ----------------------------------------

    def bench_kinds(self) -> list[BenchKind]:
        return ["move", "position_step", "velocity_step", "pwm_step", "frequency_response"]

    def bench_plan(self, test: BenchTest, latest: Sample, params: Mapping[str, int]) -> BenchPlan:
        """SLAP2 tests: a move is ``mr`` with the profile as set; a position step is
        the same move with sv and sa at their maximum for the test (the SLAP2 has no
        way to bypass its profile generator, so this is the closest to a step); a
        velocity step is ``vm`` at the given sv; a PWM step is ``spwm``. Position
        tests end with the controller holding (pm), velocity and PWM tests with st.
        """
        if latest.flags.get("move") or latest.flags.get("vm"):
            raise DeviceRefusedError(
                "the axis is moving: a test must start from rest (wait, or press STOP)"
            )
        position = latest.channels.get("position") or 0.0
        if latest.flags.get("pm") and latest.channels.get("setpoint") is not None:
            # mr is relative to the target the controller holds, not to where the shaft
            # happens to stand within its hold error.
            position = float(latest.channels["setpoint"] or position)
        band = float(params.get("inpos_window", 5))
        faults = ["oc", "limit1", "limit2"]
        if test.kind in ("move", "position_step"):
            if test.distance == 0:
                raise InvalidArgumentError("distance", "distance must not be 0")
            overrides = (
                {"velocity": codec.VELOCITY_MAX, "acceleration": codec.ACCELERATION_MAX}
                if test.kind == "position_step"
                else {}
            )
            return BenchPlan(
                setup=[] if latest.flags.get("pm") else [("position_mode", {})],
                trigger=[("move_relative", {"distance": test.distance})],
                finish=[],
                response="position",
                y0=position,
                y_final=position + test.distance,
                band=band,
                overrides=overrides,
                done_flag="inpos",
                moving_flag="move",
                fault_flags=faults,
            )
        if test.kind == "velocity_step":
            if test.velocity == 0:
                raise InvalidArgumentError("velocity", "velocity must not be 0")
            return BenchPlan(
                setup=[("stop", {})] if latest.flags.get("pm") else [],
                overrides={"velocity": test.velocity},
                trigger=[("velocity_mode", {})],
                finish=[("stop", {})],
                response="velocity",
                y0=latest.channels.get("velocity") or 0.0,
                y_final=test.velocity * codec.COUNTS_S_PER_SV,
                band=None,
                fault_flags=faults,
            )
        if test.pwm == 0:
            raise InvalidArgumentError("pwm", "pwm must not be 0")
        return BenchPlan(
            setup=[],
            trigger=[("open_loop_pwm", {"pwm": test.pwm})],
            finish=[("stop", {})],
            response="velocity",
            y0=latest.channels.get("velocity") or 0.0,
            y_final=latest.channels.get("velocity") or 0.0,
            band=None,
            fault_flags=faults,
        )
