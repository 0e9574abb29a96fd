"""EP7047-1032 "Positioning interface" codec (sans-IO): process image and CoE addresses.

Source: ``shared/spec/ep7047.md`` (normative), the German vendor manual
(``shared/seeds/004_…``) where the spec is silent. This module turns the 22 output bytes
(master -> drive) and the 24 input bytes (drive -> master) of the "Positioning
interface" PDO assignment into frozen dataclasses and back, and names every CoE object
the positioning interface uses. No I/O, no clocks: the EtherCAT driver moves the bytes,
``servotune.devices.ep7047.sim.engine`` produces them in simulation.

Units, used as name suffixes:

- ``counts``: position increments of the drive's counter (encoder or internal counter);
- ``bp``: basis points of the speed range 0x8012:05, the drive's velocity unit
  (10000 = 100 %; with a range of 4000 full steps/s, 5000 bp = 2000 full steps/s);
- ``ms`` / ``us``: milliseconds / microseconds. Accelerations are *times* in ms for a
  change of 100 % of the speed range (1000 ms: 0 -> 100 % in 1 s, 0 -> 50 % in 0.5 s).

Decision (spec silent): every 32-bit position (target, actual, counter, latch, set
counter value, calibration position) is read and written as two's complement. The
vendor's description types some of them unsigned; the bits are the same, and modulo
and relative moves reach negative positions (the manual's own table ends at -990°).
"""

from __future__ import annotations

import enum
import functools
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from typing import Final

# --- identity and PDO assignment --------------------------------------------------------

VENDOR_ID: Final = 0x0000_0002  # Beckhoff Automation
PRODUCT_CODE: Final = 0x1B87_4052  # EP7047-1032
# 0x1C12 / 0x1C13 contents for "Positioning interface" (written in PRE-OP). Other EL70x1
# terminals use other indices: never reuse these lists for them.
RXPDO_ASSIGNMENT: Final = (0x1601, 0x1602, 0x1606)
TXPDO_ASSIGNMENT: Final = (0x1A01, 0x1A03, 0x1A07)
# "Positioning interface compact": the POS PDOs without velocity/start type/ramps.
RXPDO_ASSIGNMENT_COMPACT: Final = (0x1601, 0x1602, 0x1605)
TXPDO_ASSIGNMENT_COMPACT: Final = (0x1A01, 0x1A03, 0x1A06)

OUTPUTS_SIZE: Final = 22
INPUTS_SIZE: Final = 24

SPEED_RANGE_FULL_SCALE_BP: Final = 10_000  # 100 % of the speed range
CYCLE_S: Final = 250e-6  # the positioning controller's internal cycle

# 0x8012:05 "Speed range" code -> full steps per second at 10000 bp. Taken from the
# vendor's EL70x1 documentation, not from the seed manual: verify on the device.
SPEED_RANGE_STEPS_S: Final[Mapping[int, int]] = {
    0: 1000,
    1: 2000,
    2: 4000,
    3: 8000,
    4: 16000,
    5: 32000,
}


class CodecError(ValueError):
    """Bytes of the wrong length, or a value that does not fit its process-data field."""


# --- enums ------------------------------------------------------------------------------


class StartType(enum.IntEnum):
    """0x7020:22 / 0x8021:01 "Start type": how the target position is computed."""

    ABSOLUTE = 0x0001
    RELATIVE = 0x0002
    ENDLESS_PLUS = 0x0003
    ENDLESS_MINUS = 0x0004
    ADDITIVE = 0x0006
    ABSOLUTE_CHANGE = 0x1001
    RELATIVE_CHANGE = 0x1002
    ADDITIVE_CHANGE = 0x1006
    MODULO_SHORT = 0x0105
    MODULO_SHORT_EXT = 0x0115
    MODULO_PLUS = 0x0205
    MODULO_PLUS_EXT = 0x0215
    MODULO_MINUS = 0x0305
    MODULO_MINUS_EXT = 0x0315
    MODULO_CURRENT = 0x0405
    MODULO_CURRENT_EXT = 0x0415
    CALI_PLC_CAM = 0x6000
    CALI_HW_SYNC = 0x6100
    SET_CALIBRATION = 0x6E00
    SET_CALIBRATION_AUTO = 0x6E01
    CLEAR_CALIBRATION = 0x6F00


CHANGE_START_TYPES: Final = frozenset(
    {StartType.ABSOLUTE_CHANGE, StartType.RELATIVE_CHANGE, StartType.ADDITIVE_CHANGE}
)
MODULO_START_TYPES: Final = frozenset(
    {
        StartType.MODULO_SHORT,
        StartType.MODULO_SHORT_EXT,
        StartType.MODULO_PLUS,
        StartType.MODULO_PLUS_EXT,
        StartType.MODULO_MINUS,
        StartType.MODULO_MINUS_EXT,
        StartType.MODULO_CURRENT,
        StartType.MODULO_CURRENT_EXT,
    }
)


class DriveState(enum.IntEnum):
    """0x9020:03 "State (drive controller)", with the manual's ids.

    The controller runs every 250 us; a PLC sampling at 1 ms never sees some of the
    one-cycle states, so anything that displays this value must say it is sampled.
    """

    INIT = 0x0000
    IDLE = 0x0001
    START = 0x0010
    ACCEL = 0x0011
    CONST = 0x0012
    DECEL = 0x0013
    EMCY = 0x0020
    STOP = 0x0021
    CALI_START = 0x0100
    CALI_GO_CAM = 0x0110
    CALI_ON_CAM = 0x0111
    CALI_GO_SYNC = 0x0120
    CALI_LEAVE_CAM = 0x0121
    CALI_STOP = 0x0130
    CALIBRATED = 0x0140
    NOT_CALIBRATED = 0x0141
    PRE_TARGET = 0x1000
    TARGET = 0x1001
    TARGET_RESTART = 0x1002
    END = 0x2000
    WARNING = 0x4000
    ERROR = 0x8000
    UNDEFINED = 0xFFFF


class PosDiag(enum.IntFlag):
    """0x9020:01 "Status word": mirrors 0xA020 subindex n at bit n-1.

    Any of these bits is also signalled as "Warning" (0x6020:03) in the inputs.
    """

    NONE = 0
    COMMAND_REJECTED = 1 << 0
    COMMAND_ABORTED = 1 << 1
    TARGET_OVERRUN = 1 << 2


class EncControl(enum.IntFlag):
    """Bytes 0-1 of the outputs: 0x7000:01..04 (the rest of the word is a gap)."""

    NONE = 0
    ENABLE_LATCH_C = 1 << 0
    ENABLE_LATCH_EXTERN_POSITIVE = 1 << 1
    SET_COUNTER = 1 << 2
    ENABLE_LATCH_EXTERN_NEGATIVE = 1 << 3


class StmControl(enum.IntFlag):
    """Bytes 6-7 of the outputs: 0x7010:01..03 and 0x7010:0C."""

    NONE = 0
    ENABLE = 1 << 0
    RESET = 1 << 1
    REDUCE_TORQUE = 1 << 2
    DIGITAL_OUTPUT_1 = 1 << 11


class PosControl(enum.IntFlag):
    """Bytes 8-9 of the outputs: 0x7020:01..02."""

    NONE = 0
    EXECUTE = 1 << 0
    EMERGENCY_STOP = 1 << 1


class EncStatus(enum.IntFlag):
    """Bytes 0-1 of the inputs: 0x6000:01..10.

    The spec only says "status word"; the bit names are those of the vendor's EL70x1
    device description (same ENC PDO). Verify against the device's ESI.
    """

    NONE = 0
    LATCH_C_VALID = 1 << 0
    LATCH_EXTERN_VALID = 1 << 1
    SET_COUNTER_DONE = 1 << 2
    COUNTER_UNDERFLOW = 1 << 3
    COUNTER_OVERFLOW = 1 << 4
    EXTRAPOLATION_STALL = 1 << 7
    INPUT_A = 1 << 8
    INPUT_B = 1 << 9
    INPUT_C = 1 << 10
    EXTERN_LATCH = 1 << 12
    SYNC_ERROR = 1 << 13
    TXPDO_TOGGLE = 1 << 15


class StmStatus(enum.IntFlag):
    """Bytes 10-11 of the inputs: 0x6010:01..08, :0C..:0E, :10."""

    NONE = 0
    READY_TO_ENABLE = 1 << 0
    READY = 1 << 1
    WARNING = 1 << 2
    ERROR = 1 << 3
    MOVING_POSITIVE = 1 << 4
    MOVING_NEGATIVE = 1 << 5
    TORQUE_REDUCED = 1 << 6
    MOTOR_STALL = 1 << 7
    DIGITAL_INPUT_1 = 1 << 11
    DIGITAL_INPUT_2 = 1 << 12
    SYNC_ERROR = 1 << 13
    TXPDO_TOGGLE = 1 << 15


class PosStatus(enum.IntFlag):
    """Bytes 12-13 of the inputs: 0x6020:01..08."""

    NONE = 0
    BUSY = 1 << 0
    IN_TARGET = 1 << 1
    WARNING = 1 << 2
    ERROR = 1 << 3
    CALIBRATED = 1 << 4
    ACCELERATE = 1 << 5
    DECELERATE = 1 << 6
    READY_TO_EXECUTE = 1 << 7


# The process image's flag words as enum members, memoised: ``PosStatus(value)`` runs
# the enum machinery in Python (about a microsecond per call, several per frame on the
# cycle thread and in the simulator), while a drive repeats a handful of values. The
# words are 16 bits, so a cache holds at most 65536 members per type. Same members as
# the plain call (tests compare every value).
_FLAG_CACHE_SIZE: Final = 1 << 16
enc_control_of: Final[Callable[[int], EncControl]] = functools.lru_cache(_FLAG_CACHE_SIZE)(
    EncControl
)
stm_control_of: Final[Callable[[int], StmControl]] = functools.lru_cache(_FLAG_CACHE_SIZE)(
    StmControl
)
pos_control_of: Final[Callable[[int], PosControl]] = functools.lru_cache(_FLAG_CACHE_SIZE)(
    PosControl
)
enc_status_of: Final[Callable[[int], EncStatus]] = functools.lru_cache(_FLAG_CACHE_SIZE)(EncStatus)
stm_status_of: Final[Callable[[int], StmStatus]] = functools.lru_cache(_FLAG_CACHE_SIZE)(StmStatus)
pos_status_of: Final[Callable[[int], PosStatus]] = functools.lru_cache(_FLAG_CACHE_SIZE)(PosStatus)

# Plain ints for the bit tests of the hot properties: an IntFlag ``&`` is a Python-level
# call that builds a member (microseconds); ``int(flag) & bit`` stays in C.
_POS_BUSY: Final = int(PosStatus.BUSY)
_POS_IN_TARGET: Final = int(PosStatus.IN_TARGET)
_POS_WARNING: Final = int(PosStatus.WARNING)
_POS_ERROR: Final = int(PosStatus.ERROR)
_POS_EXECUTE: Final = int(PosControl.EXECUTE)
_POS_EMERGENCY_STOP: Final = int(PosControl.EMERGENCY_STOP)
_STM_ENABLE: Final = int(StmControl.ENABLE)

# --- process image ----------------------------------------------------------------------

# Little-endian, no padding: ENC control word, set counter value, STM control word,
# POS control word, target, velocity, start type, acceleration, deceleration.
_OUTPUTS = struct.Struct("<HiHHihHHH")
# ENC status word, counter, latch, STM status word, POS status word, actual position,
# actual velocity, actual drive time.
_INPUTS = struct.Struct("<HiiHHihI")
assert _OUTPUTS.size == OUTPUTS_SIZE and _INPUTS.size == INPUTS_SIZE

INT16_MIN, INT16_MAX = -(1 << 15), (1 << 15) - 1
INT32_MIN, INT32_MAX = -(1 << 31), (1 << 31) - 1
UINT16_MAX = (1 << 16) - 1
UINT32_MAX = (1 << 32) - 1


@dataclass(frozen=True, slots=True)
class Outputs:
    """The 22 output bytes (RxPDO 0x1601 + 0x1602 + 0x1606), master -> drive.

    | bytes | field |
    |---|---|
    | 0-1 | ``enc_control`` (0x7000:01..04) |
    | 2-5 | ``set_counter_counts`` (0x7000:11, INT32) |
    | 6-7 | ``stm_control`` (0x7010:01..03, :0C) |
    | 8-9 | ``pos_control`` (0x7020:01..02) |
    | 10-13 | ``target_position_counts`` (0x7020:11, INT32) |
    | 14-15 | ``velocity_bp`` (0x7020:21, INT16) |
    | 16-17 | ``start_type`` (0x7020:22, UINT16) |
    | 18-19 | ``acceleration_ms`` (0x7020:23, UINT16) |
    | 20-21 | ``deceleration_ms`` (0x7020:24, UINT16) |

    ``start_type`` is a :class:`StartType` when the code is known, the raw number
    otherwise (the drive answers unknown codes with Error, so they must survive a
    decode). Bits in the gaps of the control words are kept as they are, so
    ``encode_outputs(decode_outputs(b)) == b`` for any 22 bytes.
    """

    enc_control: EncControl = EncControl.NONE
    set_counter_counts: int = 0
    stm_control: StmControl = StmControl.NONE
    pos_control: PosControl = PosControl.NONE
    target_position_counts: int = 0
    velocity_bp: int = 0
    start_type: StartType | int = 0
    acceleration_ms: int = 0
    deceleration_ms: int = 0

    @property
    def execute(self) -> bool:
        return int(self.pos_control) & _POS_EXECUTE != 0

    @property
    def emergency_stop(self) -> bool:
        return int(self.pos_control) & _POS_EMERGENCY_STOP != 0

    @property
    def enable(self) -> bool:
        return int(self.stm_control) & _STM_ENABLE != 0


@dataclass(frozen=True, slots=True)
class Inputs:
    """The 24 input bytes (TxPDO 0x1A01 + 0x1A03 + 0x1A07), drive -> master.

    | bytes | field |
    |---|---|
    | 0-1 | ``enc_status`` (0x6000:01..10) |
    | 2-5 | ``counter_counts`` (0x6000:11, INT32) |
    | 6-9 | ``latch_counts`` (0x6000:12, INT32) |
    | 10-11 | ``stm_status`` (0x6010:01..10) |
    | 12-13 | ``pos_status`` (0x6020:01..08) |
    | 14-17 | ``actual_position_counts`` (0x6020:11, INT32) |
    | 18-19 | ``actual_velocity_bp`` (0x6020:21, INT16) |
    | 20-23 | ``actual_drive_time_ms`` (0x6020:22, UINT32) |

    Decision (spec silent on the unit): "Actual drive time" is the elapsed time of the
    current or last move in milliseconds.
    """

    enc_status: EncStatus = EncStatus.NONE
    counter_counts: int = 0
    latch_counts: int = 0
    stm_status: StmStatus = StmStatus.NONE
    pos_status: PosStatus = PosStatus.NONE
    actual_position_counts: int = 0
    actual_velocity_bp: int = 0
    actual_drive_time_ms: int = 0

    @property
    def busy(self) -> bool:
        return int(self.pos_status) & _POS_BUSY != 0

    @property
    def in_target(self) -> bool:
        return int(self.pos_status) & _POS_IN_TARGET != 0

    @property
    def warning(self) -> bool:
        return int(self.pos_status) & _POS_WARNING != 0

    @property
    def error(self) -> bool:
        return int(self.pos_status) & _POS_ERROR != 0


def _check(name: str, value: int, minimum: int, maximum: int) -> None:
    if not minimum <= value <= maximum:
        raise CodecError(f"{name} must be between {minimum} and {maximum}, got {value}")


def _check_length(name: str, data: bytes, size: int) -> None:
    if len(data) != size:
        raise CodecError(f"{name} are {size} bytes, got {len(data)}")


@functools.lru_cache(maxsize=_FLAG_CACHE_SIZE)  # memoised like the flag words: 16-bit codes
def start_type_of(code: int) -> StartType | int:
    """The :class:`StartType` for ``code``, or ``code`` itself when it is not one."""
    try:
        return StartType(code)
    except ValueError:
        return code


# The PDO fields in packing order with their ranges, to name a field that does not fit.
_OUTPUT_FIELDS: Final = (
    ("ENC control", 0, UINT16_MAX),
    ("set counter value", INT32_MIN, INT32_MAX),
    ("STM control", 0, UINT16_MAX),
    ("POS control", 0, UINT16_MAX),
    ("target position", INT32_MIN, INT32_MAX),
    ("velocity", INT16_MIN, INT16_MAX),
    ("start type", 0, UINT16_MAX),
    ("acceleration", 0, UINT16_MAX),
    ("deceleration", 0, UINT16_MAX),
)
_INPUT_FIELDS: Final = (
    ("ENC status", 0, UINT16_MAX),
    ("counter value", INT32_MIN, INT32_MAX),
    ("latch value", INT32_MIN, INT32_MAX),
    ("STM status", 0, UINT16_MAX),
    ("POS status", 0, UINT16_MAX),
    ("actual position", INT32_MIN, INT32_MAX),
    ("actual velocity", INT16_MIN, INT16_MAX),
    ("actual drive time", 0, UINT32_MAX),
)


def _pack(
    packer: struct.Struct,
    what: str,
    ranges: tuple[tuple[str, int, int], ...],
    values: tuple[int, ...],
) -> bytes:
    """Pack first: each struct code range-checks exactly its PDO field's range (H:
    UINT16, I: UINT32, i: INT32, h: INT16) and never clips, so a frame that packs is
    valid; the field checks run only to name what does not fit."""
    try:
        return packer.pack(*values)
    except struct.error as exc:
        for (name, minimum, maximum), value in zip(ranges, values, strict=True):
            _check(name, int(value), minimum, maximum)
        raise CodecError(f"{what} do not fit the process image: {exc}") from exc


def encode_outputs(outputs: Outputs) -> bytes:
    """The 22 output bytes for ``outputs``; raises :class:`CodecError` if a field is out of
    its PDO range (nothing is clipped: a wrong value must never reach the drive)."""
    values = (
        outputs.enc_control,
        outputs.set_counter_counts,
        outputs.stm_control,
        outputs.pos_control,
        outputs.target_position_counts,
        outputs.velocity_bp,
        outputs.start_type,
        outputs.acceleration_ms,
        outputs.deceleration_ms,
    )
    return _pack(_OUTPUTS, "outputs", _OUTPUT_FIELDS, values)


def decode_outputs(data: bytes) -> Outputs:
    """Decode 22 output bytes (e.g. what a simulator receives from the master)."""
    _check_length("outputs", data, OUTPUTS_SIZE)
    enc, set_counter, stm, pos, target, velocity, start, acc, dec = _OUTPUTS.unpack(data)
    return Outputs(
        enc_control=enc_control_of(enc),
        set_counter_counts=set_counter,
        stm_control=stm_control_of(stm),
        pos_control=pos_control_of(pos),
        target_position_counts=target,
        velocity_bp=velocity,
        start_type=start_type_of(start),
        acceleration_ms=acc,
        deceleration_ms=dec,
    )


def encode_inputs(inputs: Inputs) -> bytes:
    """The 24 input bytes for ``inputs``; raises :class:`CodecError` on out-of-range fields."""
    values = (
        inputs.enc_status,
        inputs.counter_counts,
        inputs.latch_counts,
        inputs.stm_status,
        inputs.pos_status,
        inputs.actual_position_counts,
        inputs.actual_velocity_bp,
        inputs.actual_drive_time_ms,
    )
    return _pack(_INPUTS, "inputs", _INPUT_FIELDS, values)


def decode_inputs(data: bytes) -> Inputs:
    """Decode 24 input bytes as read from the drive."""
    _check_length("inputs", data, INPUTS_SIZE)
    enc, counter, latch, stm, pos, position, velocity, drive_time = _INPUTS.unpack(data)
    return Inputs(
        enc_status=enc_status_of(enc),
        counter_counts=counter,
        latch_counts=latch,
        stm_status=stm_status_of(stm),
        pos_status=pos_status_of(pos),
        actual_position_counts=position,
        actual_velocity_bp=velocity,
        actual_drive_time_ms=drive_time,
    )


def wrap_int32(value: int) -> int:
    """``value`` as a 32-bit counter shows it (two's complement wrap-around)."""
    return (value + (1 << 31)) % (1 << 32) - (1 << 31)


# --- CoE objects ------------------------------------------------------------------------


class DataType(enum.Enum):
    """CoE data types used here, as (struct format for an SDO transfer, minimum, maximum).

    BOOLEAN and the BITn types travel as one byte in an expedited SDO transfer.
    """

    BOOLEAN = ("<B", 0, 1)
    BIT2 = ("<B", 0, 3)
    BIT3 = ("<B", 0, 7)
    INT16 = ("<h", INT16_MIN, INT16_MAX)
    UINT16 = ("<H", 0, UINT16_MAX)
    INT32 = ("<i", INT32_MIN, INT32_MAX)
    UINT32 = ("<I", 0, UINT32_MAX)

    @property
    def minimum(self) -> int:
        return self.value[1]

    @property
    def maximum(self) -> int:
        return self.value[2]

    @property
    def size(self) -> int:
        return struct.calcsize(self.value[0])


@dataclass(frozen=True, slots=True)
class SdoObject:
    """One CoE entry: where it lives, how it is typed, what the vendor calls it."""

    index: int
    subindex: int
    data_type: DataType
    name: str
    unit: str = ""
    writable: bool = True


# The one table of CoE addresses. The seed manual itself names 0x8020:08, :09, :0A, :0C,
# :0E, :0F, 0x8021:01, :13, :14 and 0x9020:03; the other subindices and the bit lengths
# were checked against a public EtherCAT configuration of the EL7041, which carries the
# same POS objects. Positions are INT32 (see the module note).
# POS Settings 0x8020
VELOCITY_MIN = SdoObject(0x8020, 0x01, DataType.INT16, "Velocity min.", "bp")
VELOCITY_MAX = SdoObject(0x8020, 0x02, DataType.INT16, "Velocity max.", "bp")
ACCELERATION_POS = SdoObject(0x8020, 0x03, DataType.UINT16, "Acceleration pos.", "ms")
ACCELERATION_NEG = SdoObject(0x8020, 0x04, DataType.UINT16, "Acceleration neg.", "ms")
DECELERATION_POS = SdoObject(0x8020, 0x05, DataType.UINT16, "Deceleration pos.", "ms")
DECELERATION_NEG = SdoObject(0x8020, 0x06, DataType.UINT16, "Deceleration neg.", "ms")
EMERGENCY_DECELERATION = SdoObject(0x8020, 0x07, DataType.UINT16, "Emergency deceleration", "ms")
CALIBRATION_POSITION = SdoObject(0x8020, 0x08, DataType.INT32, "Calibration position", "counts")
CALIBRATION_VELOCITY_TOWARDS_CAM = SdoObject(
    0x8020, 0x09, DataType.INT16, "Calibration velocity (towards plc cam)", "bp"
)
CALIBRATION_VELOCITY_OFF_CAM = SdoObject(
    0x8020, 0x0A, DataType.INT16, "Calibration velocity (off plc cam)", "bp"
)
TARGET_WINDOW = SdoObject(0x8020, 0x0B, DataType.UINT16, "Target window", "counts")
IN_TARGET_TIMEOUT = SdoObject(0x8020, 0x0C, DataType.UINT16, "In-Target timeout", "ms")
DEAD_TIME_COMPENSATION = SdoObject(0x8020, 0x0D, DataType.INT16, "Dead time compensation", "us")
MODULO_FACTOR = SdoObject(0x8020, 0x0E, DataType.UINT32, "Modulo factor", "counts")
MODULO_TOLERANCE_WINDOW = SdoObject(
    0x8020, 0x0F, DataType.UINT32, "Modulo tolerance window", "counts"
)
# POS Features 0x8021
DEFAULT_START_TYPE = SdoObject(0x8021, 0x01, DataType.UINT16, "Start type")
TIME_INFORMATION = SdoObject(0x8021, 0x11, DataType.BIT2, "Time information")
INVERT_CALIBRATION_CAM_SEARCH = SdoObject(
    0x8021, 0x13, DataType.BOOLEAN, "Invert calibration cam search direction"
)
INVERT_SYNC_IMPULSE_SEARCH = SdoObject(
    0x8021, 0x14, DataType.BOOLEAN, "Invert sync impulse search direction"
)
# POS Info data 0x9020 and POS Diag data 0xA020 (read only)
POS_STATUS_WORD = SdoObject(0x9020, 0x01, DataType.UINT16, "Status word", writable=False)
DRIVE_STATE = SdoObject(0x9020, 0x03, DataType.UINT16, "State (drive controller)", writable=False)
DIAG_COMMAND_REJECTED = SdoObject(
    0xA020, 0x01, DataType.BOOLEAN, "Command rejected", writable=False
)
DIAG_COMMAND_ABORTED = SdoObject(0xA020, 0x02, DataType.BOOLEAN, "Command aborted", writable=False)
DIAG_TARGET_OVERRUN = SdoObject(0xA020, 0x03, DataType.BOOLEAN, "Target overrun", writable=False)
# Outside the positioning interface, but every velocity and ramp scales with it; the
# codes are those of SPEED_RANGE_STEPSDataType.
SPEED_RANGE = SdoObject(0x8012, 0x05, DataType.BIT3, "Speed range")
# Identity 0x1018 (read only): check before going to OP and refuse anything else.
IDENTITY_VENDOR_ID = SdoObject(0x1018, 0x01, DataType.UINT32, "Vendor ID", writable=False)
IDENTITY_PRODUCT_CODE = SdoObject(0x1018, 0x02, DataType.UINT32, "Product code", writable=False)
IDENTITY_REVISION = SdoObject(0x1018, 0x03, DataType.UINT32, "Revision", writable=False)

SDO_OBJECTS: Final = (
    VELOCITY_MIN,
    VELOCITY_MAX,
    ACCELERATION_POS,
    ACCELERATION_NEG,
    DECELERATION_POS,
    DECELERATION_NEG,
    EMERGENCY_DECELERATION,
    CALIBRATION_POSITION,
    CALIBRATION_VELOCITY_TOWARDS_CAM,
    CALIBRATION_VELOCITY_OFF_CAM,
    TARGET_WINDOW,
    IN_TARGET_TIMEOUT,
    DEAD_TIME_COMPENSATION,
    MODULO_FACTOR,
    MODULO_TOLERANCE_WINDOW,
    DEFAULT_START_TYPE,
    TIME_INFORMATION,
    INVERT_CALIBRATION_CAM_SEARCH,
    INVERT_SYNC_IMPULSE_SEARCH,
    POS_STATUS_WORD,
    DRIVE_STATE,
    DIAG_COMMAND_REJECTED,
    DIAG_COMMAND_ABORTED,
    DIAG_TARGET_OVERRUN,
    SPEED_RANGE,
    IDENTITY_VENDOR_ID,
    IDENTITY_PRODUCT_CODE,
    IDENTITY_REVISION,
)


def encode_sdo(obj: SdoObject, value: int) -> bytes:
    """The SDO download payload for ``value``; raises :class:`CodecError` when it does not
    fit ``obj``'s data type."""
    _check(obj.name, int(value), obj.data_type.minimum, obj.data_type.maximum)
    return struct.pack(obj.data_type.value[0], value)


def decode_sdo(obj: SdoObject, data: bytes) -> int:
    """The value of an SDO upload payload for ``obj`` (exactly the type's size)."""
    _check_length(obj.name, data, obj.data_type.size)
    value: int = struct.unpack(obj.data_type.value[0], data)[0]
    _check(obj.name, value, obj.data_type.minimum, obj.data_type.maximum)
    return value


@dataclass(frozen=True, slots=True)
class PosSettings:
    """The positioning interface's CoE settings (0x8020 "POS Settings", 0x8021 "POS
    Features"), in device units.

    Defaults are the values public EtherCAT configurations write for this family
    (velocity min 100, window 10, In-Target timeout 1000, dead time 50); read the
    device's own values over CoE rather than trusting them. ``start_type`` is the
    default start type, used when the Start type output is 0 (and by
    SET_CALIBRATION_AUTO).
    """

    velocity_min_bp: int = 100
    velocity_max_bp: int = 10_000
    acceleration_pos_ms: int = 1000
    acceleration_neg_ms: int = 1000
    deceleration_pos_ms: int = 1000
    deceleration_neg_ms: int = 1000
    emergency_deceleration_ms: int = 100
    calibration_position_counts: int = 0
    calibration_velocity_towards_cam_bp: int = 100
    calibration_velocity_off_cam_bp: int = 10
    target_window_counts: int = 10
    in_target_timeout_ms: int = 1000
    dead_time_compensation_us: int = 50
    modulo_factor_counts: int = 0
    modulo_tolerance_window_counts: int = 0
    start_type: int = StartType.ABSOLUTE
    time_information: int = 0
    invert_calibration_cam_search: bool = False
    invert_sync_impulse_search: bool = False


# PosSettings field -> its CoE entry: what a driver writes at start-up, what the
# simulator answers to SDO requests.
POS_SETTINGS_SDO: Final[Mapping[str, SdoObject]] = {
    "velocity_min_bp": VELOCITY_MIN,
    "velocity_max_bp": VELOCITY_MAX,
    "acceleration_pos_ms": ACCELERATION_POS,
    "acceleration_neg_ms": ACCELERATION_NEG,
    "deceleration_pos_ms": DECELERATION_POS,
    "deceleration_neg_ms": DECELERATION_NEG,
    "emergency_deceleration_ms": EMERGENCY_DECELERATION,
    "calibration_position_counts": CALIBRATION_POSITION,
    "calibration_velocity_towards_cam_bp": CALIBRATION_VELOCITY_TOWARDS_CAM,
    "calibration_velocity_off_cam_bp": CALIBRATION_VELOCITY_OFF_CAM,
    "target_window_counts": TARGET_WINDOW,
    "in_target_timeout_ms": IN_TARGET_TIMEOUT,
    "dead_time_compensation_us": DEAD_TIME_COMPENSATION,
    "modulo_factor_counts": MODULO_FACTOR,
    "modulo_tolerance_window_counts": MODULO_TOLERANCE_WINDOW,
    "start_type": DEFAULT_START_TYPE,
    "time_information": TIME_INFORMATION,
    "invert_calibration_cam_search": INVERT_CALIBRATION_CAM_SEARCH,
    "invert_sync_impulse_search": INVERT_SYNC_IMPULSE_SEARCH,
}
assert set(POS_SETTINGS_SDO) == {f.name for f in fields(PosSettings)}


def settings_writes(settings: PosSettings) -> tuple[tuple[SdoObject, int], ...]:
    """Every (object, value) pair that puts ``settings`` into a drive, in table order.

    Raises :class:`CodecError` for a value its object cannot hold.
    """
    writes = tuple((obj, int(getattr(settings, name))) for name, obj in POS_SETTINGS_SDO.items())
    for obj, value in writes:
        _check(obj.name, value, obj.data_type.minimum, obj.data_type.maximum)
    return writes
