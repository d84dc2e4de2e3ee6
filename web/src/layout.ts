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
  const pos: number[] = [];
  const rad: number[] = [];
  const ang: number[] = [];
  const half = Math.floor((rows + 1) / 2);
  for (const i of ri) {
    for (let j = j0; j < j1; j++) {
      let r: number;
      let a: number;
      if (kind === "dct") {
        r = hypot(i / 2, j / 2);
        a = Math.atan2(i / 2, j / 2) / (Math.PI / 2);
      } else if (kind === "dft-half") {
        const di = i < half ? i : i - rows;
        r = hypot(di, j);
        a = (Math.atan2(di, j) + Math.PI / 2) / Math.PI;
      } else {
        const du = i - Math.floor(rows / 2);
        const dv = j - Math.floor(cols / 2);
        r = hypot(du, dv);
        a = (Math.atan2(du, dv) + Math.PI) / (2 * Math.PI);
      }
      if (r <= limit) {
        pos.push(i * C + j);
        rad.push(r);
        ang.push(a);
      }
    }
  }
  const order = Array.from({ length: pos.length }, (_, k) => k);
  order.sort((a, b) => rad[a] - rad[b] || a - b); // candidates are in row-major order: ties keep it
  const out: Prefix = {
    shape: [rows, C],
    pos: Int32Array.from(order, (k) => pos[k]),
    radius: Float64Array.from(order, (k) => rad[k]),
    angle: Float64Array.from(order, (k) => Math.min(1, Math.max(0, ang[k]))),
  };
  if (cache.size > 16) cache.clear();
  cache.set(key, out);
  return out;
}
