"""The demo: simulated devices, each in a process of its own.

The serial simulators run on real ptys, so the driver opens them with exactly the
code it uses for a USB adapter; only the far end of the cable is simulated. The
EtherCAT slave runs behind the driver's master seam (``servotune.devices.ep7047.sim.process``).
Each simulator is a child process of the server (``servotune.sim.process``: spawned,
named ``sim-<device>``, stopped with the server, and ending by itself when the server
is killed), so the simulated devices never compete with the server's event loop for
one Python interpreter - see docs/simulator.md, "The demo's processes".

Every child writes a record of its device's state to
``<data dir>/sim/<device>-record.json`` about four times a second: what reached the
device, as the device sees it (the soak test checks a STOP against it).
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from servotune.config import LinkSpec
from servotune.devices.ep7047.sim.netns import netns_problem, slave_process, veth_pair
from servotune.devices.ep7047.sim.process import ep7047_sim_process
from servotune.devices.ep7047.sim.slave import DEMO_COUNTS_PER_REV
from servotune.devices.slap2.sim.line import Slap2Bus
from servotune.devices.slap2.sim.module import Slap2Module
from servotune.devices.z1100.codec import Gains
from servotune.devices.z1100.sim.chip import Z1100Chip
from servotune.devices.z1100.sim.servo import AxisParameters
from servotune.sim.physics import DcMotorParams
from servotune.sim.process import SerialSimSpec, serial_sim_process

logger = logging.getLogger(__name__)

SLAP2_BAUD = 19200
# Module 1 carries a load of 1.7x the rotor inertia and more friction (a small lead
# screw carriage). With the manual's default gains it still settles, but overshoots
# and rings visibly (measured: ~35 counts over on a 2000-count move; at 2x rotor
# inertia with less friction the defaults no longer settle), so its best gains differ
# from the unloaded module 0 and tuning it shows on the plots.
SLAP2_LOADED = DcMotorParams(load_inertia_kg_m2=6.5e-7, coulomb_friction_nm=0.5e-3)


def record_path(state_dir: Path, device: str) -> Path:
    """Where the simulator of ``device`` writes its record (see the module docstring)."""
    return state_dir / f"{device}-record.json"


def build_slap2_bus(state_dir: Path) -> Slap2Bus:
    """The demo's SLAP2 line: modules 0 (unloaded) and 1 (loaded), EEPROMs in files."""
    state_dir.mkdir(parents=True, exist_ok=True)
    return Slap2Bus(
        [
            Slap2Module(0, eeprom_path=state_dir / "slap2_0.json"),
            Slap2Module(1, eeprom_path=state_dir / "slap2_1.json", params=SLAP2_LOADED),
        ]
    )


def slap2_record(bus: Slap2Bus) -> dict[str, Any]:
    """Each module as its firmware sees it: status word, position, PWM, shaft speed."""
    return {
        "modules": [
            {
                "address": m.address,
                "rss": m.rss,
                "vm": bool(m.rss & 0b100),
                "pm": bool(m.rss & 0b1000),
                "moving": m.moving,
                "position": m.position,
                "pwm": m.pwm,
                "speed_rad_s": m.motor.speed_rad_s,
            }
            for m in bus.modules
        ]
    }


@contextlib.contextmanager
def slap2_demo_line(state_dir: Path) -> Iterator[list[LinkSpec]]:
    """Two SLAP2 modules (addresses 0 and 1) sharing one simulated RS232 line."""
    spec = SerialSimSpec(
        "slap2",
        functools.partial(build_slap2_bus, state_dir),
        SLAP2_BAUD,
        slap2_record,
        record_path(state_dir, "slap2"),
    )
    with serial_sim_process(spec) as simulator:
        yield [
            LinkSpec(
                device="slap2",
                path=simulator.ready["path"],
                link_id="demo-slap2",
                baud=SLAP2_BAUD,
                addresses=[0, 1],
                lines=512,
                names={0: "SLAP2 #0 unloaded", 1: "SLAP2 #1 with load"},
            )
        ]


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


def build_z1100_chip(state_dir: Path) -> Z1100Chip:
    """The demo's Z1100: three differently loaded motors, flash in a file."""
    state_dir.mkdir(parents=True, exist_ok=True)
    flash = state_dir / "z1100_flash.json"
    _z1100_flash(flash)
    return Z1100Chip.with_loads(Z1100_LOADS_KG_M2, flash_path=flash, jumper_baud=Z1100_BAUD)


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


@contextlib.contextmanager
def z1100_demo_line(state_dir: Path) -> Iterator[list[LinkSpec]]:
    """One simulated Z1100 chip with three differently loaded motors."""
    spec = SerialSimSpec(
        "z1100",
        functools.partial(build_z1100_chip, state_dir),
        Z1100_BAUD,
        z1100_record,
        record_path(state_dir, "z1100"),
    )
    with serial_sim_process(spec) as simulator:
        yield [
            LinkSpec(
                device="z1100",
                path=simulator.ready["path"],
                link_id="demo-z1100",
                baud=Z1100_BAUD,
                addresses=[0, 1, 2],
                lines=512,
                names={0: "Z1100 X unloaded", 1: "Z1100 Y 5x load", 2: "Z1100 Z 20x load"},
            )
        ]


@contextlib.contextmanager
def ep7047_demo_slave(state_dir: Path) -> Iterator[list[LinkSpec]]:
    """One simulated EP7047-1032 (stepper, encoder, cam, C track) in its own process,
    reached through ``ProcessMaster`` (the link spec's NIC is ``sim:<socket>``)."""
    with ep7047_sim_process(record_path(state_dir, "ep7047")) as simulator:
        yield [
            LinkSpec(
                device="ep7047",
                path=simulator.ready["path"],
                link_id="demo-ep7047",
                baud=0,
                addresses=[1],
                names={1: "EP7047 stepper"},
            )
        ]


def state_dir_problem(state_dir: Path) -> str | None:
    """Why the simulators cannot keep their state in ``state_dir`` (None: they can).

    Checked before the simulators start: each creates and writes it from its own
    process, where a failure only says "failed to start".
    """
    try:
        state_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=state_dir, prefix=".write-check-"):
            pass
    except OSError as exc:
        return (
            f"the simulators' state directory {state_dir} cannot be written by uid "
            f"{os.getuid()} ({exc.strerror or exc})"
        )
    return None


@contextlib.contextmanager
def demo_state_dir(data_dir: Path) -> Iterator[tuple[Path, str | None]]:
    """``<data_dir>/sim``, or, when that cannot be written, a temporary directory that
    lives as long as the context, with the reason. A demo on a read-only or foreign-owned
    volume still runs (its simulated EEPROMs and flash are then kept for this run only),
    as storage and the accounts database do."""
    state_dir = data_dir / "sim"
    problem = state_dir_problem(state_dir)
    if problem is None:
        yield state_dir, None
        return
    with tempfile.TemporaryDirectory(prefix="servotune-demo-sim-") as scratch:
        yield Path(scratch), problem


@contextlib.contextmanager
def ep7047_wire_demo_slave(state_dir: Path) -> Iterator[list[LinkSpec]]:
    """``--ethercat-wire``: the EP7047-1032 as a real EtherCAT slave on a veth pair (its
    own network namespace, ``servotune sim ep7047 --ifname``), driven by the real
    pysoem master - every frame crosses a network interface. Needs root (namespaces,
    raw sockets) and pysoem; where either is missing the demo says why and keeps the
    simulated slave behind the master seam."""
    problem = netns_problem()
    if problem is None:
        try:
            import pysoem  # noqa: F401 - only checked here
        except ImportError:
            problem = "pysoem is not installed (pip install -e '.[ethercat]')"
    if problem is not None:
        logger.warning("--ethercat-wire: %s; the EP7047 stays behind the master seam", problem)
        with ep7047_demo_slave(state_dir) as specs:
            yield specs
        return
    state_dir.mkdir(parents=True, exist_ok=True)
    with veth_pair() as pair, slave_process(pair, state_dir, name="ep7047-wire"):
        logger.info(
            "EP7047-1032 on a real EtherCAT wire: slave in namespace %s on %s, master on %s",
            pair.namespace,
            pair.slave_if,
            pair.master_if,
        )
        yield [
            LinkSpec(
                device="ep7047",
                path=pair.master_if,
                link_id="demo-ep7047",
                baud=0,
                addresses=[1],
                lines=DEMO_COUNTS_PER_REV // 4,
                names={1: "EP7047 stepper (EtherCAT wire)"},
            )
        ]


def demo_simulators(
    data_dir: Path, state_dir: Path | None = None, *, ethercat_wire: bool = False
) -> list[Callable[[], contextlib.AbstractContextManager[list[LinkSpec]]]]:
    """Context managers that start the demo's simulators and yield their link specs;
    their state lives in ``state_dir`` (default ``<data_dir>/sim``). ``ethercat_wire``:
    the EP7047 on a veth pair instead of behind the master seam."""
    directory = state_dir if state_dir is not None else data_dir / "sim"
    ep7047 = ep7047_wire_demo_slave if ethercat_wire else ep7047_demo_slave
    return [
        lambda: slap2_demo_line(directory),
        lambda: z1100_demo_line(directory),
        lambda: ep7047(directory),
    ]
