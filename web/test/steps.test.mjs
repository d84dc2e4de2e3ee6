// The format's steps where two languages could disagree, against the Python codec: the coefficient
// order (ties decided by hypot's last bits), the angles' bands, the table models' decays, the
// inverse DCT (scipy's idctn).
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { join } from "node:path";
import { test } from "node:test";
import { addIdct, cutOf, decayOf, prefix, slotsOf, tableModel } from "../dist/internals.mjs";
import { fixtures } from "./helpers.mjs";

const M = JSON.parse(readFileSync(join(fixtures(), "manifest.json"), "utf8"));

for (const c of M.orders) {
  const rule = c.legacy ? "legacy (1.0, 1.1)" : "integer (1.2)";
  test(`${rule} coefficient order of a ${c.rows} x ${c.cols} ${c.transform}/${c.storage} grid at cutoff ${c.cutoff} is the writer's`, () => {
    const kind = c.transform === "dct" ? "dct" : c.storage === "complex64" ? "dft-full" : "dft-half";
    const p = prefix(c.rows, c.cols, kind, cutOf(c.rows, c.cols, kind, c.cutoff, c.legacy));
    assert.equal(p.pos.length, c.order.length);
    let moved = 0;
    for (let k = 0; k < c.order.length; k++) if (p.pos[k] !== c.order[k]) moved++;
    assert.equal(moved, 0, `${moved} coefficients out of place`);
    let radii = 0;
    for (let k = 0; k < c.radius.length; k++) if (p.radius[k] !== c.radius[k]) radii++;
    assert.equal(radii, 0, `${radii} radii differ from the writer's (their bands could)`);
    for (const sectors of [1, 4, 16]) {
      let differ = 0;
      for (let k = 0; k < c.angle.length; k++) {
        const band = (a) => Math.min(Math.floor(a * sectors), sectors - 1);
        if (band(p.angle[k]) !== band(c.angle[k])) differ++;
      }
      assert.equal(differ, 0, `${differ} angles in another of ${sectors} sectors`);
    }
  });
}

test("the table models' decays are the writer's (50-digit decimal)", () => {
  for (let code = 1; code < 256; code++) assert.equal(decayOf(code), M.decays[code], `code ${code}`);
});

test("the inverse DCT is scipy's idctn(type=2, norm='ortho') within 1e-12", () => {
  const { rows, cols, coefs, heights } = M.idct;
  const out = new Float64Array(rows * cols);
  addIdct(out, Float64Array.from(coefs), rows, cols, rows, cols, 0, rows, 0, cols);
  let worst = 0;
  for (let k = 0; k < out.length; k++) worst = Math.max(worst, Math.abs(out[k] - heights[k]));
  assert.ok(worst < 1e-12, `differs by ${worst}`);
});

test("the inverse DCT by FFT equals plain sums on every FFT path (powers of two, mixed radix, Bluestein)", () => {
  // 1024: fft.js; 495 = 3^2 x 5 x 11, 1197 = 3^2 x 7 x 19, 37: the mixed-radix FFT (a generic radix);
  // 804 = 4 x 3 x 67, 643 and 1009 (primes): Bluestein over fft.js.
  let seed = 1;
  const rnd = () => (seed = (seed * 16807) % 2147483647) / 2147483647 - 0.5;
  for (const N of [1, 3, 37, 495, 643, 804, 1009, 1024, 1197]) {
    for (const M of [5, 96, 559]) {
      const K = Math.min(N, 1 + Math.floor(N / 3));
      const L = Math.min(M, 1 + Math.floor(M / 2));
      const g = Float64Array.from({ length: K * L }, rnd);
      const byFft = new Float64Array(N * M);
      const bySums = new Float64Array(N * M);
      addIdct(byFft, g, K, L, N, M, 0, N, 0, M, "fft");
      addIdct(bySums, g, K, L, N, M, 0, N, 0, M, "sums");
      let worst = 0;
      for (let k = 0; k < byFft.length; k++) worst = Math.max(worst, Math.abs(byFft[k] - bySums[k]));
      assert.ok(worst < 1e-11, `${N} x ${M}: differs by ${worst}`);
    }
  }
});

test("a table model's slots bound the symbol of every quantile in them (the narrowed search is the full one)", () => {
  const SHIFT = 12;
  for (const [maxAbs, code] of [[1, 128], [3, 90], [40, 150], [700, 200], [32768, 255], [5000, 10]]) {
    const cdf = tableModel(maxAbs, code, "test");
    const n = 2 * maxAbs + 1;
    const slots = slotsOf(cdf, n);
    assert.equal(slots.length, 2 ** (24 - SHIFT) + 1);
    // Every symbol's first quantile, the one before it, and each slot's bounds.
    const quantiles = [];
    for (let s = 0; s < n; s++) quantiles.push(cdf[s], Math.max(0, cdf[s] - 1));
    for (let t = 0; t < 2 ** (24 - SHIFT); t++) quantiles.push(t << SHIFT, ((t + 1) << SHIFT) - 1);
    for (const q of quantiles) {
      let s = 0;
      while (s + 1 < n && cdf[s + 1] <= q) s++;
      const t = q >>> SHIFT;
      assert.ok(slots[t] <= s && s <= slots[t + 1], `maxAbs ${maxAbs} code ${code}: quantile ${q} is symbol ${s}, slots ${slots[t]}..${slots[t + 1]}`);
    }
  }
});

/** format.md's COEF kind 3 table, steps 1-4, all in BigInt: the reference for tableModel's floats. */
function referenceTable(maxAbs, code) {
  const ONE = 1n << 24n;
  const R = BigInt(decayOf(code));
  const w = [1n << 32n];
  for (let k = 1; k <= maxAbs; k++) w.push((w[k - 1] * R) / 65536n);
  const W = w.reduce((s, v, k) => s + (k ? 2n * v : v), 0n);
  const n = 2 * maxAbs + 1;
  const M = ONE - BigInt(n);
  const fk = w.map((v) => (v === 0n ? 1n : 1n + (v * M) / W));
  const f = Array.from({ length: n }, (_, s) => fk[Math.abs(s - maxAbs)]);
  f[maxAbs] += ONE - fk.reduce((s, v, k) => s + (k ? 2n * v : v), 0n);
  const cdf = [];
  let K = 0n;
  for (let s = 0; s < n; s++) {
    cdf.push(Number((K * M) / ONE) + s);
    K += f[s];
  }
  cdf.push(Number(ONE));
  return cdf;
}

test("the table models built in floats are format.md's integer tables", () => {
  for (const maxAbs of [1, 2, 7, 100, 3000, 32768]) {
    for (let code = 1; code < 256; code += maxAbs > 1000 ? 37 : 5) {
      const got = tableModel(maxAbs, code, "test");
      const want = referenceTable(maxAbs, code);
      let differ = 0;
      for (let s = 0; s < want.length; s++) if (got[s] !== want[s]) differ++;
      assert.equal(differ, 0, `maxAbs ${maxAbs} code ${code}: ${differ} entries differ`);
    }
  }
});
