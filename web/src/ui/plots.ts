// The stacked, cursor-synced uPlot scopes of one axis, built from descriptor.plots.
// Data is cut from the axis' ring buffer once per animation frame (never per
// message): min/max per pixel column when dense, sample by sample with markers when
// sparse, gaps as gaps, slow channels held as steps (see decimate.ts). Flags are drawn
// as run bars straight from the buffer (cheap: a few rectangles, not a filled path).
// Scope controls: legend toggles, units on the y axes, time under the cursor, two Δ
// cursors, a trigger (trigger.ts), wheel and drag zoom, channel choice per plot (kept
// per device in localStorage), x as wall clock or relative time, CSV export.
import uPlot from "uplot";
import "uplot/dist/uPlot.min.css";
import type { AxisBuffer } from "../buffer";
import { h, replace, setText, toggleClass } from "../dom";
import { formatValue } from "../format";
import { StateNames } from "../states";
import { store } from "../store";
import type { UnitPrefs } from "../units";
import type { DeviceDescriptor, FlagDescriptor, PlotDescriptor } from "../wire.gen";
import { Cutter, flagRuns, GAP_PERIODS, medianPeriod, type Frame } from "./decimate";
import { ScopeTools } from "./scopetools";
import { drawStates, laneCount, lanePos, scanStates, stateAt, type StatesPanel, statesPx, statesRuns } from "./statesplot";
import { Trigger } from "./trigger";

export const WINDOWS_S = [5, 10, 30, 60] as const;
const LANE = 1; // height of a flag trace
const LANE_GAP = 0.55; // space between lanes
const LANE_PX = 17;
/** Lanes get thinner when a device has many flags, so line plots keep their room. */
const lanePx = (lanes: number): number => (lanes <= 8 ? LANE_PX : Math.max(13, Math.floor(150 / lanes)));
const Y_AXIS_PX = 68; // at least; wider (up to Y_AXIS_MAX_PX) for long lane labels
const Y_AXIS_MAX_PX = 116;
const Y_LABEL_PX = 14; // the unit, written along the y axis
const X_AXIS_PX = 26;
const HEADER_PX = 24;
const MIN_LINE_PX = 90;
/** Markers on the samples when they are at least this many pixels apart. */
export const MARKER_PX = 4;
const PHONE = "(max-width: 760px)";
/** Minimum interval between redraws of a rolling (live) trace: 30 Hz. */
const LIVE_REDRAW_MS = 32;

interface Theme {
  axis: string;
  grid: string;
  text: string;
  series: string[];
  severity: Record<FlagDescriptor["severity"], string>;
  font: string;
  cursor: string;
}

function css(name: string, fallback: string): string {
  const value = getComputedStyle(document.documentElement).getPropertyValue(name).trim();
  return value || fallback;
}

function readTheme(): Theme {
  return {
    axis: css("--plot-axis", "#8a96a3"),
    grid: css("--plot-grid", "#243040"),
    text: css("--text-dim", "#8a96a3"),
    series: [1, 2, 3, 4, 5, 6].map((i) => css(`--series-${i}`, "#4cc2ff")),
    severity: {
      info: css("--lamp-info", "#3fcf75"),
      warning: css("--lamp-warning", "#ffb020"),
      fault: css("--lamp-fault", "#ff4d4d"),
    },
    font: `11px ${css("--mono", "monospace")}`,
    cursor: css("--amber", "#ffae1f"),
  };
}

function decimals(incr: number): number {
  if (!Number.isFinite(incr) || incr <= 0) return 0;
  return Math.max(0, Math.min(6, -Math.floor(Math.log10(incr) + 1e-9)));
}

function axisNumber(v: number, incr: number): string {
  const abs = Math.abs(v);
  if (abs >= 1e6 && incr >= 1e5) return `${+(v / 1e6).toFixed(Math.max(0, decimals(incr / 1e6)))}M`;
  if (abs >= 1e4 && incr >= 1e3) return `${+(v / 1e3).toFixed(Math.max(0, decimals(incr / 1e3)))}k`;
  return v.toFixed(decimals(incr));
}

/** Wall-clock "14:03:22.125" of a server time (with ``digits`` decimals of seconds). */
export function clockText(serverT: number, digits: number): string {
  const offset = store.clockOffsetS;
  if (!Number.isFinite(offset)) return `${serverT.toFixed(digits)} s`;
  const ms = (serverT + offset) * 1000;
  const d = new Date(ms);
  const p = (n: number): string => String(n).padStart(2, "0");
  const frac = digits > 0 ? ((ms / 1000) % 1).toFixed(Math.min(3, digits)).slice(1) : "";
  return `${p(d.getHours())}:${p(d.getMinutes())}:${p(d.getSeconds())}${frac}`;
}

interface Panel {
  plot: PlotDescriptor;
  /** The series drawn (the user's channel choice, else the descriptor's). */
  series: string[];
  el: HTMLElement;
  host: HTMLElement;
  u: uPlot | null;
  legendValues: HTMLElement[];
  legendItems: HTMLElement[];
  unitButtons: HTMLButtonElement[];
  height: number;
  states: StatesPanel | null;
  /** Flag runs [t0, t1, …] per flag (flags plots). */
  runs: number[][];
  tab: HTMLButtonElement;
}

/** What the user chose per device: series per plot and hidden series. */
interface ScopePrefs {
  series: Record<string, string[]>;
  hidden: Record<string, string[]>;
  xMode: "clock" | "rel";
}


export class PlotStack {
  readonly el: HTMLElement;
  paused = false;
  windowS = 10;
  readonly trigger = new Trigger();
  /** The two Δ cursors (server time), null while not placed. */
  cursors: { a: number | null; b: number | null; next: "a" | "b"; on: boolean } = { a: null, b: null, next: "a", on: false };
  private zoom: [number, number] | null = null;
  private frozenEnd = Number.NaN;
  private readonly panels: Panel[] = [];
  private readonly theme = readTheme();
  private readonly scroller: HTMLElement;
  private readonly pauseButton: HTMLButtonElement;
  private readonly resetButton: HTMLButtonElement;
  private readonly windowButtons = new Map<number, HTMLButtonElement>();
  private readonly status: HTMLElement;
  private readonly observer: ResizeObserver;
  private readonly tabs: HTMLElement;
  readonly tools: ScopeTools;
  private drawnVersion = -1;
  private readonly cutter = new Cutter();
  private readonly channelFactors = new Map<string, number>();
  private readonly flat = [0, 0];
  private statusState = "";
  private statusAt = 0;
  private skipUntil = 0;
  private lastLiveDraw = 0;
  /** Duration of the last redraw (ms). */
  lastDrawMs = 0;
  private dirty = true;
  private width = 0;
  private hovering = false;
  private dragSource: uPlot | null = null;
  private downX = Number.NaN;
  private readonly syncKey: string;
  private readonly flagByName: Map<string, FlagDescriptor>;
  private readonly yAxisPx: number;
  private readonly light = document.documentElement.dataset.theme === "light";
  /** The frame drawn last and the x range shown. */
  frame: Frame | null = null;
  shown: [number, number] = [0, 0];
  private readonly prefsKey: string;
  private prefs: ScopePrefs;
  private readonly phone = window.matchMedia?.(PHONE);
  private current = 0; // the plot shown on a phone

  constructor(
    readonly descriptor: DeviceDescriptor,
    readonly buffer: AxisBuffer,
    readonly units: UnitPrefs,
    readonly axisId: string,
    signal: AbortSignal,
  ) {
    this.syncKey = `scope-${axisId}`;
    this.prefsKey = `servotune.scope.${descriptor.device}`;
    this.prefs = this.loadPrefs();
    this.flagByName = new Map(descriptor.flags.map((f) => [f.name, f]));
    this.yAxisPx = this.axisWidth(descriptor);
    this.pauseButton = h("button", { class: "btn", testid: "scope-pause", onclick: () => this.togglePause() });
    this.resetButton = h(
      "button",
      { class: "btn", testid: "scope-reset-zoom", title: "Show the whole window again (or double-click a plot)", onclick: () => this.resetZoom() },
      "Reset zoom",
    );
    const windows = h(
      "div",
      { class: "seg", role: "group", "aria-label": "Window length" },
      WINDOWS_S.map((s) => {
        const b = h("button", { class: "seg-btn", testid: `scope-window-${s}`, onclick: () => this.setWindow(s) }, `${s} s`);
        this.windowButtons.set(s, b);
        return b;
      }),
    );
    this.status = h("span", { class: "scope-status", testid: "scope-status" });
    this.tabs = h("div", { class: "seg plot-tabs", role: "tablist", "aria-label": "Plot shown" });
    this.tools = new ScopeTools(this);
    const toolbar = h(
      "div",
      { class: "scope-toolbar" },
      this.pauseButton,
      h("span", { class: "tb-label" }, "Window"),
      windows,
      this.resetButton,
      this.tools.el,
      h("span", { class: "tb-spacer" }),
      this.status,
    );
    this.scroller = h("div", { class: "scope-plots" });
    this.el = h("div", { class: "scope", testid: "scope" }, toolbar, this.tools.readout, this.tabs, this.scroller);
    descriptor.plots.forEach((plot, i) => this.panels.push(this.makePanel(plot, i)));
    this.syncSingle();
    this.syncControls();
    units.onChange(() => {
      for (const panel of this.panels) this.syncUnitButtons(panel);
      this.rebuild();
    }, signal);
    this.phone?.addEventListener("change", () => {
      this.syncSingle();
      this.rebuild();
    });
    this.observer = new ResizeObserver(() => this.layout());
    this.observer.observe(this.scroller);
    signal.addEventListener("abort", () => this.destroy(), { once: true });
  }

  private loadPrefs(): ScopePrefs {
    const prefs: ScopePrefs = { series: {}, hidden: {}, xMode: "clock" };
    try {
      const saved = JSON.parse(localStorage.getItem(this.prefsKey) ?? "{}") as Partial<ScopePrefs>;
      if (saved.series && typeof saved.series === "object") prefs.series = saved.series;
      if (saved.hidden && typeof saved.hidden === "object") prefs.hidden = saved.hidden;
      if (saved.xMode === "rel") prefs.xMode = "rel";
    } catch {
      /* a broken entry: defaults */
    }
    return prefs;
  }

  savePrefs(): void {
    try {
      localStorage.setItem(this.prefsKey, JSON.stringify(this.prefs));
    } catch {
      /* private mode */
    }
  }

  get xMode(): "clock" | "rel" {
    return this.prefs.xMode;
  }

  setXMode(mode: "clock" | "rel"): void {
    this.prefs.xMode = mode;
    this.savePrefs();
    this.dirty = true;
    this.update();
  }

  /** Line plots a user may re-choose channels for, with their current series. */
  linePlots(): { name: string; label: string; series: string[] }[] {
    return this.panels.filter((p) => p.plot.kind === "line").map((p) => ({ name: p.plot.name, label: p.plot.label, series: p.series }));
  }

  /** Show ``series`` in the line plot ``plotName`` (kept per device). */
  setSeries(plotName: string, series: string[]): void {
    const i = this.panels.findIndex((p) => p.plot.name === plotName);
    const old = this.panels[i];
    if (!old || !series.length) return;
    const descriptorSeries = old.plot.series;
    if (series.length === descriptorSeries.length && series.every((s, k) => s === descriptorSeries[k])) delete this.prefs.series[plotName];
    else this.prefs.series[plotName] = series;
    this.savePrefs();
    old.u?.destroy();
    const fresh = this.makePanel(old.plot, i);
    old.el.replaceWith(fresh.el);
    old.tab.replaceWith(fresh.tab);
    this.panels[i] = fresh;
    this.syncSingle();
    this.rebuild();
  }

  private makePanel(plot: PlotDescriptor, index: number): Panel {
    const host = h("div", { class: "plot-host", testid: `plot-${plot.name}` });
    const legendValues: HTMLElement[] = [];
    const legendItems: HTMLElement[] = [];
    const unitButtons: HTMLButtonElement[] = [];
    const known = new Set(this.descriptor.channels.map((c) => c.name));
    const chosen = plot.kind === "line" ? (this.prefs.series[plot.name] ?? []).filter((n) => known.has(n)) : [];
    const series = chosen.length ? chosen : plot.series;
    const header = h("div", { class: "plot-header" }, h("span", { class: "plot-title", title: plot.label }, plot.label));
    let states: StatesPanel | null = null;
    const hidden = new Set(this.prefs.hidden[plot.name] ?? []);
    if (plot.kind === "line") {
      const legend = h("div", { class: "plot-legend" });
      series.forEach((name, i) => {
        const channel = this.units.channel(name);
        const value = h("span", { class: "legend-value", testid: `legend-${plot.name}-${name}` }, "—");
        legendValues.push(value);
        const item = h(
          "button",
          {
            class: hidden.has(name) ? "legend-item off" : "legend-item",
            testid: `legend-toggle-${plot.name}-${name}`,
            title: `${channel?.description ?? name}\nClick to hide or show this trace`,
            "aria-pressed": hidden.has(name) ? "false" : "true",
            onclick: () => this.toggleSeries(plot.name, name),
          },
          h("span", { class: "swatch", style: `background:${this.color(i)}` }),
          h("span", { class: "legend-label" }, channel?.label ?? name),
          value,
        );
        legendItems.push(item);
        legend.appendChild(item);
      });
      header.appendChild(legend);
      const choices = this.units.common(series);
      if (choices.length > 1) {
        const seg = h("div", { class: "seg small", title: "Display unit" });
        for (const unit of choices) {
          const b = h("button", { class: "seg-btn", testid: `unit-${plot.name}-${unit}`, onclick: () => this.units.set(series, unit) }, unit);
          b.dataset.unit = unit;
          unitButtons.push(b);
          seg.appendChild(b);
        }
        header.appendChild(seg);
      } else {
        header.appendChild(h("span", { class: "plot-unit" }, this.units.unit(series[0] ?? "").unit || plot.unit));
      }
    } else if (plot.kind === "states") {
      const name = plot.series[0] ?? "";
      const channel = this.units.channel(name);
      // A states plot of a channel without value_names still gets lanes (named by id).
      const names = new StateNames(channel ?? { name, label: name, unit: "", description: "", conversions: [], value_names: {} });
      const swatch = h("span", { class: "swatch state-swatch" });
      const value = h("span", { class: "legend-value state-value", testid: `plot-${plot.name}-state` }, "—");
      const id = h("span", { class: "state-id" }, "");
      legendValues.push(value);
      header.appendChild(
        h(
          "div",
          { class: "plot-legend" },
          h("span", { class: "legend-item", title: channel?.description ?? name }, swatch, h("span", { class: "legend-label" }, channel?.label ?? name), value, id),
        ),
      );
      header.appendChild(
        h(
          "span",
          { class: "plot-unit", title: `One lane per state seen since this page opened (sampled values: short states may be missed). All named states:\n${names.values.map((v) => `${names.id(v)} ${names.name(v)}`).join("\n")}` },
          "states",
        ),
      );
      states = { channel: name, names, seen: new Set(), lanes: [], scannedT: Number.NEGATIVE_INFINITY, x: [], values: [], swatch, id };
    } else {
      header.appendChild(h("span", { class: "plot-unit" }, "status flags"));
    }
    const el = h("div", { class: `plot-panel kind-${plot.kind}` }, header, host);
    const tab = h("button", { class: "seg-btn", role: "tab", testid: `plot-tab-${plot.name}`, onclick: () => this.showPlot(index) }, plot.label);
    if (index >= this.panels.length) {
      this.scroller.appendChild(el);
      this.tabs.appendChild(tab);
    }
    if (states) scanStates(this.buffer, states);
    const panel: Panel = { plot, series, el, host, u: null, legendValues, legendItems, unitButtons, height: 0, states, runs: [], tab };
    this.syncUnitButtons(panel);
    return panel;
  }

  private toggleSeries(plotName: string, name: string): void {
    const hidden = new Set(this.prefs.hidden[plotName] ?? []);
    if (hidden.has(name)) hidden.delete(name);
    else hidden.add(name);
    this.prefs.hidden[plotName] = [...hidden];
    this.savePrefs();
    const panel = this.panels.find((p) => p.plot.name === plotName);
    if (!panel) return;
    panel.series.forEach((n, i) => {
      const item = panel.legendItems[i];
      if (item) {
        toggleClass(item, "off", hidden.has(n));
        item.setAttribute("aria-pressed", hidden.has(n) ? "false" : "true");
      }
      panel.u?.setSeries(i + 1, { show: !hidden.has(n) });
    });
  }

  private isHidden(plotName: string, name: string): boolean {
    return (this.prefs.hidden[plotName] ?? []).includes(name);
  }

  /** Phones: one plot at a time, chosen with the tabs. */
  private get single(): boolean {
    return this.phone?.matches ?? false;
  }

  private syncSingle(): void {
    toggleClass(this.el, "single", this.single);
    this.current = Math.min(this.current, this.panels.length - 1);
    this.panels.forEach((p, i) => {
      toggleClass(p.el, "current", i === this.current);
      toggleClass(p.tab, "on", i === this.current);
      p.tab.setAttribute("aria-selected", i === this.current ? "true" : "false");
    });
  }

  showPlot(index: number): void {
    this.current = index;
    this.syncSingle();
    this.rebuild();
  }

  private shows(p: Panel): boolean {
    return !this.single || this.panels[this.current] === p;
  }

  private syncUnitButtons(panel: Panel): void {
    const current = this.units.unit(panel.series[0] ?? "").unit;
    for (const b of panel.unitButtons) toggleClass(b, "on", b.dataset.unit === current);
  }

  private color(i: number): string {
    return this.theme.series[i % this.theme.series.length] as string;
  }

  /** Heights: flag and states plots get their lanes, line plots share the rest. */
  private layout(redraw = true): void {
    const width = Math.floor(this.scroller.clientWidth);
    const height = Math.floor(this.scroller.clientHeight);
    if (width < 50 || height < 50) return;
    const visible = this.panels.filter((p) => this.shows(p));
    const last = visible[visible.length - 1];
    let fixed = 0;
    let lines = 0;
    const fixedPx = (p: Panel): number | null =>
      this.single ? null : p.plot.kind === "flags" ? p.plot.series.length * lanePx(p.plot.series.length) + 8 : p.states ? statesPx(p.states) : null;
    for (const p of visible) {
      fixed += HEADER_PX + 6 + (p === last ? X_AXIS_PX : 4);
      const px = fixedPx(p);
      if (px !== null) fixed += px;
      else lines += 1;
    }
    const each = lines ? Math.max(MIN_LINE_PX, Math.floor((height - fixed - 2) / lines)) : 0;
    let changed = width !== this.width;
    for (const p of this.panels) {
      const axisPx = p === last ? X_AXIS_PX : 4;
      const total = (fixedPx(p) ?? each) + axisPx;
      if (total !== p.height) changed = true;
      p.height = total;
    }
    this.width = width;
    if (!changed) return;
    for (const p of this.panels) {
      if (p.u) p.u.setSize({ width: this.width, height: p.height });
      else this.create(p);
    }
    this.dirty = true;
    if (redraw) this.update();
  }

  /** The y axis fits the longest lane label (flags, states), within limits. */
  private axisWidth(descriptor: DeviceDescriptor): number {
    const labels: string[] = [];
    for (const plot of descriptor.plots) {
      if (plot.kind === "flags") labels.push(...plot.series.map((n) => this.flagByName.get(n)?.label ?? n));
      if (plot.kind === "states") {
        for (const n of plot.series) labels.push(...Object.values(descriptor.channels.find((c) => c.name === n)?.value_names ?? {}));
      }
    }
    const widest = Math.max(0, ...labels.map((l) => this.textWidth(l)));
    return Math.round(Math.min(Y_AXIS_MAX_PX, Math.max(Y_AXIS_PX, widest + 10)));
  }

  private measure: CanvasRenderingContext2D | null = null;

  private textWidth(text: string): number {
    if (!this.measure) {
      this.measure = document.createElement("canvas").getContext("2d");
      if (this.measure) this.measure.font = this.theme.font;
    }
    return this.measure ? this.measure.measureText(text).width : text.length * 7;
  }

  /** A lane label cut to the axis width ("NOT_CALIBRA…"). */
  private fitLabel(text: string): string {
    const room = this.yAxisPx - 8;
    if (this.textWidth(text) <= room) return text;
    let cut = text;
    while (cut.length > 1 && this.textWidth(`${cut}…`) > room) cut = cut.slice(0, -1);
    return `${cut}…`;
  }

  private showState(panel: Panel, value: number | null | undefined): void {
    const s = panel.states;
    const el = panel.legendValues[0];
    if (!s || !el) return;
    const known = value !== null && value !== undefined;
    setText(el, known ? s.names.name(value) : "—");
    setText(s.id, known && s.names.has(value) ? s.names.id(value) : "");
    const color = known ? s.names.color(value, this.light) : "transparent";
    if (s.swatch.dataset.color !== color) {
      s.swatch.dataset.color = color;
      s.swatch.style.background = color;
    }
    const title = known ? s.names.describe(value) : "";
    if (el.title !== title) el.title = title;
  }

  private rebuild(): void {
    for (const p of this.panels) {
      p.u?.destroy();
      p.u = null;
      replace(p.host);
    }
    this.width = 0;
    this.layout();
    this.dirty = true;
    this.update();
  }

  /** Whether markers are drawn: samples in the window at least MARKER_PX apart. */
  private sparse(): boolean {
    const f = this.frame;
    if (!f || f.decimated) return false;
    const [min, max] = this.shown;
    const period = Number.isFinite(f.periodS) ? f.periodS : max - min;
    const px = ((this.width - this.yAxisPx - Y_LABEL_PX) * period) / Math.max(1e-9, max - min);
    return px >= MARKER_PX;
  }

  private create(panel: Panel): void {
    const { plot } = panel;
    const theme = this.theme;
    const visible = this.panels.filter((p) => this.shows(p));
    const isLast = panel === visible[visible.length - 1];
    const flags = plot.kind === "flags";
    const states = panel.states;
    const lanes = plot.series.length;
    const laneBase = (i: number): number => (lanes - 1 - i) * (LANE + LANE_GAP);
    const unitOf = (name: string) => this.units.unit(name);
    const series: uPlot.Series[] = [{ label: "t" }];
    const stepped = uPlot.paths.stepped?.({ align: 1 });
    const linear = uPlot.paths.linear?.();
    if (states || flags) {
      // Bars (and the state step connectors) are drawn by drawStates / drawFlags from
      // the buffer; the one series only carries x for the cursor sync.
      series.push({ label: plot.label, stroke: "transparent", width: 0, paths: () => null, points: { show: false } });
    } else {
      panel.series.forEach((name, i) => {
        series.push({
          label: this.units.channel(name)?.label ?? name,
          stroke: this.color(i),
          // 1 px: software rasterisers (no GPU) draw a 1 px line as a hairline, several
          // times cheaper than a wider stroke, which must be outlined and filled.
          width: 1,
          show: !this.isHidden(plot.name, name),
          spanGaps: false,
          // Slow channels hold their value until the next real sample: a step, not a
          // line that seems to lead the fast ones.
          paths: (u, si, i0, i1) => (this.frame?.slow.has(name) ? stepped : linear)?.(u, si, i0, i1) ?? null,
          points: {
            size: 5,
            fill: this.color(i),
            show: () => !this.frame?.slow.has(name) && this.sparse(),
            filter: () => this.slowMarkers(name),
          },
          value: (_u, v) => formatValue(v, unitOf(name)),
        });
      });
    }
    const xAxis: uPlot.Axis = {
      stroke: theme.axis,
      font: theme.font,
      grid: { stroke: theme.grid, width: 1 },
      ticks: { stroke: theme.grid, width: 1, size: isLast ? 4 : 0 },
      space: this.prefs.xMode === "clock" ? 96 : 70,
      size: isLast ? X_AXIS_PX : 4,
      gap: 2,
      values: isLast ? (_u, splits, _ai, _space, incr) => splits.map((v) => this.xText(v, incr)) : (_u, splits) => splits.map(() => ""),
    };
    const label = !flags && !states ? this.units.unit(panel.series[0] ?? "").unit || plot.unit : "";
    const yCommon = { font: theme.font, size: this.yAxisPx, gap: 4, label, labelSize: Y_LABEL_PX, labelGap: 0, labelFont: theme.font };
    const yAxis: uPlot.Axis = states
      ? {
          ...yCommon,
          stroke: theme.text,
          grid: { show: false },
          ticks: { show: false },
          splits: () => states.lanes.map((v) => lanePos(states, v)),
          values: (_u, splits) =>
            splits.map((pos) => {
              const value = states.lanes[laneCount(states) - 1 - pos];
              return value === undefined ? "" : this.fitLabel(states.names.name(value));
            }),
        }
      : flags
        ? {
            ...yCommon,
            stroke: theme.text,
            grid: { show: false },
            ticks: { show: false },
            splits: () => plot.series.map((_n, i) => laneBase(i) + LANE / 2),
            values: (_u, splits) =>
              splits.map((_v, i) => {
                const name = plot.series[i] ?? "";
                return this.fitLabel(this.flagByName.get(name)?.label ?? name);
              }),
          }
        : {
            ...yCommon,
            stroke: theme.axis,
            space: 18,
            grid: { stroke: theme.grid, width: 1 },
            ticks: { stroke: theme.grid, width: 1, size: 3 },
            values: (_u, splits, _ai, _space, incr) => splits.map((v) => axisNumber(v, incr)),
          };
    const opts: uPlot.Options = {
      width: this.width,
      height: panel.height,
      legend: { show: false },
      padding: [flags || states ? 4 : 9, 10, 0, 0],
      cursor: {
        sync: { key: this.syncKey, setSeries: false },
        drag: { x: true, y: false, setScale: false },
        points: states || flags ? { show: false } : { size: 5, fill: (u, si) => (u.series[si]?.stroke as (u: uPlot, si: number) => string)?.(u, si) },
        focus: { prox: -1 },
      },
      scales: {
        x: { time: false },
        y: states
          ? { auto: true, range: () => [-0.5, laneCount(states) - 0.5] }
          : flags
            ? { auto: false, range: [-0.35, laneBase(0) + LANE + 0.35] }
            : {
                auto: true,
                range: (_u, min, max) => {
                  if (!Number.isFinite(min) || !Number.isFinite(max)) return [-1, 1];
                  if (max - min < 1e-9) {
                    const pad = Math.max(Math.abs(max) * 0.05, 1);
                    return [min - pad, max + pad];
                  }
                  const pad = (max - min) * 0.08;
                  return [min - pad, max + pad];
                },
              },
      },
      axes: [xAxis, yAxis],
      series,
      hooks: {
        setSelect: [(u) => this.onSelect(u)],
        setCursor: [(u) => this.onCursor(panel, u)],
        drawAxes: states ? [(u) => drawStates(u, states, this.theme, this.light, css("--mono", "monospace"))] : flags ? [(u) => this.drawFlags(panel, u)] : [],
        draw: [(u) => this.drawCursors(u)],
      },
    };
    const empty: uPlot.AlignedData = [[], ...series.slice(1).map(() => [] as number[])];
    panel.u = new uPlot(opts, empty, panel.host);
    const u = panel.u;
    // Synced plots mirror the selection; only the plot that was dragged on zooms.
    u.over.addEventListener("mousedown", (e) => {
      this.dragSource = u;
      this.downX = e.clientX;
    });
    u.over.addEventListener("click", (e) => {
      if (Math.abs(e.clientX - this.downX) > 3) return;
      if (this.cursors.on) this.placeCursor(u.posToVal(e.offsetX, "x"));
    });
    u.over.addEventListener("dblclick", () => this.resetZoom());
    u.over.addEventListener("wheel", (e) => this.onWheel(u, e), { passive: false });
    u.over.addEventListener("mouseenter", () => (this.hovering = true));
    u.over.addEventListener("mouseleave", () => {
      this.hovering = false;
      this.tools.cursorTime(null);
      this.refreshLegend();
    });
  }

  /** Indices of the real samples of a slow channel, when they are far enough apart. */
  private slowMarkers(name: string): number[] | null {
    const f = this.frame;
    const real = f?.real.get(name);
    if (!f || !real || !f.slow.has(name)) return null;
    const [min, max] = this.shown;
    const px = ((this.width - this.yAxisPx) * (f.slow.get(name) as number)) / Math.max(1e-9, max - min);
    return px >= MARKER_PX ? real : null;
  }

  /** x tick text: wall clock, or seconds relative to the trigger point or the right edge. */
  private xText(v: number, incr: number): string {
    if (this.prefs.xMode === "clock") return clockText(v, decimals(incr));
    const ref = this.trigger.capturedT ?? this.shown[1];
    const rel = v - ref;
    return `${rel > 0 ? "+" : ""}${rel.toFixed(decimals(incr))} s`;
  }

  /** Cursor time as shown in the readouts. */
  timeText(t: number): string {
    if (this.prefs.xMode === "clock") return clockText(t, 3);
    const ref = this.trigger.capturedT ?? this.shown[1];
    return `${(t - ref).toFixed(3)} s`;
  }

  /** Run bars of the flags, one lane each, straight from the buffer. */
  private drawFlags(panel: Panel, u: uPlot): void {
    const ctx = u.ctx;
    const { left, top, width, height } = u.bbox;
    const px = devicePixelRatio || 1;
    const lanes = panel.plot.series.length;
    ctx.save();
    ctx.beginPath();
    ctx.rect(left, top, width, height);
    ctx.clip();
    panel.plot.series.forEach((name, i) => {
      const base = (lanes - 1 - i) * (LANE + LANE_GAP);
      const y0 = u.valToPos(base, "y", true);
      const y1 = u.valToPos(base + LANE, "y", true);
      ctx.fillStyle = this.theme.grid;
      ctx.fillRect(left, Math.round(y0) - px, width, px);
      const severity = this.flagByName.get(name)?.severity ?? "info";
      ctx.fillStyle = this.theme.severity[severity];
      const runs = panel.runs[i] ?? [];
      for (let k = 0; k + 1 < runs.length; k += 2) {
        const x0 = u.valToPos(runs[k] as number, "x", true);
        const x1 = u.valToPos(runs[k + 1] as number, "x", true);
        if (x1 < left || x0 > left + width) continue;
        ctx.fillRect(x0, y1, Math.max(px, x1 - x0), y0 - y1);
      }
    });
    ctx.restore();
  }

  /** The Δ cursors on every plot: vertical lines A and B. */
  private drawCursors(u: uPlot): void {
    const { a, b } = this.cursors;
    if (a === null && b === null) return;
    const ctx = u.ctx;
    const { left, top, width, height } = u.bbox;
    const px = devicePixelRatio || 1;
    ctx.save();
    ctx.strokeStyle = this.theme.cursor;
    ctx.fillStyle = this.theme.cursor;
    ctx.lineWidth = px;
    ctx.font = `bold ${10 * px}px ${css("--mono", "monospace")}`;
    for (const [name, t] of [["A", a], ["B", b]] as const) {
      if (t === null) continue;
      const x = Math.round(u.valToPos(t, "x", true)) + 0.5;
      if (x < left || x > left + width) continue;
      ctx.setLineDash(name === "A" ? [] : [4 * px, 3 * px]);
      ctx.beginPath();
      ctx.moveTo(x, top);
      ctx.lineTo(x, top + height);
      ctx.stroke();
      ctx.fillText(name, x + 3 * px, top + 10 * px);
    }
    ctx.restore();
  }

  /** Put the next Δ cursor on the sample nearest to ``t``. */
  placeCursor(t: number): void {
    const snapped = this.nearestSampleT(t);
    if (snapped === null) return;
    this.cursors[this.cursors.next] = snapped;
    this.cursors.next = this.cursors.next === "a" ? "b" : "a";
    this.redrawOverlays();
  }

  setCursors(a: number | null, b: number | null): void {
    this.cursors.a = a;
    this.cursors.b = b;
    this.cursors.next = "a";
    this.redrawOverlays();
  }

  redrawOverlays(): void {
    for (const p of this.panels) if (this.shows(p)) p.u?.redraw(false, false);
    this.tools.syncCursors();
  }

  nearestSampleT(t: number): number | null {
    const b = this.buffer;
    if (!b.length) return null;
    const i = Math.min(b.end - 1, Math.max(b.start, b.indexAt(t)));
    const j = Math.max(b.start, i - 1);
    const ti = b.t[i] as number;
    const tj = b.t[j] as number;
    return Math.abs(ti - t) <= Math.abs(tj - t) ? ti : tj;
  }

  /** The latest real value of ``name`` at or before ``t`` (device units), or null. */
  valueAt(name: string, t: number): number | null {
    const b = this.buffer;
    const col = b.channels.get(name);
    if (!col || !b.length) return null;
    let i = Math.min(b.end - 1, b.indexAt(t + 1e-9) - 1);
    for (let k = 0; i >= b.start && k < 4096; i--, k++) {
      const v = col[i] as number;
      if (!Number.isNaN(v)) return v;
    }
    return null;
  }

  /** Channels drawn now (visible line series), with their plot. */
  drawnChannels(): { name: string; label: string }[] {
    const out: { name: string; label: string }[] = [];
    for (const p of this.panels) {
      if (p.plot.kind !== "line") continue;
      for (const name of p.series) if (!this.isHidden(p.plot.name, name)) out.push({ name, label: this.units.channel(name)?.label ?? name });
    }
    return out;
  }

  private onWheel(u: uPlot, e: WheelEvent): void {
    e.preventDefault();
    const [min, max] = this.shown;
    if (!(max > min)) return;
    const c = u.posToVal(e.offsetX, "x");
    const f = e.deltaY > 0 ? 1.25 : 0.8;
    const lo = c - (c - min) * f;
    const hi = c + (max - c) * f;
    if (hi - lo < 1e-3) return;
    if (!this.paused) this.pause();
    this.zoom = [lo, hi];
    this.dirty = true;
    this.syncControls();
    this.update();
  }

  private onSelect(u: uPlot): void {
    const { left, width } = u.select;
    if (width < 4 || u !== this.dragSource) return;
    this.dragSource = null;
    const min = u.posToVal(left, "x");
    const max = u.posToVal(left + width, "x");
    // Clear after the synced plots have mirrored the selection.
    requestAnimationFrame(() => {
      for (const p of this.panels) p.u?.setSelect({ left: 0, top: 0, width: 0, height: 0 }, false);
    });
    if (!(max > min)) return;
    if (!this.paused) this.pause();
    this.zoom = [min, max];
    this.dirty = true;
    this.syncControls();
    this.update();
  }

  private onCursor(panel: Panel, u: uPlot): void {
    const left = u.cursor.left;
    if (left !== undefined && left >= 0 && u.over.matches(":hover")) this.tools.cursorTime(u.posToVal(left, "x"));
    const idx = u.cursor.idx;
    if (panel.states) {
      if (left !== undefined && left >= 0) this.showState(panel, stateAt(panel.states, u.posToVal(left, "x")));
      return;
    }
    if (idx === null || idx === undefined || panel.plot.kind !== "line") return;
    panel.series.forEach((name, i) => {
      const column = u.data[i + 1];
      // Slow channels are held: the value shown is their latest real sample.
      const value = column?.[idx];
      const el = panel.legendValues[i];
      if (el) setText(el, formatValue(value ?? null, this.units.unit(name)));
    });
  }

  /** Latest values in the legends while the cursor is not over a plot; a slow value with its age. */
  refreshLegend(): void {
    const stale = store.ws.kind !== "open";
    toggleClass(this.el, "stale", stale);
    if (stale) {
      setText(this.status, "stale · disconnected");
      this.status.dataset.stale = "1";
    } else if (this.status.dataset.stale) {
      delete this.status.dataset.stale;
      this.dirty = true;
    }
    if (this.hovering) return;
    for (const p of this.panels) {
      if (p.states) this.showState(p, this.buffer.latest.get(p.states.channel));
      if (p.plot.kind !== "line") continue;
      p.series.forEach((name, i) => {
        const el = p.legendValues[i];
        if (!el) return;
        const unit = this.units.unit(name);
        const raw = this.buffer.latest.get(name);
        const at = this.buffer.latestT.get(name);
        const age = at === undefined ? 0 : this.buffer.lastT - at;
        const text = formatValue(raw === undefined ? null : raw * unit.factor, unit);
        // A value older than a few base periods says how old it is.
        const period = this.frame?.periodS ?? 0.1;
        setText(el, age > GAP_PERIODS * period ? `${text} · ${age.toFixed(1)} s old` : text);
      });
    }
  }

  togglePause(): void {
    if (this.paused) this.resume();
    else this.pause();
  }

  pause(): void {
    this.paused = true;
    this.frozenEnd = this.shown[1] || this.buffer.lastT;
    this.syncControls();
  }

  resume(): void {
    this.paused = false;
    this.zoom = null;
    this.dirty = true;
    this.syncControls();
    this.update();
  }

  resetZoom(): void {
    this.zoom = null;
    this.dirty = true;
    this.syncControls();
    this.update();
  }

  setWindow(seconds: number): void {
    this.windowS = seconds;
    this.zoom = null;
    this.dirty = true;
    this.syncControls();
    this.update();
  }

  /** Trigger settings changed: (re)arm, and show the live trace until it fires. */
  rearm(): void {
    this.trigger.capturedT = null;
    this.trigger.arm(this.buffer);
    if (this.paused) {
      this.paused = false;
      this.zoom = null;
    }
    this.dirty = true;
    this.syncControls();
    this.update();
  }

  private syncControls(): void {
    replace(this.pauseButton, h("span", { class: "icon" }, this.paused ? "▶" : "❚❚"), this.paused ? " Resume" : " Pause");
    toggleClass(this.pauseButton, "active", this.paused);
    this.resetButton.disabled = this.zoom === null;
    for (const [s, b] of this.windowButtons) toggleClass(b, "on", s === this.windowS);
    this.el.dataset.paused = this.paused ? "1" : "0";
    this.tools.syncTrigger();
  }

  /** The x range to show now, and whether it follows the live data. */
  private range(): { min: number; max: number; live: boolean } {
    if (this.zoom) return { min: this.zoom[0], max: this.zoom[1], live: false };
    const captured = this.trigger.active ? this.trigger.window(this.windowS) : null;
    if (captured) return { min: captured[0], max: captured[1], live: false };
    const end = this.paused ? this.frozenEnd : this.buffer.lastT;
    // Before the server's clock has run a whole window, sweep from 0 like a scope.
    if (!Number.isFinite(end)) return { min: 0, max: this.windowS, live: !this.paused };
    if (end < this.windowS) return { min: 0, max: this.windowS, live: !this.paused };
    return { min: end - this.windowS, max: end, live: !this.paused };
  }

  /** Pixel columns of the plot area (one min/max pair each when dense). */
  private columns(): number {
    return Math.max(50, Math.floor(this.width - this.yAxisPx - Y_LABEL_PX));
  }

  /** Redraw now, whatever changed (benchmark, tests). */
  redraw(): void {
    this.dirty = true;
    this.skipUntil = 0;
    this.update();
  }

  /** Called once per animation frame; redraws only if something changed. A redraw
   * that took long makes the next one wait as long again (at most half of the main
   * thread for the scope), so input and the STOP button never queue behind plots. */
  update(): void {
    if (!this.width || this.panels.some((p) => this.shows(p) && !p.u)) return;
    const started = performance.now();
    if (started < this.skipUntil) return;
    if (this.trigger.poll(this.buffer, this.windowS)) {
      this.dirty = true;
      if (this.trigger.config.mode === "single") this.tools.fired();
      this.syncControls();
    }
    const columns = this.columns();
    const range = this.range();
    const { live } = range;
    let { min, max } = range;
    let origin = min;
    const colS = (max - min) / columns;
    if (live && min > 0) {
      // A rolling trace sits on pixel columns fixed in time (origin 0): each redraw
      // scrolls by whole columns and the column cache (decimate.ts) only folds in what
      // is new. The newest sample is at most one column from the right edge.
      max = Math.ceil(max / colS - 1e-9) * colS;
      min = max - this.windowS;
      origin = 0;
    }
    if (live && this.buffer.version === this.drawnVersion && !this.dirty) return;
    // A rolling trace redraws at most every LIVE_REDRAW_MS and at most once per pixel
    // column of time (a 60 s window moves 1 px per ~55 ms: redrawing faster shows
    // nothing new). With software canvases (no GPU) the raster of every redraw is most
    // of a frame's cost.
    if (live && !this.dirty && started - this.lastLiveDraw < Math.max(LIVE_REDRAW_MS, 1000 * colS)) return;
    if (live) this.lastLiveDraw = started;
    if (!live && !this.dirty) return;
    this.dirty = false;
    this.drawnVersion = this.buffer.version;
    this.shown = [min, max];
    const buffer = this.buffer;
    // One sample either side so lines run to the plot edges.
    const lo = Math.max(buffer.start, buffer.indexAt(min) - 1);
    const hi = Math.min(buffer.end, buffer.indexAt(max) + 1);
    const channels = this.channelFactors;
    channels.clear();
    for (const p of this.panels) {
      if (p.plot.kind !== "line" || !this.shows(p)) continue;
      for (const name of p.series) channels.set(name, this.units.unit(name).factor);
    }
    const frame = this.cutter.cut(buffer, lo, hi, min, max, columns, channels, origin);
    this.frame = frame;
    const gapS = GAP_PERIODS * (Number.isFinite(frame.periodS) ? frame.periodS : medianPeriod(buffer.t, lo, hi) || 1);
    let newLanes = false;
    for (const p of this.panels) if (p.states && scanStates(this.buffer, p.states)) newLanes = true;
    if (newLanes) this.layout(false);
    const flat = this.flat;
    flat[0] = min;
    flat[1] = max;
    for (const p of this.panels) {
      if (!this.shows(p)) continue;
      const u = p.u as uPlot;
      const s = p.states;
      if (s) {
        statesRuns(this.buffer, s, lo, hi);
        const ys = s.values.map((v) => lanePos(s, v));
        u.batch(() => {
          u.setData([s.x, ys] as uPlot.AlignedData, false);
          u.setScale("x", { min, max });
        });
        continue;
      }
      if (p.plot.kind === "flags") {
        p.runs = p.plot.series.map((name) => flagRuns(buffer, name, lo, hi, gapS));
        u.batch(() => {
          u.setData([flat, [null, null]] as uPlot.AlignedData, false);
          u.setScale("x", { min, max });
        });
        continue;
      }
      const ys = p.series.map((name) => frame.channels.get(name) ?? []);
      u.batch(() => {
        u.setData([frame.x, ...ys] as uPlot.AlignedData, false);
        u.setScale("x", { min, max });
      });
    }
    if (this.status.dataset.stale) return;
    const t = this.trigger;
    const state = t.capturedT !== null && t.active
      ? `triggered ${clockText(t.capturedT, 3)}`
      : this.paused
        ? this.zoom
          ? "paused · zoomed"
          : "paused"
        : t.armed
          ? t.pendingT !== null
            ? "trigger · recording"
            : "trigger armed"
          : "live";
    // The status (with its sample count) is text in the DOM: a layout each time it
    // changes, so it is written at most 4 times a second unless the state changed.
    if (state !== this.statusState || started - this.statusAt > 250) {
      this.statusState = state;
      this.statusAt = started;
      setText(this.status, `${state} · ${(max - min).toFixed(max - min < 10 ? 2 : 1)} s · ${Math.max(0, hi - lo)} samples${frame.decimated ? "" : this.sparse() ? " · markers" : ""}`);
    }
    toggleClass(this.status, "live", live);
    this.tools.syncCursors();
    const took = performance.now() - started;
    this.lastDrawMs = took;
    this.skipUntil = took > 8 ? started + 2 * took : 0;
  }

  destroy(): void {
    this.observer.disconnect();
    for (const p of this.panels) p.u?.destroy();
  }
}
