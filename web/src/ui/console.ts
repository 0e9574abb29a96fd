// The raw console of one axis: lines go to the module as typed, every reply line is shown.
import { api } from "../api";
import { h } from "../dom";
import { formatClock } from "../format";
import { store } from "../store";
import type { DeviceDescriptor } from "../schema.gen";
import { errorText, statusLabel } from "./feedback";

/** Output and history survive switching axes (per axis). */
const transcripts = new Map<string, HTMLElement[]>();
const histories = new Map<string, string[]>();
const HISTORY_MAX = 200;

export class ConsolePanel {
  readonly el: HTMLElement;
  private readonly output: HTMLElement;
  private readonly input: HTMLInputElement;
  private readonly history: string[];
  private readonly intro: HTMLElement;
  private cursor: number;
  private draft = "";
  readonly toggleButton: HTMLButtonElement;
  onExpand: (open: boolean) => void = () => {};
  private expanded = false;

  constructor(
    private readonly axisId: string,
    axisName: string,
    private readonly descriptor: DeviceDescriptor,
  ) {
    this.history = histories.get(axisId) ?? [];
    histories.set(axisId, this.history);
    this.cursor = this.history.length;
    this.output = h("div", { class: "console-output", testid: "console-output", role: "log", "aria-live": "polite" });
    const lines = transcripts.get(axisId) ?? [];
    transcripts.set(axisId, lines);
    this.intro = h(
      "div",
      { class: "con-note", testid: "console-help" },
      h("div", null, descriptor.console.help),
      h("div", { class: "con-note-dim" }, `${axisName} (${descriptor.model}) · ↑/↓ history · Esc still stops every axis.`),
    );
    this.output.append(this.intro, ...lines);
    this.input = h("input", {
      class: "input console-input mono",
      testid: "console-input",
      placeholder: "command, Enter to send · ↑/↓ history",
      spellcheck: false,
      autocomplete: "off",
      maxlength: "64",
      "aria-label": "Console line",
    });
    this.input.addEventListener("keydown", (event) => this.onKey(event));
    const send = h("button", { class: "btn", testid: "console-send", onclick: () => this.submit() }, "Send");
    const clear = h("button", { class: "btn ghost", testid: "console-clear", title: "Clear the output", onclick: () => this.clear() }, "Clear");
    const chips = h(
      "div",
      { class: "chips" },
      h("span", { class: "chips-label" }, "Examples"),
      descriptor.console.examples.map((example) =>
        h(
          "button",
          {
            class: "chip mono",
            testid: `console-example-${example}`,
            title: `Send ${example}`,
            onclick: () => {
              this.input.value = example;
              this.submit();
            },
          },
          example,
        ),
      ),
    );
    this.el = h(
      "div",
      { class: "console" },
      chips,
      this.output,
      h("div", { class: "console-line" }, h("span", { class: "prompt mono" }, ">"), this.input, send, clear),
    );
    this.toggleButton = h("button", {
      class: "btn ghost small",
      testid: "console-toggle",
      title: "Show or hide the console output",
      onclick: () => this.setExpanded(!this.expanded),
    });
    queueMicrotask(() => (this.output.scrollTop = this.output.scrollHeight));
  }

  setExpanded(open: boolean): void {
    this.expanded = open;
    this.el.classList.toggle("open", open);
    this.toggleButton.textContent = open ? "Hide ▾" : "Show ▴";
    this.onExpand(open);
    if (open) this.output.scrollTop = this.output.scrollHeight;
  }

  focus(): void {
    this.input.focus();
  }

  private onKey(event: KeyboardEvent): void {
    if (event.key === "Enter") {
      event.preventDefault();
      this.submit();
    } else if (event.key === "ArrowUp") {
      if (!this.history.length) return;
      event.preventDefault();
      if (this.cursor === this.history.length) this.draft = this.input.value;
      this.cursor = Math.max(0, this.cursor - 1);
      this.input.value = this.history[this.cursor] ?? "";
    } else if (event.key === "ArrowDown") {
      if (this.cursor >= this.history.length) return;
      event.preventDefault();
      this.cursor += 1;
      this.input.value = this.cursor === this.history.length ? this.draft : (this.history[this.cursor] ?? "");
    }
  }

  private append(el: HTMLElement): void {
    const lines = transcripts.get(this.axisId) as HTMLElement[];
    lines.push(el);
    if (lines.length > 500) lines.splice(0, lines.length - 500).forEach((n) => n.remove());
    const stick = this.output.scrollHeight - this.output.scrollTop - this.output.clientHeight < 40;
    this.output.appendChild(el);
    if (stick) this.output.scrollTop = this.output.scrollHeight;
  }

  private clear(): void {
    transcripts.set(this.axisId, []);
    this.output.replaceChildren(this.intro);
  }

  private submit(): void {
    const line = this.input.value;
    if (!line.trim()) return;
    if (!this.expanded) this.setExpanded(true);
    if (this.history[this.history.length - 1] !== line) this.history.push(line);
    if (this.history.length > HISTORY_MAX) this.history.splice(0, this.history.length - HISTORY_MAX);
    this.cursor = this.history.length;
    this.draft = "";
    this.input.value = "";
    const time = h("span", { class: "con-time" }, formatClock(new Date()));
    const sentText = h("span", { class: "con-sent" }, `> ${line}`);
    const body = h("div", { class: "con-body" }, h("div", { class: "con-wait" }, "…"));
    const entry = h("div", { class: "con-entry pending" }, h("div", { class: "con-head" }, sentText, time), body);
    this.append(entry);
    // The device's refusal shows in its status flags (e.g. SLAP2 `uc`, Z1100 error
    // bits): warning/fault flags that come on after the line are reported with it.
    const buffer = store.buffer(this.axisId);
    const watched = this.descriptor.flags.filter((f) => f.severity !== "info");
    const before = new Set(watched.filter((f) => buffer.latestFlags.get(f.name) === 1).map((f) => f.name));
    const sentAt = buffer.lastT;
    const refusal = (): void => {
      if (!(buffer.lastT > sentAt)) return;
      const raised = watched.filter((f) => !before.has(f.name) && buffer.latestFlags.get(f.name) === 1);
      if (raised.length) body.appendChild(h("div", { class: "con-error", testid: "console-refusal" }, `device reports: ${raised.map((f) => `${f.label} (${f.name})`).join(", ")}`));
    };
    void api
      .console(this.axisId, line)
      .then((reply) => {
        sentText.textContent = `> ${reply.sent}`;
        if (reply.sent !== line.trim()) sentText.title = `typed: ${line}`;
        const parts: HTMLElement[] = [];
        const text = reply.reply.join("\n");
        if (text.trim()) parts.push(h("pre", { class: "con-reply" }, text));
        else if (!reply.error) parts.push(h("div", { class: "con-empty", testid: "console-no-reply" }, "(no reply)"));
        if (reply.error) parts.push(h("div", { class: "con-error" }, reply.error));
        body.replaceChildren(...parts);
        entry.classList.remove("pending");
        entry.classList.toggle("error", !!reply.error);
        // Flags arrive with the next telemetry samples: look twice.
        window.setTimeout(refusal, 400);
        window.setTimeout(() => body.querySelector("[data-testid=console-refusal]") || refusal(), 1200);
      })
      .catch((error: unknown) => {
        body.replaceChildren(h("div", { class: "con-error" }, `${statusLabel(error)}: ${errorText(error)}`));
        entry.classList.remove("pending");
        entry.classList.add("error");
      })
      .finally(() => {
        if (this.output.scrollHeight - this.output.scrollTop - this.output.clientHeight < 200) {
          this.output.scrollTop = this.output.scrollHeight;
        }
      });
  }
}
