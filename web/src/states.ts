// Enumerated channels (``ChannelDescriptor.value_names``): the name of a value, its id
// as shown next to the name, and a stable colour per state for the states plot.
import type { ChannelDescriptor } from "./schema.gen";

export class StateNames {
  /** Named values, ascending. */
  readonly values: number[];
  private readonly names = new Map<number, string>();
  private readonly hex: boolean;

  constructor(readonly channel: ChannelDescriptor) {
    for (const [key, name] of Object.entries(channel.value_names)) {
      const value = Number(key);
      if (Number.isFinite(value)) this.names.set(value, name);
    }
    this.values = [...this.names.keys()].sort((a, b) => a - b);
    // Ids that span more than a byte read better in hex (0x1001 rather than 4097).
    this.hex = (this.values[this.values.length - 1] ?? 0) >= 256;
  }

  static of(channel: ChannelDescriptor | undefined): StateNames | null {
    return channel && Object.keys(channel.value_names ?? {}).length ? new StateNames(channel) : null;
  }

  has(value: number): boolean {
    return this.names.has(value);
  }

  /** "TARGET", or the id itself for a value the descriptor does not name. */
  name(value: number): string {
    return this.names.get(value) ?? this.id(value);
  }

  /** The id as shown small next to the name: "0x1001" or "5". */
  id(value: number): string {
    if (!Number.isInteger(value)) return String(value);
    if (!this.hex || value < 0) return String(value);
    return `0x${value.toString(16).toUpperCase().padStart(4, "0")}`;
  }

  /** Hover text of a value: name, id in both bases, and what the channel is. */
  describe(value: number): string {
    const known = this.names.has(value);
    const ids = this.hex && Number.isInteger(value) && value >= 0 ? `${this.id(value)} = ${value}` : String(value);
    return `${known ? this.name(value) : "unnamed value"} (id ${ids})\n${this.channel.label}: ${this.channel.description}`;
  }

  /** A colour per state, stable across sessions: golden-angle hues in value order. */
  color(value: number, light: boolean): string {
    const index = this.values.indexOf(value);
    if (index < 0) return light ? "#8793a0" : "#5d6a78";
    const hue = (200 + index * 137.508) % 360;
    return light ? `hsl(${hue.toFixed(0)} 62% 42%)` : `hsl(${hue.toFixed(0)} 70% 62%)`;
  }
}
