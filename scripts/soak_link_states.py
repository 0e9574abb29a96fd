"""Soak the demo beside a CPU hog and count false link states.

Starts the demo server (all three simulated devices), puts ``HOGS`` busy loops beside
it, polls every link's status once a second for ``SECONDS`` (tolerant of a server
that stalls), and counts the transitions to ``error`` in the server's log. No device is
cut during the soak, so every ``error`` is a false one.

usage: .venv/bin/python scripts/soak_link_states.py SECONDS LOG_PATH [HOGS=2]
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

from servotune.perf.demo import cpu_hog, demo_server


def _get(url: str) -> Any:
    with urllib.request.urlopen(url, timeout=30) as reply:
        return json.load(reply)


def main() -> None:
    seconds = float(sys.argv[1])
    log = Path(sys.argv[2])
    hogs = int(sys.argv[3]) if len(sys.argv) > 3 else 2
    loads: list[float] = []
    states: dict[str, dict[str, int]] = {}
    unanswered = 0
    with demo_server(log_path=log) as server:
        time.sleep(5)
        with cpu_hog(hogs) if hogs else contextlib.nullcontext():
            time.sleep(2)
            started = time.monotonic()
            while time.monotonic() - started < seconds:
                loads.append(os.getloadavg()[0])
                try:
                    for link in _get(f"{server.base_url}/api/links"):
                        state = _get(f"{server.base_url}/api/links/{link['id']}/status")["state"]
                        counts = states.setdefault(link["id"], {})
                        counts[state] = counts.get(state, 0) + 1
                except OSError:
                    unanswered += 1
                time.sleep(1)
            ran_s = time.monotonic() - started
    errors = [
        line
        for line in log.read_text(errors="replace").splitlines()
        if re.search(r"link \S+: error", line)
    ]
    print(
        f"{hogs} hogs, {ran_s:.0f} s, load {min(loads):.1f}-{max(loads):.1f}; "
        f"status polls unanswered in 30 s: {unanswered}"
    )
    print("states sampled once a second:", states)
    print(f"transitions to error: {len(errors)}")
    for line in errors[:20]:
        print("  ", line)


if __name__ == "__main__":
    main()
