"""The demo: simulated devices, each in a process of its own.

The serial simulators run on real ptys, so the driver opens them with exactly the
code it uses for a USB adapter; only the far end of the cable is simulated. The
EtherCAT slave runs behind the driver's master seam (``servotune.devices.ep7047.sim.process``).
Each simulator is a child process of the server (``servotune.sim.process``: spawned,
named ``sim-<device>``, stopped with the server, and ending by itself when the server
is killed), so the simulated devices never compete with the server's event loop for
one Python interpreter - see docs/simulator.md, "The demo's processes". What each
device runs is its registry entry's ``simulator.demo``.

Every child writes a record of its device's state to
``<data dir>/sim/<device>-record.json`` about four times a second
(``servotune.sim.process.record_path``): what reached the device, as the device sees
it (the soak test checks a STOP against it).
"""

from __future__ import annotations

import contextlib
import functools
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

from servotune.config import LinkSpec
from servotune.devices import default_registry
from servotune.registry import DemoArgs, Registry


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


def demo_simulators(
    data_dir: Path,
    state_dir: Path | None = None,
    *,
    ethercat_wire: bool = False,
    devices: Registry | None = None,
) -> list[Callable[[], contextlib.AbstractContextManager[list[LinkSpec]]]]:
    """Context managers that start the demo's simulators (one per device of ``devices``
    that has one; default ``default_registry()``) and yield their link specs; their
    state lives in ``state_dir`` (default ``<data_dir>/sim``). ``ethercat_wire``: an
    EtherCAT slave on a veth pair instead of behind the master seam."""
    args = DemoArgs(state_dir if state_dir is not None else data_dir / "sim", ethercat_wire)
    registry = devices if devices is not None else default_registry()
    return [
        functools.partial(entry.simulator.demo, args)
        for entry in registry.simulated()
        if entry.simulator is not None
    ]
