// Scope tools of one PlotStack: time under the cursor, Δ cursors, trigger settings,
// x as wall clock or relative time, channel choice per plot and CSV export.
import { h, replace, setText, toggleClass } from "../dom";
import { formatValue } from "../format";
import { store } from "../store";
import type { PlotStack } from "./plots";
import type { Edge, TriggerSource } from "./trigger";

export class ScopeTools {
  readonly el: HTMLElement;
  /** The row under the toolbar: Δ cursor readout and trigger settings. */
  readonly readout: HTMLElement;
  private readonly time: HTMLElement;
  private readonly cursorButton: HTMLButtonElement;
  private readonly triggerButton: HTMLButtonElement;
  private readonly cursorRow: HTMLElement;
  private cursorKey = "";
  private readonly triggerRow: HTMLElement;
  private readonly channelsRow: HTMLElement;
  private readonly channelsButton: HTMLButtonElement;
  private readonly xButtons: Record<"clock" | "rel", HTMLButtonElement>;
  private readonly source: HTMLSelectElement;
  private readonly level: HTMLInputElement;
  private readonly edge: HTMLSelectElement;
  private readonly pre: HTMLInputElement;
  private readonly mode: HTMLSelectElement;
  private readonly triggerState: HTMLElement;

  constructor(private readonly stack: PlotStack) {
    const d = stack.descriptor;
    this.time = h("span", { class: "cursor-time mono", testid: "cursor-time", title: "Time under the cursor" }, "");
    this.cursorButton = h(
      "button",
      { class: "btn", testid: "cursors-toggle", title: "Two Δ cursors: click a plot to place A, click again for B (they snap to samples)", onclick: () => this.toggleCursors() },
      "Δ Cursors",
    );
    this.triggerButton = h("button", { class: "btn", testid: "trigger-toggle", title: "Trigger: a flag edge or a level crossing freezes a window", onclick: () => this.toggleRow(this.triggerRow, this.triggerButton) }, "Trigger");
    this.channelsButton = h("button", { class: "btn", testid: "channels-toggle", title: "Choose the channels of each plot (kept for this device)", onclick: () => this.toggleChannels() }, "Channels");
    this.xButtons = {
      clock: h("button", { class: "seg-btn", testid: "x-clock", title: "x axis: wall clock", onclick: () => this.setX("clock") }, "clock"),
      rel: h("button", { class: "seg-btn", testid: "x-rel", title: "x axis: seconds relative to the trigger point (or the right edge)", onclick: () => this.setX("rel") }, "rel"),
    };
    const csv = h("button", { class: "btn", testid: "scope-csv", title: "Download the visible window as CSV (device units, with the trigger time)", onclick: () => this.exportCsv() }, "CSV");
    this.el = h(
      "div",
      { class: "scope-tools" },
      this.cursorButton,
      this.triggerButton,
      h("div", { class: "seg small", role: "group", "aria-label": "Time axis" }, this.xButtons.clock, this.xButtons.rel),
      this.channelsButton,
      csv,
      this.time,
    );

    // Trigger settings.
    this.source = h("select", { class: "input", testid: "trigger-source", "aria-label": "Trigger source" });
    this.source.append(h("option", { value: "" }, "off"));
    for (const f of d.flags) {
      this.source.append(h("option", { value: `flag:${f.name}:rising` }, `${f.label} ↑ rising`));
      this.source.append(h("option", { value: `flag:${f.name}:falling` }, `${f.label} ↓ falling`));
    }
    for (const c of d.channels) if (!Object.keys(c.value_names).length) this.source.append(h("option", { value: `level:${c.name}` }, `${c.label} crosses level`));
    this.level = h("input", { class: "input num", type: "number", testid: "trigger-level", value: "0", "aria-label": "Trigger level (display unit)", title: "Level in the channel's display unit" });
    this.edge = h("select", { class: "input", testid: "trigger-edge", "aria-label": "Edge" }, h("option", { value: "rising" }, "rising"), h("option", { value: "falling" }, "falling"));
    this.pre = h("input", { class: "input num", type: "number", testid: "trigger-pre", value: "20", min: 0, max: 90, step: 5, "aria-label": "Pre-trigger %", title: "Share of the window before the trigger point, 0..90 %" });
    this.mode = h("select", { class: "input", testid: "trigger-mode", "aria-label": "Trigger mode" }, h("option", { value: "single" }, "single"), h("option", { value: "normal" }, "normal"));
    this.triggerState = h("span", { class: "trigger-state mono", testid: "trigger-state" }, "off");
    const levelBox = h("span", { class: "trigger-level-box" }, this.level, this.edge);
    const arm = h("button", { class: "btn primary", testid: "trigger-arm", title: "Arm the trigger (again)", onclick: () => this.apply() }, "Arm");
    for (const el of [this.source, this.edge, this.mode]) el.addEventListener("change", () => this.apply());
    for (const el of [this.level, this.pre]) el.addEventListener("change", () => this.apply());
    this.source.addEventListener("change", () => (levelBox.hidden = !this.source.value.startsWith("level:")));
    levelBox.hidden = true;
    this.triggerRow = h(
      "div",
      { class: "scope-row trigger-row", testid: "trigger-row", hidden: true },
      h("span", { class: "tb-label" }, "Trigger"),
      this.source,
      levelBox,
      h("label", { class: "arg" }, h("span", { class: "arg-name" }, "pre"), this.pre, h("span", { class: "unit" }, "%")),
      this.mode,
      arm,
      this.triggerState,
    );
    this.cursorRow = h("div", { class: "scope-row cursor-row", testid: "cursor-readout", hidden: true });
    this.channelsRow = h("div", { class: "scope-row channels-row", testid: "channels-row", hidden: true });
    this.readout = h("div", { class: "scope-rows" }, this.triggerRow, this.cursorRow, this.channelsRow);
    this.syncX();
  }

  private toggleRow(row: HTMLElement, button: HTMLElement): void {
    row.hidden = !row.hidden;
    toggleClass(button, "on", !row.hidden);
  }

  cursorTime(t: number | null): void {
    setText(this.time, t === null ? "" : `t ${this.stack.timeText(t)}`);
  }

  private setX(mode: "clock" | "rel"): void {
    this.stack.setXMode(mode);
    this.syncX();
  }

  private syncX(): void {
    toggleClass(this.xButtons.clock, "on", this.stack.xMode === "clock");
    toggleClass(this.xButtons.rel, "on", this.stack.xMode === "rel");
  }

  private toggleCursors(): void {
    const c = this.stack.cursors;
    c.on = !c.on;
    if (!c.on) this.stack.setCursors(null, null);
    toggleClass(this.cursorButton, "on", c.on);
    this.cursorRow.hidden = !c.on;
    this.syncCursors();
  }

  /** The Δ readout: A, B, Δt, 1/Δt and Δy of every drawn channel. */
  syncCursors(): void {
    const { a, b, on } = this.stack.cursors;
    if (!on) return;
    // [testid, label, text, title]: the DOM is rebuilt only when a text changed (this
    // runs on every redraw of the scope).
    const items: [string, string, string, string][] = [
      ["cursor-a", "A ", a === null ? "click a plot" : this.stack.timeText(a), ""],
      ["cursor-b", "B ", b === null ? (a === null ? "—" : "click again") : this.stack.timeText(b), ""],
    ];
    if (a !== null && b !== null) {
      const dt = b - a;
      items.push(["cursor-dt", "Δt ", `${dt.toFixed(4)} s`, ""], ["cursor-freq", "1/Δt ", dt === 0 ? "—" : `${(1 / Math.abs(dt)).toFixed(3)} Hz`, ""]);
      for (const { name, label } of this.stack.drawnChannels()) {
        const unit = this.stack.units.unit(name);
        const va = this.stack.valueAt(name, a);
        const vb = this.stack.valueAt(name, b);
        const dy = va === null || vb === null ? null : (vb - va) * unit.factor;
        items.push([`cursor-dy-${name}`, `Δ${label} `, `${formatValue(dy, unit)} ${unit.unit}`, `${label} at A and B`]);
      }
    }
    const key = items.map((i) => i.join("\u0001")).join("\u0002");
    if (key === this.cursorKey) return;
    this.cursorKey = key;
    replace(
      this.cursorRow,
      items.map(([testid, label, text, title]) => h("span", { class: "cur-item", testid, title: title || undefined }, h("b", null, label), text)),
    );
  }

  private apply(): void {
    const value = this.source.value;
    const t = this.stack.trigger;
    let source: TriggerSource | null = null;
    if (value.startsWith("flag:")) {
      const [, name, edge] = value.split(":");
      source = { kind: "flag", name: name as string, edge: edge as Edge };
    } else if (value.startsWith("level:")) {
      const name = value.slice(6);
      const factor = this.stack.units.unit(name).factor || 1;
      const level = Number(this.level.value);
      toggleClass(this.level, "invalid", !Number.isFinite(level));
      if (!Number.isFinite(level)) return;
      source = { kind: "level", name, edge: this.edge.value as Edge, level: level / factor };
    }
    const pre = Number(this.pre.value);
    const valid = Number.isFinite(pre) && pre >= 0 && pre <= 90;
    toggleClass(this.pre, "invalid", !valid);
    this.pre.title = valid ? "Share of the window before the trigger point, 0..90 %" : `pre-trigger = ${this.pre.value} is out of range: allowed 0..90 %`;
    t.config = { source, mode: this.mode.value === "normal" ? "normal" : "single", pre: valid ? pre / 100 : t.config.pre };
    if (!source) t.off();
    this.stack.rearm();
  }

  /** A single-shot capture completed. */
  fired(): void {
    this.syncTrigger();
  }

  syncTrigger(): void {
    const t = this.stack.trigger;
    let text = "off";
    if (t.active) {
      if (t.pendingT !== null) text = `recording from ${this.stack.timeText(t.pendingT)}`;
      else if (t.armed) text = t.capturedT === null ? "armed · waiting" : `captured ${this.stack.timeText(t.capturedT)} · armed`;
      else if (t.capturedT !== null) text = `captured ${this.stack.timeText(t.capturedT)} · single (Arm for another)`;
    }
    setText(this.triggerState, text);
    this.triggerState.dataset.state = !t.active ? "off" : t.capturedT !== null ? "captured" : "armed";
    toggleClass(this.triggerButton, "armed", t.active);
  }

  private toggleChannels(): void {
    this.toggleRow(this.channelsRow, this.channelsButton);
    if (this.channelsRow.hidden) return;
    const channels = this.stack.descriptor.channels.filter((c) => !Object.keys(c.value_names).length);
    replace(
      this.channelsRow,
      this.stack.linePlots().map((plot) =>
        h(
          "fieldset",
          { class: "channel-choice" },
          h("legend", null, plot.label),
          channels.map((c) => {
            const box = h("input", { type: "checkbox", checked: plot.series.includes(c.name), testid: `channel-${plot.name}-${c.name}` });
            box.addEventListener("change", () => {
              const now = this.stack.linePlots().find((p) => p.name === plot.name)?.series ?? [];
              const next = box.checked ? [...now, c.name] : now.filter((n) => n !== c.name);
              if (!next.length) {
                box.checked = true;
                return;
              }
              this.stack.setSeries(plot.name, next);
            });
            return h("label", { class: "channel-option", title: c.description }, box, ` ${c.label}`);
          }),
        ),
      ),
    );
  }

  /** The visible window, every channel (device units) and flag, as CSV. */
  exportCsv(): string {
    const s = this.stack;
    const b = s.view;
    const [min, max] = s.shown;
    const lo = Math.max(b.start, b.indexAt(min));
    const hi = Math.min(b.end, b.indexAt(max + 1e-9));
    const channels = s.descriptor.channels.map((c) => c.name).filter((n) => b.channels.has(n));
    const flags = s.descriptor.flags.map((f) => f.name).filter((n) => b.flags.has(n));
    const trig = s.trigger.active ? s.trigger.capturedT : null;
    const offset = store.clockOffsetS;
    const iso = (t: number): string => (Number.isFinite(offset) ? new Date((t + offset) * 1000).toISOString() : "");
    const lines = [
      `# servotune scope export: axis ${s.axisId} (${s.descriptor.model})`,
      `# window_s: ${min.toFixed(6)} .. ${max.toFixed(6)} (server clock), ${iso(min)} .. ${iso(max)}`,
      `# trigger_t_s: ${trig === null ? "none" : `${trig.toFixed(6)} (${iso(trig)})`}`,
      `# units: ${s.descriptor.channels.filter((c) => b.channels.has(c.name)).map((c) => `${c.name}=${c.unit || "-"}`).join(" ")}`,
      ["t_s", "wall_clock", "t_rel_trigger_s", ...channels, ...flags].join(","),
    ];
    for (let i = lo; i < hi; i++) {
      const t = b.t[i] as number;
      const row = [t.toFixed(6), iso(t), trig === null ? "" : (t - trig).toFixed(6)];
      for (const n of channels) {
        const v = (b.channels.get(n) as Float64Array)[i] as number;
        row.push(Number.isNaN(v) ? "" : String(v));
      }
      for (const n of flags) row.push(String((b.flags.get(n) as Uint8Array)[i]));
      lines.push(row.join(","));
    }
    const text = `${lines.join("\n")}\n`;
    const url = URL.createObjectURL(new Blob([text], { type: "text/csv" }));
    const a = h("a", { href: url, download: `${s.axisId}-scope-${new Date().toISOString().replace(/[:.]/g, "-")}.csv` });
    document.body.appendChild(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10_000);
    return text;
  }
}
