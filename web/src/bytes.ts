// Little-endian reads with bounds checks, LEB128, CRC-32 and zstd frames: the byte-level helpers
// every section shares.
import CRC32 from "crc-32";
import { Decompress, decompress as zstdDecompress } from "fzstd";
import { CorruptFileError } from "./errors.js";
import { NATIVE_MAX_BYTES, nativeZstd } from "./zstd.js";

export const ZSTD_MAGIC = [0x28, 0xb5, 0x2f, 0xfd];

/** ISO-HDLC CRC-32 (zlib.crc32) as an unsigned integer. */
export function crc32(data: Uint8Array): number {
  return CRC32.buf(data) >>> 0;
}

export function view(data: Uint8Array): DataView {
  return new DataView(data.buffer, data.byteOffset, data.byteLength);
}

export function u16(d: Uint8Array, at: number): number {
  return d[at] | (d[at + 1] << 8);
}

export function u32(d: Uint8Array, at: number): number {
  return (d[at] | (d[at + 1] << 8) | (d[at + 2] << 16) | (d[at + 3] << 24)) >>> 0;
}

export function i32(d: Uint8Array, at: number): number {
  return d[at] | (d[at + 1] << 8) | (d[at + 2] << 16) | (d[at + 3] << 24);
}

/** An unsigned 64-bit value as a double: exact below 2**53, and above it only ever compared with
 * lengths and counts far smaller, so the rounding never changes a decision. */
export function u64(d: Uint8Array, at: number): number {
  return u32(d, at) + u32(d, at + 4) * 4294967296;
}

export function f64(d: Uint8Array, at: number): number {
  return view(d).getFloat64(at, true);
}

export function f32(d: Uint8Array, at: number): number {
  return view(d).getFloat32(at, true);
}

/** Unsigned LEB128 at `pos`: [value, next position]. At most 10 bytes and below 2**64 (format.md):
 * a tenth byte above 1, or ten bytes that all say more follows, is refused, never reduced. */
export function uleb(d: Uint8Array, pos: number, truncated: string, wide: string): [number, number] {
  let value = 0;
  let scale = 1;
  for (let k = 0; k < 10; k++) {
    if (pos + k >= d.length) throw new CorruptFileError(truncated);
    const byte = d[pos + k];
    value += (byte & 0x7f) * scale;
    scale *= 128;
    if (!(byte & 0x80)) {
      if (k === 9 && byte > 1) break;
      return [value, pos + k + 1];
    }
  }
  throw new CorruptFileError(wide);
}

/** The exact decimal value of the LEB128 at `pos` (for messages: a double rounds above 2**53). */
export function ulebText(d: Uint8Array, pos: number): string {
  let value = 0n;
  for (let k = 0; k < 10 && pos + k < d.length; k++) {
    value |= BigInt(d[pos + k] & 0x7f) << BigInt(7 * k);
    if (!(d[pos + k] & 0x80)) break;
  }
  return value.toString();
}

export function count(n: number): string {
  return n.toLocaleString("en-US");
}

export interface FrameHeader {
  /** Declared content size in bytes, or null when the frame does not state it. */
  contentSize: number | null;
  windowSize: number;
}

/** The header of the zstd frame starting at byte 0 (RFC 8878, 3.1.1.1). */
export function zstdHeader(frame: Uint8Array, what: string): FrameHeader {
  if (frame.length < 6 || ZSTD_MAGIC.some((b, k) => frame[k] !== b)) {
    throw new CorruptFileError(`${what} is not a zstd frame`);
  }
  const fhd = frame[4];
  const fcsFlag = fhd >> 6;
  const single = (fhd >> 5) & 1;
  if (fhd & 0x08) throw new CorruptFileError(`${what} is not a zstd frame (reserved bit set)`);
  const dictBytes = [0, 1, 2, 4][fhd & 3];
  let at = 5;
  let windowSize = 0;
  if (!single) {
    const wd = frame[at++];
    const base = 2 ** (10 + (wd >> 3));
    windowSize = base + (base / 8) * (wd & 7);
  }
  at += dictBytes;
  const fcsBytes = fcsFlag === 0 ? single : 1 << fcsFlag;
  if (at + fcsBytes > frame.length) throw new CorruptFileError(`${what} is truncated`);
  let contentSize: number | null = null;
  if (fcsBytes === 1) contentSize = frame[at];
  else if (fcsBytes === 2) contentSize = u16(frame, at) + 256;
  else if (fcsBytes === 4) contentSize = u32(frame, at);
  else if (fcsBytes === 8) contentSize = u64(frame, at);
  if (single) windowSize = contentSize ?? 0;
  return { contentSize, windowSize };
}

/** One zstd frame, refused if it declares (or yields) more than `limit` bytes; the declared size
 * is checked before anything is allocated. */
export function inflate(frame: Uint8Array, limit: number, what: string): Uint8Array {
  const head = zstdHeader(frame, what);
  if (head.contentSize !== null && head.contentSize > limit) {
    throw new CorruptFileError(`${what} declares ${head.contentSize} bytes, more than the ${limit} it can hold`);
  }
  if (head.contentSize === null && head.windowSize > Math.max(limit, 1 << 20)) {
    // fzstd allocates the window of a frame without a size: a crafted window must not cost gigabytes.
    throw new CorruptFileError(`${what} does not state its size and asks for a ${head.windowSize}-byte window`);
  }
  if (head.contentSize === 0) return new Uint8Array(0);
  let out: Uint8Array;
  try {
    const native = head.contentSize !== null && head.contentSize <= NATIVE_MAX_BYTES ? nativeZstd() : null;
    if (native) {
      // libzstd writes at most the declared size; an error (a negative size) gives no bytes.
      out = native.decode(frame, head.contentSize!);
      if (out.length === 0) throw new CorruptFileError(`${what} does not decompress`);
    } else out = head.contentSize === null ? inflateBounded(frame, limit, what) : zstdDecompress(frame);
  } catch (exc) {
    if (exc instanceof CorruptFileError) throw exc;
    throw new CorruptFileError(`${what} does not decompress: ${exc instanceof Error ? exc.message : String(exc)}`);
  }
  if (out.length > limit) throw new CorruptFileError(`${what} decompresses to more than ${limit} bytes`);
  if (head.contentSize !== null && out.length !== head.contentSize) {
    throw new CorruptFileError(`${what} decompresses to ${out.length} bytes, not the ${head.contentSize} it declares`);
  }
  return out;
}

/** A frame without a stated size, streamed so that a bomb stops at `limit` bytes of output. */
function inflateBounded(frame: Uint8Array, limit: number, what: string): Uint8Array {
  const parts: Uint8Array[] = [];
  let total = 0;
  const stream = new Decompress((chunk: Uint8Array) => {
    total += chunk.length;
    if (total > limit) throw new CorruptFileError(`${what} decompresses to more than ${limit} bytes`);
    parts.push(chunk.slice());
  });
  stream.push(frame, true);
  const out = new Uint8Array(total);
  let at = 0;
  for (const p of parts) {
    out.set(p, at);
    at += p.length;
  }
  return out;
}
