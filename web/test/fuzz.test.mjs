// A few thousand mutated files (seeded): each is refused with the decoder's own error class or
// decoded, never hanging and never throwing anything else. Half the mutations recompute the CRCs
// after damaging a payload, as a crafted file would, so the checks behind the checksums are reached.
// Each is decoded twice, by the WebAssembly path (kernels, ANS and zstd, the zstd decoder loaded
// first) and by TypeScript alone (useWasm(false)): the same verdict and the same heights, but for
// zstd frames whose blocks hold more than the frame declares, which fzstd cuts at the declared size
// and libzstd (the WebAssembly decoder, as the Python decoder's zstandard) refuses.
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { join } from "node:path";
import { test } from "node:test";
import CRC32 from "crc-32";
import { decode, DftpccError, ready, useWasm } from "../dist/dftpcc.mjs";
import { bytes, fixtures, ROOT } from "./helpers.mjs";

const DIR = fixtures();
const ITERATIONS = Number(process.env.DFTPCC_FUZZ_ITERATIONS ?? 3000);
const SEED = Number(process.env.DFTPCC_FUZZ_SEED ?? 11);
/** A decode taking more CPU time than this is a hang (the largest seed decodes in well under a
 * second); CPU time, so that a shared machine's load does not fail the test. */
const HANG_CPU_MS = 10_000;
// Residual layers early (the small seeds are picked most): predicted (kind 5) and sparse (kind 4),
// whose decoders and application run in the kernels.
const SEEDS = ["legacy_compact_max_error_predicted", "alirt_exact", "legacy_compact_max_error_sparse", "field_oriented",
  "field_footprint", "gale_maxerr_coarse", "gale_rmse", "gale_default",
  "gale_maxerr", "gale_dft", "gale_zstd", "gale_paper", "davos_tiled_maxerr",
  // Version 1.0 and 1.1 maps (tests/legacy): the legacy coefficient order.
  "legacy_tie_dct", "legacy_compact_dft", "legacy_tiled_map_residual", "legacy_paper_dft"];

function rng(seed) {
  let a = seed >>> 0;
  return () => {
    a = (a + 0x6d2b79f5) >>> 0;
    let t = a;
    t = Math.imul(t ^ (t >>> 15), t | 1);
    t ^= t + Math.imul(t ^ (t >>> 7), t | 61);
    return ((t ^ (t >>> 14)) >>> 0) / 4294967296;
  };
}

function leb(d, pos) {
  let v = 0;
  let s = 1;
  for (let k = 0; k < 10 && pos < d.length; k++) {
    const b = d[pos++];
    v += (b & 0x7f) * s;
    s *= 128;
    if (!(b & 0x80)) return [v, pos];
  }
  return null;
}

/** The section table's payload spans and CRC positions, or null when it does not parse. */
function table(d) {
  if (d.length < 20) return null;
  const count = (d[12] | (d[13] << 8) | (d[14] << 16) | (d[15] << 24)) >>> 0;
  if (count > 100_000) return null;
  const out = [];
  let pos = 16;
  for (let i = 0; i < count; i++) {
    const t = leb(d, pos + 4);
    if (!t) return null;
    const l = leb(d, t[1]);
    if (!l) return null;
    out.push({ length: l[0], crcAt: l[1] });
    pos = l[1] + 4;
    if (pos > d.length) return null;
  }
  let at = pos + 4;
  for (const e of out) {
    e.offset = at;
    at += e.length;
  }
  return { end: pos, sections: out };
}

function put32(d, at, v) {
  if (at < 0 || at + 4 > d.length) return;
  d[at] = v & 255;
  d[at + 1] = (v >>> 8) & 255;
  d[at + 2] = (v >>> 16) & 255;
  d[at + 3] = (v >>> 24) & 255;
}

/** Recomputes every section's CRC and the table's, as whoever crafted the file would. */
function reseal(d) {
  const t = table(d);
  if (!t) return;
  for (const s of t.sections) {
    if (s.offset + s.length <= d.length) put32(d, s.crcAt, CRC32.buf(d.subarray(s.offset, s.offset + s.length)) >>> 0);
  }
  if (t.end + 4 <= d.length) put32(d, t.end, CRC32.buf(d.subarray(0, t.end)) >>> 0);
}

const INTERESTING = [0, 1, 2, 0x7f, 0x80, 0xff, 0x100, 0xffff, 0x10000, 0x7fffffff, 0x80000000, 0xffffffff, 1 << 20, 1 << 28];

function mutate(src, r) {
  const d = Uint8Array.from(src);
  const pick = (n) => Math.floor(r() * n);
  const t = table(d);
  const inPayload = () => {
    if (!t || !t.sections.length) return pick(d.length);
    const s = t.sections[pick(t.sections.length)];
    return Math.min(d.length - 1, s.offset + pick(Math.max(1, s.length)));
  };
  const how = pick(6);
  if (how === 0) {
    for (let k = 0, n = 1 + pick(4); k < n; k++) d[pick(d.length)] ^= 1 << pick(8);
    return d;
  }
  if (how === 1) return d.subarray(0, pick(d.length));
  if (how === 2) {
    for (let k = 0, n = 1 + pick(3); k < n; k++) d[inPayload()] ^= 1 << pick(8);
  } else if (how === 3) {
    const at = inPayload() & ~3;
    put32(d, at, r() < 0.7 ? INTERESTING[pick(INTERESTING.length)] : pick(2 ** 32));
  } else if (how === 4) {
    const at = inPayload();
    const n = 1 + pick(16);
    for (let k = 0; k < n && at + k < d.length; k++) d[at + k] = pick(256);
  } else {
    const at = inPayload();
    d[at] = r() < 0.5 ? 0 : 255;
  }
  reseal(d);
  return d;
}

/** decode(data)'s outcome: its heights, or the class of its refusal (any other throw fails the test). */
function outcome(data, i) {
  try {
    return decode(data).heights;
  } catch (e) {
    if (!(e instanceof DftpccError)) {
      assert.fail(`mutation ${i} threw ${e?.name}: ${e?.message}\n${e?.stack}`);
    }
    lastRefusal = e.message;
    return e.name;
  }
}

let lastRefusal = "";

/** The same heights (NaN equal to NaN, 0 to -0) or the same refusal. */
function same(a, b) {
  if (typeof a === "string" || typeof b === "string") return a === b;
  if (a.length !== b.length) return false;
  for (let k = 0; k < a.length; k++) if (!(a[k] === b[k] || (Number.isNaN(a[k]) && Number.isNaN(b[k])))) return false;
  return true;
}

test(`${ITERATIONS} mutated files are refused or decoded, never hanging or crashing (seed ${SEED})`, async (t) => {
  assert.ok(await ready(), "the WebAssembly zstd decoder did not load");
  const seeds = SEEDS.map((n) => bytes(join(DIR, `${n}.dftpc`)));
  const corpus = Object.keys(JSON.parse(readFileSync(join(ROOT, "tests", "corpus", "expected.json"), "utf8")))
    .map((n) => bytes(join(ROOT, "tests", "corpus", n)));
  const r = rng(SEED);
  const counts = { decoded: 0, refused: 0, stricter: 0 };
  const classes = {};
  let slowest = 0;
  for (let i = 0; i < ITERATIONS; i++) {
    // Small seeds most often: a mutation of a large map costs a whole decode when it survives.
    const pool = r() < 0.15 ? corpus : seeds;
    const weight = r();
    const src = pool === corpus ? pool[Math.floor(r() * pool.length)] : pool[Math.floor(weight * weight * pool.length)];
    const data = mutate(src, r);
    const c0 = process.cpuUsage();
    const got = outcome(data, i);
    if (typeof got === "string") {
      counts.refused++;
      classes[got] = (classes[got] ?? 0) + 1;
    } else counts.decoded++;
    const used = process.cpuUsage(c0);
    const ms = (used.user + used.system) / 1000;
    slowest = Math.max(slowest, ms);
    assert.ok(ms < HANG_CPU_MS, `mutation ${i} took ${ms} ms of CPU`);
    const why = lastRefusal;
    useWasm(false);
    try {
      const plain = outcome(data, i);
      if (typeof got === "string" && typeof plain !== "string" && why.endsWith("does not decompress")) {
        counts.stricter++;
        continue;
      }
      assert.ok(same(got, plain), `mutation ${i}: WebAssembly ${typeof got === "string" ? `${got} (${why})` : "decoded"}, TypeScript ${typeof plain === "string" ? plain : "decoded"} (or other heights)`);
    } finally {
      useWasm(true);
    }
  }
  t.diagnostic(`decoded ${counts.decoded}, refused ${counts.refused} (${JSON.stringify(classes)}; ${counts.stricter} by libzstd only), `
    + `slowest ${slowest.toFixed(0)} ms of CPU`);
});
