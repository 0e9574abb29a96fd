"""Serve a simulated device on a real pseudo-terminal, with RS232 wire timing.

``PtySimulator`` owns the master side of a pty in one daemon thread. Host programs
open the slave side (``path``) like any serial port, e.g. with pyserial. Timing model
(8N1: 10 bit times per character, ``char_s = 10 / baud``):

* A host byte read from the master at wall time ``t`` has completely arrived at the
  device at ``max(t, previous arrival) + char_s``: back-to-back bytes queue up on the
  host-to-device wire. The device is advanced to that arrival time and receives the
  byte as soon as it is read (the arrival time is known then, so the device simply runs
  up to a character ahead of the wall clock; only the output is wall-timed).
* Every byte the device transmits finishes at ``max(previous finish, ready) + char_s``
  (``ready`` = the simulation time it was produced) and is written to the master fd at
  that moment, so the host sees it no earlier than a real line would deliver it.
* The device is also advanced at least every ``IDLE_ADVANCE_S``, so the physics keeps
  running and a banner after a power cycle comes out by itself.

Simulation time is the monotonic clock since ``start()`` (continuing where it stopped
after a restart). The thread sleeps in ``select.select`` with float timeouts until
the next due event: ``selectors``/``epoll`` round timeouts up to whole milliseconds,
which is two characters at 19200 baud.

Fault injection (``drop_echoes``, ``inject_garbage``, ``set_silent``, ``stall_host``,
``unplug``, ``replug``, ``power_cycle``) is thread-safe: each request is executed by the owner
thread between two events, so no other thread ever touches the fds or the device.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import queue
import random
import select
import signal
import sys
import threading
import time
import tty
from collections import deque
from collections.abc import Callable
from pathlib import Path
from types import FrameType, TracebackType
from typing import TypeVar, cast

from servotune.sim.base import PowerCyclable, SimDevice
from servotune.transports.ethercat_cycle import guard_realtime

logger = logging.getLogger(__name__)

T = TypeVar("T")

IDLE_ADVANCE_S = 0.005
_REQUEST_TIMEOUT_S = 5.0
_READ_CHUNK = 4096
_PR_SET_TIMERSLACK = 29  # linux/prctl.h
# Real-time priority of a simulator process where the OS grants it (root or
# CAP_SYS_NICE): below the EtherCAT cycle process (50) and its simulated wire slave
# (60), whose 2 ms deadlines are stricter than an RS232 character's.
SIM_RT_PRIORITY = 40
# Otherwise: this nice value (of its own scheduling group, or of the process).
SIM_NICE = -10


class _Request:
    """A function to run on the owner thread, and its outcome."""

    __slots__ = ("done", "error", "function", "result")

    def __init__(self, function: Callable[[], object]) -> None:
        self.function = function
        self.done = threading.Event()
        self.result: object = None
        self.error: BaseException | None = None


class HostStalls:
    """A host that runs its receive callbacks late, as the wire shows it (a fault for
    ``PtySimulator.stall_host``): after one CR in ``every`` (drawn from a generator
    seeded with ``seed``: the same bytes, the same stalls) the device's output is
    held back ``seconds`` (drawn in that range). With probability ``after_cr`` the
    hold starts at the CR's echo: the device acted on the CR on time, the host sees
    the echo and the reply late, exactly as if it had stalled after writing the CR
    (its stamps of that exchange are late). Otherwise it starts at the echo of the
    next byte received: the host's next CR leaves late (its stamps stay right)."""

    def __init__(
        self, every: int, seconds: tuple[float, float], *, after_cr: float = 0.7, seed: int = 0
    ) -> None:
        if every < 1 or not 0 <= seconds[0] <= seconds[1]:
            raise ValueError("every >= 1 and 0 <= seconds[0] <= seconds[1]")
        self.every = every
        self.seconds = seconds
        self.after_cr = after_cr
        self._random = random.Random(seed)
        self._before_next = 0.0
        self.after_cr_count = 0
        self.before_count = 0

    def delay(self, byte: int) -> float:
        """How long the output caused by receiving ``byte`` is held back."""
        if byte != 0x0D:
            held, self._before_next = self._before_next, 0.0
            return held
        if self._random.random() >= 1.0 / self.every:
            return 0.0
        pause = self._random.uniform(*self.seconds)
        if self._random.random() < self.after_cr:
            self.after_cr_count += 1
            return pause
        self.before_count += 1
        self._before_next = pause
        return 0.0


class PtySimulator:
    """A ``SimDevice`` on a pseudo-terminal (see the module docstring).

    ``baud``: the line rate the device is paced at; the caller takes it from the
    device (its ``LinkRules.default_baud``, or what the user asked for).
    ``link_path``: also maintain a symlink there pointing at the current slave device
    (replaced if it exists; removed on ``unplug`` and ``stop``). ``path`` is the name
    hosts should open: the link if given, otherwise the slave's ``/dev/pts/N``.
    """

    def __init__(self, device: SimDevice, *, baud: int, link_path: str | None = None) -> None:
        if baud <= 0:
            raise ValueError("baud must be positive")
        self.device = device
        self.baud = baud
        self.char_s = 10.0 / baud
        self.link_path = link_path
        self._master: int | None = None
        self._slave: int | None = None
        self._slave_name: str | None = None
        self._wake_r, self._wake_w = -1, -1
        self._thread: threading.Thread | None = None
        self._stopping = False
        self._requests: queue.SimpleQueue[_Request] = queue.SimpleQueue()
        self._epoch = 0.0
        self._sim_time_s = 0.0  # where simulation time resumes after a restart
        # Owner-thread state (also touched before start / after stop, single-threaded).
        self._outbound: deque[tuple[float, int]] = deque()  # (finish time, byte)
        self._last_arrival_s = 0.0
        self._line_free_s = 0.0  # when the device-to-host wire is free again
        self._drop_pending = 0
        self._garble: tuple[int, int] | None = None  # (line's first byte, its echo)
        self._host_line_start = True
        self._silent = False
        self._stalls: HostStalls | None = None
        self.overflow_bytes = 0  # device bytes lost because the host did not read

    # --- lifecycle ----------------------------------------------------------------------

    @property
    def path(self) -> str:
        """What a host opens: ``link_path`` or the slave's device name."""
        if self.link_path is not None:
            return self.link_path
        if self._slave_name is None:
            raise RuntimeError("the simulator has no pty (not started or unplugged)")
        return self._slave_name

    @property
    def slave_name(self) -> str | None:
        """The current ``/dev/pts/N`` (``None`` while unplugged or stopped)."""
        return self._slave_name

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        """Open the pty, create the link, start the owner thread."""
        if self._thread is not None:
            raise RuntimeError("already started")
        self._open_pty()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._stopping = False
        self._epoch = time.monotonic() - self._sim_time_s
        self._last_arrival_s = self._line_free_s = self._sim_time_s
        self._thread = threading.Thread(target=self._run, name="pty-simulator", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the thread and close the pty and the link. Idempotent."""
        thread = self._thread
        if thread is not None:
            self._stopping = True
            self._wake()
            thread.join()
            self._thread = None
            self._sim_time_s = self._now()
        self._close_pty()
        for fd in (self._wake_r, self._wake_w):
            if fd >= 0:
                os.close(fd)
        self._wake_r = self._wake_w = -1

    def __enter__(self) -> PtySimulator:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()

    # --- fault injection (any thread) ------------------------------------------------

    def drop_echoes(self, n: int) -> None:
        """Swallow the next ``n`` bytes the device transmits (echoes, replies)."""
        if n < 0:
            raise ValueError("n must not be negative")

        def request() -> None:
            self._drop_pending += n

        self._call(request)

    def garble_line_echo(self, first: int, instead: int) -> None:
        """The echo of the first byte of the next host line that begins with ``first``
        comes back as ``instead`` (one character of line noise, e.g. on a selection)."""

        def request() -> None:
            self._garble = (first, instead)

        self._call(request)

    def inject_garbage(self, data: bytes) -> None:
        """Put ``data`` on the device-to-host wire now, as line noise would."""
        payload = bytes(data)
        self._call(lambda: self._schedule_output(payload, self._now(), faults=False))

    def stall_host(self, stalls: HostStalls | None) -> None:
        """Inject host stalls (``HostStalls``) from now on; None ends them."""

        def request() -> None:
            self._stalls = stalls

        self._call(request)

    def set_silent(self, silent: bool) -> None:
        """A cut cable: while silent nothing flows either way; host bytes are lost."""

        def request() -> None:
            self._silent = silent
            if silent:
                self._outbound.clear()

        self._call(request)

    def unplug(self) -> None:
        """Close the pty (hosts see the port vanish) and remove the link."""
        self._call(self._close_pty)

    def replug(self) -> None:
        """A new pty (new slave name), link re-pointed; the device keeps its state."""

        def request() -> None:
            self._close_pty()
            self._open_pty()

        self._call(request)

    def power_cycle(self, address: int | None = None) -> None:
        """Power-cycle the device (or one module of it), if it supports that."""
        device = self.device
        if not isinstance(device, PowerCyclable):
            raise TypeError(f"{type(device).__name__} cannot be power-cycled")
        self._call(lambda: device.power_cycle(address))

    def call(self, function: Callable[[], T]) -> T:
        """Run ``function`` on the owner thread between two events and return its result
        (e.g. to read the device's state consistently from another thread)."""
        return self._call(function)

    # --- owner thread -----------------------------------------------------------------

    def _call(self, function: Callable[[], T]) -> T:
        """Run ``function`` on the owner thread (directly if the thread is not running)."""
        if not self.running or threading.current_thread() is self._thread:
            return function()
        request = _Request(function)
        self._requests.put(request)
        self._wake()
        if not request.done.wait(_REQUEST_TIMEOUT_S):
            raise TimeoutError("the simulator thread did not answer")
        if request.error is not None:
            raise request.error
        return cast(T, request.result)

    def _wake(self) -> None:
        # a full pipe already guarantees a wake-up
        with contextlib.suppress(BlockingIOError, OSError):
            os.write(self._wake_w, b"!")

    def _now(self) -> float:
        return time.monotonic() - self._epoch

    def _run(self) -> None:
        _reduce_timer_slack()
        try:
            self._loop()
        except Exception:
            # Must not die silently: hosts would only see a dead line. ``running`` turns
            # False, which run_pty_simulator() reports.
            logger.exception("pty simulator thread failed")

    def _loop(self) -> None:
        last_advance_s = -IDLE_ADVANCE_S
        # Timed wake-ups come late by a fairly constant amount, even with minimal timer
        # slack (docs/simulator.md). Without correction every byte would leave that
        # much after its wire time, a systematic modelling error of a fixed share of
        # every echoed character. So the thread wakes early by the measured median
        # lateness (a running estimate, capped at a quarter character) and writes
        # what is due within that margin: bytes leave at their wire time on average.
        lateness_s = 0.0
        max_early_s = self.char_s / 4
        while not self._stopping:
            now = self._now()
            # The wire-timed write first: it is what a waiting host is blocked on.
            self._flush_due(now + lateness_s)
            if not self._requests.empty():
                self._run_requests()
            if now - last_advance_s >= IDLE_ADVANCE_S:
                self._schedule_output(self.device.advance_to(now), now)
                last_advance_s = now
                self._flush_due(now)  # a banner may start right away
            deadline = last_advance_s + IDLE_ADVANCE_S
            wire_timed = bool(self._outbound) and self._outbound[0][0] - lateness_s < deadline
            if wire_timed:
                deadline = self._outbound[0][0] - lateness_s
            before = self._now()
            timeout = deadline - before
            readers = [self._wake_r] if self._master is None else [self._wake_r, self._master]
            ready, _, _ = select.select(readers, [], [], max(timeout, 0.0))
            if wire_timed and not ready and timeout > 0:
                late_s = self._now() - deadline
                lateness_s = min(max_early_s, max(0.0, lateness_s + 0.1 * (late_s - lateness_s)))
            if self._wake_r in ready:
                with contextlib.suppress(BlockingIOError):
                    os.read(self._wake_r, _READ_CHUNK)
            if self._master is not None and self._master in ready:
                self._read_host()

    def _run_requests(self) -> None:
        while True:
            try:
                request = self._requests.get_nowait()
            except queue.Empty:
                return
            try:
                request.result = request.function()
            except Exception as exc:  # handed to the caller, who re-raises it
                request.error = exc
            request.done.set()

    def _read_host(self) -> None:
        assert self._master is not None
        try:
            data = os.read(self._master, _READ_CHUNK)
        except BlockingIOError:
            return
        except OSError:
            # EIO would mean no slave is open; we hold one, so this is unexpected.
            logger.warning("reading the pty master failed", exc_info=True)
            return
        if self._silent:
            return  # the cable is cut: the bytes never reach the device
        t = self._now()
        arrival = self._last_arrival_s
        device = self.device
        for byte in data:
            arrival = (t if t > arrival else arrival) + self.char_s
            # The byte's arrival time is known now, so it is delivered at once in
            # simulation time (the device runs up to one character ahead of the wall
            # clock). Waiting for the arrival in wall time as well would add a timer
            # wake-up, with its latency, to every echo round trip.
            self._schedule_output(device.advance_to(arrival), arrival)
            held = self._stalls.delay(byte) if self._stalls is not None else 0.0
            out = device.receive(byte)
            garble = self._garble
            if garble and self._host_line_start and byte == garble[0] and out[:1] == bytes([byte]):
                out, self._garble = bytes([garble[1]]) + out[1:], None
            self._host_line_start = byte in (0x0D, 0x18)  # after CR or Ctrl-X
            self._schedule_output(out, arrival + held)
        self._last_arrival_s = arrival

    def _schedule_output(self, data: bytes, ready_s: float, *, faults: bool = True) -> None:
        if not data or self._silent:
            return
        if faults and self._drop_pending:
            dropped = min(self._drop_pending, len(data))
            self._drop_pending -= dropped
            data = data[dropped:]
        finish = self._line_free_s
        for byte in data:
            finish = (ready_s if ready_s > finish else finish) + self.char_s
            self._outbound.append((finish, byte))
        self._line_free_s = finish

    def _flush_due(self, now: float) -> None:
        outbound = self._outbound
        if not outbound or outbound[0][0] > now:
            return
        batch = bytearray()
        while outbound and outbound[0][0] <= now:
            batch.append(outbound.popleft()[1])
        if self._master is None:
            return  # unplugged: the bytes go nowhere
        try:
            written = os.write(self._master, batch)
        except BlockingIOError:
            written = 0
        except OSError:
            logger.warning("writing the pty master failed", exc_info=True)
            written = 0
        # The host is not reading and the pty buffer is full: a real UART overruns.
        self.overflow_bytes += len(batch) - written

    # --- pty handling -----------------------------------------------------------------

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        # Raw at once: no echo, no CR/LF translation, before any host can open it.
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self._slave_name = os.ttyname(slave)
        if self.link_path is not None:
            link = Path(self.link_path)
            temporary = link.with_name(f".{link.name}.{os.getpid()}.tmp")
            with contextlib.suppress(FileNotFoundError):
                temporary.unlink()
            temporary.symlink_to(self._slave_name)
            os.replace(temporary, link)  # atomic: hosts never see a missing link

    def _close_pty(self) -> None:
        if self.link_path is not None and self._slave_name is not None:
            link = Path(self.link_path)
            # only remove the link if it is still ours
            with contextlib.suppress(OSError):
                if link.is_symlink() and os.readlink(link) == self._slave_name:
                    link.unlink()
        for fd in (self._master, self._slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = None
        self._slave_name = None
        self._outbound.clear()


def _reduce_timer_slack() -> None:
    """Ask Linux to wake this thread on time (best effort, this thread only).

    By default the kernel may delay a timed wake-up by 50 us to batch timers; with two
    timed wake-ups per echoed character that alone costs ~10 % of the wire rate at
    19200 baud. Elsewhere (or if prctl fails) the default slack stays.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_TIMERSLACK, 1, 0, 0, 0)
    except (OSError, AttributeError):
        logger.debug("could not reduce the timer slack", exc_info=True)


def device_scheduling(what: str, *, own_session: bool = False) -> str:
    """Schedule this simulator process like the hardware it stands in for, which answers
    at once whatever the host does; returns what was granted (for the log). Call it
    from the process's main thread before it starts the simulator's thread (which
    inherits the policy).

    At normal priority a loaded host wakes a simulator late by more than a driver's
    character timeout now and then, and the link shows an error no wire would
    (figures: docs/simulator.md, "Under load"). So: real-time (SCHED_FIFO
    ``SIM_RT_PRIORITY``) with the spin guard armed (``guard_realtime``: a simulator
    that runs 0.2 s without blocking drops back to normal priority). Where that is
    refused: nice ``SIM_NICE`` where granted. ``own_session``: also a session - on
    Linux a scheduling group (autogroup) - of its own first, so that without any
    privilege it is at least not one more thread of a busy server's group (a child
    process that ignores SIGINT and ends with its lifeline loses nothing by leaving
    the terminal's session).
    """
    if not sys.platform.startswith("linux"):
        return f"{what}: default scheduling (not Linux)"
    group = ""
    if own_session:
        try:
            os.setsid()
            group = " in a scheduling group of its own"
        except OSError as exc:
            group = f" (no session of its own: {exc})"
    try:
        guard_realtime(what)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(SIM_RT_PRIORITY))
    except (OSError, AttributeError, ValueError) as refused:
        try:
            if own_session and group.startswith(" in"):
                with open("/proc/self/autogroup", "w", encoding="ascii") as autogroup:
                    autogroup.write(str(SIM_NICE))
            else:
                os.setpriority(os.PRIO_PROCESS, 0, SIM_NICE)
        except OSError as exc:
            return (
                f"{what}{group} at normal priority (real-time refused: {refused}; nice "
                f"{SIM_NICE} refused: {exc}): a loaded host may delay its answers"
            )
        return f"{what}{group} at nice {SIM_NICE} (real-time refused: {refused})"
    return f"{what}{group} at real-time priority (SCHED_FIFO {SIM_RT_PRIORITY})"


def run_pty_simulator(device: SimDevice, *, baud: int, link_path: str | None = None) -> None:
    """Serve ``device`` on a pty until SIGINT or SIGTERM; call from the main thread.

    The first line on stdout is the path to open (flushed at once, for scripts that
    start the simulator as a subprocess). Cleans up the pty and the link on exit.
    """
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    logger.info("%s", device_scheduling("the simulated device"))
    simulator = PtySimulator(device, baud=baud, link_path=link_path)
    try:
        simulator.start()
        print(simulator.path, flush=True)
        while not stop.wait(0.5):
            if not simulator.running:
                raise RuntimeError("the simulator thread stopped")
    finally:
        simulator.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
