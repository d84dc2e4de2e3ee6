// RESD payloads (format.md, "RESD"): one integer per rebuilt cell, in COEF's chunks, as one sparse
// chunk (kind 4) or one predicted chunk (kind 5).
import { AnsDecoder, KERNEL_SLOTTED_SYMBOLS, SLOT_SHIFT, slotsOf, tableModel } from "./ans.js";
import { crc32, i32, u16, u32 } from "./bytes.js";
import { decodeStream, streamEnd } from "./coef.js";
import { CorruptFileError } from "./errors.js";
import { countOnes, decodeMask } from "./mask.js";
import { align16, kernels, Kernels, WasmMemoryError } from "./wasm.js";

/** A sparse residual layer (kind 4): `picture` (rows x cols, 1 where a rebuilt cell's integer is not
 * 0) and those integers, `nonzero`, in row-major order. */
export interface SparseResidual {
  picture: Uint8Array;
  nonzero: Float64Array;
}

/** The residual integers of the rebuilt cells of `mask` (rows x cols), in row-major order. */
export function decodeResidual(p: Uint8Array, mask: Uint8Array, rows: number, cols: number): Float64Array {
  const layer = decodeResidualLayer(p, mask, rows, cols);
  return layer instanceof Float64Array ? layer : spread(layer, mask);
}

/** A sparse layer's integers, one per rebuilt cell of `mask`, in row-major order. */
export function spread({ picture, nonzero }: SparseResidual, mask: Uint8Array): Float64Array {
  const out = new Float64Array(countOnes(mask));
  for (let k = 0, c = 0, v = 0; k < mask.length; k++) {
    if (!mask[k]) continue;
    if (picture[k]) out[c] = nonzero[v++];
    c++;
  }
  return out;
}

/** decodeResidual's integers, or a sparse layer as it is coded (its nonzero integers and where they
 * go: a grid of bytes, not of doubles, for a map's whole grid). */
export function decodeResidualLayer(p: Uint8Array, mask: Uint8Array, rows: number, cols: number): Float64Array | SparseResidual {
  const total = countOnes(mask);
  const kind = p.length >= 20 ? u32(p, 16) : -1;
  if (kind === 4 || kind === 5) {
    const nchunks = u32(p, 0);
    const count = u32(p, 4);
    const nbytes = u32(p, 8);
    const body = p.subarray(20, 20 + nbytes);
    if (nchunks !== 1 || count !== total) {
      throw new CorruptFileError(`coefficient chunk 0 of kind ${kind} must be the stream's only chunk, with all ${total} values`);
    }
    if (20 + nbytes !== p.length) throw new CorruptFileError(`residual chunk 0 of kind ${kind} has a wrong length`);
    if (crc32(body) !== u32(p, 12)) throw new CorruptFileError("residual chunk 0 fails its checksum");
    return kind === 4 ? sparse(body, mask, rows, cols) : predicted(body, mask, rows, cols, total);
  }
  const s = decodeStream(p, total, null, null, { name: "residual" });
  if (!s.ints) throw new CorruptFileError("residual layer holds float values");
  return s.ints;
}

function sparse(body: Uint8Array, mask: Uint8Array, rows: number, cols: number): SparseResidual {
  if (body.length < 4) throw new CorruptFileError("sparse residual is truncated");
  const L = u32(body, 0);
  if (4 + L > body.length) throw new CorruptFileError("sparse residual's nonzero map runs past the chunk");
  const picture = decodeMask(body.subarray(4, 4 + L), rows, cols);
  if (!within(picture, mask)) throw new CorruptFileError("sparse residual sets a cell that is not rebuilt");
  const n = countOnes(picture);
  const signsAt = body.length - Math.ceil(n / 8);
  if (signsAt < 4 + L) throw new CorruptFileError("sparse residual has no room for its signs");
  const region = body.subarray(4 + L, signsAt);
  const sizes = decodeStream(region, n, null, null, { free: true, name: "sparse residual's magnitude" });
  if (streamEnd(region) !== region.length) {
    throw new CorruptFileError("sparse residual's magnitudes do not end where its signs start");
  }
  if (!sizes.ints) throw new CorruptFileError("sparse residual's magnitudes are not integers");
  const nonzero = new Float64Array(n);
  for (let v = 0; v < n; v++) {
    const size = sizes.ints[v];
    if (size < 0 || size > 2 ** 62) throw new CorruptFileError("sparse residual's magnitudes are out of range");
    const negative = (body[signsAt + (v >> 3)] >> (7 - (v & 7))) & 1;
    nonzero[v] = negative ? -(size + 1) : size + 1;
  }
  if (n % 8 && body[body.length - 1] & ((1 << (8 - (n % 8))) - 1)) {
    throw new CorruptFileError("sparse residual has a stray sign bit");
  }
  return { picture, nonzero };
}

/** Whether every set cell of `picture` is set in `mask` (grids of 0s and 1s): four cells a word. */
function within(picture: Uint8Array, mask: Uint8Array): boolean {
  const aligned = picture.byteOffset % 4 === 0 && mask.byteOffset % 4 === 0;
  const words = aligned ? picture.length >> 2 : 0;
  const p = new Uint32Array(picture.buffer, picture.byteOffset, words);
  const m = new Uint32Array(mask.buffer, mask.byteOffset, words);
  for (let k = 0; k < words; k++) if (p[k] & ~m[k]) return false;
  for (let k = 4 * words; k < picture.length; k++) if (picture[k] & ~mask[k]) return false;
  return true;
}

// Neighbours W, N, NW, NE, WW, NN, NNE as (rows up, columns left).
const UP = [0, 1, 1, 1, 0, 2, 2];
const LEFT = [1, 0, 1, -1, 2, 0, -1];
const ACTIVITY = [2, 2, 1, 1, 1, 1, 0];
/** A class's slot table (ans.ts slotsOf, 4097 entries) pays for itself over a layer of this many
 * cells, and for alphabets of at least 2 SLOTTED_WIDTH + 1 symbols (a binary search of 4+ steps). */
const SLOTTED_CELLS = 1 << 16;
const SLOTTED_WIDTH = 8;

function predicted(body: Uint8Array, mask: Uint8Array, rows: number, cols: number, total: number): Float64Array {
  const what = "predicted residual layer";
  if (body.length < 29) throw new CorruptFileError(`${what} has a wrong length`);
  const a = Array.from({ length: 7 }, (_, k) => i32(body, 4 * k));
  const listed = body[28];
  if (a.some((x) => Math.abs(x) >= 2 ** 24) || listed < 1 || listed > 64 || body.length < 29 + listed) {
    throw new CorruptFileError(`${what} has an implausible header`);
  }
  const codes = new Uint8Array(64);
  codes.set(body.subarray(29, 29 + listed));
  const coded: number[] = [];
  for (let k = 0; k < 64; k++) if (codes[k]) coded.push(k);
  const at = 29 + listed + 2 * coded.length;
  if (body.length < at || (body.length - at) % 4) throw new CorruptFileError(`${what} has a wrong length`);
  const widths = new Int32Array(64);
  coded.forEach((k, q) => { widths[k] = u16(body, 29 + listed + 2 * q); });
  if (coded.some((k) => widths[k] > 2 ** 15)) throw new CorruptFileError(`${what} has an implausible header`);
  let entries = 0;
  for (const k of coded) entries += 2 * widths[k] + 1;
  if (entries > 16 * total + 2 ** 19) {
    throw new CorruptFileError(`${what} asks for larger probability tables than its ${total} values allow`);
  }
  const models = coded.map((k) => tableModel(widths[k], codes[k], what));
  const modelOf: Array<Int32Array | null> = new Array(64).fill(null);
  coded.forEach((k, q) => { modelOf[k] = models[q]; });
  // Wide alphabets search their quantile's slot rather than the whole table (a table's worth of
  // slots each: only for a layer of more cells than that).
  const slotted = total >= SLOTTED_CELLS;
  const slotsOfClass: Array<Int32Array | null> = modelOf.map((m, k) => (m && slotted && widths[k] >= SLOTTED_WIDTH ? slotsOf(m, 2 * widths[k] + 1) : null));
  const coder = new AnsDecoder(body.subarray(at), what);
  const k = kernels();
  if (k) {
    try {
      return predictedInKernels(k, body.subarray(at), a, modelOf, widths, mask, rows, cols, total);
    } catch (e) {
      if (!(e instanceof WasmMemoryError)) throw e;
    }
  }
  const V = new Float64Array(rows * cols);
  const E = new Float64Array(rows * cols);
  const nb = (g: Float64Array, r: number, c: number, up: number, left: number): number => {
    if (r === 0 && c === 0) return 0;
    if (up && r === 0) return g[c - 1];
    if (!up && c === 0) return g[(r - 1) * cols];
    const rr = Math.max(r - up, 0);
    const cc = Math.min(Math.max(c - left, 0), cols - 1);
    return g[rr * cols + cc];
  };
  // One anti-diagonal (2 r + c = k) at a time; its cells' errors decode class by class (0 to 63),
  // each class in the order of its cells (a stable counting sort), then its values predict.
  const most = longestWavefront(rows, cols);
  const line = new Int32Array(most);
  const lineClass = new Uint8Array(most);
  const order = new Int32Array(most);
  const starts = new Int32Array(65);
  const NONE = 255;
  // While every value so far is below 2**26 in magnitude, sum a_k x_k exactly in one float64 (each
  // product below 2**50, seven below 2**53); past that, split as the general case does.
  const SMALL = 2 ** 26;
  let small = true;
  for (let k = 0; k < 2 * (rows - 1) + cols; k++) {
    let n = 0;
    starts.fill(0);
    for (let r = Math.max(0, Math.ceil((k - cols + 1) / 2)); r < rows && 2 * r <= k; r++) {
      const c = k - 2 * r;
      const cell = r * cols + c;
      line[n] = cell;
      if (!mask[cell]) {
        lineClass[n++] = NONE;
        continue;
      }
      let act = 0;
      if (r >= 2 && c >= 2 && c < cols - 1) {
        const up = cell - cols;
        act = 2 * Math.abs(E[cell - 1]) + 2 * Math.abs(E[up]) + Math.abs(E[up - 1]) + Math.abs(E[up + 1])
          + Math.abs(E[cell - 2]) + Math.abs(E[up - cols]);
      } else {
        for (let q = 0; q < 7; q++) if (ACTIVITY[q]) act += ACTIVITY[q] * Math.abs(nb(E, r, c, UP[q], LEFT[q]));
      }
      let cls = 0;
      if (act > 0) {
        const bits = 32 - Math.clz32(act);
        const s = bits >= 2 ? (act >>> (bits - 2)) & 1 : 0;
        cls = Math.min(63, 2 * bits - 1 + s);
      }
      lineClass[n++] = cls;
      starts[cls + 1]++;
    }
    for (let cls = 0; cls < 64; cls++) starts[cls + 1] += starts[cls];
    for (let i = 0; i < n; i++) {
      const cls = lineClass[i];
      if (cls !== NONE) order[starts[cls]++] = line[i];
    }
    // starts[cls] is now the end of class cls; it began where class cls - 1 ended.
    for (let cls = 0, from = 0; cls < 64; cls++) {
      const to = starts[cls];
      const model = modelOf[cls];
      if (model) {
        const w = widths[cls];
        const m = 2 * w + 1;
        const slots = slotsOfClass[cls];
        if (slots) for (let i = from; i < to; i++) E[order[i]] = coder.decodeSlotted(model, slots) - w;
        else for (let i = from; i < to; i++) E[order[i]] = coder.decode(model, m) - w;
      }
      from = to;
    }
    for (let i = 0; i < n; i++) {
      const cell = line[i];
      const r = Math.floor(cell / cols);
      const c = cell - r * cols;
      let v: number;
      if (lineClass[i] !== NONE) {
        if (small && r >= 2 && c >= 2 && c < cols - 1) {
          const up = cell - cols;
          const up2 = up - cols;
          // P = (sum a_k x_k + 2**15) >> 16, the sum exact below 2**53.
          const S = a[0] * V[cell - 1] + a[1] * V[up] + a[2] * V[up - 1] + a[3] * V[up + 1] + a[4] * V[cell - 2]
            + a[5] * V[up2] + a[6] * V[up2 + 1];
          v = Math.floor((S + 32768) / 65536) + E[cell];
        } else {
          // P = (sum a_k x_k + 2**15) >> 16 exactly: x = 65536 xh + xl splits each product below 2**53.
          let sh = 0;
          let sl = 0;
          for (let q = 0; q < 7; q++) {
            const x = nb(V, r, c, UP[q], LEFT[q]);
            const xh = Math.floor(x / 65536);
            sh += a[q] * xh;
            sl += a[q] * (x - xh * 65536);
          }
          v = sh + Math.floor((sl + 32768) / 65536) + E[cell];
        }
      } else {
        v = nb(V, r, c, 0, 1);
      }
      if (Math.abs(v) >= 2 ** 31) throw new CorruptFileError(`${what} decodes to values beyond 2**31`);
      if (Math.abs(v) >= SMALL) small = false;
      V[cell] = v;
    }
  }
  const out = new Float64Array(total);
  for (let k = 0, c = 0; k < mask.length; k++) if (mask[k]) out[c++] = V[k];
  return out;
}

/** The longest wavefront (2 r + c = k) of a rows x cols grid. */
function longestWavefront(rows: number, cols: number): number {
  return Math.min(rows, Math.ceil(cols / 2) + 1);
}

/**
 * predicted()'s decode after its header, in the WebAssembly kernels (kernels.ts predicted): the same
 * wavefronts, classes, symbols and integer predictions, so the same values (web/test/wasm.test.mjs
 * compares the two paths on real and on random chunks). `words` has been checked by an AnsDecoder.
 * Throws WasmMemoryError when the kernels' memory cannot hold the grids.
 */
function predictedInKernels(k: Kernels, words: Uint8Array, a: number[], modelOf: Array<Int32Array | null>,
  widths: Int32Array, mask: Uint8Array, rows: number, cols: number, total: number): Float64Array {
  const cells = rows * cols;
  const most = longestWavefront(rows, cols);
  const sizes = [align16(words.length), align16(4 * cells), align16(40 * rows), align16(cells), align16(4 * most),
    align16(most), align16(4 * most), align16(4 * 65), 64 * 16, 32, 8 * total];
  const at: number[] = [];
  let end = k.scratch(sizes.reduce((x, y) => x + y, 0));
  for (const n of sizes) {
    at.push(end);
    end += n;
  }
  const [wP, vP, ringP, maskP, lineP, classP, orderP, startsP, descP, weightsP, outP] = at;
  // The tables above the scratch region, uploaded once per model (they move when it grows).
  const desc = new Int32Array(64 * 4);
  for (let cls = 0; cls < 64; cls++) {
    const m = modelOf[cls];
    if (!m) continue;
    const n = 2 * widths[cls] + 1;
    desc.set([k.ints(m), n >= KERNEL_SLOTTED_SYMBOLS ? k.ints(slotsOf(m, n)) : 0, n, widths[cls]], 4 * cls);
  }
  const mem = k.bytes();
  mem.set(words, wP);
  mem.set(mask, maskP);
  const i32s = new Int32Array(mem.buffer);
  i32s.set(desc, descP / 4);
  i32s.set(a, weightsP / 4);
  const status = k.ex.predicted(wP, words.length / 4, weightsP, descP, maskP, rows, cols, vP, ringP, lineP, classP, orderP,
    startsP, outP, SLOT_SHIFT);
  if (status) throw new CorruptFileError("predicted residual layer decodes to values beyond 2**31");
  return new Float64Array(k.view().buffer.slice(outP, outP + 8 * total));
}
