// The one stability verdict of a discrete loop, in the browser: the same steps as
// server/servotune/tuning/stability.py (Schur-Cohn on the characteristic polynomial
// built from the exact controller and plant polynomials), checked against the same
// cases in tests/unit/tuning/test_stability.py (this file is compiled and run under node there).
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

// --- margins: the same rule as tuning.stability.loop_margins ------------------------

export const MARGIN_GRID_POINTS = 1000;
export const MARGIN_GRID_FROM_HZ = 0.1;

export interface LoopMargins {
  gainMarginDb: number | null;
  phaseMarginDeg: number | null;
  crossoverHz: number | null;
  phaseCrossoverHz: number | null;
}

export interface DiscreteLoop extends LoopLaw {
  period_s: number;
}

interface Complex {
  re: number;
  im: number;
}

/** Open loop L(e^{jwT}) of the law (the Z1100's hold gains, KABD) and the plant. */
export function openLoop(model: DiscreteLoop, gains: Record<string, number>, f: number): Complex {
  const w = 2 * Math.PI * f * model.period_s;
  // z^-k = cos(kw) - j sin(kw)
  const zk = (k: number): Complex => ({ re: Math.cos(k * w), im: -Math.sin(k * w) });
  const poly = (c: number[]): Complex => {
    let re = 0;
    let im = 0;
    c.forEach((v, k) => {
      const z = zk(k);
      re += v * z.re;
      im += v * z.im;
    });
    return { re, im };
  };
  const div = (a: Complex, b: Complex): Complex => {
    const d = b.re * b.re + b.im * b.im;
    return { re: (a.re * b.re + a.im * b.im) / d, im: (a.im * b.re - a.re * b.im) / d };
  };
  const mul = (a: Complex, b: Complex): Complex => ({ re: a.re * b.re - a.im * b.im, im: a.re * b.im + a.im * b.re });
  const p = div(poly(model.plant_num), poly(model.plant_den));
  let c: Complex;
  if (model.law === "slap2_pid") {
    const one = { re: 1, im: 0 };
    const z1 = zk(1);
    const integ = div(one, { re: 1 - z1.re, im: -z1.im }); // z/(z-1) = 1/(1-z^-1)
    const kp = gains.kp ?? 0;
    const ki = gains.ki ?? 0;
    const kd = gains.kd ?? 0;
    c = { re: (16 * kp + ki * integ.re + 32 * kd * (1 - z1.re)) / 4096, im: (ki * integ.im - 32 * kd * z1.im) / 4096 };
  } else {
    const z32 = zk(32);
    const d = { re: 1 - z32.re, im: -z32.im };
    const k = gains.kabd_k ?? 0;
    const a = gains.kabd_a ?? 0;
    const b = gains.kabd_b ?? 0;
    c = { re: (k * (16 + a * d.re) + b * d.re) / 64, im: (k * a * d.im + b * d.im) / 64 };
  }
  return mul(c, p);
}

/** The frequencies margins are read on (Hz): log-spaced up to just below Nyquist. */
export function marginGrid(periodS: number): number[] {
  const top = 0.999 * (0.5 / periodS);
  const out: number[] = [];
  for (let i = 0; i < MARGIN_GRID_POINTS; i++) out.push(MARGIN_GRID_FROM_HZ * Math.pow(top / MARGIN_GRID_FROM_HZ, i / (MARGIN_GRID_POINTS - 1)));
  return out;
}

/** Gain and phase margins of L on a rising grid, crossings interpolated linearly in
 * log f (dB, unwrapped degrees): the phase margin the smallest 180 + phase (wrapped)
 * where |L| crosses 1, the gain margin the smallest -dB where the phase crosses -180
 * (mod 360) with |L| < 1; null where there is none. */
export function loopMargins(f: number[], loop: Complex[]): LoopMargins {
  const db = loop.map((l) => 20 * Math.log10(Math.hypot(l.re, l.im)));
  const phase: number[] = [];
  let previous = NaN;
  let turns = 0;
  loop.forEach((l) => {
    const raw = (Math.atan2(l.im, l.re) * 180) / Math.PI;
    if (!Number.isNaN(previous)) {
      const jump = raw + turns - previous;
      if (jump > 180) turns -= 360 * Math.round(jump / 360);
      else if (jump < -180) turns += 360 * Math.round(-jump / 360);
    }
    previous = raw + turns;
    phase.push(previous);
  });
  const out: LoopMargins = { gainMarginDb: null, phaseMarginDeg: null, crossoverHz: null, phaseCrossoverHz: null };
  let pm = Infinity;
  let gm = Infinity;
  for (let i = 0; i + 1 < f.length; i++) {
    const a = db[i] as number;
    const b = db[i + 1] as number;
    const at = (x: number): number => Math.exp(Math.log(f[i] as number) + x * (Math.log(f[i + 1] as number) - Math.log(f[i] as number)));
    if (Number.isFinite(a) && Number.isFinite(b) && a >= 0 !== b >= 0) {
      const x = a / (a - b);
      const ph = (phase[i] as number) + x * ((phase[i + 1] as number) - (phase[i] as number));
      let margin = (((ph + 180) % 360) + 360) % 360;
      if (margin > 180) margin -= 360;
      if (margin < pm) {
        pm = margin;
        out.phaseMarginDeg = margin;
        out.crossoverHz = at(x);
      }
    }
    const p = phase[i] as number;
    const q = phase[i + 1] as number;
    const first = Math.ceil((Math.min(p, q) + 180) / 360);
    const last = Math.floor((Math.max(p, q) + 180) / 360);
    for (let k = first; k <= last; k++) {
      const level = -180 + 360 * k;
      if (q === level && p !== level) continue;
      const x = p === q ? 0 : (level - p) / (q - p);
      const gain = a + x * (b - a);
      if (Number.isFinite(gain) && gain < 0 && -gain < gm) {
        gm = -gain;
        out.gainMarginDb = -gain;
        out.phaseCrossoverHz = at(x);
      }
    }
  }
  return out;
}

/** The margins of the law around the plant, read on ``marginGrid``. */
export function modelMargins(model: DiscreteLoop, gains: Record<string, number>): LoopMargins {
  const f = marginGrid(model.period_s);
  return loopMargins(f, f.map((x) => openLoop(model, gains, x)));
}
