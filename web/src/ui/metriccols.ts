// The metric columns of the bench's runs table, shared with the auto-tune panel (its
// predicted and measured metrics use the same columns, units and definitions).
import type { RunMetrics } from "../api";
import { h, setText } from "../dom";
import { metricHelp } from "../metrics";
import type { DeviceDescriptor, RunQuality as StoredQuality } from "../schema.gen";

export interface MetricColumn {
  key: string; // testid suffix: bench-metric-{run}-{key}
  label: string;
  unit: string;
  help: string;
  get(m: RunMetrics): number | null | undefined;
  /** The ± of the value where the server gives one (flag times: flags are polled). */
  resolution?(m: RunMetrics): number | null | undefined;
  /** For times located between samples: the run's sample spacing. A difference within
   * it is no difference (the auto-tune's verdict uses the same resolution). */
  spacing?(m: RunMetrics): number | null | undefined;
  text(v: number): string;
  /** An absolute difference below this is not "better" or "worse". */
  slack: number;
}

/** What the server says of a finished run (servotune/bench/quality.py): ``bad`` runs are
 * not comparable (limit switch, stall, did not move, ended outside the window, cut
 * off); ``untrusted`` names the metrics set to null and why. */
export type RunQuality = Required<Pick<StoredQuality, "status" | "reasons" | "untrusted">>;

/** The quality of a run, if the server stored one (older runs have none). */
export function qualityOf(run: object | null | undefined): RunQuality | null {
  const q = (run as { quality?: unknown } | null | undefined)?.quality;
  if (!q || typeof q !== "object") return null;
  const r = q as Partial<RunQuality>;
  return { status: r.status ?? "good", reasons: r.reasons ?? [], untrusted: r.untrusted ?? {} };
}

/** Relative change that colours a cell against its reference (the baseline). */
export const DELTA = 0.1;

export function num(v: number): string {
  const abs = Math.abs(v);
  if (Number.isInteger(v)) return String(v);
  if (abs >= 100) return v.toFixed(0);
  if (abs >= 10) return v.toFixed(1);
  return v.toFixed(2);
}

export const ms = (s: number): string => {
  const v = s * 1000;
  if (v === 0) return "0";
  return Math.abs(v) >= 100 ? v.toFixed(0) : v.toFixed(1);
};

/** The columns for a set of metrics: the fixed ones, following error if the device has
 * it, time to each arrival flag that occurs and time in each fault flag. */
export function metricColumns(descriptor: DeviceDescriptor, metrics: (RunMetrics | null | undefined)[]): MetricColumn[] {
  const flagLabel = new Map(descriptor.flags.map((f) => [f.name, f.label]));
  const channelUnit = (name: string): string => descriptor.channels.find((c) => c.name === name)?.unit ?? "";
  const cols: MetricColumn[] = [
    { key: "rise_time_s", label: "rise", unit: "ms", help: metricHelp("rise_time_s"), get: (m) => m.rise_time_s, spacing: (m) => m.max_sample_gap_s, text: ms, slack: 0.005 },
    { key: "overshoot_pct", label: "OS", unit: "%", help: metricHelp("overshoot_pct"), get: (m) => m.overshoot_pct, text: (v) => (v < 10 ? v.toFixed(2) : v.toFixed(1)), slack: 0.5 },
    { key: "settling_time_s", label: "settle", unit: "ms", help: metricHelp("settling_time_s"), get: (m) => m.settling_time_s, spacing: (m) => m.max_sample_gap_s, text: ms, slack: 0.005 },
    { key: "steady_state_error", label: "ss err", unit: "resp", help: `${metricHelp("steady_state_error")} (units of the response)`, get: (m) => m.steady_state_error, text: num, slack: 1 },
  ];
  const hasFe = descriptor.channels.some((c) => c.name === "following_error") || metrics.some((m) => m?.peak_following_error != null);
  if (hasFe) {
    const unit = channelUnit("following_error");
    cols.push(
      { key: "peak_following_error", label: "FE pk", unit, help: metricHelp("peak_following_error"), get: (m) => m.peak_following_error, text: num, slack: 1 },
      { key: "rms_following_error", label: "FE rms", unit, help: metricHelp("rms_following_error"), get: (m) => m.rms_following_error, text: num, slack: 1 },
    );
  }
  // Arrival flags (inpos, in_target): time to them; fault flags: time spent in them.
  const arrival = new Set<string>();
  const inFlag = new Set<string>();
  for (const m of metrics) {
    for (const k of Object.keys(m?.time_to_flag_s ?? {})) arrival.add(k);
    for (const k of Object.keys(m?.time_in_flag_s ?? {})) inFlag.add(k);
  }
  for (const f of descriptor.flags) if (f.severity === "fault") inFlag.add(f.name);
  for (const flag of arrival) {
    cols.push({
      key: `time_to_flag_s.${flag}`,
      label: `→ ${flagLabel.get(flag) ?? flag}`,
      unit: "ms",
      help: `Time to ${flag}: ${metricHelp("time_to_flag_s")}`,
      get: (m) => m.time_to_flag_s?.[flag],
      resolution: (m) => m.time_to_flag_resolution_s?.[flag],
      text: ms,
      slack: 0.005,
    });
  }
  for (const flag of inFlag) {
    const severity = descriptor.flags.find((f) => f.name === flag)?.severity;
    if (severity !== "fault") continue;
    cols.push({
      key: `time_in_flag_s.${flag}`,
      label: `in ${flagLabel.get(flag) ?? flag}`,
      unit: "ms",
      help: `Time in ${flag}: ${metricHelp("time_in_flag_s")}`,
      get: (m) => m.time_in_flag_s?.[flag],
      resolution: (m) => m.time_in_flag_resolution_s?.[flag],
      text: ms,
      slack: 0.005,
    });
  }
  cols.push({ key: "oscillations", label: "osc", unit: "n", help: metricHelp("oscillations"), get: (m) => m.oscillations, text: (v) => String(v), slack: 0.5 });
  return cols;
}

/** The header cells of ``cols`` (label, unit below, definition on hover). */
export function metricHeads(cols: MetricColumn[]): HTMLElement[] {
  return cols.map((c) =>
    h("th", { class: "c-metric", title: `${c.label} [${c.unit}]\n${c.help}`, "data-metric": c.key }, h("span", null, c.label), h("span", { class: "th-unit" }, c.unit)),
  );
}

/**
 * One metric cell: the value (``data-value`` holds the server's number, empty when
 * none), green/red when at least DELTA better/worse than ``reference`` (named
 * ``refName`` in the hover text), ``selfName`` as hover text when it is the reference.
 * A null metric listed in ``untrusted`` shows "?" with the server's reason. Pass no
 * ``reference`` for a bad run (or a bad reference): it must not look "better".
 */
export function metricCell(
  c: MetricColumn,
  metrics: RunMetrics | null | undefined,
  reference: RunMetrics | null | undefined,
  testid: string | undefined,
  selfName: string | null,
  refName = "the baseline",
  untrusted: Record<string, string> = {},
): HTMLTableCellElement {
  const value = metrics ? c.get(metrics) : null;
  const cell = h("td", { class: "c-metric num", testid });
  if (value === null || value === undefined || !Number.isFinite(value)) {
    const why = untrusted[c.key];
    // A metric the server could not trust: "?" with the reason, never a number.
    setText(cell, why ? "?" : "—");
    cell.classList.add("none");
    if (why) {
      cell.classList.add("untrusted");
      cell.dataset.untrusted = why;
      cell.title = `not trusted: ${why}`;
    }
    cell.dataset.value = "";
    return cell;
  }
  cell.dataset.value = String(value);
  const resolution = metrics && c.resolution ? c.resolution(metrics) : null;
  if (resolution != null && Number.isFinite(resolution) && resolution > 0) {
    // A polled flag: the time lies within ± half the poll period around the value.
    cell.dataset.resolution = String(resolution);
    setText(cell, `${c.text(value)} ±${c.text(resolution)}`);
  } else setText(cell, c.text(value));
  const ref = reference ? c.get(reference) : null;
  if (ref !== null && ref !== undefined && Number.isFinite(ref)) {
    const a = Math.abs(value);
    const b = Math.abs(ref);
    const rel = b > 0 ? (a - b) / b : a > 0 ? 1 : 0;
    // Two polled times differ only beyond both their ± (else neither is "better").
    const refResolution = reference && c.resolution ? c.resolution(reference) ?? 0 : 0;
    const spacing = Math.max((c.spacing?.(metrics as RunMetrics) ?? 0) || 0, (reference && c.spacing ? c.spacing(reference) ?? 0 : 0) || 0);
    const slack = Math.max(c.slack, (resolution ?? 0) + refResolution, spacing);
    if (Math.abs(a - b) > slack && Math.abs(rel) >= DELTA) {
      cell.classList.add(a < b ? "better" : "worse");
      cell.title = `${c.text(value)} vs ${c.text(ref)} on ${refName} (${rel > 0 ? "+" : ""}${(rel * 100).toFixed(0)} %)`;
    } else cell.title = `${c.text(value)} ≈ ${refName} ${c.text(ref)}`;
  } else if (selfName) cell.title = selfName;
  return cell;
}
