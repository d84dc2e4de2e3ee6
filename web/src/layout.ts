// Which coefficient is which (format.md, "Which coefficient is which"): the kept prefix of the
// coefficients sorted by radius, ties in row-major order, with each one's radius and angle.

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

/** The radius limit (1 - cutoff) hypot(rows/2, cols/2) (1 + 1e-12), frequency pixels. */
export function radiusLimit(rows: number, cols: number, cutoff: number): number {
  return (1 - cutoff) * Math.hypot(rows / 2, cols / 2) * (1 + 1e-12);
}

const cache = new Map<string, Prefix>();
const MAX_CACHED_COEFS = 1 << 22;
let cachedCoefs = 0;

/** The kept coefficients of a rows x cols grid within `limit` (radiusLimit, or the base layer's). */
export function prefix(rows: number, cols: number, kind: Transform, limit: number): Prefix {
  const key = `${rows},${cols},${kind},${limit}`;
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
  // within a tie, by the writer's hypot value (its last bit can split a tie, format.md).
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
      const r = kind === "dct" ? hypot(i / 2, j / 2) : hypot(di, dj);
      if (r <= limit) {
        cPos[m] = i * C + j;
        cRad[m] = r;
        cI[m] = di;
        cJ[m] = dj;
        const sq = di * di + dj * dj;
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
  // Within a run of equal squares the writer's radii may differ in their last bit: order by them.
  for (let a = 0; a < m;) {
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
