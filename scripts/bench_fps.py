"""Frame rate and long tasks of the live dashboard pages (headless Chromium).

Usage: python scripts/bench_fps.py http://127.0.0.1:8106 [seconds] [--profile]
For each demo page (SLAP2, Z1100, EP7047, overview) at 1600x1000 and a 10 s and
60 s window: frames per second (requestAnimationFrame count) and long tasks
(PerformanceObserver 'longtask', > 50 ms) over ``seconds``. Then the draw time of
4 plots x 50k points (window.__servotune.benchDraw, p95 over 60 draws).
Machine-dependent by nature: a benchmark, not a test.
"""

from __future__ import annotations

import asyncio
import json
import os
import sys

from playwright.async_api import async_playwright

PROFILE_PAGE = os.environ.get("PROFILE_PAGE", "ep7047")

PAGES = {
    "slap2": "#/axis/demo-slap2-0",
    "z1100": "#/axis/demo-z1100-x",
    "ep7047": "#/axis/demo-ep7047-1",
    "overview": "#/overview",
}

MEASURE = """async (seconds) => {
  const longs = [];
  const po = new PerformanceObserver((l) => { for (const e of l.getEntries()) longs.push(e.duration); });
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


async def main(base: str, seconds: float, profile: bool) -> None:
    async with async_playwright() as p:
        browser = await p.chromium.launch(
            executable_path="/usr/bin/chromium", args=["--no-sandbox", "--disable-gpu"]
        )
        page = await browser.new_page(viewport={"width": 1600, "height": 1000})
        for name, frag in PAGES.items():
            for window_s in (10, 60):
                await page.goto(f"{base}/{frag}")
                await page.wait_for_timeout(2000)
                button = page.get_by_test_id(f"scope-window-{window_s}")
                if await button.count():
                    await button.click()
                elif window_s != 10:
                    continue
                await page.wait_for_timeout(500)
                if profile and name == PROFILE_PAGE:
                    cdp = await page.context.new_cdp_session(page)
                    await cdp.send("Profiler.enable")
                    await cdp.send("Profiler.start")
                metrics = await page.context.new_cdp_session(page)
                await metrics.send("Performance.enable")
                before = {m["name"]: m["value"] for m in (await metrics.send("Performance.getMetrics"))["metrics"]}
                result = await page.evaluate(MEASURE, seconds)
                after = {m["name"]: m["value"] for m in (await metrics.send("Performance.getMetrics"))["metrics"]}
                # Main-thread busy time per second (ms/s): less sensitive to a loaded
                # machine than fps, which also waits for the CPU.
                for key in ("TaskDuration", "ScriptDuration", "LayoutDuration", "RecalcStyleDuration"):
                    result[key + "_ms_per_s"] = round(1000 * (after[key] - before[key]) / seconds)
                await metrics.detach()
                if profile and name == PROFILE_PAGE:
                    prof = (await cdp.send("Profiler.stop"))["profile"]
                    self_time: dict[str, float] = {}
                    nodes = {n["id"]: n for n in prof["nodes"]}
                    dt = prof["timeDeltas"]
                    for sid, d in zip(prof["samples"], dt, strict=False):
                        cf = nodes[sid]["callFrame"]
                        key = f'{cf["functionName"] or "(anon)"} {cf["url"].rsplit("/", 1)[-1]}:{cf["lineNumber"]}'
                        self_time[key] = self_time.get(key, 0) + d / 1000
                    top = sorted(self_time.items(), key=lambda kv: -kv[1])[:25]
                    print(json.dumps(top, indent=0))
                print(name, f"window {window_s} s", json.dumps(result))
        draw = await page.evaluate(
            "() => window.__servotune.benchDraw ? window.__servotune.benchDraw() : null"
        )
        print("draw 4 plots x 50k points", json.dumps(draw))
        await browser.close()


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    asyncio.run(main(args[0], float(args[1]) if len(args) > 1 else 5.0, "--profile" in sys.argv))
