"""The EP7047-1032 driver over a REAL EtherCAT master (SOEM, through pysoem) against the
simulated slave on a veth pair (``servotune sim ep7047 --ifname``, in a network
namespace of its own). Every frame here crosses a kernel network interface: bring-up,
SII, mailbox CoE, PDO mapping, FMMUs, the working counter and the watchdog are real.

Needs root (namespaces, raw sockets); skipped with the reason elsewhere, never on CI.
Each test makes its own namespace and slave (unique names) and removes them.
"""

from __future__ import annotations

import asyncio
import os
import re
import signal
import time
from pathlib import Path

import pytest

from servotune.devices.ep7047.codec import DriveState, StartType
from servotune.devices.ep7047.descriptor import INVERSION_PARAMETER, PARAMETER_SDO
from servotune.devices.ep7047.link import PysoemMaster
from servotune.hub.hub import Hub
from servotune.link.base import DeviceRefusedError, InvalidArgumentError
from servotune.transports.ethercat_cycle import CycleProcessMaster
from tests.support.ep7047_cases import load_cases
from tests.support.ep7047_wire import Wire, WireRun, start_endless, wire_hub, wire_link, wire_setup
from tests.support.waiting import wait_for

pytestmark = pytest.mark.slow

TURN_DEGREES = 3600  # the manual's tables in tenths of a degree: modulo factor 360°
# The modulo cases check where a move ends, not how it gets there: full speed and short
# ramps keep their 74 moves short (the ramps themselves are checked by the other moves).
FAST = {"velocity": 10000, "acceleration_ms": 50, "deceleration_ms": 50}


@pytest.fixture
def wire(tmp_path: Path) -> Wire:  # type: ignore[misc]
    with wire_setup(tmp_path) as setup:
        yield setup


# --- bring-up ---------------------------------------------------------------------------


async def test_wire_bring_up_reaches_op_and_streams_every_cycle(wire: Wire) -> None:
    started = time.monotonic()
    async with wire_link(wire) as run:
        bring_up_s = time.monotonic() - started
        state, message = run.sink.states[-1]
        assert state == "connected"
        assert "EP7047-1032 rev 0x00100005 in OP" in message
        record = run.record()
        assert record["al_state"] == 0x08 and not record["al_error"]
        count = len(run.samples)
        await asyncio.sleep(1.0)
        frames = record["frames"]
        assert len(run.samples) > count  # samples flow ...
        assert run.record()["frames"] > frames  # ... and frames cross the wire
        # Every frame arrived at the slave and carried its working counter.
        assert run.link.counters["lost_frames"] == 0, run.link.counters
        print(f"bring-up to OP {bring_up_s * 1000:.0f} ms")


async def test_wire_identity_mismatch_is_refused_naming_what_was_found(tmp_path: Path) -> None:
    with wire_setup(tmp_path, "--product", "0x1B773052") as wire:
        async with wire_link(wire, connect=False) as run:
            await wait_for(lambda: run.link.state == "error", 10, "the link to refuse the device")
            message = run.sink.states[-1][1]
            assert "is not an EP7047-1032" in message
            assert "product 0x1B773052" in message and "vendor 0x00000002" in message
            assert "expected vendor 0x00000002 product 0x1B874052" in message
            await asyncio.sleep(0.3)
            assert run.record()["al_state"] < 0x04  # never mapped, never in OP


async def test_wire_refused_state_change_names_the_al_status_code(wire: Wire) -> None:
    wire.slave.control("refuse", state=0x08, code=0x001A)
    async with wire_link(wire, connect=False) as run:
        await wait_for(
            lambda: any("did not reach OP" in m for _, m in run.sink.states), 15, "OP refused"
        )
        message = next(m for _, m in run.sink.states if "did not reach OP" in m)
        assert "SAFE-OP + ERROR" in message
        assert "AL status 0x001A (synchronization error)" in message
        wire.slave.control("refuse", state=0, code=0)
        await run.connected(15)  # the next bring-up acknowledges and reaches OP


# --- CoE --------------------------------------------------------------------------------


async def test_wire_every_parameter_is_written_and_read_back_over_sdo(wire: Wire) -> None:
    async with wire_link(wire) as run:
        read = await run.axis.read_params()
        assert set(read) == {*PARAMETER_SDO, INVERSION_PARAMETER}
        values = {
            "velocity_min_bp": 77,
            "velocity_max_bp": 9000,
            "acceleration_pos_ms": 301,
            "acceleration_neg_ms": 302,
            "deceleration_pos_ms": 303,
            "deceleration_neg_ms": 304,
            "emergency_deceleration_ms": 55,
            "calibration_position_counts": -1234,
            "calibration_velocity_towards_cam_bp": 900,
            "calibration_velocity_off_cam_bp": 250,
            "target_window_counts": 12,
            "in_target_timeout_ms": 400,
            "modulo_factor_counts": 3600,
            "modulo_tolerance_window_counts": 10,
            "default_start_type": int(StartType.RELATIVE),
            INVERSION_PARAMETER: 1,
        }
        assert set(values) == set(read)
        readback = await run.axis.write_params(values)
        assert readback == values
        # The slave's own view (its object dictionary, its engine), not the driver's.
        settings = run.record()["settings"]
        assert settings["velocity_min_bp"] == 77
        assert settings["calibration_position_counts"] == -1234
        assert settings["modulo_factor_counts"] == 3600
        assert settings["start_type"] == int(StartType.RELATIVE)
        assert settings["invert_calibration_cam_search"] is True
        assert settings["invert_sync_impulse_search"] is False
        assert await run.axis.read_params() == values


async def test_wire_a_value_the_drive_refuses_is_a_field_error_with_the_abort(
    wire: Wire,
) -> None:
    async with wire_link(wire) as run:
        # The slave refuses a tolerance window of half the modulo factor (4096) or more.
        with pytest.raises(InvalidArgumentError) as refused:
            await run.axis.write_params({"modulo_tolerance_window_counts": 3000})
        assert refused.value.field == "modulo_tolerance_window_counts"
        assert "0x06090031" in str(refused.value)
        assert run.record()["settings"]["modulo_tolerance_window_counts"] == 20  # unchanged
        # Through the console: the data type admits 20000, the drive does not.
        with pytest.raises(InvalidArgumentError) as console:
            await run.axis.console("0x8020:02 = 20000")
        assert "0x06090031" in str(console.value)
        assert run.record()["settings"]["velocity_max_bp"] == 10000


# --- moves ------------------------------------------------------------------------------


async def _modulo_setup(run: WireRun, window: int) -> None:
    await run.axis.write_params(
        {"modulo_factor_counts": TURN_DEGREES, "modulo_tolerance_window_counts": window}
    )


async def test_wire_every_modulo_case_of_the_manual(wire: Wire) -> None:
    cases = load_cases()  # the manual's tables in tenths of a degree
    assert len(cases) == 37
    async with wire_link(wire) as run:
        await run.axis.command("enable", {})
        window = None
        for case in cases:
            if case.window != window:
                window = case.window
                await _modulo_setup(run, window)
            await run.move_and_wait(StartType.ABSOLUTE, case.start, **FAST)
            assert run.position() == case.start
            await run.move_and_wait(case.start_type, case.target, **FAST)
            where = f"{case.start_type.name} from {case.start} to {case.target}"
            assert run.position() == case.abs_end, where
            assert run.position() - case.start == case.relative, where
            assert run.record()["actual_counts"] == case.abs_end, where  # the slave's view


async def test_wire_plain_and_change_moves(wire: Wire) -> None:
    async with wire_link(wire) as run:
        await run.axis.command("enable", {})
        await run.move_and_wait(StartType.ABSOLUTE, 5000)
        assert run.position() == 5000
        # The state machine, sampled over CoE (0x9020:03) while the move ran: the drive
        # was seen moving. Which of the move's states a sample catches is the sampling's
        # (a short deceleration can fall between two reads: the descriptor says the value
        # is sampled), so no particular one is required.
        moving = {float(DriveState.ACCEL), float(DriveState.CONST), float(DriveState.DECEL)}
        states = {s.channels["drive_state"] for s in run.samples} - {None}
        assert states & moving, states
        await run.move_and_wait(StartType.RELATIVE, -1500)
        assert run.position() == 3500
        await run.move_and_wait(StartType.ADDITIVE, 500)
        assert run.position() == 4000
        # The manual's ABSOLUTE_CHANGE example, scaled: after the ramp-up a new target
        # with a lower velocity and steeper ramps; it decelerates onto it, In-Target.
        await run.move(StartType.ABSOLUTE, 40000, velocity=2000, acceleration_ms=100)
        await wait_for(lambda: run.position() > 8000, 5, "the move to cruise")
        message = await run.move(
            StartType.ABSOLUTE_CHANGE, 20000, velocity=1500, acceleration_ms=50,
            deceleration_ms=50,
        )  # fmt: skip
        assert "taken" in message
        await run.move_ended(15)
        assert run.position() == 20000 and run.flag("in_target")
        # ADDITIVE_CHANGE: the active target (40000) + the operand.
        await run.move(StartType.ABSOLUTE, 40000, velocity=2000, acceleration_ms=100)
        await wait_for(lambda: run.position() > 25000, 5, "the move to cruise")
        await run.move(StartType.ADDITIVE_CHANGE, -10000, velocity=2000)
        await run.move_ended(15)
        assert run.position() == 30000 and run.flag("in_target")
        await run.move(StartType.ENDLESS_PLUS, 0, velocity=1000)
        with pytest.raises(DeviceRefusedError, match="active target"):
            await run.move(StartType.ADDITIVE_CHANGE, 100, velocity=1000)
        await run.axis.command("halt", {})
        await run.move_ended()
        assert run.position() > 30000
        assert round(run.record()["actual_counts"]) == run.position()


async def test_wire_calibration_on_the_cam_then_clear_and_set(wire: Wire) -> None:
    async with wire_link(wire) as run:
        await run.axis.command("enable", {})
        await run.axis.command("cali_plc_cam", {})  # the demo's cam: 6000..6800 counts
        await wait_for(lambda: run.flag("calibrated") and not run.flag("busy"), 20, "Calibrated")
        # After the In-Target timeout the calibration position (0) is the actual position.
        assert run.position() == 0 and round(run.record()["actual_counts"]) == 0
        await run.axis.command("clear_calibration", {})
        await wait_for(lambda: not run.flag("calibrated"), 3, "Calibrated cleared")
        await run.axis.command("set_calibration", {})
        await wait_for(lambda: run.flag("calibrated"), 3, "Calibrated set")


async def test_wire_change_at_standstill_is_refused_before_the_wire(wire: Wire) -> None:
    async with wire_link(wire) as run:
        await run.axis.command("enable", {})
        with pytest.raises(DeviceRefusedError, match="Execute is low"):
            await run.move(StartType.ABSOLUTE_CHANGE, 100)


async def test_wire_stop_ramps_down_and_drops_enable(wire: Wire) -> None:
    async with wire_link(wire) as run:
        await run.axis.command("enable", {})
        await run.move(StartType.ENDLESS_PLUS, 0, velocity=8000)
        await wait_for(lambda: run.record()["velocity_counts_s"] > 20000, 5, "full speed")
        await run.axis.stop()
        await wait_for(lambda: not run.flag("enable_out"), 3, "Enable off after STOP")
        record = run.record()
        assert record["velocity_counts_s"] == 0 and not record["enabled"]
        assert any("STOP: stopped at" in text for _, _, text in run.sink.events)


# --- faults on the wire -----------------------------------------------------------------


async def test_wire_dropped_and_unprocessed_frames_are_counted_not_alarmed(wire: Wire) -> None:
    async with wire_link(wire) as run:
        for _ in range(2):  # two frames lost in a row, twice: ~20 ms without an answer
            wire.slave.control("drop", count=2)
            await asyncio.sleep(0.2)
        wire.slave.control("unprocessed", count=3)  # answered, working counter 0
        await asyncio.sleep(0.2)
        await wait_for(lambda: run.link.counters["lost_frames"] >= 7, 2, "7 lost cycles")
        record = run.record()
        assert (record["dropped"], record["unprocessed"]) == (4, 3)
        assert run.link.state == "connected"
        assert [s for s, _ in run.sink.states].count("connected") == 1  # never left OP
        assert not [e for e in run.sink.events if e[0] == "error"]


async def test_wire_cable_pull_is_an_error_within_the_watchdog_then_op_again(
    wire: Wire, tmp_path: Path
) -> None:
    async with wire_hub(wire, tmp_path) as (hub, link):
        axis_id = link.axes[0].id
        await start_endless(hub, axis_id, 3000)
        pulled = time.monotonic()
        wire.pair.set_master_link(False)
        await wait_for(lambda: link.state == "error", 1, "the link to notice the pull")
        noticed_s = time.monotonic() - pulled
        message = hub.link_status(link.id).message
        assert "no EtherCAT frame comes back on" in message, message
        assert "cable" in message
        # Within the watchdog time, as the driver measured it on the wire (the time
        # seen here adds the `ip` command and this loop's polling: printed only).
        silent_ms = int(re.search(r"for (\d+) ms", message).group(1))  # type: ignore[union-attr]
        print(f"cable pull: link error after {silent_ms} ms of silence ({noticed_s * 1000:.0f} ms "
              "seen by the test)")  # fmt: skip
        assert silent_ms < 100
        # The slave on its own: the watchdog stopped the motor, outputs safe.
        await wait_for(lambda: wire.slave.record()["watchdog_trips"] == 1, 2, "the trip")
        record = wire.slave.record()
        assert record["al_error"] and record["al_code"] == 0x001B
        assert record["velocity_counts_s"] == 0 and not record["enabled"]
        assert await hub.stop_all() != []  # could not go out: the link is down
        wire.pair.set_master_link(True)
        await wait_for(lambda: link.state == "connected", 15, "OP again")
        entry = hub.entry(axis_id)
        await wait_for(lambda: not entry.stop_on_reconnect, 5, "the STOP sent after the return")
        assert not wire.slave.record()["enabled"]  # nothing moved by itself


async def test_wire_a_stalled_cycle_trips_the_watchdog_and_recovers_without_motion(
    wire: Wire, tmp_path: Path
) -> None:
    """SIGSTOP of the cycle process for 200 ms: the slave's watchdog (100 ms) trips, the
    drive drops Enable; the driver says so (not a reset: the settings are kept) and
    brings the slave back to OP with Enable off - nothing moves by itself."""
    master = CycleProcessMaster(PysoemMaster, cycle_s=0.002)
    async with wire_hub(wire, tmp_path, master=master) as (hub, link):
        axis_id = link.axes[0].id
        entry = hub.entry(axis_id)
        await start_endless(hub, axis_id, 2000)
        await wait_for(lambda: wire.slave.record()["velocity_counts_s"] > 0, 3, "motion")
        assert master.pid is not None
        os.kill(master.pid, signal.SIGSTOP)
        await asyncio.sleep(0.2)
        os.kill(master.pid, signal.SIGCONT)
        await wait_for(lambda: wire.slave.record()["watchdog_trips"] == 1, 3, "the trip")
        await wait_for(
            lambda: any("back in OP after its watchdog trip" in m for _, _, m in _events(hub)),
            15,
            "OP again after the trip",
        )
        texts = [m for _, _, m in _events(hub)]
        assert any("dropped Enable because process data stopped" in m for m in texts), texts
        assert not any("may be lost" in m for m in texts)
        assert entry.health != "reset"
        # Nothing moves by itself: Enable off in the outputs and at the drive, at rest.
        await wait_for(lambda: link.state == "connected", 5, "connected")
        before = wire.slave.record()
        await asyncio.sleep(0.5)
        after = wire.slave.record()
        assert not after["enabled"] and after["velocity_counts_s"] == 0
        assert after["actual_counts"] == before["actual_counts"]
        latest = entry.latest
        assert latest is not None and not latest.flags["enable_out"]


def _events(hub: Hub) -> list[tuple[str, str | None, str]]:
    return [(e.level, e.axis, e.message) for e in hub._events]
