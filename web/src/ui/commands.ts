// The control strip: descriptor commands grouped by ``group`` (stop, mode, motion,
// calibration, other; persist commands live in the tuning panel's header).
import { ApiError, api } from "../api";
import type { AxisBuffer } from "../buffer";
import { h, setText, toggleClass } from "../dom";
import { store } from "../store";
import type { ArgumentDescriptor, CommandDescriptor, DeviceDescriptor } from "../schema.gen";
import { confirmDialog, errorText, showError, statusLabel } from "./feedback";

/** Argument values the user typed, kept across axis switches: "axis/command/arg". */
const remembered = new Map<string, string>();

export const GROUP_TITLES: Record<CommandDescriptor["group"], string> = {
  stop: "Axis",
  mode: "Mode",
  motion: "Motion",
  calibration: "Calibration",
  persist: "Settings",
  other: "Other",
};

function rangeText(arg: ArgumentDescriptor): string {
  return `${arg.minimum}..${arg.maximum}${arg.unit ? ` ${arg.unit}` : ""}`;
}

/** Client-side check; the server stays authoritative and is always asked. */
function checkArg(arg: ArgumentDescriptor, text: string): string | null {
  if (text.trim() === "") return `${arg.label}: enter a value (${rangeText(arg)})`;
  const value = Number(text);
  if (!Number.isInteger(value)) return `${arg.label} must be an integer in ${rangeText(arg)}`;
  if (value < arg.minimum || value > arg.maximum) return `${arg.label} = ${value} is out of range: allowed ${rangeText(arg)}`;
  return null;
}

export interface CommandRunner {
  axisId: string;
  status: HTMLElement;
  /** Inputs by argument name of the command that is running, to mark the 422 field. */
  run(cmd: CommandDescriptor, args: Record<string, number>, button: HTMLElement, inputs?: Map<string, HTMLElement>): Promise<boolean>;
}

export function makeRunner(axisId: string, status: HTMLElement): CommandRunner {
  return {
    axisId,
    status,
    async run(cmd, args, button, inputs) {
      if (cmd.confirm) {
        const ok = await confirmDialog(cmd.label, cmd.confirm, cmd.label);
        if (!ok) {
          setStatus(status, "info", `${cmd.label}: cancelled`);
          return false;
        }
      }
      button.classList.add("busy");
      for (const input of inputs?.values() ?? []) input.classList.remove("server-invalid");
      setStatus(status, "pending", `${cmd.label} …`);
      try {
        const result = await api.command(axisId, cmd.name, args);
        const sent = result.sent.length ? ` → ${result.sent.join(" ")}` : "";
        if (result.outcome_pending) {
          // A move to a target: sent is not done. ✓ only once it arrived (move_outcome).
          setStatus(status, "pending", `… ${cmd.label}${sent}: ${result.message}`);
          watchOutcome(axisId, cmd, status);
          return true;
        }
        setStatus(status, "ok", `✓ ${cmd.label}${sent}${result.message && result.message !== "ok" ? ` (${result.message})` : ""}`);
        return true;
      } catch (error) {
        const text = showError(cmd.label, error);
        setStatus(status, "error", `✗ ${cmd.label}: ${statusLabel(error)} — ${text}`);
        if (error instanceof ApiError && error.field && inputs?.has(error.field)) {
          const input = inputs.get(error.field) as HTMLElement;
          input.classList.add("server-invalid");
          input.title = errorText(error);
        }
        return false;
      } finally {
        button.classList.remove("busy");
      }
    },
  };
}

/** The end of the move ``cmd`` started: ✓ arrived, ⚠ stopped short (a limit switch,
 * a fault, a STOP) with where the axis stopped. A later command's status wins. */
function watchOutcome(axisId: string, cmd: CommandDescriptor, status: HTMLElement): void {
  const stamp = String(Date.now()) + Math.random();
  status.dataset.watch = stamp;
  const done = new AbortController();
  store.on(
    "moveOutcome",
    (m) => {
      if (m.axis !== axisId || m.command !== cmd.name) return;
      done.abort();
      if (status.dataset.watch !== stamp) return;
      delete status.dataset.watch;
      if (m.outcome === "arrived") setStatus(status, "ok", `✓ ${m.message}`);
      else if (m.outcome === "timeout") setStatus(status, "info", m.message);
      else setStatus(status, "warn", `⚠ ${m.message}`);
    },
    done.signal,
  );
}

function setStatus(el: HTMLElement, kind: "ok" | "error" | "pending" | "info" | "warn", text: string): void {
  if (kind !== "pending") delete el.dataset.watch;
  el.dataset.kind = kind;
  setText(el, text);
  el.title = text;
}

function argInput(axisId: string, cmd: CommandDescriptor, arg: ArgumentDescriptor, submit: () => void): HTMLInputElement | HTMLSelectElement {
  const key = `${axisId}/${cmd.name}/${arg.name}`;
  if (arg.choices.length) {
    const select = h(
      "select",
      { class: "input", testid: `cmd-${cmd.name}-${arg.name}`, title: `${arg.label}` },
      arg.choices.map((c) => h("option", { value: String(c.value), title: c.description }, c.label)),
    );
    select.value = remembered.get(key) ?? String(arg.default);
    select.addEventListener("change", () => remembered.set(key, select.value));
    return select;
  }
  const input = h("input", {
    class: "input num",
    type: "number",
    step: 1,
    min: arg.minimum,
    max: arg.maximum,
    value: remembered.get(key) ?? String(arg.default),
    testid: `cmd-${cmd.name}-${arg.name}`,
    title: `${arg.label}: ${rangeText(arg)}`,
    "aria-label": `${cmd.label}: ${arg.label}`,
  });
  const validate = (): void => {
    const problem = checkArg(arg, input.value);
    toggleClass(input, "invalid", problem !== null);
    input.title = problem ?? `${arg.label}: ${rangeText(arg)}`;
    input.classList.remove("server-invalid");
  };
  input.addEventListener("input", () => {
    remembered.set(key, input.value);
    validate();
  });
  input.addEventListener("keydown", (event) => {
    if (event.key === "Enter") {
      event.preventDefault();
      submit();
    }
  });
  validate();
  return input;
}

/** An argument's field with its unit; named too when the command has several. */
function argLabel(cmd: CommandDescriptor, arg: ArgumentDescriptor, input: HTMLElement): HTMLElement {
  const named = cmd.arguments.length > 1 && !arg.choices.length;
  return h(
    "label",
    { class: "arg" },
    named ? h("span", { class: "arg-name", title: arg.label }, arg.label) : null,
    input,
    arg.unit && !arg.choices.length ? h("span", { class: "unit" }, arg.unit) : null,
  );
}

function readArgs(cmd: CommandDescriptor, inputs: Map<string, HTMLInputElement | HTMLSelectElement>): Record<string, number> {
  const args: Record<string, number> = {};
  for (const arg of cmd.arguments) {
    const text = inputs.get(arg.name)?.value ?? "";
    // Sent as typed (the server answers 422 with the field and range if wrong).
    args[arg.name] = text.trim() === "" ? Number.NaN : Number(text);
  }
  return args;
}

/** A button plus argument inputs for one command (generic path). */
export function commandWidget(runner: CommandRunner, cmd: CommandDescriptor, extraClass = ""): HTMLElement {
  const inputs = new Map<string, HTMLInputElement | HTMLSelectElement>();
  const button = h("button", {
    class: `btn cmd ${extraClass}`.trim(),
    testid: `cmd-${cmd.name}`,
    title: cmd.description + (cmd.confirm ? " (asks for confirmation)" : ""),
  });
  button.append(cmd.label, cmd.confirm ? h("span", { class: "confirm-mark", "aria-hidden": "true" }, "…") : "");
  const submit = (): void => {
    void runner.run(cmd, readArgs(cmd, inputs), button, inputs as Map<string, HTMLElement>);
  };
  button.addEventListener("click", submit);
  const parts: HTMLElement[] = [button];
  for (const arg of cmd.arguments) {
    const input = argInput(runner.axisId, cmd, arg, submit);
    inputs.set(arg.name, input);
    parts.push(argLabel(cmd, arg, input));
  }
  return h("div", { class: "cmd-widget" }, parts);
}

/** move_relative with one argument: jog ◀ ▶ by the step in the field. */
function jogWidget(runner: CommandRunner, cmd: CommandDescriptor, arg: ArgumentDescriptor): HTMLElement {
  const inputs = new Map<string, HTMLInputElement | HTMLSelectElement>();
  const button = h("button", { class: "btn cmd", testid: `cmd-${cmd.name}`, title: cmd.description }, cmd.label);
  const step = argInput(runner.axisId, cmd, arg, () => button.click()) as HTMLInputElement;
  step.classList.add("jog-step");
  inputs.set(arg.name, step);
  const jog = (sign: 1 | -1, el: HTMLElement): void => {
    const magnitude = Math.abs(Number(step.value));
    const args = { [arg.name]: step.value.trim() === "" ? Number.NaN : sign * magnitude };
    void runner.run({ ...cmd, label: `Jog ${sign > 0 ? "+" : "−"}` }, args, el, inputs as Map<string, HTMLElement>);
  };
  const neg: HTMLButtonElement = h("button", {
    class: "btn jog",
    testid: `jog-${cmd.name}-neg`,
    title: `Jog negative by the step (${cmd.name})`,
    "aria-label": "Jog negative",
    onclick: () => jog(-1, neg),
  }, "◀");
  const pos: HTMLButtonElement = h("button", {
    class: "btn jog",
    testid: `jog-${cmd.name}-pos`,
    title: `Jog positive by the step (${cmd.name})`,
    "aria-label": "Jog positive",
    onclick: () => jog(1, pos),
  }, "▶");
  button.addEventListener("click", () => void runner.run(cmd, readArgs(cmd, inputs), button, inputs as Map<string, HTMLElement>));
  return h(
    "div",
    { class: "cmd-widget jog-widget" },
    h("span", { class: "widget-label" }, "Jog"),
    neg,
    h("label", { class: "arg" }, step, arg.unit ? h("span", { class: "unit" }, arg.unit) : null),
    pos,
    button,
  );
}

/** A command with an abort_command (calibration): choice select, start, abort. */
class RunningCommand {
  readonly el: HTMLElement;
  private running = false;
  private startedAt = 0;
  private lastMoveAt = 0;
  private lastValue = Number.NaN;
  private readonly abortButton: HTMLButtonElement;
  private readonly state: HTMLElement;
  private readonly describe: HTMLElement[] = [];

  constructor(
    runner: CommandRunner,
    cmd: CommandDescriptor,
    abort: CommandDescriptor | undefined,
    abortTestId: string,
    private readonly watch: string | undefined,
  ) {
    const inputs = new Map<string, HTMLInputElement | HTMLSelectElement>();
    const start = h("button", { class: "btn cmd", testid: `cmd-${cmd.name}`, title: cmd.description }, cmd.label);
    const parts: HTMLElement[] = [];
    for (const arg of cmd.arguments) {
      const input = argInput(runner.axisId, cmd, arg, () => start.click());
      inputs.set(arg.name, input);
      if (input instanceof HTMLSelectElement) {
        const describe = h("div", { class: "choice-description", testid: `choice-description-${cmd.name}-${arg.name}` });
        const sync = (): void => {
          const choice = arg.choices.find((c) => String(c.value) === input.value);
          setText(describe, choice?.description ?? "");
          input.title = choice ? `${choice.label}: ${choice.description}` : arg.label;
        };
        input.addEventListener("change", sync);
        sync();
        parts.push(argLabel(cmd, arg, input));
        this.describe.push(describe);
      } else {
        parts.push(argLabel(cmd, arg, input));
      }
    }
    start.addEventListener("click", async () => {
      const ok = await runner.run(cmd, readArgs(cmd, inputs), start, inputs as Map<string, HTMLElement>);
      if (ok) this.setRunning(true);
    });
    this.abortButton = h("button", {
      class: "btn cmd abort",
      testid: abort ? abortTestId : undefined,
      title: abort?.description ?? "",
      onclick: async () => {
        if (!abort) return;
        const ok = await runner.run(abort, {}, this.abortButton);
        if (ok) this.setRunning(false);
      },
    }, abort?.label ?? "Abort");
    this.state = h("span", { class: "run-state", testid: `run-state-${cmd.name}` });
    this.el = h("div", { class: "cmd-widget running-widget" }, parts, start, abort ? this.abortButton : null, this.state, this.describe);
    this.setRunning(false);
  }

  setRunning(on: boolean): void {
    this.running = on;
    this.startedAt = performance.now();
    this.lastMoveAt = this.startedAt;
    this.lastValue = Number.NaN;
    toggleClass(this.el, "is-running", on);
    toggleClass(this.abortButton, "armed", on);
    setText(this.state, on ? "running" : "");
  }

  /** Generic end detection: the watched channel has not moved for 1.5 s. */
  tick(buffer: AxisBuffer): void {
    if (!this.running || !this.watch) return;
    const value = buffer.latest.get(this.watch);
    const now = performance.now();
    if (value === undefined) return;
    if (!Number.isFinite(this.lastValue) || Math.abs(value - this.lastValue) > 1) {
      this.lastValue = value;
      this.lastMoveAt = now;
    }
    if (now - this.startedAt > 2500 && now - this.lastMoveAt > 1500) this.setRunning(false);
  }
}

export class Controls {
  readonly el: HTMLElement;
  readonly status: HTMLElement;
  readonly runner: CommandRunner;
  private readonly running: RunningCommand[] = [];
  /** Mode buttons shown as engaged while their descriptor flag is on. */
  private readonly engaged: [string, HTMLElement][] = [];

  constructor(axisId: string, descriptor: DeviceDescriptor) {
    this.status = h("div", { class: "cmd-status", testid: "command-status", "aria-live": "polite" });
    this.runner = makeRunner(axisId, this.status);
    const byName = new Map(descriptor.commands.map((c) => [c.name, c]));
    // An abort command used by exactly one command of its own group is shown only as
    // that command's Abort button; one shared or of another group (e.g. a "halt" in
    // the stop group) keeps its own button and the Abort buttons get "abort-<cmd>".
    const users = new Map<string, CommandDescriptor[]>();
    for (const c of descriptor.commands) {
      if (c.abort_command) users.set(c.abort_command, [...(users.get(c.abort_command) ?? []), c]);
    }
    const aborts = new Set(
      [...users.entries()]
        .filter(([name, list]) => list.length === 1 && byName.get(name)?.group === list[0]?.group)
        .map(([name]) => name),
    );
    const watch = descriptor.plots.find((p) => p.kind === "line")?.series[0];
    const groups = new Map<CommandDescriptor["group"], HTMLElement[]>();
    for (const cmd of descriptor.commands) {
      // A hold-to-run command (the jog) only ever goes out from the jog buttons, whose
      // release stops it: a plain button would start it with nothing to end it.
      if (aborts.has(cmd.name) || cmd.group === "persist" || cmd.hold_to_run) continue;
      let widget: HTMLElement;
      const only = cmd.arguments.length === 1 ? cmd.arguments[0] : undefined;
      if (cmd.abort_command) {
        const abortTestId = aborts.has(cmd.abort_command) ? `cmd-${cmd.abort_command}` : `abort-${cmd.name}`;
        const rc = new RunningCommand(this.runner, cmd, byName.get(cmd.abort_command), abortTestId, watch);
        this.running.push(rc);
        widget = rc.el;
      } else if (cmd.name === "move_relative" && only && !only.choices.length) {
        widget = jogWidget(this.runner, cmd, only);
      } else if (cmd.group === "stop") {
        // The device's gentler stops (e.g. SLAP2 stop and hold) do not look like STOP.
        widget = commandWidget(this.runner, cmd, descriptor.stop.gentler.includes(cmd.name) ? "" : "danger");
      } else {
        widget = commandWidget(this.runner, cmd, cmd.group === "mode" ? "mode" : "");
        if (cmd.active_flag) this.engaged.push([cmd.active_flag, widget]);
      }
      const list = groups.get(cmd.group) ?? [];
      list.push(widget);
      groups.set(cmd.group, list);
    }
    // Short groups first so the wide motion group wraps as a whole.
    const order: CommandDescriptor["group"][] = ["stop", "mode", "calibration", "other", "motion"];
    // What this device's STOP does now (shortest stop, then its safe state), what it does
    // instead when the loop is not working, and the gentler stops, at the stop group.
    const stop = descriptor.stop;
    const gentler = stop.gentler.map((n) => byName.get(n)?.label ?? n);
    const categories = ["power cut at once", "controlled stop, then power off", "controlled stop, holds under power"];
    groups.get("stop")?.push(
      h(
        "div",
        {
          class: "stop-effect",
          testid: "stop-effect",
          title: `STOP sends ${stop.sends}: stop category ${stop.category} (${categories[stop.category]}).${stop.power_off_command ? ` ${byName.get(stop.power_off_command)?.label ?? stop.power_off_command} cuts the power at once.` : ""}`,
        },
        stop.summary + (stop.loop_failed ? `; ${stop.loop_failed}` : "") + (gentler.length ? `. Gentler: ${gentler.join(", ")}.` : "."),
      ),
    );
    const boxes = order
      .filter((g) => groups.has(g))
      .map((g) =>
        h(
          "section",
          { class: `cmd-group group-${g}`, "data-group": g },
          h("div", { class: "group-title" }, GROUP_TITLES[g]),
          h("div", { class: "group-body" }, groups.get(g) ?? []),
        ),
      );
    this.el = h("div", { class: "controls" }, h("div", { class: "cmd-groups" }, boxes));
  }

  tick(buffer: AxisBuffer): void {
    for (const rc of this.running) rc.tick(buffer);
    for (const [flag, widget] of this.engaged) {
      const on = buffer.latestFlags.get(flag) === 1;
      const button = widget.querySelector("button");
      if (button && button.classList.contains("engaged") !== on) {
        button.classList.toggle("engaged", on);
        button.setAttribute("aria-pressed", on ? "true" : "false");
      }
    }
  }

  /** A STOP (this axis or all) ends whatever was running. */
  stopped(): void {
    for (const rc of this.running) rc.setRunning(false);
  }
}
