// Margins against a target (server/servotune/tuning/targets.py), the same words in
// the auto-tune's proposal, the what-if view and the frequency-response table.
import type { MarginReport, MarginTarget } from "../api";
import { h } from "../dom";

export const PRESET_HELP: Record<string, string> = {
  stiff: "a rigid load: faster, thinner margins",
  medium: "the default (as Kollmorgen's auto-tuner): GM 8 dB, PM 45°",
  soft: "a compliant or uncertain load: slower, thicker margins",
};

export function targetText(t: MarginTarget): string {
  return `${t.preset}: PM ≥ ${t.phase_margin_deg}°, GM ≥ ${t.gain_margin_db} dB`;
}

function fmt(v: number | null | undefined, digits: number, unit: string): string {
  return v === null || v === undefined || !Number.isFinite(v) ? "—" : `${v.toFixed(digits)} ${unit}`;
}

/** What falls short of the target, in words ("" when it is met or unknown). */
export function shortfall(pm: number | null, gm: number | null, stable: boolean | null, t: MarginTarget): string {
  const out: string[] = [];
  if (stable === false) out.push("the closed loop is unstable");
  else {
    if (pm !== null && pm < t.phase_margin_deg) out.push(`phase margin ${pm.toFixed(1)}° is below ${t.phase_margin_deg}°`);
    if (gm !== null && gm < t.gain_margin_db) out.push(`gain margin ${gm.toFixed(1)} dB is below ${t.gain_margin_db} dB`);
  }
  return out.join("; ");
}

/** A margin value coloured against its target: "ok" at or above it, "low" below.
 * ``unbounded`` says why a missing value is infinite (shown as ∞, "ok"), not unknown. */
export function marginValue(v: number | null, target: number, digits: number, unit: string, testid?: string, unbounded?: string): HTMLElement {
  if (v === null && unbounded) {
    return h("span", { class: "margin-value ok", testid, title: `${unbounded}; target ≥ ${target} ${unit}` }, `∞ (${unbounded})`);
  }
  const kind = v === null || !Number.isFinite(v) ? "" : v >= target ? "ok" : "low";
  return h("span", { class: `margin-value ${kind}`, testid, title: `target ≥ ${target} ${unit}` }, fmt(v, digits, unit));
}

/** The warning line under margins below their target (null when met or unknown). */
export function marginWarning(report: Pick<MarginReport, "warning" | "meets_target">, testid = "margin-warning"): HTMLElement | null {
  if (report.meets_target !== false || !report.warning) return null;
  return h("div", { class: "at-warning margin-warning", testid, role: "note" }, h("b", null, "⚠ "), report.warning);
}
