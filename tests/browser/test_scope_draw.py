"""The scope's pixels (headless Chromium): what the trace layer and uPlot put on the canvas.

On the scope lab (window.__servotune.lab, known synthetic data), pixels are read back
from the plot's canvas: a dense series rasterised by the trace layer keeps a one-sample
spike (min/max per column) in the column of its time; a gap in time stays empty; sparse
data is drawn by uPlot with a marker on every sample.
"""

from __future__ import annotations

import pytest
from playwright.async_api import Browser, Page, expect

from tests.support.browser import open_page
from tests.support.servers import LiveServer

pytestmark = pytest.mark.browser

# Helpers in the page: the uPlot of lab plot 0, a pixel of its canvas (device px), the
# canvas position of a (time, value), and the colour of trace 0.
HELPERS = """() => {
  const u = () => window.__lab.stack.panels[0].u;
  window.__px = (x, y) => Array.from(u().ctx.getImageData(Math.round(x), Math.round(y), 1, 1).data);
  window.__pos = (t, v) => [u().valToPos(t, 'x', true), u().valToPos(v, 'y', true)];
  window.__bbox = () => { const b = u().bbox; return [b.left, b.top, b.width, b.height]; };
  window.__color = () => {
    const c = document.createElement('canvas').getContext('2d');
    c.fillStyle = window.__lab.stack.color(0); c.fillRect(0, 0, 1, 1);
    return Array.from(c.getImageData(0, 0, 1, 1).data);
  };
}"""

# ch0 of a dense lab (20000 samples, 0.5 ms apart: 10 s) set to 0 but for a one-sample
# spike to +900 at 2.5 s and to -900 at 7.5 s; a new window length folds it afresh
# (redraw(): a redraw right after a slow one would otherwise wait).
SPIKES = """() => {
  const b = window.__lab.buffer, col = b.channels.get('ch0');
  for (let i = b.start; i < b.end; i++) col[i] = 0;
  col[b.indexAt(2.5)] = 900;
  col[b.indexAt(7.5)] = -900;
  const s = window.__lab.stack;
  s.windowS = 5;
  s.redraw();
  s.windowS = 10;
  s.redraw();
}"""

# The same dense lab with a 2 s hole in time: every sample from 4 s on moved 2 s later.
HOLE = """() => {
  const b = window.__lab.buffer;
  for (let i = b.indexAt(4); i < b.end; i++) b.t[i] += 2;
  b.lastT = b.t[b.end - 1];
  b.version += 1;
  window.__lab.stack.windowS = 12;
  window.__lab.stack.redraw();
}"""


def near(a: list[int], b: list[int]) -> bool:
    return all(abs(x - y) <= 40 for x, y in zip(a[:3], b[:3], strict=True)) and a[3] > 200


async def lab(page: Page, samples: int, period_s: float) -> None:
    await page.evaluate(
        f"window.__lab = window.__servotune.lab({{samples: {samples}, periodS: {period_s}}})"
    )
    await expect(page.get_by_test_id("scope-lab").get_by_test_id("scope-status")).to_contain_text(
        f"{samples} samples"
    )
    await page.evaluate(HELPERS)


async def test_dense_trace_keeps_extremes_in_their_columns(
    browser: Browser,
    slap2: LiveServer,
) -> None:
    page, errors = await open_page(browser, slap2, 1280, 800)
    await lab(page, 20000, 0.0005)
    await page.evaluate(SPIKES)
    await page.wait_for_timeout(100)
    color = await page.evaluate("window.__color()")
    for t, v in ((2.5, 900.0), (7.5, -900.0)):
        x, y = await page.evaluate(f"window.__pos({t}, {v})")
        _x0, y0 = await page.evaluate(f"window.__pos({t}, 0)")
        # The spike's column (±1 px: a column's first and last sample may straddle a
        # pixel edge) is coloured from the zero line to the extreme...
        for frac in (0.1, 0.5, 0.95):
            row = y0 + frac * (y - y0)
            pixels = await page.evaluate(f"[-1, 0, 1].map((d) => window.__px({x} + d, {row}))")
            assert any(near(p, color) for p in pixels), (t, frac, pixels, color)
        # ...and not beyond it, nor in the columns a few pixels either side.
        beyond = y + (12 if v < 0 else -12)
        assert not near(await page.evaluate(f"window.__px({x}, {beyond})"), color)
        for dx in (-4, 4):
            assert not near(await page.evaluate(f"window.__px({x + dx}, {y})"), color), dx
        # The flat line at 0 is drawn beside it (a 1 px row: ±1 px for the rounding).
        pixels = await page.evaluate(f"[-1, 0, 1].map((d) => window.__px({x - 40}, {y0} + d))")
        assert any(near(p, color) for p in pixels), pixels
    assert "markers" not in (
        await page.get_by_test_id("scope-lab").get_by_test_id("scope-status").text_content() or ""
    )
    assert not errors


async def test_gap_stays_empty_and_sparse_samples_get_markers(
    browser: Browser,
    slap2: LiveServer,
) -> None:
    page, errors = await open_page(browser, slap2, 1280, 800)
    await lab(page, 20000, 0.0005)
    await page.evaluate(HOLE)
    await page.wait_for_timeout(100)
    color = await page.evaluate("window.__color()")
    _left, top, _w, height = await page.evaluate("window.__bbox()")

    async def traced(t: float) -> int:
        x, _y = await page.evaluate(f"window.__pos({t}, 0)")
        rows = range(int(top), int(top + height))
        js = f"[{','.join(f'window.__px({x}, {r})' for r in rows)}]"
        return sum(near(p, color) for p in await page.evaluate(js))

    for t in (4.5, 5.0, 5.5):
        assert await traced(t) == 0, t  # nothing drawn across the hole
    for t in (2.0, 8.0):
        assert await traced(t) > 0, t
    await page.evaluate("window.__lab.destroy()")
    # 40 samples 0.25 s apart: ch0 = round(1000 sin(pi t)) peaks at 0.5 s: the lines
    # from the peak go down, only a marker covers the pixels just above it.
    await lab(page, 40, 0.25)
    await expect(page.get_by_test_id("scope-lab").get_by_test_id("scope-status")).to_contain_text(
        "markers"
    )
    for t in (0.5, 2.5):
        x, y = await page.evaluate(f"window.__pos({t}, 1000)")
        assert near(await page.evaluate(f"window.__px({x}, {y - 2})"), color), t
        assert not near(await page.evaluate(f"window.__px({x}, {y - 7})"), color), t
    assert not errors


# A rolling window on the lab (20000 samples 0.5 ms apart, a 10 s window): 50 times 50
# new samples of a noisy sine, each followed by a redraw, as on a live page. The noise
# (deterministic, +-300) is only where |sin| < 0.6: the extremes stay the sine's own (its
# peaks fall on samples), so the y range holds and the redraws shift. Returns the trace
# layers' counts in all and of the last redraw.
ROLL = """async () => {
  const s = window.__lab.stack, b = window.__lab.buffer;
  let seed = 7;
  const rnd = () => {
    seed ^= seed << 13; seed ^= seed >>> 17; seed ^= seed << 5;
    return (seed >>> 0) / 4294967296;
  };
  const signal = (t, c) => {
    const v = Math.sin(Math.PI * t);
    return Math.round(1000 * v + (Math.abs(v) < 0.6 ? 300 * (2 * rnd() - 1) : 0)) + c;
  };
  let at = b.end - b.start;
  let before = null;
  for (let i = 0; i < 50; i++) {
    const t = Array.from({length: 50}, (_v, k) => (at + k) * 0.0005);
    const channels = {};
    for (let c = 0; c < 4; c++) channels['ch' + c] = t.map((x) => signal(x, c));
    b.push({type: 'telemetry', axis: 'lab', t, channels, flags: {move: t.map(() => 0)}});
    at += 50;
    before = s.layerCounts();
    s.redraw();
    await new Promise((r) => requestAnimationFrame(() => r()));
  }
  const after = s.layerCounts();
  return {all: after, last: after.shifted - before.shifted};
}"""

AREA = """() => {
  const u = window.__lab.stack.panels[0].u, b = u.bbox;
  const r = [b.left, b.top, b.width, b.height].map(Math.round);
  return Array.from(new Uint32Array(u.ctx.getImageData(r[0], r[1], r[2], r[3]).data.buffer));
}"""


async def test_rolling_redraw_by_shift_equals_a_whole_redraw(
    browser: Browser,
    slap2: LiveServer,
) -> None:
    page, errors = await open_page(browser, slap2, 1280, 800)
    await lab(page, 20000, 0.0005)
    counts = await page.evaluate(ROLL)
    # The rolling redraws shifted the last raster (but for the periodic whole redraw),
    # the last one too (4 line plots): the comparison below is of shifted pixels.
    assert counts["all"]["shifted"] >= 160 and counts["last"] == 4, counts
    shifted = await page.evaluate(AREA)
    # New plots (new trace layers) draw the same frame whole (skipUntil: a rebuild right
    # after a slow redraw would otherwise wait).
    await page.evaluate("() => { const s = window.__lab.stack; s.skipUntil = 0; s.rebuild(); }")
    after = await page.evaluate("() => window.__lab.stack.layerCounts()")
    assert after["shifted"] == 0 and after["whole"] > 0, after
    whole = await page.evaluate(AREA)
    assert len(whole) == len(shifted) > 10000
    color = await page.evaluate("window.__color()")
    traced = sum(1 for p in whole if p & 0xFF == color[0] and (p >> 8) & 0xFF == color[1])
    assert traced > 1000  # the trace is there to compare
    differ = sum(1 for a, b in zip(shifted, whole, strict=True) if a != b)
    # Equal (a rounding at a column edge could differ: none here; a shift that redrew
    # its changed columns from 3 px too far right left 34 stale pixels).
    assert differ <= 0.00005 * len(whole), (differ, len(whole))
    assert not errors
