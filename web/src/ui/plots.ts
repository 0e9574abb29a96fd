// The stacked, cursor-synced uPlot scopes of one axis, built from descriptor.plots.
// Data is cut from the axis' ring buffer once per animation frame (never per
// message) and min/max-decimated to about two points per pixel.
import uPlot from "uplot";
import "uplot/dist/uPlot.min.css";
import type { AxisBuffer } from "../buffer";
import { h, replace, setText, toggleClass } from "../dom";
import { formatValue } from "../format";
import type { UnitPrefs } from "../units";
import type { DeviceDescriptor, FlagDescriptor, PlotDescriptor } from "../wire.gen";

export const WINDOWS_S = [5, 10, 30, 60] as const;
const LANE = 1; // height of a flag trace
const LANE_GAP = 0.55; // space between lanes
const LANE_PX = 17;
/** Lanes get thinner when a device has many flags, so line plots keep their room. */
const lanePx = (lanes: number): number => (lanes <= 8 ? LANE_PX : Math.max(13, Math.floor(150 / lanes)));
const Y_AXIS_PX = 68;
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

interface Panel {
  plot: PlotDescriptor;
  el: HTMLElement;
  host: HTMLElement;
  u: uPlot | null;
  legendValues: HTMLElement[];
  unitButtons: HTMLButtonElement[];
  height: number;
}

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

  constructor(
    descriptor: DeviceDescriptor,
    private readonly buffer: AxisBuffer,
    private readonly units: UnitPrefs,
    axisId: string,
    signal: AbortSignal,
  ) {
    this.syncKey = `scope-${axisId}`;
    this.flagByName = new Map(descriptor.flags.map((f) => [f.name, f]));
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
    } else {
      header.appendChild(h("span", { class: "plot-unit" }, "status flags"));
    }
    const el = h("div", { class: `plot-panel kind-${plot.kind}` }, header, host);
    this.scroller.appendChild(el);
    const panel: Panel = { plot, el, host, u: null, legendValues, unitButtons, height: 0 };
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

  /** Heights: flag plots get their lanes, line plots share the rest. */
  private layout(): void {
    const width = Math.floor(this.scroller.clientWidth);
    const height = Math.floor(this.scroller.clientHeight);
    if (width < 50 || height < 50) return;
    const last = this.panels.length - 1;
    let fixed = 0;
    let lines = 0;
    this.panels.forEach((p, i) => {
      fixed += HEADER_PX + 6 + (i === last ? X_AXIS_PX : 4);
      if (p.plot.kind === "flags") fixed += p.plot.series.length * lanePx(p.plot.series.length) + 8;
      else lines += 1;
    });
    const each = lines ? Math.max(MIN_LINE_PX, Math.floor((height - fixed - 2) / lines)) : 0;
    let changed = width !== this.width;
    this.panels.forEach((p, i) => {
      const axisPx = i === last ? X_AXIS_PX : 4;
      const plotPx = p.plot.kind === "flags" ? p.plot.series.length * lanePx(p.plot.series.length) + 8 : each;
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
    this.update();
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
    const lanes = plot.series.length;
    const laneBase = (i: number): number => (lanes - 1 - i) * (LANE + LANE_GAP);
    const unitOf = (name: string) => this.units.unit(name);
    const series: uPlot.Series[] = [{ label: "t" }];
    plot.series.forEach((name, i) => {
      if (flags) {
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
    const yAxis: uPlot.Axis = flags
      ? {
          stroke: theme.text,
          font: theme.font,
          size: Y_AXIS_PX,
          gap: 4,
          grid: { show: false },
          ticks: { show: false },
          splits: () => plot.series.map((_n, i) => laneBase(i) + LANE / 2),
          values: (_u, splits) =>
            splits.map((_v, i) => {
              const name = plot.series[i] ?? "";
              return this.flagByName.get(name)?.label ?? name;
            }),
        }
      : {
          stroke: theme.axis,
          font: theme.font,
          size: Y_AXIS_PX,
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
      padding: [flags ? 4 : 9, 10, 0, 0],
      cursor: {
        sync: { key: this.syncKey, setSeries: false },
        drag: { x: true, y: false, setScale: false },
        points: { size: 5, fill: (u, si) => (u.series[si]?.stroke as (u: uPlot, si: number) => string)?.(u, si) },
        focus: { prox: -1 },
      },
      scales: {
        x: { time: false },
        y: flags
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
      },
    };
    const empty: uPlot.AlignedData = [[], ...plot.series.map(() => [] as number[])];
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
      for (const name of p.plot.series) {
        if (p.plot.kind === "flags") flags.push(name);
        else channels.set(name, this.units.unit(name).factor);
      }
    }
    const buckets = Math.max(50, Math.floor(this.width - Y_AXIS_PX));
    const frame = cut(buffer, lo, hi, buckets, channels, flags);
    for (const p of this.panels) {
      const u = p.u as uPlot;
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
