// The tuning test bench of one axis: a test form (with the user's limits), the runs
// table with metrics, an overlay of the selected runs aligned at the trigger, and the
// parameters that differ between them; the auto-tune, frequency-response and what-if
// panels where the bench info offers them. Progress comes from websocket ``run``
// messages, so every browser sees a run appear and finish. This file holds the parts
// together (form.ts, limits.ts, runs.ts, plots.ts, diff.ts, import.ts).
import { api, type BenchInfo, type BenchRun } from "../../api";
import { h, replace, setText } from "../../dom";
import { store } from "../../store";
import type { Conversion, DeviceDescriptor, RunUpdate } from "../../schema.gen";
import { AutoTunePanel } from "../autotune";
import { FrfPanel } from "../bode";
import { errorText } from "../feedback";
import { metricColumns } from "../metriccols";
import { setMetricDefinitions } from "../../metrics";
import { WhatIfPanel } from "../whatif";
import { ParamDiff } from "./diff";
import { BenchForm } from "./form";
import { RunImport } from "./import";
import { type FieldName, type Units, shortId } from "./kinds";
import { RunOverlay } from "./plots";
import { RunsTable } from "./runs";
import { column, triggerTime } from "./samples";
import { Selection } from "./selection";

export class BenchView {
  readonly el: HTMLElement;
  private info: BenchInfo | null = null;
  private runs: BenchRun[] = [];
  // the device's channels until the bench info (``fields``) says what each field sets
  private readonly units: Units;
  private readonly conversions: Record<FieldName, Conversion[]>;
  private readonly selection: Selection;
  private readonly form: BenchForm;
  private readonly table: RunsTable;
  private readonly overlay: RunOverlay;
  private readonly diff: ParamDiff;
  // Only for devices the auto-tune assistant supports (descriptor.autotune).
  private readonly autotune: AutoTunePanel | null;
  private readonly storageBanner: HTMLElement;
  private refreshing: Promise<void> | null = null;
  private refreshAgain = false;
  private finished = new Set<string>(); // runs that finished while we watched: select them
  // the frequency-response and what-if panels (ui/bode.ts, ui/whatif.ts), as the bench info offers them
  private frf: FrfPanel | null = null;
  private whatif: WhatIfPanel | null = null;
  private readonly extras: HTMLElement;

  constructor(
    private readonly axisId: string,
    private readonly descriptor: DeviceDescriptor,
    private readonly signal: AbortSignal,
  ) {
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
    this.selection = new Selection(axisId);
    this.form = new BenchForm(axisId, descriptor, this.units, this.conversions, {
      info: () => this.info,
      runs: () => this.runs,
      started: (run) => {
        if (!this.runs.some((r) => r.id === run.id)) this.runs.push(run);
        this.finished.add(run.id);
        this.table.render();
      },
      limitsSaved: (limits) => this.autotune?.setLimits(limits),
    });
    this.overlay = new RunOverlay(axisId, descriptor, this.units, signal);
    this.diff = new ParamDiff(descriptor);
    this.table = new RunsTable(descriptor, this.units, this.selection, {
      info: () => this.info,
      runs: () => this.runs,
      selectionChanged: () => void this.draw(),
      rendered: () => this.diff.show(this.selectedRuns(), (id) => this.selection.color(id)),
      refresh: () => this.refresh(),
      showError: (error, field) => this.form.showError(error, field),
    });
    const importer = new RunImport(axisId, async (id) => {
      this.finished.add(id);
      await this.refresh();
    });
    const runsPane = h(
      "section",
      { class: "bench-runs-pane" },
      h(
        "div",
        { class: "pane-header" },
        h("span", { class: "pane-title" }, "Runs"),
        this.table.title,
        h("span", { class: "tb-spacer" }),
        importer.status,
        importer.button,
        importer.input,
      ),
      h("div", { class: "bench-table-scroll" }, this.table.el),
      h("div", { class: "bench-diff-pane" }, this.diff.el),
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
    this.el = h("div", { class: "bench", "data-axis": axisId }, this.storageBanner, this.form.el, ...(this.autotune ? [this.autotune.el] : []), this.overlay.el, runsPane, this.extras);
    store.on("storage", (msg) => this.showStorage(msg.writable, msg.message), signal);
    void fetch("/api/storage", { signal })
      .then((r) => (r.ok ? (r.json() as Promise<{ writable: boolean; message: string }>) : null))
      .then((st) => st && this.showStorage(st.writable, st.message))
      .catch(() => undefined);

    store.on("run", (msg) => msg.axis === axisId && this.onRun(msg), signal);
    // Runs may have started or finished while the websocket was down.
    store.on("ws", (state) => state.kind === "open" && this.info !== null && void this.refresh(), signal);
    signal.addEventListener("abort", () => this.overlay.destroy(), { once: true });
    void this.load();
  }

  // --- loading ------------------------------------------------------------------------

  private async load(): Promise<void> {
    try {
      this.info = await api.bench(this.axisId);
    } catch (error) {
      this.form.showLoadError(error, () => void this.load());
      return;
    }
    if (this.signal.aborted) return;
    setMetricDefinitions(this.info.definitions);
    for (const [name, field] of Object.entries(this.info.fields)) {
      if (!(name in this.units)) continue;
      this.units[name as FieldName] = field.unit;
      this.conversions[name as FieldName] = field.conversions;
    }
    this.form.render();
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
          setText(this.table.title, `cannot list the runs: ${errorText(error)}`);
          break;
        }
        if (this.signal.aborted) return;
        this.reconcileSelection();
        this.table.render();
        this.form.syncRunButton();
        void this.draw();
      } while (this.refreshAgain);
    })().finally(() => {
      this.refreshing = null;
    });
    return this.refreshing;
  }

  private reconcileSelection(): void {
    const ids = new Set(this.runs.map((r) => r.id));
    let sel = this.selection.ids().filter((id) => ids.has(id));
    const first = !this.selection.known() || sel.length === 0;
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
    sel = this.selection.cap(sel, this.runs);
    this.selection.save(sel);
    this.selection.assignColors(sel);
  }

  // --- progress -----------------------------------------------------------------------

  private onRun(msg: RunUpdate): void {
    this.form.syncProgress(msg);
    const known = this.runs.find((r) => r.id === msg.run_id);
    if (msg.status !== "recording") {
      this.finished.add(msg.run_id);
      this.whatif?.runEnded(msg.run_id, msg.status, msg.message);
      void this.whatif?.load(); // an identification may have given a new model
    }
    if (known && msg.status === "recording") {
      known.status = "recording";
      this.table.showRecording(msg.run_id, msg.elapsed_s);
      this.form.syncRunButton();
      return;
    }
    this.form.syncRunButton();
    void this.refresh();
  }

  /** Select exactly ``ids`` (those stored) in the overlay, e.g. the auto-tune's
   * baseline and verification runs. */
  async showRuns(ids: string[]): Promise<void> {
    await this.refresh();
    if (this.signal.aborted) return;
    const known = new Set(this.runs.map((r) => r.id));
    const sel = ids.filter((id) => known.has(id));
    if (!sel.length) return;
    this.selection.save(sel);
    this.selection.assignColors(sel);
    this.table.render();
    await this.draw();
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

  // --- overlay ------------------------------------------------------------------------

  /** The selected runs in display order: the baseline first, then oldest to newest. */
  private selectedRuns(): BenchRun[] {
    const sel = new Set(this.selection.ids());
    return this.runs.filter((r) => sel.has(r.id)).sort((a, b) => Number(b.baseline) - Number(a.baseline) || (a.created_s ?? 0) - (b.created_s ?? 0));
  }

  private async draw(): Promise<void> {
    const runs = this.selectedRuns();
    // Runs of one response only (position or velocity): that of the last selected run.
    const sel = this.selection.ids();
    const lastId = [...sel].reverse().find((id) => runs.some((r) => r.id === id));
    const color = (id: string): string => this.selection.color(id);
    const frfRuns = runs.filter((r) => r.test.kind === "frequency_response");
    this.frf?.show(frfRuns.map((r) => ({ id: r.id, color: color(r.id), label: shortId(r.id), recording: r.status === "recording" })));
    const loaded = await this.overlay.show(runs, lastId, this.runs.length, color);
    if (loaded === null) return;
    // The what-if view shows its prediction next to the newest selected position run.
    const lastStep = [...loaded].reverse().find((r) => r.test.kind === "position_step" || r.test.kind === "move");
    if (this.whatif) {
      const col = lastStep ? column(lastStep, "position", triggerTime(lastStep), lastStep.plan.y0) : null;
      const delayS = (lastStep as { trigger_latency_s?: number } | undefined)?.trigger_latency_s ?? 0;
      const distance = lastStep ? (lastStep.test as { distance?: number }).distance ?? null : null;
      this.whatif.setMeasured(lastStep && col ? { id: lastStep.id, distance, label: `${shortId(lastStep.id)} measured`, delayS, t: col.x, y: col.y } : null);
    }
  }

}
