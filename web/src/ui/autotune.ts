// The auto-tune assistant in the bench (server/servotune/api/autotune_routes.py):
// identify the plant within the user's limits, show the fitted model, the rule, the
// proposed gains and the metrics predicted for them and for the gains in use; accept
// and verify, then predicted against measured with both runs in the bench overlay.
// Which devices it supports is the server's answer (409 for the others).
import {
  ApiError,
  api,
  type AutoTuneAccepted,
  type AutoTuneDecision,
  type AutoTuneGoal,
  type AutoTuneProposal,
  type AutoTuneRecommendation,
  type AutoTuneRequest,
  type AutoTuneResult,
  type AutoTuneSession,
  type BenchLimits,
  type GainSet,
  type MarginPreset,
  type MarginReport,
  type RunMetrics,
  measuredMetrics,
} from "../api";
import { h, replace, setText, toggleClass } from "../dom";
import { store } from "../store";
import type { DeviceDescriptor } from "../schema.gen";
import { errorText, statusLabel } from "./feedback";
import { PRESET_HELP, marginValue, marginWarning, targetText } from "./margins";
import { type MetricColumn, metricCell, metricHeads, num } from "./metriccols";

const GOALS: Record<AutoTuneGoal, { label: string; help: string }> = {
  no_overshoot: { label: "No overshoot (≤ 1 %)", help: "The fastest gains whose predicted overshoot stays within 1 %" },
  fast: { label: "Fast (≤ 10 %)", help: "The fastest gains whose predicted overshoot stays within 10 %" },
};

/** The fitted model's fields, as the server names them. */
const MODEL_FIELDS: { key: string; label: string; help: string; text(v: number): string }[] = [
  { key: "gain_counts_s_per_pwm", label: "gain K", help: "Steady velocity per PWM unit above friction", text: (v) => `${num(v)} counts/s per PWM` },
  { key: "tau_s", label: "time constant τ", help: "Mechanical time constant of the velocity response", text: (v) => `${(v * 1000).toFixed(1)} ms` },
  { key: "friction_pwm", label: "friction", help: "PWM that just overcomes friction (Coulomb friction and stiction)", text: (v) => `${v.toFixed(1)} PWM` },
  { key: "rms_error_counts", label: "fit error", help: "RMS of the model's positions against the recorded ones", text: (v) => `${v.toFixed(2)} counts rms` },
  { key: "samples", label: "samples", help: "Samples of the identification run used by the fit", text: (v) => String(v) },
  { key: "delay_s", label: "delay", help: "When the PWM steps took effect after their timestamps (fitted)", text: (v) => `${(v * 1000).toFixed(2)} ms` },
];

const TESTS: Record<"position_step" | "move", { label: string; help: string }> = {
  position_step: { label: "position step", help: "Tune for (and verify with) a move with velocity and acceleration at their maximum: the closest to a step" },
  move: { label: "move", help: "Tune for (and verify with) a move with the axis' own velocity and acceleration" },
};

interface Form {
  max_pwm: string;
  max_distance: string;
  response: AutoTuneGoal;
  margins: MarginPreset;
  test: "position_step" | "move";
  direction: "1" | "-1";
  distance: string; // "" = the server's default
}

/** Remembered per axis across view switches. */
const forms = new Map<string, Form>();
const OPEN_KEY = "servotune.autotune.open";

export interface AutoTuneHost {
  /** Metric columns as in the runs table, including those ``metrics`` need. */
  columns(metrics: (RunMetrics | null | undefined)[]): MetricColumn[];
  /** Select exactly these runs in the bench overlay (after re-reading the list). */
  showRuns(ids: string[]): Promise<void>;
  /** A new identified model (and proposal) exists: views built on it reload it. */
  modelChanged(): void;
  /** Stored runs changed (a decision recorded on the identification run): re-read them. */
  runsChanged(): void;
}

function gainsText(g: GainSet | undefined): string {
  return g ? Object.entries(g).map(([k, v]) => `${k} ${v}`).join(" · ") : "—";
}

export class AutoTunePanel {
  readonly el: HTMLElement;
  private readonly form: Form;
  private readonly maxPwm: HTMLInputElement;
  private readonly maxDistance: HTMLInputElement;
  private readonly goal: HTMLSelectElement;
  private readonly margins: HTMLSelectElement;
  private readonly test: HTMLSelectElement;
  private readonly direction: HTMLSelectElement;
  private readonly distance: HTMLInputElement;
  private readonly identifyButton: HTMLButtonElement;
  private readonly progress: HTMLElement;
  private readonly error: HTMLElement;
  private readonly details: HTMLElement;
  private readonly toggle: HTMLButtonElement;
  private open: boolean;
  private limits: BenchLimits | null = null;
  private proposal: AutoTuneProposal | null = null;
  private result: AutoTuneResult | null = null;
  /** The choice made for the shown proposal, and this axis' earlier ones (newest last). */
  private decision: AutoTuneDecision | null = null;
  private history: AutoTuneDecision[] = [];
  private busy: "identify" | "accept" | "keep" | "revert" | null = null;
  private busySince = 0;
  private lastEvent = "";
  private timer: number | undefined;
  private poll: number | undefined;

  constructor(
    private readonly axisId: string,
    private readonly descriptor: DeviceDescriptor,
    private readonly host: AutoTuneHost,
    private readonly signal: AbortSignal,
  ) {
    this.form = forms.get(axisId) ?? { max_pwm: "", max_distance: "", response: "no_overshoot", margins: "medium", test: "position_step", direction: "1", distance: "" };
    forms.set(axisId, this.form);
    this.open = localStorage.getItem(OPEN_KEY) !== "0";

    const numberInput = (testid: string, label: string, key: "max_pwm" | "max_distance" | "distance", title: string): HTMLInputElement => {
      const input = h("input", { class: "input num small", type: "number", step: 1, min: 1, testid, "aria-label": label, title, value: this.form[key] });
      input.addEventListener("input", () => {
        this.form[key] = input.value;
        input.classList.remove("server-invalid");
        this.validate();
      });
      input.addEventListener("keydown", (event) => {
        if (event.key === "Enter") {
          event.preventDefault();
          void this.identify();
        }
      });
      return input;
    };
    this.maxPwm = numberInput("at-max-pwm", "largest PWM", "max_pwm", "Largest open-loop PWM of the identification staircase (±, within your bench limit; devices without open loop identify with a move and ignore it)");
    this.maxDistance = numberInput(
      "at-max-distance",
      "largest distance",
      "max_distance",
      "No identification or test travels further than this from where it starts (counts, within your bench limit)",
    );
    this.goal = h(
      "select",
      { class: "input", testid: "at-response", "aria-label": "Response", title: "What the proposal optimises for" },
      (Object.keys(GOALS) as AutoTuneGoal[]).map((g) => h("option", { value: g, title: GOALS[g].help }, GOALS[g].label)),
    );
    this.goal.value = this.form.response;
    this.goal.addEventListener("change", () => (this.form.response = this.goal.value as AutoTuneGoal));
    this.margins = h(
      "select",
      { class: "input", testid: "at-margins", "aria-label": "Margin target", title: "The margins the gains are designed to (on the identified model): stiff PM 40° / GM 6 dB, medium PM 45° / GM 8 dB (default), soft PM 60° / GM 12 dB" },
      (["stiff", "medium", "soft"] as MarginPreset[]).map((m) => h("option", { value: m, title: PRESET_HELP[m] }, m)),
    );
    this.margins.value = this.form.margins;
    this.margins.addEventListener("change", () => (this.form.margins = this.margins.value as MarginPreset));
    this.test = h(
      "select",
      { class: "input", testid: "at-test", "aria-label": "Test", title: "The bench test the gains are tuned for and verified with" },
      (Object.keys(TESTS) as (keyof typeof TESTS)[]).map((t) => h("option", { value: t, title: TESTS[t].help }, TESTS[t].label)),
    );
    this.test.value = this.form.test;
    this.test.addEventListener("change", () => (this.form.test = this.test.value as Form["test"]));
    this.direction = h(
      "select",
      { class: "input", testid: "at-direction", "aria-label": "Direction", title: "Identification and tests towards positive or negative counts: mind the mechanics (the open-loop staircase may ignore limit switches)" },
      h("option", { value: "1" }, "+"),
      h("option", { value: "-1" }, "−"),
    );
    this.direction.value = this.form.direction;
    this.direction.addEventListener("change", () => (this.form.direction = this.direction.value as Form["direction"]));
    this.distance = numberInput("at-distance", "test distance", "distance", "Distance of the baseline and verification tests (counts); empty: the server's default (1000, or half the distance limit)");
    this.distance.placeholder = "auto";
    this.identifyButton = h(
      "button",
      {
        class: "btn primary",
        testid: "at-identify",
        title: "An identification test within your limits (the axis moves: an open-loop PWM staircase, or a move where the device has no open loop), fit a model, propose gains. STOP / Esc stops.",
        onclick: () => void this.identify(),
      },
      "Identify",
    );
    this.progress = h("span", { class: "at-progress", testid: "at-progress", "aria-live": "polite" });
    // The whole message, wrapped: a failed identification says what failed, that the
    // axis was stopped and whether it returned to its start.
    this.error = h("div", { class: "at-error", testid: "at-error", role: "alert", hidden: true, style: "white-space: normal; overflow-wrap: anywhere; max-height: none" });
    this.details = h("div", { class: "at-details" });
    this.toggle = h(
      "button",
      { class: "at-toggle", testid: "at-toggle", title: "Show or hide the proposal and the verification", onclick: () => this.setOpen(!this.open) },
      h("span", { class: "ps-caret", "aria-hidden": "true" }),
      h("span", { class: "pane-title" }, "Auto-tune"),
    );
    const field = (label: string, input: HTMLElement, unit: string): HTMLElement =>
      h("label", { class: "bl" }, h("span", { class: "bl-label" }, label), input, unit ? h("span", { class: "unit" }, unit) : null);
    this.el = h(
      "section",
      { class: "autotune", testid: "at-panel", "data-open": "1" },
      h(
        "div",
        { class: "at-bar" },
        this.toggle,
        field("PWM ±", this.maxPwm, ""),
        field("distance ±", this.maxDistance, this.descriptor.channels.find((c) => c.name === "position")?.unit ?? "counts"),
        field("goal", this.goal, ""),
        field("margins", this.margins, ""),
        h(
          "span",
          { class: "at-test-fields" },
          field("test", this.test, ""),
          field("", this.direction, ""),
          field("", this.distance, this.descriptor.channels.find((c) => c.name === "position")?.unit ?? "counts"),
        ),
        this.identifyButton,
        this.progress,
      ),
      this.error,
      this.details,
    );
    this.setOpen(this.open);
    store.on(
      "event",
      (e) => {
        if (e.axis !== axisId || !/auto-?tune/i.test(e.message)) return;
        this.lastEvent = e.message.replace(/^auto-tune:\s*/i, "");
        this.syncProgress();
        if (/^auto-?tune:\s*proposed/i.test(e.message)) {
          // A new model and proposal (this page's or another's): whatever is built on
          // them reloads without a page reload.
          this.host.modelChanged();
          if (!this.busy) void this.loadSession();
        }
      },
      signal,
    );
    store.on(
      "run",
      (msg) => {
        if (msg.axis === axisId && this.busy) {
          this.lastEvent = `${msg.message || msg.status} · run #${msg.run_id.slice(0, 4)} ${msg.elapsed_s.toFixed(1)} s`;
          this.syncProgress();
        }
      },
      signal,
    );
    signal.addEventListener(
      "abort",
      () => {
        window.clearInterval(this.timer);
        window.clearTimeout(this.poll);
      },
      { once: true },
    );
    void this.loadSession();
  }

  /** The bench limits: the defaults of the fields and the client-side check. */
  setLimits(limits: BenchLimits): void {
    this.limits = limits;
    if (!this.form.max_pwm) this.form.max_pwm = String(Math.min(60, limits.max_pwm));
    if (!this.form.max_distance) this.form.max_distance = String(Math.min(4000, limits.max_distance_counts));
    this.maxPwm.value = this.form.max_pwm;
    this.maxDistance.value = this.form.max_distance;
    this.maxPwm.max = String(limits.max_pwm);
    this.maxDistance.max = String(limits.max_distance_counts);
    this.validate();
  }

  private setOpen(open: boolean): void {
    this.open = open;
    try {
      localStorage.setItem(OPEN_KEY, open ? "1" : "0");
    } catch {
      /* private mode */
    }
    this.el.dataset.open = open ? "1" : "0";
    this.details.hidden = !open;
    this.toggle.setAttribute("aria-expanded", open ? "true" : "false");
  }

  private validate(): void {
    const check = (input: HTMLInputElement, limit: number | undefined): void => {
      const v = Number(input.value);
      toggleClass(input, "invalid", input.value.trim() === "" || !Number.isInteger(v) || v < 1 || (limit !== undefined && v > limit));
    };
    check(this.maxPwm, this.limits?.max_pwm);
    check(this.maxDistance, this.limits?.max_distance_counts);
    const d = Number(this.distance.value);
    const dLimit = Number(this.maxDistance.value);
    toggleClass(this.distance, "invalid", this.distance.value.trim() !== "" && (!Number.isInteger(d) || d < 1 || (Number.isFinite(dLimit) && d > dLimit)));
  }

  // --- session ------------------------------------------------------------------------

  private async loadSession(): Promise<void> {
    let session: AutoTuneSession;
    try {
      session = await api.autotune(this.axisId);
    } catch (error) {
      if (this.signal.aborted) return;
      this.showError(error, true);
      return;
    }
    if (this.signal.aborted) return;
    this.el.dataset.state = session.state;
    if (session.request && !forms.get(this.axisId)?.max_pwm) {
      this.form.max_pwm = String(session.request.max_pwm);
      this.form.max_distance = String(session.request.max_distance_counts);
    }
    const req = session.request;
    if (req) {
      if (req.response) this.goal.value = this.form.response = req.response;
      if (req.margins) this.margins.value = this.form.margins = req.margins;
      if (req.test === "position_step" || req.test === "move") this.test.value = this.form.test = req.test;
      if (req.direction === 1 || req.direction === -1) this.direction.value = this.form.direction = String(req.direction) as Form["direction"];
    }
    this.proposal = session.proposal;
    // A verification that ended early (STOP, a failure) is no result: the state says
    // "failed" and the message why.
    this.result = session.result && !("stopped" in session.result) ? session.result : null;
    this.decision = session.decision ?? null;
    this.history = session.history ?? [];
    if (session.state === "identifying" || session.state === "verifying") {
      // Running from another browser: follow it until it ends.
      setText(this.progress, `${session.state} … ${session.message}`);
      this.progress.dataset.kind = "pending";
      this.poll = window.setTimeout(() => void this.loadSession(), 1000);
    } else if (session.state === "failed") {
      this.setProgress("error", session.message);
    } else if (session.message) this.setProgress("", session.message);
    this.render();
  }

  // --- identify -----------------------------------------------------------------------

  private request(): AutoTuneRequest {
    const n = (input: HTMLInputElement): number => (input.value.trim() === "" ? Number.NaN : Number(input.value));
    const body: AutoTuneRequest = {
      max_pwm: n(this.maxPwm),
      max_distance_counts: n(this.maxDistance),
      response: this.goal.value as AutoTuneGoal,
      margins: this.margins.value as MarginPreset,
      test: this.test.value as Form["test"],
      direction: this.direction.value === "-1" ? -1 : 1,
    };
    if (this.distance.value.trim() !== "") body.distance = n(this.distance);
    return body;
  }

  private async identify(): Promise<void> {
    if (this.busy) return;
    this.clearError();
    this.start("identify");
    try {
      const proposal = await api.autotuneIdentify(this.axisId, this.request());
      const took = this.elapsed();
      this.stop();
      this.proposal = proposal;
      this.result = null;
      this.decision = null;
      this.el.dataset.state = "proposed";
      this.setProgress("ok", `✓ model fitted, gains proposed (${took})`);
      this.setOpen(true);
      this.host.modelChanged();
    } catch (error) {
      this.failed(error);
    } finally {
      this.render();
    }
  }

  private async accept(): Promise<void> {
    if (this.busy || !this.proposal) return;
    this.clearError();
    this.start("accept");
    let result: AutoTuneAccepted;
    const proposal = this.proposal;
    try {
      result = await api.autotuneAccept(this.axisId);
      this.decided("write", proposal.gains, proposal.recommendation);
    } catch (error) {
      this.failed(error);
      this.render();
      return;
    }
    const took = this.elapsed();
    this.stop();
    if ("stopped" in result) {
      const ended = result;
      // STOP during the verification: the server stopped the axis and put the previous
      // gains back, or says loudly that it could not (then: one click to revert).
      this.result = null;
      this.el.dataset.state = "failed";
      const message = ended.message || "verification stopped";
      this.setProgress("error", `■ ${message}`);
      replace(
        this.error,
        h("span", null, message),
        ended.unverified
          ? h("button", { class: "btn small warn", testid: "at-revert-unverified", onclick: () => void this.revert() }, "Revert to the previous gains")
          : null,
      );
      this.error.hidden = false;
      this.render();
      return;
    }
    this.result = result;
    this.el.dataset.state = "verified";
    this.setProgress("ok", `✓ verified: ${result.verdict} (${took})`);
    this.render();
    await this.host.showRuns([result.baseline_run_id, result.verification_run_id].filter((id): id is string => !!id));
  }

  /** Decline the proposal: nothing is written, the choice is recorded by the server. */
  private async keep(): Promise<void> {
    if (this.busy || !this.proposal) return;
    this.clearError();
    this.start("keep");
    try {
      const decision = await api.autotuneKeep(this.axisId);
      this.stop();
      this.record(decision);
      this.host.runsChanged();
      this.el.dataset.state = "kept";
      this.setProgress("ok", `✓ kept the gains in use (${gainsText(decision.gains)}): nothing written`);
    } catch (error) {
      this.failed(error);
    } finally {
      this.render();
    }
  }

  /** The server recorded an accept as a decision: show it as the session would. */
  private decided(action: "keep" | "write", gains: GainSet, rec: AutoTuneRecommendation | undefined): void {
    const decision: AutoTuneDecision = {
      action,
      gains,
      recommended: rec?.action ?? null,
      followed: !rec || rec.action === action,
      reason: rec?.reason ?? null,
      at_s: Date.now() / 1000,
      identification_run_id: this.proposal?.identification_run_id ?? null,
    };
    this.record(decision);
  }

  private record(decision: AutoTuneDecision): void {
    this.decision = decision;
    this.history = [...this.history, decision].slice(-20);
  }

  /** A call failed: its error under the bar, the progress line cleared. */
  private failed(error: unknown): void {
    this.stop();
    this.showError(error);
    this.setProgress("", "");
  }

  private async revert(): Promise<void> {
    if (this.busy) return;
    this.clearError();
    this.start("revert");
    try {
      const readback = await api.autotuneRevert(this.axisId);
      this.stop();
      store.setDeviceParams(this.axisId, readback, true);
      this.setProgress("ok", `✓ reverted to ${gainsText(readback)}`);
      this.result = null;
      this.proposal = null;
      this.el.dataset.state = "idle";
    } catch (error) {
      this.failed(error);
    } finally {
      this.render();
    }
  }

  private start(kind: "identify" | "accept" | "keep" | "revert"): void {
    this.busy = kind;
    this.busySince = performance.now();
    this.lastEvent = "";
    this.identifyButton.disabled = true;
    this.identifyButton.classList.add("busy");
    this.el.dataset.busy = kind;
    this.render();
    this.syncProgress();
    window.clearInterval(this.timer);
    this.timer = window.setInterval(() => this.syncProgress(), 200);
  }

  private stop(): void {
    this.busy = null;
    window.clearInterval(this.timer);
    this.identifyButton.disabled = false;
    this.identifyButton.classList.remove("busy");
    delete this.el.dataset.busy;
  }

  private elapsed(): string {
    return `${((performance.now() - this.busySince) / 1000).toFixed(1)} s`;
  }

  private syncProgress(): void {
    if (!this.busy) return;
    const what = { identify: "Identifying: test, fit, gain search", accept: "Verifying: baseline test, write, verification test", keep: "Keeping the gains in use", revert: "Reverting" }[this.busy];
    this.setProgress("pending", `● ${what} … ${this.elapsed()}${this.lastEvent ? ` · ${this.lastEvent}` : ""}`);
  }

  private setProgress(kind: string, text: string): void {
    this.progress.dataset.kind = kind;
    setText(this.progress, text);
    this.progress.title = text;
  }

  private showError(error: unknown, onLoad = false): void {
    const field = error instanceof ApiError ? error.field : null;
    const input = { max_pwm: this.maxPwm, max_distance_counts: this.maxDistance, distance: this.distance, test: this.test, direction: this.direction }[field ?? ""] ?? null;
    input?.classList.add("server-invalid");
    let text = `${statusLabel(error)}: ${errorText(error)}`;
    if (error instanceof ApiError && error.status === 404 && !field) {
      text = `Auto-tune is not available on this server (${errorText(error)}): its /autotune routes are missing.`;
    }
    this.error.dataset.status = error instanceof ApiError ? String(error.status) : "";
    this.error.dataset.field = field ?? "";
    toggleClass(this.error, "unsupported", onLoad);
    setText(this.error, text);
    this.error.hidden = false;
  }

  private clearError(): void {
    this.error.hidden = true;
    setText(this.error, "");
    for (const input of [this.maxPwm, this.maxDistance, this.distance, this.test, this.direction]) input.classList.remove("server-invalid");
  }

  // --- proposal and result ------------------------------------------------------------

  private label(name: string): string {
    return this.descriptor.parameters.find((p) => p.name === name)?.label ?? name;
  }

  private render(): void {
    const p = this.proposal;
    if (!p) {
      replace(this.details);
      this.toggle.disabled = true;
      return;
    }
    this.toggle.disabled = false;
    const busy = this.busy !== null;
    const cols = this.host.columns([p.predicted, p.predicted_default, measuredMetrics(this.result?.measured), this.result?.baseline_measured]);
    replace(this.details, this.proposalView(p, cols, busy), this.result ? this.resultView(p, this.result, cols, busy) : null);
  }

  /** The proposal against the gains in use: margins on the model (coloured against the
   * target they were designed to), crossover, loop and the predicted step; the warning
   * under margins below the target. */
  private compareView(p: AutoTuneProposal): HTMLElement | null {
    const m = p.margins;
    if (!m) return null;
    const t = m.target;
    const now = p.margins_default;
    const ms = (v: number | null | undefined): string => (v === null || v === undefined ? "does not settle" : `${(v * 1000).toFixed(0)} ms`);
    const pct = (v: number | null | undefined): string => (v === null || v === undefined ? "—" : `${v.toFixed(1)} %`);
    const hz = (r: MarginReport | undefined): string => (r?.gain_crossover_hz === null || r?.gain_crossover_hz === undefined ? "—" : `${r.gain_crossover_hz.toFixed(0)} Hz`);
    const loop = (r: MarginReport | undefined): string => (r?.stable === false ? "UNSTABLE" : r?.stable ? "stable" : "—");
    const row = (key: string, label: string, help: string, current: HTMLElement | string, proposed: HTMLElement | string, target: string): HTMLElement =>
      h(
        "tr",
        { "data-row": key },
        h("td", { class: "d-name", title: help }, label),
        h("td", { class: "d-val num", testid: `at-cmp-${key}-current` }, current),
        h("td", { class: "d-val num", testid: `at-cmp-${key}-proposed` }, proposed),
        h("td", { class: "d-val num at-cmp-target" }, target),
      );
    const pm = (r: MarginReport | undefined, key: string): HTMLElement | string => (r ? marginValue(r.phase_margin_deg, t.phase_margin_deg, 1, "°", `at-pm-${key}`) : "—");
    const gm = (r: MarginReport | undefined, key: string): HTMLElement | string => (r ? marginValue(r.gain_margin_db, t.gain_margin_db, 1, "dB", `at-gm-${key}`) : "—");
    return h(
      "div",
      { class: "at-card at-margins", testid: "at-margins-card" },
      h("div", { class: "at-card-title" }, "Proposal vs gains in use", h("span", { class: "at-card-sub", testid: "at-margin-target" }, ` — on the model; target ${targetText(t)}`)),
      h(
        "table",
        { class: "diff-table at-compare", testid: "at-compare" },
        h("thead", null, h("tr", null, h("th", { class: "d-name" }, ""), h("th", null, "now"), h("th", null, "proposed"), h("th", null, "target"))),
        h(
          "tbody",
          null,
          row("pm", "phase margin", "Phase margin of the loop on the identified model", pm(now, "current"), pm(m, "proposed"), `≥ ${t.phase_margin_deg}°`),
          row("gm", "gain margin", "Gain margin of the loop on the identified model", gm(now, "current"), gm(m, "proposed"), `≥ ${t.gain_margin_db} dB`),
          row("crossover", "crossover", "Gain crossover frequency on the model", hz(now), hz(m), ""),
          row("loop", "loop", "Closed-loop stability on the model (the exact discrete loop)", h("span", { testid: "at-stable-current" }, loop(now)), h("span", { testid: "at-stable-proposed" }, loop(m)), "stable"),
          row("settling", "settling", "Settling time of the tuned-for move, predicted on the model", ms(p.predicted_default?.settling_time_s), ms(p.predicted?.settling_time_s), ""),
          row("overshoot", "overshoot", "Overshoot of the tuned-for move, predicted on the model", pct(p.predicted_default?.overshoot_pct), pct(p.predicted?.overshoot_pct), ""),
        ),
      ),
      marginWarning(m, "at-margin-warning"),
      m.meets_target === false ? h("div", { class: "at-sub" }, "no gains of the search reach the target on this model: these are the closest it found") : null,
    );
  }

  /** The decision taken for the shown proposal, and this axis' earlier ones. */
  private decisionView(): HTMLElement | null {
    const d = this.decision;
    const line = d
      ? h(
          "div",
          { class: `at-decision${d.followed ? "" : " against"}`, testid: "at-decision", "data-action": d.action, "data-followed": d.followed ? "1" : "0" },
          h("b", null, d.action === "keep" ? `✓ Kept the gains in use (${gainsText(d.gains)}): nothing written to the device` : `Wrote the proposal (${gainsText(d.gains)})`),
          d.recommended ? (d.followed ? " — as recommended." : ` — against the recommendation to ${d.recommended === "keep" ? "keep the gains in use" : "write the proposal"}.`) : null,
          d.action === "keep" ? h("span", { class: "at-hint" }, " Identify again for a new proposal.") : null,
        )
      : null;
    const past = this.history.slice(-5).reverse();
    const list = past.length
      ? h(
          "details",
          { class: "at-history", testid: "at-history" },
          h("summary", null, `Decisions on this axis (${this.history.length})`),
          h(
            "ul",
            null,
            past.map((e) =>
              h(
                "li",
                { "data-action": e.action, title: e.reason ?? "" },
                `${new Date(e.at_s * 1000).toLocaleTimeString()} · ${e.action === "keep" ? "kept" : "wrote"} ${gainsText(e.gains)}`,
                e.recommended ? (e.followed ? " · as recommended" : ` · against the recommendation (${e.recommended})`) : "",
                e.identification_run_id ? ` · identification run #${e.identification_run_id.slice(0, 4)}` : "",
              ),
            ),
          ),
        )
      : null;
    return line || list ? h("div", { class: "at-decisions" }, line, list) : null;
  }

  private proposalView(p: AutoTuneProposal, cols: MetricColumn[], busy: boolean): HTMLElement {
    const model = h(
      "div",
      { class: "at-card at-model", testid: "at-model" },
      h("div", { class: "at-card-title" }, "Fitted model"),
      h(
        "dl",
        { class: "at-kv" },
        MODEL_FIELDS.filter((f) => typeof p.model[f.key] === "number").map((f) => [
          h("dt", { title: f.help }, f.label),
          h("dd", { class: "mono", "data-key": f.key }, f.text(p.model[f.key] as number)),
        ]),
        Object.entries(p.model)
          .filter(([k]) => !MODEL_FIELDS.some((f) => f.key === k))
          .map(([k, v]) => [h("dt", null, k), h("dd", { class: "mono" }, String(v))]),
      ),
      p.test
        ? h(
            "div",
            { class: "at-sub", title: Object.entries(p.test).map(([k, v]) => `${k} = ${v}`).join("\n") },
            `tuned for a ${p.test.distance !== undefined ? `${p.test.distance > 0 ? "+" : ""}${p.test.distance} counts ` : ""}move${p.test.band !== undefined ? `, settled within ±${p.test.band}` : ""}`,
          )
        : null,
    );
    const names = [...new Set([...Object.keys(p.current_gains), ...Object.keys(p.gains)])];
    const gains = h(
      "div",
      { class: "at-card at-gains" },
      h("div", { class: "at-card-title" }, "Gains"),
      h(
        "table",
        { class: "diff-table at-gains-table", testid: "at-gains" },
        h("thead", null, h("tr", null, h("th", { class: "d-name" }, ""), h("th", null, "now"), h("th", null, "proposed"))),
        h(
          "tbody",
          null,
          names.map((n) => {
            const now = p.current_gains[n];
            const next = p.gains[n];
            const changed = now !== next;
            const factor = now && next !== undefined ? next / now : null;
            return h(
              "tr",
              { "data-param": n },
              h("td", { class: "d-name", title: n }, this.label(n), h("span", { class: "d-key mono" }, ` ${n}`)),
              h("td", { class: "d-val num" }, now === undefined ? "—" : String(now)),
              h(
                "td",
                { class: `d-val num${changed ? " differs" : ""}`, testid: `at-gain-${n}`, title: factor !== null && changed ? `× ${factor.toFixed(2)}` : "unchanged" },
                next === undefined ? "—" : String(next),
              ),
            );
          }),
        ),
      ),
      p.design?.unchanged === true ? h("div", { class: "at-sub" }, "the gains in use already fit the rule best") : null,
    );
    const rowLabel = (title: string, sub: string): HTMLElement => h("td", { class: "at-row-label" }, h("b", null, title), h("span", { class: "at-row-sub mono" }, sub));
    const excursion = (v: number | undefined): HTMLElement => h("td", { class: "c-metric num" }, v === undefined ? "—" : String(v));
    const metrics = h(
      "div",
      { class: "at-card at-predicted" },
      h("div", { class: "at-card-title" }, "Predicted on the model", h("span", { class: "at-card-sub" }, " — same metrics as the runs table; colours: proposed vs now")),
      h(
        "div",
        { class: "at-table-scroll" },
        h(
          "table",
          { class: "bench-table at-metrics", testid: "at-predicted" },
          h("thead", null, h("tr", null, h("th", { class: "at-row-label" }, ""), metricHeads(cols), h("th", { class: "c-metric", title: "Largest distance from the start, predicted (counts)" }, h("span", null, "travel"), h("span", { class: "th-unit" }, "counts")))),
          h(
            "tbody",
            null,
            h(
              "tr",
              { "data-row": "current" },
              rowLabel("now", gainsText(p.current_gains)),
              cols.map((c) => metricCell(c, p.predicted_default, null, `at-predicted-current-${c.key}`, null)),
              excursion(p.default_excursion),
            ),
            h(
              "tr",
              { "data-row": "proposed", class: "at-proposed-row" },
              rowLabel("proposed", gainsText(p.gains)),
              cols.map((c) => metricCell(c, p.predicted, p.predicted_default, `at-predicted-proposed-${c.key}`, null, "the gains in use")),
              excursion(p.predicted_excursion),
            ),
          ),
        ),
      ),
      h(
        "div",
        { class: "at-sub" },
        [
          p.predicted_peak_pwm !== undefined ? `peak PWM ${p.predicted_peak_pwm}` : "",
          p.travel_counts !== undefined ? `identification travelled ${p.travel_counts} counts` : "",
          p.candidates !== undefined ? `${p.candidates} candidates, ${p.simulations ?? "?"} robustness simulations` : "",
          p.design
            ? Object.entries(p.design)
                .filter(([k, v]) => k !== "unchanged" && (typeof v !== "object" || v === null))
                .map(([k, v]) => `${k} ${typeof v === "number" ? num(v) : String(v)}`)
                .join(", ")
            : "",
        ]
          .filter(Boolean)
          .join(" · "),
      ),
    );
    const ruleText = h("p", { class: "at-rule-text", title: "Click to show all / less" }, p.rule);
    ruleText.addEventListener("click", () => ruleText.classList.toggle("expanded"));
    const rule = h(
      "div",
      { class: "at-card at-rule", testid: "at-rule" },
      h("div", { class: "at-card-title" }, "Rule", h("span", { class: "at-card-sub" }, ` — ${p.response ? GOALS[p.response]?.label ?? p.response : ""}`)),
      ruleText,
    );
    // A proposal is decided once (kept, or accepted and verified): Identify gives a new
    // one. The recommended action is the primary button and comes first; the other is
    // the explicit alternative ("Write proposal anyway" when keeping is recommended).
    const rec = p.recommendation;
    const keepFirst = rec?.action === "keep";
    const writeTitle = "Run a baseline test with the gains in use, write the proposed gains (validated, read back), run the same test again. The axis moves; STOP / Esc stops.";
    const acceptButton = h(
      "button",
      { class: `btn ${keepFirst ? "warn" : "primary"}`, testid: "at-accept", "data-default": keepFirst ? "0" : "1", disabled: busy, title: writeTitle, onclick: () => void this.accept() },
      keepFirst ? "Write proposal anyway" : "Accept and verify",
    );
    const keepButton = h(
      "button",
      {
        class: `btn ${keepFirst ? "primary" : ""}`,
        testid: "at-keep",
        "data-default": keepFirst ? "1" : "0",
        disabled: busy,
        title: "Decline the proposal: the gains in use stay, nothing is written to the device (the decision is recorded with the identification run)",
        onclick: () => void this.keep(),
      },
      "Keep current gains",
    );
    const decided = this.result !== null || this.decision !== null;
    const buttons = decided ? [] : keepFirst ? [keepButton, acceptButton] : [acceptButton, keepButton];
    const recommendation =
      rec && !decided
        ? h(
            "div",
            { class: `at-recommend r-${rec.action}`, testid: "at-recommendation", "data-action": rec.action, role: "note" },
            h("b", null, rec.action === "keep" ? "Recommended: keep the gains in use" : "Recommended: write the proposal"),
            ` — ${rec.reason}`,
          )
        : null;
    const noBaseline = p.baseline_possible === false;
    const distance = p.test?.distance;
    const attempts = p.identification_run_ids?.length ?? 1;
    return h(
      "div",
      { class: "at-proposal", testid: "at-proposal", "data-run": p.identification_run_id },
      (p.warnings ?? []).map((w) => h("div", { class: "at-warning", testid: "at-warning", role: "note" }, h("b", null, "⚠ "), w)),
      attempts > 1 ? h("div", { class: "at-sub" }, `identified in ${attempts} attempts (runs ${(p.identification_run_ids ?? []).map((id) => `#${id.slice(0, 4)}`).join(", ")})`) : null,
      // The comparison, the recommendation and the buttons together (the decision's
      // view); the full predicted metrics and the rule's text below them.
      h("div", { class: "at-grid" }, this.compareView(p), gains, model),
      recommendation,
      h(
        "div",
        { class: "at-actions" },
        ...buttons,
        h(
          "span",
          { class: `at-hint${noBaseline && !decided ? " warn" : ""}` },
          this.result
            ? "Accepted and verified (below). Identify again for a new proposal."
            : this.decision
            ? ""
            : noBaseline
            ? `The gains in use are predicted to travel ${p.default_excursion ?? "?"} counts, beyond your distance limit: the baseline test is skipped, only the verification runs.`
            : `${keepFirst ? "Writing moves" : "Moves"} the axis: a baseline test with the gains in use, then the same test with the proposed gains${distance !== undefined ? ` (${distance} counts each)` : ""}.`,
        ),
      ),
      this.decisionView(),
      // Once verified, the result table repeats the predictions next to the measurements.
      this.result ? null : metrics,
      h("div", { class: "at-grid" }, rule),
    );
  }

  private resultView(p: AutoTuneProposal, r: AutoTuneResult, cols: MetricColumn[], busy: boolean): HTMLElement {
    const previous = r.previous_gains ?? p.current_gains;
    const proposed = r.gains ?? p.gains;
    const verdict = r.verdict ?? "unknown";
    const rowLabel = (title: string, sub: string, run: string | null): HTMLElement =>
      h("td", { class: "at-row-label", title: run ? `run ${run}` : "" }, h("b", null, title), h("span", { class: "at-row-sub mono" }, sub));
    const rows = [
      h(
        "tr",
        { "data-row": "proposed-predicted" },
        rowLabel("proposed · predicted", gainsText(proposed), null),
        cols.map((c) => metricCell(c, r.predicted, null, `at-result-predicted-${c.key}`, null)),
      ),
      h(
        "tr",
        { "data-row": "proposed-measured", class: "at-proposed-row", "data-run": r.verification_run_id },
        rowLabel("proposed · measured", `run #${r.verification_run_id.slice(0, 4)}`, r.verification_run_id),
        cols.map((c) => metricCell(c, measuredMetrics(r.measured), r.baseline_measured ?? null, `at-result-measured-${c.key}`, null, "the baseline run")),
      ),
      h(
        "tr",
        { "data-row": "previous-predicted" },
        rowLabel("before · predicted", gainsText(previous), null),
        cols.map((c) => metricCell(c, r.predicted_default ?? p.predicted_default, null, `at-result-previous-predicted-${c.key}`, null)),
      ),
      h(
        "tr",
        { "data-row": "previous-measured", "data-run": r.baseline_run_id ?? "" },
        rowLabel("before · measured", r.baseline_run_id ? `baseline run #${r.baseline_run_id.slice(0, 4)}` : "no baseline run", r.baseline_run_id),
        cols.map((c) => metricCell(c, r.baseline_measured ?? null, null, `at-result-baseline-${c.key}`, null)),
      ),
    ];
    const ids = [r.baseline_run_id, r.verification_run_id].filter((id): id is string => !!id);
    return h(
      "div",
      { class: "at-result", testid: "at-result", "data-verdict": verdict },
      h(
        "div",
        { class: "at-result-head" },
        h("span", { class: "at-card-title" }, "Verification"),
        h("span", { class: `at-verdict v-${verdict.replace(/\s+/g, "-")}`, testid: "at-verdict", title: "Measured settling (and overshoot) of the verification run against the baseline run" }, verdict),
        r.verdict_reason ? h("span", { class: "at-hint", testid: "at-verdict-reason" }, r.verdict_reason) : null,
        r.baseline_note ? h("span", { class: "at-hint warn" }, r.baseline_note) : null,
        h("span", { class: "tb-spacer" }),
        h("button", { class: "btn small", testid: "at-show-runs", title: "Select the baseline and verification runs in the overlay", onclick: () => void this.host.showRuns(ids) }, "Show both runs"),
        h(
          "button",
          {
            class: "btn small warn",
            testid: "at-revert",
            disabled: busy,
            title: `Write back the gains in use before: ${gainsText(previous)}`,
            onclick: () => void this.revert(),
          },
          `Revert to ${gainsText(previous)}`,
        ),
      ),
      h(
        "div",
        { class: "at-table-scroll" },
        h("table", { class: "bench-table at-metrics", testid: "at-result-table" }, h("thead", null, h("tr", null, h("th", { class: "at-row-label" }, ""), metricHeads(cols))), h("tbody", null, rows)),
      ),
      h("div", { class: "at-sub" }, "Colours of the measured row: the verification run against the baseline run. The proposed gains stay on the device (not persisted in it)."),
    );
  }
}
