// Parameter sets of one axis (server/servotune/api/param_set_routes.py): save what the
// device has now under a name, compare a set three ways (device read now | values typed
// in the tuning fields and not applied | the set), restore it to the device, and, as a
// separate explicit step, persist it with the device's own save command.
import { ApiError, api, type ParamSet } from "../api";
import { h, replace, setText, toggleClass } from "../dom";
import { clock } from "../format";
import { store } from "../store";
import type { CommandDescriptor, DeviceDescriptor, ParameterDescriptor } from "../schema.gen";
import { confirmDialog, errorText, showError, statusLabel } from "./feedback";

/** The server's rule (SaveSetRequest.name): letters, digits, _ and space . , + ( ) # - */
const NAME_RE = /^[\p{L}\p{N}_ .,+()#-]+$/u;
const NAME_MAX = 60;
const NAME_RULE = "letters, digits, space and . , + ( ) # - _ (1 to 60 characters)";

// Kept across axis switches and reloads.
const selectedSet = new Map<string, string>(); // axis -> set name
const OPEN_KEY = "servotune.paramsets.open";
const ONLY_KEY = "servotune.paramsets.only-differing";

function stored(key: string, fallback: boolean): boolean {
  const v = localStorage.getItem(key);
  return v === null ? fallback : v === "1";
}

function remember(key: string, on: boolean): void {
  try {
    localStorage.setItem(key, on ? "1" : "0");
  } catch {
    /* private mode */
  }
}

/** Client-side check of a set name; null when fine (the server checks again). */
export function nameProblem(name: string): string | null {
  if (!name) return "Enter a name for the set.";
  if (name.length > NAME_MAX) return `The name is ${name.length} characters long: at most ${NAME_MAX}.`;
  if (!NAME_RE.test(name)) {
    const bad = [...new Set([...name].filter((c) => !NAME_RE.test(c)))].join(" ");
    return `Not allowed in a name: ${bad} — use ${NAME_RULE}.`;
  }
  if (/^\.+$/.test(name)) return "A name of dots only cannot be addressed: add a letter or digit.";
  return null;
}

/** The device's own "store permanently" command: group persist, not the re-apply. */
export function persistCommand(d: DeviceDescriptor): CommandDescriptor | null {
  return d.commands.find((c) => c.group === "persist" && c.name !== "restore_parameters") ?? null;
}

function valueText(v: number | undefined): string {
  return v === undefined ? "—" : String(v);
}

export class ParamSetsPanel {
  readonly el: HTMLElement;
  private sets: ParamSet[] = [];
  private open: boolean;
  private onlyDiffering: boolean;
  private readonly params: Map<string, ParameterDescriptor>;
  private readonly persist: CommandDescriptor | null;
  private readonly toggle: HTMLButtonElement;
  private readonly count: HTMLElement;
  private readonly body: HTMLElement;
  private readonly nameInput: HTMLInputElement;
  private readonly noteInput: HTMLInputElement;
  private readonly saveButton: HTMLButtonElement;
  private readonly saveError: HTMLElement;
  private readonly list: HTMLElement;
  private readonly detail: HTMLElement;
  private readonly diffHost: HTMLElement;
  private readonly summary: HTMLElement;
  private readonly onlyBox: HTMLInputElement;
  private readonly compareButton: HTMLButtonElement;
  private readonly restoreButton: HTMLButtonElement;
  private readonly persistButton: HTMLButtonElement | null;
  private readonly status: HTMLElement;
  private comparedAt: number | null = null;
  private compareToken = 0;

  constructor(
    private readonly axisId: string,
    private readonly descriptor: DeviceDescriptor,
    signal: AbortSignal,
  ) {
    this.params = new Map(descriptor.parameters.map((p) => [p.name, p]));
    this.persist = persistCommand(descriptor);
    this.open = stored(OPEN_KEY, true);
    this.onlyDiffering = stored(ONLY_KEY, true);

    this.count = h("span", { class: "ps-count" });
    this.toggle = h(
      "button",
      { class: "ps-toggle", testid: "ps-toggle", title: "Named sets of parameter values: save, compare, restore", onclick: () => this.setOpen(!this.open) },
      h("span", { class: "ps-caret", "aria-hidden": "true" }),
      h("span", { class: "pane-title" }, "Parameter sets"),
      this.count,
    );

    this.nameInput = h("input", {
      class: "input ps-name",
      type: "text",
      maxlength: NAME_MAX,
      placeholder: "name, e.g. kp 80 #2",
      testid: "ps-name",
      "aria-label": "Name of the new set",
      title: `Name of the set: ${NAME_RULE}. Saving under an existing name replaces that set.`,
    });
    this.noteInput = h("input", {
      class: "input ps-note",
      type: "text",
      maxlength: 200,
      placeholder: "note (optional)",
      testid: "ps-note",
      "aria-label": "Note",
    });
    this.saveButton = h(
      "button",
      {
        class: "btn small",
        testid: "ps-save",
        title: "Read every parameter from the device now and store the values under this name (not the values typed in the fields and not applied)",
        onclick: () => void this.save(),
      },
      "Save device values",
    );
    for (const input of [this.nameInput, this.noteInput]) {
      input.addEventListener("keydown", (event) => {
        if (event.key === "Enter") {
          event.preventDefault();
          void this.save();
        }
      });
    }
    this.nameInput.addEventListener("input", () => {
      this.nameInput.classList.remove("server-invalid");
      const problem = this.nameInput.value ? nameProblem(this.nameInput.value) : null;
      toggleClass(this.nameInput, "invalid", problem !== null);
      this.showSaveError(problem);
    });
    this.saveError = h("div", { class: "ps-error", testid: "ps-error", role: "alert", hidden: true });

    this.list = h("div", { class: "ps-list", testid: "ps-list", role: "listbox", "aria-label": "Parameter sets" });

    this.onlyBox = h("input", { type: "checkbox", checked: this.onlyDiffering, testid: "ps-only-differing" });
    this.onlyBox.addEventListener("change", () => {
      this.onlyDiffering = this.onlyBox.checked;
      remember(ONLY_KEY, this.onlyDiffering);
      this.renderDiff();
    });
    this.summary = h("span", { class: "ps-summary", testid: "ps-summary" });
    this.compareButton = h(
      "button",
      { class: "btn small ghost", testid: "ps-compare", title: "Read the device again and compare", onclick: () => void this.compare() },
      "↻ Read device",
    );
    this.diffHost = h("div", { class: "ps-diff-scroll" });
    this.restoreButton = h(
      "button",
      {
        class: "btn small",
        testid: "ps-restore",
        title: "Write the set to the device (validated, read back). Does not persist it in the device.",
        onclick: () => void this.restore(),
      },
      "Restore set to device…",
    );
    this.persistButton = this.persist
      ? h(
          "button",
          {
            class: "btn small warn",
            testid: "ps-persist",
            title: `${this.persist.label}: ${this.persist.description}`,
            onclick: () => void this.runPersist(),
          },
          "Persist in device…",
        )
      : null;
    this.status = h("div", { class: "ps-status", testid: "ps-status", "aria-live": "polite" });
    this.detail = h(
      "div",
      { class: "ps-detail" },
      h(
        "div",
        { class: "ps-diff-bar" },
        h("label", { class: "ps-only", title: "Show only the parameters whose values are not the same in the three columns" }, this.onlyBox, "only differing"),
        this.summary,
        h("span", { class: "tb-spacer" }),
        this.compareButton,
        h("button", { class: "icon-del", testid: "ps-close", title: "Close the comparison", onclick: () => this.select(null) }, "✕"),
      ),
      this.diffHost,
    );
    this.body = h(
      "div",
      { class: "ps-body" },
      h("div", { class: "ps-save-row" }, this.nameInput, this.noteInput, this.saveButton),
      this.saveError,
      this.list,
      this.detail,
      h(
        "div",
        { class: "ps-actions" },
        this.restoreButton,
        this.persistButton,
        this.persist ? null : h("span", { class: "ps-hint", title: "The descriptor of this device has no save command" }, "no save-to-device command on this device"),
      ),
      this.status,
    );
    this.el = h("section", { class: "param-sets", "data-open": "1" }, this.toggle, this.body);
    this.setOpen(this.open);

    const rerender = (): void => {
      if (this.selected()) this.renderDiff();
    };
    store.on("params", ({ axis }) => axis === axisId && rerender(), signal);
    store.on("uiParams", (axis) => axis === axisId && rerender(), signal);
    void this.load();
  }

  private setOpen(open: boolean): void {
    this.open = open;
    remember(OPEN_KEY, open);
    this.body.hidden = !open;
    this.el.dataset.open = open ? "1" : "0";
    this.toggle.setAttribute("aria-expanded", open ? "true" : "false");
  }

  private selected(): ParamSet | null {
    const name = selectedSet.get(this.axisId);
    return this.sets.find((s) => s.name === name) ?? null;
  }

  async load(): Promise<void> {
    try {
      this.sets = await api.paramSets(this.axisId);
    } catch (error) {
      replace(this.list, h("div", { class: "ps-empty error" }, `Cannot list the sets: ${statusLabel(error)} — ${errorText(error)}`));
      return;
    }
    this.renderList();
    if (this.selected()) void this.compare();
    else this.renderDiff();
  }

  // --- save ---------------------------------------------------------------------------

  private showSaveError(text: string | null): void {
    this.saveError.hidden = text === null;
    setText(this.saveError, text ?? "");
  }

  private async save(): Promise<void> {
    const name = this.nameInput.value.trim();
    const problem = nameProblem(name);
    if (problem) {
      toggleClass(this.nameInput, "invalid", true);
      this.showSaveError(problem);
      this.nameInput.focus();
      return;
    }
    if (this.sets.some((s) => s.name === name)) {
      const ok = await confirmDialog(`Replace set “${name}”`, `A set named “${name}” exists. Replace its values with what the device has now?`, "Replace");
      if (!ok) return;
    }
    this.showSaveError(null);
    this.saveButton.classList.add("busy");
    this.setStatus("pending", `Reading the device and saving “${name}” …`);
    try {
      const saved = await api.saveParamSet(this.axisId, name, this.noteInput.value.trim());
      store.setDeviceParams(this.axisId, saved.params, false);
      this.nameInput.value = "";
      this.noteInput.value = "";
      selectedSet.set(this.axisId, saved.name);
      this.setStatus("ok", `✓ Saved ${Object.keys(saved.params).length} device values as “${saved.name}”`);
      await this.load();
    } catch (error) {
      const text = `${statusLabel(error)}: ${errorText(error)}`;
      if (error instanceof ApiError && error.status === 422) {
        this.nameInput.classList.add("server-invalid");
        this.showSaveError(error.field === "name" ? `${text} — use ${NAME_RULE}` : text);
        this.setStatus("", "");
      } else this.setStatus("error", `✗ Save “${name}”: ${text}`);
    } finally {
      this.saveButton.classList.remove("busy");
    }
  }

  // --- list ---------------------------------------------------------------------------

  private renderList(): void {
    setText(this.count, this.sets.length ? String(this.sets.length) : "");
    const current = this.selected();
    if (!this.sets.length) {
      replace(this.list, h("div", { class: "ps-empty" }, "No sets yet: name the device's current values above and save them."));
      return;
    }
    // Newest first.
    const rows = [...this.sets].reverse().map((set) => {
      const when = clock(set.created_s);
      const other = set.device !== this.descriptor.device;
      const on = current?.name === set.name;
      const select = h(
        "button",
        {
          class: `ps-item${on ? " on" : ""}${other ? " other" : ""}`,
          testid: `ps-select-${set.name}`,
          role: "option",
          "aria-selected": on ? "true" : "false",
          title: `${set.name}\nsaved ${when.full} from a ${set.device}${set.note ? `\nnote: ${set.note}` : ""}\n${Object.entries(set.params)
            .map(([k, v]) => `${k}=${v}`)
            .join(" ")}`,
          onclick: () => this.select(set.name),
        },
        h("span", { class: "ps-radio", "aria-hidden": "true" }),
        h("span", { class: "ps-item-name" }, set.name),
        other ? h("span", { class: "tag ps-other" }, set.device) : null,
        set.note ? h("span", { class: "ps-item-note" }, set.note) : h("span", { class: "ps-item-note" }),
        h("span", { class: "ps-item-time mono" }, when.time),
      );
      const del = h(
        "button",
        { class: "icon-del", testid: `ps-delete-${set.name}`, title: `Delete the set “${set.name}”`, onclick: () => void this.remove(set) },
        "✕",
      );
      return h("div", { class: "ps-row", "data-set": set.name }, select, del);
    });
    replace(this.list, rows);
  }

  private select(name: string | null): void {
    if (name === null) selectedSet.delete(this.axisId);
    else selectedSet.set(this.axisId, name);
    this.comparedAt = null;
    this.renderList();
    this.renderDiff();
    if (name !== null) void this.compare();
  }

  private async remove(set: ParamSet): Promise<void> {
    const ok = await confirmDialog(`Delete set “${set.name}”`, `Delete the parameter set “${set.name}” (saved ${clock(set.created_s).full})? The device is not changed.`, "Delete");
    if (!ok) return;
    try {
      await api.deleteParamSet(this.axisId, set.name);
      if (selectedSet.get(this.axisId) === set.name) selectedSet.delete(this.axisId);
      this.setStatus("ok", `✓ Deleted “${set.name}”`);
    } catch (error) {
      this.setStatus("error", `✗ Delete “${set.name}”: ${statusLabel(error)} — ${errorText(error)}`);
    }
    await this.load();
  }

  // --- compare ------------------------------------------------------------------------

  /** Read the device now (the server's compare); the table renders from the store. */
  private async compare(): Promise<void> {
    const set = this.selected();
    if (!set) return;
    const token = ++this.compareToken;
    this.compareButton.classList.add("busy");
    try {
      const cmp = await api.compareParamSet(this.axisId, set.name);
      if (token !== this.compareToken) return;
      store.setDeviceParams(this.axisId, cmp.device, false);
      set.params = cmp.saved;
      this.comparedAt = Date.now();
      this.renderDiff();
    } catch (error) {
      if (token !== this.compareToken) return;
      this.setStatus("error", `✗ Compare with “${set.name}”: ${statusLabel(error)} — ${errorText(error)}`);
      this.renderDiff();
    } finally {
      if (token === this.compareToken) this.compareButton.classList.remove("busy");
    }
  }

  private renderDiff(): void {
    const set = this.selected();
    this.detail.hidden = set === null;
    this.restoreButton.disabled = set === null || set.device !== this.descriptor.device;
    this.restoreButton.title =
      set === null
        ? "Select a set first"
        : set.device !== this.descriptor.device
          ? `“${set.name}” was saved from a ${set.device}: it cannot be restored to this ${this.descriptor.device}`
          : `Write the ${Object.keys(set.params).length} values of “${set.name}” to the device (validated, read back). Does not persist them in the device.`;
    if (!set) {
      replace(this.diffHost);
      return;
    }
    const device = store.deviceValues(this.axisId);
    const ui = store.uiValues(this.axisId);
    const names = [...this.descriptor.parameters.map((p) => p.name)];
    for (const name of Object.keys(set.params)) if (!this.params.has(name)) names.push(name);
    let differing = 0;
    let pendingCount = 0;
    const rows: HTMLElement[] = [];
    for (const name of names) {
      const p = this.params.get(name);
      const dev = device.get(name);
      const saved = set.params[name];
      const pending = ui.get(name);
      const uiPending = pending !== undefined && pending !== dev;
      const devDiffers = dev !== undefined && saved !== undefined && dev !== saved;
      const missing = saved === undefined || dev === undefined;
      const rowDiffers = devDiffers || uiPending || (saved === undefined) !== (dev === undefined);
      if (rowDiffers) differing += 1;
      if (uiPending) pendingCount += 1;
      if (this.onlyDiffering && !rowDiffers) continue;
      rows.push(
        h(
          "tr",
          { class: `${rowDiffers ? "differs" : ""}${missing ? " missing" : ""}`.trim() || undefined, "data-param": name },
          h(
            "td",
            { class: "d-name", title: p ? `${p.label} (${name})${p.unit ? ` [${p.unit}]` : ""}\n${p.description}` : `${name}: not a parameter of this device` },
            p?.label ?? name,
            p && p.label.toLowerCase() !== name ? h("span", { class: "d-key mono" }, ` ${name}`) : null,
            p?.unit ? h("span", { class: "d-unit" }, ` ${p.unit}`) : null,
          ),
          h(
            "td",
            { class: `d-val num${devDiffers ? " dev-differs" : ""}`, "data-col": "device", title: dev === undefined ? "not read yet" : `on the device: ${dev}` },
            valueText(dev),
          ),
          h(
            "td",
            {
              class: `d-val num ui${uiPending ? " pending" : " same"}${uiPending && pending === saved ? " matches" : ""}`,
              "data-col": "ui",
              title: uiPending
                ? `typed in the field, not written to the device${pending === saved ? " (as in the set)" : ""}`
                : "the field shows the device's value",
            },
            uiPending ? String(pending) : "·",
          ),
          h(
            "td",
            { class: `d-val num saved${devDiffers ? " differs" : ""}`, "data-col": "saved", title: saved === undefined ? "not in this set" : `in “${set.name}”: ${saved}` },
            valueText(saved),
          ),
        ),
      );
    }
    if (!rows.length) {
      rows.push(h("tr", { class: "ps-same" }, h("td", { colspan: 4 }, `The device has every value of “${set.name}” and no field holds an unapplied value.`)));
    }
    const read = this.comparedAt ? `read ${clock(this.comparedAt / 1000).time}` : "last known";
    setText(this.summary, `${differing}/${names.length} differ${pendingCount ? ` · ${pendingCount} unapplied` : ""} · ${read}`);
    this.summary.title =
      `${differing} of ${names.length} parameters differ between the device, the fields and “${set.name}” (saved ${clock(set.created_s).full}${set.note ? `, ${set.note}` : ""})` +
      `${pendingCount ? `; ${pendingCount} typed in the fields and not applied` : ""}; device values ${this.comparedAt ? `read at ${clock(this.comparedAt / 1000).time}` : "as last reported"}`;
    const table = h(
      "table",
      { class: "diff-table ps-diff", testid: "ps-diff", "data-set": set.name, "data-differing": String(differing) },
      h(
        "thead",
        null,
        h(
          "tr",
          null,
          h("th", { class: "d-name" }, "parameter"),
          h("th", { title: "Read from the device (now, or as last reported)" }, "device"),
          h("th", { title: "Values typed in the tuning fields and not written to the device" }, "UI"),
          h("th", { class: "ps-saved-head", title: `The set “${set.name}”` }, "saved"),
        ),
      ),
      h("tbody", null, rows),
    );
    const scroller = this.diffHost;
    const scroll = scroller.scrollTop;
    replace(this.diffHost, table);
    scroller.scrollTop = scroll;
  }

  // --- restore and persist ------------------------------------------------------------

  private async restore(): Promise<void> {
    const set = this.selected();
    if (!set) return;
    const ui = store.uiValues(this.axisId);
    const device = store.deviceValues(this.axisId);
    const dropped = Object.keys(set.params).filter((n) => ui.has(n) && ui.get(n) !== device.get(n));
    const persistText = this.persist
      ? ` To keep them after a reset or power cycle, use “Persist in device” (${this.persist.label}) afterwards.`
      : "";
    const ok = await confirmDialog(
      `Restore “${set.name}”`,
      `Write the ${Object.keys(set.params).length} values of “${set.name}” to the device now (each validated and read back)? ` +
        `This does NOT persist them in the device: it keeps them only until it is reset or powered off.${persistText}` +
        (dropped.length ? ` Your unapplied values of ${dropped.join(", ")} in the tuning fields are replaced.` : ""),
      "Restore",
    );
    if (!ok) return;
    this.restoreButton.classList.add("busy");
    this.setStatus("pending", `Restoring “${set.name}” …`);
    try {
      const readback = await api.restoreParamSet(this.axisId, set.name);
      store.setDeviceParams(this.axisId, readback, true);
      store.emit("uiParams", this.axisId);
      const kept = Object.entries(set.params).filter(([k, v]) => readback[k] !== undefined && readback[k] !== v);
      if (kept.length) {
        this.setStatus("warn", `Restored “${set.name}”, but the device kept ${kept.map(([k, v]) => `${k}=${readback[k]} (set ${v})`).join(", ")} — not persisted`);
      } else this.setStatus("ok", `✓ Restored ${Object.keys(readback).length} values of “${set.name}” to the device — not persisted in it`);
      this.comparedAt = Date.now();
      this.renderDiff();
    } catch (error) {
      const text = showError(`Restore “${set.name}”`, error);
      this.setStatus("error", `✗ Restore “${set.name}”: ${statusLabel(error)} — ${text}`);
      void this.compare();
    } finally {
      this.restoreButton.classList.remove("busy");
    }
  }

  private async runPersist(): Promise<void> {
    const cmd = this.persist;
    const button = this.persistButton;
    if (!cmd || !button) return;
    const pending = [...store.uiValues(this.axisId).entries()].filter(([k, v]) => store.deviceValues(this.axisId).get(k) !== v).map(([k]) => k);
    const ok = await confirmDialog(
      cmd.label,
      `${cmd.confirm ?? `Run “${cmd.label}” on the device?`}\n\n${cmd.description}` +
        (pending.length ? `\n\nNot included: the unapplied values of ${pending.join(", ")} (the device stores what it has).` : ""),
      cmd.label,
    );
    if (!ok) {
      this.setStatus("", `${cmd.label}: cancelled`);
      return;
    }
    button.classList.add("busy");
    this.setStatus("pending", `${cmd.label} …`);
    try {
      const result = await api.command(this.axisId, cmd.name, {});
      const sent = result.sent.length ? ` → ${result.sent.join(" ")}` : "";
      this.setStatus("ok", `✓ ${cmd.label}${sent}${result.message && result.message !== "ok" ? ` (${result.message})` : ""}`);
    } catch (error) {
      const text = showError(cmd.label, error);
      this.setStatus("error", `✗ ${cmd.label}: ${statusLabel(error)} — ${text}`);
    } finally {
      button.classList.remove("busy");
    }
  }

  private setStatus(kind: string, text: string): void {
    this.status.dataset.kind = kind;
    setText(this.status, text);
    this.status.hidden = text === "";
  }
}
