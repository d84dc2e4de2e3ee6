// dftpcc's .dftpc decoder for JavaScript: decode(bytes, options) -> {width, height, heights, mask,
// header, ...} and applyDelta(base, delta) -> the next version of a map, written from docs/format.md.
export { decode, readHeader } from "./decode.js";
export type { DecodeOptions, DecodedMap, Header } from "./decode.js";
export { applyDelta } from "./delta.js";
export { DftpccError, CorruptFileError, ResourceLimitError, UnsupportedFormatError, InvalidInputError } from "./errors.js";
export { useWasm } from "./wasm.js";
export { ready } from "./zstd.js";
