// Per-axis telemetry ring: contiguous typed arrays with compaction, so any time
// window is a plain index range. Missing samples (null) are stored as NaN.
import type { Telemetry } from "./schema.gen";

export const KEEP_SECONDS = 60;
const INITIAL_CAPACITY = 8192;
const MAX_CAPACITY = 1 << 21;
/** Epochs of detached copies (``snapshot``): never equal to a live ring's, so a view's
 * caches (decimation, flag runs) start over when it switches between the two. */
let snapshotEpoch = 1 << 30;

export class AxisBuffer {
  capacity = INITIAL_CAPACITY;
  start = 0;
  end = 0;
  t = new Float64Array(INITIAL_CAPACITY);
  readonly channels = new Map<string, Float64Array>();
  readonly flags = new Map<string, Uint8Array>();
  /** Latest non-null value per channel and latest state per flag. */
  readonly latest = new Map<string, number>();
  /** Server time of the latest non-null value per channel (the age of a slow value). */
  readonly latestT = new Map<string, number>();
  readonly latestFlags = new Map<string, number>();
  samplesReceived = 0;
  lastT = Number.NaN;
  /** Bumped on every push, so views can tell whether to redraw. */
  version = 0;
  /** Absolute sample number of index 0 (compaction moves data, not sample numbers):
   * index i holds sample ``base + i``, so a cache can tell which samples are new. */
  base = 0;
  /** Bumped by clear(): sample numbers start over, caches must too. */
  epoch = 0;

  get length(): number {
    return this.end - this.start;
  }

  clear(): void {
    this.start = this.end = 0;
    this.latest.clear();
    this.latestT.clear();
    this.latestFlags.clear();
    this.lastT = Number.NaN;
    this.base = 0;
    this.epoch += 1;
    this.version += 1;
  }

  push(msg: Telemetry): void {
    const n = msg.t.length;
    if (n === 0) return;
    const first = msg.t[0] as number;
    // The server restarted (its clock starts at 0 again): start over.
    if (Number.isFinite(this.lastT) && first < this.lastT - 1) this.clear();
    this.reserve(n);
    const at = this.end;
    this.t.set(msg.t, at);
    for (const [name, values] of Object.entries(msg.channels)) {
      const column = this.channel(name);
      let latest: number | undefined;
      let latestAt = 0;
      for (let i = 0; i < n; i++) {
        const v = values[i];
        if (v === null || v === undefined) column[at + i] = Number.NaN;
        else {
          column[at + i] = v;
          latest = v;
          latestAt = i;
        }
      }
      if (latest !== undefined) {
        this.latest.set(name, latest);
        this.latestT.set(name, msg.t[latestAt] as number);
      }
    }
    for (const [name, column] of this.channels) {
      if (!(name in msg.channels)) column.fill(Number.NaN, at, at + n);
    }
    for (const [name, values] of Object.entries(msg.flags)) {
      const column = this.flag(name);
      for (let i = 0; i < n; i++) column[at + i] = values[i] ? 1 : 0;
      this.latestFlags.set(name, values[n - 1] ? 1 : 0);
    }
    for (const [name, column] of this.flags) {
      if (!(name in msg.flags)) column.fill(column[at - 1] ?? 0, at, at + n);
    }
    this.end += n;
    this.samplesReceived += n;
    this.lastT = msg.t[n - 1] as number;
    this.version += 1;
  }

  /** A detached copy of the samples with times in [``from``, ``to``] (and one either
   * side): what a single-shot capture keeps once the ring has dropped them (it keeps
   * KEEP_SECONDS). Never written to again. */
  snapshot(from: number, to: number): AxisBuffer {
    const lo = Math.max(this.start, this.indexAt(from) - 1);
    const hi = Math.min(this.end, this.indexAt(to) + 1);
    const copy = new AxisBuffer();
    const n = Math.max(0, hi - lo);
    copy.capacity = Math.max(1, n);
    copy.t = this.t.slice(lo, hi);
    for (const [name, col] of this.channels) copy.channels.set(name, col.slice(lo, hi));
    for (const [name, col] of this.flags) copy.flags.set(name, col.slice(lo, hi));
    copy.end = n;
    copy.samplesReceived = n;
    copy.lastT = n ? (copy.t[n - 1] as number) : Number.NaN;
    snapshotEpoch += 1;
    copy.epoch = snapshotEpoch;
    copy.version = 1;
    return copy;
  }

  /** First index whose time is >= ``time`` (binary search). */
  indexAt(time: number): number {
    let lo = this.start;
    let hi = this.end;
    while (lo < hi) {
      const mid = (lo + hi) >>> 1;
      if ((this.t[mid] as number) < time) lo = mid + 1;
      else hi = mid;
    }
    return lo;
  }

  /** Time of the sample nearest to ``time``, or null when empty. */
  nearestT(time: number): number | null {
    if (!this.length) return null;
    const i = Math.min(this.end - 1, Math.max(this.start, this.indexAt(time)));
    const j = Math.max(this.start, i - 1);
    const ti = this.t[i] as number;
    const tj = this.t[j] as number;
    return Math.abs(ti - time) <= Math.abs(tj - time) ? ti : tj;
  }

  /** The latest real (non-null) value of ``name`` at or before ``time``, or null. */
  valueAt(name: string, time: number): number | null {
    const col = this.channels.get(name);
    if (!col || !this.length) return null;
    let i = Math.min(this.end - 1, this.indexAt(time + 1e-9) - 1);
    for (let k = 0; i >= this.start && k < 4096; i--, k++) {
      const v = col[i] as number;
      if (!Number.isNaN(v)) return v;
    }
    return null;
  }

  get firstT(): number {
    return this.length ? (this.t[this.start] as number) : Number.NaN;
  }

  private channel(name: string): Float64Array {
    let column = this.channels.get(name);
    if (!column) {
      column = new Float64Array(this.capacity).fill(Number.NaN);
      this.channels.set(name, column);
    }
    return column;
  }

  private flag(name: string): Uint8Array {
    let column = this.flags.get(name);
    if (!column) {
      column = new Uint8Array(this.capacity);
      this.flags.set(name, column);
    }
    return column;
  }

  /** Make room for ``n`` more samples: drop what is older than KEEP_SECONDS, compact, grow. */
  private reserve(n: number): void {
    if (this.end + n <= this.capacity) return;
    if (Number.isFinite(this.lastT)) {
      this.start = Math.max(this.start, this.indexAt(this.lastT - KEEP_SECONDS));
    }
    let capacity = this.capacity;
    while (this.length + n > capacity * 0.75 && capacity < MAX_CAPACITY) capacity *= 2;
    if (this.length + n > capacity) {
      // Faster than MAX_CAPACITY/60 s allows: keep what fits.
      this.start = this.end - (capacity - n);
    }
    const move = <A extends Float64Array | Uint8Array>(old: A, make: (size: number) => A): A => {
      if (capacity === this.capacity) {
        old.copyWithin(0, this.start, this.end);
        return old;
      }
      const fresh = make(capacity);
      fresh.set(old.subarray(this.start, this.end));
      return fresh;
    };
    this.t = move(this.t, (s) => new Float64Array(s));
    for (const [name, col] of this.channels) {
      this.channels.set(name, move(col, (s) => new Float64Array(s).fill(Number.NaN)));
    }
    for (const [name, col] of this.flags) this.flags.set(name, move(col, (s) => new Uint8Array(s)));
    this.end -= this.start;
    this.base += this.start;
    this.start = 0;
    this.capacity = capacity;
  }
}
