// The 3D twin of the axes (viser, served by the dashboard at /twin/), as iframes.
//
// On an axis page the user picks "3D off", "3D tab" (replaces the plots) or "3D beside"
// (a panel next to the plots); the choice is remembered in localStorage. The iframe of
// one axis is /twin/axis/<id>, which the server redirects to viser's page with a camera
// that frames that axis (viser shows one scene to every viewer; the camera is per
// viewer). The rig view (#/rig) is /twin/ itself: every axis of every link side by side.
// An iframe exists only while it is visible: the twin's server side does no work when
// nobody is looking, and a hidden WebGL canvas would cost the browser for nothing.
import { h, replace, toggleClass } from "../dom";
import "./twin.css";

export type TwinMode = "off" | "tab" | "beside";
const MODE_KEY = "servotune.twin";

function storedMode(): TwinMode {
  try {
    const value = localStorage.getItem(MODE_KEY);
    return value === "tab" || value === "beside" ? value : "off";
  } catch {
    return "off";
  }
}

function frame(src: string, title: string): HTMLIFrameElement {
  return h("iframe", { src, title, testid: "twin-frame", loading: "eager", allow: "fullscreen" });
}

/** The 3D choice and panel of one axis page. ``mount`` it into the scope area. */
export class TwinPanel {
  readonly el: HTMLElement;
  readonly toggle: HTMLElement;
  private mode: TwinMode = storedMode();
  private host: HTMLElement | null = null;
  private readonly buttons: Record<TwinMode, HTMLButtonElement>;

  constructor(private readonly axisId: string, private readonly axisName: string) {
    this.el = h("div", { class: "twin-panel", testid: "twin-panel" });
    const button = (mode: TwinMode, label: string, title: string): HTMLButtonElement =>
      h("button", { class: "seg-btn", testid: `twin-${mode}`, title, onclick: () => this.setMode(mode) }, label);
    this.buttons = {
      off: button("off", "2D", "Plots only"),
      tab: button("tab", "3D", "3D twin instead of the plots"),
      beside: button("beside", "2D+3D", "3D twin beside the plots"),
    };
    this.toggle = h(
      "div",
      { class: "seg view-toggle twin-toggle", role: "group", "aria-label": "3D twin" },
      this.buttons.off,
      this.buttons.tab,
      this.buttons.beside,
    );
  }

  /** Put the panel into the scope area (whose layout it switches). */
  mount(scopeArea: HTMLElement): void {
    this.host = scopeArea;
    scopeArea.append(this.el);
    this.sync();
  }

  setMode(mode: TwinMode): void {
    this.mode = mode;
    try {
      localStorage.setItem(MODE_KEY, mode);
    } catch {
      /* private mode: not remembered */
    }
    this.sync();
  }

  private sync(): void {
    for (const [mode, btn] of Object.entries(this.buttons)) {
      toggleClass(btn, "on", mode === this.mode);
      btn.setAttribute("aria-pressed", mode === this.mode ? "true" : "false");
    }
    if (this.host) this.host.dataset.twin = this.mode;
    if (this.mode === "off") replace(this.el);
    else if (!this.el.querySelector("iframe")) {
      replace(
        this.el,
        frame(`/twin/axis/${encodeURIComponent(this.axisId)}`, `3D twin of ${this.axisName}`),
        h("a", { class: "twin-rig-link", href: "#/rig", title: "Every axis of every link" }, "rig view"),
      );
    }
  }
}

/** The rig view: every axis of every link in one 3D scene. */
export function rigView(): HTMLElement {
  return h(
    "div",
    { class: "twin-rig-view", testid: "twin-rig" },
    h("div", { class: "twin-rig-title" }, "Rig — 3D twin of every axis (drag to orbit, scroll to zoom)"),
    h("div", { class: "twin-rig" }, frame("/twin/", "3D twin of the rig")),
  );
}

/** The nav entry of the rig view. */
export function rigNavLink(): HTMLAnchorElement {
  return h("a", { class: "nav-rig", href: "#/rig", testid: "nav-rig" }, "Rig 3D view");
}
