"""A SIMULATED EtherCAT master with simulated EP7047-1032 slaves behind it (a fake).

``SimulatedEthercatMaster`` implements the driver's library seam
(``servotune.transports.ethercat.EthercatMaster``, pysoem's names) without a network: it is
the test fake of the EP7047 driver and what the demo runs in-process. Nothing here
touches a NIC or raw sockets.

Each ``SimulatedEp7047Slave`` has:

* identity (vendor 0x2, product 0x1B874052, a revision) from its "SII", changeable with
  ``set_identity`` for mismatch tests;
* a CoE object dictionary: the SDO table of ``servotune.devices.ep7047.codec`` backed by the
  engine's settings and diagnosis, 0x1018 identity, 0x8012:05 speed range (read only
  here), and the PDO assignment 0x1C12/0x1C13 - writable in PRE-OP only, sub 0 first
  set to 0, only PDOs the slave has, in the right direction (else the SDO aborts a real
  slave would give);
* the EtherCAT state machine INIT / PRE-OP / SAFE-OP / OP with its rules: SAFE-OP needs
  a mapped process image, OP needs valid outputs received in SAFE-OP; a refused
  transition sets the error indication and an AL status code, which only an
  acknowledge (state | 0x10) clears;
* the positioning engine (``Ep7047Engine`` + ``StepperPlant``: an encoder counter, a cam
  on digital input 1, a C-track pulse), stepped by the number of 250 us cycles that
  elapsed between two exchanges - deterministic given the clock, which can be injected.
  The outputs of an exchange take effect from that exchange on; the inputs it returns
  are those of the last cycle before it (one exchange of latency, as on the wire);
* the SyncManager watchdog: when no process data arrives for more than ``watchdog_s``
  (100 ms) the slave runs on with all-zero outputs (Enable off: a moving motor coasts
  to a stop on its load's inertia); the AL state stays OP, like a Beckhoff terminal. More than 1 s
  without an exchange is skipped rather than computed (the watchdog has long stopped
  the motor by then).

Fault injection: ``drop_out_of_op()`` (the slave falls to SAFE-OP + ERROR and refuses OP
until ``return_to_op()``), ``inject_lost_frames(n)`` (the next n frames come back with
working counter 0), ``set_identity(...)``, ``sdo_delay_s`` (a slow mailbox: every SDO
transfer takes that long). ``history`` keeps (time, outputs, inputs)
of every good exchange for tests.

The factory default PDO assignment is the velocity interface (0x1601 0x1602 0x1604 /
0x1A01 0x1A03), an assumption of the simulation: a master that does not assign the
positioning interface gets a 10/12-byte image and the driver must notice.
"""

from __future__ import annotations

import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Final

from servotune.devices.ep7047 import codec
from servotune.devices.ep7047.codec import (
    CYCLE_S,
    CodecError,
    Inputs,
    Outputs,
    PosSettings,
    SdoObject,
)
from servotune.devices.ep7047.sim.engine import Ep7047Engine
from servotune.devices.ep7047.sim.plant import DEMO_MECHANICS, DriveConfig, StepperPlant
from servotune.transports.ethercat import (
    INIT_STATE,
    OP_STATE,
    PREOP_STATE,
    SAFEOP_STATE,
    STATE_ACK,
    STATE_ERROR,
    EthercatMailboxError,
    EthercatSdoError,
    EthercatSlave,
    EthercatUnavailableError,
)

WATCHDOG_S: Final = 0.1
MAX_CATCH_UP_S: Final = 1.0
DEFAULT_REVISION: Final = 0x0010_0005
SAFE_OUTPUTS: Final = Outputs()

# PDO -> bytes, for the PDOs this simulated slave has.
PDO_SIZES: Final = {
    0x1601: 6,  # ENC control
    0x1602: 2,  # STM control
    0x1604: 2,  # STM velocity
    0x1606: 14,  # POS control
    0x1A01: 10,  # ENC status
    0x1A03: 2,  # STM status
    0x1A07: 12,  # POS status
}
DEFAULT_RX_ASSIGNMENT: Final = (0x1601, 0x1602, 0x1604)
DEFAULT_TX_ASSIGNMENT: Final = (0x1A01, 0x1A03)
MAX_ASSIGNED: Final = 4

# SDO abort codes the simulation gives.
ABORT_NO_OBJECT: Final = 0x0602_0000
ABORT_READ_ONLY: Final = 0x0601_0002
ABORT_LENGTH: Final = 0x0607_0010
ABORT_VALUE_RANGE: Final = 0x0609_0030
ABORT_STATE: Final = 0x0800_0022

AL_INVALID_STATE_CHANGE: Final = 0x0011
AL_SYNC_ERROR: Final = 0x001A
AL_WATCHDOG: Final = 0x001B
AL_INVALID_OUTPUTS: Final = 0x001D

_OBJECTS: Final = {(o.index, o.subindex): o for o in codec.SDO_OBJECTS}
_READ_ONLY_HERE: Final = frozenset({codec.TIME_INFORMATION, codec.SPEED_RANGE})


@dataclass(frozen=True, slots=True)
class Exchange:
    """One good process-data exchange as the simulated slave saw it."""

    t: float
    outputs: Outputs
    inputs: Inputs
    state: int  # AL state at the exchange


class SimulatedEp7047Slave:
    """One SIMULATED EP7047-1032 (implements the driver's ``EthercatSlave``)."""

    def __init__(
        self,
        engine: Ep7047Engine | None = None,
        *,
        speed_range_code: int = 1,
        revision: int = DEFAULT_REVISION,
        name: str = "EP7047-1032",
        watchdog_s: float = WATCHDOG_S,
    ) -> None:
        self.engine = engine if engine is not None else Ep7047Engine()
        self.watchdog_s = watchdog_s
        self.sdo_delay_s = 0.0  # simulated mailbox latency of every SDO transfer
        self.speed_range_code = speed_range_code
        self._man = codec.VENDOR_ID
        self._id = codec.PRODUCT_CODE
        self._rev = revision
        self._name = name
        self._lock = threading.RLock()
        self._al_state = INIT_STATE
        self._al_error = False
        self._al_status = 0
        self._state_field = INIT_STATE  # pysoem's slave.state: last read, or to request
        self._fault = False
        self._assign: dict[int, list[int]] = {
            0x1C12: list(DEFAULT_RX_ASSIGNMENT),
            0x1C13: list(DEFAULT_TX_ASSIGNMENT),
        }
        self._staged: dict[int, dict[int, int]] = {}
        self._mapped: tuple[int, int] | None = None
        self._out_buf = b""
        self._in_buf = b""
        self._sent: bytes | None = None
        self._lost = False
        self._frames_in_safeop = 0
        self._latched = SAFE_OUTPUTS
        self._latched_bytes: bytes | None = None  # what _latched was decoded from
        # Fixed from config_map to the next unmap (the assignment is writable in PRE-OP
        # only, and leaving SAFE-OP/OP for PRE-OP unmaps): read every exchange.
        self._positioning = False
        self._encoded: Inputs | None = None  # the Inputs that _in_buf was encoded from
        self._t0: float | None = None
        self._cycle_no = 0
        self._wd_cycle = 0  # the watchdog expires after this cycle
        self._last_inputs = Inputs()
        self.watchdog_tripped = False
        # Bounded like ``history``: the demo reads the drive state 100 times a second,
        # and an unbounded log grew by ~8 million entries a day.
        self.sdo_log: deque[tuple[int, str, int, int, int]] = deque(maxlen=100_000)
        self.history: deque[Exchange] = deque(maxlen=100_000)

    # --- identity (SII) -------------------------------------------------------------------

    @property
    def man(self) -> int:
        return self._man

    @property
    def id(self) -> int:
        return self._id

    @property
    def rev(self) -> int:
        return self._rev

    @property
    def name(self) -> str:
        return self._name

    def set_identity(
        self,
        *,
        vendor: int | None = None,
        product: int | None = None,
        revision: int | None = None,
        name: str | None = None,
    ) -> None:
        """Pretend to be another device (for identity-mismatch tests)."""
        with self._lock:
            if vendor is not None:
                self._man = vendor
            if product is not None:
                self._id = product
            if revision is not None:
                self._rev = revision
            if name is not None:
                self._name = name

    # --- state machine --------------------------------------------------------------------

    @property
    def al_state(self) -> int:
        """The actual AL state with the error bit (what a state read returns)."""
        with self._lock:
            return self._al_state | (STATE_ERROR if self._al_error else 0)

    @property
    def state(self) -> int:
        return self._state_field

    @state.setter
    def state(self, value: int) -> None:
        self._state_field = value

    @property
    def al_status(self) -> int:
        return self._al_status

    def refresh_state(self) -> int:
        self._state_field = self.al_state
        return self._state_field

    def write_state(self) -> int:
        self.request_state(self._state_field)
        return 1

    def state_check(self, expected_state: int, timeout: int = 2000) -> int:
        # Transitions are immediate here: nothing to wait for.
        return self.refresh_state()

    def request_state(self, value: int) -> None:
        """An AL control write: the requested state, optionally with the acknowledge bit."""
        with self._lock:
            target = value & 0x0F
            if value & STATE_ACK:
                self._al_error = False
                self._al_status = 0
            elif self._al_error and target > self._al_state:
                return  # the error indication must be acknowledged first
            if target == INIT_STATE:
                self._al_state = INIT_STATE
                self._unmap()
            elif target == PREOP_STATE:
                if self._al_state == INIT_STATE or self._al_state > PREOP_STATE:
                    self._unmap()
                self._al_state = PREOP_STATE
            elif target == SAFEOP_STATE:
                if self._al_state == OP_STATE:
                    self._al_state = SAFEOP_STATE
                elif self._al_state == PREOP_STATE:
                    if self._mapped is None:
                        self._refuse(AL_INVALID_OUTPUTS)
                    else:
                        self._al_state = SAFEOP_STATE
                        self._frames_in_safeop = 0
                elif self._al_state != SAFEOP_STATE:
                    self._refuse(AL_INVALID_STATE_CHANGE)
            elif target == OP_STATE:
                if self._al_state == SAFEOP_STATE:
                    if self._fault:
                        self._refuse(AL_SYNC_ERROR)
                    elif self._frames_in_safeop == 0:
                        self._refuse(AL_WATCHDOG)  # no valid outputs yet
                    else:
                        self._al_state = OP_STATE
                elif self._al_state != OP_STATE:
                    self._refuse(AL_INVALID_STATE_CHANGE)

    def _refuse(self, code: int) -> None:
        self._al_error = True
        self._al_status = code

    def _unmap(self) -> None:
        self._mapped = None
        self._positioning = False
        self._encoded = None
        self._out_buf = self._in_buf = b""
        self._latched = SAFE_OUTPUTS
        self._latched_bytes = None

    # --- faults ---------------------------------------------------------------------------

    def drop_out_of_op(self, al_status: int = AL_SYNC_ERROR) -> None:
        """Fall to SAFE-OP + ERROR (outputs safe) and refuse OP until ``return_to_op``."""
        with self._lock:
            self._fault = True
            if self._al_state == OP_STATE:
                self._al_state = SAFEOP_STATE
            self._al_error = True
            self._al_status = al_status
            self._latched = SAFE_OUTPUTS
            self._latched_bytes = None

    def return_to_op(self) -> None:
        """The fault is gone: OP is accepted again (a master brings the slave back to OP;
        a slave still in SAFE-OP + ERROR from the drop returns to OP at once)."""
        with self._lock:
            self._fault = False
            if self._al_state == SAFEOP_STATE and self._al_status == AL_SYNC_ERROR:
                self._al_error = False
                self._al_status = 0
                self._al_state = OP_STATE

    def inject_lost_frame(self) -> None:
        with self._lock:
            self._lost = True

    # --- mailbox (CoE) --------------------------------------------------------------------

    def _abort(self, index: int, subindex: int, code: int, desc: str) -> EthercatSdoError:
        return EthercatSdoError(index, subindex, code, desc)

    def sdo_read(self, index: int, subindex: int, size: int = 0) -> bytes:
        if self.sdo_delay_s > 0:
            time.sleep(self.sdo_delay_s)
        with self._lock:
            if self._al_state == INIT_STATE:
                raise EthercatMailboxError("no mailbox in INIT")
            if index in self._assign:
                entries = self._assign[index]
                if subindex == 0:
                    data = bytes([len(entries)])
                elif 1 <= subindex <= MAX_ASSIGNED:
                    if entries:
                        pdo = entries[subindex - 1] if subindex <= len(entries) else 0
                    else:
                        pdo = self._staged.get(index, {}).get(subindex, 0)
                    data = struct.pack("<H", pdo)
                else:
                    raise self._abort(index, subindex, 0x0609_0011, "subindex does not exist")
            else:
                obj = _OBJECTS.get((index, subindex))
                if obj is None:
                    raise self._abort(index, subindex, ABORT_NO_OBJECT, "object does not exist")
                data = codec.encode_sdo(obj, self._value(obj))
            self.sdo_log.append((self._al_state, "read", index, subindex, _as_int(data)))
            return data

    def _value(self, obj: SdoObject) -> int:
        if obj == codec.IDENTITY_VENDOR_ID:
            return self._man
        if obj == codec.IDENTITY_PRODUCT_CODE:
            return self._id
        if obj == codec.IDENTITY_REVISION:
            return self._rev
        if obj == codec.SPEED_RANGE:
            return self.speed_range_code
        return self.engine.read_sdo(obj)

    def sdo_write(self, index: int, subindex: int, data: bytes) -> None:
        if self.sdo_delay_s > 0:
            time.sleep(self.sdo_delay_s)
        with self._lock:
            if self._al_state == INIT_STATE:
                raise EthercatMailboxError("no mailbox in INIT")
            self.sdo_log.append((self._al_state, "write", index, subindex, _as_int(data)))
            if index in self._assign:
                self._write_assignment(index, subindex, data)
                return
            obj = _OBJECTS.get((index, subindex))
            if obj is None:
                raise self._abort(index, subindex, ABORT_NO_OBJECT, "object does not exist")
            if not obj.writable or obj in _READ_ONLY_HERE:
                raise self._abort(index, subindex, ABORT_READ_ONLY, "read only object")
            if len(data) != obj.data_type.size:
                raise self._abort(index, subindex, ABORT_LENGTH, "length does not match")
            try:
                value = codec.decode_sdo(obj, data)
            except CodecError:
                raise self._abort(
                    index, subindex, ABORT_VALUE_RANGE, "value range exceeded"
                ) from None
            self.engine.write_sdo(obj, value)

    def _write_assignment(self, index: int, subindex: int, data: bytes) -> None:
        """CiA 301: sub 0 := 0, then the entries, then sub 0 := their number."""
        if self._al_state != PREOP_STATE:
            raise self._abort(index, subindex, ABORT_STATE, "PDO assignment only in PRE-OP")
        entries = self._assign[index]
        staged = self._staged.setdefault(index, {})
        if subindex == 0:
            if len(data) != 1:
                raise self._abort(index, subindex, ABORT_LENGTH, "sub 0 is one byte")
            count = data[0]
            if count == 0:
                entries.clear()
                staged.clear()
                return
            if entries:
                raise self._abort(index, subindex, ABORT_STATE, "set sub 0 to 0 first")
            if count > MAX_ASSIGNED or any(i not in staged for i in range(1, count + 1)):
                raise self._abort(index, subindex, ABORT_VALUE_RANGE, "entries not written")
            entries[:] = [staged[i] for i in range(1, count + 1)]
            return
        if not 1 <= subindex <= MAX_ASSIGNED:
            raise self._abort(index, subindex, 0x0609_0011, "subindex does not exist")
        if len(data) != 2:
            raise self._abort(index, subindex, ABORT_LENGTH, "entries are UINT16")
        if entries:
            raise self._abort(index, subindex, ABORT_STATE, "set sub 0 to 0 first")
        pdo = struct.unpack("<H", data)[0]
        direction = 0x1600 if index == 0x1C12 else 0x1A00
        if pdo not in PDO_SIZES or pdo & 0xFF00 != direction:
            raise self._abort(index, subindex, ABORT_VALUE_RANGE, f"no PDO 0x{pdo:04X} here")
        staged[subindex] = pdo

    # --- process data ---------------------------------------------------------------------

    @property
    def output(self) -> bytes:
        return self._out_buf

    @output.setter
    def output(self, value: bytes) -> None:
        with self._lock:
            if self._mapped is None:
                raise ValueError("the process data is not mapped (config_map)")
            if len(value) != self._mapped[0]:
                raise ValueError(f"outputs are {self._mapped[0]} bytes, got {len(value)}")
            self._out_buf = bytes(value)

    @property
    def input(self) -> bytes:
        return self._in_buf

    @property
    def positioning_interface(self) -> bool:
        """True when the PDO assignment is the full "Positioning interface"."""
        return (
            tuple(self._assign[0x1C12]) == codec.RXPDO_ASSIGNMENT
            and tuple(self._assign[0x1C13]) == codec.TXPDO_ASSIGNMENT
        )

    def map(self) -> tuple[int, int]:
        """config_map: size the process image from the assignment, then go to SAFE-OP."""
        with self._lock:
            if self._al_state != PREOP_STATE:
                return (0, 0)
            sizes = (
                sum(PDO_SIZES[p] for p in self._assign[0x1C12]),
                sum(PDO_SIZES[p] for p in self._assign[0x1C13]),
            )
            self._mapped = sizes
            self._positioning = self.positioning_interface
            self._encoded = None
            self._out_buf = bytes(sizes[0])
            self._in_buf = bytes(sizes[1])
            self.request_state(SAFEOP_STATE)
            return sizes

    def send(self) -> None:
        with self._lock:
            self._sent = self._out_buf if self._mapped is not None else None

    def receive(self, now: float) -> int:
        """Process the frame sent last; returns this slave's working-counter share."""
        with self._lock:
            self.advance(now)
            sent, self._sent = self._sent, None
            lost, self._lost = self._lost, False
            if sent is None or lost or self._al_state < SAFEOP_STATE:
                return 0
            inputs = self._last_inputs
            if self._positioning and inputs is not self._encoded:
                self._in_buf = codec.encode_inputs(inputs)
                self._encoded = inputs
            if self._al_state == SAFEOP_STATE:
                self._frames_in_safeop += 1
                return 1  # inputs only: the outputs are not taken in SAFE-OP
            if self._positioning and sent != self._latched_bytes:
                # Unchanged outputs keep the same object: decoding is skipped and the
                # engine sees "same outputs as the cycle before" at a glance.
                self._latched = codec.decode_outputs(sent)
                self._latched_bytes = sent
            self._wd_cycle = self._cycle_no + round(self.watchdog_s / CYCLE_S)
            self.watchdog_tripped = False
            self.history.append(Exchange(now, self._latched, self._last_inputs, self._al_state))
            return 3

    def advance(self, now: float) -> None:
        """Step the engine through every 250 us cycle up to ``now``.

        The cycles run in at most two stretches of constant outputs - the latched ones
        up to the watchdog's expiry, all-zero after it - through ``Ep7047Engine.run``,
        which skips quiet stretches in one go (same result as cycle by cycle).
        """
        with self._lock:
            if self._t0 is None:
                self._t0 = now
            target = int((now - self._t0) / CYCLE_S)
            count = min(target - self._cycle_no, round(MAX_CATCH_UP_S / CYCLE_S))
            if count > 0:
                first = self._cycle_no + 1  # the first cycle to run
                latched = 0
                if self._al_state == OP_STATE:
                    latched = max(0, min(count, self._wd_cycle - first + 1))
                    if latched < count:
                        self.watchdog_tripped = True
                if latched:
                    self._last_inputs = self.engine.run(self._latched, latched)
                if count > latched:
                    self._last_inputs = self.engine.run(SAFE_OUTPUTS, count - latched)
                self._cycle_no += count
            self._cycle_no = max(self._cycle_no, target)  # time beyond the catch-up is skipped

    def reset_to_preop(self) -> None:
        """config_init: INIT (acknowledged) then PRE-OP; the PDO assignment is kept."""
        with self._lock:
            self.request_state(INIT_STATE | STATE_ACK)
            self.request_state(PREOP_STATE)
            self._state_field = self.al_state


def _as_int(data: bytes) -> int:
    return int.from_bytes(data, "little")


class SimulatedEthercatMaster:
    """A SIMULATED EtherCAT master (the driver's ``EthercatMaster``) over simulated slaves.

    ``clock`` is the simulation's time source (seconds, monotonic); the slaves' engines
    advance by the 250 us cycles elapsed on it between exchanges.
    """

    def __init__(
        self,
        slaves: Sequence[SimulatedEp7047Slave] | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._all = list(slaves) if slaves is not None else [SimulatedEp7047Slave()]
        self._lost_frames = 0
        self._clock = clock
        self._open = False
        self._found: list[SimulatedEp7047Slave] = []
        self._state_field = INIT_STATE
        self.ifname: str | None = None
        self.open_error: str | None = None
        self.opened = 0

    # --- EthercatMaster -------------------------------------------------------------------

    def open(self, ifname: str) -> None:
        if self.open_error is not None:
            raise EthercatUnavailableError(self.open_error)
        self.ifname = ifname
        self._open = True
        self.opened += 1

    def _require_open(self) -> None:
        if not self._open:
            raise EthercatMailboxError("the simulated master is not open")

    def config_init(self) -> int:
        self._require_open()
        self._found = list(self._all)
        for slave in self._found:
            slave.reset_to_preop()
        return len(self._found)

    @property
    def slaves(self) -> Sequence[EthercatSlave]:
        return self._found

    def config_map(self) -> int:
        self._require_open()
        return sum(sum(slave.map()) for slave in self._found)

    def send_processdata(self) -> int:
        self._require_open()
        lose = self._lost_frames > 0
        if lose:
            self._lost_frames -= 1
        for slave in self._found:
            slave.send()
            if lose:
                slave.inject_lost_frame()
        return 1 if self._found else 0

    def receive_processdata(self, timeout: int = 2000) -> int:
        self._require_open()
        now = self._clock()
        return sum(slave.receive(now) for slave in self._found)

    def read_state(self) -> int:
        self._require_open()
        states = [slave.refresh_state() for slave in self._found]
        self._state_field = _lowest(states)
        return self._state_field

    def write_state(self) -> int:
        self._require_open()
        for slave in self._found:
            slave.request_state(self._state_field)
        return len(self._found)

    def state_check(self, expected_state: int, timeout: int = 50000) -> int:
        return self.read_state()

    @property
    def state(self) -> int:
        return self._state_field

    @state.setter
    def state(self, value: int) -> None:
        self._state_field = value

    @property
    def expected_wkc(self) -> int:
        return 3 * len(self._found)

    def close(self) -> None:
        self._open = False

    # --- simulation controls --------------------------------------------------------------

    def slave(self, position: int = 1) -> SimulatedEp7047Slave:
        """The simulated slave at bus position ``position`` (from 1)."""
        return self._all[position - 1]

    def drop_out_of_op(self, position: int = 1, al_status: int = AL_SYNC_ERROR) -> None:
        self.slave(position).drop_out_of_op(al_status)

    def return_to_op(self, position: int = 1) -> None:
        self.slave(position).return_to_op()

    def inject_lost_frames(self, count: int) -> None:
        """The next ``count`` frames come back with working counter 0."""
        self._lost_frames = count

    def set_identity(
        self,
        position: int = 1,
        *,
        vendor: int | None = None,
        product: int | None = None,
        revision: int | None = None,
        name: str | None = None,
    ) -> None:
        self.slave(position).set_identity(
            vendor=vendor, product=product, revision=revision, name=name
        )

    @property
    def history(self) -> deque[Exchange]:
        return self.slave(1).history


def _lowest(states: Sequence[int]) -> int:
    if not states:
        return 0
    error = any(s & STATE_ERROR for s in states)
    return min(s & 0x0F for s in states) | (STATE_ERROR if error else 0)


# --- the demo axis ------------------------------------------------------------------------------

DEMO_SPEED_RANGE_STEPS_S: Final = 2000  # 0x8012:05 code 1
DEMO_FULL_STEPS_PER_REV: Final = 200
DEMO_COUNTS_PER_REV: Final = 4096  # 1024-line encoder, 4 x
DEMO_SETTINGS: Final = PosSettings(
    velocity_min_bp=50,
    velocity_max_bp=10_000,
    acceleration_pos_ms=400,
    acceleration_neg_ms=400,
    deceleration_pos_ms=400,
    deceleration_neg_ms=400,
    emergency_deceleration_ms=100,
    calibration_position_counts=0,
    calibration_velocity_towards_cam_bp=1000,
    calibration_velocity_off_cam_bp=300,
    target_window_counts=10,
    in_target_timeout_ms=500,
    modulo_factor_counts=DEMO_COUNTS_PER_REV,
    modulo_tolerance_window_counts=20,
    invert_sync_impulse_search=True,
)


def demo_slave() -> SimulatedEp7047Slave:
    """A stepper (200 steps/rev) with a 1024-line encoder, a cam a turn and a half away
    (digital input 1, 6000..6800 counts) and a C-track pulse once a turn; its rotor and
    load (``DEMO_MECHANICS``) coast when the output stage is switched off at speed, and
    the encoder counts the coast."""
    config = DriveConfig(
        speed_range_steps_s=DEMO_SPEED_RANGE_STEPS_S,
        counts_per_full_step=DEMO_COUNTS_PER_REV / DEMO_FULL_STEPS_PER_REV,
    )
    plant = StepperPlant(
        cam_counts=(6000.0, 6800.0),
        sync_period_counts=float(DEMO_COUNTS_PER_REV),
        sync_phase_counts=1024.0,
        mechanics=DEMO_MECHANICS,
    )
    speed_code = next(
        code
        for code, steps in codec.SPEED_RANGE_STEPS_S.items()
        if steps == DEMO_SPEED_RANGE_STEPS_S
    )
    return SimulatedEp7047Slave(
        Ep7047Engine(DEMO_SETTINGS, config, plant), speed_range_code=speed_code
    )


def demo_master(*, clock: Callable[[], float] = time.monotonic) -> SimulatedEthercatMaster:
    """The in-process demo: one simulated EP7047-1032 (see :func:`demo_slave`). Pass
    ``speed_range_steps_s=DEMO_SPEED_RANGE_STEPS_S`` and
    ``counts_per_rev=DEMO_COUNTS_PER_REV`` to ``build_ep7047_link``."""
    return SimulatedEthercatMaster([demo_slave()], clock=clock)
