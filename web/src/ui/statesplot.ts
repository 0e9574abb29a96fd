// The "states" plot of the scope: an enumerated channel (e.g. the EP7047 drive state)
// as a timeline with one lane per state seen, drawn as coloured run bars joined by a
// step trace. Split from plots.ts; the PlotStack owns the panels and calls these.
import type uPlot from "uplot";
import type { AxisBuffer } from "../buffer";
import type { StateNames } from "../states";

export const STATE_LANE_PX = 15; // one lane per state of a states plot

/** A "states" plot: the channel as a timeline, one lane per state that occurred. */
export interface StatesPanel {
  channel: string;
  names: StateNames;
  seen: Set<number>;
  lanes: number[]; // state values, ascending; the first lane is drawn at the top
  scannedT: number; // the buffer is scanned for new states up to here
  x: number[]; // the drawn run starts (and the last sample's time)
  values: number[]; // the state from each x on
  swatch: HTMLElement;
  id: HTMLElement;
}

/** Lanes drawn for a states plot (two at least, so one state is not a full-height bar). */
export const laneCount = (s: StatesPanel): number => Math.max(2, s.lanes.length);
export const statesPx = (s: StatesPanel): number => laneCount(s) * STATE_LANE_PX + 8;

/** Add the states that occurred in the buffer since the last scan; true if any is new. */
export function scanStates(buffer: AxisBuffer, s: StatesPanel): boolean {
  const col = buffer.channels.get(s.channel);
  if (!col) return false;
  const from = Math.max(buffer.start, buffer.indexAt(s.scannedT));
  let added = false;
  for (let i = from; i < buffer.end; i++) {
    const v = col[i] as number;
    if (Number.isNaN(v) || s.seen.has(v)) continue;
    s.seen.add(v);
    added = true;
  }
  if (buffer.end > buffer.start) s.scannedT = (buffer.t[buffer.end - 1] as number) + 1e-9;
  if (added) s.lanes = [...s.seen].sort((a, b) => a - b);
  return added;
}

/** y of a state's lane: the first lane (lowest value) at the top. */
export function lanePos(s: StatesPanel, value: number): number {
  return laneCount(s) - 1 - s.lanes.indexOf(value);
}

/** The run-length form of [lo, hi): a point where the state changes, and the end.
 * A missing sample (slow or skipped read) holds the state before it. */
export function statesRuns(buffer: AxisBuffer, s: StatesPanel, lo: number, hi: number): void {
  const col = buffer.channels.get(s.channel);
  s.x = [];
  s.values = [];
  if (!col || hi <= lo) return;
  let current = Number.NaN;
  for (let i = lo - 1; i >= Math.max(buffer.start, lo - 4096) && Number.isNaN(current); i--) current = col[i] as number;
  if (!Number.isNaN(current)) {
    s.x.push(buffer.t[lo] as number);
    s.values.push(current);
  }
  for (let i = lo; i < hi; i++) {
    const v = col[i] as number;
    if (Number.isNaN(v) || v === current) continue;
    const t = buffer.t[i] as number;
    if (s.x.length && (s.x[s.x.length - 1] as number) >= t) s.values[s.values.length - 1] = v;
    else {
      s.x.push(t);
      s.values.push(v);
    }
    current = v;
  }
  const end = buffer.t[hi - 1] as number;
  if (s.x.length && end > (s.x[s.x.length - 1] as number)) {
    s.x.push(end);
    s.values.push(current);
  }
}

/** The state at time ``x`` of what is drawn (null before the first run). */
export function stateAt(s: StatesPanel, x: number): number | null {
  let lo = 0;
  let hi = s.x.length - 1;
  if (hi < 0 || x < (s.x[0] as number)) return null;
  while (lo < hi) {
    const mid = (lo + hi + 1) >> 1;
    if ((s.x[mid] as number) <= x) lo = mid;
    else hi = mid - 1;
  }
  return s.values[lo] ?? null;
}

/** Coloured bars, one per run of a state, in its lane, joined by a step trace. */
export function drawStates(u: uPlot, s: StatesPanel, theme: { grid: string; axis: string }, light: boolean, mono: string): void {
  const ctx = u.ctx;
  const { left, top, width, height } = u.bbox;
  const px = devicePixelRatio || 1;
  const lane = height / laneCount(s);
  const bar = Math.max(3 * px, lane * 0.64);
  ctx.save();
  ctx.beginPath();
  ctx.rect(left, top, width, height);
  ctx.clip();
  // Faint lane guides.
  ctx.fillStyle = theme.grid;
  for (let i = 0; i < laneCount(s); i++) ctx.fillRect(left, Math.round(top + (i + 0.5) * lane), width, px);
  ctx.font = `${10 * px}px ${mono}`;
  ctx.textBaseline = "middle";
  ctx.textAlign = "left";
  // The step trace: a vertical connector at each change, bar edge to bar edge.
  ctx.strokeStyle = theme.axis;
  ctx.lineWidth = px;
  ctx.beginPath();
  for (let i = 1; i + 1 < s.x.length; i++) {
    const from = s.values[i - 1] as number;
    const to = s.values[i] as number;
    const x = Math.round(u.valToPos(s.x[i] as number, "x", true)) + 0.5;
    if (x < left || x > left + width) continue;
    const y0 = u.valToPos(lanePos(s, from), "y", true);
    const y1 = u.valToPos(lanePos(s, to), "y", true);
    const dir = y1 > y0 ? 1 : -1;
    ctx.moveTo(x, y0 + (dir * bar) / 2);
    ctx.lineTo(x, y1 - (dir * bar) / 2);
  }
  ctx.stroke();
  for (let i = 0; i + 1 < s.x.length; i++) {
    const value = s.values[i] as number;
    const x0 = u.valToPos(s.x[i] as number, "x", true);
    const x1 = u.valToPos(s.x[i + 1] as number, "x", true);
    if (x1 < left || x0 > left + width) continue;
    const y = u.valToPos(lanePos(s, value), "y", true);
    const w = Math.max(2 * px, x1 - x0);
    ctx.fillStyle = s.names.color(value, light);
    ctx.globalAlpha = 0.85;
    ctx.fillRect(x0, y - bar / 2, w, bar);
    ctx.globalAlpha = 1;
    // The name inside a bar wide enough for it (the lane label is on the axis too).
    const name = s.names.name(value);
    const visible0 = Math.max(x0, left);
    const visibleW = Math.min(x1, left + width) - visible0;
    if (bar >= 9 * px && visibleW > ctx.measureText(name).width + 8 * px) {
      ctx.fillStyle = light ? "#ffffff" : "#0b0f14";
      ctx.fillText(name, visible0 + 4 * px, y + 0.5 * px);
    }
  }
  ctx.restore();
}
