// REST calls. Every 4xx/5xx body is {detail, field}; ApiError carries both.
import type {
  AxisInfo,
  AxisState,
  CommandResult,
  ConsoleReply,
  DeviceDescriptor,
  LinkInfo,
} from "./wire.gen";

export class ApiError extends Error {
  constructor(
    readonly status: number,
    readonly detail: string,
    readonly field: string | null,
  ) {
    super(detail);
    this.name = "ApiError";
  }
}

function detailOf(body: unknown, status: number, statusText: string): { detail: string; field: string | null } {
  if (body && typeof body === "object" && "detail" in body) {
    const b = body as { detail: unknown; field?: unknown };
    const field = typeof b.field === "string" ? b.field : null;
    if (typeof b.detail === "string") return { detail: b.detail, field };
    if (Array.isArray(b.detail)) {
      // FastAPI's default validation body, should the server not translate it.
      const first = b.detail[0] as { msg?: string; loc?: unknown[] } | undefined;
      const loc = first?.loc?.filter((p) => p !== "body").join(".") ?? "";
      return { detail: `${loc ? loc + ": " : ""}${first?.msg ?? "invalid request"}`, field: loc || field };
    }
  }
  return { detail: `HTTP ${status} ${statusText}`.trim(), field: null };
}

async function request<T>(method: string, path: string, body?: unknown): Promise<T> {
  let response: Response;
  try {
    response = await fetch(path, {
      method,
      headers: body === undefined ? {} : { "Content-Type": "application/json" },
      body: body === undefined ? null : JSON.stringify(body),
    });
  } catch (error) {
    throw new ApiError(0, `server unreachable: ${(error as Error).message}`, null);
  }
  const text = await response.text();
  let parsed: unknown = null;
  if (text) {
    try {
      parsed = JSON.parse(text);
    } catch {
      parsed = null;
    }
  }
  if (!response.ok) {
    const { detail, field } = detailOf(parsed, response.status, response.statusText);
    throw new ApiError(response.status, detail, field);
  }
  return parsed as T;
}

const axis = (id: string): string => `/api/axes/${encodeURIComponent(id)}`;

export const api = {
  axes: () => request<AxisInfo[]>("GET", "/api/axes"),
  links: () => request<LinkInfo[]>("GET", "/api/links"),
  descriptor: (id: string) => request<DeviceDescriptor>("GET", `${axis(id)}/descriptor`),
  readParams: (id: string) => request<Record<string, number>>("GET", `${axis(id)}/params`),
  writeParams: (id: string, values: Record<string, number>) =>
    request<Record<string, number>>("PATCH", `${axis(id)}/params`, values),
  state: (id: string) => request<AxisState>("GET", `${axis(id)}/state`),
  command: (id: string, command: string, args: Record<string, number>) =>
    request<CommandResult>("POST", `${axis(id)}/commands`, { command, ...args }),
  console: (id: string, line: string) => request<ConsoleReply>("POST", `${axis(id)}/console`, { line }),
  stopAll: () => request<{ failed: string[] }>("POST", "/api/stop"),
};
