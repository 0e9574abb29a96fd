// The bench's test form: the test kind and its one size field (distance, velocity or
// PWM, in the unit the bench info gives), duration, note, the Run button, the live run
// line and the error callout; the user's limits below it (limits.ts).
import { ApiError, api, type BenchInfo, type BenchKind, type BenchLimits, type BenchRun, type BenchTestRequest } from "../../api";
import { h, replace, setText, toggleClass } from "../../dom";
import { store } from "../../store";
import type { Conversion, DeviceDescriptor, RunUpdate } from "../../schema.gen";
import { errorText, statusLabel } from "../feedback";
import { type FieldName, KINDS, type Units, shortId } from "./kinds";
import { LimitsEditor } from "./limits";

interface FormValues {
  kind: BenchKind | null;
  distance: string;
  velocity: string;
  pwm: string;
  duration: string;
  note: string;
}

// Kept across view toggles and axis switches (like the command arguments).
const forms = new Map<string, FormValues>();

export interface FormHost {
  info(): BenchInfo | null;
  runs(): BenchRun[];
  /** The server took the test: ``run`` is recording. */
  started(run: BenchRun): void;
  limitsSaved(limits: BenchLimits): void;
}

export class BenchForm {
  readonly el: HTMLElement;
  private readonly form: FormValues;
  private readonly fieldWraps = new Map<string, HTMLElement>();
  private readonly inputs = new Map<string, HTMLInputElement | HTMLSelectElement>();
  private readonly hints = new Map<string, HTMLElement>();
  private kindHelp: HTMLElement | null = null;
  private runButton: HTMLButtonElement | null = null;
  private readonly progress: HTMLElement;
  private readonly error: HTMLElement;
  private readonly limits: LimitsEditor;
  private starting = false;

  constructor(
    private readonly axisId: string,
    private readonly descriptor: DeviceDescriptor,
    private readonly units: Units,
    private readonly conversions: Record<FieldName, Conversion[]>,
    private readonly host: FormHost,
  ) {
    this.form = forms.get(axisId) ?? { kind: null, distance: "4000", velocity: "2000", pwm: "30", duration: "2", note: "" };
    forms.set(axisId, this.form);
    const pwmArg = descriptor.commands.flatMap((c) => c.arguments).find((a) => a.name === "pwm");
    if (pwmArg && !this.form.pwm) this.form.pwm = String(pwmArg.default);
    this.progress = h("div", { class: "bench-progress", testid: "bench-progress", "aria-live": "polite" });
    this.error = h("div", { class: "bench-error", testid: "bench-error", role: "alert", hidden: true });
    this.limits = new LimitsEditor(axisId, {
      info: () => host.info(),
      clearError: () => this.clearError(),
      showError: (error, field) => this.showError(error, field),
      validate: () => this.validate(),
      saved: (limits) => host.limitsSaved(limits),
    });
    this.el = h("div", { class: "bench-form" }, h("div", { class: "bench-loading" }, "Loading the bench …"));
  }

  /** The bench info could not be loaded: say so, with a retry. */
  showLoadError(error: unknown, retry: () => void): void {
    replace(
      this.el,
      h(
        "div",
        { class: "bench-loading error" },
        `Cannot load the bench: ${statusLabel(error)} — ${errorText(error)} `,
        h("button", { class: "btn small", onclick: retry }, "Retry"),
      ),
    );
  }

  /** (Re)build the form for the bench info now (kinds, limits, units). */
  render(): void {
    const info = this.host.info() as BenchInfo;
    if (!info.kinds.length) {
      replace(
        this.el,
        h(
          "div",
          { class: "bench-unsupported", testid: "bench-unsupported" },
          h("b", null, "No bench tests for this device yet."),
          ` The ${this.descriptor.model} driver does not plan bench tests; stored or imported runs are listed below.`,
        ),
        this.progress,
      );
      return;
    }
    // The frequency response has its own form (ui/bode.ts).
    const formKinds = info.kinds.filter((k): k is BenchKind => k in KINDS && k !== "frequency_response");
    if (!this.form.kind || !formKinds.includes(this.form.kind)) this.form.kind = formKinds[0] as BenchKind;
    const kind = h(
      "select",
      { class: "input", testid: "bench-kind", "aria-label": "Test kind" },
      formKinds.map((k) => h("option", { value: k, title: KINDS[k]?.help ?? k }, KINDS[k]?.label ?? k)),
    );
    kind.value = this.form.kind;
    kind.addEventListener("change", () => {
      this.form.kind = kind.value as BenchKind;
      this.clearError();
      this.syncKind();
    });
    this.inputs.set("kind", kind);

    const numberField = (name: string, label: string, unit: string, step: string, title: string): HTMLElement => {
      const key = name === "duration_s" ? "duration" : name;
      const input = h("input", {
        class: "input num",
        type: "number",
        step,
        value: this.form[key as keyof FormValues] ?? "",
        testid: `bench-${key}`,
        title,
        "aria-label": label,
      });
      input.addEventListener("input", () => {
        (this.form as unknown as Record<string, string>)[key] = input.value;
        input.classList.remove("server-invalid");
        this.syncHints();
        this.validate();
      });
      input.addEventListener("keydown", (event) => {
        if (event.key === "Enter") {
          event.preventDefault();
          void this.start();
        }
      });
      this.inputs.set(name, input);
      const hint = h("span", { class: "bf-hint" });
      this.hints.set(name, hint);
      const wrap = h(
        "label",
        { class: "bf", "data-field": name },
        h("span", { class: "bf-label" }, label),
        h("span", { class: "bf-control" }, input, unit ? h("span", { class: "unit" }, unit) : null, hint),
      );
      this.fieldWraps.set(name, wrap);
      return wrap;
    };
    const distance = numberField("distance", "Distance", this.units.distance, "1", "Relative distance of the move, signed (device units)");
    const velocity = numberField("velocity", "Velocity", this.units.velocity, "1", "Commanded velocity, signed (device units)");
    const pwm = numberField("pwm", "PWM", this.units.pwm || "duty", "1", "Open-loop PWM duty, signed");
    const duration = numberField("duration_s", "Duration", "s", "0.1", "Longest recording after the trigger; position tests end earlier once settled in position");
    const note = h("input", {
      class: "input bf-note",
      type: "text",
      maxlength: 200,
      value: this.form.note,
      placeholder: "what changed, e.g. kp 40 → 80",
      testid: "bench-note",
      "aria-label": "Note",
    });
    note.addEventListener("input", () => (this.form.note = note.value));
    note.addEventListener("keydown", (event) => {
      if (event.key === "Enter") {
        event.preventDefault();
        void this.start();
      }
    });
    this.inputs.set("note", note);
    const noteWrap = h("label", { class: "bf bf-grow", "data-field": "note" }, h("span", { class: "bf-label" }, "Note"), h("span", { class: "bf-control" }, note));
    this.fieldWraps.set("note", noteWrap);
    const kindWrap = h("label", { class: "bf", "data-field": "kind" }, h("span", { class: "bf-label" }, "Test"), h("span", { class: "bf-control" }, kind));
    this.fieldWraps.set("kind", kindWrap);
    this.runButton = h(
      "button",
      { class: "btn primary bench-run", testid: "bench-run", title: "Run the test now (Enter in a field). STOP / Esc stops the axis.", onclick: () => void this.start() },
      "▶ Run test",
    );
    const runWrap = h("div", { class: "bf bf-run", "data-field": "run" }, this.runButton);
    this.fieldWraps.set("run", runWrap);
    this.kindHelp = h("span", { class: "bench-kind-help" });

    const limits = this.limits.render(info, this.units);
    replace(
      this.el,
      h("div", { class: "bench-form-row" }, kindWrap, distance, velocity, pwm, duration, noteWrap, runWrap),
      h("div", { class: "bench-form-sub" }, this.kindHelp, h("span", { class: "tb-spacer" }), this.progress),
      limits,
      this.error,
    );
    this.limits.fill(info.limits);
    this.syncKind();
    this.syncProgress(store.runs.get(this.axisId) ?? null);
  }

  private syncKind(): void {
    const kind = this.form.kind;
    if (!kind) return;
    const spec = KINDS[kind];
    for (const f of ["distance", "velocity", "pwm"] as const) {
      const wrap = this.fieldWraps.get(f);
      if (wrap) wrap.hidden = spec.field !== f;
    }
    if (this.kindHelp) setText(this.kindHelp, spec.help);
    this.syncHints();
    this.validate();
  }

  private syncHints(): void {
    for (const f of ["distance", "velocity"] as const) {
      const hint = this.hints.get(f);
      const value = Number(this.inputs.get(f)?.value);
      const conv = this.conversions[f][0];
      if (hint) setText(hint, conv && Number.isFinite(value) && value !== 0 ? `= ${(value * conv.factor).toFixed(conv.digits)} ${conv.unit}` : "");
    }
  }

  /** Client-side check against the limits (the server checks again and is authoritative). */
  validate(): void {
    const info = this.host.info();
    if (!info || !this.form.kind) return;
    const limits = info.limits;
    const field = KINDS[this.form.kind].field;
    const check = (name: string, limit: number, symmetric: boolean): void => {
      const input = this.inputs.get(name);
      if (!input) return;
      const v = Number(input.value);
      const bad = input.value.trim() === "" || !Number.isFinite(v) || (symmetric ? Math.abs(v) > limit : v > limit || v <= 0);
      toggleClass(input, "invalid", bad);
    };
    if (field === "distance") check("distance", limits.max_distance_counts, true);
    if (field === "velocity") check("velocity", limits.max_velocity, true);
    if (field === "pwm") check("pwm", limits.max_pwm, true);
    check("duration_s", limits.max_duration_s, false);
  }

  private request(): BenchTestRequest {
    const n = (name: string): number => {
      const v = Number(this.inputs.get(name)?.value ?? "0");
      return Number.isFinite(v) ? v : 0;
    };
    const kind = this.form.kind as BenchKind;
    const field = KINDS[kind].field;
    return {
      kind,
      distance: field === "distance" ? Math.round(n("distance")) : 0,
      velocity: field === "velocity" ? Math.round(n("velocity")) : 0,
      pwm: field === "pwm" ? Math.round(n("pwm")) : 0,
      duration_s: n("duration_s"),
      note: this.form.note.trim(),
    };
  }

  private async start(): Promise<void> {
    if (!this.runButton || this.runButton.disabled || this.starting || !this.form.kind) return;
    this.clearError();
    this.starting = true;
    this.syncRunButton();
    const test = this.request();
    try {
      const run = await api.startRun(this.axisId, test);
      const known = store.runs.get(this.axisId);
      if (!known || known.run_id !== run.id) {
        this.syncProgress({ type: "run", axis: this.axisId, run_id: run.id, status: "recording", elapsed_s: 0, samples: 0, message: "armed" });
      }
      this.host.started(run);
    } catch (error) {
      this.showError(error, "run");
    } finally {
      this.starting = false;
      this.syncRunButton();
    }
  }

  /** A run records on this axis, as far as the list and the ``run`` messages tell:
   * a run only ever goes from recording to finished, so "finished" in either wins. */
  private busy(): boolean {
    if (this.starting) return true;
    const recording = new Set<string>();
    const finished = new Set<string>();
    for (const run of this.host.runs()) (run.status === "recording" ? recording : finished).add(run.id);
    const msg = store.runs.get(this.axisId);
    if (msg) (msg.status === "recording" ? recording : finished).add(msg.run_id);
    return [...recording].some((id) => !finished.has(id));
  }

  syncRunButton(): void {
    if (!this.runButton) return;
    const busy = this.busy();
    this.runButton.disabled = busy;
    toggleClass(this.runButton, "recording", busy && !this.starting);
    setText(this.runButton, busy ? (this.starting ? "Starting …" : "● Recording") : "▶ Run test");
  }

  /** The server's (or the client's) refusal as a callout at the field it names. */
  showError(error: unknown, fallbackField: string): void {
    const field = error instanceof ApiError && error.field ? error.field : null;
    const wrap = (name: string): HTMLElement | undefined => this.fieldWraps.get(name) ?? this.limits.wraps.get(name);
    const target = (field && wrap(field)) || wrap(fallbackField) || wrap("run");
    const input = field ? this.inputs.get(field) ?? this.limits.input(field) : undefined;
    input?.classList.add("server-invalid");
    setText(this.error, `${statusLabel(error)}: ${errorText(error)}`);
    this.error.dataset.field = field ?? "";
    this.error.hidden = false;
    if (target) {
      target.appendChild(this.error);
      // Keep the callout inside the form: right-aligned under fields near the right edge.
      const host = this.el.getBoundingClientRect();
      const box = target.getBoundingClientRect();
      toggleClass(this.error, "align-right", box.left - host.left > host.width * 0.55);
    }
  }

  clearError(): void {
    this.error.hidden = true;
    setText(this.error, "");
    for (const input of [...this.inputs.values(), ...this.limits.allInputs()]) input.classList.remove("server-invalid");
  }

  /** The live line of the run recording on this axis (null: ready). */
  syncProgress(msg: RunUpdate | null): void {
    if (!msg) {
      setText(this.progress, "ready");
      this.progress.dataset.status = "idle";
      this.progress.title = "";
      return;
    }
    this.progress.dataset.status = msg.status;
    this.progress.dataset.run = msg.run_id;
    const id = shortId(msg.run_id);
    const stats = `${msg.elapsed_s.toFixed(1)} s · ${msg.samples} samples`;
    let text: string;
    if (msg.status === "recording") text = `● REC ${id} · ${stats}${msg.message && !/^\d/.test(msg.message) ? ` · ${msg.message}` : ""}`;
    // No ✓ here: whether the run is good is the table's verdict (quality), not "complete".
    else if (msg.status === "complete") text = `■ ${id} finished · ${stats}`;
    else text = `✗ ${id} incomplete · ${stats}${msg.message ? ` — ${msg.message}` : ""}`;
    setText(this.progress, text);
    this.progress.title = msg.message;
  }
}
