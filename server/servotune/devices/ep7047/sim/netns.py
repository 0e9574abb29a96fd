"""A network namespace and a veth pair for the EP7047 on a real wire (tests, benchmarks
and ``servotune demo --ethercat-wire``), created and removed by name.

``veth_pair()`` creates ``stn<id>`` (a namespace) and a veth pair ``stm<id>`` (the
master's end, in this namespace) / ``sts<id>`` (the slave's end, moved into the
namespace), both up, IPv6 off (no router solicitations on the wire), and removes both
by their names afterwards. The id is this process's pid and a counter, so parallel runs
do not collide. ``slave_process()`` starts ``servotune sim ep7047 --ifname`` inside the
namespace with a control socket.

CI runs as root; where CAP_NET_ADMIN is missing, ``netns_problem()`` gives the reason
(tests skip with it, the demo says it and keeps the seam).
"""

from __future__ import annotations

import contextlib
import itertools
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from servotune.devices.ep7047.sim.wire_loop import control_request

CAP_NET_ADMIN = 12
_counter = itertools.count()


def _caps() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("CapEff:"):
            return int(line.split()[1], 16)
    return 0


def netns_problem() -> str | None:
    """Why this process cannot make namespaces and veth pairs, or None."""
    if not sys.platform.startswith("linux"):
        return "network namespaces need Linux"
    if not (_caps() >> CAP_NET_ADMIN) & 1:
        return "creating a network namespace and a veth pair needs CAP_NET_ADMIN (run as root)"
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is not installed"
    return None


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], check=check, capture_output=True, text=True, timeout=10)


@dataclass(frozen=True)
class VethPair:
    namespace: str
    master_if: str
    slave_if: str

    def set_master_link(self, up: bool) -> None:
        """Pull (False) or plug (True) the cable: the master's end down or up."""
        _ip("link", "set", self.master_if, "up" if up else "down")


@contextlib.contextmanager
def veth_pair() -> Iterator[VethPair]:
    suffix = f"{os.getpid() % 100000}{next(_counter)}"
    pair = VethPair(f"stn{suffix}", f"stm{suffix}", f"sts{suffix}")
    # Leftovers of a killed run that had the same pid: removed by name first.
    _ip("link", "del", pair.master_if, check=False)
    _ip("netns", "del", pair.namespace, check=False)
    try:
        _ip("netns", "add", pair.namespace)
        _ip(
            "link",
            "add",
            pair.master_if,
            "type",
            "veth",
            "peer",
            "name",
            pair.slave_if,
            "netns",
            pair.namespace,
        )
        for path in (f"/proc/sys/net/ipv6/conf/{pair.master_if}/disable_ipv6",):
            with contextlib.suppress(OSError):
                Path(path).write_text("1")
        _ip(
            "netns",
            "exec",
            pair.namespace,
            "sysctl",
            "-q",
            "-w",
            f"net.ipv6.conf.{pair.slave_if}.disable_ipv6=1",
            check=False,
        )
        _ip("link", "set", pair.master_if, "up")
        _ip("-n", pair.namespace, "link", "set", pair.slave_if, "up")
        _ip("-n", pair.namespace, "link", "set", "lo", "up")
        yield pair
    finally:
        _ip("link", "del", pair.master_if, check=False)
        _ip("netns", "del", pair.namespace, check=False)


@dataclass
class SlaveProcess:
    process: subprocess.Popen[str]
    control_path: str
    pair: VethPair

    def control(self, op: str, **args: Any) -> dict[str, Any]:
        return control_request(self.control_path, {"op": op, **args})

    def record(self) -> dict[str, Any]:
        answer = self.control("record")
        result: dict[str, Any] = answer["ok"]
        return result

    def signal(self, sig: int) -> None:
        self.process.send_signal(sig)

    @property
    def pid(self) -> int:
        """The simulator's process id (``ip netns exec`` execs it: the same process)."""
        return self.process.pid

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(5)


@contextlib.contextmanager
def slave_process(
    pair: VethPair, tmp_path: Path, *extra: str, name: str = "slave"
) -> Iterator[SlaveProcess]:
    control_path = str(tmp_path / f"{name}.ctl")
    command = [
        "ip",
        "netns",
        "exec",
        pair.namespace,
        sys.executable,
        "-m",
        "servotune",
        "sim",
        "ep7047",
        "--ifname",
        pair.slave_if,
        "--control",
        control_path,
        *extra,
    ]
    log_path = tmp_path / f"{name}.log"
    with log_path.open("w") as log:  # a file, not a pipe nobody reads (it could fill)
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, text=True)
    slave = SlaveProcess(process, control_path, pair)
    try:
        deadline = time.monotonic() + 30
        while not Path(control_path).exists():
            if process.poll() is not None:
                raise RuntimeError(f"the wire simulator ended: {log_path.read_text()}")
            if time.monotonic() > deadline:
                raise RuntimeError("the wire simulator did not start within 30 s")
            time.sleep(0.05)
        yield slave
    finally:
        slave.stop()
