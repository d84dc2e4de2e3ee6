// The pruned inverse DCT against direct O(N^2) sums written here from the definitions: the FFTs on a
// band of nonzero inputs (a generic radix that skips the zero pairs, Bluestein's convolution cut to
// the band) and addIdct over quarter circles of coefficients, windows and odd and prime sides.
import assert from "node:assert/strict";
import { test } from "node:test";
import { addIdct, BluesteinFft, factorize, MixedFft } from "../dist/internals.mjs";

let seed = 7;
const rnd = () => (seed = (seed * 16807) % 2147483647) / 2147483647 - 0.5;

/** x (complex, length n) zero outside [0, lo) and (n - lo, n), random inside. */
function banded(n, lo) {
  const re = new Float64Array(n);
  const im = new Float64Array(n);
  for (let k = 0; k < n; k++) {
    if (k < lo || k > n - lo) {
      re[k] = rnd();
      im[k] = rnd();
    }
  }
  return [re, im];
}

/** The forward DFT by its definition, exp(-2 pi i j k / n), angles reduced exactly. */
function dft(re, im) {
  const n = re.length;
  const yr = new Float64Array(n);
  const yi = new Float64Array(n);
  for (let j = 0; j < n; j++) {
    let sr = 0;
    let si = 0;
    for (let k = 0; k < n; k++) {
      const a = (-2 * Math.PI * ((j * k) % n)) / n;
      const c = Math.cos(a);
      const s = Math.sin(a);
      sr += re[k] * c - im[k] * s;
      si += re[k] * s + im[k] * c;
    }
    yr[j] = sr;
    yi[j] = si;
  }
  return [yr, yi];
}

function worst(ar, ai, br, bi) {
  let w = 0;
  for (let k = 0; k < ar.length; k++) w = Math.max(w, Math.abs(ar[k] - br[k]), Math.abs(ai[k] - bi[k]));
  return w;
}

// Sides with a generic radix first (67, 43, 11, 13, 7: its zero pairs skipped), small radices only,
// and primes (Bluestein's only way); bands from a single entry to the whole input.
const SIDES = [7, 13, 35, 67 * 3, 2 * 3 * 5 * 11, 13 * 43, 4 * 3 * 67, 97, 263, 337, 1024];

for (const n of SIDES) {
  test(`the FFT of length ${n} (${factorize(n).join(" x ")}) on a band of nonzero inputs is the DFT's`, () => {
    for (const lo of new Set([1, 2, 3, Math.ceil(n / 10), Math.floor(n / 4), Math.floor(n / 2) - 1, Math.ceil(n / 2), Math.ceil(n / 2) + 1, n])) {
      if (lo < 1) continue;
      const [re, im] = banded(n, lo);
      const [er, ei] = dft(re, im);
      const tol = 1e-11 * n;
      if (factorize(n).every((R) => R <= 257)) {
        const fr = re.slice();
        const fi = im.slice();
        new MixedFft(n, factorize(n)).forward(fr, fi, lo);
        const e = worst(fr, fi, er, ei);
        assert.ok(e < tol, `mixed radix, band ${lo}: differs by ${e}`);
      }
      const br = re.slice();
      const bi = im.slice();
      new BluesteinFft(n, lo).forward(br, bi);
      const e = worst(br, bi, er, ei);
      assert.ok(e < tol, `Bluestein, band ${lo}: differs by ${e}`);
    }
  });
}

/** phi_N(k, n) of the orthonormal DCT-II, straight from its definition. */
function phi(N, k, r) {
  return (k === 0 ? Math.sqrt(1 / N) : Math.sqrt(2 / N)) * Math.cos((Math.PI * k * (2 * r + 1)) / (2 * N));
}

/** out (h x w) = sum over the K x L corner g of g[k][l] phi_N(k, r) phi_M(l, c). */
function direct(g, K, L, N, M, r0, h, c0, w) {
  const out = new Float64Array(h * w);
  for (let k = 0; k < K; k++) {
    for (let l = 0; l < L; l++) {
      const x = g[k * L + l];
      if (x === 0) continue;
      for (let r = 0; r < h; r++) {
        const a = x * phi(N, k, r0 + r);
        for (let c = 0; c < w; c++) out[r * w + c] += a * phi(M, l, c0 + c);
      }
    }
  }
  return out;
}

test("addIdct over quarter circles of coefficients, windows and odd or prime sides is the direct sum", () => {
  // [N, M, radius as a fraction of the diagonal]: coarse (a progressive prefix) to wide corners.
  const cases = [[37, 41, 0.1], [67 * 3, 53, 0.3], [101, 97, 0.45], [13, 263, 0.2], [4 * 3 * 67, 29, 0.05], [45, 64, 0.9]];
  for (const [N, M, f] of cases) {
    const radius = f * Math.hypot(N, M);
    const K = Math.min(N, Math.floor(radius) + 1);
    const L = Math.min(M, Math.floor(radius) + 1);
    const g = new Float64Array(K * L);
    for (let k = 0; k < K; k++) for (let l = 0; l < L; l++) if (Math.hypot(k, l) <= radius) g[k * L + l] = rnd();
    const windows = [[0, N, 0, M], [Math.floor(N / 3), Math.ceil(N / 2), 1, M - 1], [N - 1, 1, 0, 1]];
    for (const [r0, h, c0, w] of windows) {
      const want = direct(g, K, L, N, M, r0, h, c0, w);
      let scale = 0;
      for (const v of want) scale = Math.max(scale, Math.abs(v));
      for (const mode of ["fft", "sums", "auto"]) {
        const got = new Float64Array(h * w).fill(1); // addIdct adds
        addIdct(got, g, K, L, N, M, r0, h, c0, w, mode);
        let e = 0;
        for (let q = 0; q < got.length; q++) e = Math.max(e, Math.abs(got[q] - 1 - want[q]));
        assert.ok(e < 1e-12 * Math.max(1, scale) * Math.sqrt(N * M), `${N} x ${M}, radius ${radius.toFixed(1)}, window rows ${r0}+${h} cols ${c0}+${w}, ${mode}: differs by ${e}`);
      }
    }
  }
});
