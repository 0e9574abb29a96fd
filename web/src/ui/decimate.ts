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
/** A cut keeps the last base period while the median period is within ±25 % of it. */
export const PERIOD_HOLD = 0.25;

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
  /** Typical base sample period (s), the median of the sampled intervals (the last
   * cut's while the median stays within PERIOD_HOLD of it). */
  periodS: number;
  /** Bumped by every cut (Cutter.cut): a drawing can tell which cut it shows. */
  serial: number;
  /** A decimated frame cut on the same pixel columns as the cut before it (serial − 1)
   * equals it in every column that ends before this time: only later columns got new
   * samples (+Infinity: none did). −Infinity when anything may differ (new columns,
   * channels, a cleared buffer, sparse data). */
  changedFromT: number;
}

const periods = new Float64Array(257);

/** The median of up to 257 evenly spread intervals of t[lo..hi) (no allocation). */
export function medianPeriod(t: Float64Array, lo: number, hi: number): number {
  const n = hi - lo;
  if (n < 2) return Number.NaN;
  const step = Math.max(1, Math.floor((n - 1) / 256));
  let m = 0;
  for (let i = lo + 1; i < hi && m < periods.length; i += step) periods[m++] = (t[i] as number) - (t[i - 1] as number);
  const d = periods.subarray(0, m).sort();
  return d[m >> 1] as number;
}

/** Ring slot of column ``k`` (columns before the origin are negative). */
const ring = (k: number, cap: number): number => ((k % cap) + cap) % cap;

/** Per-column min/max of the samples, folded in incrementally.
 *
 * Columns are fixed in time: column k spans [origin + k·colS, origin + (k+1)·colS). A
 * rolling window keeps origin and colS, so every column it already folded stays valid
 * and only the samples that arrived since the last frame are folded in (a few per frame
 * instead of the whole window). The columns live in a ring of typed arrays allocated
 * once per (columns, channels); nothing is allocated per frame. */
class ColumnCache {
  origin = Number.NaN;
  colS = Number.NaN;
  names: string[] = [];
  cap = 0;
  /** Columns k0 .. k1-1 are held (absolute column numbers). */
  k0 = 0;
  k1 = 0;
  /** The next sample to fold (absolute sample number, AxisBuffer.base + index). */
  next = 0;
  /** The first column the last update folded a sample into (−Infinity after a reset,
   * +Infinity when it folded none). */
  touched = Number.NEGATIVE_INFINITY;
  epoch = -1;
  tFirst = new Float64Array(0);
  tLast = new Float64Array(0);
  n = new Uint32Array(0);
  min: Float64Array[] = [];
  max: Float64Array[] = [];
  tMin: Float64Array[] = [];
  tMax: Float64Array[] = [];
  count: Uint32Array[] = [];

  private reset(buffer: AxisBuffer, origin: number, colS: number, names: string[], cap: number, kStart: number): void {
    if (cap !== this.cap || names.length !== this.names.length) {
      this.cap = cap;
      this.tFirst = new Float64Array(cap);
      this.tLast = new Float64Array(cap);
      this.n = new Uint32Array(cap);
      this.min = names.map(() => new Float64Array(cap));
      this.max = names.map(() => new Float64Array(cap));
      this.tMin = names.map(() => new Float64Array(cap));
      this.tMax = names.map(() => new Float64Array(cap));
      this.count = names.map(() => new Uint32Array(cap));
    }
    this.origin = origin;
    this.colS = colS;
    this.names = names;
    this.epoch = buffer.epoch;
    this.k0 = this.k1 = kStart;
    this.next = buffer.base + Math.max(buffer.start, buffer.indexAt(origin + kStart * colS));
  }

  private open(k: number): void {
    const slot = ring(k, this.cap);
    this.n[slot] = 0;
    for (let c = 0; c < this.names.length; c++) {
      (this.count[c] as Uint32Array)[slot] = 0;
      (this.min[c] as Float64Array)[slot] = Infinity;
      (this.max[c] as Float64Array)[slot] = -Infinity;
    }
  }

  /** Hold columns kStart..kStop (inclusive) of ``names``, folding only what is new. */
  update(buffer: AxisBuffer, origin: number, colS: number, names: string[], kStart: number, kStop: number): void {
    const cap = Math.max(64, kStop - kStart + 16);
    const same = origin === this.origin && colS === this.colS && buffer.epoch === this.epoch && names.length === this.names.length && names.every((n, i) => n === this.names[i]);
    // A different grid or channel set, a window that grew to the left, a ring too small,
    // or samples the buffer has dropped since: fold the window from scratch, once.
    const reset = !same || kStart < this.k0 || cap > this.cap || this.next < buffer.base + buffer.start;
    if (reset) this.reset(buffer, origin, colS, names, cap, kStart);
    this.touched = reset ? Number.NEGATIVE_INFINITY : Number.POSITIVE_INFINITY;
    const t = buffer.t;
    const cols = names.map((n) => buffer.channels.get(n));
    const limit = origin + (kStop + 1) * colS;
    let i = this.next - buffer.base;
    const end = buffer.end;
    for (; i < end; i++) {
      const ti = t[i] as number;
      if (ti >= limit) break;
      const k = Math.floor((ti - origin) / colS);
      if (k < this.k0) continue;
      if (k < this.touched) this.touched = k;
      while (this.k1 <= k) {
        this.open(this.k1);
        this.k1 += 1;
        if (this.k1 - this.k0 > this.cap) this.k0 = this.k1 - this.cap;
      }
      const slot = ring(k, this.cap);
      if (this.n[slot] === 0) this.tFirst[slot] = ti;
      this.tLast[slot] = ti;
      this.n[slot] += 1;
      for (let c = 0; c < cols.length; c++) {
        const col = cols[c];
        if (!col) continue;
        const v = col[i] as number;
        if (Number.isNaN(v)) continue;
        (this.count[c] as Uint32Array)[slot] += 1;
        const mn = this.min[c] as Float64Array;
        const mx = this.max[c] as Float64Array;
        if (v < (mn[slot] as number)) {
          mn[slot] = v;
          (this.tMin[c] as Float64Array)[slot] = ti;
        }
        if (v > (mx[slot] as number)) {
          mx[slot] = v;
          (this.tMax[c] as Float64Array)[slot] = ti;
        }
      }
    }
    this.next = buffer.base + i;
    // Columns older than the window are let go (the ring reuses their slots).
    if (kStart > this.k0) this.k0 = Math.min(kStart, this.k1);
  }
}

/** Put ``n`` items in a reused array (no allocation once it has grown). */
function sized<T>(a: T[], n: number): T[] {
  a.length = n;
  return a;
}

/**
 * Cuts time windows out of an axis buffer for drawing, reusing its arrays frame after
 * frame (the returned Frame and its arrays are the same objects each call: draw them
 * before the next call).
 */
export class Cutter {
  private readonly cache = new ColumnCache();
  private readonly frame: Frame = {
    x: [],
    channels: new Map(),
    real: new Map(),
    slow: new Map(),
    decimated: false,
    samples: 0,
    periodS: Number.NaN,
    serial: 0,
    changedFromT: Number.NEGATIVE_INFINITY,
  };
  private at: number[] = [];
  /** The base period of the last cut (see cut). */
  private periodS = Number.NaN;
  private readonly columnsOf = new Map<string, (number | null)[]>();
  private readonly realOf = new Map<string, number[]>();

  private out(name: string): (number | null)[] {
    let a = this.columnsOf.get(name);
    if (!a) {
      a = [];
      this.columnsOf.set(name, a);
    }
    return a;
  }

  private realIdx(name: string): number[] {
    let a = this.realOf.get(name);
    if (!a) {
      a = [];
      this.realOf.set(name, a);
    }
    a.length = 0;
    return a;
  }

  /**
   * Cut [lo, hi) of ``buffer`` for an x range [xmin, xmax] drawn ``columns`` pixels wide.
   * ``channels``: name and display factor (unit conversion). ``origin``: where the pixel
   * columns start in time (a rolling window passes a fixed origin and a range aligned to
   * whole columns, so the columns already folded stay valid); default ``xmin``.
   */
  cut(
    buffer: AxisBuffer,
    lo: number,
    hi: number,
    xmin: number,
    xmax: number,
    columns: number,
    channels: Iterable<[string, number]>,
    origin = xmin,
  ): Frame {
    const t = buffer.t;
    const n = Math.max(0, hi - lo);
    // The period (and with it the gap threshold) is held while the median stays within
    // PERIOD_HOLD of it: the median of a batched stream (EP7047) moves a little from
    // frame to frame, and a new threshold may move a gap marker in any column, so the
    // trace layer would have to draw every column again instead of shifting them.
    const measured = medianPeriod(t, lo, hi);
    const held = this.periodS;
    const periodS = Number.isFinite(held) && Number.isFinite(measured) && Math.abs(measured - held) <= PERIOD_HOLD * held ? held : measured;
    this.periodS = periodS;
    const gapS = Number.isFinite(periodS) ? GAP_PERIODS * periodS : Number.POSITIVE_INFINITY;
    const frame = this.frame;
    frame.channels.clear();
    frame.real.clear();
    frame.slow.clear();
    frame.decimated = false;
    frame.samples = n;
    frame.periodS = periodS;
    frame.serial += 1;
    frame.changedFromT = Number.NEGATIVE_INFINITY;
    const list = [...channels];
    if (n <= columns * 2) {
      this.sparse(buffer, lo, hi, gapS, list);
      return frame;
    }
    // Min/max per pixel column, from the column cache.
    frame.decimated = true;
    const colS = (xmax - xmin) / columns;
    const kLo = Math.floor((xmin - origin) / colS + 1e-9) - 1; // one column either side, so
    const kHi = Math.floor((xmax - origin) / colS + 1e-9) + 1; // lines run to the plot edges
    const names = list.map(([name]) => name);
    const cache = this.cache;
    cache.update(buffer, origin, colS, names, kLo, kHi);
    // (A column that got samples also changes the gap marker and join before it: the
    // consumer redraws from a little left of this time.)
    frame.changedFromT = cache.touched === Number.POSITIVE_INFINITY ? Number.POSITIVE_INFINITY : origin + cache.touched * colS;
    const cap = cache.cap;
    const from = Math.max(kLo, cache.k0);
    const to = Math.min(kHi + 1, cache.k1);
    // Which channels are slow in this window, and their own period.
    let total = 0;
    let tA = Number.NaN;
    let tZ = Number.NaN;
    for (let k = from; k < to; k++) {
      const s = ring(k, cap);
      const m = cache.n[s] as number;
      if (!m) continue;
      total += m;
      if (Number.isNaN(tA)) tA = cache.tFirst[s] as number;
      tZ = cache.tLast[s] as number;
    }
    const counts = names.map((_n, c) => {
      let count = 0;
      const cc = cache.count[c] as Uint32Array;
      for (let k = from; k < to; k++) count += cc[ring(k, cap)] as number;
      return count;
    });
    names.forEach((name, c) => {
      const count = counts[c] as number;
      if (buffer.channels.has(name) && total >= 4 && count > 0 && count < SLOW_FILL * total) frame.slow.set(name, (tZ - tA) / Math.max(1, count - 1));
    });
    // x: the first and the last sample time of every non-empty column; a null point
    // (x between the two) where the time between columns is a gap.
    const x = frame.x;
    let nx = 0;
    let prevT = Number.NaN;
    for (let k = from; k < to; k++) {
      const s = ring(k, cap);
      if (!cache.n[s]) continue;
      const a = cache.tFirst[s] as number;
      if (!Number.isNaN(prevT) && a - prevT > gapS) x[nx++] = (prevT + a) / 2;
      x[nx++] = a;
      x[nx++] = cache.tLast[s] as number;
      prevT = cache.tLast[s] as number;
    }
    x.length = nx;
    list.forEach(([name, factor], c) => {
      const out = sized(this.out(name), nx);
      const slowPeriod = frame.slow.get(name);
      const real = slowPeriod === undefined ? null : this.realIdx(name);
      const holdS = slowPeriod === undefined ? 0 : Math.max(gapS, SLOW_HOLD * slowPeriod);
      const mn = cache.min[c] as Float64Array;
      const mx = cache.max[c] as Float64Array;
      const tmn = cache.tMin[c] as Float64Array;
      const tmx = cache.tMax[c] as Float64Array;
      const cc = cache.count[c] as Uint32Array;
      let held = Number.NaN;
      let heldT = Number.NEGATIVE_INFINITY;
      let j = 0;
      let prev = Number.NaN;
      const present = buffer.channels.has(name);
      for (let k = from; k < to; k++) {
        const s = ring(k, cap);
        if (!cache.n[s]) continue;
        const a = cache.tFirst[s] as number;
        if (!Number.isNaN(prev) && a - prev > gapS) out[j++] = null;
        prev = cache.tLast[s] as number;
        if (present && (cc[s] as number) > 0) {
          const lo_ = mn[s] as number;
          const hi_ = mx[s] as number;
          const minFirst = (tmn[s] as number) <= (tmx[s] as number);
          if (real) {
            real.push(j);
            held = minFirst ? hi_ : lo_;
            heldT = Math.max(tmn[s] as number, tmx[s] as number);
          }
          out[j++] = (minFirst ? lo_ : hi_) * factor;
          out[j++] = (minFirst ? hi_ : lo_) * factor;
        } else if (real && !Number.isNaN(held) && a - heldT <= holdS) {
          out[j++] = held * factor;
          out[j++] = held * factor;
        } else {
          out[j++] = null;
          out[j++] = null;
        }
      }
      if (real) frame.real.set(name, real);
      frame.channels.set(name, out);
    });
    return frame;
  }

  /** Sample by sample (sparse data); a null point marks every gap in time. */
  private sparse(buffer: AxisBuffer, lo: number, hi: number, gapS: number, list: [string, number][]): void {
    const frame = this.frame;
    const t = buffer.t;
    const n = hi - lo;
    for (const [name] of list) {
      const col = buffer.channels.get(name);
      if (!col || n < 4) continue;
      let count = 0;
      for (let i = lo; i < hi; i++) if (!Number.isNaN(col[i] as number)) count++;
      if (count > 0 && count < SLOW_FILL * n) frame.slow.set(name, ((t[hi - 1] as number) - (t[lo] as number)) / Math.max(1, count - 1));
    }
    const x = frame.x;
    const at = this.at; // buffer index per x, -1 for a gap marker
    let nx = 0;
    for (let i = lo; i < hi; i++) {
      const ti = t[i] as number;
      if (i > lo && ti - (t[i - 1] as number) > gapS) {
        x[nx] = ((t[i - 1] as number) + ti) / 2;
        at[nx++] = -1;
      }
      x[nx] = ti;
      at[nx++] = i;
    }
    x.length = nx;
    at.length = nx;
    for (const [name, factor] of list) {
      const col = buffer.channels.get(name);
      const out = sized(this.out(name), nx);
      const slowPeriod = frame.slow.get(name);
      if (!col) out.fill(null);
      else if (slowPeriod === undefined) {
        for (let k = 0; k < nx; k++) {
          const i = at[k] as number;
          const v = i < 0 ? Number.NaN : (col[i] as number);
          out[k] = Number.isNaN(v) ? null : v * factor;
        }
      } else {
        const real = this.realIdx(name);
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
        for (let k = 0; k < nx; k++) {
          const i = at[k] as number;
          const v = i < 0 ? Number.NaN : (col[i] as number);
          out[k] = null;
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
  }
}

/** One-off cut (tests, CSV): a fresh Cutter, see Cutter.cut. */
export function cut(
  buffer: AxisBuffer,
  lo: number,
  hi: number,
  xmin: number,
  xmax: number,
  columns: number,
  channels: Iterable<[string, number]>,
): Frame {
  return new Cutter().cut(buffer, lo, hi, xmin, xmax, columns, channels);
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

/**
 * The runs of one flag (as flagRuns) for a window that moves forward, scanning only the
 * samples that arrived since the last call. Runs that ended before the window are let
 * go; a run that began before it keeps its real start (the plot clips it). Any other
 * request — a window that moved back or ends earlier than the last (pause, zoom), a
 * cleared buffer, a gap threshold more than 25 % off the one scanned with — scans the
 * window afresh, once. The returned array is reused: draw it before the next call.
 */
export class FlagRunCache {
  private closed: number[] = [];
  /** Index in ``closed`` of the first run still in the window. */
  private head = 0;
  private open = Number.NaN;
  /** Absolute sample numbers (AxisBuffer.base + index): scanned [from, next). */
  private from = 0;
  private next = 0;
  private epoch = -1;
  private gapS = Number.NaN;
  private readonly out: number[] = [];

  constructor(readonly name: string) {}

  runs(buffer: AxisBuffer, lo: number, hi: number, gapS: number): number[] {
    const out = this.out;
    out.length = 0;
    const col = buffer.flags.get(this.name);
    if (!col || hi <= lo) return out;
    const t = buffer.t;
    const absLo = buffer.base + lo;
    const absHi = buffer.base + hi;
    const sameGap = gapS === this.gapS || Math.abs(gapS - this.gapS) <= 0.25 * this.gapS;
    if (buffer.epoch !== this.epoch || !sameGap || absLo < this.from || absHi < this.next || this.next < buffer.base + buffer.start) {
      this.closed.length = 0;
      this.head = 0;
      this.open = Number.NaN;
      this.from = this.next = absLo;
      this.epoch = buffer.epoch;
      this.gapS = gapS;
    }
    const first = this.from - buffer.base;
    for (let i = this.next - buffer.base; i < hi; i++) {
      const ti = t[i] as number;
      if (!Number.isNaN(this.open) && i > first && ti - (t[i - 1] as number) > this.gapS) {
        this.closed.push(this.open, t[i - 1] as number);
        this.open = Number.NaN;
      }
      const on = col[i] === 1;
      if (on && Number.isNaN(this.open)) this.open = ti;
      else if (!on && !Number.isNaN(this.open)) {
        this.closed.push(this.open, ti);
        this.open = Number.NaN;
      }
    }
    this.next = absHi;
    const startT = t[lo] as number;
    while (this.head + 1 < this.closed.length && (this.closed[this.head + 1] as number) < startT) this.head += 2;
    if (this.head > 256) {
      this.closed.splice(0, this.head);
      this.head = 0;
    }
    for (let k = this.head; k < this.closed.length; k++) out.push(this.closed[k] as number);
    if (!Number.isNaN(this.open)) out.push(this.open, t[hi - 1] as number);
    return out;
  }
}
