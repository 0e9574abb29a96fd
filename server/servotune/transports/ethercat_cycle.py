"""The EtherCAT process-data cycle in a process of its own: a cycle a loaded host cannot
stall.

``CycleProcessMaster`` is the driver's ``EthercatMaster`` (pysoem's names) over a child
process that owns the real master (``PysoemMaster`` on a NIC, or any master a
picklable factory builds, e.g. the demo's ``ProcessMaster`` behind the seam). Why: in
the server, the driver's cycle thread shares one interpreter lock with the event loop,
the hub, the websockets and the other links; under load it missed the slave's 100 ms
watchdog (the demo's EP7047 lost its process data 64 times in 23 minutes). In the child
nothing else runs: it sends the latest outputs every period to an absolute deadline at
real-time priority (SCHED_FIFO where the OS grants it; the reason is logged and shown
where it does not), whatever the server does.

Channels (``multiprocessing`` pipes between this process and its own child):

* requests (``rpc``): bring-up, state machine, SDO transfers; answered one at a time,
  run by the child between two cycles;
* the outputs (``cyc``, parent -> child): the parent sends them with a sequence number;
  the child takes the latest at each cycle;
* the latest cycle (shared memory: a file in /dev/shm mapped by both and unlinked at
  once, so nothing is left behind however the processes end): a seqlock-protected record
  of the last exchange - its sequence number, send time, working counter, the outputs'
  sequence number it carried, the lost exchanges so far, the send time of the last good
  one, and the inputs - plus one byte per cycle on a wake-up pipe (non-blocking on the
  child's side). A server that was stalled reads the *latest* cycle when it runs again,
  never a backlog of old ones, and the child never waits for it.

Semantics for the driver: the first ``send_processdata`` after ``config_map`` starts the
cycle (in SAFE-OP: the slave's watchdog is served from the moment it enters OP, however
long this process takes to call again); ``send_processdata`` hands the outputs over;
``receive_processdata`` waits for the first cycle that carried them and returns its
working counter and inputs (so a handshake that waits for the drive's answer to an
output still sees it). The driver's own loop does not sleep (``paced``): it runs at the
child's pace. ``last_good_t()`` is the send time of the child's last good exchange: the
driver judges the slave's watchdog by the wire, not by its own thread.

Safety (decisions): the child lives as long as this process (its end of the request
pipe closes when this process dies, however it dies: the child then sends all-zero
outputs for a few cycles - Enable off - asks for INIT and exits). A server that is
alive but sends nothing for ``SERVER_SILENCE_S`` (10 s; a first choice of 2 s was
reached once in a 30-minute soak at load 16-20 with a CPU hog: the server's thread can
be held that long on a starved host, and stopping the drive then is the false trip this
process exists to avoid) is taken as hung: the child stops the cycle, so the slave's own
watchdog stops the drive, and the driver finds it in SAFE-OP + ERROR when it runs again.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import mmap
import multiprocessing
import os
import resource
import select
import signal
import struct
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any, Final

from servotune.transports.ethercat import (
    INIT_STATE,
    EthercatError,
    EthercatMailboxError,
    EthercatMaster,
    EthercatSdoError,
    EthercatSlave,
    EthercatUnavailableError,
    RemoteSlave,
)

logger = logging.getLogger(__name__)

SERVER_SILENCE_S: Final = 10.0
SILENCE_LOGGED_S: Final = 0.5  # a silence this long is logged when it ends
REQUEST_HELD_LOGGED_S: Final = 0.02  # a request that holds the cycle this long is logged
LATE_LOGGED_S: Final = 0.02  # an exchange this late (the host held the cycle) is logged
LOST_RUN_LOGGED: Final = 5  # lost exchanges in a row this many or more are logged
REQUEST_TIMEOUT_S: Final = 5.0
CYCLE_REPLY_TIMEOUT_S: Final = 1.0
START_TIMEOUT_S: Final = 30.0
RT_PRIORITY: Final = 50
# The spin guard (guard_realtime): CPU time at real-time priority without one blocking
# call. A cycle blocks every period (its CPU is ~0.1 ms of each); 0.2 s of it is a bug.
RT_SPIN_LIMIT_S: Final = 0.2
RT_KILL_LIMIT_S: Final = 2.0
# The shared latest cycle: seqlock counter (odd while written), seq, sent_t, wkc,
# out_seq, lost, last_good_t, inputs length; then the inputs.
_RECORD = struct.Struct("<QQdiQQdI")
_INPUTS_MAX: Final = 1024
_SHARED_SIZE: Final = _RECORD.size + _INPUTS_MAX
_OUTPUTS = struct.Struct("<Q")  # out_seq, then the outputs of each slave
_PR_SET_NAME: Final = 15
# Requests whose answer ends with every slave's (state, AL status) after the call.
_REPORTS_STATES: Final = frozenset(
    {"read_state", "write_state", "state_check", "sdo_read", "sdo_write",
     "slave_write_state", "slave_state_check"}
)  # fmt: skip


def raise_priority(what: str, priority: int = RT_PRIORITY) -> tuple[bool, str]:
    """SCHED_FIFO ``priority`` for the calling thread (and threads it starts later), with
    the spin guard (:func:`guard_realtime`) armed first; (granted, what was granted or
    why not - for the log and the user). Call it from the main thread (the guard's
    signal handler is installed there)."""
    try:
        guard_realtime(what)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError, ValueError) as exc:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, -10)
        except OSError:
            return False, (
                f"{what} runs at normal priority: real-time scheduling was refused ({exc}); "
                "run servotune as root or give it CAP_SYS_NICE (`sudo setcap "
                "cap_net_raw,cap_net_admin,cap_sys_nice+ep $(readlink -f .venv/bin/python)`) "
                "so that a loaded host cannot delay the process data"
            )
        return False, f"{what} at nice -10: real-time scheduling was refused ({exc})"
    text = f"{what} at real-time priority (SCHED_FIFO {priority})"
    problem = lock_memory()
    if problem is not None:
        text += f"; its memory is not locked ({problem}): a page fault may still delay it"
    runtime_us = rt_runtime_us()
    if runtime_us is not None and runtime_us < 0:
        text += (
            "; the kernel's real-time throttling is off (sched_rt_runtime_us = -1): only "
            "the spin guard stands between a stuck real-time process and the host"
        )
    return True, text


_MCL_CURRENT: Final = 1  # sys/mman.h


def lock_memory() -> str | None:
    """Lock every page this process has mapped now (its interpreter, libraries, heap)
    into RAM: a real-time loop must not wait for a page to be read back from disk
    after the kernel dropped it from the page cache on a busy host (the usual first
    step of a real-time process, beside its priority). Only the current pages: locking
    future ones too would make a later allocation fail where the lock limit is low.
    None when done, else why not."""
    if not sys.platform.startswith("linux"):
        return "not Linux"
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.mlockall(_MCL_CURRENT) != 0:
            return (
                os.strerror(ctypes.get_errno()) + " (needs CAP_IPC_LOCK or a higher RLIMIT_MEMLOCK)"
            )
    except (OSError, AttributeError) as exc:
        return str(exc)
    return None


def raise_weight(what: str, nice: int) -> str:
    """A larger share of the CPU at normal priority (nice ``nice``) for this process;
    what was granted or why not."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    except OSError as exc:
        return f"{what} at normal priority ({exc}: nice {nice} needs CAP_SYS_NICE)"
    return f"{what} at normal priority, nice {nice}"


def rt_runtime_us() -> int | None:
    """The kernel's real-time throttling budget per period (µs; -1: off; None: unknown)."""
    try:
        with open("/proc/sys/kernel/sched_rt_runtime_us") as file:
            return int(file.read())
    except (OSError, ValueError):
        return None


def guard_realtime(what: str) -> None:
    """Arm the kernel's guard against a real-time process that spins: RLIMIT_RTTIME.

    Every loop of ours at real-time priority sleeps until its deadline (a frame, a
    period, a request), so none of them runs ``RT_SPIN_LIMIT_S`` without blocking; one
    that does is a bug that starves every normal task on its core (the server, the
    simulators, the kernel's own workers - a ``workqueue lockup`` with pty work stuck).
    Then the kernel sends SIGXCPU: this process drops every thread to normal priority
    and says so; a spin inside C code that never lets the handler run is ended by
    SIGKILL at ``RT_KILL_LIMIT_S`` (the drive's own watchdog then stops the motor).
    """
    soft_us, hard_us = int(RT_SPIN_LIMIT_S * 1e6), int(RT_KILL_LIMIT_S * 1e6)

    def demote(signum: int, frame: object) -> None:
        drop_realtime()
        logger.error(
            "%s ran %.1f s at real-time priority without sleeping (a busy loop): it now "
            "runs at normal priority",
            what,
            RT_SPIN_LIMIT_S,
        )

    signal.signal(signal.SIGXCPU, demote)
    _, hard = resource.getrlimit(resource.RLIMIT_RTTIME)
    if hard != resource.RLIM_INFINITY:
        hard_us = min(hard_us, hard)
    resource.setrlimit(resource.RLIMIT_RTTIME, (min(soft_us, hard_us), hard_us))


def drop_realtime() -> None:
    """Every thread of this process back to normal priority (SCHED_OTHER)."""
    with contextlib.suppress(OSError):
        for tid in os.listdir("/proc/self/task"):
            with contextlib.suppress(OSError, ValueError):
                os.sched_setscheduler(int(tid), os.SCHED_OTHER, os.sched_param(0))


def set_process_name(name: str) -> None:
    """Best effort: ``/proc/<pid>/comm`` (15 characters) on Linux."""
    if not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_NAME, ctypes.c_char_p(name.encode()[:15]), 0, 0, 0)


# --- the child ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class CycleSpec:
    """What the child runs: ``factory()`` builds the master (module level or a
    ``functools.partial``: it is pickled); the period; the process name."""

    factory: Callable[[], EthercatMaster]
    cycle_s: float
    name: str = "ec-cycle"
    realtime: bool = True


def _error_reply(exc: Exception) -> tuple[str, ...]:
    if isinstance(exc, EthercatSdoError):
        return ("sdo", str(exc.index), str(exc.subindex), str(exc.abort_code), exc.desc)
    if isinstance(exc, EthercatUnavailableError):
        return ("unavailable", str(exc))
    if isinstance(exc, ValueError):
        return ("value", str(exc))
    return ("mailbox", f"{exc}" if isinstance(exc, EthercatError) else repr(exc))


def _raise_from(reply: tuple[str, ...]) -> None:
    kind = reply[0]
    if kind == "sdo":
        raise EthercatSdoError(int(reply[1]), int(reply[2]), int(reply[3]), reply[4])
    if kind == "unavailable":
        raise EthercatUnavailableError(reply[1])
    if kind == "value":
        raise ValueError(reply[1])
    raise EthercatMailboxError(reply[1])


def _slave_info(slave: EthercatSlave) -> tuple[int, int, int, str, int, int]:
    return (slave.man, slave.id, slave.rev, slave.name, slave.state, slave.al_status)


class _Child:
    def __init__(
        self, spec: CycleSpec, rpc: Connection, cyc: Connection, shared: mmap.mmap, wake: int
    ) -> None:
        self.spec = spec
        self.rpc = rpc
        self.cyc = cyc
        self.shared = shared
        self.wake = wake
        self.lock_count = 0
        self.master: EthercatMaster | None = None
        self.cyclic = False
        self.outputs: list[bytes] = []
        self.out_seq = 0
        self.seq = 0
        self.lost = 0
        self.lost_run = 0
        self.last_good_t = 0.0
        self.heard_t = time.monotonic()

    def run(self) -> None:
        period = self.spec.cycle_s
        deadline = time.monotonic()
        while True:
            if self.cyclic:
                if time.monotonic() - self.heard_t > SERVER_SILENCE_S:
                    logger.error(
                        "the server sent nothing for %.1f s: the cycle stops, the drive's "
                        "watchdog stops the motor",
                        SERVER_SILENCE_S,
                    )
                    self.cyclic = False
                    continue
                self._take_outputs()
                late = time.monotonic() - deadline
                if late > LATE_LOGGED_S:
                    logger.warning(
                        "an exchange went out %.0f ms late (the host held the cycle)", late * 1000
                    )
                self._exchange()
                deadline += period
                delay = deadline - time.monotonic()
                if delay < -period:
                    deadline = time.monotonic()  # more than a period late: re-anchor
                # Requests in the rest of the period (at least one, so none starves).
                served = False
                while True:
                    remaining = deadline - time.monotonic()
                    if served and remaining <= 0:
                        break
                    if not self.rpc.poll(max(remaining, 0)):
                        break
                    if not self._serve_one():
                        return
                    served = True
                remaining = deadline - time.monotonic()
                if remaining > 0:
                    time.sleep(remaining)
            else:
                if self.rpc.poll(0.05) and not self._serve_one():
                    return
                deadline = time.monotonic()

    def _take_outputs(self) -> None:
        cyc = self.cyc
        with contextlib.suppress(OSError, EOFError):
            while cyc.poll(0):
                message = cyc.recv_bytes()
                self.out_seq = _OUTPUTS.unpack_from(message)[0]
                self._heard()
                self._split_outputs(message[_OUTPUTS.size :])

    def _heard(self) -> None:
        now = time.monotonic()
        silence = now - self.heard_t
        if silence > SILENCE_LOGGED_S and self.cyclic:
            logger.warning("the server was silent for %.2f s (the cycle went on)", silence)
        self.heard_t = now

    def _split_outputs(self, data: bytes) -> None:
        master = self.master
        if master is None:
            return
        offset = 0
        for slave in master.slaves:
            size = len(slave.output)
            if size:
                slave.output = data[offset : offset + size]
                offset += size

    def _exchange(self) -> None:
        master = self.master
        if master is None:
            return
        sent_t = time.monotonic()
        try:
            master.send_processdata()
            wkc = master.receive_processdata(min(2000, int(self.spec.cycle_s * 1e6)))
        except (EthercatError, OSError) as exc:
            logger.warning("exchange failed: %s", exc)
            wkc = -1
        self.seq += 1
        if wkc == master.expected_wkc:
            if self.lost_run >= LOST_RUN_LOGGED:
                logger.warning(
                    "%d exchanges in a row got no valid answer (%.0f ms without good process data)",
                    self.lost_run,
                    (sent_t - self.last_good_t) * 1000,
                )
            self.lost_run = 0
            self.last_good_t = sent_t
        else:
            self.lost += 1
            self.lost_run += 1
        inputs = b"".join(slave.input for slave in master.slaves)[:_INPUTS_MAX]
        # Seqlock: odd while writing; a reader retries until it reads one even value.
        self.lock_count += 1
        struct.pack_into("<Q", self.shared, 0, self.lock_count)
        self.shared[_RECORD.size : _RECORD.size + len(inputs)] = inputs
        struct.pack_into(
            "<QdiQQdI", self.shared, 8, self.seq, sent_t, wkc, self.out_seq, self.lost,
            self.last_good_t, len(inputs),
        )  # fmt: skip
        self.lock_count += 1
        struct.pack_into("<Q", self.shared, 0, self.lock_count)
        with contextlib.suppress(BlockingIOError, OSError):  # full: the server is behind
            os.write(self.wake, b"\x01")

    def _serve_one(self) -> bool:
        try:
            request = self.rpc.recv()
        except (EOFError, OSError):
            self._server_gone()
            return False
        self._heard()
        op, args = request[0], request[1:]
        if op == "stop":
            self._close()
            self.rpc.send(("ok", None))
            return False
        started = time.monotonic()
        try:
            result = self._do(op, args)
        except Exception as exc:
            reply: tuple[Any, ...] = ("error", *_error_reply(exc))
        else:
            reply = ("ok", result)
        held_s = time.monotonic() - started
        if self.cyclic and held_s > REQUEST_HELD_LOGGED_S:
            # Between two cycles: no process data went out meanwhile.
            logger.warning("%s held the cycle for %.0f ms", op, held_s * 1000)
        try:
            self.rpc.send(reply)
        except OSError:
            self._server_gone()
            return False
        return True

    def _do(self, op: str, args: tuple[Any, ...]) -> Any:
        if op == "open":
            self._close()
            self.master = self.spec.factory()
            self.master.open(str(args[0]))
            if self.spec.realtime:
                lock_memory()  # again: the master's library is mapped only now
            return None
        master = self.master
        if master is None:
            raise EthercatMailboxError("the EtherCAT master is not open")
        if op == "config_init":
            self.cyclic = False
            found = master.config_init()
            return found, [_slave_info(s) for s in master.slaves]
        if op == "config_map":
            total = master.config_map()
            return total, [(len(s.output), bytes(s.input)) for s in master.slaves]
        if op == "start_cyclic":
            self.cyclic = True
            self.last_good_t = time.monotonic()
            self.heard_t = time.monotonic()
            return None
        if op == "read_state":
            return master.read_state(), self._states()
        if op == "write_state":
            master.state = int(args[0])
            return master.write_state(), self._states()
        if op == "state_check":
            return master.state_check(int(args[0]), int(args[1])), self._states()
        if op == "expected_wkc":
            return master.expected_wkc
        slave = master.slaves[int(args[0]) - 1]
        if op == "sdo_read":
            return bytes(slave.sdo_read(int(args[1]), int(args[2]), int(args[3]))), self._states()
        if op == "sdo_write":
            slave.sdo_write(int(args[1]), int(args[2]), bytes(args[3]))
            return None, self._states()
        if op == "slave_write_state":
            slave.state = int(args[1])
            return slave.write_state(), self._states()
        if op == "slave_state_check":
            return slave.state_check(int(args[1]), int(args[2])), self._states()
        if op == "close":
            self._close()
            return None
        raise EthercatMailboxError(f"unknown request {op!r}")

    def _states(self) -> list[tuple[int, int]]:
        master = self.master
        return [] if master is None else [(s.state, s.al_status) for s in master.slaves]

    def _close(self) -> None:
        self.cyclic = False
        master, self.master = self.master, None
        if master is not None:
            with contextlib.suppress(Exception):
                master.close()

    def _server_gone(self) -> None:
        """The server died: all-zero outputs (Enable off) for a few cycles, INIT, exit."""
        master = self.master
        if master is not None and self.cyclic:
            with contextlib.suppress(Exception):
                for slave in master.slaves:
                    slave.output = bytes(len(slave.output))
                for _ in range(5):
                    master.send_processdata()
                    master.receive_processdata(2000)
                    time.sleep(self.spec.cycle_s)
                master.state = INIT_STATE
                master.write_state()
        self._close()


def _child_main(
    spec: CycleSpec, rpc: Connection, cyc: Connection, shared_path: str, wake: Connection
) -> None:
    set_process_name(spec.name)
    # Ctrl-C and a service manager's SIGTERM reach the whole process group: the server
    # ramps the axis down through this process first, then stops it (or its death
    # closes the request pipe, and the child makes the outputs safe by itself).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    logging.basicConfig(
        level=logging.INFO, format=f"%(asctime)s %(levelname)s {spec.name}: %(message)s"
    )
    fd = os.open(shared_path, os.O_RDWR)
    try:
        shared = mmap.mmap(fd, _SHARED_SIZE)
    finally:
        os.close(fd)
    wake_fd = wake.fileno()
    os.set_blocking(wake_fd, False)  # never wait for the server
    granted, text = raise_priority("the EtherCAT cycle") if spec.realtime else (False, "")
    rpc.send(("ready", os.getpid(), granted, text))
    _Child(spec, rpc, cyc, shared, wake_fd).run()


# --- the parent: the driver's EthercatMaster -------------------------------------------------


class CycleProcessMaster:
    """The driver's ``EthercatMaster`` over a cycle process (see the module docstring).

    ``factory`` builds the real master in the child (picklable). The child is started by
    ``open`` and ended by :meth:`shutdown` (or with this process).
    """

    paced = True

    def __init__(
        self,
        factory: Callable[[], EthercatMaster],
        *,
        cycle_s: float = 0.002,
        name: str = "ec-cycle",
        realtime: bool = True,
    ) -> None:
        self._spec = CycleSpec(factory, cycle_s, name, realtime)
        self._process: multiprocessing.process.BaseProcess | None = None
        self._rpc: Connection | None = None
        self._cyc: Connection | None = None
        self._wake: Connection | None = None
        self._shared: mmap.mmap | None = None
        self._seen_seq = 0
        self._lock = threading.Lock()
        self._slaves: list[RemoteSlave] = []
        self._state = INIT_STATE
        self._expected_wkc = 0
        self._out_seq = 0
        self._cyclic = False  # the child runs the cycle; set by the first send in OP
        self._last_good_t: float | None = None
        self._lost = 0
        self.pid: int | None = None
        self.priority_granted = False
        self.priority_text = ""

    # --- the child -----------------------------------------------------------------------

    def _start(self) -> None:
        if self._process is not None and self._process.is_alive():
            return
        self._reap()
        context = multiprocessing.get_context("spawn")
        rpc_parent, rpc_child = context.Pipe()
        cyc_parent, cyc_child = context.Pipe()
        wake_parent, wake_child = context.Pipe(duplex=False)
        # The shared latest cycle: a file in /dev/shm (RAM), unlinked once both map it.
        directory = "/dev/shm" if os.path.isdir("/dev/shm") else None
        fd, shared_path = tempfile.mkstemp(prefix="servotune-ec-", dir=directory)
        try:
            os.ftruncate(fd, _SHARED_SIZE)
            self._shared = mmap.mmap(fd, _SHARED_SIZE)
        finally:
            os.close(fd)
        process = context.Process(
            target=_child_main,
            args=(self._spec, rpc_child, cyc_child, shared_path, wake_child),
            name=self._spec.name,
            daemon=True,
        )
        try:
            process.start()
        finally:
            rpc_child.close()
            cyc_child.close()
            wake_child.close()
        self._process, self._rpc, self._cyc, self._wake = (
            process, rpc_parent, cyc_parent, wake_parent
        )  # fmt: skip
        self._seen_seq = 0
        try:
            ready = rpc_parent.poll(START_TIMEOUT_S)
        finally:
            os.unlink(shared_path)  # mapped by the child by now, or it failed to start
        if not ready:
            self._reap()
            raise EthercatUnavailableError(
                f"the EtherCAT cycle process did not start within {START_TIMEOUT_S:g} s"
            )
        try:
            _, pid, granted, text = rpc_parent.recv()
        except (EOFError, OSError) as exc:
            self._reap()
            raise EthercatUnavailableError(f"the EtherCAT cycle process ended: {exc!r}") from exc
        self.pid, self.priority_granted, self.priority_text = pid, granted, text
        if text:
            (logger.info if granted else logger.warning)("%s", text)

    def _reap(self) -> None:
        process, self._process = self._process, None
        for conn in (self._rpc, self._cyc, self._wake):
            if conn is not None:
                conn.close()
        self._rpc = self._cyc = self._wake = None
        if self._shared is not None:
            self._shared.close()
            self._shared = None
        if process is not None:
            process.join(2.0)
            if process.is_alive():
                process.kill()
                process.join(2.0)
            process.close()

    def shutdown(self) -> None:
        """End the child (the link is done with this master)."""
        with self._lock:
            rpc = self._rpc
            if rpc is not None and self._process is not None and self._process.is_alive():
                with contextlib.suppress(OSError, EOFError):
                    rpc.send(("stop",))
                    if rpc.poll(2.0):
                        rpc.recv()
            self._reap()

    def _call(self, op: str, *args: Any) -> Any:
        with self._lock:
            rpc = self._rpc
            if rpc is None or self._process is None or not self._process.is_alive():
                raise EthercatMailboxError("the EtherCAT cycle process is not running")
            try:
                rpc.send((op, *args))
                if not rpc.poll(REQUEST_TIMEOUT_S):
                    raise EthercatMailboxError(
                        f"the EtherCAT cycle process did not answer {op} within "
                        f"{REQUEST_TIMEOUT_S:g} s"
                    )
                reply = rpc.recv()
            except (EOFError, OSError) as exc:
                raise EthercatMailboxError(f"lost the EtherCAT cycle process: {exc!r}") from exc
        if reply[0] == "error":
            _raise_from(reply[1:])
        result = reply[1]
        if op in _REPORTS_STATES:
            self._update_states(result[-1])
            return result[0]
        return result

    def _update_states(self, states: Sequence[tuple[int, int]]) -> None:
        for slave, (state, al_status) in zip(self._slaves, states, strict=False):
            slave.reported(state, al_status)

    # --- EthercatMaster -----------------------------------------------------------------

    def open(self, ifname: str) -> None:
        self._start()
        self._call("open", ifname)

    def config_init(self) -> int:
        found, infos = self._call("config_init")
        self._cyclic = False
        self._slaves = [RemoteSlave(self, i + 1, info) for i, info in enumerate(infos)]
        return int(found)

    @property
    def slaves(self) -> Sequence[EthercatSlave]:
        return self._slaves

    def config_map(self) -> int:
        total, images = self._call("config_map")
        for slave, (output_size, inputs) in zip(self._slaves, images, strict=True):
            slave.mapped(output_size, inputs)
        self._expected_wkc = int(self._call("expected_wkc"))
        return int(total)

    def _outputs(self) -> bytes:
        return b"".join(s.output for s in self._slaves)

    def send_processdata(self) -> int:
        """Hand the outputs to the cycle; the first call after ``config_map`` starts it
        (in SAFE-OP, so that the slave's watchdog is served from the moment it enters
        OP, whatever this process does between its request for OP and its next call)."""
        outputs = self._outputs()
        if not self._cyclic:
            self._call("start_cyclic")
            self._cyclic = True
        if self._cyc is None:
            raise EthercatMailboxError("the EtherCAT cycle process is not running")
        self._out_seq += 1
        try:
            self._cyc.send_bytes(_OUTPUTS.pack(self._out_seq) + outputs)
        except OSError as exc:
            raise EthercatMailboxError(f"lost the EtherCAT cycle process: {exc!r}") from exc
        return 1

    def receive_processdata(self, timeout: int = 2000) -> int:
        """The working counter of the first cycle that carried the outputs handed over
        last (0 before the cycle runs)."""
        if not self._cyclic:
            return 0
        return self._await_cycle()

    def _await_cycle(self) -> int:
        wake = self._wake
        if wake is None or self._shared is None:
            raise EthercatMailboxError("the EtherCAT cycle process is not running")
        deadline = time.monotonic() + CYCLE_REPLY_TIMEOUT_S
        while True:
            wkc, out_seq = self._read_latest()
            if out_seq >= self._out_seq:
                return wkc
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise EthercatMailboxError(
                    f"the EtherCAT cycle process sent no cycle for {CYCLE_REPLY_TIMEOUT_S:g} s"
                )
            readable, _, _ = select.select([wake], [], [], remaining)
            if readable:
                try:
                    os.read(wake.fileno(), 4096)  # the wake-ups so far: the latest counts
                except OSError as exc:
                    raise EthercatMailboxError(f"lost the EtherCAT cycle process: {exc!r}") from exc

    def _read_latest(self) -> tuple[int, int]:
        """The latest cycle from the shared record (seqlock): (wkc, outputs' seq); the
        inputs, the last good send time and the lost count are taken over."""
        shared = self._shared
        assert shared is not None
        for _ in range(10_000):
            before = struct.unpack_from("<Q", shared, 0)[0]
            if before & 1:
                continue  # the child is writing it (a few microseconds)
            _, seq, _, wkc, out_seq, lost, last_good_t, size = _RECORD.unpack_from(shared, 0)
            inputs = bytes(shared[_RECORD.size : _RECORD.size + size])
            if struct.unpack_from("<Q", shared, 0)[0] == before:
                break
        else:  # stopped while writing (SIGSTOP): nothing new until it runs again
            return -1, 0
        if seq != self._seen_seq:
            self._seen_seq = seq
            self._set_inputs(inputs)
            self._lost = lost
            if last_good_t:
                self._last_good_t = last_good_t
        return wkc, out_seq

    def _set_inputs(self, data: bytes) -> None:
        offset = 0
        for slave in self._slaves:
            size = len(slave.input)
            slave.input = data[offset : offset + size]
            offset += size

    def last_good_t(self) -> float | None:
        """The send time of the cycle's last good exchange, as of its latest cycle (None
        before the cycle runs)."""
        if self._shared is not None and self._cyclic:
            self._read_latest()
        return self._last_good_t

    @property
    def cycle_lost(self) -> int:
        """Exchanges of the cycle process without the expected working counter."""
        return self._lost

    # --- SlaveCalls (for RemoteSlave) ----------------------------------------------

    def slave_sdo_read(self, position: int, index: int, subindex: int, size: int) -> bytes:
        data: bytes = self._call("sdo_read", position, index, subindex, size)
        return data

    def slave_sdo_write(self, position: int, index: int, subindex: int, data: bytes) -> None:
        self._call("sdo_write", position, index, subindex, data)

    def slave_write_state(self, position: int, state: int) -> int:
        return int(self._call("slave_write_state", position, state))

    def slave_state_check(self, position: int, expected_state: int, timeout: int) -> int:
        return int(self._call("slave_state_check", position, expected_state, timeout))

    def read_state(self) -> int:
        return int(self._call("read_state"))

    def write_state(self) -> int:
        return int(self._call("write_state", self._state))

    def state_check(self, expected_state: int, timeout: int = 50000) -> int:
        return int(self._call("state_check", expected_state, timeout))

    @property
    def state(self) -> int:
        return self._state

    @state.setter
    def state(self, value: int) -> None:
        self._state = value

    @property
    def expected_wkc(self) -> int:
        return self._expected_wkc

    def close(self) -> None:
        self._cyclic = False
        self._state = INIT_STATE
        if self._process is not None and self._process.is_alive():
            with contextlib.suppress(EthercatError):
                self._call("close")
