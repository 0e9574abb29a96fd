"""Simulators in their own processes: start, records, stop, no orphans, and the EP7047
driver against ``ProcessMaster`` (the simulated slave in a child process)."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import serial

from servotune.devices.ep7047.codec import StartType
from servotune.devices.ep7047.link import (
    Ep7047Axis,
    Ep7047Link,
    EthercatUnavailableError,
    build_ep7047_link,
)
from servotune.devices.ep7047.sim.process import (
    ProcessMaster,
    ep7047_sim_process,
    is_process_address,
)
from servotune.devices.ep7047.sim.slave import DEMO_COUNTS_PER_REV, DEMO_SPEED_RANGE_STEPS_S
from servotune.sim.process import SimProcess, SimProcessError
from tests.support import sim_builders
from tests.support.paths import SERVER
from tests.support.sim_lines import simulator_process
from tests.support.sink import RecordingSink
from tests.support.waiting import wait_for


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie (exited, not yet reaped) counts as gone
    with contextlib.suppress(OSError):
        if Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z":
            return False
    return True


def _wait_gone(pid: int, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if not _alive(pid):
            return True
        time.sleep(0.05)
    return False


def test_serial_simulator_process_serves_its_pty_records_and_stops(tmp_path: Path) -> None:
    from servotune.devices.slap2.entry import demo_line as slap2_demo_line

    with slap2_demo_line(tmp_path) as specs:
        (spec,) = specs
        born_ns = os.stat(spec.path).st_ctime_ns
        port = serial.Serial(spec.path, 19200, timeout=2)
        try:
            # the power-on banner may be on its way (or partly read by opening): skip it
            port.read_until(b"\r\n")
            port.reset_input_buffer()
            for byte in b"rp\r":
                port.write(bytes([byte]))
                assert port.read(1) == bytes([byte])  # echo from the child's firmware
            assert port.read_until(b"\r\n").strip().lstrip(b"-").isdigit()
        finally:
            port.close()
        record = tmp_path / "slap2-record.json"
        wait_for_file(record, 10)
        text = record.read_text()
        assert '"modules"' in text and '"address": 1' in text
    # The kernel reuses pty numbers: another process on the machine may have opened a
    # new /dev/pts/N with the same number since; that one is a different device (a new
    # inode change time), not ours outliving its simulator.
    with contextlib.suppress(FileNotFoundError):
        assert os.stat(spec.path).st_ctime_ns != born_ns, "the pty outlived its simulator"


def wait_for_file(path: Path, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not path.exists():
        assert time.monotonic() < deadline, f"{path} was not written"
        time.sleep(0.05)


def test_a_simulator_that_fails_to_build_reports_it() -> None:
    process = SimProcess("broken", _fail, None)
    with pytest.raises(SimProcessError, match="failed to start"):
        process.start(timeout_s=60)
    assert not process.alive


def _fail(spec: object, conn: object) -> None:
    raise RuntimeError("no such device")


def test_children_end_when_the_server_is_killed(tmp_path: Path) -> None:
    """SIGKILL leaves no time to clean up: the children see their lifeline end."""
    script = textwrap.dedent(
        f"""
        import sys, time
        sys.path.insert(0, {str(SERVER)!r})
        from servotune.devices.slap2.entry import demo_line as slap2_demo_line
        from servotune.devices.ep7047.entry import demo_slave as ep7047_demo_slave
        from pathlib import Path
        with slap2_demo_line(Path({str(tmp_path)!r})) as a, ep7047_demo_slave(
            Path({str(tmp_path)!r})
        ) as b:
            print(a[0].path, b[0].path, flush=True)
            time.sleep(600)
        """
    )
    parent = subprocess.Popen(
        [sys.executable, "-c", script], stdout=subprocess.PIPE, stdin=subprocess.DEVNULL
    )
    try:
        assert parent.stdout is not None
        line = parent.stdout.readline().decode().split()
        assert len(line) == 2, line
        _pty_path, address = line
        assert is_process_address(address)
        children = _children(parent.pid)
        assert len(children) >= 2, children
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
        for child in children:
            assert _wait_gone(child, 10), f"simulator process {child} outlived the server"
        socket_path = address.removeprefix("sim:")
        assert not os.path.exists(socket_path), "the EP7047 socket was left behind"
        assert not os.path.exists(os.path.dirname(socket_path))
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
        if parent.stdout is not None:
            parent.stdout.close()


def _children(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError):
                stat = (entry / "stat").read_text()
                if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                    found.append(int(entry.name))
    return found


# --- the EP7047 driver over ProcessMaster ------------------------------------------------


@contextlib.asynccontextmanager
async def process_link(
    tmp_path: Path,
) -> AsyncIterator[tuple[Ep7047Link, Ep7047Axis, RecordingSink, SimProcess, ProcessMaster]]:
    simulator = ep7047_sim_process(tmp_path / "ep7047-record.json")
    await asyncio.to_thread(simulator.start)
    try:
        master = ProcessMaster(simulator.ready["path"].removeprefix("sim:"))
        sink = RecordingSink()
        link = build_ep7047_link(
            "ec",
            simulator.ready["path"],
            1,
            sink,
            master=master,
            speed_range_steps_s=DEMO_SPEED_RANGE_STEPS_S,
            counts_per_rev=DEMO_COUNTS_PER_REV,
        )
        axis = link.axes[0]
        assert isinstance(axis, Ep7047Axis)
        task = asyncio.create_task(link.run())
        try:
            await wait_for(lambda: link.state == "connected", 30, "the link to reach OP")
            yield link, axis, sink, simulator, master
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
    finally:
        await asyncio.to_thread(simulator.stop)


async def test_ep7047_driver_over_a_process_master_brings_up_moves_and_stops(
    tmp_path: Path,
) -> None:
    async with process_link(tmp_path) as (link, axis, sink, simulator, master):
        assert "in OP on sim:" in link.message
        samples = sink.samples[axis.id]
        params = sink.params[axis.id]
        assert params["modulo_factor_counts"] == DEMO_COUNTS_PER_REV  # read over CoE
        await axis.command("enable", {})
        await wait_for(lambda: bool(samples[-1].flags["stm_ready"]), 5, "STM Ready")
        start = samples[-1].channels["position"]
        assert start is not None
        await axis.command(
            "execute_move",
            {
                "start_type": int(StartType.RELATIVE),
                "target": 200_000,
                "velocity": 5000,
                "acceleration_ms": 200,
                "deceleration_ms": 200,
            },
        )
        await wait_for(lambda: bool(samples[-1].flags["busy"]), 5, "Busy")
        record = await asyncio.to_thread(master.record)
        assert record["slaves"][0]["busy"] is True
        await axis.stop()
        await wait_for(
            lambda: not samples[-1].flags["busy"] and not samples[-1].flags["enable_out"],
            10,
            "the STOP to ramp down and drop Enable",
        )
        # The device itself (in the other process) shows it stopped and disabled.
        slave = (await asyncio.to_thread(simulator.request, "record"))["device"]["slaves"][0]
        assert slave["busy"] is False
        assert slave["enabled"] is False
        assert slave["velocity_counts_s"] == 0.0
        position = samples[-1].channels["position"]
        assert position is not None and start < position < start + 200_000


async def test_ep7047_link_reconnects_when_the_simulator_process_is_replaced(
    tmp_path: Path,
) -> None:
    async with process_link(tmp_path) as (link, _axis, _sink, simulator, _master):
        pid = simulator.pid
        assert pid is not None
        os.kill(pid, signal.SIGKILL)  # the far end dies: nothing answers any more
        await wait_for(lambda: link.state != "connected", 10, "the link to notice")
        assert link.state in ("reconnecting", "error")


def test_process_master_without_a_simulator_says_what_is_missing(tmp_path: Path) -> None:
    master = ProcessMaster(str(tmp_path / "nothing.sock"))
    with pytest.raises(EthercatUnavailableError, match="does not answer"):
        master.open("sim")


def test_binary_sdo_read_gives_what_the_json_request_gives(tmp_path: Path) -> None:
    """The cyclic SDO read is binary (``R``); it must answer exactly as the JSON request
    did: the same bytes, the same abort, and each slave's state updated."""
    from servotune.devices.ep7047 import codec
    from servotune.transports.ethercat import EthercatSdoError

    with ep7047_sim_process(tmp_path / "record.json") as simulator:
        master = ProcessMaster(simulator.ready["path"].removeprefix("sim:"))
        master.open("sim")
        try:
            assert master.config_init() == 1
            slave = master.slaves[0]
            obj = codec.DRIVE_STATE
            binary = slave.sdo_read(obj.index, obj.subindex, obj.data_type.size)
            as_json = bytes.fromhex(
                str(master._call("sdo_read", 1, obj.index, obj.subindex, obj.data_type.size))
            )
            assert binary == as_json and len(binary) == obj.data_type.size
            # Both replies carry each slave's state: it is set again from them.
            slave._state = -1
            slave.sdo_read(obj.index, obj.subindex, obj.data_type.size)
            state_binary = slave.state
            slave._state = -1
            master._call("sdo_read", 1, obj.index, obj.subindex, obj.data_type.size)
            assert state_binary == slave.state != -1
            with pytest.raises(EthercatSdoError) as binary_abort:
                slave.sdo_read(0x7FFF, 0x01, 2)
            with pytest.raises(EthercatSdoError) as json_abort:
                master._call("sdo_read", 1, 0x7FFF, 0x01, 2)
            assert binary_abort.value.abort_code == json_abort.value.abort_code != 0
        finally:
            master.close()


def test_a_remote_reads_the_device_in_its_process_and_refuses_to_write_a_copy(
    tmp_path: Path,
) -> None:
    build = functools.partial(sim_builders.slap2_line, [0], tmp_path)
    with simulator_process("remote", build, 19200) as (simulator, bus):
        assert simulator.baud == 19200 and simulator.path.startswith("/dev/")
        module = bus.module(0)
        assert module.settings["kp"] == 40 and module.rss == bus.module(0).rss
        with pytest.raises(TypeError):
            module.settings["kp"] = 1  # a copy: refused, not silently lost
        module.motor.external_torque_nm = 0.01  # set in the device itself
        assert module.motor.external_torque_nm == 0.01
        with pytest.raises(SimProcessError, match="no_such_thing"):
            _ = bus.no_such_thing
