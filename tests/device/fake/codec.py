"""The fake servo's wire codec (sans-IO): ASCII lines ending in LF.

Host -> device: ``R`` read the position, ``M<counts>`` move to an absolute position,
``S`` stop where the shaft is, ``V<counts/s>`` set the speed, ``Q`` read the speed.
Device -> host, one line per command: ``P<counts> <moving 0|1>`` (to ``R``),
``V<counts/s>`` (to ``Q``), ``OK`` (done) or ``NO`` (refused).

``LineDecoder.feed`` takes any bytes and returns the replies completed so far; a line
it cannot read is dropped and counted (``dropped``): the next LF resynchronises.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

LF: Final = b"\n"
POSITION_LIMIT: Final = 10_000_000
SPEED_RANGE: Final = (1, 10_000)  # counts/s
DEFAULT_SPEED: Final = 2_000


@dataclass(frozen=True, slots=True)
class Position:
    counts: int
    moving: bool


@dataclass(frozen=True, slots=True)
class Speed:
    counts_s: int


@dataclass(frozen=True, slots=True)
class Ok:
    pass


@dataclass(frozen=True, slots=True)
class Refused:
    pass


Reply = Position | Speed | Ok | Refused


def _check(name: str, value: int, low: int, high: int) -> None:
    if not low <= value <= high:
        raise ValueError(f"{name} must be {low}..{high} (got {value})")


def make_read() -> bytes:
    return b"R\n"


def make_read_speed() -> bytes:
    return b"Q\n"


def make_move(target: int) -> bytes:
    _check("position", target, -POSITION_LIMIT, POSITION_LIMIT)
    return f"M{target}\n".encode()


def make_set_speed(counts_s: int) -> bytes:
    _check("speed", counts_s, *SPEED_RANGE)
    return f"V{counts_s}\n".encode()


def make_stop() -> bytes:
    return b"S\n"


def encode_reply(reply: Reply) -> bytes:
    """The device's side (the simulator and the tests use it)."""
    if isinstance(reply, Position):
        return f"P{reply.counts} {int(reply.moving)}\n".encode()
    if isinstance(reply, Speed):
        return f"V{reply.counts_s}\n".encode()
    return b"OK\n" if isinstance(reply, Ok) else b"NO\n"


def parse_reply(line: str) -> Reply | None:
    """One reply line without its LF; None when it is not one."""
    try:
        if line == "OK":
            return Ok()
        if line == "NO":
            return Refused()
        if line.startswith("V"):
            return Speed(int(line[1:]))
        if line.startswith("P"):
            counts, moving = line[1:].split(" ")
            if moving not in ("0", "1"):
                return None
            return Position(int(counts), moving == "1")
    except ValueError:
        return None
    return None


class LineDecoder:
    """Bytes in, replies out; resynchronises on LF (see the module docstring)."""

    def __init__(self) -> None:
        self._buffer = bytearray()
        self.dropped = 0

    def feed(self, data: bytes) -> list[Reply]:
        replies: list[Reply] = []
        self._buffer += data
        while (end := self._buffer.find(LF)) >= 0:
            raw = bytes(self._buffer[:end])
            del self._buffer[: end + 1]
            reply = parse_reply(raw.decode("ascii", errors="replace"))
            if reply is None:
                self.dropped += 1
            else:
                replies.append(reply)
        return replies
