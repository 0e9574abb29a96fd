// Big numbers for every channel (latest value, chosen unit) and a lamp per flag.
import type { AxisBuffer } from "../buffer";
import { h, setText, toggleClass } from "../dom";
import { formatValue } from "../format";
import { StateNames } from "../states";
import type { UnitPrefs } from "../units";
import type { DeviceDescriptor } from "../schema.gen";

export class Readouts {
  readonly el: HTMLElement;
  private readonly values = new Map<string, HTMLElement>();
  private readonly unitLabels = new Map<string, HTMLElement>();
  private readonly lamps = new Map<string, HTMLElement>();
  /** "0.6 s old" beside a value that did not come with the latest sample (slow channel). */
  private readonly ages = new Map<string, HTMLElement>();
  /** Buffer index up to which the flags were shown. */
  private scannedTo = 0;
  /** Enumerated channels: the value shows as its name, the id small beside it. */
  private readonly states = new Map<string, { names: StateNames; box: HTMLElement }>();

  constructor(
    private readonly descriptor: DeviceDescriptor,
    private readonly buffer: AxisBuffer,
    private readonly units: UnitPrefs,
    signal: AbortSignal,
  ) {
    const numbers = h("div", { class: "readouts" });
    for (const channel of descriptor.channels) {
      const value = h("span", { class: "readout-value", testid: `readout-${channel.name}` }, "—");
      const names = StateNames.of(channel);
      const multi = channel.conversions.length > 0 && !names;
      const unit = h(
        multi ? "button" : "span",
        {
          class: multi ? "readout-unit switchable" : "readout-unit",
          title: multi ? "Click to change the display unit" : undefined,
          testid: `unit-readout-${channel.name}`,
          onclick: multi ? () => units.cycle(channel.name) : undefined,
        },
        "",
      );
      this.values.set(channel.name, value);
      const age = h("span", { class: "readout-age", testid: `readout-age-${channel.name}`, title: "Age of this value: the channel is read less often than the others" }, "");
      this.ages.set(channel.name, age);
      this.unitLabels.set(channel.name, unit);
      const box = h(
        "div",
        { class: names ? "readout enum" : "readout", title: `${channel.label}: ${channel.description}` },
        h("div", { class: "readout-label" }, channel.label, age),
        h("div", { class: "readout-line" }, value, unit),
      );
      if (names) {
        unit.classList.add("readout-id");
        this.states.set(channel.name, { names, box });
      }
      numbers.appendChild(box);
    }
    const lamps = h("div", { class: "lamps" });
    // Two rows for a handful of flags, up to four for devices with many.
    const rows = Math.min(4, Math.max(2, Math.ceil(descriptor.flags.length / 7)));
    lamps.style.setProperty("--lamp-cols", String(Math.max(1, Math.ceil(descriptor.flags.length / rows))));
    for (const flag of descriptor.flags) {
      const lamp = h(
        "div",
        {
          class: `lamp sev-${flag.severity}`,
          testid: `flag-${flag.name}`,
          title: `${flag.label} (${flag.severity}): ${flag.description}`,
          "data-on": "0",
        },
        h("span", { class: "lamp-dot" }),
        h("span", { class: "lamp-label" }, flag.label),
      );
      this.lamps.set(flag.name, lamp);
      lamps.appendChild(lamp);
    }
    this.el = h("div", { class: "readout-bar" }, numbers, lamps);
    units.onChange(() => this.update(), signal);
    this.update();
  }

  update(): void {
    for (const channel of this.descriptor.channels) {
      const unit = this.units.unit(channel.name);
      const raw = this.buffer.latest.get(channel.name);
      const el = this.values.get(channel.name) as HTMLElement;
      const state = this.states.get(channel.name);
      if (state) {
        const known = raw !== undefined && state.names.has(raw);
        setText(el, raw === undefined ? "—" : state.names.name(raw));
        toggleClass(el, "unnamed", raw !== undefined && !known);
        const value = raw === undefined ? "" : String(raw);
        if (el.dataset.value !== value) el.dataset.value = value;
        // The id beside a name; an unnamed value already shows as its id.
        setText(this.unitLabels.get(channel.name) as HTMLElement, known ? state.names.id(raw) : channel.unit);
        const title = raw === undefined ? `${channel.label}: ${channel.description}` : state.names.describe(raw);
        if (state.box.title !== title) state.box.title = title;
        continue;
      }
      setText(el, formatValue(raw === undefined ? null : raw * unit.factor, unit));
      // Attributes only when they change: a same-value write still invalidates style.
      if (el.dataset.unit !== unit.unit) el.dataset.unit = unit.unit;
      const at = this.buffer.latestT.get(channel.name);
      const age = at === undefined ? 0 : this.buffer.lastT - at;
      setText(this.ages.get(channel.name) as HTMLElement, age > 0.05 ? ` · ${age.toFixed(1)} s old` : "");
      setText(this.unitLabels.get(channel.name) as HTMLElement, unit.unit);
    }
    const stale = !Number.isFinite(this.buffer.lastT);
    // A lamp is on if the flag was on in any sample since the last refresh (10 Hz), so
    // a pulse shorter than the refresh period (a short move's `busy`) is not missed.
    const b = this.buffer;
    const from = Math.max(b.start, Math.min(this.scannedTo, b.end - 1));
    if (b.end < this.scannedTo) this.scannedTo = b.start; // the buffer was cleared
    for (const [name, lamp] of this.lamps) {
      let on = b.latestFlags.get(name) === 1;
      const col = b.flags.get(name);
      if (col && !on) for (let i = from; i < b.end && !on; i++) on = col[i] === 1;
      if (lamp.dataset.on !== (on ? "1" : "0")) lamp.dataset.on = on ? "1" : "0";
      toggleClass(lamp, "on", on);
      toggleClass(lamp, "stale", stale);
    }
    this.scannedTo = b.end;
  }
}
