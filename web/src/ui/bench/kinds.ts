// The bench's test kinds and how a run is named in the table, the legend and dialogs.
import type { BenchKind, BenchRun } from "../../api";
import { ms } from "../metriccols";

export type FieldName = "distance" | "velocity" | "pwm";

export const KINDS: Record<BenchKind, { label: string; short: string; field: FieldName; help: string }> = {
  move: {
    label: "Move",
    short: "move",
    field: "distance",
    help: "Relative move by the distance with the motion profile as set (velocity, acceleration) — the response is the position.",
  },
  position_step: {
    label: "Position step",
    short: "pos step",
    field: "distance",
    help: "The same move with the profile limits at their maximum for the test: as close to a true step as the device allows — position response.",
  },
  velocity_step: {
    label: "Velocity step",
    short: "vel step",
    field: "velocity",
    help: "Constant-velocity run at the velocity, then stop — the response is the velocity against the commanded one.",
  },
  frequency_response: {
    label: "Frequency response",
    short: "FRF",
    field: "distance",
    help: "A multisine around the held position where the device takes one, else the identified model: see the Frequency response panel.",
  },
  pwm_step: {
    label: "PWM step",
    short: "pwm step",
    field: "pwm",
    help: "Open-loop PWM (no controller) at the duty, then stop — the plant's raw velocity response, no target.",
  },
};

/** The unit of each form field (``GET /api/axes/{id}/bench`` ``fields``). */
export type Units = Record<FieldName, string>;

export function shortId(id: string): string {
  return `#${id.slice(0, 4)}`;
}

export function testSize(run: BenchRun, units: Units, withUnit = true): string {
  const field = KINDS[run.test.kind]?.field ?? "distance";
  const value = run.test[field];
  const unit = withUnit ? units[field] : "";
  return `${value > 0 && field === "distance" ? "+" : ""}${value}${unit ? ` ${unit}` : ""}`;
}

/** A run's test, plan, metrics and parameters, for a tooltip. */
export function runTitle(run: BenchRun, units: Units): string {
  const m = run.metrics;
  const lines = [
    `${KINDS[run.test.kind]?.label ?? run.test.kind} ${testSize(run, units)} · ${run.test.duration_s} s`,
    `response ${run.plan.response}: ${run.plan.y0} → ${run.plan.y_final}${run.plan.band !== null ? ` ± ${run.plan.band}` : ""}`,
  ];
  if (Object.keys(run.plan.overrides).length) lines.push(`overrides during the test: ${Object.entries(run.plan.overrides).map(([k, v]) => `${k}=${v}`).join(" ")}`);
  if (m) {
    if (m.samples !== undefined) lines.push(`${m.samples} samples${m.max_sample_gap_s ? `, largest gap ${ms(m.max_sample_gap_s)} ms` : ""}`);
    if (m.peak_value !== null && m.peak_time_s !== null) lines.push(`peak ${m.peak_value} at ${ms(m.peak_time_s)} ms`);
  }
  lines.push(`parameters: ${Object.entries(run.params).map(([k, v]) => `${k}=${v}`).join(" ")}`);
  if (run.test.note) lines.push(`note: ${run.test.note}`);
  return lines.join("\n");
}
