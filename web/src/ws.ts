// The websocket: reconnects with exponential backoff and reports its state.
import type { ClientMessage, ControlClientMessage, ControlServerMessage, RunUpdate, ServerMessage } from "./schema.gen";

/** What the server sends. ``RunUpdate`` (bench progress) is listed on its own because the
 * generated ``ServerMessage`` union does not include it yet; once it does, this is the
 * same type (a repeated member of a union is harmless). */
export type Incoming = ServerMessage | RunUpdate;
/** Everything on the socket: the store's messages plus the control lock's (ui/controllock.ts). */
export type WsMessage = Incoming | ControlServerMessage;

export type WsState =
  | { kind: "connecting"; attempt: number }
  | { kind: "open"; since: number }
  | { kind: "waiting"; attempt: number; retryAt: number; reason: string };

export interface WsHandlers {
  message(msg: WsMessage): void;
  state(state: WsState): void;
}

const BACKOFF_MS = [500, 1000, 2000, 4000, 8000];
const PING_MS = 5000;

export class WsClient {
  private socket: WebSocket | null = null;
  private attempt = 0;
  private timer: number | undefined;
  private pingTimer: number | undefined;
  private stopped = false;
  state: WsState = { kind: "connecting", attempt: 0 };

  constructor(
    private readonly url: string,
    private readonly handlers: WsHandlers,
  ) {}

  start(): void {
    this.stopped = false;
    this.connect();
  }

  stop(): void {
    this.stopped = true;
    window.clearTimeout(this.timer);
    window.clearInterval(this.pingTimer);
    this.socket?.close();
  }

  send(msg: ClientMessage | ControlClientMessage): void {
    if (this.socket?.readyState === WebSocket.OPEN) this.socket.send(JSON.stringify(msg));
  }

  /** Reconnect now instead of waiting for the backoff (the user clicked the state). */
  retryNow(): void {
    if (this.state.kind === "waiting") {
      window.clearTimeout(this.timer);
      this.connect();
    }
  }

  private setState(state: WsState): void {
    this.state = state;
    this.handlers.state(state);
  }

  private connect(): void {
    this.attempt += 1;
    this.setState({ kind: "connecting", attempt: this.attempt });
    let socket: WebSocket;
    try {
      socket = new WebSocket(this.url);
    } catch (error) {
      this.scheduleRetry(String(error));
      return;
    }
    this.socket = socket;
    let opened = false;
    socket.onopen = () => {
      opened = true;
      this.attempt = 0;
      this.setState({ kind: "open", since: performance.now() });
      this.send({ type: "ping" });
      window.clearInterval(this.pingTimer);
      this.pingTimer = window.setInterval(() => this.send({ type: "ping" }), PING_MS);
    };
    socket.onmessage = (event: MessageEvent) => {
      if (typeof event.data !== "string") return;
      let msg: WsMessage;
      try {
        msg = JSON.parse(event.data) as WsMessage;
      } catch {
        return;
      }
      this.handlers.message(msg);
    };
    socket.onclose = (event: CloseEvent) => {
      window.clearInterval(this.pingTimer);
      if (this.socket !== socket) return;
      this.socket = null;
      if (this.stopped) return;
      const reason = opened
        ? `closed${event.code ? ` (${event.code})` : ""}`
        : "server unreachable";
      this.scheduleRetry(reason);
    };
  }

  private scheduleRetry(reason: string): void {
    const delay = BACKOFF_MS[Math.min(this.attempt - 1, BACKOFF_MS.length - 1)] ?? 8000;
    this.setState({ kind: "waiting", attempt: this.attempt, retryAt: performance.now() + delay, reason });
    this.timer = window.setTimeout(() => this.connect(), delay);
  }
}

export function wsUrl(): string {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  return `${proto}//${location.host}/ws`;
}
