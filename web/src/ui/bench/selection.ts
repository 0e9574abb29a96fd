// Which runs of an axis the overlay shows, and their colours: kept across view toggles
// and axis switches, and in localStorage across reloads.
import type { BenchRun } from "../../api";

const MAX_SELECTED = 8;

const selections = new Map<string, string[]>(); // axis -> selected run ids, in selection order
const colors = new Map<string, number>(); // run id -> palette slot while selected

function palette(): string[] {
  const style = getComputedStyle(document.documentElement);
  const series = [1, 2, 3, 4, 5, 6].map((i) => style.getPropertyValue(`--series-${i}`).trim() || "#4cc2ff");
  const extra = [7, 8].map((i) => style.getPropertyValue(`--series-${i}`).trim() || (i === 7 ? "#ff8a5c" : "#9fb3c8"));
  return [...series, ...extra];
}

/** The selection of one axis. */
export class Selection {
  constructor(private readonly axisId: string) {}

  /** The selected run ids, in selection order (read from localStorage the first time). */
  ids(): string[] {
    let sel = selections.get(this.axisId);
    if (!sel) {
      try {
        sel = JSON.parse(localStorage.getItem(`servotune.bench.selected.${this.axisId}`) ?? "[]") as string[];
      } catch {
        sel = [];
      }
      selections.set(this.axisId, sel);
    }
    return sel;
  }

  /** Whether this axis' selection has been read or set in this page. */
  known(): boolean {
    return selections.has(this.axisId);
  }

  save(sel: string[]): void {
    selections.set(this.axisId, sel);
    try {
      localStorage.setItem(`servotune.bench.selected.${this.axisId}`, JSON.stringify(sel));
    } catch {
      /* private mode */
    }
  }

  /** At most MAX_SELECTED, dropping the oldest selected that is not the baseline. */
  cap(sel: string[], runs: BenchRun[]): string[] {
    const baseline = runs.find((r) => r.baseline)?.id;
    while (sel.length > MAX_SELECTED) {
      const drop = sel.findIndex((id) => id !== baseline);
      sel.splice(drop < 0 ? 0 : drop, 1);
    }
    return sel;
  }

  /** Keep each selected run's colour; give the newly selected the free slots. */
  assignColors(sel: string[]): void {
    const slots = palette().length;
    const used = new Set<number>();
    for (const id of sel) {
      const slot = colors.get(id);
      if (slot !== undefined && !used.has(slot)) used.add(slot);
      else colors.delete(id);
    }
    for (const id of sel) {
      if (colors.has(id)) continue;
      let slot = 0;
      while (used.has(slot) && slot < slots - 1) slot++;
      used.add(slot);
      colors.set(id, slot);
    }
  }

  color(id: string): string {
    const p = palette();
    return p[(colors.get(id) ?? 0) % p.length] as string;
  }
}
