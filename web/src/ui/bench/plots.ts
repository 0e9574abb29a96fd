// The overlay of the selected runs, aligned at their trigger t0: the response (position
// or velocity minus its start) with targets and bands, the following error below, a
// legend that reads the value under the cursor, zoom linked between the two.
import type { BenchRun, BenchRunDetail } from "../../api";
import { h, replace, setText, toggleClass } from "../../dom";
import type { DeviceDescriptor } from "../../schema.gen";
import { type Target, type Trace, Overlay, plotTheme, valueAt } from "../benchplot";
import { errorText } from "../feedback";
import { num } from "../metriccols";
import { diffParams } from "./diff";
import { KINDS, type Units, runTitle, shortId, testSize } from "./kinds";
import { column, detail, triggerTime } from "./samples";

export class RunOverlay {
  readonly el: HTMLElement;
  private readonly response: Overlay;
  private readonly following: Overlay;
  private readonly responseTitle: HTMLElement;
  private readonly responseNote: HTMLElement;
  private readonly feTitle: HTMLElement;
  private readonly legend: HTMLElement;
  private readonly fePanel: HTMLElement;
  private traces: { trace: Trace; run: BenchRun; label: string; legendValue: HTMLElement }[] = [];
  private drawToken = 0;

  constructor(
    axisId: string,
    private readonly descriptor: DeviceDescriptor,
    private readonly units: Units,
    private readonly signal: AbortSignal,
  ) {
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
    this.el = h(
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
  }

  destroy(): void {
    this.response.destroy();
    this.following.destroy();
  }

  channelUnit(name: string): string {
    return this.descriptor.channels.find((c) => c.name === name)?.unit ?? "";
  }

  private responseUnit(): string {
    const first = this.traces[0]?.run;
    return first ? this.channelUnit(first.plan.response) : "";
  }

  /** Overlay the step runs of ``runs`` (the selected runs in display order; ``lastId``
   * the last selected: its response is drawn, position or velocity); ``stored``: how
   * many runs the axis has. The runs' details as drawn, or null when a newer call
   * superseded this one or the samples could not be loaded. */
  async show(runs: BenchRun[], lastId: string | undefined, stored: number, color: (id: string) => string): Promise<BenchRunDetail[] | null> {
    const token = ++this.drawToken;
    const stepRuns = runs.filter((r) => r.test.kind !== "frequency_response");
    const response = stepRuns.find((r) => r.id === lastId)?.plan.response ?? stepRuns[0]?.plan.response;
    const drawn = stepRuns.filter((r) => r.plan.response === response);
    const skipped = stepRuns.length - drawn.length;
    let loaded: BenchRunDetail[];
    try {
      loaded = await Promise.all(drawn.map((r) => detail(r)));
    } catch (error) {
      if (token !== this.drawToken) return null;
      this.response.set([], [], `cannot load the samples: ${errorText(error)}`);
      return null;
    }
    if (token !== this.drawToken || this.signal.aborted) return null;
    const differing = diffParams(loaded);
    this.traces = [];
    const fe: Trace[] = [];
    const targets: Target[] = [];
    for (const run of loaded) {
      const runColor = color(run.id);
      const t0 = triggerTime(run);
      const y = column(run, run.plan.response, t0, run.plan.y0);
      if (!y) continue;
      const trace: Trace = { id: run.id, color: runColor, x: y.x, y: y.y, bold: run.baseline ?? false, settle: run.metrics?.settling_time_s ?? null };
      const gains = differing.map((p) => `${p}=${run.params[p] ?? "—"}`).join(" ");
      const label = `${shortId(run.id)} ${KINDS[run.test.kind]?.short ?? run.test.kind} ${testSize(run, this.units)}`;
      const legendValue = h("span", { class: "legend-value" }, "");
      this.traces.push({ trace, run, label: `${label}${gains ? ` ${gains}` : ""}`, legendValue });
      const e = column(run, "following_error", t0, 0);
      if (e) fe.push({ ...trace, x: e.x, y: e.y, settle: null });
      const target = run.plan.y_final - run.plan.y0;
      if (run.test.kind !== "pwm_step") targets.push({ y: target, band: run.plan.band, color: runColor });
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
    const message = !stored
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
    this.renderLegend(differing);
    return loaded;
  }

  private renderLegend(differing: string[]): void {
    replace(
      this.legend,
      this.traces.map(({ trace, run, label, legendValue }) =>
        h(
          "span",
          {
            class: `bench-legend-item${run.baseline ? " baseline" : ""}`,
            title: `${label}\n${runTitle(run, this.units)}`,
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
}
