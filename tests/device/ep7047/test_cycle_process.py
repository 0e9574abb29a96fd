"""The EtherCAT cycle in a process of its own (``transports.ethercat_cycle``), with the
simulated master (``demo_master``) inside the child: no network, no root.

The point of the cycle process: a server thread that is held up does not hold the
cycle. The test holds the driver's thread for 2.5 s in the middle of a move (longer than
the stream of records that the first design filled and garbled); the drive's watchdog
(100 ms, counted in the child by the simulated slave) must not trip, the driver must
not believe it tripped, and the move must end In-Target.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import sys
import time
from collections.abc import AsyncIterator

import pytest

from servotune.config import LinkSpec
from servotune.devices import default_registry
from servotune.devices.ep7047.codec import StartType
from servotune.devices.ep7047.cycle import Cycle
from servotune.devices.ep7047.link import Ep7047Link, build_ep7047_link
from servotune.devices.ep7047.sim.slave import (
    DEMO_COUNTS_PER_REV,
    DEMO_SPEED_RANGE_STEPS_S,
    demo_master,
)
from servotune.link.base import Link
from servotune.transports.ethercat_cycle import CycleProcessMaster
from tests.support.sink import RecordingSink
from tests.support.waiting import wait_for


@contextlib.asynccontextmanager
async def _connected(link: Link) -> AsyncIterator[Ep7047Link]:
    """``link`` running, in OP through its cycle process; cancelled on the way out."""
    assert isinstance(link, Ep7047Link)
    task = asyncio.create_task(link.run())
    try:
        await wait_for(lambda: link.state == "connected", 60, "OP through the cycle process")
        yield link
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


async def test_a_held_server_thread_does_not_hold_the_cycle(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    sink = RecordingSink()
    master = CycleProcessMaster(demo_master, cycle_s=0.002, name="ec-cycle-test")
    link = build_ep7047_link(
        "cp",
        "simeth0",
        1,
        sink,
        master=master,
        speed_range_steps_s=DEMO_SPEED_RANGE_STEPS_S,
        counts_per_rev=DEMO_COUNTS_PER_REV,
    )
    async with _connected(link):
        axis = link.axes[0]
        await axis.command("enable", {})
        move = {
            "start_type": int(StartType.ABSOLUTE),
            "target": 3 * DEMO_COUNTS_PER_REV,
            "velocity": 2000,
            "acceleration_ms": 100,
            "deceleration_ms": 100,
        }
        await axis.command("execute_move", move)
        held = {"done": False}
        original = Cycle._emit

        def held_once(self: Cycle, *args: object) -> None:
            if not held["done"]:
                held["done"] = True
                time.sleep(2.5)  # the server's thread, held up mid-move
            original(self, *args)  # type: ignore[arg-type]

        monkeypatch.setattr(Cycle, "_emit", held_once)
        await wait_for(lambda: held["done"], 5, "the hold")
        samples = sink.samples[axis.id]
        await wait_for(
            lambda: not samples[-1].flags["busy"] and not samples[-1].flags["execute_out"],
            20,
            "the move to end",
        )
        assert samples[-1].flags["in_target"], sink.events[-3:]
        assert samples[-1].channels["position"] == 3 * DEMO_COUNTS_PER_REV
        assert link.counters["watchdog_trips"] == 0, sink.events
        assert not [m for _, _, m in sink.events if "process data" in m]
        assert link.state == "connected" and [s for s, _ in sink.states].count("connected") == 1
        assert master.pid is not None
    pid = master.pid
    assert pid is not None
    with pytest.raises(ProcessLookupError):  # the link's end ended the cycle process
        for _ in range(100):
            os.kill(pid, 0)
            await asyncio.sleep(0.05)


def _hold_the_interpreter(seconds: float) -> None:
    """Hold the interpreter lock for ``seconds``, as a full garbage collection of a big
    heap does on a loaded host: no other thread of this process runs meanwhile (the
    switch interval, 5 ms, is what would otherwise hand the lock on)."""
    interval = sys.getswitchinterval()
    sys.setswitchinterval(30.0)
    try:
        time.sleep(0.02)  # threads that waited under the old interval take and leave it
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            pass
    finally:
        sys.setswitchinterval(interval)


async def test_the_sim_link_spec_keeps_the_drive_enabled_through_a_held_interpreter() -> None:
    # ``ep7047:sim`` (the tests' and the page's simulated drive) must feed the drive's
    # 100 ms watchdog from the cycle process, as a real NIC's link does: a held
    # interpreter in the server (a full collection on a loaded host, docs/architecture.md
    # "Heavy work") delays the server, it must not drop Enable.
    sink = RecordingSink()
    spec = LinkSpec("ep7047", "sim", "ep", 0, [1])
    async with _connected(default_registry().build_link(spec, sink)) as link:
        axis = link.axes[0]
        await axis.command("enable", {})
        samples = sink.samples[axis.id]
        await wait_for(lambda: samples and samples[-1].flags["stm_ready"], 20, "enabled")
        _hold_the_interpreter(0.5)
        held_at = len(samples)
        await wait_for(lambda: len(samples) > held_at + 5, 20, "samples after the hold")
        assert link.counters["watchdog_trips"] == 0, sink.events
        assert samples[-1].flags["stm_ready"], sink.events[-3:]
        assert link.state == "connected"
