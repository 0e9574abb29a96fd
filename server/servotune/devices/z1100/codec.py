"""CNC Designer Z1100 three-axis DC servo chip: wire codec (sans-IO), its public face.

Source: ``shared/spec/z1100.md`` (normative, including its errata decisions) and the
Turkish vendor manual (``shared/seeds/002_…``) where the spec is silent. The codec
turns typed values into request packets and reply packets into typed values; it never
touches a port or a clock. The link engine moves the bytes; ``servotune.devices.z1100.sim.chip``
answers them in simulation.

The codec is two modules, cut where the frame ends and its meaning begins:

* ``servotune.devices.z1100.frame``: the frame - errata decisions and constants, the
  command table, the reply code, request and reply packets, the stream decoders and
  the fence. Wire format and units are described there.
* this module: what a 32-bit data word means (gains, Cab and Job, start/stop bits,
  positions, limits, errors; the typed value of any Get), the Stm unit, and the
  ``make_*`` request builders, each of which checks its ranges.

This module may import ``devices.z1100.frame`` and the standard library, nothing else of
servotune; ``devices.z1100.frame`` never imports this module. The drivers, the simulator and
the tests import the codec as a whole from here
(``from servotune.devices.z1100 import codec``), so every public name of
``devices.z1100.frame`` is re-exported below (see ``__all__``).
"""

from __future__ import annotations

import enum
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Final

from servotune.devices.z1100.frame import (
    AXES,
    AXIS_MASK,
    BAUD_BY_JUMPERS,
    BAUD_RATES,
    BYTE_MAX,
    COMMANDS,
    COUNTS_PER_REV,
    DEFAULT_BAUD,
    DIRECTION_BIT_POSITIVE,
    ERROR_BITS,
    FENCE_BYTE,
    GAIN_MAX,
    GET_BIT,
    GET_SWITCH_BYTE,
    HEADER,
    INT16_MAX,
    INT16_MIN,
    INT32_MAX,
    INT32_MIN,
    LIMIT_MAX_COUNTS,
    PACKET_TIMEOUT_S,
    POSITIVE32_MAX,
    REJECTION_MASK,
    REPLY_SIZE,
    REPLY_TIMEOUT_S,
    REQUEST_SIZE,
    STM_DEFAULT,
    STM_TICK_S,
    UINT32_MAX,
    UPPER_NIBBLE_SHIFT,
    BadRequest,
    CodecError,
    Command,
    CommandInfo,
    Field,
    Reply,
    ReplyCode,
    ReplyDecoder,
    Request,
    RequestDecoder,
    _check,
    _check_axis,
    decode_reply,
    decode_request,
    encode_reply,
    encode_request,
    error_message,
    getter_of,
    is_fence_reply,
    make_fence,
    moving_flag,
    reply_checksum,
    request_checksum,
    resolve,
    stall_message,
)

# The codec's public surface, as ``codec.<name>``: this module's names ...
__all__ = [
    "CAB_MASK",
    "Cab",
    "Gains",
    "GetValue",
    "Job",
    "StartStatus",
    "StopStatus",
    "decode_get",
    "job_of",
    "make_clr",
    "make_estop",
    "make_flash",
    "make_get",
    "make_get_kab",
    "make_set_acc",
    "make_set_baud",
    "make_set_busy",
    "make_set_cab",
    "make_set_hac",
    "make_set_hvm",
    "make_set_job",
    "make_set_kab",
    "make_set_limit",
    "make_set_stm",
    "make_set_target",
    "make_set_vmax",
    "make_start",
    "make_stop",
    "make_zero",
    "pack_axes",
    "pack_error",
    "pack_int32",
    "pack_kab",
    "pack_limit",
    "pack_start",
    "pack_stop",
    "request_name",
    "sample_time_s",
    "stm_for",
    "unpack_axes",
    "unpack_error",
    "unpack_int32",
    "unpack_kab",
    "unpack_limit",
    "unpack_start",
    "unpack_stop",
]
# ... and, re-exported, every public name of z1100_wire: the drivers, the simulator and
# the tests address both halves as one namespace (listing them is what makes mypy
# --strict accept the re-export).
__all__ += [
    "AXES",
    "AXIS_MASK",
    "BAUD_BY_JUMPERS",
    "BAUD_RATES",
    "BYTE_MAX",
    "COMMANDS",
    "COUNTS_PER_REV",
    "DEFAULT_BAUD",
    "DIRECTION_BIT_POSITIVE",
    "ERROR_BITS",
    "FENCE_BYTE",
    "GAIN_MAX",
    "GET_BIT",
    "GET_SWITCH_BYTE",
    "HEADER",
    "INT16_MAX",
    "INT16_MIN",
    "INT32_MAX",
    "INT32_MIN",
    "LIMIT_MAX_COUNTS",
    "PACKET_TIMEOUT_S",
    "POSITIVE32_MAX",
    "REJECTION_MASK",
    "REPLY_SIZE",
    "REPLY_TIMEOUT_S",
    "REQUEST_SIZE",
    "STM_DEFAULT",
    "STM_TICK_S",
    "UINT32_MAX",
    "UPPER_NIBBLE_SHIFT",
    "BadRequest",
    "CodecError",
    "Command",
    "CommandInfo",
    "Field",
    "Reply",
    "ReplyCode",
    "ReplyDecoder",
    "Request",
    "RequestDecoder",
    "decode_reply",
    "decode_request",
    "encode_reply",
    "encode_request",
    "error_message",
    "getter_of",
    "is_fence_reply",
    "make_fence",
    "moving_flag",
    "reply_checksum",
    "request_checksum",
    "resolve",
    "stall_message",
]


# --- data words ------------------------------------------------------------------------


class Cab(enum.IntFlag):
    """SetCab/GetCab D0: wiring inversions made in software."""

    NONE = 0
    MOTOR_REVERSED = 1 << 0  # motor leads reversed
    ENCODER_SWAPPED = 1 << 1  # encoder A/B swapped
    SWITCH_ACTIVE_HIGH = 1 << 2  # home switch input reads 1 when pressed


CAB_MASK: Final = int(Cab.MOTOR_REVERSED | Cab.ENCODER_SWAPPED | Cab.SWITCH_ACTIVE_HIGH)


class Job(enum.IntEnum):
    """SetJob/GetJob D0."""

    FREE = 0  # free shaft: motor power off (allowed while moving)
    UNDEFINED = 1  # "tanımsız" in the manual
    TARGET = 2  # go to the target with the trapezoidal profile
    VELOCITY = 3  # turn at constant velocity (direction in SetStart)


@dataclass(frozen=True, slots=True)
class Gains:
    """K (gain), A (derivative on the forward path), B (tachometric), 0..255 each."""

    k: int
    a: int
    b: int

    def __post_init__(self) -> None:
        for name, value in (("K", self.k), ("A", self.a), ("B", self.b)):
            _check(name, value, 0, GAIN_MAX)


@dataclass(frozen=True, slots=True)
class StartStatus:
    """SetStart/GetStart D0: axes started (running) and axes whose direction bit is 1
    (positive: counts increase). Direction bits matter only in the velocity job."""

    running: frozenset[int] = frozenset()
    positive: frozenset[int] = frozenset()


@dataclass(frozen=True, slots=True)
class StopStatus:
    """GetStop/GetEstop D0: axes stopped by a Stop/Estop command, axes stopped by their
    error limit (stall; persists until Clr, a new Start or a Job)."""

    by_command: frozenset[int] = frozenset()
    stalled: frozenset[int] = frozenset()


def pack_axes(axes: Iterable[int]) -> int:
    """Bits 0..2 for axes 0..2 (Start, Stop, Estop)."""
    bits = 0
    for axis in axes:
        _check_axis(axis)
        bits |= 1 << axis
    return bits


def unpack_axes(bits: int) -> frozenset[int]:
    """Axes whose bit (0..2) is set; other bits are ignored."""
    return frozenset(axis for axis in range(AXES) if bits >> axis & 1)


def pack_kab(gains: Gains) -> int:
    """K in D2, A in D1, B in D0 (D3 = 0)."""
    return gains.k << 16 | gains.a << 8 | gains.b


def unpack_kab(data: int) -> Gains:
    """K = D2, A = D1, B = D0 (D3 is ignored)."""
    return Gains(data >> 16 & 0xFF, data >> 8 & 0xFF, data & 0xFF)


def pack_int32(value: int) -> int:
    """A signed position as the unsigned data word (two's complement)."""
    _check("value", value, INT32_MIN, INT32_MAX)
    return value & UINT32_MAX


def unpack_int32(data: int) -> int:
    """The data word as a signed 32-bit number (positions)."""
    return data - (1 << 32) if data & 0x8000_0000 else data


def pack_limit(limit_counts: int) -> int:
    """The error limit (0..16383 counts) in D1:D0."""
    _check("error limit", limit_counts, 0, LIMIT_MAX_COUNTS)
    return limit_counts


def unpack_limit(data: int) -> int:
    """ErrMax = (D1 << 8) | D0 (errata decision)."""
    return data & 0xFFFF


def pack_error(error_counts: int) -> int:
    """A position error as D1:D0 (signed 16-bit); the chip saturates larger errors."""
    _check("position error", error_counts, INT16_MIN, INT16_MAX)
    return error_counts & 0xFFFF


def unpack_error(data: int) -> int:
    """D1:D0 as a signed 16-bit number (errata decision)."""
    raw = data & 0xFFFF
    return raw - (1 << ERROR_BITS) if raw >> (ERROR_BITS - 1) else raw


def _direction_bits(axes: frozenset[int]) -> frozenset[int]:
    """Positive axes -> axes whose direction bit is 1, and back (an involution)."""
    return axes if DIRECTION_BIT_POSITIVE else frozenset(range(AXES)) - axes


def pack_start(status: StartStatus) -> int:
    """D0 of SetStart/GetStart: bit k runs motor k+1, bit k+4 is its direction."""
    directions = pack_axes(_direction_bits(status.positive))
    return pack_axes(status.running) | directions << UPPER_NIBBLE_SHIFT


def unpack_start(data: int) -> StartStatus:
    """Inverse of :func:`pack_start`; bits 3 and 7..31 are ignored."""
    positive = _direction_bits(unpack_axes(data >> UPPER_NIBBLE_SHIFT))
    return StartStatus(unpack_axes(data), positive)


def pack_stop(status: StopStatus) -> int:
    """D0 of GetStop/GetEstop: bit k stopped by command, bit k+4 stalled (motor k+1)."""
    return pack_axes(status.by_command) | pack_axes(status.stalled) << UPPER_NIBBLE_SHIFT


def unpack_stop(data: int) -> StopStatus:
    """Inverse of :func:`pack_stop`; other bits are ignored."""
    return StopStatus(unpack_axes(data), unpack_axes(data >> UPPER_NIBBLE_SHIFT))


def job_of(value: int) -> Job | int:
    """The :class:`Job` for a D0 value, or the number itself when the manual has none."""
    try:
        return Job(value)
    except ValueError:
        return value


GetValue = int | bool | Gains | Cab | Job | StartStatus | StopStatus


def decode_get(command: Command, data: int) -> GetValue:
    """The value a Get reply's data word carries, typed by the command's table entry
    (e.g. :class:`Gains` for GetKABH, a signed int for GetEncoder and GetError)."""
    field = COMMANDS[command].reply
    if field is Field.KAB:
        return unpack_kab(data)
    if field is Field.INT32:
        return unpack_int32(data)
    if field is Field.LIMIT:
        return unpack_limit(data)
    if field is Field.ERROR:
        return unpack_error(data)
    if field is Field.CAB:
        return Cab(data & CAB_MASK)
    if field is Field.JOB:
        return job_of(data & 0xFF)
    if field in (Field.BUSY, Field.SWITCH):
        return bool(data & 1)
    if field is Field.START:
        return unpack_start(data)
    if field is Field.STOP:
        return unpack_stop(data)
    if field is Field.STM:
        return data & 0xFF
    if field is Field.POSITIVE32:
        return data
    raise CodecError(f"{COMMANDS[command].name} carries no value")


# --- units -----------------------------------------------------------------------------


def sample_time_s(stm: int) -> float:
    """The servo sampling time for an Stm value: Stm x 32 us."""
    _check("Stm", stm, 1, BYTE_MAX)
    return stm * STM_TICK_S


def stm_for(sample_time_s: float) -> int:
    """The Stm value closest to ``sample_time_s`` (32 us .. 8.16 ms)."""
    stm = round(sample_time_s / STM_TICK_S)
    _check("Stm (sampling time / 32 us)", stm, 1, BYTE_MAX)
    return stm


# --- request builders --------------------------------------------------------------------
# Each returns a Request and sends nothing; each checks its ranges and raises
# CodecError naming the field and the allowed range, so a wrong value never reaches
# the chip (the chip has no "bad value" reply bit).


def _axis_request(command: Command, axis: int, data: int = 0) -> Request:
    _check_axis(axis)
    return Request(command + axis, data)


def make_set_kab(axis: int, k: int, a: int, b: int, *, moving: bool = True) -> Request:
    """SetKABH (``moving=True``: gains while moving; also overwrites KABD) or SetKABD
    (gains at standstill; send after KABH)."""
    command = Command.SET_KABH if moving else Command.SET_KABD
    return _axis_request(command, axis, pack_kab(Gains(k, a, b)))


def make_get_kab(axis: int, *, moving: bool = True) -> Request:
    """GetKABH (``moving=True``) or GetKABD."""
    return _axis_request(Command.GET_KABH if moving else Command.GET_KABD, axis)


def _positive(name: str, value: int) -> int:
    _check(name, value, 0, POSITIVE32_MAX)
    return value


def make_set_vmax(axis: int, vmax_counts_s: int) -> Request:
    """SetVmax (forbidden while the motor moves; 0 = the motor never turns)."""
    return _axis_request(Command.SET_VMAX, axis, _positive("Vmax (counts/s)", vmax_counts_s))


def make_set_acc(axis: int, acc_counts_s2: int) -> Request:
    """SetAcc: acceleration = deceleration (forbidden while the motor moves)."""
    return _axis_request(Command.SET_ACC, axis, _positive("Acc (counts/s^2)", acc_counts_s2))


def make_set_stm(axis: int, stm: int) -> Request:
    """SetStm: sampling time = ``stm`` x 32 us (1..255; 1 at power-on)."""
    _check("Stm", stm, 1, BYTE_MAX)
    return _axis_request(Command.SET_STM, axis, stm)


def make_set_hvm(axis: int, hvm_counts_s: int) -> Request:
    """SetHvm: max speed while homing (forbidden while the motor moves)."""
    return _axis_request(Command.SET_HVM, axis, _positive("Hvm (counts/s)", hvm_counts_s))


def make_set_hac(axis: int, hac_counts_s2: int) -> Request:
    """SetHac: acceleration while homing (forbidden while the motor moves)."""
    return _axis_request(Command.SET_HAC, axis, _positive("Hac (counts/s^2)", hac_counts_s2))


def make_set_limit(axis: int, limit_counts: int) -> Request:
    """SetLimit: position error (0..16383 counts) beyond which motor power is cut."""
    return _axis_request(Command.SET_LIMIT, axis, pack_limit(limit_counts))


def make_set_cab(axis: int, cab: Cab) -> Request:
    """SetCab (forbidden while the motor moves)."""
    _check("Cab", int(cab), 0, CAB_MASK)
    return _axis_request(Command.SET_CAB, axis, int(cab))


def make_set_job(axis: int, job: Job) -> Request:
    """SetJob: clears earlier errors; forbidden while moving except ``Job.FREE``."""
    _check("job", int(job), 0, max(Job))
    return _axis_request(Command.SET_JOB, axis, int(job))


def make_set_busy(axis: int, drives_busy: bool) -> Request:
    """SetBusy: whether this motor holds the BUSY pin low while it moves."""
    return _axis_request(Command.SET_BUSY, axis, int(drives_busy))


def make_set_target(axis: int, target_counts: int) -> Request:
    """SetTarget (signed 32-bit; forbidden while the motor moves)."""
    _check("target (counts)", target_counts, INT32_MIN, INT32_MAX)
    return _axis_request(Command.SET_TARGET, axis, pack_int32(target_counts))


def make_start(axes: Iterable[int], *, positive: Iterable[int] = ()) -> Request:
    """SetStart for ``axes``; ``positive``: axes whose velocity-job direction is +."""
    return Request(Command.SET_START, pack_start(StartStatus(frozenset(axes), frozenset(positive))))


def make_stop(axes: Iterable[int]) -> Request:
    """SetStop: these motors decelerate to a stop (velocity job only)."""
    return Request(Command.SET_STOP, pack_axes(axes))


def make_estop(axes: Iterable[int]) -> Request:
    """SetEstop: these motors stop at once (a hard jolt)."""
    return Request(Command.SET_ESTOP, pack_axes(axes))


def make_clr() -> Request:
    """SetClr: clears the stall errors."""
    return Request(Command.SET_CLR)


def make_zero(axis: int) -> Request:
    """SetZero: go to the home switch with Hvm/Hac (forbidden while the motor moves)."""
    return _axis_request(Command.SET_ZERO, axis)


def make_set_baud(baud: int) -> Request:
    """SetBaud: the chip answers at the old rate, then switches."""
    if baud not in BAUD_RATES:
        raise CodecError(f"baud must be one of {', '.join(map(str, BAUD_RATES))}, got {baud!r}")
    return Request(Command.SET_BAUD, baud)


def make_flash() -> Request:
    """SetFlash: write the parameters to flash (loaded at power-on)."""
    return Request(Command.SET_FLASH)


def request_name(request: Request) -> str:
    """A request as the driver reports what it sent, e.g. ``SetEstop 2``,
    ``SetJob[motor 1] 0``, ``GetEncoder[motor 3]``."""
    command = request.command
    if command is None:
        return f"0x{request.command_byte:02X}"
    info = COMMANDS[command]
    axis = request.axis
    suffix = f"[motor {axis + 1}]" if axis is not None else ""
    data = f" {request.data}" if not command.is_get and info.request is not Field.NONE else ""
    return f"{info.name}{suffix}{data}"


def make_get(command: Command, axis: int | None = None) -> Request:
    """Any Get; ``axis`` is required for per-axis commands and refused otherwise."""
    info = COMMANDS[command]
    if not command.is_get:
        raise CodecError(f"{info.name} is not a Get command")
    if info.per_axis:
        if axis is None:
            raise CodecError(f"{info.name} needs an axis (0..{AXES - 1})")
        return _axis_request(command, axis)
    if axis is not None:
        raise CodecError(f"{info.name} is for the whole chip and takes no axis")
    return Request(command)
