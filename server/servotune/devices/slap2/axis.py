"""The SLAP2 axis driver: one module as the user tunes it.

Descriptor commands become wire commands here (pure), and every exchange goes through
the module's link (``Slap2AxisLink``, declared here; ``devices/slap2/link.Slap2Link``
implements it), which owns the line. Also the demo autopilot, the bench plans and the
capture capability of a SLAP2 axis.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Mapping
from typing import Protocol

from servotune.descriptor import DeviceDescriptor
from servotune.devices.slap2 import codec
from servotune.devices.slap2.capture import ProfileState
from servotune.devices.slap2.profile import ProfileTrack, TrapezoidGenerator
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

# The stop commands go out back to back: a uc check (rss) between st and pm would let
# the shaft coast for one more exchange. Whether pm took is seen in the next poll.
_ST = codec.Command("st")
_PM = codec.Command("pm")
_BRAKE = codec.Command("spwm0")
# Below this speed (counts/s) an unpowered shaft counts as standing: STOP sends st only.
COASTING_COUNTS_S = 200.0
# Jog: a move towards the end of the counter's range at sv (the manual's own way to
# drive towards E1 fast is "pm, ma -8000000"); the release stops it (jog_stop).
JOG_TARGET = codec.POSITION_LIMIT
# jog_stop: the ma that decelerates the jog goes on the wire this long after the
# profile's state is read (the exchange itself, the selection, a poll in flight).
_JOG_STOP_LEAD_S = 0.012


class Slap2ModuleView(Protocol):
    """What the axis reads of its module's state as the link knows it (owner task's
    values: the last poll, and the commands sent since)."""

    @property
    def rss(self) -> int | None: ...
    @property
    def expected_mode(self) -> str: ...
    @property
    def position(self) -> int | None: ...
    @property
    def position_t(self) -> float | None: ...
    @property
    def following_error(self) -> int | None: ...
    @property
    def velocity(self) -> float | None: ...
    @property
    def known(self) -> Mapping[str, int]: ...
    @property
    def profile(self) -> ProfileState: ...
    @property
    def last_command_latch_s(self) -> float | None: ...
    @property
    def last_command_latch_span_s(self) -> float | None: ...


class Slap2AxisLink(Protocol):
    """What a ``Slap2Axis`` needs of its link (``Slap2Link``): identity, the module's
    state, and the operations that run as jobs on the line's owner task."""

    @property
    def descriptor(self) -> DeviceDescriptor: ...

    def axis_id(self, address: int) -> str: ...

    def axis_name(self, address: int) -> str: ...

    def now(self) -> float: ...

    def module_state(self, address: int) -> Slap2ModuleView: ...

    async def op_read_params(self, address: int) -> dict[str, int]: ...

    async def op_write_params(
        self, address: int, values: Mapping[str, int], source: str
    ) -> dict[str, int]: ...

    async def op_execute(
        self,
        address: int,
        commands: list[codec.Command],
        *,
        urgent: bool = False,
        stop: bool | None = None,
    ) -> list[str]: ...

    async def op_raw_byte(self, address: int, byte: int, *, urgent: bool = False) -> None: ...

    async def op_console(self, address: int, line: str) -> tuple[str, list[str]]: ...

    def capture(
        self, address: int, reason: str
    ) -> contextlib.AbstractAsyncContextManager[None]: ...


class Slap2Axis(AxisDriver):
    """One SLAP2 module: the axis the user tunes. All I/O goes through its link."""

    def __init__(self, link: Slap2AxisLink, address: int) -> None:
        self._link = link
        self._address = address
        # The direction of the jog servotune started last (0: none since the last release).
        self._jog_direction = 0

    @property
    def id(self) -> str:
        return self._link.axis_id(self._address)

    @property
    def name(self) -> str:
        return self._link.axis_name(self._address)

    @property
    def address(self) -> int:
        return self._address

    @property
    def descriptor(self) -> DeviceDescriptor:
        return self._link.descriptor

    async def read_params(self) -> dict[str, int]:
        return await self._link.op_read_params(self._address)

    async def write_params(
        self, values: Mapping[str, int], source: str = "write"
    ) -> dict[str, int]:
        return await self._link.op_write_params(self._address, values, source)

    def make_command(self, name: str, args: Mapping[str, int]) -> list[codec.Command]:
        """Build the wire commands for a descriptor command (pure; no I/O)."""
        if name == "power_off":
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
                    "vm'): Power off (st) first, then save"
                )
        if name == "hold":
            return await self._hold()
        if name == "stop":
            return self._as_command(await self.stop())
        if name == "jog_stop":
            return self._as_command(await self.jog_stop())
        if name == "jog":
            return await self._jog(args["direction"])
        commands = self.make_command(name, args)
        sent = await self._link.op_execute(self._address, commands, urgent=name == "power_off")
        return CommandOutcome(sent, "ok")

    @staticmethod
    def _as_command(outcome: StopOutcome) -> CommandOutcome:
        return CommandOutcome(outcome.sent, outcome.message)

    # --- stops (drivers.base.StopModes; docs/control.md "Stops") ----------------------

    def mode(self) -> str:
        """What the module does as far as the driver knows: ``pm``, ``vm``, ``pwm``
        (open loop), ``off`` (unpowered), or ``off?`` (neither pm nor vm in the last
        status word, and no command of servotune's since that tells more: st or spwm).
        The commands servotune sent are newer than the last poll; a calibration runs in
        pm (the status word says so)."""
        module = self._link.module_state(self._address)
        if module.expected_mode in ("pm", "vm", "pwm", "off"):
            return module.expected_mode
        flags = codec.decode_rss(module.rss or 0)
        if flags["vm"]:
            return "vm"
        if flags["pm"]:
            return "pm"
        return "off?"

    def stop_commands(
        self, mode: str, velocity_counts_s: float | None
    ) -> tuple[list[codec.Command], str]:
        """STOP with a working loop, by mode (pure): the commands and the ``StopAction``.

        Decision (measured on the simulator, docs/control.md): holding in pm where the
        shaft is stops far shorter than any profile deceleration, because the loop
        brakes with the full supply at once (loaded demo module at 187 000 counts/s:
        ~1 200 counts against ~6 200 with sa at its maximum and ~110 000 for st alone).
        From vm or open-loop PWM, pm alone (it holds the position where it is); from pm,
        st then pm (a second pm in pm changes nothing, and st also ends a calibration,
        during which pm is refused). An unpowered shaft that still turns gets the brake
        (spwm 0: the winding shorted, no energy fed; switched off once at rest, by the
        hub); an unpowered standing one st only - STOP never powers an unpowered motor.
        The hub watches a hold until the axis is at rest and brakes if the loop
        oscillates instead (``servotune.hub.stops``).
        """
        if mode in ("vm", "pwm"):
            return [_PM], "hold"
        if mode == "pm":
            return [_ST, _PM], "hold"
        if velocity_counts_s is not None and abs(velocity_counts_s) > COASTING_COUNTS_S:
            return [_BRAKE], "brake"
        return [_ST], "power_off"

    async def stop(self) -> StopOutcome:
        module = self._link.module_state(self._address)
        commands, action = self.stop_commands(self.mode(), module.velocity)
        sent = await self._link.op_execute(self._address, commands, urgent=True, stop=True)
        message = {
            "hold": "stopped: holding the position under power (pm)",
            "brake": "braking: winding shorted (spwm 0); st once at rest",
            "power_off": "motor unpowered (st)",
        }[action]
        return StopOutcome(sent, action, message)  # type: ignore[arg-type]

    async def controlled_stop(self) -> StopOutcome:
        """The SLAP2's shortest stop is already one that holds (``stop``)."""
        return await self.stop()

    async def power_off(self) -> StopOutcome:
        sent = await self._link.op_execute(self._address, [_ST], urgent=True, stop=True)
        return StopOutcome(sent, "power_off", "motor unpowered (st)")

    async def brake(self) -> StopOutcome:
        """spwm 0: the bridge puts 0 V on the winding, so the turning motor's own back-EMF
        brakes it - no loop, no encoder needed, no energy fed (the manual is silent on
        what spwm 0 does electrically; a bridge that applies the PWM as voltage shorts
        the winding at 0, which the simulator models; docs/control.md)."""
        sent = await self._link.op_execute(self._address, [_BRAKE], urgent=True, stop=True)
        return StopOutcome(sent, "brake", "braking: winding shorted (spwm 0); st once at rest")

    async def unjudged_stop(self) -> StopOutcome:
        """The brake (``brake``): it needs no loop and no encoder, and back-EMF plus
        friction stops the shaft sooner than friction alone, so it is never longer than
        st; where the loop works it is longer than the hold in pm but of the same order,
        where it oscillates far shorter than a hold that the watch brakes later
        (docs/control.md). Ends unpowered once at rest."""
        return await self.brake()

    async def hold_here(self) -> StopOutcome:
        sent = await self._link.op_execute(self._address, [codec.make_simple("pm")])
        return StopOutcome(sent, "hold", "holding the position under power (pm)")

    # --- jog both ways ------------------------------------------------------------------

    def jog_commands(self, direction: int, mode: str) -> list[codec.Command]:
        """A jog (pure): pm unless in pm (from vm it holds where the shaft is), then a
        move towards the end of the range in ``direction`` at sv and sa."""
        commands = [] if mode == "pm" else [codec.make_simple("pm")]
        return [*commands, codec.make_move_absolute(JOG_TARGET if direction > 0 else -JOG_TARGET)]

    async def _jog(self, direction: int) -> CommandOutcome:
        commands = self.jog_commands(direction, self.mode())
        sent = await self._link.op_execute(self._address, commands)
        self._jog_direction = 1 if direction > 0 else -1
        return CommandOutcome(sent, "jogging: release to stop")

    def _polled_jog_track(self) -> ProfileTrack | None:
        """The running jog as the last poll saw it, when its reconstruction was dropped
        (the link drops a profile that disagrees with rp + pe, e.g. after a command
        whose latch time is uncertain): from the polled setpoint at the poll's time, at
        the measured speed (at most sv) towards the jog's end. None unless a jog of ours
        runs in pm and the poll knows position, error, sv and sa."""
        direction = self._jog_direction
        module = self._link.module_state(self._address)
        flags = codec.decode_rss(module.rss or 0)
        sv = module.known.get("velocity")
        sa = module.known.get("acceleration")
        if (
            direction == 0
            or not flags["pm"]
            or not flags["move"]
            or module.position is None
            or module.position_t is None
            or module.following_error is None
            or not sv
            or not sa
        ):
            return None
        generator = TrapezoidGenerator.from_wire(
            module.position + module.following_error, direction * JOG_TARGET, sv, sa
        )
        # The measured speed (counts/s) in the jog's direction, at most sv: a jog still
        # accelerating is not taken for one at full speed.
        measured_counts_tick = abs(module.velocity or 0.0) * codec.TICK_S
        generator.velocity = direction * min(generator.vmax, measured_counts_tick)
        generator.moving = True
        return ProfileTrack(module.position_t, generator)

    def jog_stop_target(self, now_s: float) -> int | None:
        """Where the running move comes to rest decelerating with its own sa, if the
        ``ma`` went out now (pure), or None when nothing is known of it.

        Two estimates: the reconstructed profile of the move the driver sent
        (``devices.slap2.capture``) and, for a jog of ours, the last poll (polled
        setpoint, measured speed). A jog's shaft only moves towards the jog's end, so
        the estimate further along that way is taken: a profile whose latch time a
        starved host stamped late lags the shaft, and planning from it would send the
        axis back the way it came."""
        estimates = [
            self._rest_point(track, now_s)
            for track in (
                self._link.module_state(self._address).profile.track,
                self._polled_jog_track(),
            )
            if track is not None
        ]
        if not estimates:
            return None
        direction = self._jog_direction
        return max(estimates, key=lambda target: target * direction) if direction else estimates[0]

    @staticmethod
    def _rest_point(track: ProfileTrack, now_s: float) -> int:
        """Where ``track`` comes to rest decelerating with its own acceleration from the
        state it has ``_JOG_STOP_LEAD_S`` after ``now_s``."""
        state = track.state_at(now_s + _JOG_STOP_LEAD_S)
        if not state.moving or state.acceleration <= 0:
            return round(state.setpoint)
        v = abs(state.velocity)
        a = state.acceleration
        ticks = math.ceil(v / a)
        braking = v * ticks - a * ticks * (ticks + 1) / 2  # setpoint travel while v -> 0
        direction = 1.0 if state.velocity > 0 else -1.0
        return round(state.setpoint + direction * max(0.0, braking))

    async def jog_stop(self) -> StopOutcome:
        """Release of a jog: the running move decelerates with sa and holds where it
        comes to rest (a new ma replans from the generator's state); without a known
        profile (a move typed in the console) the controlled stop."""
        target = self.jog_stop_target(self._link.now()) if self.mode() == "pm" else None
        self._jog_direction = 0
        if target is not None:
            sent = await self._link.op_execute(
                self._address, [codec.make_move_absolute(target)], urgent=True, stop=True
            )
            return StopOutcome(sent, "hold", f"decelerating with sa to {target}, then holding")
        return await self.controlled_stop()

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

    def capture(self, reason: str) -> contextlib.AbstractAsyncContextManager[None]:
        """``link.base.Capturer``: the line polls this module only while open."""
        return self._link.capture(self._address, reason)

    @property
    def last_command_latch_s(self) -> float | None:
        """``link.base.CommandClock``: when the module executed the last command."""
        return self._link.module_state(self._address).last_command_latch_s

    @property
    def last_command_latch_span_s(self) -> float | None:
        """``link.base.CommandClock``: how far before that it may have been."""
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
        velocity step is ``vm`` at the given sv (positive: sv has no sign); a PWM step
        is ``spwm``. Every test ends with the controller holding (pm): position tests
        stay in pm, velocity and PWM tests end with STOP, which holds where the shaft
        is (``stop_commands``).
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
            if not 0 < test.velocity <= codec.VELOCITY_MAX:
                raise InvalidArgumentError(
                    "velocity",
                    f"velocity must be 1..{codec.VELOCITY_MAX} (sv): the SLAP2's sv is a "
                    "speed without a sign (manual), velocity mode turns towards positive "
                    "counts only",
                )
            return BenchPlan(
                setup=[],
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
