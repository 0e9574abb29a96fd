"""Draw time of the live scope: 4 plots x 50k points, redraw plus raster (headless Chromium).

Usage:
    python scripts/perf_draw.py DIST_OR_URL [--ab OTHER_DIST_OR_URL] [--rounds N] [--runs N]
                                [--width 1200] [--height 800]

DIST_OR_URL is a built client (a directory such as server/servotune/web_dist, served
here on a free port: the scope lab needs no servotune server) or the URL of a running
server. On a page of that client it mounts the scope lab (window.__servotune.lab: 4 line
plots of 50k samples 1 ms apart and a flag lane, a 50 s window) and times, per redraw:

- rolling: 100 new samples (0.1 s) pushed before each redraw, the window following them,
  as on a live page;
- static: a redraw of unchanged data.

Each time is the script time of ``stack.redraw()`` plus the raster of every canvas,
forced by reading one pixel of each (Chromium records canvas commands and rasterises
them lazily: without the read, a software canvas' raster would fall outside the timing):
wall time (performance.now) and the main thread's CPU time of the same span (``cpu``:
thread timestamps of two trace marks around it; on a loaded machine wall time is
mostly the wait for a core, CPU time stays near the cost of the redraw).
Prints min/p50/p95/max (ms) per round with the load average (on a loaded machine the
min is the least disturbed figure) and the trace-layer redraw counts (whole, shifted,
reused); ``--ab`` alternates two builds
round by round so both see the same machine load. A benchmark, not a test: the figures
depend on the machine and its load.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import http.server
import itertools
import json
import os
import statistics
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from playwright.async_api import Browser, async_playwright

CHROMIUM = "/usr/bin/chromium"
# The data sets: the lab's sine (1000 counts, 0.5 Hz), and the same with +-60 counts of
# noise (a velocity or a following error looks like that: every column spans a range).
DATA = {"smooth": 0, "noisy": 60}

BENCH_JS = """async ({runs, samples, periodS, noise, width, height}) => {
  const plots = 4;
  const lab = window.__servotune.lab({samples, periodS, plots, width, height});
  const frame = () => new Promise((r) => requestAnimationFrame(() => r()));
  const canvases = [...lab.el.querySelectorAll('canvas')];
  const raster = () => { for (const c of canvases) c.getContext('2d').getImageData(0, 0, 1, 1); };
  // Deterministic noise (xorshift32), +-noise counts around the lab's sine.
  let seed = 12345;
  const rnd = () => {
    seed ^= seed << 13; seed ^= seed >>> 17; seed ^= seed << 5;
    return (seed >>> 0) / 4294967296;
  };
  const sine = (t) => 1000 * Math.sin(2 * Math.PI * 0.5 * t);
  const signal = (t) => Math.round(sine(t) + noise * (2 * rnd() - 1));
  const b = lab.buffer;
  if (noise) {
    for (let c = 0; c < plots; c++) {
      const col = b.channels.get(`ch${c}`);
      for (let i = b.start; i < b.end; i++) col[i] = signal(b.t[i]) + c;
    }
  }
  let at = samples;
  const more = (m) => {
    const t = Array.from({length: m}, (_v, k) => (at + k) * periodS);
    const channels = {};
    for (let i = 0; i < plots; i++) channels[`ch${i}`] = t.map((x) => signal(x) + i);
    const move = t.map((_x, k) => (((at + k) % samples) > samples / 3
                                   && ((at + k) % samples) < (2 * samples) / 3 ? 1 : 0));
    at += m;
    return {type: 'telemetry', axis: 'lab', t, channels, flags: {move}};
  };
  await frame(); await frame();
  // A new window length folds the (changed) data afresh.
  lab.stack.windowS = samples * periodS * 0.999; lab.stack.redraw();
  lab.stack.windowS = samples * periodS; lab.stack.redraw();
  await frame();
  // Each timed redraw is bracketed by two trace marks (console.timeStamp), so the
  // benchmark can read the main thread's CPU time of it from a trace as well.
  const time = (fn, phase) => {
    console.timeStamp(`bench-draw:${phase}:0`);
    const t0 = performance.now(); fn(); raster(); const took = performance.now() - t0;
    console.timeStamp(`bench-draw:${phase}:1`);
    return took;
  };
  const rolling = [], still = [];
  for (let i = 0; i < runs; i++) {
    b.push(more(100));
    rolling.push(time(() => lab.stack.redraw(), 'rolling'));
    await frame();
  }
  for (let i = 0; i < runs; i++) {
    still.push(time(() => lab.stack.redraw(), 'static'));
    await frame();
  }
  const q = (a) => {
    a.sort((x, y) => x - y);
    const at_ = (p) => Math.round(a[Math.min(a.length - 1, Math.floor(p * a.length))] * 100) / 100;
    return {min: at_(0), p50: at_(0.5), p95: at_(0.95), max: at_(1)};
  };
  // Trace-layer redraws (whole / shifted / reused) over both phases; null: an older client.
  const layers = lab.stack.layerCounts ? lab.stack.layerCounts() : null;
  lab.destroy();
  return {rolling: q(rolling), static: q(still), layers};
}"""


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


@contextlib.contextmanager
def served(target: str) -> Iterator[str]:
    """The base URL of ``target``: a URL as is, a directory served on a free port."""
    if target.startswith("http"):
        yield target.rstrip("/")
        return
    root = Path(target).resolve()
    assert (root / "index.html").exists(), f"no built client in {root}"

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *_args: Any) -> None:
            pass

    handler = functools.partial(Quiet, directory=str(root))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


def quantiles(values: list[float]) -> dict[str, float]:
    v = sorted(values)
    at = lambda p: round(v[min(len(v) - 1, int(p * len(v)))], 2)  # noqa: E731
    return {"min": at(0), "p50": at(0.5), "p95": at(0.95), "max": at(1)} if v else {}


def cpu_times(events: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """CPU time (ms) of each timed redraw, per phase, from the marks' thread timestamps.

    Thread time counts only what the main thread ran: on a loaded machine it stays near
    the cost of the redraw where wall time grows with the wait for a core."""
    marks: dict[str, list[tuple[int, int]]] = {}
    for e in events:
        msg = (e.get("args", {}).get("data") or {}).get("message", "")
        if e.get("name") == "TimeStamp" and msg.startswith("bench-draw:") and "tts" in e:
            _, phase, edge = msg.split(":")
            marks.setdefault(phase, []).append((int(edge), int(e["tts"])))
    out = {}
    for phase, seq in marks.items():
        pairs = itertools.pairwise(seq)
        took = [(b - a) / 1000 for (ea, a), (eb, b) in pairs if ea == 0 and eb == 1]
        out[phase] = quantiles(took)
    return out


async def measure(browser: Browser, base: str, runs: int, size: tuple[int, int]) -> Any:
    page = await browser.new_page(viewport={"width": 1600, "height": 1000})
    try:
        await page.goto(f"{base}/#/overview")
        await page.wait_for_function("() => !!(window.__servotune && window.__servotune.lab)")
        await page.wait_for_timeout(500)
        cdp = await page.context.new_cdp_session(page)
        events: list[dict[str, Any]] = []
        complete = asyncio.Event()
        cdp.on("Tracing.dataCollected", lambda e: events.extend(e["value"]))
        cdp.on("Tracing.tracingComplete", lambda _e: complete.set())
        out = {}
        for name, noise in DATA.items():
            events.clear()
            complete.clear()
            trace = {"categories": "devtools.timeline", "transferMode": "ReportEvents"}
            await cdp.send("Tracing.start", trace)
            args = {"runs": runs, "samples": 50_000, "periodS": 0.001, "noise": noise}
            out[name] = await page.evaluate(BENCH_JS, {**args, "width": size[0], "height": size[1]})
            await cdp.send("Tracing.end")
            await complete.wait()
            out[name]["cpu"] = cpu_times(events)
        return out
    finally:
        await page.close()


def option(name: str, default: str) -> str:
    return sys.argv[sys.argv.index(name) + 1] if name in sys.argv else default


async def main() -> None:
    values = {option(n, "") for n in ("--ab", "--rounds", "--runs", "--width", "--height")}
    args = [a for a in sys.argv[1:] if not a.startswith("--") and a not in values]
    if not args:
        raise SystemExit(__doc__)
    targets = [("B", args[0])]
    if "--ab" in sys.argv:
        targets = [("A", option("--ab", "")), ("B", args[0])]
    rounds = int(option("--rounds", "3"))
    runs = int(option("--runs", "60"))
    size = (int(option("--width", "1200")), int(option("--height", "800")))
    results: dict[str, list[Any]] = {}
    with contextlib.ExitStack() as stack:
        bases = [(label, stack.enter_context(served(t))) for label, t in targets]
        async with async_playwright() as p:
            browser = await p.chromium.launch(
                executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"]
            )
            for r in range(rounds):
                for label, base in bases:
                    res = await measure(browser, base, runs, size)
                    results.setdefault(label, []).append(res)
                    print(f"[{r + 1}] {label} load {load()}  {json.dumps(res)}", flush=True)
            await browser.close()
    print(f"\nmedians over {rounds} rounds of {runs} redraws (ms), load now {load()}:")
    for label, rs in results.items():
        med = {
            f"{data}.{kind}.{q}": round(statistics.median(x[data][kind][q] for x in rs), 2)
            for data in DATA
            for kind in ("rolling", "static")
            for q in ("min", "p50", "p95", "max")
        }
        print(f"  {label}  wall {json.dumps(med)}")
        cpu = {
            f"{data}.{kind}.{q}": round(statistics.median(x[data]["cpu"][kind][q] for x in rs), 2)
            for data in DATA
            for kind in ("rolling", "static")
            for q in ("min", "p50", "p95", "max")
            if all(x[data]["cpu"].get(kind) for x in rs)
        }
        print(f"  {label}  cpu  {json.dumps(cpu)}")


if __name__ == "__main__":
    asyncio.run(main())
