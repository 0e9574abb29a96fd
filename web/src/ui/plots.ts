// The stacked, cursor-synced uPlot scopes of one axis, built from descriptor.plots.
// Data is cut from the axis' ring buffer once per animation frame (never per
// message) and min/max-decimated to about two points per pixel.
import uPlot from "uplot";
import "uplot/dist/uPlot.min.css";
import type { AxisBuffer } from "../buffer";
import { h, replace, setText, toggleClass } from "../dom";
import { formatValue } from "../format";
import { StateNames } from "../states";
import type { UnitPrefs } from "../units";
import type { DeviceDescriptor, FlagDescriptor, PlotDescriptor } from "../wire.gen";

export const WINDOWS_S = [5, 10, 30, 60] as const;
const LANE = 1; // height of a flag trace
const LANE_GAP = 0.55; // space between lanes
const LANE_PX = 17;
/** Lanes get thinner when a device has many flags, so line plots keep their room. */
const lanePx = (lanes: number): number => (lanes <= 8 ? LANE_PX : Math.max(13, Math.floor(150 / lanes)));
const STATE_LANE_PX = 15; // one lane per state of a states plot
const Y_AXIS_PX = 68; // at least; wider (up to Y_AXIS_MAX_PX) for long lane labels
const Y_AXIS_MAX_PX = 116;
const X_AXIS_PX = 26;
const HEADER_PX = 24;
const MIN_LINE_PX = 70;

interface Theme {
  axis: string;
  grid: string;
  text: string;
  series: string[];
  severity: Record<FlagDescriptor["severity"], string>;
  font: string;
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
  };
}

/** One frame of data: shared x plus every channel and flag over the visible range. */
interface Frame {
  x: number[];
  channels: Map<string, (number | null)[]>;
  flags: Map<string, number[]>;
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

/** Cut [lo, hi) out of the buffer, at most ``buckets`` min/max pairs. */
function cut(
  buffer: AxisBuffer,
  lo: number,
  hi: number,
  buckets: number,
  channels: Iterable<[string, number]>, // name, unit factor
  flags: string[],
): Frame {
  const n = Math.max(0, hi - lo);
  const frame: Frame = { x: [], channels: new Map(), flags: new Map() };
  const t = buffer.t;
  const channelList = [...channels];
  if (n <= buckets * 2) {
    frame.x = Array.from(t.subarray(lo, hi));
    for (const [name, factor] of channelList) {
      const col = buffer.channels.get(name);
      const out: (number | null)[] = new Array(n);
      for (let i = 0; i < n; i++) {
        const v = col ? (col[lo + i] as number) : Number.NaN;
        out[i] = Number.isNaN(v) ? null : v * factor;
      }
      frame.channels.set(name, out);
    }
    for (const name of flags) {
      const col = buffer.flags.get(name);
      frame.flags.set(name, col ? Array.from(col.subarray(lo, hi)) : new Array<number>(n).fill(0));
    }
    return frame;
  }
  const bounds: number[] = [];
  for (let b = 0; b <= buckets; b++) bounds.push(lo + Math.floor((b * n) / buckets));
  const x: number[] = [];
  for (let b = 0; b < buckets; b++) {
    const a = bounds[b] as number;
    const z = (bounds[b + 1] as number) - 1;
    if (z < a) continue;
    x.push(t[a] as number, t[z] as number);
  }
  frame.x = x;
  for (const [name, factor] of channelList) {
    const col = buffer.channels.get(name);
    const out: (number | null)[] = [];
    for (let b = 0; b < buckets; b++) {
      const a = bounds[b] as number;
      const z = bounds[b + 1] as number;
      if (z <= a) continue;
      let min = Infinity;
      let max = -Infinity;
      let iMin = 0;
      let iMax = 0;
      if (col) {
        for (let i = a; i < z; i++) {
          const v = col[i] as number;
          if (Number.isNaN(v)) continue;
          if (v < min) {
            min = v;
            iMin = i;
          }
          if (v > max) {
            max = v;
            iMax = i;
          }
        }
      }
      if (min === Infinity) out.push(null, null);
      else if (iMin <= iMax) out.push(min * factor, max * factor);
      else out.push(max * factor, min * factor);
    }
    frame.channels.set(name, out);
  }
  for (const name of flags) {
    const col = buffer.flags.get(name);
    const out: number[] = [];
    for (let b = 0; b < buckets; b++) {
      const a = bounds[b] as number;
      const z = bounds[b + 1] as number;
      if (z <= a) continue;
      let any = 0;
      if (col) for (let i = a; i < z && !any; i++) any = col[i] as number;
      out.push(any, any);
    }
    frame.flags.set(name, out);
  }
  return frame;
}

/** A "states" plot: the channel as a timeline, one lane per state that occurred. */
interface StatesPanel {
  channel: string;
  names: StateNames;
  seen: Set<number>;
  lanes: number[]; // state values, ascending; the first lane is drawn at the top
  scannedT: number; // the buffer is scanned for new states up to here
  x: number[]; // the drawn run starts (and the last sample's time)
  values: number[]; // the state from each x on
  swatch: HTMLElement;
  id: HTMLElement;
}

interface Panel {
  plot: PlotDescriptor;
  el: HTMLElement;
  host: HTMLElement;
  u: uPlot | null;
  legendValues: HTMLElement[];
  unitButtons: HTMLButtonElement[];
  height: number;
  states: StatesPanel | null;
}

/** Lanes drawn for a states plot (two at least, so one state is not a full-height bar). */
const laneCount = (s: StatesPanel): number => Math.max(2, s.lanes.length);
const statesPx = (s: StatesPanel): number => laneCount(s) * STATE_LANE_PX + 8;

export class PlotStack {
  readonly el: HTMLElement;
  paused = false;
  windowS = 10;
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
  private drawnVersion = -1;
  private dirty = true;
  private width = 0;
  private hovering = false;
  private dragSource: uPlot | null = null;
  private readonly syncKey: string;
  private readonly flagByName: Map<string, FlagDescriptor>;
  private readonly yAxisPx: number;
  private readonly light = document.documentElement.dataset.theme === "light";

  constructor(
    descriptor: DeviceDescriptor,
    private readonly buffer: AxisBuffer,
    private readonly units: UnitPrefs,
    axisId: string,
    signal: AbortSignal,
  ) {
    this.syncKey = `scope-${axisId}`;
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
        const b = h(
          "button",
          { class: "seg-btn", testid: `scope-window-${s}`, onclick: () => this.setWindow(s) },
          `${s} s`,
        );
        this.windowButtons.set(s, b);
        return b;
      }),
    );
    this.status = h("span", { class: "scope-status", testid: "scope-status" });
    const toolbar = h(
      "div",
      { class: "scope-toolbar" },
      this.pauseButton,
      h("span", { class: "tb-label" }, "Window"),
      windows,
      this.resetButton,
      h("span", { class: "tb-hint" }, "drag to zoom · double-click to reset"),
      h("span", { class: "tb-spacer" }),
      this.status,
    );
    this.scroller = h("div", { class: "scope-plots" });
    this.el = h("div", { class: "scope" }, toolbar, this.scroller);
    for (const plot of descriptor.plots) this.panels.push(this.makePanel(plot));
    this.syncControls();
    units.onChange(() => {
      for (const panel of this.panels) this.syncUnitButtons(panel);
      this.rebuild();
    }, signal);
    this.observer = new ResizeObserver(() => this.layout());
    this.observer.observe(this.scroller);
    signal.addEventListener("abort", () => this.destroy(), { once: true });
  }

  private makePanel(plot: PlotDescriptor): Panel {
    const host = h("div", { class: "plot-host", testid: `plot-${plot.name}` });
    const legendValues: HTMLElement[] = [];
    const unitButtons: HTMLButtonElement[] = [];
    const header = h("div", { class: "plot-header" }, h("span", { class: "plot-title" }, plot.label));
    let states: StatesPanel | null = null;
    if (plot.kind === "line") {
      const legend = h("div", { class: "plot-legend" });
      plot.series.forEach((name, i) => {
        const channel = this.units.channel(name);
        const value = h("span", { class: "legend-value" }, "—");
        legendValues.push(value);
        legend.appendChild(
          h(
            "span",
            { class: "legend-item", title: channel?.description ?? name },
            h("span", { class: "swatch", style: `background:${this.color(i)}` }),
            h("span", { class: "legend-label" }, channel?.label ?? name),
            value,
          ),
        );
      });
      header.appendChild(legend);
      const choices = this.units.common(plot.series);
      if (choices.length > 1) {
        const seg = h("div", { class: "seg small", title: "Display unit" });
        for (const unit of choices) {
          const b = h(
            "button",
            { class: "seg-btn", testid: `unit-${plot.name}-${unit}`, onclick: () => this.units.set(plot.series, unit) },
            unit,
          );
          b.dataset.unit = unit;
          unitButtons.push(b);
          seg.appendChild(b);
        }
        header.appendChild(seg);
      } else {
        header.appendChild(h("span", { class: "plot-unit" }, this.units.unit(plot.series[0] ?? "").unit || plot.unit));
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
    this.scroller.appendChild(el);
    if (states) this.scanStates(states);
    const panel: Panel = { plot, el, host, u: null, legendValues, unitButtons, height: 0, states };
    this.syncUnitButtons(panel);
    return panel;
  }

  private syncUnitButtons(panel: Panel): void {
    const current = this.units.unit(panel.plot.series[0] ?? "").unit;
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
    const last = this.panels.length - 1;
    let fixed = 0;
    let lines = 0;
    const fixedPx = (p: Panel): number | null =>
      p.plot.kind === "flags" ? p.plot.series.length * lanePx(p.plot.series.length) + 8 : p.states ? statesPx(p.states) : null;
    this.panels.forEach((p, i) => {
      fixed += HEADER_PX + 6 + (i === last ? X_AXIS_PX : 4);
      const px = fixedPx(p);
      if (px !== null) fixed += px;
      else lines += 1;
    });
    const each = lines ? Math.max(MIN_LINE_PX, Math.floor((height - fixed - 2) / lines)) : 0;
    let changed = width !== this.width;
    this.panels.forEach((p, i) => {
      const axisPx = i === last ? X_AXIS_PX : 4;
      const plotPx = fixedPx(p) ?? each;
      const total = plotPx + axisPx;
      if (total !== p.height) changed = true;
      p.height = total;
    });
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

  /** Add the states that occurred in the buffer since the last scan; true if any is new. */
  private scanStates(s: StatesPanel): boolean {
    const buffer = this.buffer;
    const col = buffer.channels.get(s.channel);
    if (!col) return false;
    const from = Math.max(buffer.start, buffer.indexAt(s.scannedT));
    let added = false;
    for (let i = from; i < buffer.end; i++) {
      const v = col[i] as number;
      if (Number.isNaN(v) || s.seen.has(v)) continue;
      s.seen.add(v);
      added = true;
    }
    if (buffer.end > buffer.start) s.scannedT = (buffer.t[buffer.end - 1] as number) + 1e-9;
    if (added) s.lanes = [...s.seen].sort((a, b) => a - b);
    return added;
  }

  /** y of a state's lane: the first lane (lowest value) at the top. */
  private lanePos(s: StatesPanel, value: number): number {
    return laneCount(s) - 1 - s.lanes.indexOf(value);
  }

  /** The run-length form of [lo, hi): a point where the state changes, and the end.
   * A missing sample (slow or skipped read) holds the state before it. */
  private statesRuns(s: StatesPanel, lo: number, hi: number): void {
    const buffer = this.buffer;
    const col = buffer.channels.get(s.channel);
    s.x = [];
    s.values = [];
    if (!col || hi <= lo) return;
    let current = Number.NaN;
    for (let i = lo - 1; i >= Math.max(buffer.start, lo - 4096) && Number.isNaN(current); i--) current = col[i] as number;
    if (!Number.isNaN(current)) {
      s.x.push(buffer.t[lo] as number);
      s.values.push(current);
    }
    for (let i = lo; i < hi; i++) {
      const v = col[i] as number;
      if (Number.isNaN(v) || v === current) continue;
      const t = buffer.t[i] as number;
      if (s.x.length && (s.x[s.x.length - 1] as number) >= t) s.values[s.values.length - 1] = v;
      else {
        s.x.push(t);
        s.values.push(v);
      }
      current = v;
    }
    const end = buffer.t[hi - 1] as number;
    if (s.x.length && end > (s.x[s.x.length - 1] as number)) {
      s.x.push(end);
      s.values.push(current);
    }
  }

  /** The state at time ``x`` of what is drawn (null before the first run). */
  private stateAt(s: StatesPanel, x: number): number | null {
    let lo = 0;
    let hi = s.x.length - 1;
    if (hi < 0 || x < (s.x[0] as number)) return null;
    while (lo < hi) {
      const mid = (lo + hi + 1) >> 1;
      if ((s.x[mid] as number) <= x) lo = mid;
      else hi = mid - 1;
    }
    return s.values[lo] ?? null;
  }

  private showState(panel: Panel, value: number | null | undefined): void {
    const s = panel.states;
    const el = panel.legendValues[0];
    if (!s || !el) return;
    const known = value !== null && value !== undefined;
    setText(el, known ? s.names.name(value) : "—");
    setText(s.id, known && s.names.has(value) ? s.names.id(value) : "");
    s.swatch.style.background = known ? s.names.color(value, this.light) : "transparent";
    el.title = known ? s.names.describe(value) : "";
  }

  /** Coloured bars, one per run of a state, in its lane, joined by a step trace. */
  private drawStates(panel: Panel, u: uPlot): void {
    const s = panel.states;
    if (!s) return;
    const ctx = u.ctx;
    const { left, top, width, height } = u.bbox;
    const px = devicePixelRatio || 1;
    const lane = height / laneCount(s);
    const bar = Math.max(3 * px, lane * 0.64);
    ctx.save();
    ctx.beginPath();
    ctx.rect(left, top, width, height);
    ctx.clip();
    // Faint lane guides.
    ctx.fillStyle = this.theme.grid;
    for (let i = 0; i < laneCount(s); i++) ctx.fillRect(left, Math.round(top + (i + 0.5) * lane), width, px);
    ctx.font = `${10 * px}px ${css("--mono", "monospace")}`;
    ctx.textBaseline = "middle";
    ctx.textAlign = "left";
    // The step trace: a vertical connector at each change, bar edge to bar edge.
    ctx.strokeStyle = this.theme.axis;
    ctx.lineWidth = px;
    ctx.beginPath();
    for (let i = 1; i + 1 < s.x.length; i++) {
      const from = s.values[i - 1] as number;
      const to = s.values[i] as number;
      const x = Math.round(u.valToPos(s.x[i] as number, "x", true)) + 0.5;
      if (x < left || x > left + width) continue;
      const y0 = u.valToPos(this.lanePos(s, from), "y", true);
      const y1 = u.valToPos(this.lanePos(s, to), "y", true);
      const dir = y1 > y0 ? 1 : -1;
      ctx.moveTo(x, y0 + (dir * bar) / 2);
      ctx.lineTo(x, y1 - (dir * bar) / 2);
    }
    ctx.stroke();
    for (let i = 0; i + 1 < s.x.length; i++) {
      const value = s.values[i] as number;
      const x0 = u.valToPos(s.x[i] as number, "x", true);
      const x1 = u.valToPos(s.x[i + 1] as number, "x", true);
      if (x1 < left || x0 > left + width) continue;
      const y = u.valToPos(this.lanePos(s, value), "y", true);
      const w = Math.max(2 * px, x1 - x0);
      ctx.fillStyle = s.names.color(value, this.light);
      ctx.globalAlpha = 0.85;
      ctx.fillRect(x0, y - bar / 2, w, bar);
      ctx.globalAlpha = 1;
      // The name inside a bar wide enough for it (the lane label is on the axis too).
      const name = s.names.name(value);
      const visible0 = Math.max(x0, left);
      const visibleW = Math.min(x1, left + width) - visible0;
      if (bar >= 9 * px && visibleW > ctx.measureText(name).width + 8 * px) {
        ctx.fillStyle = this.light ? "#ffffff" : "#0b0f14";
        ctx.fillText(name, visible0 + 4 * px, y + 0.5 * px);
      }
    }
    ctx.restore();
  }

  private rebuild(): void {
    for (const p of this.panels) {
      p.u?.destroy();
      p.u = null;
      replace(p.host);
    }
    if (this.width) for (const p of this.panels) this.create(p);
    this.dirty = true;
    this.update();
  }

  private create(panel: Panel): void {
    const { plot } = panel;
    const theme = this.theme;
    const isLast = panel === this.panels[this.panels.length - 1];
    const flags = plot.kind === "flags";
    const states = panel.states;
    const lanes = plot.series.length;
    const laneBase = (i: number): number => (lanes - 1 - i) * (LANE + LANE_GAP);
    const unitOf = (name: string) => this.units.unit(name);
    const series: uPlot.Series[] = [{ label: "t" }];
    plot.series.forEach((name, i) => {
      if (states) {
        // Bars and the step connectors are drawn by drawStates; the series only
        // carries the data (cursor sync).
        if (i === 0) {
          series.push({
            label: this.units.channel(name)?.label ?? name,
            stroke: "transparent",
            width: 0,
            paths: () => null,
            points: { show: false },
          });
        }
      } else if (flags) {
        const severity = this.flagByName.get(name)?.severity ?? "info";
        const color = theme.severity[severity];
        // Off is a muted baseline; on is a block in the severity colour.
        series.push({
          label: this.flagByName.get(name)?.label ?? name,
          stroke: theme.axis,
          width: 1,
          fill: `${color}b0`,
          fillTo: laneBase(i),
          paths: uPlot.paths.stepped?.({ align: 1 }),
          points: { show: false },
        });
      } else {
        series.push({
          label: this.units.channel(name)?.label ?? name,
          stroke: this.color(i),
          width: i === 0 ? 1.5 : 1.25,
          dash: i === 1 ? [5, 3] : undefined,
          spanGaps: true,
          points: { show: false },
          value: (_u, v) => formatValue(v, unitOf(name)),
        });
      }
    });
    const xAxis: uPlot.Axis = {
      stroke: theme.axis,
      font: theme.font,
      grid: { stroke: theme.grid, width: 1 },
      ticks: { stroke: theme.grid, width: 1, size: isLast ? 4 : 0 },
      space: 70,
      size: isLast ? X_AXIS_PX : 4,
      gap: 2,
      values: isLast
        ? (_u, splits, _ai, _space, incr) => splits.map((v) => `${v.toFixed(decimals(incr))} s`)
        : (_u, splits) => splits.map(() => ""),
    };
    const yAxis: uPlot.Axis = states
      ? {
          stroke: theme.text,
          font: theme.font,
          size: this.yAxisPx,
          gap: 4,
          grid: { show: false },
          ticks: { show: false },
          splits: () => states.lanes.map((v) => this.lanePos(states, v)),
          values: (_u, splits) =>
            splits.map((pos) => {
              const value = states.lanes[laneCount(states) - 1 - pos];
              return value === undefined ? "" : this.fitLabel(states.names.name(value));
            }),
        }
      : flags
      ? {
          stroke: theme.text,
          font: theme.font,
          size: this.yAxisPx,
          gap: 4,
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
          stroke: theme.axis,
          font: theme.font,
          size: this.yAxisPx,
          gap: 4,
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
        points: states ? { show: false } : { size: 5, fill: (u, si) => (u.series[si]?.stroke as (u: uPlot, si: number) => string)?.(u, si) },
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
        drawAxes: states ? [(u) => this.drawStates(panel, u)] : [],
      },
    };
    const empty: uPlot.AlignedData = [[], ...(states ? [[] as number[]] : plot.series.map(() => [] as number[]))];
    panel.u = new uPlot(opts, empty, panel.host);
    const u = panel.u;
    // Synced plots mirror the selection; only the plot that was dragged on zooms.
    u.over.addEventListener("mousedown", () => (this.dragSource = u));
    u.over.addEventListener("dblclick", () => this.resetZoom());
    panel.u.over.addEventListener("mouseenter", () => (this.hovering = true));
    panel.u.over.addEventListener("mouseleave", () => {
      this.hovering = false;
      this.refreshLegend();
    });
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
    const idx = u.cursor.idx;
    if (panel.states) {
      const left = u.cursor.left;
      if (left !== undefined && left >= 0) this.showState(panel, this.stateAt(panel.states, u.posToVal(left, "x")));
      return;
    }
    if (idx === null || idx === undefined || panel.plot.kind !== "line") return;
    panel.plot.series.forEach((name, i) => {
      const column = u.data[i + 1];
      // Slow channels have gaps: show their latest sample at or before the cursor.
      let value = column?.[idx];
      for (let j = idx - 1; (value === null || value === undefined) && j >= 0 && j > idx - 64; j--) value = column?.[j];
      const el = panel.legendValues[i];
      if (el) setText(el, formatValue(value ?? null, this.units.unit(name)));
    });
  }

  /** Latest values in the legends while the cursor is not over a plot. */
  refreshLegend(): void {
    if (this.hovering) return;
    for (const p of this.panels) {
      if (p.states) this.showState(p, this.buffer.latest.get(p.states.channel));
      if (p.plot.kind !== "line") continue;
      p.plot.series.forEach((name, i) => {
        const el = p.legendValues[i];
        const unit = this.units.unit(name);
        const raw = this.buffer.latest.get(name);
        if (el) setText(el, formatValue(raw === undefined ? null : raw * unit.factor, unit));
      });
    }
  }

  togglePause(): void {
    if (this.paused) this.resume();
    else this.pause();
  }

  pause(): void {
    this.paused = true;
    this.frozenEnd = this.buffer.lastT;
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

  private syncControls(): void {
    replace(
      this.pauseButton,
      h("span", { class: "icon" }, this.paused ? "▶" : "❚❚"),
      this.paused ? " Resume" : " Pause",
    );
    toggleClass(this.pauseButton, "active", this.paused);
    this.resetButton.disabled = this.zoom === null;
    for (const [s, b] of this.windowButtons) toggleClass(b, "on", s === this.windowS);
    this.el.dataset.paused = this.paused ? "1" : "0";
  }

  /** Called once per animation frame; redraws only if something changed. */
  update(): void {
    if (!this.width || this.panels.some((p) => !p.u)) return;
    const live = !this.paused;
    if (live && this.buffer.version === this.drawnVersion && !this.dirty) return;
    if (!live && !this.dirty) return;
    this.dirty = false;
    this.drawnVersion = this.buffer.version;
    const end = live ? this.buffer.lastT : this.frozenEnd;
    let min: number;
    let max: number;
    if (this.zoom) [min, max] = this.zoom;
    // Before the server's clock has run a whole window, sweep from 0 like a scope.
    else if (Number.isFinite(end)) [min, max] = end < this.windowS ? [0, this.windowS] : [end - this.windowS, end];
    else [min, max] = [0, this.windowS];
    const buffer = this.buffer;
    // One sample either side so lines run to the plot edges.
    const lo = Math.max(buffer.start, buffer.indexAt(min) - 1);
    const hi = Math.min(buffer.end, buffer.indexAt(max) + 1);
    const channels = new Map<string, number>();
    const flags: string[] = [];
    for (const p of this.panels) {
      if (p.states) continue;
      for (const name of p.plot.series) {
        if (p.plot.kind === "flags") flags.push(name);
        else channels.set(name, this.units.unit(name).factor);
      }
    }
    const buckets = Math.max(50, Math.floor(this.width - this.yAxisPx));
    const frame = cut(buffer, lo, hi, buckets, channels, flags);
    let newLanes = false;
    for (const p of this.panels) if (p.states && this.scanStates(p.states)) newLanes = true;
    if (newLanes) this.layout(false);
    for (const p of this.panels) {
      const u = p.u as uPlot;
      const s = p.states;
      if (s) {
        this.statesRuns(s, lo, hi);
        const ys = s.values.map((v) => this.lanePos(s, v));
        u.batch(() => {
          u.setData([s.x, ys] as uPlot.AlignedData, false);
          u.setScale("x", { min, max });
        });
        continue;
      }
      const lanes = p.plot.series.length;
      const ys = p.plot.series.map((name, i) => {
        if (p.plot.kind === "flags") {
          const base = (lanes - 1 - i) * (LANE + LANE_GAP);
          return (frame.flags.get(name) ?? []).map((v) => base + v * LANE);
        }
        return frame.channels.get(name) ?? [];
      });
      u.batch(() => {
        u.setData([frame.x, ...ys] as uPlot.AlignedData, false);
        u.setScale("x", { min, max });
      });
    }
    const state = this.paused ? (this.zoom ? "paused · zoomed" : "paused") : "live";
    setText(this.status, `${state} · ${(max - min).toFixed(max - min < 10 ? 2 : 1)} s · ${Math.max(0, hi - lo)} samples`);
    toggleClass(this.status, "live", !this.paused);
  }

  destroy(): void {
    this.observer.disconnect();
    for (const p of this.panels) p.u?.destroy();
  }
}
