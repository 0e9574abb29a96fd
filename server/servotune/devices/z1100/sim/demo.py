"""The simulated Z1100 as servotune runs it: the demo's chip (three differently loaded
motors with an integrator's flash, in a process of its own) and ``servotune sim z1100``.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Final

from servotune.devices.z1100.codec import (
    DEFAULT_BAUD,
    BadRequest,
    Gains,
    RequestDecoder,
    request_name,
)
from servotune.devices.z1100.sim.chip import Z1100Chip
from servotune.devices.z1100.sim.servo import AxisHardware, AxisParameters
from servotune.sim.process import SimProcess, demo_serial_process
from servotune.sim.pty import run_pty_simulator
from servotune.sim.trace import TracedDevice

# Three motors with different loads, so their best gains differ (see the tuning table
# in docs/z1100-simulator.md): unloaded, 5x and 20x the rotor inertia.
Z1100_LOADS_KG_M2: Final = (0.0, 1.9e-6, 7.6e-6)
# The demo chip's flash as an integrator would have left it: gains from that table
# for each load, Stm 1, moves of about 3000 rpm. Without a flash the chip powers up
# with every parameter 0 and cannot move (manual).
Z1100_DEMO_FLASH: Final = [
    {"kabh": [32, 16, 8], "kabd": [24, 16, 8]},
    {"kabh": [128, 16, 8], "kabd": [96, 16, 8]},
    {"kabh": [128, 64, 8], "kabd": [96, 64, 8]},
]
DEMO_NAMES: Final = {0: "Z1100 X unloaded", 1: "Z1100 Y 5x load", 2: "Z1100 Z 20x load"}


def write_demo_flash(
    path: Path, gains: Sequence[Mapping[str, Sequence[int]]] = Z1100_DEMO_FLASH
) -> None:
    """A flash at ``path`` as the demo's integrator leaves it, unless a flash is there:
    each axis's ``gains`` (``{"kabh": (k, a, b), "kabd": (k, a, b)}``, the demo's
    ``Z1100_DEMO_FLASH`` by default) with the demo's profile (moves of about 3000 rpm)."""
    if path.exists():
        return
    axes = [
        AxisParameters(
            kabh=Gains(*axis["kabh"]),
            kabd=Gains(*axis["kabd"]),
            vmax_counts_s=100_000,
            acc_counts_s2=1_000_000,
            limit_counts=4000,
            hvm_counts_s=20_000,
            hac_counts_s2=200_000,
        ).to_json()
        for axis in gains
    ]
    path.write_text(json.dumps({"axes": axes}))


def build_z1100_chip(state_dir: Path) -> Z1100Chip:
    """The demo's Z1100: three differently loaded motors, flash in a file."""
    state_dir.mkdir(parents=True, exist_ok=True)
    flash = state_dir / "z1100_flash.json"
    write_demo_flash(flash)
    return Z1100Chip.with_loads(Z1100_LOADS_KG_M2, flash_path=flash, jumper_baud=DEFAULT_BAUD)


def stop_plant(address: int, state_dir: Path) -> TracedDevice[Z1100Chip]:
    """The demo's chip without home switches (nothing but a stop ends a motion), its
    flash in ``state_dir``, tracing motor ``address``'s shaft; a copy is powered off as
    Job 0 does (``perf.stops``)."""
    flash = state_dir / "z1100_flash.json"
    write_demo_flash(flash)
    chip = Z1100Chip(
        [
            AxisHardware(load_inertia_kg_m2=j, home_switch_counts=-(10**9))
            for j in Z1100_LOADS_KG_M2
        ],
        flash_path=flash,
        jumper_baud=DEFAULT_BAUD,
    )

    def read(chip: Z1100Chip) -> tuple[float, float]:
        state = chip.axis_state(address)
        return float(state.encoder_counts), float(state.speed_counts_s)

    decoder = RequestDecoder()

    def decode(byte: int) -> list[str]:
        # The host's requests, named as the driver names what it sent.
        events = decoder.feed(bytes((byte,)))
        return [request_name(e) for e in events if not isinstance(e, BadRequest)]

    return TracedDevice(
        chip,
        read,
        lambda: bool(chip.axis_state(address).powered),
        decode,
        lambda copy: copy.free(address),  # the driver's power-off: SetJob 0
    )


def z1100_record(chip: Z1100Chip) -> dict[str, Any]:
    """Each axis as the chip sees it: job, start bit, power, speed, counter."""
    axes = []
    for axis in range(3):
        state = chip.axis_state(axis)
        axes.append(
            {
                "axis": axis,
                "job": state.job,
                "running": state.running,
                "powered": state.powered,
                "stopped_by_command": state.stopped_by_command,
                "stalled": state.stalled,
                "encoder_counts": state.encoder_counts,
                "speed_counts_s": state.speed_counts_s,
            }
        )
    return {"axes": axes}


def demo_chip_process(state_dir: Path) -> contextlib.AbstractContextManager[SimProcess]:
    """The demo's chip in a child process; its ``ready["path"]`` is the pty to open."""
    return demo_serial_process("z1100", build_z1100_chip, DEFAULT_BAUD, z1100_record, state_dir)


def serve_z1100(baud: int, state_dir: Path | None, link_path: str | None) -> None:
    """``servotune sim z1100``: a chip with unloaded motors on a pty, its flash in
    ``state_dir/z1100_flash.json`` (in memory without). Blocks until SIGINT/SIGTERM."""
    flash = state_dir / "z1100_flash.json" if state_dir else None
    chip = Z1100Chip(flash_path=flash, jumper_baud=baud)
    run_pty_simulator(chip, baud=baud, link_path=link_path)
