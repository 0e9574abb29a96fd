// Scope trigger: a flag edge (e.g. `move` rising) or a channel crossing a level, with a
// pre-trigger share of the window, single or normal mode. Works on the axis' ring
// buffer: new samples are scanned once per frame (only those not scanned yet), and a
// capture completes when the buffer has reached the end of the post-trigger part.
import type { AxisBuffer } from "../buffer";

export type Edge = "rising" | "falling";

export type TriggerSource =
  | { kind: "flag"; name: string; edge: Edge }
  | { kind: "level"; name: string; edge: Edge; level: number }; // level in device units

export interface TriggerConfig {
  source: TriggerSource | null;
  mode: "single" | "normal";
  /** Share of the window before the trigger point, 0..0.9. */
  pre: number;
}

export class Trigger {
  config: TriggerConfig = { source: null, mode: "single", pre: 0.2 };
  armed = false;
  /** Server time of the trigger point being recorded (post-trigger part not complete). */
  pendingT: number | null = null;
  /** Server time of the trigger point of the capture on screen. */
  capturedT: number | null = null;
  private scanFrom = Number.NaN;

  get active(): boolean {
    return this.config.source !== null;
  }

  arm(buffer: AxisBuffer): void {
    this.armed = this.active;
    this.pendingT = null;
    this.scanFrom = buffer.lastT;
  }

  off(): void {
    this.config.source = null;
    this.armed = false;
    this.pendingT = null;
    this.capturedT = null;
  }

  /** The window [min, max] of the capture on screen, or null. */
  window(windowS: number): [number, number] | null {
    if (this.capturedT === null) return null;
    const pre = this.config.pre * windowS;
    return [this.capturedT - pre, this.capturedT + windowS - pre];
  }

  /** Scan what arrived since the last call; true when a new capture completed. */
  poll(buffer: AxisBuffer, windowS: number): boolean {
    const source = this.config.source;
    if (!this.armed || !source || !Number.isFinite(buffer.lastT)) return false;
    if (this.pendingT === null) {
      const from = Number.isFinite(this.scanFrom) ? Math.max(buffer.start + 1, buffer.indexAt(this.scanFrom)) : buffer.end;
      this.pendingT = findEdge(buffer, source, from, buffer.end);
      this.scanFrom = buffer.lastT;
    }
    if (this.pendingT === null) return false;
    const post = windowS * (1 - this.config.pre);
    if (buffer.lastT < this.pendingT + post) return false;
    this.capturedT = this.pendingT;
    this.pendingT = null;
    if (this.config.mode === "single") this.armed = false;
    // Normal mode: the next trigger is searched after this capture's window (hold-off).
    else this.scanFrom = this.capturedT + post;
    return true;
  }
}

/** Time of the first edge in buffer indices [from, to), or null. */
export function findEdge(buffer: AxisBuffer, source: TriggerSource, from: number, to: number): number | null {
  const t = buffer.t;
  if (source.kind === "flag") {
    const col = buffer.flags.get(source.name);
    if (!col) return null;
    const want = source.edge === "rising" ? 1 : 0;
    for (let i = Math.max(from, buffer.start + 1); i < to; i++) {
      if (col[i] === want && col[i - 1] !== want) return t[i] as number;
    }
    return null;
  }
  const col = buffer.channels.get(source.name);
  if (!col) return null;
  let prev = Number.NaN;
  for (let i = from - 1; i >= buffer.start && Number.isNaN(prev) && i > from - 256; i--) prev = col[i] as number;
  for (let i = from; i < to; i++) {
    const v = col[i] as number;
    if (Number.isNaN(v)) continue;
    if (!Number.isNaN(prev)) {
      if (source.edge === "rising" && prev < source.level && v >= source.level) return t[i] as number;
      if (source.edge === "falling" && prev > source.level && v <= source.level) return t[i] as number;
    }
    prev = v;
  }
  return null;
}
