// The container (format.md, "Layout" and "Sections"): preamble, section table, CRCs, and the header
// sections GEOM, PARM, STAT and CRS, each checked before anything is allocated from it
// (docs/format-validation.md, sections 1-3).
import { count as fmt, crc32, f32, f64, inflate, u32, u64, uleb, ulebText, zstdHeader, ZSTD_MAGIC } from "./bytes.js";
import { CorruptFileError, ResourceLimitError, UnsupportedFormatError } from "./errors.js";

export const MAGIC = [0x89, 0x44, 0x46, 0x54, 0x50, 0x43, 0x0d, 0x0a];
export const MAX_SECTIONS = 1024;
export const MAX_SECTIONS_TILED = 2 ** 24;
export const MAX_JSON_BYTES = 2 ** 20;
export const MAX_CELLS = 100_000_000;
export const MAX_TILED_CELLS = 2 ** 36;
export const FREE_CELLS = 2 ** 21;
export const CELLS_PER_BYTE = 1024;
export const MAX_COORDINATE_M = 1e12;
export const MAX_PLANE_M = 1e18;
/** Bytes a decoded cell costs, for messages only (format-validation.md). */
const DECODE_BYTES_PER_CELL = 96;
const MAX_JSON_DEPTH = 512;

export interface Entry {
  tag: string;
  tile: number;
  /** The tile number's exact decimal text (a double rounds those above 2**53). */
  tileText: string;
  offset: number;
  length: number;
  crc: number;
}

export interface Table {
  major: number;
  minor: number;
  entries: Entry[];
}

/** The cells a file of `size` bytes may ask a reader to decode (format-validation.md). */
export function cellBudget(size: number, maxCells?: number): number {
  if (maxCells !== undefined) return Math.min(maxCells, MAX_CELLS);
  return Math.min(MAX_CELLS, Math.max(FREE_CELLS, CELLS_PER_BYTE * size));
}

export function budgetMessage(what: string, cells: number, budget: number, size: number): string {
  const gb = ((cells * DECODE_BYTES_PER_CELL) / 1e9).toFixed(1);
  return `refusing to decode: ${what} (${fmt(cells)} cells, about ${gb} GB to decode), more than the ${fmt(budget)} cells allowed `
    + `for a ${fmt(size)}-byte file; if you trust this file, decode it with maxCells: ${cells} (Python: max_cells=${cells})`;
}

function tagOf(d: Uint8Array, at: number): string {
  return String.fromCharCode(d[at], d[at + 1], d[at + 2], d[at + 3]);
}

/** Preamble and section table: every entry read and the table's CRC checked before any is used;
 * bytes after the last payload refused. */
export function parseTable(data: Uint8Array): Table {
  if (data.length < 20) throw new CorruptFileError(`not a .dftpc file: only ${data.length} bytes`);
  if (MAGIC.some((b, k) => data[k] !== b)) throw new CorruptFileError("not a .dftpc file (bad magic bytes)");
  const major = data[8];
  const minor = data[9];
  if (major !== 1) throw new UnsupportedFormatError(`.dftpc format version ${major}.${minor} is not supported`);
  const count = u32(data, 12);
  const most = minor === 0 ? MAX_SECTIONS : MAX_SECTIONS_TILED;
  if (count > most) throw new CorruptFileError(`section table claims ${count} sections, more than the ${most} allowed`);
  const truncated = "file is truncated inside its section table";
  if (16 + 10 * count + 4 > data.length) throw new CorruptFileError(truncated);
  const raw: Array<[string, number, number, number, string]> = [];
  let pos = 16;
  for (let i = 0; i < count; i++) {
    if (pos + 4 > data.length) throw new CorruptFileError(truncated);
    const tag = tagOf(data, pos);
    const wide = `section table entry ${i} holds an integer wider than 64 bits`;
    const [tile, p1] = uleb(data, pos + 4, truncated, wide);
    const [length, p2] = uleb(data, p1, truncated, wide);
    if (p2 + 4 > data.length) throw new CorruptFileError(truncated);
    raw.push([tag, tile, length, u32(data, p2), tile > Number.MAX_SAFE_INTEGER ? ulebText(data, pos + 4) : String(tile)]);
    pos = p2 + 4;
  }
  if (pos + 4 > data.length) throw new CorruptFileError(truncated);
  if (crc32(data.subarray(0, pos)) !== u32(data, pos)) throw new CorruptFileError("section table fails its checksum");
  let offset = pos + 4;
  const entries: Entry[] = [];
  for (const [tag, tile, length, crc, tileText] of raw) {
    entries.push({ tag, tile, tileText, offset, length, crc });
    offset += length; // beyond 2**53 only ever compared with the file's far smaller length
  }
  if (data.length > offset) {
    throw new CorruptFileError(`${data.length - offset} trailing byte(s) after the last section, which ends at byte ${offset} `
      + "(two files joined, or data appended in transfer?)");
  }
  return { major, minor, entries };
}

/** tile -> tag -> the first entry of that tag in that tile (repeats ignored). */
export function byTile(entries: Entry[]): Map<number, Map<string, Entry>> {
  const out = new Map<number, Map<string, Entry>>();
  for (const e of entries) {
    let t = out.get(e.tile);
    if (!t) out.set(e.tile, (t = new Map()));
    if (!t.has(e.tag)) t.set(e.tag, e);
  }
  return out;
}

/** A section's payload, checked against its CRC; `prefix` names the tile in messages. */
export function payload(data: Uint8Array, e: Entry, prefix = ""): Uint8Array {
  const end = e.offset + e.length;
  if (end > data.length) {
    throw new CorruptFileError(`${prefix}file is truncated: section ${e.tag.trim()} needs bytes up to ${end}, file has ${data.length}`);
  }
  const p = data.subarray(e.offset, end);
  if (crc32(p) !== e.crc) throw new CorruptFileError(`${prefix}section ${e.tag.trim()} fails its checksum (damaged file)`);
  return p;
}

export interface Geometry {
  x0: number;
  y0: number;
  z0: number;
  resolution: number;
  rows: number;
  cols: number;
  angle: number;
  points: number;
  cells: number;
  plane: [number, number, number];
  /** Row spacing along v (metres); the resolution for square cells. */
  dy: number;
}

export function parseGeom(p: Uint8Array, tiled: boolean, size: number, maxCells?: number): Geometry {
  if (p.length < 88) throw new CorruptFileError("geometry section is too short");
  const g: Geometry = {
    x0: f64(p, 0), y0: f64(p, 8), z0: f64(p, 16), resolution: f64(p, 24), rows: u32(p, 32), cols: u32(p, 36),
    angle: f64(p, 40), points: u64(p, 48), cells: u64(p, 56), plane: [f64(p, 64), f64(p, 72), f64(p, 80)], dy: 0,
  };
  const floats = [g.x0, g.y0, g.z0, g.resolution, g.angle, ...g.plane];
  if (!floats.every(Number.isFinite) || !(g.resolution > 0)) {
    throw new CorruptFileError("geometry section holds non-finite or non-positive values");
  }
  if (Math.max(Math.abs(g.x0), Math.abs(g.y0), Math.abs(g.z0)) > MAX_COORDINATE_M) {
    throw new CorruptFileError("geometry section states an origin beyond 1e+12 m");
  }
  const { rows, cols } = g;
  if (rows < 1 || cols < 1) throw new CorruptFileError(`implausible grid ${rows} x ${cols}`);
  if (g.resolution * Math.max(rows, cols) > MAX_COORDINATE_M) {
    throw new CorruptFileError(`grid ${rows} x ${cols} of ${g.resolution} m cells extends beyond 1e+12 m`);
  }
  const [a, b, c] = g.plane;
  if (Math.abs(a) + Math.abs(b) * cols + Math.abs(c) * rows > MAX_PLANE_M) {
    throw new CorruptFileError(`detrending plane (${a}, ${b}, ${c}) leaves the map by more than 1e+18 m`);
  }
  const cells = rows * cols;
  const most = tiled ? MAX_TILED_CELLS : MAX_CELLS;
  if (cells > most) {
    throw new ResourceLimitError(`the header asks for a ${rows} x ${cols} grid (${fmt(cells)} cells), more than the ${fmt(most)}-cell limit of the format`);
  }
  if (!tiled) {
    const budget = cellBudget(size, maxCells);
    if (cells > budget) throw new ResourceLimitError(budgetMessage(`the header asks for a ${rows} x ${cols} grid`, cells, budget, size));
  }
  if (!(g.cells >= 1 && g.cells <= cells)) {
    throw new CorruptFileError(`implausible grid ${rows} x ${cols} with ${g.cells} occupied cells`);
  }
  g.dy = g.resolution;
  if (p.length >= 96) {
    const dy = f64(p, 88);
    if (!Number.isFinite(dy) || dy < 0) throw new CorruptFileError("geometry holds an invalid row spacing");
    if (dy * rows > MAX_COORDINATE_M) throw new CorruptFileError(`grid ${rows} rows of ${dy} m extend beyond 1e+12 m`);
    if (dy > 0) g.dy = dy;
  }
  return g;
}

/** PARM fields left out take these, fixed for all 1.x files. */
export const V1_DEFAULTS: Record<string, unknown> = {
  cutoff: 0.8, profile: "compact", aggregate: "mean", frame: "axis", transform: "dct", detrend: "plane",
  fill: "consistent", storage: "quantized", step: 0, deadzone: 0.1, coder: "ans", mask: "exact", target_rmse: 0,
  target_max_error: 0, target_bpp: 0, target_reloc: 0,
};

const CHOICES: Record<string, string[]> = {
  profile: ["paper", "compact"], aggregate: ["mean", "median", "min", "max"], frame: ["axis", "oriented"],
  transform: ["dft", "dct"], detrend: ["none", "plane"], fill: ["zero", "smooth", "consistent"],
  storage: ["quantized", "complex64"], coder: ["ans", "zstd"], mask: ["exact", "footprint"],
};

export interface Params {
  cutoff: number;
  transform: "dft" | "dct";
  storage: "quantized" | "complex64";
  detrend: "none" | "plane";
  step: number;
  target_max_error: number;
  tile_size: number;
  [field: string]: unknown;
}

function depth(text: string): number {
  let d = 0;
  let most = 0;
  let inString = false;
  for (let k = 0; k < text.length; k++) {
    const ch = text.charCodeAt(k);
    if (inString) {
      if (ch === 92) k++;
      else if (ch === 34) inString = false;
    } else if (ch === 34) inString = true;
    else if (ch === 91 || ch === 123) most = Math.max(most, ++d);
    else if (ch === 93 || ch === 125) d--;
  }
  return most;
}

/** A PARM or CRS payload: a UTF-8 JSON object, as text or one zstd frame of it. */
export function parseJson(p: Uint8Array, name: string): Record<string, unknown> {
  let bytes = p;
  if (p.length >= 4 && ZSTD_MAGIC.every((b, k) => p[k] === b)) {
    const declared = zstdHeader(p, `section ${name}`).contentSize;
    if (declared !== null && declared > MAX_JSON_BYTES) {
      throw new CorruptFileError(`section ${name} declares more than ${MAX_JSON_BYTES} bytes of JSON (${declared})`);
    }
    bytes = inflate(p, MAX_JSON_BYTES, `section ${name}`);
  }
  let text: string;
  try {
    text = new TextDecoder("utf-8", { fatal: true }).decode(bytes);
  } catch (exc) {
    throw new CorruptFileError(`section ${name} is not UTF-8: ${String(exc)}`);
  }
  if (depth(text) > MAX_JSON_DEPTH) throw new CorruptFileError(`section ${name} nests JSON too deeply`);
  let obj: unknown;
  try {
    obj = JSON.parse(text);
  } catch (exc) {
    throw new CorruptFileError(`section ${name} is not valid JSON: ${exc instanceof Error ? exc.message : String(exc)}`);
  }
  if (typeof obj !== "object" || obj === null || Array.isArray(obj)) {
    throw new CorruptFileError(`section ${name} must be a JSON object`);
  }
  return obj as Record<string, unknown>;
}

export function parseParams(p: Uint8Array, g: Geometry): Params {
  let raw: Record<string, unknown>;
  try {
    raw = parseJson(p, "PARM");
  } catch (exc) {
    if (!(exc instanceof CorruptFileError) || /declares more than|too deeply/.test(exc.message)) throw exc;
    throw new CorruptFileError(`parameter section is invalid: ${exc.message}`);
  }
  const params: Record<string, unknown> = { ...V1_DEFAULTS, tile_size: 0, ...raw };
  const bad = (why: string) => new CorruptFileError(`parameter section is invalid: ${why}`);
  const num = (k: string) => {
    const v = params[k];
    if (typeof v !== "number" || !Number.isFinite(v)) throw bad(`${k} must be a finite number`);
    return v;
  };
  if (params.cutoff === null) throw new CorruptFileError("parameter section states no cutoff");
  const cutoff = num("cutoff");
  if (!(cutoff >= 0 && cutoff < 1)) throw bad("cutoff must be in [0, 1)");
  for (const [k, choices] of Object.entries(CHOICES)) {
    if (typeof params[k] !== "string" || !choices.includes(params[k] as string)) throw bad(`${k} must be one of ${choices.join(", ")}`);
  }
  for (const k of ["step", "target_rmse", "target_max_error", "target_reloc"]) {
    const v = num(k);
    if (v < 0 || v > MAX_COORDINATE_M) throw bad(`${k === "step" ? "quantizer step" : k} must be in [0, 1e+12]`);
  }
  const deadzone = num("deadzone");
  if (!(deadzone >= 0 && deadzone < 0.5)) throw bad("deadzone must be in [0, 0.5)");
  if (num("target_bpp") < 0) throw bad("target_bpp must be >= 0");
  const targets = ["target_rmse", "target_max_error", "target_bpp", "target_reloc"].filter((k) => (params[k] as number) > 0);
  if (targets.length > 1) throw bad("at most one target");
  const tile = params.tile_size;
  if (typeof tile !== "number" || !Number.isInteger(tile) || tile < 0) throw bad("tile_size must be a whole number");
  if ("resolution" in raw) {
    const r = params.resolution;
    if (typeof r !== "number" || !Number.isFinite(r) || r <= 0) throw bad("resolution must be positive and finite");
    if (Math.abs(r - g.resolution) > 1e-9 * Math.max(Math.abs(r), Math.abs(g.resolution))) {
      throw new CorruptFileError(`parameter resolution ${r} m disagrees with the grid's ${g.resolution} m`);
    }
  }
  if (params.storage === "quantized" && !((params.step as number) > 0 && (params.step as number) <= MAX_COORDINATE_M)) {
    throw new CorruptFileError(`quantizer step ${params.step} m is not in (0, 1e+12]`);
  }
  if (params.mask === "exact" && g.points < g.cells) {
    throw new CorruptFileError(`header states ${g.points} original points for ${g.cells} occupied cells`);
  }
  return params as Params;
}

const STAT_FLOATS: Record<number, string> = {
  0: "dem_rmse_m", 1: "dem_max_error_m", 2: "gridding_rmse_m", 3: "vertical_rmse_m", 4: "unrepresented_fraction",
  5: "unrepresented_rmse_m", 6: "reloc_success_fraction", 7: "target_rmse_m",
};
const STAT_INTS: Record<number, string> = { 128: "coef_count", 129: "cells_interpolated" };

export function parseStat(p: Uint8Array): Record<string, number> {
  if (p.length === 0) throw new CorruptFileError("section STAT is empty");
  if (p[0] !== 1) throw new CorruptFileError(`section STAT has unknown coding 0x${p[0].toString(16).padStart(2, "0")} (binary STAT starts with 0x01)`);
  const stats: Record<string, number> = {};
  let i = 1;
  while (i < p.length) {
    const id = p[i++];
    if (id < 128) {
      if (i + 4 > p.length) throw new CorruptFileError("section STAT is truncated");
      const v = f32(p, i);
      i += 4;
      if (!Number.isFinite(v)) throw new CorruptFileError(`section STAT: field ${id} is not finite`);
      if (STAT_FLOATS[id]) stats[STAT_FLOATS[id]] = v;
    } else {
      const [v, next] = uleb(p, i, "section STAT is truncated", "section STAT holds an integer wider than 64 bits");
      i = next;
      if (STAT_INTS[id]) stats[STAT_INTS[id]] = v;
    }
  }
  return stats;
}

const B64 = /^(?:[A-Za-z0-9+/]{4})*(?:[A-Za-z0-9+/]{2}==|[A-Za-z0-9+/]{3}=)?$/;

export function parseCrs(p: Uint8Array): Record<string, unknown> {
  const crs = parseJson(p, "CRS");
  if ("wkt" in crs && crs.wkt !== null && typeof crs.wkt !== "string") throw new CorruptFileError("section CRS: wkt must be a string");
  if ("las_vlrs" in crs) {
    const vlrs = crs.las_vlrs;
    if (!Array.isArray(vlrs)) throw new CorruptFileError("section CRS: las_vlrs must be a list");
    vlrs.forEach((v, i) => {
      const bad = () => new CorruptFileError(`section CRS: LAS record ${i} is malformed`);
      if (typeof v !== "object" || v === null || Array.isArray(v)) throw bad();
      const id = v.record_id;
      if (typeof id !== "number" || !Number.isInteger(id) || id < 0 || id > 65535) throw bad();
      if (typeof v.description !== "string" || new TextEncoder().encode(v.description).length > 32) throw bad();
      if ("data" in v) {
        if (typeof v.data !== "string" || !B64.test(v.data) || (v.data.length / 4) * 3 > 65535 + 3) throw bad();
      } else if (typeof v.text !== "string") throw bad();
    });
  }
  return crs;
}
