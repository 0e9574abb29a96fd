"""The simulated fake servo (a ``servotune.sim.base.SimDevice``): it parses the host's
lines itself (not with ``codec.py``: a simulator is the codec's independent check) and
moves its shaft towards the target at ``speed`` counts/s. Served on a pseudo-terminal by
the generic ``servotune.sim.pty.PtySimulator``."""

from __future__ import annotations

SPEED_MAX = 10_000


class FakeServo:
    """One axis; ``lines_seen`` is every line the host sent, in order."""

    def __init__(self, speed: int = 2_000) -> None:
        self.position = 0.0
        self.target = 0
        self.speed = speed
        self.lines_seen: list[str] = []
        self._t = 0.0
        self._line = bytearray()

    @property
    def moving(self) -> bool:
        return round(self.position) != self.target

    def advance_to(self, t_s: float) -> bytes:
        if t_s > self._t:
            step = self.speed * (t_s - self._t)
            gap = self.target - self.position
            self.position = (
                self.target if abs(gap) <= step else self.position + step * (1 if gap > 0 else -1)
            )
            self._t = t_s
        return b""

    def receive(self, byte: int) -> bytes:
        if byte != 0x0A:
            self._line.append(byte)
            return b""
        line = self._line.decode("ascii", errors="replace")
        self._line.clear()
        self.lines_seen.append(line)
        return self._answer(line)

    def _answer(self, line: str) -> bytes:
        if line == "R":
            return f"P{round(self.position)} {int(self.moving)}\n".encode()
        if line == "Q":
            return f"V{self.speed}\n".encode()
        if line == "S":
            self.target = round(self.position)
            return b"OK\n"
        try:
            value = int(line[1:])
        except ValueError:
            return b"NO\n"
        if line[:1] == "M":
            self.target = value
            return b"OK\n"
        if line[:1] == "V" and 1 <= value <= SPEED_MAX:
            self.speed = value
            return b"OK\n"
        return b"NO\n"
