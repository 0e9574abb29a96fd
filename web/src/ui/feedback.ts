// Error toast (data-testid="error-message" always holds the latest error) and the
// confirmation dialog used by commands that carry ``confirm`` text.
import { ApiError } from "../api";
import { h, setText } from "../dom";
import { store } from "../store";

let toast: HTMLElement | null = null;
let toastText: HTMLElement | null = null;
let toastContext: HTMLElement | null = null;
let hideTimer: number | undefined;

export function mountToast(parent: HTMLElement): void {
  toastContext = h("div", { class: "toast-context" });
  toastText = h("div", { class: "toast-text", testid: "error-message", role: "alert" });
  toast = h(
    "div",
    { class: "toast", hidden: true },
    h("div", { class: "toast-icon" }, "!"),
    h("div", { class: "toast-body" }, toastContext, toastText),
    h("button", { class: "toast-close", title: "Dismiss", onclick: hideToast }, "×"),
  );
  parent.appendChild(toast);
}

export function hideToast(): void {
  if (toast) toast.hidden = true;
}

/** Describe an error for a user: the server's detail as is, with its HTTP class. */
export function errorText(error: unknown): string {
  if (error instanceof ApiError) return error.detail;
  if (error instanceof Error) return error.message;
  return String(error);
}

export function statusLabel(error: unknown): string {
  if (!(error instanceof ApiError)) return "error";
  // A failed measurement is not a refusal (the device refused nothing); every other
  // 409 says in its detail who refused and why (the device, a busy axis, ...).
  if (error.kind === "measurement") return "measurement failed";
  switch (error.status) {
    case 0:
      return "no connection";
    case 409:
      return "refused";
    case 422:
      return "invalid value";
    case 503:
      return "link down";
    case 504:
      return "no answer";
    default:
      return `HTTP ${error.status}`;
  }
}

export function showError(context: string, error: unknown): string {
  const text = errorText(error);
  if (toast && toastText && toastContext) {
    setText(toastContext, `${context} — ${statusLabel(error)}`);
    toastText.textContent = text;
    toast.hidden = false;
    toast.classList.remove("flash");
    void toast.offsetWidth;
    toast.classList.add("flash");
    window.clearTimeout(hideTimer);
    hideTimer = window.setTimeout(hideToast, 12000);
  }
  store.emit("error", text);
  return text;
}

/** Ask before a command that needs it; resolves true on OK. Esc cancels (the dialog only: main.ts does not STOP while a dialog is open). */
export function confirmDialog(title: string, text: string, okLabel: string): Promise<boolean> {
  return new Promise((resolve) => {
    const previous = document.activeElement as HTMLElement | null;
    let done = false;
    const finish = (ok: boolean): void => {
      if (done) return;
      done = true;
      overlay.remove();
      document.removeEventListener("keydown", onKey, true);
      previous?.focus?.();
      resolve(ok);
    };
    const onKey = (event: KeyboardEvent): void => {
      if (event.key === "Escape") finish(false);
      else if (event.key === "Enter" && document.activeElement === ok) {
        event.preventDefault();
        finish(true);
      } else if (event.key === "Tab") {
        // Keep focus inside the dialog.
        event.preventDefault();
        (document.activeElement === ok ? cancel : ok).focus();
      }
    };
    const ok = h("button", { class: "btn primary", testid: "confirm-ok", onclick: () => finish(true) }, okLabel);
    const cancel = h("button", { class: "btn", testid: "confirm-cancel", onclick: () => finish(false) }, "Cancel");
    const overlay = h(
      "div",
      { class: "modal-overlay", testid: "confirm-dialog" },
      h(
        "div",
        { class: "modal", role: "dialog", "aria-modal": "true", "aria-label": title },
        h("div", { class: "modal-title" }, h("span", { class: "modal-warn" }, "⚠"), title),
        h("div", { class: "modal-text" }, text),
        h("div", { class: "modal-actions" }, cancel, ok),
      ),
    );
    overlay.addEventListener("mousedown", (event) => {
      if (event.target === overlay) finish(false);
    });
    document.addEventListener("keydown", onKey, true);
    document.body.appendChild(overlay);
    cancel.focus();
  });
}
