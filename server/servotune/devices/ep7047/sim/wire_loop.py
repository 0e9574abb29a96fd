"""The simulated EP7047-1032 on a network interface: the AF_PACKET socket loop, the
control socket (fault injection, the slave's own record) and ``servotune sim ep7047
--ifname IF``. The slave itself is ``servotune.devices.ep7047.sim.wire.WireSlave``.

The loop answers every EtherCAT frame (EtherType 0x88A4) that arrives on the interface
at once, steps the drive in between (at least every 20 ms, and when the watchdog is
due), and serves control requests (JSON over a Unix datagram socket: a path socket
reaches into a network namespace). It asks for real-time priority (SCHED_FIFO 60): a
real slave is hardware, and a simulated one that a CPU hog delays would make the
master count lost frames that no wire lost.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import select
import socket
import threading
import time
from collections.abc import Callable
from typing import Any, Final

from servotune.devices.ep7047.sim.sii import Identity
from servotune.devices.ep7047.sim.wire import WireSlave
from servotune.sim.ethercat_esc import ETHERTYPE_ECAT
from servotune.transports.ethercat_cycle import raise_priority

logger = logging.getLogger(__name__)

SOL_PACKET: Final = 263  # linux/socket.h
PACKET_IGNORE_OUTGOING: Final = 23  # linux/if_packet.h (Linux 4.20+)
PACKET_OUTGOING: Final = 4
# Real-time, above the cycle process (50): this stands in for hardware, which answers a
# frame at once whatever the host does; below the cycle (SOEM answers its own frames in
# between) or at normal priority under a CPU hog it answered late enough for SOEM to
# count a lost frame no wire lost (docs/ep7047-wire.md, the soaks).
# It never spins: the loop sleeps in select() until a frame, a control request or the
# watchdog's deadline (at least WAIT_MIN_S away); tests/device/ep7047/test_rt.py measures it.
RT_PRIORITY: Final = 60
# The shortest wait for the watchdog's deadline: the drive steps in 250 us cycles and a
# trip is judged at the cycle where it falls, so waking earlier than the next cycle
# would only loop (a zero timeout at real-time priority is a busy loop).
WAIT_MIN_S: Final = 0.00025
WAIT_MAX_S: Final = 0.02


def _open_socket(ifname: str) -> socket.socket:
    sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETHERTYPE_ECAT))
    sock.bind((ifname, ETHERTYPE_ECAT))
    with contextlib.suppress(OSError):
        sock.setsockopt(SOL_PACKET, PACKET_IGNORE_OUTGOING, 1)
    sock.setblocking(False)
    return sock


def _reply_frame(frame: bytes, payload: bytes) -> bytes:
    # The ESC sets the locally administered bit of the source address on the way back
    # through port 0 (SOEM uses it to tell the primary from the secondary port).
    source = bytes([frame[6] | 0x02]) + frame[7:12]
    return frame[0:6] + source + frame[12:14] + payload


def serve_wire(
    slave: WireSlave,
    ifname: str,
    stop: threading.Event,
    *,
    control_path: str | None = None,
    ready: Callable[[str], None] | None = None,
) -> None:
    """Answer EtherCAT frames on ``ifname`` until ``stop``; control requests (JSON lines
    on a Unix datagram socket at ``control_path``) between frames."""
    sock = _open_socket(ifname)
    control: socket.socket | None = None
    if control_path is not None:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(control_path)
        control = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        control.bind(control_path)
        control.setblocking(False)
    readers = [sock] if control is None else [sock, control]
    try:
        if ready is not None:
            ready(ifname)
        while not stop.is_set():
            deadline = slave.next_deadline_ns()
            now = time.monotonic_ns()
            timeout = (
                WAIT_MAX_S
                if deadline is None
                else min(WAIT_MAX_S, max(WAIT_MIN_S, (deadline - now) / 1e9))
            )
            readable, _, _ = select.select(readers, [], [], timeout)
            if sock in readable:
                _drain(sock, slave)
            else:
                with slave._lock:
                    slave.advance(time.monotonic_ns())
            if control is not None and control in readable:
                _control(control, slave)
    finally:
        sock.close()
        if control is not None:
            control.close()
            with contextlib.suppress(FileNotFoundError):
                os.unlink(control_path or "")


def _drain(sock: socket.socket, slave: WireSlave) -> None:
    while True:
        try:
            frame, address = sock.recvfrom(2048)
        except BlockingIOError:
            return
        except OSError as exc:  # the interface went down or away: reported once
            if exc.errno != errno.ENETDOWN:
                raise
            logger.warning("%s: waiting for the interface", exc)
            return
        if address[2] == PACKET_OUTGOING or len(frame) < 16:
            continue
        if frame[12:14] != b"\x88\xa4":
            continue
        payload = bytearray(frame[14:])
        if slave.frame(payload, time.monotonic_ns()):
            delay_us = slave.faults.answer_delay_us
            if delay_us:  # a slow slave: it sleeps (at its real-time priority: never spins)
                time.sleep(delay_us / 1e6)
            with contextlib.suppress(OSError):  # the interface went down: the master sees it
                sock.send(_reply_frame(frame, bytes(payload)))


def _control(control: socket.socket, slave: WireSlave) -> None:
    while True:
        try:
            data, peer = control.recvfrom(4096)
        except BlockingIOError:
            return
        try:
            answer = slave.control(json.loads(data))
        except (ValueError, TypeError) as exc:
            answer = {"error": str(exc)}
        if peer:
            with contextlib.suppress(OSError):
                control.sendto(json.dumps(answer).encode(), peer)


def control_request(path: str, request: dict[str, Any], timeout_s: float = 2.0) -> dict[str, Any]:
    """Send one control request to a running wire slave and return its answer."""
    client = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    local = f"{path}.client-{os.getpid()}-{threading.get_native_id()}"
    with contextlib.suppress(FileNotFoundError):
        os.unlink(local)
    try:
        client.bind(local)
        client.settimeout(timeout_s)
        client.sendto(json.dumps(request).encode(), path)
        answer: dict[str, Any] = json.loads(client.recv(65536))
        return answer
    finally:
        client.close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(local)


def demo_wire_slave(identity: Identity | None = None) -> WireSlave:
    """The demo's drive (``devices.ep7047.sim.slave.demo_slave``'s engine) behind the wire."""
    from servotune.devices.ep7047.sim.slave import demo_slave

    simulated = demo_slave()
    return WireSlave(
        simulated.engine, identity=identity, speed_range_code=simulated.speed_range_code
    )


def run_wire_simulator(
    ifname: str,
    *,
    control_path: str | None = None,
    identity: Identity | None = None,
    realtime: bool = True,
) -> None:
    """``servotune sim ep7047 --ifname IF``: serve the demo drive on ``ifname`` in the
    foreground until SIGINT/SIGTERM."""
    import signal

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: stop.set())
    if realtime:
        print(raise_priority("the EP7047 wire simulator", RT_PRIORITY)[1], flush=True)
    slave = demo_wire_slave(identity)

    def ready(name: str) -> None:
        ident = slave.identity
        print(
            f"EP7047-1032 simulator on {name}: vendor 0x{ident.vendor:08X} product "
            f"0x{ident.product:08X} revision 0x{ident.revision:08X}"
            + (f"; control socket {control_path}" if control_path else ""),
            flush=True,
        )

    serve_wire(slave, ifname, stop, control_path=control_path, ready=ready)
