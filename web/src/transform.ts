// Inverse transforms of a low-passed spectrum (format.md, "Decoding" step 3): scipy's
// idctn(type=2, norm="ortho"), numpy's irfft2(norm="ortho") and ifft2(ifftshift(F)).real, separable,
// over the kept corner of the spectrum only. The DCT runs each axis as plain sums or by FFT
// (dct.ts), whichever costs less for the corner's size, and evaluates only the cells asked for (a
// tile of its coded window); the DFTs, used by the paper profile and --transform dft only, are sums.
import { Dct3, MixedFft } from "./dct.js";
import { align16, Kernels, kernels, WasmMemoryError } from "./wasm.js";

/** cos(2 pi m / period) for m = 0 .. period-1: bases at exact integer phase. */
function cosTable(_n: number, period: number): Float64Array {
  const t = new Float64Array(period);
  for (let m = 0; m < period; m++) t[m] = Math.cos((2 * Math.PI * m) / period);
  return t;
}

/** phi_N(k, n) for k < K and n in cells [c0, c0 + w): a K x w matrix, row-major. */
function dctBasis(N: number, K: number, c0: number, w: number): Float64Array {
  const cells = new Int32Array(w);
  for (let c = 0; c < w; c++) cells[c] = c0 + c;
  return dctBasisAt(N, K, cells);
}

/** phi_N(k, n) for k < K and n in `cells`: a K x cells.length matrix, row-major. */
function dctBasisAt(N: number, K: number, cells: Int32Array): Float64Array {
  const table = cosTable(N, 4 * N);
  const w = cells.length;
  const out = new Float64Array(K * w);
  const a0 = 1 / Math.sqrt(N);
  const ak = Math.sqrt(2 / N);
  for (let k = 0; k < K; k++) {
    for (let c = 0; c < w; c++) {
      out[k * w + c] = k === 0 ? a0 : ak * table[(k * (2 * cells[c] + 1)) % (4 * N)];
    }
  }
  return out;
}

/** The inverse orthonormal DCT-II of the coefficients g (a dense K x L corner of the N x M spectrum,
 * row-major) at the cells (rows[i], cols[j]) only: a rows.length x cols.length array, row-major. As
 * plain sums (K L + rows.length K products a sampled column), for a few samples of a narrow corner. */
export function sampleIdct(g: Float64Array, K: number, L: number, N: number, M: number,
  rows: Int32Array, cols: Int32Array): Float64Array {
  const nr = rows.length;
  const nc = cols.length;
  const out = new Float64Array(nr * nc);
  if (K === 0 || L === 0) return out;
  const bc = dctBasisAt(M, L, cols);
  const br = dctBasisAt(N, K, rows);
  // t (K x nc): each row of g along the columns; then each column of t along the rows.
  const t = new Float64Array(K * nc);
  for (let k = 0; k < K; k++) {
    const o = k * nc;
    for (let j = 0; j < L; j++) {
      const x = g[k * L + j];
      if (x === 0) continue;
      const b = j * nc;
      for (let c = 0; c < nc; c++) t[o + c] += x * bc[b + c];
    }
  }
  for (let k = 0; k < K; k++) {
    const o = k * nc;
    for (let i = 0; i < nr; i++) {
      const y = br[k * nr + i];
      const d = i * nc;
      for (let c = 0; c < nc; c++) out[d + c] += y * t[o + c];
    }
  }
  return out;
}

export type IdctMode = "auto" | "sums" | "fft";

/** A strided set of vectors: vector v's element k is at a[off + v * vs + k * es]. */
interface Strided {
  a: Float64Array;
  off: number;
  vs: number;
  es: number;
}

/**
 * out += the inverse DCT along one axis of `nvec` vectors of at most `klen` coefficients (inp), each
 * a length-n transform evaluated at cells [c0, c0 + w) (out's elements), by plain sums or by FFT,
 * whichever costs less (or as `mode` says).
 */
function idctAxis(inp: Strided, nvec: number, klen: number, n: number, c0: number, w: number, out: Strided, mode: IdctMode): void {
  const plan = dctOf(n);
  const useFft = mode === "fft" || (mode === "auto" && fftCost(plan, nvec, klen, w) < sumsCost(nvec, klen, w));
  if (!useFft) {
    const basis = dctBasis(n, klen, c0, w);
    for (let v = 0; v < nvec; v++) {
      const i0 = inp.off + v * inp.vs;
      const o0 = out.off + v * out.vs;
      const es = out.es;
      for (let k = 0; k < klen; k++) {
        const x = inp.a[i0 + k * inp.es];
        if (x === 0) continue;
        const b = k * w;
        if (es === 1) for (let c = 0; c < w; c++) out.a[o0 + c] += x * basis[b + c];
        else for (let c = 0; c < w; c++) out.a[o0 + c * es] += x * basis[b + c];
      }
    }
    return;
  }
  for (let v = 0; v < nvec; v += 2) {
    const two = v + 1 < nvec;
    // Each pair only as long as its longer vector's last nonzero coefficient (a quarter circle's
    // rows shorten): a shorter band prunes the FFT.
    let len = klen;
    const i1 = inp.off + v * inp.vs;
    const i2 = two ? i1 + inp.vs : -1;
    while (len > 0 && inp.a[i1 + (len - 1) * inp.es] === 0 && (!two || inp.a[i2 + (len - 1) * inp.es] === 0)) len--;
    if (len === 0) continue;
    const o1 = out.off + v * out.vs;
    plan.run(inp.a, i1, i2, inp.es, len, out.a, o1, two ? o1 + out.vs : -1, out.es, c0, w);
  }
}

/** DCT plans by length (their tables cost a few trigonometric calls a point): a map's transforms
 * have one or two lengths, a tiled map's windows a few. */
const plans = new Map<number, Dct3>();

function dctOf(n: number): Dct3 {
  let plan = plans.get(n);
  if (!plan) {
    if (plans.size >= 8) plans.clear();
    plan = new Dct3(n);
    plans.set(n, plan);
  }
  return plan;
}

/** Plain sums cost about this many times an FFT's estimated flop each (measured in Node 20 and
 * Chromium: the crossing of the two paths over the shared DEMs' shapes). */
const SUMS_WEIGHT = 2;

function sumsCost(nvec: number, klen: number, w: number): number {
  return SUMS_WEIGHT * nvec * klen * w;
}

function fftCost(plan: Dct3, nvec: number, klen: number, w: number): number {
  return Math.ceil(nvec / 2) * plan.cost(klen) + 2 * nvec * w;
}

function axisCost(nvec: number, klen: number, n: number, w: number): number {
  return Math.min(sumsCost(nvec, klen, w), fftCost(dctOf(n), nvec, klen, w));
}

/** Columns first (L vectors along the N rows, then h vectors along the M columns) or rows first. */
function columnsFirstOf(K: number, L: number, N: number, M: number, h: number, w: number): boolean {
  return axisCost(L, K, N, h) + axisCost(h, L, M, w) <= axisCost(K, L, M, w) + axisCost(w, K, N, h);
}

/** out (h x w) += the inverse orthonormal DCT-II of the coefficients g (a dense K x L corner of the
 * N x M spectrum, row-major), at rows [r0, r0 + h) and columns [c0, c0 + w) of the N x M grid. */
export function addIdct(out: Float64Array, g: Float64Array, K: number, L: number, N: number, M: number,
  r0: number, h: number, c0: number, w: number, mode: IdctMode = "auto"): void {
  if (K === 0 || L === 0) return;
  const k = mode === "sums" ? null : kernels();
  if (k) {
    try {
      const p = idctInKernels(k, g, K, L, N, M, r0, h, c0, w, 0, mode, out);
      out.set(k.view().subarray(p / 8, p / 8 + h * w));
      return;
    } catch (e) {
      if (!(e instanceof WasmMemoryError)) throw e;
    }
  }
  const columnsFirst = columnsFirstOf(K, L, N, M, h, w);
  if (columnsFirst) {
    // t (h x L): column j of g (element stride L) to column j of t.
    const t = new Float64Array(h * L);
    idctAxis({ a: g, off: 0, vs: 1, es: L }, L, K, N, r0, h, { a: t, off: 0, vs: 1, es: L }, mode);
    idctAxis({ a: t, off: 0, vs: L, es: 1 }, h, L, M, c0, w, { a: out, off: 0, vs: w, es: 1 }, mode);
  } else {
    // u (K x w): row i of g to row i of u; then column c of u to column c of out.
    const u = new Float64Array(K * w);
    idctAxis({ a: g, off: 0, vs: L, es: 1 }, K, L, M, c0, w, { a: u, off: 0, vs: w, es: 1 }, mode);
    idctAxis({ a: u, off: 0, vs: 1, es: w }, w, K, N, r0, h, { a: out, off: 0, vs: 1, es: w }, mode);
  }
}

/** A strided set of vectors in the kernels' memory: vector v's element k at byte p + 8 (off + v vs +
 * k es). */
interface KStrided {
  p: number;
  off: number;
  vs: number;
  es: number;
}

/**
 * The inverse DCT of the corner g as addIdct's, computed in the kernels' memory, added to `init`
 * (h x w) when given, else to zeros: returns the byte offset of its h x w result in the kernels'
 * memory, followed by `extra` bytes of scratch (16-aligned), both valid until the next use of the
 * kernels. Throws WasmMemoryError when the memory cannot grow.
 */
export function idctInKernels(k: Kernels, g: Float64Array, K: number, L: number, N: number, M: number,
  r0: number, h: number, c0: number, w: number, extra: number, mode: IdctMode = "auto", init: Float64Array | null = null): number {
  return inKernels(k, g, K, L, N, M, r0, h, c0, w, extra, mode, init, null).grid;
}

/**
 * The inverse of the whole N x M grid, with the finishing pass fused into its last axis where that
 * runs by FFT (each output finished as it comes, not in a pass over the grid): before the passes,
 * `fin(finP, extraP, down)` writes the finishing descriptor (kernels.ts finishZeros) at finP, 80
 * bytes, given the offset of the `extra` bytes of scratch and whether the last axis runs down the
 * columns. Returns the grid's offset, the extra bytes' and whether the pass was fused (else the
 * grid holds the heights before the finishing pass and fin was not called).
 */
export function idctFinishedInKernels(k: Kernels, g: Float64Array, K: number, L: number, N: number, M: number,
  extra: number, fin: (finP: number, extraP: number, down: boolean) => void): { grid: number; extra: number; fused: boolean } {
  return inKernels(k, g, K, L, N, M, 0, N, 0, M, extra + 80, "auto", null, fin);
}

function inKernels(k: Kernels, g: Float64Array, K: number, L: number, N: number, M: number,
  r0: number, h: number, c0: number, w: number, extra: number, mode: IdctMode, init: Float64Array | null,
  fin: ((finP: number, extraP: number, down: boolean) => void) | null): { grid: number; extra: number; fused: boolean } {
  const columnsFirst = columnsFirstOf(K, L, N, M, h, w);
  const fused = fin !== null && (columnsFirst ? usesFft(h, L, M, w, mode) : usesFft(w, K, N, h, mode));
  const tn = columnsFirst ? h * L : K * w;
  const gridBytes = align16(8 * h * w);
  const extraBytes = align16(extra);
  // The plain sums' basis (K x h or L x w, the larger of an axis's).
  const basisN = Math.max(K * h, L * w);
  const outP = k.scratch(gridBytes + extraBytes + 8 * K * L + 8 * tn + 8 * basisN);
  const gP = outP + gridBytes + extraBytes;
  const tP = gP + 8 * K * L;
  const bP = tP + 8 * tn;
  const f = k.view();
  if (init) f.set(init, outP / 8);
  else if (!fused) f.fill(0, outP / 8, outP / 8 + h * w);
  f.set(g.subarray(0, K * L), gP / 8);
  f.fill(0, tP / 8, tP / 8 + tn);
  // The descriptor in the first 80 bytes of the extra scratch, the caller's bytes after it.
  const finP = fused ? outP + gridBytes : 0;
  if (fused) fin!(finP, outP + gridBytes + 80, !columnsFirst);
  if (columnsFirst) {
    // t as L x h (t transposed): the second axis reads four adjacent vectors a call.
    idctAxisKernels(k, { p: gP, off: 0, vs: 1, es: L }, L, K, N, r0, h, { p: tP, off: 0, vs: h, es: 1 }, mode, 0, bP);
    idctAxisKernels(k, { p: tP, off: 0, vs: 1, es: h }, h, L, M, c0, w, { p: outP, off: 0, vs: w, es: 1 }, mode, finP, bP);
  } else {
    idctAxisKernels(k, { p: gP, off: 0, vs: L, es: 1 }, K, L, M, c0, w, { p: tP, off: 0, vs: w, es: 1 }, mode, 0, bP);
    idctAxisKernels(k, { p: tP, off: 0, vs: 1, es: w }, w, K, N, r0, h, { p: outP, off: 0, vs: 1, es: w }, mode, finP, bP);
  }
  return { grid: outP, extra: outP + gridBytes + (fin ? 80 : 0), fused };
}

function usesFft(nvec: number, klen: number, n: number, w: number, mode: IdctMode): boolean {
  return mode === "fft" || (mode === "auto" && fftCost(dctOf(n), nvec, klen, w) < sumsCost(nvec, klen, w));
}

/** idctAxis on the kernels' memory: the same sums or FFTs, the FFTs two pairs of vectors a call
 * (pairs whose FFT is the same plan and band branch; a pair alone otherwise, so that each pair's
 * arithmetic is the TypeScript path's). */
function idctAxisKernels(k: Kernels, inp: KStrided, nvec: number, klen: number, n: number, c0: number, w: number,
  out: KStrided, mode: IdctMode, finP: number, basisP: number): void {
  const plan = dctOf(n);
  if (!usesFft(nvec, klen, n, w, mode)) {
    k.view().set(dctBasis(n, klen, c0, w), basisP / 8);
    k.ex.sumsAxis(inp.p, inp.off, inp.vs, inp.es, nvec, klen, basisP, out.p, out.off, out.vs, out.es, w);
    return;
  }
  const dct = k.dct(plan);
  type Pair = { v: number; two: boolean; K: number; f: ReturnType<Dct3["fft"]["pick"]>; narrow: boolean };
  const run = (A: Pair, B: Pair | null) => {
    const fp = A.f instanceof MixedFft ? k.mixed(A.f) : k.bluestein(A.f);
    const i0 = inp.off + A.v * inp.vs;
    const o0 = out.off + A.v * out.vs;
    const i2 = B ? inp.off + B.v * inp.vs : -1;
    const o2 = B ? out.off + B.v * out.vs : -1;
    k.ex.dctGroup(dct, A.f instanceof MixedFft ? 0 : 1, fp, inp.p, i0, A.two ? i0 + inp.vs : -1, i2, B?.two ? i2 + inp.vs : -1,
      inp.es, B ? Math.max(A.K, B.K) : A.K, out.p, o0, A.two ? o0 + out.vs : -1, o2, B?.two ? o2 + out.vs : -1, out.es, c0, w, finP);
  };
  let pending: Pair | null = null;
  for (let v = 0; v < nvec; v += 2) {
    const two = v + 1 < nvec;
    let len = klen;
    const a = k.view();
    const i1 = inp.p / 8 + inp.off + v * inp.vs;
    const i2 = two ? i1 + inp.vs : -1;
    while (len > 0 && a[i1 + (len - 1) * inp.es] === 0 && (!two || a[i2 + (len - 1) * inp.es] === 0)) len--;
    if (len === 0) {
      // Vectors of zeros: their cells are finished as zeros.
      if (finP) for (let u = v; u < Math.min(v + 2, nvec); u++) k.ex.finishZeros(finP, out.off + u * out.vs, out.es, w);
      continue;
    }
    const K = Math.min(len, n);
    const pair: Pair = { v, two, K, f: plan.fft.pick(K), narrow: 2 * K - 1 < n };
    if (pending && pending.f === pair.f && pending.narrow === pair.narrow) {
      run(pending, pair);
      pending = null;
    } else {
      if (pending) run(pending, null);
      pending = pair;
    }
  }
  if (pending) run(pending, null);
}

/** out (rows x cols) = irfft2(F, s=(rows, cols), norm="ortho") for F of shape rows x (cols//2 + 1)
 * given by its kept entries (flat positions, values real and imaginary interleaved). */
export function irfft2(pos: Int32Array, values: Float64Array, rows: number, cols: number, out: Float64Array): void {
  const C = Math.floor(cols / 2) + 1;
  let J = 0;
  for (let k = 0; k < pos.length; k++) J = Math.max(J, (pos[k] % C) + 1);
  const cr = cosTable(rows, rows);
  const sr = sinTable(rows);
  // Pass 1: inverse complex DFT along the rows axis, column by column: T (rows x J) complex.
  const tre = new Float64Array(rows * J);
  const tim = new Float64Array(rows * J);
  for (let k = 0; k < pos.length; k++) {
    const i = Math.floor(pos[k] / C);
    const j = pos[k] - i * C;
    const re = values[2 * k];
    const im = values[2 * k + 1];
    if (re === 0 && im === 0) continue;
    for (let r = 0, m = 0; r < rows; r++, m = m + i >= rows ? m + i - rows : m + i) {
      const c = cr[m];
      const s = sr[m];
      tre[r * J + j] += re * c - im * s;
      tim[r * J + j] += re * s + im * c;
    }
  }
  // Pass 2: the real inverse along the columns axis (Hermitian half: DC and Nyquist taken as real).
  const cc = cosTable(cols, cols);
  const sc = sinTable(cols);
  const norm = 1 / Math.sqrt(rows * cols);
  for (let r = 0; r < rows; r++) {
    for (let j = 0; j < J; j++) {
      let re = tre[r * J + j];
      let im = tim[r * J + j];
      const twice = j === 0 || (cols % 2 === 0 && j === cols / 2) ? 1 : 2;
      if (twice === 1) im = 0;
      re *= twice * norm;
      im *= twice * norm;
      if (re === 0 && im === 0) continue;
      const o = r * cols;
      for (let c = 0, m = 0; c < cols; c++, m = m + j >= cols ? m + j - cols : m + j) {
        out[o + c] += re * cc[m] - im * sc[m];
      }
    }
  }
}

/** out (rows x cols) = ifft2(ifftshift(F)).real for the fftshifted F given by its kept entries. */
export function ifft2Shifted(pos: Int32Array, values: Float64Array, rows: number, cols: number, out: Float64Array): void {
  const cr = cosTable(rows, rows);
  const cc = cosTable(cols, cols);
  const sr = sinTable(rows);
  const sc = sinTable(cols);
  const hr = Math.floor(rows / 2);
  const hc = Math.floor(cols / 2);
  const js: number[] = [];
  const slot = new Map<number, number>();
  for (let k = 0; k < pos.length; k++) {
    const j = pos[k] % cols;
    if (!slot.has(j)) {
      slot.set(j, js.length);
      js.push(j);
    }
  }
  const J = js.length;
  const tre = new Float64Array(rows * J);
  const tim = new Float64Array(rows * J);
  for (let k = 0; k < pos.length; k++) {
    const i = Math.floor(pos[k] / cols);
    const s = slot.get(pos[k] - i * cols)!;
    const du = i - hr;
    const re = values[2 * k];
    const im = values[2 * k + 1];
    const step = ((du % rows) + rows) % rows;
    for (let r = 0, m = 0; r < rows; r++, m = m + step >= rows ? m + step - rows : m + step) {
      const c = cr[m];
      const sn = sr[m];
      tre[r * J + s] += re * c - im * sn;
      tim[r * J + s] += re * sn + im * c;
    }
  }
  const norm = 1 / (rows * cols);
  for (let r = 0; r < rows; r++) {
    for (let s = 0; s < J; s++) {
      const re = tre[r * J + s] * norm;
      const im = tim[r * J + s] * norm;
      const dv = js[s] - hc;
      const o = r * cols;
      const step = ((dv % cols) + cols) % cols;
      for (let c = 0, m = 0; c < cols; c++, m = m + step >= cols ? m + step - cols : m + step) {
        out[o + c] += re * cc[m] - im * sc[m];
      }
    }
  }
}

/** sin(2 pi m / N) for m = 0 .. N-1. */
function sinTable(n: number): Float64Array {
  const t = new Float64Array(n);
  for (let m = 0; m < n; m++) t[m] = Math.sin((2 * Math.PI * m) / n);
  return t;
}
