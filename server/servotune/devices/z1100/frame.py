"""CNC Designer Z1100 three-axis DC servo chip: the wire half of the codec (sans-IO).

Source: ``shared/spec/z1100.md`` (normative, including its errata decisions) and the
Turkish vendor manual (``shared/seeds/002_…``) where the spec is silent. The codec
turns typed values into request packets and reply packets into typed values; it never
touches a port or a clock. The link engine moves the bytes; ``servotune.devices.z1100.sim.chip``
answers them in simulation.

What lives here, and why the codec is cut here: everything about the frame - the
errata decisions and constants, the command table, the reply code, the request and
reply packets with their checksums, the two stream decoders and the fence that brings
the line back in step. What a 32-bit data word *means* (gains, start/stop bits,
positions, the Stm unit) and the ``make_*`` request builders live one level up, in
``servotune.devices.z1100.codec``, which imports this module and nothing imports the other
way round. This module imports only the standard library; anything may import it,
though the rest of the code base addresses the codec as a whole through
``servotune.devices.z1100.codec`` (which re-exports every public name here).

Wire format (8N1, one request then one reply; the chip never talks unasked, except
that line noise can make it send a reply nobody asked for):

* request, 7 bytes: ``0x5A, Cmd, D3, D2, D1, D0, CS`` with
  ``CS = (0 - (Cmd + D3 + D2 + D1 + D0)) & 0xFF`` (the header is not summed);
* reply, 6 bytes: ``Code, D3, D2, D1, D0, CS``, valid when all six bytes sum to 0
  modulo 256. The data word is big-endian: ``D3 << 24 | D2 << 16 | D1 << 8 | D0``.

Per-axis commands carry the axis in their low two bits (``base + 0..2`` for motors
1..3); a Get is its Set with bit 7 set. Axes are numbered 0..2 here, as on the wire;
messages for people say "motor 1..3", as the manual does.

Units, used as name suffixes: ``counts`` (encoder counts, x4 quadrature),
``counts_s`` (counts per second), ``counts_s2`` (counts per second squared), ``s``.

Every departure from the manual's text is decided once, in the "errata decisions"
section below; nothing else in the code base repeats those numbers.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Final

# --- errata decisions (shared/spec/z1100.md, "Errata in the manual") ------------------
# The one place for them: change a decision here and the codec, the simulator and
# the tests follow.

# The manual lists GetSwitch with GetError's bytes (0xC0..0xC2). It gets the next free
# slot of the 4-step pattern.
GET_SWITCH_BYTE: Final = 0xC4
# SetLimit/GetLimit: the error limit is D1:D0 (the manual's GetLimit says D2:D0 and
# also calls D1:D0 "HomeSpeed"; SetLimit writes D1:D0, which wins). 14 bits.
LIMIT_MAX_COUNTS: Final = 16383
# Start/GetStart/GetStop/GetEstop: the manual's bit labels repeat motor numbers. Bit k
# belongs to motor k+1 and so does bit k+4 (direction in Start/GetStart, stall in
# GetStop/GetEstop).
UPPER_NIBBLE_SHIFT: Final = 4
# Start direction bit: the manual says only "1 one way, 0 the other". Decision: 1 runs
# towards increasing counts (away from the home switch), 0 towards decreasing counts.
DIRECTION_BIT_POSITIVE: Final = 1
# GetError: the sign is not stated; D1:D0 is read as a signed 16-bit number. The
# simulator reports position error = profile position - encoder position.
ERROR_BITS: Final = 16
# SetBaud: the data format is not stated; the data word is the baud rate itself. The
# chip answers at the old rate, then switches.
# The jumper table allows 1200..38400 although the text names only 9600: all of them.
BAUD_RATES: Final = (1200, 2400, 4800, 9600, 19200, 38400)
# The manual's example checksums (0xC0 for every GetKABH, 0xBC for every GetVmax ...)
# do not follow its own formula; the formula is normative (see request_checksum()).

# --- constants -----------------------------------------------------------------------

HEADER: Final = 0x5A
REQUEST_SIZE: Final = 7
REPLY_SIZE: Final = 6
AXES: Final = 3
GET_BIT: Final = 0x80
AXIS_MASK: Final = 0x03

STM_TICK_S: Final = 32e-6  # sampling time = Stm x 32 us
STM_DEFAULT: Final = 1  # the manual's power-on value
PACKET_TIMEOUT_S: Final = 0.100  # all 7 request bytes within 100 ms of the first
REPLY_TIMEOUT_S: Final = 0.100  # the host repeats a command unanswered after 100 ms
COUNTS_PER_REV: Final = 2048  # 512-line encoder counted x4 (the manual's example)
DEFAULT_BAUD: Final = 9600
# J3 J2 J1 jumpers read at reset (1 = fitted) -> baud rate.
BAUD_BY_JUMPERS: Final[Mapping[int, int]] = {
    0b000: 1200,
    0b001: 2400,
    0b010: 4800,
    0b011: 9600,
    0b100: 19200,
    0b101: 38400,
}

GAIN_MAX: Final = 255
BYTE_MAX: Final = 0xFF
UINT32_MAX: Final = 0xFFFF_FFFF
# "The 32-bit parameter must always be positive": speeds and accelerations are read
# as signed 32-bit numbers, so the top bit must be clear.
POSITIVE32_MAX: Final = 0x7FFF_FFFF
INT32_MIN, INT32_MAX = -(1 << 31), (1 << 31) - 1
INT16_MIN, INT16_MAX = -(1 << (ERROR_BITS - 1)), (1 << (ERROR_BITS - 1)) - 1


class CodecError(ValueError):
    """A value that does not fit its field, or bytes that are not a valid packet."""


# --- command table -------------------------------------------------------------------


class Command(enum.IntEnum):
    """Command bytes as for motor 1 (axis 0); a per-axis command adds the axis (0..2).

    ``SET_*`` write, ``GET_*`` read; ``GET_X == SET_X | 0x80`` wherever both exist.
    """

    SET_KABH = 0x00
    SET_KABD = 0x04
    SET_VMAX = 0x08
    SET_ACC = 0x0C
    SET_STM = 0x10
    SET_HVM = 0x14
    SET_HAC = 0x18
    SET_LIMIT = 0x1C
    SET_CAB = 0x20
    SET_JOB = 0x24
    SET_BUSY = 0x28
    SET_TARGET = 0x2C
    SET_START = 0x30
    SET_STOP = 0x34
    SET_ESTOP = 0x38
    SET_CLR = 0x3C
    SET_ZERO = 0x40
    SET_BAUD = 0x44
    SET_FLASH = 0x48
    GET_KABH = 0x80
    GET_KABD = 0x84
    GET_VMAX = 0x88
    GET_ACC = 0x8C
    GET_STM = 0x90
    GET_HVM = 0x94
    GET_HAC = 0x98
    GET_LIMIT = 0x9C
    GET_CAB = 0xA0
    GET_JOB = 0xA4
    GET_BUSY = 0xA8
    GET_TARGET = 0xAC
    GET_START = 0xB0
    GET_STOP = 0xB4
    GET_ESTOP = 0xB8
    GET_ENCODER = 0xBC
    GET_ERROR = 0xC0
    GET_SWITCH = GET_SWITCH_BYTE

    @property
    def is_get(self) -> bool:
        """Bit 7 set: a read."""
        return bool(self & GET_BIT)


class Field(enum.Enum):
    """How a command's 32-bit data word is laid out (request data or reply data)."""

    NONE = "none"  # no meaning; sent as 0
    KAB = "kab"  # D2 = K, D1 = A, D0 = B
    POSITIVE32 = "positive32"  # 0 .. 2^31-1 (speed or acceleration)
    INT32 = "int32"  # two's complement (positions)
    STM = "stm"  # D0: sampling time in 32 us units
    LIMIT = "limit"  # D1:D0, 0..16383
    CAB = "cab"  # D0 bits 0..2, see Cab
    JOB = "job"  # D0, see Job
    BUSY = "busy"  # D0 bit 0
    START = "start"  # D0 bits 0..2 start/running, 4..6 direction
    AXES = "axes"  # D0 bits 0..2: motors addressed (Stop, Estop)
    STOP = "stop"  # D0 bits 0..2 stopped by command, 4..6 stopped by stall
    ERROR = "error"  # D1:D0 signed 16-bit
    SWITCH = "switch"  # D0: 1 = home switch pressed
    BAUD = "baud"  # the baud rate itself


@dataclass(frozen=True, slots=True)
class CommandInfo:
    """One row of the command table (spec, "Commands").

    ``request`` / ``reply`` describe the data word each way. ``forbidden_while_moving``:
    the chip refuses the command (reply bit 4/5/6) while the addressed motor moves
    (Job is refused only for jobs other than 0).
    """

    command: Command
    name: str
    per_axis: bool
    request: Field
    reply: Field
    forbidden_while_moving: bool
    summary: str


def _info(
    command: Command,
    name: str,
    per_axis: bool,
    request: Field,
    reply: Field,
    summary: str,
    *,
    forbidden: bool = False,
) -> CommandInfo:
    return CommandInfo(command, name, per_axis, request, reply, forbidden, summary)


C, F = Command, Field
COMMANDS: Final[Mapping[Command, CommandInfo]] = {
    info.command: info
    for info in (
        _info(C.SET_KABH, "SetKABH", True, F.KAB, F.NONE, "gains while moving (also KABD)"),
        _info(C.SET_KABD, "SetKABD", True, F.KAB, F.NONE, "gains while standing still"),
        _info(C.SET_VMAX, "SetVmax", True, F.POSITIVE32, F.NONE, "max speed", forbidden=True),
        _info(C.SET_ACC, "SetAcc", True, F.POSITIVE32, F.NONE, "acceleration", forbidden=True),
        _info(C.SET_STM, "SetStm", True, F.STM, F.NONE, "sampling time x 32 us"),
        _info(C.SET_HVM, "SetHvm", True, F.POSITIVE32, F.NONE, "homing speed", forbidden=True),
        _info(C.SET_HAC, "SetHac", True, F.POSITIVE32, F.NONE, "homing accel", forbidden=True),
        _info(C.SET_LIMIT, "SetLimit", True, F.LIMIT, F.NONE, "error limit (stall)"),
        _info(C.SET_CAB, "SetCab", True, F.CAB, F.NONE, "wiring inversions", forbidden=True),
        _info(C.SET_JOB, "SetJob", True, F.JOB, F.NONE, "job; clears errors", forbidden=True),
        _info(C.SET_BUSY, "SetBusy", True, F.BUSY, F.NONE, "motor drives the BUSY pin"),
        _info(C.SET_TARGET, "SetTarget", True, F.INT32, F.NONE, "target", forbidden=True),
        _info(C.SET_START, "SetStart", False, F.START, F.NONE, "start motors", forbidden=True),
        _info(C.SET_STOP, "SetStop", False, F.AXES, F.NONE, "decelerate (velocity job)"),
        _info(C.SET_ESTOP, "SetEstop", False, F.AXES, F.NONE, "stop at once"),
        _info(C.SET_CLR, "SetClr", False, F.NONE, F.NONE, "clear stall errors"),
        _info(C.SET_ZERO, "SetZero", True, F.NONE, F.NONE, "go home", forbidden=True),
        _info(C.SET_BAUD, "SetBaud", False, F.BAUD, F.NONE, "change baud rate"),
        _info(C.SET_FLASH, "SetFlash", False, F.NONE, F.NONE, "save parameters to flash"),
        _info(C.GET_KABH, "GetKABH", True, F.NONE, F.KAB, "gains while moving"),
        _info(C.GET_KABD, "GetKABD", True, F.NONE, F.KAB, "gains while standing still"),
        _info(C.GET_VMAX, "GetVmax", True, F.NONE, F.POSITIVE32, "max speed"),
        _info(C.GET_ACC, "GetAcc", True, F.NONE, F.POSITIVE32, "acceleration"),
        _info(C.GET_STM, "GetStm", True, F.NONE, F.STM, "sampling time x 32 us"),
        _info(C.GET_HVM, "GetHvm", True, F.NONE, F.POSITIVE32, "homing speed"),
        _info(C.GET_HAC, "GetHac", True, F.NONE, F.POSITIVE32, "homing acceleration"),
        _info(C.GET_LIMIT, "GetLimit", True, F.NONE, F.LIMIT, "error limit"),
        _info(C.GET_CAB, "GetCab", True, F.NONE, F.CAB, "wiring inversions"),
        _info(C.GET_JOB, "GetJob", True, F.NONE, F.JOB, "job"),
        _info(C.GET_BUSY, "GetBusy", True, F.NONE, F.BUSY, "motor drives the BUSY pin"),
        _info(C.GET_TARGET, "GetTarget", True, F.NONE, F.INT32, "target"),
        _info(C.GET_START, "GetStart", False, F.NONE, F.START, "running motors"),
        _info(C.GET_STOP, "GetStop", False, F.NONE, F.STOP, "stopped motors"),
        _info(C.GET_ESTOP, "GetEstop", False, F.NONE, F.STOP, "stopped motors"),
        _info(C.GET_ENCODER, "GetEncoder", True, F.NONE, F.INT32, "encoder position"),
        _info(C.GET_ERROR, "GetError", True, F.NONE, F.ERROR, "position error"),
        _info(C.GET_SWITCH, "GetSwitch", True, F.NONE, F.SWITCH, "home switch"),
    )
}
del C, F
assert set(COMMANDS) == set(Command)

# raw byte -> (command, axis or None); everything else is an unknown command
_BY_BYTE: Final[Mapping[int, tuple[Command, int | None]]] = {
    (info.command + axis if info.per_axis else info.command): (
        info.command,
        axis if info.per_axis else None,
    )
    for info in COMMANDS.values()
    for axis in (range(AXES) if info.per_axis else (0,))
}


def resolve(command_byte: int) -> tuple[Command, int | None] | None:
    """``(command, axis)`` for a raw command byte; axis is ``None`` for commands of the
    whole chip. ``None`` when the chip does not know the byte (reply bit 1)."""
    return _BY_BYTE.get(command_byte)


def getter_of(command: Command) -> Command | None:
    """The Get paired with a Set (``Set | 0x80``), or ``None`` if the Set has no Get.

    Clr, Zero, Baud and Flash have none: 0xBC, 0xC0 and 0xC4 are GetEncoder, GetError
    and GetSwitch, which read something else.
    """
    if command.is_get:
        raise CodecError(f"{COMMANDS[command].name} is not a Set command")
    return Command(command | GET_BIT) if command <= Command.SET_ESTOP else None


# --- reply code ----------------------------------------------------------------------


class ReplyCode(enum.IntFlag):
    """The reply's first byte. Any of bits 0..6: the command was not executed. Bit 7
    is a flag, not a rejection: a motor stopped on its error limit (GetStop says
    which), and the reply's data is valid."""

    OK = 0
    CHECKSUM = 1 << 0
    UNKNOWN_COMMAND = 1 << 1
    TIMEOUT = 1 << 2
    COMMUNICATION = 1 << 3
    MOVING_1 = 1 << 4
    MOVING_2 = 1 << 5
    MOVING_3 = 1 << 6
    STALL = 1 << 7


REJECTION_MASK: Final = ReplyCode(0x7F)
_MESSAGES: Final = (
    (ReplyCode.CHECKSUM, "checksum wrong"),
    (ReplyCode.UNKNOWN_COMMAND, "unknown command"),
    (ReplyCode.TIMEOUT, "packet not complete within 100 ms"),
    (ReplyCode.COMMUNICATION, "communication error (overrun, framing or noise)"),
    (ReplyCode.MOVING_1, "forbidden while motor 1 is moving"),
    (ReplyCode.MOVING_2, "forbidden while motor 2 is moving"),
    (ReplyCode.MOVING_3, "forbidden while motor 3 is moving"),
)


def moving_flag(axis: int) -> ReplyCode:
    """The "forbidden while motor axis+1 is moving" bit."""
    _check_axis(axis)
    return ReplyCode(ReplyCode.MOVING_1 << axis)


def error_message(code: int) -> str | None:
    """A sentence for a person naming every rejection bit in ``code`` (bits 0..6), e.g.
    ``"forbidden while motor 2 is moving"``; ``None`` when the command was executed.
    The stall flag (bit 7) is not a rejection: see :func:`stall_message`."""
    parts = [text for flag, text in _MESSAGES if code & flag]
    return "; ".join(parts) if parts else None


def stall_message(code: int) -> str | None:
    """The explanation of bit 7 when it is set, else ``None``."""
    if code & ReplyCode.STALL:
        return "a motor was stopped by its error limit (stall); GetStop tells which"
    return None


# --- packets ---------------------------------------------------------------------------


def _data_bytes(data: int) -> bytes:
    return data.to_bytes(4, "big")


def request_checksum(command_byte: int, data: int) -> int:
    """CS = (0 - (Cmd + D3 + D2 + D1 + D0)) & 0xFF; the 0x5A header is not summed."""
    return -(command_byte + sum(_data_bytes(data))) & 0xFF


def reply_checksum(code: int, data: int) -> int:
    """The byte that makes the six reply bytes sum to 0 modulo 256."""
    return -(code + sum(_data_bytes(data))) & 0xFF


def _check(name: str, value: int, minimum: int, maximum: int) -> None:
    if isinstance(value, bool) or not minimum <= value <= maximum:
        raise CodecError(f"{name} must be between {minimum} and {maximum}, got {value!r}")


def _check_axis(axis: int) -> None:
    if isinstance(axis, bool) or not 0 <= axis < AXES:
        raise CodecError(f"axis must be between 0 and {AXES - 1} (motor 1..3), got {axis!r}")


@dataclass(frozen=True, slots=True)
class Request:
    """One request packet: the raw command byte (base + axis) and the 32-bit data word
    (unsigned; signed values are packed by the ``make_*`` builders).

    Any byte is representable, known or not, so the simulator can answer an unknown
    command and ``decode_request(encode_request(r)) == r`` always holds.
    """

    command_byte: int
    data: int = 0

    def __post_init__(self) -> None:
        _check("command byte", self.command_byte, 0, BYTE_MAX)
        _check("data", self.data, 0, UINT32_MAX)

    @property
    def command(self) -> Command | None:
        """The command without its axis offset, ``None`` for an unknown byte."""
        resolved = resolve(self.command_byte)
        return None if resolved is None else resolved[0]

    @property
    def axis(self) -> int | None:
        """0..2 for a per-axis command, ``None`` for whole-chip and unknown commands."""
        resolved = resolve(self.command_byte)
        return None if resolved is None else resolved[1]

    def encode(self) -> bytes:
        """The 7 bytes on the wire (see :func:`encode_request`)."""
        return encode_request(self)


@dataclass(frozen=True, slots=True)
class Reply:
    """One reply packet: code byte and 32-bit data word (unsigned)."""

    code: ReplyCode
    data: int = 0

    def __post_init__(self) -> None:
        _check("reply code", int(self.code), 0, BYTE_MAX)
        _check("data", self.data, 0, UINT32_MAX)

    @property
    def executed(self) -> bool:
        """No rejection bit (0..6) is set: the command ran and the data is valid."""
        return not self.code & REJECTION_MASK

    @property
    def stall(self) -> bool:
        """Bit 7: some motor stopped on its error limit (GetStop tells which)."""
        return bool(self.code & ReplyCode.STALL)

    def error_message(self) -> str | None:
        """See :func:`error_message`: ``None`` when the command was executed."""
        return error_message(self.code)

    def encode(self) -> bytes:
        """The 6 bytes on the wire (see :func:`encode_reply`)."""
        return encode_reply(self)


@dataclass(frozen=True, slots=True)
class BadRequest:
    """Seven bytes that started with the header but failed the checksum (reply bit 0)."""

    raw: bytes


def encode_request(request: Request) -> bytes:
    """The 7 bytes of ``request``."""
    cmd, data = request.command_byte, request.data
    return bytes((HEADER, cmd, *_data_bytes(data), request_checksum(cmd, data)))


def decode_request(packet: bytes) -> Request:
    """Decode exactly 7 bytes; raises :class:`CodecError` on a wrong length, header or
    checksum."""
    if len(packet) != REQUEST_SIZE:
        raise CodecError(f"a request is {REQUEST_SIZE} bytes, got {len(packet)}")
    if packet[0] != HEADER:
        raise CodecError(f"a request starts with 0x{HEADER:02X}, got 0x{packet[0]:02X}")
    if sum(packet[1:]) & 0xFF:
        raise CodecError(f"request checksum wrong: {packet.hex(' ')}")
    return Request(packet[1], int.from_bytes(packet[2:6], "big"))


def encode_reply(reply: Reply) -> bytes:
    """The 6 bytes of ``reply``."""
    code, data = int(reply.code), reply.data
    return bytes((code, *_data_bytes(data), reply_checksum(code, data)))


def decode_reply(packet: bytes) -> Reply:
    """Decode exactly 6 bytes; raises :class:`CodecError` on a wrong length or sum."""
    if len(packet) != REPLY_SIZE:
        raise CodecError(f"a reply is {REPLY_SIZE} bytes, got {len(packet)}")
    if sum(packet) & 0xFF:
        raise CodecError(f"reply checksum wrong: {packet.hex(' ')}")
    return Reply(ReplyCode(packet[0]), int.from_bytes(packet[1:5], "big"))


class ReplyDecoder:
    """Incremental reply decoder for the host side: ``feed(bytes) -> [Reply, ...]``.

    Replies have no header, so frame boundaries cannot be seen in the bytes: the
    decoder slides a 6-byte window over its buffer, accepts the window when its sum is
    0 modulo 256 and otherwise drops the oldest byte (counted in ``discarded``) and
    tries again. Ambiguity, by construction: after garbage, a window that straddles
    garbage and a real reply sums to 0 by chance with probability 1/256 and is
    accepted as a (wrong) reply, and six zero bytes are a valid reply (code 0, data
    0). Never raises on any input.

    The chip talks only when asked (or on line noise), so the link engine should call
    :meth:`clear` before each request and take the first reply after it; a reply
    that arrives with no request outstanding is unsolicited (line noise).
    """

    def __init__(self) -> None:
        self._buffer = bytearray()
        self.discarded = 0

    def feed(self, data: bytes) -> list[Reply]:
        """Add received bytes; returns the replies completed, oldest first."""
        buffer = self._buffer
        buffer += data
        replies: list[Reply] = []
        start = 0
        while len(buffer) - start >= REPLY_SIZE:
            window = buffer[start : start + REPLY_SIZE]
            if sum(window) & 0xFF == 0:
                replies.append(Reply(ReplyCode(window[0]), int.from_bytes(window[1:5], "big")))
                start += REPLY_SIZE
            else:
                start += 1
                self.discarded += 1
        del buffer[:start]
        return replies

    @property
    def pending(self) -> int:
        """Bytes buffered that do not yet form a reply."""
        return len(self._buffer)

    def clear(self) -> bytes:
        """Forget (and return) buffered bytes, e.g. before sending a new request."""
        data = bytes(self._buffer)
        self._buffer.clear()
        return data


class RequestDecoder:
    """Incremental request decoder for the chip side: ``feed(bytes) -> events``.

    Follows what the chip's firmware does: while idle, bytes other than the 0x5A
    header are ignored (that is how it resynchronises on garbage); from a header on,
    seven bytes make a packet, which is a :class:`Request` when its checksum is right
    and a :class:`BadRequest` (reply bit 0) otherwise - all seven bytes are consumed
    either way, so a packet whose header was garbage swallows part of the next one.
    The 100 ms packet timeout needs a clock, so it is the caller's: it calls
    :meth:`clear` when the first byte of ``pending`` is too old.
    """

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[Request | BadRequest]:
        """Add received bytes; returns the packets completed, oldest first."""
        events: list[Request | BadRequest] = []
        buffer = self._buffer
        for byte in data:
            if not buffer and byte != HEADER:
                continue
            buffer.append(byte)
            if len(buffer) == REQUEST_SIZE:
                packet = bytes(buffer)
                buffer.clear()
                if sum(packet[1:]) & 0xFF:
                    events.append(BadRequest(packet))
                else:
                    events.append(Request(packet[1], int.from_bytes(packet[2:6], "big")))
        return events

    @property
    def pending(self) -> int:
        """Bytes of an incomplete packet (0 while waiting for a header)."""
        return len(self._buffer)

    def clear(self) -> bytes:
        """Discard an incomplete packet (the 100 ms timeout); returns its bytes."""
        data = bytes(self._buffer)
        self._buffer.clear()
        return data


# --- the fence: bringing the line back in step ------------------------------------------
# Replies carry no header and no echo of their request, so after a timeout nothing in a
# reply says which request it answers. Decision (the manual is silent on recovery): the
# host sends a command byte the chip does not know; the chip answers every request in
# order, and this one with reply bit 1 ("Mevcut olmayan komut isteği geldi", manual
# 002_*.txt), which no known request ever earns. Once that answer is in, every reply to
# an earlier request has arrived (or is lost for good): the line is in step. 0x7C sits
# in the unused gap between the last Set (0x4A, SetFlash) and the first Get (0x80).
FENCE_BYTE: Final = 0x7C
assert FENCE_BYTE not in _BY_BYTE, "the fence byte must be unknown to the chip"


def make_fence() -> Request:
    """The fence request: unknown to the chip, answered in order with reply bit 1."""
    return Request(FENCE_BYTE)


def is_fence_reply(reply: Reply) -> bool:
    """Whether ``reply`` is the chip's answer to a fence: the "unknown command" bit and
    no other rejection bit (bit 7, a stall, rides on any reply). The data word is not
    looked at: the manual does not say what the chip puts there for a refused command."""
    return (reply.code & REJECTION_MASK) == ReplyCode.UNKNOWN_COMMAND
