"""Soak: the whole demo (autopilot on, simulators as child processes) under a CPU hog.

``python -m servotune demo`` runs as a subprocess, exactly as a user starts it; the
test spawns one busy process per core for ``SOAK_S`` seconds, then watches the links
recover, presses STOP and checks it on the simulated devices themselves (the records
their processes write) and in the telemetry. Asserted are truths, not speeds:

* no dead link: every link is connected again within ``RECOVER_S`` after the hog
  stops, and its samples flow;
* every link state is truthful: an axis shown ``ok`` on a link that the status calls
  ``connected`` for two polls in a row delivered samples in that time (no more than
  ``STALE_S`` without; a silent device must be shown offline, the hub's rule);
* no reset banner without a real reset (nothing power-cycles a device here);
* STOP reaches every axis: the API reports no failure, each device's own record
  shows it stopped, and so does the last telemetry.

Printed (``-s`` shows them): CPU per process, link rates as a share of the wire
limit, error counters, events by level and the most frequent event texts, and the
load average - machine-dependent figures that are reported, never asserted.
"""

from __future__ import annotations

import json
import time
import urllib.error
from collections import Counter
from pathlib import Path
from typing import Any

import pytest

from servotune.perf.demo import (
    BackgroundThread,
    StreamWatcher,
    cpu_hog,
    cpu_seconds,
    demo_server,
    get_json,
    load_average,
    post_json,
    process_name,
    process_tree,
)

pytestmark = pytest.mark.slow

SOAK_S = 180.0  # "several minutes": three, the CI run can afford that
POLL_S = 1.0
STALE_S = 5.0  # a connected link goes no longer than this without a sample
RECOVER_S = 30.0
STOP_S = 15.0


OBSERVER_STALL_S = 1.0  # a gap of the test's own clock thread this long is a stall


class ObserverStalls(BackgroundThread):
    """A thread of this test process that ticks every 50 ms and keeps every gap between
    two ticks longer than ``OBSERVER_STALL_S``: the observer itself (or the whole
    machine) was held off the CPU then. Across such a gap the test cannot tell a
    silent link from samples it has not read yet, so it does not judge; the server's
    own stalls do not hold this thread (another process) and stay judged."""

    join_s = 2.0

    def __init__(self) -> None:
        super().__init__("stall-meter")
        self.gaps: list[tuple[float, float]] = []  # (start, end), monotonic

    def _run(self) -> None:
        last = time.monotonic()
        while not self._stop.wait(0.05):
            now = time.monotonic()
            if now - last > OBSERVER_STALL_S:
                self.gaps.append((last, now))
            last = now

    def since(self, t: float) -> list[tuple[float, float]]:
        """The gaps that ended after ``t`` (a gap still open ends at the next tick, so
        the caller also checks how late its own poll came)."""
        return [gap for gap in list(self.gaps) if gap[1] > t]


def _read_record(path: Path) -> dict[str, Any]:
    for _ in range(20):
        try:
            record: dict[str, Any] = json.loads(path.read_text())
            return record
        except (OSError, ValueError):
            time.sleep(0.1)
    raise AssertionError(f"no readable simulator record at {path}")


def _device_stopped(device: str, record: dict[str, Any]) -> list[str]:
    """What in a simulator's record says the device is not (yet) stopped."""
    problems: list[str] = []
    data = record["device"]
    if device == "slap2":  # STOP holds in pm where the shaft is, or braked off
        for module in data["modules"]:
            # In pm the loop drives the PWM to hold the position: only open loop must be 0.
            if module["vm"] or module["moving"] or (module["pwm"] and not module["pm"]):
                problems.append(f"SLAP2 module {module['address']}: {module}")
    elif device == "z1100":  # stop: decelerate to standstill
        for axis in data["axes"]:
            if axis["running"] or axis["speed_counts_s"] != 0.0:
                problems.append(f"Z1100 axis {axis['axis']}: {axis}")
    elif device == "ep7047":  # ramp down, then Enable off
        for slave in data["slaves"]:
            if slave["busy"] or slave["enabled"] or slave["velocity_counts_s"] != 0.0:
                problems.append(f"EP7047 slave {slave['position']}: {slave}")
    return problems


STOPPED_FLAGS = {
    "slap2": ("vm", "move"),
    "z1100": ("running",),
    "ep7047": ("busy", "enable_out", "execute_out"),
}


def test_soak_demo_under_a_cpu_hog(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    log = tmp_path / "server.log"
    lies: list[str] = []
    load_seen: list[float] = []
    with demo_server(data_dir=data_dir, log_path=log, connect_timeout_s=120) as server:
        base = server.base_url
        axes = get_json(f"{base}/api/axes")
        links = get_json(f"{base}/api/links")
        axes_of = {link["id"]: [a["id"] for a in axes if a["link"] == link["id"]] for link in links}
        device_of = {link["id"]: link["device"] for link in links}
        with StreamWatcher(base) as stream:
            pids = process_tree(server.pid)
            names = {pid: "server" if pid == server.pid else process_name(pid) for pid in pids}
            cpu_start = {pid: cpu_seconds(pid) for pid in pids}
            ratios: dict[str, list[float]] = {link_id: [] for link_id in axes_of}
            first_status = {i: server.link_status(i) for i in axes_of}
            connected_polls = Counter[str]()
            not_ok = Counter[tuple[str, str]]()
            samples_before: dict[str, int] = {}
            observer_skips = 0
            polls = 0
            unanswered: list[float] = []
            last_progress = {a: time.monotonic() for ids in axes_of.values() for a in ids}
            t0 = time.monotonic()
            with cpu_hog(), ObserverStalls() as stalls:
                while time.monotonic() - t0 < SOAK_S:
                    asleep = time.monotonic()
                    time.sleep(POLL_S)
                    load_seen.append(load_average()[0])
                    now = time.monotonic()
                    held_s = now - asleep - POLL_S
                    if held_s > OBSERVER_STALL_S:
                        stalls.gaps.append((asleep + POLL_S, now))
                    with stream.lock:
                        counts = dict(stream.counts.samples)
                        health = dict(stream.counts.health)
                    for link_id, axis_ids in axes_of.items():
                        polls += 1
                        try:
                            status = server.link_status(link_id)
                        except (TimeoutError, urllib.error.URLError) as error:
                            if isinstance(error, urllib.error.URLError) and not isinstance(
                                error.reason, TimeoutError
                            ):
                                raise
                            # The server did not answer in 5 s (its log says why: "the
                            # server did not run for N s"). Nothing was claimed meanwhile:
                            # judged again from now on, and counted in the report.
                            unanswered.append(now - t0)
                            for axis_id in axis_ids:
                                last_progress[axis_id] = time.monotonic()
                            continue
                        if status["wire_limit_hz"] > 0:
                            ratios[link_id].append(status["rate_hz"] / status["wire_limit_hz"])
                        for axis_id in axis_ids:
                            if counts.get(axis_id, 0) > samples_before.get(axis_id, 0):
                                last_progress[axis_id] = now
                        if status["state"] == "connected":
                            connected_polls[link_id] += 1
                            for axis_id in axis_ids:
                                if health.get(axis_id) != "ok":
                                    # shown paused (a capture), offline (the hub's
                                    # "no telemetry" rule) or reset: not claiming
                                    # samples, the truth told by the axis itself
                                    not_ok[axis_id, health.get(axis_id, "?")] += 1
                                    last_progress[axis_id] = now
                                    continue
                                stale_s = now - last_progress[axis_id]
                                if connected_polls[link_id] < 2 or stale_s <= STALE_S:
                                    continue
                                since = last_progress[axis_id]
                                if stalls.since(since) or stream.down_since(since):
                                    # Not judged: the observer was stalled (see
                                    # ObserverStalls) or its websocket was down (it
                                    # connects again, as the web client does; the
                                    # samples meanwhile never reached it); judged
                                    # again from now on.
                                    observer_skips += 1
                                    last_progress[axis_id] = now
                                    continue
                                lies.append(
                                    f"{link_id} says connected but {axis_id} had no "
                                    f"sample for {stale_s:.1f} s (t={now - t0:.0f} s; "
                                    f"status {status['rate_hz']:.1f} Hz, errors "
                                    f"{status['errors']}, {status['message']!r})"
                                )
                        else:
                            connected_polls[link_id] = 0
                            for axis_id in axis_ids:
                                last_progress[axis_id] = now  # not claiming anything
                    samples_before = counts
            soak_s = time.monotonic() - t0
            gaps = sorted(stalls.gaps)
            cpu: dict[str, float] = {}
            for pid in pids:
                before, after = cpu_start[pid], cpu_seconds(pid)
                if before is not None and after is not None:
                    cpu[f"{names[pid]} ({pid})"] = (after - before) / soak_s
            # No dead link: all connected again (and delivering) once the hog is gone.
            deadline = time.monotonic() + RECOVER_S
            states: dict[str, str] = {}
            while time.monotonic() < deadline:
                states = {i: server.link_status(i)["state"] for i in axes_of}
                if all(state == "connected" for state in states.values()):
                    break
                time.sleep(0.5)
            final_status = {i: server.link_status(i) for i in axes_of}
            with stream.lock:
                before_stop = dict(stream.counts.samples)
            time.sleep(STALE_S)  # the same bound as for truthfulness
            with stream.lock:
                flowing = {
                    a: stream.counts.samples.get(a, 0) > before_stop.get(a, 0)
                    for ids in axes_of.values()
                    for a in ids
                }
            # STOP, then the devices' own records and the telemetry.
            stop_reply = post_json(f"{base}/api/stop")
            deadline = time.monotonic() + STOP_S
            not_stopped: list[str] = []
            while time.monotonic() < deadline:
                not_stopped = []
                for device in set(device_of.values()):
                    record = _read_record(data_dir / "sim" / f"{device}-record.json")
                    not_stopped += _device_stopped(device, record)
                if not not_stopped:
                    break
                time.sleep(0.25)
            time.sleep(1.0)  # telemetry after the stop
            with stream.lock:
                flags = {a: dict(f) for a, f in stream.counts.last_flags.items()}
                events = Counter(stream.counts.events)
                resets = Counter(stream.counts.resets)
                texts = Counter(_kind_of(text) for text in stream.counts.event_texts)
            stream_error = stream.error
            drops = list(stream.drops)

    report = [
        f"soak {soak_s:.0f} s with a CPU hog on every core; load average (1 min) "
        f"min {min(load_seen):.1f} max {max(load_seen):.1f}",
        "CPU per process (CPU s per s): "
        + ", ".join(f"{name} {share:.3f}" for name, share in cpu.items()),
    ]
    for link_id, values in ratios.items():
        values = sorted(values)
        median = values[len(values) // 2] if values else 0.0
        errors = final_status[link_id]["errors"] - first_status[link_id]["errors"]
        extra = {
            k: v
            for k, v in final_status[link_id].items()
            if k not in ("type", "link", "state", "message", "rate_hz", "wire_limit_hz")
        }
        report.append(
            f"{link_id}: rate/wire median {median:.0%} min {values[0] if values else 0:.0%}; "
            f"errors +{errors}; final {final_status[link_id]['state']} {extra}"
        )
    held = ", ".join(f"{end - start:.1f} s at t={start - t0:.0f} s" for start, end in gaps)
    report.append(
        f"observer stalls over {OBSERVER_STALL_S:g} s: {held or 'none'}; "
        f"axis judgements skipped across them: {observer_skips}"
    )
    report.append(
        f"websocket drops (connected again): {len(drops)}"
        + "".join(
            f"; at t={lost - t0:.0f} s for {back - lost if back else 0:.1f} s: {why}"
            for lost, back, why in drops[:5]
        )
    )
    report.append(
        f"status polls unanswered in 5 s: {len(unanswered)} of {polls}"
        + "".join(f"; t={t:.0f} s" for t in unanswered[:5])
    )
    report.append(f"events by level: {dict(events)}; reset banners: {dict(resets)}")
    report.append(
        "polls with an axis of a connected link shown not ok: "
        + (", ".join(f"{a} {h} x{n}" for (a, h), n in sorted(not_ok.items())) or "none")
    )
    report.append(
        "most frequent events: " + "; ".join(f"{n}x {t}" for t, n in texts.most_common(8))
    )
    print("\n" + "\n".join(report))

    assert stream_error is None, f"the websocket failed for good: {stream_error}"
    # A link stuck in "error" after an internal error is a supervision bug (supervision,
    # drivers/ and hub/hub.py, another branch): this assertion stays, whoever fixes it.
    assert all(state == "connected" for state in states.values()), (
        f"dead link(s) {RECOVER_S:g} s after the hog stopped: {states}\n{_tail(log)}"
    )
    assert all(flowing.values()), f"connected but no samples: {flowing}"
    assert not lies, "link state not truthful:\n" + "\n".join(lies[:20])
    # A server that stalls now and then is reported; one that mostly does not answer is not
    # a soak that judged anything.
    assert len(unanswered) <= polls // 10, f"{len(unanswered)} of {polls} status polls unanswered"
    assert stop_reply == {"failed": []}, stop_reply
    assert not not_stopped, "STOP did not reach every axis:\n" + "\n".join(not_stopped)
    for axis in axes:
        device = axis["device"]
        for flag in STOPPED_FLAGS[device]:
            assert not flags.get(axis["id"], {}).get(flag), (
                axis["id"],
                flag,
                flags.get(axis["id"]),
            )
    # Needs the drivers' false-alarm rules (docs/architecture.md, Supervision): a slow
    # host alone must not produce "reset - settings may be lost". Nothing resets here.
    assert sum(resets.values()) == 0, f"reset banner(s) without a reset: {dict(resets)}"


def _kind_of(text: str) -> str:
    """An event text without its numbers and quoted bytes, to count by kind."""
    head = text.split(":", 2)
    kind = ":".join(head[:2]) if len(head) > 2 else text
    return "".join("#" if ch.isdigit() else ch for ch in kind)[:90]


def _tail(path: Path, lines: int = 40) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no server log)"
