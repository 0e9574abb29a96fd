// Number formatting and unit conversions shared by readouts, plots and the tuning panel.
import type { Conversion } from "./schema.gen";

/** A display unit: the device unit (factor 1) or one of the descriptor's conversions. */
export interface Unit {
  unit: string;
  factor: number;
  digits: number | null; // null: native device units, digits chosen by magnitude
}

export function nativeUnit(unit: string): Unit {
  return { unit, factor: 1, digits: null };
}

export function unitsOf(unit: string, conversions: Conversion[]): Unit[] {
  return [nativeUnit(unit), ...conversions.map((c) => ({ unit: c.unit, factor: c.factor, digits: c.digits }))];
}

/** Format a value already converted to ``unit``. ASCII minus so tests can parse it. */
export function formatValue(value: number | null | undefined, unit: Unit): string {
  if (value === null || value === undefined || !Number.isFinite(value)) return "—";
  if (unit.digits !== null) return value.toFixed(unit.digits);
  if (Number.isInteger(value)) return String(value);
  const abs = Math.abs(value);
  return value.toFixed(abs >= 1000 ? 0 : abs >= 10 ? 1 : 2);
}

export function convert(value: number, unit: Unit): number {
  return value * unit.factor;
}

/** "549.2 rpm" for a conversion of a raw device value. */
export function formatConverted(raw: number, c: Conversion): string {
  return `${(raw * c.factor).toFixed(c.digits)} ${c.unit}`;
}

/** Seconds as shown in the event log: server clock, 0.1 s resolution. */
export function formatSeconds(t: number): string {
  return `${t.toFixed(1)} s`;
}

export function formatClock(date: Date): string {
  const p = (n: number, w = 2): string => String(n).padStart(w, "0");
  return `${p(date.getHours())}:${p(date.getMinutes())}:${p(date.getSeconds())}.${p(date.getMilliseconds(), 3)}`;
}

/** A stored item's time (unix seconds): "14:03:22" today, "11-23 14:03" before. */
export function clock(unixS: number): { time: string; full: string } {
  const d = new Date(unixS * 1000);
  const p = (n: number): string => String(n).padStart(2, "0");
  const time = `${p(d.getHours())}:${p(d.getMinutes())}:${p(d.getSeconds())}`;
  const today = new Date().toDateString() === d.toDateString();
  return { time: today ? time : `${p(d.getMonth() + 1)}-${p(d.getDate())} ${time.slice(0, 5)}`, full: d.toLocaleString() };
}
