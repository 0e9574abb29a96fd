// The user's limits of an axis' bench tests: every test is checked against them before
// anything moves (the server checks again and is authoritative).
import { api, type BenchInfo, type BenchLimits } from "../../api";
import { h, setText, toggleClass } from "../../dom";
import type { Units } from "./kinds";

export interface LimitsHost {
  info(): BenchInfo | null;
  clearError(): void;
  showError(error: unknown, fallbackField: string): void;
  /** The limits shown changed: check the form's fields against them. */
  validate(): void;
  saved(limits: BenchLimits): void;
}

export class LimitsEditor {
  readonly status: HTMLElement;
  /** The wrapper of each limit's input, by its field name (for error callouts). */
  readonly wraps = new Map<string, HTMLElement>();
  private readonly inputs = new Map<keyof BenchLimits, HTMLInputElement>();
  private save: HTMLButtonElement | null = null;

  constructor(
    private readonly axisId: string,
    private readonly host: LimitsHost,
  ) {
    this.status = h("span", { class: "bench-limits-status" });
  }

  input(field: string): HTMLInputElement | undefined {
    return this.inputs.get(field as keyof BenchLimits);
  }

  allInputs(): HTMLInputElement[] {
    return [...this.inputs.values()];
  }

  render(info: BenchInfo, units: Units): HTMLElement {
    const limitField = (key: keyof BenchLimits, label: string, unit: string, step: string): HTMLElement => {
      const input = h("input", {
        class: "input num small",
        type: "number",
        step,
        min: 0,
        testid: `bench-limit-${key}`,
        "aria-label": label,
        title: `${label}: every test on this axis is checked against it before anything moves`,
      });
      input.addEventListener("input", () => {
        input.classList.remove("server-invalid");
        this.syncDirty();
      });
      input.addEventListener("keydown", (event) => {
        if (event.key === "Enter") {
          event.preventDefault();
          void this.saveLimits();
        }
      });
      this.inputs.set(key, input);
      const wrap = h("label", { class: "bl", "data-field": key }, h("span", { class: "bl-label" }, label), input, unit ? h("span", { class: "unit" }, unit) : null);
      this.wraps.set(key, wrap);
      return wrap;
    };
    this.save = h("button", { class: "btn small", testid: "bench-limits-save", onclick: () => void this.saveLimits() }, "Save");
    return h(
      "div",
      { class: "bench-limits", title: "Your limits for this axis: a test beyond them is refused before anything moves" },
      h("span", { class: "tb-label" }, "Limits"),
      limitField("max_distance_counts", "distance ±", units.distance, "1"),
      info.kinds.includes("velocity_step") ? limitField("max_velocity", "velocity ±", units.velocity, "1") : null,
      info.kinds.includes("pwm_step") ? limitField("max_pwm", "pwm ±", "", "1") : null,
      limitField("max_duration_s", "duration ≤", "s", "0.5"),
      this.save,
      this.status,
    );
  }

  fill(limits: BenchLimits): void {
    for (const [key, input] of this.inputs) input.value = String(limits[key]);
    this.syncDirty();
    this.host.validate();
  }

  private read(): BenchLimits {
    const current = (this.host.info() as BenchInfo).limits;
    const value = (key: "max_distance_counts" | "max_velocity" | "max_pwm" | "max_duration_s"): number => {
      const input = this.inputs.get(key);
      return input ? Number(input.value) : current[key];
    };
    // The travel window has no field here: it is sent back as the server holds it.
    return {
      max_distance_counts: value("max_distance_counts"),
      max_velocity: value("max_velocity"),
      max_pwm: value("max_pwm"),
      max_duration_s: value("max_duration_s"),
      min_position_counts: current.min_position_counts,
      max_position_counts: current.max_position_counts,
    };
  }

  private syncDirty(): void {
    const info = this.host.info();
    if (!info || !this.save) return;
    const shown = this.read();
    const dirty = (Object.keys(shown) as (keyof BenchLimits)[]).some((k) => shown[k] !== info.limits[k]);
    this.save.disabled = !dirty;
    toggleClass(this.save, "warn", dirty);
    if (dirty) setText(this.status, "not saved");
  }

  private async saveLimits(): Promise<void> {
    const info = this.host.info();
    if (!info || !this.save) return;
    this.host.clearError();
    this.save.classList.add("busy");
    try {
      const saved = await api.setBenchLimits(this.axisId, this.read());
      info.limits = saved;
      this.fill(saved);
      this.host.saved(saved);
      setText(this.status, "✓ saved");
    } catch (error) {
      this.host.showError(error, "max_distance_counts");
      setText(this.status, "");
    } finally {
      this.save.classList.remove("busy");
    }
  }
}
