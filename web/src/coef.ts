// COEF-structured streams (format.md, "COEF"): chunks of kinds 0 (zstd byte planes), 1 (complex64)
// and 3 (ANS with table models), as COEF, BASE, RESD and a sparse residual's magnitudes hold them.
import { AnsDecoder, ansInKernels, decodeGroup, tableModel } from "./ans.js";
import { crc32, f32, inflate, u32 } from "./bytes.js";
import { CorruptFileError } from "./errors.js";
import { lap, mark } from "./stages.js";
import { kernels, WasmMemoryError } from "./wasm.js";

export const MAX_CHUNK_COEFS = 2 ** 28;
export const MAX_ANS_SYMBOL = 2 ** 15;
const BAND_LAYOUTS: Array<[number, number]> = [[4, 1], [8, 1], [8, 4], [8, 16]];

export interface Stream {
  /** Quantized integers (as doubles), or null for a complex stream. */
  ints: Float64Array | null;
  /** Complex values, real and imaginary interleaved, or null for an integer stream. */
  complex: Float64Array | null;
  /** Values decoded: the stream's length, or fewer from a cut section read progressively. */
  decoded: number;
}

export interface StreamOptions {
  /** 1.1's BASE and tile COEF, a sparse residual's magnitudes: chunk lengths of the writer's choosing. */
  free?: boolean;
  /** A prefix read progressively: whole chunks are kept, a cut one and those after it dropped. */
  partial?: boolean;
  /** Chunk kinds 4 and 5 are RESD's; everywhere else they are unknown kinds. */
  name?: string;
}

/** 1.0's chunk bounds: lengths 256, 512, 1024, ... cut at the stream's length. */
export function chunkBounds(total: number): Array<[number, number]> {
  const out: Array<[number, number]> = [];
  for (let start = 0, len = 256; start < total; start += len, len *= 2) out.push([start, Math.min(start + len, total)]);
  return out;
}

export function decodeStream(p: Uint8Array, total: number, radius: Float64Array | null,
  angle: Float64Array | null, options: StreamOptions = {}): Stream {
  const { free = false, partial = false } = options;
  const name = options.name ?? "coefficient";
  let ints: Float64Array | null = null;
  let complex: Float64Array | null = null;
  if (p.length < 4) {
    if (partial) return { ints: new Float64Array(total), complex: null, decoded: 0 };
    throw new CorruptFileError(`${name} section is truncated`);
  }
  const nchunks = u32(p, 0);
  const bounds = free ? null : chunkBounds(total);
  if (free ? nchunks > total : nchunks !== bounds!.length) {
    throw new CorruptFileError(`${name} section has ${nchunks} chunks, header implies ${free ? `at most ${total}` : bounds!.length}`);
  }
  let pos = 4;
  let stop = 0;
  let t = mark();
  let kinds = 0; // bit k: a chunk of kind k
  for (let k = 0; k < nchunks; k++) {
    if (pos + 16 > p.length) {
      if (partial) break;
      throw new CorruptFileError(`${name} chunk ${k} is truncated`);
    }
    const count = u32(p, pos);
    const nbytes = u32(p, pos + 4);
    const crc = u32(p, pos + 8);
    const kind = u32(p, pos + 12);
    const start = stop;
    const expected = free ? null : bounds![k][1] - bounds![k][0];
    if (free ? count < 1 || count > total - start : count !== expected) {
      throw new CorruptFileError(`${name} chunk ${k} holds ${count} values, expected ${expected ?? `1 to ${total - start}`}`);
    }
    if (count > MAX_CHUNK_COEFS) throw new CorruptFileError(`${name} chunk ${k} holds ${count} values, more than ${MAX_CHUNK_COEFS}`);
    if (pos + 16 + nbytes > p.length) {
      if (partial) break;
      throw new CorruptFileError(`${name} chunk ${k} is truncated`);
    }
    const body = p.subarray(pos + 16, pos + 16 + nbytes);
    if (crc32(body) !== crc) throw new CorruptFileError(`${name} chunk ${k} fails its checksum`);
    t = lap("checksums", t);
    pos += 16 + nbytes;
    stop = start + count;
    const what = `${name} chunk ${k}`;
    if (kind === 1) {
      if (ints) throw new CorruptFileError(`${name} chunks mix kinds`);
      if (nbytes !== 8 * count) throw new CorruptFileError(`${what} has a wrong length`);
      complex ??= new Float64Array(2 * total);
      for (let v = 0; v < 2 * count; v++) complex[2 * start + v] = f32(body, 4 * v);
    } else if (kind === 0 || kind === 3) {
      if (complex) throw new CorruptFileError(`${name} chunks mix kinds`);
      ints ??= new Float64Array(total);
      if (kind === 0) {
        zstdChunk(body, count, ints, start, what);
        t = lap("coefficients (zstd)", t);
      } else {
        ansChunk(body, count, ints, start, radius, angle, what);
        t = lap("coefficients (ANS)", t);
      }
    } else {
      throw new CorruptFileError(`${what} has unknown kind ${kind}`);
    }
    kinds |= 1 << kind;
  }
  if (!partial && stop !== total) throw new CorruptFileError(`${name} chunks hold ${stop} values, expected ${total}`);
  if (!partial && pos !== p.length && !free) {
    // Bytes after the last chunk are no part of the stream; the reader of a section checks its end.
  }
  if (!ints && !complex) ints = new Float64Array(total);
  void kinds;
  return { ints, complex, decoded: stop };
}

/** Where a stream's chunks end, for structures that must end at a given byte (a sparse residual). */
export function streamEnd(p: Uint8Array): number {
  let pos = 4;
  const n = u32(p, 0);
  for (let k = 0; k < n && pos + 16 <= p.length; k++) pos += 16 + u32(p, pos + 4);
  return pos;
}

function zstdChunk(body: Uint8Array, count: number, out: Float64Array, start: number, what: string): void {
  const raw = inflate(body, 1 + 8 * count, what);
  const w = raw.length ? raw[0] : 0;
  if (w < 1 || w > 8 || raw.length !== 1 + w * count) throw new CorruptFileError(`${what} has an inconsistent length`);
  if (w <= 4) {
    // The common widths in one pass without the inner loop (a few times faster in V8): the same sums.
    const p1 = 1 + count;
    const p2 = 1 + 2 * count;
    const p3 = 1 + 3 * count;
    for (let v = 0; v < count; v++) {
      let lo = raw[1 + v];
      if (w > 1) lo += raw[p1 + v] * 256;
      if (w > 2) lo += raw[p2 + v] * 65536;
      if (w > 3) lo += raw[p3 + v] * 16777216;
      out[start + v] = lo % 2 === 0 ? lo / 2 : -(lo + 1) / 2;
    }
    return;
  }
  for (let v = 0; v < count; v++) {
    let lo = 0;
    let hi = 0;
    for (let b = 0; b < Math.min(w, 4); b++) lo += raw[1 + b * count + v] * 2 ** (8 * b);
    for (let b = 4; b < w; b++) hi += raw[1 + b * count + v] * 2 ** (8 * (b - 4));
    // Zigzag: z even is q = z / 2, z odd is q = -(z + 1) / 2 (one rounding each, as int64 -> float64).
    out[start + v] = lo % 2 === 0 ? (hi * 4294967296 + lo) / 2 : -(hi * 4294967296 + (lo + 1)) / 2;
  }
}

/** The band of a coefficient at radius r and angle a (format.md, COEF kind 3, step 1). */
function bandOf(r: number, a: number, width: number, sectors: number): number {
  return Math.floor(r / width) * sectors + Math.min(Math.floor(a * sectors), sectors - 1);
}

const bandTables = new WeakMap<Float64Array, Array<Int32Array | undefined>>();

/** Every coefficient's band in a layout, for a stream's radius and angle arrays: computed once while
 * the arrays live (layout.ts caches a grid's order, so a map's later decodes, such as a progressive
 * load's prefixes, skip the floating-point steps). */
function bandsOf(radius: Float64Array, angle: Float64Array, layout: number): Int32Array {
  let byLayout = bandTables.get(radius);
  if (!byLayout) bandTables.set(radius, (byLayout = []));
  let bands = byLayout[layout];
  if (!bands) {
    const [width, sectors] = BAND_LAYOUTS[layout];
    bands = new Int32Array(radius.length);
    for (let v = 0; v < radius.length; v++) bands[v] = bandOf(radius[v], angle[v], width, sectors);
    byLayout[layout] = bands;
  }
  return bands;
}

function ansChunk(body: Uint8Array, count: number, out: Float64Array, start: number,
  radius: Float64Array | null, angle: Float64Array | null, what: string): void {
  if (body.length < 9) throw new CorruptFileError(`${what} is truncated`);
  const layout = body[0];
  const maxAbs = u32(body, 1);
  const side = u32(body, 5);
  if (layout >= BAND_LAYOUTS.length || maxAbs > MAX_ANS_SYMBOL || 9 + side > body.length) {
    throw new CorruptFileError(`${what} has an implausible header`);
  }
  const bands = radius && angle && radius.length === angle.length && radius.length >= start + count ? bandsOf(radius, angle, layout) : null;
  const band = new Int32Array(count);
  let lo = Infinity;
  let hi = -Infinity;
  if (bands) {
    for (let v = 0; v < count; v++) {
      const b = bands[start + v];
      band[v] = b;
      if (b < lo) lo = b;
      if (b > hi) hi = b;
    }
  } else {
    const [width, sectors] = BAND_LAYOUTS[layout];
    for (let v = 0; v < count; v++) {
      const r = radius ? radius[start + v] : 0;
      const a = angle ? angle[start + v] : 0;
      const b = bandOf(r, a, width, sectors);
      band[v] = b;
      if (b < lo) lo = b;
      if (b > hi) hi = b;
    }
  }
  const nbands = hi - lo + 1;
  let codes: Uint8Array;
  if (side === nbands) codes = body.subarray(9, 9 + side);
  else if (side > nbands) throw new CorruptFileError(`${what} has ${side} bytes of band scales for ${nbands} bands`);
  else codes = inflate(body.subarray(9, 9 + side), nbands, `${what}'s band scales`);
  if (codes.length !== nbands) throw new CorruptFileError(`${what} has ${codes.length} band scales, expected ${nbands}`);
  // The values of each scale code in stream order, codes ascending (a counting sort; code 0 is all zeros).
  const ends = new Int32Array(257);
  for (let v = 0; v < count; v++) {
    const c = codes[band[v] - lo];
    band[v] = c;
    ends[c + 1]++;
  }
  let groups = 0;
  for (let c = 1; c < 256; c++) if (ends[c + 1]) groups++;
  if (groups * (2 * maxAbs + 1) > 16 * count + 2 ** 19) {
    throw new CorruptFileError(`${what} asks for larger probability tables than its ${count} values allow`);
  }
  for (let c = 0; c < 256; c++) ends[c + 1] += ends[c];
  const at = new Int32Array(count);
  const fill = ends.slice(0, 256);
  for (let v = 0; v < count; v++) at[fill[band[v]]++] = v;
  const words = body.subarray(9 + side);
  const coder = new AnsDecoder(words, what); // checks the words before either path reads them
  const used: number[] = [];
  for (let c = 1; c < 256; c++) if (ends[c + 1] > ends[c]) used.push(c);
  const models = used.map((c) => tableModel(maxAbs, c, what));
  const here = out.subarray(start, start + count);
  const k = kernels();
  if (k && used.length) {
    try {
      const groups = used.map((c, q) => ({ cdf: models[q], count: ends[c + 1] - ends[c] }));
      // Code 0's values (zeros) come first in `at`: the kernel decodes the rest.
      ansInKernels(k, words, groups, maxAbs, at.subarray(ends[1]), here);
      return;
    } catch (e) {
      if (!(e instanceof WasmMemoryError)) throw e;
    }
  }
  used.forEach((c, q) => decodeGroup(coder, models[q], maxAbs, here, at.subarray(ends[c], ends[c + 1]), ends[c + 1] - ends[c]));
}
