// The WebAssembly SIMD kernels (web/wasm/kernels.ts) against the TypeScript path they replace: the
// same operations in the same order, so the same heights to the bit (a zero's sign aside), on every
// fixture map (whole, windows, float32, progressive prefixes and previews) and on inverse DCTs of
// sides that take each FFT (radices 2 to 5, a generic odd radix, Bluestein's), bands and windows.
import assert from "node:assert/strict";
import { existsSync, mkdtempSync, readdirSync, readFileSync, rmSync } from "node:fs";
import { createServer } from "node:http";
import { tmpdir } from "node:os";
import { join } from "node:path";
import { test } from "node:test";
import CRC32 from "crc-32";
import puppeteer from "puppeteer-core";
import { decode, ready, useWasm } from "../dist/dftpcc.mjs";
import * as internals from "../dist/internals.mjs";
import { bytes, fixtures, WEB } from "./helpers.mjs";

const DIR = fixtures();
// The WebAssembly zstd decoder loaded before the comparisons: the kernels' side of each is all WebAssembly.
const zstdLoaded = await ready();

/** Index of the first element where a and b differ (NaN equal to NaN, 0 to -0), or -1. */
function firstDiff(a, b) {
  if (a.length !== b.length) return 0;
  for (let k = 0; k < a.length; k++) if (!(a[k] === b[k] || (Number.isNaN(a[k]) && Number.isNaN(b[k])))) return k;
  return -1;
}

/** decode(data, options) by the kernels and by TypeScript alone: the results, or the errors' texts. */
function both(data, options) {
  const out = [];
  for (const on of [true, false]) {
    useWasm(on);
    try {
      out.push(decode(data, options));
    } catch (e) {
      out.push(`${e.name}: ${e.message}`);
    } finally {
      useWasm(true);
    }
  }
  return out;
}

test("the kernels load in Node (WebAssembly SIMD), and useWasm switches them off and on", () => {
  assert.ok(internals.kernels(), "no WebAssembly SIMD kernels");
  assert.ok(zstdLoaded, "the WebAssembly zstd decoder did not load");
  assert.equal(useWasm(false), false);
  assert.equal(useWasm(true), true);
});

const maps = readdirSync(DIR).filter((n) => n.endsWith(".dftpc")).sort();
// Small maps, large ones, then small again: the kernels' memory grows and its plans are rebuilt.
const order = [...maps, ...maps.slice().reverse()];

test("every fixture map decodes to the same heights by the kernels and by TypeScript", () => {
  let compared = 0;
  for (const name of order) {
    const data = bytes(join(DIR, name));
    for (const options of [{}, { float32: true }]) {
      const [w, t] = both(data, options);
      if (typeof t === "string") {
        assert.equal(w, t, `${name}: the paths fail differently`);
        continue;
      }
      assert.equal(typeof w, "object", `${name}: ${w}`);
      assert.equal(w.heights.constructor, t.heights.constructor, name);
      assert.equal(firstDiff(w.heights, t.heights), -1, `${name} ${JSON.stringify(options)}: heights differ`);
      assert.equal(firstDiff(w.mask, t.mask), -1, `${name}: masks differ`);
      assert.deepEqual(w.statistics, t.statistics, name);
      compared++;
      const { width: W, height: H } = t;
      if (options.float32 || W < 4 || H < 4) continue;
      // A window inside the grid, with odd sides (the kernels' pairs of cells and a single one).
      const win = { rows: [1, H - 2], cols: [1, Math.max(2, W - 2)] };
      const [ww, tw] = both(data, { window: win });
      assert.equal(firstDiff(ww.heights, tw.heights), -1, `${name} window: heights differ`);
      assert.deepEqual(ww.statistics, tw.statistics, `${name} window`);
      if (!t.header.tiled) {
        for (const f of [0.05, 0.3, 0.6]) {
          const opts = { fileSize: data.length };
          const prefix = data.subarray(0, Math.floor(f * data.length));
          const [wp, tp] = both(prefix, opts);
          if (typeof tp === "string") {
            assert.equal(wp, tp, `${name} prefix ${f}`);
            continue;
          }
          assert.equal(firstDiff(wp.heights, tp.heights), -1, `${name} prefix ${f}: heights differ`);
          // With the kernels a preview is the exact decode (cheaper than the TypeScript samples).
          const pv = decode(prefix, { ...opts, preview: true });
          assert.equal(pv.stride, undefined, `${name} prefix ${f}: a preview sampled`);
          assert.equal(firstDiff(pv.heights, tp.heights), -1, `${name} prefix ${f} preview: heights differ`);
        }
      }
    }
  }
  assert.ok(compared >= maps.length, `compared ${compared} decodes`);
});

let seed = 11;
const rnd = () => (seed = (seed * 16807) % 2147483647) / 2147483647 - 0.5;

/** addIdct by the kernels and by TypeScript alone, into the same random starting grid. */
function idctBoth(K, L, N, M, r0, h, c0, w, mode, zeroRows) {
  const g = new Float64Array(K * L);
  // A quarter circle of coefficients (rows shorten: pairs of vectors with different bands), some
  // rows all zeros (vectors the FFT skips).
  for (let i = 0; i < K; i++) {
    const len = zeroRows && i % 5 === 3 ? 0 : Math.ceil(L * Math.sqrt(Math.max(0, 1 - (i / K) ** 2)));
    for (let j = 0; j < len; j++) g[i * L + j] = rnd();
  }
  const init = new Float64Array(h * w).map(() => rnd());
  const out = [];
  for (const on of [true, false]) {
    internals.useWasm(on);
    const o = init.slice();
    internals.addIdct(o, g, K, L, N, M, r0, h, c0, w, mode);
    out.push(o);
  }
  internals.useWasm(true);
  return out;
}

// Sides by their FFTs: 2^k (radix 4 and 2), 3 and 5 mixed, a generic odd radix first (7, 11, 13,
// 43, 67), primes and large prime factors (Bluestein's over a smooth length).
const SIDES = [2, 3, 7, 16, 30, 35, 67 * 3, 2 * 3 * 5 * 11, 13 * 43, 4 * 3 * 67, 97, 263, 337, 349, 1024, 3 * 347];

for (const N of SIDES) {
  test(`addIdct on side ${N}: the kernels give the TypeScript path's bits`, () => {
    const M = SIDES[(SIDES.indexOf(N) + 5) % SIDES.length];
    for (const [K, L] of [[1, 1], [Math.ceil(N / 3), Math.ceil(M / 2)], [N, M], [Math.max(1, N >> 3), M]]) {
      for (const mode of ["fft", "auto"]) {
        const cases = [[0, N, 0, M], [Math.floor(N / 3), Math.max(1, N >> 1), Math.floor(M / 4), Math.max(1, M >> 1)]];
        for (const [r0, h, c0, w] of cases) {
          const [a, b] = idctBoth(K, L, N, M, r0, h, c0, w, mode, K > 4);
          const k = firstDiff(a, b);
          assert.equal(k, -1, `K ${K} L ${L} N ${N} M ${M} rows ${r0}+${h} cols ${c0}+${w} ${mode}: ${a[k]} vs ${b[k]}`);
        }
      }
    }
  });
}

/** finishWindow's heights from the TypeScript path's inverse, written here from its definition. */
function finishedByTypeScript(g, K, L, rows, cols, mask, z0, [a, b, c], f32) {
  internals.useWasm(false);
  const h = new Float64Array(rows * cols);
  internals.addIdct(h, g, K, L, rows, cols, 0, rows, 0, cols);
  internals.useWasm(true);
  const heights = f32 ? new Float32Array(rows * cols) : new Float64Array(rows * cols);
  let minZ = Infinity;
  let maxZ = -Infinity;
  let cells = 0;
  for (let r = 0; r < rows; r++) {
    for (let q = 0; q < cols; q++) {
      const k = r * cols + q;
      if (!mask[k]) {
        heights[k] = NaN;
        continue;
      }
      const z = h[k] + (z0 + (a + c * r) + b * q);
      heights[k] = z;
      minZ = Math.min(minZ, z);
      maxZ = Math.max(maxZ, z);
      cells++;
    }
  }
  return { heights, minZ, maxZ, cells };
}

// The finishing pass fused into the inverse's last axis: along rows (200 x 180 and 128 x 256 run
// columns first) and down columns (90 x 77 and 160 x 240 run rows first), with the vectors of zeros
// the inverse skips (a corner of zeros: every vector is one), float64 and float32, a plane and holes;
// and not fused (97 x 120's narrow corner: its last axis by plain sums, then finish()).
for (const [rows, cols, K, L] of [[90, 77, 60, 50], [200, 180, 150, 120], [160, 240, 130, 200], [128, 256, 100, 200], [97, 120, 3, 110]]) {
  for (const zeros of [false, true]) {
    test(`the fused finishing pass on a ${rows} x ${cols} grid, a ${K} x ${L} corner${zeros ? " of zeros" : ""}: TypeScript's heights`, () => {
      const g = new Float64Array(K * L);
      if (!zeros) for (let k = 0; k < g.length; k++) g[k] = 100 * rnd() / (1 + k);
      const mask = new Uint8Array(rows * cols).map((_, k) => (k % 11 === 3 ? 0 : 1));
      const plane = [3.25, 0.01 * rnd(), 0.02 * rnd()];
      for (const f32 of [false, true]) {
        const got = internals.cornerFinished(internals.kernels(), { g, K, L }, mask, rows, cols, [0, rows, 0, cols], 1234.5, plane, f32);
        const want = finishedByTypeScript(g, K, L, rows, cols, mask, 1234.5, plane, f32);
        assert.equal(firstDiff(got.heights, want.heights), -1, `f32 ${f32}: heights differ`);
        assert.deepEqual([got.minZ, got.maxZ, got.cells], [want.minZ, want.maxZ, want.cells]);
      }
    });
  }
}

test("the kernels' ANS decoder gives the TypeScript decoder's symbols, on any words (damaged ones too)", () => {
  const k = internals.kernels();
  let seed = 12345;
  const rand = () => ((seed = (Math.imul(seed, 1103515245) + 12345) >>> 0) / 2 ** 32);
  let compared = 0;
  // Narrow and wide alphabets (a wide one's table searched through its slots), groups below and above
  // the TypeScript path's slotted size, and word runs that end before the symbols do (state refills stop).
  for (const maxAbs of [1, 3, 40, 2000, 23118]) {
    for (const nwords of [0, 1, 2, 7, 3000]) {
      const counts = [1, 5, 300, 1024, 2500].filter(() => rand() < 0.8);
      if (!counts.length) counts.push(17);
      const codes = counts.map(() => 1 + Math.floor(rand() * 255));
      const total = counts.reduce((a, b) => a + b, 0) + 33; // 33 positions in no group stay zero
      const words = new Uint8Array(4 * nwords);
      for (let b = 0; b < words.length; b++) words[b] = Math.floor(rand() * 256);
      if (nwords) words[words.length - 1] |= 1; // a last word of zero is refused before either path
      const perm = Int32Array.from({ length: total }, (_, i) => i);
      for (let i = total - 1; i > 0; i--) {
        const j = Math.floor(rand() * (i + 1));
        [perm[i], perm[j]] = [perm[j], perm[i]];
      }
      const at = perm.subarray(0, total - 33);
      const models = codes.map((c) => internals.tableModel(maxAbs, c, "test"));
      const ts = new Float64Array(total);
      const coder = new internals.AnsDecoder(words, "test");
      let from = 0;
      counts.forEach((n, q) => {
        internals.decodeGroup(coder, models[q], maxAbs, ts, at.subarray(from, from + n), n);
        from += n;
      });
      const wasm = new Float64Array(total).fill(7); // the kernel's zeros overwrite whatever was there
      internals.ansInKernels(k, words, counts.map((n, q) => ({ cdf: models[q], count: n })), maxAbs, at, wasm);
      assert.equal(firstDiff(wasm, ts), -1, `maxAbs ${maxAbs}, ${nwords} words, groups ${counts}: symbols differ`);
      compared++;
    }
  }
  assert.equal(compared, 25);
});

/** decode-like f() by the kernels and by TypeScript alone: the results, or the errors' texts. */
function bothPaths(f) {
  const out = [];
  for (const on of [true, false]) {
    internals.useWasm(on);
    try {
      out.push(f());
    } catch (e) {
      out.push(`${e.name}: ${e.message}`);
    } finally {
      internals.useWasm(true);
    }
  }
  return out;
}

const u32le = (v) => [v & 255, (v >>> 8) & 255, (v >>> 16) & 255, (v >>> 24) & 255];

/** A RESD section of one kind-5 chunk holding `total` values, around `body`. */
function predictedSection(body, total) {
  const crc = CRC32.buf(body) >>> 0;
  return Uint8Array.from([...u32le(1), ...u32le(total), ...u32le(body.length), ...u32le(crc), ...u32le(5), ...body]);
}

test("the kernels' predicted residual decoder (RESD kind 5) gives the TypeScript path's integers, or its refusal, on random chunks", () => {
  let seed = 424242;
  const rand = () => ((seed = (Math.imul(seed, 1103515245) + 12345) >>> 0) / 2 ** 32);
  const pick = (a) => a[Math.floor(rand() * a.length)];
  const verdicts = { decoded: 0, refused: 0 };
  // Rows and columns of one (rules 1-4 everywhere), narrow grids, and grids with an interior.
  const shapes = [[1, 1], [1, 9], [8, 1], [2, 2], [3, 5], [5, 3], [17, 4], [40, 61], [97, 130]];
  for (let trial = 0; trial < 300; trial++) {
    const [rows, cols] = shapes[trial % shapes.length];
    const density = pick([1, 1, 0.7, 0.2]);
    const mask = Uint8Array.from({ length: rows * cols }, () => (rand() < density ? 1 : 0));
    const total = mask.reduce((a, b) => a + b, 0);
    // Weights summing to 2**16 (a real fit), small random ones, ones near the 2**24 limit (values
    // that pass 2**26, the TypeScript path's exact-float bound, then 2**31: a refusal), and halves of
    // 2**16, positive and negative (sums halfway between two integers: the rounding and the floor).
    const style = trial % 5;
    const weights = Array.from({ length: 7 }, () => (style === 0 ? 0 : style === 1 ? Math.floor((rand() - 0.5) * 2 ** 17)
      : style === 2 ? Math.floor((rand() - 0.5) * 2 ** 25) : style === 4 ? 32768 * Math.floor(rand() * 5 - 2) : 0));
    if (style === 0) weights[Math.floor(rand() * 7)] = 65536;
    if (style === 3) [weights[0], weights[1], weights[2]] = [2 ** 17, 2 ** 17, -(2 ** 17) + 1];
    const C = 1 + Math.floor(rand() * 64);
    const codes = Array.from({ length: C }, () => (rand() < 0.2 ? 0 : 1 + Math.floor(rand() * 255)));
    const widths = codes.filter((c) => c).map(() => pick([1, 1, 2, 3, 7, 40, 300, 2 ** 15, trial === 7 ? 0 : 5]));
    const nwords = pick([0, 1, 2, 5, 60, 4000]);
    const body = [];
    for (const w of weights) body.push(...u32le(w | 0));
    body.push(C, ...codes);
    for (const w of widths) body.push(w & 255, w >> 8);
    for (let k = 0; k < 4 * nwords; k++) body.push(Math.floor(rand() * 256));
    if (nwords) body[body.length - 1] |= 1; // a last word of 0 is refused alike (AnsDecoder)
    const section = predictedSection(Uint8Array.from(body), total);
    const [w, t] = bothPaths(() => internals.decodeResidual(section, mask, rows, cols));
    if (typeof t === "string") {
      assert.equal(w, t, `trial ${trial}: the paths refuse differently`);
      verdicts.refused++;
      continue;
    }
    assert.equal(typeof w, "object", `trial ${trial}: ${w}`);
    const k = firstDiff(w, t);
    assert.equal(k, -1, `trial ${trial} (${rows} x ${cols}, weights ${weights}): value ${k} is ${w[k]} by the kernels, ${t[k]} by TypeScript`);
    verdicts.decoded++;
  }
  // Both outcomes are exercised: decodes of every shape, and refusals (values past 2**31, tables).
  assert.ok(verdicts.decoded >= 150 && verdicts.refused >= 10, JSON.stringify(verdicts));
});

/** A zstd frame of one raw block (bytes.length <= 255): a MASK's seed lines without an encoder. */
function rawZstd(bytes) {
  const n = bytes.length;
  return [0x28, 0xb5, 0x2f, 0xfd, 0x20, n, ((n << 3) | 1) & 255, (n >> 5) & 255, (n >> 13) & 255, ...bytes];
}

test("the kernels' context-coded mask (MASK kinds 2 and 3, a sparse residual's picture) gives the TypeScript path's bits on random words", () => {
  let seed = 777;
  const rand = () => ((seed = (Math.imul(seed, 1103515245) + 12345) >>> 0) / 2 ** 32);
  let compared = 0;
  for (const [rows, cols] of [[1, 1], [1, 40], [30, 1], [7, 9], [64, 50], [33, 120], [200, 150]]) {
    for (const kind of [2, 3]) {
      const transposed = rows > cols ? 1 : 0;
      const n = transposed ? cols : rows;
      const w = transposed ? rows : cols;
      for (const stripe of [1, 3, 16, n]) {
        const L = Math.min(stripe, n);
        const seeds = Math.ceil(n / L) - 1 + (kind === 3 ? 1 : 0);
        if (3 * seeds * 4 > 255) continue; // one raw zstd block of up to 255 bytes
        // Each seed line: zeros, then ones from a random column (two runs; one run when it is 0 or w).
        const values = [];
        for (let s = 0; s < seeds; s++) {
          const a = Math.floor(rand() * (w + 1));
          if (a === 0 || a === w) values.push(1, w);
          else values.push(2, a, w - a);
        }
        const planes = [0, 1, 2, 3].flatMap((b) => values.map((v) => (v >>> (8 * b)) & 255));
        const frame = seeds ? rawZstd(planes) : [];
        const nwords = 1 + Math.floor(rand() * 3 * Math.max(1, (rows * cols) / 64));
        const words = Array.from({ length: 4 * nwords }, () => Math.floor(rand() * 256));
        words[words.length - 1] |= 1;
        const p = Uint8Array.from([kind, transposed, ...u32le(stripe), ...u32le(frame.length), ...frame, ...words]);
        const [a, b] = bothPaths(() => internals.decodeMask(p, rows, cols));
        assert.equal(typeof b, "object", `${rows} x ${cols} kind ${kind} stripe ${stripe}: ${b}`);
        assert.equal(firstDiff(a, b), -1, `${rows} x ${cols} kind ${kind} stripe ${stripe}: the bits differ`);
        compared++;
      }
    }
  }
  assert.ok(compared >= 40, `compared ${compared}`);
});

test("a kernels' decode leaves the caller's buffers alone: the heights outlive the next decode", () => {
  const name = maps.find((n) => n.startsWith("gale_default"));
  const data = bytes(join(DIR, name));
  const a = decode(data);
  const copy = a.heights.slice();
  decode(bytes(join(DIR, maps.find((n) => n.startsWith("davos")))));
  decode(data, { float32: true });
  assert.equal(firstDiff(a.heights, copy), -1);
});

test("in Chromium (a page's main thread) the kernels load and give the TypeScript path's bits", async (t) => {
  const CHROMIUM = process.env.CHROMIUM ?? "/usr/bin/chromium";
  assert.ok(existsSync(CHROMIUM), `${CHROMIUM} is missing: apt-get install chromium (or set CHROMIUM)`);
  // The first maps, and maps with a residual layer (sparse and predicted).
  const untiled = maps.filter((n) => !n.includes("tiled"));
  const names = [...untiled.slice(0, 6), ...untiled.filter((n) => /max_?err/.test(n))];
  const server = createServer((req, res) => {
    const file = req.url === "/dftpcc.mjs" ? join(WEB, "dist", "dftpcc.mjs") : join(DIR, req.url.slice(1).replace(/[^\w.-]/g, ""));
    if (req.url === "/" || !existsSync(file)) {
      res.writeHead(req.url === "/" ? 200 : 404, { "content-type": "text/html" });
      res.end("<!doctype html><title>wasm</title>");
      return;
    }
    res.writeHead(200, { "content-type": file.endsWith(".mjs") ? "text/javascript" : "application/octet-stream" });
    res.end(readFileSync(file));
  });
  await new Promise((resolve) => server.listen(0, "127.0.0.1", resolve));
  const work = mkdtempSync(join(tmpdir(), "dftpcc-wasm-test-"));
  const browser = await puppeteer.launch({ executablePath: CHROMIUM, headless: true, pipe: true,
    args: ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", `--user-data-dir=${join(work, "profile")}`] });
  try {
    const page = await browser.newPage();
    await page.goto(`http://127.0.0.1:${server.address().port}/`);
    const got = await page.evaluate(async (names) => {
      const { decode, useWasm } = await import("/dftpcc.mjs");
      const loaded = useWasm(true);
      const out = {};
      for (const name of names) {
        const data = new Uint8Array(await (await fetch(`/${name}`)).arrayBuffer());
        useWasm(true);
        const a = decode(data);
        useWasm(false);
        const b = decode(data);
        useWasm(true);
        let diff = 0;
        for (let k = 0; k < a.heights.length; k++) if (!(a.heights[k] === b.heights[k] || (Number.isNaN(a.heights[k]) && Number.isNaN(b.heights[k])))) diff++;
        out[name] = { cells: a.heights.length, diff };
      }
      return { loaded, out };
    }, names);
    assert.ok(got.loaded, "the kernels did not load in Chromium");
    for (const name of names) {
      assert.equal(got.out[name].diff, 0, `${name}: ${got.out[name].diff} heights differ in Chromium`);
      t.diagnostic(`${name}: ${got.out[name].cells} cells equal`);
    }
  } finally {
    await browser.close();
    server.close();
    rmSync(work, { recursive: true, force: true });
  }
});

test("a memory that cannot grow leaves the kernels as they were; a large one is let go after use", () => {
  const k = internals.kernels();
  assert.throws(() => k.scratch(2 ** 33), internals.WasmMemoryError);
  const [a, b] = idctBoth(40, 30, 97, 128, 0, 97, 0, 128, "auto", true);
  assert.equal(firstDiff(a, b), -1, "after a refused growth");
  // 300 MiB of scratch (address space only: nothing is written) is more than a page keeps.
  k.scratch(300 * 2 ** 20);
  assert.ok(k.held() > 256 * 2 ** 20);
  internals.releaseKernels();
  const fresh = internals.kernels();
  assert.notEqual(fresh, k);
  assert.ok(fresh.held() < 256 * 2 ** 20);
  const [c, d] = idctBoth(40, 30, 97, 128, 0, 97, 0, 128, "auto", true);
  assert.equal(firstDiff(c, d), -1, "with a fresh instance");
});
