// The control lock per axis (server: servotune/hub/control_lock.py, docs/control.md): the badge
// (free / yours / held by NAME) with Take / Request / Release / Force, the Allow/Deny
// prompt, the heartbeats that keep this tab's lease, read-only controls while another
// tab holds the axis (STOP stays live), and hold-to-run jog buttons.
import "./controllock.css";
import { api, reauthenticate, setClientId } from "../api";
import { h, replace, setText, toggleClass } from "../dom";
import type { ControlPrompt, ControlServerMessage, ControlStatus, DeviceDescriptor, Welcome } from "../schema.gen";
import { type WsClient, type WsMessage, wsUrl } from "../ws";
import { showError } from "./feedback";

const CONTROL_TYPES = new Set(["welcome", "control_status", "control_prompt", "control_reply"]);

/** The tab's heartbeats (docs/control.md, "The dead-man"): a dedicated worker sends
 * them on a websocket of its own (``/ws?beat=<client id>``), so a page busy drawing on a
 * loaded machine does not delay them (its timers are not throttled when the tab is
 * hidden either). The page tells the worker it is alive on every tick; the worker reports
 * how long ago that was (``page_age_ms``): a frozen page (it could not release a jog)
 * loses its axes after the server's ``frozen_page_s``. Until the worker's socket is open,
 * or where workers are not available, the page sends the heartbeats itself. */
class Heartbeats {
  private worker: Worker | null = null;
  private timer: number | undefined;
  private running = false;

  constructor(private readonly fallback: () => void) {
    try {
      const source = `
        let ws = null, timer = 0, alive = 0, url = "", holding = false;
        const open = () => {
          const socket = new WebSocket(url);
          ws = socket;
          socket.onclose = () => { if (ws === socket) { ws = null; if (timer) setTimeout(() => timer && !ws && open(), 500); } };
        };
        const beat = () => {
          const age = holding ? Math.max(0, Math.round(performance.now() - alive)) : null;
          if (ws && ws.readyState === 1) ws.send(JSON.stringify({ type: "heartbeat", page_age_ms: age }));
          else postMessage("fallback");
        };
        onmessage = (e) => {
          const m = e.data;
          if (m.kind === "alive") { alive = performance.now(); return; }
          if (m.kind === "hold") { holding = m.on; alive = performance.now(); return; }
          clearInterval(timer); timer = 0;
          if (ws) { const old = ws; ws = null; old.close(); }
          if (m.kind === "start") { url = m.url; alive = performance.now(); open(); timer = setInterval(beat, m.period); }
        };`;
      const url = URL.createObjectURL(new Blob([source], { type: "text/javascript" }));
      this.worker = new Worker(url);
      this.worker.onmessage = () => this.fallback();
    } catch {
      this.worker = null;
    }
  }

  start(periodMs: number, beatUrl: string): void {
    this.stop();
    this.running = true;
    this.fallback();
    if (this.worker) {
      this.worker.postMessage({ kind: "start", url: beatUrl, period: periodMs });
      this.timer = window.setInterval(() => this.worker?.postMessage({ kind: "alive" }), periodMs);
    } else {
      this.timer = window.setInterval(this.fallback, periodMs);
    }
  }

  stop(): void {
    if (!this.running) return;
    this.running = false;
    this.worker?.postMessage({ kind: "stop" });
    window.clearInterval(this.timer);
  }

  /** A hold-to-run control (a jog) is engaged or let go: only while one is, the worker
   * reports the page's age, and a frozen page loses its axes (it could not release). */
  holding(on: boolean): void {
    this.worker?.postMessage({ kind: "hold", on });
  }
}

type Listener = (axis: string | null) => void;

/** This tab's side of the lock: who it is, who holds what, what was asked. */
export class ControlState {
  welcome: Welcome | null = null;
  readonly status = new Map<string, ControlStatus>();
  readonly prompts = new Map<string, ControlPrompt & { until: number }>();
  private ws: WsClient | null = null;
  private readonly listeners = new Set<Listener>();
  private readonly ticker = new Heartbeats(() => this.ws?.send({ type: "heartbeat", page_age_ms: null }));
  private promptHost: HTMLElement | null = null;

  attach(ws: WsClient): void {
    this.ws = ws;
  }

  /** The websocket's state changed: without a connection this tab holds nothing. */
  connection(open: boolean): void {
    if (open) return;
    this.welcome = null;
    setClientId(null);
    this.prompts.clear();
    this.ticker.stop();
    this.renderPrompts();
    this.emit(null);
  }

  /** Handle a control message; false for every other message (the store's). */
  handle(msg: WsMessage): msg is ControlServerMessage {
    if (!CONTROL_TYPES.has(msg.type)) return false;
    const m = msg as ControlServerMessage;
    switch (m.type) {
      case "welcome":
        this.welcome = m;
        setClientId(m.client_id);
        this.syncTicker();
        this.emit(null);
        break;
      case "control_status":
        this.status.set(m.axis, m);
        if (!this.mine(m.axis)) this.prompts.delete(m.axis);
        this.renderPrompts();
        this.emit(m.axis);
        break;
      case "control_prompt":
        this.prompts.set(m.axis, { ...m, until: performance.now() + m.timeout_s * 1000 });
        this.renderPrompts();
        break;
      case "control_reply":
        if (!m.ok && m.action === "force" && m.axis && m.message.includes("password again")) {
          // Forcing a hand-over is a dangerous action: the password again, then retry.
          const axis = m.axis;
          void reauthenticate().then((ok) => {
            if (ok) this.send("force_control", axis);
          });
        } else if (!m.ok && m.action !== "answer") showError(`Control of ${m.axis ?? "axis"}`, new Error(m.message));
        if (m.axis) this.prompts.delete(m.axis);
        this.renderPrompts();
        this.emit(m.axis);
        break;
    }
    return true;
  }

  private held = 0;

  /** A jog button was pressed (+1) or released (-1) in this tab. */
  holdToRun(delta: 1 | -1): void {
    this.held = Math.max(0, this.held + delta);
    this.ticker.holding(this.held > 0);
  }

  mine(axis: string): boolean {
    const holder = this.status.get(axis)?.holder;
    return !!holder && !!this.welcome && holder.client_tag === this.welcome.client_tag;
  }

  /** Another tab (or user) holds it: this tab's controls are read-only. */
  lockedOut(axis: string): boolean {
    const holder = this.status.get(axis)?.holder;
    return !!holder && holder.kind === "user" && !this.mine(axis);
  }

  may(permission: string): boolean {
    return this.welcome?.permissions.includes(permission) ?? false;
  }

  send(type: "take_control" | "request_control" | "release_control" | "force_control", axis: string): void {
    this.ws?.send({ type, axis });
  }

  answer(axis: string, allow: boolean): void {
    this.ws?.send({ type: "answer_control", axis, allow });
    this.prompts.delete(axis);
    this.renderPrompts();
  }

  on(fn: Listener, signal: AbortSignal): void {
    this.listeners.add(fn);
    signal.addEventListener("abort", () => this.listeners.delete(fn), { once: true });
  }

  mountPrompts(parent: HTMLElement): void {
    this.promptHost = h("div", { class: "control-prompts", testid: "control-prompts" });
    parent.appendChild(this.promptHost);
    window.setInterval(() => this.renderPrompts(), 1000);
  }

  /** Heartbeats whenever this tab may hold an axis, not only while it does: a take
   * (explicit, or implicit by a change) must not wait for the first one. */
  private syncTicker(): void {
    const canHold = this.may("control") || this.may("force_control");
    if (canHold && this.welcome) {
      const beatUrl = `${wsUrl()}?beat=${encodeURIComponent(this.welcome.client_id)}`;
      this.ticker.start(this.welcome.heartbeat_period_s * 1000, beatUrl);
    } else this.ticker.stop();
  }

  private emit(axis: string | null): void {
    for (const fn of [...this.listeners]) fn(axis);
  }

  private renderPrompts(): void {
    if (!this.promptHost) return;
    const now = performance.now();
    replace(
      this.promptHost,
      [...this.prompts.values()].map((p) =>
        h(
          "div",
          { class: "control-prompt", role: "alertdialog", testid: `control-prompt-${p.axis}` },
          h("b", null, `${p.requester} (tab ${p.requester_tag}) asks for control of ${p.axis}`),
          h(
            "span",
            { class: "control-prompt-detail" },
            `The axis is stopped before it changes hands. No answer in ${Math.max(0, Math.ceil((p.until - now) / 1000))} s: granted if you were idle ${p.idle_grant_s} s, else denied.`,
          ),
          h("button", { class: "btn", testid: "control-allow", onclick: () => this.answer(p.axis, true) }, "Allow"),
          h("button", { class: "btn warn", testid: "control-deny", onclick: () => this.answer(p.axis, false) }, "Deny"),
        ),
      ),
    );
  }
}

export const control = new ControlState();

interface JogSpec {
  label: string;
  title: string;
  side: "minus" | "plus";
  press: [string, Record<string, number>];
  release: string;
}

/** Hold-to-run jog both ways, from the descriptor's ``jog`` (the device's own way of
 * reversing; the release is a controlled stop that holds). */
function jogSpecs(d: DeviceDescriptor): JogSpec[] {
  const jog = d.jog;
  if (!jog) return [];
  return [
    { label: "◀ jog", title: jog.title, side: "minus", press: [jog.minus.command, jog.minus.args], release: jog.release },
    { label: "jog ▶", title: jog.title, side: "plus", press: [jog.plus.command, jog.plus.args], release: jog.release },
  ];
}

function jogButton(axisId: string, spec: JogSpec, signal: AbortSignal): HTMLButtonElement {
  const button = h("button", { class: "btn jog-hold", title: spec.title, testid: `jog-${spec.side}` }, spec.label);
  let active = false;
  const press = (): void => {
    if (active) return;
    active = true;
    control.holdToRun(1);
    button.classList.add("engaged");
    const [name, args] = spec.press;
    api.command(axisId, name, args).catch((error: unknown) => showError(spec.label, error));
  };
  const release = (): void => {
    if (!active) return;
    active = false;
    control.holdToRun(-1);
    button.classList.remove("engaged");
    api.command(axisId, spec.release, {}).catch((error: unknown) => showError(`${spec.label}: release`, error));
  };
  button.addEventListener("pointerdown", (event) => {
    button.setPointerCapture(event.pointerId);
    press();
  });
  for (const type of ["pointerup", "pointercancel", "lostpointercapture"]) button.addEventListener(type, release);
  button.addEventListener("keydown", (event) => {
    if ((event.key === " " || event.key === "Enter") && !event.repeat) press();
  });
  button.addEventListener("keyup", release);
  button.addEventListener("blur", release);
  window.addEventListener("blur", release, { signal });
  document.addEventListener("visibilitychange", () => document.hidden && release(), { signal });
  signal.addEventListener("abort", release, { once: true });
  return button;
}

/** The control strip of one axis; toggles ``control-locked`` on ``view`` (read-only). */
export function controlStrip(axisId: string, d: DeviceDescriptor, view: HTMLElement, signal: AbortSignal): HTMLElement {
  const badge = h("span", { class: "badge control-badge", testid: "control-badge" });
  const take = h("button", { class: "btn", testid: "control-take", title: "Only this tab may change the axis until you release it", onclick: () => control.send("take_control", axisId) }, "Take control");
  const request = h("button", { class: "btn", testid: "control-request", title: "Ask the holder; they get Allow / Deny", onclick: () => control.send("request_control", axisId) }, "Request control");
  const release = h("button", { class: "btn", testid: "control-release", title: "Stop the axis and let go of it", onclick: () => control.send("release_control", axisId) }, "Release");
  const force = h("button", { class: "btn warn", testid: "control-force", title: "Admin: stop the axis and take it from the holder", onclick: () => control.send("force_control", axisId) }, "Force");
  const pending = h("span", { class: "control-pending", testid: "control-pending" });
  const jogs = jogSpecs(d).map((spec) => jogButton(axisId, spec, signal));
  const jogBox = h("span", { class: "jog-box", testid: "jog-box" }, jogs);
  const el = h("div", { class: "control-strip", testid: "control-strip" }, badge, take, request, release, force, pending, jogBox);

  const sync = (): void => {
    const status = control.status.get(axisId);
    const holder = status?.holder ?? null;
    const mine = control.mine(axisId);
    const locked = control.lockedOut(axisId);
    const canControl = control.may("control") || control.may("force_control");
    let text = "free";
    if (mine) text = "yours";
    else if (holder?.kind === "user") text = `held by ${holder.user}${holder.user === control.welcome?.user ? " (another tab)" : ""}`;
    else if (holder?.kind === "autopilot") text = "autopilot";
    else if (holder?.kind === "server") text = "stopping (start-up)";
    setText(badge, text);
    badge.dataset.state = mine ? "mine" : locked ? "held" : "free";
    badge.title = mine
      ? "This tab controls the axis. Closing it, or losing the connection, stops the axis."
      : locked
        ? "Another tab controls this axis: the controls are read-only here (STOP always works)."
        : "Nobody controls this axis: a change from this tab takes it.";
    take.hidden = mine || locked || !canControl;
    request.hidden = !locked || !canControl;
    release.hidden = !mine;
    force.hidden = !locked || !control.may("force_control");
    const p = status?.pending;
    setText(pending, p ? `${p.user} (tab ${p.client_tag}) asked for control` : "");
    pending.hidden = !p;
    jogBox.hidden = locked || !control.may("move") || jogs.length === 0;
    toggleClass(view, "control-locked", locked);
  };
  sync();
  control.on((axis) => (axis === null || axis === axisId) && sync(), signal);
  return el;
}
