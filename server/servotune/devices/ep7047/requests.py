"""The EP7047-1032 driver's requests, the queue that hands them to the cycle, the cycle's
state and counters: data shared by the link (``devices.ep7047.link``), its event-loop bridge
(``devices.ep7047.bridge``), the cycle (``devices.ep7047.cycle``) and the command
handshakes (``devices.ep7047.handshakes``). See ``servotune.devices.ep7047.link`` for the
design.
"""

from __future__ import annotations

import asyncio
import enum
import math
import threading
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Final

from servotune.devices.ep7047.codec import (
    DriveState,
    Inputs,
    Outputs,
    PosControl,
    PosDiag,
    SdoObject,
    StartType,
    StmControl,
)
from servotune.devices.ep7047.descriptor import DIAG_FLAGS, POS_FLAGS, STM_FLAGS
from servotune.link.base import DeviceRefusedError, InvalidArgumentError
from servotune.schema import LinkState

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
# Nice value the cycle thread asks for (see Cycle._raise_priority).
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


class RequestQueue:
    """The requests the event loop hands to the cycle, urgent ones (STOP, Emergency stop,
    Halt) apart from the rest, each kind in order. Thread-safe. ``urgent`` and ``normal``
    may be peeked without the lock (a request appended meanwhile is seen at the next
    peek); only the methods take requests out."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.urgent: deque[_Request] = deque()
        self.normal: deque[_Request] = deque()

    def put(self, request: _Request) -> None:
        with self._lock:
            if request.kind in _URGENT_KINDS:
                self.urgent.append(request)
            else:
                self.normal.append(request)

    def take_urgent(self) -> list[_Request]:
        """Every urgent request, oldest first."""
        with self._lock:
            urgent = list(self.urgent)
            self.urgent.clear()
        return urgent

    def pop_normal(self) -> _Request | None:
        """The oldest other request, or None."""
        with self._lock:
            return self.normal.popleft() if self.normal else None

    def drop_commands(self) -> list[_Request]:
        """Take every queued command out (SDO transfers stay queued) and return them."""
        with self._lock:
            dropped = [r for r in self.normal if r.kind not in _SDO_KINDS]
            self.normal = deque(r for r in self.normal if r.kind in _SDO_KINDS)
        return dropped

    def take_all(self) -> list[_Request]:
        """Every queued request, urgent ones first."""
        with self._lock:
            queued = [*self.urgent, *self.normal]
            self.urgent.clear()
            self.normal.clear()
        return queued


@dataclass(slots=True)
class CycleCounters:
    """The link's counters (``Ep7047Link.counters``): written by the cycle thread (the
    link counts restarts), read by the event loop."""

    errors: int = 0  # lost cycles and failed SDO transfers
    lost_frames: int = 0
    overruns: int = 0
    watchdog_trips: int = 0
    restarts: int = 0
