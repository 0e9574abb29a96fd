"""The simulator on a real pseudo-terminal: wire timing, faults, the CLI entry point."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial

from servotune.devices.slap2.codec import DEFAULT_BAUD
from servotune.devices.slap2.sim.line import Slap2Line
from servotune.sim.pty import PtySimulator

BAUD = DEFAULT_BAUD
CHAR_S = 10 / BAUD


@pytest.fixture
def simulator(tmp_path: Path) -> Iterator[PtySimulator]:
    sim = PtySimulator(Slap2Line.with_addresses([0, 1]), baud=BAUD, link_path=str(tmp_path / "tty"))
    sim.start()
    try:
        yield sim
    finally:
        sim.stop()


def open_port(path: str) -> serial.Serial:
    port = serial.Serial(path, BAUD, timeout=0.2)
    drain(port)
    return port


def drain(port: serial.Serial) -> bytes:
    """Read until the line is quiet for 50 ms (the banner, leftovers)."""
    port.timeout = 0.05
    data = bytearray()
    while chunk := port.read(256):
        data += chunk
    port.timeout = 0.2
    return bytes(data)


def exchange(port: serial.Serial, text: str) -> tuple[str, list[float]]:
    """The manual's sstring/rstring: one char, wait for its echo, ...; then the reply.

    Returns the reply and the round-trip time of each echoed character.
    """
    round_trips = []
    for byte in text.encode("ascii") + b"\r":
        start = time.perf_counter()
        port.write(bytes([byte]))
        echo = port.read(1)
        round_trips.append(time.perf_counter() - start)
        assert echo == bytes([byte]), (text, echo)
    reply = bytearray()
    while not reply.endswith(b"\r"):
        byte = port.read(1)
        assert byte, f"no reply to {text!r}"
        reply += byte
    return reply.decode("ascii").rstrip("\r"), round_trips


def test_echo_and_reply_over_the_pty_take_wire_time(simulator: PtySimulator) -> None:
    port = open_port(simulator.path)
    try:
        reply, round_trips = exchange(port, "rp")
        assert reply == "0"
        for _ in range(5):
            reply, more = exchange(port, "rp")
            round_trips += more
        # host -> device char plus device -> host echo: two character times at least
        assert min(round_trips) >= 0.8 * 2 * CHAR_S
        start = time.perf_counter()
        assert exchange(port, "id")[0].startswith("SLAP2")
        # 3 echoed chars + a 27-char reply line: the wire cannot be faster
        assert time.perf_counter() - start >= 0.8 * (3 * 2 + 27) * CHAR_S
    finally:
        port.close()


def test_back_to_back_bytes_queue_on_the_wire(simulator: PtySimulator) -> None:
    port = open_port(simulator.path)
    try:
        start = time.perf_counter()
        port.write(b"rp\rrp\r")  # not waiting for echoes: the line is the bottleneck
        received = bytearray()
        while received.count(b"\r") < 4:
            chunk = port.read(64)
            assert chunk
            received += chunk
        assert received == b"rp\r0\rrp\r0\r"
        assert time.perf_counter() - start >= 0.8 * len(received) * CHAR_S
    finally:
        port.close()


def test_banner_and_power_cycle_on_the_wire(simulator: PtySimulator) -> None:
    port = open_port(simulator.path)
    try:
        simulator.power_cycle()
        time.sleep(0.1)
        assert drain(port).startswith(b"SLAP2 V2205")
        assert exchange(port, "se1")[0] == ""
        simulator.power_cycle(1)  # address 1 powers up deselected and silent
        port.write(b"r")
        assert port.read(1) == b""
    finally:
        port.close()


def test_drop_echoes_and_inject_garbage(simulator: PtySimulator) -> None:
    port = open_port(simulator.path)
    try:
        simulator.drop_echoes(1)
        port.write(b"r")
        assert port.read(1) == b""  # the echo is lost
        port.write(b"\x18")  # Ctrl-X: start over
        assert port.read(1) == b"\x18"
        simulator.inject_garbage(b"#!?")
        assert port.read(3) == b"#!?"
        assert exchange(port, "qp")[0] == "40"
    finally:
        port.close()


def test_silent_line_carries_nothing(simulator: PtySimulator) -> None:
    port = open_port(simulator.path)
    try:
        simulator.set_silent(True)
        port.write(b"kp 77\r")
        assert port.read(1) == b""
        simulator.set_silent(False)
        assert exchange(port, "qp")[0] == "40"  # the kp line never reached the module
    finally:
        port.close()


def test_unplug_and_replug(simulator: PtySimulator) -> None:
    link = simulator.path
    port = open_port(link)
    assert exchange(port, "kp 77")[0] == ""
    simulator.unplug()
    assert simulator.slave_name is None
    assert not os.path.lexists(link)
    with pytest.raises(serial.SerialException):
        port.write(b"q")
        port.read(1)
    port.close()
    with pytest.raises(serial.SerialException):
        serial.Serial(link, BAUD, timeout=0.2)
    simulator.replug()
    assert os.path.exists(link)
    assert simulator.slave_name is not None
    port = open_port(link)
    try:
        assert exchange(port, "qp")[0] == "77"  # the device kept its state
    finally:
        port.close()


def test_stop_removes_the_link(tmp_path: Path) -> None:
    link = tmp_path / "tty"
    sim = PtySimulator(Slap2Line.with_addresses([0]), baud=BAUD, link_path=str(link))
    sim.start()
    assert link.is_symlink()
    sim.stop()
    assert not os.path.lexists(link)


def run_cli_session(process: subprocess.Popen[str], link: Path, state_dir: Path) -> None:
    assert process.stdout is not None
    assert process.stdout.readline().strip() == str(link)  # the path is the first line
    port = open_port(str(link))
    try:
        assert exchange(port, "kp 66")[0] == ""
        assert exchange(port, "pg")[0] == ""
        assert exchange(port, "se1")[0] == ""
        assert exchange(port, "qp")[0] == "40"
    finally:
        port.close()
    process.send_signal(signal.SIGTERM)
    assert process.wait(timeout=5) == 0
    assert not os.path.lexists(link)
    assert (state_dir / "slap2_0.json").exists()


@pytest.mark.slow
def test_cli_entry_point_prints_the_path_first_and_stops_on_sigterm(tmp_path: Path) -> None:
    link = tmp_path / "slap"
    state_dir = tmp_path / "state"
    code = (
        "from servotune.devices.slap2.sim.demo import serve_slap2; from pathlib import Path; "
        f"serve_slap2([0, 1], {BAUD}, Path({str(state_dir)!r}), {str(link)!r})"
    )
    command = [sys.executable, "-c", code]
    with subprocess.Popen(command, stdout=subprocess.PIPE, text=True) as process:
        try:
            run_cli_session(process, link, state_dir)
        finally:
            if process.poll() is None:
                process.kill()
