// The one stability verdict of a discrete loop, in the browser: the same steps as
// server/servotune/tuning/stability.py (Schur-Cohn on the characteristic polynomial
// built from the exact controller and plant polynomials), checked against the same
// cases in tests/test_stability.py (this file is compiled and run under node there).
// No imports: it must compile on its own.

/** Whether every root of a0 z^n + ... + an lies strictly inside the unit circle:
 * k = an / a0, |k| < 1, and the same for (a_i - k a_(n-i)) / (1 - k^2), i < n. */
export function schurStable(coefficients: number[]): boolean {
  let a = coefficients.slice();
  while (a.length && a[0] === 0) a.shift();
  while (a.length && a[a.length - 1] === 0) a.pop();
  if (!a.length || a.some((v) => !Number.isFinite(v))) return false;
  while (a.length > 1) {
    const n = a.length - 1;
    const k = (a[n] as number) / (a[0] as number);
    if (!(Math.abs(k) < 1)) return false;
    const next: number[] = [];
    for (let i = 0; i < n; i++) next.push(((a[i] as number) - k * (a[n - i] as number)) / (1 - k * k));
    a = next;
  }
  return true;
}

function multiply(p: number[], q: number[]): number[] {
  const out = new Array<number>(p.length + q.length - 1).fill(0);
  p.forEach((x, i) => q.forEach((y, j) => (out[i + j] = (out[i + j] as number) + x * y)));
  return out;
}

function add(p: number[], q: number[]): number[] {
  const out = new Array<number>(Math.max(p.length, q.length)).fill(0);
  p.forEach((x, i) => (out[i] = (out[i] as number) + x));
  q.forEach((x, i) => (out[i] = (out[i] as number) + x));
  return out;
}

export interface LoopLaw {
  law: "slap2_pid" | "z1100_kab";
  /** The discrete plant, coefficients of z^-1 (den[0] = 1). */
  plant_num: number[];
  plant_den: number[];
}

/** The characteristic polynomial Dc Ap + Nc Bp of the law (the Z1100 with its hold
 * gains, KABD) around the plant, as coefficients of z^-1 - read as descending powers
 * of z, the same list. The SLAP2 PID with ki = 0 has no integrator: no factor 1 - z^-1
 * to read as a pole on the unit circle. */
export function characteristic(model: LoopLaw, gains: Record<string, number>): number[] {
  let nc: number[];
  let dc: number[];
  if (model.law === "slap2_pid") {
    const kp = gains.kp ?? 0;
    const ki = gains.ki ?? 0;
    const kd = gains.kd ?? 0;
    if (ki) {
      nc = [16 * kp + ki + 32 * kd, -16 * kp - 64 * kd, 32 * kd];
      dc = [4096, -4096];
    } else {
      nc = [16 * kp + 32 * kd, -32 * kd];
      dc = [4096];
    }
  } else {
    const k = gains.kabd_k ?? 0;
    const a = gains.kabd_a ?? 0;
    const b = gains.kabd_b ?? 0;
    nc = new Array<number>(33).fill(0);
    nc[0] = 16 * k + k * a + b;
    nc[32] = -(k * a + b);
    dc = [64];
  }
  return add(multiply(dc, model.plant_den), multiply(nc, model.plant_num));
}

/** The verdict the server gives for the same loop (tuning.loops.LoopModel.stable). */
export function loopStable(model: LoopLaw, gains: Record<string, number>): boolean {
  return schurStable(characteristic(model, gains));
}
