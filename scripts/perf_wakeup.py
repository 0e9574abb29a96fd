"""How late the host wakes a mostly idle process, and what a pty round trip adds
(a simulated device must answer like hardware: docs/simulator.md, "Under load").

    .venv/bin/python scripts/perf_wakeup.py --seconds 60 sleep normal
    setsid .venv/bin/python scripts/perf_wakeup.py --seconds 60 sleep normal  # own group
    .venv/bin/python scripts/perf_wakeup.py --seconds 60 sleep fifo  # root/CAP_SYS_NICE
    .venv/bin/python scripts/perf_wakeup.py --seconds 60 pty fifo

``sleep``: sleeps of 1 ms in a loop (cyclictest's idea); prints the lateness of the
wake-ups. ``pty``: one byte written to a pty's slave side, echoed by a forked process on
its master side, every 5 ms; prints the round trips. ``normal`` / ``fifo``: the policy of
both processes (SCHED_FIFO 40 and 39). Linux only. Run it beside the load you care about
(another terminal's CPU hog: ``sh -c 'while :; do :; done'`` per core).
"""

from __future__ import annotations

import argparse
import os
import select
import time
import tty


def _policy(mode: str, priority: int) -> None:
    if mode == "fifo":
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))


def sleeps(seconds: float) -> list[float]:
    lates = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        t = time.monotonic()
        time.sleep(0.001)
        lates.append(time.monotonic() - t - 0.001)
    return lates


def pty_round_trips(seconds: float, mode: str) -> list[float]:
    master, slave = os.openpty()
    tty.setraw(slave)
    tty.setraw(master)
    pid = os.fork()
    if pid == 0:
        _policy(mode, 40)
        os.close(slave)
        while data := os.read(master, 64):
            os.write(master, data)
        os._exit(0)
    os.close(master)
    trips = []
    end = time.monotonic() + seconds
    try:
        while time.monotonic() < end:
            t = time.monotonic()
            os.write(slave, b"x")
            if select.select([slave], [], [], 5.0)[0]:
                os.read(slave, 64)
            trips.append(time.monotonic() - t)
            time.sleep(0.005)
    finally:
        os.kill(pid, 9)
        os.waitpid(pid, 0)
    return trips


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("what", choices=["sleep", "pty"])
    parser.add_argument("mode", choices=["normal", "fifo"])
    parser.add_argument("--seconds", type=float, default=60.0)
    args = parser.parse_args()
    _policy(args.mode, 39)
    if args.what == "sleep":
        values = sleeps(args.seconds)
    else:
        values = pty_round_trips(args.seconds, args.mode)
    values.sort()
    n = len(values)
    print(
        f"{args.what} {args.mode} (session {os.getsid(0)}): n={n} "
        f"median={1e3 * values[n // 2]:.2f} ms 99.9%={1e3 * values[int(n * 0.999)]:.1f} ms "
        f"worst={1e3 * values[-1]:.1f} ms over 50 ms: {sum(v > 0.05 for v in values)}, "
        f"over 150 ms: {sum(v > 0.15 for v in values)}; load average {os.getloadavg()[0]:.1f}"
    )


if __name__ == "__main__":
    main()
