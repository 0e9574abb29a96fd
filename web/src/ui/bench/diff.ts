// The parameters that differ between the selected runs, side by side.
import type { BenchRun } from "../../api";
import { h, replace } from "../../dom";
import type { DeviceDescriptor } from "../../schema.gen";
import { shortId } from "./kinds";

export class ParamDiff {
  readonly el: HTMLElement;

  constructor(private readonly descriptor: DeviceDescriptor) {
    this.el = h("div", { class: "bench-diff", testid: "bench-param-diff" });
  }

  show(runs: BenchRun[], color: (id: string) => string): void {
    if (runs.length < 2) {
      replace(this.el, h("div", { class: "bench-diff-side" }, h("span", { class: "pane-title" }, "Parameter diff"), h("span", { class: "pane-sub" }, "select two or more runs to compare their parameters")));
      return;
    }
    const names = diffParams(runs);
    const labels = new Map(this.descriptor.parameters.map((p) => [p.name, p]));
    const ref = runs[0] as BenchRun;
    const header = h(
      "tr",
      null,
      h("th", { class: "d-name" }, "parameter"),
      runs.map((r) =>
        h(
          "th",
          { class: `d-run${r.baseline ? " baseline" : ""}`, title: `${r.id}${r.baseline ? " (baseline)" : ""}` },
          h("span", { class: "run-swatch", style: `background:${color(r.id)}` }),
          `${r.baseline ? "★ " : ""}${shortId(r.id)}`,
        ),
      ),
    );
    const rows = names.map((name) => {
      const p = labels.get(name);
      return h(
        "tr",
        { "data-param": name },
        h("td", { class: "d-name", title: p?.description ?? name }, p ? `${p.label}` : name, h("span", { class: "d-key mono" }, p && p.label.toLowerCase() !== name ? ` ${name}` : "")),
        runs.map((r, i) => {
          const v = r.params[name];
          const differs = i > 0 && v !== ref.params[name];
          return h("td", { class: `d-val num${differs ? " differs" : ""}${i === 0 ? " ref" : ""}` }, v === undefined ? "—" : String(v), p?.unit ? h("span", { class: "d-unit" }, ` ${p.unit}`) : null);
        }),
      );
    });
    const table = h("table", { class: "diff-table" }, h("thead", null, header), h("tbody", null, rows));
    const caption = names.length
      ? `${names.length} of ${new Set(runs.flatMap((r) => Object.keys(r.params))).size} parameters differ between the ${runs.length} selected runs; highlighted: not as in ${ref.baseline ? "the ★ baseline" : "the oldest selected run"} ${shortId(ref.id)}`
      : `the ${runs.length} selected runs ran with identical parameters`;
    replace(
      this.el,
      h("div", { class: "bench-diff-side" }, h("span", { class: "pane-title" }, "Parameter diff"), h("span", { class: "pane-sub" }, caption)),
      names.length ? table : null,
    );
  }
}

/** Parameters whose values are not the same in every run (in descriptor order of the first). */
export function diffParams(runs: BenchRun[]): string[] {
  if (runs.length < 2) return [];
  const names: string[] = [];
  const seen = new Set<string>();
  for (const run of runs) for (const name of Object.keys(run.params)) if (!seen.has(name)) (seen.add(name), names.push(name));
  return names.filter((name) => runs.some((r) => r.params[name] !== runs[0]?.params[name]));
}
