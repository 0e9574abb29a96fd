"""FRF closed-loop bias at the low tones against the truth, and how many tones are trusted.

Usage (from the repository root, with the project's venv):
    .venv/bin/python scripts/perf_frf_trust.py [--repeats 5] [--hog 2] [--gains 600/10/1500]
        [--gains autotune] [--port 18791] [--json out.json]

Starts ``servotune demo --no-autopilot`` on a port of its own (a fresh data directory,
``servotune.perf.demo.demo_server``), and on the loaded SLAP2 axis ("SLAP2 #1 with
load") writes each set of gains and runs
the bench's ``frequency_response`` test (1-10 Hz, amplitude 200, 6 s: the case that
showed the bias) ``--repeats`` times through the REST API, as a user's browser does. ``autotune``
as gains: the auto-tune's proposal, identified once on the demo (from 600/10/1500, the
default margins) before the runs; nothing is accepted, the gains are written as any
others. ``--hog N`` runs N busy-looping processes (``servotune.perf.demo.cpu_hog``) for
the whole measurement: the loaded case.

For every tone up to ``--top-hz`` (5) each run prints the product's |T| (dB) and
phase, whether it is trusted and its stated bound (``error_db`` / ``error_deg``), and
the truth twice, never the product's own estimate:
* ``fit``: a per-tone least-squares fit (``tuning.frf.tone_fit``) of the run's own
  position column against its own setpoint column over the analysed whole periods;
* ``sim``: the simulated module's own closed loop at the same tones with the same gains
  and the demo's loaded plant (``tests/support/frf_harness.simulator_response``: the multisine
  sent at every controller tick, no wire, no host).
A tone marked trusted whose reading differs from the truth by more than its stated
bound (against ``fit``: plus the fit's own two standard errors, printed) is listed as a
VIOLATION (with the run id: the run stays in the demo's data directory, printed at
the end; ``--from-data`` analyses its runs again). The load average is printed with
each run. A benchmark, not a test: what it measures depends on the machine.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the physical check's own simulator response (tests/support)

from tests.support.frf_harness import simulator_response  # noqa: E402

from servotune.bench.frf import analyse_run  # noqa: E402
from servotune.devices.slap2.sim.demo import SLAP2_LOADED  # noqa: E402
from servotune.perf.demo import cpu_hog, demo_server, load_average  # noqa: E402
from servotune.storage import Storage  # noqa: E402
from servotune.tuning.frf import tone_fit  # noqa: E402
from servotune.tuning.frfrun import Excitation  # noqa: E402

AXIS_NAME = "SLAP2 #1 with load"
FRF_REQUEST = {
    "kind": "frequency_response",
    "amplitude": 200,
    "low_hz": 1.0,
    "high_hz": 10.0,
    "duration_s": 6.0,
}


def loadavg() -> str:
    return " ".join(f"{x:.2f}" for x in load_average())


class Api:
    def __init__(self, base: str) -> None:
        self.http = httpx.Client(base_url=base, timeout=120)
        token = self.http.get("/api/auth/session").json().get("csrf_token", "")
        self.http.headers["X-CSRF-Token"] = token

    def call(self, method: str, path: str, **kw: Any) -> Any:
        r = self.http.request(method, path, **kw)
        if r.status_code >= 400:
            raise RuntimeError(f"{method} {path}: {r.status_code} {r.text}")
        return r.json() if r.content else None

    def axis(self, name: str) -> str:
        for a in self.call("GET", "/api/axes"):
            if a.get("name") == name:
                return str(a["id"])
        raise RuntimeError(f"no axis named {name!r}")

    def write_gains(self, axis: str, gains: dict[str, int]) -> None:
        self.call("PATCH", f"/api/axes/{axis}/params?confirm_unstable=true", json=gains)

    def frf_run(self, axis: str) -> tuple[dict[str, Any], dict[str, Any]]:
        for attempt in range(3):
            try:
                run_id = self.call("POST", f"/api/axes/{axis}/bench/runs", json=FRF_REQUEST)["id"]
                break
            except RuntimeError as exc:  # the axis still busy after the last run
                if attempt == 2:
                    raise
                print(f"    start refused ({exc}); again in 2 s", flush=True)
                time.sleep(2)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            time.sleep(0.5)
            meta = self.call("GET", f"/api/bench/runs/{run_id}")
            if meta["status"] != "recording":
                break
        run = self.call("GET", f"/api/bench/runs/{run_id}")
        if run["status"] != "complete":
            return run, {"measured": None, "measured_problem": run.get("message")}
        frf = self.call("GET", f"/api/bench/runs/{run_id}/frf")
        return run, frf


def truth_fit(run: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(tones, T, bound in dB) from the run's own position against its own setpoint
    column over the analysed whole periods. The fit is linear, so the position's tones
    are the setpoint's plus the following error's: ``T = 1 + E/U``; the bound is two
    standard errors of the following error's fit over |U| (the position's own residual
    carries the setpoint's, which cancels in the ratio)."""
    exc = run["excitation"]
    cols = run["columns"]
    ip, isp = cols.index("position"), cols.index("setpoint")
    t0 = float(run.get("t0_s") or 0.0)
    period = float(exc["period_s"])
    start = int(exc.get("settle_periods", 1)) * period
    rows = [r for r in run["samples"] if r[ip] is not None and r[isp] is not None]
    t = np.array([r[0] for r in rows]) - t0
    whole = int((t[-1] - start) / period + 1e-9)
    keep = (t >= start) & (t <= start + whole * period)
    tones = np.asarray(exc["tones_hz"])
    ref = float(t[keep].mean())
    position = np.array([r[ip] for r in rows])[keep]
    setpoint = np.array([r[isp] for r in rows])[keep]
    u = tone_fit(t[keep], setpoint, tones, ref)
    e = tone_fit(t[keep], position - setpoint, tones, ref)
    relative = 2 * e.standard_error / np.abs(u.amplitude)
    return tones, np.asarray(1 + e.amplitude / u.amplitude), 20 * np.log10(1 + relative)


def db(x: complex) -> float:
    return 20 * math.log10(abs(x))


def deg(x: complex) -> float:
    return math.degrees(math.atan2(x.imag, x.real))


def measure(
    api: Api, axis: str, label: str, gains: dict[str, int], repeats: int, top_hz: float
) -> list[dict[str, Any]]:
    api.write_gains(axis, gains)
    time.sleep(1.0)
    g = (gains["kp"], gains["ki"], gains["kd"])
    out = []
    for i in range(repeats):
        load_before = loadavg()
        run, frf = api.frf_run(axis)
        row = compare(run, frf, label, g, top_hz)
        row["repeat"] = i + 1
        row["load"] = f"{load_before} -> {loadavg()}"
        out.append(row)
        print_run(row)
        time.sleep(1.0)
    return out


def compare(
    run: dict[str, Any],
    frf: dict[str, Any],
    label: str,
    g: tuple[int, int, int],
    top_hz: float,
) -> dict[str, Any]:
    """One run's tones up to ``top_hz``: the product's reading against both truths."""
    m = frf.get("measured")
    row: dict[str, Any] = {
        "gains": label,
        "repeat": 0,
        "run_id": run["id"],
        "load": "",
        "status": run["status"],
        "problem": frf.get("measured_problem") or run.get("message"),
        "tones": [],
    }
    if m is not None:
        cl = m["closed_loop"]
        f = np.asarray(cl["frequency_hz"])
        tones, t_fit, fit_bound_db = truth_fit(run)
        t_sim = simulator_response(SLAP2_LOADED, g, Excitation.from_dict(run["excitation"]))
        row["input_check_counts"] = m.get("input_check_counts")
        row["rate_hz"] = m.get("sample_rate_hz")
        for k, fk in enumerate(f):
            if fk > top_hz + 1e-9:
                continue
            j = int(np.argmin(np.abs(tones - fk)))
            mag, ph = cl["magnitude_db"][k], cl["phase_deg"][k]
            e_db, e_deg = cl["error_db"][k], cl["error_deg"][k]
            tone = {
                "hz": round(float(fk), 2),
                "db": mag,
                "deg": ph,
                "trusted": cl["trusted"][k],
                "why": cl["not_trusted_because"][k],
                "error_db": e_db,
                "error_deg": e_deg,
                "fit_db": round(db(t_fit[j]), 3),
                "fit_bound_db": round(float(fit_bound_db[j]), 3),
                "fit_deg": round(deg(t_fit[j]), 2),
                "sim_db": round(db(t_sim[j]), 3),
                "sim_deg": round(deg(t_sim[j]), 2),
            }
            for truth in ("fit", "sim"):
                off_db = abs(mag - tone[f"{truth}_db"])
                off_deg = abs((ph - tone[f"{truth}_deg"] + 180) % 360 - 180)
                # the fit's own uncertainty widens what "off" means against it; the
                # simulator's response (every tick, no wire, no noise) has none
                slack_db = tone["fit_bound_db"] if truth == "fit" else 0.0
                slack_deg = math.degrees(10 ** (slack_db / 20) - 1)
                off_db, off_deg = off_db - slack_db, off_deg - slack_deg
                tone[f"bias_db_{truth}"] = round(mag - tone[f"{truth}_db"], 3)
                tone[f"bias_deg_{truth}"] = round((ph - tone[f"{truth}_deg"] + 180) % 360 - 180, 2)
                if tone["trusted"] and (
                    e_db is None or off_db > e_db or e_deg is None or off_deg > e_deg
                ):
                    tone.setdefault("violations", []).append(truth)
            row["tones"].append(tone)
    return row


def shifted(run: dict[str, Any], counts: float) -> dict[str, Any]:
    """The run as if the axis had been held ``counts`` further: positions, setpoints,
    the excitation's y0 and every target sent moved by the same amount (the loop is
    the same; a bias once grew with where the axis stood)."""
    cols = run["columns"]
    idx = [cols.index(c) for c in ("position", "setpoint") if c in cols]
    samples = [
        [v + counts if i in idx and v is not None else v for i, v in enumerate(row)]
        for row in run["samples"]
    ]
    exc = dict(run["excitation"])
    exc["y0"] = float(exc["y0"]) + counts
    exc["sent"] = [[s[0], s[1] + counts, *s[2:]] for s in exc.get("sent", [])]
    return run | {"samples": samples, "excitation": exc}


def from_data(data_dir: Path, top_hz: float, shift: float = 0.0) -> list[dict[str, Any]]:
    """The stored frequency-response runs of a demo data directory, analysed again as
    ``GET /api/bench/runs/{id}/frf`` does (``bench.frf.analyse_run``), optionally
    ``shifted``."""
    storage = Storage(data_dir / "servotune.db")
    out = []
    for run_id in storage.run_ids():
        run = storage.get_run(run_id)
        if run is None or (run.get("test") or {}).get("kind") != "frequency_response":
            continue
        if shift and run["status"] == "complete":
            run = shifted(run, shift)
        params = run.get("params") or {}
        g = (int(params["kp"]), int(params["ki"]), int(params["kd"]))
        frf = analyse_run(run, None) if run["status"] == "complete" else {"measured": None}
        row = compare(run, frf, "{}/{}/{}".format(*g), g, top_hz)
        out.append(row)
        print_run(row)
    return out


def print_run(row: dict[str, Any]) -> None:
    tones = row["tones"]
    trusted = sum(1 for t in tones if t["trusted"])
    head = (
        f"  {row['gains']:>13} #{row['repeat']} run {row['run_id']} load {row['load']} "
        f"{row['status']}"
    )
    if not tones:
        print(f"{head}: no response ({row['problem']})", flush=True)
        return
    print(
        f"{head}: {trusted}/{len(tones)} trusted, input check {row.get('input_check_counts')} "
        f"counts, {row.get('rate_hz')} samples/s",
        flush=True,
    )
    for t in tones:
        flag = " VIOLATION vs " + "+".join(t["violations"]) if t.get("violations") else ""
        why = "" if t["trusted"] else f" ({t['why']})"
        print(
            f"    {t['hz']:4.1f} Hz {t['db']:+6.2f} dB {t['deg']:+6.1f} deg "
            f"{'T' if t['trusted'] else '-'} ±{t['error_db']} dB ±{t['error_deg']} deg | "
            f"bias vs fit {t['bias_db_fit']:+.2f} dB {t['bias_deg_fit']:+.1f} deg "
            f"(fit ±{t['fit_bound_db']:.2f} dB), "
            f"vs sim {t['bias_db_sim']:+.2f} dB {t['bias_deg_sim']:+.1f} deg"
            f"{why}{flag}",
            flush=True,
        )


def autotune_gains(api: Api, axis: str) -> dict[str, int]:
    api.write_gains(axis, {"kp": 600, "ki": 10, "kd": 1500})
    time.sleep(1.5)
    body = {"max_pwm": 60, "max_distance_counts": 4000, "response": "no_overshoot"}
    proposal = api.call("POST", f"/api/axes/{axis}/autotune/identify", json=body)
    gains = {k: int(v) for k, v in proposal["gains"].items()}
    m = proposal.get("margins") or {}
    print(
        f"  auto-tune proposal {gains}: PM {m.get('phase_margin_deg')} deg, "
        f"GM {m.get('gain_margin_db')} dB, meets target {m.get('meets_target')}",
        flush=True,
    )
    return gains


def parse_gains(text: str) -> dict[str, int]:
    kp, ki, kd = (int(x) for x in text.split("/"))
    return {"kp": kp, "ki": ki, "kd": kd}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--hog", type=int, default=0, help="busy-looping processes meanwhile")
    ap.add_argument("--gains", action="append", help="kp/ki/kd or 'autotune' (repeatable)")
    ap.add_argument("--autotune-gains", help="kp/ki/kd to use for 'autotune' (skip identify)")
    ap.add_argument("--top-hz", type=float, default=5.0)
    ap.add_argument("--port", type=int, default=18791)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--from-data", type=Path, help="analyse a data directory's runs again")
    ap.add_argument(
        "--shift", type=float, default=0.0, help="with --from-data: as if held this far away"
    )
    args = ap.parse_args()
    if args.from_data:
        report(from_data(args.from_data, args.top_hz, args.shift), args.json, args.from_data)
        return
    sets = args.gains or ["600/10/1500", "autotune"]
    data_dir = Path(tempfile.mkdtemp(prefix="frf_trust_"))
    print(f"demo data: {data_dir}; hog {args.hog}; load {loadavg()}", flush=True)
    results: list[dict[str, Any]] = []
    with demo_server(
        port=args.port, data_dir=data_dir, autopilot=False, log_path=data_dir / "demo.log"
    ) as server:
        api = Api(server.base_url)
        axis = api.axis(AXIS_NAME)
        time.sleep(2.0)
        with cpu_hog(args.hog) if args.hog else contextlib.nullcontext():
            for text in sets:
                if text == "autotune":
                    gains = (
                        parse_gains(args.autotune_gains)
                        if args.autotune_gains
                        else autotune_gains(api, axis)
                    )
                    label = "{kp}/{ki}/{kd}".format(**gains)
                else:
                    gains, label = parse_gains(text), text
                results += measure(api, axis, label, gains, args.repeats, args.top_hz)
    report(results, args.json, data_dir)


def report(results: list[dict[str, Any]], out: Path | None, data_dir: Path) -> None:
    violations = [
        (r["run_id"], t["hz"], t["violations"])
        for r in results
        for t in r["tones"]
        if t.get("violations")
    ]
    print(f"violations (trusted, off by more than the stated bound): {violations or 'none'}")
    print("summary per gains (1-5 Hz; bias = product - simulator, worst |bias|):")
    for label in dict.fromkeys(r["gains"] for r in results):
        rows = [r for r in results if r["gains"] == label]
        tones = [t for r in rows for t in r["tones"]]
        trusted = [t for t in tones if t["trusted"]]

        def worst(ts: list[dict[str, Any]], key: str) -> str:
            return f"{max((abs(t[key]) for t in ts), default=math.nan):.2f}"

        print(
            f"  {label}: {sum(1 for r in rows if r['tones'])}/{len(rows)} runs analysed, "
            f"trusted per run {[sum(t['trusted'] for t in r['tones']) for r in rows if r['tones']]}"
            f" = {len(trusted)}/{len(tones)} tones; all tones {worst(tones, 'bias_db_sim')} dB "
            f"{worst(tones, 'bias_deg_sim')} deg, trusted {worst(trusted, 'bias_db_sim')} dB "
            f"{worst(trusted, 'bias_deg_sim')} deg; vs fit: all {worst(tones, 'bias_db_fit')} dB, "
            f"trusted {worst(trusted, 'bias_db_fit')} dB; stated bounds of the trusted "
            f"{min((t['error_db'] for t in trusted), default=math.nan):.2f}.."
            f"{max((t['error_db'] for t in trusted), default=math.nan):.2f} dB"
        )
    if out:
        out.write_text(json.dumps(results, indent=1))
    print(f"runs kept in {data_dir}")


if __name__ == "__main__":
    main()
