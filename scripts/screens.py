"""Screenshots of the dashboard at phone, laptop and desktop sizes (headless Chromium).

Usage: python scripts/screens.py http://127.0.0.1:8106 OUT_DIR [theme]
Takes the SLAP2, Z1100 and EP7047 axis pages, the rig overview and the EP7047 bench at
390x844, 1280x800 and 1600x1000, and reports horizontal overflow, off-screen command
buttons, whether the global STOP is inside the viewport, and text cut short (ellipsis,
or clipped by its box) without a tooltip.
"""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

from playwright.async_api import async_playwright

SIZES = {"phone": (390, 844), "laptop": (1280, 800), "desktop": (1600, 1000)}
PAGES = {
    "slap2": "#/axis/demo-slap2-0",
    "z1100": "#/axis/demo-z1100-x",
    "ep7047": "#/axis/demo-ep7047-1",
    "overview": "#/overview",
    "bench": "#/axis/demo-ep7047-1",
}
VIEW_BUTTON = {"bench": "bench-toggle"}

CHECK = """() => {
  const vw = document.documentElement.clientWidth, vh = innerHeight;
  const out = [];
  for (const b of document.querySelectorAll('.controls button, .stop-all')) {
    const r = b.getBoundingClientRect();
    if (!r.width) continue;
    if (r.left < 0 || r.right > vw + 0.5)
      out.push((b.textContent || '').trim().slice(0, 30)
               + ' @' + Math.round(r.left) + '..' + Math.round(r.right));
  }
  const stop = document.querySelector('.stop-all');
  const sr = stop ? stop.getBoundingClientRect() : null;
  const stopOn = !!sr && sr.width > 0 && sr.left >= 0 && sr.top >= 0
    && sr.right <= vw && sr.bottom <= vh;
  const cut = [];
  for (const el of document.querySelectorAll('body *')) {
    if (el.children.length || !el.textContent.trim()) continue;
    if (el.closest('svg, canvas, [hidden]')) continue;
    const cs = getComputedStyle(el);
    if (cs.display === 'none' || cs.visibility === 'hidden') continue;
    if (!el.getClientRects().length) continue;
    const over = el.scrollWidth > el.clientWidth + 1
      && (cs.overflowX !== 'visible' || cs.textOverflow === 'ellipsis');
    if (!over) continue;
    let titled = false;
    for (let e = el; e && e !== document.body; e = e.parentElement) {
      if (e.getAttribute('title')) { titled = true; break; }
    }
    if (!titled) cut.push(el.textContent.trim().slice(0, 40));
  }
  return {scrollW: document.documentElement.scrollWidth, vw, offscreen: out,
          stopInViewport: stopOn, cutWithoutTooltip: cut.slice(0, 20)};
}"""


async def main(base: str, out: Path, theme: str) -> None:
    async with async_playwright() as p:
        browser = await p.chromium.launch(
            executable_path="/usr/bin/chromium", args=["--no-sandbox", "--disable-gpu"]
        )
        for size, (w, hgt) in SIZES.items():
            ctx = await browser.new_context(
                viewport={"width": w, "height": hgt},
                color_scheme=theme,  # type: ignore[arg-type]
            )
            page = await ctx.new_page()
            page.on("pageerror", lambda exc: print("PAGE ERROR", exc))
            for name, frag in PAGES.items():
                await page.goto(f"{base}/{frag}")
                if name in VIEW_BUTTON:
                    await page.get_by_test_id(VIEW_BUTTON[name]).click()
                await page.wait_for_timeout(2500)
                await page.screenshot(path=str(out / f"{name}-{size}.png"))
                print(size, name, await page.evaluate(CHECK))
            await ctx.close()
        await browser.close()


if __name__ == "__main__":
    Path(sys.argv[2]).mkdir(parents=True, exist_ok=True)
    asyncio.run(main(sys.argv[1], Path(sys.argv[2]), sys.argv[3] if len(sys.argv) > 3 else "dark"))
