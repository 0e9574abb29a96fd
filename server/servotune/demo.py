"""The demo: simulated devices on pseudo-terminals inside the server process.

The simulators run on real ptys, so the driver opens them with exactly the code it
uses for a USB adapter; only the far end of the cable is simulated.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from pathlib import Path

from servotune.config import LinkSpec
from servotune.sim.physics import DcMotorParams
from servotune.sim.serial_sim import PtySimulator
from servotune.sim.slap2 import Slap2Bus, Slap2Module

SLAP2_BAUD = 19200
# Module 1 carries a load of 1.7x the rotor inertia and more friction (a small lead
# screw carriage). With the manual's default gains it still settles, but overshoots
# and rings visibly (measured: ~35 counts over on a 2000-count move; at 2x rotor
# inertia with less friction the defaults no longer settle), so its best gains differ
# from the unloaded module 0 and tuning it shows on the plots.
SLAP2_LOADED = DcMotorParams(load_inertia_kg_m2=6.5e-7, coulomb_friction_nm=0.5e-3)


@contextlib.contextmanager
def slap2_demo_line(state_dir: Path) -> Iterator[list[LinkSpec]]:
    """Two SLAP2 modules (addresses 0 and 1) sharing one simulated RS232 line."""
    state_dir.mkdir(parents=True, exist_ok=True)
    bus = Slap2Bus(
        [
            Slap2Module(0, eeprom_path=state_dir / "slap2_0.json"),
            Slap2Module(1, eeprom_path=state_dir / "slap2_1.json", params=SLAP2_LOADED),
        ]
    )
    simulator = PtySimulator(bus, baud=SLAP2_BAUD)
    simulator.start()
    try:
        yield [
            LinkSpec(
                device="slap2",
                path=simulator.path,
                link_id="demo-slap2",
                baud=SLAP2_BAUD,
                addresses=[0, 1],
                lines=512,
                names={0: "SLAP2 #0 unloaded", 1: "SLAP2 #1 with load"},
            )
        ]
    finally:
        simulator.stop()


def demo_simulators(
    data_dir: Path,
) -> list[Callable[[], contextlib.AbstractContextManager[list[LinkSpec]]]]:
    """Context managers that start the demo's simulators and yield their link specs."""
    return [lambda: slap2_demo_line(data_dir / "sim")]
