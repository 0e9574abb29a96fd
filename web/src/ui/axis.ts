// One axis page, built entirely from its device descriptor.
import { api } from "../api";
import { h, replace, setText, toggleClass } from "../dom";
import { store } from "../store";
import { UnitPrefs } from "../units";
import type { AxisInfo, DeviceDescriptor } from "../schema.gen";
import { BenchView } from "./bench/view";
import { Controls, makeRunner } from "./commands";
import { ConsolePanel } from "./console";
import { controlStrip } from "./controllock";
import { PlotStack } from "./plots";
import { Readouts } from "./readouts";
import { TuningPanel } from "./tuning";
import { TwinPanel } from "./twin";

export const HEALTH_TEXT: Record<string, string> = {
  ok: "ok",
  reset: "reset — settings may be lost",
  offline: "offline",
  paused: "paused",
};

/** Whether the console pane is unfolded, kept across axis switches. */
let consoleOpen = false;
/** Whether the bench replaces the scope, kept across axis switches and reloads. */
let benchOpen = localStorage.getItem("servotune.view") === "bench";

export class AxisView {
  readonly el: HTMLElement;
  private readonly abort = new AbortController();
  private plots: PlotStack | null = null;
  private readouts: Readouts | null = null;
  private controls: Controls | null = null;
  private lastSlow = 0;
  private readonly health: HTMLElement;
  private readonly banner: HTMLElement;
  private readonly operated: HTMLElement;
  private bench: BenchView | null = null;
  private benchArea: HTMLElement | null = null;
  private descriptor: DeviceDescriptor | null = null;
  private readonly liveButton: HTMLButtonElement;
  private readonly benchButton: HTMLButtonElement;

  constructor(private readonly axis: AxisInfo) {
    this.health = h("span", { class: "badge health", testid: "axis-health" });
    this.operated = h("span", { class: "badge subtle", testid: "axis-operated" });
    this.banner = h("div", { class: "banner-slot" });
    this.liveButton = h(
      "button",
      { class: "seg-btn", testid: "live-toggle", title: "Live scope, readouts and commands", onclick: () => this.setBench(false) },
      "Live",
    );
    this.benchButton = h(
      "button",
      { class: "seg-btn", testid: "bench-toggle", title: "Tuning test bench: repeatable tests, metrics, run comparison", onclick: () => this.setBench(true) },
      "Bench",
    );
    this.el = h(
      "div",
      { class: "axis-view loading", "data-axis": axis.id },
      h("div", { class: "axis-loading" }, `Loading ${axis.name} …`),
    );
    void this.load();
  }

  private async load(): Promise<void> {
    let descriptor: DeviceDescriptor;
    try {
      descriptor = await store.descriptor(this.axis.id, () => api.descriptor(this.axis.id));
    } catch (error) {
      replace(
        this.el,
        h(
          "div",
          { class: "axis-loading error" },
          `Cannot load the descriptor of ${this.axis.name}: ${(error as Error).message}`,
          h("button", { class: "btn", onclick: () => void this.load() }, "Retry"),
        ),
      );
      return;
    }
    if (this.abort.signal.aborted) return;
    this.descriptor = descriptor;
    this.render(descriptor);
  }

  /** Show the bench (built on first use) instead of the scope, or the scope again. */
  setBench(open: boolean): void {
    benchOpen = open;
    try {
      localStorage.setItem("servotune.view", open ? "bench" : "live");
    } catch {
      /* private mode */
    }
    this.syncView();
  }

  private syncView(): void {
    toggleClass(this.liveButton, "on", !benchOpen);
    toggleClass(this.benchButton, "on", benchOpen);
    this.benchButton.setAttribute("aria-pressed", benchOpen ? "true" : "false");
    toggleClass(this.el, "bench-open", benchOpen);
    if (benchOpen && !this.bench && this.descriptor && this.benchArea) {
      this.bench = new BenchView(this.axis.id, this.descriptor, this.abort.signal);
      replace(this.benchArea, this.bench.el);
    }
    if (benchOpen) void this.bench?.refresh();
  }

  private render(d: DeviceDescriptor): void {
    const signal = this.abort.signal;
    const axis = this.axis;
    const buffer = store.buffer(axis.id);
    const units = new UnitPrefs(d);
    this.readouts = new Readouts(d, buffer, units, signal);
    this.plots = new PlotStack(d, buffer, units, axis.id, signal);
    this.controls = new Controls(axis.id, d);
    const tuning = new TuningPanel(axis.id, d, signal);
    const consolePanel = new ConsolePanel(axis.id, axis.name, d);
    this.benchArea = h("section", { class: "bench-area" });
    const twin = new TwinPanel(axis.id, axis.name);
    const scopeArea = h("section", { class: "scope-area" }, this.plots.el);
    twin.mount(scopeArea);

    const header = h(
      "div",
      { class: "axis-header" },
      h(
        "div",
        { class: "axis-title" },
        h("h1", { testid: "axis-name" }, axis.name),
        h("span", { class: "axis-model", testid: "axis-model" }, d.model),
        this.health,
        this.operated,
        h("span", { class: "axis-meta mono" }, `${axis.id} · ${axis.link} · addr ${axis.address}`),
        h("span", { class: "tb-spacer" }),
        this.controls.status,
        controlStrip(axis.id, d, this.el, signal),
        h("div", { class: "seg view-toggle", role: "group", "aria-label": "View" }, this.liveButton, this.benchButton),
        twin.toggle,
      ),
      h("div", { class: "axis-summary", title: `${d.title} — ${d.summary}` }, h("b", null, d.title), " — ", d.summary),
    );

    // Tuning and console are both always on screen: the console docks below the
    // parameters, folded to its input line until it is used.
    const consolePane = h(
      "section",
      { class: "side-pane console-pane", testid: "console-pane" },
      h(
        "div",
        { class: "pane-header" },
        h("span", { class: "pane-title" }, "Console"),
        h("span", { class: "pane-sub" }, `${axis.name} · raw device lines`),
        h("span", { class: "tb-spacer" }),
        consolePanel.toggleButton,
      ),
      consolePanel.el,
    );
    consolePanel.onExpand = (open) => {
      consoleOpen = open;
      toggleClass(consolePane, "open", open);
    };
    consolePanel.setExpanded(consoleOpen);
    const side = h(
      "aside",
      { class: "side" },
      h("section", { class: "side-pane tuning-pane" }, tuning.el),
      consolePane,
    );

    replace(
      this.el,
      header,
      this.banner,
      this.readouts.el,
      this.controls.el,
      h("div", { class: "work" }, scopeArea, this.benchArea, side),
    );
    this.el.classList.remove("loading");
    this.syncView();

    const restore = d.commands.find((c) => c.name === "restore_parameters");
    const bannerRunner = makeRunner(axis.id, this.controls.status);
    const syncStatus = (): void => {
      const status = store.axisStatus.get(axis.id);
      const health = status?.health ?? "ok";
      // "paused: capture on #n" names the axis the line is devoted to (docs/capture.md).
      setText(this.health, health === "paused" ? status?.message || "paused" : HEALTH_TEXT[health] ?? health);
      this.health.dataset.health = health;
      this.health.title = status?.message || `health: ${health}`;
      const autopilot = store.autopilot && status && !status.operated;
      setText(this.operated, autopilot ? "autopilot moving" : "");
      this.operated.hidden = !autopilot;
      if (health === "reset") {
        if (!this.banner.firstChild) {
          const button = restore
            ? h("button", { class: "btn warn", testid: "reset-restore", title: restore.description }, restore.label)
            : null;
          button?.addEventListener("click", () => void bannerRunner.run(restore as NonNullable<typeof restore>, {}, button));
          replace(
            this.banner,
            h(
              "div",
              { class: "banner reset", testid: "reset-banner", role: "alert" },
              h("span", { class: "banner-icon" }, "⚠"),
              h("div", { class: "banner-text" }, h("b", null, "Module reset — settings may be lost"), h("span", { class: "banner-detail" }, status?.message ?? "")),
              button,
            ),
          );
        } else {
          const detail = this.banner.querySelector(".banner-detail");
          if (detail) setText(detail, status?.message ?? "");
        }
      } else if (health === "offline") {
        replace(
          this.banner,
          h(
            "div",
            { class: "banner offline", testid: "offline-banner", role: "alert" },
            h("span", { class: "banner-icon" }, "⨯"),
            h("div", { class: "banner-text" }, h("b", null, "Axis offline"), h("span", { class: "banner-detail" }, status?.message ?? "")),
          ),
        );
      } else replace(this.banner);
    };
    syncStatus();
    store.on("axisStatus", (id) => id === axis.id && syncStatus(), signal);
    store.on("topology", syncStatus, signal);
    store.on(
      "event",
      (e) => {
        if (/stop/i.test(e.message) && (e.axis === null || e.axis === axis.id)) this.controls?.stopped();
      },
      signal,
    );
  }

  /** Animation frame: plots redraw if new data arrived; readouts at about 10 Hz. */
  frame(now: number): void {
    if (!benchOpen || !this.bench) this.plots?.update();
    if (now - this.lastSlow > 100) {
      this.lastSlow = now;
      this.readouts?.update();
      this.plots?.refreshLegend();
      if (this.controls) this.controls.tick(store.buffer(this.axis.id));
    }
  }

  stopped(): void {
    this.controls?.stopped();
  }

  /** The live scope (tests, benchmarks). */
  get scope(): PlotStack | null {
    return this.plots;
  }

  destroy(): void {
    this.abort.abort();
    this.el.remove();
  }
}
