// Application state fed by the websocket and REST replies; views subscribe to topics.
import { AxisBuffer } from "./buffer";
import type {
  AxisInfo,
  AxisStatus,
  DeviceDescriptor,
  Event as WireEvent,
  LinkInfo,
  LinkStatus,
  MoveOutcome,
  RunUpdate,
  StorageStatus,
} from "./schema.gen";
import type { Incoming, WsState } from "./ws";

export interface Topics {
  topology: void; // axes or links changed (hello)
  link: string; // link id whose status changed
  axisStatus: string; // axis id
  params: { axis: string; names: string[] };
  uiParams: string; // axis id: the user changed a value in the tuning fields
  event: WireEvent;
  run: RunUpdate; // bench run progress (every browser gets it)
  storage: StorageStatus; // saving failed / works again
  clientStats: void;
  moveOutcome: MoveOutcome; // how a user's move to a target ended
  ws: WsState;
  error: string;
  theme: void;
}

type Listener<T> = (value: T) => void;

export class Store {
  axes: AxisInfo[] = [];
  links: LinkInfo[] = [];
  autopilot = false;
  serverVersion = "";
  readonly linkStatus = new Map<string, LinkStatus>();
  readonly axisStatus = new Map<string, AxisStatus>();
  readonly buffers = new Map<string, AxisBuffer>();
  /** Parameter values as last read back from the device, per axis. */
  readonly deviceParams = new Map<string, Map<string, number>>();
  /** Per axis: the persisted values the device's save command stored, as far as the
   * server saw it save them (absent: not known). */
  readonly storedParams = new Map<string, Map<string, number>>();
  /** Values the user entered that the device does not have (yet), per axis. */
  readonly uiParams = new Map<string, Map<string, number>>();
  readonly descriptors = new Map<string, Promise<DeviceDescriptor>>();
  readonly events: WireEvent[] = [];
  /** The latest bench ``run`` message per axis (a recording one means "busy"). */
  readonly runs = new Map<string, RunUpdate>();
  /** The last storage_status (null: none received, the server saves normally). */
  storage: StorageStatus | null = null;
  stats = { sent: 0, dropped: 0 };
  /** Wall clock (unix s) minus server clock (s), estimated from telemetry arrivals: the
   * smallest difference seen is the one with the least transport delay. NaN until the
   * first telemetry. Used for wall-clock times of events and of the scope's x axis. */
  clockOffsetS = Number.NaN;
  ws: WsState = { kind: "connecting", attempt: 0 };
  private readonly listeners = new Map<keyof Topics, Set<Listener<never>>>();

  on<K extends keyof Topics>(topic: K, fn: Listener<Topics[K]>, signal?: AbortSignal): void {
    let set = this.listeners.get(topic);
    if (!set) {
      set = new Set();
      this.listeners.set(topic, set);
    }
    set.add(fn as Listener<never>);
    signal?.addEventListener("abort", () => set.delete(fn as Listener<never>), { once: true });
  }

  emit<K extends keyof Topics>(topic: K, value: Topics[K]): void {
    const set = this.listeners.get(topic);
    if (!set) return;
    for (const fn of [...set]) {
      try {
        (fn as Listener<Topics[K]>)(value);
      } catch (error) {
        console.error(`listener of ${topic} failed`, error);
      }
    }
  }

  buffer(axis: string): AxisBuffer {
    let buffer = this.buffers.get(axis);
    if (!buffer) {
      buffer = new AxisBuffer();
      this.buffers.set(axis, buffer);
    }
    return buffer;
  }

  axis(id: string): AxisInfo | undefined {
    return this.axes.find((a) => a.id === id);
  }

  deviceValues(axis: string): Map<string, number> {
    let map = this.deviceParams.get(axis);
    if (!map) {
      map = new Map();
      this.deviceParams.set(axis, map);
    }
    return map;
  }

  uiValues(axis: string): Map<string, number> {
    let map = this.uiParams.get(axis);
    if (!map) {
      map = new Map();
      this.uiParams.set(axis, map);
    }
    return map;
  }

  /** Device values read back (REST reply or websocket ``params``). */
  setDeviceParams(axis: string, values: Record<string, number>, adoptInUi: boolean): void {
    const device = this.deviceValues(axis);
    const ui = this.uiValues(axis);
    for (const [name, value] of Object.entries(values)) {
      const before = device.get(name);
      device.set(name, value);
      // A field the user has not edited follows the device; an edited one keeps its
      // value (and stays marked) unless this read-back answers the user's own write.
      if (adoptInUi || !ui.has(name) || ui.get(name) === before) ui.delete(name);
      if (ui.get(name) === value) ui.delete(name);
    }
    this.emit("params", { axis, names: Object.keys(values) });
  }

  descriptor(axis: string, load: () => Promise<DeviceDescriptor>): Promise<DeviceDescriptor> {
    let promise = this.descriptors.get(axis);
    if (!promise) {
      promise = load();
      promise.catch(() => this.descriptors.delete(axis));
      this.descriptors.set(axis, promise);
    }
    return promise;
  }

  handle(msg: Incoming): void {
    switch (msg.type) {
      case "telemetry": {
        this.buffer(msg.axis).push(msg);
        const last = msg.t[msg.t.length - 1];
        if (last !== undefined) {
          const offset = Date.now() / 1000 - last;
          if (!(offset >= this.clockOffsetS)) this.clockOffsetS = offset;
        }
        break;
      }
      case "hello":
        this.axes = msg.axes;
        this.links = msg.links;
        this.autopilot = msg.autopilot;
        this.serverVersion = msg.server_version;
        this.clockOffsetS = Number.NaN; // a new server may have a new clock
        this.emit("topology", undefined);
        break;
      case "link_status":
        this.linkStatus.set(msg.link, msg);
        this.emit("link", msg.link);
        break;
      case "axis_status":
        this.axisStatus.set(msg.axis, msg);
        this.emit("axisStatus", msg.axis);
        break;
      case "params":
        if (msg.source === "stored") {
          this.storedParams.set(msg.axis, new Map(Object.entries(msg.values)));
          this.emit("params", { axis: msg.axis, names: Object.keys(msg.values) });
        } else this.setDeviceParams(msg.axis, msg.values, false);
        break;
      case "event":
        // The server replays recent events on (re)connect: skip those already shown.
        if (this.events.some((e) => e.t === msg.t && e.message === msg.message && e.axis === msg.axis)) break;
        this.events.push(msg);
        if (this.events.length > 1000) this.events.splice(0, this.events.length - 1000);
        this.emit("event", msg);
        break;
      case "run":
        this.runs.set(msg.axis, msg);
        this.emit("run", msg);
        break;
      case "storage_status":
        this.storage = msg;
        this.emit("storage", msg);
        break;
      case "client_stats":
        this.stats = { sent: msg.sent, dropped: msg.dropped };
        this.emit("clientStats", undefined);
        break;
      case "move_outcome":
        this.emit("moveOutcome", msg);
        break;
      default: {
        const never: never = msg;
        console.warn("unknown message", never);
      }
    }
  }
}

export const store = new Store();
