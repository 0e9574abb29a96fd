"""Link supervision helpers: a tap on a simulated line, a hub on one line."""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from servotune.devices.slap2.link import Slap2Link, Slap2LinkConfig
from servotune.sim.base import SimDevice
from servotune.transports.serial import SerialConnector


class Tap:
    """A SimDevice between the pty and a device: records what the device received and
    lets a test rewrite what it sends (called on the simulator's thread)."""

    def __init__(self, device: SimDevice) -> None:
        self.device = device
        self.received = bytearray()
        self._lock = threading.Lock()
        # (received byte, device output) -> what goes on the wire instead
        self.rewrite: Callable[[int, bytes], bytes] | None = None
        self._late: list[tuple[float, bytes]] = []
        self._in_order = False
        self._now = 0.0

    def power_cycle(self, address: int | None = None) -> None:
        self.device.power_cycle(address)  # type: ignore[attr-defined]

    def send_late(self, data: bytes, delay_s: float, *, in_order: bool = False) -> None:
        """Put ``data`` on the wire ``delay_s`` after the current simulation time.

        ``in_order``: a device that is slow to answer, as on a real line: whatever it
        sends later waits behind ``data`` (and is due no earlier than it). Without it,
        later output overtakes ``data``, which no single serial device can do."""
        due = self._now + delay_s
        if in_order and self._late:
            due = max(due, self._late[-1][0])
        self._late.append((due, data))
        self._in_order = in_order

    def _hold_behind_late(self, out: bytes) -> bytes:
        # Output of a device answering late in order queues behind what is held back.
        if out and self._late and self._in_order:
            self._late.append((self._late[-1][0], out))
            return b""
        return out

    def advance_to(self, t_s: float) -> bytes:
        self._now = max(self._now, t_s)
        out = self._hold_behind_late(self.device.advance_to(t_s))
        due = [item for item in self._late if item[0] <= t_s]
        if due:
            self._late = [item for item in self._late if item[0] > t_s]
            out += b"".join(data for _, data in due)
        return out

    def receive(self, byte: int) -> bytes:
        with self._lock:
            self.received.append(byte)
        out = self.device.receive(byte)
        if self.rewrite is not None:
            out = self.rewrite(byte, out)
        return self._hold_behind_late(out)

    def mark(self) -> int:
        with self._lock:
            return len(self.received)

    def since(self, mark: int) -> bytes:
        with self._lock:
            return bytes(self.received[mark:])


def hub_on_line(
    path: str, addresses: list[int], tmp_path: Path, **settings: Any
) -> tuple[Any, Slap2Link]:
    """(a hub over one SLAP2 link on ``path``, that link): the link reports to the
    hub, which exists only after the link, so a forwarding sink bridges the two.
    ``settings``: fields of ``Slap2LinkConfig`` to change."""
    from servotune.hub.hub import Hub
    from servotune.storage import Storage

    holder: list[Hub] = []

    class Forward:
        def __getattr__(self, name: str) -> object:
            return getattr(holder[0], name)

    config = Slap2LinkConfig(link_id="line", path=path, addresses=addresses, **settings)
    link = Slap2Link(config, SerialConnector(path, 19200), Forward())  # type: ignore[arg-type]
    hub = Hub([link], Storage(tmp_path / "db.sqlite"))
    holder.append(hub)
    return hub, link
