"""The EP7047-1032 EtherCAT driver against the FAKE master (``SimulatedEthercatMaster``).

Every ``test_fake_master_*`` test runs the real driver (cycle thread, bring-up, SDO,
handshakes) against the simulated master and slave in real time, 2 ms cycle; nothing
here touches a network interface. Real hardware: ``tests/device/ep7047/test_hardware.py``.

The logic tests give the watchdog 0.5 s on both sides (driver and simulated slave) so
that a busy CI host cannot abort their moves; the stall test uses the real 100 ms.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import sys
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, replace
from pathlib import Path

import pytest

from servotune.devices.ep7047.codec import PosSettings, StartType
from servotune.devices.ep7047.descriptor import (
    INVERSION_PARAMETER,
    PARAMETER_SDO,
    ep7047_descriptor,
)
from servotune.devices.ep7047.link import (
    OP_STATE,
    PREOP_STATE,
    Ep7047Axis,
    Ep7047Link,
    build_ep7047_link,
    raw_socket_problem,
)
from servotune.devices.ep7047.requests import STATE_ACTIVE_S
from servotune.devices.ep7047.sim.slave import (
    DEMO_COUNTS_PER_REV,
    DEMO_SPEED_RANGE_STEPS_S,
    SimulatedEp7047Slave,
    SimulatedEthercatMaster,
    demo_master,
)
from servotune.hub.hub import Hub
from servotune.link.base import DeviceRefusedError, InvalidArgumentError, LinkDownError, Sample
from servotune.storage import Storage
from tests.support.sink import RecordingSink
from tests.support.waiting import wait_for

TURN = DEMO_COUNTS_PER_REV  # the demo slave's modulo factor: one turn
TOLERANT_WATCHDOG_S = 0.5


@dataclass
class Running:
    link: Ep7047Link
    axis: Ep7047Axis
    sink: RecordingSink
    master: SimulatedEthercatMaster

    @property
    def slave(self) -> SimulatedEp7047Slave:
        return self.master.slave(1)

    @property
    def samples(self) -> list[Sample]:
        return self.sink.samples[self.axis.id]

    def latest_flag(self, name: str) -> bool:
        return bool(self.sink.samples[self.axis.id][-1].flags[name])

    def latest_channel(self, name: str) -> float | None:
        return self.sink.samples[self.axis.id][-1].channels[name]

    async def connected(self) -> None:
        await wait_for(lambda: self.link.state == "connected", 5, "the link to reach OP")

    async def move_ended(self, timeout_s: float = 5) -> None:
        await wait_for(
            lambda: not self.latest_flag("busy") and not self.latest_flag("execute_out"),
            timeout_s,
            "the move to end (Busy low, Execute dropped)",
        )

    async def move(self, start_type: StartType, target: int, velocity: int = 5000) -> str:
        outcome = await self.axis.command(
            "execute_move",
            {
                "start_type": int(start_type),
                "target": target,
                "velocity": velocity,
                "acceleration_ms": 200,
                "deceleration_ms": 200,
            },
        )
        return outcome.message


@contextlib.asynccontextmanager
async def running(
    master: SimulatedEthercatMaster | None = None,
    *,
    connect: bool = True,
    watchdog_s: float = TOLERANT_WATCHDOG_S,
    **options: object,
) -> AsyncIterator[Running]:
    master = master if master is not None else demo_master()
    master.slave(1).watchdog_s = watchdog_s
    sink = RecordingSink()
    link = build_ep7047_link(
        "ec",
        "simeth0",
        1,
        sink,
        master=master,
        speed_range_steps_s=DEMO_SPEED_RANGE_STEPS_S,
        counts_per_rev=DEMO_COUNTS_PER_REV,
        watchdog_s=watchdog_s,
        **options,  # type: ignore[arg-type]
    )
    axis = link.axes[0]
    assert isinstance(axis, Ep7047Axis)
    task = asyncio.create_task(link.run())
    try:
        run = Running(link, axis, sink, master)
        if connect:
            await run.connected()
        yield run
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


def move_args(start_type: StartType, target: int, velocity: int = 5000) -> dict[str, int]:
    return {
        "start_type": int(start_type),
        "target": target,
        "velocity": velocity,
        "acceleration_ms": 200,
        "deceleration_ms": 200,
    }


# --- bring-up ---------------------------------------------------------------------------


async def test_fake_master_bring_up_assigns_pdos_in_preop_reads_settings_and_streams() -> None:
    async with running() as run:
        slave = run.slave
        assert slave.al_state == OP_STATE
        assert "rev 0x00100005" in run.link.message
        assert run.sink.health[run.axis.id][0] == "ok"
        # PDO assignment over CoE, in PRE-OP, by the CiA procedure
        assignment = [
            (sub, value)
            for state, op, index, sub, value in slave.sdo_log
            if op == "write" and index == 0x1C12 and state == PREOP_STATE
        ]
        assert assignment == [(0, 0), (1, 0x1601), (2, 0x1602), (3, 0x1606), (0, 3)]
        assert any(
            op == "write" and index == 0x1C13 and value == 0x1A07 and state == PREOP_STATE
            for state, op, index, _, value in slave.sdo_log
        )
        assert slave.positioning_interface
        # the drive's own settings were read, not overwritten with servotune defaults
        params = run.sink.params[run.axis.id]
        assert params["modulo_factor_counts"] == TURN
        assert params["calibration_search_inversion"] == 0b10  # sync search inverted
        assert params["in_target_timeout_ms"] == 500
        # every cycle delivers a sample carrying every descriptor channel and flag
        # (How many cycles run in 0.5 s depends on the host; a sample per good
        # exchange does not.)
        count = len(run.samples)
        exchanged_before = len(run.master.history)
        await asyncio.sleep(0.5)
        exchanged = len(run.master.history) - exchanged_before
        assert 0 < exchanged <= 0.5 / 0.002 + 5
        await wait_for(
            lambda: len(run.samples) >= count + exchanged, 2, "a sample for every exchange"
        )
        sample = run.sink.samples[run.axis.id][-1]
        descriptor = run.axis.descriptor
        assert set(sample.channels) == {c.name for c in descriptor.channels}
        assert set(sample.flags) == {f.name for f in descriptor.flags}
        assert sample.flags["enable_out"] is False  # nothing is enabled by itself
        assert any(s.channels["drive_state"] == 0x0001 for s in run.sink.samples[run.axis.id])


async def test_fake_master_identity_mismatch_is_a_clear_error_and_never_reaches_op() -> None:
    master = demo_master()
    master.set_identity(product=0x1B773052, name="EL7037")
    async with running(master, connect=False) as run:
        await wait_for(lambda: run.link.state == "error", 3, "the error state")
        message = run.link.message
        assert "not an EP7047-1032" in message
        assert "0x1B773052" in message and "0x1B874052" in message and "EL7037" in message
        assert run.slave.al_state == PREOP_STATE
        assert not any(index == 0x1C12 for _, _, index, _, _ in run.slave.sdo_log)
        with pytest.raises(LinkDownError):
            await run.axis.command("enable", {})


async def test_fake_master_unavailable_ethercat_is_reported_with_the_fix(tmp_path: Path) -> None:
    (tmp_path / "eth1").mkdir()
    master = demo_master()
    master.open_error = raw_socket_problem("eth1", euid=1000, cap_eff=0, net_dir=tmp_path)
    if master.open_error is None:
        pytest.skip("the raw socket check is Linux only")
    async with running(master, connect=False) as run:
        await wait_for(lambda: run.link.state == "error", 3, "the error state")
        assert run.link.message == master.open_error


def test_raw_socket_problem_names_the_exact_fix(tmp_path: Path) -> None:
    (tmp_path / "eth1").mkdir()
    if not sys.platform.startswith("linux"):
        pytest.skip("the check is Linux only")
    message = raw_socket_problem("eth1", euid=1000, cap_eff=0, net_dir=tmp_path)
    assert message is not None
    assert "CAP_NET_RAW" in message and "root" in message
    assert "sudo setcap cap_net_raw,cap_net_admin+ep $(readlink -f .venv/bin/python)" in message
    assert raw_socket_problem("eth1", euid=1000, cap_eff=1 << 13, net_dir=tmp_path) is None
    assert raw_socket_problem("eth1", euid=0, cap_eff=0, net_dir=tmp_path) is None
    missing = raw_socket_problem("eth9", euid=0, cap_eff=0, net_dir=tmp_path)
    assert missing is not None and "'eth9'" in missing and "eth1" in missing


async def test_pysoem_missing_gives_a_clear_error_state(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "pysoem", None)  # import pysoem -> ImportError
    sink = RecordingSink()
    link = build_ep7047_link("ec", "eth1", 1, sink)  # master None: the real pysoem master
    task = asyncio.create_task(link.run())
    try:
        await wait_for(lambda: link.state == "error", 3, "the error state")
        state, message = sink.states[-1]
        assert state == "error"
        assert "pysoem is not installed" in message
        assert "pip install 'servotune[ethercat]'" in message
        with pytest.raises(LinkDownError):
            await link.axes[0].stop()
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


# --- settings -----------------------------------------------------------------------------


async def test_fake_master_settings_are_written_by_sdo_and_read_back() -> None:
    async with running() as run:
        values = {
            "velocity_max_bp": 6000,
            "modulo_factor_counts": 3600,
            "calibration_search_inversion": 0b01,
            "default_start_type": int(StartType.MODULO_PLUS),
        }
        readback = await run.axis.write_params(values)
        assert readback == values
        settings = run.slave.engine.settings
        assert settings.velocity_max_bp == 6000
        assert settings.modulo_factor_counts == 3600
        assert settings.invert_calibration_cam_search is True
        assert settings.invert_sync_impulse_search is False
        assert settings.start_type == StartType.MODULO_PLUS
        assert run.sink.params[run.axis.id]["modulo_factor_counts"] == 3600
        # each value was written, then read back
        # (the drive-state samples, 0x9020:03, may come in between: they are another job)
        log = [
            (op, index, sub)
            for _, op, index, sub, _ in run.slave.sdo_log
            if (index, sub) != (0x9020, 0x03)
        ]
        write_at = log.index(("write", 0x8020, 0x02))
        assert log[write_at + 1] == ("read", 0x8020, 0x02)
        # a _CHANGE type cannot be the default start type: refused before any SDO
        before = len(run.slave.sdo_log)
        with pytest.raises(InvalidArgumentError) as refused:
            await run.axis.write_params({"default_start_type": int(StartType.ABSOLUTE_CHANGE)})
        assert refused.value.field == "default_start_type"
        assert not any(op == "write" for _, op, *_ in list(run.slave.sdo_log)[before:])
        assert (await run.axis.read_params())["velocity_max_bp"] == 6000
        # the console reads and writes CoE objects of the positioning interface
        sent, lines = await run.axis.console("0x9020:03")
        assert sent == "0x9020:03"
        assert lines == ["0x9020:03 State (drive controller) = IDLE (0x0001)"]
        _, lines = await run.axis.console("0x8020:0E = 4096")
        assert lines == ["0x8020:0E Modulo factor = 4096 counts"]
        assert run.slave.engine.settings.modulo_factor_counts == 4096
        assert run.sink.params[run.axis.id]["modulo_factor_counts"] == 4096
        for bad in ("0x1234:01", "0x9020:03 = 1", "0x8020:02 = 40000", "hello"):
            with pytest.raises(InvalidArgumentError) as refused:
                await run.axis.console(bad)
            assert refused.value.field == "line"


async def test_fake_master_configured_settings_are_written_at_bring_up() -> None:
    settings = replace(PosSettings(), modulo_factor_counts=1000, target_window_counts=7)
    async with running(settings=settings) as run:
        assert run.slave.engine.settings.modulo_factor_counts == 1000
        assert run.slave.engine.settings.target_window_counts == 7
        assert run.sink.params[run.axis.id]["modulo_factor_counts"] == 1000


# --- moves ----------------------------------------------------------------------------------


async def test_fake_master_modulo_plus_move_ends_in_target_at_the_right_position() -> None:
    async with running() as run:
        await run.axis.command("enable", {})
        assert "started" in await run.move(StartType.MODULO_PLUS, 1024)
        await run.move_ended()
        assert run.latest_flag("in_target")
        assert run.latest_channel("position") == pytest.approx(1024, abs=10)
        # From 1024 to modulo position 512 the positive way: 3584 counts on, to 4608.
        start = len(run.samples)
        await run.move(StartType.MODULO_PLUS, 512)
        await run.move_ended()
        samples = run.sink.samples[run.axis.id][start:]
        assert run.latest_flag("in_target")
        assert run.latest_channel("position") == pytest.approx(TURN + 512, abs=10)
        positions = [s.channels["position"] or 0 for s in samples]
        assert all(b >= a for a, b in itertools.pairwise(positions)), "went back"
        assert any(s.channels["target"] == TURN + 512 for s in samples)
        assert any("MODULO_PLUS ended" in m and "In-Target" in m for _, _, m in run.sink.events)


async def test_fake_master_execute_is_held_until_busy_rose_and_fell() -> None:
    async with running() as run:
        await run.axis.command("enable", {})
        history = run.master.history
        first = len(history)
        await run.move(StartType.ABSOLUTE, 3000)
        await run.move_ended()
        await asyncio.sleep(0.02)
        frames = list(history)[first:]
        execute = [f.outputs.execute for f in frames]
        busy = [f.inputs.busy for f in frames]
        rise = execute.index(True)
        # the move's parameters went out one cycle before Execute rose
        assert frames[rise - 1].outputs.target_position_counts == 3000
        assert not frames[rise - 1].outputs.execute
        busy_first = busy.index(True)
        busy_last = len(busy) - 1 - busy[::-1].index(True)
        assert rise < busy_first
        assert all(execute[rise : busy_last + 1]), "Execute dropped while Busy (move aborted)"
        drop = execute.index(False, rise)
        assert busy_last < drop <= busy_last + 3, (busy_last, drop)
        assert not any(execute[drop:]), "Execute raised again"
        assert frames[-1].inputs.in_target


async def test_fake_master_drive_rejection_comes_back_as_409_with_the_diagnosis() -> None:
    async with running() as run:
        await run.axis.command("enable", {})
        slow_ramp = move_args(StartType.ABSOLUTE, 60000, 8000) | {"acceleration_ms": 3000}
        await run.axis.command("execute_move", slow_ramp)
        # While accelerating the drive cannot take a change (manual): Command rejected.
        with pytest.raises(DeviceRefusedError, match="Command rejected"):
            await run.axis.command(
                "execute_move", move_args(StartType.ABSOLUTE_CHANGE, 20000, 3000)
            )
        assert run.latest_flag("busy"), "the running move goes on"
        assert run.latest_flag("command_rejected") and run.latest_flag("warning")
        await run.axis.command("halt", {})
        await run.move_ended()
        # Instant command: no Busy may be seen at a 2 ms cycle, the flags decide.
        outcome = await run.axis.command("set_calibration", {})
        assert "Calibrated" in outcome.message
        await wait_for(lambda: run.latest_flag("calibrated"), 1, "Calibrated")


async def test_fake_master_calibration_on_the_cam_sets_the_counter() -> None:
    async with running() as run:
        await run.axis.command("enable", {})
        await run.axis.command("cali_plc_cam", {})
        await run.move_ended(timeout_s=6)
        events = run.sink.events
        assert run.latest_flag("calibrated"), events
        # the counter now reads the calibration position (0) where the cam was left
        assert run.latest_channel("position") == pytest.approx(0, abs=20), events
        assert run.slave.engine.plant.shaft_counts == pytest.approx(6000, abs=20), events


# --- stop -----------------------------------------------------------------------------------


async def test_fake_master_stop_overtakes_a_queued_move() -> None:
    async with running() as run:
        await run.axis.command("enable", {})
        history = run.master.history
        first = len(history)
        writes = asyncio.create_task(
            run.axis.write_params({"target_window_counts": 11, "in_target_timeout_ms": 400})
        )
        queued_move = asyncio.create_task(
            run.axis.command("execute_move", move_args(StartType.ABSOLUTE, 30000))
        )
        await asyncio.sleep(0)  # both are queued before the STOP
        await run.axis.stop()
        with pytest.raises(DeviceRefusedError, match="STOP came first"):
            await queued_move
        assert await writes == {"target_window_counts": 11, "in_target_timeout_ms": 400}
        await wait_for(lambda: not run.latest_flag("enable_out"), 1, "Enable off after STOP")
        assert not any(f.outputs.execute for f in list(history)[first:]), "the move was sent"
        assert run.latest_channel("position") == 0
        assert any("STOP" in m and "Enable off" in m for _, _, m in run.sink.events)


async def test_fake_master_stop_during_a_move_ramps_down_then_drops_enable() -> None:
    async with running() as run:
        await run.axis.command("enable", {})
        await run.move(StartType.ABSOLUTE, 200_000, velocity=8000)
        await wait_for(lambda: (run.latest_channel("velocity") or 0) > 1000, 2, "cruising")
        history = run.master.history
        first = len(history)
        await run.axis.stop()
        frames = list(history)[first:]
        # on the very next cycle (the one in flight may already have left)
        assert any(f.outputs.emergency_stop and not f.outputs.execute for f in frames[:2])
        await wait_for(lambda: not run.latest_flag("enable_out"), 2, "Enable off")
        # the sample shows the decision; the next exchange carries it to the slave
        await wait_for(
            lambda: any(not f.outputs.enable for f in list(history)[first:]), 2, "Enable off sent"
        )
        frames = list(history)[first:]
        enabled = [f.outputs.enable for f in frames]
        off = enabled.index(False)
        assert not frames[off - 1].inputs.busy, "Enable dropped before standstill"
        assert run.latest_channel("position") < 100_000
        assert any(f.inputs.warning for f in frames)  # Command aborted
        assert not run.latest_flag("emergency_stop_out")


# --- refusals before anything reaches the outputs ----------------------------------------------


async def test_fake_master_bad_input_is_refused_before_the_outputs() -> None:
    async with running() as run:
        history = run.master.history
        first = len(history)
        bad: list[tuple[dict[str, int], str, str]] = [
            (move_args(StartType.ABSOLUTE, 7001, velocity=20000), "velocity", "1..10000"),
            (move_args(StartType.ABSOLUTE, 7002, velocity=0), "velocity", "1..10000"),
            ({**move_args(StartType.ABSOLUTE, 7003), "start_type": 0x1234}, "start_type", ""),
            # (an omitted acceleration takes the descriptor's default: not a refusal)
            (
                {**move_args(StartType.ABSOLUTE, 7004), "acceleration_ms": 70000},
                "acceleration_ms",
                "0..65535",
            ),
            ({**move_args(StartType.ABSOLUTE, 7005), "speed": 1}, "speed", ""),
        ]
        for args, field, text in bad:
            with pytest.raises(InvalidArgumentError) as refused:
                await run.axis.command("execute_move", args)
            assert refused.value.field == field, args
            assert text in str(refused.value)
        with pytest.raises(InvalidArgumentError) as refused:
            await run.axis.write_params({"target_window_counts": 70000})
        assert refused.value.field == "target_window_counts"
        assert "0..65535" in str(refused.value)
        # Refused by the server because the drive would refuse it (409):
        with pytest.raises(DeviceRefusedError, match="not enabled"):
            await run.move(StartType.ABSOLUTE, 7006)
        await run.axis.command("enable", {})
        with pytest.raises(DeviceRefusedError, match="Execute is low"):
            await run.move(StartType.ABSOLUTE_CHANGE, 7007)
        with pytest.raises(DeviceRefusedError, match=r"0\.\.4095"):
            await run.move(StartType.MODULO_SHORT, 7008)
        with pytest.raises(DeviceRefusedError, match="default start type"):
            await run.move(StartType.SET_CALIBRATION_AUTO, 7009)
        await asyncio.sleep(0.02)
        frames = list(history)[first:]
        assert not any(f.outputs.execute for f in frames)
        assert not any(7001 <= f.outputs.target_position_counts <= 7009 for f in frames)


# --- faults ---------------------------------------------------------------------------------


async def test_fake_master_drop_out_of_op_reports_then_recovers_with_settings() -> None:
    async with running() as run:
        await run.axis.command("enable", {})
        await run.axis.write_params({"target_window_counts": 33})
        run.master.drop_out_of_op()
        await wait_for(
            lambda: run.link.state in ("error", "reconnecting"), 2, "the link to go down"
        )
        assert "SAFE-OP + ERROR" in run.link.message and "0x001A" in run.link.message
        assert run.sink.health[run.axis.id][0] == "offline"
        with pytest.raises(LinkDownError):
            await run.axis.command("enable", {})
        await asyncio.sleep(0.6)
        assert run.link.state == "reconnecting", "OP must not come back while the fault lasts"
        # The box was power cycled meanwhile: its settings are back at the defaults.
        run.slave.engine.settings = PosSettings()
        run.master.return_to_op()
        await wait_for(lambda: run.link.state == "connected", 8, "recovery")
        count = len(run.samples)
        await wait_for(lambda: len(run.samples) > count + 20, 2, "samples again")
        assert run.slave.engine.settings.target_window_counts == 33, "settings not re-written"
        assert not run.latest_flag("enable_out"), "Enable must not come back by itself"
        assert any("back in OP" in m for _, _, m in run.sink.events)
        await run.axis.command("enable", {})
        await run.move(StartType.RELATIVE, 500)
        await run.move_ended()
        assert run.latest_flag("in_target")


async def test_fake_master_a_stall_past_the_watchdog_drops_enable_for_good() -> None:
    async with running(watchdog_s=0.1) as run:  # the device default
        await run.axis.command("enable", {})
        run.slave.sdo_delay_s = 0.15  # a slow mailbox holds the cycle thread up
        await asyncio.sleep(0.05)
        run.slave.sdo_delay_s = 0.0
        await wait_for(
            lambda: any("watchdog" in m for _, _, m in run.sink.events), 2, "the stall event"
        )
        # The samples of the cycles after the stall (they may still be on their way to
        # the event loop): Enable off, and it stays off.
        await wait_for(lambda: not run.latest_flag("enable_out"), 2, "Enable dropped")
        off_at = len(run.samples)
        await wait_for(lambda: len(run.samples) > off_at + 20, 2, "more samples")
        assert not any(s.flags["enable_out"] for s in run.samples[off_at:]), (
            "Enable re-asserted after the watchdog"
        )
        assert not run.latest_flag("stm_ready")
        assert run.link.state == "connected"
        await run.axis.command("enable", {})
        assert run.latest_flag("stm_ready")


async def test_fake_master_a_stall_after_a_reply_is_a_watchdog_gap_not_a_silent_abort() -> None:
    """The cycle thread can be held up after a frame's reply has arrived (the GIL taken
    by another thread, the host busy): the slave counts its watchdog from the frame it
    got, so the driver must too - not from when its thread saw the reply. Seen in the
    demo as "ABSOLUTE ended ...: Error: Command aborted" with no watchdog message, and
    Enable silently re-asserted by the next frame."""
    master = demo_master()
    real_receive = master.receive_processdata
    stalls = [0]

    def receive_then_stall(timeout: int = 2000) -> int:
        wkc = real_receive(timeout)
        if stalls[0] > 0:
            stalls[0] -= 1
            time.sleep(0.15)  # the reply is in; the thread runs again 150 ms later
        return wkc

    master.receive_processdata = receive_then_stall  # type: ignore[method-assign]
    async with running(master, watchdog_s=0.1) as run:  # the device default
        await run.axis.command("enable", {})
        moving = asyncio.create_task(run.move(StartType.RELATIVE, 20 * TURN))
        await wait_for(lambda: run.latest_flag("busy"), 2, "the move to start")
        stalls[0] = 1
        await wait_for(lambda: stalls[0] == 0, 2, "the stall")
        await wait_for(
            lambda: any("watchdog" in m for _, _, m in run.sink.events), 2, "the stall event"
        )
        with contextlib.suppress(DeviceRefusedError):
            await asyncio.wait_for(moving, 5)
        await wait_for(lambda: not run.latest_flag("enable_out"), 2, "Enable dropped")
        off_at = len(run.samples)
        await wait_for(lambda: len(run.samples) > off_at + 20, 2, "more samples")
        assert not any(s.flags["enable_out"] for s in run.samples[off_at:]), (
            "Enable re-asserted after the watchdog"
        )


async def test_fake_master_drive_state_is_read_fast_while_moving_slowly_at_rest() -> None:
    """The drive state (0x9020:03) is a mailbox read: every 10 ms while the drive does
    something, every 100 ms at rest (nothing changes it by itself there). Bounds that a
    slow host can only make smaller: at rest at most one read per 100 ms (plus one);
    the move's states (ACCEL/CONST/DECEL...) still reach the samples."""

    def state_reads() -> int:
        return sum(1 for _, op, index, sub, _ in run.slave.sdo_log if (index, sub) == (0x9020, 3))

    async with running() as run:
        await run.axis.command("enable", {})
        await asyncio.sleep(STATE_ACTIVE_S + 0.2)  # past the burst after the flags changed
        before = state_reads()
        await asyncio.sleep(1.0)
        at_rest = state_reads() - before
        assert 1 <= at_rest <= 11, f"{at_rest} drive-state reads in 1 s at rest"
        first = len(run.samples)
        await run.move(StartType.RELATIVE, 3 * TURN)
        await run.move_ended()
        states = {
            int(s.channels["drive_state"])
            for s in run.samples[first:]
            if s.channels["drive_state"] is not None
        }
        assert len(states) >= 3, f"drive states seen during the move: {sorted(states)}"


async def test_fake_master_lost_frames_are_counted_and_a_long_gap_is_a_drop_out() -> None:
    async with running() as run:
        errors = run.link.errors
        run.master.inject_lost_frames(3)
        await asyncio.sleep(0.1)
        assert run.link.errors >= errors + 3
        assert run.link.state == "connected"
        assert all(state == "connected" for state, _ in run.sink.states)
        run.master.inject_lost_frames(50)
        # (on a slow host the recovery may follow before a look at the state)
        await wait_for(
            lambda: any(state == "reconnecting" for state, _ in run.sink.states), 2, "the drop-out"
        )
        assert any(
            "no process data" in m for state, m in run.sink.states if state == "reconnecting"
        )
        await wait_for(lambda: run.link.state == "connected", 5, "recovery")


# --- descriptor and hub -----------------------------------------------------------------------


def test_descriptor_offers_every_start_type_and_every_coe_setting() -> None:
    descriptor = ep7047_descriptor(DEMO_SPEED_RANGE_STEPS_S, DEMO_COUNTS_PER_REV)
    start_type = descriptor.command("execute_move").arguments[0]
    assert {c.value for c in start_type.choices} == {int(s) for s in StartType}
    assert all(c.description for c in start_type.choices)
    names = {p.name for p in descriptor.parameters}
    assert names == set(PARAMETER_SDO) | {INVERSION_PARAMETER}
    assert all(p.persisted for p in descriptor.parameters)
    velocity_max = descriptor.parameter("velocity_max_bp")
    steps_s = next(c for c in velocity_max.conversions if c.unit == "steps/s")
    assert 10000 * steps_s.factor == pytest.approx(DEMO_SPEED_RANGE_STEPS_S)
    assert "sampled" in descriptor.summary
    commands = {c.name for c in descriptor.commands}
    assert {"stop", "emergency_stop", "enable", "disable", "reset_error"} <= commands
    assert {"cali_plc_cam", "cali_hw_sync", "set_calibration", "clear_calibration"} <= commands
    assert {"set_calibration_auto", "restore_parameters"} <= commands
    flag_plot = next(p for p in descriptor.plots if p.kind == "flags")
    assert {"busy", "in_target", "command_rejected"} <= set(flag_plot.series)


async def test_fake_master_behind_the_hub_validates_and_runs_the_demo_autopilot(
    tmp_path: Path,
) -> None:
    storage = Storage(tmp_path / "servotune.db")
    hub = Hub([], storage, autopilot=True)
    link = build_ep7047_link(
        "ec",
        "simeth0",
        1,
        hub,
        master=demo_master(),
        speed_range_steps_s=DEMO_SPEED_RANGE_STEPS_S,
        counts_per_rev=DEMO_COUNTS_PER_REV,
    )
    hub.add_link(link)
    await hub.start()
    try:
        axis_id = link.axes[0].id
        entry = hub.entry(axis_id)

        def position() -> float:
            latest = entry.latest
            return (latest.channels["position"] or 0.0) if latest is not None else 0.0

        await wait_for(lambda: abs(position()) > 3000, 8, "the demo autopilot to move a turn")
        with pytest.raises(InvalidArgumentError) as refused:
            await hub.command(axis_id, "execute_move", move_args(StartType.ABSOLUTE, 0, 20000))
        assert refused.value.field == "velocity"
        assert await hub.stop_all() == []
        await wait_for(
            lambda: entry.latest is not None and not entry.latest.flags["enable_out"],
            2,
            "Enable off after STOP",
        )
    finally:
        await hub.stop()
        storage.close()


async def test_fake_master_cycle_thread_crash_is_reported_and_restarted(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Supervision: a bug in the cycle thread shows ``error`` with the message, the
    thread is restarted on a new master, the axis comes back with Enable off."""
    async with running() as run:
        await run.axis.command("enable", {})
        original = run.link.cycle._cyclic
        crashed: list[bool] = []

        def crashing(master: object, slave: object) -> None:
            if not crashed:
                crashed.append(True)
                raise RuntimeError("injected bug in the cycle")
            original(master, slave)  # type: ignore[arg-type]

        index = len(run.sink.states)
        monkeypatch.setattr(run.link.cycle, "_cyclic", crashing)
        run.master.drop_out_of_op()  # the drop-out makes the thread enter _cyclic again
        await wait_for(
            lambda: any(s == "reconnecting" for s, _ in run.sink.states[index:]), 5, "drop-out"
        )
        run.master.return_to_op()
        await wait_for(lambda: bool(crashed), 5, "the injected crash")
        await wait_for(
            lambda: run.link.state == "connected" and run.link.counters["restarts"] == 1,
            10,
            "the restart",
        )
        states = [s for s, _ in run.sink.states[index:]]
        assert "error" in states
        error_at = states.index("error")
        assert "connected" in states[error_at:]
        assert any("injected bug" in m for s, m in run.sink.states[index:] if s == "error")
        count = len(run.samples)
        await wait_for(lambda: len(run.samples) > count + 20, 5, "samples again")
        assert not run.latest_flag("enable_out"), "Enable must not come back by itself"
        await run.axis.command("enable", {})
        await run.axis.stop()
        await wait_for(lambda: not run.latest_flag("enable_out"), 5, "the STOP on the wire")
        assert any(f.outputs.emergency_stop for f in list(run.master.history)[-2000:]), (
            "the STOP never reached the slave"
        )
