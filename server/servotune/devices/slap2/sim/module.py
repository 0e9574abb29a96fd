"""SLAP2 firmware emulation: one module (``Slap2Module``).

The seam: a module is a motion controller with a host interface in front of it. The
controller (the 841.5 us tick: profile generator, PID, in-position, limit switches,
calibration, idle fast path) and the manual's constants it runs on are in
``devices/slap2/sim/controller.py`` (``Slap2Controller``). Here is the host interface on top - line
parser (echo, Ctrl-X, Ctrl-K, ``se``), command table, replies, EEPROM file, power-on
reset and banner. ``Slap2Module`` has a ``Slap2Controller`` (``controller``): it decides
what a command may do (the refusals, ``uc``) and commands the controller through that
class's public methods. The RS232 line the modules share, ``Slap2Line``, is in
``devices/slap2/sim/line.py`` on top of this one.

Sans-IO: nothing here reads a clock or touches a file descriptor (except the optional
EEPROM file). The modules are driven in simulation time by ``Slap2Line`` through the
``SimDevice`` contract (``advance_to`` / ``receive``); ``PtySimulator`` puts the line on a
real pseudo-terminal with wire timing. Every decision where the manual is silent is
listed in docs/simulator.md; the important ones are repeated next to the code that
implements them. Units: see ``devices/slap2/sim/controller.py``.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Final

# The manual's constants from the codec, their one home (devices/slap2/sim/controller.py
# says why the simulator stays an independent oracle all the same).
from servotune.devices.slap2.codec import (
    CR,
    CTRL_K,
    CTRL_X,
    MAX_ADDRESS,
    POSITION_LIMIT,
    REFUSED_REPLY,
)
from servotune.devices.slap2.sim.controller import (
    FACTORY_DEFAULTS,
    HEX,
    INV1,
    INV2,
    L1ON,
    L2ON,
    PWM_MAX,
    SETTING_RANGES,
    UCON,
    Slap2Controller,
)
from servotune.sim.physics import DcMotor, DcMotorParams

logger = logging.getLogger(__name__)

SPACE: Final = 0x20

SOFTWARE_VERSION: Final = 2205
HARDWARE_VERSION: Final = 2209
DEFAULT_SERIAL_BASE: Final = 10000  # default serial number = base + address
_MAX_LINE_CHARS: Final = 40  # longer input is refused at CR (a real buffer is finite)

SYSCON_NAMES: Final = ("l1on", "l2on", "inv1", "inv2", "hex", "ucon")
RSS_NAMES: Final = ("limit1", "limit2", "vm", "pm", "move", "inpos", "cal", "oc", "uc")

_Reply = None | int | str | list[str]


class _RefusedError(Exception):
    """The command is unknown or not executable: sets ``uc``, changes nothing."""


def format_number(value: int, hex_mode: bool) -> str:
    """Decimal, or ``0x3E8`` / ``-0x3E8`` in hex mode."""
    if not hex_mode:
        return str(value)
    return f"-0x{-value:X}" if value < 0 else f"0x{value:X}"


def _parse_argument(text: str) -> int | None:
    if not text:
        return None
    digits = text[1:] if text[0] in "+-" else text
    if not digits.isdigit() or not digits.isascii():
        raise _RefusedError
    return int(text, 10)


def _split(line: str) -> tuple[str, str]:
    """``"sv-100"`` -> ``("sv", "-100")``: the mnemonic is the leading run of letters."""
    letters = 0
    while letters < len(line) and "a" <= line[letters] <= "z":
        letters += 1
    return line[:letters], line[letters:]


def _in_range(value: int | None, minimum: int, maximum: int) -> int:
    if value is None or not minimum <= value <= maximum:
        raise _RefusedError
    return value


def _no_argument(value: int | None) -> None:
    if value is not None:
        raise _RefusedError


class Slap2Module:
    """Firmware of one SLAP2 module driving one simulated motor.

    Contract:

    * ``receive(byte)`` handles one host byte and returns what *this* module transmits
      (echo, reply); a module whose transmitter is off still parses every line so it
      can react to ``se``.
    * ``tick()`` runs one 841.5 us controller cycle (profile generator, PID, inpos,
      limit switches, calibration) and integrates the motor over the cycle
      (``controller.tick``); ``run_ticks(n)`` is ``n`` of them.
    * ``take_output()`` returns unsolicited bytes (the power-on banner of address 0).
    * ``power_cycle()`` is a reset: RAM settings from the EEPROM, counter 0, modes off,
      cal flag 0. The motor shaft keeps its physical angle.

    The read-only properties (``position``, ``rss``, ``in_position`` ...) let tests and
    demos observe the firmware without going through the wire.
    """

    def __init__(
        self,
        address: int = 0,
        *,
        serial_number: int | None = None,
        eeprom_path: Path | None = None,
        params: DcMotorParams | None = None,
        motor: DcMotor | None = None,
    ) -> None:
        """``params`` configures the plant (load inertia, friction, switches, lines,
        supply); alternatively pass a ready ``motor``. ``eeprom_path`` is the JSON file
        that plays the EEPROM (``None``: kept in memory, lost with the object)."""
        if not 0 <= address <= MAX_ADDRESS:
            raise ValueError(f"address must be 0..{MAX_ADDRESS}")
        if params is not None and motor is not None:
            raise ValueError("give params or a motor, not both")
        self.address = address
        self.serial_number = (
            serial_number if serial_number is not None else DEFAULT_SERIAL_BASE + address
        )
        self.eeprom_path = eeprom_path
        self._memory_eeprom: dict[str, int] | None = None
        self.controller = Slap2Controller(motor if motor is not None else DcMotor(params))
        self._commands = self._command_table()
        # Everything below is (re)initialised by power_cycle(); listed for clarity.
        self._buffer = bytearray()
        self._overflow = False
        self._transmitting = False
        self._pending = bytearray()
        self._uc = False
        self.power_cycle()

    # --- the controller -----------------------------------------------------------

    @property
    def motor(self) -> DcMotor:
        return self.controller.motor

    def tick(self) -> None:
        """One 841.5 us controller cycle (``Slap2Controller.tick``)."""
        self.controller.tick()

    def run_ticks(self, n: int) -> None:
        """``n`` controller cycles (``Slap2Controller.run_ticks``)."""
        self.controller.run_ticks(n)

    # --- observation ----------------------------------------------------------------

    @property
    def position(self) -> int:
        """The position counter as ``rp`` reports it."""
        return self.controller.position

    @property
    def setpoint(self) -> int:
        """The profile generator's setpoint in counter units."""
        return self.controller.setpoint

    @property
    def following_error(self) -> int:
        """``pe``: setpoint minus actual position."""
        return self.controller.following_error

    @property
    def in_position(self) -> bool:
        return self.controller.in_position

    @property
    def moving(self) -> bool:
        return self.controller.moving

    @property
    def calibrated(self) -> bool:
        return self.controller.calibrated

    @property
    def calibrating(self) -> bool:
        return self.controller.calibrating

    @property
    def current_limited(self) -> bool:
        return self.controller.current_limited

    @property
    def pwm(self) -> int:
        """The PWM value applied during the last tick (-255..255, 0 when unpowered)."""
        return self.controller.pwm

    @property
    def transmitting(self) -> bool:
        """The module's RS232 transmitter is on (it is the selected module)."""
        return self._transmitting

    @property
    def settings(self) -> dict[str, int]:
        """A copy of the RAM settings (the ``pg`` set)."""
        return self.controller.settings

    @property
    def rss(self) -> int:
        """The ``rss`` status word as it would be read now."""
        c = self.controller
        return (
            c.limit1_level
            | c.limit2_level << 1
            | c.velocity_mode << 2
            | c.position_mode << 3
            | c.moving << 4
            | c.in_position << 5
            | c.calibrated << 6
            | c.current_limited << 7
            | self._uc << 8
        )

    @property
    def ss(self) -> int:
        """The legacy ``ss`` status byte as it would be read now."""
        c = self.controller
        syscon = c.setting("syscon")
        return (
            c.limit1_level
            | c.limit2_level << 1
            | c.velocity_mode << 2
            | c.position_mode << 3
            | c.moving << 4
            | c.decelerating << 5
            | ((syscon & (L1ON | L2ON)) == (L1ON | L2ON)) << 6
            | self._uc << 7
        )

    # --- power and EEPROM -------------------------------------------------------------

    def banner(self) -> bytes:
        """The power-on line address 0 sends."""
        text = f"SLAP2 V{SOFTWARE_VERSION} HW{HARDWARE_VERSION} SN{self.serial_number}"
        return text.encode("ascii") + b"\r\n"

    def identification(self) -> str:
        """The ``id`` reply: module type, software and hardware version, serial number."""
        return f"SLAP2 SW{SOFTWARE_VERSION} HW{HARDWARE_VERSION} SN{self.serial_number}"

    def power_cycle(self) -> None:
        """Reset as at power-on (see the class docstring)."""
        self.controller.reset(self._read_eeprom())
        self._buffer.clear()
        self._overflow = False
        self._pending.clear()
        self._transmitting = self.address == 0
        if self.address == 0:
            self._pending += self.banner()
        self._uc = False

    def _read_eeprom(self) -> dict[str, int]:
        stored: object = None
        if self.eeprom_path is None:
            stored = self._memory_eeprom
        else:
            try:
                stored = json.loads(self.eeprom_path.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                # missing (blank, erased by de), unreadable or corrupt: factory defaults
                stored = None
            stored = stored.get("settings") if isinstance(stored, dict) else None
        settings = dict(FACTORY_DEFAULTS)
        if isinstance(stored, dict):
            for name, (minimum, maximum) in SETTING_RANGES.items():
                value = stored.get(name)
                # a value outside its range is a corrupt cell: keep the default there
                if isinstance(value, bool) or not isinstance(value, int):
                    continue
                if minimum <= value <= maximum:
                    settings[name] = value
        return settings

    def _write_eeprom(self, settings: dict[str, int] | None) -> None:
        if self.eeprom_path is None:
            self._memory_eeprom = None if settings is None else dict(settings)
            return
        if settings is None:
            self.eeprom_path.unlink(missing_ok=True)
            return
        document = {
            "format": "servotune-slap2-eeprom",
            "version": 1,
            "address": self.address,
            "serial": self.serial_number,
            "settings": settings,
        }
        self.eeprom_path.parent.mkdir(parents=True, exist_ok=True)
        temporary = self.eeprom_path.with_name(self.eeprom_path.name + ".tmp")
        temporary.write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
        os.replace(temporary, self.eeprom_path)  # never leave a half-written EEPROM

    # --- serial input -----------------------------------------------------------------

    def take_output(self) -> bytes:
        """Unsolicited bytes waiting to be sent (the banner); empties the queue."""
        if not self._pending:
            return b""
        data = bytes(self._pending)
        self._pending.clear()
        return data

    def receive(self, byte: int) -> bytes:
        """One host byte arrived; returns this module's transmission (see class doc)."""
        self.controller.wake()  # a command may change anything the controller reads
        out = bytearray(self._pending)
        self._pending.clear()
        if self._transmitting:
            out.append(byte)  # every byte is echoed, control characters included
        if byte == CR:
            line = self._buffer.decode("latin-1").lower()
            overflow = self._overflow
            self._buffer.clear()
            self._overflow = False
            if self._transmitting:
                out += self._execute(line, overflow)
            elif self._listen(line):
                out.append(CR)  # selected by se: transmitter on, reply CR
        elif byte == CTRL_X:
            self._buffer.clear()
            self._overflow = False
        elif byte == CTRL_K:
            if self._transmitting and self.controller.calibrating:
                self.controller.abort_calibration()
        elif byte == SPACE or byte < SPACE:
            pass  # spaces are filtered on reception; so are LF and other controls
        elif len(self._buffer) < _MAX_LINE_CHARS:
            self._buffer.append(byte)
        else:
            self._overflow = True
        return bytes(out)

    def _listen(self, line: str) -> bool:
        """A deselected module reacts to ``se <own address>`` only; True if selected."""
        mnemonic, argument_text = _split(line)
        if mnemonic != "se":
            return False
        try:
            address = _parse_argument(argument_text)
        except _RefusedError:
            return False
        self._transmitting = address == self.address
        return self._transmitting

    def _execute(self, line: str, overflow: bool) -> bytes:
        if not line and not overflow:
            # No command (a bare CR, or CR after Ctrl-X): the echo is all, uc untouched.
            return b""
        mnemonic, argument_text = _split(line)
        handler = self._commands.get(mnemonic)
        try:
            if handler is None or overflow:
                raise _RefusedError
            reply = handler(_parse_argument(argument_text))
        except _RefusedError:
            self._uc = True
            if self.controller.setting("syscon") & UCON:
                return REFUSED_REPLY.encode("ascii") + b"\r"
            return b"\r"
        if mnemonic not in ("rss", "ss", "rrss"):
            self._uc = False
        if not self._transmitting:
            return b""  # se to another address: transmitter off, no reply
        return self._format_reply(reply)

    def _format_reply(self, reply: _Reply) -> bytes:
        if reply is None:
            return b"\r"
        if isinstance(reply, int):
            hex_mode = bool(self.controller.setting("syscon") & HEX)
            return format_number(reply, hex_mode).encode("ascii") + b"\r"
        if isinstance(reply, str):
            return reply.encode("ascii") + b"\r"
        return "".join(f"{line}\r\n" for line in reply).encode("ascii")

    # --- command table ----------------------------------------------------------------

    def _command_table(self) -> dict[str, Callable[[int | None], _Reply]]:
        table: dict[str, Callable[[int | None], _Reply]] = {
            "se": self._cmd_se,
            "pm": self._cmd_pm,
            "vm": self._cmd_vm,
            "spwm": self._cmd_spwm,
            "st": self._cmd_st,
            "cal": lambda n: self._cmd_cal(n, legacy=False),
            "ca": lambda n: self._cmd_cal(n, legacy=True),
            "ma": lambda n: self._cmd_move(n, relative=False),
            "mr": lambda n: self._cmd_move(n, relative=True),
            "rp": self._reader(lambda: self.position),
            "sp": self._cmd_sp,
            "zp": self._cmd_zp,
            "pe": self._reader(lambda: self.following_error),
            "rve": self._reader(self.controller.measured_velocity_sv),
            "rss": self._cmd_rss,
            "ss": self._cmd_ss,
            "rrss": self._cmd_rrss,
            "sc": self._cmd_sc,
            "rc": self._reader(lambda: round(self.controller.setting("scl") * 15 / 2000)),
            "ssb": lambda n: self._cmd_syscon_bit(n, True),
            "rsb": lambda n: self._cmd_syscon_bit(n, False),
            "rrsyscon": self._cmd_rrsyscon,
            "li": self._cmd_li,
            "il": self._cmd_il,
            "ql": self._reader(lambda: self.controller.setting("syscon") >> 2 & 3),
            "id": self._reader(self.identification),
            "pg": self._cmd_pg,
            "de": self._cmd_de,
            "rep": self._cmd_rep,
        }
        setters = {
            "sv": "sv",
            "sa": "sa",
            "scv": "scv",
            "sca": "sca",
            "kp": "kp",
            "ki": "ki",
            "kd": "kd",
            "sipw": "sipw",
            "ws": "sipw",
            "sipt": "sipt",
            "scl": "scl",
            "ssyscon": "syscon",
        }
        getters = {
            "rv": "sv",
            "ra": "sa",
            "rcv": "scv",
            "rca": "sca",
            "qp": "kp",
            "qi": "ki",
            "qd": "kd",
            "ripw": "sipw",
            "rw": "sipw",
            "ript": "sipt",
            "rcl": "scl",
            "rsyscon": "syscon",
        }
        for mnemonic, name in setters.items():
            table[mnemonic] = self._setter(name)
        for mnemonic, name in getters.items():
            table[mnemonic] = self._getter(name)
        return table

    def _setter(self, name: str) -> Callable[[int | None], _Reply]:
        minimum, maximum = SETTING_RANGES[name]

        def handler(value: int | None) -> _Reply:
            self.controller.set_setting(name, _in_range(value, minimum, maximum))
            return None

        return handler

    def _getter(self, name: str) -> Callable[[int | None], _Reply]:
        return self._reader(lambda: self.controller.setting(name))

    @staticmethod
    def _reader(read: Callable[[], int | str]) -> Callable[[int | None], _Reply]:
        def handler(value: int | None) -> _Reply:
            _no_argument(value)
            return read()

        return handler

    # --- commands ---------------------------------------------------------------------

    def _cmd_se(self, value: int | None) -> _Reply:
        address = _in_range(value, 0, MAX_ADDRESS)
        self._transmitting = address == self.address
        return None

    def _cmd_pm(self, value: int | None) -> _Reply:
        _no_argument(value)
        if self.controller.calibrating:
            raise _RefusedError  # calibration running: st or Ctrl-K first
        self.controller.engage_position_mode()
        return None

    def _cmd_vm(self, value: int | None) -> _Reply:
        _no_argument(value)
        if self.controller.calibrating or self.controller.setting("sa") == 0:
            raise _RefusedError
        self.controller.engage_velocity_mode()
        return None

    def _cmd_spwm(self, value: int | None) -> _Reply:
        self.controller.open_loop(_in_range(value, -PWM_MAX, PWM_MAX))
        return None

    def _cmd_st(self, value: int | None) -> _Reply:
        _no_argument(value)
        self.controller.stop()
        return None

    def _cmd_move(self, value: int | None, *, relative: bool) -> _Reply:
        if value is None:
            raise _RefusedError
        controller = self.controller
        if not controller.position_mode or controller.calibrating:
            raise _RefusedError  # ma/mr need pm (and no calibration running)
        if controller.setting("sv") == 0 or controller.setting("sa") == 0:
            raise _RefusedError  # a profile without speed or acceleration never ends
        if relative:
            _in_range(value, -2 * POSITION_LIMIT, 2 * POSITION_LIMIT)
            target = controller.target + value
        else:
            target = value
        controller.move_to(_in_range(target, -POSITION_LIMIT, POSITION_LIMIT))
        return None

    def _cmd_sp(self, value: int | None) -> _Reply:
        self.controller.set_position(_in_range(value, -POSITION_LIMIT, POSITION_LIMIT))
        return None

    def _cmd_zp(self, value: int | None) -> _Reply:
        _no_argument(value)
        return self._cmd_sp(0)

    def _cmd_rss(self, value: int | None) -> _Reply:
        _no_argument(value)
        status = self.rss  # uc of the previous command ...
        self._uc = False  # ... then cleared: rss itself was fine
        return status

    def _cmd_ss(self, value: int | None) -> _Reply:
        _no_argument(value)
        status = self.ss
        self._uc = False
        return status

    def _cmd_rrss(self, value: int | None) -> _Reply:
        _no_argument(value)
        status = self.rss
        self._uc = False
        return [f"{name}: {status >> bit & 1}" for bit, name in enumerate(RSS_NAMES)]

    def _cmd_rrsyscon(self, value: int | None) -> _Reply:
        _no_argument(value)
        syscon = self.controller.setting("syscon")
        return [f"{name}: {syscon >> bit & 1}" for bit, name in enumerate(SYSCON_NAMES)]

    def _cmd_rep(self, value: int | None) -> _Reply:
        _no_argument(value)
        lines = [self.identification(), f"address: {self.address}"]
        lines += [f"{name}: {self.controller.setting(name)}" for name in FACTORY_DEFAULTS]
        return lines

    def _cmd_sc(self, value: int | None) -> _Reply:
        steps = _in_range(value, 0, 15)
        self.controller.set_setting("scl", steps * 2000 // 15)
        return None

    def _cmd_syscon_bit(self, value: int | None, set_bit: bool) -> _Reply:
        bit = _in_range(value, 0, len(SYSCON_NAMES) - 1)
        syscon = self.controller.setting("syscon")
        syscon = syscon | 1 << bit if set_bit else syscon & ~(1 << bit)
        self.controller.set_setting("syscon", syscon)
        return None

    def _cmd_li(self, value: int | None) -> _Reply:
        enable = _in_range(value, 0, 1)
        syscon = self.controller.setting("syscon") & ~(L1ON | L2ON)
        self.controller.set_setting("syscon", syscon | (L1ON | L2ON if enable else 0))
        return None

    def _cmd_il(self, value: int | None) -> _Reply:
        inversion = _in_range(value, 0, 3)
        syscon = self.controller.setting("syscon") & ~(INV1 | INV2)
        self.controller.set_setting("syscon", syscon | inversion << 2)
        return None

    def _cmd_pg(self, value: int | None) -> _Reply:
        _no_argument(value)
        if self.controller.position_mode or self.controller.velocity_mode:
            raise _RefusedError  # the manual: not while pm or vm (calibration runs in pm)
        self._store(self.controller.settings)
        return None

    def _cmd_de(self, value: int | None) -> _Reply:
        if value is None or value != self.serial_number:
            raise _RefusedError
        self._store(None)  # defaults take effect at the next power-on
        return None

    def _store(self, settings: dict[str, int] | None) -> None:
        try:
            self._write_eeprom(settings)
        except OSError as exc:
            # A simulator problem (state directory not writable), not a wire event: the
            # host sees a refused command and the log says why.
            logger.warning("SLAP2 %d: EEPROM file not written: %s", self.address, exc)
            raise _RefusedError from exc

    def _cmd_cal(self, value: int | None, *, legacy: bool) -> _Reply:
        cal_mode = _in_range(value, 0, 5)
        controller = self.controller
        if controller.calibrating:
            raise _RefusedError
        if legacy:
            speed, acceleration = abs(controller.setting("sv")), controller.setting("sa")
        else:
            speed, acceleration = controller.setting("scv"), controller.setting("sca")
        if speed == 0 or acceleration == 0:
            raise _RefusedError
        direction = -1 if cal_mode % 2 == 0 else 1
        syscon = controller.setting("syscon")
        if cal_mode < 4 and not syscon & (L1ON if direction < 0 else L2ON):
            raise _RefusedError  # the reference switch is disabled in syscon
        controller.start_calibration(cal_mode, direction, speed, acceleration)
        return None
