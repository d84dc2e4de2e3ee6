// MASK payloads (format.md, "MASK"): which cells are rebuilt, kind 0 (zstd bitmap) and kinds 2 and 3
// (context-coded lines with ANS), also the nonzero map of a sparse residual.
import { AnsDecoder, bernoulliLeft1 } from "./ans.js";
import { inflate, u32 } from "./bytes.js";
import { CorruptFileError } from "./errors.js";
import { align16, kernels, Kernels, WasmMemoryError } from "./wasm.js";

const POPCOUNT = Uint8Array.from({ length: 256 }, (_, c) => {
  let n = 0;
  for (let b = c; b; b >>= 1) n += b & 1;
  return n;
});

/** A bitmap byte of eight rebuilt cells. */
const FULL = 0xff;

/** A bitmap byte's eight cells (most significant bit first) as bytes 0 or 1 in two little-endian words. */
const BITS_LO = new Uint32Array(256);
const BITS_HI = new Uint32Array(256);
for (let c = 0; c < 256; c++) {
  for (let b = 0; b < 4; b++) {
    BITS_LO[c] += ((c >> (7 - b)) & 1) * 2 ** (8 * b);
    BITS_HI[c] += ((c >> (3 - b)) & 1) * 2 ** (8 * b);
  }
}

/** The number of 1s of a mask of 0s and 1s: four cells a word, the byte lanes folded before they
 * could overflow (a full-grid pass in V8 costs a few ns a cell; this one a quarter of that). */
export function countOnes(mask: Uint8Array): number {
  const words = mask.byteOffset % 4 === 0 ? mask.length >> 2 : 0;
  const w = new Uint32Array(mask.buffer, mask.byteOffset, words);
  let total = 0;
  for (let k = 0; k < words;) {
    const end = Math.min(words, k + 255);
    let acc = 0;
    for (; k < end; k++) acc = (acc + w[k]) | 0;
    total += (acc & 0xff) + ((acc >>> 8) & 0xff) + ((acc >>> 16) & 0xff) + (acc >>> 24);
  }
  for (let k = 4 * words; k < mask.length; k++) total += mask[k];
  return total;
}

/** The rows x cols occupancy, row-major, 1 = rebuilt. */
export function decodeMask(p: Uint8Array, rows: number, cols: number): Uint8Array {
  if (p.length < 2) throw new CorruptFileError("occupancy mask is truncated");
  const kind = p[0];
  if (kind === 0) {
    const nbytes = Math.ceil((rows * cols) / 8);
    const raw = inflate(p.subarray(2), nbytes, "occupancy mask");
    if (raw.length !== nbytes) throw new CorruptFileError("occupancy mask has the wrong size for the grid");
    const out = new Uint8Array(rows * cols);
    // Eight cells a byte as two little-endian words of a table (a per-cell shift costs a few ns a cell in V8).
    const whole = out.length >> 3;
    const words = new Uint32Array(out.buffer, 0, 2 * whole);
    // A map's mask is mostly runs of full bytes (and the zeros of an empty stretch, which the array
    // holds already): a run is one fill.
    for (let i = 0; i < whole;) {
      const b = raw[i];
      if (b === FULL || b === 0) {
        let j = i + 1;
        while (j < whole && raw[j] === b) j++;
        if (b) out.fill(1, 8 * i, 8 * j);
        i = j;
        continue;
      }
      words[2 * i] = BITS_LO[b];
      words[2 * i + 1] = BITS_HI[b];
      i++;
    }
    for (let k = 8 * whole; k < out.length; k++) out[k] = (raw[k >> 3] >> (7 - (k & 7))) & 1;
    return out;
  }
  if (kind === 2 || kind === 3) return contextMask(p, rows, cols, kind === 3);
  throw new CorruptFileError(`occupancy mask has unknown coding ${kind}`);
}

function seedLines(frame: Uint8Array, count: number, w: number): Uint8Array[] {
  if (count === 0) {
    if (frame.length) throw new CorruptFileError("occupancy mask has seed lines it does not need");
    return [];
  }
  const raw = inflate(frame, 4 * (w + 2) * count, "occupancy mask's seed lines");
  if (raw.length % 4) throw new CorruptFileError("occupancy mask's seed lines have a wrong length");
  const m = raw.length / 4;
  const value = (i: number) => (raw[i] | (raw[m + i] << 8) | (raw[2 * m + i] << 16) | (raw[3 * m + i] << 24)) >>> 0;
  const lines: Uint8Array[] = [];
  let i = 0;
  for (let s = 0; s < count; s++) {
    if (i >= m) throw new CorruptFileError("occupancy mask's seed lines are truncated");
    const k = value(i);
    if (k < 1 || i + 1 + k > m) throw new CorruptFileError(`occupancy mask's seed line ${s} does not add up to ${w} cells`);
    let total = 0;
    for (let r = 0; r < k; r++) total += value(i + 1 + r);
    if (total !== w) throw new CorruptFileError(`occupancy mask's seed line ${s} does not add up to ${w} cells`);
    const line = new Uint8Array(w);
    let at = 0;
    for (let r = 0; r < k; r++) {
      const len = value(i + 1 + r);
      if (r & 1) line.fill(1, at, at + len);
      at += len;
    }
    lines.push(line);
    i += 1 + k;
  }
  if (i !== m) throw new CorruptFileError("occupancy mask's seed lines have trailing data");
  return lines;
}

function contextMask(p: Uint8Array, rows: number, cols: number, firstSeed: boolean): Uint8Array {
  const transposed = p[1];
  if (transposed !== (rows > cols ? 1 : 0)) throw new CorruptFileError("occupancy mask runs along the wrong axis");
  const n = transposed ? cols : rows; // lines
  const w = transposed ? rows : cols; // their length
  if (p.length < 10) throw new CorruptFileError("occupancy mask is truncated");
  const stripe = u32(p, 2);
  const seedBytes = u32(p, 6);
  if (stripe < 1 || 10 + seedBytes > p.length) throw new CorruptFileError("occupancy mask has a wrong length");
  const L = Math.min(stripe, n);
  const nStripes = Math.ceil(n / L);
  const first = firstSeed ? 1 : 0;
  const lines = new Uint8Array(n * w);
  const seeds = seedLines(p.subarray(10, 10 + seedBytes), nStripes - 1 + first, w);
  for (let k = 0; k < seeds.length; k++) lines.set(seeds[k], (k + 1 - first) * L * w);
  const coder = new AnsDecoder(p.subarray(10 + seedBytes), "occupancy mask");
  const k = kernels();
  if (k) {
    try {
      contextInKernels(k, lines, p.subarray(10 + seedBytes), n, w, L, nStripes, first);
      return transposed ? transpose(lines, rows, cols) : lines;
    } catch (e) {
      if (!(e instanceof WasmMemoryError)) throw e;
    }
  }
  const pc = new Float64Array(256);
  for (let c = 0; c < 256; c++) pc[c] = (POPCOUNT[c] + 0.5) / 9;
  const n1 = new Float64Array(256);
  const nn = new Float64Array(256);
  const left1 = new Float64Array(256);
  const ctx = new Uint8Array(nStripes * w);
  const padA = new Uint8Array(w + 5); // one zero more: the sliding windows read a cell ahead
  const padB = new Uint8Array(w + 5);
  for (let t = first; t < L; t++) {
    // The lines of this step, stripe by stripe: line t of stripe s is line s*L + t.
    let m = 0; // cells this step
    const idx: number[] = [];
    for (let s = 0; s < (t ? nStripes : 1); s++) if (s * L + t < n) idx.push(s * L + t);
    for (const i of idx) {
      const base = m;
      if (t === 0) {
        ctx.fill(0, base, base + w);
      } else {
        // Lines A (t-1) and B (t-2, or t-1 again for t = 1), padded with two zeros each side.
        padA.set(lines.subarray((i - 1) * w, i * w), 2);
        padB.set(lines.subarray((t >= 2 ? i - 2 : i - 1) * w, (t >= 2 ? i - 1 : i) * w), 2);
        // ctx = padA[j .. j+4] as bits 0-4, padB[j+1 .. j+3] as bits 5-7: both windows slide a cell.
        let a = padA[0] | (padA[1] << 1) | (padA[2] << 2) | (padA[3] << 3) | (padA[4] << 4);
        let b = padB[1] | (padB[2] << 1) | (padB[3] << 2);
        for (let j = 0; j < w; j++) {
          ctx[base + j] = a | (b << 5);
          a = (a >> 1) | (padA[j + 5] << 4);
          b = (b >> 1) | (padB[j + 4] << 2);
        }
      }
      m += w;
    }
    for (let c = 0; c < 256; c++) left1[c] = bernoulliLeft1((n1[c] + pc[c]) / (nn[c] + 1));
    const bits = new Uint8Array(m);
    // Context 0, then 255 (one model each), then every other cell with its own context's model; the
    // counts of each context updated as its cells decode (the models change only between steps).
    for (const c of [0, 255]) {
      const l = left1[c];
      let cells = 0;
      let ones = 0;
      for (let k = 0; k < m; k++) {
        if (ctx[k] === c) {
          const bit = coder.decodeBit(l);
          bits[k] = bit;
          ones += bit;
          cells++;
        }
      }
      nn[c] += cells;
      n1[c] += ones;
    }
    for (let k = 0; k < m; k++) {
      const c = ctx[k];
      if (c !== 0 && c !== 255) {
        const bit = coder.decodeBit(left1[c]);
        bits[k] = bit;
        nn[c] += 1;
        n1[c] += bit;
      }
    }
    for (let q = 0; q < idx.length; q++) lines.set(bits.subarray(q * w, (q + 1) * w), idx[q] * w);
  }
  return transposed ? transpose(lines, rows, cols) : lines;
}

/** The rows x cols grid of lines that ran down its columns (cols lines of rows cells). */
function transpose(lines: Uint8Array, rows: number, cols: number): Uint8Array {
  const out = new Uint8Array(rows * cols);
  for (let i = 0; i < cols; i++) for (let j = 0; j < rows; j++) out[j * cols + i] = lines[i * rows + j];
  return out;
}

/**
 * contextMask's steps in the WebAssembly kernels (kernels.ts contextMask): the same contexts, models
 * and bits, written into `lines` (n lines of w cells, its seed lines set). `words` has been checked by
 * an AnsDecoder. Throws WasmMemoryError when the kernels' memory cannot hold the lines.
 */
function contextInKernels(k: Kernels, lines: Uint8Array, words: Uint8Array, n: number, w: number, L: number,
  nStripes: number, first: number): void {
  const sizes = [align16(n * w), align16(words.length), 6144, align16(2 * w + 16) + 2 * nStripes * w];
  const at: number[] = [];
  let end = k.scratch(sizes.reduce((x, y) => x + y, 0));
  for (const size of sizes) {
    at.push(end);
    end += size;
  }
  const [linesP, wordsP, tablesP, scratchP] = at;
  const mem = k.bytes();
  mem.set(lines, linesP);
  mem.set(words, wordsP);
  k.ex.contextMask(linesP, n, w, L, nStripes, first, wordsP, words.length / 4, scratchP, tablesP);
  lines.set(k.bytes().subarray(linesP, linesP + n * w));
}
