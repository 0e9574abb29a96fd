// The stacked, cursor-synced uPlot scopes of one axis, built from descriptor.plots.
// Data is cut from the axis' ring buffer once per animation frame (never per
// message): min/max per pixel column when dense, sample by sample with markers when
// sparse, gaps as gaps, slow channels held as steps (see decimate.ts). Flags are drawn
// as run bars straight from the buffer (cheap: a few rectangles, not a filled path).
// Scope controls: legend toggles, units on the y axes, time under the cursor, two Δ
// cursors, a trigger (trigger.ts), wheel and drag zoom, channel choice per plot (kept
// per device in localStorage), x as wall clock or relative time, CSV export.
// plotkit.ts holds what does not depend on the stack's state (theme, axis text, the
// uPlot options and header of a panel, the flag-bar and cursor hooks).
import uPlot from "uplot";
import "uplot/dist/uPlot.min.css";
import type { AxisBuffer } from "../buffer";
import { h, replace, setText, toggleClass } from "../dom";
import { formatValue } from "../format";
import { store } from "../store";
import type { UnitPrefs } from "../units";
import type { DeviceDescriptor, FlagDescriptor, PlotDescriptor } from "../schema.gen";
import { Cutter, FlagRunCache, GAP_PERIODS, medianPeriod, type Frame } from "./decimate";
import { ScopeTools } from "./scopetools";
import {
  clockText,
  decimals,
  HEADER_PX,
  lanePx,
  MARKER_PX,
  MIN_LINE_PX,
  PAD_RIGHT_PX,
  type Panel,
  panelHeader,
  PHONE,
  type PlotHost,
  plotOptions,
  readTheme,
  WINDOWS_S,
  X_AXIS_PX,
  Y_AXIS_MAX_PX,
  Y_AXIS_PX,
  Y_LABEL_PX,
} from "./plotkit";
import { lanePos, scanStates, stateAt, statesPx, statesRuns } from "./statesplot";
import { type LayerCounts, layerCounts } from "./tracelayer";
import { Trigger } from "./trigger";

/** Minimum interval between redraws of a rolling (live) trace: 30 Hz. */
const LIVE_REDRAW_MS = 32;

/** What the user chose per device: series per plot and hidden series. */
interface ScopePrefs {
  series: Record<string, string[]>;
  hidden: Record<string, string[]>;
  xMode: "clock" | "rel";
}

export { clockText, MARKER_PX, WINDOWS_S };

/** The scope of one axis. Members that the panel options and hooks (plotkit.ts) use are
 * public: they are the PlotHost interface, not an API for other views. */
export class PlotStack implements PlotHost {
  readonly el: HTMLElement;
  paused = false;
  windowS = 10;
  readonly trigger = new Trigger();
  /** The two Δ cursors (server time), null while not placed. */
  cursors: { a: number | null; b: number | null; next: "a" | "b"; on: boolean } = { a: null, b: null, next: "a", on: false };
  private zoom: [number, number] | null = null;
  private frozenEnd = Number.NaN;
  /** The window of the last single-shot capture, copied out of the ring (``view``). */
  private held: AxisBuffer | null = null;
  private readonly panels: Panel[] = [];
  readonly theme = readTheme();
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
  private boxW = 0;
  private boxH = 0;
  private skipUntil = 0;
  private lastLiveDraw = 0;
  /** Duration of the last redraw (ms). */
  lastDrawMs = 0;
  private dirty = true;
  private width = 0;
  private hovering = false;
  private dragSource: uPlot | null = null;
  private downX = Number.NaN;
  readonly syncKey: string;
  readonly flagByName: Map<string, FlagDescriptor>;
  readonly yAxisPx: number;
  readonly light = document.documentElement.dataset.theme === "light";
  /** The frame drawn last and the x range shown. */
  frame: Frame | null = null;
  shown: [number, number] = [0, 0];
  private readonly prefsKey: string;
  private prefs: ScopePrefs;
  private readonly phone = window.matchMedia?.(PHONE);
  /** Phones: one plot at a time, chosen with the tabs. Kept from the media query's change
   * events: reading ``matches`` in every frame is a style query each time. */
  private single = this.phone?.matches ?? false;
  /** Flag runs per flag, scanned only for new samples. */
  private readonly flagRuns = new Map<string, FlagRunCache>();
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
      this.single = this.phone?.matches ?? false;
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
    const { header, states } = panelHeader(this, plot, series, legendValues, legendItems, unitButtons);
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

  toggleSeries(plotName: string, name: string): void {
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

  hiddenOf(plotName: string): string[] {
    return this.prefs.hidden[plotName] ?? [];
  }

  isHidden(plotName: string, name: string): boolean {
    return (this.prefs.hidden[plotName] ?? []).includes(name);
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

  color(i: number): string {
    return this.theme.series[i % this.theme.series.length] as string;
  }

  /** Heights: flag and states plots get their lanes, line plots share the rest. */
  private layout(redraw = true, measure = true): void {
    // The size is read where layout is fresh (the ResizeObserver callback, a rebuild);
    // from a redraw (new state lanes) the last size is reused: reading it there would
    // force a synchronous layout in the middle of the frame.
    if (measure || !this.boxW) {
      this.boxW = this.scroller.clientWidth;
      this.boxH = this.scroller.clientHeight;
    }
    const width = Math.floor(this.boxW);
    const height = Math.floor(this.boxH);
    if (width < 50 || height < 50) return;
    const visible = this.panels.filter((p) => this.shows(p));
    const last = visible[visible.length - 1];
    let fixed = 0;
    let lines = 0;
    const fixedPx = (p: Panel): number | null =>
      this.single ? null : p.plot.kind === "flags" ? p.plot.series.length * lanePx(p.plot.series.length) + 8 : p.states ? statesPx(p.states) : null;
    // A phone wraps a legend that does not fit next to the title (seen: two of
    // three traces were hidden behind a sideways scroll): the headers are measured
    // where the layout is fresh, their last height reused otherwise.
    if (measure) {
      for (const p of visible) {
        const header = p.el.firstElementChild as HTMLElement | null;
        p.headerPx = header ? Math.max(HEADER_PX, header.offsetHeight) : HEADER_PX;
      }
    }
    for (const p of visible) {
      fixed += (p.headerPx ?? HEADER_PX) + 6 + (p === last ? X_AXIS_PX : 4);
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
  private readonly fitted = new Map<string, string>();

  /** (Cached: the lane labels are drawn on every redraw, measuring them is not free.) */
  fitLabel(text: string): string {
    const known = this.fitted.get(text);
    if (known !== undefined) return known;
    const room = this.yAxisPx - 8;
    let fit = text;
    if (this.textWidth(text) > room) {
      let cut = text;
      while (cut.length > 1 && this.textWidth(`${cut}…`) > room) cut = cut.slice(0, -1);
      fit = `${cut}…`;
    }
    this.fitted.set(text, fit);
    return fit;
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
  sparse(): boolean {
    const f = this.frame;
    if (!f || f.decimated) return false;
    const [min, max] = this.shown;
    const period = Number.isFinite(f.periodS) ? f.periodS : max - min;
    const px = ((this.width - this.yAxisPx - Y_LABEL_PX) * period) / Math.max(1e-9, max - min);
    return px >= MARKER_PX;
  }

  private create(panel: Panel): void {
    const visible = this.panels.filter((p) => this.shows(p));
    const opts = plotOptions(this, panel, this.width, panel === visible[visible.length - 1]);
    const series = opts.series;
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
  slowMarkers(name: string): number[] | null {
    const f = this.frame;
    const real = f?.real.get(name);
    if (!f || !real || !f.slow.has(name)) return null;
    const [min, max] = this.shown;
    const px = ((this.width - this.yAxisPx) * (f.slow.get(name) as number)) / Math.max(1e-9, max - min);
    return px >= MARKER_PX ? real : null;
  }

  /** x tick text: wall clock, or seconds relative to the trigger point or the right edge. */
  xText(v: number, incr: number): string {
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
    return this.view.nearestT(t);
  }

  /** The latest real value of ``name`` at or before ``t`` (device units), or null. */
  valueAt(name: string, t: number): number | null {
    return this.view.valueAt(name, t);
  }

  /** What the plots show: the live ring, or a single-shot capture's own copy of its
   * window while it is on screen (kept until re-armed or cleared: the ring drops
   * samples older than KEEP_SECONDS, and the capture once went blank with it). */
  get view(): AxisBuffer {
    const t = this.trigger;
    return t.active && t.capturedT !== null && this.held ? this.held : this.buffer;
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

  onSelect(u: uPlot): void {
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

  onCursor(panel: Panel, u: uPlot): void {
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
    this.held = null;
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

  /** Pixel columns of the plot area (one min/max pair each when dense): uPlot's plot
   * width, so a rolling window moves by whole pixels (the trace layer shifts them). */
  private columns(): number {
    return Math.max(50, Math.floor(this.width - this.yAxisPx - Y_LABEL_PX - PAD_RIGHT_PX));
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
      const window = this.trigger.window(this.windowS);
      if (window) {
        const margin = 0.1 * (window[1] - window[0]);
        this.held = this.buffer.snapshot(window[0] - margin, window[1] + margin);
      }
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
    const buffer = this.view;
    if (live && buffer.version === this.drawnVersion && !this.dirty) return;
    // A rolling trace redraws at most every LIVE_REDRAW_MS and at most once per pixel
    // column of time (a 60 s window moves 1 px per ~55 ms: redrawing faster shows
    // nothing new). With software canvases (no GPU) the raster of every redraw is most
    // of a frame's cost.
    if (live && !this.dirty && started - this.lastLiveDraw < Math.max(LIVE_REDRAW_MS, 1000 * colS)) return;
    if (live) this.lastLiveDraw = started;
    if (!live && !this.dirty) return;
    this.dirty = false;
    this.drawnVersion = buffer.version;
    this.shown = [min, max];
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
    for (const p of this.panels) if (p.states && scanStates(buffer, p.states)) newLanes = true;
    if (newLanes) this.layout(false, false);
    const flat = this.flat;
    flat[0] = min;
    flat[1] = max;
    for (const p of this.panels) {
      if (!this.shows(p)) continue;
      const u = p.u as uPlot;
      const s = p.states;
      if (s) {
        statesRuns(buffer, s, lo, hi);
        const ys = s.values.map((v) => lanePos(s, v));
        u.batch(() => {
          u.setData([s.x, ys] as uPlot.AlignedData, false);
          u.setScale("x", { min, max });
        });
        continue;
      }
      if (p.plot.kind === "flags") {
        p.runs = p.plot.series.map((name) => this.runsOf(name).runs(buffer, lo, hi, gapS));
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

  /** Trace-layer redraws of the line plots since they were made (tests, benchmarks). */
  layerCounts(): LayerCounts {
    return layerCounts(this.panels.map((p) => p.u));
  }

  private runsOf(name: string): FlagRunCache {
    let cache = this.flagRuns.get(name);
    if (!cache) {
      cache = new FlagRunCache(name);
      this.flagRuns.set(name, cache);
    }
    return cache;
  }

  destroy(): void {
    this.observer.disconnect();
    for (const p of this.panels) p.u?.destroy();
  }
}
