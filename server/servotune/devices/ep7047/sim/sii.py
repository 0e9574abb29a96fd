"""The SII (EEPROM) image of the simulated EP7047-1032 on the wire: the ESC
configuration area, the identity (vendor, product, revision, serial), the mailbox and
the categories SOEM reads (strings, general, FMMU, SyncManagers, TxPDO/RxPDO).

Facts a master relies on (SOEM 1.4): the slave's name is string #1 (the General
category's name index is not used for it); category codes are decimal (10, 30, 40,
41, 50, 51); the checksum (word 7) is not checked, but is computed as the ESC would.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Final

from servotune.devices.ep7047.sim import coe
from servotune.devices.ep7047.sim.coe import Mapped

# Identity (the spec: vendor 0x2 Beckhoff, product 0x1B874052 EP7047-1032).
VENDOR_BECKHOFF: Final = 0x0000_0002
PRODUCT_EP7047_1032: Final = 0x1B87_4052
REVISION: Final = 0x0010_0005
SERIAL: Final = 0x0000_2A2A
DEVICE_NAME: Final = "EP7047-1032"

MAILBOX_OUT: Final = 0x1000  # SM0: master -> slave
MAILBOX_IN: Final = 0x1080  # SM1: slave -> master
MAILBOX_SIZE: Final = 128
OUTPUTS_SM_START: Final = 0x1100
INPUTS_SM_START: Final = 0x1180


# --- SII -------------------------------------------------------------------------------

SII_STRINGS: Final = 10
SII_GENERAL: Final = 30
SII_FMMU: Final = 40
SII_SYNCM: Final = 41
SII_TXPDO: Final = 50
SII_RXPDO: Final = 51


def _crc8(data: bytes) -> int:
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def _category(code: int, data: bytes) -> bytes:
    if len(data) % 2:
        data += b"\x00"
    return struct.pack("<HH", code, len(data) // 2) + data


@dataclass(frozen=True, slots=True)
class Identity:
    vendor: int = VENDOR_BECKHOFF
    product: int = PRODUCT_EP7047_1032
    revision: int = REVISION
    serial: int = SERIAL
    name: str = DEVICE_NAME


def build_sii(identity: Identity) -> bytes:
    """The EEPROM image: ESC configuration area, identity, mailbox, categories."""
    words = bytearray(0x80)
    struct.pack_into("<HHHH", words, 0, 0x0C08, 0x0000, 0x0000, 0x0000)  # PDI: 16-bit uC
    struct.pack_into("<HH", words, 8, 0x0000, 0x0000)
    words[14] = _crc8(bytes(words[0:14]))  # word 7: checksum over words 0..6
    struct.pack_into(
        "<IIII",
        words,
        0x08 * 2,
        identity.vendor,
        identity.product,
        identity.revision,
        identity.serial,
    )
    struct.pack_into(
        "<HHHHH", words, 0x18 * 2, MAILBOX_OUT, MAILBOX_SIZE, MAILBOX_IN, MAILBOX_SIZE, 0x0004
    )  # standard mailbox, CoE
    struct.pack_into("<HH", words, 0x3E * 2, 15, 1)  # 16 kbit EEPROM, version 1
    strings = [identity.name, "Drives", f"{identity.name} stepper motor box, positioning"]
    blob = bytes([len(strings)]) + b"".join(bytes([len(s.encode())]) + s.encode() for s in strings)
    general = bytearray(32)
    general[0:4] = bytes([2, 0, 1, 3])  # group, image, order, name string indices
    general[5] = 0x05  # CoE details: SDO, PDO assign (no SDO info, no complete access)
    general[0x1C:0x1E] = struct.pack("<H", 0x0011)  # physical ports
    fmmu = bytes([1, 2, 3, 0xFF])  # outputs, inputs, mailbox state
    syncm = b"".join(
        struct.pack("<HHBBBB", start, length, control, 0, 0x01, 0)
        for start, length, control in (
            (MAILBOX_OUT, MAILBOX_SIZE, 0x26),
            (MAILBOX_IN, MAILBOX_SIZE, 0x22),
            (OUTPUTS_SM_START, 0, 0x64),  # buffered, write, watchdog trigger
            (INPUTS_SM_START, 0, 0x20),
        )
    )
    categories = [
        _category(SII_STRINGS, blob),
        _category(SII_GENERAL, bytes(general)),
        _category(SII_FMMU, fmmu),
        _category(SII_SYNCM, syncm),
        _category(SII_TXPDO, _sii_pdos(coe.TXPDO_MAPS, coe.DEFAULT_TX, 3)),
        _category(SII_RXPDO, _sii_pdos(coe.RXPDO_MAPS, coe.DEFAULT_RX, 2)),
    ]
    image = bytes(words) + b"".join(categories) + b"\xff\xff"
    return image.ljust(2048, b"\xff")


def _sii_pdos(
    maps: Mapping[int, tuple[str, tuple[Mapped, ...]]], default: tuple[int, ...], sm: int
) -> bytes:
    out = bytearray()
    for pdo, (_, entries) in maps.items():
        out += struct.pack("<HBBBBH", pdo, len(entries), sm if pdo in default else 0xFF, 0, 0, 0)
        for entry in entries:
            out += struct.pack("<HBBBBH", entry.index, entry.subindex, 0, 0, entry.bits, 0)
    return bytes(out)
