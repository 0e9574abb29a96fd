// The bench overlays: several runs on one uPlot, aligned at the trigger (t − t0), with
// the target, the settling band and the settling instants drawn on the canvas.
import uPlot from "uplot";
import { h, replace, setText } from "../dom";
import { fitLastTick } from "./plotkit";

export interface Trace {
  id: string;
  color: string;
  x: number[]; // s after t0, ascending
  y: (number | null)[];
  bold: boolean; // the baseline
  settle: number | null; // s after t0, drawn as a tick on the target line
}

export interface Target {
  y: number;
  band: number | null;
  color: string | null; // null: neutral (all runs share this target)
}

export interface PlotTheme {
  axis: string;
  grid: string;
  text: string;
  faint: string;
  font: string;
}

function css(name: string, fallback: string): string {
  const value = getComputedStyle(document.documentElement).getPropertyValue(name).trim();
  return value || fallback;
}

export function plotTheme(): PlotTheme {
  return {
    axis: css("--plot-axis", "#8a96a3"),
    grid: css("--plot-grid", "#243040"),
    text: css("--text-dim", "#8a96a3"),
    faint: css("--text-faint", "#5d6a78"),
    font: `11px ${css("--mono", "monospace")}`,
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

/** Value of a trace at ``x``: the sample at or before it (the samples are polled). */
export function valueAt(trace: Trace, x: number): number | null {
  const xs = trace.x;
  let lo = 0;
  let hi = xs.length - 1;
  if (hi < 0 || x < (xs[0] as number)) return null;
  while (lo < hi) {
    const mid = (lo + hi + 1) >> 1;
    if ((xs[mid] as number) <= x) lo = mid;
    else hi = mid - 1;
  }
  for (let i = lo; i >= 0 && i > lo - 8; i--) {
    const v = trace.y[i];
    if (v !== null && v !== undefined) return v;
  }
  return null;
}

/** One overlay plot; rebuilt whenever its set of traces changes (they are small). */
export class Overlay {
  readonly el: HTMLElement;
  readonly host: HTMLElement;
  private u: uPlot | null = null;
  private traces: Trace[] = [];
  private targets: Target[] = [];
  private readonly observer: ResizeObserver;
  private readonly empty: HTMLElement;
  private width = 0;
  private height = 0;
  private syncing = false;
  /** The x range shown (null: the whole run); the y range follows it. */
  private xWindow: [number, number] | null = null;
  /** Initial end of the x range (s): the interesting part, not a long flat tail. */
  private focus: number | null = null;
  /** Called with the cursor's x (s after t0), or null when it leaves the plot. */
  onCursor: (x: number | null) => void = () => {};
  /** Called when the user zooms (x range) or resets (null). */
  onZoom: (range: [number, number] | null) => void = () => {};

  constructor(
    testid: string,
    private readonly syncKey: string,
    private readonly theme: PlotTheme,
    private readonly yUnit: () => string,
  ) {
    this.empty = h("div", { class: "bench-plot-empty" });
    this.host = h("div", { class: "bench-host", testid, "data-series": "0" }, this.empty);
    this.el = this.host;
    this.observer = new ResizeObserver(() => this.resize());
    this.observer.observe(this.host);
  }

  private resize(): void {
    const width = Math.floor(this.host.clientWidth);
    const height = Math.floor(this.host.clientHeight);
    if (width < 50 || height < 40) return;
    if (width === this.width && height === this.height) return;
    this.width = width;
    this.height = height;
    if (this.u) this.u.setSize({ width, height });
    else if (this.traces.length) this.build();
  }

  /** Replace what is drawn. ``message`` shows instead of the plot when nothing is. */
  set(traces: Trace[], targets: Target[], message: string, focus: number | null = null): void {
    this.traces = traces;
    this.targets = targets;
    this.focus = focus;
    this.host.dataset.series = String(traces.length);
    setText(this.empty, message);
    this.u?.destroy();
    this.u = null;
    this.xWindow = null;
    if (!traces.length) {
      replace(this.host, this.empty);
      return;
    }
    replace(this.host);
    this.build();
  }

  setX(range: [number, number] | null): void {
    if (!this.u) return;
    this.syncing = true;
    if (range) this.u.setScale("x", { min: range[0], max: range[1] });
    else this.u.setScale("x", this.fullX());
    this.syncing = false;
  }

  private fullX(): { min: number; max: number } {
    let min = 0;
    let max = 0.5;
    for (const t of this.traces) {
      if (t.x.length) {
        min = Math.min(min, t.x[0] as number);
        max = Math.max(max, t.x[t.x.length - 1] as number);
      }
    }
    return { min, max };
  }

  private build(): void {
    if (!this.width || !this.height) return;
    const theme = this.theme;
    const data = uPlot.join(this.traces.map((t) => [t.x, t.y.map((v) => (v === null ? null : v))] as uPlot.AlignedData)) as uPlot.AlignedData;
    const sparse = this.traces.every((t) => t.x.length < this.width / 6);
    const series: uPlot.Series[] = [
      {},
      ...this.traces.map((t) => ({
        label: t.id,
        stroke: t.color,
        width: t.bold ? 2.25 : 1.5,
        spanGaps: true,
        points: { show: sparse, size: t.bold ? 5 : 4, fill: t.color, stroke: t.color },
      })),
    ];
    const full = this.fullX();
    const opts: uPlot.Options = {
      width: this.width,
      height: this.height,
      legend: { show: false },
      padding: [10, 14, 0, 0],
      cursor: {
        sync: { key: this.syncKey, setSeries: false },
        drag: { x: true, y: false, setScale: true },
        points: { size: 6 },
        focus: { prox: 24 },
      },
      focus: { alpha: 0.3 },
      scales: {
        x: { time: false, range: (_u, min, max) => (min === max ? [full.min, full.max] : [min, max]) },
        y: {
          // From the samples after the trigger (what the metrics look at): a wild
          // pre-trigger value (an axis still moving when armed) must not squash the rest.
          range: (u, dataMin, dataMax) => this.yRange(u, dataMin, dataMax),
        },
      },
      axes: [
        {
          stroke: theme.axis,
          font: theme.font,
          grid: { stroke: theme.grid, width: 1 },
          ticks: { stroke: theme.grid, width: 1, size: 4 },
          space: 60,
          size: 24,
          gap: 2,
          // The last label is dropped when centring it on its tick would cut it.
          values: (u, splits, _ai, _space, incr) => fitLastTick(u, splits.map((v) => `${v.toFixed(decimals(incr))} s`), splits),
        },
        {
          stroke: theme.axis,
          font: theme.font,
          size: 60,
          gap: 4,
          space: this.height < 120 ? 14 : 22,
          grid: { stroke: theme.grid, width: 1 },
          ticks: { stroke: theme.grid, width: 1, size: 3 },
          values: (_u, splits, _ai, _space, incr) => splits.map((v) => axisNumber(v, incr)),
        },
      ],
      series,
      hooks: {
        drawClear: [(u) => this.drawUnder(u)],
        draw: [(u) => this.drawOver(u)],
        setCursor: [
          (u) => {
            const left = u.cursor.left;
            this.onCursor(left === undefined || left < 0 ? null : u.posToVal(left, "x"));
          },
        ],
        setScale: [
          (u, key) => {
            if (key !== "x") return;
            const { min, max } = u.scales.x;
            if (min === undefined || max === undefined) return;
            const isFull = Math.abs(min - full.min) < 1e-9 && Math.abs(max - full.max) < 1e-9;
            const window: [number, number] | null = isFull ? null : [min, max];
            if (String(window) !== String(this.xWindow)) {
              this.xWindow = window;
              // y was ranged over the previous window: range it again for this one.
              queueMicrotask(() => {
                const [min, max] = this.yRange(u, Number.NaN, Number.NaN);
                u.setScale("y", { min, max });
              });
            }
            if (!this.syncing) this.onZoom(window);
          },
        ],
      },
    };
    this.u = new uPlot(opts, data, this.host);
    if (this.focus !== null && this.focus < full.max) {
      this.syncing = true;
      this.u.setScale("x", { min: full.min, max: this.focus });
      this.syncing = false;
    }
    this.u.over.addEventListener("mouseleave", () => this.onCursor(null));
    this.u.over.title = `drag: zoom · double-click: whole run · ${this.yUnit()}`;
  }

  /** The y range: the traces from t0 on in the visible x range, the targets, and 0. */
  private yRange(u: uPlot, dataMin: number, dataMax: number): [number, number] {
    let [min, max] = this.visibleRange(u);
    if (!Number.isFinite(min) || !Number.isFinite(max)) [min, max] = [dataMin, dataMax];
    for (const t of this.targets) {
      min = Math.min(min, t.y - (t.band ?? 0));
      max = Math.max(max, t.y + (t.band ?? 0));
    }
    min = Math.min(min, 0);
    max = Math.max(max, 0);
    if (!Number.isFinite(min) || !Number.isFinite(max)) return [-1, 1];
    if (max - min < 1e-9) return [min - 1, max + 1];
    const pad = (max - min) * 0.07;
    return [min - pad, max + pad];
  }

  /** Min and max of the traces over the visible x range from t0 on. */
  private visibleRange(u: uPlot): [number, number] {
    const xs = u.data[0] as number[];
    const lo = Math.max(0, this.xWindow?.[0] ?? 0);
    const hi = this.xWindow?.[1] ?? Infinity;
    let min = Infinity;
    let max = -Infinity;
    for (let s = 1; s < u.data.length; s++) {
      const ys = u.data[s] as (number | null)[];
      for (let i = 0; i < xs.length; i++) {
        const x = xs[i] as number;
        const y = ys[i];
        if (x < lo || x > hi || y === null || y === undefined) continue;
        if (y < min) min = y;
        if (y > max) max = y;
      }
    }
    return [min, max];
  }

  /** Band and target under the traces; the trigger line. */
  private drawUnder(u: uPlot): void {
    const ctx = u.ctx;
    const { left, top, width, height } = u.bbox;
    ctx.save();
    ctx.beginPath();
    ctx.rect(left, top, width, height);
    ctx.clip();
    const px = devicePixelRatio || 1;
    for (const t of this.targets) {
      const color = t.color ?? this.theme.text;
      if (t.band !== null && t.band > 0) {
        const y1 = u.valToPos(t.y + t.band, "y", true);
        const y2 = u.valToPos(t.y - t.band, "y", true);
        ctx.fillStyle = color;
        ctx.globalAlpha = 0.1;
        ctx.fillRect(left, Math.min(y1, y2), width, Math.max(px, Math.abs(y2 - y1)));
        ctx.globalAlpha = 1;
      }
      const y = Math.round(u.valToPos(t.y, "y", true)) + 0.5;
      ctx.strokeStyle = color;
      ctx.globalAlpha = t.color ? 0.75 : 0.9;
      ctx.lineWidth = px;
      ctx.setLineDash([6 * px, 4 * px]);
      ctx.beginPath();
      ctx.moveTo(left, y);
      ctx.lineTo(left + width, y);
      ctx.stroke();
      ctx.globalAlpha = 1;
    }
    // The trigger (t0) and the zero line.
    ctx.setLineDash([2 * px, 3 * px]);
    ctx.strokeStyle = this.theme.faint;
    ctx.lineWidth = px;
    const x0 = Math.round(u.valToPos(0, "x", true)) + 0.5;
    if (x0 >= left && x0 <= left + width) {
      ctx.beginPath();
      ctx.moveTo(x0, top);
      ctx.lineTo(x0, top + height);
      ctx.stroke();
      ctx.setLineDash([]);
      ctx.fillStyle = this.theme.faint;
      ctx.font = `${10 * px}px ${getComputedStyle(document.documentElement).getPropertyValue("--mono")}`;
      ctx.fillText("t0", x0 + 3 * px, top + 10 * px);
    }
    ctx.restore();
  }

  /** Settling instants: a tick in the run's colour on its target line. */
  private drawOver(u: uPlot): void {
    const ctx = u.ctx;
    const { left, top, width, height } = u.bbox;
    const px = devicePixelRatio || 1;
    ctx.save();
    ctx.beginPath();
    ctx.rect(left, top, width, height);
    ctx.clip();
    for (const trace of this.traces) {
      if (trace.settle === null) continue;
      const target = this.targets.find((t) => t.color === trace.color) ?? this.targets.find((t) => t.color === null);
      if (!target) continue;
      const x = u.valToPos(trace.settle, "x", true);
      const y = u.valToPos(target.y, "y", true);
      ctx.strokeStyle = trace.color;
      ctx.lineWidth = 2 * px;
      ctx.beginPath();
      ctx.moveTo(x, y - 9 * px);
      ctx.lineTo(x, y + 9 * px);
      ctx.stroke();
    }
    ctx.restore();
  }

  destroy(): void {
    this.observer.disconnect();
    this.u?.destroy();
    this.u = null;
  }
}
