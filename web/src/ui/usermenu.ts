// User menu (name, role, audit page, log out) and read-only controls for what the
// role may not do. The server refuses such calls anyway (403); greying the controls
// out only saves the user a refused click. STOP stays live for everyone.
import { request } from "../api";
import { h } from "../dom";
import { openAudit } from "./audit";
import type { SessionInfo } from "../schema.gen";
import "./auth.css";

/** Controls (by data-testid) and the permission each needs. Stop-group buttons and
 *  aborts are never listed: stopping is allowed to every logged-in user. */
const NEEDS: [RegExp, string][] = [
  [/^cmd-(save_eeprom|save_flash)$/, "persist"],
  [/^ps-persist$/, "persist"],
  [/^bench-limit(s-save|-.+)$/, "limits"],
  [/^(cmd-|jog-|run-state-)/, "move"],
  [/^param-.+-(input|slider|bit-.+)$/, "tune"],
  [/^(reset-restore|overwrite-write-.+)$/, "tune"],
  [/^at-(identify|accept|revert|gain-.+|direction|test)$/, "autotune"],
  [/^bench-(run|import|import-file|note|kind|distance|velocity|pwm|duration_s)$/, "bench"],
  [/^bench-run-(delete|baseline)-.+$/, "bench"],
  [/^console-(input|send|example-.+)$/, "console"],
  [/^(ps-save|ps-restore|ps-name|ps-note|ps-delete-.+)$/, "param_sets"],
];
const ALWAYS_LIVE = /^(stop-all|cmd-(stop|power_off|jog_stop|halt|emergency_stop|decelerate|abort_calibration)|abort-.+)$/;

function neededPermission(testid: string): string | null {
  if (ALWAYS_LIVE.test(testid)) return null;
  for (const [pattern, permission] of NEEDS) if (pattern.test(testid)) return permission;
  return null;
}

function applyReadOnly(root: ParentNode, allowed: Set<string>): void {
  for (const el of Array.from(root.querySelectorAll<HTMLElement>("[data-testid]"))) {
    const needed = neededPermission(el.dataset.testid ?? "");
    if (needed === null || allowed.has(needed)) continue;
    const control = el instanceof HTMLButtonElement || el instanceof HTMLInputElement || el instanceof HTMLSelectElement || el instanceof HTMLTextAreaElement;
    // Only when it changes: every write is a mutation record the observer would see.
    if (control && !el.disabled) el.disabled = true;
    if (!el.hasAttribute("data-readonly-control")) {
      el.setAttribute("data-readonly-control", needed);
      el.title = `Your role may not do this (needs “${needed}”)`;
    }
  }
}

/** Keep controls the role may not use disabled, also those the UI creates later. */
export function enforceReadOnly(session: SessionInfo): void {
  const allowed = new Set(session.permissions);
  if (["move", "tune", "bench", "autotune", "console", "param_sets", "persist", "limits"].every((p) => allowed.has(p))) return;
  document.body.dataset.role = session.role ?? "";
  let pending = false;
  const observer = new MutationObserver(() => {
    if (pending) return;
    pending = true;
    // A task, not a microtask: the page's own updates finish first and a burst of
    // mutations costs one pass.
    setTimeout(() => {
      pending = false;
      applyReadOnly(document, allowed);
    }, 0);
  });
  observer.observe(document.body, { childList: true, subtree: true, attributes: true, attributeFilter: ["disabled"] });
  applyReadOnly(document, allowed);
}

/** The user menu, appended to ``host`` (the top bar). */
export function mountUserMenu(host: HTMLElement, session: SessionInfo): HTMLElement {
  const name = session.mode === "local" ? "local" : (session.user ?? "?");
  const panel = h("div", { class: "user-menu-panel", testid: "user-menu-panel", hidden: true });
  const toggle = h(
    "button",
    { class: "btn ghost", testid: "user-menu", title: "Your account", onclick: () => (panel.hidden = !panel.hidden) },
    h("span", { testid: "user-name" }, name),
    h("span", { class: "role", testid: "user-role" }, session.role ?? ""),
  );
  const canChange = session.permissions.includes("move");
  if (!canChange) panel.append(h("div", { class: "readonly-note", testid: "readonly-note" }, "View only: you can watch and STOP, not move."));
  panel.append(
    h("button", { class: "btn small", testid: "open-audit", onclick: () => { panel.hidden = true; openAudit(session); } },
      session.permissions.includes("audit_all") ? "Audit log" : "My actions"),
  );
  if (session.mode === "exposed") {
    panel.append(
      h("button", {
        class: "btn small",
        testid: "logout",
        onclick: () => void request<null>("POST", "/api/auth/logout").finally(() => location.reload()),
      }, "Log out"),
    );
  }
  const menu = h("div", { class: session.mode === "local" ? "user-menu local" : "user-menu" }, toggle, panel);
  // Before the STOP button: STOP stays the right-most, always-visible element.
  const stop = host.querySelector(".stop-all");
  if (stop) host.insertBefore(menu, stop);
  else host.appendChild(menu);
  document.addEventListener("click", (event) => {
    if (!menu.contains(event.target as Node)) panel.hidden = true;
  });
  enforceReadOnly(session);
  return menu;
}
