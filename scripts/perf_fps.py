"""Frame rate, long tasks and CPU of the live dashboard pages (headless Chromium).

Usage:
    python scripts/perf_fps.py BASE [seconds] [--pages ep7047,slap2] [--windows 10,60]
                                [--ab OTHER_BASE] [--rounds N] [--warm S] [--no-draw] [--profile]

For each page (SLAP2, Z1100, EP7047 live pages, the rig overview, the EP7047 bench) at
1600x1000, opened once and warmed for ``--warm`` seconds (default 2), then at each
window length in turn (a 10 s and a 60 s window; pages without a scope: once), over
``seconds`` each (the buffer fills from the page's start, so a 60 s window is full only
with --warm 60 or more; ``samples_shown`` is the number of samples in the window): frames per
second (requestAnimationFrame count), long tasks
(PerformanceObserver 'longtask', > 50 ms: count, total and worst), the CPU time of the
renderer and GPU processes per second (CDP SystemInfo.getProcessInfo: CPU time, which a
loaded machine inflates far less than wall time) and the main thread's busy time.

Then the draw time of 4 plots x 50k points (window.__servotune.benchDraw: a rolling
redraw with new samples each frame, a static full redraw, and a cold redraw that
re-decimates the whole window; p50/p95/max of the script time of the redraw, and how
many trace-layer redraws of each phase were whole, shifted or reused).

``--ab OTHER_BASE`` measures OTHER_BASE (A) and BASE (B) alternately, ``--rounds`` times
each, so both see the same machine load; the medians are printed per page at the end.
The machine's load average is printed with every run.
Machine-dependent by nature: a benchmark, not a test.
"""

from __future__ import annotations

import asyncio
import json
import os
import statistics
import sys
from typing import Any

from playwright.async_api import Browser, Page, async_playwright

PROFILE_PAGE = os.environ.get("PROFILE_PAGE", "ep7047")
WARM_S = 2.0

PAGES = {
    "slap2": "#/axis/demo-slap2-0",
    "z1100": "#/axis/demo-z1100-x",
    "ep7047": "#/axis/demo-ep7047-1",
    "overview": "#/overview",
    # The tuning bench of the EP7047 (the "Bench" view of an axis page: runs table,
    # overlay plot; the live scope is hidden, the telemetry keeps arriving).
    "bench": "#/axis/demo-ep7047-1",
}
# Pages that are an axis page with another view switched on (test id of its button).
VIEW_BUTTON = {"bench": "bench-toggle"}

MEASURE = """async (seconds) => {
  const longs = [];
  const po = new PerformanceObserver((l) => {
    for (const e of l.getEntries()) longs.push(e.duration);
  });
  po.observe({ type: 'longtask', buffered: false });
  let frames = 0;
  let run = true;
  const tick = () => { frames++; if (run) requestAnimationFrame(tick); };
  requestAnimationFrame(tick);
  await new Promise((r) => setTimeout(r, seconds * 1000));
  run = false;
  po.disconnect();
  return { fps: frames / seconds, long_tasks: longs.length,
           long_ms: Math.round(longs.reduce((a, b) => a + b, 0)),
           worst_ms: Math.round(Math.max(0, ...longs)) };
}"""


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


async def process_cpu(browser: Browser) -> dict[str, float]:
    """Cumulative CPU seconds per process type (renderer, gpu, browser)."""
    cdp = await browser.new_browser_cdp_session()
    info = await cdp.send("SystemInfo.getProcessInfo")
    await cdp.detach()
    out: dict[str, float] = {}
    for proc in info["processInfo"]:
        out[proc["type"]] = out.get(proc["type"], 0.0) + float(proc["cpuTime"])
    return out


async def measure_window(
    page: Page, browser: Browser, seconds: float, profile: bool
) -> dict[str, Any]:
    """fps, long tasks, process CPU and main-thread time of ``page`` over ``seconds``."""
    cdp = None
    if profile:
        cdp = await page.context.new_cdp_session(page)
        await cdp.send("Profiler.enable")
        await cdp.send("Profiler.start")
    metrics = await page.context.new_cdp_session(page)
    await metrics.send("Performance.enable")
    before = {
        m["name"]: m["value"] for m in (await metrics.send("Performance.getMetrics"))["metrics"]
    }
    cpu_before = await process_cpu(browser)
    result: dict[str, Any] = await page.evaluate(MEASURE, seconds)
    cpu_after = await process_cpu(browser)
    after = {
        m["name"]: m["value"] for m in (await metrics.send("Performance.getMetrics"))["metrics"]
    }
    for kind in ("renderer", "GPU"):
        used = cpu_after.get(kind, 0.0) - cpu_before.get(kind, 0.0)
        result[f"cpu_{kind.lower()}_ms_per_s"] = round(1000 * used / seconds)
    # Renderer CPU per frame shown: the cost of a frame, whatever the load let through.
    frames = max(1.0, result["fps"] * seconds)
    result["cpu_renderer_ms_per_frame"] = round(
        result["cpu_renderer_ms_per_s"] * seconds / frames, 2
    )
    # Main-thread busy time per second (ms/s, wall time: inflated by a loaded machine).
    for key in ("TaskDuration", "ScriptDuration", "LayoutDuration"):
        result[key + "_ms_per_s"] = round(1000 * (after[key] - before[key]) / seconds)
    await metrics.detach()
    if cdp is not None:
        prof = (await cdp.send("Profiler.stop"))["profile"]
        self_time: dict[str, float] = {}
        nodes = {n["id"]: n for n in prof["nodes"]}
        for sid, d in zip(prof["samples"], prof["timeDeltas"], strict=False):
            cf = nodes[sid]["callFrame"]
            where = f"{cf['url'].rsplit('/', 1)[-1]}:{cf['lineNumber']}"
            key = f"{cf['functionName'] or '(anon)'} {where}"
            self_time[key] = self_time.get(key, 0) + d / 1000
        print(json.dumps(sorted(self_time.items(), key=lambda kv: -kv[1])[:25], indent=0))
        await cdp.detach()
    # The samples in the window at the end (a 60 s window is full only after 60 s).
    result["samples_shown"] = await page.evaluate(
        "() => { const s = window.__servotune.scope(); return s && s.frame ? s.frame.samples : 0; }"
    )
    return result


async def measure_page(
    browser: Browser, base: str, name: str, windows: list[int], seconds: float, profile: bool
) -> dict[int, dict[str, Any]]:
    """One page, warmed once (--warm), then each window length in turn.

    A page without a scope is measured once (reported as the first window).
    """
    page = await browser.new_page(viewport={"width": 1600, "height": 1000})
    out: dict[int, dict[str, Any]] = {}
    try:
        await page.goto(f"{base}/{PAGES[name]}")
        if name in VIEW_BUTTON:
            await page.get_by_test_id(VIEW_BUTTON[name]).click()
        # The buffer fills from the page's start: --warm seconds of data before measuring.
        await page.wait_for_timeout(1000 * WARM_S)
        for window_s in windows:
            button = page.get_by_test_id(f"scope-window-{window_s}")
            if await button.count() and await button.is_visible():
                await button.click()
            elif out:
                break  # a page without a scope: measured once
            # The pointer off the plots (a hover would draw the cursor and the legend values).
            await page.mouse.move(2, 998)
            await page.wait_for_timeout(500)
            out[window_s] = await measure_window(
                page, browser, seconds, profile and name == PROFILE_PAGE
            )
        return out
    finally:
        await page.close()


async def draw_bench(browser: Browser, base: str) -> Any:
    page = await browser.new_page(viewport={"width": 1600, "height": 1000})
    try:
        # The overview: no live scope of its own competing with the benchmark's.
        await page.goto(f"{base}/{PAGES['overview']}")
        await page.wait_for_timeout(1500)
        return await page.evaluate(
            "() => window.__servotune.benchDraw ? window.__servotune.benchDraw() : null"
        )
    finally:
        await page.close()


async def main(
    bases: list[tuple[str, str]],
    seconds: float,
    pages: list[str],
    windows: list[int],
    rounds: int,
    draw: bool,
    profile: bool,
) -> None:
    results: dict[tuple[str, str, int], list[dict[str, Any]]] = {}
    draws: dict[str, list[Any]] = {}
    async with async_playwright() as p:
        browser = await p.chromium.launch(
            executable_path="/usr/bin/chromium", args=["--no-sandbox", "--disable-gpu"]
        )
        for r in range(rounds):
            for name in pages:
                for label, base in bases:
                    measured = await measure_page(browser, base, name, windows, seconds, profile)
                    for window_s, res in measured.items():
                        results.setdefault((label, name, window_s), []).append(res)
                        head = f"[{r + 1}] {label} {name} window {window_s} s"
                        print(f"{head}  load {load()}  {json.dumps(res)}", flush=True)
            if draw:
                for label, base in bases:
                    d = await draw_bench(browser, base)
                    draws.setdefault(label, []).append(d)
                    head = f"[{r + 1}] {label} draw 4 plots x 50k points"
                    print(f"{head}  load {load()}  {json.dumps(d)}", flush=True)
        await browser.close()
    if rounds > 1 or len(bases) > 1:
        print("\nmedians over the rounds:")
        keys = (
            "fps",
            "long_tasks",
            "long_ms",
            "worst_ms",
            "cpu_renderer_ms_per_s",
            "cpu_gpu_ms_per_s",
            "cpu_renderer_ms_per_frame",
        )
        for (label, name, window_s), rs in results.items():
            med = {k: round(statistics.median(x[k] for x in rs), 1) for k in keys}
            print(f"  {label} {name} window {window_s} s  {json.dumps(med)}")
        for label, ds in draws.items():
            flat: dict[str, float] = {}
            for key in ds[0] or {}:
                if key == "layers":  # redraw counts per phase: printed per round above
                    continue
                if isinstance(ds[0][key], dict):
                    for q in ds[0][key]:
                        flat[f"{key}.{q}"] = round(statistics.median(d[key][q] for d in ds), 2)
                else:  # an older client: one set of figures
                    flat[key] = round(statistics.median(d[key] for d in ds), 2)
            print(f"  {label} draw  {json.dumps(flat)}")


def option(name: str, default: str) -> str:
    if name in sys.argv:
        return sys.argv[sys.argv.index(name) + 1]
    return default


if __name__ == "__main__":
    values = {option(n, "") for n in ("--pages", "--windows", "--ab", "--rounds", "--warm")}
    WARM_S = float(option("--warm", "2"))
    args = [a for a in sys.argv[1:] if not a.startswith("--") and a not in values]
    bases = [("B", args[0])]
    if "--ab" in sys.argv:
        bases = [("A", option("--ab", "")), ("B", args[0])]
    asyncio.run(
        main(
            bases,
            float(args[1]) if len(args) > 1 else 5.0,
            option("--pages", ",".join(PAGES)).split(","),
            [int(w) for w in option("--windows", "10,60").split(",")],
            int(option("--rounds", "1")),
            "--no-draw" not in sys.argv,
            "--profile" in sys.argv,
        )
    )
