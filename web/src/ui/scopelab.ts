// A scope on a known, synthetic data set: the draw-time benchmark (4 plots × 50k
// points) and browser tests (markers on sparse data, Δ cursors on known sample times)
// use it through window.__servotune. Not reachable from the user interface.
import { AxisBuffer } from "../buffer";
import { h } from "../dom";
import { UnitPrefs } from "../units";
import type { DeviceDescriptor } from "../wire.gen";
import { PlotStack } from "./plots";

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

/** Draw time of 4 plots × 50k points: ``runs`` full redraws, p50/p95/max in ms. */
export async function benchDraw(runs = 60): Promise<{ p50: number; p95: number; max: number; points: number }> {
  const lab = mountLab({ samples: 50_000, periodS: 0.001, plots: 4 });
  await new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)));
  const times: number[] = [];
  for (let i = 0; i < runs; i++) {
    const t0 = performance.now();
    lab.stack.redraw();
    times.push(performance.now() - t0);
    await new Promise((r) => requestAnimationFrame(r));
  }
  lab.destroy();
  times.sort((a, b) => a - b);
  const q = (p: number): number => Math.round((times[Math.min(times.length - 1, Math.floor(p * times.length))] as number) * 100) / 100;
  return { p50: q(0.5), p95: q(0.95), max: q(1), points: 50_000 };
}
