"""``servotune perf demo``: CPU per process and link rates of the whole demo.

Starts ``python -m servotune demo`` (autopilot on) on a free port as a child process
(or measures one already running, ``--url`` and ``--pid``), waits until every link is
connected, then for ``seconds`` samples:

* CPU per process - the server and each of its child processes (the simulators) - as
  CPU seconds per wall second from ``/proc/<pid>/stat`` (utime + stime; 1.0 is one
  core busy). That figure is far less sensitive to other work on the machine than a
  rate, so it is what to compare between machines;
* every link's ``rate_hz / wire_limit_hz`` from ``GET /api/links/{id}/status``, once a
  second (median and minimum), its state and its error counter, and its
  ``wire_busy`` (the share of time the line carried any of its exchanges: polls,
  commands and echoes; the autopilot's moves share the wire with the polls);
* the websocket stream: events by level and axis health changes to ``reset``;
* the load average before and after.

``--hog`` runs one busy process per CPU core during the measurement (a CPU hog on
both cores). Linux only (``/proc``). Not a test: the figures depend on the
machine; ``tests/integration/perf/test_soak.py`` asserts the truths and prints the same figures.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
import urllib.request
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Self

_CLOCK_TICKS_S = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


# --- processes ------------------------------------------------------------------------


def _stat_fields(pid: int) -> list[str] | None:
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    # The command name (field 2) may hold spaces and parentheses: split after the last ")".
    return text[text.rindex(")") + 2 :].split()


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of ``pid`` so far (its own threads, not its children)."""
    fields = _stat_fields(pid)
    if fields is None:
        return None
    return (int(fields[11]) + int(fields[12])) / _CLOCK_TICKS_S


def children(pid: int) -> list[int]:
    """Direct child processes of ``pid``."""
    found: list[int] = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        fields = _stat_fields(int(entry.name))
        if fields is not None and int(fields[1]) == pid:
            found.append(int(entry.name))
    return sorted(found)


def process_tree(pid: int) -> list[int]:
    """``pid`` and all its descendants."""
    tree = [pid]
    for child in children(pid):
        tree.extend(process_tree(child))
    return tree


def process_name(pid: int) -> str:
    """The process' name (``comm``): the simulators name themselves ``sim-<device>``;
    multiprocessing's resource tracker (a child of every spawning process) is named."""
    try:
        name = Path(f"/proc/{pid}/comm").read_text().strip()
        if b"resource_tracker" in Path(f"/proc/{pid}/cmdline").read_bytes():
            return "mp-resource-tracker"
        return name
    except OSError:
        return "?"


def load_average() -> tuple[float, float, float]:
    one, five, fifteen = os.getloadavg()
    return one, five, fifteen


@contextlib.contextmanager
def cpu_hog(processes: int | None = None) -> Iterator[list[int]]:
    """One busy-looping process per core (or ``processes``), killed on exit."""
    count = processes if processes is not None else os.cpu_count() or 1
    hogs = [
        subprocess.Popen(
            [sys.executable, "-c", "while True: pass"],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
        )
        for _ in range(count)
    ]
    try:
        yield [hog.pid for hog in hogs]
    finally:
        for hog in hogs:
            hog.kill()
        for hog in hogs:
            hog.wait()


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


# --- the demo as a child process ------------------------------------------------------


def get_json(url: str, timeout_s: float = 5.0) -> Any:
    with urllib.request.urlopen(url, timeout=timeout_s) as response:
        return json.loads(response.read())


def post_json(url: str, body: Any = None, timeout_s: float = 10.0) -> Any:
    """POST as the web client does: JSON with the server's CSRF token (local mode)."""
    parts = urllib.parse.urlsplit(url)
    session = get_json(f"{parts.scheme}://{parts.netloc}/api/auth/session", timeout_s)
    data = json.dumps(body if body is not None else {}).encode()
    request = urllib.request.Request(
        url,
        data=data,
        headers={"Content-Type": "application/json", "X-CSRF-Token": session["csrf_token"]},
        method="POST",
    )
    with urllib.request.urlopen(request, timeout=timeout_s) as response:
        return json.loads(response.read())


@dataclass
class DemoServer:
    """A ``servotune demo`` child process (see :func:`demo_server`)."""

    process: subprocess.Popen[bytes]
    base_url: str
    data_dir: Path

    @property
    def pid(self) -> int:
        return self.process.pid

    def link_ids(self) -> list[str]:
        return [link["id"] for link in get_json(f"{self.base_url}/api/links")]

    def link_status(self, link_id: str) -> dict[str, Any]:
        status: dict[str, Any] = get_json(f"{self.base_url}/api/links/{link_id}/status")
        return status


def wait_connected(base_url: str, timeout_s: float) -> list[str]:
    """Wait until the server answers and every link is ``connected``; returns the ids."""
    deadline = time.monotonic() + timeout_s
    last = "no answer"
    while time.monotonic() < deadline:
        try:
            ids = [link["id"] for link in get_json(f"{base_url}/api/links", 2.0)]
            states = {i: get_json(f"{base_url}/api/links/{i}/status", 2.0)["state"] for i in ids}
        except (OSError, ValueError) as exc:
            last = repr(exc)
        else:
            if ids and all(state == "connected" for state in states.values()):
                return ids
            last = repr(states)
        time.sleep(0.25)
    raise TimeoutError(f"the demo did not connect every link within {timeout_s:g} s: {last}")


@contextlib.contextmanager
def demo_server(
    *,
    port: int | None = None,
    data_dir: Path | None = None,
    autopilot: bool = True,
    connect_timeout_s: float = 60.0,
    log_path: Path | None = None,
) -> Iterator[DemoServer]:
    """Run ``python -m servotune demo`` until the block ends (SIGTERM, then SIGKILL)."""
    port = port if port is not None else free_port()
    with contextlib.ExitStack() as stack:
        if data_dir is None:
            data_dir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="st-demo-")))
        command = [sys.executable, "-m", "servotune", "demo", "--port", str(port)]
        command += ["--data-dir", str(data_dir)]
        if not autopilot:
            command.append("--no-autopilot")
        log = stack.enter_context(
            open(log_path, "wb") if log_path is not None else open(os.devnull, "wb")  # noqa: SIM115
        )
        process = subprocess.Popen(
            command, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT
        )
        server = DemoServer(process, f"http://127.0.0.1:{port}", data_dir)
        try:
            wait_connected(server.base_url, connect_timeout_s)
            yield server
        finally:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(15)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


# --- the measurement ------------------------------------------------------------------


@dataclass
class LinkFigures:
    ratios: list[float] = field(default_factory=list)
    # the link's wire_busy (the share of time its line carried any of its exchanges)
    busy: list[float] = field(default_factory=list)
    states: Counter[str] = field(default_factory=Counter)
    errors_first: int | None = None
    errors_last: int = 0
    wire_limit_hz: float = 0.0
    # the link's counters (retries, desyncs, dropped bytes, ...) at the first and the
    # last status read of the measurement
    counters_first: dict[str, int] | None = None
    counters_last: dict[str, int] = field(default_factory=dict)

    def per_minute(self, seconds: float) -> dict[str, float]:
        """What each counter grew by during the measurement, per minute."""
        first = self.counters_first or {}
        return {
            name: (value - first.get(name, 0)) * 60.0 / seconds
            for name, value in sorted(self.counters_last.items())
        }

    @property
    def median(self) -> float:
        return statistics.median(self.ratios) if self.ratios else 0.0

    @property
    def minimum(self) -> float:
        return min(self.ratios) if self.ratios else 0.0

    @property
    def busy_median(self) -> float | None:
        return statistics.median(self.busy) if self.busy else None


@dataclass
class StreamCounts:
    """What the websocket showed: events by level, axis health changes."""

    events: Counter[str] = field(default_factory=Counter)
    event_texts: list[str] = field(default_factory=list)
    resets: Counter[str] = field(default_factory=Counter)
    health: dict[str, str] = field(default_factory=dict)
    link_states: dict[str, str] = field(default_factory=dict)
    samples: Counter[str] = field(default_factory=Counter)
    last_t: dict[str, float] = field(default_factory=dict)
    last_flags: dict[str, dict[str, int]] = field(default_factory=dict)
    last_channels: dict[str, dict[str, float | None]] = field(default_factory=dict)


class BackgroundThread:
    """A daemon thread for the length of a ``with`` block: ``_run`` until ``_stop`` is
    set on exit, then joined for up to ``join_s``."""

    join_s = 5.0

    def __init__(self, name: str) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def __enter__(self) -> Self:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(self.join_s)

    def _run(self) -> None:
        raise NotImplementedError


class StreamWatcher(BackgroundThread):
    """Reads ``/ws`` in a thread and keeps :class:`StreamCounts` (needs ``websockets``).

    Like the web client it connects again when the connection drops (a server starved
    long enough misses the websocket keep-alive and closes it): every drop is kept in
    ``drops`` as ``(lost, back, reason)`` (monotonic times; ``back`` is None while it
    is down), and ``error`` is set only when no connection could be made for
    ``GIVE_UP_S``."""

    GIVE_UP_S = 30.0

    def __init__(self, base_url: str) -> None:
        super().__init__("stream-watcher")
        self.url = base_url.replace("http://", "ws://") + "/ws"
        self.counts = StreamCounts()
        self.lock = threading.Lock()
        self.error: str | None = None
        self.drops: list[tuple[float, float | None, str]] = []

    def down_since(self, t: float) -> bool:
        """Whether the connection was down at any time after ``t``."""
        with self.lock:
            return any(back is None or back > t for _, back, _ in self.drops)

    def _run(self) -> None:
        from websockets.exceptions import WebSocketException
        from websockets.sync.client import connect
        from websockets.typing import Origin

        # The dashboard's own origin: the server refuses any other.
        origin = Origin(self.url.replace("ws://", "http://", 1).removesuffix("/ws"))
        failing_since: float | None = None
        backoff_s = 0.25
        while not self._stop.is_set():
            try:
                with connect(self.url, max_size=None, open_timeout=10, origin=origin) as ws:
                    with self.lock:
                        if self.drops and self.drops[-1][1] is None:
                            lost, _, why = self.drops[-1]
                            self.drops[-1] = (lost, time.monotonic(), why)
                    failing_since, backoff_s = None, 0.25
                    while not self._stop.is_set():
                        try:
                            text = ws.recv(timeout=0.2)
                        except TimeoutError:
                            continue
                        self._note(json.loads(text))
            except (OSError, WebSocketException) as exc:
                now = time.monotonic()
                with self.lock:
                    if not self.drops or self.drops[-1][1] is not None:
                        self.drops.append((now, None, repr(exc)))
                failing_since = failing_since if failing_since is not None else now
                if now - failing_since > self.GIVE_UP_S:
                    self.error = f"no connection for {now - failing_since:.0f} s: {exc!r}"
                    return
                self._stop.wait(backoff_s)
                backoff_s = min(2 * backoff_s, 2.0)

    def _note(self, message: dict[str, Any]) -> None:
        kind = message.get("type")
        with self.lock:
            counts = self.counts
            if kind == "event":
                counts.events[message["level"]] += 1
                counts.event_texts.append(f"{message['level']}: {message['message']}")
            elif kind == "axis_status":
                axis, health = message["axis"], message["health"]
                if health == "reset" and counts.health.get(axis) != "reset":
                    counts.resets[axis] += 1
                counts.health[axis] = health
            elif kind == "link_status":
                counts.link_states[message["link"]] = message["state"]
            elif kind == "telemetry":
                axis = message["axis"]
                times = message["t"]
                counts.samples[axis] += len(times)
                if times:
                    counts.last_t[axis] = times[-1]
                    counts.last_flags[axis] = {k: v[-1] for k, v in message["flags"].items()}
                    counts.last_channels[axis] = {k: v[-1] for k, v in message["channels"].items()}


@dataclass
class BenchReport:
    seconds: float
    cpu: dict[str, float]  # process label -> CPU s per s
    links: dict[str, LinkFigures]
    load_before: tuple[float, float, float]
    load_after: tuple[float, float, float]
    stream: StreamCounts | None = None

    def lines(self, title: str) -> list[str]:
        out = [
            f"== {title}: {self.seconds:.0f} s, load average {self.load_before[0]:.2f} -> "
            f"{self.load_after[0]:.2f} (1 min), {os.cpu_count()} cores"
        ]
        out.append("CPU (CPU seconds per second; 1.00 = one core):")
        sims = 0.0
        for label, share in self.cpu.items():
            out.append(f"  {label:<28} {share:6.3f}")
            if label.startswith("sim-"):
                sims += share
        out.append(f"  {'simulators together':<28} {sims:6.3f}")
        out.append("links (rate / wire limit, sampled once a second):")
        for link_id, figures in self.links.items():
            errors = figures.errors_last - (figures.errors_first or 0)
            states = ", ".join(f"{k} {v}" for k, v in sorted(figures.states.items()))
            out.append(
                f"  {link_id:<14} median {figures.median:6.1%}  min {figures.minimum:6.1%}  "
                f"of {figures.wire_limit_hz:7.1f} Hz  errors +{errors}  ({states})"
            )
            if figures.busy_median is not None:
                # Polls, commands and echoes: the autopilot's moves share the wire, so
                # the sample rate stays below the poll set's limit while this does not.
                out.append(
                    f"  {'':<14} line busy (all exchanges) median {figures.busy_median:6.1%}  "
                    f"min {min(figures.busy):6.1%}"
                )
            counted = figures.per_minute(self.seconds)
            if counted:
                out.append(
                    f"  {'':<14} per minute: "
                    + ", ".join(f"{name} {rate:.1f}" for name, rate in counted.items())
                )
        if self.stream is not None:
            # The work done, to compare CPU figures between runs on a loaded host: a
            # starved link does less work, so less CPU there is no saving.
            delivered = sum(self.stream.samples.values()) / self.seconds
            if delivered:
                server_ms = self.cpu.get("server", 0.0) / delivered * 1e6
                out.append(
                    f"work: {delivered:.0f} telemetry samples/s delivered (all axes); CPU "
                    f"per 1000 samples: server {server_ms:.1f} ms, "
                    f"simulators {sims / delivered * 1e6:.1f} ms"
                )
            else:
                out.append("work: no telemetry received")
            levels = ", ".join(f"{k} {v}" for k, v in sorted(self.stream.events.items()))
            resets = sum(self.stream.resets.values())
            out.append(f"events: {levels or 'none'}; reset banners: {resets}")
            # The warnings and errors themselves: a count alone cannot tell a true alarm
            # (an autopilot move refused for a reason) from a false one.
            alarms = Counter(
                text for text in self.stream.event_texts if not text.startswith("info:")
            )
            for text, count in alarms.most_common(8):
                out.append(f"  {count:3d} x {text[:150]}")
        return out


def measure(
    base_url: str, root_pid: int, seconds: float, *, watch_stream: bool = True
) -> BenchReport:
    """CPU per process of ``root_pid``'s tree and the link ratios over ``seconds``."""
    link_ids = [link["id"] for link in get_json(f"{base_url}/api/links")]
    pids = process_tree(root_pid)
    labels = {
        pid: "server" if pid == root_pid else f"{process_name(pid)} (pid {pid})" for pid in pids
    }
    links = {link_id: LinkFigures() for link_id in link_ids}
    load_before = load_average()
    with contextlib.ExitStack() as stack:
        watcher = stack.enter_context(StreamWatcher(base_url)) if watch_stream else None
        start = {pid: cpu_seconds(pid) for pid in pids}
        t0 = time.monotonic()
        next_poll = t0
        while time.monotonic() - t0 < seconds:
            for link_id in link_ids:
                status = get_json(f"{base_url}/api/links/{link_id}/status")
                figures = links[link_id]
                figures.states[status["state"]] += 1
                figures.wire_limit_hz = status["wire_limit_hz"]
                if status["wire_limit_hz"] > 0:
                    figures.ratios.append(status["rate_hz"] / status["wire_limit_hz"])
                if status.get("wire_busy") is not None:
                    figures.busy.append(status["wire_busy"])
                if figures.errors_first is None:
                    figures.errors_first = status["errors"]
                    figures.counters_first = dict(status.get("counters") or {})
                figures.errors_last = status["errors"]
                figures.counters_last = dict(status.get("counters") or {})
            next_poll += 1.0
            time.sleep(max(0.0, next_poll - time.monotonic()))
        elapsed = time.monotonic() - t0
        end = {pid: cpu_seconds(pid) for pid in pids}
    cpu: dict[str, float] = {}
    for pid in pids:
        before, after = start[pid], end[pid]
        if before is not None and after is not None:
            cpu[labels[pid]] = (after - before) / elapsed
    return BenchReport(
        elapsed, cpu, links, load_before, load_average(), watcher.counts if watcher else None
    )


def run_demo_bench(
    *,
    seconds: float,
    hog: str,
    port: int | None,
    url: str | None,
    pid: int | None,
    warm_up_s: float = 5.0,
) -> int:
    """The ``servotune perf demo`` command; ``hog`` is ``off``, ``on`` or ``both``."""
    phases = {"off": [False], "on": [True], "both": [False, True]}[hog]
    with contextlib.ExitStack() as stack:
        if url is None:
            print("starting the demo (autopilot on) ...", flush=True)
            server = stack.enter_context(demo_server(port=port))
            url, pid = server.base_url, server.pid
        elif pid is None:
            print("servotune perf demo: --url needs --pid (the server's process id)")
            return 2
        assert pid is not None
        time.sleep(warm_up_s)
        for with_hog in phases:
            with contextlib.ExitStack() as phase:
                if with_hog:
                    phase.enter_context(cpu_hog())
                    time.sleep(2.0)  # let the scheduler settle with the hogs
                report = measure(url, pid, seconds)
            title = "with a CPU hog on every core" if with_hog else "without a hog"
            print("\n".join(report.lines(title)), flush=True)
    return 0
