"""The Z1100 link: one chip, three motors, one request per reply (the axis driver is
in ``devices.z1100.axis``). The link *has* a ``LinkEngine`` (owner task, job queues,
reconnects, status), for which it is the ``LinkSession``, and a ``Z1100Exchange``
(``devices.z1100.exchange``: one request, one reply, retries and fences; its rules are
there).

Rules (``shared/spec/z1100.md``), and decisions where it is silent:

* A poll that still fails after its retries is counted and the poll goes on; the
  link shows ``error`` only after three failed poll cycles in a row and turns
  ``connected`` again with the next good one.
* Polling: GetEncoder and GetError for the three motors every cycle; GetStart, GetStop
  and one GetSwitch every ``status_every`` cycles (the running/stall bits change only
  at move boundaries, and every extra 13-byte transaction costs 1.4 ms at 9600 baud).
* Chip reset (the manual's hint): GetKABH, GetVmax or GetAcc reading 0 after they
  were loaded. One of them is read back every ``verify_period_s``.
* STOP is Estop for the motor (stops at once); ``decelerate`` is the chip's Stop.
* Capture (``link.base.Capturer``, docs/capture.md): while a measurement records a
  motor, the line polls GetEncoder of that motor (one sample each), GetError every
  3rd sample while it runs, every 6th at rest (the following error is a slow channel, None
  between its reads), GetStart every ``CAPTURE_STATUS_PERIOD_S`` (the running bits of
  all motors in one transaction), GetStop only after a stall bit, no GetSwitch and no
  verify reads; the other motors pause ("paused: capture on ...").
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections import deque
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field

from servotune.descriptor import DeviceDescriptor
from servotune.devices.z1100 import codec
from servotune.devices.z1100.axis import Z1100Axis, describe_reply, parse_console_line, request_name
from servotune.devices.z1100.descriptor import FORBIDDEN_WHILE_MOVING, z1100_descriptor
from servotune.devices.z1100.exchange import TRANSACTION_CHARS, Z1100Exchange
from servotune.link.base import (
    AxisDriver,
    DeviceRefusedError,
    DriverError,
    DriverSink,
    InvalidArgumentError,
    Sample,
    check_console_line,
)
from servotune.link.capture import CaptureRegistry, CaptureStats
from servotune.link.engine import LinkEngine, engine_face, recent_rate_hz
from servotune.link.setpoint import SkewedSetpoint
from servotune.transports.base import ByteChannel, Connector

logger = logging.getLogger(__name__)

RESET_WITNESSES = ("kabh_k", "vmax", "acc")
# GetError in a capture: every 3rd sample while the motor runs (the following error is
# what the Z1100 identification fits, and the verdict's peak), every 6th at rest.
CAPTURE_ERROR_EVERY_RUNNING = 3
CAPTURE_ERROR_EVERY = 6
CAPTURE_STATUS_PERIOD_S = 0.1
_SCALAR_PARAMS: dict[str, tuple[codec.Command, codec.Command]] = {
    "vmax": (codec.Command.SET_VMAX, codec.Command.GET_VMAX),
    "acc": (codec.Command.SET_ACC, codec.Command.GET_ACC),
    "limit": (codec.Command.SET_LIMIT, codec.Command.GET_LIMIT),
    "stm": (codec.Command.SET_STM, codec.Command.GET_STM),
    "hvm": (codec.Command.SET_HVM, codec.Command.GET_HVM),
    "hac": (codec.Command.SET_HAC, codec.Command.GET_HAC),
    "cab": (codec.Command.SET_CAB, codec.Command.GET_CAB),
    "busy": (codec.Command.SET_BUSY, codec.Command.GET_BUSY),
}


@dataclass(slots=True)
class Z1100LinkConfig:
    link_id: str
    path: str
    baud: int = codec.DEFAULT_BAUD
    lines: int = 512
    names: dict[int, str] = field(default_factory=dict)
    reply_timeout_s: float = codec.REPLY_TIMEOUT_S
    retries: int = 3
    status_every: int = 4
    verify_period_s: float = 2.0
    reconnect_max_s: float = 5.0
    # How long the answer to a fence may take: late replies queued before it arrive
    # first, so this covers the worst lateness the line tolerates (10 replies' worth).
    fence_timeout_s: float = 1.0
    # Failed poll cycles in a row before the link shows ``error`` (one failed cycle on
    # a slow host is a retry, not an alarm).
    error_after_failures: int = 3


@dataclass(slots=True)
class _MotorState:
    axis: int
    position: int | None = None
    position_t: float | None = None
    following_error: int | None = None
    velocity: float | None = None
    target: int | None = None
    running: bool = False
    positive: bool = False
    stopped: bool = False
    stall: bool = False
    switch: bool = False
    job: int = codec.Job.FREE  # the job servotune last set (a reset makes it 0)
    known: dict[str, int] = field(default_factory=dict)
    samples: deque[float] = field(default_factory=lambda: deque(maxlen=1024))
    capture: CaptureStats | None = None
    last_capture: CaptureStats | None = None
    paused: bool = False
    since_error: int = 0
    # position + GetError, two reads a transaction apart (drivers.setpoint)
    skewed: SkewedSetpoint = field(default_factory=SkewedSetpoint)


class Z1100Link:
    """Owner of the serial line to one Z1100 chip (three axes): ``link.base.Link``, the
    ``LinkSession`` of its ``engine``, the link each ``Z1100Axis`` talks to."""

    device = "z1100"

    def __init__(
        self,
        config: Z1100LinkConfig,
        connector: Connector,
        sink: DriverSink,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._engine = LinkEngine(
            config.link_id,
            config.path,
            config.baud,
            connector,
            sink,
            self,
            clock=clock,
            reconnect_max_s=config.reconnect_max_s,
        )
        self._exchange = Z1100Exchange(config, self._engine, clock)
        self._connector = connector
        self._sink = sink
        self._clock = clock
        self.config = config
        self._descriptor = z1100_descriptor(4 * config.lines)
        self._motors = [_MotorState(axis) for axis in range(codec.AXES)]
        self._axes: list[AxisDriver] = [Z1100Axis(self, axis) for axis in range(codec.AXES)]
        self._online = False
        self._cycle = 0
        self._verify_index = 0
        self._last_verify_t = 0.0
        self._failed_cycles = 0
        self._captures = CaptureRegistry(self._capture_changed)
        self._capture_index = 0
        self._last_status_t = 0.0
        self._flags_t: float | None = None  # when the flags were last read (GetStart)
        # Fences whose answer did not come (a line worse than merely late).
        self._engine.count("fence_timeouts", 0)

    # --- its parts, its axes -----------------------------------------------------------

    @property
    def engine(self) -> LinkEngine:
        """The owner task, job queues and status of this line."""
        return self._engine

    @property
    def axes(self) -> list[AxisDriver]:
        return list(self._axes)

    @property
    def descriptor(self) -> DeviceDescriptor:
        """The descriptor the chip's three axes share."""
        return self._descriptor

    # link.base.Link (with HasCounters, HasWireBusy, WireStats): the engine's members.
    id, path, baud, state, errors, counters, wire_busy, now, run = engine_face()

    # --- identity ---------------------------------------------------------------------

    def axis_id(self, axis: int) -> str:
        return f"{self.id}-{'xyz'[axis]}"

    def axis_name(self, axis: int) -> str:
        return self.config.names.get(axis, f"Z1100 motor {axis + 1}")

    def motor(self, axis: int) -> _MotorState:
        return self._motors[axis]

    def link_down(self) -> None:
        self._online = False
        for motor in self._motors:
            self._sink.on_axis_health(self.axis_id(motor.axis), "offline", "link down")

    async def _resync(self, channel: ByteChannel) -> bool:
        """``Z1100Exchange.resync`` (the fence) for the link's own checks."""
        return await self._exchange.resync(channel)

    # --- session ----------------------------------------------------------------------

    async def run_session(self, channel: ByteChannel) -> None:
        self._engine.set_state("connecting", f"probing the chip on {self.path}")
        channel.discard_input()
        await self._probe()
        self._engine.connected_once = True
        self._engine.set_state("connected", self._connector.description)
        while True:
            job = self._engine.take_job()
            if job is not None:
                await self._engine.run_job(job)
                continue
            now = self._clock()
            if not self._online:
                await self._engine.wait_job_or(1.0)
                if not self._engine.jobs_pending:
                    await self._probe()
                continue
            stalls = self._engine.host_stall_count
            try:
                captured = [m for m in self._motors if m.capture is not None]
                if captured:
                    await self._capture_step(captured)
                    continue
                if now - self._last_verify_t >= self.config.verify_period_s:
                    self._last_verify_t = now
                    await self._verify_step()
                    continue
                await self._poll_cycle()
            except DriverError as exc:
                # A poll is never a reason to end the session (a refusal or an odd
                # reply to a poll is a desynchronisation): resynchronise and go on.
                excused = self._engine.host_stall_count > stalls
                await self._poll_failed(channel, exc, excused=excused)
            else:
                self._failed_cycles = 0
                if self._engine.state == "error":
                    self._engine.set_state("connected", self._connector.description)

    async def _poll_failed(
        self, channel: ByteChannel, exc: DriverError, *, excused: bool = False
    ) -> None:
        """A poll cycle failed: resynchronise; ``error`` after
        ``error_after_failures`` in a row. A cycle that failed while the host held its
        answers back (``excused``: a timeout of it was excused, ``LinkEngine.host_stalled``)
        is no evidence against the chip and does not count."""
        if not excused:
            self._failed_cycles += 1
        self._engine.count("desyncs")
        logger.info("%s: poll failed (%s), resynchronising", self.id, exc)
        await self._resync(channel)
        if self._failed_cycles >= self.config.error_after_failures:
            if self._engine.state != "error":
                self._sink.on_event("error", None, f"{self.id}: {exc}")
            self._engine.set_state("error", str(exc))

    async def _probe(self) -> None:
        try:
            for motor in self._motors:
                values = await self._read_params(motor.axis)
                motor.target = codec.unpack_int32(
                    (
                        await self._exchange.request(
                            codec.make_get(codec.Command.GET_TARGET, motor.axis)
                        )
                    ).data
                )
                self._sink.on_params(self.axis_id(motor.axis), values, "read")
            await self._read_status()
        except DriverError as exc:
            if self._online or not self._engine.connected_once:
                self._sink.on_event("warning", None, f"{self.id}: {exc}")
            self._online = False
            for motor in self._motors:
                self._sink.on_axis_health(self.axis_id(motor.axis), "offline", str(exc))
            return
        self._online = True
        on = ", ".join(f"motor {a + 1}" for a in sorted(self._captures.addresses))
        for motor in self._motors:
            if motor.paused:
                self._sink.on_axis_health(
                    self.axis_id(motor.axis), "paused", f"paused: capture on {on}"
                )
            else:
                self._sink.on_axis_health(self.axis_id(motor.axis), "ok", "")

    async def _poll_cycle(self) -> None:
        self._cycle += 1
        for motor in self._motors:
            if self._engine.urgent_pending:
                return
            position = codec.unpack_int32(
                (
                    await self._exchange.request(
                        codec.make_get(codec.Command.GET_ENCODER, motor.axis)
                    )
                ).data
            )
            t = self._exchange.last_latch_t
            error = await self._exchange.get_int(codec.Command.GET_ERROR, motor.axis)
            if motor.position is not None and motor.position_t is not None and t > motor.position_t:
                motor.velocity = (position - motor.position) / (t - motor.position_t)
            motor.position, motor.position_t, motor.following_error = position, t, error
            self._emit(motor, t)
        if self._exchange.stall_noted or self._cycle % self.config.status_every == 0:
            self._exchange.stall_noted = False
            await self._read_status()

    async def _read_status(self) -> None:
        start = await self._exchange.get(codec.Command.GET_START)
        self._flags_t = self._exchange.last_latch_t
        stop = await self._exchange.get(codec.Command.GET_STOP)
        assert isinstance(start, codec.StartStatus) and isinstance(stop, codec.StopStatus)
        axis = self._cycle % codec.AXES
        switch = await self._exchange.get(codec.Command.GET_SWITCH, axis)
        self._motors[axis].switch = bool(switch)
        for motor in self._motors:
            was_stalled = motor.stall
            motor.running = motor.axis in start.running
            motor.positive = motor.axis in start.positive
            motor.stopped = motor.axis in stop.by_command
            motor.stall = motor.axis in stop.stalled
            if motor.stall and not was_stalled:
                self._sink.on_event(
                    "error",
                    self.axis_id(motor.axis),
                    "stall: the error limit was exceeded and the chip cut motor power",
                )

    # --- capture (drivers.base.Capturer; see the module docstring) -------------------

    def capture(self, axis: int, reason: str) -> contextlib.AbstractAsyncContextManager[None]:
        """Devote the line to motor ``axis`` while the context is open."""
        if not 0 <= axis < codec.AXES:
            raise InvalidArgumentError("axis", f"the Z1100 has motors 0..{codec.AXES - 1}")
        return self._captures.hold(axis, reason)

    def capture_stats(self, axis: int) -> CaptureStats | None:
        """The running capture's statistics of a motor, else its last capture's."""
        motor = self._motors[axis]
        return motor.capture if motor.capture is not None else motor.last_capture

    def _capture_changed(self) -> None:
        captured = set(self._captures.addresses)
        now = self._clock()
        for motor in self._motors:
            if motor.axis in captured and motor.capture is None:
                motor.capture = CaptureStats(started_s=now)
                motor.since_error = CAPTURE_ERROR_EVERY  # the first sample reads it
                motor.samples.clear()  # the rate restarts with the limit (see below)
            elif motor.axis not in captured and motor.capture is not None:
                motor.capture.ended_s = now
                motor.last_capture, motor.capture = motor.capture, None
                # The rate counts the samples of the last 2 s against the limit of the
                # poll set in force: the capture's dense samples, counted against the
                # normal poll set's limit, would read above 100 % of the wire.
                motor.samples.clear()
            paused = bool(captured) and motor.axis not in captured
            if paused != motor.paused:
                motor.paused = paused
                if self._online:
                    on = ", ".join(f"motor {a + 1}" for a in sorted(captured))
                    self._sink.on_axis_health(
                        self.axis_id(motor.axis),
                        "paused" if paused else "ok",
                        f"paused: capture on {on}" if paused else "",
                    )
        self._engine.wake()

    async def _capture_step(self, captured: list[_MotorState]) -> None:
        """One sample of a captured motor: GetEncoder, GetError/GetStart when due."""
        motor = captured[self._capture_index % len(captured)]
        self._capture_index += 1
        stats = motor.capture
        assert stats is not None
        before = self._exchange.transactions
        try:
            position = codec.unpack_int32(
                (
                    await self._exchange.request(
                        codec.make_get(codec.Command.GET_ENCODER, motor.axis)
                    )
                ).data
            )
            t = self._exchange.last_latch_t
            error: int | None = None
            motor.since_error += 1
            every = CAPTURE_ERROR_EVERY_RUNNING if motor.running else CAPTURE_ERROR_EVERY
            if not self._engine.urgent_pending and motor.since_error >= every:
                error = await self._exchange.get_int(codec.Command.GET_ERROR, motor.axis)
                motor.since_error = 0
            if not self._engine.urgent_pending and (
                self._exchange.stall_noted or t - self._last_status_t >= CAPTURE_STATUS_PERIOD_S
            ):
                self._last_status_t = t
                await self._read_capture_status()
        finally:
            stats.wire_chars += (self._exchange.transactions - before) * TRANSACTION_CHARS
        self._failed_cycles = 0
        if self._engine.state == "error":
            self._engine.set_state("connected", self._connector.description)
        stats.samples += 1
        if motor.position is not None and motor.position_t is not None and t > motor.position_t:
            motor.velocity = (position - motor.position) / (t - motor.position_t)
        motor.position, motor.position_t = position, t
        if error is not None:
            motor.following_error = error
        self._emit(motor, t, fresh_error=error is not None)

    async def _read_capture_status(self) -> None:
        """GetStart (running bits of all motors); GetStop only after a stall bit."""
        start = await self._exchange.get(codec.Command.GET_START)
        self._flags_t = self._exchange.last_latch_t
        assert isinstance(start, codec.StartStatus)
        for motor in self._motors:
            motor.running = motor.axis in start.running
            motor.positive = motor.axis in start.positive
        if self._exchange.stall_noted:
            self._exchange.stall_noted = False
            stop = await self._exchange.get(codec.Command.GET_STOP)
            assert isinstance(stop, codec.StopStatus)
            for motor in self._motors:
                was_stalled = motor.stall
                motor.stopped = motor.axis in stop.by_command
                motor.stall = motor.axis in stop.stalled
                if motor.stall and not was_stalled:
                    self._sink.on_event(
                        "error",
                        self.axis_id(motor.axis),
                        "stall: the error limit was exceeded and the chip cut motor power",
                    )

    def _emit(self, motor: _MotorState, t: float, *, fresh_error: bool = True) -> None:
        motor.samples.append(t)
        position = motor.position
        # In a capture the following error is read every few samples only: None in
        # between (a slow channel), never a stale value next to a fresh position.
        error = motor.following_error if fresh_error else None
        channels: dict[str, float | None] = {
            "position": position,
            "target": motor.target,
            # Only while the error is steady: on a ringing motor the sum of two reads a
            # transaction apart is no setpoint (drivers.setpoint).
            "setpoint": motor.skewed.setpoint(position, error, profile_running=motor.running),
            "following_error": error,
            "velocity": motor.velocity,
        }
        flags = {
            "running": motor.running,
            "positive": motor.positive,
            "stopped": motor.stopped,
            "stall": motor.stall,
            "switch": motor.switch,
        }
        # The flags are those of the last status read (GetStart first; ``flags_t``).
        self._sink.on_sample(
            self.axis_id(motor.axis), Sample(t, channels, flags, flags_t=self._flags_t)
        )

    async def _verify_step(self) -> None:
        motor = self._motors[self._verify_index % codec.AXES]
        if motor.job in (codec.Job.TARGET, codec.Job.VELOCITY) and not motor.running:
            # Parameters stored with SetFlash come back after a reset, so the 0-reads
            # miss it; the job does not survive a reset (it powers up as 0, free shaft).
            job = await self._exchange.get(codec.Command.GET_JOB, motor.axis)
            if job == codec.Job.FREE and await self._confirm_zero(
                lambda: self._exchange.get_int(codec.Command.GET_JOB, motor.axis)
            ):
                motor.job = codec.Job.FREE
                for each in self._motors:
                    each.job = codec.Job.FREE
                    self._sink.on_axis_health(
                        self.axis_id(each.axis),
                        "reset",
                        "chip reset: the job reads 0 (free shaft) although servotune set it — "
                        "the motors are unpowered and RAM settings may be lost",
                    )
                self._sink.on_event("warning", None, f"{self.id}: chip reset detected (job 0)")
                await self._probe_params_only()
                return
        witness = RESET_WITNESSES[(self._verify_index // codec.AXES) % len(RESET_WITNESSES)]
        self._verify_index += 1
        expected = motor.known.get(witness)
        if not expected:
            return
        if await self._read_witness(motor.axis, witness) != 0:
            return
        # Confirm with a second reading of all three witnesses after a fence: one late
        # or misframed reply (the protocol has no header; on a stalled host a reply can
        # land after its request timed out) must not wipe the state. A fence that went
        # unanswered leaves the line out of step: no verdict now, the next check asks
        # again.
        if not await self._resync(self._engine.require_channel()):
            return
        zeros = [w for w in RESET_WITNESSES if await self._read_witness(motor.axis, w) == 0]
        if len(zeros) >= 2:
            for each in self._motors:
                name = "KABH K" if witness == "kabh_k" else witness
                each.known.clear()
                self._sink.on_axis_health(
                    self.axis_id(each.axis),
                    "reset",
                    f"chip reset: {name} reads 0 after it was loaded — parameters lost",
                )
            self._sink.on_event("warning", None, f"{self.id}: chip reset detected")
            await self._probe_params_only()

    async def _confirm_zero(self, read: Callable[[], Awaitable[int]]) -> bool:
        """A zero read once is confirmed only by reading zero again after a fence (late
        replies to earlier requests are dropped first): the reset cue must survive a
        slow host without a false alarm. A fence that went unanswered confirms
        nothing: the line may still be out of step (a starved host can leave a late
        zero in the line after the fence timed out)."""
        if not await self._resync(self._engine.require_channel()):
            return False
        return await read() == 0

    async def _read_witness(self, axis: int, witness: str) -> int:
        if witness == "kabh_k":
            gains = await self._exchange.get(codec.Command.GET_KABH, axis)
            assert isinstance(gains, codec.Gains)
            return gains.k
        return await self._exchange.get_int(_SCALAR_PARAMS[witness][1], axis)

    async def _probe_params_only(self) -> None:
        for motor in self._motors:
            if self._engine.urgent_pending:
                return  # a STOP first; the next verify step reads again
            values = await self._read_params(motor.axis)
            self._sink.on_params(self.axis_id(motor.axis), values, "read")

    # --- parameters -------------------------------------------------------------------

    async def _read_params(self, axis: int) -> dict[str, int]:
        values: dict[str, int] = {}
        for prefix, command in (("kabh", codec.Command.GET_KABH), ("kabd", codec.Command.GET_KABD)):
            gains = await self._exchange.get(command, axis)
            assert isinstance(gains, codec.Gains)
            values.update({f"{prefix}_k": gains.k, f"{prefix}_a": gains.a, f"{prefix}_b": gains.b})
        for name, (_, getter) in _SCALAR_PARAMS.items():
            await self._engine.let_stops_pass()
            values[name] = int(await self._exchange.get_int(getter, axis))
        self._motors[axis].known.update(values)
        return values

    async def _write_params(self, axis: int, values: Mapping[str, int]) -> dict[str, int]:
        motor = self._motors[axis]
        if motor.running:
            blocked = sorted(FORBIDDEN_WHILE_MOVING & set(values))
            if blocked:
                raise DeviceRefusedError(
                    f"{blocked[0]}: the chip refuses it while motor {axis + 1} is moving "
                    "(forbidden while moving: Vmax, Acc, Hvm, Hac, Cab) — stop it first"
                )
        readback: dict[str, int] = {}
        # KABH first: writing it overwrites KABD (manual), so KABD must come after.
        for prefix, moving in (("kabh", True), ("kabd", False)):
            names = [f"{prefix}_{g}" for g in "kab"]
            if not any(n in values for n in names):
                continue
            k, a, b = (values.get(n, motor.known.get(n, 0)) for n in names)
            await self._engine.let_stops_pass()
            await self._exchange.request(codec.make_set_kab(axis, k, a, b, moving=moving))
            for read_prefix, command in (
                ("kabh", codec.Command.GET_KABH),
                ("kabd", codec.Command.GET_KABD),
            ):
                gains = await self._exchange.get(command, axis)
                assert isinstance(gains, codec.Gains)
                readback.update(
                    {
                        f"{read_prefix}_k": gains.k,
                        f"{read_prefix}_a": gains.a,
                        f"{read_prefix}_b": gains.b,
                    }
                )
        for name, value in values.items():
            if name not in _SCALAR_PARAMS:
                continue
            setter, getter = _SCALAR_PARAMS[name]
            await self._engine.let_stops_pass()
            await self._exchange.request(codec.Request(setter + axis, int(value)))
            readback[name] = await self._exchange.get_int(getter, axis)
        motor.known.update(readback)
        return readback

    # --- operations used by Z1100Axis -------------------------------------------------

    async def op_read_params(self, axis: int) -> dict[str, int]:
        async def job() -> dict[str, int]:
            return await self._read_params(axis)

        values = await self._engine.submit(job)
        self._sink.on_params(self.axis_id(axis), values, "read")
        return values

    async def op_write_params(
        self, axis: int, values: Mapping[str, int], source: str
    ) -> dict[str, int]:
        async def job() -> dict[str, int]:
            return await self._write_params(axis, values)

        readback = await self._engine.submit(job)
        self._sink.on_params(self.axis_id(axis), readback, source)
        return readback

    async def op_requests(
        self,
        axis: int,
        requests: list[codec.Request],
        *,
        urgent: bool = False,
        starts: bool = False,
        stop: bool | None = None,
    ) -> list[str]:
        """Send ``requests`` for motor ``axis`` as one job; ``stop`` (default: an Estop
        among them) fails the motor's queued motion first and makes it urgent."""

        async def job() -> list[str]:
            sent = []
            for request in requests:
                reply = await self._exchange.request(request)
                sent.append(request_name(request))
                if request.command is codec.Command.SET_TARGET:
                    self._motors[axis].target = codec.unpack_int32(request.data)
                elif request.command is codec.Command.SET_JOB:
                    self._motors[axis].job = request.data & 0xFF
                del reply
            if starts:
                self._motors[axis].running = True
            return sent

        is_stop = (
            any(r.command is codec.Command.SET_ESTOP for r in requests) if stop is None else stop
        )
        return await self._engine.submit(job, urgent=urgent, axis=axis, motion=True, stop=is_stop)

    async def op_console(self, axis: int, line: str) -> tuple[str, list[str]]:
        check_console_line(line)
        request = parse_console_line(line, axis)

        async def job() -> list[str]:
            reply = await self._exchange.request(request)
            return describe_reply(request, reply)

        return request_name(request), await self._engine.submit(job, axis=axis, motion=True)

    def wire_limit_hz(self) -> float:
        """Samples/s per axis the wire allows: 13 bytes per transaction at 10 bits.

        Per cycle: GetEncoder + GetError for three motors, plus GetStart, GetStop and
        one GetSwitch every ``status_every`` cycles. During a capture: the limit of the
        captured motors' actual poll mix, from the transactions it took.
        """
        char_s = 10 / self.config.baud
        captures = [m.capture for m in self._motors if m.capture is not None]
        if captures:
            samples = sum(c.samples for c in captures)
            chars = sum(c.wire_chars for c in captures)
            if samples and chars:
                return samples / len(captures) / (chars * char_s)
            return 1 / (TRANSACTION_CHARS * char_s * len(captures))
        per_cycle = 2 * codec.AXES + 3 / self.config.status_every
        return 1 / (per_cycle * (codec.REQUEST_SIZE + codec.REPLY_SIZE) * char_s)

    def achieved_rate_hz(self) -> float:
        """Mean samples/s per motor over the last 2 s (falls to 0 when polling stops)."""
        now = self._clock()
        rates = [recent_rate_hz(m.samples, now) for m in self._motors if not m.paused]
        return sum(rates) / len(rates) if self._online and rates else 0.0


__all__ = ["Z1100Axis", "Z1100Link", "Z1100LinkConfig", "describe_reply", "parse_console_line"]
