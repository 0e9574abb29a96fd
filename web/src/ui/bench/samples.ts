// A run's samples: fetched once per finished run, aligned at its trigger.
import { api, type BenchRun, type BenchRunDetail } from "../../api";

/** The recorder arms this long before the trigger (servotune/bench/service.py PRE_TRIGGER_S). */
const PRE_TRIGGER_S = 0.2;

const details = new Map<string, Promise<BenchRunDetail>>(); // finished runs only

export function detail(run: BenchRun): Promise<BenchRunDetail> {
  const key = `${run.id}:${run.status}`;
  let promise = details.get(key);
  if (!promise) {
    promise = api.run(run.id);
    if (run.status === "recording") return promise; // still growing: never cached
    promise.catch(() => details.delete(key));
    details.set(key, promise);
  }
  return promise;
}

/**
 * The trigger time t0 of a run, in the samples' clock: ``t0_s`` as the server stored
 * it. Runs stored before the server kept t0 (or imported without it) fall back to an
 * estimate, which can be off by up to a sample gap or more: the recorder arms PRE_TRIGGER_S (0.2 s) before it sends the trigger, so t0 ≈ the
 * first sample's time + 0.2 s. The parameter writes and setup commands before that
 * pause, and the wait for the first sample after arming, shift it by up to a sample
 * gap, so when the metrics are there t0 is recovered exactly from them instead:
 * ``peak_time_s`` is the time after t0 of the FIRST sample with ``peak_value`` (the
 * value may repeat while the axis rests at its peak), so t0 = t(the earliest sample
 * with that value whose t0 is plausible) − peak_time_s. Plausible: not before the
 * first sample (it comes at most a sample gap after arming, t0 ≥ arming + 0.2 s) and
 * not more than 1.5 s after the estimate.
 */
export function triggerTime(run: BenchRunDetail): number {
  // The server stores the trigger time (t0_s) with every run it records: use it.
  const stored = run.t0_s;
  if (typeof stored === "number" && Number.isFinite(stored)) return stored;
  const first = (run.samples[0]?.[0] as number | undefined) ?? 0;
  const estimate = first + PRE_TRIGGER_S;
  const m = run.metrics;
  const index = run.columns.indexOf(run.plan.response);
  if (!m || m.peak_time_s === null || m.peak_value === null || index < 1) return estimate;
  for (const row of run.samples) {
    if (row[index] !== m.peak_value) continue;
    const t0 = (row[0] as number) - m.peak_time_s;
    if (t0 >= first && t0 <= estimate + 1.5) return t0;
  }
  return estimate;
}

/** One column of a run against t − t0, minus ``offset`` (y0 for the response). */
export function column(run: BenchRunDetail, name: string, t0: number, offset: number): { x: number[]; y: (number | null)[] } | null {
  const index = run.columns.indexOf(name);
  if (index < 1 || !run.samples.length) return null;
  const x: number[] = [];
  const y: (number | null)[] = [];
  let any = false;
  for (const row of run.samples) {
    const t = row[0] as number;
    const v = row[index];
    x.push(Math.round((t - t0) * 1e6) / 1e6);
    if (typeof v === "number" && Number.isFinite(v)) {
      y.push(v - offset);
      any = true;
    } else y.push(null);
  }
  return any ? { x, y } : null;
}
