// The parts of a scope plot that do not depend on the stack's state: constants, theme,
// axis text, the Panel record, the canvas hooks (flag bars, Δ cursors), the uPlot
// options of one panel and its header (legend, unit buttons). Split from plots.ts; the
// PlotStack (plots.ts) is the PlotHost these are given.
import uPlot from "uplot";
import { h } from "../dom";
import { formatValue } from "../format";
import { StateNames } from "../states";
import { store } from "../store";
import type { UnitPrefs } from "../units";
import type { FlagDescriptor, PlotDescriptor } from "../schema.gen";
import type { Frame } from "./decimate";
import { drawStates, laneCount, lanePos, type StatesPanel } from "./statesplot";
import { drawTraceLayer, rastered } from "./tracelayer";

export const WINDOWS_S = [5, 10, 30, 60] as const;
export const LANE = 1; // height of a flag trace
export const LANE_GAP = 0.55; // space between lanes
export const LANE_PX = 17;
/** Lanes get thinner when a device has many flags, so line plots keep their room. */
export const lanePx = (lanes: number): number => (lanes <= 8 ? LANE_PX : Math.max(13, Math.floor(150 / lanes)));
export const Y_AXIS_PX = 68; // at least; wider (up to Y_AXIS_MAX_PX) for long lane labels
export const Y_AXIS_MAX_PX = 116;
export const Y_LABEL_PX = 14; // the unit, written along the y axis
/** Room right of the plot area (uPlot padding), so the last x tick label fits. */
export const PAD_RIGHT_PX = 10;
export const X_AXIS_PX = 26;
export const HEADER_PX = 24;
export const MIN_LINE_PX = 90;
/** Markers on the samples when they are at least this many pixels apart. */
export const MARKER_PX = 4;
export const PHONE = "(max-width: 760px)";

export interface Theme {
  axis: string;
  grid: string;
  text: string;
  series: string[];
  severity: Record<FlagDescriptor["severity"], string>;
  font: string;
  /** The monospace family (read once: getComputedStyle in a draw hook costs a style pass). */
  mono: string;
  cursor: string;
}

export function css(name: string, fallback: string): string {
  const value = getComputedStyle(document.documentElement).getPropertyValue(name).trim();
  return value || fallback;
}

export function readTheme(): Theme {
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
    mono: css("--mono", "monospace"),
    cursor: css("--amber", "#ffae1f"),
  };
}

export function decimals(incr: number): number {
  if (!Number.isFinite(incr) || incr <= 0) return 0;
  return Math.max(0, Math.min(6, -Math.floor(Math.log10(incr) + 1e-9)));
}

export function axisNumber(v: number, incr: number): string {
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

export interface Panel {
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
  /** The header's height as last measured (a phone's legend may wrap), px. */
  headerPx?: number;
  states: StatesPanel | null;
  /** Flag runs [t0, t1, …] per flag (flags plots). */
  runs: number[][];
  tab: HTMLButtonElement;
}

/** What the options, hooks and header of a panel ask of the stack that owns it. */
export interface PlotHost {
  readonly theme: Theme;
  readonly units: UnitPrefs;
  readonly yAxisPx: number;
  readonly syncKey: string;
  readonly light: boolean;
  readonly flagByName: Map<string, FlagDescriptor>;
  readonly xMode: "clock" | "rel";
  readonly frame: Frame | null;
  readonly cursors: { a: number | null; b: number | null };
  color(i: number): string;
  isHidden(plotName: string, name: string): boolean;
  hiddenOf(plotName: string): string[];
  sparse(): boolean;
  slowMarkers(name: string): number[] | null;
  xText(v: number, incr: number): string;
  fitLabel(text: string): string;
  onSelect(u: uPlot): void;
  onCursor(panel: Panel, u: uPlot): void;
  toggleSeries(plotName: string, name: string): void;
}

/** Run bars of the flags, one lane each, straight from the buffer. */
export function drawFlags(host: PlotHost, panel: Panel, u: uPlot): void {
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
    ctx.fillStyle = host.theme.grid;
    ctx.fillRect(left, Math.round(y0) - px, width, px);
    const severity = host.flagByName.get(name)?.severity ?? "info";
    ctx.fillStyle = host.theme.severity[severity];
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
export function drawCursors(host: PlotHost, u: uPlot): void {
  const { a, b } = host.cursors;
  if (a === null && b === null) return;
  const ctx = u.ctx;
  const { left, top, width, height } = u.bbox;
  const px = devicePixelRatio || 1;
  ctx.save();
  ctx.strokeStyle = host.theme.cursor;
  ctx.fillStyle = host.theme.cursor;
  ctx.lineWidth = px;
  ctx.font = `bold ${10 * px}px ${host.theme.mono}`;
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

/** Width of an x tick label (11 px monospace: about 0.62 em per character). */
const TICK_CHAR_PX = 6.9;

/** The x tick labels with the last one dropped when it would run past the canvas's right
 * edge (uPlot centres a label on its tick: the right half would be cut). */
export function fitLastTick(u: uPlot, labels: string[], splits: number[]): string[] {
  const k = labels.length - 1;
  const last = labels[k];
  const at = splits[k];
  if (last === undefined || at === undefined) return labels;
  const px = devicePixelRatio || 1;
  const right = u.bbox.left / px + u.valToPos(at, "x") + (last.length * TICK_CHAR_PX) / 2;
  if (right > u.width) labels[k] = "";
  return labels;
}

/** The uPlot options of ``panel`` (``isLast``: the bottom plot, which carries the x axis). */
export function plotOptions(host: PlotHost, panel: Panel, width: number, isLast: boolean): uPlot.Options {
  const { plot } = panel;
  const theme = host.theme;
  const flags = plot.kind === "flags";
  const states = panel.states;
  const lanes = plot.series.length;
  const laneBase = (i: number): number => (lanes - 1 - i) * (LANE + LANE_GAP);
  const unitOf = (name: string) => host.units.unit(name);
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
        label: host.units.channel(name)?.label ?? name,
        stroke: host.color(i),
        // 1 px: software rasterisers (no GPU) draw a 1 px line as a hairline, several
        // times cheaper than a wider stroke, which must be outlined and filled.
        width: 1,
        show: !host.isHidden(plot.name, name),
        spanGaps: false,
        // Slow channels hold their value until the next real sample: a step, not a
        // line that seems to lead the fast ones. A decimated fast series is drawn by
        // the trace layer (tracelayer.ts), not by a path.
        paths: (u, si, i0, i1) => (rastered(host.frame, name) ? null : (host.frame?.slow.has(name) ? stepped : linear)?.(u, si, i0, i1)) ?? null,
        points: {
          size: 5,
          fill: host.color(i),
          show: () => !host.frame?.slow.has(name) && host.sparse(),
          filter: () => host.slowMarkers(name),
        },
        value: (_u, v) => formatValue(v, unitOf(name)),
      });
    });
  }
  const line = !flags && !states;
  const xAxis: uPlot.Axis = {
    stroke: theme.axis,
    font: theme.font,
    // A line plot's grid is drawn by its trace layer (which replaces the plot area's pixels).
    grid: line ? { show: false } : { stroke: theme.grid, width: 1 },
    ticks: { stroke: theme.grid, width: 1, size: isLast ? 4 : 0 },
    space: host.xMode === "clock" ? 96 : 70,
    size: isLast ? X_AXIS_PX : 4,
    gap: 2,
    values: isLast ? (u, splits, _ai, _space, incr) => fitLastTick(u, splits.map((v) => host.xText(v, incr)), splits) : (_u, splits) => splits.map(() => ""),
  };
  const label = !flags && !states ? host.units.unit(panel.series[0] ?? "").unit || plot.unit : "";
  const yCommon = { font: theme.font, size: host.yAxisPx, gap: 4, label, labelSize: Y_LABEL_PX, labelGap: 0, labelFont: theme.font };
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
            return value === undefined ? "" : host.fitLabel(states.names.name(value));
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
              return host.fitLabel(host.flagByName.get(name)?.label ?? name);
            }),
        }
      : {
          ...yCommon,
          stroke: theme.axis,
          space: 18,
          grid: { show: false }, // drawn by the trace layer
          ticks: { stroke: theme.grid, width: 1, size: 3 },
          values: (_u, splits, _ai, _space, incr) => splits.map((v) => axisNumber(v, incr)),
        };
  const opts: uPlot.Options = {
    width,
    height: panel.height,
    legend: { show: false },
    padding: [flags || states ? 4 : 9, PAD_RIGHT_PX, 0, 0],
    cursor: {
      sync: { key: host.syncKey, setSeries: false },
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
      setSelect: [(u) => host.onSelect(u)],
      setCursor: [(u) => host.onCursor(panel, u)],
      drawAxes: states
        ? [(u) => drawStates(u, states, host.theme, host.light, host.theme.mono)]
        : flags
          ? [(u) => drawFlags(host, panel, u)]
          : [(u) => drawTraceLayer(host, panel.series, u)],
      draw: [(u) => drawCursors(host, u)],
    },
  };
  return opts;
}

/** The header of a panel: title, legend (toggles, values) or state swatch, unit choice. */
export function panelHeader(
  host: PlotHost,
  plot: PlotDescriptor,
  series: string[],
  legendValues: HTMLElement[],
  legendItems: HTMLElement[],
  unitButtons: HTMLButtonElement[],
): { header: HTMLElement; states: StatesPanel | null } {
  const header = h("div", { class: "plot-header" }, h("span", { class: "plot-title", title: plot.label }, plot.label));
  let states: StatesPanel | null = null;
  const hidden = new Set(host.hiddenOf(plot.name));
  if (plot.kind === "line") {
    const legend = h("div", { class: "plot-legend" });
    series.forEach((name, i) => {
      const channel = host.units.channel(name);
      const value = h("span", { class: "legend-value", testid: `legend-${plot.name}-${name}` }, "—");
      legendValues.push(value);
      const item = h(
        "button",
        {
          class: hidden.has(name) ? "legend-item off" : "legend-item",
          testid: `legend-toggle-${plot.name}-${name}`,
          title: `${channel?.description ?? name}\nClick to hide or show this trace`,
          "aria-pressed": hidden.has(name) ? "false" : "true",
          onclick: () => host.toggleSeries(plot.name, name),
        },
        h("span", { class: "swatch", style: `background:${host.color(i)}` }),
        h("span", { class: "legend-label" }, channel?.label ?? name),
        value,
      );
      legendItems.push(item);
      legend.appendChild(item);
    });
    header.appendChild(legend);
    const choices = host.units.common(series);
    if (choices.length > 1) {
      const seg = h("div", { class: "seg small", title: "Display unit" });
      for (const unit of choices) {
        const b = h("button", { class: "seg-btn", testid: `unit-${plot.name}-${unit}`, onclick: () => host.units.set(series, unit) }, unit);
        b.dataset.unit = unit;
        unitButtons.push(b);
        seg.appendChild(b);
      }
      header.appendChild(seg);
    } else {
      header.appendChild(h("span", { class: "plot-unit" }, host.units.unit(series[0] ?? "").unit || plot.unit));
    }
  } else if (plot.kind === "states") {
    const name = plot.series[0] ?? "";
    const channel = host.units.channel(name);
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
  return { header, states };
}
