"""An EtherCAT slave controller (ESC) in software: the register space and datagram
handling of one slave, for the simulated EP7047-1032 on a real Ethernet interface.

Sans-IO: :meth:`Esc.process` takes the EtherCAT payload of one frame (after the
Ethernet header, EtherType 0x88A4) and returns it as the slave sends it on (data read,
working counters incremented, auto-increment addresses counted), or None when the frame
is no EtherCAT datagram frame. The application behind the ESC (the AL state machine,
the mailbox, the process data; ``servotune.devices.ep7047.sim.wire``) is an
:class:`EscApplication`.

What is emulated (ETG.1000.4, Beckhoff's ESC datasheet section II, as SOEM uses it):

* the 64 KiB address space: registers 0x0000-0x0FFF, process RAM from 0x1000; reads of
  any address, writes to read-only registers ignored (counted, as the hardware does);
* every datagram command: APRD/APWR/APRW (position addressing, the ADP counted up),
  FPRD/FPWR/FPRW (station address 0x0010), BRD/BWR/BRW (a broadcast read ORs the data
  in), LRD/LWR/LRW (logical, through the FMMUs), ARMW/FRMW (read here or write);
  working counter +1 for a read, +1 for a write, +2 for the write of a read-write;
* the EEPROM interface 0x0500-0x050F (read 4 or 8 bytes, write a word, reload) over an
  SII image given by the application;
* SyncManagers 0x0800+8n: mailbox mode (SM0 write, SM1 read: full flag 0x0805/0x080D
  bit 3, set when the last byte is written, cleared when the last byte is read, repeat
  request/acknowledge) and buffered mode (SM2 outputs, SM3 inputs). An SM disabled by
  the master (activate bit 0) or by the application (PDI deactivate) takes no access:
  a logical access to it is not counted (which is why the outputs' share of the
  working counter is missing outside OP);
* FMMUs 0x0600+16n, byte granular (bit offsets within a byte are not used by SOEM for
  byte-aligned slaves and not emulated);
* the process-data watchdog: divider 0x0400, time 0x0420 (defaults 2498 and 1000 =
  100 ms, as after power-on; a master may write them), restarted by every write to an
  SM whose watchdog trigger (control bit 6) is set; status 0x0440, counter 0x0442;
* DL status 0x0110 (port 0 open with communication and link, ports 1-3 closed),
  AL control/status 0x0120/0x0130/0x0134, the DC system time 0x0910 (nanoseconds of
  the slave's clock), receive times 0x0900 latched by a write to 0x0900, offset 0x0920
  and delay 0x0928 stored.

Not emulated: ports other than 0 (the frame always returns through port 0, the
slave is the end of the line), bit-granular FMMUs, the PDI and IRQ registers beyond
storing them, the ESC's own EEPROM checksum check (SOEM does not read it either).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Final, Protocol

ETHERTYPE_ECAT: Final = 0x88A4

# Datagram commands (ETG.1000.4).
NOP, APRD, APWR, APRW, FPRD, FPWR, FPRW, BRD, BWR, BRW, LRD, LWR, LRW, ARMW, FRMW = range(15)
_READS: Final = frozenset({APRD, FPRD, BRD, LRD, APRW, FPRW, BRW, LRW, ARMW, FRMW})
_WRITES: Final = frozenset({APWR, FPWR, BWR, LWR, APRW, FPRW, BRW, LRW})

# Registers.
REG_TYPE: Final = 0x0000
REG_FEATURES: Final = 0x0008
REG_STATION_ADDRESS: Final = 0x0010
REG_STATION_ALIAS: Final = 0x0012
REG_DL_CONTROL: Final = 0x0100
REG_DL_STATUS: Final = 0x0110
REG_AL_CONTROL: Final = 0x0120
REG_AL_STATUS: Final = 0x0130
REG_AL_STATUS_CODE: Final = 0x0134
REG_PDI_CONTROL: Final = 0x0140
REG_WD_DIVIDER: Final = 0x0400
REG_WD_TIME_PDI: Final = 0x0410
REG_WD_TIME_PD: Final = 0x0420
REG_WD_STATUS_PD: Final = 0x0440
REG_WD_COUNTER_PD: Final = 0x0442
REG_EEPROM_CONFIG: Final = 0x0500
REG_EEPROM_CONTROL: Final = 0x0502
REG_EEPROM_ADDRESS: Final = 0x0504
REG_EEPROM_DATA: Final = 0x0508
REG_FMMU0: Final = 0x0600
REG_SM0: Final = 0x0800
REG_DC_RECEIVE_TIME: Final = 0x0900
REG_DC_SYSTEM_TIME: Final = 0x0910
REG_DC_SYSTEM_OFFSET: Final = 0x0920
REG_DC_SYSTEM_DELAY: Final = 0x0928
PROCESS_RAM: Final = 0x1000
MEMORY_SIZE: Final = 0x10000
FMMU_COUNT: Final = 8
SM_COUNT: Final = 8

# EEPROM control/status bits (0x0502).
EEPROM_READ_8_BYTES: Final = 0x0040
EEPROM_CMD_MASK: Final = 0x0700
EEPROM_CMD_READ: Final = 0x0100
EEPROM_CMD_WRITE: Final = 0x0200
EEPROM_CMD_RELOAD: Final = 0x0300
EEPROM_ERROR_COMMAND: Final = 0x2000
EEPROM_BUSY: Final = 0x8000

# SyncManager control/status bits.
SM_MODE_MASK: Final = 0x03
SM_MODE_MAILBOX: Final = 0x02
SM_DIRECTION_WRITE: Final = 0x04  # bits 2-3 = 01: the master writes
SM_WATCHDOG_TRIGGER: Final = 0x40
SM_STATUS_FULL: Final = 0x08
SM_ACTIVATE_ENABLE: Final = 0x01
SM_ACTIVATE_REPEAT: Final = 0x02
SM_PDI_DEACTIVATE: Final = 0x01
SM_PDI_REPEAT_ACK: Final = 0x02

# Write masks: which bytes the master may write (1) - everything else is read only.
_WRITABLE: Final = (
    (0x0010, 0x0014),  # station address, alias
    (0x0100, 0x0104),  # DL control
    (0x0120, 0x0122),  # AL control
    (0x0200, 0x0204),  # ECAT event mask
    (0x0300, 0x0314),  # error counters (a write clears them)
    (0x0400, 0x0402),  # watchdog divider
    (0x0410, 0x0412),  # PDI watchdog time
    (0x0420, 0x0422),  # process-data watchdog time
    (0x0442, 0x0444),  # watchdog counters (a write clears them)
    (0x0500, 0x0501),  # EEPROM configuration
    (0x0502, 0x0510),  # EEPROM control, address, data
    (0x0600, 0x0700),  # FMMUs
    (0x0900, 0x0904),  # DC receive time latch (a write latches)
    (0x0910, 0x0918),  # DC system time (a write is a drift compensation sample)
    (0x0920, 0x0930),  # DC offset, delay
    (0x0930, 0x0936),  # DC speed counter, filter depths
    (0x0980, 0x0982),  # DC activation
    (0x0990, 0x09A8),  # DC sync times
    (PROCESS_RAM, MEMORY_SIZE),
)


def _writable_map() -> bytearray:
    mask = bytearray(MEMORY_SIZE)
    for start, end in _WRITABLE:
        mask[start:end] = b"\x01" * (end - start)
    for n in range(SM_COUNT):  # start, length, control and activate; not status, PDI
        base = REG_SM0 + 8 * n
        mask[base : base + 5] = b"\x01" * 5
        mask[base + 6] = 1
    return mask


class EscApplication(Protocol):
    """What the ESC calls in the slave's application (its PDI side)."""

    def al_control(self, value: int) -> None:
        """The master wrote the AL control register 0x0120."""
        ...

    def mailbox_written(self, data: bytes) -> None:
        """The write mailbox (SM0) is full: ``data`` is its whole area."""
        ...

    def mailbox_read(self) -> None:
        """The read mailbox (SM1) was read to its end: it is empty again."""
        ...

    def mailbox_repeat(self) -> None:
        """The master asks for the last read-mailbox message again (repeat request)."""
        ...

    def outputs_written(self, sm: int) -> None:
        """A buffered write SyncManager (outputs) got its last byte in this frame."""
        ...


class Esc:
    """The register space of one slave controller; see the module docstring.

    ``clock_ns`` is the slave's local time in nanoseconds (the DC system time and the
    watchdog count with it). ``sii`` is the EEPROM image (bytes, word-addressed by the
    master).
    """

    def __init__(self, sii: bytes, clock_ns: Callable[[], int]) -> None:
        self.memory = bytearray(MEMORY_SIZE)
        self._writable = _writable_map()
        self.sii = bytearray(sii)
        self._clock_ns = clock_ns
        self.app: EscApplication | None = None
        self._frame_dirty_outputs: set[int] = set()
        self._watchdog_start_ns = clock_ns()
        self._watchdog_armed = False
        self._dc_offset_ns = 0
        self.frames = 0
        self._reset_registers()

    # --- registers --------------------------------------------------------------------

    def _reset_registers(self) -> None:
        m = self.memory
        m[REG_TYPE] = 0x11  # ET1100-like
        m[0x0001] = 0x02  # revision
        m[0x0004] = FMMU_COUNT
        m[0x0005] = SM_COUNT
        m[0x0006] = 8  # KiB of process RAM
        m[0x0007] = 0x0F  # ports 0 and 1 MII/EBUS
        # Features: FMMU bytewise, DC supported (bit 2), 64-bit DC (bit 3), enhanced
        # link detection.
        struct.pack_into("<H", m, REG_FEATURES, 0x01CC)
        # DL status: PDI operational (EEPROM loaded), physical link and communication on
        # port 0, ports 1-3 closed (their loop bit set, no communication): the end of
        # the line. SOEM reads the topology from bits 8-15.
        dl_status = 0x0001 | 0x0010 | 0x0200 | 0x0400 | 0x1000 | 0x4000
        struct.pack_into("<H", m, REG_DL_STATUS, dl_status)
        struct.pack_into("<H", m, REG_AL_STATUS, 0x0001)  # INIT
        m[REG_PDI_CONTROL] = 0x08  # 16-bit asynchronous microcontroller interface
        struct.pack_into("<H", m, REG_WD_DIVIDER, 2498)  # 25 MHz / 2500: 100 us ticks
        struct.pack_into("<H", m, REG_WD_TIME_PDI, 1000)
        struct.pack_into("<H", m, REG_WD_TIME_PD, 1000)  # 100 ms
        struct.pack_into("<H", m, REG_WD_STATUS_PD, 0x0001)  # not expired
        struct.pack_into("<H", m, REG_EEPROM_CONTROL, EEPROM_READ_8_BYTES)

    def u8(self, address: int) -> int:
        return self.memory[address]

    def u16(self, address: int) -> int:
        value: int = struct.unpack_from("<H", self.memory, address)[0]
        return value

    def set_u16(self, address: int, value: int) -> None:
        struct.pack_into("<H", self.memory, address, value)

    def set_al_status(self, state: int, code: int) -> None:
        """The application's AL status (state | 0x10 for an error indication) and code."""
        self.set_u16(REG_AL_STATUS, state)
        self.set_u16(REG_AL_STATUS_CODE, code)

    # --- SyncManagers (application side) ------------------------------------------------

    def sm(self, n: int) -> tuple[int, int, int]:
        """(start, length, control) of SyncManager ``n`` as the master configured it."""
        base = REG_SM0 + 8 * n
        start, length, control = struct.unpack_from("<HHB", self.memory, base)
        return start, length, control

    def sm_enabled(self, n: int) -> bool:
        base = REG_SM0 + 8 * n
        return bool(self.memory[base + 6] & SM_ACTIVATE_ENABLE) and not (
            self.memory[base + 7] & SM_PDI_DEACTIVATE
        )

    def set_sm_pdi_enabled(self, n: int, enabled: bool) -> None:
        """The application (de)activates SyncManager ``n`` (0x0807+8n bit 0)."""
        base = REG_SM0 + 8 * n + 7
        if enabled:
            self.memory[base] &= ~SM_PDI_DEACTIVATE & 0xFF
        else:
            self.memory[base] |= SM_PDI_DEACTIVATE
            self.memory[base - 2] &= ~SM_STATUS_FULL & 0xFF  # a deactivated SM is empty

    def sm_full(self, n: int) -> bool:
        return bool(self.memory[REG_SM0 + 8 * n + 5] & SM_STATUS_FULL)

    def _set_full(self, n: int, full: bool) -> None:
        status = REG_SM0 + 8 * n + 5
        if full:
            self.memory[status] |= SM_STATUS_FULL
        else:
            self.memory[status] &= ~SM_STATUS_FULL & 0xFF

    def put_mailbox(self, n: int, data: bytes) -> bool:
        """The application writes ``data`` into read mailbox ``n`` (SM1); False when it
        is still full (the master has not read the last one)."""
        start, length, _ = self.sm(n)
        if self.sm_full(n) or not self.sm_enabled(n) or length == 0:
            return False
        padded = data[:length].ljust(length, b"\x00")
        self.memory[start : start + length] = padded
        self._set_full(n, True)
        return True

    def take_mailbox(self, n: int) -> None:
        """The application has read write mailbox ``n`` (SM0): empty again."""
        self._set_full(n, False)

    def sm_data(self, n: int) -> bytes:
        start, length, _ = self.sm(n)
        return bytes(self.memory[start : start + length])

    def write_sm_data(self, n: int, data: bytes) -> None:
        """The application writes a buffered read SM's area (the inputs)."""
        start, length, _ = self.sm(n)
        self.memory[start : start + min(length, len(data))] = data[:length]

    # --- watchdog -------------------------------------------------------------------------

    @property
    def watchdog_ns(self) -> int:
        """The process-data watchdog time (0 = disabled), from 0x0400 and 0x0420."""
        ticks = self.u16(REG_WD_TIME_PD)
        divider = self.u16(REG_WD_DIVIDER)
        return ticks * (divider + 2) * 40  # 25 MHz: 40 ns a clock

    def arm_watchdog(self, armed: bool) -> None:
        """The application starts (OP) or stops watching the process data."""
        self._watchdog_armed = armed
        self._watchdog_start_ns = self._clock_ns()
        self.set_u16(REG_WD_STATUS_PD, 0x0001)

    def watchdog_expired(self) -> bool:
        """True once the armed watchdog ran out (latched until it is armed again)."""
        limit = self.watchdog_ns
        if not self._watchdog_armed or limit == 0:
            return False
        if self._clock_ns() - self._watchdog_start_ns <= limit:
            return False
        if self.u16(REG_WD_STATUS_PD) & 1:
            self.set_u16(REG_WD_STATUS_PD, 0x0000)
            counter = min(self.u8(REG_WD_COUNTER_PD) + 1, 0xFF)
            self.memory[REG_WD_COUNTER_PD] = counter
        return True

    def watchdog_remaining_ns(self) -> int | None:
        """Nanoseconds until the armed watchdog expires (None: not armed)."""
        limit = self.watchdog_ns
        if not self._watchdog_armed or limit == 0:
            return None
        return self._watchdog_start_ns + limit - self._clock_ns()

    # --- frames ---------------------------------------------------------------------------

    def process(self, payload: bytearray) -> bool:
        """Process the EtherCAT frame ``payload`` in place (EtherCAT header first);
        False when it is not a datagram frame (then it passes unchanged)."""
        if len(payload) < 2:
            return False
        header = payload[0] | payload[1] << 8
        length, frame_type = header & 0x07FF, header >> 12
        if frame_type != 1 or length + 2 > len(payload):
            return False
        self.frames += 1
        now_ns = self._clock_ns()
        self._frame_dirty_outputs.clear()
        offset = 2
        end = 2 + length
        while offset + 12 <= end:
            command = payload[offset]
            address = payload[offset + 2 : offset + 6]
            size_word = payload[offset + 6] | payload[offset + 7] << 8
            size = size_word & 0x07FF
            more = size_word & 0x8000
            data_start = offset + 10
            data_end = data_start + size
            if data_end + 2 > end:
                break  # malformed: leave the rest as it is
            wkc_add, new_address = self._datagram(
                command, bytes(address), payload, data_start, size, now_ns
            )
            if new_address is not None:
                payload[offset + 2 : offset + 4] = struct.pack("<H", new_address)
            if wkc_add:
                wkc = (payload[data_end] | payload[data_end + 1] << 8) + wkc_add
                payload[data_end : data_end + 2] = struct.pack("<H", wkc & 0xFFFF)
            offset = data_end + 2
            if not more:
                break
        app = self.app
        if app is not None:
            for sm in sorted(self._frame_dirty_outputs):
                app.outputs_written(sm)
        return True

    def _datagram(
        self, command: int, address: bytes, frame: bytearray, start: int, size: int, now_ns: int
    ) -> tuple[int, int | None]:
        """Execute one datagram on ``frame[start:start+size]``: (working counter to add,
        the new ADP for position-addressed and broadcast commands)."""
        adp, ado = struct.unpack("<HH", address)
        if command in (APRD, APWR, APRW, ARMW):
            addressed = adp == 0
            new_adp = (adp + 1) & 0xFFFF
            if command == ARMW:
                return self._read_multiple_write(addressed, ado, frame, start, size), new_adp
            return self._physical(command, addressed, ado, frame, start, size, now_ns), new_adp
        if command in (FPRD, FPWR, FPRW, FRMW):
            addressed = adp == self.u16(REG_STATION_ADDRESS)
            if command == FRMW:
                return self._read_multiple_write(addressed, ado, frame, start, size), None
            return self._physical(command, addressed, ado, frame, start, size, now_ns), None
        if command in (BRD, BWR, BRW):
            new_adp = (adp + 1) & 0xFFFF
            return self._physical(command, True, ado, frame, start, size, now_ns), new_adp
        if command in (LRD, LWR, LRW):
            logical = adp | ado << 16
            return self._logical(command, logical, frame, start, size), None
        return 0, None

    def _read_multiple_write(
        self, addressed: bool, ado: int, frame: bytearray, start: int, size: int
    ) -> int:
        # The addressed slave reads (the DC reference clock); all others write.
        if addressed:
            self._refresh_dc(ado, size)
            data = self._read_physical(ado, size)
            if data is None:
                return 0
            frame[start : start + size] = data
        else:
            self._write_physical(ado, bytes(frame[start : start + size]), self._clock_ns())
        return 1

    def _physical(
        self,
        command: int,
        addressed: bool,
        ado: int,
        frame: bytearray,
        start: int,
        size: int,
        now_ns: int,
    ) -> int:
        if not addressed or ado + size > MEMORY_SIZE:
            return 0
        wkc = 0
        written = bytes(frame[start : start + size])
        if command in _READS:
            self._refresh_dc(ado, size)
            data = self._read_physical(ado, size)
            if data is not None:
                if command in (BRD, BRW):
                    frame[start : start + size] = bytes(
                        a | b for a, b in zip(frame[start : start + size], data, strict=True)
                    )
                else:
                    frame[start : start + size] = data
                wkc += 1
        if command in _WRITES and self._write_physical(ado, written, now_ns):
            wkc += 2 if command in (APRW, FPRW, BRW) else 1
        return wkc

    def _logical(self, command: int, logical: int, frame: bytearray, start: int, size: int) -> int:
        read_hit = write_hit = False
        end = logical + size
        for n in range(FMMU_COUNT):
            base = REG_FMMU0 + 16 * n
            log_start, log_len, _, _, phys, _, kind, active = struct.unpack_from(
                "<IHBBHBBB", self.memory, base
            )
            if not active or log_len == 0:
                continue
            lo, hi = max(logical, log_start), min(end, log_start + log_len)
            if lo >= hi:
                continue
            frame_lo = start + lo - logical
            phys_lo = phys + lo - log_start
            count = hi - lo
            if kind & 0x01 and command in (LRD, LRW):
                data = self._read_physical(phys_lo, count)
                if data is not None:
                    frame[frame_lo : frame_lo + count] = data
                    read_hit = True
            if (
                kind & 0x02
                and command in (LWR, LRW)
                and self._write_ram(phys_lo, bytes(frame[frame_lo : frame_lo + count]))
            ):
                write_hit = True
        if not write_hit:
            return 1 if read_hit else 0
        return (1 if read_hit else 0) + (2 if command == LRW else 1)

    # --- memory access with side effects ------------------------------------------------

    def _sm_at(self, address: int, size: int) -> list[tuple[int, int, int, int]]:
        """SyncManagers whose area overlaps [address, address+size): (n, start, length,
        control)."""
        hits = []
        for n in range(SM_COUNT):
            start, length, control = self.sm(n)
            if length and start < address + size and address < start + length:
                hits.append((n, start, length, control))
        return hits

    def _read_physical(self, address: int, size: int) -> bytes | None:
        """Master read; None when an SM refuses it (disabled, or an empty mailbox)."""
        if address >= PROCESS_RAM:
            for n, start, length, control in self._sm_at(address, size):
                if not self.sm_enabled(n):
                    return None
                if control & SM_DIRECTION_WRITE:
                    continue  # reading back a write area: no side effect
                if control & SM_MODE_MASK == SM_MODE_MAILBOX:
                    if not self.sm_full(n):
                        return None
                    if address + size >= start + length:  # the last byte: read out
                        data = bytes(self.memory[address : address + size])
                        self._set_full(n, False)
                        if self.app is not None:
                            self.app.mailbox_read()
                        return data
        return bytes(self.memory[address : address + size])

    def _write_physical(self, address: int, data: bytes, now_ns: int) -> bool:
        """Master write; False when an SM refuses it."""
        size = len(data)
        if address >= PROCESS_RAM:
            return self._write_ram(address, data)
        touches_al_control = address <= REG_AL_CONTROL < address + size
        repeat_before = self.memory[REG_SM0 + 8 + 6] & SM_ACTIVATE_REPEAT
        for i, byte in enumerate(data):
            target = address + i
            if self._writable[target]:
                self.memory[target] = byte
        self._register_side_effects(address, size, now_ns, repeat_before)
        if touches_al_control and self.app is not None:
            self.app.al_control(self.u16(REG_AL_CONTROL))
        return True

    def _write_ram(self, address: int, data: bytes) -> bool:
        size = len(data)
        hits = self._sm_at(address, size)
        for n, _, _, control in hits:
            if not self.sm_enabled(n) or not control & SM_DIRECTION_WRITE:
                return False
            if control & SM_MODE_MASK == SM_MODE_MAILBOX and self.sm_full(n):
                return False  # the application has not read the last one yet
        self.memory[address : address + size] = data
        for n, start, length, control in hits:
            if address + size < start + length:
                continue  # not the last byte: the buffer is not complete yet
            if control & SM_WATCHDOG_TRIGGER:
                self._watchdog_start_ns = self._clock_ns()
            if control & SM_MODE_MASK == SM_MODE_MAILBOX:
                self._set_full(n, True)
                if self.app is not None:
                    self.app.mailbox_written(bytes(self.memory[start : start + length]))
            else:
                self._frame_dirty_outputs.add(n)
        return True

    def _register_side_effects(
        self, address: int, size: int, now_ns: int, repeat_before: int
    ) -> None:
        end = address + size
        if address <= REG_EEPROM_CONTROL + 1 and end > REG_EEPROM_CONTROL:
            self._eeprom_command()
        if address <= REG_DC_RECEIVE_TIME < end:
            # A write to 0x0900 latches the receive time of this frame on every port.
            local = now_ns & 0xFFFFFFFF
            for port in range(4):
                struct.pack_into("<I", self.memory, REG_DC_RECEIVE_TIME + 4 * port, local)
            struct.pack_into("<Q", self.memory, 0x0918, now_ns)  # receive time ECAT unit
        if address < REG_DC_SYSTEM_OFFSET + 8 and end > REG_DC_SYSTEM_OFFSET:
            self._dc_offset_ns = struct.unpack_from("<q", self.memory, REG_DC_SYSTEM_OFFSET)[0]
        if address <= 0x0300 < end or (address < 0x0314 and end > 0x0300):
            self.memory[0x0300:0x0314] = bytes(0x14)  # error counters: a write clears
        if address < REG_WD_COUNTER_PD + 2 and end > REG_WD_COUNTER_PD:
            self.memory[REG_WD_COUNTER_PD : REG_WD_COUNTER_PD + 2] = b"\x00\x00"
        # The read mailbox's repeat request (0x080E bit 1) toggled: the master lost a
        # reply; the application puts it in again, then the ESC acknowledges.
        repeat = self.memory[REG_SM0 + 8 + 6] & SM_ACTIVATE_REPEAT
        if repeat != repeat_before:
            if self.app is not None:
                self.app.mailbox_repeat()
            pdi = REG_SM0 + 8 + 7
            if repeat:
                self.memory[pdi] |= SM_PDI_REPEAT_ACK
            else:
                self.memory[pdi] &= ~SM_PDI_REPEAT_ACK & 0xFF

    def _refresh_dc(self, address: int, size: int) -> None:
        if address < REG_DC_SYSTEM_TIME + 8 and address + size > REG_DC_SYSTEM_TIME:
            system = (self._clock_ns() + self._dc_offset_ns) & 0xFFFF_FFFF_FFFF_FFFF
            struct.pack_into("<Q", self.memory, REG_DC_SYSTEM_TIME, system)

    # --- EEPROM -------------------------------------------------------------------------

    def _eeprom_command(self) -> None:
        control = self.u16(REG_EEPROM_CONTROL)
        command = control & EEPROM_CMD_MASK
        status = EEPROM_READ_8_BYTES  # never busy: the command completes at once
        word = struct.unpack_from("<I", self.memory, REG_EEPROM_ADDRESS)[0]
        if command == EEPROM_CMD_READ:
            data = bytes(self.sii[2 * word : 2 * word + 8]).ljust(8, b"\xff")
            self.memory[REG_EEPROM_DATA : REG_EEPROM_DATA + 8] = data
        elif command == EEPROM_CMD_WRITE:
            if control & 0x0001:  # write enable, in the same access
                value = self.memory[REG_EEPROM_DATA : REG_EEPROM_DATA + 2]
                if 2 * word + 2 <= len(self.sii):
                    self.sii[2 * word : 2 * word + 2] = value
            else:
                status |= EEPROM_ERROR_COMMAND
        elif command not in (0, EEPROM_CMD_RELOAD):
            status |= EEPROM_ERROR_COMMAND
        self.set_u16(REG_EEPROM_CONTROL, status)
