"""SLAP2 simulation, top layer: the RS232 line several modules share (``Slap2Line``).

The seam: ``devices/slap2/sim/module.py`` is the firmware of one module (``Slap2Module``,
on top of the controller in ``devices/slap2/sim/controller.py``); this is the multi-drop
line in front of them - every host byte to every module, their transmissions merged in
line order, simulation time advanced in whole controller ticks on all modules - and the
``SimDevice`` that ``PtySimulator`` (``sim/pty.py``) puts on a pseudo-terminal. Sans-IO:
no clock, no file descriptor (the modules' optional EEPROM files aside).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from pathlib import Path

from servotune.devices.slap2.sim.controller import TICK_S
from servotune.devices.slap2.sim.module import Slap2Module
from servotune.sim.physics import DcMotorParams


class Slap2Line:
    """Several SLAP2 modules on one RS232 line; implements ``SimDevice``.

    Every host byte goes to every module; the bytes of all modules whose transmitter is
    on are returned (normally exactly one: the selected module; the echo of the
    previously selected module comes first). Time advances in whole controller ticks
    of 841.5 us on all modules in lock-step; ``advance_to`` keeps the fraction of a
    tick for the next call and never steps backwards. Deterministic: no clock inside.
    """

    def __init__(self, modules: Iterable[Slap2Module]) -> None:
        self._modules: list[Slap2Module] = list(modules)
        if not self._modules:
            raise ValueError("a line needs at least one module")
        addresses = [m.address for m in self._modules]
        if len(set(addresses)) != len(addresses):
            raise ValueError(f"duplicate module addresses: {addresses}")
        self._by_address = {m.address: m for m in self._modules}
        self._ticks = 0
        self._time_s = 0.0

    @classmethod
    def with_addresses(
        cls,
        addresses: Sequence[int],
        *,
        state_dir: Path | None = None,
        params: DcMotorParams | None = None,
    ) -> Slap2Line:
        """Modules with default serial numbers; EEPROM files ``slap2_<addr>.json``."""
        modules = []
        for address in addresses:
            path = state_dir / f"slap2_{address}.json" if state_dir is not None else None
            modules.append(Slap2Module(address, eeprom_path=path, params=params))
        return cls(modules)

    @property
    def modules(self) -> list[Slap2Module]:
        return list(self._modules)

    @property
    def time_s(self) -> float:
        """Simulation time reached."""
        return self._time_s

    @property
    def ticks(self) -> int:
        """Controller ticks run so far."""
        return self._ticks

    def module(self, address: int) -> Slap2Module:
        """The module with this address (``KeyError`` if there is none)."""
        return self._by_address[address]

    def power_cycle(self, address: int | None = None) -> None:
        """Power-cycle one module, or all (``None``: the whole line's supply).

        Only address 0 powers up selected (and sends its banner); if another module
        was selected when address 0 alone is cycled, both transmit afterwards, as two
        real modules would.
        """
        targets = self._modules if address is None else [self.module(address)]
        for module in targets:
            module.power_cycle()

    def advance_to(self, t_s: float) -> bytes:
        """Run every module's controller ticks due up to ``t_s``; returns banners."""
        if t_s > self._time_s:
            self._time_s = t_s
            due = math.floor(t_s / TICK_S + 1e-9)
            if due > self._ticks:
                # The modules do not interact between two host bytes (each has its own
                # motor), so each runs its ticks in one go: the same as lock-step.
                for module in self._modules:
                    module.run_ticks(due - self._ticks)
                self._ticks = due
        return b"".join(module.take_output() for module in self._modules)

    def receive(self, byte: int) -> bytes:
        """Deliver one host byte to every module; returns what goes on the line."""
        first = bytearray()
        later = bytearray()
        for module in self._modules:
            was_transmitting = module.transmitting
            data = module.receive(byte)
            (first if was_transmitting else later).extend(data)
        return bytes(first + later)
