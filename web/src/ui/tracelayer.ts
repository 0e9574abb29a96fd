// Dense traces rasterised into pixels and put straight into the plot's canvas.
//
// Why: in Chromium's software canvas (no GPU) the raster of a stroked path with
// thousands of segments is most of a redraw's cost. A min/max-decimated trace is, per
// pixel column, one vertical span from the column's min to its max (plus the join to
// the next column): writing those spans into a Uint32 pixel buffer and handing it over
// with one putImageData costs a fraction of that. uPlot still draws the axes and tick
// labels and every sparse or slow series (markers, held steps); the grid inside the
// plot area is drawn here too, at uPlot's own split positions (``axis._splits``),
// because putImageData replaces the pixels of the plot area rather than blending.
//
// Contract: ``drawTraceLayer`` is a uPlot ``drawAxes`` hook of a line panel (it runs
// after uPlot's axes and before its series). It fills the plot area with the grid and,
// when the frame is decimated, with every visible, non-slow series of the panel (drawn
// in series order, later over earlier); those series' uPlot paths must be null then
// (plotkit.ts). A null in a series is a gap: the trace breaks there.
import type uPlot from "uplot";
import type { Frame } from "./decimate";

/** What the layer needs of the stack: the frame drawn, the panel's series, colours. */
export interface TraceHost {
  readonly frame: Frame | null;
  readonly theme: { grid: string };
  color(i: number): string;
}

const pixels = new Map<string, number>();
let probe: CanvasRenderingContext2D | null = null;

/** A CSS colour as one ImageData pixel (bytes r, g, b, a in memory: little-endian Uint32). */
export function pixelOf(color: string): number {
  const known = pixels.get(color);
  if (known !== undefined) return known;
  if (!probe) probe = document.createElement("canvas").getContext("2d", { willReadFrequently: true });
  let value = 0xff_ff_ff_ff;
  if (probe) {
    probe.clearRect(0, 0, 1, 1);
    probe.fillStyle = color;
    probe.fillRect(0, 0, 1, 1);
    const [r, g, b, a] = probe.getImageData(0, 0, 1, 1).data;
    value = (((a as number) << 24) | ((b as number) << 16) | ((g as number) << 8) | (r as number)) >>> 0;
  }
  pixels.set(color, value);
  return value;
}

/** What one raster of a layer was drawn from: a later frame that matches it but for a
 * whole-pixel shift of the x range only needs its new columns drawn. */
interface Drawn {
  serial: number;
  xmin: number;
  kx: number;
  ymax: number;
  ky: number;
  periodS: number;
  /** Colour of each series drawn, in order (0: not drawn). */
  colors: number[];
  vlines: number[];
  hlines: number[];
  grid: number;
}

/** Whole redraws at least this often (in shifted redraws): a shift repeats the pixels
 * of the last raster, so any rounding difference at a column edge is let go soon. */
const FULL_EVERY = 60;

/** The pixel buffer of one plot area, reused while its size stays. */
export class TraceLayer {
  private image: ImageData | null = null;
  private px = new Uint32Array(0);
  private w = 0;
  private h = 0;
  /** Line width in device pixels (2 on a 2× screen, so a trace stays 1 CSS px). */
  private lw = 1;
  /** Columns left of this one are kept (shifted), not drawn. */
  private from = 0;
  private drawn: Drawn | null = null;
  private shifts = 0;
  /** Redraws since the layer was made: whole, shifted, and reused (the same pixels: a
   * cut without new samples, an overlay redraw) (tests, benchmarks). */
  readonly counts = { whole: 0, shifted: 0, reused: 0 };

  /** Clear to transparent, sized ``w`` × ``h`` device pixels. */
  begin(w: number, h: number, lw: number): void {
    if (!this.image || this.w !== w || this.h !== h) {
      this.image = new ImageData(w, h);
      this.px = new Uint32Array(this.image.data.buffer);
      this.w = w;
      this.h = h;
      this.drawn = null;
    } else this.px.fill(0);
    this.lw = lw;
    this.from = 0;
    this.shifts = 0;
    this.counts.whole += 1;
  }

  /**
   * Reuse the last raster for ``next`` if it was drawn from the same scales, grid,
   * series and gap threshold but for an x range moved right by a whole number of
   * pixels: shift the pixels left by that many and clear the columns from where
   * ``changedFromT`` (time) falls — the caller then draws only those (grid and traces
   * clip to them). Returns false (nothing done) when the raster must be drawn whole.
   */
  shift(next: Drawn, changedFromT: number, w: number, h: number, lw: number): boolean {
    const last = this.drawn;
    if (!last || !this.image || this.w !== w || this.h !== h || this.lw !== lw || this.shifts >= FULL_EVERY) return false;
    if (next.serial !== last.serial + 1 && next.serial !== last.serial) return false;
    if (next.serial === last.serial) changedFromT = Number.POSITIVE_INFINITY; // the same cut
    if (Number.isNaN(changedFromT) || changedFromT === Number.NEGATIVE_INFINITY) return false;
    if (next.ymax !== last.ymax || next.ky !== last.ky || next.grid !== last.grid) return false;
    if (Math.abs(next.kx - last.kx) > 1e-9 * Math.abs(last.kx)) return false;
    if (!(next.periodS === last.periodS || (Number.isNaN(next.periodS) && Number.isNaN(last.periodS)))) return false;
    if (!same(next.colors, last.colors) || !same(next.hlines, last.hlines)) return false;
    const d = (next.xmin - last.xmin) * next.kx;
    const k = Math.round(d);
    if (Math.abs(d - k) > 1e-6 || k < 0 || 2 * k > w) return false;
    // Columns from here on are drawn again: the first changed one, less the join into it
    // and a line width; at least the k columns that come in on the right.
    const changedPx = Number.isFinite(changedFromT) ? Math.floor((changedFromT - next.xmin) * next.kx) - 2 * lw - 2 : w;
    const from = Math.max(0, Math.min(w - k, changedPx));
    if (2 * from < w) return false; // most of it changed: as cheap to draw it whole
    // The grid lines left of ``from`` must be where the shifted ones are.
    const kept = (c: number): boolean => c + lw > 0 && c < from;
    const moved = last.vlines.map((c) => c - k).filter(kept);
    if (!same(moved, next.vlines.filter(kept))) return false;
    const px = this.px;
    for (let y = 0, row = 0; y < h; y++, row += w) {
      if (k) px.copyWithin(row, row + k, row + w);
      px.fill(0, row + from, row + w);
    }
    this.from = from;
    if (k || from < w) {
      this.shifts += 1;
      this.counts.shifted += 1;
    } else this.counts.reused += 1;
    return true;
  }

  /** Remember what this raster was drawn from (for the next ``shift``). */
  done(drawn: Drawn): void {
    this.drawn = drawn;
  }

  /** A vertical grid line at column ``c``. */
  vline(c: number, color: number): void {
    const { px, w, h } = this;
    for (let k = 0; k < this.lw; k++) {
      const x = c + k;
      if (x < this.from || x >= w) continue;
      for (let y = 0, i = x; y < h; y++, i += w) px[i] = color;
    }
  }

  /** A horizontal grid line at row ``r``. */
  hline(r: number, color: number): void {
    for (let k = 0; k < this.lw; k++) {
      const y = r + k;
      if (y < 0 || y >= this.h) continue;
      this.px.fill(color, y * this.w + this.from, (y + 1) * this.w);
    }
  }

  /** Column ``c`` from row ya to row yb (either order, fractional), lw wide. */
  private span(c: number, ya: number, yb: number, color: number): void {
    const { px, w, h, lw } = this;
    let r0 = Math.floor(ya < yb ? ya : yb);
    let r1 = Math.floor(ya < yb ? yb : ya) + lw - 1;
    if (r1 < 0 || r0 >= h) return;
    if (r0 < 0) r0 = 0;
    if (r1 >= h) r1 = h - 1;
    for (let x = c; x < c + lw; x++) {
      if (x < this.from || x >= w) continue;
      for (let r = r0, i = r0 * w + x; r <= r1; r++, i += w) px[i] = color;
    }
  }

  /** The segment (x0, y0)–(x1, y1) (x0 ≤ x1, device px in the plot area) as column spans. */
  private segment(x0: number, y0: number, x1: number, y1: number, color: number): void {
    const c0 = Math.floor(x0);
    const c1 = Math.floor(x1);
    // Wholly left of the columns drawn (kept from the last raster).
    if (c1 + this.lw <= this.from) return;
    if (c0 === c1 || !(x1 > x0)) {
      this.span(c0, y0, y1, color);
      return;
    }
    const slope = (y1 - y0) / (x1 - x0);
    const from = Math.max(c0, this.from - this.lw);
    const to = Math.min(c1, this.w - 1);
    for (let c = from; c <= to; c++) {
      const xa = c > x0 ? c : x0;
      const xb = c + 1 < x1 ? c + 1 : x1;
      this.span(c, y0 + (xa - x0) * slope, y0 + (xb - x0) * slope, color);
    }
  }

  /** A series: consecutive points joined, a null breaks the line. */
  trace(xs: ArrayLike<number>, ys: ArrayLike<number | null>, xmin: number, kx: number, ymax: number, ky: number, color: number): void {
    const n = Math.min(xs.length, ys.length);
    let have = false;
    let x0 = 0;
    let y0 = 0;
    for (let j = 0; j < n; j++) {
      const v = ys[j];
      if (v === null || v === undefined) {
        have = false;
        continue;
      }
      const x1 = ((xs[j] as number) - xmin) * kx;
      const y1 = (ymax - v) * ky;
      if (have) this.segment(x0, y0, x1, y1, color);
      else this.segment(x1, y1, x1, y1, color);
      x0 = x1;
      y0 = y1;
      have = true;
    }
  }

  /** Hand the pixels to the canvas at (left, top). */
  put(ctx: CanvasRenderingContext2D, left: number, top: number): void {
    if (this.image) ctx.putImageData(this.image, left, top);
  }
}

function same(a: number[], b: number[]): boolean {
  if (a.length !== b.length) return false;
  for (let i = 0; i < a.length; i++) if (a[i] !== b[i]) return false;
  return true;
}

const layers = new WeakMap<uPlot, TraceLayer>();

/** uPlot keeps the split values of each axis from its last layout (not in its types). */
type WithSplits = uPlot.Axis & { _splits?: number[] };

/** Whether the layer draws ``name`` in this frame (uPlot must not build its path then). */
export function rastered(frame: Frame | null, name: string): boolean {
  return !!frame && frame.decimated && !frame.slow.has(name);
}

export type LayerCounts = TraceLayer["counts"];

/** The trace-layer redraws of ``plots`` summed: whole, shifted, reused (tests, benchmarks). */
export function layerCounts(plots: (uPlot | null)[]): LayerCounts {
  const out = { whole: 0, shifted: 0, reused: 0 };
  for (const u of plots) {
    const c = u ? layers.get(u)?.counts : undefined;
    if (c) {
      out.whole += c.whole;
      out.shifted += c.shifted;
      out.reused += c.reused;
    }
  }
  return out;
}

/** The drawAxes hook of a line panel: grid and dense traces of ``series`` into ``u``'s plot area.
 * A rolling window that moved by whole pixels, on unchanged scales, shifts the last
 * raster and draws only its new columns (TraceLayer.shift). */
export function drawTraceLayer(host: TraceHost, series: string[], u: uPlot): void {
  const { left, top, width, height } = u.bbox;
  const w = Math.round(width);
  const h = Math.round(height);
  if (w <= 0 || h <= 0) return;
  let layer = layers.get(u);
  if (!layer) {
    layer = new TraceLayer();
    layers.set(u, layer);
  }
  const x0 = Math.round(left);
  const y0 = Math.round(top);
  const lw = Math.max(1, Math.round(devicePixelRatio || 1));
  const grid = pixelOf(host.theme.grid);
  const frame = host.frame;
  const sx = u.scales.x;
  const sy = u.scales.y;
  const dense = !!frame?.decimated && sx && sy && sx.min != null && sx.max != null && sy.min != null && sy.max != null && sx.max > sx.min && sy.max > sy.min;
  const xmin = sx?.min ?? 0;
  const ymax = sy?.max ?? 0;
  const kx = dense ? width / ((sx.max as number) - xmin) : 0;
  const ky = dense ? height / (ymax - (sy.min as number)) : 0;
  const vlines = ((u.axes[0] as WithSplits)._splits ?? []).map((v) => Math.round(u.valToPos(v, "x", true)) - x0);
  const hlines = ((u.axes[1] as WithSplits)._splits ?? []).map((v) => Math.round(u.valToPos(v, "y", true)) - y0);
  const colors = series.map((name, i) => (dense && u.series[i + 1]?.show && rastered(frame, name) ? pixelOf(host.color(i)) : 0));
  const drawn = { serial: frame?.serial ?? -1, xmin, kx, ymax, ky, periodS: frame?.periodS ?? Number.NaN, colors, vlines, hlines, grid };
  if (!(dense && frame && layer.shift(drawn, frame.changedFromT, w, h, lw))) layer.begin(w, h, lw);
  for (const c of vlines) layer.vline(c, grid);
  for (const r of hlines) layer.hline(r, grid);
  if (dense && frame) {
    series.forEach((name, i) => {
      const color = colors[i] as number;
      const ys = frame.channels.get(name);
      if (color && ys) layer.trace(frame.x, ys, xmin, kx, ymax, ky, color);
    });
  }
  layer.done(drawn);
  layer.put(u.ctx, x0, y0);
}
