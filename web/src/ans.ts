// The entropy decoder of MASK kinds 2 and 3, COEF kind 3 and RESD kind 5: constriction's stack ANS
// coder (32-bit words, 64-bit state, 24-bit probabilities) and the two models the format uses, a
// categorical table built from integers (format.md, COEF kind 3, steps 1-4) and a Bernoulli, both
// quantized as constriction's `perfect=False` models are (docs/format.md, "ANS").
import { u32 } from "./bytes.js";
import { CorruptFileError } from "./errors.js";
import { align16, Kernels } from "./wasm.js";

const PRECISION = 24;
const ONE = 1 << PRECISION; // 2**24
const QUANTILE_MASK = ONE - 1;
const TWO32 = 4294967296;
const INV_65536 = 1 / 65536;
const INV_TWO32 = 1 / TWO32;
/** A table model's quantiles in slots of 2**SLOT_SHIFT: slotsOf's bounds per slot. */
export const SLOT_SHIFT = 12;
/** Groups shorter than this search the table itself (a slot table costs 2**(24 - SLOT_SHIFT) steps). */
const SLOTTED_GROUP = 1024;

/** A stack ANS decoder over u32 words read from the end of the buffer (constriction's
 * `AnsCoder(words)`): the state is a 64-bit integer kept as two 32-bit halves in doubles. */
export class AnsDecoder {
  private readonly words: Uint32Array;
  private pos: number;
  private hi = 0;
  private lo = 0;

  constructor(bytes: Uint8Array, what: string) {
    if (bytes.length % 4) throw new CorruptFileError(`${what} has a wrong length (not whole 32-bit words)`);
    const n = bytes.length / 4;
    this.words = new Uint32Array(n);
    for (let k = 0; k < n; k++) this.words[k] = u32(bytes, 4 * k);
    this.pos = n;
    if (n > 0) {
      const first = this.words[--this.pos];
      if (first === 0) throw new CorruptFileError(`${what} does not decode: ANS data never ends in a zero word`);
      this.lo = first;
      if (this.pos > 0) {
        this.hi = this.lo;
        this.lo = this.words[--this.pos];
      }
    }
  }

  /** The next symbol under a model given by its cumulative table `cdf` (n + 1 entries, cdf[0] = 0,
   * cdf[n] = 2**24). */
  decode(cdf: Int32Array, n: number): number {
    return this.symbolBetween(cdf, 0, n - 1);
  }

  /** decode() with the symbols at the slots' bounds (slotsOf(cdf)) narrowing the search: the
   * quantile's slot holds one or two symbols of a model with large alphabets, not log2 n steps. */
  decodeSlotted(cdf: Int32Array, slots: Int32Array): number {
    const t = (this.lo & QUANTILE_MASK) >>> SLOT_SHIFT;
    return this.symbolBetween(cdf, slots[t], slots[t + 1]);
  }

  /** The largest symbol s in a..b with cdf[s] <= the quantile, decoded. */
  private symbolBetween(cdf: Int32Array, a: number, b: number): number {
    const quantile = this.lo & QUANTILE_MASK;
    while (a < b) {
      const m = (a + b + 1) >> 1;
      if (cdf[m] <= quantile) a = m;
      else b = m - 1;
    }
    this.advance(quantile - cdf[a], cdf[a + 1] - cdf[a]);
    return a;
  }

  /** One bit of a Bernoulli model whose cumulative table is [0, left1, 2**24]. */
  decodeBit(left1: number): number {
    const quantile = this.lo & QUANTILE_MASK;
    if (quantile < left1) {
      this.advance(quantile, left1);
      return 0;
    }
    this.advance(quantile - left1, ONE - left1);
    return 1;
  }

  /** state = (state >> 24) * probability + remainder, then refill a word when the state fell
   * below 2**32; in exact integer steps (every partial product below 2**53). */
  private advance(remainder: number, probability: number): void {
    const sh = this.hi >>> 24;
    const sl = (this.hi & 0xffffff) * 256 + (this.lo >>> 24); // below 2**32
    const sa = sl >>> 16;
    const sb = sl & 0xffff;
    const t1 = sb * probability + remainder;
    const t2 = sa * probability;
    // Products by powers of two are exact: the floors below are the integer shifts, without a division.
    const t2h = Math.floor(t2 * INV_65536);
    const low = t1 + (t2 - t2h * 65536) * 65536;
    const carry = Math.floor(low * INV_TWO32);
    let lo = low - carry * TWO32;
    let hi = sh * probability + t2h + carry;
    if (hi === 0 && this.pos > 0) {
      hi = lo;
      lo = this.words[--this.pos];
    }
    this.hi = hi;
    this.lo = lo;
  }
}

/** constriction's `perfect=False` quantization of a Bernoulli(p): the one inner boundary of the
 * cumulative table [0, left1, 2**24] (fast_quantized_cdf over [1 - p, p]). */
export function bernoulliLeft1(p: number): number {
  const q = 1 - p;
  const scale = (ONE - 2) / (q + p);
  return Math.floor(q * scale) + 1;
}

// --- the table models of COEF kind 3 and RESD kind 5 ---------------------------------------------

function iroot(x: bigint, k: bigint): bigint {
  // floor(x ** (1/k)) by Newton's method from above.
  if (x < 2n) return x;
  let y = 1n << (BigInt(x.toString(2).length) / k + 1n);
  for (;;) {
    const z = ((k - 1n) * y + x / y ** (k - 1n)) / k;
    if (z >= y) return y;
    y = z;
  }
}

/** R(code) = floor(65536 (sqrt(1 + b^2) - 1) / b), b = max(2 ** ((code - 128) / 8), 0.05), exactly
 * (fixed point at 10**40, far beyond the 16 digits the floor needs). */
function decay(code: number): number {
  const S = 10n ** 40n;
  const e = code - 128;
  let B = e >= 0 ? iroot(S ** 8n << BigInt(e), 8n) : iroot((S ** 8n) >> BigInt(-e), 8n);
  if (B * 20n < S) B = S / 20n;
  return Number((65536n * (iroot(S * S + B * B, 2n) - S)) / B);
}

const DECAY: number[] = Array.from({ length: 256 }, (_, c) => (c === 0 ? 0 : decay(c)));

/** R of scale code `code` (1-255). */
export function decayOf(code: number): number {
  return DECAY[code];
}
const tables = new Map<number, Int32Array>();
const MAX_CACHED_ENTRIES = 1 << 21;
let cached = 0;

/** The cumulative table (2 max_abs + 2 entries) of the categorical model of scale code `code` over
 * the symbols q + max_abs, q = -max_abs..max_abs: format.md's integer weights f, then constriction's
 * fast quantization of f / 2**24 (left_i = floor(K_i (2**24 - n) / 2**24) + i, K_i the sum of f
 * before i). */
export function tableModel(maxAbs: number, code: number, what: string): Int32Array {
  const key = code * 65537 + maxAbs;
  const hit = tables.get(key);
  if (hit) return hit;
  const n = 2 * maxAbs + 1;
  if (n < 2) throw new CorruptFileError(`${what} does not decode: a model over one symbol`);
  const R = DECAY[code];
  const w = new Float64Array(maxAbs + 1);
  w[0] = TWO32;
  for (let k = 1; k <= maxAbs; k++) w[k] = Math.floor((w[k - 1] * R) / 65536);
  let W = w[0];
  for (let k = 1; k <= maxAbs; k++) W += 2 * w[k];
  const M = ONE - n;
  const fk = new Float64Array(maxAbs + 1);
  for (let k = 0; k <= maxAbs; k++) fk[k] = w[k] === 0 ? 1 : 1 + floorRatio(w[k], M, W);
  let sum = fk[0];
  for (let k = 1; k <= maxAbs; k++) sum += 2 * fk[k];
  const f = new Float64Array(n);
  for (let s = 0; s < n; s++) f[s] = fk[Math.abs(s - maxAbs)];
  f[maxAbs] += ONE - sum;
  const cdf = new Int32Array(n + 1);
  let K = 0;
  for (let s = 0; s < n; s++) {
    cdf[s] = Math.floor((K * M) / ONE) + s;
    K += f[s];
  }
  cdf[n] = ONE;
  // Bounded by entries, not by tables: a crafted stream of many large alphabets must not pin memory.
  cached += cdf.length;
  if (cached > MAX_CACHED_ENTRIES) {
    tables.clear();
    cached = cdf.length;
  }
  tables.set(key, cdf);
  return cdf;
}

/** floor(a b / c) exactly for integers a <= 2**32, b < 2**24, 0 < c < 2**53: in floats (the quotient,
 * below 2**24, is within 2**-27 of a b / c) unless it lies that close to an integer, then in BigInt
 * (a table of tens of thousands of entries builds in a fraction of a millisecond, not tens). */
function floorRatio(a: number, b: number, c: number): number {
  const x = (a * b) / c;
  const q = Math.floor(x);
  if (x - q > RATIO_GUARD && q + 1 - x > RATIO_GUARD) return q;
  return Number((BigInt(a) * BigInt(b)) / BigInt(c));
}

/** Far above floorRatio's float error (2**-27 at most), far below the gap to the next integer. */
const RATIO_GUARD = 1e-6;

/** Decodes `count` symbols of one model into `out` at the positions `at` (or 0..count-1), as
 * symbol - maxAbs. */
export function decodeGroup(coder: AnsDecoder, cdf: Int32Array, maxAbs: number, out: Float64Array,
  at: Int32Array | number[], count: number): void {
  const n = 2 * maxAbs + 1;
  if (count >= SLOTTED_GROUP && n > 2) {
    const slots = slotsOf(cdf, n);
    for (let k = 0; k < count; k++) out[at[k]] = coder.decodeSlotted(cdf, slots) - maxAbs;
  } else {
    for (let k = 0; k < count; k++) out[at[k]] = coder.decode(cdf, n) - maxAbs;
  }
}

const slotTables = new WeakMap<Int32Array, Int32Array>();

/** For a cumulative table of n symbols: entry t is the symbol of quantile t 2**SLOT_SHIFT (the
 * largest s with cdf[s] <= it), and the last entry n - 1; a quantile of slot t decodes to a symbol
 * between entries t and t + 1 (the symbol grows with the quantile). Cached with the table. */
export function slotsOf(cdf: Int32Array, n: number): Int32Array {
  let slots = slotTables.get(cdf);
  if (slots) return slots;
  const m = ONE >>> SLOT_SHIFT;
  slots = new Int32Array(m + 1);
  let s = 0;
  for (let t = 0; t < m; t++) {
    const q = t << SLOT_SHIFT;
    while (s + 1 < n && cdf[s + 1] <= q) s++;
    slots[t] = s;
  }
  slots[m] = n - 1;
  slotTables.set(cdf, slots);
  return slots;
}

/** Symbols from which the kernels search a quantile's slot rather than the whole table: a slot
 * table is built once per model and stays in the kernels' memory (Kernels.ints), so even a short
 * group's search pays for it (a binary search of a wide table costs a mispredicted branch a step). */
export const KERNEL_SLOTTED_SYMBOLS = 64;

/**
 * decodeGroup over consecutive groups of one chunk in the WebAssembly kernels (kernels.ts ansGroups):
 * `words` the chunk's ANS words (checked by an AnsDecoder), groups[g] `count` values of the model
 * `cdf` (tableModel of maxAbs), their positions in `out` at[...] in group order; the same symbols as
 * the TypeScript decoder; `out` (the chunk's values) gets zeros where no group writes. Throws
 * WasmMemoryError when the kernels' memory cannot hold the chunk.
 */
export function ansInKernels(k: Kernels, words: Uint8Array, groups: Array<{ cdf: Int32Array; count: number }>,
  maxAbs: number, at: Int32Array, out: Float64Array): void {
  const n = 2 * maxAbs + 1;
  const values = at.length;
  const wordsBytes = align16(words.length);
  const descBytes = align16(16 * groups.length);
  const wP = k.scratch(wordsBytes + descBytes + align16(4 * values) + 8 * out.length);
  const dP = wP + wordsBytes;
  const atP = dP + descBytes;
  const outP = atP + align16(4 * values);
  // The tables above the scratch region, uploaded once per model (they move when it grows).
  const desc = new Int32Array(4 * groups.length);
  groups.forEach((g, q) => {
    desc.set([k.ints(g.cdf), n >= KERNEL_SLOTTED_SYMBOLS ? k.ints(slotsOf(g.cdf, n)) : 0, n, g.count], 4 * q);
  });
  const mem = k.bytes();
  mem.set(words, wP);
  const i32 = new Int32Array(mem.buffer);
  i32.set(desc, dP / 4);
  i32.set(at, atP / 4);
  // Positions in no group (code 0's) stay zero, as in `out` before the TypeScript path writes it.
  const res = new Float64Array(mem.buffer, outP, out.length);
  res.fill(0);
  k.ex.ansGroups(wP, words.length / 4, dP, groups.length, atP, outP, maxAbs, SLOT_SHIFT);
  out.set(res);
}
