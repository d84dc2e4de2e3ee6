import { UnsupportedFormatError } from "./errors.js";

// Which coefficient is which (format.md, "Which coefficient is which"): the kept prefix of the
// coefficients with each one's radius and angle. Version 1.2 sorts by the integer key i² + j²
// (di² + dj² for the DFT), ties in row-major order, and cuts at an integer bound derived in exact
// arithmetic (BigInt); 1.0 and 1.1 sort by the writer's hypot (the legacy order, emulated below).

const EPS = 2 ** -54;
const TINY = 2 ** -459;
const LARGE = 2 ** 511;
const SCALE = 2 ** -600;

function kernel(ax: number, ay: number): number {
  let h = Math.sqrt(ax * ax + ay * ay);
  let t1: number;
  let t2: number;
  if (h <= 2.0 * ay) {
    const delta = h - ay;
    t1 = ax * (2.0 * delta - ax);
    t2 = (delta - 2.0 * (ax - ay)) * delta;
  } else {
    const delta = h - ax;
    t1 = 2.0 * delta * (ax - 2.0 * ay);
    t2 = (4.0 * delta - ay) * ay + delta * delta;
  }
  h -= (t1 + t2) / (2.0 * h);
  return h;
}

/** hypot as the writer computes it (numpy's, i.e. glibc 2.35+'s without FMA: Borges' corrected
 * square root), bit for bit: ties of the radius order are decided by its last bits (format.md). */
export function hypot(x: number, y: number): number {
  x = Math.abs(x);
  y = Math.abs(y);
  const ax = x < y ? y : x;
  const ay = x < y ? x : y;
  if (ax > LARGE) {
    if (ay <= ax * EPS) return ax + ay;
    return kernel(ax * SCALE, ay * SCALE) / SCALE;
  }
  if (ay < TINY) {
    if (ax >= ay / EPS) return ax + ay;
    return kernel(ax / SCALE, ay / SCALE) * SCALE;
  }
  if (ay <= ax * EPS) return ax + ay;
  return kernel(ax, ay);
}

export type Transform = "dct" | "dft-half" | "dft-full";

export interface Prefix {
  /** Shape of the coefficient array (rows x cols; rows x (cols//2 + 1) for dft-half). */
  shape: [number, number];
  /** Flat row-major index in that array of each kept coefficient, in stream order. */
  pos: Int32Array;
  radius: Float64Array;
  angle: Float64Array;
}

/** The legacy radius limit (1 - cutoff) hypot(rows/2, cols/2) (1 + 1e-12), frequency pixels. */
export function radiusLimit(rows: number, cols: number, cutoff: number): number {
  return (1 - cutoff) * Math.hypot(rows / 2, cols / 2) * (1 + 1e-12);
}

/** Where the stream stops: the legacy float radius `limit`, or (version 1.2) every key up to
 * `qmax`, whose radius `limit` then is (it bounds the candidates enumerated). */
export interface Cut {
  legacy: boolean;
  limit: number;
  qmax: number;
}

/** A binary64 number as an exact fraction m / 2^e (m, e BigInt; x finite and >= 0). */
function fraction(x: number): [bigint, bigint] {
  const view = new DataView(new ArrayBuffer(8));
  view.setFloat64(0, x);
  const bits = view.getBigUint64(0);
  const exp = Number((bits >> 52n) & 0x7ffn);
  const frac = bits & ((1n << 52n) - 1n);
  // value = m * 2^(exp - 1075) (normal) or frac * 2^-1074 (subnormal): as m / 2^e with e >= 0 here.
  const m = exp === 0 ? frac : frac | (1n << 52n);
  const e = 1075 - Math.max(exp, 1);
  return e >= 0 ? [m, BigInt(e)] : [m << BigInt(-e), 0n];
}

/** S, the slack 1 + 1e-12 as binary64: 0x1.0000000001198p+0 = (2^52 + 4504) / 2^52. */
const S_NUM = (1n << 52n) + 4504n;
const S_SHIFT = 52n;

/** floor(A² S² (rows² + cols²) / c) exactly, A = 1 - cutoff in binary64 (format.md). */
function keyBound(rows: number, cols: number, cutoff: number, c: number): bigint {
  const [a, u] = fraction(1 - cutoff);
  const d = BigInt(rows) * BigInt(rows) + BigInt(cols) * BigInt(cols);
  return ((a * a * S_NUM * S_NUM * d) >> (2n * u + 2n * S_SHIFT)) / BigInt(c);
}

/** Keys are exact in binary64 below 2^53: a grid beyond it (a line of 10^8 cells) is refused. */
function checkKeys(rows: number, cols: number): void {
  if (rows * rows + cols * cols >= 2 ** 53) {
    throw new UnsupportedFormatError(`a ${rows} x ${cols} grid's frequency keys exceed 2^53: this decoder does not read it`);
  }
}

function integerCut(q: bigint, rows: number, cols: number, dct: boolean): Cut {
  const most = BigInt(rows) * BigInt(rows) + BigInt(cols) * BigInt(cols);
  const qmax = Number(q < most ? q : most);
  return { legacy: false, qmax, limit: Math.sqrt(qmax) * (dct ? 0.5 : 1) };
}

/** The cut of the file's (or a coarser) cutoff: the legacy radius, or version 1.2's integer bound. */
export function cutOf(rows: number, cols: number, kind: Transform, cutoff: number, legacy: boolean): Cut {
  if (legacy) return { legacy, limit: radiusLimit(rows, cols, cutoff), qmax: NaN };
  checkKeys(rows, cols);
  const dct = kind === "dct";
  return integerCut(keyBound(rows, cols, cutoff, dct ? 1 : 4), rows, cols, dct);
}

/** The base layer's cut (format.md, "BASE"): within the cutoff's circle and reach K cycles per tile of T cells. */
export function baseCut(rows: number, cols: number, cutoff: number, reach: number, T: number, legacy: boolean): Cut {
  if (legacy) {
    const limit = Math.min((reach * Math.max(rows, cols)) / T, (1 - cutoff) * Math.hypot(rows / 2, cols / 2)) * (1 + 1e-12);
    return { legacy, limit, qmax: NaN };
  }
  checkKeys(rows, cols);
  const km = BigInt(reach) * BigInt(Math.max(rows, cols));
  const byReach = (4n * S_NUM * S_NUM * km * km) / ((1n << (2n * S_SHIFT)) * BigInt(T) * BigInt(T));
  const byCutoff = keyBound(rows, cols, cutoff, 1);
  return integerCut(byReach < byCutoff ? byReach : byCutoff, rows, cols, true);
}

const cache = new Map<string, Prefix>();
const MAX_CACHED_COEFS = 1 << 22;
let cachedCoefs = 0;

/** The kept coefficients of a rows x cols grid within `cut` (cutOf, or the base layer's baseCut). */
export function prefix(rows: number, cols: number, kind: Transform, cut: Cut): Prefix {
  const { legacy, limit, qmax } = cut;
  const key = `${rows},${cols},${kind},${legacy},${limit},${qmax}`;
  const hit = cache.get(key);
  if (hit) return hit;
  const C = kind === "dft-half" ? Math.floor(cols / 2) + 1 : cols;
  const ri: number[] = []; // candidate rows (array indices), ascending
  const reach = Math.floor(2 * limit) + 1;
  if (kind === "dct") {
    for (let i = 0; i < Math.min(rows, reach); i++) ri.push(i);
  } else if (kind === "dft-half") {
    const lim = Math.floor(limit) + 1;
    const half = Math.floor((rows + 1) / 2);
    for (let i = 0; i < rows; i++) {
      const di = i < half ? i : i - rows;
      if (Math.abs(di) <= lim) ri.push(i);
    }
  } else {
    const lim = Math.floor(limit) + 1;
    const c0 = Math.floor(rows / 2);
    for (let i = Math.max(0, c0 - lim); i < Math.min(rows, c0 + lim + 1); i++) ri.push(i);
  }
  let j0 = 0;
  let j1 = C;
  if (kind === "dct") j1 = Math.min(cols, reach);
  else if (kind === "dft-half") j1 = Math.min(C, Math.floor(limit) + 2);
  else {
    const c0 = Math.floor(cols / 2);
    const lim = Math.floor(limit) + 1;
    j0 = Math.max(0, c0 - lim);
    j1 = Math.min(cols, c0 + lim + 1);
  }
  // Candidates inside the circle, in row-major order, with the exact integer square of their radius
  // (in half-steps for the DCT): the sort is by that integer (stable, so row-major on ties), then,
  // for a legacy file, within a tie by the writer's hypot value (its last bit can split a tie).
  const half = Math.floor((rows + 1) / 2);
  const nCand = ri.length * (j1 - j0);
  const cPos = new Int32Array(nCand);
  const cRad = new Float64Array(nCand);
  const cSq = new Float64Array(nCand);
  const cI = new Int32Array(nCand);
  const cJ = new Int32Array(nCand);
  let m = 0;
  let sqMax = 0;
  for (const i of ri) {
    const di = kind === "dct" ? i : kind === "dft-half" ? (i < half ? i : i - rows) : i - Math.floor(rows / 2);
    for (let j = j0; j < j1; j++) {
      const dj = kind === "dft-full" ? j - Math.floor(cols / 2) : j;
      const sq = di * di + dj * dj;
      let r: number;
      if (legacy) r = kind === "dct" ? hypot(i / 2, j / 2) : hypot(di, dj);
      else r = sq <= qmax ? Math.sqrt(sq) * (kind === "dct" ? 0.5 : 1) : Infinity;
      if (r <= limit) {
        cPos[m] = i * C + j;
        cRad[m] = r;
        cI[m] = di;
        cJ[m] = dj;
        cSq[m] = sq;
        if (sq > sqMax) sqMax = sq;
        m++;
      }
    }
  }
  let order: Int32Array;
  if (sqMax <= 8 * m + 1024) {
    // Counting sort by the integer square: O(m), stable.
    const start = new Int32Array(sqMax + 2);
    for (let k = 0; k < m; k++) start[cSq[k] + 1]++;
    for (let q = 1; q < start.length; q++) start[q] += start[q - 1];
    order = new Int32Array(m);
    for (let k = 0; k < m; k++) order[start[cSq[k]]++] = k;
  } else {
    order = Int32Array.from({ length: m }, (_, k) => k);
    order.sort((a, b) => cSq[a] - cSq[b] || a - b);
  }
  // Within a run of equal squares a legacy writer's radii may differ in their last bit: order by them.
  for (let a = 0; legacy && a < m;) {
    let b = a + 1;
    while (b < m && cSq[order[b]] === cSq[order[a]]) b++;
    if (b - a > 1) {
      const run = Array.from(order.subarray(a, b));
      run.sort((x, y) => cRad[x] - cRad[y] || x - y);
      order.set(run, a);
    }
    a = b;
  }
  const out: Prefix = {
    shape: [rows, C],
    pos: new Int32Array(m),
    radius: new Float64Array(m),
    angle: new Float64Array(m),
  };
  for (let q = 0; q < m; q++) {
    const k = order[q];
    out.pos[q] = cPos[k];
    out.radius[q] = cRad[k];
    let a: number;
    if (kind === "dct") a = Math.atan2(cI[k] / 2, cJ[k] / 2) / (Math.PI / 2);
    else if (kind === "dft-half") a = (Math.atan2(cI[k], cJ[k]) + Math.PI / 2) / Math.PI;
    else a = (Math.atan2(cI[k], cJ[k]) + Math.PI) / (2 * Math.PI);
    out.angle[q] = Math.min(1, Math.max(0, a));
  }
  // Bounded by coefficients held, not by entries: a crafted file's grids must not pin memory.
  cachedCoefs += m;
  if (cache.size >= 16 || cachedCoefs > MAX_CACHED_COEFS) {
    cache.clear();
    cachedCoefs = m;
  }
  cache.set(key, out);
  return out;
}
