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

/** The pixel buffer of one plot area, reused while its size stays. */
export class TraceLayer {
  private image: ImageData | null = null;
  private px = new Uint32Array(0);
  private w = 0;
  private h = 0;
  /** Line width in device pixels (2 on a 2× screen, so a trace stays 1 CSS px). */
  private lw = 1;

  /** Clear to transparent, sized ``w`` × ``h`` device pixels. */
  begin(w: number, h: number, lw: number): void {
    if (!this.image || this.w !== w || this.h !== h) {
      this.image = new ImageData(w, h);
      this.px = new Uint32Array(this.image.data.buffer);
      this.w = w;
      this.h = h;
    } else this.px.fill(0);
    this.lw = lw;
  }

  /** A vertical grid line at column ``c``. */
  vline(c: number, color: number): void {
    const { px, w, h } = this;
    for (let k = 0; k < this.lw; k++) {
      const x = c + k;
      if (x < 0 || x >= w) continue;
      for (let y = 0, i = x; y < h; y++, i += w) px[i] = color;
    }
  }

  /** A horizontal grid line at row ``r``. */
  hline(r: number, color: number): void {
    for (let k = 0; k < this.lw; k++) {
      const y = r + k;
      if (y < 0 || y >= this.h) continue;
      this.px.fill(color, y * this.w, (y + 1) * this.w);
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
      if (x < 0 || x >= w) continue;
      for (let r = r0, i = r0 * w + x; r <= r1; r++, i += w) px[i] = color;
    }
  }

  /** The segment (x0, y0)–(x1, y1) (x0 ≤ x1, device px in the plot area) as column spans. */
  private segment(x0: number, y0: number, x1: number, y1: number, color: number): void {
    const c0 = Math.floor(x0);
    const c1 = Math.floor(x1);
    if (c0 === c1 || !(x1 > x0)) {
      this.span(c0, y0, y1, color);
      return;
    }
    const slope = (y1 - y0) / (x1 - x0);
    const from = Math.max(c0, -this.lw);
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

const layers = new WeakMap<uPlot, TraceLayer>();

/** uPlot keeps the split values of each axis from its last layout (not in its types). */
type WithSplits = uPlot.Axis & { _splits?: number[] };

/** Whether the layer draws ``name`` in this frame (uPlot must not build its path then). */
export function rastered(frame: Frame | null, name: string): boolean {
  return !!frame && frame.decimated && !frame.slow.has(name);
}

/** The drawAxes hook of a line panel: grid and dense traces of ``series`` into ``u``'s plot area. */
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
  layer.begin(w, h, Math.max(1, Math.round(devicePixelRatio || 1)));
  const grid = pixelOf(host.theme.grid);
  for (const v of (u.axes[0] as WithSplits)._splits ?? []) layer.vline(Math.round(u.valToPos(v, "x", true)) - x0, grid);
  for (const v of (u.axes[1] as WithSplits)._splits ?? []) layer.hline(Math.round(u.valToPos(v, "y", true)) - y0, grid);
  const frame = host.frame;
  const sx = u.scales.x;
  const sy = u.scales.y;
  if (frame?.decimated && sx && sy && sx.min != null && sx.max != null && sy.min != null && sy.max != null && sx.max > sx.min && sy.max > sy.min) {
    const kx = width / (sx.max - sx.min);
    const ky = height / (sy.max - sy.min);
    series.forEach((name, i) => {
      if (!u.series[i + 1]?.show || !rastered(frame, name)) return;
      const ys = frame.channels.get(name);
      if (ys) layer.trace(frame.x, ys, sx.min as number, kx, sy.max as number, ky, pixelOf(host.color(i)));
    });
  }
  layer.put(u.ctx, x0, y0);
}
