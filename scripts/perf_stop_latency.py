"""STOP latency and telemetry gaps of the demo while a large run is imported and exported.

The rule: a STOP must be answered (and on the wire) within 50 ms and the
telemetry must not pause for more than 100 ms while any API request runs. This starts
``servotune demo`` (autopilot off, so STOPs do not fight the moves) as a child process
and, from this process (a client like a browser, not sharing the server's loop):

1. records a short bench move on the SLAP2 axis and takes its ``run.json``;
2. sends a STOP to the EP7047 axis every ``--stop-period-s`` and times each answer
   (the EP7047 driver answers a STOP after the exchange that carried it: the answer
   time bounds the time to the wire);
3. watches the websocket for the EP7047 axis's telemetry and notes every gap;
4. phases: idle, an import of ``--rows`` samples (multipart), the JSON export of the
   imported run, its CSV export. Per phase: STOP count, median, 95th percentile and
   maximum; the largest telemetry gap.

Run: ``PYTHONPATH=server python scripts/perf_stop_latency.py [--rows 250000] [--hog]``.
The figures depend on the machine (its load average is printed); compare runs made on
the same machine state. Not a test: ``tests/integration/perf/test_loop_latency.py``
asserts the truths.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import statistics
import sys
import threading
import time
import urllib.request
import uuid
from typing import Any

from servotune.perf.demo import cpu_hog, demo_server, get_json

STOP_AXIS = "demo-ep7047-1"
RUN_AXIS = "demo-slap2-1"


class Client:
    """REST as the dashboard does it (local mode: the CSRF token of the session)."""

    def __init__(self, base_url: str) -> None:
        self.base_url = base_url
        self.token = get_json(f"{base_url}/api/auth/session")["csrf_token"]

    def request(
        self,
        method: str,
        path: str,
        body: bytes | None = None,
        content_type: str = "application/json",
        timeout_s: float = 300.0,
    ) -> tuple[int, bytes]:
        request = urllib.request.Request(
            self.base_url + path,
            data=body,
            headers={"Content-Type": content_type, "X-CSRF-Token": self.token},
            method=method,
        )
        try:
            with urllib.request.urlopen(request, timeout=timeout_s) as response:
                return response.status, response.read()
        except urllib.error.HTTPError as exc:
            return exc.code, exc.read()

    def post_json(self, path: str, value: Any) -> tuple[int, Any]:
        status, data = self.request("POST", path, json.dumps(value).encode())
        return status, json.loads(data) if data else None


def big_csv(meta: dict[str, Any], rows: int) -> bytes:
    columns, flags = meta["columns"], meta["flags"]
    out = io.StringIO()
    out.write(",".join([*columns, *flags]) + "\n")
    values = ",".join(f"{1000.0 + i:.1f}" for i in range(len(columns) - 1))
    flag_text = ",".join("0" for _ in flags)
    for i in range(rows):
        out.write(f"{i * 0.02:.6f},{values},{flag_text}\n")
    return out.getvalue().encode()


def multipart(meta: dict[str, Any], csv_bytes: bytes) -> tuple[bytes, str]:
    boundary = uuid.uuid4().hex
    parts = [
        f'--{boundary}\r\nContent-Disposition: form-data; name="meta"; filename="run.json"\r\n'
        "Content-Type: application/json\r\n\r\n".encode(),
        json.dumps(meta).encode(),
        f'\r\n--{boundary}\r\nContent-Disposition: form-data; name="csv"; '
        'filename="samples.csv"\r\nContent-Type: text/csv\r\n\r\n'.encode(),
        csv_bytes,
        f"\r\n--{boundary}--\r\n".encode(),
    ]
    return b"".join(parts), f"multipart/form-data; boundary={boundary}"


class Stopper(threading.Thread):
    """A STOP every ``period_s``; keeps (sent, latency, status)."""

    def __init__(self, client: Client, period_s: float) -> None:
        super().__init__(name="stopper", daemon=True)
        self.client = client
        self.period_s = period_s
        self.done = threading.Event()
        self.stops: list[tuple[float, float, int]] = []

    def run(self) -> None:
        path = f"/api/axes/{STOP_AXIS}/commands"
        body = json.dumps({"command": "stop"}).encode()
        while not self.done.is_set():
            sent = time.perf_counter()
            status, _ = self.client.request("POST", path, body, timeout_s=30)
            self.stops.append((sent, time.perf_counter() - sent, status))
            self.done.wait(self.period_s)


class TelemetryWatch(threading.Thread):
    """Arrival times of the STOP axis's telemetry messages."""

    def __init__(self, base_url: str) -> None:
        super().__init__(name="telemetry", daemon=True)
        self.url = base_url.replace("http://", "ws://") + "/ws"
        self.done = threading.Event()
        self.times: list[float] = []

    def run(self) -> None:
        from websockets.sync.client import connect
        from websockets.typing import Origin

        origin = Origin(self.url.replace("ws://", "http://", 1).removesuffix("/ws"))
        with connect(self.url, max_size=None, open_timeout=10, origin=origin) as ws:
            while not self.done.is_set():
                try:
                    text = ws.recv(timeout=0.2)
                except TimeoutError:
                    continue
                if isinstance(text, str) and '"telemetry"' in text[:40] and STOP_AXIS in text[:80]:
                    self.times.append(time.perf_counter())


def wait_run(client: Client, run_id: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        _, data = client.request("GET", f"/api/axes/{RUN_AXIS}/bench/runs")
        run = next(r for r in json.loads(data) if r["id"] == run_id)
        if run["status"] != "recording":
            return
        time.sleep(0.1)
    raise SystemExit(f"run {run_id} did not finish")


def report(phases: list[tuple[str, float, float]], stopper: Stopper, watch: TelemetryWatch) -> None:
    gaps = [(b, b - a) for a, b in zip(watch.times, watch.times[1:], strict=False)]
    print(f"{'phase':<14} {'s':>6} {'STOPs':>6} {'median':>8} {'p95':>8} {'max':>8} {'gap max':>8}")
    for name, t_from, t_to in phases:
        latencies = sorted(lat for sent, lat, _ in stopper.stops if t_from <= sent < t_to)
        in_gaps = [g for t, g in gaps if t_from <= t < t_to] or [0.0]
        if not latencies:
            print(f"{name:<14} {t_to - t_from:6.1f}  no STOP answered")
            continue
        p95 = latencies[min(len(latencies) - 1, int(0.95 * len(latencies)))]
        print(
            f"{name:<14} {t_to - t_from:6.1f} {len(latencies):6d} "
            f"{statistics.median(latencies) * 1000:6.0f}ms {p95 * 1000:6.0f}ms "
            f"{latencies[-1] * 1000:6.0f}ms {max(in_gaps) * 1000:6.0f}ms"
        )
    statuses = sorted({status for _, _, status in stopper.stops})
    print(f"STOP answers: {statuses}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", type=int, default=250_000, help="samples in the import")
    parser.add_argument("--stop-period-s", type=float, default=0.1)
    parser.add_argument("--port", type=int, default=None)
    parser.add_argument("--hog", action="store_true", help="a busy process on every core")
    args = parser.parse_args()
    with demo_server(port=args.port, autopilot=False) as server, contextlib.ExitStack() as stack:
        client = Client(server.base_url)
        for _ in range(60):  # a loaded host: the axis may not have telemetry yet
            status, started = client.post_json(
                f"/api/axes/{RUN_AXIS}/bench/runs", {"kind": "move", "distance": 500}
            )
            if status != 409:
                break
            time.sleep(0.5)
        if status != 202:
            print(f"could not start the bench run: {status} {started}", file=sys.stderr)
            return 1
        wait_run(client, started["id"])
        _, meta_bytes = client.request("GET", f"/api/bench/runs/{started['id']}/run.json")
        meta = json.loads(meta_bytes)
        body, content_type = multipart(meta, big_csv(meta, args.rows))
        print(f"import: {len(body) / 1e6:.1f} MB, {args.rows} rows; cores {os.cpu_count()}")
        if args.hog:
            stack.enter_context(cpu_hog())
        watch = TelemetryWatch(server.base_url)
        stopper = Stopper(client, args.stop_period_s)
        watch.start()
        time.sleep(1.0)
        load_before = os.getloadavg()
        stopper.start()
        phases: list[tuple[str, float, float]] = []
        t = time.perf_counter()
        time.sleep(3.0)
        phases.append(("idle", t, time.perf_counter()))
        t = time.perf_counter()
        status, data = client.request(
            "POST", f"/api/axes/{RUN_AXIS}/bench/runs/import", body, content_type
        )
        phases.append(("import", t, time.perf_counter()))
        if status != 201:
            print(f"import failed: {status} {data[:300]!r}", file=sys.stderr)
            return 1
        run_id = json.loads(data)["id"]
        t = time.perf_counter()
        status, data = client.request("GET", f"/api/bench/runs/{run_id}")
        phases.append(("export json", t, time.perf_counter()))
        t = time.perf_counter()
        status, data = client.request("GET", f"/api/bench/runs/{run_id}/samples.csv")
        phases.append(("export csv", t, time.perf_counter()))
        stopper.done.set()
        watch.done.set()
        stopper.join(30)
        watch.join(5)
        load_after = os.getloadavg()
        print(
            f"load average {load_before[0]:.2f} -> {load_after[0]:.2f} (1 min)"
            f"{', CPU hog on every core' if args.hog else ''}"
        )
        report(phases, stopper, watch)
    return 0


if __name__ == "__main__":
    sys.exit(main())
