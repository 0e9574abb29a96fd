// Rig overview: one tile per axis (position, motion state, link rate, health, who holds
// its control lock), each opening its axis page. Built from the descriptors, so it knows nothing per device
// except which flag means "moving" / "in position" (by name, see STATE_FLAGS).
import { api } from "../api";
import { h, replace, setText } from "../dom";
import { formatValue, nativeUnit } from "../format";
import { store } from "../store";
import type { AxisInfo, DeviceDescriptor } from "../schema.gen";
import { HEALTH_TEXT } from "./axis";
import { control } from "./controllock";

/** Who holds the control lock of ``axisId`` (from the server's control_status messages). */
export function holderText(axisId: string): { text: string; state: "mine" | "held" | "autopilot" | "free" | "unknown" } {
  const status = control.status.get(axisId);
  if (!status) return { text: "control: —", state: "unknown" };
  const holder = status.holder;
  if (control.mine(axisId)) return { text: "control: this tab", state: "mine" };
  if (holder?.kind === "user") {
    const other = holder.user === control.welcome?.user ? " (another tab)" : "";
    return { text: `control: ${holder.user}${other}`, state: "held" };
  }
  if (holder?.kind === "autopilot") return { text: "control: autopilot", state: "autopilot" };
  if (holder?.kind === "server") return { text: "control: server (stopping)", state: "held" };
  return { text: "control: free", state: "free" };
}

/** Flag names that mean "moving" and "in position" across the supported devices. */
const MOVING = /^(move|running|busy|moving_positive|moving_negative)$/;
const IN_POSITION = /^(inpos|in_target)$/;

interface Tile {
  axis: AxisInfo;
  el: HTMLElement;
  position: HTMLElement;
  unit: HTMLElement;
  state: HTMLElement;
  rate: HTMLElement;
  health: HTMLElement;
  holder: HTMLElement;
  stop: HTMLElement;
  descriptor: DeviceDescriptor | null;
}

export class OverviewView {
  readonly el: HTMLElement;
  private readonly tiles: Tile[] = [];
  private readonly abort = new AbortController();
  private last = 0;

  constructor() {
    const grid = h("div", { class: "overview-grid" });
    this.el = h(
      "div",
      { class: "overview", testid: "overview" },
      h("div", { class: "overview-head" }, h("h1", null, "Rig overview"), h("span", { class: "axis-meta" }, `${store.axes.length} axes · click a tile to open the axis`)),
      grid,
    );
    for (const axis of store.axes) {
      const tile: Tile = {
        axis,
        position: h("span", { class: "tile-value mono", testid: `tile-position-${axis.id}` }, "—"),
        unit: h("span", { class: "readout-unit" }, ""),
        state: h("span", { class: "tile-state", testid: `tile-state-${axis.id}` }, "—"),
        rate: h("span", { class: "tile-rate mono" }, "— Hz"),
        health: h("span", { class: "badge health" }, "ok"),
        holder: h("span", { class: "tile-holder", testid: `tile-control-${axis.id}`, title: "Who holds the control lock of this axis (STOP works for everyone)" }, "control: —"),
        // What STOP does to this axis, on every screen (the top bar has room for it
        // only on wide ones)
        stop: h("div", { class: "tile-stop", testid: `tile-stop-${axis.id}` }, ""),
        descriptor: null,
        el: h("a"),
      };
      tile.el = h(
        "a",
        { class: "tile", href: `#/axis/${encodeURIComponent(axis.id)}`, testid: `tile-${axis.id}`, title: `Open ${axis.name}` },
        h("div", { class: "tile-head" }, h("span", { class: "tile-name" }, axis.name), tile.health),
        h("div", { class: "tile-meta mono" }, `${axis.device} · ${axis.link} · #${axis.address}`),
        h("div", { class: "tile-line" }, tile.position, tile.unit),
        h("div", { class: "tile-line" }, tile.state, tile.rate),
        h("div", { class: "tile-line" }, tile.holder),
        tile.stop,
      );
      grid.appendChild(tile.el);
      this.tiles.push(tile);
      store
        .descriptor(axis.id, () => api.descriptor(axis.id))
        .then((d) => {
          tile.descriptor = d;
          setText(tile.stop, `STOP: ${d.stop.summary}`);
          setText(tile.unit, d.channels.find((c) => c.name === this.positionChannel(d))?.unit ?? "");
        })
        .catch(() => setText(tile.state, "no descriptor"));
    }
    if (!this.tiles.length) replace(grid, h("div", { class: "empty-state" }, "No axes yet."));
    store.on("topology", () => undefined, this.abort.signal);
    const syncHolders = (axis: string | null): void => {
      for (const tile of this.tiles) if (axis === null || axis === tile.axis.id) this.syncHolder(tile);
    };
    syncHolders(null);
    control.on(syncHolders, this.abort.signal);
  }

  private syncHolder(tile: Tile): void {
    const { text, state } = holderText(tile.axis.id);
    setText(tile.holder, text);
    if (tile.holder.dataset.state !== state) tile.holder.dataset.state = state;
  }

  private positionChannel(d: DeviceDescriptor): string {
    return d.channels.find((c) => c.name === "position")?.name ?? d.plots[0]?.series[0] ?? d.channels[0]?.name ?? "";
  }

  /** Tiles refresh at about 5 Hz: numbers a person reads, not a plot. */
  frame(now: number): void {
    if (now - this.last < 200) return;
    this.last = now;
    for (const tile of this.tiles) this.refresh(tile);
  }

  private refresh(tile: Tile): void {
    const d = tile.descriptor;
    const buffer = store.buffers.get(tile.axis.id);
    const status = store.axisStatus.get(tile.axis.id);
    const health = status?.health ?? "ok";
    setText(tile.health, HEALTH_TEXT[health] ?? health);
    tile.health.dataset.health = health;
    const link = store.linkStatus.get(tile.axis.link);
    setText(tile.rate, link ? `${link.rate_hz.toFixed(1)} Hz · ${link.state}` : "— Hz");
    if (!d || !buffer) return;
    const raw = buffer.latest.get(this.positionChannel(d));
    setText(tile.position, formatValue(raw ?? null, nativeUnit("")));
    const on = (re: RegExp): boolean => d.flags.some((f) => re.test(f.name) && buffer.latestFlags.get(f.name) === 1);
    const faults = d.flags.filter((f) => f.severity === "fault" && buffer.latestFlags.get(f.name) === 1).map((f) => f.label);
    let state: string;
    if (health === "offline") state = "offline";
    else if (faults.length) state = `fault: ${faults.join(", ")}`;
    else if (on(MOVING)) state = "moving";
    else if (on(IN_POSITION)) state = "in position";
    else state = "standstill";
    setText(tile.state, state);
    tile.state.dataset.state = state.startsWith("fault") ? "fault" : state.replace(" ", "-");
    tile.el.dataset.state = tile.state.dataset.state;
  }

  destroy(): void {
    this.abort.abort();
    this.el.remove();
  }
}
