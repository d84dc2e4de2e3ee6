// decode(bytes, options): a .dftpc file (version 1.0, the tiled 1.1, or 1.2 of either layout) to its DEM, as LERC's
// JavaScript decoder returns pixels and mask. format.md "Decoding", "Progressive decoding" and
// "Tiles: version 1.1".
import { count as fmt, f32, inflate, u16, u32 } from "./bytes.js";
import { decodeStream } from "./coef.js";
import {
  budgetMessage, byTile, cellBudget, Entry, Geometry, MAX_CELLS, Params, parseCrs, parseGeom, parseParams, parseStat,
  parseTable, payload,
} from "./container.js";
import { CorruptFileError, guard, InvalidInputError, ResourceLimitError } from "./errors.js";
import { baseCut, cutOf, prefix, Transform } from "./layout.js";
import { countOnes, decodeMask } from "./mask.js";
import { lap, mark } from "./stages.js";
import { decodeResidual, decodeResidualLayer, spread, SparseResidual } from "./residual.js";
import { addIdct, idctFinishedInKernels, idctInKernels, ifft2Shifted, irfft2, sampleIdct } from "./transform.js";
import { align16, Kernels, kernels, releaseKernels, WasmMemoryError } from "./wasm.js";

export interface DecodeOptions {
  /** Decode only the first maxBytes bytes, as if the rest had not arrived (untiled maps). */
  maxBytes?: number;
  /** Size of the whole file when `bytes` is a prefix of it (the budget counts the whole file). */
  fileSize?: number;
  /** Cells a trusted file may ask for beyond the default budget (never beyond 10^8). */
  maxCells?: number;
  /** Decode an untiled map at a larger cutoff than its own. */
  cutoff?: number;
  /** Only these cells: [start, stop) row and column ranges (of a tiled map only its tiles decode). */
  window?: { rows: [number, number]; cols: [number, number] };
  /** Heights as float32 rather than float64. */
  float32?: boolean;
  /** A progressive prefix of an untiled DCT map (ignored otherwise): its spectrum holds low
   * frequencies only, so the heights are evaluated every few cells (PREVIEW_SAMPLES a shortest
   * period along each axis) and bilinear between them, a preview much cheaper than the whole grid's
   * inverse in TypeScript; it differs from the exact prefix decode by that interpolation
   * (DecodedMap.stride). Where the WebAssembly kernels run (useWasm), the exact decode costs less
   * and is returned instead. */
  preview?: boolean;
}

export interface Header {
  version: string;
  tiled: boolean;
  geometry: Geometry;
  params: Params;
  stats: Record<string, number>;
  crs: Record<string, unknown>;
  sizes: { mask_bytes: number; coef_bytes: number; residual_bytes: number };
  tiles?: { size: number; overlap: number; reach: number; ty: number; tx: number; cells: Float64Array };
}

export interface DecodedMap {
  /** Columns and rows of the decoded window (the whole grid unless options.window). */
  width: number;
  height: number;
  /** First row and column of the window in the map's grid. */
  row0: number;
  col0: number;
  /** Heights (metres, z0 included), row-major, row 0 at the smallest v; NaN where mask is 0. */
  heights: Float32Array | Float64Array;
  /** 1 where the cell is rebuilt. */
  mask: Uint8Array;
  header: Header;
  statistics: { minZ: number; maxZ: number; cells: number };
  /** Bytes the decode used: the file, or the prefix read progressively. */
  bytesRead: number;
  /** Whether the COEF section was cut (a progressive prefix): the map is low-passed further. */
  partial: boolean;
  /** Cells between the heights evaluated exactly, the rest interpolated (options.preview); absent: 1. */
  stride?: number;
}

const TIDX_HEAD = 8;

/** The header of a .dftpc file (every check of format-validation.md sections 1-3 and, for a tiled
 * map, its tile index), without decoding the map. */
export function readHeader(bytes: Uint8Array, options: DecodeOptions = {}): Header {
  return guard("damaged file", () => open(bytes, options).header);
}

interface Opened {
  data: Uint8Array;
  header: Header;
  sections: Map<string, Uint8Array | null>; // null: cut by a progressive prefix
  entries: Entry[];
  size: number;
  cutCoef: boolean;
  /** A 1.0 or 1.1 file: the coefficients follow the legacy hypot order (format.md). */
  legacy: boolean;
}

function open(bytes: Uint8Array, options: DecodeOptions): Opened {
  const { maxBytes, maxCells } = options;
  if (maxBytes !== undefined && !(Number.isInteger(maxBytes) && maxBytes >= 0)) throw new InvalidInputError("maxBytes must be a whole number >= 0");
  if (maxCells !== undefined && !(Number.isInteger(maxCells) && maxCells > 0)) throw new InvalidInputError("maxCells must be a whole number > 0");
  const size = Math.max(options.fileSize ?? bytes.length, bytes.length);
  const partial = maxBytes !== undefined || size > bytes.length;
  const data = maxBytes !== undefined ? bytes.subarray(0, maxBytes) : bytes;
  const table = parseTable(data);
  const tiles = byTile(table.entries);
  const tile0 = tiles.get(0) ?? new Map<string, Entry>();
  const tiled = tile0.has("TIDX");
  if (tiled && table.minor === 0) throw new CorruptFileError("a version 1.0 file holds a tile index (TIDX): a tiled map is version 1.1");
  if (tiled && partial) throw new InvalidInputError("a tiled map (format 1.1) has no progressive decoding: decode a window instead");
  if (tiled && options.cutoff !== undefined) throw new InvalidInputError("a tiled map (format 1.1) decodes at its own cutoff only");
  const sections = new Map<string, Uint8Array | null>();
  let cutCoef = false;
  for (const [tag, e] of tile0) {
    if (partial && e.offset + e.length > data.length && (tag === "COEF" || tag === "RESD")) {
      // A progressive prefix: a cut COEF is kept as far as it goes (chunk CRCs only), a cut RESD dropped.
      if (tag === "COEF") {
        sections.set(tag, data.subarray(Math.min(e.offset, data.length)));
        cutCoef = true;
      } else sections.set(tag, null);
      continue;
    }
    sections.set(tag, payload(data, e));
  }
  const required = tiled ? ["GEOM", "PARM", "STAT", "TIDX", "BASE"] : ["GEOM", "PARM", "MASK", "COEF"];
  for (const tag of required) if (!sections.has(tag)) throw new CorruptFileError(`section ${tag} is missing`);
  if (tiled) {
    for (const tag of ["COEF"]) if (sections.has(tag)) throw new CorruptFileError(`a tiled map holds no section ${tag} at tile 0`);
  }
  const geometry = parseGeom(sections.get("GEOM")!, tiled, size, maxCells);
  const params = parseParams(sections.get("PARM")!, geometry);
  const stats = sections.has("STAT") ? parseStat(sections.get("STAT")!) : {};
  const crs = sections.has("CRS ") ? parseCrs(sections.get("CRS ")!) : {};
  const cc = stats.coef_count;
  if (cc === undefined || !(cc >= 0 && cc <= geometry.rows * geometry.cols)) {
    throw new CorruptFileError("coefficient count is missing or implausible");
  }
  const len = (tag: string) => tile0.get(tag)?.length ?? 0;
  const header: Header = {
    version: `${table.major}.${table.minor}`, tiled, geometry, params, stats, crs,
    sizes: { mask_bytes: len("MASK"), coef_bytes: len("COEF"), residual_bytes: len("RESD") },
  };
  if (tiled) header.tiles = tileIndex(sections, header, data.length, tiles);
  return { data, header, sections, entries: table.entries, size, cutCoef, legacy: table.minor < 2 };
}

/** A .dftpc file's DEM. Throws the classes of errors.ts only. */
export function decode(bytes: Uint8Array, options: DecodeOptions = {}): DecodedMap {
  return guard("damaged file", () => {
    try {
      const t = mark();
      const o = open(bytes, options);
      lap("header", t);
      const out = o.header.tiled ? decodeTiled(o, options) : decodeWhole(o, options);
      return out;
    } finally {
      releaseKernels();
    }
  });
}

function finish(o: Opened, h: Float64Array, mask: Uint8Array, rows: number, cols: number, row0: number, col0: number,
  options: DecodeOptions, partial: boolean): DecodedMap {
  const z0 = o.header.geometry.z0;
  const heights = options.float32 ? new Float32Array(h.length) : new Float64Array(h.length);
  let minZ = Infinity;
  let maxZ = -Infinity;
  let cells = 0;
  for (let k = 0; k < h.length; k++) {
    if (mask[k]) {
      const z = z0 + h[k];
      heights[k] = z;
      if (z < minZ) minZ = z;
      if (z > maxZ) maxZ = z;
      cells++;
    } else heights[k] = NaN;
  }
  return {
    width: cols, height: rows, row0, col0, heights, mask, header: o.header,
    statistics: { minZ, maxZ, cells }, bytesRead: o.data.length, partial,
  };
}

function checkFinite(h: Float64Array, mask: Uint8Array, prefix = ""): void {
  for (let k = 0; k < h.length; k++) {
    if (mask[k] && !Number.isFinite(h[k])) throw new CorruptFileError(`${prefix}coefficients decode to non-finite heights (damaged or crafted file)`);
  }
}

function checkWindow(options: DecodeOptions, rows: number, cols: number): [number, number, number, number] {
  if (!options.window) return [0, rows, 0, cols];
  const { rows: [r0, r1], cols: [c0, c1] } = options.window;
  if (![r0, r1, c0, c1].every(Number.isInteger) || !(0 <= r0 && r0 < r1 && r1 <= rows && 0 <= c0 && c0 < c1 && c1 <= cols)) {
    throw new InvalidInputError(`window rows [${r0}, ${r1}), cols [${c0}, ${c1}) is not inside the ${rows} x ${cols} grid`);
  }
  return [r0, r1, c0, c1];
}

// --- version 1.0 -----------------------------------------------------------------------------------

function decodeWhole(o: Opened, options: DecodeOptions): DecodedMap {
  const { geometry: g, params, stats } = o.header;
  const { rows, cols } = g;
  const [wr0, wr1, wc0, wc1] = checkWindow(options, rows, cols);
  let t = mark();
  const mask = decodeMask(o.sections.get("MASK")!, rows, cols);
  if (countOnes(mask) !== g.cells) throw new CorruptFileError("occupancy mask disagrees with the header's cell count");
  t = lap("mask", t);
  const kind: Transform = params.transform === "dct" ? "dct" : params.storage === "complex64" ? "dft-full" : "dft-half";
  const pre = prefix(rows, cols, kind, cutOf(rows, cols, kind, params.cutoff, o.legacy));
  const kept = pre.pos.length;
  if (stats.coef_count !== kept) throw new CorruptFileError("coefficient count disagrees with the grid and cutoff");
  let use = kept;
  if (options.cutoff !== undefined) {
    const c = options.cutoff;
    if (!(typeof c === "number" && c >= 0 && c < 1)) throw new InvalidInputError("cutoff must be in [0, 1)");
    if (c < params.cutoff) throw new InvalidInputError(`cannot decode at cutoff ${c}: the file holds coefficients up to cutoff ${params.cutoff} only`);
    use = prefix(rows, cols, kind, cutOf(rows, cols, kind, c, o.legacy)).pos.length;
  }
  const pairs = kind === "dft-half";
  const per = pairs ? 2 : 1;
  // A DFT's pairs share their coefficient's radius and angle; a DCT reads the cached order's own.
  let radius = pre.radius;
  let angle = pre.angle;
  if (per > 1) {
    radius = new Float64Array(per * kept);
    angle = new Float64Array(per * kept);
    for (let k = 0; k < kept; k++) {
      for (let q = 0; q < per; q++) {
        radius[per * k + q] = pre.radius[k];
        angle[per * k + q] = pre.angle[k];
      }
    }
  }
  const coef = o.sections.get("COEF")!;
  t = lap("coefficient order", t);
  const s = decodeStream(coef, per * kept, radius, angle, { partial: o.cutCoef });
  t = mark();
  // A progressive prefix holds the first coefficients only (the rest are zeros): its corner of the
  // spectrum, and so its inverse, is that much smaller.
  if (kind === "dct") use = Math.min(use, s.decoded);
  // A preview samples a cut spectrum; a residual layer (whole only if COEF is) keeps the exact path,
  // and so do the kernels: their exact inverse costs less than the samples' sums, interpolation and
  // finishing pass in TypeScript (web/bench: a 5 % prefix 3.8 to 8.2 ms exact, 3.9 to 14 ms sampled).
  const preview = options.preview === true && o.cutCoef && kind === "dct" && !o.sections.get("RESD") && kernels() === null;
  const plane = params.detrend === "plane" ? g.plane : null;
  const resd = o.sections.get("RESD") ?? null;
  // The residual layer's integers, once decoded (by the kernels' path, kept should it fall back).
  let q: Float64Array | SparseResidual | null = null;
  if (kind === "dct") {
    const k = kernels();
    let corner: Corner | null = null;
    if (k && params.storage === "quantized" && s.ints) {
      const ints = s.ints;
      const step = params.step;
      corner = cornerOf(pre.pos, use, ints, 1, step, cols);
    } else if (k && params.storage !== "quantized" && s.complex) {
      const v = s.complex;
      corner = cornerOf(pre.pos, use, v, 2, 1, cols); // a complex64 DCT: the real parts
    }
    t = lap("corner", t);
    if (k && corner && previewStride(corner, rows, cols, preview) === 1) {
      if (resd) {
        q = residualOf(o, resd, mask, rows, cols);
        t = lap("residual layer", t);
      }
      try {
        const win = [wr0, wr1, wc0, wc1];
        const out = q ? residualInKernels(k, o, corner, q, mask, rows, cols, win, plane, options)
          : finishInKernels(k, o, corner, mask, rows, cols, win, plane, options, o.cutCoef);
        lap("inverse and finish (WebAssembly)", t);
        return out;
      } catch (e) {
        if (!(e instanceof WasmMemoryError)) throw e;
      }
    }
  }
  const h = new Float64Array(rows * cols);
  let stride = 1;
  if (params.storage === "quantized") {
    if (!s.ints) throw new CorruptFileError("quantized file holds float coefficients");
    const step = params.step;
    if (kind === "dct") {
      const ints = s.ints;
      stride = addDctCorner(h, pre.pos, use, ints, 1, step, rows, cols, preview);
    } else {
      const v = new Float64Array(2 * use);
      for (let k = 0; k < 2 * use; k++) v[k] = s.ints[k] * step;
      irfft2(pre.pos.subarray(0, use), v, rows, cols, h);
    }
  } else {
    if (!s.complex && kept) throw new CorruptFileError("complex64 file holds integer coefficients");
    const v = s.complex ?? new Float64Array(0);
    if (kind === "dct") {
      stride = addDctCorner(h, pre.pos, use, v, 2, 1, rows, cols, preview); // a complex64 DCT: the real parts
    } else if (kind === "dft-full") {
      ifft2Shifted(pre.pos.subarray(0, use), v.subarray(0, 2 * use), rows, cols, h);
    } else {
      irfft2(pre.pos.subarray(0, use), v.subarray(0, 2 * use), rows, cols, h);
    }
  }
  t = lap("inverse", t);
  if (resd) {
    const e = params.target_max_error;
    q ??= residualOf(o, resd, mask, rows, cols);
    if (!(q instanceof Float64Array)) q = spread(q, mask);
    t = lap("residual layer", t);
    // The plane first, as the writer sums them (heights + plane, then the residual).
    if (params.detrend === "plane") addPlane(h, rows, cols, g.plane);
    for (let k = 0, c = 0; k < mask.length; k++) if (mask[k]) h[k] += q[c++] * 2 * e * (1 - 1e-6);
    const out = finishWindow(o, h, mask, rows, cols, [wr0, wr1, wc0, wc1], null, options, o.cutCoef);
    lap("finish", t);
    return out;
  }
  const out = finishWindow(o, h, mask, rows, cols, [wr0, wr1, wc0, wc1], plane, options, o.cutCoef);
  lap("finish", t);
  if (stride > 1) out.stride = stride;
  return out;
}

/** The residual layer's integers (one per rebuilt cell), refused in a file without a maximum-error target. */
function residualOf(o: Opened, resd: Uint8Array, mask: Uint8Array, rows: number, cols: number): Float64Array | SparseResidual {
  if (!(o.header.params.target_max_error > 0)) {
    throw new CorruptFileError("a residual layer (RESD) in a file without a maximum-error target");
  }
  return decodeResidualLayer(resd, mask, rows, cols);
}

/** decodeWhole's inverse DCT of a corner, plane, residual layer (its integers q) and finishWindow's
 * pass in the WebAssembly kernels: the TypeScript path's operations in its order, so its heights.
 * For the whole grid the pass is fused into the inverse's last axis (kernels.ts finishCell, with the
 * residual's terms as a grid), as cornerFinished does without a residual. Throws WasmMemoryError
 * when the kernels' memory cannot hold the grid. */
function residualInKernels(k: Kernels, o: Opened, corner: Corner, q: Float64Array | SparseResidual, mask: Uint8Array, rows: number,
  cols: number, [wr0, wr1, wc0, wc1]: number[], plane: number[] | null, options: DecodeOptions): DecodedMap {
  const f32 = options.float32 === true;
  const W = wc1 - wc0;
  const H = wr1 - wr0;
  const whole = H === rows && W === cols;
  const e = o.header.params.target_max_error;
  const z0 = o.header.geometry.z0;
  const [a, b, c] = plane ?? [0, 0, 0];
  // A sparse layer goes in as its picture and nonzero integers (a byte a cell, not a double).
  const sparse = q instanceof Float64Array ? null : q;
  const values = sparse ? sparse.nonzero : (q as Float64Array);
  // The extra scratch after the grid: mask, heights, 16 bytes of results, the residual's integers,
  // its picture, and (fused) the grid of its terms.
  const maskBytes = align16(rows * cols);
  const heightBytes = align16((f32 ? 4 : 8) * H * W);
  const valueBytes = align16(8 * values.length);
  const pictureBytes = sparse ? align16(rows * cols) : 0;
  const layout = (extraP: number) => {
    const maskP = extraP;
    const outP = maskP + maskBytes;
    const resP = outP + heightBytes;
    const qP = resP + 16;
    const pictureP = qP + valueBytes;
    const gridP = pictureP + pictureBytes;
    k.bytes().set(mask, maskP);
    k.view().set(values, qP / 8);
    if (sparse) k.bytes().set(sparse.picture, pictureP);
    return { maskP, outP, resP, qP, pictureP: sparse ? pictureP : 0, gridP };
  };
  const extra = maskBytes + heightBytes + 16 + valueBytes + pictureBytes;
  let at: ReturnType<typeof layout> | null = null;
  let hP: number;
  let fused = false;
  if (whole) {
    const r = idctFinishedInKernels(k, corner.g, corner.K, corner.L, rows, cols, extra + align16(8 * rows * cols), (finP, extraP, down) => {
      at = layout(extraP);
      k.ex.residualGrid(at.gridP, at.maskP, at.qP, at.pictureP, rows * cols, e);
      k.view().set([z0, a, b, c, Infinity, -Infinity], finP / 8);
      new Int32Array(k.view().buffer, finP + 48, 8).set([at.maskP, at.outP, f32 ? 1 : 0, cols, 0, down ? 1 : 0, at.gridP, plane ? 1 : 0]);
    });
    hP = r.grid;
    fused = r.fused;
    if (!fused) at = layout(r.extra);
  } else {
    hP = idctInKernels(k, corner.g, corner.K, corner.L, rows, cols, 0, rows, 0, cols, extra);
    at = layout(hP + align16(8 * rows * cols));
  }
  const { maskP, outP, resP, qP, pictureP } = at!;
  const f = finishedWindow(k, fused, maskP, hP, outP, resP, () => {
    k.ex.addResidual(hP, maskP, qP, pictureP, rows, cols, plane ? 1 : 0, a, b, c, e);
    // The plane is in the grid now: the finishing pass adds z0 alone, as finishWindow's does.
    return k.ex.finish(hP, maskP, outP, cols, wr0, wr1, wc0, wc1, z0, 0, 0, 0, f32 ? 1 : 0, resP);
  }, mask, null, rows, cols, [wr0, wr1, wc0, wc1], f32);
  return {
    width: W, height: H, row0: wr0, col0: wc0, heights: f.heights, mask: f.mask, header: o.header,
    statistics: { minZ: f.minZ, maxZ: f.maxZ, cells: f.cells }, bytesRead: o.data.length, partial: o.cutCoef,
  };
}

function addPlane(h: Float64Array, rows: number, cols: number, [a, b, c]: number[]): void {
  for (let r = 0; r < rows; r++) {
    const row = a + c * r;
    for (let cc = 0, k = r * cols; cc < cols; cc++, k++) h[k] += row + b * cc;
  }
}

/** The window's heights from the whole grid's h (plus the plane a + b c + c r when given), z0 added,
 * NaN off the mask, in one pass (each pass over a grid costs a few ns a cell in V8): in place when
 * the window is the grid and float64 is asked for. */
function finishWindow(o: Opened, h: Float64Array, mask: Uint8Array, rows: number, cols: number,
  [wr0, wr1, wc0, wc1]: number[], plane: number[] | null, options: DecodeOptions, partial: boolean): DecodedMap {
  const z0 = o.header.geometry.z0;
  const W = wc1 - wc0;
  const H = wr1 - wr0;
  const whole = H === rows && W === cols;
  const heights = whole && !options.float32 ? h : options.float32 ? new Float32Array(H * W) : new Float64Array(H * W);
  const outMask = whole ? mask : new Uint8Array(H * W);
  const [a, b, c] = plane ?? [0, 0, 0];
  let minZ = Infinity;
  let maxZ = -Infinity;
  let cells = 0;
  for (let r = wr0; r < wr1; r++) {
    const row = z0 + (a + c * r);
    const k0 = r * cols;
    const t0 = (r - wr0) * W;
    if (!whole) outMask.set(mask.subarray(k0 + wc0, k0 + wc1), t0);
    for (let q = wc0, k = k0 + wc0, t = t0; q < wc1; q++, k++, t++) {
      if (mask[k]) {
        const z = h[k] + (row + b * q);
        heights[t] = z;
        // Math.min and max carry a NaN through: the finite check below costs the loop nothing.
        minZ = Math.min(minZ, z);
        maxZ = Math.max(maxZ, z);
        cells++;
      } else heights[t] = NaN;
    }
  }
  if ((cells && !(Number.isFinite(minZ) && Number.isFinite(maxZ))) || (!whole && !allFinite(h, mask, plane, rows, cols))) {
    throw new CorruptFileError("coefficients decode to non-finite heights (damaged or crafted file)");
  }
  return {
    width: W, height: H, row0: wr0, col0: wc0, heights, mask: outMask, header: o.header,
    statistics: { minZ, maxZ, cells }, bytesRead: o.data.length, partial,
  };
}

/** decodeWhole's inverse DCT of a corner and finishWindow's pass in the WebAssembly kernels (the
 * same operations in the same order: the same heights). Throws WasmMemoryError when the kernels'
 * memory cannot hold the grid. */
function finishInKernels(k: Kernels, o: Opened, corner: Corner, mask: Uint8Array, rows: number, cols: number,
  win: number[], plane: number[] | null, options: DecodeOptions, partial: boolean): DecodedMap {
  const f = cornerFinished(k, corner, mask, rows, cols, win, o.header.geometry.z0, plane, options.float32 === true);
  return {
    width: win[3] - win[2], height: win[1] - win[0], row0: win[0], col0: win[2], heights: f.heights, mask: f.mask,
    header: o.header, statistics: { minZ: f.minZ, maxZ: f.maxZ, cells: f.cells }, bytesRead: o.data.length, partial,
  };
}

/** The heights of the window [wr0, wr1) x [wc0, wc1) from a corner of DCT coefficients of the whole
 * rows x cols grid, as finishWindow gives them (z0 and the plane a + b q + c r added, NaN off the
 * mask), by the kernels. Throws WasmMemoryError when their memory cannot hold the grid. */
export function cornerFinished(k: Kernels, corner: Corner, mask: Uint8Array, rows: number, cols: number,
  [wr0, wr1, wc0, wc1]: number[], z0: number, plane: number[] | null, f32: boolean):
  { heights: Float32Array | Float64Array; mask: Uint8Array; minZ: number; maxZ: number; cells: number } {
  const W = wc1 - wc0;
  const H = wr1 - wr0;
  const whole = H === rows && W === cols;
  const maskBytes = align16(rows * cols);
  const heightBytes = align16((f32 ? 4 : 8) * H * W);
  const extra = maskBytes + heightBytes + 16;
  const [a, b, c] = plane ?? [0, 0, 0];
  let hP: number;
  let maskP: number;
  let fused = false;
  if (whole) {
    // The finishing pass fused into the inverse's last axis (see idctFinishedInKernels).
    const r = idctFinishedInKernels(k, corner.g, corner.K, corner.L, rows, cols, extra, (finP, extraP, down) => {
      k.bytes().set(mask, extraP);
      k.view().set([z0, a, b, c, Infinity, -Infinity], finP / 8);
      new Int32Array(k.view().buffer, finP + 48, 8).set([extraP, extraP + maskBytes, f32 ? 1 : 0, cols, 0, down ? 1 : 0, 0, 0]);
    });
    hP = r.grid;
    maskP = r.extra;
    fused = r.fused;
  } else {
    hP = idctInKernels(k, corner.g, corner.K, corner.L, rows, cols, 0, rows, 0, cols, extra);
    maskP = hP + align16(8 * rows * cols);
  }
  const outP = maskP + maskBytes;
  const resP = outP + heightBytes;
  return finishedWindow(k, fused, maskP, hP, outP, resP, () => {
    k.bytes().set(mask, maskP);
    return k.ex.finish(hP, maskP, outP, cols, wr0, wr1, wc0, wc1, z0, a, b, c, f32 ? 1 : 0, resP);
  }, mask, plane, rows, cols, [wr0, wr1, wc0, wc1], f32);
}

/** A window the kernels finished: the fused pass's results (``fused``: its block 80 bytes before
 * ``maskP``) or ``finish()``'s (which runs the finishing pass and returns the cells it counted, its
 * extremes at ``resP``); refused where a rebuilt height is not finite (the whole grid at ``hP``,
 * ``gridPlane`` added, checked for a window), and its heights (at ``outP``) and mask copied out. */
function finishedWindow(k: Kernels, fused: boolean, maskP: number, hP: number, outP: number, resP: number,
  finish: () => number, mask: Uint8Array, gridPlane: number[] | null, rows: number, cols: number,
  [wr0, wr1, wc0, wc1]: number[], f32: boolean):
  { heights: Float32Array | Float64Array; mask: Uint8Array; minZ: number; maxZ: number; cells: number } {
  const W = wc1 - wc0;
  const H = wr1 - wr0;
  const whole = H === rows && W === cols;
  let cells: number;
  let mem: Float64Array;
  let minZ: number;
  let maxZ: number;
  if (fused) {
    mem = k.view();
    const finP = maskP - 80;
    minZ = mem[finP / 8 + 4];
    maxZ = mem[finP / 8 + 5];
    cells = new Int32Array(mem.buffer, finP + 64, 1)[0];
  } else {
    cells = finish();
    mem = k.view();
    minZ = mem[resP / 8];
    maxZ = mem[resP / 8 + 1];
  }
  if ((cells && !(Number.isFinite(minZ) && Number.isFinite(maxZ)))
    || (!whole && !allFinite(mem.subarray(hP / 8, hP / 8 + rows * cols), mask, gridPlane, rows, cols))) {
    throw new CorruptFileError("coefficients decode to non-finite heights (damaged or crafted file)");
  }
  const heights = f32 ? new Float32Array(mem.buffer.slice(outP, outP + 4 * H * W)) : new Float64Array(mem.buffer.slice(outP, outP + 8 * H * W));
  let outMask = mask;
  if (!whole) {
    outMask = new Uint8Array(H * W);
    for (let r = wr0; r < wr1; r++) outMask.set(mask.subarray(r * cols + wc0, r * cols + wc1), (r - wr0) * W);
  }
  return { heights, mask: outMask, minZ, maxZ, cells };
}

/** Every rebuilt cell of the grid finite (a window's decode refuses a damaged file as a whole one does). */
function allFinite(h: Float64Array, mask: Uint8Array, plane: number[] | null, rows: number, cols: number): boolean {
  const [a, b, c] = plane ?? [0, 0, 0];
  for (let r = 0; r < rows; r++) {
    const row = a + c * r;
    for (let q = 0, k = r * cols; q < cols; q++, k++) {
      if (mask[k]) {
        const v = plane ? h[k] + row + b * q : h[k];
        if (v - v !== 0) return false;
      }
    }
  }
  return true;
}

// --- version 1.1 -----------------------------------------------------------------------------------

export const TILE_MIN = 16;
export const TILE_MAX = 65536;
export const MAX_TILES = 2 ** 20;
export const TILES_PER_FILE_BYTE = 64;

function tileIndex(sections: Map<string, Uint8Array | null>, header: Header, fileBytes: number,
  tiles: Map<number, Map<string, Entry>>): NonNullable<Header["tiles"]> {
  const { geometry: g, params } = header;
  const { rows, cols } = g;
  for (const [k, v] of [["transform", "dct"], ["storage", "quantized"], ["detrend", "plane"], ["mask", "exact"]]) {
    if (params[k] !== v) throw new CorruptFileError(`a tiled map is coded with the DCT, quantized, a plane and an exact mask, not ${k}=${params[k]}`);
  }
  const p = sections.get("TIDX")!;
  if (p.length < 7) throw new CorruptFileError("tile index is too short");
  const coding = p[0];
  if (coding !== 1 && coding !== 2) throw new CorruptFileError(`tile index has unknown coding ${coding}`);
  const T = u32(p, 1);
  if (T < TILE_MIN || T > TILE_MAX) throw new CorruptFileError(`tile size ${T} is not in [16, 65536]`);
  if (T !== params.tile_size) throw new CorruptFileError(`the tile index says tiles of ${T} cells, the parameters ${params.tile_size}`);
  if (rows <= T && cols <= T) throw new CorruptFileError(`a ${rows} x ${cols} grid fits one tile of ${T} cells: it is no tiled map`);
  const ty = Math.ceil(rows / T);
  const tx = Math.ceil(cols / T);
  const n = ty * tx;
  if (n > MAX_TILES) throw new CorruptFileError(`${n} tiles of ${T} cells, more than the 1,048,576 a file may hold`);
  if (n > TILES_PER_FILE_BYTE * fileBytes) throw new CorruptFileError(`${n} tiles in a ${fileBytes}-byte file: more than 64 a byte (crafted?)`);
  const overlap = u16(p, 5);
  if (2 * overlap > T) throw new CorruptFileError(`tile overlap ${overlap} is more than half the tile size ${T}`);
  if (p.length < TIDX_HEAD) throw new CorruptFileError("tile index is too short");
  const reach = p[7];
  const frame = p.subarray(TIDX_HEAD);
  let declared: number | null;
  try {
    declared = zstdDeclared(frame);
  } catch {
    throw new CorruptFileError("tile index does not decompress: not a zstd frame");
  }
  if (declared === null) throw new CorruptFileError("tile index's zstd frame does not state its content size");
  if (declared < 4 * n || declared > 12 * n || (declared - 4 * n) % 8) {
    throw new CorruptFileError(`tile index declares ${declared} bytes, not 4 per tile and 8 per occupied tile of ${n} tiles`);
  }
  const raw = inflate(frame, declared, "tile index");
  if (raw.length !== declared) throw new CorruptFileError("tile index is shorter than it declares");
  const cells = new Float64Array(n);
  let m = 0;
  for (let k = 0; k < n; k++) {
    cells[k] = (raw[k] | (raw[n + k] << 8) | (raw[2 * n + k] << 16) | (raw[3 * n + k] << 24)) >>> 0;
    if (cells[k]) m++;
  }
  if (declared !== 4 * n + 8 * m) throw new CorruptFileError(`tile index holds ${declared} bytes where ${n} tiles, ${m} occupied, need ${4 * n + 8 * m}`);
  const fig = raw.subarray(4 * n);
  const bytes4 = new Uint8Array(4);
  for (let v = 0; v < 2 * m; v++) {
    let x: number;
    if (coding === 1) x = f32(fig, 4 * v);
    else {
      for (let b = 0; b < 4; b++) bytes4[b] = fig[b * 2 * m + v];
      x = f32(bytes4, 0);
    }
    if (!(Number.isFinite(x) && x >= 0)) throw new CorruptFileError("tile index holds a negative or non-finite error");
  }
  let total = 0;
  for (let k = 0; k < n; k++) {
    const [r0, r1, c0, c1] = tileBox(k + 1, rows, cols, T, tx);
    if (cells[k] > (r1 - r0) * (c1 - c0)) throw new CorruptFileError(`tile ${k + 1} claims ${cells[k]} cells in a ${r1 - r0} x ${c1 - c0} tile`);
    total += cells[k];
  }
  if (total !== g.cells) throw new CorruptFileError(`the tiles' cells add up to ${total}, the map states ${g.cells}`);
  if (sections.has("RESD")) {
    if (!sections.has("MASK")) throw new CorruptFileError("a map residual (RESD at tile 0) needs the map mask");
    if (!(params.target_max_error > 0)) throw new CorruptFileError("a map residual (RESD at tile 0) in a file without a maximum-error target");
  }
  for (const [k, secs] of tiles) {
    if (k > n) throw new CorruptFileError(`section table names tile ${[...secs.values()][0].tileText}, but the map has ${n} tiles`);
  }
  const mapMask = sections.has("MASK");
  const mapResid = sections.has("RESD");
  for (let k = 1; k <= n; k++) {
    const have = tiles.get(k) ?? new Map<string, Entry>();
    const [r0, r1, c0, c1] = tileBox(k, rows, cols, T, tx);
    const occupied = cells[k - 1] > 0;
    const full = cells[k - 1] === (r1 - r0) * (c1 - c0);
    const want = (tag: string) => {
      if (!occupied) return false;
      if (tag === "MASK") return !mapMask;
      if (tag === "RESD") return params.target_max_error > 0 && !mapResid;
      return true;
    };
    let ok = true;
    for (const tag of ["MASK", "COEF", "RESD"]) {
      const has = have.has(tag);
      if (tag === "MASK" && full && !has && !mapMask) continue;
      if (tag === "COEF" && !has && occupied) continue;
      if (has !== want(tag)) ok = false;
    }
    if (!ok) {
      const got = ["COEF", "MASK", "RESD"].filter((t) => have.has(t)).join(", ") || "none";
      const need = ["COEF", "MASK", "RESD"].filter(want).join(", ") || "none";
      throw new CorruptFileError(`tile ${k} has sections ${got} where its index entry needs ${need}`);
    }
  }
  return { size: T, overlap, reach, ty, tx, cells };
}

function zstdDeclared(frame: Uint8Array): number | null {
  // The frame header alone (bytes.ts reads it the same way for every frame).
  const fhd = frame[4];
  if (frame.length < 6 || frame[0] !== 0x28 || frame[1] !== 0xb5 || frame[2] !== 0x2f || frame[3] !== 0xfd || fhd & 8) throw new Error("not zstd");
  const fcsFlag = fhd >> 6;
  const single = (fhd >> 5) & 1;
  const at = 5 + (single ? 0 : 1) + [0, 1, 2, 4][fhd & 3];
  const fcsBytes = fcsFlag === 0 ? single : 1 << fcsFlag;
  if (fcsBytes === 0) return null;
  if (at + fcsBytes > frame.length) throw new Error("truncated");
  if (fcsBytes === 1) return frame[at];
  if (fcsBytes === 2) return u16(frame, at) + 256;
  if (fcsBytes === 4) return u32(frame, at);
  return u32(frame, at) + u32(frame, at + 4) * 4294967296;
}

function tileBox(k: number, rows: number, cols: number, T: number, tx: number): [number, number, number, number] {
  const i = Math.floor((k - 1) / tx);
  const j = (k - 1) % tx;
  return [i * T, Math.min(rows, (i + 1) * T), j * T, Math.min(cols, (j + 1) * T)];
}

function decodeTiled(o: Opened, options: DecodeOptions): DecodedMap {
  const { geometry: g, params, stats } = o.header;
  const t = o.header.tiles!;
  const { rows, cols } = g;
  const [wr0, wr1, wc0, wc1] = checkWindow(options, rows, cols);
  const T = t.size;
  const ti0 = Math.floor(wr0 / T);
  const ti1 = Math.ceil(wr1 / T);
  const tj0 = Math.floor(wc0 / T);
  const tj1 = Math.ceil(wc1 / T);
  // The budget: every cell of the tiles the window touches, the base layer's frequency pairs, and
  // the map mask and residual (decoded whole for any window).
  const cutoff = params.cutoff;
  const bcut = baseCut(rows, cols, cutoff, t.reach, T, o.legacy);
  const baseRadius = bcut.limit;
  const ni = Math.min(rows, Math.floor(2 * baseRadius) + 1);
  const nj = Math.min(cols, Math.floor(2 * baseRadius) + 1);
  const spanR = Math.min(rows, ti1 * T) - ti0 * T;
  const spanC = Math.min(cols, tj1 * T) - tj0 * T;
  let need = spanR * spanC + ni * nj;
  if (o.sections.has("MASK")) need += rows * cols;
  if (o.sections.has("RESD")) need += rows * cols;
  const budget = cellBudget(o.size, options.maxCells);
  if (need > budget) {
    throw new ResourceLimitError(`refusing to decode ${fmt(need)} cells of tiles at once, more than the ${fmt(budget)} allowed for a ${fmt(o.size)}-byte file; `
      + `decode a window or, if you trust this file, decode it with maxCells: ${Math.min(need, MAX_CELLS)}`);
  }
  void budgetMessage;
  // BASE: the whole grid's lowest DCT coefficients, a dense ni x nj corner.
  let base = new Float64Array(0);
  let bk = 0;
  let bl = 0;
  const basePayload = o.sections.get("BASE")!;
  if (t.reach === 0) {
    if (stats.coef_count !== 0) throw new CorruptFileError(`the base layer's coefficient count ${stats.coef_count} disagrees with the grid, tile size and cutoff (0)`);
    decodeStream(basePayload, 0, null, null, { free: true, name: "base layer" });
  } else {
    const pre = prefix(ni, nj, "dct", bcut);
    const kept = pre.pos.length;
    if (stats.coef_count !== kept) {
      throw new CorruptFileError(`the base layer's coefficient count ${stats.coef_count} disagrees with the grid, tile size and cutoff (${kept})`);
    }
    const s = decodeStream(basePayload, kept, pre.radius, pre.angle, { free: true, name: "base layer" });
    if (!s.ints) throw new CorruptFileError("the base layer is not one integer per coefficient");
    base = new Float64Array(ni * nj);
    for (let k = 0; k < kept; k++) {
      const i = Math.floor(pre.pos[k] / nj);
      const j = pre.pos[k] - i * nj;
      base[i * nj + j] = s.ints[k] * params.step;
      bk = Math.max(bk, i + 1);
      bl = Math.max(bl, j + 1);
    }
    const dense = new Float64Array(bk * bl);
    for (let i = 0; i < bk; i++) for (let j = 0; j < bl; j++) dense[i * bl + j] = base[i * nj + j];
    base = dense;
  }
  let mapMask: Uint8Array | null = null;
  if (o.sections.has("MASK")) {
    mapMask = prefixed("map mask: ", () => decodeMask(o.sections.get("MASK")!, rows, cols));
    if (countOnes(mapMask) !== g.cells) throw new CorruptFileError("map mask: occupancy mask disagrees with the header's cell count");
  }
  let mapResid: Float64Array | null = null;
  if (o.sections.has("RESD")) {
    const q = prefixed("map residual: ", () => decodeResidual(o.sections.get("RESD")!, mapMask!, rows, cols));
    mapResid = new Float64Array(rows * cols);
    for (let k = 0, c = 0; k < mapMask!.length; k++) if (mapMask![k]) mapResid[k] = q[c++];
  }
  const W = wc1 - wc0;
  const H = wr1 - wr0;
  const heights = new Float64Array(H * W);
  const mask = new Uint8Array(H * W);
  const tiles = byTile(o.entries);
  for (let i = ti0; i < ti1; i++) {
    for (let j = tj0; j < tj1; j++) {
      const k = 1 + i * t.tx + j;
      const count = t.cells[k - 1];
      if (!count) continue;
      const where = `tile ${k} (tile row ${i}, column ${j}): `;
      prefixed(where, () => decodeTile(o, k, tiles.get(k) ?? new Map(), count, base, bk, bl, mapMask, mapResid,
        heights, mask, wr0, wr1, wc0, wc1, where));
    }
  }
  return finish(o, heights, mask, H, W, wr0, wc0, options, false);
}

function prefixed<T>(where: string, f: () => T): T {
  try {
    return f();
  } catch (exc) {
    if (exc instanceof CorruptFileError && !exc.message.startsWith(where)) {
      const e = new (exc.constructor as typeof CorruptFileError)(where + exc.message);
      throw e;
    }
    throw exc;
  }
}

function decodeTile(o: Opened, k: number, secs: Map<string, Entry>, count: number, base: Float64Array, bk: number,
  bl: number, mapMask: Uint8Array | null, mapResid: Float64Array | null, heights: Float64Array, outMask: Uint8Array,
  wr0: number, wr1: number, wc0: number, wc1: number, where: string): void {
  const { geometry: g, params } = o.header;
  const t = o.header.tiles!;
  const { rows, cols } = g;
  const [r0, r1, c0, c1] = tileBox(k, rows, cols, t.size, t.tx);
  const h = r1 - r0;
  const w = c1 - c0;
  let mask: Uint8Array;
  if (mapMask) {
    mask = new Uint8Array(h * w);
    for (let r = 0; r < h; r++) mask.set(mapMask.subarray((r0 + r) * cols + c0, (r0 + r) * cols + c1), r * w);
  } else if (secs.has("MASK")) {
    mask = decodeMask(payload(o.data, secs.get("MASK")!, ""), h, w);
  } else {
    mask = new Uint8Array(h * w).fill(1);
  }
  if (countOnes(mask) !== count) throw new CorruptFileError("occupancy mask disagrees with the tile index's cell count");
  // The coded window: the tile and M cells around it, within the map.
  const M = t.overlap;
  const yr0 = Math.max(0, r0 - M);
  const yr1 = Math.min(rows, r1 + M);
  const yc0 = Math.max(0, c0 - M);
  const yc1 = Math.min(cols, c1 + M);
  const HH = yr1 - yr0;
  const WW = yc1 - yc0;
  const tileH = new Float64Array(h * w);
  if (secs.has("COEF")) {
    const pre = prefix(HH, WW, "dct", cutOf(HH, WW, "dct", params.cutoff, o.legacy));
    const s = decodeStream(payload(o.data, secs.get("COEF")!, ""), pre.pos.length, pre.radius, pre.angle, { free: true });
    if (!s.ints) throw new CorruptFileError("holds float coefficients");
    let K = 0;
    let L = 0;
    for (let q = 0; q < pre.pos.length; q++) {
      K = Math.max(K, Math.floor(pre.pos[q] / WW) + 1);
      L = Math.max(L, (pre.pos[q] % WW) + 1);
    }
    const gm = new Float64Array(K * L);
    for (let q = 0; q < pre.pos.length; q++) {
      const i = Math.floor(pre.pos[q] / WW);
      gm[i * L + (pre.pos[q] - i * WW)] = s.ints[q] * params.step;
    }
    addIdct(tileH, gm, K, L, HH, WW, r0 - yr0, h, c0 - yc0, w);
  }
  const bh = new Float64Array(h * w);
  addIdct(bh, base, bk, bl, rows, cols, r0, h, c0, w);
  const [a, b, c] = g.plane;
  for (let r = 0; r < h; r++) {
    for (let q = 0; q < w; q++) {
      tileH[r * w + q] = tileH[r * w + q] + bh[r * w + q] + (a + b * (c0 + q) + c * (r0 + r));
    }
  }
  const e = params.target_max_error;
  if (mapResid) {
    for (let r = 0; r < h; r++) for (let q = 0; q < w; q++) {
      if (mask[r * w + q]) tileH[r * w + q] += mapResid[(r0 + r) * cols + c0 + q] * 2 * e * (1 - 1e-6);
    }
  } else if (e > 0) {
    const qv = decodeResidual(payload(o.data, secs.get("RESD")!, ""), mask, h, w);
    for (let p = 0, cc = 0; p < mask.length; p++) if (mask[p]) tileH[p] += qv[cc++] * 2 * e * (1 - 1e-6);
  }
  checkFinite(tileH, mask);
  void where;
  for (let r = Math.max(r0, wr0); r < Math.min(r1, wr1); r++) {
    for (let q = Math.max(c0, wc0); q < Math.min(c1, wc1); q++) {
      const src = (r - r0) * w + (q - c0);
      const dst = (r - wr0) * (wc1 - wc0) + (q - wc0);
      outMask[dst] = mask[src];
      heights[dst] = tileH[src];
    }
  }
}

/** Samples a shortest period of a preview's spectrum along each axis (a cosine of index k over n
 * cells has period 2 n / k): bilinear interpolation between 8 samples a period is within 8 % of
 * its amplitude, and the prefix's highest frequencies carry the least of it. */
const PREVIEW_SAMPLES = 8;
/** At most this many cells between a preview's samples (a handful of coefficients still shows). */
const PREVIEW_MAX_STRIDE = 32;
/** Fewer cells between samples save too little of the whole inverse to be worth interpolating. */
const PREVIEW_MIN_STRIDE = 3;
/** A preview's sums (products) at most this share of rows cols log2(rows cols) (about the whole
 * grid's FFT work, measured in Node on the shared DEMs: below it the samples cost less). */
const PREVIEW_SUMS_SHARE = 0.5;

/** Add to ``h`` the inverse DCT of the first ``use`` coefficients at flat positions ``pos`` (values
 * ``values[every k] scale``), laid in the smallest top-left corner of the spectrum that holds them; for a
 * preview, at every few cells and bilinear between. Returns the cells between evaluated ones. */
function addDctCorner(h: Float64Array, pos: Int32Array, use: number, values: Float64Array, every: number, scale: number,
  rows: number, cols: number, preview = false): number {
  const corner = cornerOf(pos, use, values, every, scale, cols);
  const { g: gm, K, L } = corner;
  const stride = previewStride(corner, rows, cols, preview);
  if (stride === 1) {
    addIdct(h, gm, K, L, rows, cols, 0, rows, 0, cols);
    return 1;
  }
  const rs = sampled(rows, stride);
  const cs = sampled(cols, stride);
  addBilinear(h, rows, cols, sampleIdct(gm, K, L, rows, cols, rs, cs), rs, cs);
  return stride;
}

/** The smallest top-left corner of the spectrum that holds the first `use` coefficients: K x L, row-major. */
export interface Corner {
  g: Float64Array;
  K: number;
  L: number;
}

/** Coefficient k's value is values[every k] scale (scale 1 leaves it as it is). */
function cornerOf(pos: Int32Array, use: number, values: Float64Array, every: number, scale: number, cols: number): Corner {
  let K = 0;
  let L = 0;
  for (let k = 0; k < use; k++) {
    const i = Math.floor(pos[k] / cols);
    if (i >= K) K = i + 1;
    const j = pos[k] - i * cols;
    if (j >= L) L = j + 1;
  }
  const g = new Float64Array(K * L);
  for (let k = 0; k < use; k++) {
    const i = Math.floor(pos[k] / cols);
    g[i * L + (pos[k] - i * cols)] = values[every * k] * scale;
  }
  return { g, K, L };
}

/** Cells between a preview's evaluated heights; 1: the exact inverse (no preview asked, or one that
 * would save too little). */
function previewStride({ K, L }: Corner, rows: number, cols: number, preview: boolean): number {
  const spacing = (n: number, k: number) => (k > 1 ? (2 * n) / ((k - 1) * PREVIEW_SAMPLES) : Infinity);
  const stride = preview ? Math.min(PREVIEW_MAX_STRIDE, Math.floor(Math.min(spacing(rows, K), spacing(cols, L)))) : 1;
  // The samples' plain sums grow as the corner's cube: against a rough count of the whole grid's
  // FFTs, a preview pays only for a narrow corner (a few per cent of a map's bytes).
  const [nr, nc] = [Math.ceil((rows - 1) / stride) + 1, Math.ceil((cols - 1) / stride) + 1];
  const sums = K * nc * (L + nr);
  return stride < PREVIEW_MIN_STRIDE || sums > PREVIEW_SUMS_SHARE * rows * cols * Math.log2(rows * cols) ? 1 : stride;
}

/** Cells 0, s, 2 s, ... and the last one. */
function sampled(n: number, s: number): Int32Array {
  const m = Math.ceil((n - 1) / s) + 1;
  const out = new Int32Array(m);
  for (let i = 0; i < m; i++) out[i] = Math.min(i * s, n - 1);
  return out;
}

/** h (rows x cols) += the bilinear interpolation of v, given at rows rs and columns cs (each
 * starting at 0 and ending at the last cell). */
function addBilinear(h: Float64Array, rows: number, cols: number, v: Float64Array, rs: Int32Array, cs: Int32Array): void {
  const nc = cs.length;
  // Each sampled row along the columns first (rs.length x cols), then the rows between them.
  const wide = new Float64Array(rs.length * cols);
  for (let i = 0; i < rs.length; i++) {
    const o = i * cols;
    const vo = i * nc;
    for (let j = 0; j + 1 < nc; j++) {
      const a = cs[j];
      const va = v[vo + j];
      const d = (v[vo + j + 1] - va) / (cs[j + 1] - a);
      for (let c = a; c < cs[j + 1]; c++) wide[o + c] = va + d * (c - a);
    }
    wide[o + cs[nc - 1]] = v[vo + nc - 1];
  }
  for (let i = 0; i < rs.length; i++) {
    const a = rs[i];
    const last = i + 1 === rs.length;
    const b = last ? a + 1 : rs[i + 1];
    const ua = wide.subarray(i * cols, (i + 1) * cols);
    const ub = last ? ua : wide.subarray((i + 1) * cols, (i + 2) * cols);
    for (let r = a; r < b; r++) {
      const f = (r - a) / (b - a);
      const o = r * cols;
      for (let c = 0; c < cols; c++) h[o + c] += ua[c] + f * (ub[c] - ua[c]);
    }
  }
}
