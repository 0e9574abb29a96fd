// servotune web client: bootstrap, routing (#/axis/<id>), the frame loop and STOP.
import "./style.css";
import "./screens.css";
import { api } from "./api";
import { h, replace, setText } from "./dom";
import { store } from "./store";
import { AxisView } from "./ui/axis";
import { control } from "./ui/controllock";
import { mountToast, showError } from "./ui/feedback";
import { authGate } from "./ui/login";
import { mountUserMenu } from "./ui/usermenu";
import { OverviewView } from "./ui/overview";
import type { PlotStack } from "./ui/plots";
import { benchDraw, type Lab, type LabOptions, mountLab } from "./ui/scopelab";
import { EventLog, Nav, TopBar, wsText } from "./ui/shell";
import { rigNavLink, rigView } from "./ui/twin";
import { WsClient, wsUrl } from "./ws";

declare global {
  interface Window {
    __servotune: {
      samplesReceived(axisId: string): number;
      lastT(axisId: string): number;
      wsState(): string;
      currentAxis(): string | null;
      scope(): PlotStack | null;
      lab(opts: LabOptions): Lab;
      benchDraw(runs?: number): ReturnType<typeof benchDraw>;
    };
  }
}

const THEME_KEY = "servotune.theme";
// The user's choice if they made one, else the OS preference (and follow it while unchosen).
const prefersLight = window.matchMedia?.("(prefers-color-scheme: light)");
function initialTheme(): "light" | "dark" {
  const saved = localStorage.getItem(THEME_KEY);
  if (saved === "light" || saved === "dark") return saved;
  return prefersLight?.matches ? "light" : "dark";
}
document.documentElement.dataset.theme = initialTheme();
prefersLight?.addEventListener("change", () => {
  if (localStorage.getItem(THEME_KEY)) return;
  document.documentElement.dataset.theme = initialTheme();
  if (viewAxis || overview) route(true);
});

const app = document.getElementById("app") as HTMLElement;
let view: AxisView | null = null;
let viewAxis: string | null = null;
let overview: OverviewView | null = null;

async function stopAll(source: string): Promise<void> {
  topbar.stopFeedback("STOP sent …", true);
  view?.stopped();
  try {
    const result = await api.stopAll();
    if (result.failed?.length) {
      topbar.stopFeedback(`STOP failed on ${result.failed.join(", ")}`, false);
      showError("STOP", new Error(`stop failed on ${result.failed.join(", ")}`));
    } else topbar.stopFeedback(`STOPPED (${source})`, true);
  } catch (error) {
    topbar.stopFeedback("STOP not confirmed", false);
    showError("STOP all axes", error);
  }
}

const ws = new WsClient(wsUrl(), {
  message: (msg) => {
    if (!control.handle(msg)) store.handle(msg);
  },
  state: (state) => {
    control.connection(state.kind === "open");
    store.ws = state;
    topbar.setWs(state);
    document.body.dataset.ws = state.kind;
    connection.hidden = state.kind === "open";
    setText(connectionText, state.kind === "waiting" ? `No connection to the servotune server (${state.reason}) — ${wsText(state)}. Live values below are stale.` : "Connecting to the servotune server …");
    store.emit("ws", state);
  },
});

const topbar = new TopBar({
  stop: () => void stopAll("button"),
  toggleEvents: () => events.toggle(),
  retry: () => ws.retryNow(),
  toggleNav: () => document.body.classList.toggle("nav-open"),
  toggleTheme: () => {
    const next = document.documentElement.dataset.theme === "light" ? "dark" : "light";
    document.documentElement.dataset.theme = next;
    localStorage.setItem(THEME_KEY, next);
    if (viewAxis || overview) route(true);
  },
});
const nav = new Nav();
const events = new EventLog(
  (n, severe) => topbar.setUnread(n, severe),
  (id) => store.axis(id)?.name ?? id,
  (open) => topbar.eventsButton.classList.toggle("on", open),
);
nav.onOpenEvents = () => events.toggle(true);
const connectionText = h("span");
const connection = h("div", { class: "connection-banner", testid: "connection-banner", hidden: true }, h("span", { class: "dot" }), connectionText);
const content = h("main", { class: "content" });
const toastHost = h("div", { class: "toast-host" });
replace(app, topbar.el, h("div", { class: "body" }, nav.el, h("div", { class: "main-col" }, connection, content, events.el)), toastHost);
mountToast(toastHost);
control.mountPrompts(document.body);
const rigLink = rigNavLink();
nav.el.append(rigLink);

function axisFromHash(): string | null {
  const match = /^#\/axis\/(.+)$/.exec(location.hash);
  return match ? decodeURIComponent(match[1] as string) : null;
}

function route(force = false): void {
  document.body.classList.remove("nav-open");
  rigLink.classList.toggle("on", location.hash === "#/rig");
  if (location.hash === "#/rig") {
    overview?.destroy();
    overview = null;
    if (content.querySelector("[data-testid=twin-rig]")) return; // keep the live iframe
    view?.destroy();
    view = null;
    viewAxis = null;
    nav.select("");
    replace(content, rigView());
    document.title = "Rig 3D — servotune";
    return;
  }
  if (location.hash === "#/overview") {
    view?.destroy();
    view = null;
    viewAxis = null;
    nav.select("");
    if (overview && !force) return;
    overview?.destroy();
    overview = new OverviewView();
    replace(content, overview.el);
    document.title = "Rig overview — servotune";
    return;
  }
  overview?.destroy();
  overview = null;
  const wanted = axisFromHash();
  const axis = store.axes.find((a) => a.id === wanted) ?? store.axes[0];
  if (!axis) {
    view?.destroy();
    view = null;
    viewAxis = null;
    replace(content, h("div", { class: "empty-state" }, store.ws.kind === "open" ? "No axes: start servotune with at least one --link." : "Waiting for the servotune server …"));
    return;
  }
  if (wanted !== axis.id) history.replaceState(null, "", `#/axis/${encodeURIComponent(axis.id)}`);
  nav.select(axis.id);
  if (!force && viewAxis === axis.id && view) return;
  view?.destroy();
  viewAxis = axis.id;
  view = new AxisView(axis);
  replace(content, view.el);
  document.title = `${axis.name} — servotune`;
}

window.addEventListener("hashchange", () => route());
store.on("topology", () => {
  // A new server (or new config) may list other axes; the current view stays if still there.
  const still = viewAxis && store.axes.some((a) => a.id === viewAxis);
  route(!still);
});

// Esc stops every axis from anywhere, inputs included (capture phase), except in an open
// dialog: there Esc closes the dialog only (its own handler), so dismissing a
// confirmation never fires a global STOP that unpowers the SLAP2 axes.
window.addEventListener(
  "keydown",
  (event) => {
    if (event.key !== "Escape" || event.repeat) return;
    if (document.querySelector('[aria-modal="true"]')) return;
    void stopAll("Esc");
  },
  true,
);

// What STOP does on each device family present (descriptor ``stop``), shown at the button.
store.on("topology", () => {
  const firstOfDevice = new Map<string, string>();
  for (const a of store.axes) if (!firstOfDevice.has(a.device)) firstOfDevice.set(a.device, a.id);
  void Promise.all(
    [...firstOfDevice.values()].map((id) => store.descriptor(id, () => api.descriptor(id)).then((d) => d.stop.summary, () => null)),
  ).then((summaries) => topbar.setStopEffects(summaries.filter((s): s is string => s !== null)));
});

// Frame loop: at most one redraw per animation frame, however many messages came.
let waitingTick = 0;
function frame(now: number): void {
  view?.frame(now);
  overview?.frame(now);
  if (store.ws.kind === "waiting" && now - waitingTick > 250) {
    waitingTick = now;
    topbar.setWs(store.ws);
    setText(connectionText, `No connection to the servotune server (${store.ws.reason}) — ${wsText(store.ws, now)}. Live values below are stale.`);
  }
  requestAnimationFrame(frame);
}
requestAnimationFrame(frame);

window.__servotune = {
  samplesReceived: (axisId) => store.buffers.get(axisId)?.samplesReceived ?? 0,
  lastT: (axisId) => {
    const t = store.buffers.get(axisId)?.lastT;
    return t === undefined || Number.isNaN(t) ? 0 : t;
  },
  wsState: () => store.ws.kind,
  currentAxis: () => viewAxis,
  scope: () => view?.scope ?? null,
  lab: (opts) => mountLab(opts),
  benchDraw: (runs) => benchDraw(runs),
};

// REST first (the page works even before the websocket is up), then the stream.
route();
Promise.all([api.axes(), api.links()])
  .then(([axes, links]) => {
    if (store.axes.length) return; // hello was faster
    store.axes = axes;
    store.links = links;
    store.emit("topology", undefined);
  })
  .catch(() => {
    /* the websocket's hello will bring the topology */
  });
// Exposed mode: nothing streams before a login (ui/login.ts shows the login page).
void authGate().then((session) => {
  if (session === "login") return;
  if (session) mountUserMenu(topbar.el, session);
  control.attach(ws);
  ws.start();
});
