// Top bar (STOP, connection, drops, event toggle), navigation (links -> axes) and the
// event log drawer.
import { h, replace, setText, toggleClass } from "../dom";
import { formatSeconds } from "../format";
import { store } from "../store";
import type { Event as WireEvent, LinkState } from "../wire.gen";
import type { WsState } from "../ws";
import { HEALTH_TEXT } from "./axis";

const LAMP: Record<LinkState, string> = {
  connected: "green",
  connecting: "amber",
  reconnecting: "amber",
  error: "red",
  disconnected: "red",
};

export function wsText(state: WsState, now = performance.now()): string {
  switch (state.kind) {
    case "open":
      return "connected";
    case "connecting":
      return state.attempt > 1 ? `connecting (attempt ${state.attempt})` : "connecting";
    case "waiting": {
      const s = Math.max(0, Math.ceil((state.retryAt - now) / 1000));
      return `disconnected · retry in ${s} s`;
    }
  }
}

export class TopBar {
  readonly el: HTMLElement;
  readonly stopButton: HTMLButtonElement;
  readonly eventsButton: HTMLButtonElement;
  private readonly ws: HTMLElement;
  private readonly wsLabel: HTMLElement;
  private readonly dropped: HTMLElement;
  private readonly unread: HTMLElement;
  private readonly autopilot: HTMLElement;
  private readonly stopNote: HTMLElement;
  private readonly stopEffect: HTMLElement;
  private readonly version: HTMLElement;

  constructor(handlers: { stop(): void; toggleEvents(): void; retry(): void; toggleTheme(): void }) {
    this.stopButton = h(
      "button",
      { class: "stop-all", testid: "stop-all", title: "Stop every axis now (Esc, from anywhere)", onclick: () => handlers.stop() },
      h("span", { class: "stop-label" }, "STOP"),
      h("span", { class: "stop-hint" }, "all axes · Esc"),
    );
    this.wsLabel = h("span", { class: "ws-label" }, "connecting");
    this.ws = h(
      "button",
      { class: "ws-state", testid: "ws-state", title: "Websocket to the servotune server", onclick: () => handlers.retry() },
      h("span", { class: "dot" }),
      this.wsLabel,
    );
    this.dropped = h("span", { class: "mono", testid: "dropped-frames" }, "0");
    this.unread = h("span", { class: "count", testid: "events-unread", hidden: true });
    this.eventsButton = h(
      "button",
      { class: "btn ghost events-toggle", testid: "events-toggle", title: "Show or hide the event log", onclick: () => handlers.toggleEvents() },
      "Event log",
      this.unread,
    );
    this.autopilot = h("span", { class: "chip-autopilot", testid: "autopilot", hidden: true, title: "The demo moves each simulated axis until you operate it" }, "DEMO · autopilot");
    this.stopNote = h("span", { class: "stop-note", testid: "stop-note", "aria-live": "assertive" });
    this.stopEffect = h("span", { class: "stop-effect", testid: "stop-effect-all" });
    this.version = h("span", { class: "version" });
    this.el = h(
      "header",
      { class: "topbar" },
      h(
        "div",
        { class: "brand" },
        h("span", { class: "brand-mark", "aria-hidden": "true" }),
        h("span", { class: "brand-name" }, "servotune"),
        this.version,
      ),
      this.autopilot,
      h("span", { class: "tb-spacer" }),
      this.ws,
      h("span", { class: "stat", title: "Websocket messages the server dropped for this browser because it fell behind" }, h("span", { class: "stat-label" }, "dropped"), this.dropped),
      this.eventsButton,
      h("button", { class: "btn ghost icon-btn", testid: "theme-toggle", title: "Light / dark", onclick: () => handlers.toggleTheme() }, "◐"),
      this.stopNote,
      this.stopEffect,
      this.stopButton,
    );
    store.on("clientStats", () => {
      setText(this.dropped, String(store.stats.dropped));
      toggleClass(this.dropped, "warn", store.stats.dropped > 0);
      this.dropped.title = `${store.stats.sent} sent, ${store.stats.dropped} dropped`;
    });
    store.on("topology", () => {
      this.autopilot.hidden = !store.autopilot;
      setText(this.version, store.serverVersion ? `v${store.serverVersion}` : "");
    });
  }

  setWs(state: WsState): void {
    setText(this.wsLabel, wsText(state));
    this.ws.dataset.state = state.kind;
    this.ws.title =
      state.kind === "waiting" ? `Connection lost (${state.reason}); click to retry now` : "Websocket to the servotune server";
  }

  /** The descriptors' stop effects of the devices present, next to the button. */
  setStopEffects(summaries: string[]): void {
    setText(this.stopEffect, summaries.join(" · "));
    this.stopButton.title = ["Stop every axis now (Esc, from anywhere but a dialog).", ...summaries].join("\n");
  }

  setUnread(n: number, severe: boolean): void {
    this.unread.hidden = n === 0;
    setText(this.unread, n > 99 ? "99+" : String(n));
    toggleClass(this.unread, "severe", severe);
  }

  stopFeedback(text: string, ok: boolean): void {
    setText(this.stopNote, text);
    this.stopNote.dataset.ok = ok ? "1" : "0";
    this.stopButton.classList.remove("fired");
    void this.stopButton.offsetWidth;
    this.stopButton.classList.add("fired");
  }
}

export class Nav {
  readonly el: HTMLElement;
  private readonly list: HTMLElement;
  private current = "";

  constructor() {
    this.list = h("div", { class: "nav-list" });
    this.el = h("nav", { class: "nav", "aria-label": "Links and axes" }, h("div", { class: "nav-title" }, "Links & axes"), this.list);
    store.on("topology", () => this.render());
    store.on("link", () => this.refresh());
    store.on("axisStatus", () => this.refresh());
    this.render();
  }

  select(axisId: string): void {
    this.current = axisId;
    for (const a of this.list.querySelectorAll<HTMLElement>(".nav-axis")) toggleClass(a, "on", a.dataset.axis === axisId);
  }

  render(): void {
    const children: HTMLElement[] = [];
    const linkIds = new Set(store.links.map((l) => l.id));
    const orphans = store.axes.filter((a) => !linkIds.has(a.link));
    for (const link of store.links) {
      const axes = store.axes.filter((a) => a.link === link.id);
      children.push(
        h(
          "div",
          { class: "nav-link", "data-link": link.id },
          h(
            "div",
            { class: "link-head" },
            h("span", { class: "link-state", testid: `link-state-${link.id}` }, h("span", { class: "lamp-dot" }), h("span", { class: "link-state-text" }, "—")),
            h("span", { class: "link-name", title: link.id }, link.id),
          ),
          h("div", { class: "link-meta mono", title: `${link.device} on ${link.path}` }, `${link.device} · ${link.path}${link.baud ? ` · ${link.baud}` : ""}`),
          h("div", { class: "link-rate mono", testid: `link-rate-${link.id}` }, "—"),
          h("div", { class: "link-message" }),
          h(
            "div",
            { class: "nav-axes" },
            axes.map((a) =>
              h(
                "a",
                { class: "nav-axis", href: `#/axis/${encodeURIComponent(a.id)}`, testid: `axis-link-${a.id}`, "data-axis": a.id, title: `${a.name} — ${a.id} (${a.device}, address ${a.address})` },
                h("span", { class: "axis-lamp" }),
                h("span", { class: "nav-axis-name" }, a.name),
                h("span", { class: "nav-axis-addr mono" }, `#${a.address}`),
                h("span", { class: "nav-health", testid: `nav-health-${a.id}` }),
              ),
            ),
          ),
        ),
      );
    }
    for (const a of orphans) {
      children.push(h("a", { class: "nav-axis", href: `#/axis/${encodeURIComponent(a.id)}`, testid: `axis-link-${a.id}`, "data-axis": a.id }, a.name));
    }
    if (!children.length) children.push(h("div", { class: "nav-empty" }, "No links configured."));
    replace(this.list, children);
    this.refresh();
    this.select(this.current);
  }

  refresh(): void {
    for (const el of this.list.querySelectorAll<HTMLElement>(".nav-link")) {
      const id = el.dataset.link as string;
      const status = store.linkStatus.get(id);
      const stateEl = el.querySelector<HTMLElement>(".link-state") as HTMLElement;
      const state = status?.state;
      stateEl.dataset.state = state ?? "unknown";
      stateEl.dataset.lamp = state ? LAMP[state] : "off";
      setText(stateEl.querySelector(".link-state-text") as HTMLElement, state ?? "unknown");
      stateEl.title = status?.message ? `${state}: ${status.message}` : (state ?? "no status yet");
      const rate = el.querySelector<HTMLElement>(".link-rate") as HTMLElement;
      if (status && (status.state === "connected" || status.rate_hz > 0)) {
        const pct = status.wire_limit_hz > 0 ? ` (${Math.round((100 * status.rate_hz) / status.wire_limit_hz)} % of wire)` : "";
        setText(rate, `${status.rate_hz.toFixed(1)} Hz${pct}`);
        rate.title = `telemetry samples per second per axis; the wire allows ${status.wire_limit_hz.toFixed(1)} Hz for this poll set; ${status.errors} errors`;
      } else setText(rate, "— Hz");
      const message = el.querySelector<HTMLElement>(".link-message") as HTMLElement;
      setText(message, status && status.state !== "connected" ? status.message : status && status.errors ? `${status.errors} errors` : "");
      message.dataset.state = status?.state ?? "";
    }
    for (const el of this.list.querySelectorAll<HTMLElement>(".nav-axis")) {
      const id = el.dataset.axis as string;
      const status = store.axisStatus.get(id);
      const health = status?.health ?? "ok";
      el.dataset.health = health;
      const badge = el.querySelector<HTMLElement>(".nav-health");
      if (badge) {
        setText(badge, health === "ok" ? "" : (HEALTH_TEXT[health] ?? health));
        badge.title = status?.message ?? "";
      }
    }
  }
}

export class EventLog {
  readonly el: HTMLElement;
  private readonly list: HTMLElement;
  private open = false;
  private unread = 0;
  private severe = false;
  private onlyProblems = false;

  constructor(
    private readonly onUnread: (n: number, severe: boolean) => void,
    private readonly axisName: (id: string) => string,
    private readonly onToggle: (open: boolean) => void,
  ) {
    this.list = h("div", { class: "event-list", role: "log" });
    const filter = h("button", { class: "btn ghost small", testid: "events-filter" }, "Warnings only");
    filter.addEventListener("click", () => {
      this.onlyProblems = !this.onlyProblems;
      toggleClass(filter, "on", this.onlyProblems);
      toggleClass(this.list, "only-problems", this.onlyProblems);
    });
    this.el = h(
      "section",
      { class: "event-log", testid: "event-log", hidden: true },
      h(
        "div",
        { class: "event-head" },
        h("span", { class: "event-title" }, "Event log"),
        h("span", { class: "tb-spacer" }),
        filter,
        h("button", { class: "btn ghost small", onclick: () => this.clear() }, "Clear"),
        h("button", { class: "btn ghost small", title: "Close", onclick: () => this.toggle(false) }, "×"),
      ),
      this.list,
    );
    for (const e of store.events) this.add(e, false);
    store.on("event", (e) => this.add(e, true));
  }

  toggle(force?: boolean): void {
    this.open = force ?? !this.open;
    this.el.hidden = !this.open;
    this.onToggle(this.open);
    if (this.open) {
      this.unread = 0;
      this.severe = false;
      this.onUnread(0, false);
      this.list.scrollTop = this.list.scrollHeight;
    }
  }

  private clear(): void {
    this.list.replaceChildren();
  }

  private add(e: WireEvent, live: boolean): void {
    const stick = this.list.scrollHeight - this.list.scrollTop - this.list.clientHeight < 30;
    this.list.appendChild(
      h(
        "div",
        { class: `event level-${e.level}`, "data-level": e.level },
        h("span", { class: "ev-time mono" }, formatSeconds(e.t)),
        h("span", { class: "ev-level" }, e.level),
        h("span", { class: "ev-axis" }, e.axis ? this.axisName(e.axis) : "all"),
        h("span", { class: "ev-message" }, e.message),
      ),
    );
    while (this.list.childElementCount > 500) this.list.firstElementChild?.remove();
    if (stick || !live) this.list.scrollTop = this.list.scrollHeight;
    if (!this.open && live) {
      this.unread += 1;
      this.severe ||= e.level !== "info";
      this.onUnread(this.unread, this.severe);
    }
  }
}
