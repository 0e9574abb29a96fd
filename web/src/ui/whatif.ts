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
import { errorText } from "./feedback";
import { plotTheme } from "./benchplot";

export interface WhatIfModel {
  device: string;
  law: "slap2_pid" | "z1100_kab";
  period_s: number;
  plant_num: number[];
  plant_den: number[];
  pwm_limit: number;
  plant: { gain_counts_s_per_unit: number; tau_s: number; source: string };
}

export interface WhatIfInfo {
  axis_id: string;
  device: string;
  gains: Record<string, number | null>;
  ranges: Record<string, [number, number]>;
  verify: { kind: "position_step" | "move"; velocity_counts_s: number; acceleration_counts_s2: number };
  model: WhatIfModel | null;
  problem: string | null;
}

export interface Prediction {
  t: number[];
  y: number[];
  overshootPct: number;
  settlingS: number | null;
  peakPwm: number;
}

export interface LoopMargins {
  gainMarginDb: number | null;
  phaseMarginDeg: number | null;
  crossoverHz: number | null;
  phaseCrossoverHz: number | null;
}

/** The trapezoid of the profile generators (the simulators' per-sample rule): speed
 * min(v + a, vmax, sqrt(2 a d)) per sample, so a short move never reaches vmax. */
function profile(distance: number, vmaxPerTick: number, accPerTick: number, ticks: number): Float64Array {
  const ref = new Float64Array(ticks);
  let r = 0;
  let v = 0;
  const goal = Math.abs(distance);
  const sign = Math.sign(distance);
  for (let n = 0; n < ticks; n++) {
    const d = goal - r;
    if (d > 0) {
      const speed = Math.min(v + accPerTick, vmaxPerTick, Math.sqrt(2 * accPerTick * d));
      if (speed >= d) {
        r = goal;
        v = 0;
      } else {
        r += speed;
        v = speed;
      }
    }
    ref[n] = sign * r;
  }
  return ref;
}

/** Predicted response to the verification step: the exact law on the discrete plant,
 * the PWM clamped at its limit (friction is not modelled: see docs/frequency-response.md). */
export function predictStep(model: WhatIfModel, gains: Record<string, number>, distance: number, verify: WhatIfInfo["verify"], horizonS: number, band: number): Prediction {
  const ts = model.period_s;
  const ticks = Math.max(2, Math.round(horizonS / ts));
  const ref = profile(distance, verify.velocity_counts_s * ts, verify.acceleration_counts_s2 * ts * ts, ticks);
  const num = model.plant_num;
  const den = model.plant_den;
  const order = den.length - 1;
  const uHist = new Float64Array(order + 1);
  const yHist = new Float64Array(order + 1);
  const window = 32;
  const eWin = new Float64Array(window);
  const yWin = new Float64Array(window);
  let wi = 0;
  let sum = 0;
  let ePrev = 0;
  let peakPwm = 0;
  const every = Math.max(1, Math.floor(ticks / 1500));
  const t: number[] = [];
  const y: number[] = [];
  let moving = true;
  for (let n = 0; n < ticks; n++) {
    // plant output at tick n from past inputs and outputs (num[0] = 0: strictly proper)
    let yn = 0;
    for (let i = 1; i <= order; i++) yn += (num[i] ?? 0) * (uHist[i - 1] ?? 0) - (den[i] ?? 0) * (yHist[i - 1] ?? 0);
    const counts = Math.round(yn);
    const target = Math.floor((ref[n] as number) + 0.5);
    const e = target - counts;
    let u: number;
    if (model.law === "slap2_pid") {
      sum += e;
      u = (16 * (gains.kp ?? 0) * e + (gains.ki ?? 0) * sum + 32 * (gains.kd ?? 0) * (e - ePrev)) / 4096;
      ePrev = e;
    } else {
      if (moving && n > 0 && ref[n] === distance && ref[n - 1] === distance) moving = false;
      const p = moving ? "kabh" : "kabd";
      const de = e - (eWin[wi] as number);
      const dy = counts - (yWin[wi] as number);
      eWin[wi] = e;
      yWin[wi] = counts;
      wi = (wi + 1) % window;
      u = Math.trunc(((gains[`${p}_k`] ?? 0) * (16 * e + (gains[`${p}_a`] ?? 0) * de) - (gains[`${p}_b`] ?? 0) * dy) / 64);
    }
    u = Math.max(-model.pwm_limit, Math.min(model.pwm_limit, u));
    peakPwm = Math.max(peakPwm, Math.abs(u));
    for (let i = order; i > 0; i--) {
      uHist[i] = uHist[i - 1] as number;
      yHist[i] = yHist[i - 1] as number;
    }
    uHist[0] = u;
    yHist[0] = yn;
    if (n % every === 0) {
      t.push(n * ts);
      y.push(yn);
    }
  }
  const sign = Math.sign(distance) || 1;
  const peak = Math.max(...y.map((v) => v * sign));
  const overshootPct = Math.max(0, ((peak - Math.abs(distance)) / Math.abs(distance)) * 100);
  let settlingS: number | null = null;
  for (let i = y.length - 1; i >= 0; i--) {
    if (Math.abs((y[i] as number) - distance) > band) {
      settlingS = i + 1 < t.length ? (t[i + 1] as number) : null;
      break;
    }
    if (i === 0) settlingS = 0;
  }
  return { t, y, overshootPct, settlingS, peakPwm };
}

interface Complex {
  re: number;
  im: number;
}

/** Open loop L(e^{jwT}) of the law (the Z1100's hold gains, KABD) and the plant. */
function openLoop(model: WhatIfModel, gains: Record<string, number>, f: number): Complex {
  const w = 2 * Math.PI * f * model.period_s;
  // z^-k = cos(kw) - j sin(kw)
  const zk = (k: number): Complex => ({ re: Math.cos(k * w), im: -Math.sin(k * w) });
  const poly = (c: number[]): Complex => {
    let re = 0;
    let im = 0;
    c.forEach((v, k) => {
      const z = zk(k);
      re += v * z.re;
      im += v * z.im;
    });
    return { re, im };
  };
  const div = (a: Complex, b: Complex): Complex => {
    const d = b.re * b.re + b.im * b.im;
    return { re: (a.re * b.re + a.im * b.im) / d, im: (a.im * b.re - a.re * b.im) / d };
  };
  const mul = (a: Complex, b: Complex): Complex => ({ re: a.re * b.re - a.im * b.im, im: a.re * b.im + a.im * b.re });
  const p = div(poly(model.plant_num), poly(model.plant_den));
  let c: Complex;
  if (model.law === "slap2_pid") {
    const one = { re: 1, im: 0 };
    const z1 = zk(1);
    const integ = div(one, { re: 1 - z1.re, im: -z1.im }); // z/(z-1) = 1/(1-z^-1)
    const kp = gains.kp ?? 0;
    const ki = gains.ki ?? 0;
    const kd = gains.kd ?? 0;
    c = { re: (16 * kp + ki * integ.re + 32 * kd * (1 - z1.re)) / 4096, im: (ki * integ.im - 32 * kd * z1.im) / 4096 };
  } else {
    const z32 = zk(32);
    const d = { re: 1 - z32.re, im: -z32.im };
    const k = gains.kabd_k ?? 0;
    const a = gains.kabd_a ?? 0;
    const b = gains.kabd_b ?? 0;
    c = { re: (k * (16 + a * d.re) + b * d.re) / 64, im: (k * a * d.im + b * d.im) / 64 };
  }
  return mul(c, p);
}

/** Gain and phase margins from L on a log grid (crossings interpolated in log f). */
export function predictMargins(model: WhatIfModel, gains: Record<string, number>): LoopMargins {
  const nyq = 0.5 / model.period_s;
  const n = 600;
  let prevMag = NaN;
  let prevPhase = NaN;
  let prevF = NaN;
  let unwrap = 0;
  let lastRaw = NaN;
  const out: LoopMargins = { gainMarginDb: null, phaseMarginDeg: null, crossoverHz: null, phaseCrossoverHz: null };
  for (let i = 0; i < n; i++) {
    const f = 0.1 * Math.pow((nyq * 0.999) / 0.1, i / (n - 1));
    const l = openLoop(model, gains, f);
    const mag = Math.hypot(l.re, l.im);
    let raw = (Math.atan2(l.im, l.re) * 180) / Math.PI;
    if (!Number.isNaN(lastRaw)) {
      if (raw + unwrap - (lastRaw + unwrap) > 180) unwrap -= 360;
      else if (raw + unwrap - (lastRaw + unwrap) < -180) unwrap += 360;
    }
    lastRaw = raw;
    raw += unwrap;
    if (i > 0) {
      const frac = (a: number, b: number, target: number): number => (target - a) / (b - a);
      const logf = (x: number): number => Math.exp(Math.log(prevF) + x * (Math.log(f) - Math.log(prevF)));
      if (out.crossoverHz === null && prevMag >= 1 && mag < 1) {
        const x = frac(Math.log(prevMag), Math.log(mag), 0);
        out.crossoverHz = logf(x);
        out.phaseMarginDeg = 180 + prevPhase + x * (raw - prevPhase);
      }
      // Phase crossover: the phase passes -180 (mod 360) going down.
      const k = Math.floor((prevPhase + 180) / 360);
      const level = -180 + 360 * k;
      if (out.phaseCrossoverHz === null && prevPhase >= level && raw < level) {
        const x = frac(prevPhase, raw, level);
        out.phaseCrossoverHz = logf(x);
        const m = Math.exp(Math.log(prevMag) + x * (Math.log(mag) - Math.log(prevMag)));
        out.gainMarginDb = -20 * Math.log10(m);
      }
    }
    prevMag = mag;
    prevPhase = raw;
    prevF = f;
  }
  if (out.phaseMarginDeg !== null) out.phaseMarginDeg = ((out.phaseMarginDeg + 180) % 360 + 360) % 360 - 180;
  return out;
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
  private readonly plotHost: HTMLElement;
  private readonly sliders = new Map<string, HTMLInputElement>();
  private readonly distance: HTMLInputElement;
  private u: uPlot | null = null;
  private measured: Measured | null = null;
  private lastUpdateMs: number[] = [];
  private applyButton: HTMLButtonElement | null = null;

  constructor(
    private readonly axisId: string,
    private readonly onVerify: (distance: number, kind: "position_step" | "move") => Promise<void>,
  ) {
    this.status = h("span", { class: "pane-sub", testid: "whatif-status" });
    this.readout = h("div", { class: "whatif-readout", testid: "whatif-readout" });
    this.plotHost = h("div", { class: "whatif-plot", testid: "whatif-plot" });
    this.distance = h("input", { class: "input num", type: "number", value: "2000", testid: "whatif-distance", "aria-label": "Step distance (counts)" });
    this.distance.addEventListener("input", () => this.update());
    this.body = h("div", { class: "whatif-body" });
    this.el = h(
      "section",
      { class: "whatif-panel", testid: "whatif-panel" },
      h("div", { class: "pane-header" }, h("span", { class: "pane-title" }, "What-if gains"), this.status),
      this.body,
      this.readout,
      this.plotHost,
    );
  }

  async load(): Promise<void> {
    try {
      this.info = await request<WhatIfInfo>("GET", `/api/axes/${encodeURIComponent(this.axisId)}/whatif`);
    } catch (error) {
      setText(this.status, `unavailable: ${errorText(error)}`);
      return;
    }
    this.render();
  }

  setMeasured(measured: Measured | null): void {
    this.measured = measured;
    this.update();
  }

  private render(): void {
    const info = this.info;
    if (!info) return;
    if (!info.model) {
      setText(this.status, info.problem ?? "no model");
      replace(this.body);
      return;
    }
    setText(this.status, `plant: ${info.model.plant.source}, gain ${info.model.plant.gain_counts_s_per_unit.toFixed(1)} counts/s per PWM, τ ${(info.model.plant.tau_s * 1000).toFixed(1)} ms · nothing is written until Apply`);
    this.sliders.clear();
    const rows = Object.entries(info.gains).map(([name, value]) => {
      const [lo, hi] = info.ranges[name] ?? [0, 1000];
      const v = value ?? 0;
      const max = Math.min(hi, Math.max(4 * v, 100));
      const slider = h("input", { type: "range", min: String(lo), max: String(max), step: "1", value: String(v), testid: `whatif-${name}`, "aria-label": name });
      const shown = h("span", { class: "mono whatif-value" }, String(v));
      slider.addEventListener("input", () => {
        setText(shown, slider.value);
        this.update();
      });
      this.sliders.set(name, slider);
      return h("label", { class: "whatif-gain" }, h("span", { class: "bf-label" }, name), slider, shown);
    });
    this.applyButton = h("button", { class: "btn primary", testid: "whatif-apply", onclick: () => void this.apply() }, "Apply and verify");
    replace(this.body, ...rows, h("label", { class: "whatif-gain" }, h("span", { class: "bf-label" }, "step"), this.distance), this.applyButton);
    this.update();
  }

  gains(): Record<string, number> {
    const out: Record<string, number> = {};
    for (const [name, slider] of this.sliders) out[name] = Number(slider.value);
    return out;
  }

  /** Redraw prediction and margins; the time it takes is shown and kept. */
  update(): void {
    const info = this.info;
    if (!info?.model) return;
    const start = performance.now();
    const gains = this.gains();
    const distance = Number(this.distance.value) || 0;
    if (!distance) return;
    const horizon = this.measured?.t.length ? Math.max(0.3, this.measured.t[this.measured.t.length - 1] as number) : 0.6;
    const delay = this.measured?.delayS ?? 0;
    const raw = predictStep(info.model, gains, distance, info.verify, Math.max(0.05, horizon - delay), 5);
    const prediction = delay ? { ...raw, t: raw.t.map((t) => t + delay), settlingS: raw.settlingS === null ? null : raw.settlingS + delay } : raw;
    const margins = predictMargins(info.model, gains);
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
    replace(
      this.readout,
      h("span", { testid: "whatif-pm" }, `phase margin ${fmt(margins.phaseMarginDeg, 1, "°")}`),
      " · ",
      h("span", { testid: "whatif-gm" }, `gain margin ${fmt(margins.gainMarginDb, 1, "dB")}`),
      " · ",
      `crossover ${fmt(margins.crossoverHz, 1, "Hz")}`,
      " · ",
      `predicted overshoot ${prediction.overshootPct.toFixed(1)} %, settling (±5) ${fmt(prediction.settlingS === null ? null : prediction.settlingS * 1000, 0, "ms")}, peak PWM ${prediction.peakPwm.toFixed(0)}`,
      versus === null ? "" : h("span", { testid: "whatif-vs-measured" }, ` · vs ${this.measured?.label ?? "measured"} (aligned at its command's acknowledgement, +${(delay * 1000).toFixed(0)} ms): rms ${versus.toFixed(1)} counts`),
      h("span", { class: "tb-hint" }, ` · update ${computeMs.toFixed(2)} ms compute, ${totalMs.toFixed(2)} ms with the plot`),
    );
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
      await this.onVerify(Math.round(Number(this.distance.value)), this.info.verify.kind);
      setText(this.status, "gains written; verification step running");
    } catch (error) {
      setText(this.status, `not applied: ${errorText(error)}`);
    } finally {
      this.applyButton.disabled = false;
    }
  }
}
