// A scope on a known, synthetic data set: the draw-time benchmark (4 plots × 50k
// points) and browser tests (markers on sparse data, Δ cursors on known sample times)
// use it through window.__servotune. Not reachable from the user interface.
import { AxisBuffer } from "../buffer";
import { h } from "../dom";
import { UnitPrefs } from "../units";
import type { DeviceDescriptor } from "../schema.gen";
import { PlotStack } from "./plots";
import type { LayerCounts } from "./tracelayer";

export interface LabOptions {
  samples: number;
  periodS: number;
  plots?: number;
  width?: number;
  height?: number;
}

export interface Lab {
  stack: PlotStack;
  buffer: AxisBuffer;
  el: HTMLElement;
  destroy(): void;
}

function descriptor(plots: number): DeviceDescriptor {
  const names = Array.from({ length: plots }, (_v, i) => `ch${i}`);
  return {
    device: "lab",
    model: "synthetic",
    title: "Scope lab",
    summary: "known data",
    parameters: [],
    channels: names.map((name) => ({ name, label: name, unit: "counts", description: "synthetic", conversions: [], value_names: {} })),
    flags: [{ name: "move", label: "move", description: "synthetic", severity: "info" }],
    plots: [
      ...names.map((name) => ({ name, label: name, unit: "counts", series: [name], kind: "line" as const })),
      { name: "flags", label: "flags", unit: "", series: ["move"], kind: "flags" as const },
    ],
    commands: [],
    console: { enabled: false, prompt: "", help: "", examples: [] },
  } as unknown as DeviceDescriptor;
}

/** Mount a scope on ``samples`` samples, ``periodS`` apart: ch_i = 1000·sin + i, move on in the middle third. */
export function mountLab(opts: LabOptions): Lab {
  const plots = opts.plots ?? 4;
  const d = descriptor(plots);
  const buffer = new AxisBuffer();
  const n = opts.samples;
  const chunk = 5000;
  for (let at = 0; at < n; at += chunk) {
    const m = Math.min(chunk, n - at);
    const t = Array.from({ length: m }, (_v, k) => (at + k) * opts.periodS);
    const channels: Record<string, number[]> = {};
    for (let i = 0; i < plots; i++) channels[`ch${i}`] = t.map((x) => Math.round(1000 * Math.sin(2 * Math.PI * 0.5 * x) + i));
    const move = t.map((_x, k) => ((at + k) > n / 3 && (at + k) < (2 * n) / 3 ? 1 : 0));
    buffer.push({ type: "telemetry", axis: "lab", t, channels, flags: { move } });
  }
  const abort = new AbortController();
  const stack = new PlotStack(d, buffer, new UnitPrefs(d), "lab", abort.signal);
  stack.setWindow(n * opts.periodS);
  const el = h("div", { class: "scope-lab", testid: "scope-lab", style: `position:fixed;left:0;top:0;z-index:100;width:${opts.width ?? 1200}px;height:${opts.height ?? 800}px;display:flex;overflow:hidden;background:var(--plot-bg)` }, stack.el);
  stack.el.style.flex = "1";
  stack.el.style.minWidth = "0";
  document.body.appendChild(el);
  return {
    stack,
    buffer,
    el,
    destroy: () => {
      abort.abort();
      el.remove();
    },
  };
}

type Quantiles = { p50: number; p95: number; max: number };

function quantiles(times: number[]): Quantiles {
  times.sort((a, b) => a - b);
  const q = (p: number): number => Math.round((times[Math.min(times.length - 1, Math.floor(p * times.length))] as number) * 100) / 100;
  return { p50: q(0.5), p95: q(0.95), max: q(1) };
}

/** ``m`` new samples of the lab's data set after sample ``at`` (the same signal). */
function more(at: number, m: number, periodS: number, plots: number, n: number): Parameters<AxisBuffer["push"]>[0] {
  const t = Array.from({ length: m }, (_v, k) => (at + k) * periodS);
  const channels: Record<string, number[]> = {};
  for (let i = 0; i < plots; i++) channels[`ch${i}`] = t.map((x) => Math.round(1000 * Math.sin(2 * Math.PI * 0.5 * x) + i));
  const move = t.map((_x, k) => (((at + k) % n) > n / 3 && ((at + k) % n) < (2 * n) / 3 ? 1 : 0));
  return { type: "telemetry", axis: "lab", t, channels, flags: { move } };
}

/**
 * Draw time of 4 plots × 50k points in the window (script time of a redraw, ms):
 * - rolling: 100 new samples (0.1 s) before each redraw, the window following them,
 *   as on a live page (the column cache folds in only the new samples);
 * - static: a full redraw of unchanged data (decimated columns reused);
 * - cold: a redraw after the window changed, which decimates all 4 × 50k again.
 */
export async function benchDraw(
  runs = 60,
): Promise<{ rolling: Quantiles; static: Quantiles; cold: Quantiles; points: number; layers: Record<string, LayerCounts> }> {
  const n = 50_000;
  const periodS = 0.001;
  const plots = 4;
  const lab = mountLab({ samples: n, periodS, plots });
  const frame = (): Promise<void> => new Promise((r) => requestAnimationFrame(() => r()));
  await frame();
  await frame();
  const rolling: number[] = [];
  const still: number[] = [];
  const cold: number[] = [];
  let at = n;
  // Trace-layer redraws per phase (whole / shifted / reused: what the times are made of).
  const counts = (): LayerCounts => lab.stack.layerCounts();
  const diff = (a: LayerCounts, b: LayerCounts): LayerCounts => ({
    whole: b.whole - a.whole,
    shifted: b.shifted - a.shifted,
    reused: b.reused - a.reused,
  });
  const c0 = counts();
  for (let i = 0; i < runs; i++) {
    lab.buffer.push(more(at, 100, periodS, plots, n));
    at += 100;
    const t0 = performance.now();
    lab.stack.redraw();
    rolling.push(performance.now() - t0);
    await frame();
  }
  const c1 = counts();
  for (let i = 0; i < runs; i++) {
    const t0 = performance.now();
    lab.stack.redraw();
    still.push(performance.now() - t0);
    await frame();
  }
  const c2 = counts();
  for (let i = 0; i < Math.min(runs, 30); i++) {
    // A new window length: new pixel columns, so all 4 × 50k samples are decimated again.
    lab.stack.windowS = i % 2 ? n * periodS : n * periodS * 0.999;
    const t0 = performance.now();
    lab.stack.redraw();
    cold.push(performance.now() - t0);
    await frame();
  }
  const layers = { rolling: diff(c0, c1), static: diff(c1, c2), cold: diff(c2, counts()) };
  lab.destroy();
  return { rolling: quantiles(rolling), static: quantiles(still), cold: quantiles(cold), points: n, layers };
}
