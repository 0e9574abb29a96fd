// What-if gains (issue 9 part 3): move a gain slider BEFORE writing it and see the
// predicted step response and margins, from the identified plant and the device's exact
// controller arithmetic, next to the last measured run; "Apply" writes the gains and
// runs the verification step. The model comes once from GET /api/axes/{id}/whatif
// (server/servotune/tuning/whatif.py: the plant discretised with a zero-order hold at
// the controller period); every update is computed here, in a few hundred
// microseconds to a few milliseconds, with no request.
import uPlot from "uplot";
import { api, request } from "../api";
import { h, replace, setText } from "../dom";
import { loopStable, modelMargins, predictStep, type LoopMargins, type Prediction } from "../stability";
import type { MarginTarget, WhatIfInfo, WhatIfModel } from "../schema.gen";
import { errorText } from "./feedback";
import { plotTheme } from "./benchplot";
import { marginValue, shortfall, targetText } from "./margins";

export type { LoopMargins, Prediction };
export { predictStep };

/** Gain and phase margins of the law around the plant, by the one rule the server
 * uses (web/src/stability.ts, tuning.stability.loop_margins). */
export function predictMargins(model: WhatIfModel, gains: Record<string, number>): LoopMargins {
  return modelMargins(model, gains);
}

/** RMS of measured - predicted at the measured samples (the prediction interpolated
 * linearly; samples after its horizon are left out). */
export function rmsAgainst(p: Prediction, m: Measured): number | null {
  let sum = 0;
  let n = 0;
  let j = 0;
  m.t.forEach((t, i) => {
    const y = m.y[i];
    if (y === null || y === undefined || t < 0 || t > (p.t[p.t.length - 1] ?? 0)) return;
    while (j + 1 < p.t.length && (p.t[j + 1] as number) < t) j++;
    const t0 = p.t[j] as number;
    const t1 = (p.t[j + 1] ?? t0) as number;
    const y0 = p.y[j] as number;
    const y1 = (p.y[j + 1] ?? y0) as number;
    const pred = t1 > t0 ? y0 + ((t - t0) / (t1 - t0)) * (y1 - y0) : y0;
    sum += (y - pred) ** 2;
    n++;
  });
  return n ? Math.sqrt(sum / n) : null;
}

function fmt(v: number | null, digits: number, unit: string): string {
  return v === null || !Number.isFinite(v) ? "—" : `${v.toFixed(digits)} ${unit}`;
}

export interface Measured {
  /** The run compared with; its step distance is the prediction's. */
  id: string;
  distance: number | null;
  label: string;
  /** When the device acknowledged the step's command, after t0 (s): the prediction
   * starts there (the samples' t0 is stamped before the command is sent). */
  delayS: number;
  t: number[];
  y: (number | null)[];
}

export class WhatIfPanel {
  readonly el: HTMLElement;
  private info: WhatIfInfo | null = null;
  private readonly body: HTMLElement;
  private readonly status: HTMLElement;
  private readonly readout: HTMLElement;
  private readonly warning: HTMLElement;
  private readonly plotHost: HTMLElement;
  private readonly sliders = new Map<string, HTMLInputElement>();
  private readonly numbers = new Map<string, HTMLInputElement>();
  private readonly distance: HTMLInputElement;
  private readonly targetSelect: HTMLSelectElement;
  private u: uPlot | null = null;
  private measured: Measured | null = null;
  private lastUpdateMs: number[] = [];
  private applyButton: HTMLButtonElement | null = null;
  /** The verification run "Apply and verify" started, until it ends. */
  private verifying: string | null = null;
  private loads = 0;

  constructor(
    private readonly axisId: string,
    private readonly onVerify: (distance: number, kind: "position_step" | "move") => Promise<string>,
  ) {
    this.status = h("span", { class: "pane-sub", testid: "whatif-status" });
    this.readout = h("div", { class: "whatif-readout", testid: "whatif-readout" });
    this.warning = h("div", { class: "whatif-warning", testid: "whatif-warning" });
    this.plotHost = h("div", { class: "whatif-plot", testid: "whatif-plot" });
    this.distance = h("input", { class: "input num", type: "number", value: "1000", step: "1", testid: "whatif-distance", "aria-label": "Step distance (counts)", title: "The step predicted and verified (counts): the compared run's when one is selected" });
    this.distance.addEventListener("input", () => this.update());
    this.targetSelect = h("select", { class: "input", testid: "whatif-target", "aria-label": "Margin target", title: "The margins the prediction is read against" });
    this.targetSelect.addEventListener("change", () => this.update());
    this.body = h("div", { class: "whatif-body" });
    this.el = h(
      "section",
      { class: "whatif-panel", testid: "whatif-panel" },
      h("div", { class: "pane-header" }, h("span", { class: "pane-title" }, "What-if gains"), this.status),
      this.body,
      this.readout,
      this.warning,
      this.plotHost,
    );
  }

  /** (Re)load the model and the gains in use: on opening the bench, after every
   * identification and whenever a run ends (an identification from another page),
   * without a page reload; the sliders are rebuilt only when the model changed. */
  async load(): Promise<void> {
    const load = ++this.loads;
    let info: WhatIfInfo;
    try {
      info = await request<WhatIfInfo>("GET", `/api/axes/${encodeURIComponent(this.axisId)}/whatif`);
    } catch (error) {
      if (load === this.loads) setText(this.status, `unavailable: ${errorText(error)}`);
      return;
    }
    if (load !== this.loads) return;
    const same = this.info?.model && info.model && JSON.stringify(this.info.model) === JSON.stringify(info.model);
    this.info = info;
    // The same model: keep what the user has set on the sliders.
    if (!same) this.render();
  }

  setMeasured(measured: Measured | null): void {
    const changed = measured?.id !== this.measured?.id;
    this.measured = measured;
    // The step predicted is the one it is compared with.
    if (changed && measured?.distance) this.distance.value = String(measured.distance);
    this.update();
  }

  /** A bench run ended: the verification this panel started says so. */
  runEnded(runId: string, status: string, message: string): void {
    if (runId !== this.verifying) return;
    this.verifying = null;
    setText(this.status, status === "complete" ? `gains written; verification #${runId.slice(0, 4)} done — selected in the runs table` : `gains written; verification #${runId.slice(0, 4)} ${status}${message ? `: ${message}` : ""}`);
    this.status.dataset.state = status;
  }

  private render(): void {
    const info = this.info;
    if (!info) return;
    if (!info.model) {
      setText(this.status, info.problem ?? "no model");
      replace(this.body);
      replace(this.readout);
      replace(this.warning);
      return;
    }
    if (!this.verifying) setText(this.status, `plant: ${info.model.plant.source}, gain ${info.model.plant.gain_counts_s_per_unit.toFixed(1)} counts/s per PWM, τ ${(info.model.plant.tau_s * 1000).toFixed(1)} ms · nothing is written until Apply`);
    replace(
      this.targetSelect,
      Object.values(info.targets).map((t) => h("option", { value: t.preset }, targetText(t))),
    );
    this.targetSelect.value = info.target.preset;
    this.sliders.clear();
    this.numbers.clear();
    const rows = Object.entries(info.gains).map(([name, value]) => {
      const [lo, hi] = info.ranges[name] ?? [0, 1000];
      const v = value ?? 0;
      // The slider spans the gains in use, the proposal, and room around both; the
      // number field takes anything the device does.
      const proposed = info.proposal?.[name] ?? 0;
      const max = Math.min(hi, Math.max(4 * v, 2 * proposed, 100));
      const slider = h("input", { type: "range", min: String(lo), max: String(max), step: "1", value: String(v), testid: `whatif-${name}`, "aria-label": `${name} (slider)` });
      const number = h("input", { class: "input num whatif-number", type: "number", min: String(lo), max: String(hi), step: "1", value: String(v), testid: `whatif-${name}-value`, "aria-label": name, title: `${name}: ${lo}..${hi}` });
      slider.addEventListener("input", () => {
        number.value = slider.value;
        number.classList.remove("invalid");
        this.update();
      });
      number.addEventListener("input", () => {
        const n = Number(number.value);
        const ok = number.value.trim() !== "" && Number.isInteger(n) && n >= lo && n <= hi;
        number.classList.toggle("invalid", !ok);
        if (!ok) return;
        if (n > Number(slider.max)) slider.max = String(Math.min(hi, 2 * n));
        slider.value = String(n);
        this.update();
      });
      this.sliders.set(name, slider);
      this.numbers.set(name, number);
      return h("label", { class: "whatif-gain" }, h("span", { class: "bf-label" }, name), slider, number);
    });
    this.applyButton = h("button", { class: "btn primary", testid: "whatif-apply", onclick: () => void this.apply() }, "Apply and verify");
    const set = (gains: Record<string, number | null>): void => {
      for (const [name, v] of Object.entries(gains)) {
        const number = this.numbers.get(name);
        if (!number || v === null || v === undefined) continue;
        number.value = String(v);
        number.dispatchEvent(new Event("input"));
      }
    };
    replace(
      this.body,
      ...rows,
      h("label", { class: "whatif-gain" }, h("span", { class: "bf-label" }, "step"), this.distance),
      h("label", { class: "whatif-gain" }, h("span", { class: "bf-label" }, "margins"), this.targetSelect),
      h("button", { class: "btn small", testid: "whatif-in-use", title: "Back to the gains in use", onclick: () => set(info.gains) }, "in use"),
      info.proposal ? h("button", { class: "btn small", testid: "whatif-proposal", title: "The auto-tune's proposal", onclick: () => set(info.proposal ?? {}) }, "proposal") : null,
      this.applyButton,
    );
    this.update();
  }

  gains(): Record<string, number> {
    const out: Record<string, number> = {};
    for (const [name, slider] of this.sliders) out[name] = Number(slider.value);
    return out;
  }

  private target(): MarginTarget | null {
    const info = this.info;
    return info ? (info.targets[this.targetSelect.value] ?? info.target) : null;
  }

  /** Redraw prediction and margins; the time it takes is shown and kept. */
  update(): void {
    const info = this.info;
    const target = this.target();
    if (!info?.model || !target) return;
    const start = performance.now();
    const gains = this.gains();
    const distance = Number(this.distance.value) || 0;
    if (!distance) return;
    const horizon = this.measured?.t.length ? Math.max(0.3, this.measured.t[this.measured.t.length - 1] as number) : 0.6;
    const delay = this.measured?.delayS ?? 0;
    const raw = predictStep(info.model, gains, distance, info.verify, Math.max(0.05, horizon - delay), 5);
    const prediction = delay ? { ...raw, t: raw.t.map((t) => t + delay), settlingS: raw.settlingS === null ? null : raw.settlingS + delay } : raw;
    const margins = predictMargins(info.model, gains);
    const stable = loopStable(info.model, gains);
    const computeMs = performance.now() - start;
    const versus = this.measured ? rmsAgainst(prediction, this.measured) : null;
    this.draw(prediction);
    const totalMs = performance.now() - start;
    this.lastUpdateMs.push(totalMs);
    this.el.dataset.updateMs = totalMs.toFixed(3);
    this.el.dataset.computeMs = computeMs.toFixed(3);
    this.el.dataset.overshoot = prediction.overshootPct.toFixed(3);
    this.el.dataset.settling = prediction.settlingS === null ? "" : prediction.settlingS.toFixed(4);
    this.el.dataset.rmsVsMeasured = versus === null ? "" : versus.toFixed(3);
    this.el.dataset.stable = stable ? "1" : "0";
    replace(
      this.readout,
      h("span", { testid: "whatif-pm" }, "phase margin ", marginValue(margins.phaseMarginDeg, target.phase_margin_deg, 1, "°")),
      " · ",
      h("span", { testid: "whatif-gm" }, "gain margin ", marginValue(margins.gainMarginDb, target.gain_margin_db, 1, "dB", undefined, stable && margins.phaseCrossoverHz === null ? "the phase stays above −180° up to Nyquist" : undefined)),
      " · ",
      `crossover ${fmt(margins.crossoverHz, 1, "Hz")}`,
      " · ",
      h("span", { testid: "whatif-stable", class: stable ? "" : "margin-value low" }, stable ? "closed loop stable" : "closed loop UNSTABLE"),
      " · ",
      `predicted overshoot ${prediction.overshootPct.toFixed(1)} %, settling (±5) ${fmt(prediction.settlingS === null ? null : prediction.settlingS * 1000, 0, "ms")}, peak PWM ${prediction.peakPwm.toFixed(0)}`,
      versus === null ? "" : h("span", { testid: "whatif-vs-measured" }, ` · vs ${this.measured?.label ?? "measured"} (aligned at its command's acknowledgement, +${(delay * 1000).toFixed(0)} ms): rms ${versus.toFixed(1)} counts`),
      h("span", { class: "tb-hint" }, ` · update ${computeMs.toFixed(2)} ms compute, ${totalMs.toFixed(2)} ms with the plot`),
    );
    const short = shortfall(margins.phaseMarginDeg, margins.gainMarginDb, stable, target);
    this.warning.hidden = !short;
    replace(this.warning, short ? h("div", { class: "at-warning margin-warning", role: "note" }, h("b", null, "⚠ "), `${short} (target ${targetText(target)})`) : null);
  }

  private draw(p: Prediction): void {
    const theme = plotTheme();
    const width = Math.floor(this.plotHost.clientWidth) || 600;
    const series: uPlot.Series[] = [{}, { label: "predicted", stroke: "#4c9aff", width: 2 }];
    const parts: uPlot.AlignedData[] = [[p.t, p.y]];
    if (this.measured) {
      series.push({ label: this.measured.label, stroke: "#f5a524", paths: () => null, points: { show: true, size: 5, fill: "#f5a524" } });
      parts.push([this.measured.t, this.measured.y] as uPlot.AlignedData);
    }
    const data = uPlot.join(parts);
    if (this.u && this.u.series.length === series.length) {
      this.u.setData(data);
      return;
    }
    this.u?.destroy();
    this.u = new uPlot(
      {
        width,
        height: 200,
        legend: { show: true },
        scales: { x: { time: false } },
        axes: [
          { stroke: theme.axis, grid: { stroke: theme.grid }, font: theme.font, label: "s after t0", labelFont: theme.font },
          { stroke: theme.axis, grid: { stroke: theme.grid }, font: theme.font, size: 56 },
        ],
        series,
      },
      data,
      this.plotHost,
    );
  }

  private async apply(): Promise<void> {
    if (!this.info || !this.applyButton) return;
    this.applyButton.disabled = true;
    try {
      await api.writeParams(this.axisId, this.gains());
      const runId = await this.onVerify(Math.round(Number(this.distance.value)), this.info.verify.kind);
      this.verifying = runId;
      setText(this.status, `gains written; verification #${runId.slice(0, 4)} running`);
      this.status.dataset.state = "recording";
    } catch (error) {
      setText(this.status, `not applied: ${errorText(error)}`);
    } finally {
      this.applyButton.disabled = false;
    }
  }
}
