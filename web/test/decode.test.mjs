// The decoder against the Python decoder on files the codec writes from ../shared/data: the mask
// exactly, the heights within float32 rounding, and every height within the file's stated maximum
// error of the DEM it was made from.
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { join } from "node:path";
import { test } from "node:test";
import { decode, useWasm } from "../dist/dftpcc.mjs";
import { bytes, f64, fixtures } from "./helpers.mjs";

const DIR = fixtures();
const MANIFEST = JSON.parse(readFileSync(join(DIR, "manifest.json"), "utf8"));
/** Half a float32 ulp, relative: "within float32 rounding". */
const F32_HALF_ULP = 2 ** -24;
/** Slack on a stated maximum error (metres): the float64 sums of two decoders differ in the last bits. */
const STATED_SLACK_M = 1e-9;

/** Compares a decode with the Python reference `name`; returns the largest height difference. */
function compare(map, name, label) {
  const mask = bytes(join(DIR, `${name}.mask.u8`));
  const ref = f64(join(DIR, `${name}.ref.f64`));
  assert.equal(map.mask.length, mask.length, `${label}: grid size`);
  let wrongMask = 0;
  for (let k = 0; k < mask.length; k++) if (map.mask[k] !== mask[k]) wrongMask++;
  assert.equal(wrongMask, 0, `${label}: ${wrongMask} cells of the mask differ`);
  let worst = 0;
  let worstRel = 0;
  for (let k = 0; k < mask.length; k++) {
    if (!mask[k]) {
      assert.ok(Number.isNaN(map.heights[k]), `${label}: empty cell ${k} holds a height`);
      continue;
    }
    const d = Math.abs(map.heights[k] - ref[k]);
    worst = Math.max(worst, d);
    worstRel = Math.max(worstRel, d / Math.max(Math.abs(ref[k]), 1e-300));
  }
  assert.ok(worstRel <= F32_HALF_ULP, `${label}: heights differ by ${worst} m (relative ${worstRel}) from Python's`);
  return worst;
}

for (const c of MANIFEST.legacy) {
  test(`${c.name}: a version 1.${c.minor} file (legacy coefficient order) decodes as in Python`, () => {
    const map = decode(bytes(join(DIR, `${c.name}.dftpc`)));
    assert.equal(map.header.version, `1.${c.minor}`);
    assert.equal(map.header.tiled, c.tiled);
    compare(map, c.name, c.name);
  });
}

for (const c of MANIFEST.cases) {
  test(`${c.name}: as the Python decoder, within the stated maximum error`, (t) => {
    const data = bytes(join(DIR, `${c.name}.dftpc`));
    const map = decode(data);
    assert.equal(map.width, c.cols);
    assert.equal(map.height, c.rows);
    assert.equal(map.header.tiled, c.tiled);
    const worst = compare(map, c.name, c.name);
    t.diagnostic(`largest difference from Python: ${worst.toExponential(2)} m`);
    if (c.orig && c.dem_max_error_m !== null) {
      const orig = f64(join(DIR, `${c.name}.orig.f64`));
      let err = 0;
      for (let k = 0; k < orig.length; k++) {
        if (map.mask[k] && Number.isFinite(orig[k])) err = Math.max(err, Math.abs(map.heights[k] - orig[k]));
      }
      assert.ok(err <= c.dem_max_error_m + STATED_SLACK_M, `${c.name}: error ${err} m over the stated ${c.dem_max_error_m} m`);
      t.diagnostic(`largest error ${err.toFixed(6)} m, stated ${c.dem_max_error_m} m`);
    }
    const f = decode(data, { float32: true });
    assert.ok(f.heights instanceof Float32Array);
  });
  for (const n of c.prefixes ?? []) {
    test(`${c.name}: the first ${n} bytes decode progressively as in Python`, () => {
      const data = bytes(join(DIR, `${c.name}.dftpc`));
      const map = decode(data, { maxBytes: n });
      compare(map, `${c.name}.prefix${n}`, `${c.name} prefix ${n}`);
    });
  }
  for (const [n, error] of c.prefix_refused ?? []) {
    test(`${c.name}: the first ${n} bytes are refused as in Python`, () => {
      const data = bytes(join(DIR, `${c.name}.dftpc`));
      assert.throws(() => decode(data, { maxBytes: n }), (e) => e.name === error);
    });
  }
  if (c.window) {
    test(`${c.name}: a window decodes as Python's read_window`, () => {
      const data = bytes(join(DIR, `${c.name}.dftpc`));
      const [rows, cols] = c.window;
      const map = decode(data, { window: { rows, cols } });
      assert.equal(map.height, rows[1] - rows[0]);
      compare(map, `${c.name}.window`, `${c.name} window`);
    });
  }
  if (c.cutoff !== undefined) {
    test(`${c.name}: decodes at cutoff ${c.cutoff} as in Python`, () => {
      const map = decode(bytes(join(DIR, `${c.name}.dftpc`)), { cutoff: c.cutoff });
      compare(map, `${c.name}.cutoff`, `${c.name} cutoff`);
    });
  }
}

test("a tiled map refuses progressive decoding and a decode-time cutoff", () => {
  const data = bytes(join(DIR, "davos_tiled.dftpc"));
  assert.throws(() => decode(data, { maxBytes: 1000 }), { name: "InvalidInputError" });
  assert.throws(() => decode(data, { cutoff: 0.9 }), { name: "InvalidInputError" });
});

test("a prefix handed over with the file's size decodes as maxBytes does (a page receiving a map)", () => {
  const data = bytes(join(DIR, "gale_default.dftpc"));
  const n = Math.floor(data.length / 2);
  const a = decode(data.subarray(0, n), { fileSize: data.length });
  const b = decode(data, { maxBytes: n });
  assert.ok(a.partial && b.partial);
  assert.deepEqual(a.heights, b.heights);
});

test("maxCells bounds the grid a file may ask for, before anything is decoded", () => {
  const data = bytes(join(DIR, "gale_default.dftpc"));
  assert.throws(() => decode(data, { maxCells: 1000 }), { name: "ResourceLimitError", message: /maxCells/ });
  assert.throws(() => decode(data, { maxCells: -1 }), { name: "InvalidInputError" });
  assert.throws(() => decode(data, { cutoff: 0.5 }), { name: "InvalidInputError" });
});

test("a preview of a short prefix samples the exact prefix decode every few cells and interpolates between", () => {
  const data = bytes(join(DIR, "korolev.dftpc"));
  const n = Math.floor(0.05 * data.length);
  const exact = decode(data, { maxBytes: n });
  // The TypeScript path samples (with the WebAssembly kernels the exact decode costs less: wasm.test.mjs).
  useWasm(false);
  let preview;
  try {
    preview = decode(data, { maxBytes: n, preview: true });
  } finally {
    useWasm(true);
  }
  assert.equal(exact.stride, undefined);
  const s = preview.stride;
  assert.ok(s >= 3, `a 5 % prefix samples every ${s} cells`);
  assert.deepEqual(preview.mask, exact.mask);
  const { width: W, height: H } = exact;
  const range = exact.statistics.maxZ - exact.statistics.minZ;
  let atSamples = 0;
  let between = 0;
  for (let r = 0; r < H; r++) {
    for (let c = 0; c < W; c++) {
      const k = r * W + c;
      if (!exact.mask[k]) {
        assert.ok(Number.isNaN(preview.heights[k]));
        continue;
      }
      const d = Math.abs(preview.heights[k] - exact.heights[k]);
      // Rows and columns 0, s, 2 s, ... and the last are evaluated, not interpolated.
      const sampled = (r % s === 0 || r === H - 1) && (c % s === 0 || c === W - 1);
      if (sampled) atSamples = Math.max(atSamples, d);
      else between = Math.max(between, d);
    }
  }
  assert.ok(atSamples <= 1e-9 * Math.max(1, Math.abs(exact.statistics.maxZ)), `samples off by ${atSamples} m`);
  // Eight samples a shortest period: bilinear within a few per cent of the range.
  assert.ok(between > 0 && between <= 0.05 * range, `interpolated cells off by ${between} m of a ${range} m range`);
});

test("a preview of the whole file, or of a prefix whose corner is wide, is the exact decode", () => {
  const data = bytes(join(DIR, "korolev.dftpc"));
  for (const n of [data.length, Math.floor(0.4 * data.length)]) {
    const exact = decode(data, { maxBytes: n });
    const preview = decode(data, { maxBytes: n, preview: true });
    assert.equal(preview.stride, undefined);
    assert.deepEqual(preview.heights, exact.heights);
  }
});
