"""How fast the simulated SLAP2 plant runs: simulated seconds per CPU second, per axis.

The target is >= 100x real time per axis (so 16 modules on one line would still
leave the host most of a core). Measured with ``time.process_time`` around
``Slap2Line.advance_to`` only (the firmware, the PID at 841.5 us and the motor model;
no pty, no I/O), for one module in each of these states:

* ``moving``: back-to-back 2000-count ``ma`` moves (sv 2000, sa 1000), one per
  simulated second (a move takes ~0.6 s, then it settles and holds);
* ``vm``: velocity mode at sv +-2000, reversed every simulated second (the shaft
  rarely rests and never reaches a limit switch: the dearest case, no idle fast path);
* ``holding``: pm at rest (the idle fast path skips the ticks).

Run: ``PYTHONPATH=server python scripts/perf_sim_speed.py [--seconds 10]``. The figure
depends on the machine and its load (printed); CPU time is far less sensitive to
load than wall time, but a loaded host still inflates it (caches, hyperthreads).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from servotune.devices.slap2.sim.line import Slap2Line
from servotune.devices.slap2.sim.module import Slap2Module


def _send(bus: Slap2Line, text: str) -> None:
    for byte in (text + "\r").encode("ascii"):
        bus.receive(byte)


def speed(kind: str, seconds: float) -> float:
    """Simulated seconds per CPU second for one module doing ``kind``."""
    bus = Slap2Line([Slap2Module(0)])
    t = 0.5
    bus.advance_to(t)  # the banner
    _send(bus, "pm")
    cpu_s = 0.0
    target = 0
    sv = 2000
    while t < 0.5 + seconds:
        if kind == "moving":
            target = 2000 - target
            _send(bus, f"ma{target}")
        elif kind == "vm":
            _send(bus, f"sv{sv}")
            _send(bus, "vm")
            sv = -sv
        started = time.process_time()
        bus.advance_to(t + 1.0)
        cpu_s += time.process_time() - started
        t += 1.0
    return seconds / cpu_s if cpu_s > 0 else float("inf")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="simulated time per case")
    args = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} (1 min), {os.cpu_count()} cores")
    for kind in ("moving", "vm", "holding"):
        print(f"  SLAP2 {kind:<8} {speed(kind, args.seconds):10.0f}x real time per axis")
    return 0


if __name__ == "__main__":
    sys.exit(main())
