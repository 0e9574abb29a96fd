"""The live setpoint is never drawn from reads taken at different times as if they were
one signal: on the demo's loaded SLAP2 at factory gains, ringing around a
fixed target, ``position + pe`` (two reads a transaction apart) swung by about ±1000
counts. The driver gives the reconstructed profile where it knows it, ``rp + pe``
only while pe is steady, and nothing otherwise (link/setpoint.py)."""

from __future__ import annotations

import asyncio
import contextlib
import functools
from collections.abc import AsyncIterator
from pathlib import Path

from servotune.devices.slap2.codec import ACCELERATION_MAX, VELOCITY_MAX
from servotune.devices.slap2.link import Slap2Axis, Slap2Link, Slap2LinkConfig
from servotune.devices.slap2.sim.demo import SLAP2_LOADED
from servotune.devices.slap2.sim.line import Slap2Line
from servotune.link.setpoint import STEADY_ERROR_COUNTS, SkewedSetpoint
from servotune.sim.process import SerialSimSpec, serial_sim_process
from servotune.transports.serial import SerialConnector
from tests.support.sink import RecordingSink
from tests.support.waiting import wait_for


def test_the_sum_of_two_reads_is_a_setpoint_only_while_the_error_is_steady() -> None:
    skewed = SkewedSetpoint()
    assert skewed.setpoint(1000, 3, profile_running=True) is None  # no previous read yet
    assert skewed.setpoint(1010, 4, profile_running=True) == 1014  # steady error, moving
    assert skewed.setpoint(2000, 4 + STEADY_ERROR_COUNTS + 1, profile_running=True) is None
    assert skewed.setpoint(2000, None) is None
    assert skewed.setpoint(None, 12) is None
    # The profile has ended: the position must rest too (a ringing shaft whose error
    # happened to read alike twice is no setpoint).
    resting = SkewedSetpoint()
    assert resting.setpoint(5000, -40) is None
    assert resting.setpoint(5600, -41) is None  # error alike, shaft 600 counts away
    assert resting.setpoint(5601, -41) == 5560


@contextlib.asynccontextmanager
async def loaded_line(tmp_path: Path) -> AsyncIterator[tuple[Slap2Axis, RecordingSink]]:
    """The demo's loaded SLAP2 module on a pty, simulated in a process of its own (as the
    demo runs it): this test's own work cannot starve it into late echoes."""
    build = functools.partial(
        Slap2Line.with_addresses, [0], state_dir=tmp_path, params=SLAP2_LOADED
    )
    with serial_sim_process(SerialSimSpec("setpoint", build, 19200)) as sim:
        path = sim.ready["path"]
        sink = RecordingSink()
        config = Slap2LinkConfig(link_id="line", path=path, addresses=[0])
        link = Slap2Link(config, SerialConnector(path, 19200), sink)
        task = asyncio.create_task(link.run())
        try:
            await wait_for(lambda: link.state == "connected", 10, "the link")
            await wait_for(lambda: len(sink.samples["line-0"]) > 3, 10, "samples")
            axis = link.axes[0]
            assert isinstance(axis, Slap2Axis)
            yield axis, sink
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task


async def _rest(sink: RecordingSink) -> None:
    """Until the shaft stands still (after a stop the loaded shaft coasts)."""
    for _ in range(100):
        await asyncio.sleep(0.1)
        recent = [s.channels["position"] for s in sink.samples["line-0"][-5:]]
        if len(set(recent)) == 1:
            return
    raise AssertionError("the shaft never came to rest")


async def _ring(axis: Slap2Axis, sink: RecordingSink, console: bool) -> tuple[list[float], int]:
    """Step the loaded axis by ±2000 with sv/sa at their maximum (the factory gains ring
    around the target for seconds); (the setpoints shown meanwhile, samples seen)."""
    await _rest(sink)
    await axis.write_params({"velocity": VELOCITY_MAX, "acceleration": ACCELERATION_MAX})
    await axis.command("position_mode", {})
    await asyncio.sleep(0.5)
    start = sink.samples["line-0"][-1].channels["position"]
    assert start is not None
    # Away from a limit switch the coasting shaft may have reached after a stop.
    distance = -2000 if sink.samples["line-0"][-1].flags.get("limit2") else 2000
    if console:
        await axis.console(f"mr {distance}")  # not replayed by the driver: no reconstruction
    else:
        await axis.command("move_relative", {"distance": distance})
    first = len(sink.samples["line-0"])
    await asyncio.sleep(2.0)
    recent = sink.samples["line-0"][first:]
    positions = [s.channels["position"] for s in recent if s.channels["position"] is not None]
    assert max(positions) - min(positions) > 1000, "the axis did not ring"
    shown = [s.channels["setpoint"] for s in recent if s.channels["setpoint"] is not None]
    return [v - (start + distance) for v in shown], len(recent)


async def test_a_ringing_axis_shows_no_false_setpoint(tmp_path: Path) -> None:
    async with loaded_line(tmp_path) as (axis, sink):
        # A move the driver commanded: the reconstructed profile, the target once the
        # profile has ended, whatever the shaft does.
        offsets, n = await _ring(axis, sink, console=False)
        assert len(offsets) > n // 2, "the reconstruction should give most samples"
        assert max(abs(o) for o in offsets) <= 2000
        assert sorted(abs(o) for o in offsets)[len(offsets) // 2] <= 1, offsets[-20:]
        # The axis' own STOP would hold it in pm, ringing with these gains (the hub's
        # stop service brakes that; this test has no hub): unpowered, it coasts to rest.
        await axis.power_off()
        await asyncio.sleep(0.5)
        # A console move: no reconstruction; rp + pe only while pe is steady.
        offsets, n = await _ring(axis, sink, console=True)
        wrong = [o for o in offsets if abs(o) > 2 * STEADY_ERROR_COUNTS]
        assert not wrong, f"{len(wrong)} of {len(offsets)} setpoints off the target: {wrong[:10]}"
        await axis.power_off()
