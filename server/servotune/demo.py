"""The demo: simulated devices on pseudo-terminals inside the server process.

The simulators run on real ptys, so the driver opens them with exactly the code it
uses for a USB adapter; only the far end of the cable is simulated.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Callable, Iterator
from pathlib import Path

from servotune.config import LinkSpec
from servotune.protocols.z1100 import Gains
from servotune.sim.physics import DcMotorParams
from servotune.sim.serial_sim import PtySimulator
from servotune.sim.slap2 import Slap2Bus, Slap2Module
from servotune.sim.z1100 import AxisParameters, Z1100Chip

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


Z1100_BAUD = 9600
# Three motors with different loads, so their best gains differ (see the tuning table
# in docs/z1100-simulator.md): unloaded, 5x and 20x the rotor inertia.
Z1100_LOADS_KG_M2 = (0.0, 1.9e-6, 7.6e-6)
# The demo chip's flash as an integrator would have left it: gains from that table
# for each load, Stm 1, moves of about 3000 rpm. Without a flash the chip powers up
# with every parameter 0 and cannot move (manual).
Z1100_DEMO_FLASH = [
    {"kabh": [32, 16, 8], "kabd": [24, 16, 8]},
    {"kabh": [128, 16, 8], "kabd": [96, 16, 8]},
    {"kabh": [128, 64, 8], "kabd": [96, 64, 8]},
]


def _z1100_flash(path: Path) -> None:
    if path.exists():
        return
    axes = [
        AxisParameters(
            kabh=Gains(*gains["kabh"]),
            kabd=Gains(*gains["kabd"]),
            vmax_counts_s=100_000,
            acc_counts_s2=1_000_000,
            limit_counts=4000,
            hvm_counts_s=20_000,
            hac_counts_s2=200_000,
        ).to_json()
        for gains in Z1100_DEMO_FLASH
    ]
    path.write_text(json.dumps({"axes": axes}))


@contextlib.contextmanager
def z1100_demo_line(state_dir: Path) -> Iterator[list[LinkSpec]]:
    """One simulated Z1100 chip with three differently loaded motors."""
    state_dir.mkdir(parents=True, exist_ok=True)
    flash = state_dir / "z1100_flash.json"
    _z1100_flash(flash)
    chip = Z1100Chip.with_loads(Z1100_LOADS_KG_M2, flash_path=flash, jumper_baud=Z1100_BAUD)
    simulator = PtySimulator(chip, baud=Z1100_BAUD)
    simulator.start()
    try:
        yield [
            LinkSpec(
                device="z1100",
                path=simulator.path,
                link_id="demo-z1100",
                baud=Z1100_BAUD,
                addresses=[0, 1, 2],
                lines=512,
                names={0: "Z1100 X unloaded", 1: "Z1100 Y 5x load", 2: "Z1100 Z 20x load"},
            )
        ]
    finally:
        simulator.stop()


def demo_simulators(
    data_dir: Path,
) -> list[Callable[[], contextlib.AbstractContextManager[list[LinkSpec]]]]:
    """Context managers that start the demo's simulators and yield their link specs."""
    return [
        lambda: slap2_demo_line(data_dir / "sim"),
        lambda: z1100_demo_line(data_dir / "sim"),
        ep7047_demo_slave,
    ]


@contextlib.contextmanager
def ep7047_demo_slave() -> Iterator[list[LinkSpec]]:
    """One simulated EP7047-1032 (stepper, encoder, cam, C track) on the in-process
    fake master: EtherCAT needs no pty; the link spec's NIC ``sim`` selects it."""
    yield [
        LinkSpec(
            device="ep7047",
            path="sim",
            link_id="demo-ep7047",
            baud=0,
            addresses=[1],
            names={1: "EP7047 stepper"},
        )
    ]
