// Deltas (format.md, "Deltas"): the next version of a map as pieces, copies of the base's bytes or
// new bytes carried zstd-compressed; applied after every check, nothing allocated before them.
import { sha256 } from "@noble/hashes/sha2.js";
import { crc32, inflate, u16, u32, uleb, zstdHeader } from "./bytes.js";
import { CorruptFileError, guard, InvalidInputError } from "./errors.js";

export const DELTA_MAGIC = [0x89, 0x44, 0x46, 0x54, 0x50, 0x44, 0x0d, 0x0a];
const HEAD = 76;
/** Copies may add up to this many times the base's size. */
const COPY_FACTOR = 4;
/** zstd cannot expand a byte past this (an RLE block: 3 bytes give 128 KiB); a frame declaring more
 * than this many bytes a compressed byte is crafted, refused before anything is allocated. */
const ZSTD_MAX_RATIO = 2 ** 17;

function hex(b: Uint8Array): string {
  return Array.from(b, (x) => x.toString(16).padStart(2, "0")).join("");
}

/** The file a delta makes of `base`: byte for byte the file the sender wrote. */
export function applyDelta(base: Uint8Array, delta: Uint8Array): Uint8Array {
  return guard("damaged delta", () => apply(base, delta));
}

function apply(base: Uint8Array, delta: Uint8Array): Uint8Array {
  if (delta.length < HEAD + 2 + 4 || DELTA_MAGIC.some((b, k) => delta[k] !== b)) {
    throw new CorruptFileError("not a .dftpc delta (bad magic bytes or too short)");
  }
  if (delta[8] !== 1 || delta[9] !== 0 || u16(delta, 10) !== 0) {
    // Python's reader refuses another version as a corrupt delta, so does this one.
    throw new CorruptFileError(`.dftpc delta version ${delta[8]}.${delta[9]} (flags ${u16(delta, 10)}) is not supported`);
  }
  const end = delta.length - 4;
  if (crc32(delta.subarray(0, end)) !== u32(delta, end)) throw new CorruptFileError("delta fails its checksum (damaged or cut)");
  const baseSha = delta.subarray(12, 44);
  const resultSha = delta.subarray(44, 76);
  const truncated = "delta is truncated";
  const wide = "delta holds an integer wider than 64 bits";
  const [size, p1] = uleb(delta, HEAD, truncated, wide);
  const [n, p2] = uleb(delta, p1, truncated, wide);
  if (n > (end - p2) / 2) throw new CorruptFileError(`delta claims ${n} pieces, more than its bytes hold`);
  const kinds = new Uint8Array(n);
  const offsets = new Float64Array(n);
  const lengths = new Float64Array(n);
  let pos = p2;
  let total = 0;
  let copied = 0;
  let data = 0;
  for (let k = 0; k < n; k++) {
    if (pos >= end) throw new CorruptFileError(truncated);
    const kind = delta[pos++];
    kinds[k] = kind;
    if (kind === 0) {
      const [off, q1] = uleb(delta, pos, truncated, wide);
      const [len, q2] = uleb(delta, q1, truncated, wide);
      pos = q2;
      if (off + len > base.length) throw new CorruptFileError(`delta piece ${k} copies bytes ${off} to ${off + len} of a ${base.length}-byte base`);
      offsets[k] = off;
      lengths[k] = len;
      copied += len;
    } else if (kind === 1) {
      const [len, q1] = uleb(delta, pos, truncated, wide);
      pos = q1;
      lengths[k] = len;
      data += len;
    } else {
      throw new CorruptFileError(`delta piece ${k} has unknown kind ${kind}`);
    }
    total += lengths[k];
  }
  if (total !== size) throw new CorruptFileError(`delta pieces add up to ${total} bytes, not the ${size} it states`);
  if (copied > COPY_FACTOR * base.length) throw new CorruptFileError(`delta copies ${copied} bytes of a ${base.length}-byte base (crafted?)`);
  const frame = delta.subarray(pos, end);
  const declared = frame.length ? zstdHeader(frame, "delta's new data").contentSize : null;
  if (declared === null || declared !== data) {
    throw new CorruptFileError(`delta's new data declares ${declared ?? "no"} bytes where its pieces need ${data}`);
  }
  if (declared > ZSTD_MAX_RATIO * frame.length) throw new CorruptFileError(`delta's new data declares ${declared} bytes, more than ${frame.length} compressed bytes can hold`);
  const fresh = inflate(frame, data, "delta's new data");
  if (fresh.length !== data) throw new CorruptFileError("delta's new data is shorter than it declares");
  const have = sha256(base);
  if (hex(have) !== hex(baseSha)) {
    if (hex(have) === hex(resultSha)) throw new InvalidInputError("the delta was applied already: the base is its result");
    throw new InvalidInputError("the delta was made from another map (or an earlier delta has not been applied)");
  }
  const out = new Uint8Array(size);
  let at = 0;
  let from = 0;
  for (let k = 0; k < n; k++) {
    const len = lengths[k];
    if (kinds[k] === 0) out.set(base.subarray(offsets[k], offsets[k] + len), at);
    else {
      out.set(fresh.subarray(from, from + len), at);
      from += len;
    }
    at += len;
  }
  if (hex(sha256(out)) !== hex(resultSha)) throw new CorruptFileError("the delta's result fails its SHA-256 (corrupt delta)");
  return out;
}
