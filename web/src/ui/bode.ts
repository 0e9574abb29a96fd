// The bench's frequency response: a form that starts a "frequency_response"
// run, and for the selected runs of that kind a Bode plot (magnitude dB and phase deg
// over log frequency; measured points shaded by coherence, the band beyond the usable
// one greyed; the identified model as a dashed line), the margins/bandwidth readouts
// and a Nyquist plot of the open loop. Data: GET /api/bench/runs/{id}/frf
// (server/servotune/api/frf_routes.py), computed on the server in a worker thread.
import uPlot from "uplot";
import "./frf.css";
import { api, request } from "../api";
import { h, replace, setText } from "../dom";
import type { FrfBode, FrfData, FrfMargins, FrfMeasured, FrfModel, FrfTrust, MarginTarget } from "../schema.gen";
import { errorText } from "./feedback";
import { plotTheme, type PlotTheme } from "./benchplot";
import { targetText } from "./margins";

// The analysis' shapes are generated (schema.gen.ts, servotune/schema/): a measured
// part or the model's, each drawn with the same curves.
export type Bode = FrfBode;
export type Trust = FrfTrust;
// The model's margins are a MarginReport: FrfMargins without the measured-only fields.
export type Margins = FrfMargins;
type Part = FrfMeasured | FrfModel;

export interface FrfRun {
  id: string;
  color: string;
  label: string;
  recording: boolean;
}

const MIN_COHERENCE = 0.9;

export const frfApi = {
  get: (runId: string) => request<FrfData>("GET", `/api/bench/runs/${encodeURIComponent(runId)}/frf`),
};

const cache = new Map<string, FrfData>();

function fmt(v: number | null | undefined, digits: number, unit: string): string {
  return v === null || v === undefined || !Number.isFinite(v) ? "—" : `${v.toFixed(digits)} ${unit}`;
}

/** One Bode half (magnitude or phase) on a log-frequency uPlot. */
class BodeAxis {
  readonly el: HTMLElement;
  private u: uPlot | null = null;
  private readonly observer: ResizeObserver;
  private build: (() => void) | null = null;

  constructor(testid: string) {
    this.el = h("div", { class: "bode-host", testid });
    this.observer = new ResizeObserver(() => this.build?.());
    this.observer.observe(this.el);
  }

  set(data: uPlot.AlignedData, series: uPlot.Series[], unit: string, usable: Band | null, theme: PlotTheme): void {
    this.build = () => {
      const width = Math.floor(this.el.clientWidth);
      const height = Math.floor(this.el.clientHeight) || 180;
      if (width < 50) return;
      this.u?.destroy();
      const shade = (u: uPlot): void => {
        if (usable === null) return;
        // grey outside the usable band: below its first tone and above its last
        const left = u.bbox.left;
        const right = u.bbox.left + u.bbox.width;
        const clamp = (x: number): number => Math.min(right, Math.max(left, x));
        const x0 = usable.until > 0 ? clamp(u.valToPos(usable.until, "x", true)) : left;
        const x1 = usable.from > 0 ? clamp(u.valToPos(usable.from, "x", true)) : left;
        const ctx = u.ctx;
        ctx.save();
        ctx.fillStyle = "rgba(128,128,128,0.14)";
        ctx.fillRect(x0, u.bbox.top, right - x0, u.bbox.height);
        if (usable.until > 0 && x1 > left) ctx.fillRect(left, u.bbox.top, x1 - left, u.bbox.height);
        ctx.restore();
      };
      this.u = new uPlot(
        {
          width,
          height,
          legend: { show: false },
          cursor: { drag: { x: true, y: false } },
          scales: { x: { time: false, distr: 3 } },
          axes: [
            { stroke: theme.axis, grid: { stroke: theme.grid }, font: theme.font, label: "Hz", labelFont: theme.font, size: 36 },
            { stroke: theme.axis, grid: { stroke: theme.grid }, font: theme.font, label: unit, labelFont: theme.font, size: 50 },
          ],
          series: [{}, ...series],
          hooks: { drawClear: [shade] },
        },
        data,
        this.el,
      );
    };
    this.build();
  }

  clear(): void {
    this.u?.destroy();
    this.u = null;
    this.build = null;
    replace(this.el);
  }
}

/** Coherence bins: a point is drawn in the bin of its coherence (opaque when >= 0.9). */
/** The usable band of a measurement (Hz; until = 0: none). */
interface Band {
  from: number;
  until: number;
}

/** How a measured point is drawn: trusted (every bias bounded within the limits)
 * filled; not trusted but coherent hollow; incoherent faint and hollow. */
type Bin = "trusted" | "untrusted" | "incoherent";
const BINS: { bin: Bin; alpha: string; fill: boolean; label: string }[] = [
  { bin: "trusted", alpha: "ff", fill: true, label: "trusted (±0.5 dB, ±5°)" },
  { bin: "untrusted", alpha: "b0", fill: false, label: "not trusted (see why)" },
  { bin: "incoherent", alpha: "40", fill: false, label: "coherence < 0.9" },
];

function binOf(b: Bode, j: number): Bin {
  if (b.trusted?.[j]) return "trusted";
  return (b.coherence?.[j] ?? 0) >= MIN_COHERENCE ? "untrusted" : "incoherent";
}

function hex(color: string): string {
  // Palette colours are #rrggbb; anything else is drawn without alpha shading.
  return /^#[0-9a-f]{6}$/i.test(color) ? color : "";
}

export class FrfPanel {
  readonly el: HTMLElement;
  private readonly mag = new BodeAxis("bode-magnitude");
  private readonly phase = new BodeAxis("bode-phase");
  private readonly nyquist: HTMLCanvasElement;
  private readonly readouts: HTMLElement;
  private readonly note: HTMLElement;
  private readonly error: HTMLElement;
  private readonly inputs: Record<"amplitude" | "pwm" | "low_hz" | "high_hz" | "duration_s", HTMLInputElement>;
  private readonly injectSelect: HTMLSelectElement;
  private readonly runButton: HTMLButtonElement;
  private readonly loopSelect: HTMLSelectElement;
  private runs: FrfRun[] = [];
  private token = 0;

  constructor(
    private readonly axisId: string,
    private readonly measured: boolean,
    private readonly onStarted: (id: string) => void,
  ) {
    const input = (name: string, value: string, title: string): HTMLInputElement =>
      h("input", { class: "input num", type: "number", value, testid: `frf-${name}`, "aria-label": title, title, step: "any" });
    this.inputs = {
      amplitude: input("amplitude", "200", "Peak of the multisine around the held position (counts)"),
      pwm: input("pwm", "40", "Open loop: peak of the multisine PWM (within the bench's max PWM)"),
      low_hz: input("low_hz", "1", "Lowest tone (Hz); also the frequency resolution"),
      high_hz: input("high_hz", "40", "Highest tone (Hz)"),
      duration_s: input("duration_s", "9", "Record length (s): one settling period plus at least three analysed (8 halve the error of 4 at the same coherence)"),
    };
    this.runButton = h(
      "button",
      { class: "btn primary", testid: "frf-run", onclick: () => void this.start() },
      this.measured ? "Measure frequency response" : "Model frequency response",
    );
    this.loopSelect = h(
      "select",
      { class: "input", testid: "frf-loop", "aria-label": "Which response" },
      h("option", { value: "closed" }, "closed loop T (setpoint → position)"),
      h("option", { value: "open" }, "open loop L"),
    );
    this.loopSelect.addEventListener("change", () => void this.draw());
    // Closed loop: position targets (ma) with the controller on. Open loop: the PWM
    // itself (spwm), controller off, only inside a travel window and after a confirm.
    this.injectSelect = h(
      "select",
      { class: "input", testid: "frf-inject", "aria-label": "How to inject" },
      h("option", { value: "closed" }, "closed loop (position targets, ma)"),
      h("option", { value: "open" }, "open loop (PWM, spwm) …"),
    );
    const syncInject = (): void => {
      const open = this.injectSelect.value === "open";
      (this.inputs.amplitude.closest("label") as HTMLElement | null)?.toggleAttribute("hidden", open);
      (this.inputs.pwm.closest("label") as HTMLElement | null)?.toggleAttribute("hidden", !open);
    };
    this.injectSelect.addEventListener("change", syncInject);
    const field = (label: string, el: HTMLElement): HTMLElement => h("label", { class: "bf" }, h("span", { class: "bf-label" }, label), h("span", { class: "bf-control" }, el));
    this.error = h("div", { class: "bench-error", testid: "frf-error", role: "alert", hidden: true });
    this.note = h("div", { class: "frf-note", testid: "frf-note" });
    this.readouts = h("div", { class: "frf-readouts", testid: "frf-readouts" });
    this.nyquist = h("canvas", { class: "nyquist", testid: "nyquist", width: 260, height: 260 });
    this.el = h(
      "section",
      { class: "frf-panel", testid: "frf-panel" },
      h(
        "div",
        { class: "pane-header" },
        h("span", { class: "pane-title" }, "Frequency response"),
        h(
          "span",
          { class: "pane-sub" },
          this.measured
            ? "multisine around the held position, streamed as position targets (ma)"
            : "model-based: the identified plant under the device's exact law (nothing moves)",
        ),
      ),
      h(
        "div",
        { class: "bench-form-row" },
        this.measured ? field("inject", this.injectSelect) : null,
        this.measured ? field("amplitude ±", this.inputs.amplitude) : null,
        this.measured ? field("PWM ±", this.inputs.pwm) : null,
        field("from Hz", this.inputs.low_hz),
        field("to Hz", this.inputs.high_hz),
        this.measured ? field("duration s", this.inputs.duration_s) : null,
        this.runButton,
        h("span", { class: "tb-spacer" }),
        this.loopSelect,
      ),
      this.error,
      this.note,
      h(
        "div",
        { class: "frf-plots" },
        h("div", { class: "bode" }, h("div", { class: "plot-title" }, "Magnitude"), this.mag.el, h("div", { class: "plot-title" }, "Phase"), this.phase.el),
        h("div", { class: "nyquist-wrap" }, h("div", { class: "plot-title" }, "Nyquist (open loop)"), this.nyquist),
      ),
      this.readouts,
    );
    syncInject();
  }

  private async start(): Promise<void> {
    this.error.hidden = true;
    const n = (k: keyof typeof this.inputs): number => Number(this.inputs[k].value);
    const open = this.measured && this.injectSelect.value === "open";
    if (
      open &&
      !window.confirm(
        `Open loop: the position controller is OFF and the motor is driven by PWM up to ±${Math.round(n("pwm"))} (spwm). ` +
          "Only your travel window stops it (the server stops the axis when it leaves the window); the axis is left unpowered where it ends. Continue?",
      )
    )
      return;
    this.runButton.disabled = true;
    try {
      const run = await api.startRun(this.axisId, {
        kind: "frequency_response",
        distance: 0,
        velocity: 0,
        note: "",
        duration_s: this.measured ? n("duration_s") : 1,
        amplitude: this.measured && !open ? Math.round(n("amplitude")) : 0,
        pwm: open ? Math.round(n("pwm")) : 0,
        loop: open ? "open" : "closed",
        confirm_open_loop: open,
        low_hz: n("low_hz"),
        high_hz: n("high_hz"),
      });
      this.onStarted(run.id);
    } catch (error) {
      this.error.hidden = false;
      setText(this.error, errorText(error));
    } finally {
      this.runButton.disabled = false;
    }
  }

  /** Draw these frequency-response runs (the bench's selection of that kind). */
  show(runs: FrfRun[]): void {
    // A run still recording has no response yet: drawn once it has finished.
    this.runs = runs.filter((r) => !r.recording);
    if (runs.some((r) => r.recording)) setText(this.note, "recording the frequency response …");
    void this.draw();
  }

  forget(runId: string): void {
    cache.delete(runId);
  }

  private async draw(): Promise<void> {
    const token = ++this.token;
    if (!this.runs.length) {
      if (this.note.textContent?.startsWith("recording")) return;
      this.mag.clear();
      this.phase.clear();
      replace(this.readouts);
      setText(this.note, "Select frequency-response runs in the table to see their Bode plot.");
      this.drawNyquist([]);
      return;
    }
    let loaded: FrfData[];
    try {
      loaded = await Promise.all(
        this.runs.map(async (r) => {
          const hit = cache.get(r.id);
          if (hit) return hit;
          const data = await frfApi.get(r.id);
          cache.set(r.id, data);
          return data;
        }),
      );
    } catch (error) {
      if (token === this.token) setText(this.note, `cannot load the frequency response: ${errorText(error)}`);
      return;
    }
    if (token !== this.token) return;
    const open = this.loopSelect.value === "open";
    const theme = plotTheme();
    const xs: number[][] = [];
    const mags: (number | null)[][] = [];
    const phases: (number | null)[][] = [];
    const magSeries: uPlot.Series[] = [];
    const phaseSeries: uPlot.Series[] = [];
    let usable: Band | null = null;
    const notes: string[] = [];
    loaded.forEach((d, i) => {
      const run = this.runs[i] as FrfRun;
      const base = hex(run.color) || run.color;
      if (d.model) {
        const b = open ? d.model.open_loop : d.model.closed_loop;
        xs.push(b.frequency_hz as number[]);
        mags.push(b.magnitude_db);
        phases.push(b.phase_deg);
        const s = { label: `${run.label} model`, stroke: base, width: 1.5, dash: [6, 4], points: { show: false } };
        magSeries.push(s);
        phaseSeries.push({ ...s });
      } else if (d.model_problem) notes.push(`${run.label}: no model — ${d.model_problem}`);
      if (d.measured) {
        const b = open ? d.measured.open_loop : d.measured.closed_loop;
        const tones = d.measured.loop === "open" ? (d.measured.plant ?? d.measured.closed_loop) : d.measured.closed_loop;
        const band: Band = { from: d.measured.usable_from_hz ?? 0, until: d.measured.usable_until_hz ?? 0 };
        usable = usable === null ? band : { from: Math.max(usable.from, band.from), until: Math.min(usable.until, band.until) };
        // Open loop: a tone where L is not measurable (|1 - T| small against T's
        // error) is drawn hollow and grey whatever its coherence.
        const known = (j: number): boolean => !open || (b.measurable?.[j] ?? true);
        if (open && b.measurable?.some((m) => !m)) {
          xs.push(b.frequency_hz as number[]);
          mags.push(b.magnitude_db.map((v, j) => (known(j) ? null : v)));
          phases.push(b.phase_deg.map((v, j) => (known(j) ? null : v)));
          const s: uPlot.Series = { label: `${run.label} L not measurable`, stroke: "#888888", paths: () => null, points: { show: true, size: 7, stroke: "#888888", fill: "transparent" } };
          magSeries.push(s);
          phaseSeries.push({ ...s });
        }
        for (const bin of BINS) {
          const keep = (j: number): boolean => known(j) && binOf(tones, j) === bin.bin;
          xs.push(b.frequency_hz as number[]);
          mags.push(b.magnitude_db.map((v, j) => (keep(j) ? v : null)));
          phases.push(b.phase_deg.map((v, j) => (keep(j) ? v : null)));
          const color = hex(run.color) ? `${run.color}${bin.alpha}` : run.color;
          const s: uPlot.Series = { label: `${run.label} ${bin.label}`, stroke: color, paths: () => null, points: { show: true, size: 7, width: 1.5, stroke: color, fill: bin.fill ? color : "transparent" } };
          magSeries.push(s);
          phaseSeries.push({ ...s });
        }
        const trust = d.measured.trust;
        notes.push(
          `${run.label}: measured at ${d.measured.sample_rate_hz ?? "?"} samples/s (Nyquist ${d.measured.nyquist_hz ?? "?"} Hz), ${trust ? `${trust.trusted_tones} of ${trust.tones} tones trusted` : ""}${d.measured.usable_until_hz ? ` (${fmt(d.measured.usable_from_hz, 1, "Hz")} to ${fmt(d.measured.usable_until_hz, 1, "Hz")})` : ""}, input: ${d.measured.input === "pwm" ? "open-loop PWM (spwm): the plant measured, L = C·P with the run's PID" : d.measured.input === "profile" ? "targets through the profile law" : "targets sent"}`,
        );
        const left = d.measured.not_measured_hz ?? [];
        if (left.length)
          notes.push(
            `${run.label}: ${fmt(left[0], 1, "Hz")} to ${fmt(left[left.length - 1], 1, "Hz")} ${d.measured.not_measured_reason ?? "not measured"}`,
          );
      } else if (d.measured_problem) notes.push(`${run.label}: ${d.measured_problem}`);
      if (d.model_based) notes.push(`${run.label}: MODEL-BASED (${d.model?.law ?? "device law"}), not a measurement`);
    });
    setText(this.note, notes.join(" · "));
    if (!xs.length) {
      this.mag.clear();
      this.phase.clear();
    } else {
      const join = (ys: (number | null)[][]): uPlot.AlignedData => uPlot.join(xs.map((x, i) => [x, ys[i] as (number | null)[]] as uPlot.AlignedData));
      this.mag.set(join(mags), magSeries, "dB", usable, theme);
      this.phase.set(join(phases), phaseSeries, "deg", usable, theme);
    }
    this.renderReadouts(loaded);
    this.drawNyquist(loaded);
  }

  private renderReadouts(loaded: FrfData[]): void {
    // A measured margin is a number (± its uncertainty) or "not measurable" with the
    // reason, never a number read from tones where L is unknown.
    const margin = (testid: string, v: number | null, err: number | null | undefined, unit: string, problem: string | null | undefined, target: number | undefined): HTMLElement =>
      problem
        ? h("td", { class: "frf-unmeasurable", testid, title: problem }, "not measurable")
        : h(
            "td",
            { class: `mono margin-value ${v === null || target === undefined ? "" : v >= target ? "ok" : "low"}`, testid, title: target === undefined ? "" : `target ≥ ${target} ${unit}` },
            err !== null && err !== undefined && v !== null ? `${v.toFixed(1)} ± ${err.toFixed(1)} ${unit}` : fmt(v, 1, unit),
          );
    const row = (label: string, color: string, source: string, p: Part): HTMLElement => {
      const margins: Margins = p.margins;
      return h(
        "tr",
        { "data-source": source, "data-meets-target": margins.meets_target === undefined || margins.meets_target === null ? "" : String(margins.meets_target) },
        h("td", null, h("span", { class: "swatch", style: `background:${color}` }), ` ${label}`),
        h("td", null, source),
        margin("frf-gm", margins.gain_margin_db, margins.gain_margin_error_db, "dB", margins.gain_margin_problem, margins.target?.gain_margin_db),
        margin("frf-pm", margins.phase_margin_deg, margins.phase_margin_error_deg, "°", margins.phase_margin_problem, margins.target?.phase_margin_deg),
        h("td", { class: "mono" }, fmt(margins.gain_crossover_hz, 1, "Hz")),
        h("td", { class: "mono" }, fmt(margins.phase_crossover_hz, 1, "Hz")),
        h("td", { class: "mono", testid: "frf-bw" }, fmt(p.bandwidth_hz, 1, "Hz")),
        h("td", { class: "mono" }, fmt(p.resonance_db, 1, "dB")),
        h("td", null, margins.stable === null ? "—" : margins.stable ? "stable" : "UNSTABLE"),
      );
    };
    const rows: HTMLElement[] = [];
    const reasons: HTMLElement[] = [];
    const warnings: HTMLElement[] = [];
    const details: HTMLElement[] = [];
    let target: MarginTarget | undefined;
    loaded.forEach((d, i) => {
      const run = this.runs[i] as FrfRun;
      if (d.measured) {
        rows.push(row(run.label, run.color, "measured", d.measured));
        const m = d.measured.margins;
        for (const [name, why] of [["gain margin", m.gain_margin_problem], ["phase margin", m.phase_margin_problem]] as const) {
          if (why) reasons.push(h("li", { testid: "frf-margin-reason" }, `${run.label}, ${name}: ${why}`));
        }
        if (m.meets_target === false && m.warning) warnings.push(h("div", { class: "at-warning margin-warning", testid: "frf-margin-warning", role: "note" }, h("b", null, "⚠ "), `${run.label} measured: ${m.warning}`));
        const trust = d.measured.trust;
        if (trust) {
          for (const why of trust.not_trusted) reasons.push(h("li", { testid: "frf-trust-reason" }, `${run.label}, not trusted: ${why}`));
          if (trust.input_check_excess_counts)
            reasons.push(h("li", { testid: "frf-input-check" }, `${run.label}: the rebuilt input differs from the captured setpoint by up to ${trust.input_check_excess_counts} counts beyond the tick phase at ${trust.input_check_samples_over} samples`));
          if (trust.stalled_samples_left_out || trust.stalled_targets_bounded)
            reasons.push(
              h("li", { testid: "frf-stalls" }, `${run.label}: the host stalled (latch spans up to ${trust.max_latch_span_ms ?? "?"} ms, ${trust.spans}): ${trust.stalled_samples_left_out} samples left out, ${trust.stalled_targets_bounded} targets bounded`),
            );
        }
        details.push(this.toneTable(run, d.measured));
      }
      if (d.model) {
        rows.push(row(run.label, run.color, d.model_based ? "model (model-based run)" : "model", d.model));
        const m = d.model.margins;
        if (m.meets_target === false && m.warning) warnings.push(h("div", { class: "at-warning margin-warning", testid: "frf-margin-warning", role: "note" }, h("b", null, "⚠ "), `${run.label} model: ${m.warning}`));
      }
      target = target ?? d.measured?.margins.target ?? d.model?.margins.target;
    });
    replace(
      this.readouts,
      h(
        "table",
        { class: "bench-table frf-table" },
        h(
          "tr",
          null,
          ...["run", "from", "gain margin", "phase margin", "crossover", "phase crossover", "−3 dB bandwidth", "resonance", "closed loop"].map((t) => h("th", null, t)),
        ),
        ...rows,
      ),
      target ? h("div", { class: "frf-target", testid: "frf-target" }, `margin target ${targetText(target)}`) : null,
      ...warnings,
      reasons.length ? h("ul", { class: "frf-reasons" }, ...reasons) : null,
      ...details,
    );
  }

  /** Every measured tone with its bounds and why it is (not) trusted. */
  private toneTable(run: FrfRun, m: FrfMeasured): HTMLElement {
    const b = m.loop === "open" ? (m.plant ?? m.closed_loop) : m.closed_loop;
    const n = (v: number | null | undefined, digits: number): string => (v === null || v === undefined ? "—" : v.toFixed(digits));
    return h(
      "details",
      { class: "frf-tones", testid: "frf-tones" },
      h("summary", null, `${run.label}: the ${b.frequency_hz.length} tones (${m.loop === "open" ? "plant P" : "closed loop T"})`),
      h(
        "table",
        { class: "bench-table frf-table" },
        h("tr", null, ...["Hz", "|·| dB", "± dB", "phase °", "± °", "coherence", "trusted"].map((t) => h("th", null, t))),
        ...b.frequency_hz.map((f, j) =>
          h(
            "tr",
            { "data-trusted": b.trusted?.[j] ? "1" : "0" },
            h("td", { class: "mono" }, n(f, 1)),
            h("td", { class: "mono" }, n(b.magnitude_db[j], 2)),
            h("td", { class: "mono" }, n(b.error_db?.[j], 2)),
            h("td", { class: "mono" }, n(b.phase_deg[j], 1)),
            h("td", { class: "mono" }, n(b.error_deg?.[j], 1)),
            h("td", { class: "mono" }, n(b.coherence?.[j], 3)),
            h("td", null, b.trusted?.[j] ? "yes" : `no: ${b.not_trusted_because?.[j] ?? "?"}`),
          ),
        ),
      ),
    );
  }

  private drawNyquist(loaded: FrfData[]): void {
    const c = this.nyquist;
    const ctx = c.getContext("2d");
    if (!ctx) return;
    const w = c.width;
    const hgt = c.height;
    ctx.clearRect(0, 0, w, hgt);
    const theme = plotTheme();
    const range = 2.5; // |L| up to 2.5 around the critical point is what margins are about
    const sx = (re: number): number => w / 2 + (re / range) * (w / 2) * 0.95;
    const sy = (im: number): number => hgt / 2 - (im / range) * (hgt / 2) * 0.95;
    ctx.strokeStyle = theme.grid;
    ctx.beginPath();
    ctx.moveTo(0, hgt / 2);
    ctx.lineTo(w, hgt / 2);
    ctx.moveTo(w / 2, 0);
    ctx.lineTo(w / 2, hgt);
    ctx.stroke();
    ctx.beginPath();
    ctx.arc(sx(0), sy(0), (w / 2) * 0.95 / range, 0, 2 * Math.PI);
    ctx.stroke();
    ctx.fillStyle = "#e5484d";
    ctx.beginPath();
    ctx.arc(sx(-1), sy(0), 4, 0, 2 * Math.PI);
    ctx.fill();
    ctx.fillStyle = theme.text;
    ctx.font = theme.font;
    ctx.fillText("−1", sx(-1) - 8, sy(0) + 14);
    loaded.forEach((d, i) => {
      const run = this.runs[i] as FrfRun;
      ctx.strokeStyle = run.color;
      ctx.fillStyle = run.color;
      if (d.model) {
        ctx.setLineDash([5, 3]);
        ctx.beginPath();
        let started = false;
        d.model.nyquist.re.forEach((re, j) => {
          const im = d.model?.nyquist.im[j];
          if (re === null || im === null || im === undefined || Math.abs(re) > 50 || Math.abs(im) > 50) {
            started = false;
            return;
          }
          if (started) ctx.lineTo(sx(re), sy(im));
          else ctx.moveTo(sx(re), sy(im));
          started = true;
        });
        ctx.stroke();
        ctx.setLineDash([]);
      }
      if (d.measured) {
        const coh = d.measured.closed_loop.coherence ?? [];
        d.measured.nyquist.re.forEach((re, j) => {
          const im = d.measured?.nyquist.im[j];
          if (re === null || im === null || im === undefined) return;
          const known = d.measured?.nyquist.measurable?.[j] ?? true;
          ctx.globalAlpha = known && (coh[j] ?? 0) >= MIN_COHERENCE ? 1 : 0.3;
          ctx.beginPath();
          ctx.arc(sx(re), sy(im), 3, 0, 2 * Math.PI);
          if (known) ctx.fill();
          else ctx.stroke(); // hollow: L not measurable at this tone
        });
        ctx.globalAlpha = 1;
      }
    });
    c.dataset.curves = String(loaded.length);
  }
}
