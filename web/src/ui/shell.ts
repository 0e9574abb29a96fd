// Top bar (STOP, connection, drops, event toggle), navigation (links -> axes) and the
// event log drawer.
import { h, replace, setText, toggleClass } from "../dom";
import { formatSeconds } from "../format";
import { store } from "../store";
import type { Event as WireEvent, LinkState } from "../schema.gen";
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

  readonly navButton: HTMLButtonElement;

  constructor(handlers: { stop(): void; toggleEvents(): void; retry(): void; toggleTheme(): void; toggleNav?(): void }) {
    // Phones: the axis list is a drawer behind this button (hidden on wider screens).
    this.navButton = h(
      "button",
      { class: "btn ghost nav-toggle", testid: "nav-toggle", title: "Links & axes", "aria-label": "Show the links and axes", onclick: () => handlers.toggleNav?.() },
      "☰",
    );
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
      { class: "btn ghost events-toggle", testid: "events-toggle", title: "Show or hide the event log (the count: new warnings and errors)", onclick: () => handlers.toggleEvents() },
      h("span", { class: "events-label" }, "Event log"),
      h("span", { class: "events-short", "aria-hidden": "true" }, "Log"),
      this.unread,
    );
    this.autopilot = h("span", { class: "chip-autopilot", testid: "autopilot", hidden: true, title: "The demo moves each simulated axis until you operate it" }, "DEMO · autopilot");
    this.stopNote = h("span", { class: "stop-note", testid: "stop-note", "aria-live": "assertive" });
    this.stopEffect = h("span", { class: "stop-effect", testid: "stop-effect-all" });
    this.version = h("span", { class: "version" });
    this.el = h(
      "header",
      { class: "topbar" },
      this.navButton,
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
  /** Opens the event log (a link's error count leads there). */
  onOpenEvents: (() => void) | null = null;

  constructor() {
    this.list = h("div", { class: "nav-list" });
    const overview = h("a", { class: "nav-overview", href: "#/overview", testid: "nav-overview", title: "Every axis of the rig on one page" }, "▦ Rig overview");
    this.el = h("nav", { class: "nav", "aria-label": "Links and axes" }, overview, h("div", { class: "nav-title" }, "Links & axes"), this.list);
    store.on("topology", () => this.render());
    store.on("link", () => this.refresh());
    store.on("axisStatus", () => this.refresh());
    this.render();
  }

  select(axisId: string): void {
    this.current = axisId;
    toggleClass(this.el.querySelector(".nav-overview") as HTMLElement, "on", axisId === "" && location.hash === "#/overview");
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
          h("div", {
            class: "link-message",
            testid: `link-message-${link.id}`,
            title: "Open the event log",
            role: "button",
            tabIndex: 0,
            onclick: () => this.onOpenEvents?.(),
            onkeydown: (e: KeyboardEvent) => {
              if (e.key === "Enter" || e.key === " ") this.onOpenEvents?.();
            },
          }),
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
        // wire_busy counts commands too: a link that carries moves samples less than
        // wire_limit_hz while its line stays full, and this tells the two apart.
        const busy =
          status.wire_busy !== null && status.wire_busy !== undefined
            ? `; the line was busy ${Math.round(100 * status.wire_busy)} % of the last 2 s (polls, commands and echoes)`
            : "";
        rate.title = `telemetry samples per second per axis; the wire allows ${status.wire_limit_hz.toFixed(1)} Hz for this poll set${busy}; ${countOf(status.errors, "error")}`;
      } else setText(rate, "— Hz");
      const message = el.querySelector<HTMLElement>(".link-message") as HTMLElement;
      if (status && status.state !== "connected") {
        setText(message, status.message);
        message.title = "Open the event log";
      } else if (status?.errors) {
        // Errors of single transactions the link retried or resynchronised: the link
        // stayed up, so they are counted here, not logged one by one as events.
        setText(message, `${countOf(status.errors, "wire error")}, recovered`);
        const counted = Object.entries(status.counters ?? {})
          .filter(([, n]) => n > 0)
          .map(([name, n]) => `${name.replace(/_/g, " ")} ${n}`)
          .join(", ");
        message.title =
          `Transactions that failed since the server started and were retried or resynchronised; the link stayed up.` +
          `${counted ? ` Counted: ${counted}.` : ""} The event log (click) lists what reached you as a warning or error.`;
      } else {
        setText(message, "");
        message.title = "Open the event log";
      }
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

const LEVELS = ["info", "warning", "error"] as const;

/** Wall-clock time of a server-clock time, "14:03:22.1" (server seconds if unknown yet). */
export function wallClock(t: number): { text: string; full: string } {
  const offset = store.clockOffsetS;
  if (!Number.isFinite(offset)) return { text: formatSeconds(t), full: `${formatSeconds(t)} after the server started` };
  const d = new Date((t + offset) * 1000);
  const p = (n: number): string => String(n).padStart(2, "0");
  return { text: `${p(d.getHours())}:${p(d.getMinutes())}:${p(d.getSeconds())}.${Math.floor(d.getMilliseconds() / 100)}`, full: d.toLocaleString() };
}

export class EventLog {
  readonly el: HTMLElement;
  private readonly list: HTMLElement;
  private open = false;
  /** Unread warnings and errors only: info (moves, writes) would make the badge noise. */
  private unread = 0;
  private severe = false;
  private readonly shown = new Set<string>(LEVELS);
  /** Rows whose time was written before the wall clock was known. */
  private readonly pending: { el: HTMLElement; t: number }[] = [];

  constructor(
    private readonly onUnread: (n: number, severe: boolean) => void,
    private readonly axisName: (id: string) => string,
    private readonly onToggle: (open: boolean) => void,
  ) {
    this.list = h("div", { class: "event-list", role: "log" });
    const filters = h(
      "div",
      { class: "seg small event-levels", role: "group", "aria-label": "Levels shown" },
      LEVELS.map((level) => {
        const b = h("button", { class: "seg-btn on", testid: `events-level-${level}`, "aria-pressed": "true", title: `Show ${level} events` }, level);
        b.addEventListener("click", () => {
          if (this.shown.has(level)) this.shown.delete(level);
          else this.shown.add(level);
          const on = this.shown.has(level);
          toggleClass(b, "on", on);
          b.setAttribute("aria-pressed", on ? "true" : "false");
          toggleClass(this.list, `hide-${level}`, !on);
        });
        return b;
      }),
    );
    // Kept for scripts and tests written against the old single filter.
    const filter = h("button", { class: "btn ghost small", testid: "events-filter", title: "Hide info events" }, "Warnings only");
    filter.addEventListener("click", () => {
      const only = !this.list.classList.contains("hide-info");
      toggleClass(filter, "on", only);
      toggleClass(this.list, "hide-info", only);
      toggleClass(this.list, "only-problems", only);
      const info = filters.querySelector<HTMLElement>("[data-testid=events-level-info]");
      if (info) toggleClass(info, "on", !only);
      if (only) this.shown.delete("info");
      else this.shown.add("info");
    });
    this.el = h(
      "section",
      { class: "event-log", testid: "event-log", hidden: true },
      h(
        "div",
        { class: "event-head" },
        h("span", { class: "event-title" }, "Event log"),
        filters,
        h("span", { class: "tb-spacer" }),
        filter,
        h("button", { class: "btn ghost small", onclick: () => this.clear() }, "Clear"),
        h("button", { class: "btn ghost small", title: "Close", "aria-label": "Close the event log", onclick: () => this.toggle(false) }, "×"),
      ),
      this.list,
    );
    for (const e of store.events) this.add(e, false);
    store.on("event", (e) => this.add(e, true));
    store.on("topology", () => this.retime());
  }

  toggle(force?: boolean): void {
    this.open = force ?? !this.open;
    this.el.hidden = !this.open;
    this.onToggle(this.open);
    this.retime();
    if (this.open) {
      this.unread = 0;
      this.severe = false;
      this.onUnread(0, false);
      this.list.scrollTop = this.list.scrollHeight;
    }
  }

  private clear(): void {
    this.list.replaceChildren();
    this.pending.length = 0;
  }

  /** Rewrite server-clock times as wall clock once the offset is known. */
  private retime(): void {
    if (!Number.isFinite(store.clockOffsetS)) return;
    for (const { el, t } of this.pending.splice(0)) {
      const w = wallClock(t);
      setText(el, w.text);
      el.title = w.full;
    }
  }

  private add(e: WireEvent, live: boolean): void {
    this.retime();
    const stick = this.list.scrollHeight - this.list.scrollTop - this.list.clientHeight < 30;
    const w = wallClock(e.t);
    const time = h("span", { class: "ev-time mono", title: w.full }, w.text);
    if (!Number.isFinite(store.clockOffsetS)) this.pending.push({ el: time, t: e.t });
    const axis = e.axis
      ? h("a", { class: "ev-axis", href: `#/axis/${encodeURIComponent(e.axis)}`, title: `Open ${this.axisName(e.axis)}` }, this.axisName(e.axis))
      : h("span", { class: "ev-axis" }, "all");
    this.list.appendChild(
      h(
        "div",
        { class: `event level-${e.level}`, "data-level": e.level },
        time,
        h("span", { class: "ev-level" }, e.level),
        axis,
        h("span", { class: "ev-message" }, e.message),
      ),
    );
    while (this.list.childElementCount > 500) this.list.firstElementChild?.remove();
    if (stick || !live) this.list.scrollTop = this.list.scrollHeight;
    if (!this.open && live && e.level !== "info") {
      this.unread += 1;
      this.severe ||= e.level === "error";
      this.onUnread(this.unread, this.severe);
    }
  }
}

/** "1 error", "2 errors": a count with its noun. */
function countOf(n: number, noun: string): string {
  return `${n} ${noun}${n === 1 ? "" : "s"}`;
}
