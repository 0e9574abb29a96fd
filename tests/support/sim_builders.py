"""Simulated device lines for tests (SLAP2 buses, Z1100 chips), built in a simulator
process of their own.

The builders are module-level functions (picklable) in a module that imports only the
simulators, so a spawned simulator process starts without the test machinery.
``WireRecorder`` wraps a simulated SLAP2 line and records every line the host sent, with
the wall-clock time it reached the simulated device and the module selected then: the
simulated device's own record of the wire.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from pathlib import Path
from typing import Any

from servotune.devices.slap2.sim.demo import SLAP2_LOADED
from servotune.devices.slap2.sim.line import Slap2Line
from servotune.devices.slap2.sim.module import Slap2Module
from servotune.devices.z1100.sim.chip import Z1100Chip
from servotune.devices.z1100.sim.demo import Z1100_DEMO_FLASH, Z1100_LOADS_KG_M2, write_demo_flash
from servotune.sim.physics import DcMotorParams

CR = 0x0D
CTRL_X = 0x18


def slap2_line(addresses: list[int], eeprom_dir: Path) -> Slap2Line:
    """Modules at ``addresses`` with their EEPROMs in ``eeprom_dir``."""
    return Slap2Line(
        [Slap2Module(a, eeprom_path=eeprom_dir / f"eeprom_{a}.json") for a in addresses]
    )


def recorded_slap2_line(addresses: list[int], eeprom_dir: Path) -> WireRecorder:
    """``slap2_line`` with a ``WireRecorder`` in front."""
    return WireRecorder(slap2_line(addresses, eeprom_dir))


class WireRecorder:
    """A ``SimDevice`` that passes everything to a ``Slap2Line`` and records host lines."""

    def __init__(self, bus: Slap2Line) -> None:
        self.bus = bus
        self.lines: list[tuple[float, int | None, str]] = []
        self._buffer = bytearray()
        self._selected: int | None = None
        self._lock = threading.Lock()

    def advance_to(self, t_s: float) -> bytes:
        return self.bus.advance_to(t_s)

    def receive(self, byte: int) -> bytes:
        if byte == CR:
            line = self._buffer.decode("latin-1").replace(" ", "").lower()
            self._buffer.clear()
            if line.startswith("se") and line[2:].isdigit():
                self._selected = int(line[2:])
            with self._lock:
                self.lines.append((time.monotonic(), self._selected, line))
        elif byte == CTRL_X:
            self._buffer.clear()  # the module discards the line typed so far, so do we
        elif byte >= 0x20:
            self._buffer.append(byte)
        return self.bus.receive(byte)

    def since(self, t: float, address: int | None = None) -> list[tuple[float, str]]:
        with self._lock:
            lines = list(self.lines)
        return [(at, line) for at, sel, line in lines if at >= t and address in (None, sel)]

    def first(self, line: str, address: int, after: float) -> float | None:
        for at, sent in self.since(after, address):
            if sent == line:
                return at
        return None


def demo_slap2_line() -> Slap2Line:
    """The demo's SLAP2 line (module 1 carries the load), without limit switches."""
    free: dict[str, Any] = {"limit1_count": None, "limit2_count": None}
    return Slap2Line(
        [
            Slap2Module(0, params=DcMotorParams(**free)),
            Slap2Module(1, params=dataclasses.replace(SLAP2_LOADED, **free)),
        ]
    )


def demo_slap2_line_with_eeproms(eeprom_dir: Path) -> Slap2Line:
    """The demo's SLAP2 line as the demo runs it: module 0 unloaded, module 1 with
    ``SLAP2_LOADED`` (its limit switches included), EEPROMs in ``eeprom_dir``."""
    return Slap2Line(
        [
            Slap2Module(0, eeprom_path=eeprom_dir / "eeprom_0.json"),
            Slap2Module(1, eeprom_path=eeprom_dir / "eeprom_1.json", params=SLAP2_LOADED),
        ]
    )


def z1100_chip(
    flash_path: Path, jumper_baud: int, kab: tuple[int, int, int] | None = None
) -> Z1100Chip:
    """The demo's Z1100 (its three loads, its profile) with its flash at ``flash_path``
    (written unless there): the demo's flash gains, or ``kab`` as KABH and KABD of every
    motor."""
    gains = Z1100_DEMO_FLASH
    if kab is not None:
        gains = [{"kabh": kab, "kabd": kab}] * len(Z1100_LOADS_KG_M2)
    write_demo_flash(flash_path, gains)
    return Z1100Chip.with_loads(Z1100_LOADS_KG_M2, flash_path=flash_path, jumper_baud=jumper_baud)
