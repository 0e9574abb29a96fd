// Login page (exposed mode) and the password re-entry prompt for dangerous admin actions.
// The server decides everything: this page only collects the password and shows why
// a login failed. The session lives in an HttpOnly cookie the page cannot read.
import { ApiError, request, setCsrfToken, setReauthHandler } from "../api";
import { h, replace } from "../dom";
import type { SessionInfo } from "../schema.gen";
import "./auth.css";

export function getSession(): Promise<SessionInfo> {
  return request<SessionInfo>("GET", "/api/auth/session");
}

/** Resolves with the session when the page may start (null: server unreachable, start
 *  anyway and let the websocket retry); in exposed mode without a login it shows the
 *  login page and resolves "login" (the page reloads after a successful login). */
export async function authGate(): Promise<SessionInfo | "login" | null> {
  let session: SessionInfo;
  try {
    session = await getSession();
  } catch {
    return null; // server unreachable: the websocket banner says so
  }
  setCsrfToken(session.csrf_token);
  setReauthHandler(reauthPrompt);
  if (session.mode === "exposed" && session.user === null) {
    showLoginPage();
    return "login";
  }
  return session;
}

function showLoginPage(): void {
  const user = h("input", { name: "username", autocomplete: "username", testid: "login-user", required: true });
  const password = h("input", { name: "password", type: "password", autocomplete: "current-password", testid: "login-password", required: true });
  const error = h("div", { class: "login-error", testid: "login-error", "aria-live": "assertive" });
  const submit = h("button", { class: "btn primary", type: "submit", testid: "login-submit" }, "Log in");
  const form = h(
    "form",
    { class: "login-card", testid: "login-form" },
    h("h1", null, "servotune"),
    h("div", { class: "login-note" }, "This lab's motors are behind a login. Ask the lab's admin for an account."),
    h("label", null, "User name", user),
    h("label", null, "Password", password),
    error,
    submit,
  );
  form.addEventListener("submit", (event) => {
    event.preventDefault();
    submit.disabled = true;
    error.textContent = "";
    request<SessionInfo>("POST", "/api/auth/login", { user: user.value, password: password.value })
      .then(() => location.reload())
      .catch((err: unknown) => {
        submit.disabled = false;
        password.value = "";
        error.textContent = err instanceof ApiError ? err.detail : String(err);
      });
  });
  const page = h("div", { class: "login-page", testid: "login-page" }, form);
  document.body.appendChild(page);
  user.focus();
}

/** Ask for the password again (dangerous admin action after 5 minutes); true when accepted. */
export function reauthPrompt(): Promise<boolean> {
  return new Promise((resolve) => {
    const password = h("input", { type: "password", autocomplete: "current-password", testid: "reauth-password" });
    const error = h("div", { class: "login-error", testid: "reauth-error" });
    const cancel = h("button", { class: "btn", type: "button", testid: "reauth-cancel" }, "Cancel");
    const ok = h("button", { class: "btn primary", type: "submit", testid: "reauth-ok" }, "Confirm");
    const form = h(
      "form",
      { class: "login-card" },
      h("h1", null, "Confirm with your password"),
      h("div", { class: "login-note" }, "This action changes users, the safety envelope or the device's permanent memory."),
      h("label", null, "Password", password),
      error,
      h("div", { style: "display:flex;gap:8px;justify-content:flex-end" }, cancel, ok),
    );
    const overlay = h("div", { class: "login-page", testid: "reauth-dialog" }, form);
    const done = (value: boolean): void => {
      overlay.remove();
      resolve(value);
    };
    cancel.addEventListener("click", () => done(false));
    form.addEventListener("submit", (event) => {
      event.preventDefault();
      request<null>("POST", "/api/auth/reauth", { password: password.value }, true)
        .then(() => done(true))
        .catch((err: unknown) => {
          password.value = "";
          error.textContent = err instanceof ApiError ? err.detail : String(err);
        });
    });
    replace(overlay, form);
    document.body.appendChild(overlay);
    password.focus();
  });
}
