"""Simulators in processes of their own (what the demo runs).

Why: a simulated device that runs inside the server shares one interpreter (the GIL)
with the server's event loop and its driver threads; under load the two starve each
other and the links look broken when only the host is busy. In a child process the
simulator has its own interpreter and the kernel schedules it like the far end of a
real cable.

``SimProcess`` starts one child with the ``spawn`` method (a fresh interpreter: nothing
of the server's state, threads or open files is inherited) and keeps a *lifeline*
pipe to it:

* the child reports ``ready`` with what the host must open (a pty path, or the
  ``sim:`` address of the EtherCAT simulator) and then serves small requests on the
  pipe (``stop``, ``record``, fault injection; a serial device's own methods with
  ``device``, for measurements that watch the device itself; any attribute or method
  of the device or of its ``PtySimulator`` with ``inspect``, which :class:`Remote`
  wraps so that a test reads the device as if it ran in its own process);
* the child watches the pipe: when the parent ends for whatever reason - a normal
  shutdown, a crash, SIGKILL - its end of the pipe is closed by the kernel, the child
  reads end-of-file and shuts down (closes its pty or socket) within
  ``LIFELINE_POLL_S``. No orphan is left behind;
* the child ignores SIGINT: Ctrl-C in a terminal reaches the whole process group, and
  the devices must stay on the line until the server has stopped its links (the
  server then stops its children in order);
* it names itself ``sim-<name>`` (``/proc/<pid>/comm``, what ``ps`` and ``servotune
  bench demo`` show);
* every ``LIFELINE_POLL_S`` it writes a *record* - a JSON snapshot of the simulated
  device as the device itself sees it (modes, positions, speeds) - to
  ``record_path`` if given, atomically (tests read it: it shows what reached the
  device, independently of what the server believes).

``serve_serial`` is the child for a serial device (``SimDevice`` on a
``PtySimulator``); ``servotune.devices.ep7047.sim.process.serve_ep7047`` the one for the
EtherCAT slave.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import json
import logging
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from types import MappingProxyType, TracebackType
from typing import Any, Literal

from servotune.sim.base import SimDevice
from servotune.sim.pty import PtySimulator, device_scheduling

logger = logging.getLogger(__name__)

LIFELINE_POLL_S = 0.25
START_TIMEOUT_S = 60.0  # a cold spawn imports the package: seconds on a loaded host
STOP_TIMEOUT_S = 5.0
REQUEST_TIMEOUT_S = 10.0
_PR_SET_NAME = 15  # linux/prctl.h

Handler = Callable[..., Any]


def record_path(state_dir: Path, name: str) -> Path:
    """Where the simulator ``name`` of the demo writes its record in ``state_dir``."""
    return state_dir / f"{name}-record.json"


class SimProcessError(RuntimeError):
    """A simulator process could not be started or did not answer."""


@dataclass(frozen=True, slots=True)
class SerialSimSpec:
    """What ``serve_serial`` runs: ``build()`` makes the device (it must be picklable:
    a module-level function or a ``functools.partial`` of one), on a pty at ``baud``.
    ``record`` turns the device into the JSON record (see the module docstring);
    ``link_path``: a stable symlink to the pty (``PtySimulator``)."""

    name: str
    build: Callable[[], SimDevice]
    baud: int
    record: Callable[[Any], dict[str, Any]] | None = None
    record_path: Path | None = None
    link_path: str | None = None


class SimProcess:
    """Parent side of one simulator child process (see the module docstring).

    ``target(spec, conn)`` runs in the child (module-level, picklable); it must send
    one ``{"ready": ...}`` dict on ``conn`` and then call :func:`serve_lifeline`.
    Use as a context manager, or ``start()`` / ``stop()``. ``start_method``:
    ``spawn`` (a fresh interpreter), or ``forkserver`` (a fork of multiprocessing's fork
    server, which starts clean once and imports what ``set_forkserver_preload`` names:
    for many short-lived simulators, e.g. one per test).
    """

    def __init__(
        self,
        name: str,
        target: Callable[[Any, Connection], None],
        spec: Any,
        *,
        start_method: Literal["spawn", "forkserver"] = "spawn",
    ) -> None:
        self.name = name
        self._target = target
        self._spec = spec
        self._start_method = start_method
        self._process: multiprocessing.process.BaseProcess | None = None
        self._conn: Connection | None = None
        # One request at a time on the pipe (callers may be on several threads).
        self._lock = threading.Lock()
        self._sent = 0
        self.ready: dict[str, Any] = {}

    @property
    def pid(self) -> int | None:
        return self._process.pid if self._process is not None else None

    @property
    def alive(self) -> bool:
        return self._process is not None and self._process.is_alive()

    def start(self, timeout_s: float = START_TIMEOUT_S) -> dict[str, Any]:
        """Spawn the child and wait for its ``ready`` message (returned)."""
        if self._process is not None:
            raise RuntimeError(f"simulator {self.name} already started")
        context: multiprocessing.context.SpawnContext | multiprocessing.context.ForkServerContext
        if self._start_method == "forkserver":
            context = multiprocessing.get_context("forkserver")
        else:
            context = multiprocessing.get_context("spawn")
        parent_conn, child_conn = context.Pipe()
        process = context.Process(
            target=_child_main,
            args=(self.name, self._target, self._spec, child_conn),
            name=f"sim-{self.name}",
            daemon=True,
        )
        process.start()
        child_conn.close()  # only the child holds that end: its closing is our EOF
        self._process, self._conn = process, parent_conn
        try:
            if not parent_conn.poll(timeout_s):
                raise SimProcessError(f"simulator {self.name} did not start within {timeout_s} s")
            message = parent_conn.recv()
        except (EOFError, OSError) as exc:
            process.join(STOP_TIMEOUT_S)
            exit_code = process.exitcode
            self._reap()
            raise SimProcessError(
                f"simulator {self.name} ended while starting (exit code {exit_code}); "
                "see its log above"
            ) from exc
        except SimProcessError:
            self._reap()
            raise
        if not isinstance(message, dict) or "ready" not in message:
            self._reap()
            raise SimProcessError(f"simulator {self.name} failed to start: {message!r}")
        self.ready = message["ready"]
        return self.ready

    def request(self, op: str, timeout_s: float = REQUEST_TIMEOUT_S, **args: Any) -> Any:
        """Run ``op`` in the child (its handlers); returns the result or raises."""
        with self._lock:
            conn = self._conn
            if conn is None or not self.alive:
                raise SimProcessError(f"simulator {self.name} is not running")
            self._sent += 1
            try:
                conn.send({"op": op, "args": args, "id": self._sent})
                deadline = time.monotonic() + timeout_s
                while True:
                    if not conn.poll(max(0.0, deadline - time.monotonic())):
                        raise SimProcessError(f"simulator {self.name} did not answer {op!r}")
                    reply = conn.recv()
                    # An answer to an earlier request that timed out is dropped.
                    if reply.get("id", self._sent) == self._sent:
                        break
            except (EOFError, OSError) as exc:
                raise SimProcessError(f"simulator {self.name} went away: {exc!r}") from exc
        if "error" in reply:
            raise SimProcessError(f"simulator {self.name}: {op} failed: {reply['error']}")
        return reply.get("ok")

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> None:
        """Ask the child to stop; terminate, then kill it if it does not. Idempotent."""
        if self._process is None:
            return
        conn = self._conn
        if conn is not None and self.alive:
            with contextlib.suppress(EOFError, OSError):
                conn.send({"op": "stop", "args": {}})
                if conn.poll(timeout_s):
                    conn.recv()
        self._reap(timeout_s)

    def _reap(self, timeout_s: float = STOP_TIMEOUT_S) -> None:
        process, self._process = self._process, None
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if process is None:
            return
        process.join(timeout_s)
        if process.is_alive():
            logger.warning("simulator %s did not stop; terminating it", self.name)
            process.terminate()
            process.join(timeout_s)
        if process.is_alive():
            process.kill()
            process.join(timeout_s)
        process.close()

    def __enter__(self) -> SimProcess:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()


@contextlib.contextmanager
def serial_sim_process(spec: SerialSimSpec) -> Iterator[SimProcess]:
    """A serial simulator in its own process; ``process.ready["path"]`` is its pty."""
    with SimProcess(spec.name, serve_serial, spec) as process:
        yield process


def demo_serial_process(
    name: str,
    build: Callable[[Path], SimDevice],
    baud: int,
    record: Callable[[Any], dict[str, Any]],
    state_dir: Path,
) -> contextlib.AbstractContextManager[SimProcess]:
    """The demo's serial simulator ``name``: ``build(state_dir)`` (a module-level
    function) on a pty at ``baud`` in a child process, its record at
    ``record_path(state_dir, name)``."""
    spec = SerialSimSpec(
        name, functools.partial(build, state_dir), baud, record, record_path(state_dir, name)
    )
    return serial_sim_process(spec)


Root = Literal["device", "simulator"]
# A path from the root: ("attr", name), ("item", key) or ("call", (args, kwargs)).
Step = tuple[str, Any]


class Remote:
    """An object in a serial simulator's process (``serve_serial``), reached on its
    lifeline: ``Remote(process, "device")`` is the simulated device,
    ``Remote(process, "simulator")`` its ``PtySimulator``.

    An attribute, an item or a call that yields plain data (None, numbers, strings,
    bytes, and lists, tuples and dicts of them) returns that data, read on the device's
    thread between two wire events; a dict comes read-only and a list as a tuple (a
    copy: writing to it would change nothing in the device). Anything else comes back
    as another ``Remote``; setting an attribute sets it in the device. The path is
    walked again on every access, so the calls on the way must be look-ups (e.g.
    ``line.module(0).rss``); arguments must be picklable (no closures).
    """

    __slots__ = ("_path", "_process", "_root")

    def __init__(self, process: SimProcess, root: Root, path: tuple[Step, ...] = ()) -> None:
        object.__setattr__(self, "_process", process)
        object.__setattr__(self, "_root", root)
        object.__setattr__(self, "_path", path)

    def _fetch(self, path: tuple[Step, ...]) -> Any:
        reply = self._process.request("inspect", root=self._root, path=path)
        if "value" not in reply:
            return Remote(self._process, self._root, path)
        value = reply["value"]
        if isinstance(value, dict):
            return MappingProxyType(value)
        if isinstance(value, list):
            return tuple(value)
        return value

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        return self._fetch((*self._path, ("attr", name)))

    def __getitem__(self, key: Any) -> Any:
        return self._fetch((*self._path, ("item", key)))

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self._fetch((*self._path, ("call", (args, kwargs))))

    def __setattr__(self, name: str, value: Any) -> None:
        self._process.request(
            "inspect", root=self._root, path=self._path, set_name=name, value=value
        )

    def __repr__(self) -> str:
        return f"Remote({self._process.name}:{self._root}{_describe_path(self._path)})"


def _describe_path(path: tuple[Step, ...]) -> str:
    text = ""
    for kind, arg in path:
        if kind == "attr":
            text += f".{arg}"
        elif kind == "item":
            text += f"[{arg!r}]"
        else:
            args, kwargs = arg
            text += (
                "("
                + ", ".join([*map(repr, args), *(f"{k}={v!r}" for k, v in kwargs.items())])
                + ")"
            )
    return text


_PLAIN = (type(None), bool, int, float, str, bytes)


def _is_plain(value: Any) -> bool:
    if isinstance(value, _PLAIN):
        return True
    if isinstance(value, (list, tuple)):
        return all(_is_plain(v) for v in value)
    if isinstance(value, dict):
        return all(isinstance(k, _PLAIN) and _is_plain(v) for k, v in value.items())
    return False


def _inspect(
    root: Any, path: tuple[Step, ...], set_name: str | None = None, value: Any = None
) -> dict[str, Any]:
    """The child's side of :class:`Remote`: walk ``path`` from ``root``; then set
    ``set_name`` to ``value`` there, or describe what was found."""
    target = root
    for kind, arg in path:
        if kind == "attr":
            target = getattr(target, arg)
        elif kind == "item":
            target = target[arg]
        elif kind == "call":
            args, kwargs = arg
            target = target(*args, **kwargs)
        else:
            raise ValueError(f"unknown step {kind!r}")
    if set_name is not None:
        setattr(target, set_name, value)
        return {"value": None}
    if _is_plain(target):
        return {"value": target}
    return {"object": type(target).__name__}


# --- the child side -------------------------------------------------------------------


def _child_main(
    name: str, target: Callable[[Any, Connection], None], spec: Any, conn: Connection
) -> None:
    _set_process_name(f"sim-{name}")
    # Ctrl-C goes to the whole process group; the server stops its children itself.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.basicConfig(
        level=logging.INFO, format=f"%(asctime)s %(levelname)s sim-{name}: %(message)s"
    )
    try:
        target(spec, conn)
    except (BrokenPipeError, EOFError):
        logger.info("the server went away before the simulator was ready: stopping")
    except Exception as exc:
        logger.exception("simulator %s failed", name)
        with contextlib.suppress(OSError, EOFError):
            conn.send({"failed": repr(exc)})
        sys.exit(1)


def _set_process_name(name: str) -> None:
    """Best effort: ``/proc/<pid>/comm`` (15 characters) on Linux."""
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_NAME, ctypes.c_char_p(name.encode()[:15]), 0, 0, 0)
    except (OSError, AttributeError):
        logger.debug("could not set the process name", exc_info=True)


def write_record(path: Path, record: Mapping[str, Any]) -> None:
    """Write ``record`` as JSON to ``path`` atomically (readers never see half a file)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    # One writer per record (this process): a fixed temporary name is enough, and far
    # cheaper than mkstemp's random names (this runs four times a second per simulator).
    temporary = path.parent / f".{path.name}.{os.getpid()}.tmp"
    try:
        with open(temporary, "w") as file:
            file.write(json.dumps(record))
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(temporary)
        raise


def serve_lifeline(
    conn: Connection,
    handlers: Mapping[str, Handler],
    *,
    tick: Callable[[], None] | None = None,
) -> None:
    """The child's loop: answer requests on ``conn`` until ``stop`` or end-of-file.

    ``tick`` runs every ``LIFELINE_POLL_S`` (records, health checks); an exception
    from it ends the loop (and with it the child), so a dead simulator does not live
    on as an empty shell.
    """
    while True:
        try:
            if not conn.poll(LIFELINE_POLL_S):
                if tick is not None:
                    tick()
                continue
            message = conn.recv()
        except (EOFError, OSError):
            logger.info("the server is gone: stopping")
            return
        op = message.get("op")
        args = message.get("args", {})
        if op == "stop":
            with contextlib.suppress(OSError):
                conn.send({"ok": None})
            return
        handler = handlers.get(op)
        try:
            if handler is None:
                raise KeyError(f"unknown request {op!r}")
            reply = {"ok": handler(**args)}
        except Exception as exc:  # the parent gets it as a SimProcessError
            reply = {"error": repr(exc)}
        if "id" in message:
            reply["id"] = message["id"]
        try:
            conn.send(reply)
        except OSError:
            return


def serve_serial(spec: SerialSimSpec, conn: Connection) -> None:
    """Child: the device on a pty until the lifeline says stop (or ends)."""
    device = spec.build()
    # Before the simulator's thread starts (it inherits the policy), after the build
    # (which runs without blocking: no reason to do it at real-time priority).
    logger.info("%s", device_scheduling(f"the simulated {spec.name}", own_session=True))
    simulator = PtySimulator(device, baud=spec.baud, link_path=spec.link_path)
    simulator.start()
    started = time.monotonic()
    try:
        conn.send({"ready": {"path": simulator.path, "pid": os.getpid(), "baud": spec.baud}})

        def record() -> dict[str, Any]:
            def snapshot() -> dict[str, Any]:
                data = spec.record(device) if spec.record is not None else {}
                return {
                    "name": spec.name,
                    "pid": os.getpid(),
                    "uptime_s": time.monotonic() - started,
                    "overflow_bytes": simulator.overflow_bytes,
                    "device": data,
                }

            result: dict[str, Any] = simulator.call(snapshot)
            return result

        def tick() -> None:
            if not simulator.running:
                raise SimProcessError(f"the pty simulator thread of {spec.name} stopped")
            if spec.record_path is not None:
                try:
                    write_record(spec.record_path, record())
                except (TimeoutError, OSError) as exc:
                    # A snapshot the starved device thread did not hand over in time, or
                    # a record file that could not be written, is no reason to take the
                    # device off the line (a real device does not die of a slow host):
                    # this record is skipped, the next tick writes one.
                    logger.warning("%s: record skipped: %r", spec.name, exc)

        def power_cycle(address: int | None = None) -> None:
            simulator.power_cycle(address)

        def call_device(method: str, **args: Any) -> Any:
            # A measurement's own view of the device (e.g. a shaft trace), read between
            # two wire events on the simulator's thread.
            return simulator.call(lambda: getattr(device, method)(**args))

        def inspect(root: Root, path: tuple[Step, ...], **change: Any) -> dict[str, Any]:
            if root == "simulator":  # its public methods may be called from any thread
                return _inspect(simulator, path, **change)
            return simulator.call(lambda: _inspect(device, path, **change))

        serve_lifeline(
            conn,
            {
                "record": record,
                "power_cycle": power_cycle,
                "set_silent": simulator.set_silent,
                "device": call_device,
                "inspect": inspect,
            },
            tick=tick,
        )
    finally:
        simulator.stop()
