// REST calls. Every 4xx/5xx body is {detail, field}; ApiError carries both.
import type {
  AxisInfo,
  AxisState,
  BenchInfo,
  BenchRun,
  BenchRunDetail,
  BenchLimits,
  BenchTestRequest,
  AutoTuneDecision,
  AutoTuneProposal,
  AutoTuneRequest,
  AutoTuneResult,
  AutoTuneSession,
  AutoTuneStopped,
  CommandResult,
  ConsoleReply,
  DeviceDescriptor,
  LinkInfo,
  ParamSet,
  ParamSetComparison,
  RunMetrics,
  SavedSet,
  SaveSetRequest,
  SessionInfo,
  StopResult,
} from "./schema.gen";

// REST bodies generated from server/servotune/schema/, re-exported for the views.
export type {
  AutoTuneDecision,
  AutoTuneGoal,
  AutoTuneProposal,
  AutoTuneRecommendation,
  AutoTuneRequest,
  AutoTuneResult,
  AutoTuneSession,
  AutoTuneSide,
  AutoTuneState,
  AutoTuneStopped,
  AutoTuneTestKind,
  AutoTuneVerdict,
  MarginReport,
  BenchInfo,
  BenchKind,
  BenchRun,
  BenchRunDetail,
  BenchLimits,
  BenchTestRequest,
  MarginPreset,
  MarginTarget,
  ParamSet,
  ParamSetComparison,
  RunMetrics,
  RunQuality,
  RunStatus,
  SavedSet,
} from "./schema.gen";

export class ApiError extends Error {
  constructor(
    readonly status: number,
    readonly detail: string,
    readonly field: string | null,
    /** "measurement": a measurement could not support its result; nothing was refused. */
    readonly kind: string | null = null,
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

// CSRF token for every state-changing call (servotune/auth/middleware.py). It comes
// from GET /api/auth/session and changes at login (ui/login.ts sets the new one).
let csrfToken: string | null = null;
export function setCsrfToken(token: string): void {
  csrfToken = token;
}
async function csrf(): Promise<string> {
  if (csrfToken === null) {
    const response = await fetch("/api/auth/session", { credentials: "same-origin" });
    csrfToken = ((await response.json()) as SessionInfo).csrf_token;
  }
  return csrfToken;
}

/** This tab's websocket client id (``welcome``): the control lock knows the tab by it. */
let clientId: string | null = null;

export function setClientId(id: string | null): void {
  clientId = id;
}

/** A call the server may refuse until the user confirms (409 naming ``confirm_unstable``:
 * gains the identified plant predicts unstable). The user is shown the server's reason
 * and asked; only a yes sends the call again with the confirmation. */
export async function confirmed<T>(call: (confirm: string) => Promise<T>): Promise<T> {
  try {
    return await call("");
  } catch (error) {
    if (!(error instanceof ApiError) || error.status !== 409 || error.field !== "confirm_unstable") throw error;
    if (!window.confirm(`Predicted unstable.\n\n${error.detail}\n\nWrite them anyway?`)) throw new ApiError(409, `not written: ${error.detail}`, "confirm_unstable");
    return call("?confirm_unstable=true");
  }
}

/** The headers a state-changing call sends that ``request`` does not build itself (a
 * multipart upload): the CSRF token and this tab's client id. */
export async function writeHeaders(): Promise<Record<string, string>> {
  const headers: Record<string, string> = { "X-CSRF-Token": await csrf() };
  if (clientId) headers["X-Servotune-Client"] = clientId;
  return headers;
}

export async function request<T>(method: string, path: string, body?: unknown, retried = false): Promise<T> {
  let response: Response;
  const headers: Record<string, string> = body === undefined ? {} : { "Content-Type": "application/json" };
  if (clientId) headers["X-Servotune-Client"] = clientId;
  try {
    if (method !== "GET" && method !== "HEAD") headers["X-CSRF-Token"] = await csrf();
    response = await fetch(path, {
      method,
      headers,
      credentials: "same-origin",
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
    // A dangerous admin action after 5 min asks for the password again (ui/login.ts).
    if (response.status === 401 && detail.includes("password again") && reauthHandler && !retried) {
      if (await reauthHandler()) return request<T>(method, path, body, true);
    }
    const kind = body && typeof body === "object" && typeof (body as { kind?: unknown }).kind === "string" ? (body as { kind: string }).kind : null;
    throw new ApiError(response.status, detail, field, kind);
  }
  return parsed as T;
}

let reauthHandler: (() => Promise<boolean>) | null = null;
export function setReauthHandler(handler: () => Promise<boolean>): void {
  reauthHandler = handler;
}

/** Ask for the password again (the page's prompt); true when it was accepted. The
 * websocket's forced hand-over follows the same rule as REST (docs/remote-lab.md). */
export async function reauthenticate(): Promise<boolean> {
  return reauthHandler ? reauthHandler() : false;
}

// --- test bench (server/servotune/api/bench_routes.py) ---

// BenchRun, BenchRunDetail, RunMetrics: generated (schema.gen.ts, servotune/schema/).

// --- parameter sets (server/servotune/api/param_set_routes.py) ---

// --- auto-tune (server/servotune/api/autotune_routes.py) ---

// AutoTuneRequest, AutoTuneProposal, AutoTuneResult, AutoTuneStopped, AutoTuneSession:
// generated (schema.gen.ts, servotune/schema/). Gains are by the descriptor's
// parameter names, whatever the device.

/** Gains by parameter name (the descriptor's: kp, ki, kd for a SLAP2, kabh_k, ... for a Z1100). */
export type GainSet = Record<string, number>;

/** What ``POST .../autotune/accept`` answers: the verification's result, or how it ended
 * early when the user pressed STOP. */
export type AutoTuneAccepted = AutoTuneResult | AutoTuneStopped;

/** The verification's measured metrics, null when its run has none (the server sends {}). */
export function measuredMetrics(measured: AutoTuneResult["measured"] | undefined): RunMetrics | null {
  return measured && "step" in measured ? (measured as RunMetrics) : null;
}

const axis = (id: string): string => `/api/axes/${encodeURIComponent(id)}`;
/** Set names may hold '#', ' ', '+', ... : always one encoded path segment. */
const paramSet = (id: string, name: string): string => `${axis(id)}/param-sets/${encodeURIComponent(name)}`;

export const api = {
  axes: () => request<AxisInfo[]>("GET", "/api/axes"),
  links: () => request<LinkInfo[]>("GET", "/api/links"),
  descriptor: (id: string) => request<DeviceDescriptor>("GET", `${axis(id)}/descriptor`),
  readParams: (id: string) => request<Record<string, number>>("GET", `${axis(id)}/params`),
  writeParams: (id: string, values: Record<string, number>) =>
    confirmed((confirm) => request<Record<string, number>>("PATCH", `${axis(id)}/params${confirm}`, values)),
  state: (id: string) => request<AxisState>("GET", `${axis(id)}/state`),
  command: (id: string, command: string, args: Record<string, number>) =>
    request<CommandResult>("POST", `${axis(id)}/commands`, { command, ...args }),
  console: (id: string, line: string) => request<ConsoleReply>("POST", `${axis(id)}/console`, { line }),
  stopAll: () => request<StopResult>("POST", "/api/stop"),
  bench: (id: string) => request<BenchInfo>("GET", `${axis(id)}/bench`),
  setBenchLimits: (id: string, limits: BenchLimits) => request<BenchLimits>("PUT", `${axis(id)}/bench/limits`, limits),
  startRun: (id: string, test: BenchTestRequest) => request<BenchRun>("POST", `${axis(id)}/bench/runs`, test),
  runs: (id: string) => request<BenchRun[]>("GET", `${axis(id)}/bench/runs`),
  run: (runId: string) => request<BenchRunDetail>("GET", runUrl(runId)),
  deleteRun: (runId: string) => request<null>("DELETE", runUrl(runId)),
  setBaseline: (runId: string) => request<null>("POST", `${runUrl(runId)}/baseline`),
  importRun: (id: string, meta: unknown, csv: string) =>
    request<{ id: string }>("POST", `${axis(id)}/bench/runs/import`, { meta, csv }),
  paramSets: (id: string) => request<ParamSet[]>("GET", `${axis(id)}/param-sets`),
  saveParamSet: (id: string, name: string, note: string) =>
    request<SavedSet>("POST", `${axis(id)}/param-sets`, { name, note } satisfies SaveSetRequest),
  compareParamSet: (id: string, name: string) => request<ParamSetComparison>("GET", `${paramSet(id, name)}/compare`),
  restoreParamSet: (id: string, name: string) => request<Record<string, number>>("POST", `${paramSet(id, name)}/restore`),
  deleteParamSet: (id: string, name: string) => request<null>("DELETE", paramSet(id, name)),
  autotune: (id: string) => request<AutoTuneSession>("GET", `${axis(id)}/autotune`),
  autotuneIdentify: (id: string, body: AutoTuneRequest) => request<AutoTuneProposal>("POST", `${axis(id)}/autotune/identify`, body),
  autotuneAccept: (id: string) => confirmed((confirm) => request<AutoTuneAccepted>("POST", `${axis(id)}/autotune/accept${confirm}`)),
  autotuneKeep: (id: string) => request<AutoTuneDecision>("POST", `${axis(id)}/autotune/keep`),
  autotuneRevert: (id: string) => request<Record<string, number>>("POST", `${axis(id)}/autotune/revert`),
};

export function runUrl(runId: string): string {
  return `/api/bench/runs/${encodeURIComponent(runId)}`;
}
