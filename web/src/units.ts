// The display unit chosen per channel (counts / rev / °, counts/s / rpm), shared by the
// plots and the readouts of one device family and remembered in localStorage.
import { type Unit, unitsOf } from "./format";
import type { ChannelDescriptor, DeviceDescriptor } from "./schema.gen";

export class UnitPrefs {
  private readonly chosen = new Map<string, string>();
  private readonly listeners = new Set<() => void>();
  private readonly key: string;

  constructor(private readonly descriptor: DeviceDescriptor) {
    this.key = `servotune.units.${descriptor.device}`;
    try {
      const saved = JSON.parse(localStorage.getItem(this.key) ?? "{}") as Record<string, string>;
      for (const [channel, unit] of Object.entries(saved)) this.chosen.set(channel, unit);
    } catch {
      /* ignore a corrupt entry */
    }
  }

  channel(name: string): ChannelDescriptor | undefined {
    return this.descriptor.channels.find((c) => c.name === name);
  }

  units(name: string): Unit[] {
    const channel = this.channel(name);
    return channel ? unitsOf(channel.unit, channel.conversions) : [{ unit: "", factor: 1, digits: null }];
  }

  unit(name: string): Unit {
    const all = this.units(name);
    const want = this.chosen.get(name);
    return all.find((u) => u.unit === want) ?? (all[0] as Unit);
  }

  set(names: string[], unit: string): void {
    for (const name of names) {
      if (this.units(name).some((u) => u.unit === unit)) this.chosen.set(name, unit);
    }
    try {
      localStorage.setItem(this.key, JSON.stringify(Object.fromEntries(this.chosen)));
    } catch {
      /* private mode */
    }
    for (const fn of this.listeners) fn();
  }

  /** Cycle one channel to its next unit (click on a readout's unit). */
  cycle(name: string): void {
    const all = this.units(name);
    const index = all.findIndex((u) => u.unit === this.unit(name).unit);
    const next = all[(index + 1) % all.length];
    if (next) this.set([name], next.unit);
  }

  /** Units every channel of ``names`` offers (native first), for a plot's unit toggle. */
  common(names: string[]): string[] {
    const first = names[0];
    if (first === undefined) return [];
    const base = this.units(first).map((u) => u.unit);
    return base.filter((unit) => names.every((n) => this.units(n).some((u) => u.unit === unit)));
  }

  onChange(fn: () => void, signal: AbortSignal): void {
    this.listeners.add(fn);
    signal.addEventListener("abort", () => this.listeners.delete(fn), { once: true });
  }
}
