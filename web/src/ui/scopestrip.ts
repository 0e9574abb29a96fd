// Strip redraws of a rolling trace: shift what the canvas shows by whole pixels and
// draw only the new columns.
//
// A live window sits on pixel columns fixed in time (one column per device pixel of the
// plot area, plots.ts), so when only time moved on, everything already drawn is still
// right, just further left: the canvas right of the y axis is copied k pixels to the
// left (getImageData/putImageData; no path raster) and uPlot draws its frame clipped to the last
// k + TAIL_PX pixels (the previous newest column was partial) and, on the plot with the
// x axis, to the tick labels that reach into them. Series paths are built from the
// first sample left of the strip only (PlotStack.pathsFrom), so a redraw's script and
// raster cost grows with the new columns, not with the window.
//
// What a strip redraw would get wrong is drawn whole instead: a new y range (then the
// shifted pixels are in the old scale), markers (sparse data, slow-channel samples), a
// switch between min/max columns and sample-by-sample data or of a channel to or from
// slow (held steps), a
// cursor over a plot (the values under it), x as relative time (every label changes),
// any other change (window, zoom, size, units, channels, theme: PlotStack.dirty), a
// shift of more than half the plot, and at least once per FULL_REDRAW_MS regardless,
// so the left edge (samples leaving the buffer) and a changed median period (gap
// decisions) are never off for long. The honesty rules are uPlot's and decimate.ts's,
// unchanged: a strip is the same drawing, clipped.
import type uPlot from "uplot";

/** Pixels left of the new columns redrawn too: the previous newest column was partial. */
const TAIL_PX = 3;
/** Half the widest x tick label ("14:03:22.125" in 11 px mono), css px. */
const LABEL_HALF_PX = 44;

/** A strip redraw: shift by ``shiftPx`` device pixels, redraw the last ``widthPx``. */
export interface Strip {
  shiftPx: number;
  /** The strip's left edge, device pixels from the plot area's right edge. */
  widthPx: number;
  /** Series paths are built from the last sample before this time. */
  fromT: number;
}

/** What the canvases of a stack show: the x range, column width and columns drawn. */
export class StripState {
  private max = Number.NaN;
  private colS = Number.NaN;
  private columns = 0;
  private fullAt = Number.NEGATIVE_INFINITY;
  private dpr = 0;
  private form = "";

  /** A whole redraw up to ``max`` at ``now`` (ms). ``form``: how the data is drawn
   * (min/max columns or samples, which channels are slow: held steps); a strip of one
   * form is not drawn next to pixels of another. */
  full(max: number, colS: number, columns: number, form: string, now: number): void {
    this.max = max;
    this.form = form;
    this.colS = colS;
    this.columns = columns;
    this.fullAt = now;
    this.dpr = devicePixelRatio || 1;
  }

  /** The strip to redraw for ``min..max``, or null when the whole plot must be drawn
   * (``dueBefore``: a whole redraw older than this is due). */
  next(min: number, max: number, colS: number, columns: number, form: string, dueBefore: number): Strip | null {
    if (this.fullAt < dueBefore || columns !== this.columns || form !== this.form || (devicePixelRatio || 1) !== this.dpr) return null;
    if (!(Math.abs(colS - this.colS) <= 1e-12 * Math.max(1, colS))) return null;
    const cols = (max - this.max) / colS;
    const shift = Math.round(cols);
    if (Math.abs(cols - shift) > 1e-6 || shift < 0 || shift > columns / 2) return null;
    this.max = max;
    const widthPx = shift + TAIL_PX;
    // Paths start two columns left of the strip: a sample just left of its edge may be
    // drawn on the edge column (pixel rounding), and the segment into it must be there.
    return { shiftPx: shift, widthPx, fromT: max - ((widthPx + 2) * (max - min)) / columns };
  }
}

/** The first index of sorted ``x`` with x[i] >= t (x.length when none). */
export function firstIndexAtOrAfter(x: ArrayLike<number>, t: number): number {
  let lo = 0;
  let hi = x.length;
  while (lo < hi) {
    const mid = (lo + hi) >> 1;
    if ((x[mid] as number) < t) lo = mid + 1;
    else hi = mid;
  }
  return lo;
}

/** Run ``set`` (uPlot setData/setScale) in a batch; with a strip, shift the canvas right of
 * the y axis and let uPlot draw into the strip only. Returns whether a strip redraw
 * changed the y scale (the caller then draws the plot whole). */
export function commitStrip(u: uPlot, strip: Strip | null, xAxis: boolean, set: () => void): boolean {
  if (!strip) {
    u.batch(set);
    return false;
  }
  const ctx = u.ctx;
  const canvas = ctx.canvas;
  const cw = canvas.width;
  const ch = canvas.height;
  const { left, top, width, height } = u.bbox;
  const yMin = u.scales.y?.min;
  const yMax = u.scales.y?.max;
  const shift = strip.shiftPx;
  if (shift > 0) {
    // putImageData writes the pixels as they are (no clip, no compositing): the shifted
    // pixels replace the old ones. Drawing the canvas onto itself (or through a
    // scratch canvas) costs several times a whole redraw in Chromium's software
    // canvas (measured); a read-back and a write do not.
    const w = cw - left - shift;
    ctx.putImageData(ctx.getImageData(left + shift, 0, w, ch), left, 0);
  }
  const x0 = left + width - strip.widthPx;
  ctx.save();
  ctx.beginPath();
  ctx.rect(x0, 0, cw - x0, ch);
  if (xAxis) {
    // Tick labels centred near the strip reach into the shifted pixels: redraw them whole.
    const reach = Math.ceil(LABEL_HALF_PX * (devicePixelRatio || 1));
    ctx.rect(x0 - reach, top + height, cw - x0 + reach, ch - top - height);
  }
  ctx.clip();
  try {
    // uPlot clears the canvas (clipped: the strip) and draws axes, grid, series, hooks.
    u.batch(set);
  } finally {
    ctx.restore();
  }
  return u.scales.y?.min !== yMin || u.scales.y?.max !== yMax;
}
