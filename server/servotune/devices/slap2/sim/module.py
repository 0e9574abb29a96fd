"""SLAP2 firmware emulation: one module (``Slap2Module``).

The seam: a module is a motion controller with a host interface in front of it. The
controller (the 841.5 us tick: profile generator, PID, in-position, limit switches,
calibration, idle fast path) and the manual's constants it runs on are in
``devices/slap2/sim/controller.py`` (``Slap2Controller``). Here is the host interface on top - line
parser (echo, Ctrl-X, Ctrl-K, ``se``), command table, replies, EEPROM file, power-on
reset and banner. ``Slap2Module`` subclasses ``Slap2Controller`` and drives it through
its private state (the contract is in that class's docstring). The RS232 line the
modules share, ``Slap2Bus``, is in ``devices/slap2/sim/line.py`` on top of this one.

Sans-IO: nothing here reads a clock or touches a file descriptor (except the optional
EEPROM file). The modules are driven in simulation time by ``Slap2Bus`` through the
``SimDevice`` contract (``advance_to`` / ``receive``); ``PtySimulator`` puts the bus on a
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
    _CAL_BACKOFF,
    _CAL_INDEX,
    _CAL_NONE,
    _CAL_SEEK,
    _COUNTS_TICK2_PER_SA,
    _COUNTS_TICK_PER_SV,
    _MODE_OFF,
    _MODE_PM,
    _MODE_PWM,
    _MODE_VM,
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


class Slap2Module(Slap2Controller):
    """Firmware of one SLAP2 module driving one simulated motor.

    Contract:

    * ``receive(byte)`` handles one host byte and returns what *this* module transmits
      (echo, reply); a module whose transmitter is off still parses every line so it
      can react to ``se``.
    * ``tick()`` runs one 841.5 us controller cycle (profile generator, PID, inpos,
      limit switches, calibration) and integrates the motor over the cycle (inherited
      from ``Slap2Controller``).
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
        super().__init__(motor if motor is not None else DcMotor(params))
        self._commands = self._command_table()
        # Everything below is (re)initialised by power_cycle(); listed for clarity.
        self._buffer = bytearray()
        self._overflow = False
        self._transmitting = False
        self._pending = bytearray()
        self._uc = False
        self.power_cycle()

    # --- observation ----------------------------------------------------------------

    @property
    def transmitting(self) -> bool:
        """The module's RS232 transmitter is on (it is the selected module)."""
        return self._transmitting

    @property
    def settings(self) -> dict[str, int]:
        """A copy of the RAM settings (the ``pg`` set)."""
        return dict(self._settings)

    @property
    def rss(self) -> int:
        """The ``rss`` status word as it would be read now."""
        return (
            self._level1
            | self._level2 << 1
            | (self._mode == _MODE_VM) << 2
            | (self._mode == _MODE_PM) << 3
            | self._moving << 4
            | self._inpos << 5
            | self._calibrated << 6
            | self._oc << 7
            | self._uc << 8
        )

    @property
    def ss(self) -> int:
        """The legacy ``ss`` status byte as it would be read now."""
        syscon = self._settings["syscon"]
        return (
            self._level1
            | self._level2 << 1
            | (self._mode == _MODE_VM) << 2
            | (self._mode == _MODE_PM) << 3
            | self._moving << 4
            | self._decel << 5
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
        self._settings = self._read_eeprom()
        self._apply_settings()
        self._buffer.clear()
        self._overflow = False
        self._pending.clear()
        self._transmitting = self.address == 0
        if self.address == 0:
            self._pending += self.banner()
        self._mode = _MODE_OFF
        self._pwm = self._pwm_out = 0
        self._moving = self._decel = False
        self._cal_phase = _CAL_NONE
        self._calibrated = False
        self._uc = self._oc = False
        self._inpos = False
        self._inpos_timer = 0
        count = self.motor.count
        self._offset = count  # the counter starts at 0 wherever the shaft is
        self._sp = float(count)
        self._sp_vel = 0.0
        self._target = count
        self._integral = self._e_prev = 0
        self._last_count = count
        self._vel_filt = 0.0
        self.motor.current_a = 0.0  # the bridge was off
        self._update_levels()
        self._wake()

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
        self._wake()  # a command may change anything the controller reads
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
            if self._transmitting and self._cal_phase != _CAL_NONE:
                self._fail_calibration()
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
            if self._settings["syscon"] & UCON:
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
            hex_mode = bool(self._settings["syscon"] & HEX)
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
            "rve": self._reader(self._measured_velocity_sv),
            "rss": self._cmd_rss,
            "ss": self._cmd_ss,
            "rrss": self._cmd_rrss,
            "sc": self._cmd_sc,
            "rc": self._reader(lambda: round(self._settings["scl"] * 15 / 2000)),
            "ssb": lambda n: self._cmd_syscon_bit(n, True),
            "rsb": lambda n: self._cmd_syscon_bit(n, False),
            "rrsyscon": self._cmd_rrsyscon,
            "li": self._cmd_li,
            "il": self._cmd_il,
            "ql": self._reader(lambda: self._settings["syscon"] >> 2 & 3),
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
            self._settings[name] = _in_range(value, minimum, maximum)
            self._apply_settings()
            return None

        return handler

    def _getter(self, name: str) -> Callable[[int | None], _Reply]:
        return self._reader(lambda: self._settings[name])

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
        if self._cal_phase != _CAL_NONE:
            raise _RefusedError  # calibration running: st or Ctrl-K first
        if self._mode != _MODE_PM:
            self._engage(hold=True)
            self._mode = _MODE_PM
        return None

    def _cmd_vm(self, value: int | None) -> _Reply:
        _no_argument(value)
        if self._cal_phase != _CAL_NONE or self._settings["sa"] == 0:
            raise _RefusedError
        if self._mode in (_MODE_OFF, _MODE_PWM):
            self._engage(hold=True)
        # from pm the generator keeps its state, so the speed changes smoothly
        self._mode = _MODE_VM
        self._moving = False
        self._inpos = False
        self._inpos_timer = 0
        return None

    def _cmd_spwm(self, value: int | None) -> _Reply:
        self._pwm = _in_range(value, -PWM_MAX, PWM_MAX)
        self._cal_phase = _CAL_NONE
        self._mode = _MODE_PWM
        self._moving = self._decel = self._inpos = False
        return None

    def _cmd_st(self, value: int | None) -> _Reply:
        _no_argument(value)
        self._mode = _MODE_OFF
        self._cal_phase = _CAL_NONE
        self._moving = self._decel = self._inpos = False
        self._sp_vel = 0.0
        return None

    def _cmd_move(self, value: int | None, *, relative: bool) -> _Reply:
        if value is None:
            raise _RefusedError
        if self._mode != _MODE_PM or self._cal_phase != _CAL_NONE:
            raise _RefusedError  # ma/mr need pm (and no calibration running)
        sv, sa = abs(self._settings["sv"]), self._settings["sa"]
        if sv == 0 or sa == 0:
            raise _RefusedError  # a profile without speed or acceleration never ends
        if relative:
            _in_range(value, -2 * POSITION_LIMIT, 2 * POSITION_LIMIT)
            target = self._target - self._offset + value
        else:
            target = value
        _in_range(target, -POSITION_LIMIT, POSITION_LIMIT)
        # Replan from the generator's current position and velocity: no jump.
        self._target = target + self._offset
        self._move_vmax = sv * _COUNTS_TICK_PER_SV
        self._move_acc = sa * _COUNTS_TICK2_PER_SA
        self._moving = True
        self._inpos = False
        self._inpos_timer = 0
        return None

    def _cmd_sp(self, value: int | None) -> _Reply:
        position = _in_range(value, -POSITION_LIMIT, POSITION_LIMIT)
        # Setpoint and target live in physical counts, so only the offset changes and
        # a running move or the held position is not disturbed.
        self._offset = self.motor.count - position
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
        syscon = self._settings["syscon"]
        return [f"{name}: {syscon >> bit & 1}" for bit, name in enumerate(SYSCON_NAMES)]

    def _cmd_rep(self, value: int | None) -> _Reply:
        _no_argument(value)
        lines = [self.identification(), f"address: {self.address}"]
        lines += [f"{name}: {self._settings[name]}" for name in FACTORY_DEFAULTS]
        return lines

    def _cmd_sc(self, value: int | None) -> _Reply:
        steps = _in_range(value, 0, 15)
        self._settings["scl"] = steps * 2000 // 15
        self._apply_settings()
        return None

    def _cmd_syscon_bit(self, value: int | None, set_bit: bool) -> _Reply:
        bit = _in_range(value, 0, len(SYSCON_NAMES) - 1)
        if set_bit:
            self._settings["syscon"] |= 1 << bit
        else:
            self._settings["syscon"] &= ~(1 << bit)
        self._apply_settings()
        return None

    def _cmd_li(self, value: int | None) -> _Reply:
        enable = _in_range(value, 0, 1)
        syscon = self._settings["syscon"] & ~(L1ON | L2ON)
        self._settings["syscon"] = syscon | (L1ON | L2ON if enable else 0)
        self._apply_settings()
        return None

    def _cmd_il(self, value: int | None) -> _Reply:
        inversion = _in_range(value, 0, 3)
        syscon = self._settings["syscon"] & ~(INV1 | INV2)
        self._settings["syscon"] = syscon | inversion << 2
        self._apply_settings()
        return None

    def _cmd_pg(self, value: int | None) -> _Reply:
        _no_argument(value)
        if self._mode in (_MODE_PM, _MODE_VM):
            raise _RefusedError  # the manual: not while pm or vm (calibration runs in pm)
        self._store(self._settings)
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
        if self._cal_phase != _CAL_NONE:
            raise _RefusedError
        s = self._settings
        speed, acceleration = (abs(s["sv"]), s["sa"]) if legacy else (s["scv"], s["sca"])
        if speed == 0 or acceleration == 0:
            raise _RefusedError
        direction = -1 if cal_mode % 2 == 0 else 1
        if cal_mode < 4 and not (self._l1on if direction < 0 else self._l2on):
            raise _RefusedError  # the reference switch is disabled in syscon
        if self._mode != _MODE_PM:
            self._engage(hold=True)
        # In pm the generator keeps its velocity: a cal during a move ramps smoothly.
        self._mode = _MODE_PM
        self._cal_mode = cal_mode
        self._cal_dir = direction
        self._cal_vmax = speed * _COUNTS_TICK_PER_SV
        self._cal_acc = acceleration * _COUNTS_TICK2_PER_SA
        self._calibrated = False  # stays 0 unless this calibration succeeds
        self._moving = True
        self._inpos = False
        self._inpos_timer = 0
        self._update_levels()
        reference = self._level1 if direction < 0 else self._level2
        if cal_mode >= 4:
            self._cal_phase = _CAL_INDEX
        elif reference:
            self._cal_phase = _CAL_BACKOFF  # already standing in the switch: drive out
        else:
            self._cal_phase = _CAL_SEEK
        self._cal_index_armed = False
        return None
