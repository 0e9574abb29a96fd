// The runs table: one row per stored run of the axis (newest first) with its test,
// verdict and metrics coloured against the ★ baseline; a row's checkbox selects it for
// the overlay, its star makes it the baseline.
import { api, runUrl, type BenchInfo, type BenchRun } from "../../api";
import { h, replace, setText } from "../../dom";
import { clock } from "../../format";
import type { DeviceDescriptor } from "../../schema.gen";
import { confirmDialog } from "../feedback";
import { type MetricColumn, metricCell, metricColumns, qualityOf } from "../metriccols";
import { diffParams } from "./diff";
import { KINDS, type Units, runTitle, shortId, testSize } from "./kinds";
import type { Selection } from "./selection";

export interface RunsHost {
  info(): BenchInfo | null;
  runs(): BenchRun[];
  /** The user changed the selection: redraw the overlay. */
  selectionChanged(): void;
  /** The table was rebuilt (the parameter diff follows it). */
  rendered(): void;
  refresh(): Promise<void>;
  showError(error: unknown, fallbackField: string): void;
}

export class RunsTable {
  readonly el: HTMLTableElement;
  readonly title: HTMLElement;

  constructor(
    private readonly descriptor: DeviceDescriptor,
    private readonly units: Units,
    private readonly selection: Selection,
    private readonly host: RunsHost,
  ) {
    this.el = h("table", { class: "bench-table", testid: "bench-runs" });
    this.title = h("span", { class: "pane-sub" });
  }

  /** A recording run's elapsed time, in its status cell. */
  showRecording(runId: string, elapsedS: number): void {
    const cell = this.el.querySelector<HTMLElement>(`[data-status-of="${runId}"]`);
    if (cell) setText(cell, `● rec ${elapsedS.toFixed(1)} s`);
  }

  private metricColumns(): MetricColumn[] {
    return metricColumns(this.descriptor, this.host.runs().map((r) => r.metrics));
  }

  /** Rebuild the table from the runs and the selection (the scroll position kept). */
  render(): void {
    const runs = this.host.runs();
    const cols = this.metricColumns();
    const sel = this.selection.ids();
    const baseline = runs.find((r) => r.baseline) ?? null;
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
    const ordered = [...runs].reverse(); // newest first
    for (const run of ordered) body.appendChild(this.runRow(run, cols, sel, baseline));
    if (!ordered.length) {
      body.appendChild(
        h(
          "tr",
          { class: "bench-empty-row" },
          h("td", { colspan: 6 + cols.length }, this.host.info()?.kinds.length ? "No runs yet: choose a test above and press Run test." : "No runs."),
        ),
      );
    }
    const scroller = this.el.parentElement;
    const scroll = scroller?.scrollTop ?? 0;
    replace(this.el, head, body);
    if (scroller) scroller.scrollTop = scroll;
    const recording = runs.filter((r) => r.status === "recording").length;
    setText(this.title, `${runs.length} stored · ${sel.length} selected${recording ? ` · ${recording} recording` : ""} · metric colours: better / worse than ★`);
    this.host.rendered();
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
    const swatch = h("span", { class: "run-swatch", style: selected ? `background:${this.selection.color(run.id)}` : "" });
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
    const when = clock(run.created_s ?? 0);
    const quality = qualityOf(run);
    const spec = KINDS[run.test.kind];
    const changed = baseline && baseline.id !== run.id ? diffParams([baseline, run]) : [];
    const changedText = changed.map((p) => `${p}=${run.params[p]}`).join(" ");
    const testCell = h(
      "td",
      { class: "c-test", title: runTitle(run, this.units) },
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
      this.toggleSelect(run.id, !this.selection.ids().includes(run.id));
    });
    return row;
  }

  private toggleSelect(id: string, on: boolean): void {
    let sel = this.selection.ids().filter((x) => x !== id);
    if (on) sel.push(id);
    sel = this.selection.cap(sel, this.host.runs());
    this.selection.save(sel);
    this.selection.assignColors(sel);
    this.render();
    this.host.selectionChanged();
  }

  private async makeBaseline(run: BenchRun): Promise<void> {
    if (run.baseline) return;
    try {
      await api.setBaseline(run.id);
      const sel = this.selection.ids();
      if (!sel.includes(run.id)) this.selection.save([run.id, ...sel]);
    } catch (error) {
      this.host.showError(error, "run");
    }
    await this.host.refresh();
  }

  private async remove(run: BenchRun): Promise<void> {
    const ok = await confirmDialog(
      `Delete run ${shortId(run.id)}`,
      `Delete the ${KINDS[run.test.kind]?.label ?? run.test.kind} ${testSize(run, this.units)} of ${clock(run.created_s ?? 0).full} with all its samples? This cannot be undone (export it first to keep a copy).`,
      "Delete",
    );
    if (!ok) return;
    try {
      await api.deleteRun(run.id);
    } catch (error) {
      this.host.showError(error, "run");
    }
    await this.host.refresh();
  }
}
