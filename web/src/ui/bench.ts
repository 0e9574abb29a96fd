// The tuning test bench of one axis: a test form (with the user's limits), the runs
// table with metrics, an overlay of the selected runs aligned at the trigger, and the
// parameters that differ between them. Progress comes from websocket ``run`` messages,
// so every browser sees a run appear and finish.
import {
  ApiError,
  api,
  runUrl,
  type BenchInfo,
  type BenchKind,
  type BenchLimits,
  type BenchRun,
  type BenchRunDetail,
  type BenchTestRequest,
} from "../api";
import { h, replace, setText, toggleClass } from "../dom";
import { clock } from "../format";
import { store } from "../store";
import type { Conversion, DeviceDescriptor, RunUpdate } from "../schema.gen";
import { AutoTunePanel } from "./autotune";
import { type Target, type Trace, Overlay, plotTheme, valueAt } from "./benchplot";
import { confirmDialog, errorText, statusLabel } from "./feedback";
import { type MetricColumn, metricCell, metricColumns, ms, num, qualityOf } from "./metriccols";
import { FrfPanel } from "./bode";
import { WhatIfPanel } from "./whatif";

/** The recorder arms this long before the trigger (servotune/bench/service.py PRE_TRIGGER_S). */
const PRE_TRIGGER_S = 0.2;
const MAX_SELECTED = 8;

type FieldName = "distance" | "velocity" | "pwm";

const KINDS: Record<BenchKind, { label: string; short: string; field: FieldName; help: string }> = {
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
const selections = new Map<string, string[]>(); // axis -> selected run ids, in selection order
const colors = new Map<string, number>(); // run id -> palette slot while selected
const details = new Map<string, Promise<BenchRunDetail>>(); // finished runs only

function loadSelection(axisId: string): string[] {
  let sel = selections.get(axisId);
  if (!sel) {
    try {
      sel = JSON.parse(localStorage.getItem(`servotune.bench.selected.${axisId}`) ?? "[]") as string[];
    } catch {
      sel = [];
    }
    selections.set(axisId, sel);
  }
  return sel;
}

function saveSelection(axisId: string, sel: string[]): void {
  selections.set(axisId, sel);
  try {
    localStorage.setItem(`servotune.bench.selected.${axisId}`, JSON.stringify(sel));
  } catch {
    /* private mode */
  }
}

function detail(run: BenchRun): Promise<BenchRunDetail> {
  const key = `${run.id}:${run.status}`;
  let promise = details.get(key);
  if (!promise) {
    promise = api.run(run.id);
    if (run.status === "recording") return promise; // still growing: never cached
    promise.catch(() => details.delete(key));
    details.set(key, promise);
  }
  return promise;
}

function palette(): string[] {
  const style = getComputedStyle(document.documentElement);
  const series = [1, 2, 3, 4, 5, 6].map((i) => style.getPropertyValue(`--series-${i}`).trim() || "#4cc2ff");
  const extra = [7, 8].map((i) => style.getPropertyValue(`--series-${i}`).trim() || (i === 7 ? "#ff8a5c" : "#9fb3c8"));
  return [...series, ...extra];
}

// --- formatting ----------------------------------------------------------------------

function shortId(id: string): string {
  return `#${id.slice(0, 4)}`;
}


function testSize(run: BenchRun, units: Record<FieldName, string>, withUnit = true): string {
  const field = KINDS[run.test.kind]?.field ?? "distance";
  const value = run.test[field];
  const unit = withUnit ? units[field] : "";
  return `${value > 0 && field === "distance" ? "+" : ""}${value}${unit ? ` ${unit}` : ""}`;
}

export class BenchView {
  readonly el: HTMLElement;
  private info: BenchInfo | null = null;
  private runs: BenchRun[] = [];
  private readonly descriptor: DeviceDescriptor;
  private readonly form: FormValues;
  // the device's channels until the bench info (``fields``) says what each field sets
  private units: Record<FieldName, string>;
  private conversions: Record<FieldName, Conversion[]>;
  private readonly formHost: HTMLElement;
  private readonly fieldWraps = new Map<string, HTMLElement>();
  private readonly inputs = new Map<string, HTMLInputElement | HTMLSelectElement>();
  private readonly hints = new Map<string, HTMLElement>();
  private kindHelp: HTMLElement | null = null;
  private runButton: HTMLButtonElement | null = null;
  private readonly progress: HTMLElement;
  private readonly error: HTMLElement;
  private readonly limitInputs = new Map<keyof BenchLimits, HTMLInputElement>();
  private limitsSave: HTMLButtonElement | null = null;
  private readonly limitsStatus: HTMLElement;
  // Only for devices the auto-tune assistant supports (descriptor.autotune).
  private readonly autotune: AutoTunePanel | null;
  private readonly response: Overlay;
  private readonly following: Overlay;
  private readonly responseTitle: HTMLElement;
  private readonly responseNote: HTMLElement;
  private readonly feTitle: HTMLElement;
  private readonly legend: HTMLElement;
  private readonly fePanel: HTMLElement;
  private readonly table: HTMLTableElement;
  private readonly runsTitle: HTMLElement;
  private readonly diff: HTMLElement;
  private readonly importInput: HTMLInputElement;
  private readonly importStatus: HTMLElement;
  private pendingImport: { json?: File; csv?: File } = {};
  private readonly storageBanner: HTMLElement;
  private traces: { trace: Trace; run: BenchRun; label: string; legendValue: HTMLElement }[] = [];
  private starting = false;
  private refreshing: Promise<void> | null = null;
  private refreshAgain = false;
  private finished = new Set<string>(); // runs that finished while we watched: select them
  private drawToken = 0;
  // Issue 9: the frequency-response and what-if panels (ui/bode.ts, ui/whatif.ts).
  private frf: FrfPanel | null = null;
  private whatif: WhatIfPanel | null = null;
  private readonly extras: HTMLElement;

  constructor(
    private readonly axisId: string,
    descriptor: DeviceDescriptor,
    private readonly signal: AbortSignal,
  ) {
    this.descriptor = descriptor;
    this.form = forms.get(axisId) ?? { kind: null, distance: "4000", velocity: "2000", pwm: "30", duration: "2", note: "" };
    forms.set(axisId, this.form);
    const position = descriptor.channels.find((c) => c.name === "position");
    const velocityChannel = descriptor.channels.find((c) => c.name === "velocity");
    const pwmArg = descriptor.commands.flatMap((c) => c.arguments).find((a) => a.name === "pwm");
    this.units = {
      distance: position?.unit ?? "counts",
      velocity: velocityChannel?.unit ?? "",
      pwm: pwmArg?.unit ?? "",
    };
    this.conversions = {
      distance: position?.conversions ?? [],
      velocity: velocityChannel?.conversions ?? [],
      pwm: [],
    };
    if (pwmArg && !this.form.pwm) this.form.pwm = String(pwmArg.default);

    this.progress = h("div", { class: "bench-progress", testid: "bench-progress", "aria-live": "polite" });
    this.error = h("div", { class: "bench-error", testid: "bench-error", role: "alert", hidden: true });
    this.limitsStatus = h("span", { class: "bench-limits-status" });
    this.formHost = h("div", { class: "bench-form" }, h("div", { class: "bench-loading" }, "Loading the bench …"));

    const theme = plotTheme();
    const responseUnit = (): string => this.responseUnit();
    this.response = new Overlay("bench-overlay", `bench-${axisId}`, theme, responseUnit);
    this.following = new Overlay("bench-overlay-fe", `bench-${axisId}`, theme, () => this.channelUnit("following_error"));
    this.response.onZoom = (range) => this.following.setX(range);
    this.following.onZoom = (range) => this.response.setX(range);
    this.response.onCursor = (x) => this.cursor(x);
    this.following.onCursor = (x) => this.cursor(x);
    this.responseTitle = h("span", { class: "plot-title" }, "Response");
    this.responseNote = h("span", { class: "bench-plot-note" });
    this.feTitle = h("span", { class: "plot-title" }, "Following error");
    this.legend = h("div", { class: "bench-legend" });
    this.fePanel = h(
      "div",
      { class: "bench-plot fe" },
      h("div", { class: "bench-plot-header" }, this.feTitle, h("span", { class: "plot-unit" }, this.channelUnit("following_error"))),
      this.following.el,
    );
    const plots = h(
      "section",
      { class: "bench-plots" },
      h(
        "div",
        { class: "bench-plot response" },
        h(
          "div",
          { class: "bench-plot-header" },
          this.responseTitle,
          this.responseNote,
          h("span", { class: "tb-spacer" }),
          h("span", { class: "tb-hint" }, "aligned at the trigger t0 · drag to zoom · double-click: whole run"),
        ),
        this.legend,
        this.response.el,
      ),
      this.fePanel,
    );

    this.table = h("table", { class: "bench-table", testid: "bench-runs" });
    this.runsTitle = h("span", { class: "pane-sub" });
    this.importInput = h("input", {
      type: "file",
      multiple: true,
      accept: ".json,.csv,application/json,text/csv",
      testid: "bench-import-file",
      hidden: true,
    });
    this.importInput.addEventListener("change", () => void this.importFiles());
    this.importStatus = h("span", { class: "bench-import-status", testid: "bench-import-status" });
    const importButton = h(
      "button",
      {
        class: "btn small",
        testid: "bench-import",
        title: "Import a run exported from servotune: pick its .json and its .csv (both at once, or one after the other)",
        onclick: () => this.importInput.click(),
      },
      "Import…",
    );
    this.diff = h("div", { class: "bench-diff", testid: "bench-param-diff" });
    const runsPane = h(
      "section",
      { class: "bench-runs-pane" },
      h(
        "div",
        { class: "pane-header" },
        h("span", { class: "pane-title" }, "Runs"),
        this.runsTitle,
        h("span", { class: "tb-spacer" }),
        this.importStatus,
        importButton,
        this.importInput,
      ),
      h("div", { class: "bench-table-scroll" }, this.table),
      h("div", { class: "bench-diff-pane" }, this.diff),
    );

    this.autotune = descriptor.autotune
      ? new AutoTunePanel(
          axisId,
          descriptor,
          {
            columns: (metrics) => metricColumns(this.descriptor, [...this.runs.map((r) => r.metrics), ...metrics]),
            showRuns: (ids) => this.showRuns(ids),
            // the what-if view is built on the identified model: reload it
            modelChanged: () => void this.whatif?.load(),
            // a decision was written onto the identification run (its note)
            runsChanged: () => void this.refresh(),
          },
          signal,
        )
      : null;
    this.storageBanner = h("div", { class: "banner-slot", testid: "storage-banner-slot" });
    this.extras = h("div", { class: "bench-extras" });
    // The runs right below their overlay: they are what the overlay draws.
    this.el = h("div", { class: "bench", "data-axis": axisId }, this.storageBanner, this.formHost, ...(this.autotune ? [this.autotune.el] : []), plots, runsPane, this.extras);
    store.on("storage", (msg) => this.showStorage(msg.writable, msg.message), signal);
    void fetch("/api/storage", { signal })
      .then((r) => (r.ok ? (r.json() as Promise<{ writable: boolean; message: string }>) : null))
      .then((st) => st && this.showStorage(st.writable, st.message))
      .catch(() => undefined);

    store.on("run", (msg) => msg.axis === axisId && this.onRun(msg), signal);
    // Runs may have started or finished while the websocket was down.
    store.on("ws", (state) => state.kind === "open" && this.info !== null && void this.refresh(), signal);
    signal.addEventListener(
      "abort",
      () => {
        this.response.destroy();
        this.following.destroy();
      },
      { once: true },
    );
    void this.load();
  }

  // --- loading ------------------------------------------------------------------------

  private async load(): Promise<void> {
    try {
      this.info = await api.bench(this.axisId);
    } catch (error) {
      replace(
        this.formHost,
        h(
          "div",
          { class: "bench-loading error" },
          `Cannot load the bench: ${statusLabel(error)} — ${errorText(error)} `,
          h("button", { class: "btn small", onclick: () => void this.load() }, "Retry"),
        ),
      );
      return;
    }
    if (this.signal.aborted) return;
    for (const [name, field] of Object.entries(this.info.fields)) {
      if (!(name in this.units)) continue;
      this.units[name as FieldName] = field.unit;
      this.conversions[name as FieldName] = field.conversions;
    }
    this.renderForm();
    this.autotune?.setLimits(this.info.limits);
    if (this.info.whatif && !this.whatif) {
      const axisId = this.axisId;
      this.whatif = new WhatIfPanel(axisId, async (distance, kind) => {
        const run = await api.startRun(axisId, { kind, distance, velocity: 0, pwm: 0, duration_s: 2, note: "what-if verification" });
        this.finished.add(run.id);
        await this.refresh();
        return run.id;
      });
      this.extras.append(this.whatif.el);
    }
    if (this.info.frequency_response && !this.frf) {
      this.frf = new FrfPanel(this.axisId, this.info.frequency_response === "measured", (id) => {
        this.finished.add(id);
        void this.refresh();
      });
      this.extras.prepend(this.frf.el);
    }
    void this.whatif?.load();
    await this.refresh();
  }

  /** Re-read the runs list (coalesced: one request in flight, one queued). */
  refresh(): Promise<void> {
    if (this.refreshing) {
      this.refreshAgain = true;
      return this.refreshing;
    }
    this.refreshing = (async () => {
      do {
        this.refreshAgain = false;
        try {
          this.runs = await api.runs(this.axisId);
        } catch (error) {
          setText(this.runsTitle, `cannot list the runs: ${errorText(error)}`);
          break;
        }
        if (this.signal.aborted) return;
        this.reconcileSelection();
        this.renderRuns();
        this.syncRunButton();
        void this.draw();
      } while (this.refreshAgain);
    })().finally(() => {
      this.refreshing = null;
    });
    return this.refreshing;
  }

  private selected(): string[] {
    return loadSelection(this.axisId);
  }

  private reconcileSelection(): void {
    const ids = new Set(this.runs.map((r) => r.id));
    let sel = this.selected().filter((id) => ids.has(id));
    const first = !selections.has(this.axisId) || sel.length === 0;
    for (const id of this.finished) {
      if (ids.has(id) && !sel.includes(id)) sel.push(id);
    }
    this.finished.clear();
    if (first && sel.length === 0) {
      // First look: the baseline and the latest finished run.
      const baseline = this.runs.find((r) => r.baseline);
      const latest = [...this.runs].reverse().find((r) => r.status !== "recording");
      sel = [baseline?.id, latest?.id].filter((id): id is string => !!id).filter((id, i, a) => a.indexOf(id) === i);
    }
    sel = this.capSelection(sel);
    saveSelection(this.axisId, sel);
    this.assignColors(sel);
  }

  private capSelection(sel: string[]): string[] {
    const baseline = this.runs.find((r) => r.baseline)?.id;
    while (sel.length > MAX_SELECTED) {
      const drop = sel.findIndex((id) => id !== baseline);
      sel.splice(drop < 0 ? 0 : drop, 1);
    }
    return sel;
  }

  private assignColors(sel: string[]): void {
    const slots = palette().length;
    const used = new Set<number>();
    for (const id of sel) {
      const slot = colors.get(id);
      if (slot !== undefined && !used.has(slot)) used.add(slot);
      else colors.delete(id);
    }
    for (const id of sel) {
      if (colors.has(id)) continue;
      let slot = 0;
      while (used.has(slot) && slot < slots - 1) slot++;
      used.add(slot);
      colors.set(id, slot);
    }
  }

  private color(id: string): string {
    const p = palette();
    return p[(colors.get(id) ?? 0) % p.length] as string;
  }

  // --- the form -----------------------------------------------------------------------

  private renderForm(): void {
    const info = this.info as BenchInfo;
    if (!info.kinds.length) {
      replace(
        this.formHost,
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
    const formKinds: BenchKind[] = info.kinds.filter((k) => k !== "frequency_response");
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

    const limitField = (key: keyof BenchLimits, label: string, unit: string, step: string): HTMLElement => {
      const input = h("input", {
        class: "input num small",
        type: "number",
        step,
        min: 0,
        testid: `bench-limit-${key}`,
        "aria-label": label,
        title: `${label}: every test on this axis is checked against it before anything moves`,
      });
      input.addEventListener("input", () => {
        input.classList.remove("server-invalid");
        this.syncLimitsDirty();
      });
      input.addEventListener("keydown", (event) => {
        if (event.key === "Enter") {
          event.preventDefault();
          void this.saveLimits();
        }
      });
      this.limitInputs.set(key, input);
      const wrap = h("label", { class: "bl", "data-field": key }, h("span", { class: "bl-label" }, label), input, unit ? h("span", { class: "unit" }, unit) : null);
      this.fieldWraps.set(key, wrap);
      return wrap;
    };
    this.limitsSave = h("button", { class: "btn small", testid: "bench-limits-save", onclick: () => void this.saveLimits() }, "Save");
    const limits = h(
      "div",
      { class: "bench-limits", title: "Your limits for this axis: a test beyond them is refused before anything moves" },
      h("span", { class: "tb-label" }, "Limits"),
      limitField("max_distance_counts", "distance ±", this.units.distance, "1"),
      info.kinds.includes("velocity_step") ? limitField("max_velocity", "velocity ±", this.units.velocity, "1") : null,
      info.kinds.includes("pwm_step") ? limitField("max_pwm", "pwm ±", "", "1") : null,
      limitField("max_duration_s", "duration ≤", "s", "0.5"),
      this.limitsSave,
      this.limitsStatus,
    );
    replace(
      this.formHost,
      h("div", { class: "bench-form-row" }, kindWrap, distance, velocity, pwm, duration, noteWrap, runWrap),
      h("div", { class: "bench-form-sub" }, this.kindHelp, h("span", { class: "tb-spacer" }), this.progress),
      limits,
      this.error,
    );
    this.fillLimits(info.limits);
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

  private fillLimits(limits: BenchLimits): void {
    for (const [key, input] of this.limitInputs) input.value = String(limits[key]);
    this.syncLimitsDirty();
    this.validate();
  }

  private readLimits(): BenchLimits {
    const current = (this.info as BenchInfo).limits;
    const value = (key: keyof BenchLimits): number => {
      const input = this.limitInputs.get(key);
      return input ? Number(input.value) : current[key];
    };
    return {
      max_distance_counts: value("max_distance_counts"),
      max_velocity: value("max_velocity"),
      max_pwm: value("max_pwm"),
      max_duration_s: value("max_duration_s"),
    };
  }

  private syncLimitsDirty(): void {
    if (!this.info || !this.limitsSave) return;
    const shown = this.readLimits();
    const dirty = (Object.keys(shown) as (keyof BenchLimits)[]).some((k) => shown[k] !== this.info?.limits[k]);
    this.limitsSave.disabled = !dirty;
    toggleClass(this.limitsSave, "warn", dirty);
    if (dirty) setText(this.limitsStatus, "not saved");
  }

  private async saveLimits(): Promise<void> {
    if (!this.info || !this.limitsSave) return;
    this.clearError();
    this.limitsSave.classList.add("busy");
    try {
      const saved = await api.setBenchLimits(this.axisId, this.readLimits());
      this.info.limits = saved;
      this.fillLimits(saved);
      this.autotune?.setLimits(saved);
      setText(this.limitsStatus, "✓ saved");
    } catch (error) {
      this.showError(error, "max_distance_counts");
      setText(this.limitsStatus, "");
    } finally {
      this.limitsSave.classList.remove("busy");
    }
  }

  /** Client-side check against the limits (the server checks again and is authoritative). */
  private validate(): void {
    if (!this.info || !this.form.kind) return;
    const limits = this.info.limits;
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
      if (!this.runs.some((r) => r.id === run.id)) this.runs.push(run);
      this.finished.add(run.id);
      const known = store.runs.get(this.axisId);
      if (!known || known.run_id !== run.id) {
        this.syncProgress({ type: "run", axis: this.axisId, run_id: run.id, status: "recording", elapsed_s: 0, samples: 0, message: "armed" });
      }
      this.renderRuns();
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
    for (const run of this.runs) (run.status === "recording" ? recording : finished).add(run.id);
    const msg = store.runs.get(this.axisId);
    if (msg) (msg.status === "recording" ? recording : finished).add(msg.run_id);
    return [...recording].some((id) => !finished.has(id));
  }

  private syncRunButton(): void {
    if (!this.runButton) return;
    const busy = this.busy();
    this.runButton.disabled = busy;
    toggleClass(this.runButton, "recording", busy && !this.starting);
    setText(this.runButton, busy ? (this.starting ? "Starting …" : "● Recording") : "▶ Run test");
  }

  private showError(error: unknown, fallbackField: string): void {
    const field = error instanceof ApiError && error.field ? error.field : null;
    const target = (field && this.fieldWraps.get(field)) || this.fieldWraps.get(fallbackField) || this.fieldWraps.get("run");
    const input = field ? this.inputs.get(field) ?? this.limitInputs.get(field as keyof BenchLimits) : undefined;
    input?.classList.add("server-invalid");
    setText(this.error, `${statusLabel(error)}: ${errorText(error)}`);
    this.error.dataset.field = field ?? "";
    this.error.hidden = false;
    if (target) {
      target.appendChild(this.error);
      // Keep the callout inside the form: right-aligned under fields near the right edge.
      const host = this.formHost.getBoundingClientRect();
      const box = target.getBoundingClientRect();
      toggleClass(this.error, "align-right", box.left - host.left > host.width * 0.55);
    }
  }

  private clearError(): void {
    this.error.hidden = true;
    setText(this.error, "");
    for (const input of [...this.inputs.values(), ...this.limitInputs.values()]) input.classList.remove("server-invalid");
  }

  // --- progress -----------------------------------------------------------------------

  private onRun(msg: RunUpdate): void {
    this.syncProgress(msg);
    const known = this.runs.find((r) => r.id === msg.run_id);
    if (msg.status !== "recording") {
      this.finished.add(msg.run_id);
      this.whatif?.runEnded(msg.run_id, msg.status, msg.message);
      void this.whatif?.load(); // an identification may have given a new model
    }
    if (known && msg.status === "recording") {
      known.status = "recording";
      const cell = this.table.querySelector<HTMLElement>(`[data-status-of="${msg.run_id}"]`);
      if (cell) setText(cell, `● rec ${msg.elapsed_s.toFixed(1)} s`);
      this.syncRunButton();
      return;
    }
    this.syncRunButton();
    void this.refresh();
  }

  private syncProgress(msg: RunUpdate | null): void {
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

  // --- runs table ---------------------------------------------------------------------

  private metricColumns(): MetricColumn[] {
    return metricColumns(this.descriptor, this.runs.map((r) => r.metrics));
  }

  private renderRuns(): void {
    const cols = this.metricColumns();
    const sel = this.selected();
    const baseline = this.runs.find((r) => r.baseline) ?? null;
    const head = h(
      "thead",
      null,
      h(
        "tr",
        null,
        h("th", { class: "c-sel", title: "Show in the overlay (up to 8)" }, ""),
        h("th", { class: "c-star", title: "Baseline: the reference run — metric colours and the parameter diff compare with it" }, "★"),
        h("th", { class: "c-run" }, h("span", null, "run"), h("span", { class: "th-unit" }, "time")),
        h("th", { class: "c-test" }, h("span", null, "test"), h("span", { class: "th-unit" }, "changed vs ★")),
        h("th", { class: "c-status", title: "✓ complete and good · ⚠ doubtful · ✗ bad or incomplete (the reasons under the test) · ● recording" }, "st"),
        cols.map((c) =>
          h(
            "th",
            { class: "c-metric", title: `${c.label} [${c.unit}]\n${c.help}`, "data-metric": c.key },
            h("span", null, c.label),
            h("span", { class: "th-unit" }, c.unit),
          ),
        ),
        h("th", { class: "c-actions", title: "Export (CSV samples, JSON run) · delete" }, "export"),
      ),
    );
    const body = h("tbody");
    const ordered = [...this.runs].reverse(); // newest first
    for (const run of ordered) body.appendChild(this.runRow(run, cols, sel, baseline));
    if (!ordered.length) {
      body.appendChild(
        h(
          "tr",
          { class: "bench-empty-row" },
          h("td", { colspan: 6 + cols.length }, this.info?.kinds.length ? "No runs yet: choose a test above and press Run test." : "No runs."),
        ),
      );
    }
    const scroller = this.table.parentElement;
    const scroll = scroller?.scrollTop ?? 0;
    replace(this.table, head, body);
    if (scroller) scroller.scrollTop = scroll;
    const recording = this.runs.filter((r) => r.status === "recording").length;
    setText(this.runsTitle, `${this.runs.length} stored · ${sel.length} selected${recording ? ` · ${recording} recording` : ""} · metric colours: better / worse than ★`);
    this.renderDiff();
  }

  private runRow(run: BenchRun, cols: MetricColumn[], sel: string[], baseline: BenchRun | null): HTMLElement {
    const selected = sel.includes(run.id);
    const check = h("input", {
      type: "checkbox",
      checked: selected,
      testid: `bench-run-select-${run.id}`,
      "aria-label": `Show run ${shortId(run.id)} in the overlay`,
    });
    check.addEventListener("change", () => this.toggleSelect(run.id, check.checked));
    const swatch = h("span", { class: "run-swatch", style: selected ? `background:${this.color(run.id)}` : "" });
    const star = h(
      "button",
      {
        class: `star${run.baseline ? " on" : ""}`,
        testid: `bench-run-baseline-${run.id}`,
        title: run.baseline ? "The baseline of this axis" : "Make this run the baseline (the reference the others are compared with)",
        "aria-pressed": run.baseline ? "true" : "false",
        onclick: () => void this.makeBaseline(run),
      },
      run.baseline ? "★" : "☆",
    );
    const when = clock(run.created_s);
    const quality = qualityOf(run);
    const spec = KINDS[run.test.kind];
    const changed = baseline && baseline.id !== run.id ? diffParams([baseline, run]) : [];
    const changedText = changed.map((p) => `${p}=${run.params[p]}`).join(" ");
    const testCell = h(
      "td",
      { class: "c-test", title: this.runTitle(run) },
      h("div", { class: "test-line" }, h("b", null, spec?.short ?? run.test.kind), " ", h("span", { class: "mono" }, testSize(run, this.units, false))),
      run.status === "incomplete"
        ? h("div", { class: "run-message", title: run.message }, `incomplete${run.message ? `: ${run.message}` : ""}`)
        : quality && quality.status !== "good" && quality.reasons.length
          ? h(
              "div",
              { class: "run-message", testid: `bench-run-reasons-${run.id}`, title: quality.reasons.map((r) => r.message).join("\n") },
              `${quality.status}: ${quality.reasons.map((r) => r.message).join("; ")}`,
            )
          : h(
            "div",
            { class: "test-sub" },
            changedText ? h("span", { class: "changed mono", title: `not as in the ★ baseline: ${changedText}` }, changedText) : null,
            run.test.note ? h("span", { class: "note" }, run.test.note) : null,
            run.imported_from ? h("span", { class: "note" }, "imported") : null,
          ),
    );
    // ✓ only for a complete run the server judged good: a bad run (limit switch, stall,
    // did not move, ended outside the window) is ✗ even when it ran to its end.
    let status: HTMLElement;
    const verdict = run.status === "complete" ? (quality?.status ?? "good") : run.status;
    if (verdict === "good") status = h("span", { class: "run-status ok" }, "✓");
    else if (verdict === "recording") status = h("span", { class: "run-status rec", "data-status-of": run.id }, "● rec");
    else if (verdict === "doubtful") status = h("span", { class: "run-status warn", style: "color: var(--warn, #e0a030)" }, "⚠");
    else status = h("span", { class: "run-status bad" }, "✗");
    status.dataset.quality = verdict;
    status.setAttribute("data-testid", `bench-run-status-${run.id}`);
    const reasons = quality?.reasons.map((r) => `\n• ${r.message}`).join("") ?? "";
    const statusCell = h("td", { class: "c-status", title: `${run.status}${quality ? ` · ${quality.status}` : ""}${run.message ? `: ${run.message}` : ""}${reasons}` }, status);
    // Neither a bad run nor a bad baseline is coloured "better" or "worse".
    const comparable = verdict !== "bad" && qualityOf(baseline)?.status !== "bad";
    const reference =
      comparable && baseline && baseline.id !== run.id && baseline.test.kind === run.test.kind && baseline.metrics ? baseline.metrics : null;
    const metricCells = cols.map((c) =>
      metricCell(c, run.metrics, reference, `bench-metric-${run.id}-${c.key}`, run.baseline ? "baseline" : null, "the baseline", quality?.untrusted ?? {}),
    );
    const actions = h(
      "td",
      { class: "c-actions" },
      h("a", { class: "link-btn", href: `${runUrl(run.id)}/samples.csv`, download: `run-${run.id}.csv`, testid: `bench-run-csv-${run.id}`, title: "Samples as CSV" }, "csv"),
      h("a", { class: "link-btn", href: `${runUrl(run.id)}/run.json`, download: `run-${run.id}.json`, testid: `bench-run-json-${run.id}`, title: "Test, parameters, plan and metrics as JSON" }, "json"),
      h(
        "button",
        { class: "icon-del", testid: `bench-run-delete-${run.id}`, title: "Delete this run", onclick: () => void this.remove(run) },
        "✕",
      ),
    );
    const row = h(
      "tr",
      {
        class: `run-row status-${run.status}${selected ? " selected" : ""}${run.baseline ? " baseline" : ""}`,
        testid: `bench-run-row-${run.id}`,
        "data-run": run.id,
        "data-status": run.status,
      },
      h("td", { class: "c-sel" }, h("label", { class: "sel" }, check, swatch)),
      h("td", { class: "c-star" }, star),
      h("td", { class: "c-run", title: `${run.id}\n${when.full}` }, h("div", { class: "mono run-id" }, shortId(run.id)), h("div", { class: "test-sub mono" }, when.time)),
      testCell,
      statusCell,
      metricCells,
      actions,
    );
    // A click on the row (outside its controls) toggles the selection.
    row.addEventListener("click", (event) => {
      const target = event.target as HTMLElement;
      if (target.closest("button, a, input, label")) return;
      this.toggleSelect(run.id, !this.selected().includes(run.id));
    });
    return row;
  }

  private runTitle(run: BenchRun): string {
    const m = run.metrics;
    const lines = [
      `${KINDS[run.test.kind]?.label ?? run.test.kind} ${testSize(run, this.units)} · ${run.test.duration_s} s`,
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

  /** Select exactly ``ids`` (those stored) in the overlay, e.g. the auto-tune's
   * baseline and verification runs. */
  async showRuns(ids: string[]): Promise<void> {
    await this.refresh();
    if (this.signal.aborted) return;
    const known = new Set(this.runs.map((r) => r.id));
    const sel = ids.filter((id) => known.has(id));
    if (!sel.length) return;
    saveSelection(this.axisId, sel);
    this.assignColors(sel);
    this.renderRuns();
    await this.draw();
  }

  private toggleSelect(id: string, on: boolean): void {
    let sel = this.selected().filter((x) => x !== id);
    if (on) sel.push(id);
    sel = this.capSelection(sel);
    saveSelection(this.axisId, sel);
    this.assignColors(sel);
    this.renderRuns();
    void this.draw();
  }

  private async makeBaseline(run: BenchRun): Promise<void> {
    if (run.baseline) return;
    try {
      await api.setBaseline(run.id);
      const sel = this.selected();
      if (!sel.includes(run.id)) saveSelection(this.axisId, [run.id, ...sel]);
    } catch (error) {
      this.showError(error, "run");
    }
    await this.refresh();
  }

  private async remove(run: BenchRun): Promise<void> {
    const ok = await confirmDialog(
      `Delete run ${shortId(run.id)}`,
      `Delete the ${KINDS[run.test.kind]?.label ?? run.test.kind} ${testSize(run, this.units)} of ${clock(run.created_s).full} with all its samples? This cannot be undone (export it first to keep a copy).`,
      "Delete",
    );
    if (!ok) return;
    try {
      await api.deleteRun(run.id);
    } catch (error) {
      this.showError(error, "run");
    }
    await this.refresh();
  }

  /** The "settings are not being saved" banner (GET /api/storage, storage_status). */
  private showStorage(writable: boolean, message: string): void {
    if (writable) {
      replace(this.storageBanner);
      return;
    }
    replace(
      this.storageBanner,
      h(
        "div",
        { class: "banner reset", testid: "storage-banner", role: "alert" },
        h("span", { class: "banner-icon" }, "⚠"),
        h(
          "div",
          { class: "banner-text" },
          h("b", null, "Settings are not being saved"),
          h("span", { class: "banner-detail" }, `${message} — runs, limits and sets cannot be stored; settings applied to the device are kept in memory and saved once the database works again.`),
        ),
      ),
    );
  }

  // --- import -------------------------------------------------------------------------

  private async importFiles(): Promise<void> {
    const files = [...(this.importInput.files ?? [])];
    this.importInput.value = "";
    try {
      for (const file of files) {
        // Only the start of a file is read to tell JSON from CSV: a run can be tens of
        // megabytes, and the server parses it (sent as multipart, up to 64 MiB).
        const head = await file.slice(0, 64).text();
        if (/\.json$/i.test(file.name) || head.trimStart().startsWith("{")) this.pendingImport.json = file;
        else this.pendingImport.csv = file;
      }
    } catch (error) {
      this.pendingImport = {};
      this.setImportStatus("error", `cannot read the file: ${errorText(error)}`);
      return;
    }
    const { json, csv } = this.pendingImport;
    if (json === undefined || csv === undefined) {
      this.setImportStatus("pending", json === undefined ? `${csv?.name}: now pick the run's .json` : `${json.name}: now pick the run's .csv`);
      return;
    }
    this.pendingImport = {};
    this.setImportStatus("pending", "importing …");
    try {
      const { id } = await importRunFiles(this.axisId, json, csv);
      this.finished.add(id);
      this.setImportStatus("ok", `✓ imported as ${shortId(id)}`);
      await this.refresh();
    } catch (error) {
      this.setImportStatus("error", `✗ import: ${statusLabel(error)} — ${errorText(error)}`);
    }
  }

  private setImportStatus(kind: string, text: string): void {
    this.importStatus.dataset.kind = kind;
    setText(this.importStatus, text);
    this.importStatus.title = text;
  }

  // --- overlay ------------------------------------------------------------------------

  private channelUnit(name: string): string {
    return this.descriptor.channels.find((c) => c.name === name)?.unit ?? "";
  }

  private responseUnit(): string {
    const first = this.traces[0]?.run;
    return first ? this.channelUnit(first.plan.response) : "";
  }

  /** The selected runs in display order: the baseline first, then oldest to newest. */
  private selectedRuns(): BenchRun[] {
    const sel = new Set(this.selected());
    return this.runs.filter((r) => sel.has(r.id)).sort((a, b) => Number(b.baseline) - Number(a.baseline) || a.created_s - b.created_s);
  }

  private async draw(): Promise<void> {
    const token = ++this.drawToken;
    const runs = this.selectedRuns();
    // Runs of one response only (position or velocity): that of the last selected run.
    const sel = this.selected();
    const lastId = [...sel].reverse().find((id) => runs.some((r) => r.id === id));
    const frfRuns = runs.filter((r) => r.test.kind === "frequency_response");
    this.frf?.show(frfRuns.map((r) => ({ id: r.id, color: this.color(r.id), label: shortId(r.id), recording: r.status === "recording" })));
    const stepRuns = runs.filter((r) => r.test.kind !== "frequency_response");
    const response = stepRuns.find((r) => r.id === lastId)?.plan.response ?? stepRuns[0]?.plan.response;
    const drawn = stepRuns.filter((r) => r.plan.response === response);
    const skipped = stepRuns.length - drawn.length;
    let loaded: BenchRunDetail[];
    try {
      loaded = await Promise.all(drawn.map((r) => detail(r)));
    } catch (error) {
      if (token !== this.drawToken) return;
      this.response.set([], [], `cannot load the samples: ${errorText(error)}`);
      return;
    }
    if (token !== this.drawToken || this.signal.aborted) return;
    const differing = diffParams(loaded);
    this.traces = [];
    const fe: Trace[] = [];
    const targets: Target[] = [];
    for (const run of loaded) {
      const color = this.color(run.id);
      const t0 = triggerTime(run);
      const y = column(run, run.plan.response, t0, run.plan.y0);
      if (!y) continue;
      const trace: Trace = { id: run.id, color, x: y.x, y: y.y, bold: run.baseline, settle: run.metrics?.settling_time_s ?? null };
      const gains = differing.map((p) => `${p}=${run.params[p] ?? "—"}`).join(" ");
      const label = `${shortId(run.id)} ${KINDS[run.test.kind]?.short ?? run.test.kind} ${testSize(run, this.units)}`;
      const legendValue = h("span", { class: "legend-value" }, "");
      this.traces.push({ trace, run, label: `${label}${gains ? ` ${gains}` : ""}`, legendValue });
      const e = column(run, "following_error", t0, 0);
      if (e) fe.push({ ...trace, x: e.x, y: e.y, settle: null });
      const target = run.plan.y_final - run.plan.y0;
      if (run.test.kind !== "pwm_step") targets.push({ y: target, band: run.plan.band, color });
    }
    // One neutral target when every run has the same one; else one per run, in its colour.
    const sameTarget = targets.length > 0 && targets.every((t) => t.y === targets[0]?.y && t.band === targets[0]?.band);
    const shownTargets = sameTarget ? [{ ...(targets[0] as Target), color: null }] : targets;
    const unit = this.channelUnit(response ?? "");
    const label = this.descriptor.channels.find((c) => c.name === response)?.label ?? response ?? "Response";
    setText(this.responseTitle, `${label} − start`);
    setText(
      this.responseNote,
      `${unit}${skipped ? ` · ${skipped} selected run${skipped > 1 ? "s" : ""} with another response not drawn` : ""}`,
    );
    toggleClass(this.responseNote, "warn", skipped > 0);
    const message = !this.runs.length
      ? "No runs yet."
      : !runs.length
        ? "Select runs in the table to overlay them."
        : !stepRuns.length
          ? "Frequency-response runs are drawn in the Frequency response panel below."
          : "The selected runs have no samples.";
    // Start zoomed on the response when every run settled early in a long record
    // (double-click shows the whole run).
    const ends = this.traces.map(({ trace, run }) => {
      const m = run.metrics;
      const done = Math.max(trace.settle ?? -1, ...Object.values(m?.time_to_flag_s ?? {}).map((v) => v ?? -1));
      return done > 0 ? done : null;
    });
    const focus = ends.length && ends.every((e) => e !== null) ? Math.max(...(ends as number[])) * 1.5 + 0.1 : null;
    this.response.set(this.traces.map((t) => t.trace), shownTargets, message, focus);
    this.fePanel.hidden = fe.length === 0;
    this.following.set(fe, [], "", focus);
    // The what-if view shows its prediction next to the newest selected position run.
    const lastStep = [...loaded].reverse().find((r) => r.test.kind === "position_step" || r.test.kind === "move");
    if (this.whatif) {
      const col = lastStep ? column(lastStep, "position", triggerTime(lastStep), lastStep.plan.y0) : null;
      const delayS = (lastStep as { trigger_latency_s?: number } | undefined)?.trigger_latency_s ?? 0;
      const distance = lastStep ? (lastStep.test as { distance?: number }).distance ?? null : null;
      this.whatif.setMeasured(lastStep && col ? { id: lastStep.id, distance, label: `${shortId(lastStep.id)} measured`, delayS, t: col.x, y: col.y } : null);
    }
    this.renderLegend(differing);
  }

  private renderLegend(differing: string[]): void {
    replace(
      this.legend,
      this.traces.map(({ trace, run, label, legendValue }) =>
        h(
          "span",
          {
            class: `bench-legend-item${run.baseline ? " baseline" : ""}`,
            title: `${label}\n${this.runTitle(run)}`,
            "data-run": run.id,
          },
          h("span", { class: "swatch", style: `background:${trace.color}` }),
          h("span", { class: "legend-label" }, label),
          legendValue,
        ),
      ),
      this.traces.length > 1 && !differing.length ? h("span", { class: "bench-legend-note" }, "same parameters") : null,
    );
    this.cursor(null);
  }

  private cursor(x: number | null): void {
    for (const { trace, run, legendValue } of this.traces) {
      if (x === null) {
        // Off the plot: the final value against the target.
        const last = [...trace.y].reverse().find((v) => v !== null);
        setText(legendValue, last === undefined || last === null ? "" : `end ${num(last)}`);
        legendValue.title = `last sample, ${num(run.plan.y_final - run.plan.y0)} commanded`;
      } else {
        const v = valueAt(trace, x);
        setText(legendValue, v === null ? "—" : num(v));
        legendValue.title = `at ${(x * 1000).toFixed(0)} ms`;
      }
    }
  }

  // --- parameter diff -----------------------------------------------------------------

  private renderDiff(): void {
    const runs = this.selectedRuns();
    if (runs.length < 2) {
      replace(this.diff, h("div", { class: "bench-diff-side" }, h("span", { class: "pane-title" }, "Parameter diff"), h("span", { class: "pane-sub" }, "select two or more runs to compare their parameters")));
      return;
    }
    const names = diffParams(runs);
    const labels = new Map(this.descriptor.parameters.map((p) => [p.name, p]));
    const ref = runs[0] as BenchRun;
    const header = h(
      "tr",
      null,
      h("th", { class: "d-name" }, "parameter"),
      runs.map((r) =>
        h(
          "th",
          { class: `d-run${r.baseline ? " baseline" : ""}`, title: `${r.id}${r.baseline ? " (baseline)" : ""}` },
          h("span", { class: "run-swatch", style: `background:${this.color(r.id)}` }),
          `${r.baseline ? "★ " : ""}${shortId(r.id)}`,
        ),
      ),
    );
    const rows = names.map((name) => {
      const p = labels.get(name);
      return h(
        "tr",
        { "data-param": name },
        h("td", { class: "d-name", title: p?.description ?? name }, p ? `${p.label}` : name, h("span", { class: "d-key mono" }, p && p.label.toLowerCase() !== name ? ` ${name}` : "")),
        runs.map((r, i) => {
          const v = r.params[name];
          const differs = i > 0 && v !== ref.params[name];
          return h("td", { class: `d-val num${differs ? " differs" : ""}${i === 0 ? " ref" : ""}` }, v === undefined ? "—" : String(v), p?.unit ? h("span", { class: "d-unit" }, ` ${p.unit}`) : null);
        }),
      );
    });
    const table = h("table", { class: "diff-table" }, h("thead", null, header), h("tbody", null, rows));
    const caption = names.length
      ? `${names.length} of ${new Set(runs.flatMap((r) => Object.keys(r.params))).size} parameters differ between the ${runs.length} selected runs; highlighted: not as in ${ref.baseline ? "the ★ baseline" : "the oldest selected run"} ${shortId(ref.id)}`
      : `the ${runs.length} selected runs ran with identical parameters`;
    replace(
      this.diff,
      h("div", { class: "bench-diff-side" }, h("span", { class: "pane-title" }, "Parameter diff"), h("span", { class: "pane-sub" }, caption)),
      names.length ? table : null,
    );
  }
}

/** Parameters whose values are not the same in every run (in descriptor order of the first). */
function diffParams(runs: BenchRun[]): string[] {
  if (runs.length < 2) return [];
  const names: string[] = [];
  const seen = new Set<string>();
  for (const run of runs) for (const name of Object.keys(run.params)) if (!seen.has(name)) (seen.add(name), names.push(name));
  return names.filter((name) => runs.some((r) => r.params[name] !== runs[0]?.params[name]));
}

/**
 * The trigger time t0 of a run, in the samples' clock: ``t0_s`` as the server stored
 * it. Runs stored before the server kept t0 (or imported without it) fall back to an
 * estimate, which can be off by up to a sample gap or more: the recorder arms PRE_TRIGGER_S (0.2 s) before it sends the trigger, so t0 ≈ the
 * first sample's time + 0.2 s. The parameter writes and setup commands before that
 * pause, and the wait for the first sample after arming, shift it by up to a sample
 * gap, so when the metrics are there t0 is recovered exactly from them instead:
 * ``peak_time_s`` is the time after t0 of the FIRST sample with ``peak_value`` (the
 * value may repeat while the axis rests at its peak), so t0 = t(the earliest sample
 * with that value whose t0 is plausible) − peak_time_s. Plausible: not before the
 * first sample (it comes at most a sample gap after arming, t0 ≥ arming + 0.2 s) and
 * not more than 1.5 s after the estimate.
 */
export function triggerTime(run: BenchRunDetail): number {
  // The server stores the trigger time (t0_s) with every run it records: use it.
  const stored = (run as { t0_s?: unknown }).t0_s;
  if (typeof stored === "number" && Number.isFinite(stored)) return stored;
  const first = run.samples[0]?.[0] ?? 0;
  const estimate = first + PRE_TRIGGER_S;
  const m = run.metrics;
  const index = run.columns.indexOf(run.plan.response);
  if (!m || m.peak_time_s === null || m.peak_value === null || index < 1) return estimate;
  for (const row of run.samples) {
    if (row[index] !== m.peak_value) continue;
    const t0 = (row[0] as number) - m.peak_time_s;
    if (t0 >= first && t0 <= estimate + 1.5) return t0;
  }
  return estimate;
}

/** One column of a run against t − t0, minus ``offset`` (y0 for the response). */
function column(run: BenchRunDetail, name: string, t0: number, offset: number): { x: number[]; y: (number | null)[] } | null {
  const index = run.columns.indexOf(name);
  if (index < 1 || !run.samples.length) return null;
  const x: number[] = [];
  const y: (number | null)[] = [];
  let any = false;
  for (const row of run.samples) {
    const t = row[0] as number;
    const v = row[index];
    x.push(Math.round((t - t0) * 1e6) / 1e6);
    if (typeof v === "number" && Number.isFinite(v)) {
      y.push(v - offset);
      any = true;
    } else y.push(null);
  }
  return any ? { x, y } : null;
}

/** ``POST /api/axes/{id}/bench/runs/import`` as multipart (run.json + samples.csv). */
async function importRunFiles(axisId: string, json: File, csv: File): Promise<{ id: string }> {
  const form = new FormData();
  form.append("meta", json, json.name);
  form.append("csv", csv, csv.name);
  let response: Response;
  try {
    response = await fetch(`/api/axes/${encodeURIComponent(axisId)}/bench/runs/import`, { method: "POST", body: form });
  } catch (error) {
    throw new ApiError(0, `server unreachable: ${(error as Error).message}`, null);
  }
  let body: unknown = null;
  try {
    body = await response.json();
  } catch {
    body = null;
  }
  if (!response.ok) {
    const b = (body ?? {}) as { detail?: unknown; field?: unknown };
    const detail = typeof b.detail === "string" ? b.detail : `HTTP ${response.status} ${response.statusText}`;
    throw new ApiError(response.status, detail, typeof b.field === "string" ? b.field : null);
  }
  return body as { id: string };
}
