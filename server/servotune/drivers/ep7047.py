"""Beckhoff EP7047-1032 EtherCAT driver: one slave, its positioning interface, one axis.

EtherCAT is not a byte channel, so this link implements ``drivers.base.Link`` directly
(not ``drivers.engine.LinkEngine``) but keeps its rules: one owner, STOP ahead of
everything, jobs refused while the link is down, state through the ``DriverSink``.

The library seam
    The driver talks to an EtherCAT *master* through :class:`EthercatMaster`, a small
    protocol with pysoem's own names (``open``, ``config_init``, ``slaves``,
    ``config_map``, ``send_processdata``, ``receive_processdata``, ``read_state``,
    ``write_state``, ``state_check``, ``state``, ``expected_wkc``, ``close``; per slave
    ``man``/``id``/``rev``, ``sdo_read``/``sdo_write``, ``input``/``output``, ``state``,
    ``al_status``, ``write_state``, ``state_check``). :class:`PysoemMaster` is the thin
    adapter over a real ``pysoem.Master`` (``pip install 'servotune[ethercat]'``);
    ``servotune.sim.ep7047_slave.SimulatedEthercatMaster`` is the fake used by the tests
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
import contextlib
import enum
import logging
import math
import os
import struct
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, Protocol

from servotune.descriptor import DeviceDescriptor
from servotune.drivers.base import (
    AxisDriver,
    BenchKind,
    BenchPlan,
    BenchTest,
    CommandOutcome,
    DeviceRefusedError,
    DeviceTimeoutError,
    DriverError,
    DriverSink,
    InvalidArgumentError,
    LinkDownError,
    ProtocolError,
    Sample,
    check_console_line,
)
from servotune.drivers.engine import recent_rate_hz
from servotune.drivers.ep7047_descriptor import (
    CALIBRATION_COMMANDS,
    DIAG_FLAGS,
    INVERSION_BITS,
    INVERSION_PARAMETER,
    NOT_A_DEFAULT_START_TYPE,
    PARAMETER_SDO,
    POS_FLAGS,
    STM_FLAGS,
    ep7047_descriptor,
)
from servotune.drivers.validation import validate_command
from servotune.protocols import ep7047 as codec
from servotune.protocols.ep7047 import (
    CHANGE_START_TYPES,
    MODULO_START_TYPES,
    CodecError,
    DriveState,
    Inputs,
    Outputs,
    PosControl,
    PosDiag,
    PosSettings,
    SdoObject,
    StartType,
    StmControl,
    StmStatus,
)
from servotune.sim.ep7047_engine import ModuloError, modulo_travel
from servotune.wire import AxisHealth, EventLevel, LinkState

logger = logging.getLogger(__name__)

SAMPLE_BATCH_S: Final = 0.01
"""Samples of the cycle thread go to the event loop in batches, one
``call_soon_threadsafe`` each ``SAMPLE_BATCH_S`` (5 samples at the 2 ms default
cycle) instead of one per cycle: every wake-up of the loop costs a self-pipe write,
an epoll round and a callback (measured: the per-sample wake-ups were the largest
single cost of the demo server). 10 ms is a third of the hub's telemetry batch
(``hub.BATCH_PERIOD_S``), so the plots and the twin see no added delay worth the
name; every sample is still delivered, in order. Anything else the thread posts
(a result, a state change, an event) first flushes the batch, so a caller that gets
its answer has the sample showing the drive's reaction already delivered."""
SAMPLE_BATCH_MAX: Final = 32
"""A batch is flushed at this many samples even if its 10 ms are not up (1 ms cycle,
or a test clock that does not advance)."""

# Flag tables as plain ints: the flag dict is built for every sample.
_POS_BITS: Final = tuple((name, int(bit)) for name, bit in POS_FLAGS.items())
_STM_BITS: Final = tuple((name, int(bit)) for name, bit in STM_FLAGS.items())
_DIAG_BITS: Final = tuple((name, int(bit)) for name, bit in DIAG_FLAGS.items())

# --- EtherCAT state machine values (the same numbers as pysoem's constants) ---------------

NONE_STATE: Final = 0x00
INIT_STATE: Final = 0x01
PREOP_STATE: Final = 0x02
BOOT_STATE: Final = 0x03
SAFEOP_STATE: Final = 0x04
OP_STATE: Final = 0x08
STATE_ACK: Final = 0x10  # written: acknowledge an error indication
STATE_ERROR: Final = 0x10  # read: the slave has an error indication (see AL status)

_STATE_NAMES = {
    NONE_STATE: "NONE",
    INIT_STATE: "INIT",
    PREOP_STATE: "PRE-OP",
    BOOT_STATE: "BOOT",
    SAFEOP_STATE: "SAFE-OP",
    OP_STATE: "OP",
}
# AL status codes (ETG.1000.6) a user is likely to meet with this slave.
AL_STATUS_TEXTS: Final[Mapping[int, str]] = {
    0x0000: "no error",
    0x0011: "invalid requested state change",
    0x0012: "unknown requested state",
    0x0016: "invalid mailbox configuration",
    0x001A: "synchronization error",
    0x001B: "sync manager watchdog",
    0x001D: "invalid output configuration",
    0x001E: "invalid input configuration",
    0x001F: "invalid watchdog configuration",
}

# SDO abort codes (ETG.1000.6) worth a word in a message.
SDO_ABORT_TEXTS: Final[Mapping[int, str]] = {
    0x05040000: "SDO protocol timed out",
    0x06010000: "unsupported access to an object",
    0x06010002: "attempt to write a read only object",
    0x06020000: "the object does not exist in the object dictionary",
    0x06070010: "data type does not match, length of service parameter does not match",
    0x06090011: "subindex does not exist",
    0x06090030: "value range of parameter exceeded",
    0x06090031: "value of parameter written too high",
    0x06090032: "value of parameter written too low",
    0x08000000: "general error",
    0x08000020: "data cannot be transferred or stored to the application",
    0x08000022: "data cannot be transferred because of the present device state",
}


def state_name(state: int) -> str:
    """``SAFE-OP + ERROR`` for 0x14 and so on."""
    name = _STATE_NAMES.get(state & 0x0F, f"0x{state & 0x0F:02X}")
    return f"{name} + ERROR" if state & STATE_ERROR else name


def al_status_text(code: int) -> str:
    return f"AL status 0x{code:04X} ({AL_STATUS_TEXTS.get(code, 'see ETG.1000.6')})"


# --- the library seam ---------------------------------------------------------------------


class EthercatError(Exception):
    """Base of what an :class:`EthercatMaster` raises."""


class EthercatUnavailableError(EthercatError):
    """EtherCAT cannot be used at all here: pysoem missing, no raw sockets, no such NIC.

    The message says exactly what is wrong and how to fix it.
    """


class EthercatSdoError(EthercatError):
    """The slave aborted an SDO transfer (it answered, with an abort code)."""

    def __init__(self, index: int, subindex: int, abort_code: int, desc: str = "") -> None:
        text = desc or SDO_ABORT_TEXTS.get(abort_code, "see ETG.1000.6")
        super().__init__(f"SDO abort 0x{abort_code:08X} at 0x{index:04X}:{subindex:02X}: {text}")
        self.index = index
        self.subindex = subindex
        self.abort_code = abort_code
        self.desc = text


class EthercatMailboxError(EthercatError):
    """An SDO transfer got no (valid) answer: mailbox error, timeout, working counter 0."""


class EthercatSlave(Protocol):
    """One slave as the master found it (pysoem's ``CdefSlave`` names)."""

    @property
    def man(self) -> int:
        """Vendor id from the slave's SII (EEPROM)."""
        ...

    @property
    def id(self) -> int:
        """Product code from the SII."""
        ...

    @property
    def rev(self) -> int:
        """Revision number from the SII."""
        ...

    @property
    def name(self) -> str: ...

    @property
    def state(self) -> int:
        """The state last read (``read_state``/``state_check``) or set to be requested."""
        ...

    @state.setter
    def state(self, value: int) -> None: ...

    @property
    def al_status(self) -> int:
        """The AL status code of the last state read."""
        ...

    @property
    def input(self) -> bytes:
        """This slave's input process data as of the last ``receive_processdata``."""
        ...

    @property
    def output(self) -> bytes: ...

    @output.setter
    def output(self, value: bytes) -> None:
        """Output process data, sent with the next ``send_processdata``."""
        ...

    def sdo_read(self, index: int, subindex: int, size: int = 0) -> bytes:
        """Upload one CoE entry; raises EthercatSdoError / EthercatMailboxError."""
        ...

    def sdo_write(self, index: int, subindex: int, data: bytes) -> None:
        """Download one CoE entry; raises EthercatSdoError / EthercatMailboxError."""
        ...

    def write_state(self) -> int:
        """Request ``state`` at this slave."""
        ...

    def state_check(self, expected_state: int, timeout: int = 2000) -> int:
        """Wait up to ``timeout`` us for ``expected_state``; returns the state found."""
        ...


class EthercatMaster(Protocol):
    """The EtherCAT master the driver needs (pysoem's ``Master`` names)."""

    def open(self, ifname: str) -> None:
        """Open the network interface; EthercatUnavailableError when impossible."""
        ...

    def config_init(self) -> int:
        """Enumerate the slaves (they end in PRE-OP); returns how many were found."""
        ...

    @property
    def slaves(self) -> Sequence[EthercatSlave]: ...

    def config_map(self) -> int:
        """Map every slave's PDOs into the process image (slaves go to SAFE-OP)."""
        ...

    def send_processdata(self) -> int: ...

    def receive_processdata(self, timeout: int = 2000) -> int:
        """Wait up to ``timeout`` us for the frame; returns the working counter."""
        ...

    def read_state(self) -> int:
        """Read every slave's AL state (into ``slave.state``); returns the lowest."""
        ...

    def write_state(self) -> int:
        """Request ``state`` at every slave."""
        ...

    def state_check(self, expected_state: int, timeout: int = 50000) -> int: ...

    @property
    def state(self) -> int: ...

    @state.setter
    def state(self, value: int) -> None: ...

    @property
    def expected_wkc(self) -> int: ...

    def close(self) -> None: ...


# --- pysoem adapter ---------------------------------------------------------------------

PYSOEM_MISSING: Final = (
    "pysoem is not installed, so servotune cannot talk EtherCAT: install it with "
    "`pip install 'servotune[ethercat]'` and restart servotune"
)
RAW_SOCKET_FIX: Final = (
    "run `sudo setcap cap_net_raw,cap_net_admin+ep $(readlink -f .venv/bin/python)` and "
    "restart servotune, or run servotune as root"
)
CAP_NET_RAW: Final = 13


def _effective_capabilities() -> int:
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("CapEff:"):
                return int(line.split()[1], 16)
    return 0


def raw_socket_problem(
    ifname: str,
    *,
    euid: int | None = None,
    cap_eff: int | None = None,
    net_dir: Path = Path("/sys/class/net"),
) -> str | None:
    """Why this process cannot open ``ifname`` for EtherCAT, or None if it looks fine.

    Linux only (elsewhere None): the interface must exist and raw sockets need root or
    CAP_NET_RAW. The arguments other than ``ifname`` are for tests.
    """
    if not sys.platform.startswith("linux"):
        return None
    if not (net_dir / ifname).exists():
        known = sorted(p.name for p in net_dir.iterdir()) if net_dir.is_dir() else []
        return (
            f"there is no network interface {ifname!r} on this machine (found: "
            f"{', '.join(known) or 'none'}; `ip link` lists them): use the NIC the "
            "EP7047 is plugged into"
        )
    euid = os.geteuid() if euid is None else euid
    caps = _effective_capabilities() if cap_eff is None else cap_eff
    if euid != 0 and not (caps >> CAP_NET_RAW) & 1:
        return (
            f"raw sockets are not permitted for this process (not root, no CAP_NET_RAW), "
            f"and EtherCAT on {ifname} needs them: {RAW_SOCKET_FIX}"
        )
    return None


class _PysoemSlave:
    """EthercatSlave over a ``pysoem.CdefSlave``: maps pysoem's exceptions to the seam's."""

    def __init__(self, slave: Any, pysoem: Any) -> None:
        self._slave = slave
        self._pysoem = pysoem

    @property
    def man(self) -> int:
        return int(self._slave.man)

    @property
    def id(self) -> int:
        return int(self._slave.id)

    @property
    def rev(self) -> int:
        return int(self._slave.rev)

    @property
    def name(self) -> str:
        return str(self._slave.name)

    @property
    def state(self) -> int:
        return int(self._slave.state)

    @state.setter
    def state(self, value: int) -> None:
        self._slave.state = value

    @property
    def al_status(self) -> int:
        return int(self._slave.al_status)

    @property
    def input(self) -> bytes:
        return bytes(self._slave.input)

    @property
    def output(self) -> bytes:
        return bytes(self._slave.output)

    @output.setter
    def output(self, value: bytes) -> None:
        self._slave.output = value

    def _translate(self, exc: Exception, index: int, subindex: int) -> EthercatError:
        if isinstance(exc, self._pysoem.SdoError):
            return EthercatSdoError(index, subindex, int(exc.abort_code), str(exc.desc))
        return EthercatMailboxError(
            f"no valid answer to SDO 0x{index:04X}:{subindex:02X}: {type(exc).__name__} "
            f"{getattr(exc, 'desc', '') or getattr(exc, 'message', '') or exc}"
        )

    def sdo_read(self, index: int, subindex: int, size: int = 0) -> bytes:
        try:
            return bytes(self._slave.sdo_read(index, subindex, size))
        except (
            self._pysoem.SdoError,
            self._pysoem.WkcError,
            self._pysoem.MailboxError,
            self._pysoem.PacketError,
        ) as exc:
            raise self._translate(exc, index, subindex) from exc

    def sdo_write(self, index: int, subindex: int, data: bytes) -> None:
        try:
            self._slave.sdo_write(index, subindex, data)
        except (
            self._pysoem.SdoError,
            self._pysoem.WkcError,
            self._pysoem.MailboxError,
            self._pysoem.PacketError,
        ) as exc:
            raise self._translate(exc, index, subindex) from exc

    def write_state(self) -> int:
        return int(self._slave.write_state())

    def state_check(self, expected_state: int, timeout: int = 2000) -> int:
        return int(self._slave.state_check(expected_state, timeout))


class PysoemMaster:
    """:class:`EthercatMaster` over a real ``pysoem.Master``.

    Constructing it raises :class:`EthercatUnavailableError` when pysoem is not installed;
    ``open`` raises it when the interface is missing or raw sockets are not permitted,
    each with the fix in the message.

    SDO transfers time out after ``sdo_timeout_us`` (50 ms; SOEM's default is 700 ms):
    they run between two exchanges, and a slave that does not answer must not hold the
    process data back past the 100 ms watchdog.
    """

    def __init__(self, sdo_timeout_us: int = 50_000) -> None:
        try:
            import pysoem  # optional dependency: servotune[ethercat]
        except ImportError as exc:
            raise EthercatUnavailableError(PYSOEM_MISSING) from exc
        self._pysoem: Any = pysoem
        self._master: Any = pysoem.Master()
        self._master.sdo_read_timeout = sdo_timeout_us
        self._master.sdo_write_timeout = sdo_timeout_us
        self._slaves: list[_PysoemSlave] = []

    def open(self, ifname: str) -> None:
        problem = raw_socket_problem(ifname)
        if problem is not None:
            raise EthercatUnavailableError(problem)
        try:
            self._master.open(ifname)
        except ConnectionError as exc:
            raise EthercatUnavailableError(
                f"could not open {ifname} for EtherCAT ({exc}): is it the right NIC, and may "
                f"this process use raw sockets? {RAW_SOCKET_FIX}"
            ) from exc

    def config_init(self) -> int:
        found = int(self._master.config_init())
        self._slaves = [_PysoemSlave(s, self._pysoem) for s in (self._master.slaves or [])]
        return found

    @property
    def slaves(self) -> Sequence[EthercatSlave]:
        return self._slaves

    def config_map(self) -> int:
        try:
            return int(self._master.config_map())
        except self._pysoem.ConfigMapError as exc:
            details = "; ".join(str(getattr(e, "desc", e)) for e in getattr(exc, "error_list", []))
            raise EthercatMailboxError(f"mapping the process data failed: {details}") from exc

    def send_processdata(self) -> int:
        return int(self._master.send_processdata())

    def receive_processdata(self, timeout: int = 2000) -> int:
        return int(self._master.receive_processdata(timeout))

    def read_state(self) -> int:
        return int(self._master.read_state())

    def write_state(self) -> int:
        return int(self._master.write_state())

    def state_check(self, expected_state: int, timeout: int = 50000) -> int:
        return int(self._master.state_check(expected_state, timeout))

    @property
    def state(self) -> int:
        return int(self._master.state)

    @state.setter
    def state(self, value: int) -> None:
        self._master.state = value

    @property
    def expected_wkc(self) -> int:
        return int(self._master.expected_wkc)

    def close(self) -> None:
        self._master.close()


# --- driver internals ----------------------------------------------------------------------

DEFAULT_SPEED_RANGE_STEPS_S: Final = 2000
DEFAULT_COUNTS_PER_REV: Final = 4096
# The SyncManager watchdog's default time: a gap this long without good process data
# means the slave has dropped its outputs, so the driver drops Enable too.
WATCHDOG_S: Final = 0.1
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


class _BringUpError(Exception):
    def __init__(self, message: str, *, fatal: bool = False) -> None:
        super().__init__(message)
        self.fatal = fatal


class _DropOutError(Exception):
    pass


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


class Ep7047Link:
    """One EtherCAT network interface with one EP7047-1032 slave; see the module docstring."""

    device = "ep7047"

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
        self._state_poll_s = state_poll_s
        self._max_lost = max_lost_frames
        self._reconnect_max_s = reconnect_max_s
        self._watchdog_s = watchdog_s
        self._descriptor = ep7047_descriptor(speed_range_steps_s, counts_per_rev)
        self._axis = Ep7047Axis(self, name or f"EP7047-1032 #{slave}")
        self._state: LinkState = "connecting"
        self._message = ""
        self._errors = 0
        self._overruns = 0
        self._lost_frames = 0
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
        self._last_good = time.monotonic()
        # samples not yet posted to the loop (cycle thread only, see SAMPLE_BATCH_S)
        self._sample_batch: list[Sample] = []
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
    def axes(self) -> list[AxisDriver]:
        return [self._axis]

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

    # --- the cycle thread -------------------------------------------------------------------

    def _raise_priority(self) -> None:
        """Give the cycle thread a larger CPU share (nice ``CYCLE_THREAD_NICE``).

        The slave's watchdog (100 ms, the device default) is the safe stop if the host
        dies, and it trips just the same when the host is merely busy: a cycle thread
        that gets no CPU for 100 ms makes the drive drop Enable. A loaded host (other
        work on all cores) is the normal case on a laptop, so the thread asks the
        kernel for more weight. Only this thread; it sleeps between cycles, so it
        cannot starve the others. Needs CAP_SYS_NICE (or root), granted like
        CAP_NET_RAW for real hardware; without it the thread runs at normal priority
        and the counter ``watchdog_trips`` shows what that costs.
        """
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), CYCLE_THREAD_NICE)
        except (OSError, AttributeError) as exc:
            logger.info("%s: cycle thread at normal priority (%s)", self.id, exc)
        else:
            logger.info("%s: cycle thread at nice %d", self.id, CYCLE_THREAD_NICE)

    def _thread_main(self, master: EthercatMaster) -> None:
        connected_once = False
        backoff_s = 0.25
        self._raise_priority()
        try:
            while not self._halt.is_set():
                try:
                    slave = self._bring_up(master)
                except _BringUpError as exc:
                    self._went_down(master, None, LinkDownError(f"link {self.id} is down: {exc}"))
                    state: LinkState = (
                        "error" if exc.fatal or not connected_once else "reconnecting"
                    )
                    self._post_state(state, str(exc))
                    if self._halt.wait(backoff_s):
                        break
                    backoff_s = min(backoff_s * 2, self._reconnect_max_s)
                    continue
                if connected_once:
                    self._post_event(
                        "warning",
                        f"{self.id}: slave {self._slave_pos} is back in OP; Enable is off - "
                        "press Enable to continue",
                        axis=False,
                    )
                connected_once = True
                backoff_s = 0.25
                revision = f"rev 0x{self._revision or 0:08X}"
                self._post_state(
                    "connected",
                    f"EP7047-1032 {revision} in OP on {self._ifname}, slave {self._slave_pos}, "
                    f"{self._cycle_s * 1000:g} ms cycle",
                )
                self._post_health("ok", f"EP7047-1032 {revision}")
                try:
                    try:
                        self._cyclic(master, slave)
                    except (EthercatError, OSError) as exc:  # e.g. the NIC went away
                        raise _DropOutError(f"EtherCAT failed on {self._ifname}: {exc}") from exc
                except _DropOutError as exc:
                    self._errors += 1
                    self._went_down(master, slave, LinkDownError(f"link {self.id} is down: {exc}"))
                    self._post_health("offline", str(exc))
                    self._post_state("reconnecting", str(exc))
                    self._post_event("error", f"{self.id}: {exc}", axis=False)
                    if self._halt.wait(0.25):
                        break
                    continue
                self._shutdown(master, slave)
                break
        except Exception as exc:  # a bug here must be visible, and the link must say so
            logger.exception("EtherCAT cycle thread of %s failed", self.id)
            self._went_down(master, None, LinkDownError(f"link {self.id} failed: {exc}"))
            self._post_state("error", f"internal error in the cycle thread: {exc!r}")
            self._post_health("offline", "internal error in the EtherCAT driver")
        finally:
            self._flush_samples()
            self._thread_connected = False
            self._close_quietly(master)

    def _went_down(
        self, master: EthercatMaster, slave: EthercatSlave | None, error: Exception
    ) -> None:
        """The link is down: fail every request, acknowledge errors, close the master."""
        self._thread_connected = False
        self._fail_all(error)
        if slave is not None:
            self._acknowledge(master, slave)
        self._close_quietly(master)

    def _close_quietly(self, master: EthercatMaster) -> None:
        with contextlib.suppress(Exception):
            master.close()

    def _fail_all(self, error: Exception) -> None:
        cs = self._cs
        for request in (cs.pending, cs.sdo_job, *cs.after_exchange):
            if request is not None:
                self._reject(request, error)
        cs.pending = cs.sdo_job = None
        cs.after_exchange.clear()
        with self._lock:
            queued = [*self._urgent, *self._normal]
            self._urgent.clear()
            self._normal.clear()
        for request in queued:
            self._reject(request, error)

    def _acknowledge(self, master: EthercatMaster, slave: EthercatSlave) -> None:
        """Acknowledge the slave's error indication (the bring-up acknowledges again)."""
        with contextlib.suppress(Exception):
            master.read_state()
            state = slave.state
            if state & STATE_ERROR:
                slave.state = (state & 0x0F) | STATE_ACK
                slave.write_state()

    # --- bring-up -----------------------------------------------------------------------

    def _bring_up(self, master: EthercatMaster) -> EthercatSlave:
        """Open, enumerate, check identity, assign PDOs, write settings, SAFE-OP, OP."""
        # Whatever was queued while the link was down must not run after it returns.
        self._fail_all(LinkDownError(f"link {self.id} was down: nothing was sent"))
        try:
            return self._bring_up_steps(master)
        except EthercatUnavailableError as exc:
            raise _BringUpError(str(exc), fatal=True) from exc
        except (EthercatError, OSError) as exc:
            raise _BringUpError(f"bring-up failed on {self._ifname}: {exc}") from exc
        except CodecError as exc:
            raise _BringUpError(f"bring-up read a malformed CoE value: {exc}") from exc

    def _bring_up_steps(self, master: EthercatMaster) -> EthercatSlave:
        where = f"{self._ifname}, slave {self._slave_pos}"
        master.open(self._ifname)
        found = master.config_init()
        if found <= 0:
            raise _BringUpError(
                f"no EtherCAT slave answers on {self._ifname}: check the cable into the "
                "box's X1 IN port, the link/activity LEDs at both ends and the 24 V supply"
            )
        if self._slave_pos > len(master.slaves):
            raise _BringUpError(
                f"slave {self._slave_pos} requested but only {len(master.slaves)} found on "
                f"{self._ifname}: check ?slave= in the link spec",
                fatal=True,
            )
        slave = master.slaves[self._slave_pos - 1]
        if (slave.man, slave.id) != (codec.VENDOR_ID, codec.PRODUCT_CODE):
            raise _BringUpError(
                f"slave {self._slave_pos} on {self._ifname} is not an EP7047-1032: it is "
                f"{slave.name or 'unnamed'} (vendor 0x{slave.man:08X}, product "
                f"0x{slave.id:08X}, revision 0x{slave.rev:08X}); expected vendor "
                f"0x{codec.VENDOR_ID:08X} product 0x{codec.PRODUCT_CODE:08X}. Check "
                "?slave= in the link spec",
                fatal=True,
            )
        self._revision = slave.rev
        state = slave.state_check(PREOP_STATE, 50_000)
        if state != PREOP_STATE:
            raise _BringUpError(
                f"slave did not reach PRE-OP ({where}): {state_name(state)}, "
                f"{al_status_text(slave.al_status)}"
            )
        try:
            self._assign_pdos(slave)
            self._write_stored(slave)
            values = self._read_parameters(slave)
            self._check_speed_range(slave)
        except EthercatSdoError as exc:
            raise _BringUpError(f"CoE set-up refused ({where}): {exc}") from exc
        except EthercatMailboxError as exc:
            raise _BringUpError(f"CoE set-up got no answer ({where}): {exc}") from exc
        try:
            master.config_map()
        except EthercatError as exc:
            raise _BringUpError(f"mapping the process data failed ({where}): {exc}") from exc
        out_size, in_size = len(slave.output), len(slave.input)
        if (out_size, in_size) != (codec.OUTPUTS_SIZE, codec.INPUTS_SIZE):
            raise _BringUpError(
                f"the process image is {out_size}/{in_size} bytes, expected "
                f"{codec.OUTPUTS_SIZE}/{codec.INPUTS_SIZE} for the positioning interface: "
                "the PDO assignment was not taken",
                fatal=True,
            )
        state = master.state_check(SAFEOP_STATE, 50_000)
        if state != SAFEOP_STATE:
            master.read_state()
            raise _BringUpError(
                f"slave did not reach SAFE-OP ({where}): {state_name(slave.state)}, "
                f"{al_status_text(slave.al_status)}"
            )
        # Valid (all-zero: Enable off) outputs before OP, then request OP.
        self._cs = _CycleState()
        slave.output = codec.encode_outputs(self._cs.outputs())
        master.send_processdata()
        master.receive_processdata(self._receive_timeout_us())
        master.state = OP_STATE
        master.write_state()
        for _ in range(40):
            slave.output = codec.encode_outputs(self._cs.outputs())
            master.send_processdata()
            master.receive_processdata(self._receive_timeout_us())
            if master.state_check(OP_STATE, 50_000) == OP_STATE:
                break
            if self._halt.is_set():
                raise _BringUpError("shutting down")
        else:
            master.read_state()
            raise _BringUpError(
                f"slave did not reach OP ({where}): {state_name(slave.state)}, "
                f"{al_status_text(slave.al_status)}"
            )
        self._cs.inputs = codec.decode_inputs(slave.input)
        self._cs.next_state_poll = self._clock()
        self._last_good = time.monotonic()
        self._thread_connected = True
        self._post_params(values, "read")
        return slave

    def _receive_timeout_us(self) -> int:
        return min(2000, int(self._cycle_s * 1e6))

    def _assign_pdos(self, slave: EthercatSlave) -> None:
        """ "Positioning interface": 0x1C12/0x1C13 in PRE-OP (sub 0 = 0, entries, count)."""
        for index, pdos in (
            (0x1C12, codec.RXPDO_ASSIGNMENT),
            (0x1C13, codec.TXPDO_ASSIGNMENT),
        ):
            slave.sdo_write(index, 0, bytes([0]))
            for subindex, pdo in enumerate(pdos, start=1):
                slave.sdo_write(index, subindex, struct.pack("<H", pdo))
            slave.sdo_write(index, 0, bytes([len(pdos)]))
            count = slave.sdo_read(index, 0, 1)[0]
            found = tuple(
                struct.unpack("<H", slave.sdo_read(index, s, 2))[0] for s in range(1, count + 1)
            )
            if found != pdos:
                raise _BringUpError(
                    f"PDO assignment 0x{index:04X} reads {[hex(p) for p in found]} after "
                    f"writing {[hex(p) for p in pdos]}",
                    fatal=True,
                )

    def _write_stored(self, slave: EthercatSlave) -> None:
        for obj, value in self._stored.items():
            slave.sdo_write(obj.index, obj.subindex, codec.encode_sdo(obj, value))

    def _read_coe(self, slave: EthercatSlave, obj: SdoObject) -> int:
        value = codec.decode_sdo(obj, slave.sdo_read(obj.index, obj.subindex, obj.data_type.size))
        self._coe[obj] = value
        return value

    def _read_parameters(self, slave: EthercatSlave) -> dict[str, int]:
        values = {name: self._read_coe(slave, obj) for name, obj in PARAMETER_SDO.items()}
        values[INVERSION_PARAMETER] = sum(
            self._read_coe(slave, obj) << bit for bit, obj in INVERSION_BITS.items()
        )
        return values

    def _check_speed_range(self, slave: EthercatSlave) -> None:
        code = self._read_coe(slave, codec.SPEED_RANGE)
        steps_s = codec.SPEED_RANGE_STEPS_S.get(code)
        if steps_s != self._speed_range:
            self._post_event(
                "warning",
                f"the drive's speed range 0x8012:05 is code {code} "
                f"({steps_s or 'unknown'} full steps/s) but the link is configured for "
                f"{self._speed_range} steps/s: velocities in steps/s are shown wrong - set "
                "speed_range on the link",
            )

    # --- cyclic operation ---------------------------------------------------------------

    def _cyclic(self, master: EthercatMaster, slave: EthercatSlave) -> None:
        period = self._cycle_s
        deadline = time.monotonic()
        while not self._halt.is_set():
            self._one_cycle(master, slave)
            deadline += period
            delay = deadline - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -period:
                self._overruns += 1
                deadline = time.monotonic()

    def _exchange(self, master: EthercatMaster, slave: EthercatSlave) -> bool:
        slave.output = codec.encode_outputs(self._cs.outputs())
        master.send_processdata()
        wkc = master.receive_processdata(self._receive_timeout_us())
        if wkc == master.expected_wkc:
            self._cs.lost_in_row = 0
            self._last_good = time.monotonic()
            return True
        self._errors += 1
        self._lost_frames += 1
        self._cs.lost_in_row += 1
        master.read_state()
        state = slave.state
        if state != OP_STATE:
            raise _DropOutError(
                f"slave {self._slave_pos} on {self._ifname} left OP: now {state_name(state)}, "
                f"{al_status_text(slave.al_status)}"
            )
        if self._cs.lost_in_row >= self._max_lost:
            raise _DropOutError(
                f"no process data from slave {self._slave_pos} on {self._ifname} for "
                f"{self._cs.lost_in_row} cycles (working counter {wkc}, expected "
                f"{master.expected_wkc}): cable or power?"
            )
        return False

    def _one_cycle(self, master: EthercatMaster, slave: EthercatSlave) -> None:
        self._in_cycle = True
        try:
            self._cycle_steps(master, slave)
        finally:
            self._in_cycle = False
            outbox, self._outbox = self._outbox, []
            for request, result, error in outbox:
                self._post(_settle, request.future, result, error)

    def _cycle_steps(self, master: EthercatMaster, slave: EthercatSlave) -> None:
        cs = self._cs
        now = self._clock()
        self._check_stall()
        self._take_urgent(now)
        self._before_exchange(now)  # what an earlier cycle prepared (Execute after ARMING)
        if cs.pending is None and cs.sdo_job is None:
            self._take_normal(now)
        if not self._exchange(master, slave):
            return  # stale inputs: no sample, nothing decided on them
        now = self._clock()
        previous = cs.inputs
        cs.inputs = inputs = codec.decode_inputs(slave.input)
        for request in cs.after_exchange:
            self._resolve(request, "sent")
        cs.after_exchange.clear()
        self._update_diag(slave, previous, inputs, now)
        self._advance_stop(inputs, now)
        self._advance_exec(inputs, now)
        self._advance_pending(inputs, now)
        fresh_state = self._sdo_slot(slave, now)
        self._emit(inputs, now, fresh_state)

    def _check_stall(self) -> None:
        """After a gap longer than the watchdog the slave has dropped its outputs (Enable
        off, the move aborted): never re-assert them silently - drop them here too."""
        cs = self._cs
        gap = time.monotonic() - self._last_good
        if gap <= self._watchdog_s or not (cs.enable or cs.execute or cs.emergency):
            return
        if cs.pending is not None:
            self._reject(
                cs.pending, DeviceRefusedError("no process data for too long: the drive dropped it")
            )
            cs.pending = None
        cs.enable = cs.execute = cs.emergency = cs.reset = False
        cs.stop_phase = _StopPhase.NONE
        self._drop_execute()
        self._errors += 1
        self._watchdog_trips += 1
        self._post_event(
            "error",
            f"no good process data for {gap * 1000:.0f} ms (> the {self._watchdog_s * 1000:.0f} ms "
            "watchdog): the drive has dropped its outputs; Enable is off - press Enable to "
            "continue",
        )

    # --- requests (thread side) ---------------------------------------------------------

    def _take_urgent(self, now: float) -> None:
        with self._lock:
            urgent = list(self._urgent)
            self._urgent.clear()
        for request in urgent:
            if request.kind is _Kind.HALT:
                self._apply_halt(request)
            else:
                self._apply_stop(request, now)

    def _apply_stop(self, request: _Request, now: float) -> None:
        cs = self._cs
        label = "STOP" if request.kind is _Kind.STOP else "Emergency stop"
        error = DeviceRefusedError(f"not sent: {label} came first")
        if cs.pending is not None:
            self._reject(cs.pending, DeviceRefusedError(f"aborted by {label}"))
            cs.pending = None
        with self._lock:
            keep = deque(r for r in self._normal if r.kind in _SDO_KINDS)
            dropped = [r for r in self._normal if r.kind not in _SDO_KINDS]
            self._normal = keep
        for queued in dropped:
            self._reject(queued, error)
        cs.reset = False
        self._drop_execute()
        if cs.enable:
            cs.emergency = True
            cs.stop_phase = (
                _StopPhase.STOPPING if request.kind is _Kind.STOP else _StopPhase.EMCY_HOLD
            )
            emergency_ms = self._coe.get(codec.EMERGENCY_DECELERATION, 1000)
            cs.stop_deadline = now + emergency_ms / 1000 + 0.5
            cs.stop_cycles = 0
        cs.after_exchange.append(request)

    def _apply_halt(self, request: _Request) -> None:
        cs = self._cs
        if cs.pending is not None and cs.pending.kind is _Kind.START:
            self._reject(cs.pending, DeviceRefusedError("halted before the drive took the move"))
            cs.pending = None
        self._drop_execute()
        cs.after_exchange.append(request)

    def _drop_execute(self) -> None:
        """Execute low now; a move that may have started is watched until Busy falls."""
        cs = self._cs
        cs.execute = False
        if cs.exec_state is _Exec.ARMING:  # Execute never rose: nothing started
            cs.exec_state = _Exec.IDLE
            cs.running = None
        elif cs.exec_state is not _Exec.IDLE:
            cs.exec_state = _Exec.HALTING

    def _take_normal(self, now: float) -> None:
        cs = self._cs
        while True:
            with self._lock:
                if not self._normal:
                    return
                request = self._normal.popleft()
            if request.future.done():  # the caller gave up
                continue
            if request.kind in _SDO_KINDS:
                cs.sdo_job = request
                return
            self._begin_command(request, now)
            return

    def _begin_command(self, request: _Request, now: float) -> None:
        cs = self._cs
        kind = request.kind
        if kind is _Kind.ENABLE:
            if cs.stop_phase is _StopPhase.STOPPING:
                self._reject(request, DeviceRefusedError("a STOP is in progress: wait for it"))
                return
            cs.enable = True
            request.deadline = now + 0.5
            cs.pending = request
        elif kind is _Kind.DISABLE:
            cs.enable = cs.emergency = cs.reset = False
            cs.stop_phase = _StopPhase.NONE
            self._drop_execute()
            cs.after_exchange.append(request)
        elif kind is _Kind.RESET:
            if cs.inputs.busy:
                self._reject(
                    request,
                    DeviceRefusedError(
                        "Reset is ignored while Busy: wait for the move to end or stop it"
                    ),
                )
                return
            cs.reset = True
            request.count = max(2, math.ceil(0.01 / self._cycle_s))
            cs.pending = request
        elif kind is _Kind.START:
            self._begin_start(request, now)
        else:  # pragma: no cover - urgent kinds never reach the normal queue
            self._reject(request, DeviceRefusedError(f"unexpected request {kind}"))

    def _refuse_start(self, request: _Request) -> str | None:
        """Why the drive would refuse this start now (the server knows it), or None."""
        cs = self._cs
        inputs = cs.inputs
        start_type = request.start_type
        if cs.stop_phase is not _StopPhase.NONE:
            return "a STOP / emergency stop is in progress: wait until it has ended"
        if not cs.enable or not inputs.stm_status & StmStatus.READY:
            return "the drive is not enabled: press Enable first (the drive answers Error)"
        if start_type in CHANGE_START_TYPES:
            if cs.exec_state is not _Exec.RUNNING or not inputs.busy:
                return (
                    f"{start_type.name} changes a running move, but Execute is low (no move "
                    "runs): start it with a plain start type"
                )
            if cs.running in _CALIBRATION_MOVES:
                return f"{start_type.name} cannot change a calibration"
            if start_type is StartType.ADDITIVE_CHANGE and cs.running in _ENDLESS_TYPES:
                return "ADDITIVE_CHANGE needs an active target; an ENDLESS move has none"
            return None
        if cs.exec_state is not _Exec.IDLE or inputs.busy:
            return (
                "a move is running (Busy): wait for it to end, Halt it, or change it with a "
                "_CHANGE start type"
            )
        if start_type in MODULO_START_TYPES:
            modulo = self._coe.get(codec.MODULO_FACTOR, 0)
            if modulo <= 0:
                return "the modulo factor (0x8020:0E) is 0: set 'Modulo factor' first"
            if request.target < 0:
                return (
                    f"modulo targets are 0 or more (each whole {modulo} adds a turn); got "
                    f"{request.target}"
                )
            short = start_type in (StartType.MODULO_SHORT, StartType.MODULO_SHORT_EXT)
            if short and request.target >= modulo:
                return (
                    f"{start_type.name} needs a target in 0..{modulo - 1} (modulo factor "
                    f"{modulo}); got {request.target}"
                )
        return None

    def _begin_start(self, request: _Request, now: float) -> None:
        cs = self._cs
        reason = self._refuse_start(request)
        if reason is not None:
            self._reject(request, DeviceRefusedError(reason))
            return
        cs.target = request.target
        cs.velocity_bp = request.velocity_bp
        cs.start_type = int(request.start_type)
        cs.acceleration_ms = request.acceleration_ms
        cs.deceleration_ms = request.deceleration_ms
        request.previous_target = cs.target_estimate
        cs.target_estimate = self._estimate_target(request.start_type, request.target)
        request.diag_before = cs.diag
        cs.pending = request
        if request.start_type in CHANGE_START_TYPES:
            request.deadline = now + max(10 * self._cycle_s, 0.025)
            request.stage = 1  # a change: Execute stays high
            return
        cs.exec_state = _Exec.ARMING
        cs.running = request.start_type

    def _estimate_target(self, start_type: StartType, operand: int) -> float | None:
        cs = self._cs
        actual = cs.inputs.actual_position_counts
        if start_type in (StartType.ABSOLUTE, StartType.ABSOLUTE_CHANGE):
            return float(operand)
        if start_type in (StartType.RELATIVE, StartType.RELATIVE_CHANGE):
            return float(actual + operand)
        if start_type is StartType.ADDITIVE:
            base = cs.last_target if cs.last_target is not None else actual
            return base + operand
        if start_type is StartType.ADDITIVE_CHANGE:
            base = cs.target_estimate if cs.target_estimate is not None else actual
            return base + operand
        if start_type in MODULO_START_TYPES:
            try:
                travel, _ = modulo_travel(
                    start_type,
                    actual,
                    operand,
                    self._coe.get(codec.MODULO_FACTOR, 0),
                    self._coe.get(codec.MODULO_TOLERANCE_WINDOW, 0),
                    cs.last_direction,
                )
            except ModuloError:
                return None
            return float(actual + travel)
        return None  # ENDLESS, calibration: no target

    def _before_exchange(self, now: float) -> None:
        cs = self._cs
        if cs.exec_state is _Exec.ARMING:
            cs.execute = True
            cs.exec_state = _Exec.WAIT_BUSY
            cs.move_started_t = now
            if cs.pending is not None:
                cs.pending.deadline = now + max(10 * self._cycle_s, 0.025)
        pending = cs.pending
        if pending is not None and pending.kind is _Kind.RESET and pending.stage == 0:
            pending.count -= 1
            if pending.count < 0:
                cs.reset = False
                pending.stage = 1
                pending.count = 3

    # --- evaluation after an exchange ---------------------------------------------------

    def _update_diag(
        self, slave: EthercatSlave, previous: Inputs, inputs: Inputs, now: float
    ) -> None:
        cs = self._cs
        if not inputs.warning:
            cs.diag = PosDiag.NONE
            return
        pending = cs.pending
        watching_change = pending is not None and pending.stage == 1
        rose = not previous.warning or (inputs.error and not previous.error)
        if rose or watching_change or now - cs.diag_t > 0.1:
            try:
                cs.diag = PosDiag(self._read_coe(slave, codec.POS_STATUS_WORD) & 0x7)
                cs.diag_t = now
            except (EthercatError, CodecError):
                self._errors += 1

    def _advance_stop(self, inputs: Inputs, now: float) -> None:
        cs = self._cs
        if cs.stop_phase is _StopPhase.NONE:
            return
        cs.stop_cycles += 1
        standstill = not inputs.busy and inputs.actual_velocity_bp == 0
        if cs.stop_cycles < 3 or not (standstill or now > cs.stop_deadline):
            return
        cs.emergency = False
        position = inputs.actual_position_counts
        if cs.stop_phase is _StopPhase.STOPPING:
            cs.enable = False
            self._post_event("warning", f"STOP: stopped at {position} counts, Enable off")
        else:
            self._post_event(
                "warning", f"Emergency stop: stopped at {position} counts, Enable kept"
            )
        cs.stop_phase = _StopPhase.NONE

    def _advance_exec(self, inputs: Inputs, now: float) -> None:
        """Execute: held while the move runs, dropped once Busy has risen and fallen."""
        cs = self._cs
        if cs.exec_state in (_Exec.RUNNING, _Exec.HALTING) and not inputs.busy:
            pending = cs.pending
            if pending is not None and pending.kind is _Kind.START and pending.stage == 1:
                return  # a change is being watched: _advance_pending ends it first
            halted = cs.exec_state is _Exec.HALTING
            cs.execute = False
            cs.exec_state = _Exec.IDLE
            self._finish_move(inputs, now, halted=halted)

    def _finish_move(self, inputs: Inputs, now: float, *, halted: bool) -> None:
        cs = self._cs
        running = cs.running
        cs.running = None
        if running is None:
            return
        if running in _ENDLESS_TYPES or running in _CALIBRATION_MOVES:
            cs.last_target = float(inputs.actual_position_counts)
        elif cs.target_estimate is not None:
            cs.last_target = cs.target_estimate
            if cs.target_estimate != inputs.actual_position_counts:
                cs.last_direction = 1 if cs.target_estimate > inputs.actual_position_counts else -1
        seconds = now - cs.move_started_t
        where = f"at {inputs.actual_position_counts} counts after {seconds:.2f} s"
        ok, text = self._end_outcome(running, inputs)
        if halted:
            level: EventLevel = "info" if running in _ENDLESS_TYPES else "warning"
            text = f"{running.name} halted {where}" + ("" if ok else f": {text}")
        elif ok:
            level = "info"
            text = f"{running.name} ended {where}: {text}"
        else:
            level = "error" if inputs.error else "warning"
            text = f"{running.name} ended {where}: {text}"
        self._post_event(level, text)

    def _end_outcome(self, start_type: StartType, inputs: Inputs) -> tuple[bool, str]:
        cs = self._cs
        if inputs.error:
            detail = diag_text(cs.diag) if cs.diag else self._error_hint(start_type)
            return False, f"the drive answered Error: {detail}"
        calibrated = bool(inputs.pos_status & codec.PosStatus.CALIBRATED)
        if start_type in (StartType.SET_CALIBRATION, *_CALIBRATION_MOVES):
            if calibrated:
                return True, "Calibrated"
            return False, "Calibrated is not set: " + (
                diag_text(cs.diag) if cs.diag else "calibration did not complete"
            )
        if start_type is StartType.CLEAR_CALIBRATION:
            return (not calibrated), ("Calibrated cleared" if not calibrated else "still set")
        if start_type in _ENDLESS_TYPES:
            return True, "stopped"
        if inputs.in_target:
            return True, "In-Target" + (f" (Warning: {diag_text(cs.diag)})" if cs.diag else "")
        if cs.diag & PosDiag.COMMAND_REJECTED:
            return False, f"the drive set Warning: {diag_text(cs.diag)}"
        if cs.diag:
            return False, diag_text(cs.diag)
        return False, (
            "not In-Target: the motor was not in the target window within the In-Target timeout"
        )

    def _error_hint(self, start_type: StartType) -> str:
        if start_type in MODULO_START_TYPES:
            return "modulo factor or modulo target out of range"
        state = self._cs.drive_state
        named = f" (last drive state {_state_label(state)})" if state is not None else ""
        return f"no diagnosis bit set{named}"

    def _advance_pending(self, inputs: Inputs, now: float) -> None:
        cs = self._cs
        request = cs.pending
        if request is None:
            return
        if request.kind is _Kind.ENABLE:
            if inputs.stm_status & StmStatus.READY:
                cs.pending = None
                self._resolve(request, "enabled")
            elif now > request.deadline:
                cs.pending = None
                cs.enable = False
                self._reject(
                    request,
                    DeviceRefusedError(
                        "the drive did not report STM Ready within 0.5 s after Enable: check "
                        "the motor supply and STM error; Enable dropped again"
                    ),
                )
        elif request.kind is _Kind.RESET:
            if request.stage == 1:
                request.count -= 1
                if request.count <= 0:
                    cs.pending = None
                    still = [
                        name
                        for name, flag in (
                            ("Error", inputs.error),
                            ("Warning", inputs.warning),
                            ("STM error", bool(inputs.stm_status & StmStatus.ERROR)),
                        )
                        if flag
                    ]
                    if still:
                        self._reject(
                            request,
                            DeviceRefusedError(
                                f"{' and '.join(still)} still set after Reset: {diag_text(cs.diag)}"
                            ),
                        )
                    else:
                        cs.diag = PosDiag.NONE
                        self._resolve(request, "cleared")
        elif request.kind is _Kind.START:
            if request.stage == 1:
                self._watch_change(request, inputs, now)
            else:
                self._watch_start(request, inputs, now)

    def _watch_start(self, request: _Request, inputs: Inputs, now: float) -> None:
        """WAIT_BUSY: the drive has taken the move once Busy is seen twice without Error."""
        cs = self._cs
        if cs.exec_state is _Exec.ARMING:
            return
        if inputs.busy:
            request.saw_busy = True
            request.count += 1
            if request.count >= 2 and not inputs.error:
                cs.exec_state = _Exec.RUNNING
                cs.pending = None
                self._resolve(request, f"{request.start_type.name} started")
            return
        if not request.saw_busy and now <= request.deadline:
            return
        # Busy rose and fell already, or never showed: the command is over.
        cs.pending = None
        cs.execute = False
        cs.exec_state = _Exec.IDLE
        ok, text = self._end_outcome(request.start_type, inputs)
        cs.running = None
        if not ok:
            cs.target_estimate = request.previous_target
            self._reject(request, DeviceRefusedError(f"{request.start_type.name}: {text}"))
        else:
            self._resolve(request, f"{request.start_type.name} done: {text}")

    def _watch_change(self, request: _Request, inputs: Inputs, now: float) -> None:
        cs = self._cs
        new = cs.diag & ~request.diag_before
        if new & PosDiag.COMMAND_REJECTED:
            cs.pending = None
            cs.target_estimate = request.previous_target
            self._reject(
                request,
                DeviceRefusedError(
                    f"{request.start_type.name}: the drive rejected the change: "
                    f"{diag_text(PosDiag.COMMAND_REJECTED)}"
                ),
            )
        elif not inputs.busy or now > request.deadline:
            cs.pending = None
            note = f"; {diag_text(PosDiag.TARGET_OVERRUN)}" if new & PosDiag.TARGET_OVERRUN else ""
            self._resolve(request, f"{request.start_type.name} taken{note}")

    # --- SDO slot and sample ------------------------------------------------------------

    def _sdo_slot(self, slave: EthercatSlave, now: float) -> int | None:
        """Run the user's SDO transfer, else sample the drive state when it is due."""
        cs = self._cs
        job = cs.sdo_job
        if job is not None:
            cs.sdo_job = None
            self._run_sdo(slave, job)
            return None
        if now < cs.next_state_poll:
            return None
        cs.next_state_poll = now + self._state_poll_s
        try:
            cs.drive_state = self._read_coe(slave, codec.DRIVE_STATE)
        except (EthercatError, CodecError):
            self._errors += 1
            return None
        return cs.drive_state

    def _run_sdo(self, slave: EthercatSlave, job: _Request) -> None:
        obj = job.obj
        assert obj is not None
        where = f"0x{obj.index:04X}:{obj.subindex:02X} {obj.name}"
        try:
            if job.kind is _Kind.SDO_READ:
                self._resolve(job, self._read_coe(slave, obj))
            else:
                data = codec.encode_sdo(obj, job.value)
                slave.sdo_write(obj.index, obj.subindex, data)
                self._coe[obj] = job.value
                self._stored[obj] = job.value
                self._resolve(job, None)
        except EthercatSdoError as exc:
            self._errors += 1
            self._reject(job, DeviceRefusedError(f"{where}: the drive refused it: {exc}"))
        except EthercatMailboxError as exc:
            self._errors += 1
            self._reject(job, DeviceTimeoutError(f"{where}: no answer: {exc}"))
        except CodecError as exc:
            self._errors += 1
            self._reject(job, ProtocolError(f"{where}: {exc}"))

    def _emit(self, inputs: Inputs, now: float, drive_state: int | None) -> None:
        cs = self._cs
        velocity = inputs.actual_velocity_bp * self._speed_range / codec.SPEED_RANGE_FULL_SCALE_BP
        channels: dict[str, float | None] = {
            "position": float(inputs.actual_position_counts),
            "target": cs.target_estimate,
            "velocity": velocity,
            "drive_time": float(inputs.actual_drive_time_ms),
            "drive_state": float(drive_state) if drive_state is not None else None,
        }
        pos, stm, diag = int(inputs.pos_status), int(inputs.stm_status), int(cs.diag)
        flags = {name: pos & bit != 0 for name, bit in _POS_BITS}
        for name, bit in _STM_BITS:
            flags[name] = stm & bit != 0
        for name, bit in _DIAG_BITS:
            flags[name] = diag & bit != 0
        flags["enable_out"] = cs.enable
        flags["execute_out"] = cs.execute
        flags["emergency_stop_out"] = cs.emergency
        self._post_sample(Sample(now, channels, flags))

    # --- shutdown -------------------------------------------------------------------------

    def _shutdown(self, master: EthercatMaster, slave: EthercatSlave) -> None:
        """Server stops: ramp a moving axis down, Enable off, slave to INIT."""
        cs = self._cs
        self._fail_all(LinkDownError(f"link {self.id} is shutting down"))
        with contextlib.suppress(Exception):
            if cs.enable and (cs.inputs.busy or cs.inputs.actual_velocity_bp):
                cs.execute = False
                cs.emergency = True
                end = time.monotonic() + 1.0
                while time.monotonic() < end:
                    if self._exchange(master, slave):
                        cs.inputs = codec.decode_inputs(slave.input)
                        if not cs.inputs.busy and cs.inputs.actual_velocity_bp == 0:
                            break
                    time.sleep(self._cycle_s)
            self._cs = _CycleState()
            for _ in range(2):
                self._exchange(master, slave)
                time.sleep(self._cycle_s)
            master.state = INIT_STATE
            master.write_state()


def _state_label(state: int) -> str:
    try:
        return f"{DriveState(state).name} (0x{state:04X})"
    except ValueError:
        return f"0x{state:04X}"


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
            await self.stop()
            return CommandOutcome(
                ["Emergency stop", "Execute off", "Enable off at standstill"], "STOP sent"
            )
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
            await self._link.sdo_write(obj, value)
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

    async def stop(self) -> None:
        link = self._link
        await link.submit(link.new_request(_Kind.STOP))

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
) -> Ep7047Link:
    """An EP7047-1032 link on ``ifname`` (slave position ``slave``, from 1).

    ``master`` None uses the real pysoem master (created when the link runs, so a missing
    pysoem shows as the link's error state, not as a crash). ``settings``, when given, are
    written over CoE at every bring-up; otherwise the drive's own values are read.
    ``watchdog_s`` is the slave's SyncManager watchdog time (the device default, 100 ms):
    a longer gap in the process data makes the driver drop Enable.
    """
    factory: Callable[[], EthercatMaster]
    if master is None:
        factory = PysoemMaster
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
