"""Where a SLAP2 poll cycle's time goes: byte timestamps on both sides of the pty.

The simulated SLAP2 runs in its own process (as under ``servotune sim``) with the pty
simulator's timing probe on (``PtySimulator.trace``); the real driver polls it on
uvloop in this process with the serial protocol's ``send`` / ``data_received``
stamped. Both sides read ``time.monotonic()`` (CLOCK_MONOTONIC, one clock for every
process on Linux), so every echoed character's round trip splits into:

* ``host->sim``: host ``write`` to the simulator's ``read`` of the byte (pty, wake-up
  of the simulator thread);
* ``model``: the simulator's read to the echo's wire finish time beyond the two
  character times the wire needs (the byte's own 10 bits, then the echo's);
* ``sim late``: the echo written after its wire finish time (timer lateness);
* ``sim->host``: the simulator's ``write`` to the driver's ``data_received``;
* ``host turn``: ``data_received`` of the echo to the ``write`` of the next char;

and every transaction adds the reply's (``reply``: the terminator's arrival beyond
its wire time after the CR's echo) and the gap from the reply's terminator to the
first char of the next transaction (``between``: the driver's task wake-up and
bookkeeping). Printed per poll cycle (rp+pe+rss, +rve every 8th) against the wire
time of the same characters, which is what ``Slap2Link.wire_limit_hz`` counts.

Run: ``PYTHONPATH=server python scripts/bench_slap2_timing.py [--seconds 5]``. The
figures depend on the machine and its load (printed).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import multiprocessing
import os
import statistics
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection

from servotune.bench import _CountingSink
from servotune.config import LinkSpec
from servotune.drivers.slap2 import Slap2Link
from servotune.links import build_link
from servotune.sim.serial_sim import PtySimulator
from servotune.sim.slap2 import Slap2Bus
from servotune.transports import serial as serial_transport

BAUD = 19200
CHAR_S = 10 / BAUD
CR = 0x0D

Event = tuple[str, float, int]


def _child(baud: int, conn: Connection) -> None:
    simulator = PtySimulator(Slap2Bus.with_addresses([0]), baud=baud)
    simulator.trace = []
    simulator.start()
    try:
        conn.send(simulator.path)
        conn.recv()  # "start": the measurement begins
        before = os.times()
        conn.recv()  # "stop"
        after = os.times()
        cpu_s = (after.user - before.user, after.system - before.system)
        trace: list[Event] = simulator.call(lambda: list(simulator.trace or []))
        conn.send((trace, cpu_s))
    finally:
        simulator.stop()


def _patch_host(events: list[Event]) -> None:
    """Stamp every byte the driver's serial protocol sends and receives."""
    protocol = serial_transport._SerialProtocol
    send, received = protocol.send, protocol.data_received

    def traced_send(self: serial_transport._SerialProtocol, data: bytes) -> None:
        t = time.monotonic()
        events.extend(("htx", t, b) for b in data)
        send(self, data)

    def traced_received(self: serial_transport._SerialProtocol, data: bytes) -> None:
        t = time.monotonic()
        events.extend(("hrx", t, b) for b in data)
        received(self, data)

    protocol.send = traced_send  # type: ignore[method-assign]
    protocol.data_received = traced_received  # type: ignore[method-assign]


async def _poll(path: str, seconds: float, conn: Connection) -> tuple[float, float, float, int]:
    sink = _CountingSink()
    link = build_link(LinkSpec("slap2", path, "bench", BAUD, [0]), sink)
    assert isinstance(link, Slap2Link)
    task = asyncio.create_task(link.run())
    try:
        while link.state != "connected":  # noqa: ASYNC110 - a benchmark's start-up
            await asyncio.sleep(0.05)
        await asyncio.sleep(0.5)
        start = time.monotonic()
        for samples in sink.samples.values():
            samples.clear()
        conn.send("start")
        cpu0 = time.process_time()
        await asyncio.sleep(seconds)
        times = sink.samples["bench-0"]
        rate = (len(times) - 1) / (times[-1] - times[0])
        cpu_s = time.process_time() - cpu0
        return start, rate / link.wire_limit_hz(), cpu_s / seconds, len(times)
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


@dataclass
class Breakdown:
    """Seconds per component, summed over the transactions analysed."""

    parts: dict[str, list[float]] = field(default_factory=dict)
    wire_s: float = 0.0
    total_s: float = 0.0
    cycles: float = 0.0

    def add(self, name: str, value: float) -> None:
        self.parts.setdefault(name, []).append(value)


def t_misaligned(t_s: float, start_s: float) -> str:
    return f"{t_s - start_s:+.2f} s"


def _streams(events: Sequence[Event], kind: str) -> list[tuple[float, int]]:
    return [(t, b) for k, t, b in events if k == kind]


def analyse(host: Sequence[Event], sim: Sequence[Event], start_s: float) -> Breakdown:
    """Align the four byte streams and split every transaction's time (see the doc)."""
    htx, srx = _streams(host, "htx"), _streams(sim, "rx")
    # Device bytes scheduled before the first host byte arrived: the power-on banner
    # (the host drains it, from whenever it opened the port, before it sends).
    first_rx = next(i for i, e in enumerate(sim) if e[0] == "rx")
    banner = sum(1 for e in sim[:first_rx] if e[0] == "due")
    due, stx = _streams(sim, "due")[banner:], _streams(sim, "tx")[banner:]
    hrx = [(t, b) for t, b in _streams(host, "hrx") if t > htx[0][0]]
    if len(srx) < len(htx) or len(due) != len(stx):
        raise RuntimeError("byte streams do not align (a dropped byte?)")
    out = Breakdown()
    out_i = 0
    k = 0
    previous_end: float | None = None
    while k < len(htx):
        # One transaction: chars up to and including CR, each echoed, then the reply.
        j = k
        while j < len(htx) and htx[j][1] != CR:
            j += 1
        chars = j - k + 1
        echoes = list(range(out_i, out_i + chars))
        reply_end = out_i + chars
        while reply_end < len(due) and due[reply_end][1] != CR:
            reply_end += 1
        if j == len(htx) or reply_end >= min(len(hrx), len(stx)):
            break  # the last transaction, cut off by the end of the run
        reply_chars = reply_end - (out_i + chars) + 1
        if any(
            due[e][1] != htx[k + n][1] or hrx[e][1] != htx[k + n][1] for n, e in enumerate(echoes)
        ):
            # A retry (a timeout on a starved host): the streams no longer pair up
            # simply; what came before stands.
            print(f"streams misaligned at {t_misaligned(htx[k][0], start_s)}: analysis ends there")
            break
        t0 = htx[k][0]
        steady = t0 >= start_s and previous_end is not None
        if steady:
            assert previous_end is not None
            out.add("between", t0 - previous_end)
            for n, e in enumerate(echoes):
                out.add("host->sim", srx[k + n][0] - htx[k + n][0])
                out.add("model", due[e][0] - srx[k + n][0] - 2 * CHAR_S)
                out.add("sim late", stx[e][0] - due[e][0])
                out.add("sim->host", hrx[e][0] - stx[e][0])
                if n + 1 < chars:
                    out.add("host turn", htx[k + n + 1][0] - hrx[e][0])
            r = reply_end
            out.add("reply", hrx[r][0] - hrx[echoes[-1]][0] - reply_chars * CHAR_S)
            out.wire_s += (2 * chars + reply_chars) * CHAR_S
            out.total_s += hrx[r][0] - t0 + (t0 - previous_end)
            if htx[k][1] == ord("r") and htx[k + 1][1] == ord("p"):
                out.cycles += 1
        previous_end = hrx[reply_end][0]
        out_i = reply_end + 1
        k = j + 1
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    args = parser.parse_args()
    load = os.getloadavg()[0]
    context = multiprocessing.get_context("spawn")
    parent, child = context.Pipe()
    process = context.Process(target=_child, args=(BAUD, child), daemon=True)
    process.start()
    path = parent.recv()
    host: list[Event] = []
    _patch_host(host)
    import uvloop

    start_s, ratio, host_cpu, samples = uvloop.run(_poll(path, args.seconds, parent))
    stop_s = time.monotonic()
    parent.send("stop")
    sim, (sim_user_s, sim_system_s) = parent.recv()
    sim_cpu_s = sim_user_s + sim_system_s
    process.join(5)
    host = [e for e in host if e[1] <= stop_s]
    b = analyse(host, [e for e in sim if e[1] <= stop_s + 0.05], start_s)
    print(f"load average {load:.2f} -> {os.getloadavg()[0]:.2f} (1 min), {os.cpu_count()} cores")
    print(f"achieved {ratio:.1%} of the wire limit; driver process {host_cpu:.2f} core")
    cycles = b.cycles or 1
    print(
        f"simulator process {sim_cpu_s / args.seconds:.3f} core "
        f"({sim_cpu_s / samples * 1e6:.0f} us CPU per sample, of which "
        f"{sim_system_s / samples * 1e6:.0f} us in the kernel)"
    )
    total_ms, wire_ms = b.total_s / cycles * 1e3, b.wire_s / cycles * 1e3
    print(
        f"per poll cycle: {total_ms:.2f} ms, wire {wire_ms:.2f} ms, excess "
        f"{total_ms - wire_ms:.2f} ms (the wire's share {b.wire_s / b.total_s:.1%})"
    )
    print(f"{'component':<11} {'n/cycle':>8} {'median us':>10} {'p90 us':>8} {'ms/cycle':>9}")
    for name, values in b.parts.items():
        p90 = statistics.quantiles(values, n=10)[-1] if len(values) > 10 else max(values)
        print(
            f"{name:<11} {len(values) / cycles:8.2f} {statistics.median(values) * 1e6:10.0f} "
            f"{p90 * 1e6:8.0f} {sum(values) / cycles * 1e3:9.3f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
