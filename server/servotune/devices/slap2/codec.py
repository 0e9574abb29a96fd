"""SLAP2 wire codec (sans-IO): format commands, parse replies, decode status words.

Source: ``shared/spec/slap2.md`` and the vendor manual. The SLAP2 speaks ASCII at
19200 8N1; the host sends a command one character at a time, waiting for each echo,
then CR (also echoed); the module answers one line ``text CR`` or a bare CR. This
module only turns values into text and text into values: no I/O, no clocks. The
echo-per-character exchange itself lives in ``servotune.devices.slap2.link``.
"""

from __future__ import annotations

import enum
import functools
from dataclasses import dataclass

CR = 0x0D
LF = 0x0A
CTRL_X = 0x18  # discards the module's input buffer before CR
CTRL_K = 0x0B  # aborts a running calibration

TICK_S = 841.5e-6
POSITION_LIMIT = 1 << 24
GAIN_MAX = 32767
# The manual gives no upper bound for sv/sa/sipw/sipt; the 16-bit range is the
# decision shared with the simulator (docs/simulator.md).
VELOCITY_MAX = 65535
ACCELERATION_MAX = 65535
WINDOW_MAX = 65535
CURRENT_LIMIT_MAX_MA = 2000
PWM_MAX = 255
MAX_ADDRESS = 15
DEFAULT_BAUD = 19200  # 8N1

RPM_PER_SV_LINE = 140.417  # rpm = SV * 140.417 / lines
RPM_PER_MIN_PER_SA_LINE = 35946.7  # rpm/min = SA * 35946.7 / lines
# counts/s = rpm / 60 * 4 * lines: the line count cancels.
COUNTS_S_PER_SV = RPM_PER_SV_LINE * 4 / 60
COUNTS_S2_PER_SA = RPM_PER_MIN_PER_SA_LINE * 4 / 3600

REFUSED_REPLY = "-1UC"
MULTILINE_COMMANDS = ("rep", "rrss", "rrsyscon")


class RssBit(enum.IntEnum):
    """Bits of the ``rss`` status word (new flags)."""

    limit1 = 0
    limit2 = 1
    vm = 2
    pm = 3
    move = 4
    inpos = 5
    cal = 6
    oc = 7
    uc = 8


class SsBit(enum.IntEnum):
    """Bits of the legacy ``ss`` status byte."""

    limit1 = 0
    limit2 = 1
    vmode = 2
    pmode = 3
    move = 4
    deccel = 5
    esactiv = 6
    uc = 7


class SysconBit(enum.IntEnum):
    """Bits of the system configuration word (``ssyscon`` / ``rsyscon``)."""

    l1on = 0
    l2on = 1
    inv1 = 2
    inv2 = 3
    hex = 4
    ucon = 5


class ReplyKind(enum.Enum):
    EMPTY = "empty"
    NUMBER = "number"
    REFUSED = "refused"
    TEXT = "text"


@dataclass(frozen=True, slots=True)
class Reply:
    """One decoded reply line.

    ``kind`` is EMPTY for a bare CR, REFUSED for ``-1UC`` (syscon ``ucon`` set),
    NUMBER when the whole line is a decimal or ``0x`` hex number (``value`` holds it),
    TEXT otherwise (``id``, multi-line listings).
    """

    kind: ReplyKind
    text: str
    value: int | None = None


@dataclass(frozen=True, slots=True)
class Command:
    """A command ready for the wire, built by a ``make_*`` function.

    ``text`` has no spaces and no CR. ``multiline`` marks replies read until the line
    goes quiet. ``changes_device`` marks commands whose refusal must be checked
    (``-1UC`` reply, or the ``uc`` bit of ``rss`` when ``ucon`` is off).
    """

    text: str
    multiline: bool = False
    changes_device: bool = False


class CodecError(ValueError):
    """A value that cannot be put on the wire, or a reply that cannot be understood."""


def parse_int(text: str) -> int:
    """Parse a numeric reply: decimal (``-1234``) or hex (``0x3E8``, ``-0x3E8``).

    A hex reply of 2^31 or more is read as a 32-bit two's complement value, because
    the manual does not say how hex mode prints negative numbers.
    """
    stripped = text.strip()
    if not stripped:
        raise CodecError("empty number")
    negative = stripped.startswith("-")
    body = stripped[1:] if negative or stripped.startswith("+") else stripped
    try:
        if body[:2].lower() == "0x":
            value = int(body[2:], 16)
            if not negative and value >= 1 << 31 and value < 1 << 32:
                value -= 1 << 32
        elif body.isdigit():
            value = int(body, 10)
        else:
            raise CodecError(f"not a number: {text!r}")
    except ValueError as exc:
        raise CodecError(f"not a number: {text!r}") from exc
    return -value if negative else value


def parse_reply(line: str) -> Reply:
    """Classify one reply line (without its CR)."""
    text = line.strip()
    if not text:
        return Reply(ReplyKind.EMPTY, "")
    if text == REFUSED_REPLY:
        return Reply(ReplyKind.REFUSED, text)
    try:
        return Reply(ReplyKind.NUMBER, text, parse_int(text))
    except CodecError:
        return Reply(ReplyKind.TEXT, text)


def format_int(value: int, *, hex_mode: bool = False) -> str:
    """Format a number the way the module prints it (used by the simulator and tests)."""
    if not hex_mode:
        return str(value)
    return f"-0x{-value:X}" if value < 0 else f"0x{value:X}"


def normalise_line(line: str) -> str:
    """Turn a user's console line into wire text: spaces removed, printable ASCII only.

    The module ignores spaces on reception, so ``sv 1000`` and ``sv1000`` are the same;
    removing them also keeps the echo comparison unambiguous.
    """
    text = "".join(line.split())
    if not text:
        raise CodecError("empty command")
    if not text.isascii() or not text.isprintable():
        raise CodecError("only printable ASCII characters can be sent")
    return text


@functools.cache
def _bit_table(bits: type[enum.IntEnum]) -> tuple[tuple[str, int], ...]:
    return tuple((bit.name, bit.value) for bit in bits)


def decode_bits(value: int, bits: type[enum.IntEnum]) -> dict[str, bool]:
    """Map a status/config word to ``{flag name: bool}`` for the given bit enum (a new
    dict per call).

    The enum's (name, bit) pairs are looked up once: iterating an enum and reading its
    members' properties per call is slow (docs/capture.md), and a capture decodes
    ``rss`` several times per sample at ~150 samples/s, between two transactions on
    the wire."""
    return {name: bool(value >> bit & 1) for name, bit in _bit_table(bits)}


def encode_bits(flags: dict[str, bool], bits: type[enum.IntEnum]) -> int:
    value = 0
    for bit in bits:
        if flags.get(bit.name, False):
            value |= 1 << bit.value
    return value


def decode_rss(value: int) -> dict[str, bool]:
    return decode_bits(value, RssBit)


def decode_ss(value: int) -> dict[str, bool]:
    return decode_bits(value, SsBit)


def decode_syscon(value: int) -> dict[str, bool]:
    return decode_bits(value, SysconBit)


# --- unit conversions (manual, section sv / sa / sipt) ---------------------------------


def sv_to_rpm(sv: float, lines: int) -> float:
    return sv * RPM_PER_SV_LINE / lines


def rpm_to_sv(rpm: float, lines: int) -> int:
    """Manual example: 2500 rpm at 512 lines -> 9115.7 -> 9116."""
    return round(rpm * lines / RPM_PER_SV_LINE)


def sa_to_rpm_per_min(sa: float, lines: int) -> float:
    return sa * RPM_PER_MIN_PER_SA_LINE / lines


def rpm_per_min_to_sa(rpm_per_min: float, lines: int) -> int:
    """Manual example: 5000 rpm/min at 512 lines -> 71.21 -> 71."""
    return round(rpm_per_min * lines / RPM_PER_MIN_PER_SA_LINE)


def ticks_to_ms(ticks: float) -> float:
    return ticks * TICK_S * 1000


def ms_to_ticks(ms: float) -> int:
    return round(ms / (TICK_S * 1000))


# --- command builders -----------------------------------------------------------------


def _check_range(name: str, value: int, minimum: int, maximum: int) -> None:
    if not minimum <= value <= maximum:
        raise CodecError(f"{name} must be between {minimum} and {maximum}, got {value}")


def make_select(address: int) -> Command:
    _check_range("address", address, 0, MAX_ADDRESS)
    return Command(f"se{address}")


def make_read(mnemonic: str) -> Command:
    return Command(mnemonic, multiline=mnemonic in MULTILINE_COMMANDS)


def make_set(mnemonic: str, value: int) -> Command:
    return Command(f"{mnemonic}{value}", changes_device=True)


def make_set_gains(kp: int, ki: int, kd: int) -> list[Command]:
    """Commands that set the PID gains (each 0..32767)."""
    for name, value in (("kp", kp), ("ki", ki), ("kd", kd)):
        _check_range(name, value, 0, GAIN_MAX)
    return [make_set("kp", kp), make_set("ki", ki), make_set("kd", kd)]


def make_move_absolute(position: int) -> Command:
    _check_range("position", position, -POSITION_LIMIT, POSITION_LIMIT)
    return Command(f"ma{position}", changes_device=True)


def make_move_relative(distance: int) -> Command:
    _check_range("distance", distance, -2 * POSITION_LIMIT, 2 * POSITION_LIMIT)
    return Command(f"mr{distance}", changes_device=True)


def make_set_position(position: int) -> Command:
    _check_range("position", position, -POSITION_LIMIT, POSITION_LIMIT)
    return Command(f"sp{position}", changes_device=True)


def make_pwm(pwm: int) -> Command:
    _check_range("pwm", pwm, -PWM_MAX, PWM_MAX)
    return Command(f"spwm{pwm}", changes_device=True)


def make_calibrate(mode: int) -> Command:
    _check_range("mode", mode, 0, 5)
    return Command(f"cal{mode}", changes_device=True)


def make_simple(mnemonic: str) -> Command:
    """``pm``, ``vm``, ``st``, ``pg``: commands without an argument that change state."""
    return Command(mnemonic, changes_device=True)


class LineDecoder:
    """Incremental decoder of reply lines: ``feed(bytes) -> complete lines``.

    Follows the manual's "rstring": characters above ASCII 31 are collected, CR ends
    a line, everything else (LF, NUL, control characters, line noise below 32) is
    dropped. Bytes above 127 cannot come from the module; they are dropped too so a
    noisy line never raises.
    """

    def __init__(self) -> None:
        self._buffer: list[str] = []

    def feed(self, data: bytes) -> list[str]:
        lines: list[str] = []
        for byte in data:
            if byte == CR:
                lines.append("".join(self._buffer))
                self._buffer.clear()
            elif 31 < byte < 127:
                self._buffer.append(chr(byte))
        return lines

    @property
    def pending(self) -> str:
        """Characters received since the last CR."""
        return "".join(self._buffer)

    def flush(self) -> str:
        """Return and forget a partial line (for when the line went quiet)."""
        text = self.pending
        self._buffer.clear()
        return text
