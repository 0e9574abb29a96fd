// Cutting a time window out of an axis buffer for drawing: honest and cheap.
//
// - Dense data is min/max-decimated per pixel column (time-based columns, so a gap in
//   time stays a gap and an extreme inside a column is never lost).
// - Sparse data is returned sample by sample; the caller draws markers on the samples
//   when they are more than a few pixels apart.
// - A gap in time longer than GAP_PERIODS sample periods becomes a null (a break in the
//   line), never a straight line across it.
// - A slow channel (one that has a value in less than SLOW_FILL of the samples, e.g.
//   SLAP2 `rve` every 8th poll) is returned held: its last real value is repeated until
//   its next real sample (drawn as a step), for at most SLOW_HOLD of its own periods; the
//   indices of its real samples are returned too (markers and "age" of the value).
import type { AxisBuffer } from "../buffer";

export const GAP_PERIODS = 5;
export const SLOW_FILL = 0.6;
export const SLOW_HOLD = 3;

export interface Frame {
  x: number[];
  channels: Map<string, (number | null)[]>;
  /** Index in ``x`` of every real sample of each slow channel. */
  real: Map<string, number[]>;
  /** Slow channels with their own sample period (s). */
  slow: Map<string, number>;
  decimated: boolean;
  /** Samples in the window (before decimation). */
  samples: number;
  /** Typical base sample period (s), the median of the sampled intervals. */
  periodS: number;
}

/** The median of up to 257 evenly spread intervals of t[lo..hi). */
export function medianPeriod(t: Float64Array, lo: number, hi: number): number {
  const n = hi - lo;
  if (n < 2) return Number.NaN;
  const step = Math.max(1, Math.floor((n - 1) / 256));
  const d: number[] = [];
  for (let i = lo + 1; i < hi; i += step) d.push((t[i] as number) - (t[i - 1] as number));
  d.sort((a, b) => a - b);
  return d[d.length >> 1] as number;
}

/**
 * Cut [lo, hi) of ``buffer`` for an x range [xmin, xmax] drawn ``columns`` pixels wide.
 * ``channels``: name and display factor (unit conversion).
 */
export function cut(
  buffer: AxisBuffer,
  lo: number,
  hi: number,
  xmin: number,
  xmax: number,
  columns: number,
  channels: Iterable<[string, number]>,
): Frame {
  const t = buffer.t;
  const n = Math.max(0, hi - lo);
  const periodS = medianPeriod(t, lo, hi);
  const gapS = Number.isFinite(periodS) ? GAP_PERIODS * periodS : Number.POSITIVE_INFINITY;
  const frame: Frame = { x: [], channels: new Map(), real: new Map(), slow: new Map(), decimated: false, samples: n, periodS };
  const list = [...channels];
  // Which channels are slow, and their own period.
  for (const [name] of list) {
    const col = buffer.channels.get(name);
    if (!col || n < 4) continue;
    let count = 0;
    for (let i = lo; i < hi; i++) if (!Number.isNaN(col[i] as number)) count++;
    if (count > 0 && count < SLOW_FILL * n) frame.slow.set(name, ((t[hi - 1] as number) - (t[lo] as number)) / Math.max(1, count - 1));
  }
  if (n <= columns * 2) {
    // Sample by sample; a null point marks every gap in time.
    const x: number[] = [];
    const at: number[] = []; // buffer index per x, -1 for a gap marker
    for (let i = lo; i < hi; i++) {
      const ti = t[i] as number;
      if (i > lo && ti - (t[i - 1] as number) > gapS) {
        x.push(((t[i - 1] as number) + ti) / 2);
        at.push(-1);
      }
      x.push(ti);
      at.push(i);
    }
    frame.x = x;
    for (const [name, factor] of list) {
      const col = buffer.channels.get(name);
      const out: (number | null)[] = new Array(x.length).fill(null);
      const slowPeriod = frame.slow.get(name);
      if (col && slowPeriod === undefined) {
        for (let k = 0; k < x.length; k++) {
          const i = at[k] as number;
          const v = i < 0 ? Number.NaN : (col[i] as number);
          out[k] = Number.isNaN(v) ? null : v * factor;
        }
      } else if (col && slowPeriod !== undefined) {
        const real: number[] = [];
        const holdS = Math.max(gapS, SLOW_HOLD * slowPeriod);
        let held = Number.NaN;
        let heldT = Number.NEGATIVE_INFINITY;
        // Start held with the last real value before the window (within the hold time).
        for (let i = lo - 1; i >= Math.max(buffer.start, lo - 256); i--) {
          const v = col[i] as number;
          if (!Number.isNaN(v)) {
            held = v;
            heldT = t[i] as number;
            break;
          }
        }
        for (let k = 0; k < x.length; k++) {
          const i = at[k] as number;
          const v = i < 0 ? Number.NaN : (col[i] as number);
          if (!Number.isNaN(v)) {
            held = v;
            heldT = x[k] as number;
            out[k] = v * factor;
            real.push(k);
          } else if (i >= 0 && !Number.isNaN(held) && (x[k] as number) - heldT <= holdS) out[k] = held * factor;
        }
        frame.real.set(name, real);
      }
      frame.channels.set(name, out);
    }
    return frame;
  }
  // Min/max per pixel column.
  frame.decimated = true;
  const colS = (xmax - xmin) / columns;
  const starts: number[] = []; // first buffer index of each non-empty column
  let last = -1;
  for (let i = lo; i < hi; i++) {
    const c = Math.min(columns - 1, Math.max(0, Math.floor(((t[i] as number) - xmin) / colS)));
    if (c !== last) {
      starts.push(i);
      last = c;
    }
  }
  starts.push(hi);
  const x: number[] = [];
  const gapBefore: boolean[] = [];
  for (let b = 0; b + 1 < starts.length; b++) {
    const a = starts[b] as number;
    const z = (starts[b + 1] as number) - 1;
    const gap = b > 0 && (t[a] as number) - (t[a - 1] as number) > gapS;
    if (gap) x.push(((t[a - 1] as number) + (t[a] as number)) / 2);
    gapBefore.push(gap);
    x.push(t[a] as number, t[z] as number);
  }
  frame.x = x;
  for (const [name, factor] of list) {
    const col = buffer.channels.get(name);
    const out: (number | null)[] = [];
    const real: number[] = [];
    const slowPeriod = frame.slow.get(name);
    const holdS = slowPeriod === undefined ? 0 : Math.max(gapS, SLOW_HOLD * slowPeriod);
    let held = Number.NaN;
    let heldT = Number.NEGATIVE_INFINITY;
    for (let b = 0; b + 1 < starts.length; b++) {
      const a = starts[b] as number;
      const z = starts[b + 1] as number;
      if (gapBefore[b]) out.push(null);
      let min = Infinity;
      let max = -Infinity;
      let iMin = 0;
      let iMax = 0;
      if (col) {
        for (let i = a; i < z; i++) {
          const v = col[i] as number;
          if (Number.isNaN(v)) continue;
          if (v < min) {
            min = v;
            iMin = i;
          }
          if (v > max) {
            max = v;
            iMax = i;
          }
        }
      }
      if (min !== Infinity) {
        if (slowPeriod !== undefined) {
          real.push(out.length);
          held = iMin <= iMax ? max : min;
          heldT = t[Math.max(iMin, iMax)] as number;
        }
        if (iMin <= iMax) out.push(min * factor, max * factor);
        else out.push(max * factor, min * factor);
      } else if (slowPeriod !== undefined && !Number.isNaN(held) && (t[a] as number) - heldT <= holdS) {
        out.push(held * factor, held * factor);
      } else out.push(null, null);
    }
    if (slowPeriod !== undefined) frame.real.set(name, real);
    frame.channels.set(name, out);
  }
  return frame;
}

/** Intervals [t0, t1, t0, t1, …] where ``flag`` is on in [lo, hi); a gap in time ends a run. */
export function flagRuns(buffer: AxisBuffer, name: string, lo: number, hi: number, gapS: number): number[] {
  const col = buffer.flags.get(name);
  const t = buffer.t;
  const runs: number[] = [];
  if (!col || hi <= lo) return runs;
  let start = Number.NaN;
  for (let i = lo; i < hi; i++) {
    const on = col[i] === 1;
    const ti = t[i] as number;
    if (!Number.isNaN(start) && i > lo && ti - (t[i - 1] as number) > gapS) {
      runs.push(start, t[i - 1] as number);
      start = Number.NaN;
    }
    if (on && Number.isNaN(start)) start = ti;
    else if (!on && !Number.isNaN(start)) {
      runs.push(start, ti);
      start = Number.NaN;
    }
  }
  if (!Number.isNaN(start)) runs.push(start, t[hi - 1] as number);
  return runs;
}
