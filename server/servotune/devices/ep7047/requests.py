"""The EP7047-1032 driver's requests, the cycle thread's state and the plumbing between
the event loop and the cycle thread (``_LinkCore``: status, the thread-to-loop posts,
the sample batches). See ``servotune.devices.ep7047.link`` for the design; the link class
is assembled there from ``_LinkCore`` < ``_CommandCycle`` (``devices.ep7047.handshakes``) <
``_CycleThread`` (``devices.ep7047.cycle``) < ``Ep7047Link``, each layer using only those below.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Final

from servotune.descriptor import DeviceDescriptor
from servotune.devices.ep7047 import codec
from servotune.devices.ep7047.codec import (
    DriveState,
    Inputs,
    Outputs,
    PosControl,
    PosDiag,
    PosSettings,
    SdoObject,
    StartType,
    StmControl,
)
from servotune.devices.ep7047.descriptor import DIAG_FLAGS, POS_FLAGS, STM_FLAGS, ep7047_descriptor
from servotune.link.base import DeviceRefusedError, DriverSink, InvalidArgumentError, Sample
from servotune.link.engine import recent_rate_hz
from servotune.schema import AxisHealth, EventLevel, LinkState
from servotune.transports.ethercat import EthercatMaster

SAMPLE_BATCH_S: Final = 0.02
"""Samples of the cycle thread go to the event loop in batches, one
``call_soon_threadsafe`` each ``SAMPLE_BATCH_S`` (10 samples at the 2 ms default
cycle) instead of one per cycle: every wake-up of the loop costs a self-pipe write,
an epoll round and a callback (docs/ep7047-driver.md, "CPU": the per-sample wake-ups
were the largest single cost of the demo server). 20 ms stays below
the hub's telemetry batch (``hub.state.BATCH_PERIOD_S``, 1/30 s), so every telemetry
message still carries new samples of this axis and the plots see no added delay
worth the name; every sample is still delivered, in order, with its own time.
Anything else the thread posts (a result, a state change, an event) first flushes
the batch, so a caller that gets its answer has the sample showing the drive's
reaction already delivered."""
SAMPLE_BATCH_MAX: Final = 32
"""A batch is flushed at this many samples even if its 20 ms are not up (1 ms cycle,
or a test clock that does not advance)."""

# Flag tables as plain ints: the flag dict is built for every sample.
_POS_BITS: Final = tuple((name, int(bit)) for name, bit in POS_FLAGS.items())
_STM_BITS: Final = tuple((name, int(bit)) for name, bit in STM_FLAGS.items())
_DIAG_BITS: Final = tuple((name, int(bit)) for name, bit in DIAG_FLAGS.items())


# --- driver internals ----------------------------------------------------------------------

DEFAULT_SPEED_RANGE_STEPS_S: Final = 2000
DEFAULT_COUNTS_PER_REV: Final = 4096
# The SyncManager watchdog's default time: a gap this long without good process data
# means the slave has dropped its outputs, so the driver drops Enable too.
WATCHDOG_S: Final = 0.1
STATE_ACTIVE_S: Final = 0.5
"""How long after a status flag changed the drive state is still read at the fast rate."""
WATCHDOG_MARGIN_S: Final = 0.002
"""How much sooner than the slave the driver counts its watchdog as expired. The gap
is measured between the times the cycle thread *sent* two frames (what the slave's
SyncManager counts), stamped just before each send; the margin covers the few
microseconds between stamp and wire, a thread switch between the last check and the
send, and the slave's own timer granularity (the simulator counts whole 250 us
cycles). Decision: better to drop Enable ourselves at 98 ms and say so than to let
the drive drop it unseen at 100 ms and re-assert it with the next frame."""
# Nice value the cycle thread asks for (see Ep7047Link._raise_priority).
CYCLE_THREAD_NICE: Final = -10

_DIAG_TEXTS: Final[Mapping[PosDiag, str]] = {
    PosDiag.COMMAND_REJECTED: (
        "Command rejected (a dynamic change cannot be taken at standstill or while accelerating)"
    ),
    PosDiag.COMMAND_ABORTED: (
        "Command aborted (ended early by an internal error, Emergency stop or Execute low)"
    ),
    PosDiag.TARGET_OVERRUN: "Target overrun (a late change forces a reversal past the target)",
}


def diag_text(diag: PosDiag) -> str:
    """The manual's meaning of every bit set in ``diag``."""
    parts = [text for bit, text in _DIAG_TEXTS.items() if diag & bit]
    return "; ".join(parts) if parts else "no diagnosis bit set"


# SDO abort codes that refuse the *value* (ETG.1000.6): range, too high, too low,
# length/type. The request went out; the drive kept its old value.
VALUE_ABORT_CODES: Final = frozenset(
    {0x0609_0030, 0x0609_0031, 0x0609_0032, 0x0609_0036, 0x0607_0010, 0x0607_0012, 0x0607_0013}
)


class SdoValueRefusedError(DeviceRefusedError):
    """The drive aborted an SDO download because of the value (``abort_code`` in
    :data:`VALUE_ABORT_CODES`); the parameter or console layer names the field."""

    def __init__(self, message: str, abort_code: int, reason: str) -> None:
        super().__init__(message)
        self.abort_code = abort_code
        self.reason = reason


class DriveRefusedValueError(InvalidArgumentError):
    """A field error from the drive itself: it aborted the SDO download of this value
    with a value-range code (the value was sent, and not taken)."""


class _BringUpError(Exception):
    def __init__(self, message: str, *, fatal: bool = False, no_answer: bool = False) -> None:
        super().__init__(message)
        self.fatal = fatal
        self.no_answer = no_answer  # nothing answers: the link shows error, and retries


class _DropOutError(Exception):
    """The slave is gone from OP; ``state`` is what the link shows while it retries:
    ``error`` when nothing answers (a pulled cable, no power), ``reconnecting`` when the
    slave answers but left OP (e.g. its watchdog tripped)."""

    def __init__(
        self, message: str, *, state: LinkState = "reconnecting", watchdog: bool = False
    ) -> None:
        super().__init__(message)
        self.state: LinkState = state
        self.watchdog = watchdog  # the drive's watchdog tripped (AL status 0x001B)


# AL status code of a SyncManager watchdog trip (ETG.1000.6).
AL_WATCHDOG: Final = 0x001B


def watchdog_trip_text(ifname: str, slave: int) -> str:
    """What a user reads when the drive's process-data watchdog tripped (AL 0x001B): what
    happened, not a reset - the drive kept its settings."""
    return (
        f"the drive (slave {slave} on {ifname}) dropped Enable because process data stopped: "
        "its SyncManager watchdog tripped (AL status 0x001B) - the motor stopped without "
        "holding torque, its settings are kept; servotune brings it back to OP with "
        "Enable off"
    )


class _Kind(enum.Enum):
    SDO_READ = enum.auto()
    SDO_WRITE = enum.auto()
    ENABLE = enum.auto()
    DISABLE = enum.auto()
    RESET = enum.auto()
    START = enum.auto()
    STOP = enum.auto()
    EMERGENCY_STOP = enum.auto()
    HALT = enum.auto()


_SDO_KINDS = frozenset({_Kind.SDO_READ, _Kind.SDO_WRITE})
_URGENT_KINDS = frozenset({_Kind.STOP, _Kind.EMERGENCY_STOP, _Kind.HALT})


@dataclass(eq=False, slots=True)
class _Request:
    kind: _Kind
    future: asyncio.Future[Any]
    obj: SdoObject | None = None
    value: int = 0
    start_type: StartType = StartType.ABSOLUTE
    target: int = 0
    velocity_bp: int = 0
    acceleration_ms: int = 0
    deceleration_ms: int = 0
    # thread-side progress of a command
    deadline: float = 0.0
    stage: int = 0
    count: int = 0
    saw_busy: bool = False
    diag_before: PosDiag = PosDiag.NONE
    previous_target: float | None = None


class _Exec(enum.Enum):
    IDLE = enum.auto()  # Execute low, nothing running
    ARMING = enum.auto()  # parameters written, Execute goes high next cycle
    WAIT_BUSY = enum.auto()  # Execute high, Busy not yet seen
    RUNNING = enum.auto()  # Execute high, Busy seen: held until Busy falls
    HALTING = enum.auto()  # Execute dropped early: waiting for Busy to fall


class _StopPhase(enum.Enum):
    NONE = enum.auto()
    STOPPING = enum.auto()  # STOP: emergency stop, then Enable off at standstill
    EMCY_HOLD = enum.auto()  # Emergency stop: released at standstill, Enable kept


@dataclass(slots=True)
class _CycleState:
    """Everything the cycle thread knows about the drive; touched only by that thread."""

    enable: bool = False
    reset: bool = False
    emergency: bool = False
    execute: bool = False
    target: int = 0
    velocity_bp: int = 0
    start_type: int = 0
    acceleration_ms: int = 0
    deceleration_ms: int = 0
    inputs: Inputs = field(default_factory=Inputs)
    exec_state: _Exec = _Exec.IDLE
    running: StartType | None = None
    move_started_t: float = 0.0
    pending: _Request | None = None
    sdo_job: _Request | None = None
    after_exchange: list[_Request] = field(default_factory=list)
    stop_phase: _StopPhase = _StopPhase.NONE
    stop_deadline: float = 0.0
    stop_cycles: int = 0
    diag: PosDiag = PosDiag.NONE
    diag_t: float = -math.inf
    drive_state: int | None = None
    next_state_poll: float = 0.0
    target_estimate: float | None = None
    last_target: float | None = None
    last_direction: int = 1
    lost_in_row: int = 0
    silent_in_row: int = 0  # cycles in a row with no frame back at all
    silent_since: float = 0.0  # the send time of the first of them

    def outputs(self) -> Outputs:
        stm = StmControl.NONE
        if self.enable:
            stm |= StmControl.ENABLE
        if self.reset:
            stm |= StmControl.RESET
        pos = PosControl.NONE
        if self.execute:
            pos |= PosControl.EXECUTE
        if self.emergency:
            pos |= PosControl.EMERGENCY_STOP
        return Outputs(
            stm_control=stm,
            pos_control=pos,
            target_position_counts=self.target,
            velocity_bp=self.velocity_bp,
            start_type=self.start_type,
            acceleration_ms=self.acceleration_ms,
            deceleration_ms=self.deceleration_ms,
        )


_CALIBRATION_MOVES = frozenset({StartType.CALI_PLC_CAM, StartType.CALI_HW_SYNC})
_INSTANT_TYPES = frozenset(
    {StartType.SET_CALIBRATION, StartType.CLEAR_CALIBRATION, StartType.SET_CALIBRATION_AUTO}
)
_ENDLESS_TYPES = frozenset({StartType.ENDLESS_PLUS, StartType.ENDLESS_MINUS})
_NEEDS_VELOCITY = frozenset(StartType) - _CALIBRATION_MOVES - _INSTANT_TYPES


def _settle(future: asyncio.Future[Any], result: Any, error: BaseException | None) -> None:
    if future.done():
        return
    if error is not None:
        future.set_exception(error)
    else:
        future.set_result(result)


def _state_label(state: int) -> str:
    try:
        return f"{DriveState(state).name} (0x{state:04X})"
    except ValueError:
        return f"0x{state:04X}"


class _LinkCore:
    """State shared by the event loop and the cycle thread, status and the posts from the
    thread to the loop. Not a link by itself: ``Ep7047Link`` is."""

    def __init__(
        self,
        link_id: str,
        ifname: str,
        slave: int,
        sink: DriverSink,
        master_factory: Callable[[], EthercatMaster],
        *,
        cycle_s: float = 0.002,
        speed_range_steps_s: int = DEFAULT_SPEED_RANGE_STEPS_S,
        counts_per_rev: int = DEFAULT_COUNTS_PER_REV,
        settings: PosSettings | None = None,
        name: str | None = None,
        clock: Callable[[], float] = time.monotonic,
        state_poll_s: float = 0.01,
        rest_state_poll_s: float = 0.1,
        max_lost_frames: int = 10,
        reconnect_max_s: float = 5.0,
        watchdog_s: float = WATCHDOG_S,
    ) -> None:
        if not 0.001 <= cycle_s <= 0.004:
            raise ValueError(f"cycle_s must be 0.001..0.004 s, got {cycle_s}")
        if slave < 1:
            raise ValueError(f"slave positions start at 1, got {slave}")
        self._link_id = link_id
        self._ifname = ifname
        self._slave_pos = slave
        self._sink = sink
        self._master_factory = master_factory
        self._cycle_s = cycle_s
        self._speed_range = speed_range_steps_s
        self._counts_per_rev = counts_per_rev
        self._clock = clock
        # The drive state (0xA010:11) is only in the mailbox: one SDO per read. Read every
        # state_poll_s while the drive does something (Busy, Execute, a STOP ramp, or
        # within STATE_ACTIVE_S of any status flag changing), every rest_state_poll_s
        # at rest, where it does not change by itself: the state timeline keeps its
        # 10 ms detail where there is detail, and a real drive's mailbox (and this
        # thread) is spared 90 % of the reads while nothing moves.
        self._state_poll_s = state_poll_s
        self._rest_state_poll_s = max(rest_state_poll_s, state_poll_s)
        self._active_until = 0.0
        self._max_lost = max_lost_frames
        self._reconnect_max_s = reconnect_max_s
        self._watchdog_s = watchdog_s
        # No frame back at all for this long is a pulled cable (an error): half the
        # watchdog, so that the user reads it before the drive has stopped, and a few
        # lost frames in a row (each ~10 ms of SOEM's waiting) are only counted.
        self._silent_limit_s = max(max_lost_frames * cycle_s, watchdog_s / 2)
        self._descriptor = ep7047_descriptor(speed_range_steps_s, counts_per_rev)
        self._axis_name = name or f"EP7047-1032 #{slave}"
        self._state: LinkState = "connecting"
        self._message = ""
        self._errors = 0
        self._overruns = 0
        self._lost_frames = 0
        self._paced_lost = 0  # the cycle process's lost exchanges counted so far
        self._watchdog_trips = 0
        self._restarts = 0
        self._sample_times: deque[float] = deque(maxlen=4096)
        # requests, shared with the cycle thread
        self._lock = threading.Lock()
        self._urgent: deque[_Request] = deque()
        self._normal: deque[_Request] = deque()
        self._halt = threading.Event()
        self._thread_connected = False
        self._loop: asyncio.AbstractEventLoop | None = None
        # CoE values: last read or written (thread), and what to write at every bring-up
        self._coe: dict[SdoObject, int] = {}
        self._stored: dict[SdoObject, int] = {}
        if settings is not None:
            for obj, value in codec.settings_writes(settings):
                if obj != codec.TIME_INFORMATION:  # manual: cannot be changed
                    self._stored[obj] = value
        self._cs = _CycleState()
        self._revision: int | None = None
        self._in_cycle = False
        self._outbox: list[tuple[_Request, Any, BaseException | None]] = []
        # When the last frame the slave took was sent (see WATCHDOG_MARGIN_S).
        self._last_good = time.monotonic()
        # samples not yet posted to the loop (cycle thread only, see SAMPLE_BATCH_S)
        self._sample_batch: list[Sample] = []
        # the last outputs encoded and inputs decoded (cycle thread only): most cycles
        # send the same outputs, and at rest receive the same inputs, as the one before
        self._outputs_key: tuple[object, ...] | None = None
        self._outputs_bytes = b""
        self._inputs_raw = b""
        self._inputs_decoded = Inputs()
        # the flags of the last sample and what they were built from (cycle thread only):
        # they change rarely, so consecutive samples share one (never mutated) dict
        self._flags_key: tuple[int, int, int, bool, bool, bool] | None = None
        self._flags: dict[str, bool] = {}
        self._batch_due = 0.0

    # --- Link protocol ------------------------------------------------------------------

    @property
    def id(self) -> str:
        return self._link_id

    @property
    def path(self) -> str:
        return f"{self._ifname} slave {self._slave_pos}"

    @property
    def baud(self) -> int:
        return 0  # not a serial line

    @property
    def state(self) -> LinkState:
        return self._state

    @property
    def errors(self) -> int:
        """Lost cycles (bad working counter) and failed SDO transfers since start."""
        return self._errors

    @property
    def descriptor(self) -> DeviceDescriptor:
        return self._descriptor

    @property
    def axis_id(self) -> str:
        return f"{self._link_id}-{self._slave_pos}"

    @property
    def cycle_s(self) -> float:
        return self._cycle_s

    def wire_limit_hz(self) -> float:
        return 1 / self._cycle_s

    def achieved_rate_hz(self) -> float:
        """Samples/s over the last 2 s, falling to 0 within 2 s when the cycles stop."""
        return recent_rate_hz(self._sample_times, self._clock())

    @property
    def counters(self) -> dict[str, int]:
        """Lost frames (bad working counter), cycle overruns (a cycle thread more than one
        period late), watchdog trips (more than ``watchdog_s`` without good process data:
        the drive dropped its outputs), restarts of the cycle thread after an internal
        error."""
        return {
            "lost_frames": self._lost_frames,
            "overruns": self._overruns,
            "watchdog_trips": self._watchdog_trips,
            "restarts": self._restarts,
        }

    # --- status (event loop side) -------------------------------------------------------

    def _set_state(self, state: LinkState, message: str) -> None:
        changed = (state, message) != (self._state, self._message)
        self._state, self._message = state, message
        if changed:
            self._publish_status()

    def _publish_status(self) -> None:
        self._sink.on_link_status(
            self.id,
            self._state,
            self._message,
            self.achieved_rate_hz(),
            self.wire_limit_hz(),
            self._errors,
        )

    def _deliver_samples(self, samples: list[Sample]) -> None:
        times = self._sample_times
        sink, axis_id = self._sink, self.axis_id
        for sample in samples:
            times.append(sample.t)
            sink.on_sample(axis_id, sample)

    def _fail_queued(self, error: Exception) -> None:
        with self._lock:
            queued = [*self._urgent, *self._normal]
            self._urgent.clear()
            self._normal.clear()
        for request in queued:
            _settle(request.future, None, error)

    # --- thread -> event loop -------------------------------------------------------------

    def _post(self, callback: Callable[..., object], *args: Any) -> None:
        """Run ``callback`` on the loop (cycle thread only), after the samples so far."""
        if self._sample_batch:
            self._flush_samples()
        self._post_now(callback, *args)

    def _post_now(self, callback: Callable[..., object], *args: Any) -> None:
        loop = self._loop
        if loop is None:
            return
        with contextlib.suppress(RuntimeError):  # the loop is closed: nobody listens
            loop.call_soon_threadsafe(callback, *args)

    def _post_sample(self, sample: Sample) -> None:
        """Queue ``sample`` for the loop; post the batch when it is due (SAMPLE_BATCH_S)."""
        batch = self._sample_batch
        batch.append(sample)
        now = time.monotonic()
        if len(batch) == 1:
            self._batch_due = now + SAMPLE_BATCH_S
        elif now >= self._batch_due or len(batch) >= SAMPLE_BATCH_MAX:
            self._flush_samples()

    def _flush_samples(self) -> None:
        batch, self._sample_batch = self._sample_batch, []
        if batch:
            self._post_now(self._deliver_samples, batch)

    def _resolve(self, request: _Request, result: Any = None) -> None:
        self._settle_later(request, result, None)

    def _reject(self, request: _Request, error: BaseException) -> None:
        self._settle_later(request, None, error)

    def _settle_later(self, request: _Request, result: Any, error: BaseException | None) -> None:
        # Within a cycle, results wait for that cycle's sample: a caller that gets its
        # answer has the sample showing the drive's reaction already delivered.
        if self._in_cycle:
            self._outbox.append((request, result, error))
        else:
            self._post(_settle, request.future, result, error)

    def _post_state(self, state: LinkState, message: str) -> None:
        self._post(self._set_state, state, message)

    def _post_event(self, level: EventLevel, message: str, *, axis: bool = True) -> None:
        self._post(self._sink.on_event, level, self.axis_id if axis else None, message)

    def _post_health(self, health: AxisHealth, message: str) -> None:
        self._post(self._sink.on_axis_health, self.axis_id, health, message)

    def _post_params(self, values: Mapping[str, int], source: str) -> None:
        self._post(self._sink.on_params, self.axis_id, dict(values), source)
