// The tuning panel: one row per descriptor parameter. A change is written on slider
// release or Enter (PATCH), and the field then shows what the device read back; a
// field whose value the device does not have is marked until they agree.
import { api } from "../api";
import { h, replace, setText, toggleClass } from "../dom";
import { formatConverted } from "../format";
import { store } from "../store";
import type { BitDescriptor, CommandDescriptor, DeviceDescriptor, ParameterDescriptor } from "../schema.gen";
import { commandWidget, makeRunner } from "./commands";
import { errorText, showError, statusLabel } from "./feedback";
import { ParamSetsPanel } from "./paramsets";

function rangeText(p: ParameterDescriptor): string {
  return `${p.minimum}..${p.maximum}${p.unit ? ` ${p.unit}` : ""}`;
}

/** "100/16/8": values of several parameters, "?" for one not known. */
function joined(names: string[], values: (name: string) => number | undefined): string {
  return names.map((n) => values(n) ?? "?").join("/");
}

/** How the parameters a write also changed are named in its offer: their group when
 * they are exactly one whole group ("gains standstill (KABD)"), else their labels. */
function subjectOf(names: string[], byName: Map<string, ParameterDescriptor>): string {
  const params = names.map((n) => byName.get(n));
  const group = params[0]?.group;
  const whole =
    group !== undefined &&
    params.every((p) => p?.group === group) &&
    [...byName.values()].filter((p) => p.group === group).length === names.length;
  if (whole && names.length > 1) return group;
  return params.map((p, i) => p?.label ?? names[i]).join(" / ");
}

/** A write changed other parameters on the device too (``overwrites``): the values the
 * user had for them before, and the offer to write those again. */
interface Offer {
  names: string[];
  before: Map<string, number>;
  el: HTMLElement;
}

function bitsOf(p: ParameterDescriptor): BitDescriptor[] {
  if (p.bits.length) return p.bits;
  const count = Math.max(1, Math.min(32, Math.floor(Math.log2(Math.max(1, p.maximum))) + 1));
  return Array.from({ length: count }, (_, bit) => ({ bit, name: `bit${bit}`, label: `bit ${bit}`, description: `Bit ${bit} of ${p.label}` }));
}

class ParamRow {
  readonly el: HTMLElement;
  private readonly input: HTMLInputElement;
  private readonly slider: HTMLInputElement | null = null;
  private readonly device: HTMLElement;
  private readonly deviceBox: HTMLElement;
  private readonly conversions: HTMLElement;
  private readonly error: HTMLElement;
  private readonly checks: Map<number, HTMLInputElement> = new Map();
  private readonly sliderMin: number;
  private readonly sliderMax: number;
  private forceInput = false;
  private busy = 0;
  private offer: Offer | null = null;
  private readonly offerHost: HTMLElement;
  private readonly persistTag: HTMLElement | null;

  constructor(
    private readonly axisId: string,
    readonly p: ParameterDescriptor,
    private readonly byName: Map<string, ParameterDescriptor>,
    /** The write group this parameter belongs to: edits are staged, the group bar writes. */
    private readonly group: string[] | null = null,
    /** The device's save command, if it has one (SLAP2 pg, Z1100 SetFlash); without one
     * a persisted parameter is stored by the write itself (EP7047 CoE). */
    private readonly saveCommand: CommandDescriptor | null = null,
  ) {
    // The slider covers the useful range (slider_minimum..slider_maximum, e.g. a signed
    // velocity of ±20000 out of ±65535); the field takes the whole range, and the
    // slider stretches to a value beyond its range (marked "extended").
    this.sliderMin = Math.max(p.minimum, p.slider_minimum ?? p.minimum);
    this.sliderMax = Math.min(p.maximum, p.slider_maximum ?? p.maximum);
    // Gains: a track of 4× the factory value (at least 0..100), so the factory value
    // sits at a quarter of it and a drag is a tuning step, not a jump across decades;
    // the field takes the full range and the track extends to a larger value.
    if (/gain/i.test(p.group) && p.default !== null && p.default > 0 && p.minimum >= 0) {
      this.sliderMax = Math.min(this.sliderMax, Math.max(100, 4 * p.default));
    }
    const tip = `${p.description}\n\n${p.name} · range ${rangeText(p)}${p.default !== null ? ` · default ${p.default}` : ""}${p.persisted ? " · stored by the device's save command" : ""}`;
    this.input = h("input", {
      class: "input num param-input",
      type: "number",
      step: 1,
      min: p.minimum,
      max: p.maximum,
      testid: `param-${p.name}-input`,
      title: `${p.label}: ${rangeText(p)} — Enter writes it to the device`,
      "aria-label": p.label,
    });
    this.device = h("span", { class: "device-value", testid: `param-${p.name}-device` }, "—");
    this.deviceBox = h("span", { class: "device", title: "Value read back from the device" }, h("span", { class: "device-label" }, "device"), this.device);
    this.conversions = h("div", { class: "param-conv", testid: `param-${p.name}-conv` });
    this.error = h("div", { class: "param-error", testid: `param-${p.name}-error`, role: "status" });
    this.offerHost = h("div", { class: "overwrite-slot" });
    this.persistTag = p.persisted ? h("span", { class: "tag persist", testid: `param-${p.name}-persist` }, "") : null;

    this.input.addEventListener("input", () => {
      const value = this.parse(this.input.value);
      if (value !== null) this.setUi(value);
      else toggleClass(this.input, "invalid", this.input.value.trim() !== "");
    });
    this.input.addEventListener("keydown", (event) => {
      if (event.key === "Enter") {
        event.preventDefault();
        const text = this.input.value.trim();
        const value = text === "" ? Number.NaN : Number(text);
        void this.commit(value);
      }
    });
    this.input.addEventListener("blur", () => this.render());

    const label = h(
      "div",
      { class: "param-label", title: tip },
      h("span", { class: "param-name" }, p.label),
      this.persistTag,
    );
    let control: HTMLElement;
    if (p.kind === "bits") {
      const boxes = bitsOf(p).map((b) => {
        const check = h("input", { type: "checkbox", testid: `param-${p.name}-bit-${b.name}` });
        check.addEventListener("change", () => void this.commit(this.wordFromChecks()));
        this.checks.set(b.bit, check);
        return h("label", { class: "bit", title: `bit ${b.bit}: ${b.description}` }, check, h("span", null, b.label));
      });
      control = h(
        "div",
        { class: "param-control bits-control" },
        h("div", { class: "bits" }, boxes),
        h("div", { class: "param-entry" }, this.input, h("span", { class: "unit" }, p.unit || "word")),
      );
    } else {
      if (p.slider) {
        this.slider = h("input", {
          class: "slider",
          type: "range",
          min: this.sliderMin,
          max: this.sliderMax,
          step: 1,
          testid: `param-${p.name}-slider`,
          "aria-label": `${p.label} slider`,
          title: `${p.label}: drag and release to write`,
        });
        const slider = this.slider;
        slider.addEventListener("input", () => this.setUi(Number(slider.value)));
        // A pointer release writes; arrow/page keys only move the value, which is written
        // when the keys rest (700 ms), on Enter or when the slider loses focus: never
        // one motor write per key step.
        let keyed = false;
        let timer = 0;
        const flush = (): void => {
          window.clearTimeout(timer);
          timer = 0;
          if (keyed) {
            keyed = false;
            void this.commit(Number(slider.value));
          }
        };
        slider.addEventListener("keydown", (event) => {
          if (event.key === "Enter") flush();
          else if (/^(Arrow|Page|Home|End)/.test(event.key)) keyed = true;
        });
        slider.addEventListener("keyup", () => {
          if (!keyed) return;
          window.clearTimeout(timer);
          timer = window.setTimeout(flush, 700);
        });
        slider.addEventListener("blur", flush);
        slider.addEventListener("change", () => {
          if (!keyed) void this.commit(Number(slider.value));
        });
      }
      control = h(
        "div",
        { class: "param-control" },
        this.slider ?? h("div", { class: "slider-none" }),
        h("div", { class: "param-entry" }, this.input, h("span", { class: "unit" }, p.unit)),
      );
    }
    this.el = h(
      "div",
      { class: `param-row kind-${p.kind}`, "data-param": p.name, title: "" },
      h("div", { class: "param-head" }, label, this.deviceBox),
      control,
      this.conversions,
      this.error,
      this.offerHost,
    );
    this.render();
  }

  private parse(text: string): number | null {
    if (text.trim() === "") return null;
    const value = Number(text);
    return Number.isInteger(value) ? value : null;
  }

  private setUi(value: number): void {
    const ui = store.uiValues(this.axisId);
    const device = store.deviceValues(this.axisId).get(this.p.name);
    if (value === device) ui.delete(this.p.name);
    else ui.set(this.p.name, value);
    this.render();
    store.emit("uiParams", this.axisId);
  }

  private wordFromChecks(): number {
    let word = this.current() ?? 0;
    for (const [bit, check] of this.checks) {
      if (check.checked) word |= 1 << bit;
      else word &= ~(1 << bit);
    }
    return word >>> 0;
  }

  /** The value the UI shows: the user's pending value, else the device's. */
  private current(): number | undefined {
    return store.uiValues(this.axisId).get(this.p.name) ?? store.deviceValues(this.axisId).get(this.p.name);
  }

  async commit(value: number): Promise<void> {
    const name = this.p.name;
    if (this.group) {
      // Staged: the group bar writes the whole group in its order.
      if (Number.isInteger(value)) this.setUi(value);
      else toggleClass(this.input, "invalid", true);
      return;
    }
    // What the user has for the parameters this write also changes on the device: the
    // values typed and not applied, else the device's (what the fields show).
    const ui = store.uiValues(this.axisId);
    const device = store.deviceValues(this.axisId);
    const overwritten = this.p.overwrites.filter((n) => n !== name);
    const typed = new Map(overwritten.filter((n) => ui.has(n)).map((n) => [n, ui.get(n) as number]));
    const before = new Map<string, number>();
    for (const n of overwritten) {
      const v = ui.get(n) ?? device.get(n);
      if (v !== undefined) before.set(n, v);
    }
    if (Number.isInteger(value)) store.uiValues(this.axisId).set(name, value);
    this.busy += 1;
    this.forceInput = true;
    this.render();
    try {
      // Always asked, even when out of range here: the server's 422 names the range.
      const readback = await api.writeParams(this.axisId, { [name]: value });
      setText(this.error, "");
      this.el.classList.remove("has-error");
      this.forceInput = true;
      store.setDeviceParams(this.axisId, readback, true);
      if (readback[name] !== undefined && readback[name] !== value) {
        setText(this.error, `The device kept ${readback[name]} (asked for ${value}).`);
        this.el.classList.add("has-note");
      } else this.el.classList.remove("has-note");
      if (overwritten.length) this.afterOverwrite(overwritten, before, typed);
    } catch (error) {
      const text = showError(`${this.p.label} (${name})`, error);
      setText(this.error, `${statusLabel(error)}: ${text}`);
      this.error.title = errorText(error);
      this.el.classList.add("has-error");
      this.el.classList.remove("has-note");
    } finally {
      this.busy -= 1;
      this.forceInput = true;
      this.render();
    }
  }

  /** After a write that also changed ``names`` on the device: keep the values the user
   * typed for them, and offer to write the user's values if the device's now differ. */
  private afterOverwrite(names: string[], before: Map<string, number>, typed: Map<string, number>): void {
    const ui = store.uiValues(this.axisId);
    const device = store.deviceValues(this.axisId);
    for (const [n, v] of typed) if (device.get(n) !== v) ui.set(n, v);
    store.emit("params", { axis: this.axisId, names });
    const changed = names.filter((n) => before.has(n) && device.get(n) !== before.get(n));
    if (!changed.length) {
      this.clearOffer();
      return;
    }
    const subject = subjectOf(names, this.byName);
    const now = joined(names, (n) => device.get(n));
    const mine = joined(names, (n) => before.get(n));
    const name = this.p.name;
    const text = h("span", { class: "overwrite-text" });
    const writeButton = h(
      "button",
      {
        class: "btn small warn",
        testid: `overwrite-write-${name}`,
        title: `Write ${names.map((n) => `${n}=${before.get(n) ?? "?"}`).join(" ")} to the device`,
        onclick: () => void this.writeOffer(),
      },
      `Write ${mine}`,
    );
    const keepButton = h(
      "button",
      { class: "btn small ghost", testid: `overwrite-keep-${name}`, title: `Keep ${now} as the device has it now`, onclick: () => this.keepOffer() },
      "Keep",
    );
    replace(
      text,
      `Writing ${this.p.label} also set ${subject} to `,
      h("b", { class: "mono" }, now),
      " on the device. Write your ",
      names.length > 1 ? "values " : "value ",
      h("b", { class: "mono" }, mine),
      " now?",
    );
    const el = h(
      "div",
      { class: "overwrite-offer", testid: `overwrite-offer-${name}`, role: "alert", "data-params": names.join(" ") },
      h("span", { class: "overwrite-icon", "aria-hidden": "true" }, "↺"),
      text,
      h("span", { class: "overwrite-actions" }, writeButton, keepButton),
    );
    this.offer = { names, before, el };
    replace(this.offerHost, el);
  }

  get hasOffer(): boolean {
    return this.offer !== null;
  }

  private clearOffer(): void {
    this.offer = null;
    replace(this.offerHost);
  }

  private async writeOffer(): Promise<void> {
    const offer = this.offer;
    if (!offer) return;
    const values: Record<string, number> = {};
    for (const n of offer.names) {
      const v = offer.before.get(n);
      if (v !== undefined) values[n] = v;
    }
    const button = offer.el.querySelector<HTMLElement>(".btn.warn");
    button?.classList.add("busy");
    try {
      const readback = await api.writeParams(this.axisId, values);
      store.setDeviceParams(this.axisId, readback, true);
      const kept = offer.names.filter((n) => readback[n] !== undefined && readback[n] !== values[n]);
      this.clearOffer();
      if (kept.length) {
        setText(this.error, `The device kept ${kept.map((n) => `${n}=${readback[n]}`).join(", ")} (asked for ${kept.map((n) => values[n]).join(", ")}).`);
        this.el.classList.add("has-note");
      }
    } catch (error) {
      const text = showError(`${offer.names.join(", ")}`, error);
      const note = offer.el.querySelector(".overwrite-error") ?? offer.el.appendChild(h("span", { class: "overwrite-error" }));
      setText(note, `${statusLabel(error)}: ${text}`);
    } finally {
      button?.classList.remove("busy");
    }
  }

  private keepOffer(): void {
    const offer = this.offer;
    if (!offer) return;
    const ui = store.uiValues(this.axisId);
    for (const n of offer.names) ui.delete(n);
    this.clearOffer();
    store.emit("params", { axis: this.axisId, names: offer.names });
    store.emit("uiParams", this.axisId);
  }

  /** "saved" only for a value known to be stored: the device keeps every write (no
   * save command), or the last save servotune saw stored this value. */
  private renderPersist(device: number | undefined): void {
    const tag = this.persistTag;
    if (!tag) return;
    const save = this.saveCommand;
    const stored = store.storedParams.get(this.axisId)?.get(this.p.name);
    let state: "saved" | "unsaved" | "storable";
    let title: string;
    if (!save) {
      state = "saved";
      title = "The device stores this setting with every write";
    } else if (stored === undefined || device === undefined) {
      state = "storable";
      title = `Kept over a power cycle only once stored with “${save.label}”; whether the value in force is stored is not known (no save seen since the server started)`;
    } else if (stored === device) {
      state = "saved";
      title = `Stored by “${save.label}”: the device loads ${stored} at power-on`;
    } else {
      state = "unsaved";
      title = `Not stored: the device holds ${device}, its memory ${stored} (the last “${save.label}”). Lost at power-off unless stored.`;
    }
    setText(tag, state);
    tag.dataset.state = state;
    tag.title = title;
  }

  render(): void {
    // An offer is settled once the device has the user's values again (written here,
    // in their own rows, or by a restore).
    if (this.offer) {
      const device = store.deviceValues(this.axisId);
      const offer = this.offer;
      if (offer.names.every((n) => !offer.before.has(n) || device.get(n) === offer.before.get(n))) this.clearOffer();
    }
    const p = this.p;
    const device = store.deviceValues(this.axisId).get(p.name);
    const pending = store.uiValues(this.axisId).get(p.name);
    const value = pending ?? device;
    const differs = pending !== undefined && pending !== device;
    toggleClass(this.el, "differs", differs);
    toggleClass(this.el, "busy", this.busy > 0);
    toggleClass(this.el, "unknown", device === undefined);
    this.el.dataset.differs = differs ? "1" : "0";
    setText(this.device, device === undefined ? "—" : p.kind === "bits" ? `${device} (0x${device.toString(16).toUpperCase()})` : String(device));
    this.renderPersist(device);
    this.deviceBox.title = differs
      ? `The device has ${device ?? "unknown"}; this field shows ${pending}. Press Enter (or release the slider) to write it.`
      : "Value read back from the device";
    const focused = document.activeElement === this.input;
    if ((!focused || this.forceInput) && value !== undefined) {
      if (this.input.value !== String(value)) this.input.value = String(value);
    } else if (!focused && value === undefined) this.input.value = "";
    this.forceInput = false;
    const ok = value === undefined || (value >= p.minimum && value <= p.maximum);
    toggleClass(this.input, "invalid", !ok);
    if (this.slider && value !== undefined) {
      const top = Math.max(this.sliderMax, Math.min(value, p.maximum));
      const bottom = Math.min(this.sliderMin, Math.max(value, p.minimum));
      if (Number(this.slider.max) !== top) this.slider.max = String(top);
      if (Number(this.slider.min) !== bottom) this.slider.min = String(bottom);
      toggleClass(this.slider, "extended", top > this.sliderMax);
      toggleClass(this.slider, "extended-low", bottom < this.sliderMin);
      if (document.activeElement !== this.slider || this.slider.value !== String(value)) {
        if (this.slider.value !== String(value)) this.slider.value = String(value);
      }
    }
    for (const [bit, check] of this.checks) {
      const on = value !== undefined && ((value >>> bit) & 1) === 1;
      if (check.checked !== on) check.checked = on;
      check.disabled = value === undefined;
      const devOn = device !== undefined && ((device >>> bit) & 1) === 1;
      toggleClass(check.parentElement as HTMLElement, "bit-differs", differs && devOn !== on);
    }
    if (value === undefined) setText(this.conversions, "");
    else if (p.conversions.length) {
      const head = `${value}${p.unit ? ` ${p.unit}` : ""}`;
      setText(this.conversions, `${head} = ${p.conversions.map((c) => formatConverted(value, c)).join(" = ")}`);
    } else setText(this.conversions, "");
  }
}

export class TuningPanel {
  readonly el: HTMLElement;
  private readonly rows = new Map<string, ParamRow>();
  private readonly readButton: HTMLButtonElement;
  private readonly status: HTMLElement;

  constructor(
    private readonly axisId: string,
    descriptor: DeviceDescriptor,
    signal: AbortSignal,
  ) {
    this.status = h("div", { class: "cmd-status tuning-status", testid: "tuning-status", "aria-live": "polite" });
    const runner = makeRunner(axisId, this.status);
    this.readButton = h(
      "button",
      { class: "btn", testid: "params-read", title: "Read every parameter from the device now", onclick: () => void this.read() },
      "Read from device",
    );
    const persist = descriptor.commands
      .filter((c: CommandDescriptor) => c.group === "persist")
      .map((c) => commandWidget(runner, c, c.confirm ? "warn" : ""));
    const filter = h("input", { class: "input filter", type: "search", placeholder: "Filter…", testid: "params-filter", "aria-label": "Filter parameters" });
    filter.addEventListener("input", () => this.filter(filter.value));
    const header = h(
      "div",
      { class: "tuning-header" },
      h("div", { class: "tuning-actions" }, h("span", { class: "pane-title" }, "Tuning"), this.readButton, persist, h("span", { class: "tb-spacer" }), filter),
      this.status,
    );
    const body = h("div", { class: "tuning-body" });
    const byName = new Map(descriptor.parameters.map((p) => [p.name, p]));
    if (descriptor.parameters.length) body.appendChild(new ParamSetsPanel(axisId, descriptor, signal).el);
    const groups = new Map<string, ParameterDescriptor[]>();
    for (const p of descriptor.parameters) {
      const list = groups.get(p.group) ?? [];
      list.push(p);
      groups.set(p.group, list);
    }
    const writeGroups = (descriptor.write_groups ?? []).filter((g) => g.length > 1 && g.every((n) => byName.has(n)));
    const groupOf = new Map<string, string[]>();
    for (const g of writeGroups) for (const n of g) groupOf.set(n, g);
    const barsPlaced = new Set<string[]>();
    for (const [group, params] of groups) {
      const section = h("section", { class: "param-group", "data-group": group }, h("div", { class: "param-group-title" }, group));
      const wg = params.map((p) => groupOf.get(p.name)).find((g) => g !== undefined);
      if (wg && !barsPlaced.has(wg)) {
        barsPlaced.add(wg);
        body.appendChild(new WriteGroupBar(axisId, wg, byName, writeGroups.indexOf(wg), signal).el);
      }
      for (const p of params) {
        const save = descriptor.commands.find((c) => c.stores_parameters != null) ?? null;
        const row = new ParamRow(axisId, p, byName, groupOf.get(p.name) ?? null, save);
        this.rows.set(p.name, row);
        section.appendChild(row.el);
      }
      body.appendChild(section);
    }
    if (!descriptor.parameters.length) replace(body, h("div", { class: "empty" }, "This device has no parameters."));
    this.el = h("div", { class: "tuning" }, header, body);
    store.on(
      "params",
      ({ axis, names }) => {
        if (axis !== this.axisId) return;
        for (const name of names) this.rows.get(name)?.render();
        for (const [name, row] of this.rows) if (row.hasOffer && !names.includes(name)) row.render();
      },
      signal,
    );
    if (store.deviceValues(axisId).size === 0 && descriptor.parameters.length) void this.read(true);
  }

  private filter(text: string): void {
    const needle = text.trim().toLowerCase();
    for (const [name, row] of this.rows) {
      const hay = `${name} ${row.p.label} ${row.p.description} ${row.p.group}`.toLowerCase();
      row.el.hidden = needle !== "" && !hay.includes(needle);
    }
    for (const section of this.el.querySelectorAll<HTMLElement>(".param-group")) {
      section.hidden = [...section.querySelectorAll<HTMLElement>(".param-row")].every((r) => r.hidden);
    }
  }

  /** Reads every parameter from the device. The "Read" button (``quiet`` false) makes the
   * fields show what the device has, dropping unapplied edits; the quiet read when the
   * panel opens only fills in the device values, so an edit made while it was under way
   * (the websocket may deliver the values first) is kept. */
  async read(quiet = false): Promise<void> {
    this.readButton.classList.add("busy");
    this.status.dataset.kind = "pending";
    setText(this.status, "Reading parameters …");
    try {
      const values = await api.readParams(this.axisId);
      store.setDeviceParams(this.axisId, values, !quiet);
      this.status.dataset.kind = "ok";
      setText(this.status, `✓ Read ${Object.keys(values).length} parameters from the device`);
    } catch (error) {
      const text = quiet ? errorText(error) : showError("Read from device", error);
      this.status.dataset.kind = "error";
      setText(this.status, `✗ Read from device: ${statusLabel(error)} — ${text}`);
    } finally {
      this.readButton.classList.remove("busy");
    }
  }
}

/** Parameters the descriptor says are written together (``write_groups``, e.g. Z1100
 * KABH then KABD, because SetKABH overwrites KABD on the chip). Their rows stage edits;
 * this bar writes the whole group, sub-group by sub-group in the descriptor's order,
 * with the user's values for every member (edited or as read), so nothing the user has
 * is silently replaced. If a later part fails, it offers one restore of that part. */
class WriteGroupBar {
  readonly el: HTMLElement;
  private readonly text: HTMLElement;
  private readonly writeButton: HTMLButtonElement;
  private readonly discardButton: HTMLButtonElement;
  private readonly status: HTMLElement;
  private readonly offerHost: HTMLElement;
  /** Consecutive members of one parameter group (e.g. the three KABH gains). */
  private readonly parts: { group: string; names: string[] }[] = [];

  constructor(
    private readonly axisId: string,
    private readonly names: string[],
    private readonly byName: Map<string, ParameterDescriptor>,
    index: number,
    signal: AbortSignal,
  ) {
    for (const n of names) {
      const group = byName.get(n)?.group ?? n;
      const last = this.parts[this.parts.length - 1];
      if (last && last.group === group) last.names.push(n);
      else this.parts.push({ group, names: [n] });
    }
    const order = this.parts.map((p) => p.group).join(", then ");
    this.text = h("span", { class: "wg-pending", testid: `write-group-${index}-pending` });
    this.writeButton = h("button", { class: "btn warn", testid: `write-group-${index}`, title: `Writes ${order}`, onclick: () => void this.write() }, "Write both sets");
    this.discardButton = h("button", { class: "btn ghost small", testid: `write-group-${index}-discard`, onclick: () => this.discard() }, "Discard edits");
    this.status = h("div", { class: "cmd-status", testid: `write-group-${index}-status`, role: "status" });
    this.offerHost = h("div", { class: "overwrite-slot" });
    this.el = h(
      "div",
      { class: "write-group", testid: `write-group-bar-${index}`, role: "group", "aria-label": "Parameters written together" },
      h(
        "div",
        { class: "wg-warn" },
        h("span", { class: "overwrite-icon", "aria-hidden": "true" }, "⚠"),
        h("span", null, `Written together: the device overwrites the later set when the first is written, so servotune writes ${order} with your values for both. Edit either set, then write.`),
      ),
      h("div", { class: "wg-actions" }, this.writeButton, this.discardButton, this.text),
      this.status,
      this.offerHost,
    );
    this.sync();
    store.on("uiParams", (id) => id === axisId && this.sync(), signal);
    store.on("params", ({ axis }) => axis === axisId && this.sync(), signal);
  }

  private value(n: string): number | undefined {
    return store.uiValues(this.axisId).get(n) ?? store.deviceValues(this.axisId).get(n);
  }

  private pending(): string[] {
    const ui = store.uiValues(this.axisId);
    const device = store.deviceValues(this.axisId);
    return this.names.filter((n) => ui.has(n) && ui.get(n) !== device.get(n));
  }

  private sync(): void {
    const pending = this.pending();
    setText(this.text, pending.length ? `${pending.length} edited: ${pending.map((n) => `${this.byName.get(n)?.label ?? n} = ${this.value(n)}`).join(", ")}` : "no edits");
    this.writeButton.disabled = pending.length === 0;
    this.discardButton.disabled = pending.length === 0;
  }

  private discard(): void {
    const ui = store.uiValues(this.axisId);
    for (const n of this.names) ui.delete(n);
    store.emit("params", { axis: this.axisId, names: this.names });
    store.emit("uiParams", this.axisId);
  }

  async write(): Promise<void> {
    const values = new Map<string, number>();
    for (const n of this.names) {
      const v = this.value(n);
      if (v === undefined) {
        setStatus(this.status, "error", `✗ ${n} is not known yet: read from the device first`);
        return;
      }
      values.set(n, v);
    }
    replace(this.offerHost);
    this.writeButton.classList.add("busy");
    let done = 0;
    try {
      for (const part of this.parts) {
        setStatus(this.status, "pending", `Writing ${part.group} …`);
        const body = Object.fromEntries(part.names.map((n) => [n, values.get(n) as number]));
        const readback = await api.writeParams(this.axisId, body);
        store.setDeviceParams(this.axisId, readback, true);
        done += 1;
      }
      setStatus(this.status, "ok", `✓ Wrote ${this.parts.map((p) => `${p.group} ${joined(p.names, (n) => store.deviceValues(this.axisId).get(n))}`).join(", then ")}`);
    } catch (error) {
      const text = showError("Write group", error);
      const failed = this.parts[done];
      setStatus(this.status, "error", `✗ ${failed?.group ?? "write"}: ${statusLabel(error)} — ${text}`);
      // One restore at most: the part that did not get the user's values.
      if (failed && done > 0) {
        const mine = joined(failed.names, (n) => values.get(n));
        const restore = h("button", { class: "btn small warn", testid: "write-group-restore" }, `Write ${failed.group} ${mine} again`);
        restore.addEventListener("click", () => {
          for (const n of failed.names) store.uiValues(this.axisId).set(n, values.get(n) as number);
          void this.write();
        });
        replace(this.offerHost, h("div", { class: "overwrite-offer", role: "alert" }, h("span", { class: "overwrite-icon" }, "↺"), h("span", { class: "overwrite-text" }, `${failed.group} on the device may now hold what ${this.parts[0]?.group} wrote.`), restore));
      }
    } finally {
      this.writeButton.classList.remove("busy");
      this.sync();
    }
  }
}

function setStatus(el: HTMLElement, kind: "ok" | "error" | "pending", text: string): void {
  el.dataset.kind = kind;
  setText(el, text);
  el.title = text;
}
