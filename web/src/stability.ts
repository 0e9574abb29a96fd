// The discrete loop in the browser: the device's controller law as data (the terms of
// schema ControllerLaw, from GET /api/axes/{id}/whatif), evaluated tick by tick and as a
// transfer function, and the one stability verdict and margin rule of the server
// (server/servotune/tuning/stability.py: Schur-Cohn on the characteristic polynomial
// built from the law's and the plant's polynomials), checked against the same cases in
// tests/unit/tuning/test_stability.py (this file is compiled and run under node there).
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

// --- the law as data (schema.ControllerLaw) -------------------------------------------

export type LawSignal = "error" | "error_sum" | "position";

/** coefficient x product(gains, each read as the gain set's prefix + name) x signal[n - delay] */
export interface LawTerm {
  coefficient: number;
  gains: string[];
  signal: LawSignal;
  delay: number;
}

export interface ControllerLaw {
  terms: LawTerm[];
  divisor: number;
  rounding: "none" | "trunc";
  gain_sets: { when: "moving" | "holding" | "always"; prefix: string }[];
}

/** The prefix of the gains in force while the target moves or holds (the set for
 * "always" when there is none for that phase). */
export function gainPrefix(law: ControllerLaw, when: "moving" | "holding"): string {
  return (law.gain_sets.find((s) => s.when === when) ?? law.gain_sets.find((s) => s.when === "always"))?.prefix ?? "";
}

function termGain(term: LawTerm, gains: Record<string, number>, prefix: string): number {
  let value = term.coefficient;
  for (const g of term.gains) value *= gains[prefix + g] ?? 0;
  return value;
}

const SIGNALS: LawSignal[] = ["error", "error_sum", "position"];

/** The law tick by tick with fixed gains: ``step`` takes this tick's error and
 * position and returns the output before the clamp (``u = round(sum(terms) / divisor)``).
 * The terms' gain products are taken once per gain set (a prediction runs tens of
 * thousands of ticks per slider move). */
export class LawRunner {
  private readonly size: number;
  // one ring of past values per signal: error, error_sum, position
  private readonly history: Float64Array[];
  private readonly signal: Int32Array;
  private readonly delay: Int32Array;
  private readonly moving: Float64Array;
  private readonly holding: Float64Array;
  private at = 0;
  private sum = 0;

  constructor(
    private readonly law: ControllerLaw,
    gains: Record<string, number>,
  ) {
    this.size = 1 + Math.max(0, ...law.terms.map((t) => t.delay));
    this.history = [0, 1, 2].map(() => new Float64Array(this.size));
    this.signal = Int32Array.from(law.terms.map((t) => SIGNALS.indexOf(t.signal)));
    this.delay = Int32Array.from(law.terms.map((t) => t.delay));
    const products = (when: "moving" | "holding"): Float64Array => Float64Array.from(law.terms.map((t) => termGain(t, gains, gainPrefix(law, when))));
    this.moving = products("moving");
    this.holding = products("holding");
  }

  step(e: number, y: number, moving: boolean): number {
    const size = this.size;
    this.at = (this.at + 1) % size;
    this.sum += e;
    const [error, sum, position] = this.history as [Float64Array, Float64Array, Float64Array];
    error[this.at] = e;
    sum[this.at] = this.sum;
    position[this.at] = y;
    const products = moving ? this.moving : this.holding;
    let acc = 0;
    for (let i = 0; i < products.length; i++) {
      const history = this.history[this.signal[i] as number] as Float64Array;
      acc += (products[i] as number) * (history[(this.at - (this.delay[i] as number) + size) % size] as number);
    }
    const u = acc / this.law.divisor;
    return this.law.rounding === "trunc" ? Math.trunc(u) : u;
  }
}

/** The law's paths as coefficients of z^-k with the holding gains (a linear analysis
 * is around a held position): on the error, on its running sum, on the position. */
function lawPaths(law: ControllerLaw, gains: Record<string, number>): Record<LawSignal, number[]> {
  const size = 1 + Math.max(0, ...law.terms.map((t) => t.delay));
  const prefix = gainPrefix(law, "holding");
  const paths: Record<LawSignal, number[]> = { error: new Array<number>(size).fill(0), error_sum: new Array<number>(size).fill(0), position: new Array<number>(size).fill(0) };
  for (const term of law.terms) {
    const path = paths[term.signal];
    path[term.delay] = (path[term.delay] as number) + termGain(term, gains, prefix);
  }
  return paths;
}

export interface LoopLaw {
  controller: ControllerLaw;
  /** The discrete plant, coefficients of z^-1 (den[0] = 1). */
  plant_num: number[];
  plant_den: number[];
}

/** The characteristic polynomial Dc Ap + Nc Bp of the law (with its holding gains)
 * around the plant, as coefficients of z^-1 - read as descending powers of z, the same
 * list. The controller seen from the error is (E + S / (1 - z^-1) - Y) / divisor; with
 * no running-sum gain (the SLAP2's ki = 0) there is no integrator: no factor 1 - z^-1 to
 * read as a pole on the unit circle. */
export function characteristic(model: LoopLaw, gains: Record<string, number>): number[] {
  const law = model.controller;
  const paths = lawPaths(law, gains);
  const direct = paths.error.map((v, k) => v - (paths.position[k] as number));
  let nc: number[];
  let dc: number[];
  if (paths.error_sum.some((v) => v !== 0)) {
    nc = add(multiply(direct, [1, -1]), paths.error_sum);
    dc = [law.divisor, -law.divisor];
  } else {
    nc = direct;
    dc = [law.divisor];
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

/** Open loop L(e^{jwT}) of the law (its holding gains) and the plant. */
export function openLoop(model: DiscreteLoop, gains: Record<string, number>, f: number): Complex {
  return openLoopOf(model, lawPaths(model.controller, gains), f);
}

function openLoopOf(model: DiscreteLoop, paths: Record<LawSignal, number[]>, f: number): Complex {
  const w = 2 * Math.PI * f * model.period_s;
  // z^-k = cos(kw) - j sin(kw)
  const zk = (k: number): Complex => ({ re: Math.cos(k * w), im: -Math.sin(k * w) });
  const poly = (c: number[]): Complex => {
    let re = 0;
    let im = 0;
    c.forEach((v, k) => {
      if (v === 0) return; // most of a long law's coefficients (the Z1100's window)
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
  // C = (E + S / (1 - z^-1) - Y) / divisor, the paths of the law with its holding gains
  const z1 = zk(1);
  const integ = div({ re: 1, im: 0 }, { re: 1 - z1.re, im: -z1.im }); // z/(z-1) = 1/(1-z^-1)
  const e = poly(paths.error);
  const y = poly(paths.position);
  const sum = mul(poly(paths.error_sum), integ);
  const divisor = model.controller.divisor;
  const c = { re: (e.re + sum.re - y.re) / divisor, im: (e.im + sum.im - y.im) / divisor };
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
  const paths = lawPaths(model.controller, gains);
  return loopMargins(f, f.map((x) => openLoopOf(model, paths, x)));
}

// --- the step prediction of the what-if view ---------------------------------------------

export interface StepModel extends DiscreteLoop {
  /** The output's clamp (PWM units). */
  pwm_limit: number;
}

/** The verification step's profile (counts/s, counts/s^2). */
export interface StepProfile {
  velocity_counts_s: number;
  acceleration_counts_s2: number;
}

export interface Prediction {
  t: number[];
  y: number[];
  overshootPct: number;
  settlingS: number | null;
  peakPwm: number;
}

/** The trapezoid of the profile generators (the simulators' per-sample rule): speed
 * min(v + a, vmax, sqrt(2 a d)) per sample, so a short move never reaches vmax. */
function profile(distance: number, vmaxPerTick: number, accPerTick: number, ticks: number): Float64Array {
  const ref = new Float64Array(ticks);
  let r = 0;
  let v = 0;
  const goal = Math.abs(distance);
  const sign = Math.sign(distance);
  for (let n = 0; n < ticks; n++) {
    const d = goal - r;
    if (d > 0) {
      const speed = Math.min(v + accPerTick, vmaxPerTick, Math.sqrt(2 * accPerTick * d));
      if (speed >= d) {
        r = goal;
        v = 0;
      } else {
        r += speed;
        v = speed;
      }
    }
    ref[n] = sign * r;
  }
  return ref;
}

/** Predicted response to the verification step: the law (``LawRunner``) on the
 * discrete plant, the output clamped at its limit (friction is not modelled: see
 * docs/frequency-response.md). The moving gain set is in force until the profile has
 * reached the distance. */
export function predictStep(model: StepModel, gains: Record<string, number>, distance: number, verify: StepProfile, horizonS: number, band: number): Prediction {
  const ts = model.period_s;
  const ticks = Math.max(2, Math.round(horizonS / ts));
  const ref = profile(distance, verify.velocity_counts_s * ts, verify.acceleration_counts_s2 * ts * ts, ticks);
  const num = model.plant_num;
  const den = model.plant_den;
  const order = den.length - 1;
  const uHist = new Float64Array(order + 1);
  const yHist = new Float64Array(order + 1);
  const law = new LawRunner(model.controller, gains);
  let peakPwm = 0;
  const every = Math.max(1, Math.floor(ticks / 1500));
  const t: number[] = [];
  const y: number[] = [];
  let moving = true;
  for (let n = 0; n < ticks; n++) {
    // plant output at tick n from past inputs and outputs (num[0] = 0: strictly proper)
    let yn = 0;
    for (let i = 1; i <= order; i++) yn += (num[i] ?? 0) * (uHist[i - 1] ?? 0) - (den[i] ?? 0) * (yHist[i - 1] ?? 0);
    const counts = Math.round(yn);
    const target = Math.floor((ref[n] as number) + 0.5);
    if (moving && n > 0 && ref[n] === distance && ref[n - 1] === distance) moving = false;
    let u = law.step(target - counts, counts, moving);
    u = Math.max(-model.pwm_limit, Math.min(model.pwm_limit, u));
    peakPwm = Math.max(peakPwm, Math.abs(u));
    for (let i = order; i > 0; i--) {
      uHist[i] = uHist[i - 1] as number;
      yHist[i] = yHist[i - 1] as number;
    }
    uHist[0] = u;
    yHist[0] = yn;
    if (n % every === 0) {
      t.push(n * ts);
      y.push(yn);
    }
  }
  const sign = Math.sign(distance) || 1;
  const peak = Math.max(...y.map((v) => v * sign));
  const overshootPct = Math.max(0, ((peak - Math.abs(distance)) / Math.abs(distance)) * 100);
  let settlingS: number | null = null;
  for (let i = y.length - 1; i >= 0; i--) {
    if (Math.abs((y[i] as number) - distance) > band) {
      settlingS = i + 1 < t.length ? (t[i + 1] as number) : null;
      break;
    }
    if (i === 0) settlingS = 0;
  }
  return { t, y, overshootPct, settlingS, peakPwm };
}
