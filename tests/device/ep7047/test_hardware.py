"""The EP7047-1032 driver on REAL hardware: opt-in, skipped unless configured.

    SERVOTUNE_EP7047_IFNAME=eth1 pytest tests/device/ep7047/test_hardware.py

needs ``pip install 'servotune[ethercat]'``, raw-socket rights (root or CAP_NET_RAW, see
docs/ep7047-driver.md) and an EP7047-1032 on that NIC. Optional:
``SERVOTUNE_EP7047_SLAVE`` (bus position, default 1), ``SERVOTUNE_EP7047_SPEED_RANGE``
(full steps/s, default 2000), ``SERVOTUNE_EP7047_MOVE=1`` to allow the one test that
turns the motor (an eighth of a turn forth and back, slowly): the axis must be free.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import AsyncIterator

import pytest

from servotune.devices.ep7047.codec import StartType
from servotune.devices.ep7047.link import Ep7047Link, build_ep7047_link
from tests.support.sink import RecordingSink
from tests.support.waiting import wait_for

IFNAME = os.environ.get("SERVOTUNE_EP7047_IFNAME", "")
pytestmark = pytest.mark.skipif(
    not IFNAME,
    reason="real EP7047-1032 hardware: set SERVOTUNE_EP7047_IFNAME to the NIC it is on",
)
SLAVE = int(os.environ.get("SERVOTUNE_EP7047_SLAVE", "1"))
SPEED_RANGE = int(os.environ.get("SERVOTUNE_EP7047_SPEED_RANGE", "2000"))
COUNTS_PER_REV = int(os.environ.get("SERVOTUNE_EP7047_COUNTS_PER_REV", "4096"))


@contextlib.asynccontextmanager
async def hardware_link() -> AsyncIterator[tuple[Ep7047Link, RecordingSink]]:
    sink = RecordingSink()
    link = build_ep7047_link(
        "hw",
        IFNAME,
        SLAVE,
        sink,
        speed_range_steps_s=SPEED_RANGE,
        counts_per_rev=COUNTS_PER_REV,
    )
    task = asyncio.create_task(link.run())
    try:
        await wait_for(
            lambda: link.state == "connected",
            15,
            f"OP on {IFNAME} (last state: {sink.states[-1] if sink.states else 'none'})",
        )
        yield link, sink
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


async def test_hardware_reaches_op_reads_settings_and_streams_every_cycle() -> None:
    async with hardware_link() as (link, sink):
        axis = link.axes[0]
        assert "EP7047-1032" in sink.states[-1][1]
        params = await axis.read_params()
        assert set(params) == {p.name for p in axis.descriptor.parameters}
        count = len(sink.samples[axis.id])
        await asyncio.sleep(1.0)
        assert len(sink.samples[axis.id]) - count > 0.8 / link.cycle_s
        assert link.errors == 0


@pytest.mark.skipif(
    os.environ.get("SERVOTUNE_EP7047_MOVE") != "1",
    reason="turns the motor: set SERVOTUNE_EP7047_MOVE=1 when the axis is free",
)
async def test_hardware_small_relative_move_forth_and_back() -> None:
    async with hardware_link() as (link, sink):
        axis = link.axes[0]
        samples = sink.samples[axis.id]
        start = samples[-1].channels["position"] or 0.0
        await axis.command("enable", {})
        try:
            for distance in (COUNTS_PER_REV // 8, -(COUNTS_PER_REV // 8)):
                await axis.command(
                    "execute_move",
                    {
                        "start_type": int(StartType.RELATIVE),
                        "target": distance,
                        "velocity": 500,
                        "acceleration_ms": 1000,
                        "deceleration_ms": 1000,
                    },
                )
                await wait_for(
                    lambda: not samples[-1].flags["busy"] and not samples[-1].flags["execute_out"],
                    10,
                    "the move to end",
                )
        finally:
            await axis.stop()
        end = samples[-1].channels["position"] or 0.0
        assert abs(end - start) < COUNTS_PER_REV / 50
