// servotune web client: bootstrap, routing (#/axis/<id>), the frame loop and STOP.
import "./style.css";
import { api } from "./api";
import { h, replace, setText } from "./dom";
import { store } from "./store";
import { AxisView } from "./ui/axis";
import { mountToast, showError } from "./ui/feedback";
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
    };
  }
}

const THEME_KEY = "servotune.theme";
document.documentElement.dataset.theme = localStorage.getItem(THEME_KEY) === "light" ? "light" : "dark";

const app = document.getElementById("app") as HTMLElement;
let view: AxisView | null = null;
let viewAxis: string | null = null;

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
  message: (msg) => store.handle(msg),
  state: (state) => {
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
  toggleTheme: () => {
    const next = document.documentElement.dataset.theme === "light" ? "dark" : "light";
    document.documentElement.dataset.theme = next;
    localStorage.setItem(THEME_KEY, next);
    if (viewAxis) route(true);
  },
});
const nav = new Nav();
const events = new EventLog(
  (n, severe) => topbar.setUnread(n, severe),
  (id) => store.axis(id)?.name ?? id,
  (open) => topbar.eventsButton.classList.toggle("on", open),
);
const connectionText = h("span");
const connection = h("div", { class: "connection-banner", testid: "connection-banner", hidden: true }, h("span", { class: "dot" }), connectionText);
const content = h("main", { class: "content" });
const toastHost = h("div", { class: "toast-host" });
replace(app, topbar.el, h("div", { class: "body" }, nav.el, h("div", { class: "main-col" }, connection, content, events.el)), toastHost);
mountToast(toastHost);
const rigLink = rigNavLink();
nav.el.append(rigLink);

function axisFromHash(): string | null {
  const match = /^#\/axis\/(.+)$/.exec(location.hash);
  return match ? decodeURIComponent(match[1] as string) : null;
}

function route(force = false): void {
  rigLink.classList.toggle("on", location.hash === "#/rig");
  if (location.hash === "#/rig") {
    if (content.querySelector("[data-testid=twin-rig]")) return; // keep the live iframe
    view?.destroy();
    view = null;
    viewAxis = null;
    nav.select("");
    replace(content, rigView());
    document.title = "Rig 3D — servotune";
    return;
  }
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

// Esc stops every axis from anywhere, inputs and dialogs included (capture phase).
window.addEventListener(
  "keydown",
  (event) => {
    if (event.key === "Escape" && !event.repeat) void stopAll("Esc");
  },
  true,
);

// Frame loop: at most one redraw per animation frame, however many messages came.
let waitingTick = 0;
function frame(now: number): void {
  view?.frame(now);
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
ws.start();
