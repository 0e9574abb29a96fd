"""Beckhoff EP7047-1032 EtherCAT driver: one slave, its positioning interface, one axis.

EtherCAT is not a byte channel, so this link implements ``link.base.Link`` directly
(not ``link.engine.LinkEngine``) but keeps its rules: one owner, STOP ahead of
everything, jobs refused while the link is down, state through the ``DriverSink``.

The library seam
    The driver talks to an EtherCAT *master* through :class:`EthercatMaster`, a small
    protocol with pysoem's own names (``open``, ``config_init``, ``slaves``,
    ``config_map``, ``send_processdata``, ``receive_processdata``, ``read_state``,
    ``write_state``, ``state_check``, ``state``, ``expected_wkc``, ``close``; per slave
    ``man``/``id``/``rev``, ``sdo_read``/``sdo_write``, ``input``/``output``, ``state``,
    ``al_status``, ``write_state``, ``state_check``). :class:`PysoemMaster` is the thin
    adapter over a real ``pysoem.Master`` (``pip install 'servotune[ethercat]'``);
    ``servotune.devices.ep7047.sim.slave.SimulatedEthercatMaster`` is the fake used by the tests
    and the demo.

The owner: one cycle thread
    Process data must flow every 1..4 ms (default 2 ms) whatever the event loop does, so
    one thread per link owns the master: bring-up, the cyclic exchange (``time.sleep``
    to an absolute deadline, so the period does not drift; more than one period late it
    re-anchors and counts an overrun), and every SDO transfer - between two exchanges,
    never concurrently with them. The event loop only submits requests to thread-safe
    queues and gets results, samples and state changes back through
    ``loop.call_soon_threadsafe``. Every cycle's sample is delivered, in batches of
    ``SAMPLE_BATCH_S`` (one loop wake-up per batch, not per cycle).

Modules (this one re-exports their public names): ``transports.ethercat`` the library
seam (protocols, errors, state values, pysoem adapter); ``devices.ep7047.requests``
requests, the cycle state and ``_LinkCore`` (status, posts from the thread to the loop,
sample batches); ``devices.ep7047.handshakes`` ``_CommandCycle`` (the command
handshakes); ``devices.ep7047.cycle`` ``_CycleThread`` (bring-up, exchange, SDO slots,
samples, shutdown); here ``Ep7047Link`` (the event-loop side), ``Ep7047Axis``
(parameters, commands, console, bench planner) and the glue.

Each cycle: (1) urgent requests (STOP, emergency stop, Halt) go into the outputs of this
very exchange; (2) the next user request, one at a time (an SDO transfer, or a command
that watches the inputs until the drive has taken it); (3) exchange and working-counter
check; (4) the handshakes: Enable until STM Ready, Reset pulsed, Execute held until Busy
has risen and fallen; (5) one SDO (the user's, or a sample of the drive state
0x9020:03); (6) the sample.

Safety: the SyncManager watchdog of the slave is left on. If servotune (or its host)
dies, no process data arrives and the slave drops its outputs (Enable off) after the
watchdog time (100 ms by default). If the cycle thread itself stalls that long, the
driver drops Enable and Execute too, so they are not re-asserted silently when the
process data resumes. After a drop out of OP the bring-up runs again and the outputs
start from zero: the axis never resumes a move or Enable by itself.

Decisions (also in docs/ep7047-driver.md):

* STOP = Emergency stop (emergency deceleration) and Execute low on the next cycle,
  queued user commands are discarded (a move queued behind a STOP must never run),
  then Enable off once the drive reports standstill (or after the emergency
  deceleration time + 0.5 s). "Emergency stop" keeps Enable (holding torque) and
  releases the bit at standstill; "Halt" only drops Execute (the drive ramps down with
  the move's deceleration - the normal end of an ENDLESS move).
* A plain start writes target, velocity, start type and ramps one cycle before raising
  Execute; Execute stays high until Busy has risen and fallen (dropping it earlier
  would abort the move), then drops. A command that ends within one 250 us drive cycle
  may never show Busy: when Busy has not risen within max(10 cycles, 25 ms), Execute is
  dropped and the flags decide (Error -> refused). ``execute_move`` returns when the
  drive has taken the move (Busy seen for two cycles) or answered it.
* A _CHANGE start type is written with Execute still high; the driver watches the
  diagnosis (0x9020:01) for a new "Command rejected" for max(10 cycles, 25 ms).
* Refused by the server (409) because the drive would refuse it: a start while not
  enabled, during STOP, or while a move runs (use a _CHANGE type); a _CHANGE type with
  Execute low; ADDITIVE_CHANGE during ENDLESS; modulo starts with modulo factor 0, a
  negative target, or a SHORT target >= the modulo factor; Reset while Busy;
  SET_CALIBRATION_AUTO through the process data (it is meant as default start type).
  Errors the drive reports itself (Error, Command rejected) come back as 409 with the
  decoded diagnosis.
* Working counter: a cycle whose working counter is not ``expected_wkc`` is lost (no
  sample, counted in ``errors``); then the slave's AL state is read: out of OP is a
  drop-out at once, otherwise 10 lost cycles in a row are.
* Parameters are written by SDO and read back; the written values are kept and written
  again at every later bring-up (after a drop-out or a power cycle of the box).
"""

from __future__ import annotations

import asyncio
import functools
import logging
import threading
from collections.abc import Callable, Mapping
from typing import Any

from servotune.descriptor import DeviceDescriptor
from servotune.devices.ep7047 import codec
from servotune.devices.ep7047.codec import CodecError, PosDiag, PosSettings, SdoObject, StartType
from servotune.devices.ep7047.cycle import _CycleThread
from servotune.devices.ep7047.descriptor import (
    CALIBRATION_COMMANDS,
    INVERSION_BITS,
    INVERSION_PARAMETER,
    NOT_A_DEFAULT_START_TYPE,
    PARAMETER_SDO,
)
from servotune.devices.ep7047.requests import (
    _NEEDS_VELOCITY,
    _URGENT_KINDS,
    DEFAULT_COUNTS_PER_REV,
    DEFAULT_SPEED_RANGE_STEPS_S,
    WATCHDOG_S,
    DriveRefusedValueError,
    SdoValueRefusedError,
    _CycleState,
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
    DriverError,
    DriverSink,
    InvalidArgumentError,
    LinkDownError,
    Sample,
    StopOutcome,
    check_console_line,
)
from servotune.link.validation import validate_command
from servotune.transports.ethercat import (
    BOOT_STATE,
    INIT_STATE,
    NONE_STATE,
    OP_STATE,
    PREOP_STATE,
    PYSOEM_MISSING,
    SAFEOP_STATE,
    STATE_ACK,
    STATE_ERROR,
    EthercatError,
    EthercatMailboxError,
    EthercatMaster,
    EthercatSdoError,
    EthercatSlave,
    EthercatUnavailableError,
    PysoemMaster,
    raw_socket_problem,
    state_name,
)
from servotune.transports.ethercat_cycle import CycleProcessMaster

logger = logging.getLogger(__name__)


class Ep7047Link(_CycleThread):
    """One EtherCAT network interface with one EP7047-1032 slave; see the module docstring."""

    device = "ep7047"

    @functools.cached_property
    def _axis(self) -> Ep7047Axis:
        return Ep7047Axis(self, self._axis_name)

    @property
    def axes(self) -> list[AxisDriver]:
        return [self._axis]

    async def _create_master(self) -> EthercatMaster:
        while True:
            try:
                return self._master_factory()
            except EthercatUnavailableError as exc:
                self._set_state("error", str(exc))
            except Exception as exc:
                logger.exception("creating the EtherCAT master of %s failed", self.id)
                self._set_state("error", f"cannot create the EtherCAT master: {exc!r}")
            await asyncio.sleep(self._reconnect_max_s)

    async def run(self) -> None:
        """Create the master, run the cycle thread, publish status; never raises for faults.

        Supervised: a cycle thread that ends without being asked to (an internal error,
        which it logged and reported as ``error``) is replaced by a new one on a new
        master with backoff (0.25 s doubling to ``reconnect_max_s``), exactly like a
        drop-out; the axis never resumes Enable or a move by itself (the bring-up
        starts from zero outputs).
        """
        self._loop = asyncio.get_running_loop()
        self._halt.clear()
        backoff_s = 0.25
        thread: threading.Thread | None = None
        try:
            while True:
                master = await self._create_master()
                self._cs = _CycleState()
                thread = threading.Thread(
                    target=self._thread_main,
                    args=(master,),
                    name=f"ep7047-cycle-{self.id}",
                    daemon=True,
                )
                thread.start()
                started = self._clock()
                last_status = started
                while thread.is_alive():
                    await asyncio.sleep(0.1)
                    if self._clock() - last_status >= 1.0:
                        last_status = self._clock()
                        self._publish_status()
                thread = None
                self._restarts += 1
                if self._clock() - started > 30.0:
                    backoff_s = 0.25
                self._fail_queued(LinkDownError(f"link {self.id} is restarting: nothing was sent"))
                reason = self._message or "the cycle thread ended"
                self._set_state("error", f"{reason}; restarting in {backoff_s:g} s")
                await asyncio.sleep(backoff_s)
                backoff_s = min(backoff_s * 2, self._reconnect_max_s)
        finally:
            self._halt.set()
            self._fail_queued(LinkDownError(f"link {self.id} is shutting down"))
            if thread is not None:
                await asyncio.to_thread(thread.join, 10.0)

    # --- requests (event loop side) -----------------------------------------------------

    async def submit(self, request: _Request) -> Any:
        """Queue ``request`` for the cycle thread and wait for its result."""
        if self._loop is None or self._state != "connected" or not self._thread_connected:
            request.future.cancel()
            raise LinkDownError(f"link {self.id} is {self._state}: nothing was sent")
        with self._lock:
            if request.kind in _URGENT_KINDS:
                self._urgent.append(request)
            else:
                self._normal.append(request)
        return await request.future

    def new_request(self, kind: _Kind, **values: Any) -> _Request:
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        return _Request(kind, future, **values)

    async def sdo_read(self, obj: SdoObject) -> int:
        value: int = await self.submit(self.new_request(_Kind.SDO_READ, obj=obj))
        return value

    async def sdo_write(self, obj: SdoObject, value: int) -> None:
        await self.submit(self.new_request(_Kind.SDO_WRITE, obj=obj, value=value))


# --- the axis ---------------------------------------------------------------------------------


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

    def __init__(self, link: Ep7047Link, name: str) -> None:
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
        return self._link._slave_pos

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
        self._link._sink.on_params(self.id, values, "read")
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
                    self._link._sink.on_params(self.id, readback, source)
                if isinstance(exc, SdoValueRefusedError):
                    raise DriveRefusedValueError(
                        name, f"{name} = {value}: the drive refused the value: {exc.reason}"
                    ) from exc
                raise DeviceRefusedError(f"{name} = {value}: {exc}") from exc
        self._link._sink.on_params(self.id, readback, source)
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
                self._link._sink.on_params(self.id, {name: value}, "read")

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
        return self._link._counts_per_rev

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


def _real_master(cycle_s: float, cycle_process: bool) -> EthercatMaster:
    """pysoem on a NIC; in a cycle process unless ``cycle_process`` is False."""
    try:
        import pysoem  # noqa: F401 - checked here, so that the link says so at once
    except ImportError as exc:
        raise EthercatUnavailableError(PYSOEM_MISSING) from exc
    if not cycle_process:
        return PysoemMaster()
    return CycleProcessMaster(PysoemMaster, cycle_s=cycle_s, name="ec-cycle")


def build_ep7047_link(
    link_id: str,
    ifname: str,
    slave: int,
    sink: DriverSink,
    *,
    master: EthercatMaster | None = None,
    cycle_s: float = 0.002,
    speed_range_steps_s: int = DEFAULT_SPEED_RANGE_STEPS_S,
    counts_per_rev: int = DEFAULT_COUNTS_PER_REV,
    settings: PosSettings | None = None,
    name: str | None = None,
    watchdog_s: float = WATCHDOG_S,
    cycle_process: bool = True,
) -> Ep7047Link:
    """An EP7047-1032 link on ``ifname`` (slave position ``slave``, from 1).

    ``master`` None uses the real pysoem master (created when the link runs, so a missing
    pysoem shows as the link's error state, not as a crash), in a cycle process of its
    own (``transports.ethercat_cycle``; ``cycle_process=False``: in the driver's thread,
    for comparison). ``settings``, when given, are written over CoE at every bring-up;
    otherwise the drive's own values are read.
    ``watchdog_s`` is the slave's SyncManager watchdog time (the device default, 100 ms):
    a longer gap in the process data makes the driver drop Enable.
    """
    factory: Callable[[], EthercatMaster]
    if master is None:
        factory = functools.partial(_real_master, cycle_s, cycle_process)
    else:
        given = master

        def factory() -> EthercatMaster:
            return given

    return Ep7047Link(
        link_id,
        ifname,
        slave,
        sink,
        factory,
        cycle_s=cycle_s,
        speed_range_steps_s=speed_range_steps_s,
        counts_per_rev=counts_per_rev,
        settings=settings,
        name=name,
        watchdog_s=watchdog_s,
    )


__all__ = [
    "BOOT_STATE",
    "INIT_STATE",
    "NONE_STATE",
    "OP_STATE",
    "PREOP_STATE",
    "SAFEOP_STATE",
    "STATE_ACK",
    "STATE_ERROR",
    "DriverError",
    "Ep7047Axis",
    "Ep7047Link",
    "EthercatError",
    "EthercatMailboxError",
    "EthercatMaster",
    "EthercatSdoError",
    "EthercatSlave",
    "EthercatUnavailableError",
    "PysoemMaster",
    "build_ep7047_link",
    "diag_text",
    "raw_socket_problem",
    "state_name",
]
