// Audit page: who did what, when, from where, on which axis, and how it ended.
// Admins see everyone's entries; other roles their own (the server filters).
import { ApiError, request } from "../api";
import { h, replace } from "../dom";
import type { AuditEntry, SessionInfo } from "../schema.gen";
import "./auth.css";

function query(filters: Record<string, string>): string {
  const params = new URLSearchParams();
  for (const [key, value] of Object.entries(filters)) if (value.trim()) params.set(key, value.trim());
  const text = params.toString();
  return text ? `?${text}` : "";
}

export function openAudit(session: SessionInfo): void {
  document.querySelector("[data-testid=audit-page]")?.remove();
  const all = session.permissions.includes("audit_all");
  const who = h("input", { placeholder: "who", testid: "audit-who", hidden: !all });
  const action = h("input", { placeholder: "action contains", testid: "audit-action" });
  const axis = h("input", { placeholder: "axis", testid: "audit-axis" });
  const result = h("input", { placeholder: "result (ok, refused, failed…)", testid: "audit-result" });
  const status = h("span", { class: "login-note", testid: "audit-status" });
  const body = h("tbody", { testid: "audit-rows" });
  const filters = (): Record<string, string> => ({ who: who.value, action: action.value, axis: axis.value, result: result.value });
  const load = (): void => {
    status.textContent = "loading …";
    request<AuditEntry[]>("GET", `/api/audit${query(filters())}`)
      .then((rows) => {
        status.textContent = `${rows.length} entr${rows.length === 1 ? "y" : "ies"}`;
        replace(
          body,
          ...rows.map((row) =>
            h(
              "tr",
              { testid: `audit-row-${row.id}` },
              h("td", { class: "mono" }, new Date(row.t_s * 1000).toISOString().replace("T", " ").slice(0, 19)),
              h("td", null, row.who),
              h("td", null, row.action),
              h("td", null, row.axis ?? ""),
              h("td", { class: "mono" }, row.address ?? ""),
              h("td", { class: "mono" }, row.before ?? ""),
              h("td", { class: "mono" }, row.after ?? ""),
              h("td", { class: row.result.split(" ")[0] ?? "" }, row.result),
              h("td", null, row.detail),
            ),
          ),
        );
      })
      .catch((err: unknown) => {
        status.textContent = err instanceof ApiError ? err.detail : String(err);
      });
  };
  for (const input of [who, action, axis, result]) input.addEventListener("change", load);
  const csv = h("button", { class: "btn small", testid: "audit-csv", onclick: () => { location.href = `/api/audit.csv${query(filters())}`; } }, "Export CSV");
  const close = h("button", { class: "btn small", testid: "audit-close", onclick: () => page.remove() }, "Close");
  const page = h(
    "div",
    { class: "audit-page", testid: "audit-page" },
    h("div", { class: "audit-filters" }, h("strong", null, all ? "Audit log" : "My actions"), who, action, axis, result, h("button", { class: "btn small", testid: "audit-refresh", onclick: load }, "Filter"), csv, close, status),
    h(
      "div",
      { class: "audit-table-wrap" },
      h(
        "table",
        { class: "audit-table" },
        h("thead", null, h("tr", null, ...["time (UTC)", "who", "action", "axis", "from", "before", "after", "result", "detail"].map((c) => h("th", null, c)))),
        body,
      ),
    ),
  );
  document.body.appendChild(page);
  load();
}
