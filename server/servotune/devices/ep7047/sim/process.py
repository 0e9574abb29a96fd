"""The simulated EP7047-1032 in a process of its own, behind the driver's master seam.

``ProcessMaster`` implements the driver's ``EthercatMaster`` (pysoem's names, see
``servotune.devices.ep7047.link``) by forwarding every call to a ``SimulatedEthercatMaster``
that runs in another process (``serve_ep7047``), over a Unix ``SOCK_SEQPACKET`` socket
(one message per call, boundaries kept by the kernel, no framing of our own, no
pickle: nothing that connects can make the simulator run code).

The address of a link is ``sim:<socket path>`` (``servotune sim ep7047 --socket PATH``
serves one; the demo starts it as a child, see ``servotune.demo``), so
``ep7047:sim:/tmp/ep.sock`` works as a link spec too.

Messages (client -> simulator -> client):

* process data, every cycle: ``P`` + the sender's monotonic time (``<d``) + the outputs
  of every slave found, in order -> ``P`` + working counter (``<H``) + their inputs.
  The time is the master's clock when the frame left: the simulated slave steps its
  250 us cycles up to it (``CLOCK_MONOTONIC`` is one clock for every process), so a
  simulator that is scheduled late still sees the frame when it passed the slave;
* an SDO read (the driver reads the drive state every 10 ms): ``R`` + position,
  index, subindex, size (``<HHBH``) -> ``r`` + each slave's state and AL status
  (``<HH``) + the data, or a ``J`` error reply as below. Binary because it is the one
  request of the cyclic operation: as JSON it cost the driver's cycle thread as much
  as the process data exchange (profiled in the demo);
* everything else (bring-up, state machine, SDO writes): ``J`` + a JSON request
  ``{"op", "args"}`` -> ``J`` + ``{"ok", "slaves"}`` or ``{"error"}``. ``slaves`` carries
  each slave's state field and AL status after the call, as pysoem updates them.
  SDO aborts and mailbox errors come back as the driver's own exception types.

Decision: a reply is awaited up to ``REPLY_TIMEOUT_S`` (1 s) whatever the receive
timeout says. There is no wire in between that could lose a frame: a reply that is
late only means the host did not schedule the simulator in time (a real EtherCAT
frame is back within microseconds and waits in the NIC for the master to read it).
Counting that as a lost frame would be a false alarm made by the simulation. If the
simulator does not answer within 1 s, or its process ends, ``EthercatMailboxError``
says so and the driver goes to ``reconnecting`` as with a pulled cable; the next
bring-up reconnects (``open``). Injected losses (``lose_frames``) still come back with
working counter 0.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import socket
import struct
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Final

from servotune.devices.ep7047.sim.slave import (
    SimulatedEp7047Slave,
    SimulatedEthercatMaster,
    demo_master,
)
from servotune.sim.process import SimProcess, serve_lifeline, write_record
from servotune.transports.ethercat import (
    INIT_STATE,
    EthercatMailboxError,
    EthercatSdoError,
    EthercatSlave,
    EthercatUnavailableError,
    RemoteSlave,
)
from servotune.transports.ethercat_cycle import raise_weight

logger = logging.getLogger(__name__)

ADDRESS_PREFIX: Final = "sim:"
REPLY_TIMEOUT_S: Final = 1.0
SIM_NICE: Final = -10  # see serve_ep7047
_MAX_MESSAGE: Final = 1 << 16
_PROCESS: Final = b"P"[0]
_JSON: Final = b"J"[0]
_SDO_READ: Final = b"R"[0]
_SDO_DATA: Final = b"r"[0]
_TIME = struct.Struct("<d")
_WKC = struct.Struct("<H")
_SDO_READ_REQUEST = struct.Struct("<HHBH")  # slave position, index, subindex, size
_SLAVE_STATE = struct.Struct("<HH")  # state, AL status


def _kernel_timeval(seconds: float) -> bytes:
    """``struct timeval`` for SO_RCVTIMEO/SO_SNDTIMEO (native ``long`` seconds and us)."""
    whole = int(seconds)
    return struct.pack("@ll", whole, round((seconds - whole) * 1e6))


def is_process_address(path: str) -> bool:
    """True for ``sim:<socket path>`` (a simulator process), not plain ``sim``."""
    return path.startswith(ADDRESS_PREFIX) and len(path) > len(ADDRESS_PREFIX)


# --- the client: the driver's EthercatMaster ------------------------------------------------


class ProcessMaster:
    """The driver's ``EthercatMaster`` over a simulator process at ``socket_path``."""

    def __init__(self, socket_path: str, *, reply_timeout_s: float = REPLY_TIMEOUT_S) -> None:
        self.socket_path = socket_path
        self._reply_timeout_s = reply_timeout_s
        self._sock: socket.socket | None = None
        self._slaves: list[RemoteSlave] = []
        self._state = INIT_STATE
        self._frame_sent = False
        self._lock = threading.Lock()

    # --- transport ------------------------------------------------------------------

    def _connect(self) -> socket.socket:
        if self._sock is not None:
            return self._sock
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        sock.settimeout(self._reply_timeout_s)
        try:
            sock.connect(self.socket_path)
        except OSError as exc:
            sock.close()
            raise EthercatUnavailableError(
                f"the EP7047 simulator does not answer at {self.socket_path} ({exc.strerror}): "
                "is its process running (servotune sim ep7047 --socket PATH)?"
            ) from exc
        # Connected: a blocking socket with the reply timeout in the kernel (SO_RCVTIMEO,
        # SO_SNDTIMEO), not Python's. A Python timeout makes every send and recv a
        # poll() first and then the call - four syscalls per exchange instead of two,
        # at 600 exchanges a second (profiled); the kernel's timeout gives the same
        # 1 s limit with one syscall each (a timed-out call fails with EAGAIN).
        sock.settimeout(None)
        timeval = _kernel_timeval(self._reply_timeout_s)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, timeval)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, timeval)
        self._sock = sock
        return sock

    def _drop(self) -> None:
        sock, self._sock = self._sock, None
        self._frame_sent = False
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.close()

    def _exchange(self, message: bytes) -> bytes:
        sock = self._sock
        if sock is None:
            raise EthercatMailboxError("the simulated master is not open")
        try:
            sock.send(message)
            reply = sock.recv(_MAX_MESSAGE)
        except (TimeoutError, BlockingIOError) as exc:  # BlockingIOError: SO_RCVTIMEO
            self._drop()
            raise self._no_answer() from exc
        except OSError as exc:
            self._drop()
            raise EthercatMailboxError(f"lost the EP7047 simulator process: {exc!r}") from exc
        if not reply:
            self._drop()
            raise EthercatMailboxError("the EP7047 simulator process closed the connection")
        return reply

    def _no_answer(self) -> EthercatMailboxError:
        return EthercatMailboxError(
            f"the EP7047 simulator did not answer within {self._reply_timeout_s:g} s"
        )

    def _call(self, op: str, *args: Any) -> Any:
        with self._lock:
            if self._frame_sent and self._sock is not None:
                self._read_frame(self._sock)  # a frame's reply not read yet: not ours
            reply = self._exchange(b"J" + json.dumps({"op": op, "args": args}).encode())
        return self._json_reply(reply)

    def _sdo_read(self, position: int, index: int, subindex: int, size: int) -> bytes:
        request = bytes([_SDO_READ]) + _SDO_READ_REQUEST.pack(position, index, subindex, size)
        with self._lock:
            if self._frame_sent and self._sock is not None:
                self._read_frame(self._sock)  # a frame's reply not read yet: not ours
            reply = self._exchange(request)
        if reply[0] != _SDO_DATA:
            return bytes.fromhex(str(self._json_reply(reply)))  # an error: raises
        offset = 1
        for slave in self._slaves:
            state, al_status = _SLAVE_STATE.unpack_from(reply, offset)
            slave.reported(state, al_status)
            offset += _SLAVE_STATE.size
        return reply[offset:]

    def _json_reply(self, reply: bytes) -> Any:
        if reply[0] != _JSON:
            raise EthercatMailboxError(f"unexpected reply from the simulator: {reply[:8]!r}")
        message = json.loads(reply[1:])
        for slave, info in zip(self._slaves, message.get("slaves", ()), strict=False):
            slave.reported(int(info["state"]), int(info["al_status"]))
        error = message.get("error")
        if error is not None:
            raise _error_from(error)
        return message.get("ok")

    # --- SlaveCalls (for RemoteSlave) ----------------------------------------------

    def slave_sdo_read(self, position: int, index: int, subindex: int, size: int) -> bytes:
        return self._sdo_read(position, index, subindex, size)

    def slave_sdo_write(self, position: int, index: int, subindex: int, data: bytes) -> None:
        self._call("sdo_write", position, index, subindex, data.hex())

    def slave_write_state(self, position: int, state: int) -> int:
        return int(self._call("slave_write_state", position, state))

    def slave_state_check(self, position: int, expected_state: int, timeout: int) -> int:
        return int(self._call("slave_state_check", position, expected_state))

    # --- EthercatMaster ---------------------------------------------------------------

    def open(self, ifname: str) -> None:
        self._connect()
        self._call("open", ifname)

    def config_init(self) -> int:
        found = self._call("config_init")
        self._slaves = [
            RemoteSlave(
                self,
                i + 1,
                (s["man"], s["id"], s["rev"], s["name"], s["state"], s["al_status"]),
            )
            for i, s in enumerate(found)
        ]
        return len(self._slaves)

    @property
    def slaves(self) -> Sequence[EthercatSlave]:
        return self._slaves

    def config_map(self) -> int:
        result = self._call("config_map")
        for slave, (output_size, input_hex) in zip(self._slaves, result["slaves"], strict=True):
            slave.mapped(int(output_size), bytes.fromhex(input_hex))
        return int(result["total"])

    def send_processdata(self) -> int:
        """Send this cycle's frame (outputs of every slave); the reply is read by
        :meth:`receive_processdata`."""
        with self._lock:
            sock = self._sock
            if sock is None:
                raise EthercatMailboxError("the simulated master is not open")
            if self._frame_sent:  # the last frame's reply was never read: read it now
                self._read_frame(sock)
            frame = b"".join(
                [b"P", _TIME.pack(time.monotonic()), *(s.output for s in self._slaves)]
            )
            try:
                sock.send(frame)
            except BlockingIOError as exc:  # SO_SNDTIMEO: the simulator reads nothing
                self._drop()
                raise self._no_answer() from exc
            except OSError as exc:
                self._drop()
                raise EthercatMailboxError(f"lost the EP7047 simulator process: {exc!r}") from exc
            self._frame_sent = True
            return 1 if self._slaves else 0

    def receive_processdata(self, timeout: int = 2000) -> int:
        """The working counter of the frame sent last (0 when none was sent); see the
        module docstring for why ``timeout`` does not shorten the wait."""
        with self._lock:
            sock = self._sock
            if sock is None:
                raise EthercatMailboxError("the simulated master is not open")
            if not self._frame_sent:
                return 0
            return self._read_frame(sock)

    def _read_frame(self, sock: socket.socket) -> int:
        self._frame_sent = False
        try:
            reply = sock.recv(_MAX_MESSAGE)
        except (TimeoutError, BlockingIOError) as exc:  # BlockingIOError: SO_RCVTIMEO
            self._drop()
            raise self._no_answer() from exc
        except OSError as exc:
            self._drop()
            raise EthercatMailboxError(f"lost the EP7047 simulator process: {exc!r}") from exc
        if not reply:
            self._drop()
            raise EthercatMailboxError("the EP7047 simulator process closed the connection")
        if reply[0] == b"E"[0]:
            raise EthercatMailboxError(f"the simulated master refused the frame: {reply[1:]!r}")
        if reply[0] != _PROCESS:
            self._drop()
            raise EthercatMailboxError(f"unexpected reply from the simulator: {reply[:8]!r}")
        wkc: int = _WKC.unpack_from(reply, 1)[0]
        offset = 1 + _WKC.size
        for slave in self._slaves:
            size = len(slave.input)
            if size:
                slave.input = reply[offset : offset + size]
                offset += size
        return wkc

    def read_state(self) -> int:
        self._state = int(self._call("read_state"))
        return self._state

    def write_state(self) -> int:
        return int(self._call("write_state", self._state))

    def state_check(self, expected_state: int, timeout: int = 50000) -> int:
        self._state = int(self._call("state_check", expected_state))
        return self._state

    @property
    def state(self) -> int:
        return self._state

    @state.setter
    def state(self, value: int) -> None:
        self._state = value

    @property
    def expected_wkc(self) -> int:
        return 3 * len(self._slaves)

    def close(self) -> None:
        if self._sock is not None:
            with contextlib.suppress(EthercatMailboxError):
                self._call("close")
        self._drop()

    # --- simulation controls (not part of the driver's seam) -------------------------

    def record(self) -> dict[str, Any]:
        """The simulated slaves' state as the simulator sees it."""
        result: dict[str, Any] = self._call("record")
        return result

    def lose_frames(self, count: int) -> None:
        """The next ``count`` frames come back with working counter 0."""
        self._call("lose_frames", count)


def _error_from(error: dict[str, Any]) -> Exception:
    kind = error.get("type")
    if kind == "sdo":
        return EthercatSdoError(
            int(error["index"]), int(error["subindex"]), int(error["abort_code"]), error["desc"]
        )
    if kind == "unavailable":
        return EthercatUnavailableError(str(error["message"]))
    if kind == "value":
        return ValueError(str(error["message"]))
    return EthercatMailboxError(str(error.get("message", error)))


# --- the server: a SimulatedEthercatMaster in this process ----------------------------------


def ep7047_record(master: SimulatedEthercatMaster) -> dict[str, Any]:
    """What the simulated slaves are doing, for the record file and tests."""
    slaves = []
    for position in range(1, len(master._all) + 1):
        slave = master.slave(position)
        engine = slave.engine
        slaves.append(
            {
                "position": position,
                "al_state": slave.al_state,
                "busy": engine.busy,
                "enabled": bool(engine._enabled),
                "drive_state": engine.state.name,
                "velocity_counts_s": engine.velocity_counts_s,
                "actual_counts": engine.plant.actual_counts,
                "cycles": engine.cycles,
                "watchdog_tripped": slave.watchdog_tripped,
                "exchanges": len(slave.history),
            }
        )
    return {"slaves": slaves}


class _SlaveServer:
    """Serves one ``SimulatedEthercatMaster`` to one client at a time."""

    def __init__(self, master: SimulatedEthercatMaster, clock: _FrameClock) -> None:
        self.master = master
        self.clock = clock
        self.lock = threading.Lock()
        self.frames = 0

    def serve(self, listener: socket.socket, stopping: threading.Event) -> None:
        while not stopping.is_set():
            try:
                client, _ = listener.accept()
            except OSError:
                return  # the listener was closed: shutting down
            with client:
                try:
                    self._serve_client(client)
                except Exception:  # a bug must not take the simulator down for good
                    logger.exception("serving the EtherCAT master failed; waiting for a new one")

    def _serve_client(self, client: socket.socket) -> None:
        while True:
            try:
                message = client.recv(_MAX_MESSAGE)
            except OSError:
                return
            if not message:
                return  # the master closed the connection (or its process ended)
            with self.lock:
                if message[0] == _PROCESS:
                    try:
                        reply = self._process_data(message)
                    except Exception as exc:  # e.g. not open, not mapped: the master is told
                        reply = b"E" + str(exc).encode()
                elif message[0] == _SDO_READ:
                    reply = self._sdo_read(message)
                elif message[0] == _JSON:
                    reply = b"J" + json.dumps(self._json(json.loads(message[1:]))).encode()
                else:
                    reply = b"J" + json.dumps({"error": {"message": "bad request"}}).encode()
            try:
                client.send(reply)
            except OSError:
                return

    def _process_data(self, message: bytes) -> bytes:
        master = self.master
        self.clock.now = _TIME.unpack_from(message, 1)[0]
        offset = 1 + _TIME.size
        found: Sequence[SimulatedEp7047Slave] = master._found
        for slave in found:
            size = len(slave.output)
            if size:
                slave.output = message[offset : offset + size]
                offset += size
        master.send_processdata()
        wkc = master.receive_processdata()
        self.frames += 1
        return b"".join([b"P", _WKC.pack(wkc), *(slave.input for slave in found)])

    def _sdo_read(self, message: bytes) -> bytes:
        try:
            position, index, subindex, size = _SDO_READ_REQUEST.unpack_from(message, 1)
        except struct.error:
            return b"J" + json.dumps({"error": {"message": "bad request"}}).encode()
        found = self.master._found
        # The success path straight (100 reads a second in the demo), the error reply
        # built by _error_answer exactly as for the JSON request.
        try:
            if not 1 <= position <= len(found):
                raise KeyError(f"no slave at position {position}")
            data = bytes(found[position - 1].sdo_read(index, subindex, size))
        except Exception as exc:
            return b"J" + json.dumps(self._error_answer("sdo_read", exc)).encode()
        states = [_SLAVE_STATE.pack(s.state, s.al_status) for s in found]
        return b"".join([b"r", *states, data])

    def _json(self, request: dict[str, Any]) -> dict[str, Any]:
        op = str(request.get("op"))
        args = list(request.get("args", []))
        return self._answer(op, lambda: self._op(self.master, op, args))

    def _answer(self, op: str, run: Callable[[], Any]) -> dict[str, Any]:
        """``{"ok", "slaves"}`` with ``run()``'s result, or ``{"error", ...}``."""
        try:
            result = run()
        except Exception as exc:
            return self._error_answer(op, exc)
        return {"ok": result, "slaves": self._states()}

    def _error_answer(self, op: str, exc: Exception) -> dict[str, Any]:
        """The ``{"error", ...}`` reply for what a request raised."""
        if isinstance(exc, EthercatSdoError):
            error: dict[str, Any] = {
                "type": "sdo",
                "index": exc.index,
                "subindex": exc.subindex,
                "abort_code": exc.abort_code,
                "desc": exc.desc,
            }
            return {"error": error, "slaves": self._states()}
        if isinstance(exc, EthercatUnavailableError):
            return {"error": {"type": "unavailable", "message": str(exc)}}
        if isinstance(exc, EthercatMailboxError | KeyError | TypeError):
            return {"error": {"type": "mailbox", "message": str(exc)}, "slaves": self._states()}
        if isinstance(exc, ValueError):
            return {"error": {"type": "value", "message": str(exc)}, "slaves": self._states()}
        # e.g. a bug in the simulation: logged, and the master told
        logger.error("request %s failed", op, exc_info=exc)
        return {"error": {"type": "mailbox", "message": repr(exc)}, "slaves": self._states()}

    def _states(self) -> list[dict[str, int]]:
        return [{"state": s.state, "al_status": s.al_status} for s in self.master._found]

    def _op(self, master: SimulatedEthercatMaster, op: str, args: list[Any]) -> Any:
        if op == "open":
            master.open(str(args[0]))
            return None
        if op == "config_init":
            master.config_init()
            return [
                {
                    "man": s.man,
                    "id": s.id,
                    "rev": s.rev,
                    "name": s.name,
                    "state": s.state,
                    "al_status": s.al_status,
                }
                for s in master._found
            ]
        if op == "config_map":
            total = master.config_map()
            return {
                "total": total,
                "slaves": [[len(s.output), s.input.hex()] for s in master._found],
            }
        if op == "read_state":
            return master.read_state()
        if op == "write_state":
            master.state = int(args[0])
            return master.write_state()
        if op == "state_check":
            return master.state_check(int(args[0]))
        if op == "close":
            master.close()
            return None
        if op == "record":
            return ep7047_record(master)
        if op == "lose_frames":
            master.inject_lost_frames(int(args[0]))
            return None
        slave = master._found[int(args[0]) - 1]
        if op == "sdo_read":
            return slave.sdo_read(int(args[1]), int(args[2]), int(args[3])).hex()
        if op == "sdo_write":
            slave.sdo_write(int(args[1]), int(args[2]), bytes.fromhex(str(args[3])))
            return None
        if op == "slave_write_state":
            slave.state = int(args[1])
            return slave.write_state()
        if op == "slave_state_check":
            return slave.state_check(int(args[1]))
        raise KeyError(f"unknown request {op!r}")


@dataclass
class _FrameClock:
    """The simulation's clock: the send time of the frame being processed."""

    now: float = 0.0

    def __call__(self) -> float:
        return self.now


@dataclass(frozen=True, slots=True)
class Ep7047SimSpec:
    """What ``serve_ep7047`` runs: ``build(clock)`` makes the simulated master (module
    level or a ``functools.partial``: it is pickled into the child)."""

    build: Callable[[Callable[[], float]], SimulatedEthercatMaster]
    socket_path: str | None = None  # default: a fresh private directory in /tmp
    record_path: Path | None = None


def _demo_build(clock: Callable[[], float]) -> SimulatedEthercatMaster:
    return demo_master(clock=clock)


@contextlib.contextmanager
def _listening(socket_path: str | None) -> Iterator[tuple[socket.socket, str]]:
    private_dir: str | None = None
    if socket_path is None:
        # A directory of our own (mode 0700): only this user can reach the socket,
        # and the path stays far below the 108-byte limit of a Unix socket address.
        private_dir = tempfile.mkdtemp(prefix="servotune-ep7047-")
        socket_path = os.path.join(private_dir, "slave.sock")
    with contextlib.suppress(FileNotFoundError):
        os.unlink(socket_path)
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        listener.bind(socket_path)
        os.chmod(socket_path, 0o600)
        listener.listen(1)
        yield listener, socket_path
    finally:
        # shutdown() wakes a thread blocked in accept(); close() alone does not.
        with contextlib.suppress(OSError):
            listener.shutdown(socket.SHUT_RDWR)
        listener.close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(socket_path)
        if private_dir is not None:
            shutil.rmtree(private_dir, ignore_errors=True)


def serve_ep7047(spec: Ep7047SimSpec, conn: Connection) -> None:
    """Child: the simulated master on a socket until the lifeline says stop (or ends)."""
    # Normal priority (no real-time wire here), with more weight where granted: the
    # driver's cycle process waits for this simulator's answer each cycle, and the
    # simulated drive judges its watchdog by the frames' send times, so only a delay of
    # ~100 ms could trip it; nice -10 keeps the answer prompt under a CPU hog without
    # letting a bug here starve the host (a real-time process that spins does).
    logger.info("%s", raise_weight("the simulated EP7047-1032", SIM_NICE))
    clock = _FrameClock(time.monotonic())
    master = spec.build(clock)
    server = _SlaveServer(master, clock)
    stopping = threading.Event()
    started = time.monotonic()
    with _listening(spec.socket_path) as (listener, path):
        thread = threading.Thread(
            target=server.serve, args=(listener, stopping), name="ep7047-sim", daemon=True
        )
        thread.start()
        conn.send({"ready": {"path": ADDRESS_PREFIX + path, "pid": os.getpid()}})

        def record() -> dict[str, Any]:
            with server.lock:
                data = ep7047_record(master)
            return {
                "name": "ep7047",
                "pid": os.getpid(),
                "uptime_s": time.monotonic() - started,
                "frames": server.frames,
                "device": data,
            }

        def tick() -> None:
            if spec.record_path is not None:
                write_record(spec.record_path, record())

        try:
            serve_lifeline(conn, {"record": record}, tick=tick)
        finally:
            stopping.set()
    thread.join(2.0)


def run_ep7047_simulator(socket_path: str) -> None:
    """``servotune sim ep7047 --socket PATH``: serve the demo slave in the foreground
    until SIGINT/SIGTERM; prints the link address first (``sim:PATH``)."""
    import signal

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: stop.set())
    clock = _FrameClock(time.monotonic())
    server = _SlaveServer(demo_master(clock=clock), clock)
    with _listening(socket_path) as (listener, path):
        thread = threading.Thread(
            target=server.serve, args=(listener, stop), name="ep7047-sim", daemon=True
        )
        thread.start()
        print(ADDRESS_PREFIX + path, flush=True)
        while not stop.wait(0.5):
            if not thread.is_alive():
                raise RuntimeError("the EP7047 simulator thread stopped")
    thread.join(2.0)


def ep7047_sim_process(record_path: Path | None = None) -> SimProcess:
    """The demo's EP7047 child (start it, then open ``ready["path"]``)."""
    return SimProcess("ep7047", serve_ep7047, Ep7047SimSpec(_demo_build, None, record_path))
