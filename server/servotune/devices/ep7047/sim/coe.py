"""The CoE side of the simulated EP7047-1032 on the wire: its object dictionary, its PDO
mapping and an SDO server (mailbox CoE, ETG.1000.6), sans-IO.

Written from the spec (``shared/spec/ep7047.md``) and the vendor manual, NOT from the
driver's codec (``servotune.devices.ep7047.codec``): this module is the independent check
of that codec. Nothing here imports it; the layout of the process image is computed
from the PDO mapping objects below, exactly as a master reads it over CoE.

Sources, object by object:

* PDO mapping 0x1601/0x1602/0x1606 (outputs) and 0x1A01/0x1A03/0x1A07 (inputs): the
  spec's tables "Outputs" and "Inputs" (bytes, bit numbers, object addresses, sizes);
  gaps are mapping entries of object 0 with the gap's length. The ENC status word's
  bit names (0x6000:01..10) are not in the spec ("status word"); they are the
  EL70x1 family's, as Beckhoff documents them. "Positioning interface compact" (0x1605,
  0x1A06) and the velocity interface's 0x1604 exist so that an assignment other than
  the full interface gives another image (the factory default here is the velocity
  interface, so a master that does not assign the positioning interface notices).
* 0x8020 POS Settings / 0x8021 POS Features: the manual's list in its order (subindices
  as the manual names them: 0x8020:08, :09, :0A, :0C, :0E, :0F, 0x8021:01, :13, :14).
  Data types and ranges are decisions where the manual gives none, written next to
  each entry: velocities are 0..10000 (the manual: 10000 = 100 % of the speed range),
  ramps and times 16 bit, positions 32 bit signed (the manual's tables reach negative
  positions), a modulo tolerance window must be below half the modulo factor (it is a
  +- window around the modulo position: half a turn would be every position), the
  default start type must be one of the manual's start types and no _CHANGE type.
* 0x9020 POS Info data (:01 status word, :03 drive state), 0xA020 POS Diag data
  (:01..:03): the manual ("the positions of the bits are the subindex - 1").
* 0x8012:05 Speed range: the spec (codes 0..5 = 1000..32000 full steps/s).
* 0x1000, 0x1008-0x100A, 0x1018, 0x1C00, 0x1C12, 0x1C13: CiA 301 / ETG.1000.6.
* 0x2000 "Simulator scratch pad": not a device object. A 256-byte OCTET_STRING of the
  simulation only, so that normal and segmented SDO transfers (both directions) can
  be exercised against it; the EP7047's own objects all fit an expedited transfer.

SDO server: expedited, normal and segmented upload and download, aborts with their
codes (sent with CoE service 2, "SDO request": SOEM takes an abort with service 3 for
a normal reply), complete access is not supported (CoE details say so; such requests
are aborted 0x06010000). In a segmented download the segment's length comes from the
mailbox length; its 3 size bits count only for a segment shorter than 7 bytes (what
SOEM sends).
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Final

# CoE data types (ETG.1000.6 table 64), what this dictionary uses.
BOOLEAN: Final = 0x0001
INTEGER16: Final = 0x0003
INTEGER32: Final = 0x0004
UNSIGNED8: Final = 0x0005
UNSIGNED16: Final = 0x0006
UNSIGNED32: Final = 0x0007
VISIBLE_STRING: Final = 0x0009
OCTET_STRING: Final = 0x000A
BIT2: Final = 0x0031
BIT3: Final = 0x0032

# SDO abort codes (ETG.1000.6).
ABORT_TOGGLE: Final = 0x0503_0000
ABORT_COMMAND: Final = 0x0504_0001
ABORT_UNSUPPORTED: Final = 0x0601_0000
ABORT_WRITE_ONLY: Final = 0x0601_0001
ABORT_READ_ONLY: Final = 0x0601_0002
ABORT_NO_OBJECT: Final = 0x0602_0000
ABORT_LENGTH: Final = 0x0607_0010
ABORT_LENGTH_HIGH: Final = 0x0607_0012
ABORT_LENGTH_LOW: Final = 0x0607_0013
ABORT_NO_SUBINDEX: Final = 0x0609_0011
ABORT_VALUE_RANGE: Final = 0x0609_0030
ABORT_VALUE_HIGH: Final = 0x0609_0031
ABORT_VALUE_LOW: Final = 0x0609_0032
ABORT_GENERAL: Final = 0x0800_0000
ABORT_STATE: Final = 0x0800_0022

# AL states (the numbers of the AL status register).
AL_INIT: Final = 0x01
AL_PREOP: Final = 0x02
AL_SAFEOP: Final = 0x04
AL_OP: Final = 0x08

_FIXED_SIZE: Final = {
    BOOLEAN: 1,
    BIT2: 1,
    BIT3: 1,
    UNSIGNED8: 1,
    INTEGER16: 2,
    UNSIGNED16: 2,
    INTEGER32: 4,
    UNSIGNED32: 4,
}
_RANGE: Final = {
    BOOLEAN: (0, 1),
    BIT2: (0, 3),
    BIT3: (0, 7),
    UNSIGNED8: (0, 0xFF),
    INTEGER16: (-(1 << 15), (1 << 15) - 1),
    UNSIGNED16: (0, 0xFFFF),
    INTEGER32: (-(1 << 31), (1 << 31) - 1),
    UNSIGNED32: (0, 0xFFFF_FFFF),
}
_SIGNED: Final = frozenset({INTEGER16, INTEGER32})


class SdoAbortError(Exception):
    def __init__(self, code: int, text: str = "") -> None:
        super().__init__(f"SDO abort 0x{code:08X}{': ' + text if text else ''}")
        self.code = code


class Access(enum.Enum):
    RO = "ro"
    RW = "rw"
    RW_PREOP = "rw in PRE-OP"  # writable in PRE-OP only (PDO assignment, speed range)


Getter = Callable[[], "int | bytes"]
Setter = Callable[[int], None]
Check = Callable[[int], None]


@dataclass(slots=True)
class Entry:
    """One CoE entry. ``value`` is stored here unless ``get``/``set`` reach elsewhere (the
    drive's settings, diagnosis or process data)."""

    index: int
    subindex: int
    name: str
    data_type: int
    access: Access = Access.RO
    value: int | bytes = 0
    get: Getter | None = None
    set: Setter | None = None
    check: Check | None = None
    minimum: int | None = None
    maximum: int | None = None
    size: int = 0  # bytes, for strings

    def read(self) -> bytes:
        value = self.get() if self.get is not None else self.value
        if isinstance(value, bytes):
            return value
        size = _FIXED_SIZE[self.data_type]
        return (value & ((1 << (8 * size)) - 1)).to_bytes(size, "little")

    def write(self, data: bytes) -> None:
        if self.data_type in (VISIBLE_STRING, OCTET_STRING):
            if len(data) > self.size:
                raise SdoAbortError(ABORT_LENGTH_HIGH, f"{self.name} holds {self.size} bytes")
            self.value = bytes(data)
            return
        size = _FIXED_SIZE[self.data_type]
        if len(data) != size:
            raise SdoAbortError(
                ABORT_LENGTH_HIGH if len(data) > size else ABORT_LENGTH_LOW,
                f"{self.name} is {size} byte(s), got {len(data)}",
            )
        value = int.from_bytes(data, "little", signed=self.data_type in _SIGNED)
        low, high = _RANGE[self.data_type]
        low = low if self.minimum is None else self.minimum
        high = high if self.maximum is None else self.maximum
        if value > high:
            raise SdoAbortError(ABORT_VALUE_HIGH, f"{self.name} = {value}: at most {high}")
        if value < low:
            raise SdoAbortError(ABORT_VALUE_LOW, f"{self.name} = {value}: at least {low}")
        if self.check is not None:
            self.check(value)
        if self.set is not None:
            self.set(value)
        else:
            self.value = value


# --- PDO mapping (the spec's tables) ----------------------------------------------------


@dataclass(frozen=True, slots=True)
class Mapped:
    """One mapping entry: object (0 for a gap), subindex, bit length."""

    index: int
    subindex: int
    bits: int
    name: str = ""

    @property
    def word(self) -> int:
        """The 32-bit value of the mapping entry (index << 16 | subindex << 8 | bits)."""
        return self.index << 16 | self.subindex << 8 | self.bits


def _gap(bits: int) -> Mapped:
    return Mapped(0, 0, bits, "gap")


# RxPDOs (master -> drive).
RXPDO_MAPS: Final[Mapping[int, tuple[str, tuple[Mapped, ...]]]] = {
    0x1601: (
        "ENC RxPDO-Map Control",
        (
            Mapped(0x7000, 0x01, 1, "Enable latch C"),
            Mapped(0x7000, 0x02, 1, "Enable latch extern on positive edge"),
            Mapped(0x7000, 0x03, 1, "Set counter"),
            Mapped(0x7000, 0x04, 1, "Enable latch extern on negative edge"),
            _gap(12),
            Mapped(0x7000, 0x11, 32, "Set counter value"),
        ),
    ),
    0x1602: (
        "STM RxPDO-Map Control",
        (
            Mapped(0x7010, 0x01, 1, "Enable"),
            Mapped(0x7010, 0x02, 1, "Reset"),
            Mapped(0x7010, 0x03, 1, "Reduce torque"),
            _gap(8),
            Mapped(0x7010, 0x0C, 1, "Digital output 1"),
            _gap(4),
        ),
    ),
    0x1604: ("STM RxPDO-Map Velocity", (Mapped(0x7010, 0x21, 16, "Velocity"),)),
    0x1605: (
        "POS RxPDO-Map Control compact",
        (
            Mapped(0x7020, 0x01, 1, "Execute"),
            Mapped(0x7020, 0x02, 1, "Emergency stop"),
            _gap(14),
            Mapped(0x7020, 0x11, 32, "Target position"),
        ),
    ),
    0x1606: (
        "POS RxPDO-Map Control",
        (
            Mapped(0x7020, 0x01, 1, "Execute"),
            Mapped(0x7020, 0x02, 1, "Emergency stop"),
            _gap(14),
            Mapped(0x7020, 0x11, 32, "Target position"),
            Mapped(0x7020, 0x21, 16, "Velocity"),
            Mapped(0x7020, 0x22, 16, "Start type"),
            Mapped(0x7020, 0x23, 16, "Acceleration"),
            Mapped(0x7020, 0x24, 16, "Deceleration"),
        ),
    ),
}
# TxPDOs (drive -> master).
TXPDO_MAPS: Final[Mapping[int, tuple[str, tuple[Mapped, ...]]]] = {
    0x1A01: (
        "ENC TxPDO-Map Status",
        (
            Mapped(0x6000, 0x01, 1, "Latch C valid"),
            Mapped(0x6000, 0x02, 1, "Latch extern valid"),
            Mapped(0x6000, 0x03, 1, "Set counter done"),
            Mapped(0x6000, 0x04, 1, "Counter underflow"),
            Mapped(0x6000, 0x05, 1, "Counter overflow"),
            _gap(2),
            Mapped(0x6000, 0x08, 1, "Extrapolation stall"),
            Mapped(0x6000, 0x09, 1, "Status of input A"),
            Mapped(0x6000, 0x0A, 1, "Status of input B"),
            Mapped(0x6000, 0x0B, 1, "Status of input C"),
            _gap(1),
            Mapped(0x6000, 0x0D, 1, "Status of extern latch"),
            Mapped(0x6000, 0x0E, 1, "Sync error"),
            _gap(1),
            Mapped(0x6000, 0x10, 1, "TxPDO Toggle"),
            Mapped(0x6000, 0x11, 32, "Counter value"),
            Mapped(0x6000, 0x12, 32, "Latch value"),
        ),
    ),
    0x1A03: (
        "STM TxPDO-Map Status",
        (
            Mapped(0x6010, 0x01, 1, "Ready to enable"),
            Mapped(0x6010, 0x02, 1, "Ready"),
            Mapped(0x6010, 0x03, 1, "Warning"),
            Mapped(0x6010, 0x04, 1, "Error"),
            Mapped(0x6010, 0x05, 1, "Moving positive"),
            Mapped(0x6010, 0x06, 1, "Moving negative"),
            Mapped(0x6010, 0x07, 1, "Torque reduced"),
            Mapped(0x6010, 0x08, 1, "Motor stall"),
            _gap(3),
            Mapped(0x6010, 0x0C, 1, "Digital input 1"),
            Mapped(0x6010, 0x0D, 1, "Digital input 2"),
            Mapped(0x6010, 0x0E, 1, "Sync error"),
            _gap(1),
            Mapped(0x6010, 0x10, 1, "TxPDO Toggle"),
        ),
    ),
    0x1A06: (
        "POS TxPDO-Map Status compact",
        (
            Mapped(0x6020, 0x01, 1, "Busy"),
            Mapped(0x6020, 0x02, 1, "In-Target"),
            Mapped(0x6020, 0x03, 1, "Warning"),
            Mapped(0x6020, 0x04, 1, "Error"),
            Mapped(0x6020, 0x05, 1, "Calibrated"),
            Mapped(0x6020, 0x06, 1, "Accelerate"),
            Mapped(0x6020, 0x07, 1, "Decelerate"),
            Mapped(0x6020, 0x08, 1, "Ready to execute"),
            _gap(8),
        ),
    ),
    0x1A07: (
        "POS TxPDO-Map Status",
        (
            Mapped(0x6020, 0x01, 1, "Busy"),
            Mapped(0x6020, 0x02, 1, "In-Target"),
            Mapped(0x6020, 0x03, 1, "Warning"),
            Mapped(0x6020, 0x04, 1, "Error"),
            Mapped(0x6020, 0x05, 1, "Calibrated"),
            Mapped(0x6020, 0x06, 1, "Accelerate"),
            Mapped(0x6020, 0x07, 1, "Decelerate"),
            Mapped(0x6020, 0x08, 1, "Ready to execute"),
            _gap(8),
            Mapped(0x6020, 0x11, 32, "Actual position"),
            Mapped(0x6020, 0x21, 16, "Actual velocity"),
            Mapped(0x6020, 0x22, 32, "Actual drive time"),
        ),
    ),
}
# The spec: "Positioning interface" = RxPDO 0x1601 + 0x1602 + 0x1606, TxPDO 0x1A01 +
# 0x1A03 + 0x1A07. The factory default of this simulation: the velocity interface.
POSITIONING_RX: Final = (0x1601, 0x1602, 0x1606)
POSITIONING_TX: Final = (0x1A01, 0x1A03, 0x1A07)
DEFAULT_RX: Final = (0x1601, 0x1602, 0x1604)
DEFAULT_TX: Final = (0x1A01, 0x1A03)
MAX_ASSIGNED: Final = 4

# Process-data objects: (index, subindex) -> CoE data type (1-bit entries are BOOLEAN).
PROCESS_TYPES: Final[Mapping[tuple[int, int], int]] = {
    (0x7000, 0x11): INTEGER32,
    (0x7010, 0x21): INTEGER16,
    (0x7020, 0x11): INTEGER32,
    (0x7020, 0x21): INTEGER16,
    (0x7020, 0x22): UNSIGNED16,
    (0x7020, 0x23): UNSIGNED16,
    (0x7020, 0x24): UNSIGNED16,
    (0x6000, 0x11): INTEGER32,
    (0x6000, 0x12): INTEGER32,
    (0x6020, 0x11): INTEGER32,
    (0x6020, 0x21): INTEGER16,
    (0x6020, 0x22): UNSIGNED32,
}


def pdo_bits(maps: Mapping[int, tuple[str, tuple[Mapped, ...]]], assigned: Iterable[int]) -> int:
    return sum(m.bits for pdo in assigned for m in maps[pdo][1])


@dataclass(frozen=True, slots=True)
class ImageLayout:
    """Where each mapped object sits in one direction's process image (bits from 0)."""

    fields: tuple[tuple[int, int, int, int, bool], ...]  # index, subindex, offset, bits, signed
    size_bytes: int

    @classmethod
    def of(
        cls, maps: Mapping[int, tuple[str, tuple[Mapped, ...]]], assigned: Iterable[int]
    ) -> ImageLayout:
        fields = []
        offset = 0
        for pdo in assigned:
            for m in maps[pdo][1]:
                if m.index:
                    signed = PROCESS_TYPES.get((m.index, m.subindex)) in _SIGNED
                    fields.append((m.index, m.subindex, offset, m.bits, signed))
                offset += m.bits
        return cls(tuple(fields), (offset + 7) // 8)

    def unpack(self, data: bytes) -> dict[tuple[int, int], int]:
        raw = int.from_bytes(data, "little")
        values = {}
        for index, subindex, offset, bits, signed in self.fields:
            value = (raw >> offset) & ((1 << bits) - 1)
            if signed and value >> (bits - 1):
                value -= 1 << bits
            values[index, subindex] = value
        return values

    def pack(self, values: Mapping[tuple[int, int], int]) -> bytes:
        raw = 0
        for index, subindex, offset, bits, _ in self.fields:
            raw |= (values.get((index, subindex), 0) & ((1 << bits) - 1)) << offset
        return raw.to_bytes(self.size_bytes, "little")


# --- the dictionary ---------------------------------------------------------------------


@dataclass(slots=True)
class ObjectDictionary:
    """Entries by (index, subindex), plus the two PDO assignments."""

    entries: dict[tuple[int, int], Entry] = field(default_factory=dict)
    rx_assigned: list[int] = field(default_factory=lambda: list(DEFAULT_RX))
    tx_assigned: list[int] = field(default_factory=lambda: list(DEFAULT_TX))
    # Entries written while sub 0 is 0, by assignment object and subindex.
    staged: dict[int, dict[int, int]] = field(default_factory=lambda: {0x1C12: {}, 0x1C13: {}})
    al_state: Callable[[], int] = lambda: AL_PREOP

    def add(self, entry: Entry) -> Entry:
        self.entries[entry.index, entry.subindex] = entry
        return entry

    def record(self, index: int, name: str, subs: Iterable[Entry]) -> None:
        """A record: its entries and sub 0 (the highest subindex, UNSIGNED8, read only)."""
        subs = list(subs)
        highest = max(e.subindex for e in subs)
        self.add(Entry(index, 0, name, UNSIGNED8, value=highest))
        for entry in subs:
            self.add(entry)

    def has_index(self, index: int) -> bool:
        return index in (0x1C12, 0x1C13) or any(i == index for i, _ in self.entries)

    # --- access -------------------------------------------------------------------------

    def upload(self, index: int, subindex: int) -> bytes:
        if index in (0x1C12, 0x1C13):
            return self._read_assignment(index, subindex)
        entry = self.entries.get((index, subindex))
        if entry is None:
            raise SdoAbortError(ABORT_NO_SUBINDEX if self.has_index(index) else ABORT_NO_OBJECT)
        return entry.read()

    def download(self, index: int, subindex: int, data: bytes) -> None:
        if index in (0x1C12, 0x1C13):
            self._write_assignment(index, subindex, data)
            return
        entry = self.entries.get((index, subindex))
        if entry is None:
            raise SdoAbortError(ABORT_NO_SUBINDEX if self.has_index(index) else ABORT_NO_OBJECT)
        if entry.access is Access.RO:
            raise SdoAbortError(ABORT_READ_ONLY, entry.name)
        if entry.access is Access.RW_PREOP and self.al_state() != AL_PREOP:
            raise SdoAbortError(ABORT_STATE, f"{entry.name} can be written in PRE-OP only")
        entry.write(data)

    def _assignment(self, index: int) -> list[int]:
        return self.rx_assigned if index == 0x1C12 else self.tx_assigned

    def _read_assignment(self, index: int, subindex: int) -> bytes:
        assigned = self._assignment(index)
        if subindex == 0:
            return bytes([len(assigned)])
        if 1 <= subindex <= MAX_ASSIGNED:
            staged = self.staged[index]
            pdo = assigned[subindex - 1] if subindex <= len(assigned) else staged.get(subindex, 0)
            return struct.pack("<H", pdo)
        raise SdoAbortError(ABORT_NO_SUBINDEX)

    def _write_assignment(self, index: int, subindex: int, data: bytes) -> None:
        """CiA 301: sub 0 := 0, then the entries, then sub 0 := their number; PRE-OP only."""
        if self.al_state() != AL_PREOP:
            raise SdoAbortError(ABORT_STATE, "the PDO assignment can be written in PRE-OP only")
        assigned = self._assignment(index)
        staged = self.staged[index]
        if subindex == 0:
            if len(data) != 1:
                raise SdoAbortError(ABORT_LENGTH, "sub 0 is UNSIGNED8")
            count = data[0]
            if count == 0:
                assigned.clear()
                staged.clear()
                return
            if assigned:
                raise SdoAbortError(ABORT_STATE, "write sub 0 := 0 first")
            if count > MAX_ASSIGNED or any(i not in staged for i in range(1, count + 1)):
                raise SdoAbortError(ABORT_VALUE_HIGH, f"{count} entries, not all written")
            assigned[:] = [staged[i] for i in range(1, count + 1)]
            return
        if not 1 <= subindex <= MAX_ASSIGNED:
            raise SdoAbortError(ABORT_NO_SUBINDEX)
        if len(data) != 2:
            raise SdoAbortError(ABORT_LENGTH, "entries are UNSIGNED16")
        if assigned:
            raise SdoAbortError(ABORT_STATE, "write sub 0 := 0 first")
        pdo = struct.unpack("<H", data)[0]
        maps = RXPDO_MAPS if index == 0x1C12 else TXPDO_MAPS
        if pdo not in maps:
            raise SdoAbortError(ABORT_VALUE_RANGE, f"no PDO 0x{pdo:04X} for 0x{index:04X}")
        staged[subindex] = pdo

    # --- layout --------------------------------------------------------------------------

    def output_layout(self) -> ImageLayout:
        return ImageLayout.of(RXPDO_MAPS, self.rx_assigned)

    def input_layout(self) -> ImageLayout:
        return ImageLayout.of(TXPDO_MAPS, self.tx_assigned)


def add_pdo_objects(od: ObjectDictionary) -> None:
    """The mapping objects (read only: the mapping of this device is fixed), 0x1C00."""
    for maps in (RXPDO_MAPS, TXPDO_MAPS):
        for pdo, (name, entries) in maps.items():
            od.record(
                pdo,
                name,
                (
                    Entry(pdo, n, f"SubIndex {n:03d}", UNSIGNED32, value=m.word)
                    for n, m in enumerate(entries, start=1)
                ),
            )
    od.record(
        0x1C00,
        "Sync manager type",
        (Entry(0x1C00, n, f"SubIndex {n:03d}", UNSIGNED8, value=n) for n in range(1, 5)),
    )


# --- the SDO server ---------------------------------------------------------------------

MAILBOX_HEADER = struct.Struct("<HHBB")  # length, address, channel/priority, type/counter
MBX_TYPE_ERROR: Final = 0x00
MBX_TYPE_COE: Final = 0x03
COE_SDO_REQUEST: Final = 2
COE_SDO_RESPONSE: Final = 3
# Mailbox error codes (ETG.1000.4): unsupported protocol, invalid header.
MBX_ERROR_UNSUPPORTED_PROTOCOL: Final = 0x0002
MBX_ERROR_INVALID_HEADER: Final = 0x0005


@dataclass(slots=True)
class _Transfer:
    index: int
    subindex: int
    data: bytearray
    toggle: int = 0
    total: int = 0  # download: the size announced


class SdoServer:
    """Answers one mailbox message at a time (``handle``: request -> reply message)."""

    def __init__(self, od: ObjectDictionary, mailbox_size: int) -> None:
        self.od = od
        self.mailbox_size = mailbox_size
        self._counter = 0
        self._upload: _Transfer | None = None
        self._download: _Transfer | None = None
        self.log: list[tuple[str, int, int, int]] = []  # (kind, index, subindex, abort/size)

    def _message(self, mbx_type: int, body: bytes) -> bytes:
        self._counter = self._counter % 7 + 1  # 1..7, 0 is reserved
        header = MAILBOX_HEADER.pack(len(body), 0, 0, mbx_type | self._counter << 4)
        return header + body

    def _coe(self, service: int, sdo: bytes) -> bytes:
        return self._message(MBX_TYPE_COE, struct.pack("<H", service << 12) + sdo)

    def _abort(self, index: int, subindex: int, code: int) -> bytes:
        self._upload = self._download = None
        self.log.append(("abort", index, subindex, code))
        body = struct.pack("<BHBI", 0x80, index, subindex, code)
        return self._coe(COE_SDO_REQUEST, body)  # service 2: what SOEM reads as an abort

    def _mailbox_error(self, code: int) -> bytes:
        return self._message(MBX_TYPE_ERROR, struct.pack("<HH", 0x01, code))

    def handle(self, message: bytes) -> bytes | None:
        """The reply to one write-mailbox message (None: nothing to answer)."""
        if len(message) < MAILBOX_HEADER.size:
            return self._mailbox_error(MBX_ERROR_INVALID_HEADER)
        length, _, _, type_counter = MAILBOX_HEADER.unpack_from(message)
        body = message[MAILBOX_HEADER.size : MAILBOX_HEADER.size + length]
        if type_counter & 0x0F != MBX_TYPE_COE:
            return self._mailbox_error(MBX_ERROR_UNSUPPORTED_PROTOCOL)
        if len(body) < 3:
            return self._mailbox_error(MBX_ERROR_INVALID_HEADER)
        service = struct.unpack_from("<H", body)[0] >> 12
        if service != COE_SDO_REQUEST:
            return self._mailbox_error(MBX_ERROR_UNSUPPORTED_PROTOCOL)
        sdo = body[2:]
        command = sdo[0]
        index, subindex = struct.unpack_from("<HB", sdo, 1) if len(sdo) >= 4 else (0, 0)
        ccs = command >> 5
        try:
            if ccs == 4:  # abort from the master
                self._upload = self._download = None
                return None
            if ccs == 2:
                return self._upload_initiate(command, index, subindex)
            if ccs == 3:
                return self._upload_segment(command)
            if ccs == 1:
                return self._download_initiate(command, index, subindex, sdo, length)
            if ccs == 0:
                return self._download_segment(command, sdo, length)
            raise SdoAbortError(ABORT_COMMAND, f"command 0x{command:02X}")
        except SdoAbortError as exc:
            if ccs in (0, 3):
                transfer = self._upload if ccs == 3 else self._download
                if transfer is not None:
                    index, subindex = transfer.index, transfer.subindex
            return self._abort(index, subindex, exc.code)

    # upload (read)

    def _upload_initiate(self, command: int, index: int, subindex: int) -> bytes:
        self._upload = None
        if command & 0x10:
            raise SdoAbortError(ABORT_UNSUPPORTED, "complete access is not supported")
        data = self.od.upload(index, subindex)
        self.log.append(("upload", index, subindex, len(data)))
        if 0 < len(data) <= 4:
            size_bits = (4 - len(data)) << 2
            body = struct.pack("<BHB", 0x43 | size_bits, index, subindex) + data.ljust(4, b"\0")
            return self._coe(COE_SDO_RESPONSE, body)
        # Normal: the size, then as much data as the mailbox holds; the rest in segments.
        room = self.mailbox_size - MAILBOX_HEADER.size - 10
        first = data[:room]
        body = struct.pack("<BHBI", 0x41, index, subindex, len(data)) + first
        if len(data) > room:
            self._upload = _Transfer(index, subindex, bytearray(data[room:]))
        return self._coe(COE_SDO_RESPONSE, body)

    def _upload_segment(self, command: int) -> bytes:
        transfer = self._upload
        if transfer is None:
            raise SdoAbortError(ABORT_COMMAND, "no upload in progress")
        toggle = command & 0x10
        if toggle != transfer.toggle:
            raise SdoAbortError(ABORT_TOGGLE)
        room = self.mailbox_size - MAILBOX_HEADER.size - 3
        chunk = bytes(transfer.data[:room])
        del transfer.data[:room]
        last = not transfer.data
        if last:
            self._upload = None
        else:
            transfer.toggle ^= 0x10
        unused = max(0, 7 - len(chunk))
        segment = bytes([toggle | unused << 1 | (1 if last else 0)]) + chunk.ljust(7, b"\0")
        return self._coe(COE_SDO_RESPONSE, segment)

    # download (write)

    def _download_initiate(
        self, command: int, index: int, subindex: int, sdo: bytes, length: int
    ) -> bytes:
        self._download = None
        if command & 0x10:
            raise SdoAbortError(ABORT_UNSUPPORTED, "complete access is not supported")
        if not self.od.has_index(index):
            raise SdoAbortError(ABORT_NO_OBJECT)
        expedited, size_indicated = command & 0x02, command & 0x01
        if expedited:
            size = 4 - ((command >> 2) & 0x03) if size_indicated else 4
            data = sdo[4 : 4 + size]
            self.od.download(index, subindex, data)
            self.log.append(("download", index, subindex, len(data)))
            return self._coe(COE_SDO_RESPONSE, struct.pack("<BHBI", 0x60, index, subindex, 0))
        total = struct.unpack_from("<I", sdo, 4)[0]
        data = sdo[8 : 8 + max(0, length - 10)]
        if len(data) >= total:
            self.od.download(index, subindex, data[:total])
            self.log.append(("download", index, subindex, total))
        else:
            self._download = _Transfer(index, subindex, bytearray(data), total=total)
        return self._coe(COE_SDO_RESPONSE, struct.pack("<BHBI", 0x60, index, subindex, 0))

    def _download_segment(self, command: int, sdo: bytes, length: int) -> bytes:
        transfer = self._download
        if transfer is None:
            raise SdoAbortError(ABORT_COMMAND, "no download in progress")
        toggle = command & 0x10
        if toggle != transfer.toggle:
            raise SdoAbortError(ABORT_TOGGLE)
        size = length - 3  # from the mailbox length; the size bits only below 7 bytes
        if size == 7:
            size -= (command >> 1) & 0x07
        transfer.data += sdo[1 : 1 + size]
        transfer.toggle ^= 0x10
        if command & 0x01:  # the last segment
            self._download = None
            if len(transfer.data) != transfer.total:
                raise SdoAbortError(
                    ABORT_LENGTH,
                    f"{len(transfer.data)} bytes arrived, {transfer.total} announced",
                )
            self.od.download(transfer.index, transfer.subindex, bytes(transfer.data))
            self.log.append(("download", transfer.index, transfer.subindex, transfer.total))
        body = bytes([0x20 | toggle]) + bytes(7)
        return self._coe(COE_SDO_RESPONSE, body)
