"""What the EtherCAT path costs the rest of the host, in each state of the wire.

The cycle process runs at real-time priority: whatever it burns there, every process
of normal priority (the server, the simulators, the kernel's own workers - among them
the one that moves pty data, ``flush_to_ldisc``) gets only what is left. This runs the
driver (pysoem, the cycle process) against the software EP7047-1032 on a veth pair, as
``perf_ep7047_wire.py`` does, and walks the wire through its states, one window each:

* ``op``: in OP, the axis enabled and moving +/- one turn;
* ``slow``: the slave answers every frame ``--delay-us`` late (its ``delay`` knob);
* ``pulled``: the cable pulled (the master's end of the veth pair down);
* ``killed``: the slave process killed (SIGKILL; the wire stays up, nothing answers).

Per window: the CPU of the cycle process (cores, from /proc), the share of samples in
which it was at SCHED_FIFO, the CPU of the server side (this process) and the slave, a
pty round trip measured meanwhile by a probe of normal priority (a byte to a pty and
its echo back from a second process: two passes through the kernel's pty workers, as
every SLAP2/Z1100 link makes), the SLAP2 link's sample rate (``servotune perf slap2``
on a pty, run during the window) and any kernel message about a workqueue lockup, a
hung task, an RCU stall or RT throttling that appeared meanwhile.

Run as root: ``.venv/bin/python scripts/perf_ep7047_rt.py [--cycle-ms 2] [--window 10]
[--hog on] [--delay-us 1500] [--phases op,slow,pulled,killed]``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import re
import select
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import tty
from pathlib import Path
from typing import Any

from perf_ep7047_wire import (  # scripts/ is this script's directory
    CLOCK_TICKS,
    Sink,
    cpu_s,
    hog,
    swing_move,
)

from servotune.devices.ep7047.link import PysoemMaster, build_ep7047_link
from servotune.devices.ep7047.sim.netns import netns_problem, slave_process, veth_pair
from servotune.devices.ep7047.sim.slave import DEMO_COUNTS_PER_REV, DEMO_SPEED_RANGE_STEPS_S
from servotune.transports.ethercat_cycle import CycleProcessMaster

KERNEL_TROUBLE = re.compile(
    r"workqueue lockup|hung_task|blocked for more than|rcu.*stall|RT throttling", re.I
)
SCHED_FIFO = 1


def pty_probe(out_path: str, period_s: float) -> None:
    """The probe (its own process): a byte to a pty, its echo back from a child, every
    ``period_s``; one line ``t rtt_s`` per round trip (``inf`` after 10 s)."""
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    if os.fork() == 0:  # the echo: another process, as a simulator is
        os.close(master)
        while True:
            os.write(slave, os.read(slave, 64))
    os.close(slave)
    with open(out_path, "w") as out:
        while True:
            t = time.monotonic()
            os.write(master, b"x")
            readable, _, _ = select.select([master], [], [], 10.0)
            rtt = time.monotonic() - t if readable else float("inf")
            if readable:
                os.read(master, 64)
            out.write(f"{t:.6f} {rtt:.6f}\n")
            out.flush()
            time.sleep(period_s)


def policy(pid: int) -> int:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[38])  # field 41 of proc(5), counted after the name


def rt_cpu_s() -> float:
    """CPU seconds so far of every thread on the host that runs at a real-time policy
    now (a thread that left it is not counted: a lower bound of the RT share)."""
    total = 0
    for stat in Path("/proc").glob("[0-9]*/task/[0-9]*/stat"):
        with contextlib.suppress(OSError, ValueError, IndexError):
            fields = stat.read_text().rsplit(")", 1)[1].split()
            if int(fields[38]) in (1, 2, 6):  # FIFO, RR, DEADLINE
                total += int(fields[11]) + int(fields[12])
    return total / CLOCK_TICKS


def kernel_lines() -> list[str]:
    result = subprocess.run(["dmesg"], capture_output=True, text=True, check=False)
    return result.stdout.splitlines()


def rtts_between(path: Path, t0: float, t1: float) -> list[float]:
    values = []
    for line in path.read_text().splitlines():
        parts = line.split()
        if len(parts) == 2 and t0 <= float(parts[0]) < t1:
            values.append(float(parts[1]))
    return values


async def slap2_rate(seconds: float) -> str:
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "servotune", "perf", "slap2", "--seconds", f"{seconds:g}",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT,
    )  # fmt: skip
    out, _ = await process.communicate()
    rates = re.findall(r"([\d.]+) samples/s =", out.decode())
    return "/".join(rates) if rates else "no samples"


async def moves(axis: Any, sink: Sink, link: Any, stop: asyncio.Event) -> None:
    target = DEMO_COUNTS_PER_REV
    while not stop.is_set():
        if link.state == "connected":
            with contextlib.suppress(Exception):
                latest = sink.latest
                if latest is not None and not latest.flags.get("enable_out"):
                    await axis.command("enable", {})
                await axis.command("execute_move", swing_move(target))
            target = -target
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), 1.5)


async def window(
    name: str, seconds: float, master: CycleProcessMaster, slave_pid: int | None, probe: Path
) -> dict[str, Any]:
    pids = {"server": os.getpid()}
    if master.pid is not None:
        pids["cycle"] = master.pid
    if slave_pid is not None:
        pids["slave"] = slave_pid
    before = {n: cpu_s(p) for n, p in pids.items()}
    dmesg_before = len(kernel_lines())
    t0 = time.monotonic()
    rate_task = asyncio.create_task(slap2_rate(max(2.0, seconds - 4.0)))
    fifo = samples = 0
    rt_shares: list[float] = []
    rt_t, rt_before = time.monotonic(), rt_cpu_s()
    while time.monotonic() - t0 < seconds:
        await asyncio.sleep(0.1)
        with contextlib.suppress(OSError, ValueError):
            if master.pid is not None:
                fifo += policy(master.pid) == SCHED_FIFO
                samples += 1
        if time.monotonic() - rt_t >= 1.0:
            rt_now, now = rt_cpu_s(), time.monotonic()
            rt_shares.append(max(0.0, rt_now - rt_before) / (now - rt_t))
            rt_t, rt_before = now, rt_now
    elapsed = time.monotonic() - t0
    cpu: dict[str, float] = {}
    for n, p in pids.items():
        with contextlib.suppress(OSError):
            cpu[n] = (cpu_s(p) - before[n]) / elapsed
    rtts = rtts_between(probe, t0, t0 + elapsed)
    finite = sorted(r for r in rtts if r != float("inf"))
    kernel = [line for line in kernel_lines()[dmesg_before:] if KERNEL_TROUBLE.search(line)]
    return {
        "phase": name,
        "cpu": cpu,
        "fifo": fifo / samples if samples else 0.0,
        "pty_n": len(rtts),
        "pty_p50_ms": statistics.median(finite) * 1000 if finite else float("nan"),
        "pty_p99_ms": finite[int(0.99 * (len(finite) - 1))] * 1000 if finite else float("nan"),
        "pty_max_ms": max(rtts) * 1000 if rtts else float("nan"),
        "pty_over_100ms": sum(1 for r in rtts if r > 0.1),
        "slap2": await rate_task,
        "kernel": kernel,
        "rt_mean": statistics.fmean(rt_shares) if rt_shares else float("nan"),
        "rt_max": max(rt_shares, default=float("nan")),
    }


def show(row: dict[str, Any]) -> None:
    cpu = row["cpu"]
    print(
        f"| {row['phase']} | {cpu.get('cycle', float('nan')):.3f} | {row['fifo']:.0%} | "
        f"{cpu.get('server', 0):.3f} | {cpu.get('slave', float('nan')):.3f} | "
        f"{row['pty_p50_ms']:.2f} / {row['pty_p99_ms']:.2f} / {row['pty_max_ms']:.1f} | "
        f"{row['pty_over_100ms']} of {row['pty_n']} | {row['slap2']} | "
        f"{row['rt_mean']:.2f} / {row['rt_max']:.2f} | "
        f"{len(row['kernel'])} |",
        flush=True,
    )
    for line in row["kernel"]:
        print(f"  kernel: {line}", flush=True)


async def main(args: argparse.Namespace) -> int:
    problem = netns_problem()
    if problem is not None:
        print(f"cannot run: {problem}", file=sys.stderr)
        return 2
    cycle_s = args.cycle_ms / 1000
    phases = args.phases.split(",")
    with (
        tempfile.TemporaryDirectory() as tmp,
        veth_pair() as pair,
        slave_process(pair, Path(tmp)) as slave,
    ):
        probe_path = Path(tmp) / "pty.txt"
        probe = subprocess.Popen(  # noqa: ASYNC220 - before anything is measured
            [sys.executable, __file__, "--pty-probe", str(probe_path)], start_new_session=True
        )
        sink = Sink()
        master = CycleProcessMaster(PysoemMaster, cycle_s=cycle_s)
        link = build_ep7047_link(
            "bench", pair.master_if, 1, sink,  # type: ignore[arg-type]
            master=master, cycle_s=cycle_s, speed_range_steps_s=DEMO_SPEED_RANGE_STEPS_S,
            counts_per_rev=DEMO_COUNTS_PER_REV,
        )  # fmt: skip
        task = asyncio.create_task(link.run())
        stop_moves = asyncio.Event()
        mover: asyncio.Task[None] | None = None
        print(
            "| state | cycle CPU (core) | cycle at FIFO | server CPU | slave CPU | "
            "pty round trip p50/p99/max ms | pty > 100 ms | SLAP2 samples/s | "
            "host RT cores mean/max-1s | kernel msgs |"
        )
        print("|---|---|---|---|---|---|---|---|---|---|")
        try:
            started = time.monotonic()
            while link.state != "connected":
                await asyncio.sleep(0.01)
                if time.monotonic() - started > 90:
                    raise RuntimeError(f"no OP: {sink.events[-3:]}")
            print(f"(OP after {time.monotonic() - started:.1f} s; {master.priority_text})")
            mover = asyncio.create_task(moves(link.axes[0], sink, link, stop_moves))
            with hog(args.hog == "on"):
                for phase in phases:
                    slave_pid: int | None = slave.pid
                    if phase == "slow":
                        slave.control("delay", us=args.delay_us)
                    elif phase == "pulled":
                        pair.set_master_link(False)
                    elif phase == "killed":
                        slave.signal(signal.SIGKILL)
                        slave.process.wait()
                        slave_pid = None
                    show(await window(phase, args.window, master, slave_pid, probe_path))
                    if phase == "slow":
                        slave.control("delay", us=0)
                    elif phase == "pulled":
                        pair.set_master_link(True)
                        back = time.monotonic()
                        while link.state != "connected" and time.monotonic() - back < 60:  # noqa: ASYNC110
                            await asyncio.sleep(0.05)
                        print(f"(cable back: {link.state} after {time.monotonic() - back:.1f} s)")
            events = [e for e in sink.events if not e.startswith("info")]
            for event in events[-12:]:
                print(f"  {event}")
        finally:
            stop_moves.set()
            if mover is not None:
                with contextlib.suppress(Exception):
                    await mover
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            os.killpg(probe.pid, signal.SIGKILL)
            probe.wait()
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--pty-probe":
        pty_probe(sys.argv[2], 0.01)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cycle-ms", type=float, default=2.0)
    parser.add_argument("--window", type=float, default=10.0, help="seconds per state")
    parser.add_argument("--hog", choices=["off", "on"], default="off")
    parser.add_argument("--delay-us", type=int, default=1500, help="the slow slave's delay")
    parser.add_argument("--phases", default="op,slow,pulled,killed")
    sys.exit(asyncio.run(main(parser.parse_args())))
